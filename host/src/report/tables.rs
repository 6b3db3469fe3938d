//! Markdown tables: the ablation table, the pose-error and pose-uncertainty tables and the
//! held-out views scored at three poses.

use super::poses::{PoseErrors, PoseUncertainty};
use super::views::ViewMetrics;

/// A GitHub-flavoured markdown table with columns padded to a common width, so it also reads
/// well as plain text. Rows shorter than the widest row are padded with empty cells (the header
/// too); `|` inside a cell is escaped.
///
/// ```
/// use orbit_nerf_host::report::markdown_table;
///
/// let table = markdown_table(&["model", "PSNR"], &[vec!["a|b".into(), "31.20".into()]]);
/// assert_eq!(
///     table,
///     "| model | PSNR  |\n|-------|-------|\n| a\\|b  | 31.20 |\n"
/// );
/// ```
pub fn markdown_table(header: &[&str], rows: &[Vec<String>]) -> String {
    let columns = rows.iter().map(Vec::len).fold(header.len(), usize::max);
    let escape = |cell: &str| cell.replace('|', "\\|");
    let header: Vec<String> = header.iter().map(|h| escape(h)).collect();
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|row| row.iter().map(|c| escape(c)).collect())
        .collect();
    let mut widths = vec![3; columns];
    for row in std::iter::once(&header).chain(&body) {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.chars().count());
        }
    }
    let line = |cells: &[String]| {
        let padded: Vec<String> = widths
            .iter()
            .enumerate()
            .map(|(i, &width)| {
                let cell = cells.get(i).map(String::as_str).unwrap_or("");
                format!("{cell:<width$}")
            })
            .collect();
        format!("| {} |\n", padded.join(" | "))
    };
    let mut table = line(&header);
    let rule: Vec<String> = widths.iter().map(|&w| "-".repeat(w)).collect();
    table.push_str(&format!("|-{}-|\n", rule.join("-|-")));
    for row in &body {
        table.push_str(&line(row));
    }
    table
}

/// One model's line in an ablation table: its mean view metrics and its training time.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelRow {
    /// The model's name, the row's first cell.
    pub name: String,
    /// The model's mean held-out view metrics.
    pub metrics: ViewMetrics,
    /// Wall time of training, seconds.
    pub train_seconds: f64,
}

/// The paper-style ablation table (PSNR with 2 decimals, SSIM and JNB with 4, foreground PSNR
/// with 2, training time in seconds with 1), followed by a note saying which JNB is reported, since JNB variants give
/// different numbers on the same image. A NaN (no SSIM window, no JNB edge block, no mask) shows as `n/a`.
pub fn ablation_table(rows: &[ModelRow]) -> String {
    let header = [
        "model",
        "PSNR right",
        "SSIM right",
        "JNB right",
        "PSNR full",
        "SSIM full",
        "JNB full",
        "CPBD full",
        "fg PSNR",
        "fg PSNR right",
        "train s",
    ];
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|row| {
            let m = &row.metrics;
            vec![
                row.name.clone(),
                format!("{:.2}", m.psnr_right),
                format_or_na(m.ssim_right, 4),
                format_or_na(m.jnb_right, 4),
                format!("{:.2}", m.psnr_full),
                format_or_na(m.ssim_full, 4),
                format_or_na(m.jnb_full, 4),
                format_or_na(m.cpbd_full, 4),
                format_or_na(m.psnr_foreground, 2),
                format_or_na(m.psnr_foreground_right, 2),
                format!("{:.1}", row.train_seconds),
            ]
        })
        .collect();
    let mut table = markdown_table(&header, &body);
    table.push_str(
        "\nPSNR in dB on 8-bit images (inf: render equals reference). JNB: Ferzli & Karam's blur \
         per edge (the beta-mean of edge width over the just-noticeable width, 5 for block \
         contrast <= 50, else 3; independent of the image size), on the render's luma; lower is \
         sharper. CPBD: Narvekar & Karam's probability of blur detection; higher is sharper. \
         \"right\": x >= width/2, the half the appearance \
         embedding was not fitted on. \"fg\": over the pixels the mask marks as target (n/a \
         without masks). With masks applied (the default) the references' sky is the background \
         colour, so SSIM is on masked images.\n",
    );
    table
}

