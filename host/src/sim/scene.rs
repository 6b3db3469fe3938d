//! Scene files: the TOML schema, its checks, the shipped presets and the resolution of the data
//! paths a scene names.
//!
//! Every problem with a scene file is reported once, as a [`HostError::Field`] naming the file
//! and the dotted path of the offending field (`effects.glare`, `poses.attitude`, ...).

use crate::error::{HostError, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The presets shipped in `scenes/`, embedded so that they work from any folder.
const PRESETS: [(&str, &str); 6] = [
    ("synthetic", include_str!("../../../scenes/synthetic.toml")),
    ("lightbox", include_str!("../../../scenes/lightbox.toml")),
    ("sunlamp", include_str!("../../../scenes/sunlamp.toml")),
    (
        "inspection",
        include_str!("../../../scenes/inspection.toml"),
    ),
    (
        "lightbox-test",
        include_str!("../../../scenes/lightbox-test.toml"),
    ),
    (
        "rendezvous",
        include_str!("../../../scenes/rendezvous.toml"),
    ),
];

/// Data files built into the binary (copies of the SLAB SPEED+ devkit values, see
/// `scenes/README.md`), by the name a scene gives them: the presets name them, and a user's
/// scene file may too.
const BUILTIN_DATA: [(&str, &str); 2] = [
    (
        "speedplus-camera.json",
        include_str!("../../../scenes/speedplus-camera.json"),
    ),
    (
        "tango-landmarks.csv",
        include_str!("../../../scenes/tango-landmarks.csv"),
    ),
];

/// A data file a scene names: on disk, or a copy built into the binary.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneData {
    /// A file on disk, as found.
    File(PathBuf),
    /// A built-in copy.
    Builtin {
        /// The name scenes give it (e.g. `speedplus-camera.json`).
        name: &'static str,
        /// Its contents.
        text: &'static str,
    },
}

impl SceneData {
    /// What to name in messages: the file, or `<built-in>/NAME`.
    pub fn origin(&self) -> PathBuf {
        match self {
            SceneData::File(path) => path.clone(),
            SceneData::Builtin { name, .. } => Path::new("<built-in>").join(name),
        }
    }

    /// The contents, read from disk for a file.
    pub fn text(&self) -> Result<String> {
        match self {
            SceneData::File(path) => {
                std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))
            }
            SceneData::Builtin { text, .. } => Ok((*text).to_owned()),
        }
    }
}

/// Names of the shipped presets.
pub fn preset_names() -> impl Iterator<Item = &'static str> {
    PRESETS.iter().map(|(name, _)| *name)
}

/// A scene file as written (every field documented in `docs/book/src/simulator.md`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// The scene's name, for messages and the stored `scene.toml`.
    pub name: String,
    /// Frames to render, at least 1.
    pub frames: u32,
    /// Seed of every random draw (poses, sun, exposure, noise): one seed, one dataset.
    pub seed: u64,
    /// Output images are `size` pixels wide (at least [`MIN_SIDE`]) ...
    pub size: u16,
    /// ... and `height` pixels tall (default: `size`, square). The camera's focal length
    /// scales with the width; the height widens or narrows the vertical field of view.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height: Option<u16>,
    /// Each pixel averages `antialias` x `antialias` rays (1 to 4; default 1).
    #[serde(default = "one")]
    pub antialias: u32,
    /// The spacecraft rendered (`[target]`).
    pub target: TargetSpec,
    /// The camera's intrinsics and lens (`[camera]`).
    pub camera: CameraSpec,
    /// How camera and target move from frame to frame (`[poses]`).
    pub poses: PoseSpec,
    /// Where the sun is in each frame (`[sun]`).
    pub sun: SunSpec,
    /// Materials defined by the scene (they may replace the built-in ones of the same name).
    #[serde(default)]
    pub materials: BTreeMap<String, MaterialSpec>,
    /// The effects to render (`[effects.NAME]`); an absent one is off.
    #[serde(default)]
    pub effects: Effects,
}

fn one() -> u32 {
    1
}

fn unit_scale() -> f32 {
    1.0
}

