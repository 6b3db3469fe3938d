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

use crate::error::{HostError, Result};
use crate::io;
use crate::metrics::{self, ImageRef, JnbVariant, MetricError};
use glam::DVec3;
use orbit_nerf_core::camera::Pose;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use std::ops::Range;
use std::path::Path;

// ---------------------------------------------------------------------------------------------
// Image metrics of one view
// ---------------------------------------------------------------------------------------------

/// Image quality of one rendered view against its reference, on the right half
/// (`x >= width / 2`, the pixels the appearance embedding was not fitted on) and on the whole
/// image.
///
/// - PSNR in dB on 8-bit values; `f64::INFINITY` when the quantised render equals the reference
///   (as scikit-image reports it; nothing is capped).
/// - SSIM as [`metrics::ssim`] (mean over the three channels).
/// - JNB is [`metrics::JnbScore::blur`] with [`JnbVariant::Paper`], lower is sharper, measured
///   on the render alone (it is a no-reference metric). `f64::NAN` when the region has no edge
///   block to measure: a blank render, or a region narrower or shorter than one 64x64 block.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewMetrics {
    pub psnr_right: f64,
    pub ssim_right: f64,
    pub jnb_right: f64,
    pub psnr_full: f64,
    pub ssim_full: f64,
    pub jnb_full: f64,
}

/// Score a render (RGB `f32` in [0, 1], row-major, `width * height * 3` values) against the
/// reference image (RGB8, same layout).
///
/// The render is quantised to 8 bits first (round half up, values outside [0, 1] clamped, NaN
/// taken as 0): the reference is 8-bit, and NeRF evaluations score renders as saved 8-bit
/// images. JNB reads the Rec.601 luma (`0.299 R + 0.587 G + 0.114 B`) of the quantised render,
/// itself rounded to 8 bits, as an image library's 8-bit gray conversion gives it to the
/// reference JNB code.
///
/// Errors when a buffer does not match `width x height x 3`, or when a region is smaller than
/// SSIM's 11x11 window.
pub fn score_view(
    render: &[f32],
    truth: &[u8],
    width: usize,
    height: usize,
) -> Result<ViewMetrics, MetricError> {
    let rendered = quantize(render);
    let rendered_image = ImageRef::new(&rendered, width, height, 3)?;
    let truth_image = ImageRef::new(truth, width, height, 3)?;
    let luma = rec601_luma(&rendered);
    let luma_image = ImageRef::new(&luma, width, height, 1)?;

    let left = width / 2;
    let right_width = width - left;
    let rendered_right = rendered_image.region(left, 0, right_width, height)?;
    let truth_right = truth_image.region(left, 0, right_width, height)?;
    let luma_right = luma_image.region(left, 0, right_width, height)?;

    Ok(ViewMetrics {
        psnr_right: metrics::psnr(&rendered_right, &truth_right)?,
        ssim_right: metrics::ssim(&rendered_right, &truth_right)?,
        jnb_right: jnb_blur(&luma_right)?,
        psnr_full: metrics::psnr(&rendered_image, &truth_image)?,
        ssim_full: metrics::ssim(&rendered_image, &truth_image)?,
        jnb_full: jnb_blur(&luma_image)?,
    })
}

/// Mean over views. PSNR and SSIM are plain means (an infinite PSNR makes the mean infinite,
/// which is the honest summary of a perfect view). JNB ignores NaN entries (views with no edge
/// block) and is NaN only when every view is. No views gives NaN everywhere.
pub fn mean_metrics(views: &[ViewMetrics]) -> ViewMetrics {
    let field_mean =
        |field: fn(&ViewMetrics) -> f64| mean(&views.iter().map(field).collect::<Vec<f64>>());
    let field_mean_ignoring_nan = |field: fn(&ViewMetrics) -> f64| {
        mean(
            &views
                .iter()
                .map(field)
                .filter(|v| !v.is_nan())
                .collect::<Vec<f64>>(),
        )
    };
    ViewMetrics {
        psnr_right: field_mean(|v| v.psnr_right),
        ssim_right: field_mean(|v| v.ssim_right),
        jnb_right: field_mean_ignoring_nan(|v| v.jnb_right),
        psnr_full: field_mean(|v| v.psnr_full),
        ssim_full: field_mean(|v| v.ssim_full),
        jnb_full: field_mean_ignoring_nan(|v| v.jnb_full),
    }
}

/// `[0, 1]` floats to bytes: `floor(v * 255 + 0.5)` clamped to 0..=255. The `as u8` cast maps
/// NaN to 0.
fn quantize(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .map(|&v| (v * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8)
        .collect()
}

/// Rec.601 luma of packed RGB8, rounded half up to 8 bits.
fn rec601_luma(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3)
        .map(|p| {
            let luma = 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64;
            (luma + 0.5).floor().min(255.0) as u8
        })
        .collect()
}

/// JNB blur of a gray image, NaN when there is no edge block to measure.
fn jnb_blur(gray: &ImageRef<u8>) -> Result<f64, MetricError> {
    let score = metrics::jnb(gray, JnbVariant::Paper)?;
    Ok(if score.edge_blocks == 0 {
        f64::NAN
    } else {
        score.blur
    })
}

// ---------------------------------------------------------------------------------------------
// Pose errors
// ---------------------------------------------------------------------------------------------

/// Angle in degrees, in [0, 180], of the relative rotation `R_a^T R_b`.
///
/// Computed in `f64` as `atan2(|v|, trace - 1)`, where `v` is the axial vector of the
/// relative rotation (`|v| = 2 sin θ`, `trace - 1 = 2 cos θ`). Unlike `acos((trace - 1) / 2)`,
/// whose slope is infinite at 0° and 180°, this stays accurate at both ends: identical poses
/// give exactly 0, and f32 rounding in the matrices does not show up as a spurious 0.03°. It
/// needs no clamping either, and is insensitive to a uniform scale error in the matrices.
pub fn rotation_error_deg(a: &Pose, b: &Pose) -> f64 {
    relative_rotation(a, b).1.to_degrees()
}

/// The rotation error of `rotation_error_deg` split by its axis in camera `a`'s frame, in
/// degrees: the part about the optical axis (the image turns in its own plane, which every
/// edge of the target shows) and the part across it (the camera turns about the target, which
/// only the target's relief shows). The two add up in quadrature to the whole angle, except at
/// exactly 180 degrees, whose axis this does not recover (it gives 0 and 0).
pub fn rotation_error_split_deg(a: &Pose, b: &Pose) -> (f64, f64) {
    let (axis, angle) = relative_rotation(a, b);
    (
        (angle * axis.z.abs()).to_degrees(),
        (angle * axis.truncate().length()).to_degrees(),
    )
}

