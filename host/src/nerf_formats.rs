//! Loaders for the two common NeRF dataset formats:
//!
//! - NeRF-synthetic (Blender): `transforms_{train,val,test}.json` with `camera_angle_x` and
//!   per-frame `file_path` (no extension, `.png` implied) and `transform_matrix`, RGBA images.
//! - nerfstudio: `transforms.json` with pinhole intrinsics (`fl_x, fl_y, cx, cy, w, h`) at the
//!   top level or per frame, `file_path` relative to the JSON's folder, optional `mask_path`,
//!   optional scene box (`aabb` or `scene_box`).
//!
//! Both store OpenGL/Blender camera-to-world matrices (x right, y up, camera looking down -z).
//! The dataset uses OpenCV axes (x right, y down, z forward), so the camera's y and z columns
//! flip sign: `R_cv = R_gl * diag(1, -1, -1)`; the camera centre is unchanged.
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

use crate::dataset::{Dataset, Frame};
use crate::error::{HostError, Result};
use glam::{DMat3, DVec3, Mat3, Quat, Vec3};
use image::{DynamicImage, ImageBuffer, Luma, Rgba};
use orbit_nerf_core::{Camera, Pose};
use rayon::prelude::*;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// K-Planes' scene box for NeRF-synthetic scenes: every object fits in [-1.5, 1.5]^3.
pub const NERF_SYNTHETIC_SCENE_MIN: [f32; 3] = [-1.5; 3];
pub const NERF_SYNTHETIC_SCENE_MAX: [f32; 3] = [1.5; 3];

/// Size of the frames a loader produces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputSize {
    /// The images' own size.
    Original,
    /// Exactly this size (the aspect ratio may change; `fx` and `fy` scale separately).
    Exact { width: u32, height: u32 },
    /// Shrink so that the longer side is at most this many pixels, keeping the aspect ratio.
    /// Never enlarges.
    MaxSide(u32),
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadOptions {
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

/// The three splits of a NeRF-synthetic scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SyntheticSplit {
    Train,
    Val,
    Test,
}

impl SyntheticSplit {
    pub fn file_name(self) -> &'static str {
        match self {
            SyntheticSplit::Train => "transforms_train.json",
            SyntheticSplit::Val => "transforms_val.json",
            SyntheticSplit::Test => "transforms_test.json",
        }
    }
}

/// Load one split of a NeRF-synthetic scene folder (e.g. `nerf_synthetic/lego`).
pub fn load_nerf_synthetic(
    scene_dir: &Path,
    split: SyntheticSplit,
    options: &LoadOptions,
) -> Result<Dataset> {
    load_nerf_synthetic_transforms(&scene_dir.join(split.file_name()), options)
}

/// Load a NeRF-synthetic `transforms_*.json`. The scene box is K-Planes' [-1.5, 1.5]^3.
pub fn load_nerf_synthetic_transforms(json_path: &Path, options: &LoadOptions) -> Result<Dataset> {
    let reader = SyntheticReader::open(json_path, options)?;
    let decoded = decode_all(&reader.jobs, options)?;
    let frames = reader
        .jobs
        .iter()
        .zip(decoded)
        .map(|(job, image)| {
            let intrinsics = reader.intrinsics(image.source_size);
            image.into_frame(job.name.clone(), job.pose, intrinsics)
        })
        .collect();
    Ok(Dataset {
        source: json_path.to_path_buf(),
        frames,
        scene_min: NERF_SYNTHETIC_SCENE_MIN,
        scene_max: NERF_SYNTHETIC_SCENE_MAX,
        background: options.background,
    })
}

/// A NeRF-synthetic `transforms_*.json` opened for reading one frame at a time: the JSON is
/// checked when it opens, an image is decoded only when its frame is asked for.
pub struct SyntheticReader {
    json_path: PathBuf,
    jobs: Vec<FrameJob>,
    angle_x: f64,
    angle_y: Option<f64>,
    options: LoadOptions,
    /// Size of the first image (every frame must have it), when it can be read.
    first_size: Option<(u32, u32)>,
}

impl SyntheticReader {
    pub fn open(json_path: &Path, options: &LoadOptions) -> Result<SyntheticReader> {
        let json = JsonFile::read(json_path)?;
        let angle_x = json.field_of_view(
            json.get(&json.root, "camera_angle_x", "camera_angle_x")?,
            "camera_angle_x",
        )?;
        let angle_y = match json.root.get("camera_angle_y") {
            Some(value) => Some(json.field_of_view(value, "camera_angle_y")?),
            None => None,
        };
        let mut jobs = Vec::new();
        for (index, frame) in json.frames()?.iter().enumerate() {
            let path_field = format!("frames[{index}].file_path");
            let mut name = json
                .string(json.get(frame, "file_path", &path_field)?, &path_field)?
                .to_owned();
            if Path::new(&name).extension().is_none() {
                name.push_str(".png");
            }
            let matrix_field = format!("frames[{index}].transform_matrix");
            let pose = json.pose(
                json.get(frame, "transform_matrix", &matrix_field)?,
                &matrix_field,
            )?;
            jobs.push(FrameJob {
                image: json.resolve(&name),
                name,
                mask: None,
                pose,
                declared_size: None,
            });
        }
        let first_size = jobs
            .first()
            .and_then(|job| image::image_dimensions(&job.image).ok());
        Ok(SyntheticReader {
            json_path: json_path.to_path_buf(),
            jobs,
            angle_x,
            angle_y,
            options: *options,
            first_size,
        })
    }

    pub fn len(&self) -> usize {
        self.jobs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.jobs.is_empty()
    }

    /// Pixels of a frame as produced (from the first image's size).
    pub fn output_pixels(&self) -> usize {
        self.first_size.map_or(0, |size| {
            let (w, h) = output_size(self.options.size, size);
            w as usize * h as usize
        })
    }

