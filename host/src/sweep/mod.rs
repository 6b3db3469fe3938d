//! Sweep descriptions: one TOML file naming the data (a simulated scene or a dataset folder),
//! the base config (a built-in preset, and a config file changing some of its fields), the variants (named config
//! overrides), the label-noise levels, the seeds and the budget. Reading one checks every
//! field (errors name the file and the field) and expands it into its tasks, each one model
//! trained and scored in its own process: `sweep run` runs them on this machine, `sweep slurm`
//! as a Slurm job array, `ablate --pose-noise` builds its levels here.
//!
//! ```toml
//! scene = "synthetic"          # a preset or a scene file; or data = "path/to/speedplus"
//! frames = 400                 # simulated scenes only; a list is the image-count study:
//!                              #   frames = [25, 50, 100, 200, 400], one task per count
//! test_scene = "lightbox-test" # optional: a separate test set (a preset or scene file),
//! test_frames = 200            #   simulated with exact labels; every task is scored on all
//!                              #   its views and trained on all of its own frames
//! test_data = "path/to/test"   # or a separate test set read from a dataset folder
//! size = 128
//! config = "spacecraft"        # a preset (default, spacecraft, tiny, standard, render), or a
//!                              #   file of the fields to change (on top of `preset`)
//! steps = 2000
//! seeds = [0, 1]
//!
//! [noise]                      # optional: the paper's pose-noise sweeps
//! rotation_deg = [0, 0.2, 0.4, 0.8, 1.6]
//! translation_mm = [0, 2, 4, 8, 16]
//!
//! [[variants]]                 # optional: default baseline, ours, ours + pose
//! name = "ours"                #   (with noise levels: ours, ours + pose)
//! set = { embedding_dim = 32, pose_correction = false }
//! size = 64                    # optional: this variant's image size (default `size`; with
//!                              #   `data`, at most its images': never upsampled)
//!
//! [anytime]                    # optional: what accuracy costs in time (`tradeoff`)
//! steps = [250, 500, 1000]     # held-out views also scored after these steps
//! quality = "psnr_foreground"  # the figure of the Pareto plots, targets and budgets
//! targets = [25, 27, 28]       # the report gives each variant's time to reach these
//! budgets_s = [30, 60, 300]    # and the best variant within each training time
//! ```

pub mod paper;
pub mod results;
pub mod run;
#[cfg(feature = "slurm")]
pub mod slurm;
pub mod studies;
pub mod tradeoff;

use crate::ablation::{APPEARANCE, APPEARANCE_POSE, BASELINE, Variant};
use crate::error::{HostError, Result};
use crate::presets;
use crate::scene_box::parse_box;
use crate::sim::Scene;
use crate::sim::scene::LabelNoise;
use crate::train::with_overrides;
use orbit_nerf_core::Config;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// A sweep description as written: every field optional except where [`Sweep`] says.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepDescription {
    /// A scene preset or scene file to simulate.
    pub scene: Option<String>,
    /// A dataset folder of any format (instead of `scene`): SPEED+/SHIRT/simulator, NeRF-synthetic, nerfstudio.
    pub data: Option<PathBuf>,
    /// Frames to simulate (default 400); a list gives one task per count (the image-count
    /// study).
    pub frames: Option<FrameCounts>,
    /// A separate test set: a scene preset or scene file simulated with exact labels
    /// (instead of holding out every `holdout`-th view).
    pub test_scene: Option<String>,
    /// Frames of the test set (default: the test scene's own).
    pub test_frames: Option<u32>,
    /// A separate test set read from a dataset folder of any format (instead of
    /// `test_scene`).
    pub test_data: Option<PathBuf>,
    /// Image size in pixels (default 128).
    pub size: Option<u32>,
    /// The built-in preset the base config starts from (see [`crate::presets`]; default
    /// `spacecraft`).
    pub preset: Option<String>,
    /// A preset (instead of `preset`), or a config file naming the fields it changes in
    /// `preset`'s config.
    pub config: Option<String>,
    /// Training steps of every model (default: the base config's).
    pub steps: Option<u32>,
    /// One task per seed for every variant and level (default: the base config's seed).
    pub seeds: Option<Vec<u64>>,
    /// Every N-th view is held out (default 8).
    pub holdout: Option<usize>,
    /// Steps fitting each held-out view's embedding (default 50).
    pub fit_steps: Option<u32>,
    /// Apply the foreground masks (default true).
    pub masks: Option<bool>,
    /// `"xmin,ymin,zmin,xmax,ymax,zmax"`, as `--scene-box`.
    pub scene_box: Option<String>,
    /// `[noise]`: the pose-noise sweeps' label-noise levels (simulated scenes only).
    pub noise: Option<NoiseLevels>,
    /// `[[variants]]`: the models to train (empty: the paper's, see [`Sweep`]).
    #[serde(default)]
    pub variants: Vec<VariantSpec>,
    /// `[anytime]`: scoring during training and the trade-off report.
    pub anytime: Option<AnytimeSpec>,
}

/// One frame count, or several (one task each).
#[derive(Clone, Debug, Deserialize)]
#[serde(untagged)]
pub enum FrameCounts {
    /// `frames = N`: one count.
    One(u32),
    /// `frames = [N, ...]`: one task per count (the image-count study).
    Many(Vec<u32>),
}

/// A separate test set, every view scored and none trained on.
#[derive(Clone, Debug, PartialEq)]
pub enum TestSet {
    /// A scene preset name or a scene file, simulated with exact labels.
    Scene {
        /// The scene preset name, or the scene file's path.
        scene: String,
        /// Views to simulate (default: the scene's own frame count).
        frames: u32,
    },
    /// A dataset folder of any format (scored at its exact poses where it has them).
    Data(PathBuf),
}

/// Scoring during training, and the trade-off report's figures (see [`Anytime`]).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnytimeSpec {
    /// Steps after which the held-out views are also scored (ascending, above 0).
    #[serde(default)]
    pub steps: Vec<u32>,
    /// The [`Quality`] name the report ranks by (default `psnr_foreground`).
    pub quality: Option<String>,
    /// Quality levels whose time to reach the report gives (in the quality's unit).
    #[serde(default)]
    pub targets: Vec<f64>,
    /// Training-time budgets, seconds, within which the report names the best variant.
    #[serde(default)]
    pub budgets_s: Vec<f64>,
}