/// Unit axis (zero for no rotation) and angle in [0, pi] of `R_a^T R_b`.
fn relative_rotation(a: &Pose, b: &Pose) -> (DVec3, f64) {
    let relative = a.rotation.as_dmat3().transpose() * b.rotation.as_dmat3();
    let (x, y, z) = (relative.x_axis, relative.y_axis, relative.z_axis);
    // Column-major: m(row, col) is `<col>_axis.<row>`.
    let axial = DVec3::new(y.z - z.y, z.x - x.z, x.y - y.x);
    let twice_cos = x.x + y.y + z.z - 1.0;
    (axial.normalize_or_zero(), axial.length().atan2(twice_cos))
}

/// Distance between the two camera centres, in the dataset's units (metres for SPEED+/SHIRT).
pub fn translation_error(a: &Pose, b: &Pose) -> f64 {
    a.center.as_dvec3().distance(b.center.as_dvec3())
}

/// Summary of per-frame pose errors against ground truth.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseErrors {
    pub rotation_deg_mean: f64,
    pub rotation_deg_median: f64,
    pub translation_mean: f64,
    pub translation_median: f64,
    /// Mean of the rotation error's parts about and across the optical axis
    /// (`rotation_error_split_deg`).
    pub about_view_axis_deg_mean: f64,
    pub across_view_axis_deg_mean: f64,
    /// Number of frames compared.
    pub frames: usize,
}

/// Rotation and translation errors of `estimated` against `truth`, frame by frame.
///
/// When the slices differ in length only the common prefix is compared (`frames` says how many);
/// empty input gives all zeros with `frames == 0`. Never panics; a non-finite pose gives NaN
/// errors, which propagate into the mean, and sort last for the median.
pub fn pose_errors(estimated: &[Pose], truth: &[Pose]) -> PoseErrors {
    let pairs = estimated.iter().zip(truth);
    let rotations: Vec<f64> = pairs
        .clone()
        .map(|(e, t)| rotation_error_deg(e, t))
        .collect();
    let (about, across): (Vec<f64>, Vec<f64>) = pairs
        .clone()
        .map(|(e, t)| rotation_error_split_deg(t, e))
        .unzip();
    let translations: Vec<f64> = pairs.map(|(e, t)| translation_error(e, t)).collect();
    if rotations.is_empty() {
        return PoseErrors::default();
    }
    PoseErrors {
        rotation_deg_mean: mean(&rotations),
        rotation_deg_median: median(&rotations),
        translation_mean: mean(&translations),
        translation_median: median(&translations),
        about_view_axis_deg_mean: mean(&about),
        across_view_axis_deg_mean: mean(&across),
        frames: rotations.len(),
    }
}

/// Arithmetic mean; NaN for an empty slice.
fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}

/// Median of a non-empty slice; the mean of the two middle values for an even count.
fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let middle = sorted.len() / 2;
    if sorted.len() % 2 == 1 {
        sorted[middle]
    } else {
        (sorted[middle - 1] + sorted[middle]) / 2.0
    }
}

// ---------------------------------------------------------------------------------------------
// Tables
// ---------------------------------------------------------------------------------------------

/// A GitHub-flavoured markdown table with columns padded to a common width, so it also reads
/// well as plain text. Rows shorter than the widest row are padded with empty cells (the header
/// too); `|` inside a cell is escaped.
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
    pub name: String,
    pub metrics: ViewMetrics,
    pub train_seconds: f64,
}

/// The paper-style ablation table (PSNR with 2 decimals, SSIM and JNB with 4, training time in
/// seconds with 1), followed by a note saying which JNB is reported, since JNB variants give
/// different numbers on the same image. A NaN JNB shows as `n/a`.
pub fn ablation_table(rows: &[ModelRow]) -> String {
    let header = [
        "model",
        "PSNR right",
        "SSIM right",
        "JNB right",
        "PSNR full",
        "SSIM full",
        "JNB full",
        "train s",
    ];
    let body: Vec<Vec<String>> = rows
        .iter()
        .map(|row| {
            let m = &row.metrics;
            vec![
                row.name.clone(),
                format!("{:.2}", m.psnr_right),
                format!("{:.4}", m.ssim_right),
                format_or_na(m.jnb_right, 4),
                format!("{:.2}", m.psnr_full),
                format!("{:.4}", m.ssim_full),
                format_or_na(m.jnb_full, 4),
                format!("{:.1}", row.train_seconds),
            ]
        })
        .collect();
    let mut table = markdown_table(&header, &body);
    table.push_str(
        "\nPSNR in dB on 8-bit images (inf: render equals reference). JNB: Ferzli & Karam blur \
         D/L, paper variant (L = edge blocks, W_JNB = 5 for block contrast <= 50), on the \
         render's luma; lower is sharper. \"right\": x >= width/2, the half the appearance \
         embedding was not fitted on.\n",
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

fn format_or_na(value: f64, decimals: usize) -> String {
    if value.is_nan() {
        "n/a".to_string()
    } else {
        format!("{value:.decimals$}")
    }
}

// ---------------------------------------------------------------------------------------------
// Bitmap font and RGB canvas
// ---------------------------------------------------------------------------------------------

/// 5x7 glyphs, rows top to bottom, bit 4 the leftmost column. Lower-case letters are drawn
/// upper-case; any other character missing here is drawn as the last entry, `?`.
static FONT: [(char, [u8; 7]); 51] = [
    ('A', [0x0E, 0x11, 0x11, 0x11, 0x1F, 0x11, 0x11]),
    ('B', [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E]),
    ('C', [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E]),
    ('D', [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C]),
    ('E', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F]),
    ('F', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10]),
    ('G', [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F]),
    ('H', [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]),
    ('I', [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('J', [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C]),
    ('K', [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11]),
    ('L', [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F]),
    ('M', [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11]),
    ('N', [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11]),
    ('O', [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('P', [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10]),
    ('Q', [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D]),
    ('R', [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11]),
    ('S', [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E]),
    ('T', [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]),
    ('U', [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('V', [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04]),
    ('W', [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A]),
    ('X', [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11]),
    ('Y', [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04]),
    ('Z', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F]),
    ('0', [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E]),
    ('1', [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('2', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F]),
    ('3', [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E]),
    ('4', [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02]),
    ('5', [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E]),
    ('6', [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E]),
    ('7', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]),
    ('8', [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E]),
    ('9', [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C]),
    (' ', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00]),
    ('+', [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00]),
    ('-', [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00]),
    ('.', [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C]),
    (',', [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08]),
    (':', [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00]),
    ('/', [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00]),
    ('%', [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03]),
    ('(', [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02]),
    (')', [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08]),
    ('[', [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E]),
    (']', [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E]),
    ('_', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F]),
    ('=', [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00]),
    ('?', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04]),
];
const GLYPH_WIDTH: usize = 5;
const GLYPH_HEIGHT: usize = 7;
/// Horizontal distance between glyph origins, in font pixels (one blank column between).
const GLYPH_ADVANCE: usize = GLYPH_WIDTH + 1;

fn glyph(c: char) -> &'static [u8; 7] {
    let upper = c.to_ascii_uppercase();
    let (_, rows) = FONT
        .iter()
        .find(|(g, _)| *g == upper)
        .unwrap_or(&FONT[FONT.len() - 1]);
    rows
}

/// Width in pixels of `text` drawn at `scale`.
fn text_width(text: &str, scale: usize) -> usize {
    let chars = text.chars().count();
    (chars * GLYPH_ADVANCE).saturating_sub(1) * scale
}

/// Calls `set(u, v)` for each lit pixel of `text` laid out left to right at `scale`, with `u`
/// along the text and `v` down from the top of the glyphs.
fn for_each_text_pixel(text: &str, scale: usize, mut set: impl FnMut(usize, usize)) {
    for (index, c) in text.chars().enumerate() {
        let origin = index * GLYPH_ADVANCE * scale;
        for (row, bits) in glyph(c).iter().enumerate() {
            for column in 0..GLYPH_WIDTH {
                if bits & (0x10 >> column) == 0 {
                    continue;
                }
                for dv in 0..scale {
                    for du in 0..scale {
                        set(origin + column * scale + du, row * scale + dv);
                    }
                }
            }
        }
    }
}

type Rgb = [u8; 3];

/// A packed RGB8 image being drawn on; writes outside it are dropped.
struct Canvas<'a> {
    pixels: &'a mut [u8],
    width: usize,
    height: usize,
}

