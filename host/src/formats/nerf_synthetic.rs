//! NeRF-synthetic (Blender) scenes: `transforms_{train,val,test}.json` with `camera_angle_x`
//! and per-frame `file_path` (no extension, `.png` implied) and `transform_matrix`, RGBA
//! images composited on the background (see [`super::transforms`]).

use super::json::JsonFile;
use super::transforms::{FrameJob, Intrinsics, LoadOptions, decode_all, decode_frame, output_size};
use crate::dataset::{Dataset, Frame, SceneBoxOrigin};
use crate::error::{HostError, Result};
use std::path::{Path, PathBuf};

/// Lower corner of K-Planes' scene box for NeRF-synthetic scenes (world units): every object
/// fits in [-1.5, 1.5]^3.
pub const NERF_SYNTHETIC_SCENE_MIN: [f32; 3] = [-1.5; 3];
/// Upper corner of K-Planes' scene box for NeRF-synthetic scenes (world units).
pub const NERF_SYNTHETIC_SCENE_MAX: [f32; 3] = [1.5; 3];

/// The three splits of a NeRF-synthetic scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SyntheticSplit {
    /// The training views (`transforms_train.json`).
    Train,
    /// The validation views (`transforms_val.json`).
    Val,
    /// The test views (`transforms_test.json`).
    Test,
}

impl SyntheticSplit {
    /// The split's transforms file name inside a scene folder.
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
    dataset_of(SyntheticReader::open(json_path, options)?, options)
}

/// [`load_nerf_synthetic_transforms`] on the text of the file `json_path` names (the images
/// are still read from the folder it names).
pub fn parse_nerf_synthetic_transforms(
    json_path: &Path,
    text: &str,
    options: &LoadOptions,
) -> Result<Dataset> {
    let json = JsonFile::parse(json_path, text)?;
    dataset_of(SyntheticReader::from_json(json, options)?, options)
}

fn dataset_of(reader: SyntheticReader, options: &LoadOptions) -> Result<Dataset> {
    let json_path = reader.json_path.as_path();
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
        scene_box: SceneBoxOrigin::Data("the NeRF-synthetic convention".into()),
        background: options.background,
        target_centred: false,
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
    /// Open and check the `transforms_*.json` at `json_path`; images are read later, per frame.
    pub fn open(json_path: &Path, options: &LoadOptions) -> Result<SyntheticReader> {
        SyntheticReader::from_json(JsonFile::read(json_path)?, options)
    }

    fn from_json(json: JsonFile, options: &LoadOptions) -> Result<SyntheticReader> {
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
            let (mut name, pose) = json.frame_file_and_pose(frame, index)?;
            if Path::new(&name).extension().is_none() {
                name.push_str(".png");
            }
            jobs.push(FrameJob {
                image: json.resolve(&name),
                name,
                mask: None,
                pose,
                declared_size: None,
                lens: None,
            });
        }
        let first_size = jobs
            .first()
            .and_then(|job| image::image_dimensions(&job.image).ok());
        Ok(SyntheticReader {
            json_path: json.path,
            jobs,
            angle_x,
            angle_y,
            options: *options,
            first_size,
        })
    }

    /// The number of frames the file lists.
    pub fn len(&self) -> usize {
        self.jobs.len()
    }

    /// Whether the file lists no frame.
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
        // libm, not the platform's math library: the same focal length on every target.
        let fx = 0.5 * w / libm::tan(0.5 * self.angle_x);
        let fy = self.angle_y.map_or(fx, |a| 0.5 * h / libm::tan(0.5 * a));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::transforms::OutputSize;
    use crate::formats::transforms::fixtures::*;
    use glam::Vec3;
    use image::RgbaImage;
    use serde_json::Value;
    use std::time::Instant;

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
        // The alpha already removed the background: applying the mask keeps the faint edge.
        assert!(frame.alpha_composited);
        let mut masked = frame.clone();
        assert!(!masked.apply_mask(options.background));
        assert_eq!(masked.pixels, frame.pixels);
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