/// The figure a trade-off report ranks variants by: a mean held-out metric.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quality {
    /// PSNR over the whole image, dB (`psnr_full`).
    PsnrFull,
    /// PSNR over the right half (the half the embedding was not fitted on), dB (`psnr_right`).
    PsnrRight,
    /// PSNR over the foreground pixels, dB (`psnr_foreground`).
    PsnrForeground,
    /// PSNR over the right half's foreground pixels, dB (`psnr_foreground_right`).
    PsnrForegroundRight,
    /// SSIM over the whole image, at most 1 (`ssim_full`).
    SsimFull,
    /// SSIM over the right half, at most 1 (`ssim_right`).
    SsimRight,
}

impl Quality {
    /// Every quality, in the order error messages list them.
    pub const ALL: [Quality; 6] = [
        Quality::PsnrFull,
        Quality::PsnrRight,
        Quality::PsnrForeground,
        Quality::PsnrForegroundRight,
        Quality::SsimFull,
        Quality::SsimRight,
    ];

    /// The name in descriptions and CSV headers (a field of the task records' metrics).
    pub fn name(self) -> &'static str {
        match self {
            Quality::PsnrFull => "psnr_full",
            Quality::PsnrRight => "psnr_right",
            Quality::PsnrForeground => "psnr_foreground",
            Quality::PsnrForegroundRight => "psnr_foreground_right",
            Quality::SsimFull => "ssim_full",
            Quality::SsimRight => "ssim_right",
        }
    }

    /// Axis and table label, with its unit.
    pub fn label(self) -> &'static str {
        match self {
            Quality::PsnrFull => "PSNR (dB)",
            Quality::PsnrRight => "right-half PSNR (dB)",
            Quality::PsnrForeground => "foreground PSNR (dB)",
            Quality::PsnrForegroundRight => "right-half foreground PSNR (dB)",
            Quality::SsimFull => "SSIM",
            Quality::SsimRight => "right-half SSIM",
        }
    }

    /// This quality's value in the metrics `m` (higher is better for every quality).
    pub fn of(self, m: &crate::report::ViewMetrics) -> f64 {
        match self {
            Quality::PsnrFull => m.psnr_full,
            Quality::PsnrRight => m.psnr_right,
            Quality::PsnrForeground => m.psnr_foreground,
            Quality::PsnrForegroundRight => m.psnr_foreground_right,
            Quality::SsimFull => m.ssim_full,
            Quality::SsimRight => m.ssim_right,
        }
    }

    /// Largest value the metric takes (a target above it is a typo).
    fn max(self) -> f64 {
        match self {
            Quality::SsimFull | Quality::SsimRight => 1.0,
            _ => 200.0,
        }
    }
}

/// A checked `[anytime]` table.
#[derive(Clone, Debug, PartialEq)]
pub struct Anytime {
    /// Ascending, distinct, above 0; a task scores those below its own steps, then its end.
    pub steps: Vec<u32>,
    /// The figure the report ranks variants by, reads targets in and plots.
    pub quality: Quality,
    /// Quality levels whose time to reach the report gives, ascending.
    pub targets: Vec<f64>,
    /// Training times (s) within which the report names the best variant, ascending.
    pub budgets_s: Vec<f64>,
}
/// Label-noise levels: the rotation sweep's (degrees, exact positions) and the translation
/// sweep's (mm per axis, exact attitudes).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseLevels {
    /// Standard deviations of the label rotation noise, degrees (0 to 180), positions exact.
    #[serde(default)]
    pub rotation_deg: Vec<f32>,
    /// Standard deviations of the label position noise per axis, mm, attitudes exact.
    #[serde(default)]
    pub translation_mm: Vec<f32>,
}

/// A named set of config overrides (fields of the config, as in a config file).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantSpec {
    /// The variant's name in task names, tables and plots (unique in the sweep).
    pub name: String,
    /// The config fields it changes in the base config (empty: the base config).
    #[serde(default)]
    pub set: toml::Table,
    /// This variant's image size (default: the sweep's).
    pub size: Option<u32>,
}

/// Where a sweep's frames come from.
#[derive(Clone, Debug, PartialEq)]
pub enum Source {
    /// A scene preset name or a scene file, simulated per task.
    Scene(String),
    /// A dataset folder.
    Data(PathBuf),
}

/// One model to train and score: a variant of the base config with a seed, on the labels of
/// one noise level.
#[derive(Clone, Debug, PartialEq)]
pub struct Task {
    /// The task's position in [`Sweep::tasks`] (its array index under Slurm).
    pub index: usize,
    /// `level, variant, seed` in words, for tables and messages.
    pub name: String,
    /// The variant's name.
    pub variant: String,
    /// The label noise the training labels get; `None` without `[noise]` (no noise added).
    pub noise: Option<LabelNoise>,
    /// The training seed (also set in `config`).
    pub seed: u64,
    /// Image size in pixels (the variant's, else the sweep's).
    pub size: u16,
    /// Frames to simulate (a simulated scene; one of the sweep's counts).
    pub frames: u32,
    /// The config to train: the base config with the variant's fields, the seed and the
    /// noise level's label prior.
    pub config: Config,
}