impl Canvas<'_> {
    fn put(&mut self, x: usize, y: usize, colour: Rgb) {
        if x < self.width && y < self.height {
            let i = (y * self.width + x) * 3;
            self.pixels[i..i + 3].copy_from_slice(&colour);
        }
    }

    fn fill_rect(&mut self, x: usize, y: usize, width: usize, height: usize, colour: Rgb) {
        for yy in y..y + height {
            for xx in x..x + width {
                self.put(xx, yy, colour);
            }
        }
    }

    /// Text whose top-left corner is at `(x, y)`.
    fn text(&mut self, x: usize, y: usize, text: &str, scale: usize, colour: Rgb) {
        for_each_text_pixel(text, scale, |u, v| self.put(x + u, y + v, colour));
    }

    /// Text rotated a quarter turn anticlockwise (read bottom to top, as a y-axis label), its
    /// glyph tops facing left at column `x`, starting at row `bottom` and going up.
    fn text_up(&mut self, x: usize, bottom: usize, text: &str, scale: usize, colour: Rgb) {
        for_each_text_pixel(text, scale, |u, v| {
            if let Some(y) = bottom.checked_sub(u) {
                self.put(x + v, y, colour);
            }
        });
    }
}

// ---------------------------------------------------------------------------------------------
// Side-by-side comparison strip
// ---------------------------------------------------------------------------------------------

/// Pixels between tiles in [`side_by_side`].
const TILE_GAP: usize = 2;
const STRIP_BACKGROUND: Rgb = [255, 255, 255];
const CAPTION_INK: Rgb = [0, 0, 0];
/// Captions wrap onto at most this many lines before their scale is reduced.
const MAX_CAPTION_LINES: usize = 2;

/// The tiles (RGB8, each `width x height`) in one row, 2 px apart on a white background, each
/// with a caption band above it holding its label, centred. Returns `(width, height, RGB8
/// pixels)` of the strip.
///
/// Captions are drawn at one scale for the whole strip, the largest that grows with the tile
/// (2x, 10x14-px glyphs, for 128-px tiles) at which every label fits its tile on at most two
/// lines, wrapping at spaces; at 1x, what still does not fit is cut. No tiles give an empty
/// `(0, 0, [])` image.
///
/// # Panics
/// When a tile's buffer is not `width * height * 3` bytes: that is a caller bug, not input.
pub fn side_by_side(tiles: &[(&str, &[u8])], width: u32, height: u32) -> (u32, u32, Vec<u8>) {
    if tiles.is_empty() {
        return (0, 0, Vec::new());
    }
    let (tile_width, tile_height) = (width as usize, height as usize);
    let (scale, captions) = layout_captions(tiles.iter().map(|(label, _)| *label), tile_width);
    let padding = 2 * scale;
    let line_pitch = (GLYPH_HEIGHT + 2) * scale;
    let lines = captions.iter().map(Vec::len).max().unwrap_or(0).max(1);
    let band = 2 * padding + lines * line_pitch - 2 * scale;
    let strip_width = tiles.len() * tile_width + (tiles.len() - 1) * TILE_GAP;
    let strip_height = band + tile_height;
    let mut pixels = STRIP_BACKGROUND.repeat(strip_width * strip_height);
    let mut canvas = Canvas {
        pixels: &mut pixels,
        width: strip_width,
        height: strip_height,
    };
    let row_bytes = tile_width * 3;
    for (index, ((label, tile), caption)) in tiles.iter().zip(&captions).enumerate() {
        assert_eq!(
            tile.len(),
            row_bytes * tile_height,
            "tile {index} ({label:?}) is not a {tile_width}x{tile_height} RGB8 image"
        );
        let left = index * (tile_width + TILE_GAP);
        for row in 0..tile_height {
            let start = ((band + row) * strip_width + left) * 3;
            canvas.pixels[start..start + row_bytes]
                .copy_from_slice(&tile[row * row_bytes..(row + 1) * row_bytes]);
        }
        for (line_index, line) in caption.iter().enumerate() {
            let x = left + tile_width.saturating_sub(text_width(line, scale)) / 2;
            let y = padding + line_index * line_pitch;
            canvas.text(x, y, line, scale, CAPTION_INK);
        }
    }
    (strip_width as u32, strip_height as u32, pixels)
}