    /// Intrinsics in source pixels: focal length from the horizontal field of view; the
    /// vertical one, when given, covers non-square sensors.
    fn intrinsics(&self, (w, h): (u32, u32)) -> Intrinsics {
        let (w, h) = (w as f64, h as f64);
        let fx = 0.5 * w / (0.5 * self.angle_x).tan();
        let fy = self.angle_y.map_or(fx, |a| 0.5 * h / (0.5 * a).tan());
        Intrinsics {
            fx,
            fy,
            cx: 0.5 * w,
            cy: 0.5 * h,
        }
    }

    /// Frame `index`, decoded; its image must have the first image's size.
    pub fn frame(&self, index: usize) -> Result<Frame> {
        let job = self
            .jobs
            .get(index)
            .ok_or_else(|| HostError::invalid(&self.json_path, format!("no frame {index}")))?;
        let image = decode_frame(job, &self.options)?;
        if let Some((w, h)) = self.first_size.filter(|&size| size != image.source_size) {
            return Err(HostError::invalid(
                &job.image,
                format!(
                    "image is {}x{} but {} is {w}x{h}: all frames must have one size",
                    image.source_size.0, image.source_size.1, self.jobs[0].name
                ),
            ));
        }
        let intrinsics = self.intrinsics(image.source_size);
        Ok(image.into_frame(job.name.clone(), job.pose, intrinsics))
    }
}

/// Camera models nerfstudio writes that are pinhole projections (plus lens distortion).
const PERSPECTIVE_CAMERA_MODELS: [&str; 5] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
];

/// Load a nerfstudio `transforms.json` (or the folder holding one).
///
/// Intrinsics may be global or per frame (a frame's value wins). Lens distortion keys (`k1`..,
/// `p1`, `p2`) are accepted and ignored: frames are treated as undistorted pinhole images.
/// Non-pinhole camera models (fisheye, equirectangular) are refused.
///
/// Masks (`mask_path`): any non-zero mask pixel is foreground, as in nerfstudio. Without a mask
/// path, an image with an alpha channel gets its mask from alpha.
///
/// Scene box: from `aabb` or `scene_box` (`[[min x, y, z], [max x, y, z]]`) when present.
/// Otherwise the box is a cube centred on the point the cameras look at (the least-squares
/// intersection of their optical axes) with half-side half the distance from that point to the
/// nearest camera: the object must lie nearer to the focus than any camera, and a cube of that
/// size keeps every camera outside it (its corners are at 0.87 of that distance). Camera sets
/// whose axes do not meet in front of them (forward-facing or outward-looking captures) need an
/// explicit box and get an error saying so.
pub fn load_nerfstudio(path: &Path, options: &LoadOptions) -> Result<Dataset> {
    let json_path = if path.is_dir() {
        path.join("transforms.json")
    } else {
        path.to_path_buf()
    };
    let json = JsonFile::read(&json_path)?;
    if let Some(model) = json.root.get("camera_model") {
        let model = json.string(model, "camera_model")?;
        if !PERSPECTIVE_CAMERA_MODELS.contains(&model) {
            return Err(json.field(
                "camera_model",
                format!(
                    "`{model}` is not a pinhole camera model (accepted: {})",
                    PERSPECTIVE_CAMERA_MODELS.join(", ")
                ),
            ));
        }
    }
    let mut jobs = Vec::new();
    let mut frame_intrinsics = Vec::new();
    for (index, frame) in json.frames()?.iter().enumerate() {
        let intrinsic = |key: &str| -> Result<f64> {
            let field = format!("frames[{index}].{key}");
            match frame.get(key).or_else(|| json.root.get(key)) {
                Some(value) => json.positive(value, &field),
                None => {
                    Err(json.field(field, "missing (neither in the frame nor at the top level)"))
                }
            }
        };
        let intrinsics = Intrinsics {
            fx: intrinsic("fl_x")?,
            fy: intrinsic("fl_y")?,
            cx: intrinsic("cx")?,
            cy: intrinsic("cy")?,
        };
        let (w, h) = (intrinsic("w")?, intrinsic("h")?);
        for (key, value) in [("w", w), ("h", h)] {
            if value.fract() != 0.0 || value > u32::MAX as f64 {
                return Err(json.field(
                    format!("frames[{index}].{key}"),
                    format!("{value} is not a pixel count"),
                ));
            }
        }
        let path_field = format!("frames[{index}].file_path");
        let name = json
            .string(json.get(frame, "file_path", &path_field)?, &path_field)?
            .to_owned();
        let mask = match frame.get("mask_path") {
            Some(value) => {
                Some(json.resolve(json.string(value, &format!("frames[{index}].mask_path"))?))
            }
            None => None,
        };
        let matrix_field = format!("frames[{index}].transform_matrix");
        let pose = json.pose(
            json.get(frame, "transform_matrix", &matrix_field)?,
            &matrix_field,
        )?;
        jobs.push(FrameJob {
            image: json.resolve(&name),
            name,
            mask,
            pose,
            declared_size: Some((w as u32, h as u32)),
        });
        frame_intrinsics.push(intrinsics);
    }
    let (scene_min, scene_max) = match ["aabb", "scene_box"]
        .into_iter()
        .find(|key| json.root.get(key).is_some())
    {
        Some(key) => json.scene_box(key)?,
        None => box_around_focus(&jobs).map_err(|reason| HostError::invalid(&json_path, reason))?,
    };
    let decoded = decode_all(&jobs, options)?;
    let frames = jobs
        .into_iter()
        .zip(decoded)
        .zip(frame_intrinsics)
        .map(|((job, image), intrinsics)| image.into_frame(job.name, job.pose, intrinsics))
        .collect();
    Ok(Dataset {
        source: json_path,
        frames,
        scene_min,
        scene_max,
        background: options.background,
    })
}

