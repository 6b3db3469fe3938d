//! SPEED+ / SHIRT datasets: the label format (read and written), the camera file, the
//! simulator's truth file, and a loader that turns any of these layouts into a [`Dataset`].
//!
//! Layouts the loader accepts (`path` is a label file or a folder):
//! - simulator output: `labels.json`, `camera.json`, `images/`, `masks/`, `truth.json`;
//! - SPEED+: `synthetic/train.json` + `synthetic/images/`, `lightbox/test.json` +
//!   `lightbox/images/`, `sunlamp/test.json` + `sunlamp/images/`, `camera.json` at the root;
//! - SHIRT: `roeN/roeN.json` + `roeN/{synthetic,lightbox}/images/` (pick the domain in
//!   [`LoadOptions::domain`]), `camera.json` at the root.
//!
//! Labels: `p_cam = R(q) p_body + r` with a scalar-first `q_vbs2tango[_true]` and
//! `r_Vo2To_vbs[_true]` in metres. The world frame of the loaded dataset is the target body frame.

pub use super::camera::SpeedCamera;
use super::json::{JsonFile, write_json};
use super::resample::Resampler;
use crate::dataset::{Dataset, Frame, SceneBoxOrigin};
use crate::error::{HostError, Result};
use orbit_nerf_core::glam::{Quat, Vec3};
use orbit_nerf_core::{Camera, Pose};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// How far a label quaternion's norm may stray from 1 before it is rejected as non-unit.
const UNIT_QUATERNION_TOLERANCE: f64 = 1e-3;

/// One pose label in SPEED+ form.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Label {
    /// The image the label belongs to, relative to the set's image folder.
    pub filename: String,
    /// Scalar-first quaternion of the rotation from the target body frame to the camera frame.
    #[serde(rename = "q_vbs2tango_true")]
    pub q_vbs2tango: [f64; 4],
    /// Target origin in camera axes (x right, y down, z forward), metres.
    #[serde(rename = "r_Vo2To_vbs_true")]
    pub r_vo2to_vbs: [f64; 3],
}

impl Label {
    /// Label for a body-to-camera rotation `q` and a target position `r` in camera axes.
    pub fn new(filename: String, q: Quat, r: Vec3) -> Label {
        // SPEED+ quaternions are scalar-first; keep the scalar part non-negative so one rotation
        // has one label.
        let q = if q.w < 0.0 { -q } else { q };
        Label {
            filename,
            q_vbs2tango: [q.w, q.x, q.y, q.z].map(f64::from),
            r_vo2to_vbs: [r.x, r.y, r.z].map(f64::from),
        }
    }

    /// The rotation body -> camera (normalised).
    pub fn rotation(&self) -> Quat {
        let [w, x, y, z] = self.q_vbs2tango.map(|v| v as f32);
        Quat::from_xyzw(x, y, z, w).normalize()
    }

    /// The target's origin in camera axes, metres (`r_Vo2To_vbs`).
    pub fn translation(&self) -> Vec3 {
        let [x, y, z] = self.r_vo2to_vbs.map(|v| v as f32);
        Vec3::new(x, y, z)
    }

    /// The camera-to-body pose this label describes.
    pub fn pose(&self) -> Option<Pose> {
        let [w, x, y, z] = self.q_vbs2tango.map(|v| v as f32);
        Pose::from_world_to_camera(Quat::from_xyzw(x, y, z, w), self.translation())
    }
}

/// Read a SPEED+ label file (`q_vbs2tango_true` or `q_vbs2tango`, `r_Vo2To_vbs_true` or
/// `r_Vo2To_vbs`). Rejects zero, non-unit and non-finite quaternions and non-finite positions.
pub fn read_labels(path: &Path) -> Result<Vec<Label>> {
    labels_of(&JsonFile::read_any(path)?)
}

/// [`read_labels`] on the text of the file `path` names.
///
/// ```
/// use orbit_nerf_host::formats::speedplus::parse_labels;
/// use std::path::Path;
///
/// let path = Path::new("train.json");
/// let text = r#"[{"filename": "img000001.jpg",
///     "q_vbs2tango_true": [1, 0, 0, 0], "r_Vo2To_vbs_true": [0.1, -0.2, 8.0]}]"#;
/// let labels = parse_labels(path, text).unwrap();
/// assert_eq!(labels[0].filename, "img000001.jpg");
/// assert_eq!(labels[0].translation().z, 8.0);
///
/// // A quaternion of norm 2 is no rotation.
/// let scaled = text.replace("[1, 0, 0, 0]", "[2, 0, 0, 0]");
/// assert!(parse_labels(path, &scaled).is_err());
/// ```
pub fn parse_labels(path: &Path, text: &str) -> Result<Vec<Label>> {
    labels_of(&JsonFile::parse_any(path, text)?)
}

fn labels_of(json: &JsonFile) -> Result<Vec<Label>> {
    check_label_names(json)?;
    label_entries(json)?
        .iter()
        .enumerate()
        .map(|(index, entry)| parse_label_entry(json, &format!("[{index}]."), entry))
        .collect()
}

