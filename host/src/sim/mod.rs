//! Scene simulator: renders a target spacecraft under orbital illumination and writes a dataset
//! in the SPEED+ format (see `docs/book/src/simulator.md`).
//!
//! A scene (TOML, [`Scene`]) names the target, the camera, the pose distribution, the sun path
//! and the effects to compute. Only the listed effects run; [`SimulationReport::timing_table`]
//! shows the time each one took, summed over frames. Frames are rendered in parallel (rayon),
//! each a pure function of the scene, its seed and its index, so the output is identical for a
//! seed whatever the thread count.
//!
//! Output folder: `images/imgNNNNNN.png`, `masks/imgNNNNNN.png`, `labels.json` (the labels to
//! train on, noisy if the scene asks), `truth.json` (exact poses, sun directions, exposures),
//! `camera.json` and `scene.toml` (the scene as run).

mod render;
pub mod scene;
mod target;
mod trajectory;

pub use scene::{Effects, Scene, SceneSpec, preset_names};
pub use target::{Target, parse_landmarks, read_landmarks};

use crate::dataset::Dataset;
use crate::error::{HostError, Result};
use crate::formats::speedplus::{Label, SpeedCamera, Truth, TruthFrame, write_labels};
use crate::io::write_png;
use rayon::prelude::*;
pub use render::RenderedImage;
use render::Renderer;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The timed parts of the simulation: the always-on pipeline and one stage per effect.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Primary rays: the closest surface under every sub-pixel sample.
    Geometry,
    /// Shadow rays towards the sun.
    Shadows,
    /// Diffuse light from the sun.
    Sun,
    /// Specular (Blinn-Phong) highlights of the sun.
    Specular,
    /// Light reflected by the Earth.
    Albedo,
    /// Averaging the sub-pixel samples into pixels and the mask.
    Resolve,
    /// Conversion to one gray channel.
    Grayscale,
    /// Exposure gain and black level.
    Exposure,
    /// Bloom around saturated pixels.
    Flare,
    /// Sensor noise.
    Noise,
    /// Gamma encoding and quantisation to 8 bits.
    Encode,
    /// Noise on the labels written for training.
    LabelNoise,
    /// Encoding and writing the PNG files.
    Write,
}

impl Stage {
    /// Every stage, in the order a frame runs them.
    pub const ALL: [Stage; 13] = [
        Stage::Geometry,
        Stage::Shadows,
        Stage::Sun,
        Stage::Specular,
        Stage::Albedo,
        Stage::Resolve,
        Stage::Grayscale,
        Stage::Exposure,
        Stage::Flare,
        Stage::Noise,
        Stage::Encode,
        Stage::LabelNoise,
        Stage::Write,
    ];

    /// The stage's name in the timing table.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Geometry => "primary rays",
            Stage::Shadows => "shadow rays",
            Stage::Sun => "direct sun",
            Stage::Specular => "specular",
            Stage::Albedo => "earth albedo",
            Stage::Resolve => "pixel resolve",
            Stage::Grayscale => "grayscale",
            Stage::Exposure => "exposure",
            Stage::Flare => "flare/bloom",
            Stage::Noise => "sensor noise",
            Stage::Encode => "gamma + 8 bit",
            Stage::LabelNoise => "label noise",
            Stage::Write => "PNG write",
        }
    }

    /// The scene effect (`[effects.NAME]`) that turns this stage on; `None` for stages that
    /// always run.
    pub fn effect(self) -> Option<&'static str> {
        match self {
            Stage::Shadows => Some("shadows"),
            Stage::Sun => Some("sun"),
            Stage::Specular => Some("specular"),
            Stage::Albedo => Some("albedo"),
            Stage::Grayscale => Some("grayscale"),
            Stage::Exposure => Some("exposure"),
            Stage::Flare => Some("flare"),
            Stage::Noise => Some("noise"),
            Stage::LabelNoise => Some("label_noise"),
            Stage::Geometry | Stage::Resolve | Stage::Encode | Stage::Write => None,
        }
    }

    /// Whether a scene with these effects runs this stage.
    pub fn runs_with(self, effects: &Effects) -> bool {
        match self {
            Stage::Shadows => effects.shadows.is_some(),
            Stage::Sun => effects.sun.is_some(),
            Stage::Specular => effects.specular.is_some(),
            Stage::Albedo => effects.albedo.is_some(),
            Stage::Grayscale => effects.grayscale.is_some(),
            Stage::Exposure => effects.exposure.is_some(),
            Stage::Flare => effects.flare.is_some(),
            Stage::Noise => effects.noise.is_some(),
            Stage::LabelNoise => effects.label_noise.is_some(),
            Stage::Geometry | Stage::Resolve | Stage::Encode | Stage::Write => true,
        }
    }
}