/// The caption scale, from 1 up to one step per 64 px of tile width (at most 4), and each
/// label's lines at that scale: the largest scale at which every label wraps onto at most
/// [`MAX_CAPTION_LINES`] lines, keeping a one-glyph-pixel margin on each side.
fn layout_captions<'a>(
    labels: impl Iterator<Item = &'a str> + Clone,
    tile_width: usize,
) -> (usize, Vec<Vec<String>>) {
    let largest = (tile_width / 64).clamp(1, 4);
    let wrap_all = |scale: usize| -> Vec<Vec<String>> {
        let max_chars = (tile_width / scale).saturating_sub(1) / GLYPH_ADVANCE;
        labels
            .clone()
            .map(|label| wrap_caption(label, max_chars))
            .collect()
    };
    for scale in (2..=largest).rev() {
        let captions = wrap_all(scale);
        if captions
            .iter()
            .all(|lines| lines.len() <= MAX_CAPTION_LINES)
        {
            return (scale, captions);
        }
    }
    let mut captions = wrap_all(1);
    for lines in &mut captions {
        lines.truncate(MAX_CAPTION_LINES);
    }
    (1, captions)
}

/// `label` broken at spaces into lines of at most `max_chars` characters; a word longer than
/// a line is cut to fit.
fn wrap_caption(label: &str, max_chars: usize) -> Vec<String> {
    let mut lines = Vec::new();
    if max_chars == 0 {
        return lines;
    }
    let mut current = String::new();
    for word in label.split_whitespace() {
        let word: String = word.chars().take(max_chars).collect();
        if current.is_empty() {
            current = word;
        } else if current.chars().count() + 1 + word.chars().count() <= max_chars {
            current.push(' ');
            current.push_str(&word);
        } else {
            lines.push(std::mem::replace(&mut current, word));
        }
    }
    if !current.is_empty() {
        lines.push(current);
    }
    lines
}

// ---------------------------------------------------------------------------------------------
// Line plots
// ---------------------------------------------------------------------------------------------

const PLOT_WIDTH: usize = 800;
const PLOT_HEIGHT: usize = 480;
/// Text is drawn at 2x (10x14-px glyphs): legible in a PNG viewer without zooming.
const PLOT_TEXT_SCALE: usize = 2;
const TICK_LENGTH: usize = 6;
const LEGEND_SWATCH: usize = 24;
const LEGEND_ROW: usize = 24;
/// Series with at most this many points also get a dot at each point, so a sweep over a few
/// settings (noise levels, image counts) shows where the measurements are.
const MARKER_LIMIT: usize = 30;
const INK: Rgb = [0, 0, 0];
const GRID: RGBColor = RGBColor(225, 225, 225);
/// Tableau 10: distinct for most colour-vision deficiencies, and on a white background.
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// An 800x480 PNG line plot of `series` (name, points): a framed plot area with grid lines,
/// ticks and tick labels on both axes, a title, axis labels, and a legend to the right with
/// one colour per series (cycling after ten). Non-finite points are left out; with no finite
/// point at all the axes run 0..1. Written atomically with [`io::write_png`].
pub fn line_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(&str, Vec<(f64, f64)>)],
) -> Result<()> {
    let finite: Vec<Vec<(f64, f64)>> = series
        .iter()
        .map(|(_, points)| {
            points
                .iter()
                .copied()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect()
        })
        .collect();
    // A little room at the sides keeps end markers and lines off the frame.
    let x_range = data_range(finite.iter().flatten().map(|p| p.0), 0.02);
    let y_range = data_range(finite.iter().flatten().map(|p| p.1), 0.05);
    let x_ticks = RangedCoordf64::from(x_range.clone()).key_points(8usize);
    let y_ticks = RangedCoordf64::from(y_range.clone()).key_points(6usize);
    let x_tick_labels = tick_labels(&x_ticks);
    let y_tick_labels = tick_labels(&y_ticks);

    let text_height = GLYPH_HEIGHT * PLOT_TEXT_SCALE;
    let y_tick_label_width = widest_text(y_tick_labels.iter().map(String::as_str));
    let legend_width = LEGEND_SWATCH + 8 + widest_text(series.iter().map(|(name, _)| *name));
    let margins = PlotMargins {
        top: 12 + text_height + 14,
        bottom: TICK_LENGTH + 6 + text_height + 12 + text_height + 10,
        left: 10 + text_height + 12 + y_tick_label_width + 6 + TICK_LENGTH,
        right: 16 + legend_width + 10,
    };

    let mut pixels = vec![255u8; PLOT_WIDTH * PLOT_HEIGHT * 3];
    let frame = {
        let size = (PLOT_WIDTH as u32, PLOT_HEIGHT as u32);
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        let geometry = PlotGeometry {
            margins: &margins,
            x_range,
            y_range,
            x_ticks: &x_ticks,
            y_ticks: &y_ticks,
            series: &finite,
        };
        draw_plot_geometry(&root, &geometry)
            .and_then(|frame| root.present().map(|()| frame))
            .map_err(|e| HostError::invalid(path, format!("drawing the plot failed: {e}")))?
    };

    let mut canvas = Canvas {
        pixels: &mut pixels,
        width: PLOT_WIDTH,
        height: PLOT_HEIGHT,
    };
    let centred_at =
        |text: &str, centre: usize| centre.saturating_sub(text_width(text, PLOT_TEXT_SCALE) / 2);
    let plot_centre = (frame.left + frame.right) / 2;
    canvas.text(
        centred_at(title, plot_centre),
        12,
        title,
        PLOT_TEXT_SCALE,
        INK,
    );
    let x_tick_label_top = frame.bottom + TICK_LENGTH + 6;
    for (label, &x) in x_tick_labels.iter().zip(&frame.x_ticks) {
        let left = centred_at(label, x);
        canvas.text(left, x_tick_label_top, label, PLOT_TEXT_SCALE, INK);
    }
    for (label, &y) in y_tick_labels.iter().zip(&frame.y_ticks) {
        let left = frame.left - TICK_LENGTH - 6 - text_width(label, PLOT_TEXT_SCALE);
        let top = y.saturating_sub(text_height / 2);
        canvas.text(left, top, label, PLOT_TEXT_SCALE, INK);
    }
    canvas.text(
        centred_at(x_label, plot_centre),
        x_tick_label_top + text_height + 12,
        x_label,
        PLOT_TEXT_SCALE,
        INK,
    );
    let y_label_bottom = (frame.top + frame.bottom + text_width(y_label, PLOT_TEXT_SCALE)) / 2;
    canvas.text_up(10, y_label_bottom, y_label, PLOT_TEXT_SCALE, INK);
    let swatch_left = frame.right + 16;
    for (index, (name, _)) in series.iter().enumerate() {
        let RGBColor(r, g, b) = PALETTE[index % PALETTE.len()];
        let top = frame.top + 4 + index * LEGEND_ROW;
        let swatch_top = top + text_height / 2 - 2;
        canvas.fill_rect(swatch_left, swatch_top, LEGEND_SWATCH, 4, [r, g, b]);
        let label_left = swatch_left + LEGEND_SWATCH + 8;
        canvas.text(label_left, top, name, PLOT_TEXT_SCALE, INK);
    }
    io::write_png(path, PLOT_WIDTH as u32, PLOT_HEIGHT as u32, 3, &pixels)
}

