//! Image resampling for the loaders. Two resamplers, because the formats need different ones:
//!
//! - `resample` (NeRF formats): pixels are turned into values first (compositing alpha on the
//!   background, say), then a box average when the size shrinks by whole factors (the
//!   convention NeRF-synthetic results are scored on), a tent filter otherwise;
//! - `Resampler` (SPEED+ / SHIRT, distorted nerfstudio frames): supersampled bilinear
//!   lookups through the lens distortion, so distorted images come out as pinhole images of
//!   any size.
//!
//! Both round to bytes with `to_byte`.

use super::transforms::{OutputSize, output_size};
use crate::error::{HostError, Result};
use image::{ImageBuffer, Luma, Rgba};
use orbit_nerf_core::Camera;
use std::path::Path;

/// A value in [0, 255] rounded to the nearest byte (out-of-range values saturate).
pub(crate) fn to_byte(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// Turn each source pixel (`IN` interleaved samples) into `OUT` values with `pixel` and
/// resample the result from `from` to `to`: a box average when both sides shrink by whole
/// factors (fused with `pixel`, so the full-size image is never stored), a tent filter
/// otherwise. Returns `OUT` interleaved `f32` per output pixel.
pub(crate) fn resample<T: Copy, const IN: usize, const OUT: usize>(
    samples: &[T],
    from: (u32, u32),
    to: (u32, u32),
    pixel: impl Fn(&[T; IN]) -> [f32; OUT],
) -> Vec<f32> {
    if from.0.is_multiple_of(to.0) && from.1.is_multiple_of(to.1) {
        return box_downsample(
            samples,
            from,
            ((from.0 / to.0) as usize, (from.1 / to.1) as usize),
            &pixel,
        );
    }
    let values: Vec<f32> = samples
        .chunks_exact(IN)
        .flat_map(|p| pixel(p.try_into().expect("IN samples")))
        .collect();
    let filter = image::imageops::FilterType::Triangle;
    match OUT {
        1 => {
            let img =
                ImageBuffer::<Luma<f32>, _>::from_raw(from.0, from.1, values).expect("buffer size");
            image::imageops::resize(&img, to.0, to.1, filter).into_raw()
        }
        4 => {
            let img =
                ImageBuffer::<Rgba<f32>, _>::from_raw(from.0, from.1, values).expect("buffer size");
            image::imageops::resize(&img, to.0, to.1, filter).into_raw()
        }
        _ => unreachable!("frames resample 1 (mask) or 4 (colour + alpha) values per pixel"),
    }
}

/// Mean of `pixel` over each `factor.0 x factor.1` block of source pixels.
fn box_downsample<T: Copy, const IN: usize, const OUT: usize>(
    samples: &[T],
    from: (u32, u32),
    factor: (usize, usize),
    pixel: &impl Fn(&[T; IN]) -> [f32; OUT],
) -> Vec<f32> {
    let (src_w, src_h) = (from.0 as usize, from.1 as usize);
    let (out_w, out_h) = (src_w / factor.0, src_h / factor.1);
    let mut out = Vec::with_capacity(out_w * out_h * OUT);
    let mut sums = vec![[0.0f32; OUT]; out_w];
    let scale = 1.0 / (factor.0 * factor.1) as f32;
    for oy in 0..out_h {
        sums.fill([0.0; OUT]);
        for sy in oy * factor.1..(oy + 1) * factor.1 {
            let row = &samples[sy * src_w * IN..(sy + 1) * src_w * IN];
            for (sum, block) in sums.iter_mut().zip(row.chunks_exact(factor.0 * IN)) {
                for p in block.chunks_exact(IN) {
                    let values = pixel(p.try_into().expect("IN samples"));
                    for (s, v) in sum.iter_mut().zip(values) {
                        *s += v;
                    }
                }
            }
        }
        out.extend(sums.iter().flat_map(|sum| sum.map(|s| s * scale)));
    }
    out
}

/// Lens distortion on normalised image coordinates, in OpenCV's two models.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Distortion {
    /// The standard model `[k1, k2, p1, p2, k3]` (radial k1, k2, k3; tangential p1, p2).
    Opencv([f32; 5]),
    /// The equidistant fisheye model of `cv::fisheye`, `[k1, k2, k3, k4]`: a ray at angle
    /// `theta` off the axis lands at radius `theta (1 + k1 theta^2 + .. + k4 theta^8)`.
    Fisheye([f32; 4]),
}

/// Below this radius the fisheye's `theta_d / r` is taken as its limit, 1 (as OpenCV does).
const FISHEYE_AXIS: f32 = 1e-8;