/// Time spent in each stage (summed over the frames and threads that ran it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageTimes([Duration; Stage::ALL.len()]);

impl StageTimes {
    /// Run `work`, adding its duration to `stage`.
    pub fn time<T>(&mut self, stage: Stage, work: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let result = work();
        self.0[stage as usize] += start.elapsed();
        result
    }

    /// The time spent in `stage` so far.
    pub fn get(&self, stage: Stage) -> Duration {
        self.0[stage as usize]
    }

    fn add(mut self, other: &StageTimes) -> StageTimes {
        for (total, time) in self.0.iter_mut().zip(&other.0) {
            *total += *time;
        }
        self
    }
}

/// What a simulation did and how long each part took.
#[derive(Clone, Debug)]
pub struct SimulationReport {
    /// Frames rendered.
    pub frames: u32,
    /// Image width in pixels.
    pub width: u16,
    /// Image height in pixels.
    pub height: u16,
    /// Triangles in the target's mesh.
    pub triangles: usize,
    /// The effects the scene asked for.
    pub effects: Effects,
    /// Time spent in each stage, summed over frames and threads.
    pub times: StageTimes,
    /// Wall time of the whole simulation.
    pub wall_time: Duration,
    /// The output folder.
    pub out: PathBuf,
    /// The labels written to `labels.json`.
    pub labels: Vec<Label>,
    /// The contents of `truth.json`.
    pub truth: Truth,
}

impl SimulationReport {
    /// One line per stage: the effect it belongs to, whether it ran, total and per-frame time.
    pub fn timing_table(&self) -> String {
        let mut table = String::new();
        let _ = writeln!(
            table,
            "{:<14} {:<12} {:<4} {:>10} {:>10}",
            "stage", "effect", "on", "total ms", "us/frame"
        );
        for stage in Stage::ALL {
            let total = self.times.get(stage).as_secs_f64() * 1e3;
            let _ = writeln!(
                table,
                "{:<14} {:<12} {:<4} {:>10.2} {:>10.1}",
                stage.name(),
                stage.effect().unwrap_or("(always)"),
                if stage.runs_with(&self.effects) {
                    "yes"
                } else {
                    "no"
                },
                total,
                1e3 * total / self.frames.max(1) as f64,
            );
        }
        let cpu: Duration = Stage::ALL.iter().map(|&s| self.times.get(s)).sum();
        let _ = writeln!(
            table,
            "{} frames of {}x{} px, {} triangles: {:.2} s wall, {:.2} s summed over threads",
            self.frames,
            self.width,
            self.height,
            self.triangles,
            self.wall_time.as_secs_f64(),
            cpu.as_secs_f64()
        );
        table
    }
}

/// The SPEED+ camera scaled to a `width` x `height` output: the focal length scales with the
/// width (the SPEED+ horizontal field of view is kept) and the principal point keeps its offset
/// from the image centre. Distortion coefficients (on normalised coordinates) carry over when
/// the scene renders with distortion.
pub fn output_camera(
    sensor: &SpeedCamera,
    width: u16,
    height: u16,
    distortion: bool,
) -> SpeedCamera {
    let scale = f64::from(width) / sensor.width as f64;
    let k = &sensor.camera_matrix;
    let (cx, cy) = (
        f64::from(width) / 2.0 + (k[0][2] - sensor.width as f64 / 2.0) * scale,
        f64::from(height) / 2.0 + (k[1][2] - sensor.height as f64 / 2.0) * scale,
    );
    SpeedCamera {
        width: u32::from(width),
        height: u32::from(height),
        pixel_pitch: sensor.pixel_pitch.map(|pitch| pitch.map(|p| p / scale)),
        camera_matrix: [
            [k[0][0] * scale, 0.0, cx],
            [0.0, k[1][1] * scale, cy],
            [0.0, 0.0, 1.0],
        ],
        dist_coeffs: if distortion {
            sensor.dist_coeffs
        } else {
            [0.0; 5]
        },
    }
}

/// Bytes a frame being rendered holds per output pixel: linear RGB f32 (12), the flare's
/// bright-pass and blur buffers (12 + 12), the mask (1), the 8-bit image (3) and its PNG
/// encoding (at most about 4).
pub const RENDER_BYTES_PER_PIXEL: u64 = 44;
/// Bytes a loaded frame holds per pixel: RGB and mask, 8 bits each.
pub const LOADED_BYTES_PER_PIXEL: u64 = 4;