fn widest_text<'a>(texts: impl Iterator<Item = &'a str>) -> usize {
    texts
        .map(|text| text_width(text, PLOT_TEXT_SCALE))
        .max()
        .unwrap_or(0)
}

/// Space around the plot area, in pixels, for text and the legend.
struct PlotMargins {
    top: usize,
    bottom: usize,
    left: usize,
    right: usize,
}

/// What [`draw_plot_geometry`] draws: everything but text.
struct PlotGeometry<'a> {
    margins: &'a PlotMargins,
    x_range: Range<f64>,
    y_range: Range<f64>,
    x_ticks: &'a [f64],
    y_ticks: &'a [f64],
    series: &'a [Vec<(f64, f64)>],
}

/// Where the plot frame and the ticks landed, in pixels, for placing text around them.
struct PlotFrame {
    left: usize,
    top: usize,
    right: usize,
    bottom: usize,
    /// Column of each x tick.
    x_ticks: Vec<usize>,
    /// Row of each y tick.
    y_ticks: Vec<usize>,
}

/// Grid, series, plot frame and tick marks, drawn with plotters. Plotters draws no text here:
/// this build has no font backend for it.
fn draw_plot_geometry<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    geometry: &PlotGeometry,
) -> std::result::Result<PlotFrame, DrawingAreaErrorKind<DB::ErrorType>> {
    let margins = geometry.margins;
    root.fill(&WHITE)?;
    let area = root.margin(
        margins.top as i32,
        margins.bottom as i32,
        margins.left as i32,
        margins.right as i32,
    );
    let mut chart = ChartBuilder::on(&area)
        .build_cartesian_2d(geometry.x_range.clone(), geometry.y_range.clone())?;
    let (x0, x1) = (geometry.x_range.start, geometry.x_range.end);
    let (y0, y1) = (geometry.y_range.start, geometry.y_range.end);
    let vertical_grid = geometry
        .x_ticks
        .iter()
        .map(|&x| PathElement::new(vec![(x, y0), (x, y1)], GRID));
    let horizontal_grid = geometry
        .y_ticks
        .iter()
        .map(|&y| PathElement::new(vec![(x0, y), (x1, y)], GRID));
    chart.draw_series(vertical_grid.chain(horizontal_grid))?;
    for (index, points) in geometry.series.iter().enumerate() {
        let colour = PALETTE[index % PALETTE.len()];
        chart.draw_series(LineSeries::new(
            points.iter().copied(),
            colour.stroke_width(2),
        ))?;
        if points.len() <= MARKER_LIMIT {
            let markers = points
                .iter()
                .map(|&point| Circle::new(point, 3, colour.filled()));
            chart.draw_series(markers)?;
        }
    }

    // The frame goes exactly through the data range's corners, so the ticks sit on it.
    let (left, top) = chart.backend_coord(&(x0, y1));
    let (right, bottom) = chart.backend_coord(&(x1, y0));
    root.draw(&Rectangle::new([(left, top), (right, bottom)], BLACK))?;
    let tick = TICK_LENGTH as i32;
    let mut x_ticks = Vec::with_capacity(geometry.x_ticks.len());
    for &x in geometry.x_ticks {
        let (column, _) = chart.backend_coord(&(x, y0));
        root.draw(&PathElement::new(
            vec![(column, bottom), (column, bottom + tick)],
            BLACK,
        ))?;
        x_ticks.push(column.max(0) as usize);
    }
    let mut y_ticks = Vec::with_capacity(geometry.y_ticks.len());
    for &y in geometry.y_ticks {
        let (_, row) = chart.backend_coord(&(x0, y));
        root.draw(&PathElement::new(
            vec![(left - tick, row), (left, row)],
            BLACK,
        ))?;
        y_ticks.push(row.max(0) as usize);
    }
    let pixel = |v: i32| v.max(0) as usize;
    Ok(PlotFrame {
        left: pixel(left),
        top: pixel(top),
        right: pixel(right),
        bottom: pixel(bottom),
        x_ticks,
        y_ticks,
    })
}

/// `min..max` of the values widened by `padding` of the span on each side; a single value is
/// widened to a span of 1 (or 10 % of its size), and no values give `0..1`.
fn data_range(values: impl Iterator<Item = f64>, padding: f64) -> Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if lo > hi {
        return 0.0..1.0;
    }
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(lo.abs()) {
        let half = (0.05 * lo.abs()).max(0.5);
        return lo - half..hi + half;
    }
    lo - padding * span..hi + padding * span
}