/// Read a file holding one SPEED+ label (a JSON object with the keys of a label file's entry).
pub fn read_label(path: &Path) -> Result<Label> {
    let json = JsonFile::read_any(path)?;
    parse_label_entry(&json, "", &json.root)
}

/// [`read_label`] on the text of the file `path` names.
pub fn parse_label(path: &Path, text: &str) -> Result<Label> {
    let json = JsonFile::parse_any(path, text)?;
    parse_label_entry(&json, "", &json.root)
}

/// Write labels as a SPEED+ label file.
pub fn write_labels(path: &Path, labels: &[Label]) -> Result<()> {
    write_json(path, labels)
}

/// A label file's entries name each image once.
fn check_label_names(json: &JsonFile) -> Result<()> {
    let entries = label_entries(json)?;
    let names = entries
        .iter()
        .map(|e| e.get("filename").and_then(Value::as_str));
    check_unique_filenames(&json.path, "", names)
}

/// The entries of a label file (a list).
fn label_entries(json: &JsonFile) -> Result<&Vec<Value>> {
    json.root
        .as_array()
        .ok_or_else(|| HostError::invalid(&json.path, "expected a JSON list of labels"))
}

/// Check one label entry; its fields are named `{prefix}{key}` in errors.
fn parse_label_entry(json: &JsonFile, prefix: &str, entry: &Value) -> Result<Label> {
    let path = &json.path;
    let field = |name: &str| format!("{prefix}{name}");
    let filename = entry
        .get("filename")
        .and_then(Value::as_str)
        .ok_or_else(|| HostError::field(path, field("filename"), "missing or not a string"))?;
    let (q_key, q_value) = first_key(entry, &["q_vbs2tango_true", "q_vbs2tango"])
        .ok_or_else(|| HostError::field(path, field("q_vbs2tango_true"), "missing"))?;
    let q: [f64; 4] = json.numbers_exact(q_value, &field(q_key))?;
    check_rotation(path, &field(q_key), &q)?;
    let (r_key, r_value) = first_key(entry, &["r_Vo2To_vbs_true", "r_Vo2To_vbs"])
        .ok_or_else(|| HostError::field(path, field("r_Vo2To_vbs_true"), "missing"))?;
    let r: [f64; 3] = json.numbers_exact(r_value, &field(r_key))?;
    check_position(path, &field(r_key), &r)?;
    Ok(Label {
        filename: filename.to_owned(),
        q_vbs2tango: q,
        r_vo2to_vbs: r,
    })
}

/// A pose's rotation must be a unit quaternion (labels and truth alike).
fn check_rotation(path: &Path, field: &str, q: &[f64; 4]) -> Result<()> {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-9 {
        return Err(HostError::field(
            path,
            field,
            "zero or non-finite quaternion",
        ));
    }
    if (norm - 1.0).abs() > UNIT_QUATERNION_TOLERANCE {
        return Err(HostError::field(
            path,
            field,
            format!("not a unit quaternion (norm {norm})"),
        ));
    }
    Ok(())
}

/// Farthest target a label may place, metres: ten times geostationary altitude, far past
/// any camera that resolves a spacecraft.
const MAX_RANGE_M: f64 = 4e8;
/// Nearest: a camera closer than this to the target's origin sits inside any spacecraft.
const MIN_RANGE_M: f64 = 1e-3;

/// A pose's position (the target's origin in camera axes, metres) must be a place a camera
/// can be: finite, off the target's origin and within [`MAX_RANGE_M`].
fn check_position(path: &Path, field: &str, r: &[f64; 3]) -> Result<()> {
    let range = r.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !range.is_finite() || range > MAX_RANGE_M {
        return Err(HostError::field(
            path,
            field,
            format!("the target is {range:e} m from the camera, beyond {MAX_RANGE_M:e} m"),
        ));
    }
    if range < MIN_RANGE_M {
        return Err(HostError::field(
            path,
            field,
            format!("the camera sits at the target's origin ({range:e} m from it)"),
        ));
    }
    Ok(())
}

/// One image, one entry: refuse labels or truth that name an image twice (`prefix` names the
/// list: `frames` gives `frames[3].filename`, an empty prefix `[3].filename`).
fn check_unique_filenames<'v>(
    path: &Path,
    prefix: &str,
    names: impl Iterator<Item = Option<&'v str>>,
) -> Result<()> {
    let mut seen = std::collections::HashMap::new();
    for (index, name) in names.enumerate() {
        let Some(name) = name else { continue };
        if let Some(first) = seen.insert(name, index) {
            return Err(HostError::field(
                path,
                format!("{prefix}[{index}].filename"),
                format!(
                    "names `{name}` again (entry {first} names it first): one image, one entry"
                ),
            ));
        }
    }
    Ok(())
}

fn first_key<'a>(entry: &'a Value, keys: &[&'static str]) -> Option<(&'static str, &'a Value)> {
    keys.iter()
        .find_map(|&key| entry.get(key).map(|value| (key, value)))
}

/// What the simulator knows exactly (`truth.json`): the true pose of every frame, the sun
/// direction and exposure it was rendered with, and the box that holds the target.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    /// Lower corner of the box holding the target, body frame, metres (with a margin).
    pub target_box_min: [f32; 3],
    /// Upper corner of the box holding the target, body frame, metres.
    pub target_box_max: [f32; 3],
    /// One entry per rendered image, in any order (paired with labels by filename).
    pub frames: Vec<TruthFrame>,
}

