//! `metrics.json`: the figures a command reports, for scripts. One schema for `train`, `eval`,
//! `ablate`, `demo` and `stream`, built here: each model's mean over the held-out views (as
//! [`super::mean_metrics`] gives it, the numbers the printed and markdown tables show), each
//! view, and how the model trained. A value that is not a number (NaN: no SSIM window, no
//! JNB edge block, no mask; or an infinite PSNR) is written as `null`.

use super::{FramePose, PoseUncertainty, ViewMetrics};
use crate::error::{HostError, Result};
use serde::Serialize;
use std::path::Path;

/// Version of the layout below; raised when a field changes meaning or goes away.
pub const FIGURES_SCHEMA: u32 = 1;

/// The contents of `metrics.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Figures {
    /// [`FIGURES_SCHEMA`] of the writer, so a script can refuse a layout it does not know.
    pub schema: u32,
    /// The command that wrote it (`train`, `eval`, `ablate`, `demo`, `stream`).
    pub command: String,
    /// One entry per model scored (an ablation's variants, a stream's and its reference).
    pub models: Vec<ModelFigures>,
}

/// One model: its mean over the held-out views, each view, and its training when known.
#[derive(Clone, Debug, Serialize)]
pub struct ModelFigures {
    /// The model's name in reports (a variant, `model`, a checkpoint's path).
    pub name: String,
    /// The mean over the held-out views, each at its label.
    pub mean: ViewMetrics,
    /// Each held-out view, in the order scored.
    pub views: Vec<ViewFigures>,
    /// How the model trained; `None` when it was only loaded (`eval`).
    pub training: Option<TrainingFigures>,
    /// The same means with the views at their exact poses and aligned, where scored.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_at: Option<MeansAt>,
    /// The training poses' refinement: each frame's uncertainty (and true error, where
    /// known) and their summary.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose_refinement: Option<PoseRefinementFigures>,
}

/// Held-out means at other poses than the labels.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct MeansAt {
    /// Each view at its exact pose (`None` where the data has none).
    pub exact_poses: Option<ViewMetrics>,
    /// Each view at its label aligned by the pose refinement on its left half.
    pub aligned: ViewMetrics,
}

/// The pose refinement's figures.
#[derive(Clone, Debug, Serialize)]
pub struct PoseRefinementFigures {
    /// The uncertainty summed up over the training frames.
    pub summary: PoseUncertainty,
    /// Each training frame's refined pose, uncertainty and (where known) true error.
    pub frames: Vec<FramePose>,
}

impl PoseRefinementFigures {
    /// The mean 1-sigma attitude and position of the training frames, in one line.
    pub fn summary_line(&self) -> String {
        let s = &self.summary;
        format!(
            "pose uncertainty (1 sigma, mean over {} frames): attitude {} deg, position {}",
            s.frames,
            (s.rotation_sigma_deg_mean).map_or("n/a".into(), |v| format!("{v:.3}")),
            (s.position_sigma_mean).map_or("n/a".into(), |v| format!("{v:.4}"))
        )
    }
}

/// One held-out view's metrics, its mean samples per ray and seconds (fit and render).
#[derive(Clone, Debug, Serialize)]
pub struct ViewFigures {
    /// The view's frame index in the dataset.
    pub index: usize,
    /// The view's image file name.
    pub name: String,
    /// The view's image metrics (written inline, not as a nested object).
    #[serde(flatten)]
    pub metrics: ViewMetrics,
    /// Mean samples per ray of the view's render.
    pub samples_per_ray: f64,
    /// Wall time of fitting the view's embedding and rendering it, seconds.
    pub seconds: f64,
}

/// How a model trained.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct TrainingFigures {
    /// Training steps the model has taken (applied or skipped).
    pub steps: u64,
    /// Steps whose update was skipped because the loss or a gradient was not finite.
    pub steps_skipped: u64,
    /// Wall time of the training steps, seconds (scoring excluded).
    pub seconds: f64,
    /// Mean samples per training ray (after early ray termination).
    pub samples_per_ray: f64,
}

impl Figures {
    /// The figures of `command` for `models`, at the current [`FIGURES_SCHEMA`].
    pub fn new(command: &str, models: Vec<ModelFigures>) -> Figures {
        Figures {
            schema: FIGURES_SCHEMA,
            command: command.to_owned(),
            models,
        }
    }

    /// Write as `dir/metrics.json`, atomically.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let path = dir.join("metrics.json");
        let text = serde_json::to_vec_pretty(self)
            .map_err(|e| HostError::invalid(&path, format!("JSON encoding failed: {e}")))?;
        crate::io::write_atomic(&path, &text)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn not_a_number_is_written_as_null() {
        let metrics = ViewMetrics {
            psnr_right: 30.5,
            ssim_right: f64::NAN,
            jnb_right: 1.0,
            psnr_full: f64::INFINITY,
            ssim_full: 0.9,
            jnb_full: 2.0,
            psnr_foreground: f64::NAN,
            psnr_foreground_right: 3.0,
            cpbd_full: 0.5,
        };
        let figures = Figures::new(
            "eval",
            vec![ModelFigures {
                name: "model".into(),
                mean: metrics,
                views: vec![],
                training: None,
                mean_at: None,
                pose_refinement: None,
            }],
        );
        let dir = tempfile::tempdir().unwrap();
        figures.write(dir.path()).unwrap();
        let text = std::fs::read_to_string(dir.path().join("metrics.json")).unwrap();
        let value: serde_json::Value = serde_json::from_str(&text).unwrap();
        let mean = &value["models"][0]["mean"];
        assert_eq!(mean["psnr_right"], 30.5);
        assert!(mean["ssim_right"].is_null() && mean["psnr_full"].is_null());
        assert_eq!(value["schema"], FIGURES_SCHEMA);
        assert_eq!(value["command"], "eval");
    }
}
