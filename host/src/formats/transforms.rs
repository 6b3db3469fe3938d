//! What the two `transforms.json` formats (NeRF-synthetic and nerfstudio) share: load
//! options, and turning frame files into [`Frame`]s.
//!
//! Both store OpenGL/Blender camera-to-world matrices (x right, y up, camera looking down -z).
//! The dataset uses OpenCV axes (x right, y down, z forward), so the camera's y and z columns
//! flip sign: `R_cv = R_gl * diag(1, -1, -1)`; the camera centre is unchanged (see
//! `JsonFile::pose` in `formats/json.rs`).
//!
//! Transparent images are composited on [`LoadOptions::background`] at full resolution
//! (`rgb * a + bg * (1 - a)`: premultiplied colour plus the background's share) *before* any resampling, so edges
//! blend with the background rather than with the black hidden under alpha = 0. Resampling is
//! a box (area) average when the size shrinks by whole factors (800 -> 100), which is what
//! NeRF-synthetic results are conventionally scored on; any other size uses a tent filter
//! widened to the scale ratio (no ringing, so values stay within the input range).
//!
//! Frames are decoded in parallel with rayon; frame order and error reporting stay those of the
//! JSON file (the first bad frame in file order is the one reported).

use super::resample::{Distortion, Resampler, resample, to_byte};
use crate::dataset::Frame;
use crate::error::{HostError, Result};
use image::DynamicImage;
use orbit_nerf_core::{Camera, Pose};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Size of the frames a loader produces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputSize {
    /// The images' own size.
    Original,
    /// Exactly this size (the aspect ratio may change; `fx` and `fy` scale separately).
    Exact {
        /// Output width in pixels.
        width: u32,
        /// Output height in pixels.
        height: u32,
    },
    /// Shrink so that the longer side is at most this many pixels, keeping the aspect ratio.
    /// Never enlarges.
    MaxSide(u32),
}

/// How a `transforms.json` loader produces its frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadOptions {
    /// Size of the frames produced.
    pub size: OutputSize,
    /// Colour (RGB in [0, 1]) that transparent pixels are composited on. The core renders onto
    /// black, so black is the default; NeRF-synthetic results in papers use white.
    pub background: [f32; 3],
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            size: OutputSize::Original,
            background: [0.0; 3],
        }
    }
}

/// Pinhole intrinsics in pixels of the source image (before resizing).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Intrinsics {
    pub(crate) fx: f64,
    pub(crate) fy: f64,
    pub(crate) cx: f64,
    pub(crate) cy: f64,
}

/// Everything needed to read one frame's pixels, gathered before the parallel decode.
pub(crate) struct FrameJob {
    pub(crate) name: String,
    pub(crate) image: PathBuf,
    pub(crate) mask: Option<PathBuf>,
    pub(crate) pose: Pose,
    /// Size the JSON says the image has, checked against the decoded image.
    pub(crate) declared_size: Option<(u32, u32)>,
    /// The lens distortion the image was taken through, undone while decoding.
    pub(crate) lens: Option<Lens>,
}

/// A distorted frame's pinhole intrinsics (source pixels) and lens distortion.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Lens {
    pub(crate) intrinsics: Intrinsics,
    pub(crate) distortion: Distortion,
}

pub(crate) struct DecodedFrame {
    pub(crate) source_size: (u32, u32),
    pub(crate) output_size: (u32, u32),
    pub(crate) pixels: Vec<u8>,
    pub(crate) mask: Option<Vec<u8>>,
    /// The mask came from the image's alpha, which the pixels are composited by.
    pub(crate) alpha_composited: bool,
}

impl DecodedFrame {
    pub(crate) fn into_frame(self, name: String, pose: Pose, source: Intrinsics) -> Frame {
        // Scaling pixel coordinates by the size ratio maps pixel centres (i + 0.5) onto pixel
        // centres, so the principal point scales exactly like the focal length.
        let sx = self.output_size.0 as f64 / self.source_size.0 as f64;
        let sy = self.output_size.1 as f64 / self.source_size.1 as f64;
        let camera = Camera {
            width: self.output_size.0 as u16,
            height: self.output_size.1 as u16,
            fx: (source.fx * sx) as f32,
            fy: (source.fy * sy) as f32,
            cx: (source.cx * sx) as f32,
            cy: (source.cy * sy) as f32,
        };
        Frame {
            name,
            camera,
            pose,
            pixels: self.pixels,
            mask: self.mask,
            alpha_composited: self.alpha_composited,
        }
    }
}

