//! nerfstudio captures: `transforms.json` with pinhole intrinsics (`fl_x, fl_y, cx, cy, w, h`)
//! at the top level or per frame, `file_path` relative to the JSON's folder, optional
//! `mask_path`, optional scene box (`aabb` or `scene_box`). Frames are read as in
//! [`super::transforms`].

use super::json::JsonFile;
use super::transforms::{FrameJob, Intrinsics, LoadOptions, decode_all};
use crate::dataset::{Dataset, SceneBoxOrigin};
use crate::error::{HostError, Result};
use glam::{DMat3, DVec3, Vec3};
use std::path::Path;

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
    dataset_of(JsonFile::read(&json_path)?, options)
}

/// [`load_nerfstudio`] on the text of the `transforms.json` file `json_path` names (the
/// images are still read from the folder it names).
pub fn parse_nerfstudio(json_path: &Path, text: &str, options: &LoadOptions) -> Result<Dataset> {
    dataset_of(JsonFile::parse(json_path, text)?, options)
}

fn dataset_of(json: JsonFile, options: &LoadOptions) -> Result<Dataset> {
    let json_path = json.path.clone();
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
}