/// The target spacecraft (`[target]`, `model = "tango"` or `"mesh"`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case", deny_unknown_fields)]
pub enum TargetSpec {
    /// Procedural TANGO (body, solar panel, three antennas) sized by the SPEED+ landmarks.
    /// Parts: `body`, `panel`, `antenna`.
    Tango {
        /// The landmarks file (a path, or the built-in `tango-landmarks.csv`): 11 `x,y,z`
        /// lines in metres, in the SPEED+ devkit's order.
        landmarks: String,
        /// Part name -> material name; see [`TargetSpec::materials`].
        #[serde(default)]
        materials: BTreeMap<String, String>,
    },
    /// A Wavefront OBJ mesh; its parts are the OBJ objects/groups, named as in the file.
    Mesh {
        /// The OBJ file, relative to the scene file's folder or the current folder.
        path: String,
        /// Multiplies the mesh coordinates to give metres.
        #[serde(default = "unit_scale")]
        scale: f32,
        /// Part name -> material name; see [`TargetSpec::materials`].
        #[serde(default)]
        materials: BTreeMap<String, String>,
    },
}

impl TargetSpec {
    /// Part name -> material name; the key `default` covers parts not listed (without it they
    /// are `paint`).
    pub fn materials(&self) -> &BTreeMap<String, String> {
        match self {
            TargetSpec::Tango { materials, .. } | TargetSpec::Mesh { materials, .. } => materials,
        }
    }
}

/// The camera (`[camera]`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// A SPEED+ `camera.json` (a path, or the built-in `speedplus-camera.json`); its
    /// intrinsics are scaled to the output size.
    pub intrinsics: String,
    /// Render with the file's lens distortion.
    #[serde(default)]
    pub distortion: bool,
}

/// How the camera and the target move (`[poses]`, `kind = "approach"` or `"random"`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum PoseSpec {
    /// SHIRT-like: the camera spirals around and towards the target (distance and elevation
    /// change linearly, azimuth makes `turns` turns) while the target spins slowly.
    Approach {
        /// Camera distance to the target centre at the first and the last frame, metres
        /// (each in (0, 100 km]).
        distance_m: [f32; 2],
        /// Camera elevation above the orbit plane at the first and the last frame, degrees
        /// (each strictly between -89 and 89).
        elevation_deg: [f32; 2],
        /// Turns of the camera's azimuth around the target from the first frame to the last.
        turns: f32,
        /// Target attitude in the orbit frame at frame 0 (scalar-first quaternion).
        attitude: [f32; 4],
        /// Body axis the target spins about (any non-zero length).
        spin_axis: [f32; 3],
        /// Target spin about `spin_axis`, degrees per frame.
        spin_deg_per_frame: f32,
    },
    /// SPEED+-like: independent random SE(3) poses, target kept in view.
    Random {
        /// Distance range `[min, max]`, metres, drawn uniformly; 0 < min <= max <= 100 km.
        distance_m: [f32; 2],
    },
}

/// The sun's direction over the frames (`[sun]`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SunSpec {
    /// How the direction changes from frame to frame.
    pub path: SunPath,
    /// Direction to the sun in the orbit frame (x along track, z towards the Earth) at frame 0
    /// (`orbit`, `fixed`); unused by `random`.
    #[serde(default = "default_sun_direction")]
    pub direction: [f32; 3],
    /// Axis the sun direction turns about along the orbit (`orbit` only).
    #[serde(default = "default_orbit_axis")]
    pub axis: [f32; 3],
    /// How far the sun direction turns about `axis` per frame, degrees (`orbit` only).
    #[serde(default)]
    pub deg_per_frame: f32,
    /// Largest angle between the directions target -> sun and target -> camera (`random`
    /// only), 10 to 180 degrees (default 180): below 180 the camera sees mostly lit faces.
    #[serde(default = "default_max_phase")]
    pub max_phase_deg: f32,
}

fn default_max_phase() -> f32 {
    180.0
}

fn default_sun_direction() -> [f32; 3] {
    [1.0, 0.0, -1.0]
}

fn default_orbit_axis() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

/// How the sun direction changes over the frames.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SunPath {
    /// The same direction (`direction`) in every frame.
    Fixed,
    /// `direction` turning about `axis` by `deg_per_frame` each frame.
    Orbit,
    /// A random direction per frame, within `max_phase_deg` of the camera's.
    Random,
}

