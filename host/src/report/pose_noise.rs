//! The report of the paper's pose-noise sweeps (rotation noise alone, translation noise alone):
//! per level, SSIM and JNB of ours with and without pose correction and the pose error of the
//! labels before and after correction, as tables and plots. `ablate --pose-noise` and
//! `sweep collect` both write it.

use super::{PoseErrors, ViewMetrics, format_or_na, line_plot, markdown_table};
use crate::error::Result;
use crate::sim::scene::LabelNoise;
use std::path::Path;

/// What one model gave at one noise level.
#[derive(Clone, Copy, Debug)]
pub struct ModelOutcome {
    /// Held-out means with each view rendered at its label.
    pub metrics: ViewMetrics,
    /// Held-out means at the exact poses; `None` where the data has none.
    pub metrics_exact: Option<ViewMetrics>,
    /// Held-out means at the labels aligned by test-time pose fitting; `None` where not scored.
    pub metrics_aligned: Option<ViewMetrics>,
    /// Pose error of the training labels against the exact poses; `None` without them.
    pub pose_before: Option<PoseErrors>,
    /// Pose error of the labels with the learned corrections against the exact poses; `None`
    /// without them.
    pub pose_after: Option<PoseErrors>,
}

/// One noise level: the two models (ours, ours + pose) trained on the same labels.
#[derive(Clone, Copy, Debug)]
pub struct NoiseLevelResult {
    /// The noise put on the training labels at this level.
    pub noise: LabelNoise,
    /// The model without pose correction.
    pub ours: ModelOutcome,
    /// The model with pose correction.
    pub pose: ModelOutcome,
}

/// One of the two sweeps: its section of the report and its plots.
struct SweepSpec {
    title: &'static str,
    column: &'static str,
    /// File name stem of its plots.
    name: &'static str,
    axis: &'static str,
    level: fn(&LabelNoise) -> f32,
    error_label: &'static str,
    error: fn(&PoseErrors) -> f64,
}

const ROTATION: SweepSpec = SweepSpec {
    title: "Rotation noise (exact positions)",
    column: "E_R deg",
    name: "rotation",
    axis: "rotation noise (deg)",
    level: |n| n.rotation_deg,
    error_label: "rotation error (deg)",
    error: |e| e.rotation_deg_mean,
};

/// The headings of the two sweeps' sections (`paper.md` takes the sections by them).
pub const POSE_NOISE_TITLES: [&str; 2] = [ROTATION.title, TRANSLATION.title];

const TRANSLATION: SweepSpec = SweepSpec {
    title: "Translation noise (exact attitudes)",
    column: "E_T mm",
    name: "translation",
    axis: "translation noise (mm)",
    level: |n| n.translation_m * 1000.0,
    error_label: "camera position error (mm)",
    error: |e| e.translation_mean * 1000.0,
};

/// The sections of the rotation sweep (levels `rotation`) and of the translation sweep (levels
/// `translation`), each left out when it has no level, with their plots written into `out`
/// (`rotation_ssim.png`, `rotation_error.png`, `translation_ssim.png`,
/// `translation_error.png`). A level missing from `results` is left out of its section.
pub fn pose_noise_sections(
    out: &Path,
    rotation: &[LabelNoise],
    translation: &[LabelNoise],
    results: &[NoiseLevelResult],
) -> Result<String> {
    let mut text = String::new();
    for (sweep, noises) in [(ROTATION, rotation), (TRANSLATION, translation)] {
        if noises.is_empty() {
            continue;
        }
        let rows: Vec<&NoiseLevelResult> = (noises.iter())
            .filter_map(|&n| results.iter().find(|l| l.noise == n))
            .collect();
        let name = sweep.name;
        text.push_str(&format!("\n## {}\n\n", sweep.title));
        text.push_str(&sweep_table(sweep.column, &rows, sweep.level));
        text.push_str(&format!(
            "\n![SSIM]({name}_ssim.png)\n![{}]({name}_error.png)\n",
            sweep.error_label
        ));
        plot_sweep(out, &sweep, &rows)?;
    }
    Ok(text)
}

