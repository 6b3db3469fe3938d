//! nerfstudio captures: `transforms.json` with pinhole intrinsics (`fl_x, fl_y, cx, cy, w, h`)
//! and lens distortion (`camera_model`, `k1`.., `p1`, `p2`) at the top level or per frame,
//! `file_path` relative to the JSON's folder, optional `mask_path`, optional scene box (`aabb`
//! or `scene_box`). Frames are read as in [`super::transforms`].

use super::camera::focal_problem;
use super::json::JsonFile;
use super::resample::Distortion;
use super::transforms::{FrameJob, Intrinsics, Lens, LoadOptions, decode_all};
use crate::dataset::{Dataset, SceneBoxOrigin};
use crate::error::{HostError, Result};
use glam::{DMat3, DVec3, Vec3};
use serde_json::Value;
use std::path::Path;

/// Camera models nerfstudio reads as pinhole projections with OpenCV's standard distortion
/// (`k1, k2, k3, p1, p2`, each zero when absent); COLMAP's radial models are its subsets.
const PERSPECTIVE_CAMERA_MODELS: [&str; 5] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
];

/// OpenCV's equidistant fisheye model (`cv::fisheye`, coefficients `k1..k4`).
const FISHEYE_CAMERA_MODEL: &str = "OPENCV_FISHEYE";

/// The lens family `camera_model` names; its coefficients may differ frame to frame.
#[derive(Clone, Copy)]
enum LensModel {
    Perspective,
    Fisheye,
}

/// Load a nerfstudio `transforms.json` (or the folder holding one).
///
/// Intrinsics and distortion coefficients may be global or per frame (a frame's value wins).
/// Distorted images are undistorted while they are decoded (to the pinhole camera of the same
/// `fl_x, fl_y, cx, cy`, as SPEED+ frames are), so rays are cast through the lens:
/// - `camera_model` absent or one of `SIMPLE_PINHOLE`, `PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`,
///   `OPENCV`: OpenCV's standard model, `k1, k2, k3` radial and `p1, p2` tangential (zero
///   when absent; `k4` is refused);
/// - `OPENCV_FISHEYE`: the equidistant fisheye `k1..k4` (`p1`, `p2` are refused);
/// - any other model (equirectangular, omnidirectional, ..) is refused.
///
/// Parts of a pinhole view that fall outside the stored image (corners under pincushion
/// distortion) come out black, as in SPEED+ frames.
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
    dataset_of(JsonFile::read(&json_path)?, options)
}

/// [`load_nerfstudio`] on the text of the `transforms.json` file `json_path` names (the
/// images are still read from the folder it names).
pub fn parse_nerfstudio(json_path: &Path, text: &str, options: &LoadOptions) -> Result<Dataset> {
    dataset_of(JsonFile::parse(json_path, text)?, options)
}

fn dataset_of(json: JsonFile, options: &LoadOptions) -> Result<Dataset> {
    let json_path = json.path.clone();
    let model = lens_model(&json)?;
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
        for (key, focal, side) in [("fl_x", intrinsics.fx, w), ("fl_y", intrinsics.fy, h)] {
            if let Some(problem) = focal_problem(focal, side) {
                return Err(json.field(format!("frames[{index}].{key}"), problem));
            }
        }
        let distortion = frame_distortion(&json, frame, index, model)?;
        let (name, pose) = json.frame_file_and_pose(frame, index)?;
        let mask = match frame.get("mask_path") {
            Some(value) => {
                Some(json.resolve(json.string(value, &format!("frames[{index}].mask_path"))?))
            }
            None => None,
        };
        jobs.push(FrameJob {
            image: json.resolve(&name),
            name,
            mask,
            pose,
            declared_size: Some((w as u32, h as u32)),
            lens: distortion.map(|distortion| Lens {
                intrinsics,
                distortion,
            }),
        });
        frame_intrinsics.push(intrinsics);
    }
    let ((scene_min, scene_max), scene_box) = match ["aabb", "scene_box"]
        .into_iter()
        .find(|key| json.root.get(key).is_some())
    {
        Some(key) => (
            json.scene_box(key)?,
            SceneBoxOrigin::Data(format!("`{key}` in {}", json_path.display())),
        ),
        None => (
            box_around_focus(&jobs).map_err(|reason| HostError::invalid(&json_path, reason))?,
            SceneBoxOrigin::Data("the cameras' common focus (no aabb in the file)".into()),
        ),
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
        scene_box,
        background: options.background,
        target_centred: false,
    })
}

