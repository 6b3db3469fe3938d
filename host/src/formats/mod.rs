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

/// The dataset formats, told apart by the layout of a folder alone (which files exist; none is
/// read), so that a command can choose its model config before it reads the data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// `transforms_train.json` (Blender convention, composited on a background colour).
    NerfSynthetic,
    /// `transforms.json`.
    Nerfstudio,
    /// Anything else: a SPEED+ / SHIRT / simulator label file or folder (with `camera.json`).
    SpeedPlus,
}

impl Format {
    /// The format [`open`] reads `path` (a folder, or a label / transforms file) as.
    ///
    /// ```
    /// use orbit_nerf_host::formats::Format;
    /// use std::path::Path;
    ///
    /// // A file is recognised by its name; a folder by the files in it.
    /// assert_eq!(Format::of(Path::new("lego/transforms_train.json")), Format::NerfSynthetic);
    /// assert_eq!(Format::of(Path::new("capture/transforms.json")), Format::Nerfstudio);
    /// assert_eq!(Format::of(Path::new("shirt/roe1/train.json")), Format::SpeedPlus);
    /// ```
    pub fn of(path: &Path) -> Format {
        let is =
            |name: &str| path.join(name).is_file() || path.file_name().is_some_and(|n| n == name);
        if is("transforms_train.json") {
            Format::NerfSynthetic
        } else if is("transforms.json") {
            Format::Nerfstudio
        } else {
            Format::SpeedPlus
        }
    }

    /// The kind of folder, for messages ("a SPEED+/SHIRT/simulator folder").
    pub fn folder(self) -> &'static str {
        match self {
            Format::NerfSynthetic => "a NeRF-synthetic folder",
            Format::Nerfstudio => "a nerfstudio folder",
            Format::SpeedPlus => "a SPEED+/SHIRT/simulator folder",
        }
    }
}

/// Open a dataset folder (or label / transforms file) of any supported format:
/// NeRF-synthetic (`transforms_train.json`), nerfstudio (`transforms.json`) or SPEED+/SHIRT
/// (a label file with `camera.json`). `max_side` resizes the images (longer side in pixels).
/// NeRF-synthetic images are composited on `background` (NeRF's convention is white).
pub fn open(path: &Path, max_side: Option<u32>, background: [f32; 3]) -> Result<Dataset> {
    Ok(open_with_truth(path, max_side, background)?.0)
}

/// [`open`], with every frame's exact pose when the data has them (a SPEED+ / simulator
/// folder's `truth.json`), in frame order: held-out views are scored there, as the paper's
/// test set is.
pub fn open_with_truth(
    path: &Path,
    max_side: Option<u32>,
    background: [f32; 3],
) -> Result<(Dataset, Option<Vec<orbit_nerf_core::Pose>>)> {
    if !path.exists() {
        return Err(HostError::invalid(path, "no such file or folder"));
    }
    let size = max_side.map_or(OutputSize::Original, OutputSize::MaxSide);
    let options = LoadOptions { size, background };
    match Format::of(path) {
        Format::NerfSynthetic => {
            let dir = if path.is_dir() {
                path
            } else {
                path.parent().unwrap_or(path)
            };
            Ok((
                nerf_synthetic::load_nerf_synthetic(dir, SyntheticSplit::Train, &options)?,
                None,
            ))
        }
        Format::Nerfstudio => Ok((nerfstudio::load_nerfstudio(path, &options)?, None)),
        Format::SpeedPlus => {
            let options = speedplus::LoadOptions {
                max_side,
                domain: None,
            };
            let set = speedplus::load(path, &options)?;
            let truth = set.true_poses()?;
            Ok((set.dataset, truth))
        }
    }
}