/// A checked sweep description and its tasks.
#[derive(Clone, Debug)]
pub struct Sweep {
    /// The description file (or what stands for it), named in errors.
    pub origin: PathBuf,
    /// Where the frames come from: a simulated scene or a dataset folder.
    pub source: Source,
    /// The frame counts, ascending (one unless the description lists several).
    pub frames: Vec<u32>,
    /// The separate test set, when the description names one (`holdout` is then unused).
    pub test: Option<TestSet>,
    /// Image size, pixels (longest side), for variants without their own.
    pub size: u16,
    /// Every N-th view is held out for scoring (2 or more).
    pub holdout: usize,
    /// Steps fitting each held-out view's embedding.
    pub fit_steps: u32,
    /// Whether the foreground masks are applied.
    pub masks: bool,
    /// The scene box stated by `scene_box` (min, max), world units; `None`: the config
    /// file's, else the data's own, else found from the training views.
    pub scene_box: Option<([f32; 3], [f32; 3])>,
    /// The base config's file, when it is one (a box it sets is used).
    pub config_file: Option<PathBuf>,
    /// The base config with the sweep's steps.
    pub base: Config,
    /// The rotation sweep's levels (attitudes noisy, positions exact); empty without
    /// `[noise]`.
    pub rotation: Vec<LabelNoise>,
    /// The translation sweep's levels (positions noisy, attitudes exact); empty without
    /// `[noise]`.
    pub translation: Vec<LabelNoise>,
    /// Scoring during training and the trade-off report (`[anytime]`).
    pub anytime: Option<Anytime>,
    /// Every task: frame count by noise level by variant by seed, indexed from 0.
    pub tasks: Vec<Task>,
}

/// Largest accepted values: beyond them a value is a typo, not a sweep.
const MAX_FRAMES: u32 = 100_000;
const MAX_SIZE: u32 = 4096;
const MAX_FIT_STEPS: u32 = 100_000;
const MAX_ROTATION_DEG: f32 = 180.0;
const MAX_TRANSLATION_MM: f32 = 100_000.0;
const MAX_TASKS: usize = 100_000;

impl Sweep {
    /// Read and check a description file; relative paths in it are relative to its folder.
    pub fn read(path: &Path) -> Result<Sweep> {
        let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
        Sweep::parse(path, &text)
    }

    /// Check the description `text`, as if read from `path` (named in errors; relative paths
    /// are taken relative to its folder).
    pub fn parse(path: &Path, text: &str) -> Result<Sweep> {
        let table: toml::Table = toml::from_str(text)
            .map_err(|e| HostError::invalid(path, format!("not valid TOML: {}", e.message())))?;
        let description: SweepDescription =
            serde_path_to_error::deserialize(table).map_err(|e| {
                let field = e.path().to_string();
                let reason = e.into_inner().to_string();
                if field == "." {
                    HostError::invalid(path, format!("not a valid sweep description: {reason}"))
                } else {
                    HostError::field(path, field, reason)
                }
            })?;
        let dir = path.parent().unwrap_or(Path::new(""));
        description.check(path, dir)
    }
}

impl Sweep {
    /// The steps after which `task` also scores its held-out views (none without `[anytime]`).
    pub fn score_at(&self, task: &Task) -> Vec<u32> {
        (self.anytime.iter())
            .flat_map(|a| a.steps.iter().copied())
            .filter(|&s| s < task.config.steps)
            .collect()
    }

    /// The sweep's noise levels in task order, each once (`[None]` without `[noise]`).
    pub fn levels(&self) -> Vec<Option<LabelNoise>> {
        let mut levels = Vec::new();
        for task in &self.tasks {
            if !levels.contains(&task.noise) {
                levels.push(task.noise);
            }
        }
        levels
    }
}