/// See [`load_nerfstudio`] for why this box.
fn box_around_focus(jobs: &[FrameJob]) -> std::result::Result<([f32; 3], [f32; 3]), String> {
    let rays: Vec<(DVec3, DVec3)> = jobs
        .iter()
        .map(|j| {
            (
                j.pose.center.as_dvec3(),
                (j.pose.rotation * Vec3::Z).as_dvec3().normalize(),
            )
        })
        .collect();
    // Least-squares point nearest to every optical axis: sum (I - d d^T) (p - o) = 0.
    let mut normal = DMat3::ZERO;
    let mut rhs = DVec3::ZERO;
    for &(origin, direction) in &rays {
        let projector = DMat3::IDENTITY
            - DMat3::from_cols(
                direction * direction.x,
                direction * direction.y,
                direction * direction.z,
            );
        normal += projector;
        rhs += projector * origin;
    }
    let n = rays.len() as f64;
    let no_focus = "cannot infer a scene box: the camera axes do not converge on a point in front of the cameras; \
                    add an `aabb` key ([[min x, y, z], [max x, y, z]])";
    // det(normal) / n^3 is the product of the normalised eigenvalues; near zero when every axis
    // is (nearly) parallel to one direction.
    if normal.determinant() / (n * n * n) < 1e-4 {
        return Err(no_focus.into());
    }
    let focus = normal.inverse() * rhs;
    let in_front = rays
        .iter()
        .filter(|(o, d)| (focus - *o).dot(*d) > 0.0)
        .count();
    if in_front * 2 < rays.len() {
        return Err(no_focus.into());
    }
    let nearest = rays
        .iter()
        .map(|(o, _)| o.distance(focus))
        .fold(f64::INFINITY, f64::min);
    let half = 0.5 * nearest;
    if !(half > 0.0 && focus.is_finite()) {
        return Err(no_focus.into());
    }
    let lo = (focus - DVec3::splat(half)).as_vec3().to_array();
    let hi = (focus + DVec3::splat(half)).as_vec3().to_array();
    Ok((lo, hi))
}

/// Pinhole intrinsics in pixels of the source image (before resizing).
#[derive(Clone, Copy, Debug)]
struct Intrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// Everything needed to read one frame's pixels, gathered before the parallel decode.
struct FrameJob {
    name: String,
    image: PathBuf,
    mask: Option<PathBuf>,
    pose: Pose,
    /// Size the JSON says the image has, checked against the decoded image.
    declared_size: Option<(u32, u32)>,
}

struct DecodedFrame {
    source_size: (u32, u32),
    output_size: (u32, u32),
    pixels: Vec<u8>,
    mask: Option<Vec<u8>>,
}

impl DecodedFrame {
    fn into_frame(self, name: String, pose: Pose, source: Intrinsics) -> Frame {
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
        }
    }
}

