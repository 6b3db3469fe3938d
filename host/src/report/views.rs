//! Image metrics of one view: PSNR, SSIM and JNB on the right half and on the whole image,
//! CPBD on the whole image.

use super::mean;
use crate::error::Result;
use crate::metrics::{self, ImageRef, JnbVariant, MetricError};

/// Image quality of one rendered view against its reference, on the right half
/// (`x >= width / 2`, the pixels the appearance embedding was not fitted on) and on the whole
/// image.
///
/// - PSNR in dB on 8-bit values; `f64::INFINITY` when the quantised render equals the reference
///   (as scikit-image reports it; nothing is capped).
/// - SSIM as [`metrics::ssim`] (mean over the three channels). `f64::NAN` when the region is
///   smaller than SSIM's 11x11 window (a tiny training size still gets its PSNR).
/// - Foreground PSNR: the same PSNR over the pixels the view's mask marks as target (all three
///   channels), whole image and right half, since whole-image PSNR of a spacecraft view is mostly
///   black sky. `f64::NAN` when the view has no mask or the region holds no target pixel.
/// - JNB is [`metrics::JnbScore::blur_per_edge`] with [`JnbVariant::Paper`]'s just-noticeable
///   widths: the blur of the edges, lower is sharper, measured on the render alone (it is a
///   no-reference metric). Not Ferzli & Karam's `D / L`, which grows with the image's edge count
///   and falls with its block count (6.2 on a 100 px lego view, 1.4 on the same view at 200 px;
///   the paper's 0.03 to 0.05 are that ratio on 540 blocks of 1920 x 1200 images), so figures of
///   two image sizes compare. `f64::NAN` when the region has no edge block to measure: a blank
///   render, or a region narrower or shorter than one 64x64 block.
/// - CPBD ([`metrics::cpbd`], Narvekar & Karam's probability of blur detection) of the whole
///   image, higher is sharper; `f64::NAN` in figures written before it was reported.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewMetrics {
    /// PSNR of the right half, dB.
    pub psnr_right: f64,
    /// SSIM of the right half, at most 1.
    pub ssim_right: f64,
    /// JNB blur per edge of the right half (lower is sharper).
    pub jnb_right: f64,
    /// PSNR of the whole image, dB.
    pub psnr_full: f64,
    /// SSIM of the whole image, at most 1.
    pub ssim_full: f64,
    /// JNB blur per edge of the whole image (lower is sharper).
    pub jnb_full: f64,
    /// PSNR over the target pixels of the whole image, dB.
    pub psnr_foreground: f64,
    /// PSNR over the target pixels of the right half, dB.
    pub psnr_foreground_right: f64,
    /// CPBD of the whole image, from 0 to 1 (higher is sharper).
    #[serde(default = "not_measured")]
    pub cpbd_full: f64,
}

/// A figure an older record does not hold.
fn not_measured() -> f64 {
    f64::NAN
}

/// Score a render (RGB `f32` in [0, 1], row-major, `width * height * 3` values) against the
/// reference image (RGB8, same layout), with the view's foreground mask (one byte per pixel,
/// 0 = background) when it has one. The reference is scored as given: with masks applied
/// (`Dataset::apply_masks`) its sky is the background colour, so SSIM measures the target.
///
/// The render is quantised to 8 bits first (round half up, values outside [0, 1] clamped): the reference is 8-bit, and NeRF evaluations score renders as saved 8-bit
/// images. JNB reads the Rec.601 luma (`0.299 R + 0.587 G + 0.114 B`) of the quantised render,
/// itself rounded to 8 bits, as an image library's 8-bit gray conversion gives it to the
/// reference JNB code.
///
/// Errors when the render holds a non-finite value (a model gone to NaN is never a score) or
/// when a buffer does not match `width x height x 3`.
pub fn score_view(
    render: &[f32],
    truth: &[u8],
    mask: Option<&[u8]>,
    width: usize,
    height: usize,
) -> Result<ViewMetrics, MetricError> {
    let non_finite = render.iter().filter(|v| !v.is_finite()).count();
    if non_finite > 0 {
        return Err(MetricError::NonFinite { count: non_finite });
    }
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
        ssim_right: ssim_or_nan(&rendered_right, &truth_right)?,
        jnb_right: jnb_blur(&luma_right)?,
        psnr_full: metrics::psnr(&rendered_image, &truth_image)?,
        ssim_full: ssim_or_nan(&rendered_image, &truth_image)?,
        jnb_full: jnb_blur(&luma_image)?,
        psnr_foreground: foreground_psnr(&rendered, truth, mask, (width, height), 0)?,
        psnr_foreground_right: foreground_psnr(&rendered, truth, mask, (width, height), left)?,
        cpbd_full: metrics::cpbd(&luma_image)?,
    })
}

