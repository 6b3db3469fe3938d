//! The in-memory dataset every loader produces and every consumer (trainer, simulator tests,
//! evaluation) reads: RGB8 frames with intrinsics, a camera-to-world pose label and an optional
//! foreground mask, plus the scene box and background colour.

use orbit_nerf_core::{Camera, Pose};
use std::path::PathBuf;

#[derive(Clone, Debug)]
pub struct Frame {
    /// File the pixels came from (relative names are fine), for messages and reports.
    pub name: String,
    pub camera: Camera,
    /// The pose label the method trains on (camera-to-world, OpenCV axes).
    pub pose: Pose,
    /// Row-major RGB8, `camera.width * camera.height * 3` bytes.
    pub pixels: Vec<u8>,
    /// Row-major foreground mask, one byte per pixel (0 = background, 255 = target).
    pub mask: Option<Vec<u8>>,
}

#[derive(Clone, Debug)]
pub struct Dataset {
    /// Folder or file the dataset was read from.
    pub source: PathBuf,
    pub frames: Vec<Frame>,
    /// Axis-aligned box (world units) that holds the whole scene (empty while
    /// `scene_box` is [`SceneBoxOrigin::Unknown`]).
    pub scene_min: [f32; 3],
    pub scene_max: [f32; 3],
    /// What gave the scene box.
    pub scene_box: SceneBoxOrigin,
    /// Colour the images were composited on, in [0, 1].
    pub background: [f32; 3],
}

/// Where a dataset's scene box came from.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneBoxOrigin {
    /// The data gives it (a truth file, a box in the file, the format's convention); says
    /// which.
    Data(String),
    /// Stated by the user (`--scene-box`, a config file); says which.
    Stated(String),
    /// Found from the frames (see [`crate::scene_box`]); the finder's account.
    Found(String),
    /// The data gives none (a SPEED+ folder without `truth.json`): state it or find it
    /// ([`crate::scene_box::choose_scene_box`]) before training.
    Unknown,
}

/// Deterministic held-out split: every `every`-th frame (0, every, 2*every, ...) is a test view.
pub fn split_every(frame_count: usize, every: usize) -> (Vec<usize>, Vec<usize>) {
    let every = every.max(1);
    (0..frame_count).partition(|i| i % every != 0)
}