/// What the simulator knows exactly about one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthFrame {
    /// The image the entry belongs to, as named in the label file.
    pub filename: String,
    /// Exact body-to-camera rotation, scalar-first unit quaternion.
    pub q_vbs2tango_true: [f64; 4],
    /// Exact target origin in camera axes (x right, y down, z forward), metres.
    #[serde(rename = "r_Vo2To_vbs_true")]
    pub r_vo2to_vbs_true: [f64; 3],
    /// Unit vector from the target towards the sun, body frame.
    pub sun_direction_body: [f64; 3],
    /// Exposure multiplier the frame was rendered with (1 = nominal).
    pub exposure: f64,
}

impl TruthFrame {
    /// The exact pose as a label (same conventions as `labels.json`).
    pub fn label(&self) -> Label {
        Label {
            filename: self.filename.clone(),
            q_vbs2tango: self.q_vbs2tango_true,
            r_vo2to_vbs: self.r_vo2to_vbs_true,
        }
    }
}

impl Truth {
    /// Read and check the truth file at `path`: unique filenames, unit quaternions, positions
    /// a camera can be at, and a finite box with min below max.
    pub fn read(path: &Path) -> Result<Truth> {
        let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
        Truth::parse(path, &text)
    }

    /// [`Truth::read`] on the text of the file `path` names.
    pub fn parse(path: &Path, text: &str) -> Result<Truth> {
        let truth: Truth = serde_json::from_str(text)
            .map_err(|e| HostError::invalid(path, format!("malformed truth file: {e}")))?;
        // A truth file is checked as strictly as labels.
        check_unique_filenames(
            path,
            "frames",
            truth.frames.iter().map(|f| Some(f.filename.as_str())),
        )?;
        for (index, frame) in truth.frames.iter().enumerate() {
            let field = |name: &str| format!("frames[{index}].{name}");
            check_rotation(path, &field("q_vbs2tango_true"), &frame.q_vbs2tango_true)?;
            check_position(path, &field("r_Vo2To_vbs_true"), &frame.r_vo2to_vbs_true)?;
            if frame.label().pose().is_none() {
                return Err(HostError::field(
                    path,
                    field("q_vbs2tango_true"),
                    "zero or non-finite pose",
                ));
            }
        }
        let (min, max) = (truth.target_box_min, truth.target_box_max);
        if !(0..3).all(|a| min[a].is_finite() && max[a].is_finite() && min[a] < max[a]) {
            return Err(HostError::field(
                path,
                "target_box_min",
                format!(
                    "the target box {min:?} .. {max:?} is not a finite box with min below max on every axis"
                ),
            ));
        }
        Ok(truth)
    }

    /// Write the truth file to `path` (atomically, pretty-printed JSON).
    pub fn write(&self, path: &Path) -> Result<()> {
        write_json(path, self)
    }

    /// The exact pose of every label, paired by filename (a truth file may list its frames in
    /// any order, and more frames than the labels); `path` names the truth file in errors.
    pub fn poses_for(&self, path: &Path, labels: &[Label]) -> Result<Vec<Pose>> {
        let by_name: std::collections::HashMap<&str, &TruthFrame> = self
            .frames
            .iter()
            .map(|frame| (frame.filename.as_str(), frame))
            .collect();
        labels
            .iter()
            .map(|label| {
                let frame = by_name.get(label.filename.as_str()).ok_or_else(|| {
                    HostError::field(
                        path,
                        "frames",
                        format!("no frame named `{}` (a label names it)", label.filename),
                    )
                })?;
                // Checked when the file was read.
                frame.label().pose().ok_or_else(|| {
                    HostError::field(
                        path,
                        "frames",
                        format!("`{}`: not a valid pose", label.filename),
                    )
                })
            })
            .collect()
    }
}

/// Choices made while loading.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Longer side to resample the images to (the aspect ratio kept, never upsampled);
    /// `None` keeps the stored size. Resampling area-averages, so downsizing does not alias.
    pub max_side: Option<u32>,
    /// SHIRT image domain inside a `roeN` folder: `synthetic` (the default) or `lightbox`.
    pub domain: Option<String>,
}

/// A loaded SPEED+ / SHIRT set.
#[derive(Clone, Debug)]
pub struct SpeedPlusSet {
    /// Frames with pinhole intrinsics (images are undistorted when `camera.json` has
    /// distortion), pose labels, masks when the folder has them, RGB8 pixels (grayscale
    /// expanded to r = g = b), black background.
    pub dataset: Dataset,
    /// The labels as read, in frame order.
    pub labels: Vec<Label>,
    /// The simulator's exact poses, sun directions and exposures, when `truth.json` is present.
    pub truth: Option<Truth>,
    /// The camera file as read (the stored image size, before any resampling).
    pub camera: SpeedCamera,
    /// The label file the set was read from (a folder resolves to the label file in it).
    pub label_file: PathBuf,
}