/// The lens family of the top-level `camera_model` (absent: perspective, as in nerfstudio).
fn lens_model(json: &JsonFile) -> Result<LensModel> {
    let Some(model) = json.root.get("camera_model") else {
        return Ok(LensModel::Perspective);
    };
    match json.string(model, "camera_model")? {
        model if PERSPECTIVE_CAMERA_MODELS.contains(&model) => Ok(LensModel::Perspective),
        FISHEYE_CAMERA_MODEL => Ok(LensModel::Fisheye),
        model => Err(json.field(
            "camera_model",
            format!(
                "`{model}` is not a pinhole or fisheye camera model (accepted: {}, \
                 {FISHEYE_CAMERA_MODEL})",
                PERSPECTIVE_CAMERA_MODELS.join(", ")
            ),
        )),
    }
}

/// Frame `index`'s distortion coefficients under `model` (the frame's own, else the top
/// level's, else zero), checked; `None` when they are all zero (a pinhole camera).
fn frame_distortion(
    json: &JsonFile,
    frame: &Value,
    index: usize,
    model: LensModel,
) -> Result<Option<Distortion>> {
    // The field named in messages is the one the value came from.
    let coefficient = |key: &str| -> Result<(f64, String)> {
        let (value, field) = match frame.get(key) {
            Some(value) => (value, format!("frames[{index}].{key}")),
            None => match json.root.get(key) {
                Some(value) => (value, key.to_string()),
                None => return Ok((0.0, key.to_string())),
            },
        };
        let c = json.number(value, &field)?;
        let limit = Distortion::limit(key);
        if c.abs() > limit {
            return Err(json.field(
                field,
                format!("{c} is not a lens distortion coefficient (|{key}| <= {limit})"),
            ));
        }
        Ok((c, field))
    };
    let value = |key: &str| coefficient(key).map(|(c, _)| c as f32);
    // A coefficient the model has no place for would be silently dropped: refuse it instead.
    let unused = |key: &str, model: &str| -> Result<()> {
        match coefficient(key)? {
            (0.0, _) => Ok(()),
            (c, field) => Err(json.field(
                field,
                format!("{key} = {c} is not a coefficient of the {model} model (`camera_model`)"),
            )),
        }
    };
    let distortion = match model {
        LensModel::Perspective => {
            unused("k4", "OPENCV")?;
            let k = [
                value("k1")?,
                value("k2")?,
                value("p1")?,
                value("p2")?,
                value("k3")?,
            ];
            Distortion::Opencv(k)
        }
        LensModel::Fisheye => {
            unused("p1", FISHEYE_CAMERA_MODEL)?;
            unused("p2", FISHEYE_CAMERA_MODEL)?;
            Distortion::Fisheye([value("k1")?, value("k2")?, value("k3")?, value("k4")?])
        }
    };
    let coefficients: &[f32] = match &distortion {
        Distortion::Opencv(k) => k,
        Distortion::Fisheye(k) => k,
    };
    Ok(coefficients.iter().any(|&c| c != 0.0).then_some(distortion))
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::transforms::OutputSize;
    use crate::formats::transforms::fixtures::*;
    use serde_json::Value;

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

        let mut equirectangular = base.clone();
        equirectangular["camera_model"] = serde_json::json!("EQUIRECTANGULAR");
        assert!(
            error_of(load(&equirectangular))
                .contains("field `camera_model`: `EQUIRECTANGULAR` is not a pinhole")
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

    /// The world point the lens tests image, the two cameras (Blender centres, looking at the
    /// origin) that see it well off their axes, and their pinhole intrinsics.
    const LENS_POINT: Vec3 = Vec3::new(0.9, -0.8, -0.5);
    const LENS_CAMERAS: [Vec3; 2] = [Vec3::new(3.0, 0.0, 0.5), Vec3::new(0.5, -3.0, 1.0)];
    const LENS_SIZE: (u32, u32) = (96, 72);
    const LENS_INTRINSICS: [f64; 4] = [75.0, 78.0, 47.3, 36.6];

    /// Normalised image coordinates of `point` seen by a camera with the Blender
    /// camera-to-world `matrix` (rows; the camera looks down -z with y up).
    fn normalised(matrix: &[Vec<f64>], point: Vec3) -> (f64, f64) {
        let column = |c: usize| DVec3::new(matrix[0][c], matrix[1][c], matrix[2][c]);
        let d = point.as_dvec3() - column(3);
        let depth = -d.dot(column(2));
        (d.dot(column(0)) / depth, -d.dot(column(1)) / depth)
    }

    /// A 96x72 capture whose two frames image [`LENS_POINT`] as a blurred dot where `distort`
    /// (frame index, undistorted normalised x, y -> distorted ones) puts it; `top` holds the
    /// top-level keys besides the intrinsics, `own` each frame's own keys.
    fn lens_scene(
        dir: &Path,
        top: Value,
        own: [Value; 2],
        distort: impl Fn(usize, f64, f64) -> (f64, f64),
    ) -> Value {
        std::fs::create_dir_all(dir.join("images")).unwrap();
        let [fx, fy, cx, cy] = LENS_INTRINSICS;
        let frames: Vec<Value> = LENS_CAMERAS
            .iter()
            .zip(own)
            .enumerate()
            .map(|(i, (&centre, own))| {
                let matrix = look_at_origin(centre);
                let (x, y) = normalised(&matrix, LENS_POINT);
                let (xd, yd) = distort(i, x, y);
                let (u, v) = (fx * xd + cx, fy * yd + cy);
                let shift = (fx * (xd - x)).hypot(fy * (yd - y));
                assert!(
                    shift > 2.0,
                    "frame {i}: the lens moves the dot only {shift} px"
                );
                let image = image::RgbImage::from_fn(LENS_SIZE.0, LENS_SIZE.1, |i, j| {
                    let (du, dv) = (i as f64 + 0.5 - u, j as f64 + 0.5 - v);
                    let value = 255.0 * (-(du * du + dv * dv) / (2.0 * 1.2 * 1.2)).exp();
                    image::Rgb([value.round() as u8; 3])
                });
                let file = format!("images/frame_{i:05}.png");
                image.save(dir.join(&file)).unwrap();
                let mut frame = serde_json::json!({"file_path": file, "transform_matrix": matrix});
                frame
                    .as_object_mut()
                    .unwrap()
                    .extend(own.as_object().unwrap().clone());
                frame
            })
            .collect();
        let mut json = serde_json::json!({
            "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": LENS_SIZE.0, "h": LENS_SIZE.1,
            "aabb": [[-1, -1, -1], [1, 1, 1]],
            "frames": frames,
        });
        json.as_object_mut()
            .unwrap()
            .extend(top.as_object().unwrap().clone());
        json
    }

    /// In every frame, the ray the frame casts through the dot's centre (the centroid of its
    /// pixels) passes [`LENS_POINT`] within a quarter of the frame's pixel.
    fn assert_rays_hit_the_point(data: &Dataset) {
        assert_eq!(data.frames.len(), 2);
        for frame in &data.frames {
            let c = &frame.camera;
            let (mut sum, mut weight) = (glam::DVec2::ZERO, 0.0);
            for (index, pixel) in frame.pixels.chunks_exact(3).enumerate() {
                let (i, j) = (index % c.width as usize, index / c.width as usize);
                let w = pixel[0] as f64;
                sum += w * glam::DVec2::new(i as f64 + 0.5, j as f64 + 0.5);
                weight += w;
            }
            let dot = sum / weight;
            let direction = frame.pose.rotation
                * Vec3::new(
                    (dot.x as f32 - c.cx) / c.fx,
                    (dot.y as f32 - c.cy) / c.fy,
                    1.0,
                );
            let d = direction.normalize();
            let to_point = LENS_POINT - frame.pose.center;
            let miss = (to_point - d * to_point.dot(d)).length();
            let miss_px = miss / to_point.dot(d) * c.fx;
            assert!(
                miss_px < 0.25,
                "{}: the ray through the dot at {dot} misses by {miss_px} px",
                frame.name
            );
        }
    }

    fn load_lens_scene(dir: &Path, json: &Value, size: OutputSize) -> Result<Dataset> {
        let options = LoadOptions {
            size,
            background: [0.0; 3],
        };
        load_nerfstudio(&write_json(dir, "transforms.json", json), &options)
    }

    /// OpenCV's standard model as its documentation writes it (`cv::projectPoints`).
    fn opencv_distort([k1, k2, k3, p1, p2]: [f64; 5], x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// OpenCV's fisheye model as its documentation writes it (`cv::fisheye`).
    fn fisheye_distort([k1, k2, k3, k4]: [f64; 4], x: f64, y: f64) -> (f64, f64) {
        let r = (x * x + y * y).sqrt();
        let theta = r.atan();
        let theta_d = theta
            * (1.0
                + k1 * theta.powi(2)
                + k2 * theta.powi(4)
                + k3 * theta.powi(6)
                + k4 * theta.powi(8));
        (theta_d / r * x, theta_d / r * y)
    }

    /// COLMAP's OPENCV model through `ns-process-data`: the stored images are distorted; the
    /// loaded frames are pinhole views whose rays pass through the imaged point, at the stored
    /// size and resized, with the top-level coefficients and a frame's own.
    #[test]
    fn opencv_distortion_is_undone_so_rays_pass_through_the_point() {
        let dir = tempfile::tempdir().unwrap();
        let top = [-0.35, 0.1, 0.02, 0.002, -0.003]; // k1, k2, k3, p1, p2
        let frame_1 = [-0.5, 0.1, 0.02, -0.004, -0.003]; // its own k1 and p1
        let json = lens_scene(
            dir.path(),
            serde_json::json!({"camera_model": "OPENCV",
                "k1": top[0], "k2": top[1], "k3": top[2], "p1": top[3], "p2": top[4]}),
            [
                serde_json::json!({}),
                serde_json::json!({"k1": frame_1[0], "p1": frame_1[3]}),
            ],
            |i, x, y| opencv_distort([top, frame_1][i], x, y),
        );
        let data = load_lens_scene(dir.path(), &json, OutputSize::Original).unwrap();
        assert_rays_hit_the_point(&data);
        assert_rays_hit_the_point(
            &load_lens_scene(dir.path(), &json, OutputSize::MaxSide(64)).unwrap(),
        );
        // Without `camera_model`, coefficients mean the same model (as in nerfstudio).
        let mut no_model = json.clone();
        no_model.as_object_mut().unwrap().remove("camera_model");
        let same = load_lens_scene(dir.path(), &no_model, OutputSize::Original).unwrap();
        assert_eq!(same.frames[1].pixels, data.frames[1].pixels);
    }

    #[test]
    fn fisheye_distortion_is_undone_so_rays_pass_through_the_point() {
        let dir = tempfile::tempdir().unwrap();
        let top = [-0.05, 0.02, -0.01, 0.004];
        let frame_1 = [-0.05, -0.03, -0.01, 0.004]; // its own k2
        let json = lens_scene(
            dir.path(),
            serde_json::json!({"camera_model": "OPENCV_FISHEYE",
                "k1": top[0], "k2": top[1], "k3": top[2], "k4": top[3]}),
            [serde_json::json!({}), serde_json::json!({"k2": frame_1[1]})],
            |i, x, y| fisheye_distort([top, frame_1][i], x, y),
        );
        assert_rays_hit_the_point(
            &load_lens_scene(dir.path(), &json, OutputSize::Original).unwrap(),
        );
    }

    /// Models without a pinhole view, and coefficients out of any lens's range or outside
    /// the model, are refused naming the file and the field.
    #[test]
    fn unsupported_lens_models_and_coefficients_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let json = lens_scene(
            dir.path(),
            serde_json::json!({"camera_model": "OPENCV", "k1": -0.35, "k2": 0.1}),
            [serde_json::json!({}), serde_json::json!({})],
            |_, x, y| opencv_distort([-0.35, 0.1, 0.0, 0.0, 0.0], x, y),
        );
        let file = dir.path().join("transforms.json").display().to_string();
        let refused = |change: &dyn Fn(&mut Value), expected: &str| {
            let mut changed = json.clone();
            change(&mut changed);
            let message = error_of(load_lens_scene(dir.path(), &changed, OutputSize::Original));
            assert!(
                message.starts_with(&file) && message.contains(expected),
                "{message}"
            );
        };
        for model in [
            "EQUIRECTANGULAR",
            "FULL_OPENCV",
            "OMNIDIRECTIONALSTEREO_L",
            "fisheye",
        ] {
            refused(
                &|json| json["camera_model"] = serde_json::json!(model),
                &format!(
                    "field `camera_model`: `{model}` is not a pinhole or fisheye camera model"
                ),
            );
        }
        refused(
            &|json| json["k1"] = serde_json::json!(-50),
            "field `k1`: -50 is not a lens distortion coefficient (|k1| <= 10)",
        );
        refused(
            &|json| json["frames"][1]["p2"] = serde_json::json!(3.0),
            "field `frames[1].p2`: 3 is not a lens distortion coefficient (|p2| <= 1)",
        );
        refused(
            &|json| json["k3"] = serde_json::json!("0.1"),
            "field `k3`: expected a number",
        );
        refused(
            &|json| json["k4"] = serde_json::json!(0.01),
            "field `k4`: k4 = 0.01 is not a coefficient of the OPENCV model",
        );
        refused(
            &|json| {
                json["camera_model"] = serde_json::json!("OPENCV_FISHEYE");
                json["frames"][0]["p1"] = serde_json::json!(0.001);
            },
            "field `frames[0].p1`: p1 = 0.001 is not a coefficient of the OPENCV_FISHEYE model",
        );
    }
}