/// Tick values printed with the fewest decimals (up to 6) that keep them distinct and exact to
/// a millionth of the tick spacing; scientific notation for very large or very small values.
fn tick_labels(ticks: &[f64]) -> Vec<String> {
    let spacing = ticks
        .windows(2)
        .map(|pair| (pair[1] - pair[0]).abs())
        .fold(f64::INFINITY, f64::min);
    let magnitude = ticks.iter().fold(0.0f64, |m, t| m.max(t.abs()));
    let scientific = magnitude >= 1e6 || (magnitude > 0.0 && magnitude < 1e-3);
    let unit = if spacing.is_finite() && spacing > 0.0 {
        spacing
    } else {
        magnitude.max(1.0)
    };
    let exact = |decimals: usize| {
        ticks.iter().all(|&t| {
            let shown: f64 = format!("{t:.decimals$}").parse().unwrap_or(f64::NAN);
            (shown - t).abs() <= 1e-6 * unit
        })
    };
    let decimals = (0..=6).find(|&d| exact(d));
    ticks
        .iter()
        // Adding 0.0 turns -0.0 into 0.0, so no tick reads "-0".
        .map(|&t| match decimals {
            Some(d) if !scientific => format!("{:.d$}", t + 0.0),
            _ => format!("{:.2e}", t + 0.0),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat3, Vec3};
    use std::path::PathBuf;

    /// An RGB8 test scene with a disc, concentric rings and stripes (hard edges for JNB) on a
    /// dark field.
    fn scene(width: usize, height: usize) -> Vec<u8> {
        let (w, h) = (width as f64, height as f64);
        let mut pixels = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                let (fx, fy) = (x as f64, y as f64);
                let disc = (fx - 0.3 * w).hypot(fy - 0.5 * h) < 0.2 * h;
                let ring_index = ((fx - 0.75 * w).hypot(fy - 0.4 * h) / 9.0) as usize;
                let ring = ring_index.is_multiple_of(2);
                let stripes = (x / 6 + y / 10).is_multiple_of(2);
                for c in 0..3 {
                    let v = 20
                        + 140 * disc as usize
                        + 50 * ring as usize
                        + 30 * stripes as usize
                        + 7 * c;
                    pixels.push(v.min(255) as u8);
                }
            }
        }
        pixels
    }

    fn to_unit(pixels: &[u8]) -> Vec<f32> {
        pixels.iter().map(|&v| v as f32 / 255.0).collect()
    }

    #[test]
    fn identical_images_score_perfectly() {
        let (w, h) = (256, 128);
        let truth = scene(w, h);
        let m = score_view(&to_unit(&truth), &truth, w, h).unwrap();
        assert_eq!(m.psnr_right, f64::INFINITY);
        assert_eq!(m.psnr_full, f64::INFINITY);
        assert!((m.ssim_right - 1.0).abs() < 1e-12, "{m:?}");
        assert!((m.ssim_full - 1.0).abs() < 1e-12, "{m:?}");
        assert!(m.jnb_right.is_finite() && m.jnb_right > 0.0, "{m:?}");
        assert!(m.jnb_full.is_finite() && m.jnb_full > 0.0, "{m:?}");
    }

    #[test]
    fn quantisation_rounds_half_up_and_clamps() {
        let values = [
            0.0,
            0.5 / 255.0 + 1e-6,
            0.49 / 255.0,
            1.0,
            1.7,
            -0.2,
            f32::NAN,
        ];
        assert_eq!(quantize(&values), vec![0, 1, 0, 255, 255, 0, 0]);
        assert_eq!(
            rec601_luma(&[255, 255, 255, 10, 10, 10, 255, 0, 0]),
            vec![255, 10, 76]
        );
    }

    #[test]
    fn blurred_render_scores_lower_ssim_and_higher_jnb() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/metric_fixtures");
        let Ok(entries) = std::fs::read_dir(&dir) else {
            eprintln!("skipping: metric fixtures not found at {}", dir.display());
            return;
        };
        let mut sharp_paths: Vec<PathBuf> = entries
            .map(|e| e.unwrap().path())
            .filter(|p| p.to_string_lossy().ends_with("_gray.pgm"))
            .collect();
        sharp_paths.sort();
        assert!(!sharp_paths.is_empty());
        let gray_to_rgb = |gray: &[u8]| gray.iter().flat_map(|&g| [g, g, g]).collect::<Vec<u8>>();
        for sharp_path in sharp_paths {
            let blurred_path = PathBuf::from(
                sharp_path
                    .to_string_lossy()
                    .replace("_gray.pgm", "_blur1.pgm"),
            );
            let (w, h, sharp) = crate::metrics::tests::read_pgm(&sharp_path);
            let (bw, bh, blurred) = crate::metrics::tests::read_pgm(&blurred_path);
            assert_eq!((bw, bh), (w, h));
            let truth = gray_to_rgb(&sharp);
            let sharp_scores = score_view(&to_unit(&truth), &truth, w, h).unwrap();
            let blurred_scores =
                score_view(&to_unit(&gray_to_rgb(&blurred)), &truth, w, h).unwrap();
            let name = sharp_path.display();
            assert!(blurred_scores.ssim_full < sharp_scores.ssim_full, "{name}");
            assert!(
                blurred_scores.ssim_right < sharp_scores.ssim_right,
                "{name}"
            );
            assert!(blurred_scores.psnr_full < sharp_scores.psnr_full, "{name}");
            assert!(blurred_scores.jnb_full > sharp_scores.jnb_full, "{name}");
            // Gray pixels have luma equal to themselves, so the full-image JNB is exactly the
            // metric on the fixture (the fixtures' expected value is sharpness = 1 / blur).
            let direct = metrics::jnb(
                &ImageRef::new(&blurred, w, h, 1).unwrap(),
                JnbVariant::Paper,
            );
            assert_eq!(blurred_scores.jnb_full, direct.unwrap().blur, "{name}");
            if w / 2 >= 64 {
                assert!(blurred_scores.jnb_right > sharp_scores.jnb_right, "{name}");
            } else {
                // A right half narrower than one 64-px JNB block has nothing to measure.
                assert!(blurred_scores.jnb_right.is_nan(), "{name}");
            }
        }
    }

    #[test]
    fn right_half_metrics_see_only_the_right_half() {
        let (w, h) = (256, 128);
        let truth = scene(w, h);
        let mut render = to_unit(&scene(w, h));
        // Perturb the right half a little, so its scores are finite and comparable.
        for (i, v) in render.iter_mut().enumerate() {
            if (i / 3) % w >= w / 2 && i % 7 == 0 {
                *v = (*v + 0.03).min(1.0);
            }
        }
        let before = score_view(&render, &truth, w, h).unwrap();
        for (i, v) in render.iter_mut().enumerate() {
            if (i / 3) % w < w / 2 {
                *v = 1.0 - *v;
            }
        }
        let after = score_view(&render, &truth, w, h).unwrap();
        assert_eq!(before.psnr_right, after.psnr_right);
        assert_eq!(before.ssim_right, after.ssim_right);
        assert_eq!(before.jnb_right, after.jnb_right);
        assert!(after.psnr_full < before.psnr_full);
        assert!(after.ssim_full < before.ssim_full);
    }

    #[test]
    fn blank_render_has_nan_jnb_and_means_skip_it() {
        let (w, h) = (128, 128);
        let truth = scene(w, h);
        let blank = score_view(&vec![0.0; w * h * 3], &truth, w, h).unwrap();
        assert!(blank.jnb_right.is_nan() && blank.jnb_full.is_nan());
        assert!(blank.psnr_full.is_finite() && blank.ssim_full < 1.0);

        let textured = score_view(&to_unit(&truth), &truth, w, h).unwrap();
        let mean = mean_metrics(&[blank, textured]);
        assert_eq!(mean.jnb_full, textured.jnb_full);
        assert_eq!(mean.jnb_right, textured.jnb_right);
        assert_eq!(mean.psnr_full, f64::INFINITY);
        assert_eq!(mean.ssim_full, (blank.ssim_full + textured.ssim_full) / 2.0);
        assert!(mean_metrics(&[blank, blank]).jnb_full.is_nan());
        assert!(mean_metrics(&[]).ssim_full.is_nan());
    }

    #[test]
    fn mismatched_buffers_are_errors() {
        let truth = scene(32, 32);
        assert!(matches!(
            score_view(&to_unit(&truth), &truth, 32, 31),
            Err(MetricError::BufferSize { .. })
        ));
        assert!(matches!(
            score_view(&to_unit(&truth), &truth[..30], 32, 32),
            Err(MetricError::BufferSize { .. })
        ));
    }

    fn pose(rotation: Mat3, center: Vec3) -> Pose {
        Pose { rotation, center }
    }

    #[test]
    fn rotation_error_splits_about_and_across_the_view_axis() {
        let base = Mat3::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0);
        let a = pose(base, Vec3::ZERO);
        let deg = |d: f32| d.to_radians();
        // Turning camera a about its own optical axis (+z) is all "about"; about x, all "across".
        let (about, across) = rotation_error_split_deg(
            &a,
            &pose(base * Mat3::from_rotation_z(deg(2.0)), Vec3::ZERO),
        );
        assert!(
            (about - 2.0).abs() < 1e-4 && across.abs() < 1e-4,
            "{about} {across}"
        );
        let (about, across) = rotation_error_split_deg(
            &a,
            &pose(base * Mat3::from_rotation_x(deg(3.0)), Vec3::ZERO),
        );
        assert!(
            about.abs() < 1e-4 && (across - 3.0).abs() < 1e-4,
            "{about} {across}"
        );
        // A mixed axis splits by its components; the parts add up in quadrature to the angle.
        let axis = Vec3::new(3.0, 0.0, 4.0).normalize();
        let mixed = pose(base * Mat3::from_axis_angle(axis, deg(5.0)), Vec3::ZERO);
        let (about, across) = rotation_error_split_deg(&a, &mixed);
        assert!(
            (about - 4.0).abs() < 1e-4 && (across - 3.0).abs() < 1e-4,
            "{about} {across}"
        );
        let whole = rotation_error_deg(&a, &mixed);
        assert!((about.hypot(across) - whole).abs() < 1e-6);
        assert_eq!(rotation_error_split_deg(&a, &a), (0.0, 0.0));
    }

    #[test]
    fn rotation_error_of_known_rotations() {
        let base = Mat3::from_rotation_z(0.7) * Mat3::from_rotation_x(-1.2);
        let a = pose(base, Vec3::ZERO);
        let ten = pose(
            base * Mat3::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 10f32.to_radians()),
            Vec3::ZERO,
        );
        assert!((rotation_error_deg(&a, &ten) - 10.0).abs() < 1e-4);
        assert!((rotation_error_deg(&ten, &a) - 10.0).abs() < 1e-4);

        let identical = rotation_error_deg(&a, &a);
        assert_eq!(identical, 0.0);

        let half_turn = pose(
            base * Mat3::from_rotation_y(std::f32::consts::PI),
            Vec3::ZERO,
        );
        let error = rotation_error_deg(&a, &half_turn);
        assert!(error.is_finite() && (error - 180.0).abs() < 1e-3, "{error}");
        let tiny = pose(
            base * Mat3::from_rotation_x(1e-3f32.to_radians()),
            Vec3::ZERO,
        );
        assert!((rotation_error_deg(&a, &tiny) - 1e-3).abs() < 1e-4);
    }

    #[test]
    fn translation_error_is_the_centre_distance() {
        let a = pose(Mat3::IDENTITY, Vec3::new(1.0, 2.0, 3.0));
        let b = pose(Mat3::from_rotation_z(1.0), Vec3::new(4.0, 6.0, 3.0));
        assert_eq!(translation_error(&a, &b), 5.0);
    }

    #[test]
    fn pose_errors_summarise_frames() {
        let truth: Vec<Pose> = (0..4)
            .map(|i| {
                pose(
                    Mat3::from_rotation_y(i as f32),
                    Vec3::new(i as f32, 0.0, 0.0),
                )
            })
            .collect();
        let offsets_deg = [1.0f32, 2.0, 3.0, 10.0];
        let offsets_m = [0.5f32, 0.25, 1.0, 2.0];
        let estimated: Vec<Pose> = truth
            .iter()
            .zip(offsets_deg.iter().zip(&offsets_m))
            .map(|(t, (&deg, &m))| {
                pose(
                    t.rotation * Mat3::from_rotation_x(deg.to_radians()),
                    t.center + Vec3::new(0.0, 0.0, m),
                )
            })
            .collect();
        let errors = pose_errors(&estimated, &truth);
        assert_eq!(errors.frames, 4);
        assert!((errors.rotation_deg_mean - 4.0).abs() < 1e-4, "{errors:?}");
        // The offsets turn the cameras about their x axes: all across the view axis.
        assert!(errors.about_view_axis_deg_mean.abs() < 1e-4, "{errors:?}");
        assert!(
            (errors.across_view_axis_deg_mean - 4.0).abs() < 1e-4,
            "{errors:?}"
        );
        assert!(
            (errors.rotation_deg_median - 2.5).abs() < 1e-4,
            "{errors:?}"
        );
        assert!(
            (errors.translation_mean - 0.9375).abs() < 1e-6,
            "{errors:?}"
        );
        assert!(
            (errors.translation_median - 0.75).abs() < 1e-6,
            "{errors:?}"
        );

        let prefix = pose_errors(&estimated[..3], &truth);
        assert_eq!(prefix.frames, 3);
        assert!(
            (prefix.rotation_deg_median - 2.0).abs() < 1e-4,
            "{prefix:?}"
        );
        assert!((prefix.translation_median - 0.5).abs() < 1e-6, "{prefix:?}");
        assert_eq!(pose_errors(&[], &truth), PoseErrors::default());
    }

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
            "train s",
        ] {
            assert!(lines[0].contains(column), "{table}");
        }
        let cells: Vec<&str> = lines[2].split('|').map(str::trim).collect();
        assert_eq!(
            cells[1..9],
            [
                "ours + pose",
                "30.54",
                "0.9500",
                "0.0333",
                "31.00",
                "0.9600",
                "n/a",
                "1800.0"
            ]
        );
        assert!(table.contains("paper variant"), "{table}");
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
    fn font_covers_the_caption_characters() {
        let fallback = glyph('?');
        for c in "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+-.:/%()_".chars() {
            assert_ne!(glyph(c), fallback, "{c:?} falls back to '?'");
        }
        assert_eq!(glyph(' '), &[0; 7]);
        assert_eq!(FONT[FONT.len() - 1].0, '?');
        assert_eq!(glyph('~'), fallback);
        let mut rows: Vec<&[u8; 7]> = FONT.iter().map(|(_, rows)| rows).collect();
        rows.sort();
        rows.dedup();
        assert_eq!(rows.len(), FONT.len(), "two characters share a glyph");
    }

    #[test]
    fn side_by_side_lays_out_captioned_tiles() {
        let (w, h) = (128usize, 96usize);
        let red = [200u8, 0, 0].repeat(w * h);
        let green = [0u8, 200, 0].repeat(w * h);
        let blue = [0u8, 0, 200].repeat(w * h);
        let (sw, sh, pixels) = side_by_side(
            &[
                ("reference", red.as_slice()),
                ("baseline", green.as_slice()),
                ("ours + pose", blue.as_slice()),
            ],
            w as u32,
            h as u32,
        );
        let band = sh as usize - h;
        assert_eq!(sw as usize, 3 * w + 2 * TILE_GAP);
        assert_eq!(pixels.len(), (sw * sh * 3) as usize);
        // 2x captions on 128-px tiles, "ours + pose" on two lines: 2 x 14-px glyphs, 4 px
        // between the lines, 4 px of padding above and below.
        assert_eq!(band, 2 * 14 + 4 + 8);
        let at = |x: usize, y: usize| {
            let i = (y * sw as usize + x) * 3;
            [pixels[i], pixels[i + 1], pixels[i + 2]]
        };
        for (tile, colour) in [[200, 0, 0], [0, 200, 0], [0, 0, 200]].iter().enumerate() {
            let left = tile * (w + TILE_GAP);
            assert_eq!(at(left, band), *colour);
            assert_eq!(at(left + w - 1, sh as usize - 1), *colour);
            let inked = (0..band)
                .flat_map(|y| (left..left + w).map(move |x| (x, y)))
                .filter(|&(x, y)| at(x, y) != STRIP_BACKGROUND)
                .count();
            assert!(inked > 50, "tile {tile}: {inked} caption pixels");
        }
        assert_eq!(at(w, band + 10), STRIP_BACKGROUND, "gap between tiles");
        assert_eq!(side_by_side(&[], 8, 8), (0, 0, Vec::new()));
    }

    #[test]
    fn long_captions_wrap_then_shrink_then_cut() {
        assert_eq!(
            wrap_caption("a caption far too long for the tile", 10),
            ["a caption", "far too", "long for", "the tile"]
        );
        assert_eq!(wrap_caption("supercalifragilistic", 5), ["super"]);
        assert!(wrap_caption("x", 0).is_empty());
        let labels = ["reference", "ours + pose"];
        assert_eq!(
            layout_captions(labels.into_iter(), 128),
            (
                2,
                vec![
                    vec!["reference".to_string()],
                    vec!["ours +".into(), "pose".into()]
                ]
            )
        );
        // Three lines at 2x on a 128-px tile: drop to 1x, where two do.
        let (scale, captions) = layout_captions(["one two three four five six"].into_iter(), 128);
        assert_eq!(scale, 1);
        assert_eq!(captions, [["one two three four", "five six"]]);

        let tile = vec![0u8; 64 * 16 * 3];
        let label = "a caption far too long for the tile";
        let (sw, sh, _) = side_by_side(&[(label, tile.as_slice())], 64, 16);
        // 1x on a 64-px tile, cut to two lines: 2 x 7-px glyphs, 2 px between, 2 + 2 padding.
        assert_eq!((sw, sh), (64, 16 + 2 * 7 + 2 + 4));
    }

    #[test]
    fn line_plot_writes_a_readable_png() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plots/psnr.png");
        let steps = |f: fn(f64) -> f64| -> Vec<(f64, f64)> {
            (0..=40).map(|i| (i as f64 * 250.0, f(i as f64))).collect()
        };
        let series = [
            (
                "baseline",
                steps(|i| 14.0 + 8.0 * (1.0 - (-i / 10.0).exp())),
            ),
            ("ours", steps(|i| 15.0 + 15.0 * (1.0 - (-i / 8.0).exp()))),
            (
                "ours + pose",
                vec![(0.0, 16.0), (5000.0, 29.0), (10000.0, f64::NAN)],
            ),
        ];
        line_plot(&path, "PSNR while training", "step", "PSNR (dB)", &series).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (PLOT_WIDTH as u32, PLOT_HEIGHT as u32));
        for RGBColor(r, g, b) in &PALETTE[..3] {
            let count = image.pixels().filter(|p| p.0 == [*r, *g, *b]).count();
            assert!(count > 40, "series colour {:?}: {count} pixels", (r, g, b));
        }
        let ink = image.pixels().filter(|p| p.0 == INK).count();
        assert!(ink > 2000, "text and axes: {ink} black pixels");

        // Degenerate input still gives a plot rather than an error.
        let flat = dir.path().join("flat.png");
        line_plot(
            &flat,
            "empty",
            "x",
            "y",
            &[("none", vec![]), ("one", vec![(1.0, 2.0)])],
        )
        .unwrap();
        assert!(image::open(&flat).is_ok());
    }

    #[test]
    fn tick_labels_use_just_enough_decimals() {
        assert_eq!(tick_labels(&[0.0, 0.25, 0.5]), ["0.00", "0.25", "0.50"]);
        assert_eq!(tick_labels(&[-5000.0, 0.0, 5000.0]), ["-5000", "0", "5000"]);
        assert_eq!(tick_labels(&[-0.0, 1.0]), ["0", "1"]);
        assert_eq!(tick_labels(&[0.0, 2e6]), ["0.00e0", "2.00e6"]);
        assert_eq!(data_range([3.0].into_iter(), 0.05), 2.5..3.5);
        assert_eq!(data_range(std::iter::empty(), 0.05), 0.0..1.0);
    }
}