/// Decode every frame in parallel, then check in file order that they share one source size.
pub(crate) fn decode_all(jobs: &[FrameJob], options: &LoadOptions) -> Result<Vec<DecodedFrame>> {
    let results: Vec<Result<DecodedFrame>> = jobs
        .par_iter()
        .map(|job| decode_frame(job, options))
        .collect();
    let decoded = results.into_iter().collect::<Result<Vec<_>>>()?;
    if let Some(first) = decoded.first() {
        for (job, frame) in jobs.iter().zip(&decoded) {
            if frame.source_size != first.source_size {
                return Err(HostError::invalid(
                    &job.image,
                    format!(
                        "image is {}x{} but {} is {}x{}: all frames must have one size",
                        frame.source_size.0,
                        frame.source_size.1,
                        jobs[0].name,
                        first.source_size.0,
                        first.source_size.1
                    ),
                ));
            }
        }
    }
    Ok(decoded)
}

fn read_image(path: &Path) -> Result<DynamicImage> {
    image::ImageReader::open(path)
        .and_then(|reader| reader.with_guessed_format())
        .map_err(|e| HostError::io(path, e))?
        .decode()
        .map_err(|e| HostError::invalid(path, format!("unreadable image: {e}")))
}

pub(crate) fn output_size(size: OutputSize, (w, h): (u32, u32)) -> (u32, u32) {
    match size {
        OutputSize::Original => (w, h),
        OutputSize::Exact { width, height } => (width, height),
        OutputSize::MaxSide(max_side) if w.max(h) > max_side => {
            let scale = max_side as f64 / w.max(h) as f64;
            (
                ((w as f64 * scale).round() as u32).max(1),
                ((h as f64 * scale).round() as u32).max(1),
            )
        }
        OutputSize::MaxSide(_) => (w, h),
    }
}

pub(crate) fn decode_frame(job: &FrameJob, options: &LoadOptions) -> Result<DecodedFrame> {
    let image = read_image(&job.image)?;
    let source_size = (image.width(), image.height());
    if let Some((w, h)) = job
        .declared_size
        .filter(|&declared| declared != source_size)
    {
        return Err(HostError::invalid(
            &job.image,
            format!(
                "image is {}x{} but the JSON declares w = {w}, h = {h}",
                source_size.0, source_size.1
            ),
        ));
    }
    let output_size = output_size(options.size, source_size);
    if output_size.0 == 0
        || output_size.1 == 0
        || output_size.0 > u16::MAX as u32
        || output_size.1 > u16::MAX as u32
    {
        return Err(HostError::invalid(
            &job.image,
            format!(
                "cannot produce a {}x{} frame (each side must be 1..=65535)",
                output_size.0, output_size.1
            ),
        ));
    }
    // A distorted frame is composited at its own size, then undistorted and resized in one
    // lookup through its lens (as SPEED+ frames are).
    let composited_size = if job.lens.is_some() {
        source_size
    } else {
        output_size
    };
    let has_alpha = image.color().has_alpha();
    let background = options.background;
    // Composite each source pixel as the resampler reads it: [r, g, b, alpha] on the
    // background. 8-bit RGBA (the usual PNG) is read in place, anything else as f32 RGBA.
    let composited = match image.as_rgba8() {
        Some(rgba) => resample(
            rgba.as_raw(),
            source_size,
            composited_size,
            |p: &[u8; 4]| composite_pixel(p.map(|v| v as f32 / 255.0), background),
        ),
        None => resample(
            image.to_rgba32f().as_raw(),
            source_size,
            composited_size,
            |p: &[f32; 4]| composite_pixel(*p, background),
        ),
    };
    drop(image);
    let pixels: Vec<u8> = composited
        .chunks_exact(4)
        .flat_map(|p| [to_u8(p[0]), to_u8(p[1]), to_u8(p[2])])
        .collect();
    let mask = match &job.mask {
        Some(mask_path) => Some(read_mask(mask_path, source_size, composited_size)?),
        None => has_alpha.then(|| {
            composited
                .chunks_exact(4)
                .map(|p| foreground(p[3]))
                .collect()
        }),
    };
    let (pixels, mask) = match job.lens {
        Some(lens) => undistort(&job.image, lens, source_size, options.size, pixels, mask)?,
        None => (pixels, mask),
    };
    Ok(DecodedFrame {
        source_size,
        output_size,
        pixels,
        alpha_composited: job.mask.is_none() && has_alpha,
        mask,
    })
}