impl SpeedPlusSet {
    /// The exact pose of every frame (in frame order, paired by filename), when the set has a
    /// truth file.
    pub fn true_poses(&self) -> Result<Option<Vec<Pose>>> {
        let Some(truth) = &self.truth else {
            return Ok(None);
        };
        let path = self
            .label_file
            .parent()
            .unwrap_or(Path::new("."))
            .join("truth.json");
        truth.poses_for(&path, &self.labels).map(Some)
    }
}

/// Load a SPEED+ / SHIRT / simulator set from a label file or a folder (see the module docs).
pub fn load(path: &Path, options: &LoadOptions) -> Result<SpeedPlusSet> {
    let reader = SpeedPlusReader::open(path, options)?;
    let labels = (0..reader.len())
        .map(|index| reader.label(index))
        .collect::<Result<Vec<_>>>()?;
    let frames = (0..reader.len())
        .into_par_iter()
        .map(|index| reader.frame(index))
        .collect::<Result<Vec<_>>>()?;
    let ((scene_min, scene_max), scene_box) = match reader.scene_box() {
        Some(found) => (
            found,
            SceneBoxOrigin::Data(format!(
                "{} (exact)",
                reader.label_file.with_file_name("truth.json").display()
            )),
        ),
        None => (([0.0; 3], [0.0; 3]), SceneBoxOrigin::Unknown),
    };
    Ok(SpeedPlusSet {
        dataset: Dataset {
            source: path.to_path_buf(),
            frames,
            scene_min,
            scene_max,
            scene_box,
            background: [0.0; 3],
            target_centred: true,
        },
        labels,
        truth: reader.truth,
        camera: reader.decoder.camera,
        label_file: reader.label_file,
    })
}

/// A SPEED+ / SHIRT / simulator set opened for reading one frame at a time: the label file,
/// camera and truth are read when it opens, a frame's label is checked and its image decoded
/// only when that frame is asked for (streaming never holds the whole set).
pub struct SpeedPlusReader {
    labels: JsonFile,
    /// The simulator's `truth.json` beside the label file, when there is one.
    pub truth: Option<Truth>,
    /// The label file the set is read from (a folder resolves to the label file in it).
    pub label_file: PathBuf,
    images_dir: PathBuf,
    masks_dir: Option<PathBuf>,
    /// Turns the set's stored images into frames (size check, resampling, undistortion).
    pub decoder: FrameDecoder,
}

impl SpeedPlusReader {
    /// Open a label file or folder: find and read the label file, `camera.json` (here or up
    /// to two folders up), the image folder and `truth.json`; no image is decoded yet.
    pub fn open(path: &Path, options: &LoadOptions) -> Result<SpeedPlusReader> {
        let label_file = find_label_file(path)?;
        let label_dir = label_file.parent().unwrap_or(Path::new(".")).to_path_buf();
        let camera_file = find_upwards(&label_dir, "camera.json").ok_or_else(|| {
            HostError::invalid(
                label_dir.join("camera.json"),
                "camera file not found here or in the two parent folders",
            )
        })?;
        let camera = SpeedCamera::read(&camera_file)?;
        let labels = JsonFile::read_any(&label_file)?;
        check_label_names(&labels)?;
        let images_dir = find_images_dir(&label_dir, options)?;
        let masks_dir = Some(label_dir.join("masks")).filter(|dir| dir.is_dir());
        let truth_file = label_dir.join("truth.json");
        let truth = if truth_file.is_file() {
            Some(Truth::read(&truth_file)?)
        } else {
            None
        };
        Ok(SpeedPlusReader {
            labels,
            truth,
            decoder: FrameDecoder::new(camera, options.max_side),
            label_file,
            images_dir,
            masks_dir,
        })
    }

    /// Frames (label entries) in the set.
    pub fn len(&self) -> usize {
        self.entries().len()
    }

    /// Whether the label file lists no frame.
    pub fn is_empty(&self) -> bool {
        self.entries().is_empty()
    }

    /// The label entries (checked to be a list when the reader opened).
    fn entries(&self) -> &[Value] {
        self.labels.root.as_array().map_or(&[], Vec::as_slice)
    }

    /// The scene box of the target from `truth.json`; `None` without one (the target is
    /// unknown: its box must be stated or found from the frames).
    pub fn scene_box(&self) -> Option<([f32; 3], [f32; 3])> {
        self.truth
            .as_ref()
            .map(|truth| (truth.target_box_min, truth.target_box_max))
    }

    /// The checked label of frame `index`.
    pub fn label(&self, index: usize) -> Result<Label> {
        let entry = self.entries().get(index).ok_or_else(|| {
            HostError::invalid(&self.label_file, format!("no label number {index}"))
        })?;
        parse_label_entry(&self.labels, &format!("[{index}]."), entry)
    }

    /// Frame `index`: label checked, image (and mask) decoded and resampled.
    pub fn frame(&self, index: usize) -> Result<Frame> {
        let label = self.label(index)?;
        let pose = label.pose().ok_or_else(|| {
            HostError::field(
                &self.label_file,
                format!("[{index}].q_vbs2tango_true"),
                "not a valid pose",
            )
        })?;
        let image_path = self.images_dir.join(&label.filename);
        let mask_path = self
            .masks_dir
            .as_ref()
            .map(|dir| dir.join(Path::new(&label.filename).with_extension("png")));
        self.decoder.decode(
            label.filename.clone(),
            pose,
            &image_path,
            mask_path.as_deref(),
        )
    }
}