/// Surface reflectance: Lambert diffuse plus a normalised Blinn-Phong lobe, optionally with a
/// grid of bright lines (solar-cell busbars, MLI seams) of the given pitch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialSpec {
    /// Diffuse albedo, linear RGB, each in [0, 1].
    pub diffuse: [f32; 3],
    /// Specular reflectance, linear RGB, each in [0, 1] (default 0: no highlight).
    #[serde(default)]
    pub specular: [f32; 3],
    /// Blinn-Phong exponent, positive (default 20): higher is a sharper highlight.
    #[serde(default = "default_shininess")]
    pub shininess: f32,
    /// Spacing of the grid lines, metres; 0 (the default) means no grid.
    #[serde(default)]
    pub grid_pitch_m: f32,
    /// How much brighter the grid lines are than the surface (0.35 is 35 % brighter), >= 0.
    #[serde(default)]
    pub grid_contrast: f32,
}

fn default_shininess() -> f32 {
    20.0
}

/// The built-in materials: `paint` (white diffuse), `mli` (gold foil, broad specular lobe),
/// `solar_cell` (dark blue, glossy, cell grid) and `metal` (grey, sharp specular).
pub fn builtin_material(name: &str) -> Option<MaterialSpec> {
    let material = |diffuse, specular, shininess, grid_pitch_m, grid_contrast| MaterialSpec {
        diffuse,
        specular,
        shininess,
        grid_pitch_m,
        grid_contrast,
    };
    match name {
        "paint" => Some(material([0.80, 0.80, 0.78], [0.04; 3], 10.0, 0.0, 0.0)),
        "mli" => Some(material(
            [0.35, 0.26, 0.10],
            [0.75, 0.58, 0.28],
            8.0,
            0.12,
            0.35,
        )),
        "solar_cell" => Some(material(
            [0.03, 0.05, 0.14],
            [0.30, 0.30, 0.34],
            120.0,
            0.04,
            4.0,
        )),
        "metal" => Some(material(
            [0.25, 0.25, 0.26],
            [0.85, 0.85, 0.85],
            60.0,
            0.0,
            0.0,
        )),
        _ => None,
    }
}

/// The effects a scene asks for; an absent table means the effect is off and never computed.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    /// Direct sunlight (`[effects.sun]`).
    pub sun: Option<SunLight>,
    /// Shadows of the target on itself (`[effects.shadows]`); needs `sun`.
    pub shadows: Option<Shadows>,
    /// Fill light from the Earth (`[effects.albedo]`).
    pub albedo: Option<EarthAlbedo>,
    /// Specular highlights (`[effects.specular]`); needs `sun`.
    pub specular: Option<Specular>,
    /// Per-frame exposure (`[effects.exposure]`); without it every frame has exposure 1.
    pub exposure: Option<Exposure>,
    /// Bloom around bright pixels (`[effects.flare]`).
    pub flare: Option<Flare>,
    /// Sensor noise (`[effects.noise]`).
    pub noise: Option<SensorNoise>,
    /// Gray images (`[effects.grayscale]`).
    pub grayscale: Option<Grayscale>,
    /// Noise on the training labels (`[effects.label_noise]`); `truth.json` stays exact.
    pub label_noise: Option<LabelNoise>,
}

/// Direct sunlight on Lambertian surfaces; a white surface facing the sun reaches `irradiance`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SunLight {
    /// Sun irradiance, linear units, positive (default 1).
    #[serde(default = "unit_scale")]
    pub irradiance: f32,
}

/// Shadow rays towards the sun against the target itself.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Shadows {}

/// Dim diffuse fill light from the sunlit Earth.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EarthAlbedo {
    /// Irradiance of the fill light relative to direct sun when the Earth is fully lit.
    pub strength: f32,
    /// Direction to the Earth in the orbit frame.
    #[serde(default = "default_earth_direction")]
    pub earth_direction: [f32; 3],
}

fn default_earth_direction() -> [f32; 3] {
    [0.0, 0.0, 1.0]
}

/// The specular lobes of the materials (without it every surface is Lambertian).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Specular {}

/// Per-frame exposure drawn log-uniformly in `range` (values above 1 over-expose and clip to
/// white, values below 1 under-expose); `black_level` crushes the darkest tones to black.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Exposure {
    /// `[min, max]` exposure multiplier, 0 < min <= max (1 is nominal).
    pub range: [f32; 2],
    /// Linear value mapped to black, in [0, 1) (default 0); the rest is stretched to fill
    /// the range.
    #[serde(default)]
    pub black_level: f32,
}