/// One sweep's table: a row per level, the level in the first column.
fn sweep_table(
    level_header: &str,
    rows: &[&NoiseLevelResult],
    level: fn(&LabelNoise) -> f32,
) -> String {
    let header = [
        level_header,
        "SSIM ours",
        "SSIM ours+pose",
        "JNB ours",
        "JNB ours+pose",
        "rot. error labels / corrected deg",
        "about view axis labels / corrected deg",
        "across view axis labels / corrected deg",
        "position error labels / corrected mm",
        "PSNR at labels ours / ours+pose",
        "PSNR at exact poses ours / ours+pose",
        "PSNR aligned ours / ours+pose",
    ];
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|l| {
            let (ours, pose) = (&l.ours, &l.pose);
            let before = pose.pose_before.unwrap_or_default();
            let after = pose.pose_after.unwrap_or_default();
            let psnr = |m: Option<ViewMetrics>| m.map_or(f64::NAN, |m| m.psnr_full);
            let pair = |a: f64, b: f64| format!("{} / {}", format_or_na(a, 2), format_or_na(b, 2));
            vec![
                format!("{}", level(&l.noise)),
                format_or_na(ours.metrics.ssim_full, 4),
                format_or_na(pose.metrics.ssim_full, 4),
                format_or_na(ours.metrics.jnb_full, 4),
                format_or_na(pose.metrics.jnb_full, 4),
                format!(
                    "{:.3} / {:.3}",
                    before.rotation_deg_mean, after.rotation_deg_mean
                ),
                format!(
                    "{:.3} / {:.3}",
                    before.about_view_axis_deg_mean, after.about_view_axis_deg_mean
                ),
                format!(
                    "{:.3} / {:.3}",
                    before.across_view_axis_deg_mean, after.across_view_axis_deg_mean
                ),
                format!(
                    "{:.1} / {:.1}",
                    before.translation_mean * 1000.0,
                    after.translation_mean * 1000.0
                ),
                pair(ours.metrics.psnr_full, pose.metrics.psnr_full),
                pair(psnr(ours.metrics_exact), psnr(pose.metrics_exact)),
                pair(psnr(ours.metrics_aligned), psnr(pose.metrics_aligned)),
            ]
        })
        .collect();
    markdown_table(&header, &rows)
}

/// `NAME_ssim.png` (held-out SSIM with and without pose correction) and `NAME_error.png` (the
/// labels' pose error before and after correction) against the noise level.
fn plot_sweep(out: &Path, sweep: &SweepSpec, rows: &[&NoiseLevelResult]) -> Result<()> {
    let points = |f: &dyn Fn(&NoiseLevelResult) -> f64| -> Vec<(f64, f64)> {
        rows.iter()
            .map(|l| ((sweep.level)(&l.noise) as f64, f(l)))
            .collect()
    };
    let error = |errors: Option<PoseErrors>| (sweep.error)(&errors.unwrap_or_default());
    line_plot(
        &out.join(format!("{}_ssim.png", sweep.name)),
        &format!("held-out SSIM vs {}", sweep.axis),
        sweep.axis,
        "SSIM",
        &[
            ("ours", points(&|l| l.ours.metrics.ssim_full)),
            ("ours + pose", points(&|l| l.pose.metrics.ssim_full)),
        ],
    )?;
    line_plot(
        &out.join(format!("{}_error.png", sweep.name)),
        &format!("{} of the training poses", sweep.error_label),
        sweep.axis,
        sweep.error_label,
        &[
            ("labels", points(&|l| error(l.pose.pose_before))),
            ("corrected", points(&|l| error(l.pose.pose_after))),
        ],
    )?;
    Ok(())
}