/// Turns stored images of one SPEED+ camera into frames: checks their size, resamples them
/// to the output size and undistorts them to a pinhole camera.
pub struct FrameDecoder {
    /// The camera file as read (the stored image size, before any resampling).
    pub camera: SpeedCamera,
    resampler: Resampler,
}

impl FrameDecoder {
    /// `max_side`: the output's longer side (the aspect ratio kept, never upsampled); `None`
    /// keeps the size.
    pub fn new(camera: SpeedCamera, max_side: Option<u32>) -> FrameDecoder {
        FrameDecoder {
            resampler: Resampler::new(camera.pinhole(), camera.distortion(), max_side),
            camera,
        }
    }

    /// The pinhole camera of the frames as they are produced.
    pub fn output_camera(&self) -> Camera {
        self.resampler.output
    }

    /// Decode an image (and mask) into a frame at `pose`.
    pub fn decode(
        &self,
        name: String,
        pose: Pose,
        image_path: &Path,
        mask_path: Option<&Path>,
    ) -> Result<Frame> {
        let bytes = std::fs::read(image_path).map_err(|e| HostError::io(image_path, e))?;
        self.decode_bytes(name, pose, (image_path, &bytes), mask_path)
    }

    /// [`FrameDecoder::decode`] of an image file's bytes (`image_path` names it in errors).
    pub fn decode_bytes(
        &self,
        name: String,
        pose: Pose,
        (image_path, bytes): (&Path, &[u8]),
        mask_path: Option<&Path>,
    ) -> Result<Frame> {
        let image = image_from_bytes(image_path, bytes, &self.camera)?.to_rgb8();
        let mask = match mask_path {
            Some(path) => Some((path, read_image(path, &self.camera)?.to_luma8())),
            None => None,
        };
        let mask = mask.as_ref().map(|(path, mask)| (*path, mask));
        self.from_images(name, pose, (image_path, &image), mask)
    }

    /// A frame at `pose` from decoded images of this camera's size (each with the path to
    /// name in messages).
    pub fn from_images(
        &self,
        name: String,
        pose: Pose,
        (image_path, image): (&Path, &image::RgbImage),
        mask: Option<(&Path, &image::GrayImage)>,
    ) -> Result<Frame> {
        let (w, h) = (self.camera.width, self.camera.height);
        for (path, size) in [(image_path, image.dimensions())]
            .into_iter()
            .chain(mask.map(|(path, mask)| (path, mask.dimensions())))
        {
            if size != (w, h) {
                return Err(HostError::invalid(
                    path,
                    format!("image is {}x{} but the camera is {w}x{h}", size.0, size.1),
                ));
            }
        }
        let resampler = &self.resampler;
        let pixels = resampler.rgb(image_path, image)?;
        let mask = match mask {
            Some((path, mask)) => Some(resampler.mask(path, mask)?),
            None => None,
        };
        Ok(Frame {
            name,
            camera: resampler.output,
            pose,
            pixels,
            mask,
            alpha_composited: false,
        })
    }
}

fn find_label_file(path: &Path) -> Result<PathBuf> {
    if path.is_file() {
        return Ok(path.to_path_buf());
    }
    if !path.is_dir() {
        return Err(HostError::io(
            path,
            std::io::Error::from(std::io::ErrorKind::NotFound),
        ));
    }
    let folder_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let candidates = [
        "labels.json".to_owned(),
        format!("{folder_name}.json"),
        "train.json".into(),
        "test.json".into(),
    ];
    candidates
        .iter()
        .map(|name| path.join(name))
        .find(|candidate| candidate.is_file())
        .ok_or_else(|| {
            HostError::invalid(
                path,
                format!("no label file here (looked for {})", candidates.join(", ")),
            )
        })
}

fn find_upwards(start: &Path, name: &str) -> Option<PathBuf> {
    start
        .ancestors()
        .take(3)
        .map(|dir| dir.join(name))
        .find(|candidate| candidate.is_file())
}

fn find_images_dir(label_dir: &Path, options: &LoadOptions) -> Result<PathBuf> {
    let domain = options.domain.as_deref().unwrap_or("synthetic");
    let candidates = [
        label_dir.join("images"),
        label_dir.join(domain).join("images"),
    ];
    candidates
        .iter()
        .find(|dir| dir.is_dir())
        .cloned()
        .ok_or_else(|| {
            HostError::invalid(
                label_dir,
                format!("no image folder (looked for images/ and {domain}/images/)"),
            )
        })
}

fn read_image(path: &Path, camera: &SpeedCamera) -> Result<image::DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| HostError::io(path, e))?;
    image_from_bytes(path, &bytes, camera)
}