/// Bloom: the light above `threshold` is blurred (Gaussian, `sigma_px`) and added back.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Flare {
    /// Linear value above which light blooms, >= 0 (default 1: white).
    #[serde(default = "unit_scale")]
    pub threshold: f32,
    /// Standard deviation of the blur, pixels, in (0, 64].
    pub sigma_px: f32,
    /// Multiplier of the blurred light added back, >= 0.
    pub strength: f32,
}

/// Sensor noise in electrons: shot noise (Gaussian approximation of Poisson) with `full_well`
/// electrons at white, plus `read_noise` electrons RMS.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorNoise {
    /// Electrons at white (linear value 1), positive: fewer electrons, more shot noise.
    pub full_well: f32,
    /// Read noise, electrons RMS, >= 0.
    pub read_noise: f32,
}

/// One luminance channel, like the real camera (PNG written as 8-bit grayscale).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Grayscale {}

/// Gaussian noise on the labels written for training: a rotation about a random axis by an
/// angle with standard deviation `rotation_deg`, and `translation_m` per axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelNoise {
    /// Standard deviation of the rotation angle, degrees, 0 to 180.
    pub rotation_deg: f32,
    /// Standard deviation of the position per axis, metres, 0 to 100 km.
    pub translation_m: f32,
}

impl LabelNoise {
    /// The labels are never stated better than this (degrees, 1 sigma): a star tracker's
    /// attitude floor, so that labels simulated exact still let the pose correction move a
    /// little instead of freezing it.
    pub const FLOOR_ROTATION_DEG: f32 = 0.1;
    /// Likewise for the camera position (metres, 1 sigma).
    pub const FLOOR_TRANSLATION_M: f32 = 0.002;

    /// Set `config`'s label prior (`pose_prior_rotation_deg`, `pose_prior_position`) to
    /// this noise, floored at [`Self::FLOOR_ROTATION_DEG`] and
    /// [`Self::FLOOR_TRANSLATION_M`], unless the config states a prior of its own.
    pub fn state_in(&self, config: &mut orbit_nerf_core::Config) {
        if config.pose_prior_rotation_deg > 0.0 || config.pose_prior_position > 0.0 {
            return;
        }
        config.pose_prior_rotation_deg = self.rotation_deg.max(Self::FLOOR_ROTATION_DEG);
        config.pose_prior_position = self.translation_m.max(Self::FLOOR_TRANSLATION_M);
    }
}

/// A checked scene, with where it came from (for messages and relative paths).
#[derive(Clone, Debug)]
pub struct Scene {
    /// The checked scene.
    pub spec: SceneSpec,
    /// The scene file (for a preset: its file in `scenes/`).
    pub origin: PathBuf,
    /// Folders a relative data path is tried against, in order.
    search_dirs: Vec<PathBuf>,
}

impl Scene {
    /// A preset name (`synthetic`, `lightbox`, `sunlamp`, `inspection`, `lightbox-test`,
    /// `rendezvous`) or the path of a scene file. A preset's data are the built-in copies; a scene file's data paths are tried relative to
    /// its folder, then the current folder, then against the built-in names.
    pub fn load(name_or_path: &str) -> Result<Scene> {
        if let Some((name, text)) = PRESETS.iter().find(|(name, _)| *name == name_or_path) {
            let origin = Path::new("<built-in>").join(format!("{name}.toml"));
            return Scene::parse(text, origin, Vec::new());
        }
        let path = Path::new(name_or_path);
        if !path.is_file() && path.extension().is_none() {
            let names: Vec<_> = preset_names().collect();
            return Err(HostError::invalid(
                path,
                format!(
                    "no such scene file, and not a preset (presets: {})",
                    names.join(", ")
                ),
            ));
        }
        let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
        let scene_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let cwd = std::env::current_dir().unwrap_or_default();
        Scene::parse(&text, path.to_path_buf(), vec![scene_dir, cwd])
    }

    /// The text `Scene::load` parses for `name_or_path`: a preset's built-in text or the
    /// file's (what a sweep record fingerprints, so a changed preset or file is noticed).
    pub fn text(name_or_path: &str) -> Result<String> {
        match PRESETS.iter().find(|(name, _)| *name == name_or_path) {
            Some((_, text)) => Ok((*text).to_string()),
            None => std::fs::read_to_string(name_or_path)
                .map_err(|e| HostError::io(Path::new(name_or_path), e)),
        }
    }