impl SweepDescription {
    /// Check every field and expand the tasks. `origin` is named in errors; relative paths are
    /// taken relative to `dir`.
    pub fn check(&self, origin: &Path, dir: &Path) -> Result<Sweep> {
        let field = |name: &str, reason: String| HostError::field(origin, name, reason);
        let relative = |p: &Path| -> PathBuf {
            if p.is_absolute() || dir.as_os_str().is_empty() {
                p.to_path_buf()
            } else {
                dir.join(p)
            }
        };
        // The label noise a simulated scene states (none: exact labels); a folder's labels
        // state none. A task without a noise level of its own sizes its pose prior by it.
        let mut scene_noise: Option<LabelNoise> = None;
        let source = match (&self.scene, &self.data) {
            (Some(_), Some(_)) => {
                return Err(field("data", "give `scene` or `data`, not both".into()));
            }
            (None, None) => {
                return Err(HostError::invalid(
                    origin,
                    "names no frames: give `scene` (a preset or scene file) or `data`",
                ));
            }
            (Some(scene), None) => {
                let is_preset = crate::sim::scene::preset_names().any(|p| p == scene);
                let scene = if is_preset {
                    scene.clone()
                } else {
                    relative(Path::new(scene)).display().to_string()
                };
                let stated = Scene::load(&scene)
                    .map_err(|e| field("scene", e.to_string()))?
                    .spec
                    .effects
                    .label_noise;
                scene_noise = Some(stated.unwrap_or(LabelNoise {
                    rotation_deg: 0.0,
                    translation_m: 0.0,
                }));
                Source::Scene(scene)
            }
            (None, Some(data)) => {
                let data = relative(data);
                if !data.is_dir() {
                    return Err(field("data", format!("{} is not a folder", data.display())));
                }
                Source::Data(data)
            }
        };
        let simulated = matches!(source, Source::Scene(_));
        if !simulated && self.frames.is_some() {
            return Err(field(
                "frames",
                "only a simulated `scene` has a frame count".into(),
            ));
        }
        if !simulated && self.noise.is_some() {
            return Err(field(
                "noise",
                "label noise needs a simulated `scene` (exact poses)".into(),
            ));
        }
        let frames = match &self.frames {
            None => vec![400],
            Some(FrameCounts::One(count)) => vec![*count],
            Some(FrameCounts::Many(counts)) => counts.clone(),
        };
        if frames.is_empty() {
            return Err(field("frames", "empty: give at least one count".into()));
        }
        for (i, &count) in frames.iter().enumerate() {
            if !(2..=MAX_FRAMES).contains(&count) {
                return Err(field(
                    "frames",
                    format!("{count} is not between 2 and {MAX_FRAMES}"),
                ));
            }
            if frames[..i].contains(&count) {
                return Err(field("frames", format!("{count} is listed twice")));
            }
        }
        let mut frames = frames;
        frames.sort_unstable();
        let test = self.test_set(origin, &relative, simulated)?;
        let size = self.size.unwrap_or(128);
        if !(8..=MAX_SIZE).contains(&size) {
            return Err(field(
                "size",
                format!("{size} is not between 8 and {MAX_SIZE} px"),
            ));
        }
        if test.is_some() && self.holdout.is_some() {
            return Err(field(
                "holdout",
                "a sweep with a `test_scene` is scored on it: every frame trains".into(),
            ));
        }
        let holdout = self.holdout.unwrap_or(8);
        if holdout < 2 || (simulated && test.is_none() && holdout > frames[0] as usize) {
            return Err(field(
                "holdout",
                format!("{holdout}: every N-th view is held out, N from 2 to the frame count"),
            ));
        }
        let fit_steps = self.fit_steps.unwrap_or(crate::train::DEFAULT_FIT_STEPS);
        if fit_steps > MAX_FIT_STEPS {
            return Err(field(
                "fit_steps",
                format!("{fit_steps} is more than {MAX_FIT_STEPS}"),
            ));
        }
        let scene_box = (self.scene_box.as_deref())
            .map(parse_box)
            .transpose()
            .map_err(|e| field("scene_box", e))?;
        let (mut base, config_file) = self.base_config(origin, &relative)?;
        if let Some(steps) = self.steps {
            if steps == 0 {
                return Err(field("steps", "0: a model needs at least one step".into()));
            }
            base.steps = steps;
            base.warmup_steps = base.warmup_steps.min(steps);
        }
        let seeds = self.seeds.clone().unwrap_or_else(|| vec![base.seed]);
        if seeds.is_empty() {
            return Err(field("seeds", "empty: give at least one seed".into()));
        }
        if let Some(seed) =
            (1..seeds.len()).find_map(|i| seeds[..i].contains(&seeds[i]).then_some(seeds[i]))
        {
            return Err(field("seeds", format!("{seed} is listed twice")));
        }
        let (rotation, translation) = match &self.noise {
            Some(noise) => noise_levels(origin, noise)?,
            None => (Vec::new(), Vec::new()),
        };
        let variants = if self.variants.is_empty() {
            default_variants(self.noise.is_some())
        } else {
            self.variants.clone()
        };
        let anytime = self
            .anytime
            .as_ref()
            .map(|a| check_anytime(origin, a))
            .transpose()?;
        let mut configs: Vec<(String, Config, u16)> = Vec::new();
        // The longer side of the data's images, read when a variant sets its own size.
        let mut data_side: Option<Option<u32>> = None;
        for (i, variant) in variants.iter().enumerate() {
            let name = variant.name.trim();
            if name.is_empty()
                || !name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || " _+.-=[],".contains(c))
            {
                return Err(field(
                    &format!("variants[{i}].name"),
                    format!(
                        "`{}`: use letters, digits, spaces and _ + . - = [ ] ,",
                        variant.name
                    ),
                ));
            }
            if configs.iter().any(|(n, _, _)| n == name) {
                return Err(field(
                    &format!("variants[{i}].name"),
                    format!("`{name}` is used twice"),
                ));
            }
            let config =
                with_overrides(origin, &format!("variants[{i}].set."), &base, &variant.set)?;
            let variant_size = variant.size.unwrap_or(size);
            if !(8..=MAX_SIZE).contains(&variant_size) {
                return Err(field(
                    &format!("variants[{i}].size"),
                    format!("{variant_size} is not between 8 and {MAX_SIZE} px"),
                ));
            }
            // A size of its own above the data's images would train the same frames again.
            if let (Some(variant_size), Source::Data(data)) = (variant.size, &source) {
                let side = *data_side.get_or_insert_with(|| data_image_side(data));
                if let Some(why) = above_data_side(variant_size, side, data) {
                    return Err(field(&format!("variants[{i}].size"), why));
                }
            }
            configs.push((name.to_string(), config, variant_size as u16));
        }
        // The noise-free level is shared by both sweeps: trained once.
        let mut levels: Vec<Option<LabelNoise>> = Vec::new();
        for &noise in rotation.iter().chain(&translation) {
            if !levels.contains(&Some(noise)) {
                levels.push(Some(noise));
            }
        }
        if levels.is_empty() {
            levels.push(None);
        }
        let count = frames.len() * levels.len() * configs.len() * seeds.len();
        if count > MAX_TASKS {
            return Err(HostError::invalid(
                origin,
                format!("{count} tasks: more than {MAX_TASKS}"),
            ));
        }
        let mut tasks = Vec::with_capacity(count);
        for &count in &frames {
            for level in &levels {
                for (variant, config, size) in &configs {
                    for &seed in &seeds {
                        let mut config = *config;
                        config.seed = seed;
                        // Each task's labels carry its level's noise, else the scene's: the
                        // pose prior is sized by it as `ablate` sizes it (floored at
                        // `LabelNoise::FLOOR_*`), unless the variant sets the prior. A model
                        // without pose correction never reads the scene's: its config stays
                        // the one `train` builds on the same frames.
                        let scene_noise = scene_noise.filter(|_| config.pose_correction);
                        if let Some(noise) = level.or(scene_noise) {
                            noise.state_in(&mut config);
                        }
                        let level_name = level.map_or(String::new(), |n| {
                            format!(
                                "noise {} deg / {} mm, ",
                                n.rotation_deg,
                                n.translation_m * 1000.0
                            )
                        });
                        let count_name = if frames.len() > 1 {
                            format!("{count} images, ")
                        } else {
                            String::new()
                        };
                        tasks.push(Task {
                            index: tasks.len(),
                            name: format!("{count_name}{level_name}{variant}, seed {seed}"),
                            variant: variant.clone(),
                            noise: *level,
                            seed,
                            size: *size,
                            frames: count,
                            config,
                        });
                    }
                }
            }
        }
        Ok(Sweep {
            origin: origin.to_path_buf(),
            source,
            frames,
            test,
            size: size as u16,
            holdout,
            fit_steps,
            masks: self.masks.unwrap_or(true),
            scene_box,
            config_file,
            base,
            rotation,
            translation,
            anytime,
            tasks,
        })
    }
}