/// Decode the bytes of the image file `path` names and check its size against `camera`'s.
fn image_from_bytes(
    path: &Path,
    bytes: &[u8],
    camera: &SpeedCamera,
) -> Result<image::DynamicImage> {
    // The format and size from the header, before decoding: a file that is not what its
    // name says, or a header of another size, is named as such (not as the decoder's limit).
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| HostError::io(path, e))?;
    match reader.format() {
        Some(image::ImageFormat::Png | image::ImageFormat::Jpeg) => {}
        Some(other) => {
            return Err(HostError::invalid(
                path,
                format!(
                    "is a {} file; SPEED+ images are PNG or JPEG",
                    other
                        .extensions_str()
                        .first()
                        .map_or(format!("{other:?}"), |e| e.to_uppercase())
                ),
            ));
        }
        None => {
            return Err(HostError::invalid(
                path,
                "is neither a PNG nor a JPEG file (unknown header)",
            ));
        }
    }
    let image = reader
        .decode()
        .map_err(|e| HostError::invalid(path, format!("cannot decode image: {e}")))?;
    if (image.width(), image.height()) != (camera.width, camera.height) {
        return Err(HostError::invalid(
            path,
            format!(
                "image is {}x{} but camera.json says {}x{}",
                image.width(),
                image.height(),
                camera.width,
                camera.height
            ),
        ));
    }
    Ok(image)
}
#[cfg(test)]
mod tests {
    use super::*;

    /// A small camera with the real SPEED+ distortion, 1920x1200 scaled to 64x40.
    fn small_camera(distortion: bool) -> SpeedCamera {
        let scale = 64.0 / 1920.0;
        SpeedCamera {
            width: 64,
            height: 40,
            pixel_pitch: Some([5.86e-6 / scale; 2]),
            camera_matrix: [
                [2988.58 * scale, 0.0, 32.0],
                [0.0, 2988.34 * scale, 20.0],
                [0.0, 0.0, 1.0],
            ],
            dist_coeffs: if distortion {
                [-0.2238, 0.5141, -0.000665, -0.000214, -0.1312]
            } else {
                [0.0; 5]
            },
        }
    }