/// The memory a simulation of `spec` needs: the frames rendered at once (one per worker
/// thread of the pool [`simulate`] runs on) and, when `load_back`, the whole dataset read back
/// to check it.
pub fn working_memory(spec: &SceneSpec, load_back: bool) -> Vec<crate::memory::Part> {
    let pixels = u64::from(spec.size) * u64::from(spec.height());
    let frames_at_once = (rayon::current_num_threads() as u64).min(u64::from(spec.frames));
    let mut parts = vec![(
        "frames being rendered",
        pixels
            .saturating_mul(RENDER_BYTES_PER_PIXEL)
            .saturating_mul(frames_at_once),
    )];
    if load_back {
        parts.push((
            "dataset read back",
            pixels
                .saturating_mul(LOADED_BYTES_PER_PIXEL)
                .saturating_mul(u64::from(spec.frames)),
        ));
    }
    parts
}

/// Image file name of frame `index` (SPEED+ numbering starts at 1), e.g. `img000001.png`.
pub fn frame_filename(index: u32) -> String {
    format!("img{:06}.png", index + 1)
}

/// Renders the frames of a scene one at a time: what [`simulate`] writes, and what a stream
/// asks for frame by frame.
pub struct FrameSimulator<'s> {
    scene: &'s Scene,
    target: Target,
    camera_file: SpeedCamera,
}

/// One rendered frame with its labels.
pub struct SimulatedFrame {
    /// The image's file name ([`frame_filename`]).
    pub filename: String,
    /// The label to train on (noisy if the scene asks).
    pub label: Label,
    /// The exact pose, sun direction and exposure.
    pub truth: TruthFrame,
    /// The rendered pixels and mask.
    pub image: RenderedImage,
    /// Time the frame spent in each stage.
    pub times: StageTimes,
}