/// Undo `lens` on a frame's pixels and mask composited at the source size `(w, h)`, resizing
/// them to `size` in the same lookup.
fn undistort(
    image_path: &Path,
    lens: Lens,
    (w, h): (u32, u32),
    size: OutputSize,
    pixels: Vec<u8>,
    mask: Option<Vec<u8>>,
) -> Result<(Vec<u8>, Option<Vec<u8>>)> {
    let side = |n: u32| {
        u16::try_from(n).map_err(|_| {
            HostError::invalid(
                image_path,
                format!("image is {w}x{h}: undistorting takes sides of up to 65535 pixels"),
            )
        })
    };
    let Intrinsics { fx, fy, cx, cy } = lens.intrinsics;
    let source = Camera {
        width: side(w)?,
        height: side(h)?,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
    };
    let resampler = Resampler::with_size(source, Some(lens.distortion), size);
    let wrong_size =
        || HostError::invalid(image_path, "pixel buffer does not match the image size");
    let image = image::RgbImage::from_raw(w, h, pixels).ok_or_else(wrong_size)?;
    let pixels = resampler.rgb(image_path, &image)?;
    let mask = match mask {
        Some(mask) => {
            let mask = image::GrayImage::from_raw(w, h, mask).ok_or_else(wrong_size)?;
            Some(resampler.mask(image_path, &mask)?)
        }
        None => None,
    };
    Ok((pixels, mask))
}

/// Straight-alpha RGBA in [0, 1] composited on `background`: `[r, g, b, alpha]`.
fn composite_pixel([r, g, b, a]: [f32; 4], background: [f32; 3]) -> [f32; 4] {
    let a = a.clamp(0.0, 1.0);
    let over = |c: f32, bg: f32| c * a + bg * (1.0 - a);
    [
        over(r, background[0]),
        over(g, background[1]),
        over(b, background[2]),
        a,
    ]
}

/// A resampled coverage (alpha or mask) in [0, 1] as a mask byte: foreground above one half.
fn foreground(coverage: f32) -> u8 {
    if coverage > 0.5 { 255 } else { 0 }
}

/// The mask image at `path` (any non-zero pixel is foreground, as in nerfstudio), which must
/// have the frame's size, resampled like the frame.
fn read_mask(path: &Path, frame_size: (u32, u32), output_size: (u32, u32)) -> Result<Vec<u8>> {
    let mask = read_image(path)?;
    if (mask.width(), mask.height()) != frame_size {
        return Err(HostError::invalid(
            path,
            format!(
                "mask is {}x{} but its image is {}x{}",
                mask.width(),
                mask.height(),
                frame_size.0,
                frame_size.1
            ),
        ));
    }
    let coverage = resample(
        mask.to_luma32f().as_raw(),
        frame_size,
        output_size,
        |&[v]: &[f32; 1]| [if v > 0.0 { 1.0 } else { 0.0 }],
    );
    Ok(coverage.into_iter().map(foreground).collect())
}

/// A value in [0, 1] as a byte.
fn to_u8(v: f32) -> u8 {
    to_byte(v * 255.0)
}

/// Scenes and checks shared by the two formats' tests.
#[cfg(test)]
pub(crate) mod fixtures {
    use crate::Result;
    use crate::dataset::{Dataset, Frame};
    use glam::Vec3;
    use image::GrayImage;
    use serde_json::Value;
    use std::path::{Path, PathBuf};

    pub(crate) fn gray(width: u32, height: u32, values: Vec<u8>) -> GrayImage {
        GrayImage::from_raw(width, height, values).unwrap()
    }

    /// Write `value` as JSON into `dir/name`.
    pub(crate) fn write_json(dir: &Path, name: &str, value: &Value) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, serde_json::to_string_pretty(value).unwrap()).unwrap();
        path
    }

    /// Blender camera-to-world matrix (rows) for a camera at `center` looking at the origin,
    /// with world z up.
    pub(crate) fn look_at_origin(center: Vec3) -> Vec<Vec<f64>> {
        let back = center.normalize(); // OpenGL camera looks down -z, so +z points away.
        let right = Vec3::Z.cross(back).normalize();
        let up = back.cross(right);
        (0..3)
            .map(|r| {
                vec![
                    right[r] as f64,
                    up[r] as f64,
                    back[r] as f64,
                    center[r] as f64,
                ]
            })
            .chain(std::iter::once(vec![0.0, 0.0, 0.0, 1.0]))
            .collect()
    }

    pub(crate) fn ring(count: usize, radius: f32, height: f32) -> Vec<Vec3> {
        (0..count)
            .map(|i| {
                let t = i as f32 / count as f32 * std::f32::consts::TAU;
                Vec3::new(radius * t.cos(), radius * t.sin(), height)
            })
            .collect()
    }

    pub(crate) fn error_of(result: Result<Dataset>) -> String {
        result.expect_err("expected an error").to_string()
    }

    /// Distance from `point` to the ray through the image centre of `frame`.
    pub(crate) fn centre_ray_miss(frame: &Frame, point: Vec3) -> f32 {
        let c = &frame.camera;
        let direction = frame.pose.rotation
            * Vec3::new(
                (c.width as f32 / 2.0 - c.cx) / c.fx,
                (c.height as f32 / 2.0 - c.cy) / c.fy,
                1.0,
            );
        let d = direction.normalize();
        let to_point = point - frame.pose.center;
        assert!(to_point.dot(d) > 0.0, "point behind the camera");
        (to_point - d * to_point.dot(d)).length()
    }
}