    /// Parse and check scene text; `origin` names it in errors.
    pub fn parse(text: &str, origin: PathBuf, search_dirs: Vec<PathBuf>) -> Result<Scene> {
        let table: toml::Table = toml::from_str(text)
            .map_err(|e| HostError::invalid(&origin, format!("TOML syntax: {e}")))?;
        check_finite(&origin, "", &toml::Value::Table(table.clone()))?;
        let spec: SceneSpec = serde_path_to_error::deserialize(table).map_err(|e| {
            let field = e.path().to_string();
            HostError::field(&origin, field, e.into_inner().to_string())
        })?;
        let scene = Scene {
            spec,
            origin,
            search_dirs,
        };
        scene.check()?;
        Ok(scene)
    }

    /// Check the scene's ranges and consistency: when loaded, and again before it is rendered,
    /// since a command may have changed it since (`--size`, `--frames`).
    pub fn check(&self) -> Result<()> {
        self.spec
            .check()
            .map_err(|(field, reason)| HostError::field(&self.origin, field, reason))
    }

    /// Resolve a data file named by `field`: absolute, or relative to the search folders
    /// (first that exists), else the built-in copy of that name.
    pub fn resolve_data(&self, field: &str, path: &str) -> Result<SceneData> {
        let given = Path::new(path);
        let candidates: Vec<PathBuf> = if given.is_absolute() {
            vec![given.to_path_buf()]
        } else {
            self.search_dirs.iter().map(|dir| dir.join(given)).collect()
        };
        if let Some(found) = candidates.iter().find(|candidate| candidate.is_file()) {
            return Ok(SceneData::File(found.clone()));
        }
        if let Some((name, text)) = BUILTIN_DATA.iter().find(|(name, _)| *name == path) {
            return Ok(SceneData::Builtin { name, text });
        }
        let tried: Vec<_> = candidates.iter().map(|c| c.display().to_string()).collect();
        let builtin: Vec<_> = BUILTIN_DATA.iter().map(|(name, _)| *name).collect();
        Err(HostError::field(
            &self.origin,
            field,
            format!(
                "file `{path}` not found (tried {}; built-in: {})",
                if tried.is_empty() {
                    "no folder".to_owned()
                } else {
                    tried.join(", ")
                },
                builtin.join(", ")
            ),
        ))
    }

    /// [`Scene::resolve_data`] for data that must be a file on disk (a mesh).
    pub fn resolve_path(&self, field: &str, path: &str) -> Result<PathBuf> {
        match self.resolve_data(field, path)? {
            SceneData::File(file) => Ok(file),
            SceneData::Builtin { name, .. } => Err(HostError::field(
                &self.origin,
                field,
                format!("`{name}` is built-in data, not a mesh file"),
            )),
        }
    }

    /// The material a part uses: the scene's `[materials.NAME]`, else a built-in one.
    pub fn material(&self, part: &str) -> Result<MaterialSpec> {
        let materials = self.spec.target.materials();
        let name = materials
            .get(part)
            .or_else(|| materials.get("default"))
            .map_or("paint", String::as_str);
        self.spec
            .materials
            .get(name)
            .cloned()
            .or_else(|| builtin_material(name))
            .ok_or_else(|| {
                HostError::field(
                    &self.origin,
                    format!("target.materials.{part}"),
                    format!("unknown material `{name}`"),
                )
            })
    }

    /// The scene as TOML (after any overrides), to store beside a dataset.
    pub fn to_toml(&self) -> Result<String> {
        let body = toml::to_string(&self.spec).map_err(|e| {
            HostError::invalid(&self.origin, format!("cannot write the scene as TOML: {e}"))
        })?;
        Ok(format!(
            "# Scene used to simulate this dataset (from {}).\n{body}",
            self.origin.display()
        ))
    }
}

/// Reject NaN and infinite numbers anywhere in the file (TOML allows `nan` and `inf`).
fn check_finite(origin: &Path, path: &str, value: &toml::Value) -> Result<()> {
    let join = |key: &str| {
        if path.is_empty() {
            key.to_owned()
        } else {
            format!("{path}.{key}")
        }
    };
    match value {
        toml::Value::Float(v) if !v.is_finite() => Err(HostError::field(
            origin,
            path,
            format!("not a finite number: {v}"),
        )),
        toml::Value::Table(table) => table
            .iter()
            .try_for_each(|(key, v)| check_finite(origin, &join(key), v)),
        toml::Value::Array(items) => items
            .iter()
            .enumerate()
            .try_for_each(|(i, v)| check_finite(origin, &format!("{path}[{i}]"), v)),
        _ => Ok(()),
    }
}