impl<'s> FrameSimulator<'s> {
    /// Build the target's mesh and the output camera of `scene`; fails when the scene is
    /// out of range (a command may have changed it since it was loaded, e.g. `--size`), or its
    /// mesh, materials or camera file cannot be read.
    pub fn new(scene: &'s Scene) -> Result<FrameSimulator<'s>> {
        scene.check()?;
        let spec = &scene.spec;
        let target = Target::build(scene)?;
        let intrinsics = scene.resolve_data("camera.intrinsics", &spec.camera.intrinsics)?;
        let sensor = SpeedCamera::parse(&intrinsics.origin(), &intrinsics.text()?)?;
        let camera_file = output_camera(&sensor, spec.size, spec.height(), spec.camera.distortion);
        Ok(FrameSimulator {
            scene,
            target,
            camera_file,
        })
    }

    /// The camera file of the output (SPEED+ format, scaled to the output size).
    pub fn camera_file(&self) -> &SpeedCamera {
        &self.camera_file
    }

    /// The box (body frame) that holds the target.
    pub fn scene_box(&self) -> ([f32; 3], [f32; 3]) {
        self.target.scene_box()
    }

    /// Triangles in the target's mesh.
    pub fn triangle_count(&self) -> usize {
        self.target.triangle_count()
    }

    /// Where frame `index` is seen from and how it is lit.
    fn view(&self, index: u32) -> Result<trajectory::FrameView> {
        let (center, radius) = (self.target.center(), self.target.radius());
        let camera = self.camera_file.pinhole();
        trajectory::frame_view(&self.scene.spec, center, radius, &camera, index)
    }

    /// The exact pose of frame `index` (what its `truth.json` entry holds), without rendering
    /// it.
    pub fn exact_pose(&self, index: u32) -> Result<orbit_nerf_core::Pose> {
        let view = self.view(index)?;
        let filename = frame_filename(index);
        Label::new(filename.clone(), view.body_to_camera, view.target_in_camera)
            .pose()
            .ok_or_else(|| HostError::field(&filename, "q_vbs2tango_true", "not a valid pose"))
    }

    /// Frame `index`: a pure function of the scene, its seed and the index. Fails when the
    /// frame's geometry is degenerate.
    pub fn render(&self, index: u32) -> Result<SimulatedFrame> {
        let spec = &self.scene.spec;
        let renderer = Renderer {
            target: &self.target,
            effects: &spec.effects,
            camera: self.camera_file.pinhole(),
            lens: spec.camera.distortion.then_some(&self.camera_file),
            antialias: spec.antialias,
            seed: spec.seed,
        };
        let mut times = StageTimes::default();
        let view = self.view(index)?;
        let filename = frame_filename(index);
        let (q, r) = match &spec.effects.label_noise {
            Some(noise) => times.time(Stage::LabelNoise, || {
                trajectory::noisy_label(&view, noise, spec.seed, index)
            })?,
            None => (view.body_to_camera, view.target_in_camera),
        };
        let label = Label::new(filename.clone(), q, r);
        let exact = Label::new(filename.clone(), view.body_to_camera, view.target_in_camera);
        let image = renderer.render(&view, index, &mut times);
        let truth = TruthFrame {
            filename: filename.clone(),
            q_vbs2tango_true: exact.q_vbs2tango,
            r_vo2to_vbs_true: exact.r_vo2to_vbs,
            sun_direction_body: view.sun_body.to_array().map(f64::from),
            exposure: view.exposure as f64,
        };
        Ok(SimulatedFrame {
            filename,
            label,
            truth,
            image,
            times,
        })
    }
}

/// Render every frame of `scene` and write the dataset to `out`. `progress` is called once per
/// finished frame (from worker threads). Output is staged in a sibling folder and moved into
/// place when complete, so a killed run leaves no partial dataset at `out` (its staging folder
/// is removed by the next run for the same `out`); an existing `out` is replaced only if it
/// is empty or holds nothing but a simulated dataset.
pub fn simulate(
    scene: &Scene,
    out: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<SimulationReport> {
    let start = Instant::now();
    let spec = &scene.spec;
    check_replaceable(out)?;
    let simulator = FrameSimulator::new(scene)?;
    remove_stale_siblings(out)?;
    let staging = sibling(out, STAGING, std::process::id());
    std::fs::create_dir_all(&staging).map_err(|e| HostError::io(&staging, e))?;

    let frames = (0..spec.frames)
        .into_par_iter()
        .map(|index| {
            let SimulatedFrame {
                filename,
                label,
                truth,
                image,
                mut times,
            } = simulator.render(index)?;
            times.time(Stage::Write, || {
                let (width, height) = (u32::from(spec.size), u32::from(spec.height()));
                write_png(
                    &staging.join("images").join(&filename),
                    width,
                    height,
                    image.channels,
                    &image.pixels,
                )?;
                write_png(
                    &staging.join("masks").join(&filename),
                    width,
                    height,
                    1,
                    &image.mask,
                )
            })?;
            progress();
            Ok((label, truth, times))
        })
        .collect::<Result<Vec<_>>>();
    let frames = match frames {
        Ok(frames) => frames,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
    };

    let times = frames
        .iter()
        .fold(StageTimes::default(), |total, (_, _, times)| {
            total.add(times)
        });
    let labels: Vec<Label> = frames.iter().map(|(label, _, _)| label.clone()).collect();
    let (box_min, box_max) = simulator.scene_box();
    let truth = Truth {
        target_box_min: box_min,
        target_box_max: box_max,
        frames: frames.into_iter().map(|(_, truth, _)| truth).collect(),
    };
    write_labels(&staging.join("labels.json"), &labels)?;
    truth.write(&staging.join("truth.json"))?;
    simulator
        .camera_file()
        .write(&staging.join("camera.json"))?;
    crate::io::write_atomic(&staging.join("scene.toml"), scene.to_toml()?.as_bytes())?;
    move_into_place(&staging, out)?;

    Ok(SimulationReport {
        frames: spec.frames,
        width: spec.size,
        height: spec.height(),
        triangles: simulator.triangle_count(),
        effects: spec.effects.clone(),
        times,
        wall_time: start.elapsed(),
        out: out.to_path_buf(),
        labels,
        truth,
    })
}

/// The entries a simulation writes into its output folder: a folder holding only these (and
/// nothing else) is a simulated dataset that a new simulation may replace.
const DATASET_ENTRIES: [&str; 6] = [
    "images",
    "masks",
    "labels.json",
    "truth.json",
    "camera.json",
    "scene.toml",
];
/// Suffixes of the sibling folders a simulation stages in and moves the old dataset to.
const STAGING: &str = "partial";
const REPLACED: &str = "old";

/// `out` may be replaced if it does not exist, is empty, or holds a simulated dataset and
/// nothing else (other files or folders inside it are never deleted).
fn check_replaceable(out: &Path) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        return Err(HostError::invalid(
            out,
            "exists and is not a folder; refusing to replace it",
        ));
    }
    let foreign = foreign_entries(out)?;
    if !foreign.is_empty() {
        return Err(HostError::invalid(
            out,
            format!(
                "holds {} that a simulation did not write; refusing to replace it (choose another --out or move them)",
                foreign.join(", ")
            ),
        ));
    }
    Ok(())
}