/// Pose errors before and after training (pose correction) for each model: rotation in degrees
/// (3 decimals), translation in the dataset's units (4 decimals), mean and median of each.
/// The frames column counts the frames compared before training.
pub fn pose_error_table(rows: &[(String, PoseErrors, PoseErrors)]) -> String {
    let header = [
        "model",
        "frames",
        "rot before mean (deg)",
        "rot before median (deg)",
        "trans before mean",
        "trans before median",
        "rot before about / across view axis (deg)",
        "rot after mean (deg)",
        "rot after median (deg)",
        "trans after mean",
        "trans after median",
        "rot after about / across view axis (deg)",
    ];
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|(name, before, after)| {
            let mut cells = vec![name.clone(), before.frames.to_string()];
            for errors in [before, after] {
                cells.extend([
                    format!("{:.3}", errors.rotation_deg_mean),
                    format!("{:.3}", errors.rotation_deg_median),
                    format!("{:.4}", errors.translation_mean),
                    format!("{:.4}", errors.translation_median),
                    format!(
                        "{:.3} / {:.3}",
                        errors.about_view_axis_deg_mean, errors.across_view_axis_deg_mean
                    ),
                ]);
            }
            cells
        })
        .collect();
    markdown_table(&header, &body)
}

/// The held-out views scored three ways, a row per model: at their labels (the paper's
/// protocol on noisy labels), at their exact poses (where the data has them) and at their
/// labels aligned by the pose refinement.
pub fn held_out_poses_table(
    rows: &[(String, ViewMetrics, Option<ViewMetrics>, ViewMetrics)],
) -> String {
    let header = [
        "model",
        "PSNR at labels",
        "PSNR at exact poses",
        "PSNR aligned",
        "SSIM at labels",
        "SSIM at exact poses",
        "SSIM aligned",
    ];
    let na = f64::NAN;
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|(name, labels, exact, aligned)| {
            vec![
                name.clone(),
                format_or_na(labels.psnr_full, 2),
                format_or_na(exact.map_or(na, |m| m.psnr_full), 2),
                format_or_na(aligned.psnr_full, 2),
                format_or_na(labels.ssim_full, 4),
                format_or_na(exact.map_or(na, |m| m.ssim_full), 4),
                format_or_na(aligned.ssim_full, 4),
            ]
        })
        .collect();
    markdown_table(&header, &body)
}

/// The refined training poses' uncertainty, a row per model with pose correction: the mean
/// 1-sigma attitude and position uncertainties and, with exact poses, the share of frames
/// whose true error lies within 3 sigma.
pub fn pose_uncertainty_table(rows: &[(String, PoseUncertainty)]) -> String {
    let header = [
        "model",
        "frames",
        "1-sigma attitude (deg)",
        "1-sigma position",
        "attitude error within 3 sigma",
        "position error within 3 sigma",
    ];
    let cell = |v: Option<f64>, d: usize| format_or_na(v.unwrap_or(f64::NAN), d);
    // The unit only beside a number: without exact poses the cell is `n/a` alone.
    let percent = |share: Option<f64>| match cell(share.map(|v| 100.0 * v), 0) {
        na if na == "n/a" => na,
        number => number + " %",
    };
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|(name, u)| {
            vec![
                name.clone(),
                u.frames.to_string(),
                cell(u.rotation_sigma_deg_mean, 3),
                cell(u.position_sigma_mean, 4),
                percent(u.rotation_within_3_sigma),
                percent(u.position_within_3_sigma),
            ]
        })
        .collect();
    markdown_table(&header, &body)
}

/// `value` with `decimals` decimals, or `n/a` when it is NaN (a metric the view could not give).
pub fn format_or_na(value: f64, decimals: usize) -> String {
    if value.is_nan() {
        "n/a".to_string()
    } else {
        format!("{value:.decimals$}")
    }
}