/// Decode every frame in parallel, then check in file order that they share one source size.
fn decode_all(jobs: &[FrameJob], options: &LoadOptions) -> Result<Vec<DecodedFrame>> {
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

fn output_size(size: OutputSize, (w, h): (u32, u32)) -> (u32, u32) {
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

fn decode_frame(job: &FrameJob, options: &LoadOptions) -> Result<DecodedFrame> {
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
    let has_alpha = image.color().has_alpha();
    let background = options.background;
    // Composite each source pixel as the resampler reads it: [r, g, b, alpha] on the
    // background. 8-bit RGBA (the usual PNG) is read in place, anything else as f32 RGBA.
    let composited = match image.as_rgba8() {
        Some(rgba) => resample(rgba.as_raw(), source_size, output_size, |p: &[u8; 4]| {
            composite_pixel(p.map(|v| v as f32 / 255.0), background)
        }),
        None => resample(
            image.to_rgba32f().as_raw(),
            source_size,
            output_size,
            |p: &[f32; 4]| composite_pixel(*p, background),
        ),
    };
    drop(image);
    let pixels = composited
        .chunks_exact(4)
        .flat_map(|p| [to_u8(p[0]), to_u8(p[1]), to_u8(p[2])])
        .collect();
    let mask = match &job.mask {
        Some(mask_path) => Some(read_mask(mask_path, source_size, output_size)?),
        None => has_alpha.then(|| {
            composited
                .chunks_exact(4)
                .map(|p| foreground(p[3]))
                .collect()
        }),
    };
    Ok(DecodedFrame {
        source_size,
        output_size,
        pixels,
        mask,
    })
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

fn to_u8(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Turn each source pixel (`IN` interleaved samples) into `OUT` values with `pixel` and
/// resample the result from `from` to `to`: a box average when both sides shrink by whole
/// factors (fused with `pixel`, so the full-size image is never stored), a tent filter
/// otherwise. Returns `OUT` interleaved `f32` per output pixel.
fn resample<T: Copy, const IN: usize, const OUT: usize>(
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

/// A parsed JSON file that reports problems as `file: field \`path\`: reason`.
struct JsonFile {
    path: PathBuf,
    root: Value,
}

impl JsonFile {
    fn read(path: &Path) -> Result<JsonFile> {
        let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
        let root: Value = serde_json::from_str(&quote_non_finite_literals(&text))
            .map_err(|e| HostError::invalid(path, format!("malformed JSON: {e}")))?;
        if !root.is_object() {
            return Err(HostError::invalid(
                path,
                "malformed JSON: the top level must be an object",
            ));
        }
        Ok(JsonFile {
            path: path.to_path_buf(),
            root,
        })
    }

    fn field(&self, field: impl Into<String>, reason: impl Into<String>) -> HostError {
        HostError::field(&self.path, field, reason)
    }

    /// A path in the file, relative to the file's folder.
    fn resolve(&self, relative: &str) -> PathBuf {
        self.path.parent().unwrap_or(Path::new("")).join(relative)
    }

    fn get<'v>(&self, object: &'v Value, key: &str, field: &str) -> Result<&'v Value> {
        object.get(key).ok_or_else(|| self.field(field, "missing"))
    }

    fn frames(&self) -> Result<&Vec<Value>> {
        match self.get(&self.root, "frames", "frames")?.as_array() {
            Some(frames) if !frames.is_empty() => Ok(frames),
            Some(_) => Err(self.field("frames", "no frames")),
            None => Err(self.field("frames", "must be a list")),
        }
    }

    fn string<'v>(&self, value: &'v Value, field: &str) -> Result<&'v str> {
        value
            .as_str()
            .ok_or_else(|| self.field(field, format!("expected a string, found {value}")))
    }

    /// A number that stays finite as `f32` (what the dataset stores).
    fn number(&self, value: &Value, field: &str) -> Result<f64> {
        if let Some(literal) = value.as_str().and_then(|s| s.strip_prefix(NON_FINITE_MARK)) {
            return Err(self.field(field, format!("{literal} is not a finite number")));
        }
        let number = value
            .as_f64()
            .ok_or_else(|| self.field(field, format!("expected a number, found {value}")))?;
        if !(number as f32).is_finite() {
            return Err(self.field(field, format!("{number:e} is not a finite 32-bit number")));
        }
        Ok(number)
    }

    fn positive(&self, value: &Value, field: &str) -> Result<f64> {
        let number = self.number(value, field)?;
        if number <= 0.0 {
            return Err(self.field(field, format!("must be positive, found {number}")));
        }
        Ok(number)
    }

    /// A pinhole field of view in radians, in (0, pi).
    fn field_of_view(&self, value: &Value, field: &str) -> Result<f64> {
        let angle = self.positive(value, field)?;
        if angle >= std::f64::consts::PI {
            return Err(self.field(
                field,
                format!("{angle} rad is not a pinhole field of view (< pi)"),
            ));
        }
        Ok(angle)
    }

    fn numbers(&self, value: &Value, field: &str) -> Result<Vec<f64>> {
        let list = value
            .as_array()
            .ok_or_else(|| self.field(field, format!("expected a list, found {value}")))?;
        list.iter()
            .enumerate()
            .map(|(i, v)| self.number(v, &format!("{field}[{i}]")))
            .collect()
    }

    /// An OpenGL camera-to-world matrix (3x4 or 4x4, rows) as an OpenCV-axes pose. The rotation
    /// must be orthonormal with determinant +1 to within 1e-3; it is then snapped to the nearest
    /// rotation so the small rounding of the file does not accumulate downstream.
    fn pose(&self, value: &Value, field: &str) -> Result<Pose> {
        let rows = value
            .as_array()
            .ok_or_else(|| self.field(field, "expected a list of rows"))?;
        if rows.len() != 3 && rows.len() != 4 {
            return Err(self.field(field, format!("expected 3 or 4 rows, found {}", rows.len())));
        }
        let mut m = [[0.0f64; 4]; 4];
        for (r, row) in rows.iter().enumerate() {
            let row_field = format!("{field}[{r}]");
            let values = self.numbers(row, &row_field)?;
            if values.len() != 4 {
                return Err(self.field(
                    row_field,
                    format!("expected 4 numbers, found {}", values.len()),
                ));
            }
            m[r].copy_from_slice(&values);
        }
        if rows.len() == 4 {
            let bottom_error = m[3]
                .iter()
                .zip([0.0, 0.0, 0.0, 1.0])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            if bottom_error > 1e-4 {
                return Err(self.field(
                    field,
                    format!("bottom row must be [0, 0, 0, 1], found {:?}", m[3]),
                ));
            }
        }
        let rotation = DMat3::from_cols(
            DVec3::new(m[0][0], m[1][0], m[2][0]),
            DVec3::new(m[0][1], m[1][1], m[2][1]),
            DVec3::new(m[0][2], m[1][2], m[2][2]),
        );
        let gram = rotation.transpose() * rotation - DMat3::IDENTITY;
        let orthonormality_error = gram
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, v| a.max(v.abs()));
        if orthonormality_error > 1e-3 {
            return Err(self.field(
                field,
                format!("not a rigid transform: the rotation part is not orthonormal (max |R^T R - I| = {orthonormality_error:.3e})"),
            ));
        }
        let det = rotation.determinant();
        if (det - 1.0).abs() > 1e-3 {
            return Err(self.field(
                field,
                format!("not a rigid transform: the rotation part has determinant {det:.4}"),
            ));
        }
        let rotation = Mat3::from_quat(Quat::from_mat3(&rotation.as_mat3()).normalize());
        // OpenGL (y up, looking down -z) to OpenCV (y down, looking down +z).
        let rotation = Mat3::from_cols(rotation.x_axis, -rotation.y_axis, -rotation.z_axis);
        let center = Vec3::new(m[0][3] as f32, m[1][3] as f32, m[2][3] as f32);
        Ok(Pose { rotation, center })
    }

    fn scene_box(&self, key: &str) -> Result<([f32; 3], [f32; 3])> {
        let corners = self.root[key]
            .as_array()
            .filter(|c| c.len() == 2)
            .ok_or_else(|| self.field(key, "expected [[min x, y, z], [max x, y, z]]"))?;
        let mut bounds = [[0.0f32; 3]; 2];
        for (i, corner) in corners.iter().enumerate() {
            let field = format!("{key}[{i}]");
            let values = self.numbers(corner, &field)?;
            if values.len() != 3 {
                return Err(
                    self.field(field, format!("expected 3 numbers, found {}", values.len()))
                );
            }
            for (b, v) in bounds[i].iter_mut().zip(values) {
                *b = v as f32;
            }
        }
        if (0..3).any(|axis| bounds[0][axis] >= bounds[1][axis]) {
            return Err(self.field(
                key,
                format!(
                    "min {:?} is not below max {:?} on every axis",
                    bounds[0], bounds[1]
                ),
            ));
        }
        Ok((bounds[0], bounds[1]))
    }
}