/// Names of the entries of `dir` that are not part of a simulated dataset.
fn foreign_entries(dir: &Path) -> Result<Vec<String>> {
    let mut foreign = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| HostError::io(dir, e))? {
        let name = entry
            .map_err(|e| HostError::io(dir, e))?
            .file_name()
            .to_string_lossy()
            .into_owned();
        // A kill during an atomic write leaves `ENTRY.tmpPID` (see `io::write_atomic`).
        let written = DATASET_ENTRIES.iter().any(|entry| {
            name.strip_prefix(entry).is_some_and(|rest| {
                rest.is_empty()
                    || rest
                        .strip_prefix(".tmp")
                        .is_some_and(|pid| pid.parse::<u32>().is_ok())
            })
        });
        if !written {
            foreign.push(name);
        }
    }
    foreign.sort();
    Ok(foreign)
}

/// `out`'s sibling `NAME.WHAT-PID`.
fn sibling(out: &Path, what: &str, pid: u32) -> PathBuf {
    let mut name = sibling_prefix(out);
    name.push_str(&format!("{what}-{pid}"));
    out.with_file_name(name)
}

fn sibling_prefix(out: &Path) -> String {
    let name = out
        .file_name()
        .map_or_else(|| "dataset".into(), |n| n.to_string_lossy().into_owned());
    format!("{name}.")
}

/// Remove what killed simulations for `out` left behind: sibling staging and replaced folders
/// whose process is gone and that hold only simulator output. Anything else is left alone.
fn remove_stale_siblings(out: &Path) -> Result<()> {
    let parent = match out.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent,
        _ => Path::new("."),
    };
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Ok(());
    };
    let prefix = sibling_prefix(out);
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix(&prefix).and_then(|rest| {
            [STAGING, REPLACED].iter().find_map(|what| {
                rest.strip_prefix(what)?
                    .strip_prefix('-')?
                    .parse::<u32>()
                    .ok()
            })
        }) else {
            continue;
        };
        let path = entry.path();
        if !process_is_gone(pid) || !path.is_dir() || !foreign_entries(&path)?.is_empty() {
            continue;
        }
        std::fs::remove_dir_all(&path).map_err(|e| HostError::io(&path, e))?;
    }
    Ok(())
}

/// Whether no process `pid` is running (Linux `/proc`); elsewhere, never assumed gone.
fn process_is_gone(pid: u32) -> bool {
    Path::new("/proc/self").exists() && !Path::new(&format!("/proc/{pid}")).exists()
}

fn move_into_place(staging: &Path, out: &Path) -> Result<()> {
    let old = sibling(out, REPLACED, std::process::id());
    if out.exists() {
        std::fs::rename(out, &old).map_err(|e| HostError::io(out, e))?;
    }
    std::fs::rename(staging, out).map_err(|e| HostError::io(out, e))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(|e| HostError::io(&old, e))?;
    }
    Ok(())
}

/// Tile up to `columns` x `columns` frames, evenly spread through the dataset, into one RGB
/// image with 2-pixel gaps. Returns (width, height, pixels).
pub fn contact_sheet(dataset: &Dataset, columns: usize) -> Result<(u32, u32, Vec<u8>)> {
    let frames = &dataset.frames;
    let first = frames
        .first()
        .ok_or_else(|| HostError::invalid(&dataset.source, "no frames to tile"))?;
    let (tile_w, tile_h) = (first.camera.width as usize, first.camera.height as usize);
    let columns = columns.clamp(1, frames.len());
    let count = (columns * columns).min(frames.len());
    let rows = count.div_ceil(columns);
    let gap = 2;
    let (width, height) = (columns * (tile_w + gap) - gap, rows * (tile_h + gap) - gap);
    let mut sheet = vec![32u8; width * height * 3];
    for tile in 0..count {
        let frame = &frames[tile * frames.len() / count];
        if (frame.camera.width as usize, frame.camera.height as usize) != (tile_w, tile_h) {
            return Err(HostError::invalid(
                &frame.name,
                "frames of different sizes cannot be tiled",
            ));
        }
        let (x0, y0) = (
            (tile % columns) * (tile_w + gap),
            (tile / columns) * (tile_h + gap),
        );
        for y in 0..tile_h {
            let row = &frame.pixels[y * tile_w * 3..(y + 1) * tile_w * 3];
            let at = ((y0 + y) * width + x0) * 3;
            sheet[at..at + tile_w * 3].copy_from_slice(row);
        }
    }
    Ok((width as u32, height as u32, sheet))
}