type Problem = (String, String);

fn problem(field: &str, reason: impl Into<String>) -> Problem {
    (field.to_owned(), reason.into())
}

fn ensure(ok: bool, field: &str, reason: &str) -> std::result::Result<(), Problem> {
    if ok {
        Ok(())
    } else {
        Err(problem(field, reason))
    }
}

/// Smallest image side, pixels: a scene's `size` and `height`, and what `--size` sets.
pub const MIN_SIDE: u16 = 8;

/// Farthest camera distance (metres): f32 positions there still resolve a centimetre, and the
/// squared distances the geometry takes stay far from overflowing.
const MAX_DISTANCE_M: f32 = 1e5;

fn non_zero(v: &[f32]) -> bool {
    v.iter().map(|x| x * x).sum::<f32>() > 1e-12
}

impl SceneSpec {
    /// Output image height in pixels.
    pub fn height(&self) -> u16 {
        self.height.unwrap_or(self.size)
    }

    /// Output images whose longer side is `side` pixels, the other scaled along (rounded, at
    /// least [`MIN_SIDE`]): what `--size` means for every command, simulated or read. A `side`
    /// below [`MIN_SIDE`] is kept, and refused by [`Scene::check`] before anything renders.
    pub fn set_longer_side(&mut self, side: u16) {
        let (width, height) = (u32::from(self.size), u32::from(self.height()));
        if height > width {
            let scaled = (width * u32::from(side) + height / 2) / height;
            self.size = scaled.clamp(u32::from(MIN_SIDE), u32::from(u16::MAX)) as u16;
            self.height = Some(side);
        } else {
            self.set_width(side);
        }
    }

    /// Output images `width` pixels wide, the height scaled along (rounded, at least
    /// [`MIN_SIDE`]), so the scene keeps its aspect ratio at any size. A `width` below
    /// [`MIN_SIDE`] is kept, and refused by [`Scene::check`] before anything renders.
    pub fn set_width(&mut self, width: u16) {
        if let Some(height) = self.height {
            let scaled = (u32::from(height) * u32::from(width) + u32::from(self.size) / 2)
                / u32::from(self.size.max(1));
            self.height = Some(scaled.clamp(u32::from(MIN_SIDE), u32::from(u16::MAX)) as u16);
        }
        self.size = width;
    }

    /// Ranges and consistency the types alone do not express.
    fn check(&self) -> std::result::Result<(), Problem> {
        ensure(self.frames >= 1, "frames", "must be at least 1")?;
        for (field, side) in [("size", self.size), ("height", self.height())] {
            ensure(
                side >= MIN_SIDE,
                field,
                &format!(
                    "{side} px is below the smallest image side, {MIN_SIDE} px (set by the scene file, or by --size)"
                ),
            )?;
        }
        ensure(
            (1..=4).contains(&self.antialias),
            "antialias",
            "must be 1, 2, 3 or 4",
        )?;
        if let TargetSpec::Mesh { scale, .. } = &self.target {
            ensure(*scale > 0.0, "target.scale", "must be positive")?;
        }
        match &self.poses {
            PoseSpec::Approach {
                distance_m,
                elevation_deg,
                attitude,
                spin_axis,
                ..
            } => {
                ensure(
                    distance_m.iter().all(|d| *d > 0.0 && *d <= MAX_DISTANCE_M),
                    "poses.distance_m",
                    "distances must be positive and at most 100 km",
                )?;
                ensure(
                    elevation_deg.iter().all(|e| e.abs() < 89.0),
                    "poses.elevation_deg",
                    "elevations must lie strictly between -89 and 89 degrees",
                )?;
                ensure(non_zero(attitude), "poses.attitude", "zero quaternion")?;
                ensure(non_zero(spin_axis), "poses.spin_axis", "zero vector")?;
            }
            PoseSpec::Random { distance_m } => {
                ensure(
                    distance_m[0] > 0.0
                        && distance_m[0] <= distance_m[1]
                        && distance_m[1] <= MAX_DISTANCE_M,
                    "poses.distance_m",
                    "must be [min, max] with 0 < min <= max <= 100 km",
                )?;
            }
        }
        ensure(
            non_zero(&self.sun.direction),
            "sun.direction",
            "zero vector",
        )?;
        ensure(non_zero(&self.sun.axis), "sun.axis", "zero vector")?;
        ensure(
            (10.0..=180.0).contains(&self.sun.max_phase_deg),
            "sun.max_phase_deg",
            "must be between 10 and 180 degrees",
        )?;
        for (name, material) in &self.materials {
            let field = format!("materials.{name}");
            let in_unit = |c: &[f32; 3]| c.iter().all(|v| (0.0..=1.0).contains(v));
            ensure(
                in_unit(&material.diffuse),
                &field,
                "diffuse must be within [0, 1]",
            )?;
            ensure(
                in_unit(&material.specular),
                &field,
                "specular must be within [0, 1]",
            )?;
            ensure(
                material.shininess > 0.0,
                &field,
                "shininess must be positive",
            )?;
            ensure(
                material.grid_pitch_m >= 0.0 && material.grid_contrast >= 0.0,
                &field,
                "grid must be >= 0",
            )?;
        }
        for (part, name) in self.target.materials() {
            ensure(
                self.materials.contains_key(name) || builtin_material(name).is_some(),
                &format!("target.materials.{part}"),
                "unknown material (built-in: paint, mli, solar_cell, metal)",
            )?;
        }
        self.effects.check()
    }
}