/// PSNR (8-bit) over the pixels of columns `x >= first_column` whose mask is not 0; NaN
/// without a mask or without such a pixel, infinite when they all match.
fn foreground_psnr(
    rendered: &[u8],
    truth: &[u8],
    mask: Option<&[u8]>,
    (width, height): (usize, usize),
    first_column: usize,
) -> Result<f64, MetricError> {
    let Some(mask) = mask else {
        return Ok(f64::NAN);
    };
    // Checks the mask's size (the images were checked by the caller).
    ImageRef::new(mask, width, height, 1)?;
    let (mut squared, mut samples) = (0.0f64, 0usize);
    for (pixel, &m) in mask.iter().enumerate() {
        if m == 0 || pixel % width.max(1) < first_column {
            continue;
        }
        for c in 0..3 {
            let e = rendered[pixel * 3 + c] as f64 - truth[pixel * 3 + c] as f64;
            squared += e * e;
        }
        samples += 3;
    }
    if samples == 0 {
        return Ok(f64::NAN);
    }
    let mse = squared / samples as f64;
    Ok(10.0 * (255.0f64 * 255.0 / mse).log10())
}

/// Mean over views. PSNR is a plain mean (an infinite PSNR makes the mean infinite, which is the
/// honest summary of a perfect view). SSIM, JNB and foreground PSNR ignore NaN entries (views
/// too small for SSIM, with no edge block, no mask or no target pixel) and are NaN only when
/// every view is. No views gives NaN everywhere.
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
        ssim_right: field_mean_ignoring_nan(|v| v.ssim_right),
        jnb_right: field_mean_ignoring_nan(|v| v.jnb_right),
        psnr_full: field_mean(|v| v.psnr_full),
        ssim_full: field_mean_ignoring_nan(|v| v.ssim_full),
        jnb_full: field_mean_ignoring_nan(|v| v.jnb_full),
        psnr_foreground: field_mean_ignoring_nan(|v| v.psnr_foreground),
        psnr_foreground_right: field_mean_ignoring_nan(|v| v.psnr_foreground_right),
        cpbd_full: field_mean_ignoring_nan(|v| v.cpbd_full),
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

/// SSIM of two RGB8 images, NaN when they are smaller than its window.
fn ssim_or_nan(rendered: &ImageRef<u8>, truth: &ImageRef<u8>) -> Result<f64, MetricError> {
    match metrics::ssim(rendered, truth) {
        Err(MetricError::TooSmall { .. }) => Ok(f64::NAN),
        other => other,
    }
}

