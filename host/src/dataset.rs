//! The in-memory dataset every loader produces and every consumer (trainer, simulator tests,
//! evaluation) reads: RGB8 frames with intrinsics, a camera-to-world pose label and an optional
//! foreground mask, plus the scene box and background colour.

use orbit_nerf_core::{Camera, Pose};
use std::path::PathBuf;

/// One image of a dataset with its camera, pose label and optional mask.
#[derive(Clone, Debug)]
pub struct Frame {
    /// File the pixels came from (relative names are fine), for messages and reports.
    pub name: String,
    /// Pinhole intrinsics of this image (pixels); width and height are the image's size.
    pub camera: Camera,
    /// The pose label the method trains on (camera-to-world, OpenCV axes).
    pub pose: Pose,
    /// Row-major RGB8, `camera.width * camera.height * 3` bytes.
    pub pixels: Vec<u8>,
    /// Row-major foreground mask, one byte per pixel (0 = background, 255 = target).
    pub mask: Option<Vec<u8>>,
    /// The mask is the image's own alpha (above one half) and the pixels are already
    /// composited on the background by that alpha: the background is removed exactly, edges
    /// included, so [`Frame::apply_mask`] leaves them as they are.
    pub alpha_composited: bool,
}

/// A whole dataset as loaded: its frames, the box that holds the scene and the background.
#[derive(Clone, Debug)]
pub struct Dataset {
    /// Folder or file the dataset was read from.
    pub source: PathBuf,
    /// The images in the loader's order; view indices (splits, truth, reports) index this.
    pub frames: Vec<Frame>,
    /// Lower corner of the axis-aligned box (world units) that holds the whole scene (zero,
    /// an empty box, while `scene_box` is [`SceneBoxOrigin::Unknown`]).
    pub scene_min: [f32; 3],
    /// Upper corner of the scene box (world units); see `scene_min`.
    pub scene_max: [f32; 3],
    /// What gave the scene box.
    pub scene_box: SceneBoxOrigin,
    /// Colour the images were composited on, in [0, 1].
    pub background: [f32; 3],
    /// The labels place a target in front of every camera (SPEED+): the scene box is the
    /// target's, so no camera can be inside it.
    pub target_centred: bool,
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

impl Frame {
    /// Remove the background as the paper does: every pixel whose mask is 0 gets the
    /// background colour (in [0, 1], rounded to 8 bits), so training targets and evaluation
    /// references hold no sky noise; returns whether it painted. Without a mask nothing
    /// changes, nor over pixels composited by their alpha: they have no sky, and painting
    /// their partly covered edge pixels would only harden the edges (1.7 dB less on lego).
    pub fn apply_mask(&mut self, background: [f32; 3]) -> bool {
        let Some(mask) = &self.mask else {
            return false;
        };
        if self.alpha_composited {
            return false;
        }
        let sky = background.map(|c| (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
        for (pixel, _) in self
            .pixels
            .chunks_exact_mut(3)
            .zip(mask)
            .filter(|(_, m)| **m == 0)
        {
            pixel.copy_from_slice(&sky);
        }
        true
    }
}

impl Dataset {
    /// [`Frame::apply_mask`] on every frame with the dataset's background; returns how many
    /// frames it painted.
    pub fn apply_masks(&mut self) -> usize {
        let background = self.background;
        self.frames
            .iter_mut()
            .filter_map(|f| f.apply_mask(background).then_some(()))
            .count()
    }
}

/// Deterministic held-out split: every `every`-th frame (0, every, 2*every, ...) is a test view.
/// Returns the training and test frame indices, in that order; `every` of 0 counts as 1 (all
/// frames held out).
///
/// ```
/// use orbit_nerf_host::dataset::split_every;
///
/// let (train, test) = split_every(7, 3);
/// assert_eq!(train, [1, 2, 4, 5]);
/// assert_eq!(test, [0, 3, 6]);
/// ```
pub fn split_every(frame_count: usize, every: usize) -> (Vec<usize>, Vec<usize>) {
    let every = every.max(1);
    (0..frame_count).partition(|i| i % every != 0)
}

/// A training set and a separate test set as one dataset (the test set's frames after the
/// training set's, its truth after the training set's), with every training frame a training
/// view and every test frame a held-out view: the paper's protocol, where the test views are
/// other viewpoints and lighting, never trained on. The exact poses are kept only when both
/// sets have them (a truth that covered half the frames would misreport the other half).
pub fn with_test_set(
    (mut train, train_truth): (Dataset, Option<Vec<Pose>>),
    (test, test_truth): (Dataset, Option<Vec<Pose>>),
) -> (Dataset, Option<Vec<Pose>>, Vec<usize>, Vec<usize>) {
    let trained = train.frames.len();
    let tested = test.frames.len();
    train.frames.extend(test.frames);
    let truth = match (train_truth, test_truth) {
        (Some(mut both), Some(test)) => {
            both.extend(test);
            Some(both)
        }
        _ => None,
    };
    (
        train,
        truth,
        (0..trained).collect(),
        (trained..trained + tested).collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use orbit_nerf_core::glam::{Mat3, Vec3};

    /// The test set's frames are held-out views only, after every training frame.
    #[test]
    fn a_separate_test_set_is_held_out_and_never_a_training_view() {
        let set = |name: &str, frames: usize| Dataset {
            source: name.into(),
            frames: (0..frames)
                .map(|i| Frame {
                    name: format!("{name}{i}"),
                    camera: Camera {
                        width: 1,
                        height: 1,
                        fx: 1.0,
                        fy: 1.0,
                        cx: 0.5,
                        cy: 0.5,
                    },
                    pose: Pose {
                        rotation: Mat3::IDENTITY,
                        center: Vec3::ZERO,
                    },
                    pixels: vec![0; 3],
                    mask: None,
                    alpha_composited: false,
                })
                .collect(),
            scene_min: [-1.0; 3],
            scene_max: [1.0; 3],
            scene_box: SceneBoxOrigin::Unknown,
            background: [0.0; 3],
            target_centred: false,
        };
        let poses = |n: usize| Some(vec![set("p", 1).frames[0].pose; n]);
        let (merged, truth, train, test) =
            with_test_set((set("train", 5), poses(5)), (set("test", 3), poses(3)));
        assert_eq!(train, [0, 1, 2, 3, 4]);
        assert_eq!(test, [5, 6, 7]);
        assert!(
            test.iter()
                .all(|&i| merged.frames[i].name.starts_with("test"))
        );
        assert!(
            train
                .iter()
                .all(|&i| merged.frames[i].name.starts_with("train"))
        );
        assert_eq!(truth.map(|t| t.len()), Some(8));
        let (_, truth, _, _) = with_test_set((set("train", 5), poses(5)), (set("test", 3), None));
        assert!(truth.is_none());
    }

    #[test]
    fn masks_paint_the_background_only_where_the_mask_is_zero_and_not_over_alpha() {
        let frame = |mask: Option<Vec<u8>>, alpha_composited: bool| Frame {
            name: "f".into(),
            camera: Camera {
                width: 3,
                height: 1,
                fx: 2.0,
                fy: 2.0,
                cx: 1.5,
                cy: 0.5,
            },
            pose: Pose {
                rotation: Mat3::IDENTITY,
                center: Vec3::ZERO,
            },
            pixels: vec![10, 20, 30, 40, 50, 60, 70, 80, 90],
            mask,
            alpha_composited,
        };
        let mut dataset = Dataset {
            source: "d".into(),
            frames: vec![
                frame(Some(vec![0, 255, 0]), false),
                frame(None, false),
                frame(Some(vec![0, 255, 0]), true),
            ],
            scene_min: [-1.0; 3],
            scene_max: [1.0; 3],
            scene_box: SceneBoxOrigin::Stated("the test".into()),
            background: [1.0, 0.0, 0.5],
            target_centred: false,
        };
        assert_eq!(dataset.apply_masks(), 1);
        assert_eq!(
            dataset.frames[0].pixels,
            vec![255, 0, 128, 40, 50, 60, 255, 0, 128]
        );
        // No mask, or a mask from the alpha the pixels are already composited by: unchanged.
        for unchanged in &dataset.frames[1..] {
            assert_eq!(unchanged.pixels, vec![10, 20, 30, 40, 50, 60, 70, 80, 90]);
        }
    }
}
