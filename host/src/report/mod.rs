//! Scoring and reporting for the paper's evaluation and ablations: per-view image metrics
//! (PSNR, SSIM, JNB on the right half and on the whole image), pose errors, markdown tables,
//! labelled comparison strips and line plots.
//!
//! Evaluation follows the paper (and K-Planes / NeRF-W): for a held-out view the appearance
//! embedding is fitted on the left half of the reference image, so the right half is the fair
//! score; the whole image is reported too because that is what the paper's figures show.
//!
//! Pictures carry their own text: a 5x7 bitmap font built into this module draws captions,
//! tick labels and legends, so no system font (absent on CI machines) is ever needed.
//! `plotters` draws the plot geometry (grid, frame, ticks, series) with its bitmap backend only.

#[cfg(all(feature = "profile", feature = "plots"))]
mod bars;
mod canvas;
mod figures;
#[cfg(feature = "plots")]
mod plot;
#[cfg(feature = "simulator")]
mod pose_noise;
mod poses;
mod strip;
mod tables;
mod views;

#[cfg(all(feature = "profile", feature = "plots"))]
pub use bars::stacked_bars;
pub use figures::{
    FIGURES_SCHEMA, Figures, MeansAt, ModelFigures, PoseRefinementFigures, TrainingFigures,
    ViewFigures,
};
#[cfg(feature = "plots")]
pub use plot::{labelled_scatter, line_plot};
#[cfg(feature = "simulator")]
pub use pose_noise::{ModelOutcome, NoiseLevelResult, POSE_NOISE_TITLES, pose_noise_sections};
pub use poses::{
    FramePose, PoseErrors, PoseUncertainty, frame_poses, pose_errors, pose_uncertainty,
    rotation_error_deg, rotation_error_split_deg, translation_error,
};
pub use strip::side_by_side;
pub use tables::{
    ModelRow, ablation_table, format_or_na, geometry_table, held_out_poses_table, markdown_table,
    pose_error_table, pose_uncertainty_table,
};
#[cfg(not(feature = "plots"))]
pub use unplotted::*;
pub use views::{ViewMetrics, mean_metrics, score_view};

/// Arithmetic mean; NaN for an empty slice.
fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}

/// Without the `plots` feature: the plots' signatures, drawing nothing (a report still names
/// them), so reports build the same way with or without plotters.
#[cfg(not(feature = "plots"))]
mod unplotted {
    use crate::error::Result;
    use std::path::Path;

    /// Not drawn: the `plots` feature is off.
    pub fn line_plot(
        _path: &Path,
        _title: &str,
        _x_label: &str,
        _y_label: &str,
        _series: &[(&str, Vec<(f64, f64)>)],
    ) -> Result<()> {
        Ok(())
    }

    /// Not drawn: the `plots` feature is off.
    pub fn labelled_scatter(
        _path: &Path,
        _title: &str,
        _x_label: &str,
        _y_label: &str,
        _names: &[&str],
        _points: &[(f64, f64)],
        _front: &[usize],
    ) -> Result<()> {
        Ok(())
    }

    /// Not drawn: the `plots` feature is off.
    #[cfg(feature = "profile")]
    pub fn stacked_bars(
        _path: &Path,
        _title: &str,
        _y_label: &str,
        _segments: &[&str],
        _bars: &[(&str, Vec<f64>)],
    ) -> Result<()> {
        Ok(())
    }
}
