//! Dataset formats: one module per format, each producing a [`Dataset`]; [`open`] picks the
//! format of a path. Formats depend on [`crate::dataset`], never the other way.

pub mod camera;
pub mod json;
pub mod nerf_synthetic;
pub mod nerfstudio;
pub mod resample;
pub mod speedplus;
pub mod transforms;

use crate::dataset::Dataset;
use crate::error::{HostError, Result};
use nerf_synthetic::SyntheticSplit;
use std::path::Path;
use transforms::{LoadOptions, OutputSize};

/// Open a dataset folder (or label / transforms file) of any supported format:
/// NeRF-synthetic (`transforms_train.json`), nerfstudio (`transforms.json`) or SPEED+/SHIRT
/// (a label file with `camera.json`). `max_side` resizes the images (longer side in pixels).
/// NeRF-synthetic images are composited on `background` (NeRF's convention is white).
pub fn open(path: &Path, max_side: Option<u32>, background: [f32; 3]) -> Result<Dataset> {
    if !path.exists() {
        return Err(HostError::invalid(path, "no such file or folder"));
    }
    let size = max_side.map_or(OutputSize::Original, OutputSize::MaxSide);
    let options = LoadOptions { size, background };
    let is = |name: &str| path.join(name).is_file() || path.file_name().is_some_and(|n| n == name);
    if is("transforms_train.json") {
        let dir = if path.is_dir() {
            path
        } else {
            path.parent().unwrap_or(path)
        };
        nerf_synthetic::load_nerf_synthetic(dir, SyntheticSplit::Train, &options)
    } else if is("transforms.json") {
        nerfstudio::load_nerfstudio(path, &options)
    } else {
        let options = speedplus::LoadOptions {
            max_side,
            domain: None,
        };
        Ok(speedplus::load(path, &options)?.dataset)
    }
}