/// Prefix of the strings that stand in for `NaN` / `Infinity` literals. Only number fields
/// look for it, and a string there is an error anyway, so it cannot hide a real value.
const NON_FINITE_MARK: &str = "non-finite literal ";

/// Python's `json.dump` writes `NaN`, `Infinity` and `-Infinity`, which are not JSON. Quote
/// them (outside strings) so the file parses and the number check can name the field that holds
/// one, instead of failing with only a line and column.
pub(crate) fn quote_non_finite_literals(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    let mut escaped = false;
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if in_string {
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
        } else if c == '"' {
            in_string = true;
        } else if let Some(literal) = ["-Infinity", "Infinity", "NaN"]
            .into_iter()
            .find(|l| rest.starts_with(l))
        {
            out.push('"');
            out.push_str(NON_FINITE_MARK);
            out.push_str(literal);
            out.push('"');
            rest = &rest[literal.len()..];
            continue;
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{GrayImage, RgbaImage};
    use std::time::Instant;

    fn gray(width: u32, height: u32, values: Vec<u8>) -> GrayImage {
        GrayImage::from_raw(width, height, values).unwrap()
    }

    /// Write `value` as JSON into `dir/name`.
    fn write_json(dir: &Path, name: &str, value: &Value) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, serde_json::to_string_pretty(value).unwrap()).unwrap();
        path
    }

    /// Blender camera-to-world matrix (rows) for a camera at `center` looking at the origin,
    /// with world z up.
    fn look_at_origin(center: Vec3) -> Vec<Vec<f64>> {
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

    fn ring(count: usize, radius: f32, height: f32) -> Vec<Vec3> {
        (0..count)
            .map(|i| {
                let t = i as f32 / count as f32 * std::f32::consts::TAU;
                Vec3::new(radius * t.cos(), radius * t.sin(), height)
            })
            .collect()
    }

    /// An RGBA test image: left half opaque red, right half transparent, one half-alpha column.
    fn rgba_image(width: u32, height: u32) -> RgbaImage {
        RgbaImage::from_fn(width, height, |x, _| {
            if x < width / 2 {
                image::Rgba([255, 0, 0, 255])
            } else if x == width / 2 {
                image::Rgba([0, 0, 255, 128])
            } else {
                image::Rgba([0, 255, 0, 0])
            }
        })
    }

    /// A NeRF-synthetic scene with `count` 16x8 frames on a ring; returns the JSON path.
    fn synthetic_scene(dir: &Path, count: usize) -> PathBuf {
        std::fs::create_dir_all(dir.join("train")).unwrap();
        let frames: Vec<Value> = ring(count, 4.0, 1.0)
            .into_iter()
            .enumerate()
            .map(|(i, c)| {
                rgba_image(16, 8).save(dir.join(format!("train/r_{i}.png"))).unwrap();
                serde_json::json!({"file_path": format!("./train/r_{i}"), "transform_matrix": look_at_origin(c)})
            })
            .collect();
        write_json(
            dir,
            "transforms_train.json",
            &serde_json::json!({"camera_angle_x": 0.69, "frames": frames}),
        )
    }

    fn error_of(result: Result<Dataset>) -> String {
        result.expect_err("expected an error").to_string()
    }

    /// Distance from `point` to the ray through the image centre of `frame`.
    fn centre_ray_miss(frame: &Frame, point: Vec3) -> f32 {
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

    #[test]
    fn synthetic_frames_composite_and_keep_order() {
        let dir = tempfile::tempdir().unwrap();
        let json = synthetic_scene(dir.path(), 5);
        let options = LoadOptions {
            size: OutputSize::Original,
            background: [1.0, 1.0, 1.0],
        };
        let data = load_nerf_synthetic(dir.path(), SyntheticSplit::Train, &options).unwrap();
        assert_eq!(data.source, json);
        assert_eq!(
            (data.scene_min, data.scene_max),
            (NERF_SYNTHETIC_SCENE_MIN, NERF_SYNTHETIC_SCENE_MAX)
        );
        let names: Vec<&str> = data.frames.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "./train/r_0.png",
                "./train/r_1.png",
                "./train/r_2.png",
                "./train/r_3.png",
                "./train/r_4.png"
            ]
        );
        let frame = &data.frames[0];
        let px = |x: usize| &frame.pixels[x * 3..x * 3 + 3];
        assert_eq!(px(0), [255, 0, 0]);
        assert_eq!(
            px(15),
            [255, 255, 255],
            "transparent pixels take the background"
        );
        // alpha 128/255 blue over white: rgb * a + bg * (1 - a).
        let a = 128.0 / 255.0;
        let mixed = ((1.0 - a) * 255.0f32).round() as u8;
        assert_eq!(px(8), [mixed, mixed, 255]);
        let mask = frame.mask.as_ref().unwrap();
        assert_eq!((mask[0], mask[8], mask[9]), (255, 255, 0));
        // f = 0.5 W / tan(angle / 2), principal point at the image centre.
        let c = frame.camera;
        assert!((c.fx - 0.5 * 16.0 / (0.5f32 * 0.69).tan()).abs() < 1e-4 && c.fx == c.fy);
        assert_eq!((c.width, c.height, c.cx, c.cy), (16, 8, 8.0, 4.0));
    }

    #[test]
    fn opengl_poses_become_opencv_poses_looking_at_the_target() {
        let dir = tempfile::tempdir().unwrap();
        synthetic_scene(dir.path(), 6);
        let data = load_nerf_synthetic(dir.path(), SyntheticSplit::Train, &LoadOptions::default())
            .unwrap();
        for frame in &data.frames {
            let r = frame.pose.rotation;
            assert!((r.determinant() - 1.0).abs() < 1e-5);
            // OpenCV: +z looks at the origin, +y points down (against world z up).
            let forward = r * Vec3::Z;
            assert!(forward.dot(-frame.pose.center.normalize()) > 0.9999);
            assert!((r * Vec3::Y).z < 0.0);
            assert!(centre_ray_miss(frame, Vec3::ZERO) < 1e-4);
        }
    }

    #[test]
    fn box_downsampling_averages_composited_pixels() {
        let dir = tempfile::tempdir().unwrap();
        synthetic_scene(dir.path(), 2);
        let options = LoadOptions {
            size: OutputSize::MaxSide(4),
            background: [0.0, 0.0, 0.0],
        };
        let data = load_nerf_synthetic(dir.path(), SyntheticSplit::Train, &options).unwrap();
        let frame = &data.frames[1];
        assert_eq!((frame.camera.width, frame.camera.height), (4, 2));
        // Factor 4: output column 2 averages source columns 8..12 (one half-alpha blue column,
        // three transparent ones) over black.
        let blue = (128.0f32 / 255.0 / 4.0 * 255.0).round() as u8;
        assert_eq!(
            &frame.pixels[..12],
            &[255, 0, 0, 255, 0, 0, 0, 0, blue, 0, 0, 0]
        );
        assert_eq!(frame.mask.as_ref().unwrap()[..4], [255, 255, 0, 0]);
        // Intrinsics scale with the image: f and the principal point shrink by 4.
        assert!((frame.camera.fx - 0.5 * 4.0 / (0.5f32 * 0.69).tan()).abs() < 1e-5);
        assert_eq!((frame.camera.cx, frame.camera.cy), (2.0, 1.0));
    }

    #[test]
    fn non_integer_resizing_filters_and_scales_intrinsics() {
        let dir = tempfile::tempdir().unwrap();
        synthetic_scene(dir.path(), 1);
        let options = LoadOptions {
            size: OutputSize::Exact {
                width: 10,
                height: 6,
            },
            background: [0.0, 1.0, 0.0],
        };
        let data = load_nerf_synthetic(dir.path(), SyntheticSplit::Train, &options).unwrap();
        let frame = &data.frames[0];
        assert_eq!(
            (frame.camera.width, frame.camera.height, frame.pixels.len()),
            (10, 6, 180)
        );
        assert_eq!(
            &frame.pixels[..3],
            &[255, 0, 0],
            "solid regions keep their colour"
        );
        assert_eq!(
            &frame.pixels[27..30],
            &[0, 255, 0],
            "background shows where alpha was 0"
        );
        let f16 = 0.5 * 16.0 / (0.5f32 * 0.69).tan();
        assert!((frame.camera.fx - f16 * 10.0 / 16.0).abs() < 1e-4);
        assert!((frame.camera.fy - f16 * 6.0 / 8.0).abs() < 1e-4);
        assert_eq!((frame.camera.cx, frame.camera.cy), (5.0, 3.0));
    }

    /// Rewrite `transforms_train.json` of a 3-frame synthetic scene with `edit` and load it.
    fn load_edited(edit: impl FnOnce(&mut Value, &Path)) -> String {
        let dir = tempfile::tempdir().unwrap();
        let json = synthetic_scene(dir.path(), 3);
        let mut value: Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        edit(&mut value, dir.path());
        write_json(dir.path(), "transforms_train.json", &value);
        let message = error_of(load_nerf_synthetic_transforms(
            &json,
            &LoadOptions::default(),
        ));
        assert!(
            message.contains("transforms_train.json") || message.contains(".png"),
            "{message}"
        );
        message
    }

    #[test]
    fn missing_transforms_file() {
        let dir = tempfile::tempdir().unwrap();
        let message = error_of(load_nerf_synthetic(
            dir.path(),
            SyntheticSplit::Val,
            &LoadOptions::default(),
        ));
        assert!(message.contains("transforms_val.json"), "{message}");
    }

    #[test]
    fn malformed_json_names_file_and_position() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("transforms_test.json");
        std::fs::write(&path, "{\"camera_angle_x\": 0.5, \"frames\": [}").unwrap();
        let message = error_of(load_nerf_synthetic_transforms(
            &path,
            &LoadOptions::default(),
        ));
        assert!(
            message.contains("transforms_test.json") && message.contains("malformed JSON"),
            "{message}"
        );
        assert!(message.contains("line 1"), "{message}");
    }

    #[test]
    fn missing_fields_are_named() {
        let message = load_edited(|v, _| {
            v.as_object_mut().unwrap().remove("camera_angle_x");
        });
        assert!(
            message.contains("field `camera_angle_x`: missing"),
            "{message}"
        );
        let message = load_edited(|v, _| {
            v["frames"][1]
                .as_object_mut()
                .unwrap()
                .remove("transform_matrix");
        });
        assert!(
            message.contains("field `frames[1].transform_matrix`: missing"),
            "{message}"
        );
        let message = load_edited(|v, _| v["frames"] = serde_json::json!([]));
        assert!(message.contains("field `frames`: no frames"), "{message}");
    }

    #[test]
    fn non_finite_numbers_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let json = synthetic_scene(dir.path(), 3);
        let text = std::fs::read_to_string(&json).unwrap();
        // Python's json.dump writes NaN for a failed pose; make frame 2's first entry one.
        let frame2 = text.match_indices("transform_matrix").nth(2).unwrap().0;
        let first_number = frame2
            + text[frame2..]
                .find(|c: char| c == '-' || c.is_ascii_digit())
                .unwrap();
        let end = first_number + text[first_number..].find([',', '\n']).unwrap();
        let edited = format!("{}NaN{}", &text[..first_number], &text[end..]);
        std::fs::write(&json, edited).unwrap();
        let message = error_of(load_nerf_synthetic_transforms(
            &json,
            &LoadOptions::default(),
        ));
        assert!(
            message
                .contains("field `frames[2].transform_matrix[0][0]`: NaN is not a finite number"),
            "{message}"
        );

        let message =
            load_edited(|v, _| v["frames"][0]["transform_matrix"][1][3] = serde_json::json!(1e39));
        assert!(
            message.contains("field `frames[0].transform_matrix[1][3]`")
                && message.contains("finite"),
            "{message}"
        );
        let message = load_edited(|v, _| v["camera_angle_x"] = serde_json::json!(-0.5));
        assert!(
            message.contains("field `camera_angle_x`: must be positive"),
            "{message}"
        );
    }

    #[test]
    fn non_rigid_matrices_are_refused() {
        let message = load_edited(|v, _| {
            for r in 0..3 {
                for c in 0..3 {
                    let x = v["frames"][1]["transform_matrix"][r][c].as_f64().unwrap();
                    v["frames"][1]["transform_matrix"][r][c] = serde_json::json!(x * 1.1);
                }
            }
        });
        assert!(
            message.contains("frames[1].transform_matrix") && message.contains("not orthonormal"),
            "{message}"
        );
        let message = load_edited(|v, _| {
            for r in 0..3 {
                let x = v["frames"][0]["transform_matrix"][r][0].as_f64().unwrap();
                v["frames"][0]["transform_matrix"][r][0] = serde_json::json!(-x);
            }
        });
        assert!(
            message.contains("frames[0].transform_matrix") && message.contains("determinant -1"),
            "{message}"
        );
        let message =
            load_edited(|v, _| v["frames"][2]["transform_matrix"][3][0] = serde_json::json!(0.5));
        assert!(
            message.contains("frames[2].transform_matrix") && message.contains("bottom row"),
            "{message}"
        );
        let message = load_edited(|v, _| {
            v["frames"][2]["transform_matrix"] = serde_json::json!([[1, 0, 0, 0]])
        });
        assert!(message.contains("expected 3 or 4 rows"), "{message}");
    }

    #[test]
    fn frames_of_different_sizes_are_refused() {
        let message =
            load_edited(|_, dir| rgba_image(32, 16).save(dir.join("train/r_2.png")).unwrap());
        assert!(
            message.contains("r_2.png") && message.contains("32x16") && message.contains("16x8"),
            "{message}"
        );
    }

    #[test]
    fn unreadable_and_missing_images() {
        let message =
            load_edited(|_, dir| std::fs::write(dir.join("train/r_1.png"), b"not a png").unwrap());
        assert!(
            message.contains("r_1.png") && message.contains("unreadable image"),
            "{message}"
        );
        let message =
            load_edited(|_, dir| std::fs::remove_file(dir.join("train/r_0.png")).unwrap());
        assert!(message.contains("r_0.png"), "{message}");
    }

    #[test]
    fn nan_literals_inside_strings_are_left_alone() {
        let text = r#"{"a": "NaN \" Infinity", "b": [NaN, -Infinity, 1]}"#;
        let value: Value = serde_json::from_str(&quote_non_finite_literals(text)).unwrap();
        assert_eq!(value["a"], "NaN \" Infinity");
        assert_eq!(
            value["b"][1]
                .as_str()
                .unwrap()
                .strip_prefix(NON_FINITE_MARK),
            Some("-Infinity")
        );
        assert_eq!(value["b"][2], 1);
    }

    /// A nerfstudio capture: 4 RGB 12x10 frames on a ring around (1, 2, 0), global intrinsics,
    /// frame 1 with its own focal length and a mask.
    fn nerfstudio_scene(dir: &Path) -> Value {
        std::fs::create_dir_all(dir.join("images")).unwrap();
        std::fs::create_dir_all(dir.join("masks")).unwrap();
        let target = Vec3::new(1.0, 2.0, 0.0);
        let frames: Vec<Value> = ring(4, 3.0, 0.5)
            .into_iter()
            .enumerate()
            .map(|(i, c)| {
                let image = image::RgbImage::from_fn(12, 10, |x, y| image::Rgb([x as u8 * 20, y as u8 * 25, i as u8]));
                image.save(dir.join(format!("images/frame_{i:05}.png"))).unwrap();
                let mut matrix = look_at_origin(c);
                for (r, row) in matrix.iter_mut().take(3).enumerate() {
                    row[3] += target[r] as f64;
                }
                let mut frame = serde_json::json!({"file_path": format!("images/frame_{i:05}.png"), "transform_matrix": matrix});
                if i == 1 {
                    frame["fl_x"] = serde_json::json!(20.0);
                    frame["mask_path"] = serde_json::json!("masks/frame_00001.png");
                    gray(12, 10, (0..120).map(|k| if k % 12 < 6 { 255 } else { 0 }).collect())
                        .save(dir.join("masks/frame_00001.png"))
                        .unwrap();
                }
                frame
            })
            .collect();
        serde_json::json!({
            "camera_model": "OPENCV",
            "fl_x": 10.0, "fl_y": 11.0, "cx": 6.0, "cy": 5.0, "w": 12, "h": 10,
            "k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": frames,
        })
    }

    #[test]
    fn nerfstudio_intrinsics_masks_and_inferred_box() {
        let dir = tempfile::tempdir().unwrap();
        let json = nerfstudio_scene(dir.path());
        write_json(dir.path(), "transforms.json", &json);
        let options = LoadOptions {
            size: OutputSize::Exact {
                width: 6,
                height: 5,
            },
            background: [0.0; 3],
        };
        let data = load_nerfstudio(dir.path(), &options).unwrap();
        assert_eq!(data.frames.len(), 4);
        let (f0, f1) = (&data.frames[0], &data.frames[1]);
        assert_eq!(
            (f0.camera.fx, f0.camera.fy, f0.camera.cx, f0.camera.cy),
            (5.0, 5.5, 3.0, 2.5)
        );
        assert_eq!(f1.camera.fx, 10.0, "a frame's own fl_x wins, scaled by 1/2");
        assert!(f0.mask.is_none(), "RGB image without mask_path has no mask");
        assert_eq!(f1.mask.as_ref().unwrap()[..6], [255, 255, 255, 0, 0, 0]);
        // Box: centred on the look-at point, half-side = half the camera distance (sqrt(9.25)).
        let half = 0.5 * (9.0f32 + 0.25).sqrt();
        for axis in 0..3 {
            let centre = [1.0, 2.0, 0.0][axis];
            assert!(
                (data.scene_min[axis] - (centre - half)).abs() < 1e-3,
                "{:?}",
                data.scene_min
            );
            assert!(
                (data.scene_max[axis] - (centre + half)).abs() < 1e-3,
                "{:?}",
                data.scene_max
            );
        }
        for frame in &data.frames {
            assert!(centre_ray_miss(frame, Vec3::new(1.0, 2.0, 0.0)) < 1e-3);
        }
    }

    #[test]
    fn nerfstudio_explicit_box_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let base = nerfstudio_scene(dir.path());
        let load = |json: &Value| {
            load_nerfstudio(
                &write_json(dir.path(), "transforms.json", json),
                &LoadOptions::default(),
            )
        };

        let mut with_box = base.clone();
        with_box["aabb"] = serde_json::json!([[-1, -2, -3], [1, 2, 3]]);
        let data = load(&with_box).unwrap();
        assert_eq!(
            (data.scene_min, data.scene_max),
            ([-1.0, -2.0, -3.0], [1.0, 2.0, 3.0])
        );

        let mut bad_box = base.clone();
        bad_box["scene_box"] = serde_json::json!([[1, 0, 0], [0, 1, 1]]);
        assert!(error_of(load(&bad_box)).contains("field `scene_box`: min"));

        let mut no_focal = base.clone();
        no_focal.as_object_mut().unwrap().remove("fl_y");
        assert!(error_of(load(&no_focal)).contains("field `frames[0].fl_y`: missing"));

        let mut fisheye = base.clone();
        fisheye["camera_model"] = serde_json::json!("OPENCV_FISHEYE");
        assert!(
            error_of(load(&fisheye))
                .contains("field `camera_model`: `OPENCV_FISHEYE` is not a pinhole")
        );

        let mut wrong_size = base.clone();
        wrong_size["frames"][2]["w"] = serde_json::json!(13);
        let message = error_of(load(&wrong_size));
        assert!(
            message.contains("frame_00002.png") && message.contains("w = 13"),
            "{message}"
        );

        let mut small_mask = base.clone();
        gray(6, 5, vec![255; 30])
            .save(dir.path().join("masks/small.png"))
            .unwrap();
        small_mask["frames"][1]["mask_path"] = serde_json::json!("masks/small.png");
        assert!(error_of(load(&small_mask)).contains("mask is 6x5 but its image is 12x10"));

        let mut parallel = base.clone();
        for i in 0..4 {
            parallel["frames"][i]["transform_matrix"] =
                serde_json::json!([[1, 0, 0, i], [0, 1, 0, 0], [0, 0, 1, 0]]);
        }
        assert!(error_of(load(&parallel)).contains("add an `aabb` key"));
    }

    fn lego_dir() -> Option<PathBuf> {
        let dir =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/nerf_synthetic/lego");
        if dir.join("transforms_train.json").is_file() {
            Some(dir)
        } else {
            eprintln!(
                "skipping: NeRF-synthetic lego not found at {}",
                dir.display()
            );
            None
        }
    }

    #[test]
    fn lego_loads_at_100_pixels() {
        let Some(dir) = lego_dir() else { return };
        let options = LoadOptions {
            size: OutputSize::MaxSide(100),
            background: [1.0, 1.0, 1.0],
        };
        let start = Instant::now();
        let data = load_nerf_synthetic(&dir, SyntheticSplit::Train, &options).unwrap();
        eprintln!(
            "lego: 100 frames 800 -> 100 px in {:.2} s",
            start.elapsed().as_secs_f64()
        );
        assert_eq!(data.frames.len(), 100);
        for frame in &data.frames {
            assert_eq!((frame.camera.width, frame.camera.height), (100, 100));
            assert_eq!(frame.pixels.len(), 100 * 100 * 3);
            let distance = frame.pose.center.length();
            assert!(
                (distance - 4.0).abs() < 0.2,
                "{}: camera {distance} from the origin",
                frame.name
            );
            assert!(
                centre_ray_miss(frame, Vec3::ZERO) < 0.5,
                "{} does not look at the origin",
                frame.name
            );
            let mask = frame.mask.as_ref().unwrap();
            let covered = mask.iter().filter(|&&m| m == 255).count();
            assert!(
                covered > 500 && covered < 9000,
                "{}: {covered} foreground pixels",
                frame.name
            );
        }
        assert!(
            data.frames[0].name.ends_with("r_0.png") && data.frames[99].name.ends_with("r_99.png")
        );

        // The metric fixtures were made the same way (composited on white, box-downsampled),
        // then turned into Rec.601 luma before rounding; this loader rounds RGB first, so luma
        // may differ by one level.
        let fixture = dir.join("../../metric_fixtures/r_0_100_gray.pgm");
        if let Ok(pgm) = std::fs::read(&fixture) {
            let expected = &pgm[pgm.len() - 100 * 100..];
            let frame = &data.frames[0];
            let mut differing = 0;
            for (i, &want) in expected.iter().enumerate() {
                let p = &frame.pixels[i * 3..i * 3 + 3];
                let luma = (0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64).round()
                    as i32;
                assert!(
                    (luma - want as i32).abs() <= 1,
                    "pixel {i}: {luma} vs {want}"
                );
                differing += (luma != want as i32) as usize;
            }
            assert!(
                differing < 1000,
                "{differing} pixels differ from the fixture"
            );
        }
    }
}