impl SweepDescription {
    /// The separate test set the description names (`test_scene`, `test_frames`), checked.
    fn test_set(
        &self,
        origin: &Path,
        relative: &dyn Fn(&Path) -> PathBuf,
        simulated: bool,
    ) -> Result<Option<TestSet>> {
        let field = |name: &str, reason: String| HostError::field(origin, name, reason);
        let Some(name) = &self.test_scene else {
            if self.test_frames.is_some() {
                return Err(field("test_frames", "needs a `test_scene`".into()));
            }
            return match &self.test_data {
                Some(data) => {
                    let data = relative(data);
                    if !data.is_dir() {
                        return Err(field(
                            "test_data",
                            format!("{} is not a folder", data.display()),
                        ));
                    }
                    Ok(Some(TestSet::Data(data)))
                }
                None => Ok(None),
            };
        };
        if self.test_data.is_some() {
            return Err(field(
                "test_data",
                "give `test_scene` or `test_data`, not both".into(),
            ));
        }
        if !simulated {
            return Err(field(
                "test_scene",
                "a separate test set goes with a simulated `scene`".into(),
            ));
        }
        let is_preset = crate::sim::scene::preset_names().any(|p| p == name);
        let scene = if is_preset {
            name.clone()
        } else {
            relative(Path::new(name)).display().to_string()
        };
        let spec = Scene::load(&scene).map_err(|e| field("test_scene", e.to_string()))?;
        let frames = self.test_frames.unwrap_or(spec.spec.frames);
        if !(1..=MAX_FRAMES).contains(&frames) {
            return Err(field(
                "test_frames",
                format!("{frames} is not between 1 and {MAX_FRAMES}"),
            ));
        }
        Ok(Some(TestSet::Scene { scene, frames }))
    }

    /// The base config the description names: `preset` (default `spacecraft`) with the fields
    /// of the `config` file, or the preset `config` names; and the file when there is one.
    fn base_config(
        &self,
        origin: &Path,
        relative: &dyn Fn(&Path) -> PathBuf,
    ) -> Result<(Config, Option<PathBuf>)> {
        let preset = self.preset.as_deref();
        let preset_config =
            || presets::config_of(origin, "preset", preset.unwrap_or(presets::SPACECRAFT));
        let Some(name) = self.config.as_deref() else {
            return Ok((preset_config()?, None));
        };
        if presets::find(name).is_some() {
            if preset.is_some() {
                return Err(HostError::field(
                    origin,
                    "config",
                    format!("`{name}` is a preset and `preset` names one too: give one"),
                ));
            }
            return Ok((presets::config_of(origin, "config", name)?, None));
        }
        let path = relative(Path::new(name));
        if !path.is_file() {
            return Err(HostError::field(
                origin,
                "config",
                format!(
                    "`{name}` is no config file and no preset ({})",
                    presets::names().collect::<Vec<_>>().join(", ")
                ),
            ));
        }
        let config = crate::train::read_config(&path, &preset_config()?)?;
        Ok((config, Some(path)))
    }
}

/// The longer side of the largest image of the dataset folder `data` (from the headers; `None`
/// when none is readable): a larger image size gives the same frames, never upsampled.
pub fn data_image_side(data: &Path) -> Option<u32> {
    crate::memory::largest_image_side(data)
}

/// Why `size` px cannot be asked of the dataset folder `data` whose images are at most `side`
/// px on their longer side (`None`: it can, or the side is unknown, which the loader names).
pub fn above_data_side(size: u32, side: Option<u32>, data: &Path) -> Option<String> {
    let side = side.filter(|&side| size > side)?;
    Some(format!(
        "{size} px is above the data's images ({side} px, {}): frames are never upsampled, so it would train on the {side} px frames again (a repeat of a smaller size); give at most {side}",
        data.display()
    ))
}

/// The paper's models as variants: with noise levels the two the pose-noise sweeps compare,
/// otherwise the ablation's three.
fn default_variants(noise: bool) -> Vec<VariantSpec> {
    let models: &[Variant] = if noise {
        &[APPEARANCE, APPEARANCE_POSE]
    } else {
        &[BASELINE, APPEARANCE, APPEARANCE_POSE]
    };
    models
        .iter()
        .map(|v| VariantSpec {
            name: v.name.to_string(),
            set: toml::Table::from_iter([
                (
                    "embedding_dim".to_string(),
                    toml::Value::Integer(v.embedding_dim.into()),
                ),
                (
                    "pose_correction".to_string(),
                    toml::Value::Boolean(v.pose_correction),
                ),
            ]),
            size: None,
        })
        .collect()
}

/// Largest accepted number of anytime points, targets and budgets.
const MAX_ANYTIME_POINTS: usize = 1000;

/// `[anytime]` checked: steps ascending and above 0, a known quality, finite targets within
/// the quality's range and finite positive budgets, each list ascending.
fn check_anytime(origin: &Path, spec: &AnytimeSpec) -> Result<Anytime> {
    let field = |name: String, reason: String| HostError::field(origin, name, reason);
    let quality = match spec.quality.as_deref() {
        None => Quality::PsnrForeground,
        Some(name) => Quality::ALL
            .into_iter()
            .find(|q| q.name() == name)
            .ok_or_else(|| {
                field(
                    "anytime.quality".into(),
                    format!(
                        "`{name}` is none of {}",
                        Quality::ALL.map(Quality::name).join(", ")
                    ),
                )
            })?,
    };
    for (name, len) in [
        ("steps", spec.steps.len()),
        ("targets", spec.targets.len()),
        ("budgets_s", spec.budgets_s.len()),
    ] {
        if len > MAX_ANYTIME_POINTS {
            return Err(field(
                format!("anytime.{name}"),
                format!("{len} values: more than {MAX_ANYTIME_POINTS}"),
            ));
        }
    }
    for (i, &step) in spec.steps.iter().enumerate() {
        if step == 0 || (i > 0 && step <= spec.steps[i - 1]) {
            return Err(field(
                format!("anytime.steps[{i}]"),
                format!("{step}: steps are above 0 and ascending"),
            ));
        }
    }
    let ascending = |name: &str, values: &[f64], range: std::ops::RangeInclusive<f64>| {
        for (i, &v) in values.iter().enumerate() {
            if !(v.is_finite() && range.contains(&v)) || (i > 0 && v <= values[i - 1]) {
                return Err(field(
                    format!("anytime.{name}[{i}]"),
                    format!(
                        "{v}: values are ascending, from {} to {}",
                        range.start(),
                        range.end()
                    ),
                ));
            }
        }
        Ok(())
    };
    ascending("targets", &spec.targets, 0.0..=quality.max())?;
    ascending("budgets_s", &spec.budgets_s, 1e-3..=1e9)?;
    Ok(Anytime {
        steps: spec.steps.clone(),
        quality,
        targets: spec.targets.clone(),
        budgets_s: spec.budgets_s.clone(),
    })
}