/// JNB blur per edge of a gray image, NaN when there is no edge to measure.
fn jnb_blur(gray: &ImageRef<u8>) -> Result<f64, MetricError> {
    let score = metrics::jnb(gray, JnbVariant::Paper)?;
    Ok(if score.edges == 0 {
        f64::NAN
    } else {
        score.blur_per_edge
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::{Path, PathBuf};

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
        let m = score_view(&to_unit(&truth), &truth, None, w, h).unwrap();
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
            let sharp_scores = score_view(&to_unit(&truth), &truth, None, w, h).unwrap();
            let blurred_scores =
                score_view(&to_unit(&gray_to_rgb(&blurred)), &truth, None, w, h).unwrap();
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
            assert_eq!(
                blurred_scores.jnb_full,
                direct.unwrap().blur_per_edge,
                "{name}"
            );
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
        let before = score_view(&render, &truth, None, w, h).unwrap();
        for (i, v) in render.iter_mut().enumerate() {
            if (i / 3) % w < w / 2 {
                *v = 1.0 - *v;
            }
        }
        let after = score_view(&render, &truth, None, w, h).unwrap();
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
        let blank = score_view(&vec![0.0; w * h * 3], &truth, None, w, h).unwrap();
        assert!(blank.jnb_right.is_nan() && blank.jnb_full.is_nan());
        assert!(blank.psnr_full.is_finite() && blank.ssim_full < 1.0);

        let textured = score_view(&to_unit(&truth), &truth, None, w, h).unwrap();
        let mean = mean_metrics(&[blank, textured]);
        assert_eq!(mean.jnb_full, textured.jnb_full);
        assert_eq!(mean.jnb_right, textured.jnb_right);
        assert_eq!(mean.psnr_full, f64::INFINITY);
        assert_eq!(mean.ssim_full, (blank.ssim_full + textured.ssim_full) / 2.0);
        assert!(mean_metrics(&[blank, blank]).jnb_full.is_nan());
        assert!(mean_metrics(&[]).ssim_full.is_nan());
    }

    #[test]
    fn views_smaller_than_the_ssim_window_score_psnr_and_no_ssim() {
        // 16x16: the whole image has a window, the 8-pixel right half does not.
        let (w, h) = (16, 16);
        let truth = scene(w, h);
        let mut render = to_unit(&truth);
        render[(w - 1) * 3] = 1.0 - render[(w - 1) * 3];
        let small = score_view(&render, &truth, None, w, h).unwrap();
        assert!(small.psnr_right.is_finite() && small.psnr_full.is_finite());
        assert!(small.ssim_right.is_nan(), "{small:?}");
        assert!(small.ssim_full.is_finite() && small.ssim_full < 1.0);

        let large = score_view(&to_unit(&scene(64, 64)), &scene(64, 64), None, 64, 64).unwrap();
        let mean = mean_metrics(&[small, large]);
        assert_eq!(mean.ssim_right, large.ssim_right);
        assert!(mean_metrics(&[small, small]).ssim_right.is_nan());
    }

    #[test]
    fn foreground_psnr_reads_only_the_masked_pixels() {
        let (w, h) = (64, 32);
        let truth = scene(w, h);
        // Target: a square straddling the two halves. The render is exact on it and wrong
        // everywhere else.
        let mask: Vec<u8> = (0..w * h)
            .map(|p| {
                if (20..44).contains(&(p % w)) && (8..24).contains(&(p / w)) {
                    255
                } else {
                    0
                }
            })
            .collect();
        let mut render = to_unit(&truth);
        for (p, &m) in mask.iter().enumerate() {
            if m == 0 {
                render[p * 3] = 1.0 - render[p * 3];
            }
        }
        let m = score_view(&render, &truth, Some(&mask), w, h).unwrap();
        assert_eq!(m.psnr_foreground, f64::INFINITY);
        assert_eq!(m.psnr_foreground_right, f64::INFINITY);
        assert!(m.psnr_full < 20.0, "{m:?}");
        // One wrong channel value (by 51 levels) in the target's left part: the right half
        // does not see it; the whole target's MSE is 51^2 / (3 * 24 * 16).
        render[(10 * w + 25) * 3] = (truth[(10 * w + 25) * 3] as f32 + 51.0) / 255.0;
        let m = score_view(&render, &truth, Some(&mask), w, h).unwrap();
        assert_eq!(m.psnr_foreground_right, f64::INFINITY);
        let expected = 10.0 * (255.0f64 * 255.0 * 3.0 * 24.0 * 16.0 / (51.0 * 51.0)).log10();
        assert!((m.psnr_foreground - expected).abs() < 1e-9, "{m:?}");
        // No mask, or an empty one: no foreground score.
        let none = score_view(&render, &truth, None, w, h).unwrap();
        assert!(none.psnr_foreground.is_nan() && none.psnr_foreground_right.is_nan());
        let empty = score_view(&render, &truth, Some(&vec![0; w * h]), w, h).unwrap();
        assert!(empty.psnr_foreground.is_nan());
        assert_eq!(mean_metrics(&[none, m]).psnr_foreground, m.psnr_foreground);
    }

    #[test]
    fn non_finite_renders_have_no_score() {
        let truth = scene(32, 32);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut render = to_unit(&truth);
            render[5] = bad;
            render[40] = bad;
            assert_eq!(
                score_view(&render, &truth, None, 32, 32),
                Err(MetricError::NonFinite { count: 2 })
            );
        }
    }

    #[test]
    fn mismatched_buffers_are_errors() {
        let truth = scene(32, 32);
        assert!(matches!(
            score_view(&to_unit(&truth), &truth, None, 32, 31),
            Err(MetricError::BufferSize { .. })
        ));
        assert!(matches!(
            score_view(&to_unit(&truth), &truth[..30], None, 32, 32),
            Err(MetricError::BufferSize { .. })
        ));
    }
}