/// The geometry table: per model its surface's size and the symmetric Chamfer distance to
/// the true shape in millimetres (mean, 95th percentile; `geometry::chamfer`), or why there is
/// none.
pub fn geometry_table(rows: &[crate::ablation::GeometryRow]) -> String {
    let header = [
        "model",
        "Chamfer mean mm",
        "Chamfer p95 mm",
        "vertices",
        "triangles",
    ];
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            let (mean, p95) = match &r.chamfer {
                Ok(c) => (
                    format!("{:.1}", c.mean * 1000.0),
                    format!("{:.1}", c.p95 * 1000.0),
                ),
                Err(why) => (format!("n/a ({why})"), "n/a".into()),
            };
            vec![
                r.name.clone(),
                mean,
                p95,
                r.vertices.to_string(),
                r.triangles.to_string(),
            ]
        })
        .collect();
    markdown_table(&header, &rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_table_pads_and_escapes() {
        let table = markdown_table(
            &["a", "long header"],
            &[vec!["x|y".into(), "1".into()], vec!["z".into()]],
        );
        assert_eq!(
            table,
            "| a    | long header |\n\
             |------|-------------|\n\
             | x\\|y | 1           |\n\
             | z    |             |\n"
        );
    }

    fn example_metrics() -> ViewMetrics {
        ViewMetrics {
            psnr_right: 30.5449,
            ssim_right: 0.950_04,
            jnb_right: 0.033_31,
            psnr_full: 31.0,
            ssim_full: 0.96,
            jnb_full: f64::NAN,
            psnr_foreground: 27.123,
            psnr_foreground_right: f64::NAN,
            cpbd_full: 0.71,
        }
    }

    #[test]
    fn ablation_table_formats_the_paper_columns() {
        let table = ablation_table(&[ModelRow {
            name: "ours + pose".into(),
            metrics: example_metrics(),
            train_seconds: 1800.04,
        }]);
        let lines: Vec<&str> = table.lines().collect();
        assert!(lines[0].starts_with("| model"), "{table}");
        for column in [
            "PSNR right",
            "SSIM right",
            "JNB right",
            "JNB full",
            "fg PSNR",
            "fg PSNR right",
            "train s",
        ] {
            assert!(lines[0].contains(column), "{table}");
        }
        let cells: Vec<&str> = lines[2].split('|').map(str::trim).collect();
        assert_eq!(
            cells[1..12],
            [
                "ours + pose",
                "30.54",
                "0.9500",
                "0.0333",
                "31.00",
                "0.9600",
                "n/a",
                "0.7100",
                "27.12",
                "n/a",
                "1800.0"
            ]
        );
        assert!(table.contains("blur per edge"), "{table}");
    }

    #[test]
    fn pose_error_table_has_before_and_after() {
        let before = PoseErrors {
            rotation_deg_mean: 1.23456,
            rotation_deg_median: 1.0,
            translation_mean: 0.012345,
            translation_median: 0.01,
            about_view_axis_deg_mean: 0.5,
            across_view_axis_deg_mean: 1.1,
            frames: 400,
        };
        let after = PoseErrors {
            rotation_deg_mean: 0.2,
            about_view_axis_deg_mean: 0.1,
            ..before
        };
        let table = pose_error_table(&[("ours".into(), before, after)]);
        let row: Vec<&str> = table
            .lines()
            .nth(2)
            .unwrap()
            .split('|')
            .map(str::trim)
            .collect();
        assert_eq!(
            row[1..13],
            [
                "ours",
                "400",
                "1.235",
                "1.000",
                "0.0123",
                "0.0100",
                "0.500 / 1.100",
                "0.200",
                "1.000",
                "0.0123",
                "0.0100",
                "0.100 / 1.100"
            ]
        );
    }

    #[test]
    fn pose_uncertainty_shares_are_percent_or_n_a_alone() {
        let with_exact = PoseUncertainty {
            rotation_sigma_deg_mean: Some(0.12345),
            position_sigma_mean: Some(0.001_23),
            rotation_within_3_sigma: Some(0.994),
            position_within_3_sigma: Some(0.5),
            frames: 40,
        };
        let without_exact = PoseUncertainty {
            rotation_within_3_sigma: None,
            position_within_3_sigma: None,
            ..with_exact
        };
        let table = pose_uncertainty_table(&[
            ("exact".into(), with_exact),
            ("labels only".into(), without_exact),
        ]);
        let row = |n: usize| -> Vec<String> {
            let line = table.lines().nth(n).unwrap();
            line.split('|').map(|c| c.trim().to_owned()).collect()
        };
        assert_eq!(
            row(2)[1..7],
            ["exact", "40", "0.123", "0.0012", "99 %", "50 %"]
        );
        assert_eq!(
            row(3)[1..7],
            ["labels only", "40", "0.123", "0.0012", "n/a", "n/a"]
        );
    }
}