/// The rotation and translation levels as label noise, each checked.
fn noise_levels(origin: &Path, noise: &NoiseLevels) -> Result<(Vec<LabelNoise>, Vec<LabelNoise>)> {
    let check = |name: &str, levels: &[f32], max: f32| -> Result<()> {
        match levels
            .iter()
            .position(|l| !(l.is_finite() && (0.0..=max).contains(l)))
        {
            Some(i) => Err(HostError::field(
                origin,
                format!("noise.{name}[{i}]"),
                format!("{} is not a noise level from 0 to {max}", levels[i]),
            )),
            None => Ok(()),
        }
    };
    check("rotation_deg", &noise.rotation_deg, MAX_ROTATION_DEG)?;
    check("translation_mm", &noise.translation_mm, MAX_TRANSLATION_MM)?;
    if noise.rotation_deg.is_empty() && noise.translation_mm.is_empty() {
        return Err(HostError::field(
            origin,
            "noise",
            "no level: give rotation_deg, translation_mm or both",
        ));
    }
    let rotation = (noise.rotation_deg.iter())
        .map(|&deg| LabelNoise {
            rotation_deg: deg,
            translation_m: 0.0,
        })
        .collect();
    let translation = (noise.translation_mm.iter())
        .map(|&mm| LabelNoise {
            rotation_deg: 0.0,
            translation_m: mm / 1000.0,
        })
        .collect();
    Ok((rotation, translation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `text` written as `sweep.toml` in a fresh folder, read and checked.
    fn read(text: &str) -> (tempfile::TempDir, Result<Sweep>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sweep.toml");
        std::fs::write(&path, text).unwrap();
        let sweep = Sweep::read(&path);
        (dir, sweep)
    }

    #[test]
    fn a_description_expands_into_levels_times_variants_times_seeds() {
        let (_dir, sweep) = read(
            r#"
scene = "synthetic"
frames = 16
size = 48
config = "tiny"
steps = 30
seeds = [3, 4]

[noise]
rotation_deg = [0, 1.6]
translation_mm = [0, 16]

[[variants]]
name = "ours"
set = { embedding_dim = 8 }

[[variants]]
name = "ours + pose"
set = { embedding_dim = 8, pose_correction = true, learning_rate = 0.02 }
"#,
        );
        let sweep = sweep.unwrap();
        // The noise-free level is shared: 3 levels x 2 variants x 2 seeds.
        assert_eq!(sweep.tasks.len(), 12);
        assert_eq!(sweep.levels().len(), 3);
        assert_eq!((sweep.rotation.len(), sweep.translation.len()), (2, 2));
        assert_eq!(sweep.translation[1].translation_m, 0.016);
        for (i, task) in sweep.tasks.iter().enumerate() {
            assert_eq!(task.index, i);
            assert_eq!(task.config.steps, 30);
            assert_eq!(task.config.seed, [3, 4][i % 2]);
            assert_eq!(task.config.embedding_dim, 8);
            assert_eq!(task.config.pose_correction, task.variant == "ours + pose");
            let lr = if task.config.pose_correction {
                0.02
            } else {
                sweep.base.learning_rate
            };
            assert_eq!(task.config.learning_rate, lr);
        }
        let last = sweep.tasks.last().unwrap();
        assert_eq!(last.name, "noise 0 deg / 16 mm, ours + pose, seed 4");
        assert_eq!(
            last.noise,
            Some(LabelNoise {
                rotation_deg: 0.0,
                translation_m: 0.016
            })
        );
    }

    /// The image-count study: one task per count (ascending), model and seed; the tasks of a
    /// model and seed differ only in their count; a separate test set replaces the hold-out.
    #[test]
    fn an_image_count_sweep_has_tasks_that_differ_only_in_the_count() {
        let (_dir, sweep) = read(
            "scene = \"synthetic\"\nframes = [100, 25, 50]\ntest_scene = \"lightbox-test\"\n\
             test_frames = 20\nseeds = [1, 2]\n",
        );
        let sweep = sweep.unwrap();
        assert_eq!(sweep.frames, [25, 50, 100]);
        assert_eq!(
            sweep.test,
            Some(TestSet::Scene {
                scene: "lightbox-test".into(),
                frames: 20
            })
        );
        assert_eq!(sweep.tasks.len(), 3 * 3 * 2);
        assert_eq!(sweep.tasks[0].name, "25 images, baseline, seed 1");
        let per_count = sweep.tasks.len() / 3;
        for (i, task) in sweep.tasks.iter().enumerate() {
            assert_eq!(task.frames, sweep.frames[i / per_count], "{}", task.name);
            let first = &sweep.tasks[i % per_count];
            let same = |t: &Task| (t.variant.clone(), t.seed, t.size, t.noise, t.config);
            assert_eq!(same(task), same(first), "{} vs {}", task.name, first.name);
        }
        let refused = |text: &str, field: &str| {
            let (_dir, sweep) = read(text);
            let error = sweep.unwrap_err().to_string();
            assert!(
                error.contains(&format!("field `{field}`")),
                "{text}: {error}"
            );
        };
        refused("scene = \"synthetic\"\nframes = []\n", "frames");
        refused("scene = \"synthetic\"\nframes = [8, 8]\n", "frames");
        refused("scene = \"synthetic\"\nframes = [8, 1]\n", "frames");
        refused("scene = \"synthetic\"\ntest_frames = 8\n", "test_frames");
        refused(
            "scene = \"synthetic\"\ntest_scene = \"lightbox-test\"\nholdout = 4\n",
            "holdout",
        );
        refused(
            "scene = \"synthetic\"\ntest_scene = \"lightbox-test\"\ntest_frames = 0\n",
            "test_frames",
        );
        refused(
            "scene = \"synthetic\"\ntest_scene = \"nowhere.toml\"\n",
            "test_scene",
        );
        refused(
            "data = \".\"\ntest_scene = \"lightbox-test\"\n",
            "test_scene",
        );
        refused(
            "scene = \"synthetic\"\ntest_data = \"nowhere\"\n",
            "test_data",
        );
        refused(
            "scene = \"synthetic\"\ntest_scene = \"lightbox-test\"\ntest_data = \".\"\n",
            "test_data",
        );
        // A folder of any format is a test set of its own, beside a scene or data.
        let (dir, sweep) = read("data = \".\"\ntest_data = \".\"\n");
        assert_eq!(
            sweep.unwrap().test,
            Some(TestSet::Data(dir.path().join(".")))
        );
    }

    #[test]
    fn anytime_steps_past_a_tasks_end_are_left_to_its_end() {
        let (_dir, sweep) = read(
            "scene = \"synthetic\"\nsteps = 100\n[anytime]\nsteps = [10, 100, 150]\n\
             [[variants]]\nname = \"short\"\nset = { steps = 50 }\n\
             [[variants]]\nname = \"long\"\nset = { steps = 200 }\nsize = 64\n",
        );
        let sweep = sweep.unwrap();
        let anytime = sweep.anytime.as_ref().unwrap();
        assert_eq!(anytime.quality, Quality::PsnrForeground);
        assert_eq!(sweep.score_at(&sweep.tasks[0]), [10]);
        assert_eq!(sweep.score_at(&sweep.tasks[1]), [10, 100, 150]);
        assert_eq!((sweep.tasks[0].size, sweep.tasks[1].size), (128, 64));
    }

    #[test]
    fn without_variants_the_papers_models_are_swept() {
        let (_dir, ablation) = read("scene = \"lightbox\"\n");
        let names: Vec<String> = ablation
            .unwrap()
            .tasks
            .into_iter()
            .map(|t| t.variant)
            .collect();
        assert_eq!(names, ["baseline", "ours", "ours + pose"]);
        let (_dir, noise) = read("scene = \"synthetic\"\n[noise]\nrotation_deg = [0.2]\n");
        let tasks = noise.unwrap().tasks;
        let names: Vec<&str> = tasks.iter().map(|t| t.variant.as_str()).collect();
        assert_eq!(names, ["ours", "ours + pose"]);
        assert_eq!(
            tasks[1].config.embedding_dim,
            crate::ablation::EMBEDDING_DIM
        );
        assert!(tasks[1].config.pose_correction);
        assert_eq!(tasks[0].config, {
            let mut c = Config::SPACECRAFT;
            c.embedding_dim = crate::ablation::EMBEDDING_DIM;
            // The level's label noise is the pose prior (its position part at the floor).
            c.pose_prior_rotation_deg = 0.2;
            c.pose_prior_position = LabelNoise::FLOOR_TRANSLATION_M;
            c
        });
    }

    /// A task without a noise level of its own trains on the labels its scene states (the
    /// `inspection` preset's 0.8 degrees and 10 mm), and its pose prior is sized by them as
    /// `ablate` sizes it; exact labels get the floor; a variant's own prior stays, and one
    /// without pose correction gets none.
    #[test]
    fn a_scenes_stated_label_noise_sizes_the_prior_of_tasks_without_a_level() {
        let prior = |text: &str| -> Vec<(f32, f32)> {
            let (_dir, sweep) = read(text);
            (sweep.unwrap().tasks.iter())
                .map(|t| {
                    (
                        t.config.pose_prior_rotation_deg,
                        t.config.pose_prior_position,
                    )
                })
                .collect()
        };
        let pose = "[[variants]]\nname = \"pose\"\nset = { pose_correction = true }\n";
        assert_eq!(
            prior(&format!("scene = \"inspection\"\n{pose}")),
            [(0.8, 0.01)]
        );
        let floor = (
            LabelNoise::FLOOR_ROTATION_DEG,
            LabelNoise::FLOOR_TRANSLATION_M,
        );
        assert_eq!(prior(&format!("scene = \"synthetic\"\n{pose}")), [floor]);
        let plain = "[[variants]]\nname = \"plain\"\nset = { pose_correction = false }\n";
        assert_eq!(
            prior(&format!("scene = \"inspection\"\n{plain}")),
            [(0.0, 0.0)]
        );
        let own = "[[variants]]\nname = \"own\"\n\
                   set = { pose_correction = true, pose_prior_rotation_deg = 3.0 }\n";
        assert_eq!(
            prior(&format!("scene = \"inspection\"\n{own}")),
            [(3.0, 0.0)]
        );
    }

    #[test]
    fn every_bad_field_is_an_error_naming_the_file_and_the_field() {
        let scene = "scene = \"synthetic\"\n";
        let cases: Vec<(String, &str)> = vec![
            (format!("{scene}size = 0"), "size"),
            (format!("{scene}size = -3"), "size"),
            (format!("{scene}size = 100000"), "size"),
            (format!("{scene}frames = 1"), "frames"),
            (format!("{scene}frames = 1e9"), "frames"),
            (format!("{scene}steps = 0"), "steps"),
            (format!("{scene}holdout = 1"), "holdout"),
            (format!("{scene}frames = 8\nholdout = 9"), "holdout"),
            (format!("{scene}fit_steps = 1000000"), "fit_steps"),
            (format!("{scene}seeds = []"), "seeds"),
            (format!("{scene}seeds = [1, 2, 1]"), "seeds"),
            (format!("{scene}config = \"huge\""), "config"),
            (format!("{scene}preset = \"huge\""), "preset"),
            (
                format!("{scene}preset = \"tiny\"\nconfig = \"default\""),
                "config",
            ),
            (format!("{scene}scene_box = \"0,0,0,1,1\""), "scene_box"),
            (
                format!("{scene}[noise]\nrotation_deg = [0, inf]"),
                "noise.rotation_deg[1]",
            ),
            (
                format!("{scene}[noise]\nrotation_deg = [nan]"),
                "noise.rotation_deg[0]",
            ),
            (
                format!("{scene}[noise]\ntranslation_mm = [-1]"),
                "noise.translation_mm[0]",
            ),
            (
                format!("{scene}[noise]\nrotation_deg = [200]"),
                "noise.rotation_deg[0]",
            ),
            (format!("{scene}[noise]"), "noise"),
            (format!("{scene}[noise]\nsideways = [1]"), "noise.sideways"),
            (
                format!("{scene}[[variants]]\nname = \"\""),
                "variants[0].name",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a|b\""),
                "variants[0].name",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\n[[variants]]\nname = \"a\""),
                "variants[1].name",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nset = {{ lerning_rate = 0.1 }}"),
                "variants[0].set.lerning_rate",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nset = {{ steps = \"many\" }}"),
                "variants[0].set.steps",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nset = {{ learning_rate = inf }}"),
                "variants[0].set.learning_rate",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nset = {{ features = 0 }}"),
                "variants[0].set.features",
            ),
            (format!("{scene}[anytime]\nsteps = [0]"), "anytime.steps[0]"),
            (
                format!("{scene}[anytime]\nsteps = [5, 5]"),
                "anytime.steps[1]",
            ),
            (
                format!("{scene}[anytime]\nsteps = [-1]"),
                "anytime.steps[0]",
            ),
            (
                format!("{scene}[anytime]\nquality = \"psnr\""),
                "anytime.quality",
            ),
            (
                format!("{scene}[anytime]\ntargets = [inf]"),
                "anytime.targets[0]",
            ),
            (
                format!("{scene}[anytime]\ntargets = [0.5, 2]\nquality = \"ssim_full\""),
                "anytime.targets[1]",
            ),
            (
                format!("{scene}[anytime]\nbudgets_s = [-1]"),
                "anytime.budgets_s[0]",
            ),
            (
                format!("{scene}[anytime]\nbudgets_s = [60, 30]"),
                "anytime.budgets_s[1]",
            ),
            (
                format!("{scene}[anytime]\nsteps = [1]\nsooner = 1"),
                "anytime.sooner",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nsize = 4"),
                "variants[0].size",
            ),
            (
                format!("{scene}[[variants]]\nname = \"a\"\nsize = 1e9"),
                "variants[0].size",
            ),
            ("scene = \"no-such-scene\"".into(), "scene"),
            ("scene = \"synthetic\"\ndata = \".\"".into(), "data"),
            ("data = \"no-such-folder\"".into(), "data"),
            ("data = \".\"\nframes = 8".into(), "frames"),
            ("data = \".\"\n[noise]\nrotation_deg = [1]".into(), "noise"),
        ];
        for (text, field) in cases {
            let (dir, sweep) = read(&text);
            let error = sweep
                .err()
                .unwrap_or_else(|| panic!("accepted:\n{text}"))
                .to_string();
            let file = dir.path().join("sweep.toml").display().to_string();
            assert!(
                error.starts_with(&file) && error.contains(&format!("field `{field}`")),
                "{text}\n=> {error}"
            );
        }
        // Whole-file errors still name the file.
        for text in [
            "size = 3",
            "scene = \"synthetic\"\nsizes = 3",
            "scene = [",
            "scene = \"synthetic\"\nseeds = 3",
        ] {
            let (dir, sweep) = read(text);
            let error = sweep
                .err()
                .unwrap_or_else(|| panic!("accepted:\n{text}"))
                .to_string();
            assert!(
                error.starts_with(&dir.path().join("sweep.toml").display().to_string()),
                "{error}"
            );
        }
    }

    #[test]
    fn a_variant_size_above_the_datas_images_is_refused() {
        let (dir, _) = read("");
        std::fs::create_dir(dir.path().join("frames")).unwrap();
        image::RgbImage::new(40, 20)
            .save(dir.path().join("frames/a.png"))
            .unwrap();
        let path = dir.path().join("sweep.toml");
        let with_size = |size: u32| {
            std::fs::write(
                &path,
                format!("data = \"frames\"\n[[variants]]\nname = \"a\"\nsize = {size}\n"),
            )
            .unwrap();
            Sweep::read(&path)
        };
        assert_eq!(with_size(40).unwrap().tasks[0].size, 40);
        let error = with_size(41).unwrap_err().to_string();
        assert!(
            error.starts_with(&path.display().to_string())
                && error.contains("field `variants[0].size`")
                && error.contains("41 px is above the data's images (40 px"),
            "{error}"
        );
        // The sweep's own size (128 by default) is the longest side asked, not refused.
        std::fs::write(&path, "data = \"frames\"\nsize = 256\n").unwrap();
        assert!(Sweep::read(&path).is_ok());
    }

    #[test]
    fn relative_paths_are_relative_to_the_description() {
        let (dir, _) = read("");
        std::fs::create_dir(dir.path().join("frames")).unwrap();
        std::fs::write(
            dir.path().join("model.toml"),
            include_str!("../../../budgets/tiny.toml"),
        )
        .unwrap();
        let path = dir.path().join("sweep.toml");
        std::fs::write(&path, "data = \"frames\"\nconfig = \"model.toml\"\n").unwrap();
        let sweep = Sweep::read(&path).unwrap();
        assert_eq!(sweep.source, Source::Data(dir.path().join("frames")));
        assert_eq!(sweep.config_file, Some(dir.path().join("model.toml")));
        assert_eq!(sweep.base.features, 8);
    }

    #[test]
    fn a_config_file_changes_the_fields_it_names_in_the_preset() {
        let (dir, _) = read("");
        std::fs::write(dir.path().join("partial.toml"), "steps = 7\n").unwrap();
        let path = dir.path().join("sweep.toml");
        // The preset's warm-up shortened to the steps, as `--steps` does.
        let with_steps = |preset: &str| Config {
            steps: 7,
            warmup_steps: 7,
            ..presets::find(preset).unwrap().config().unwrap()
        };
        for (preset, expected) in [
            ("", with_steps(presets::SPACECRAFT)),
            ("preset = \"tiny\"\n", with_steps("tiny")),
        ] {
            std::fs::write(
                &path,
                format!("scene = \"synthetic\"\n{preset}config = \"partial.toml\"\n"),
            )
            .unwrap();
            assert_eq!(Sweep::read(&path).unwrap().base, expected, "{preset}");
        }
    }
}