impl Distortion {
    /// The largest radial (`k1`, `k2`, `k3`..) coefficient accepted (absolute value): far
    /// beyond any real lens (COLMAP's and OpenCV's fits stay well under 1), so a larger one is
    /// a broken calibration.
    pub const MAX_RADIAL: f64 = 10.0;
    /// The largest tangential (`p1`, `p2`) coefficient accepted, by the same reasoning.
    pub const MAX_TANGENTIAL: f64 = 1.0;

    /// The bound of the coefficient named `name` (`k1`.., `p1`, `p2`).
    pub fn limit(name: &str) -> f64 {
        if name.starts_with('p') {
            Self::MAX_TANGENTIAL
        } else {
            Self::MAX_RADIAL
        }
    }

    /// Distort normalised image coordinates `(x, y)` (z = 1).
    pub fn apply(&self, x: f32, y: f32) -> (f32, f32) {
        match *self {
            Distortion::Opencv([k1, k2, p1, p2, k3]) => {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                (
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            Distortion::Fisheye(k) => {
                let r = (x * x + y * y).sqrt();
                if r < FISHEYE_AXIS {
                    return (x, y);
                }
                // libm, not the platform's: the same image on every target.
                let theta = libm::atanf(r);
                let scale = fisheye_radius(k, theta) / r;
                (x * scale, y * scale)
            }
        }
    }

    /// Invert [`Distortion::apply`] as OpenCV's `undistortPoints` does: fixed-point iteration
    /// (standard model), Newton's method on the angle (fisheye).
    pub fn invert(&self, xd: f32, yd: f32) -> (f32, f32) {
        match *self {
            Distortion::Opencv([k1, k2, p1, p2, k3]) => {
                let (mut x, mut y) = (xd, yd);
                for _ in 0..20 {
                    let r2 = x * x + y * y;
                    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                    let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
                    let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
                    x = (xd - dx) / radial;
                    y = (yd - dy) / radial;
                }
                (x, y)
            }
            Distortion::Fisheye(k @ [k1, k2, k3, k4]) => {
                let theta_d = (xd * xd + yd * yd).sqrt();
                if theta_d < FISHEYE_AXIS {
                    return (xd, yd);
                }
                let mut theta = theta_d;
                for _ in 0..10 {
                    let t2 = theta * theta;
                    let slope =
                        1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
                    theta -= (fisheye_radius(k, theta) - theta_d) / slope;
                }
                let scale = libm::tanf(theta) / theta_d;
                (xd * scale, yd * scale)
            }
        }
    }
}

/// The fisheye's distorted radius, `theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
/// k4 theta^8)`.
fn fisheye_radius([k1, k2, k3, k4]: [f32; 4], theta: f32) -> f32 {
    let t2 = theta * theta;
    theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
}

/// Maps stored images (possibly distorted, any size) to pinhole images of the requested size.
pub(crate) struct Resampler {
    /// The stored images' pinhole intrinsics and size.
    source: Camera,
    distortion: Option<Distortion>,
    pub(crate) output: Camera,
    /// Sub-samples per output pixel along each axis (area averaging when downsizing).
    subsamples: u32,
}

impl Resampler {
    /// `max_side`: the output's longer side (the aspect ratio kept; never larger than the
    /// stored size, so small images are not upsampled); `None` keeps the size.
    pub(crate) fn new(
        source: Camera,
        distortion: Option<Distortion>,
        max_side: Option<u32>,
    ) -> Resampler {
        let size = max_side.map_or(OutputSize::Original, OutputSize::MaxSide);
        Resampler::with_size(source, distortion, size)
    }

    /// A resampler to the frame size `size` asks for.
    pub(crate) fn with_size(
        source: Camera,
        distortion: Option<Distortion>,
        size: OutputSize,
    ) -> Resampler {
        let (source_width, source_height) = (source.width as u32, source.height as u32);
        let (out_width, out_height) = output_size(size, (source_width, source_height));
        let scale_x = out_width as f32 / source_width as f32;
        let scale_y = out_height as f32 / source_height as f32;
        let output = Camera {
            width: out_width as u16,
            height: out_height as u16,
            fx: source.fx * scale_x,
            fy: source.fy * scale_y,
            cx: source.cx * scale_x,
            cy: source.cy * scale_y,
        };
        let subsamples = (1.0 / scale_x.min(scale_y)).ceil().clamp(1.0, 16.0) as u32;
        Resampler {
            source,
            distortion,
            output,
            subsamples,
        }
    }

    fn is_identity(&self) -> bool {
        self.output == self.source && self.distortion.is_none()
    }

    pub(crate) fn rgb(&self, path: &Path, image: &image::RgbImage) -> Result<Vec<u8>> {
        if self.is_identity() {
            return Ok(image.as_raw().clone());
        }
        self.resample(path, image.as_raw(), 3)
    }

    /// Masks are resampled like images and thresholded back to 0 / 255.
    pub(crate) fn mask(&self, path: &Path, image: &image::GrayImage) -> Result<Vec<u8>> {
        if self.is_identity() {
            return Ok(image.as_raw().clone());
        }
        let mut mask = self.resample(path, image.as_raw(), 1)?;
        mask.iter_mut()
            .for_each(|v| *v = if *v >= 128 { 255 } else { 0 });
        Ok(mask)
    }

    fn resample(&self, path: &Path, source: &[u8], channels: usize) -> Result<Vec<u8>> {
        let (sw, sh) = (self.source.width as usize, self.source.height as usize);
        if source.len() != sw * sh * channels {
            return Err(HostError::invalid(
                path,
                "pixel buffer does not match the image size",
            ));
        }
        let out = &self.output;
        let src = &self.source;
        let n = self.subsamples;
        let weight = 1.0 / (n * n) as f32;
        let mut pixels = vec![0u8; out.pixel_count() * channels];
        for (index, pixel) in pixels.chunks_exact_mut(channels).enumerate() {
            let (i, j) = (
                (index % out.width as usize) as f32,
                (index / out.width as usize) as f32,
            );
            let mut sum = [0.0f32; 3];
            for sy in 0..n {
                for sx in 0..n {
                    let u = i + (sx as f32 + 0.5) / n as f32;
                    let v = j + (sy as f32 + 0.5) / n as f32;
                    let (x, y) = ((u - out.cx) / out.fx, (v - out.cy) / out.fy);
                    // Zero coefficients would map (x, y) to itself: skip the polynomial.
                    let (x, y) = self.distortion.map_or((x, y), |lens| lens.apply(x, y));
                    let value = bilinear(
                        source,
                        sw,
                        sh,
                        channels,
                        src.fx * x + src.cx - 0.5,
                        src.fy * y + src.cy - 0.5,
                    );
                    for c in 0..channels {
                        sum[c] += value[c];
                    }
                }
            }
            for c in 0..channels {
                pixel[c] = to_byte(sum[c] * weight);
            }
        }
        Ok(pixels)
    }
}

/// Bilinear sample at continuous pixel-index coordinates (pixel `i` covers `[i - 0.5, i + 0.5]`);
/// points off the image are black, points on it near the border repeat the edge pixels.
fn bilinear(
    source: &[u8],
    width: usize,
    height: usize,
    channels: usize,
    x: f32,
    y: f32,
) -> [f32; 3] {
    let mut out = [0.0; 3];
    if !(x >= -0.5 && y >= -0.5 && x <= width as f32 - 0.5 && y <= height as f32 - 0.5) {
        return out;
    }
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    for (dy, wy) in [(0, 1.0 - fy), (1, fy)] {
        for (dx, wx) in [(0, 1.0 - fx), (1, fx)] {
            let px = (x0 as i64 + dx).clamp(0, width as i64 - 1) as usize;
            let py = (y0 as i64 + dy).clamp(0, height as i64 - 1) as usize;
            let base = (py * width + px) * channels;
            for c in 0..channels {
                out[c] += wx * wy * source[base + c] as f32;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--size` for SPEED+/SHIRT frames: the longer side, landscape or portrait, and a size
    /// above the stored one keeps the stored size (no upsampling).
    #[test]
    fn the_output_has_the_requested_longer_side_and_is_never_upsampled() {
        let camera = |width, height| Camera {
            width,
            height,
            fx: 50.0,
            fy: 50.0,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
        };
        let cases = [
            ((64, 40), Some(32), (32, 20)),
            ((40, 64), Some(32), (20, 32)),
            ((64, 40), Some(1000), (64, 40)),
            ((64, 40), None, (64, 40)),
        ];
        for ((w, h), max_side, expected) in cases {
            let output = Resampler::new(camera(w, h), None, max_side).output;
            assert_eq!(
                (output.width, output.height),
                expected,
                "{w}x{h} {max_side:?}"
            );
            let scale = expected.0 as f32 / w as f32;
            assert!((output.fx - 50.0 * scale).abs() < 1e-4);
        }
    }

    /// The fisheye's inverse undoes it, out to wide angles (the standard model's is checked
    /// with the SPEED+ camera).
    #[test]
    fn the_fisheye_inverse_undoes_the_fisheye() {
        let lens = Distortion::Fisheye([-0.05, 0.02, -0.01, 0.004]);
        for (x, y) in [
            (0.0, 0.0),
            (1e-9, 0.0),
            (0.2, -0.1),
            (-0.6, 0.45),
            (1.2, 0.9),
        ] {
            let (xd, yd) = lens.apply(x, y);
            let (xu, yu) = lens.invert(xd, yd);
            assert!(
                (xu - x).abs() < 1e-5 * (1.0 + x.abs()) && (yu - y).abs() < 1e-5 * (1.0 + y.abs()),
                "({x}, {y}) -> ({xu}, {yu})"
            );
        }
    }
}