    fn write_gray_jpeg(path: &Path, value: u8) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let image =
            image::GrayImage::from_fn(64, 40, |x, _| image::Luma([value.saturating_add(x as u8)]));
        image
            .save_with_format(path, image::ImageFormat::Jpeg)
            .unwrap();
    }

    fn label_json(key_q: &str, key_r: &str, q: [f64; 4], r: [f64; 3]) -> String {
        format!(r#"[{{"filename": "img000001.jpg", "{key_q}": {q:?}, "{key_r}": {r:?}}}]"#)
    }

    const Q: [f64; 4] = [0.5, 0.5, -0.5, 0.5];
    const R: [f64; 3] = [0.1, -0.2, 6.0];

    #[test]
    fn real_speedplus_and_shirt_layouts_load_with_both_quaternion_keys() {
        let root = tempfile::tempdir().unwrap();
        let root = root.path();
        small_camera(false)
            .write(&root.join("camera.json"))
            .unwrap();
        // SPEED (2019) keys in synthetic/train.json, SPEED+ keys in lightbox/test.json.
        std::fs::create_dir_all(root.join("synthetic")).unwrap();
        std::fs::write(
            root.join("synthetic/train.json"),
            label_json("q_vbs2tango", "r_Vo2To_vbs_true", Q, R),
        )
        .unwrap();
        write_gray_jpeg(&root.join("synthetic/images/img000001.jpg"), 40);
        std::fs::create_dir_all(root.join("lightbox")).unwrap();
        std::fs::write(
            root.join("lightbox/test.json"),
            label_json("q_vbs2tango_true", "r_Vo2To_vbs_true", Q, R),
        )
        .unwrap();
        write_gray_jpeg(&root.join("lightbox/images/img000001.jpg"), 90);
        // SHIRT: roe2/roe2.json with one image folder per domain.
        std::fs::create_dir_all(root.join("roe2")).unwrap();
        std::fs::write(
            root.join("roe2/roe2.json"),
            label_json("q_vbs2tango_true", "r_Vo2To_vbs", Q, R),
        )
        .unwrap();
        write_gray_jpeg(&root.join("roe2/synthetic/images/img000001.jpg"), 10);
        write_gray_jpeg(&root.join("roe2/lightbox/images/img000001.jpg"), 150);

        let expected_pose = Label {
            filename: "img000001.jpg".into(),
            q_vbs2tango: Q,
            r_vo2to_vbs: R,
        }
        .pose()
        .unwrap();
        let cases = [
            (root.join("synthetic/train.json"), None, 40),
            (root.join("synthetic"), None, 40),
            (root.join("lightbox"), None, 90),
            (root.join("roe2"), None, 10),
            (root.join("roe2"), Some("lightbox".to_owned()), 150),
        ];
        for (path, domain, first_value) in cases {
            let set = load(
                &path,
                &LoadOptions {
                    max_side: None,
                    domain,
                },
            )
            .unwrap();
            let frame = &set.dataset.frames[0];
            assert_eq!(frame.pose, expected_pose, "{}", path.display());
            assert_eq!((frame.camera.width, frame.camera.height), (64, 40));
            assert!(
                frame
                    .pixels
                    .chunks_exact(3)
                    .all(|p| p[0] == p[1] && p[1] == p[2]),
                "gray expanded to RGB"
            );
            assert!(
                (frame.pixels[0] as i32 - first_value).abs() <= 3,
                "{} first pixel {}",
                path.display(),
                frame.pixels[0]
            );
            assert!(frame.mask.is_none() && set.truth.is_none());
            assert_eq!(set.dataset.scene_box, SceneBoxOrigin::Unknown);
        }
    }

    /// The SPEED+ devkit camera (the copy built into the presets).
    const REFERENCE_CAMERA: &str = include_str!("../../../scenes/speedplus-camera.json");

    /// The reference camera rewritten with `edit` (a JSON object), read back.
    fn camera_layout(
        edit: impl FnOnce(&mut serde_json::Map<String, Value>),
    ) -> Result<SpeedCamera> {
        let mut value: Value = serde_json::from_str(REFERENCE_CAMERA).unwrap();
        edit(value.as_object_mut().unwrap());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("camera.json");
        std::fs::write(&path, value.to_string()).unwrap();
        SpeedCamera::read(&path)
    }

    fn drop_keys(map: &mut serde_json::Map<String, Value>, keys: &[&str]) {
        for key in keys {
            map.remove(*key).unwrap();
        }
    }

    #[test]
    fn the_three_camera_layouts_load_to_the_same_camera() {
        let reference = camera_layout(|_| {}).unwrap();
        let k = reference.camera_matrix;
        assert_eq!((reference.width, reference.height), (1920, 1200));
        assert!((k[0][0] - 0.017513075965995915 / 5.86e-6).abs() < 1e-6);
        assert_eq!(reference.pixel_pitch, Some([5.86e-6; 2]));
        let matrix_alone =
            camera_layout(|m| drop_keys(m, &["ppx", "ppy", "fx", "fy", "ccx", "ccy"]));
        let pixels = camera_layout(|m| {
            drop_keys(m, &["ppx", "ppy", "cameraMatrix"]);
            m.insert("fx".into(), k[0][0].into());
            m.insert("fy".into(), k[1][1].into());
        });
        // Metres and pitch without the matrix say the same thing.
        let metres = camera_layout(|m| drop_keys(m, &["cameraMatrix"]));
        for (name, camera) in [
            ("cameraMatrix alone", matrix_alone),
            ("pixels", pixels),
            ("metres", metres),
        ] {
            let camera = camera.unwrap_or_else(|e| panic!("{name}: {e}"));
            let (a, b) = (camera.pinhole(), reference.pinhole());
            assert_eq!(
                (a.width, a.height, a.cx, a.cy),
                (b.width, b.height, b.cx, b.cy),
                "{name}"
            );
            assert!(
                (a.fx - b.fx).abs() < 1e-3 && (a.fy - b.fy).abs() < 1e-3,
                "{name}: {a:?}"
            );
            assert_eq!(camera.distortion(), reference.distortion(), "{name}");
        }
        let undistorted = camera_layout(|m| drop_keys(m, &["distCoeffs"])).unwrap();
        assert_eq!(undistorted.pinhole(), reference.pinhole());
        assert!(undistorted.distortion().is_none());
        // Written and read back: the same camera.
        let dir = tempfile::tempdir().unwrap();
        reference.write(&dir.path().join("camera.json")).unwrap();
        assert_eq!(
            SpeedCamera::read(&dir.path().join("camera.json")).unwrap(),
            reference
        );
    }

    #[test]
    fn a_camera_file_without_intrinsics_or_with_disagreeing_ones_names_the_field() {
        type Edit = Box<dyn FnOnce(&mut serde_json::Map<String, Value>)>;
        let cases: Vec<(Edit, &str, &str)> = vec![
            (
                Box::new(|m| {
                    drop_keys(m, &["ppx", "ppy", "fx", "fy", "ccx", "ccy", "cameraMatrix"])
                }),
                "cameraMatrix",
                "missing",
            ),
            (
                Box::new(|m| {
                    m.insert("fx".into(), 0.0180.into());
                }),
                "fx",
                "cameraMatrix[0][0]",
            ),
            (
                Box::new(|m| {
                    m.insert("ccy".into(), 610.0.into());
                }),
                "ccy",
                "cameraMatrix[1][2]",
            ),
            (Box::new(|m| drop_keys(m, &["ppy"])), "ppy", "missing"),
            (
                // Metres without a pitch or a matrix cannot be pixels.
                Box::new(|m| drop_keys(m, &["ppx", "ppy", "cameraMatrix"])),
                "fx",
                "pixel pitch",
            ),
            (
                Box::new(|m| drop_keys(m, &["cameraMatrix", "ccx"])),
                "ccx",
                "missing",
            ),
            (
                Box::new(|m| {
                    m.insert("ppx".into(), (-1.0).into());
                }),
                "ppx",
                "positive",
            ),
        ];
        for (edit, expected_field, expected_reason) in cases {
            match camera_layout(edit) {
                Err(HostError::Field {
                    field,
                    reason,
                    file,
                }) => {
                    assert!(file.ends_with("camera.json"));
                    assert_eq!(field, expected_field, "{reason}");
                    assert!(reason.contains(expected_reason), "{field}: {reason}");
                }
                other => panic!("{expected_field}: {other:?}"),
            }
        }
    }

    #[test]
    fn truth_pairs_with_labels_by_filename_and_must_cover_them() {
        let label = |name: &str, angle: f32| {
            Label::new(
                name.into(),
                Quat::from_rotation_y(angle),
                Vec3::new(0.0, 0.0, 5.0),
            )
        };
        let labels = vec![
            label("a.png", 0.1),
            label("b.png", 0.7),
            label("c.png", 1.3),
        ];
        let truth_frame = |l: &Label| TruthFrame {
            filename: l.filename.clone(),
            q_vbs2tango_true: l.q_vbs2tango,
            r_vo2to_vbs_true: l.r_vo2to_vbs,
            sun_direction_body: [1.0, 0.0, 0.0],
            exposure: 1.0,
        };
        // Listed in another order, with one frame the labels do not name.
        let mut truth = Truth {
            target_box_min: [-1.0; 3],
            target_box_max: [1.0; 3],
            frames: [2, 0, 1].iter().map(|&i| truth_frame(&labels[i])).collect(),
        };
        truth.frames.push(truth_frame(&label("extra.png", 2.0)));
        let path = Path::new("set/truth.json");
        let poses = truth.poses_for(path, &labels).unwrap();
        let expected: Vec<Pose> = labels.iter().map(|l| l.pose().unwrap()).collect();
        assert_eq!(poses, expected);
        truth.frames.retain(|f| f.filename != "b.png");
        match truth.poses_for(path, &labels) {
            Err(HostError::Field {
                file,
                field,
                reason,
            }) => {
                assert_eq!((file.as_path(), field.as_str()), (path, "frames"));
                assert!(reason.contains("b.png"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn loading_resizes_and_undistorts() {
        let root = tempfile::tempdir().unwrap();
        let root = root.path();
        std::fs::write(
            root.join("labels.json"),
            label_json("q_vbs2tango_true", "r_Vo2To_vbs_true", Q, R),
        )
        .unwrap();
        write_gray_jpeg(&root.join("images/img000001.jpg"), 60);
        for distortion in [false, true] {
            small_camera(distortion)
                .write(&root.join("camera.json"))
                .unwrap();
            let set = load(
                root,
                &LoadOptions {
                    max_side: Some(32),
                    domain: None,
                },
            )
            .unwrap();
            let frame = &set.dataset.frames[0];
            assert_eq!((frame.camera.width, frame.camera.height), (32, 20));
            assert!((frame.camera.fx - 2988.58 * 64.0 / 1920.0 / 2.0).abs() < 1e-3);
            assert_eq!(frame.pixels.len(), 32 * 20 * 3);
            // The horizontal ramp survives resampling (and undistortion near the centre).
            let row = 10 * 32 * 3;
            assert!(
                frame.pixels[row + 3 * 20] > frame.pixels[row + 3 * 12],
                "distortion {distortion}"
            );
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let camera = small_camera(true);
        for (x, y) in [(0.0, 0.0), (0.2, -0.1), (-0.3, 0.25), (0.32, 0.2)] {
            let (xd, yd) = camera.distort(x, y);
            let (xu, yu) = camera.undistort(xd, yd);
            assert!(
                (xu - x).abs() < 1e-5 && (yu - y).abs() < 1e-5,
                "({x}, {y}) -> ({xu}, {yu})"
            );
        }
    }

    #[test]
    fn bad_labels_name_the_file_and_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("train.json");
        let cases = [
            (
                label_json("q_vbs2tango_true", "r_Vo2To_vbs_true", [0.0; 4], R),
                "[0].q_vbs2tango_true",
            ),
            (
                label_json("q_vbs2tango", "r_Vo2To_vbs_true", [0.9, 0.0, 0.0, 0.0], R),
                "[0].q_vbs2tango",
            ),
            (
                label_json("q_vbs2tango_true", "r_Vo2To_vbs_true", Q, [0.0; 3])
                    .replace("[0.0, 0.0, 0.0]", "[0.0, 1e999, 0.0]"),
                "",
            ),
            (
                r#"[{"filename": "a.jpg", "q_vbs2tango_true": [1, 0, 0, 0]}]"#.to_owned(),
                "[0].r_Vo2To_vbs_true",
            ),
            (
                r#"[{"q_vbs2tango_true": [1, 0, 0, 0], "r_Vo2To_vbs_true": [0, 0, 1]}]"#.to_owned(),
                "[0].filename",
            ),
        ];
        for (text, expected_field) in cases {
            std::fs::write(&path, &text).unwrap();
            match read_labels(&path) {
                Err(HostError::Field { file, field, .. }) => {
                    assert_eq!(file, path);
                    assert_eq!(field, expected_field, "{text}");
                }
                // JSON cannot hold 1e999: the parser rejects the file, naming it.
                Err(HostError::Invalid { file, reason }) if expected_field.is_empty() => {
                    assert_eq!(file, path);
                    assert!(reason.contains("malformed JSON"), "{reason}");
                }
                other => panic!("{text}: {other:?}"),
            }
        }
    }
}