impl Effects {
    fn check(&self) -> std::result::Result<(), Problem> {
        ensure(
            self.sun.is_some() || self.albedo.is_some(),
            "effects",
            "no light: enable `sun` or `albedo`",
        )?;
        if let Some(sun) = &self.sun {
            ensure(
                sun.irradiance > 0.0,
                "effects.sun.irradiance",
                "must be positive",
            )?;
        }
        ensure(
            self.sun.is_some() || self.shadows.is_none(),
            "effects.shadows",
            "needs the `sun` effect",
        )?;
        ensure(
            self.sun.is_some() || self.specular.is_none(),
            "effects.specular",
            "needs the `sun` effect",
        )?;
        if let Some(albedo) = &self.albedo {
            ensure(
                albedo.strength >= 0.0,
                "effects.albedo.strength",
                "must be >= 0",
            )?;
            ensure(
                non_zero(&albedo.earth_direction),
                "effects.albedo.earth_direction",
                "zero vector",
            )?;
        }
        if let Some(exposure) = &self.exposure {
            let [low, high] = exposure.range;
            ensure(
                low > 0.0 && low <= high,
                "effects.exposure.range",
                "must be [min, max] with 0 < min <= max",
            )?;
            ensure(
                (0.0..1.0).contains(&exposure.black_level),
                "effects.exposure.black_level",
                "must be in [0, 1)",
            )?;
        }
        if let Some(flare) = &self.flare {
            ensure(
                flare.sigma_px > 0.0 && flare.sigma_px <= 64.0,
                "effects.flare.sigma_px",
                "must be in (0, 64]",
            )?;
            ensure(
                flare.strength >= 0.0,
                "effects.flare.strength",
                "must be >= 0",
            )?;
            ensure(
                flare.threshold >= 0.0,
                "effects.flare.threshold",
                "must be >= 0",
            )?;
        }
        if let Some(noise) = &self.noise {
            ensure(
                noise.full_well > 0.0,
                "effects.noise.full_well",
                "must be positive",
            )?;
            ensure(
                noise.read_noise >= 0.0,
                "effects.noise.read_noise",
                "must be >= 0",
            )?;
        }
        if let Some(labels) = &self.label_noise {
            // A sigma beyond a half turn or beyond the farthest camera is no label's noise.
            ensure(
                (0.0..=180.0).contains(&labels.rotation_deg),
                "effects.label_noise.rotation_deg",
                "must be in 0..=180 (degrees, 1 sigma)",
            )?;
            ensure(
                (0.0..=MAX_DISTANCE_M).contains(&labels.translation_m),
                "effects.label_noise.translation_m",
                &format!("must be in 0..={MAX_DISTANCE_M} (metres, 1 sigma)"),
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_width_keeps_the_aspect_ratio_and_square_scenes_stay_square() {
        let mut inspection = Scene::load("inspection").unwrap().spec;
        assert_eq!((inspection.size, inspection.height()), (240, 150));
        inspection.set_width(48);
        assert_eq!((inspection.size, inspection.height()), (48, 30));
        inspection.set_width(1000);
        assert_eq!((inspection.size, inspection.height()), (1000, 625));
        // Never below the smallest size a scene may have.
        inspection.set_width(8);
        assert_eq!((inspection.size, inspection.height()), (8, 8));
        let mut square = Scene::load("lightbox").unwrap().spec;
        square.set_width(100);
        assert_eq!(
            (square.size, square.height(), square.height),
            (100, 100, None)
        );
    }

    /// `--size` is the longer side: the width of a landscape scene, the height of a portrait.
    #[test]
    fn a_new_size_is_the_longer_side_whatever_the_orientation() {
        let mut landscape = Scene::load("inspection").unwrap().spec;
        landscape.set_longer_side(48);
        assert_eq!((landscape.size, landscape.height()), (48, 30));
        let mut portrait = landscape.clone();
        (portrait.size, portrait.height) = (150, Some(240));
        portrait.set_longer_side(48);
        assert_eq!((portrait.size, portrait.height()), (30, 48));
        portrait.set_longer_side(8);
        assert_eq!((portrait.size, portrait.height()), (8, 8));
    }

    /// The setters keep what `--size` asked for; the check that runs before rendering refuses
    /// a side below the minimum, naming the field and --size.
    #[test]
    fn a_size_below_the_minimum_set_after_loading_is_refused() {
        let refused_field = |scene: &Scene| match scene.check() {
            Err(HostError::Field { field, reason, .. }) => {
                assert!(reason.contains("--size"), "{reason}");
                field
            }
            other => panic!("expected a field error, got {other:?}"),
        };
        for side in [0, 3, MIN_SIDE - 1] {
            let mut square = Scene::load("lightbox").unwrap();
            square.spec.set_longer_side(side);
            assert_eq!(refused_field(&square), "size", "--size {side}");
            let mut landscape = Scene::load("inspection").unwrap();
            landscape.spec.set_width(side);
            assert_eq!(refused_field(&landscape), "size", "width {side}");
            let mut portrait = landscape.clone();
            (portrait.spec.size, portrait.spec.height) = (150, Some(240));
            portrait.spec.set_longer_side(side);
            assert_eq!(refused_field(&portrait), "height", "--size {side}");
        }
        let mut smallest = Scene::load("inspection").unwrap();
        smallest.spec.set_longer_side(MIN_SIDE);
        smallest.check().unwrap();
    }

    #[test]
    fn presets_use_the_built_in_data_and_scene_files_prefer_their_own() {
        for name in preset_names() {
            let scene = Scene::load(name).unwrap();
            let camera = scene
                .resolve_data("camera.intrinsics", &scene.spec.camera.intrinsics)
                .unwrap();
            assert!(
                matches!(
                    camera,
                    SceneData::Builtin {
                        name: "speedplus-camera.json",
                        ..
                    }
                ),
                "{name}: {camera:?}"
            );
        }
        let dir = tempfile::tempdir().unwrap();
        let preset = PRESETS
            .iter()
            .find(|(name, _)| *name == "lightbox")
            .unwrap()
            .1;
        let scene_file = dir.path().join("mine.toml");
        std::fs::write(&scene_file, preset).unwrap();
        let scene = Scene::load(scene_file.to_str().unwrap()).unwrap();
        // Not next to the scene file (nor, presumably, in the test's folder): the built-in copy.
        let builtin = scene
            .resolve_data("target.landmarks", "tango-landmarks.csv")
            .unwrap();
        assert_eq!(
            builtin.origin(),
            Path::new("<built-in>/tango-landmarks.csv")
        );
        assert!(builtin.text().unwrap().starts_with("x,y,z"));
        // A file of that name beside the scene file wins.
        let local = dir.path().join("tango-landmarks.csv");
        std::fs::write(&local, "x,y,z\n0,0,0\n").unwrap();
        assert_eq!(
            scene
                .resolve_data("target.landmarks", "tango-landmarks.csv")
                .unwrap(),
            SceneData::File(local)
        );
        let missing = scene
            .resolve_data("camera.intrinsics", "other.json")
            .unwrap_err();
        assert!(
            missing.to_string().contains("speedplus-camera.json")
                && missing.to_string().contains("camera.intrinsics"),
            "{missing}"
        );
        // A mesh must be a file.
        assert!(
            scene
                .resolve_path("target.path", "tango-landmarks.csv")
                .is_ok()
        );
        std::fs::remove_file(dir.path().join("tango-landmarks.csv")).unwrap();
        assert!(
            scene
                .resolve_path("target.path", "tango-landmarks.csv")
                .is_err()
        );
    }
}
