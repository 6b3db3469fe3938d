//! From a dataset folder to a scored model in one place, for the CLI and for any program that
//! embeds the host: the data settings a run folder remembers (`run.toml`), the preset and
//! scene-box rules, the memory-checked arena, the one training loop (with an [`Observer`] for
//! progress and stop requests) and a whole training run ([`Pipeline`]: open, train, refine the
//! poses, save, score, write `metrics.json`).
//!
//! ```no_run
//! use orbit_nerf_host::pipeline::{DataSettings, Pipeline, TrainOptions, Outcome};
//! # fn main() -> orbit_nerf_host::Result<()> {
//! let settings = DataSettings::new("path/to/dataset");
//! let config = orbit_nerf_host::pipeline::choose_config(None, &settings.data, None)?;
//! let pipeline = Pipeline::open(settings, config, None, None)?;
//! let options = TrainOptions::default();
//! if let Outcome::Finished(run) = pipeline.train("runs/mine".as_ref(), &options, &mut ())? {
//!     println!("held-out PSNR {:.2} dB", run.mean.psnr_full);
//! }
//! # Ok(())
//! # }
//! ```

use crate::dataset::{self, Dataset, Frame};
use crate::formats::{self, Format};
use crate::geometry::extract::{self, SurfaceOptions};
use crate::memory::Part;
use crate::report::{
    self, Figures, ModelFigures, PoseRefinementFigures, TrainingFigures, ViewMetrics,
};
use crate::scene_box::{self, StatedBox};
use crate::train::{self, RayonExecutor, ViewScore};
use crate::{HostError, Result, io, memory, presets};
use orbit_nerf_core::{Config, Executor, MemoryPlan, PoseFit, StepReport, Trainer};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// The checkpoint's name in a run folder.
pub const CHECKPOINT_FILE: &str = "checkpoint.onrf";
/// The data settings' name in a run folder.
pub const RUN_FILE: &str = "run.toml";
/// Default longest image side, pixels, for every command that reads or simulates a dataset.
pub const DEFAULT_SIZE: u32 = 128;
/// Default hold-out: every 8th view.
pub const DEFAULT_HOLDOUT: usize = 8;
/// NeRF-synthetic is composited on white; spacecraft scenes have a black sky (their loaders
/// set that themselves).
pub const NERF_BACKGROUND: [f32; 3] = [1.0; 3];

/// How a dataset folder is read: what a run folder remembers beside its checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSettings {
    /// The dataset folder (NeRF-synthetic, nerfstudio or SPEED+/SHIRT).
    pub data: PathBuf,
    /// Longest image side in pixels (smaller images keep their size: never upsampled).
    pub size: u32,
    /// Every N-th view (0, N, 2N, ...) is held out for evaluation.
    pub holdout: usize,
    /// Where a frame has a mask, its background pixels get the background colour.
    pub masks: bool,
}

/// A dataset with its training and held-out view indices.
pub struct SplitData {
    /// Every frame as read (masks already applied where asked).
    pub dataset: Dataset,
    /// Every frame's exact pose, when the data has them (`truth.json`).
    pub truth: Option<Vec<orbit_nerf_core::Pose>>,
    /// Indices into `dataset.frames` of the training views.
    pub train: Vec<usize>,
    /// Indices into `dataset.frames` of the held-out (scored) views.
    pub test: Vec<usize>,
    /// How many views a mask was applied to.
    pub masked: usize,
}

impl DataSettings {
    /// The folder `data` with the default size, hold-out and masks.
    pub fn new(data: impl Into<PathBuf>) -> DataSettings {
        DataSettings {
            data: data.into(),
            size: DEFAULT_SIZE,
            holdout: DEFAULT_HOLDOUT,
            masks: true,
        }
    }

    /// Check the memory the images will take (from their headers), with the parts a command
    /// holds `beside` them, against `limit` (default: a share of the machine's memory)
    /// before they are read.
    pub fn check_memory(&self, limit: Option<u64>, beside: &[Part]) -> Result<()> {
        let mut parts = memory::dataset_parts(&self.data, Some(self.size)).to_vec();
        parts.extend_from_slice(beside);
        memory::check_plan(&self.data, &parts, memory::limit_or_default(limit))
    }

    /// Read the dataset, apply its masks (unless `masks` is off) and split it.
    pub fn open(&self) -> Result<SplitData> {
        let (mut dataset, truth) =
            formats::open_with_truth(&self.data, Some(self.size), NERF_BACKGROUND)?;
        if dataset.frames.is_empty() {
            return Err(HostError::invalid(&self.data, "no frames"));
        }
        let masked = if self.masks { dataset.apply_masks() } else { 0 };
        let (train, test) = dataset::split_every(dataset.frames.len(), self.holdout);
        Ok(SplitData {
            dataset,
            truth,
            train,
            test,
            masked,
        })
    }
}

impl SplitData {
    /// What the data holds in memory while a model trains on it or is scored against it:
    /// the images as loaded, and the held-out views' renders (RGB f32) kept for the report.
    pub fn resident_parts(&self) -> [memory::Part; 2] {
        let frames = &self.dataset.frames;
        let loaded = (frames.iter())
            .map(|f| (f.pixels.len() + f.mask.as_ref().map_or(0, Vec::len)) as u64)
            .sum();
        let renders = (self.test.iter())
            .filter_map(|&i| frames.get(i))
            .map(|f| f.camera.width as u64 * f.camera.height as u64 * 12)
            .sum();
        [("images loaded", loaded), ("held-out renders", renders)]
    }

    /// The line saying where masks were applied, if anywhere.
    pub fn mask_note(&self) -> Option<String> {
        (self.masked > 0).then(|| {
            format!(
                "masks applied: background colour where the mask is 0 on {} views (--no-masks keeps the sky)",
                self.masked
            )
        })
    }

    /// The line saying where held-out views are scored: at their exact poses when the data
    /// has them, else at their labels.
    pub fn scored_at(&self) -> &'static str {
        match self.truth {
            Some(_) => {
                "held-out views scored at their exact poses (truth.json), as the paper's test set is"
            }
            None => "held-out views scored at their labels (the data has no exact poses)",
        }
    }

    fn training_frames(&self) -> Vec<&Frame> {
        self.train
            .iter()
            .map(|&i| &self.dataset.frames[i])
            .collect()
    }
}

/// What a training run folder remembers beside its checkpoint (`run.toml`), so that `eval`,
/// `render`, `export` and `train --resume` need only the folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunRecord {
    /// How the data was read; `data` is absolute.
    pub data: DataSettings,
    /// The data's format, as the folder's layout told it.
    pub format: String,
    /// The preset the config started from.
    pub preset: String,
    /// The scene box trained in (min, max), world units.
    pub scene_box: [[f32; 3]; 2],
}

/// The data flags as given on a command line: `None` where a flag was left out.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DataChoice {
    /// `--data`: the dataset folder.
    pub data: Option<PathBuf>,
    /// `--size`: longest image side, pixels (default [`DEFAULT_SIZE`]).
    pub size: Option<u32>,
    /// `--holdout`: every N-th view is held out (default [`DEFAULT_HOLDOUT`]).
    pub holdout: Option<usize>,
    /// `--no-masks` was given.
    pub no_masks: bool,
}

impl DataChoice {
    /// The settings of a run on the given data: the flags, the defaults where left out;
    /// `None` without a data folder.
    pub fn settings(&self) -> Option<DataSettings> {
        Some(DataSettings {
            data: self.data.clone()?,
            size: self.size.unwrap_or(DEFAULT_SIZE),
            holdout: self.holdout.unwrap_or(DEFAULT_HOLDOUT),
            masks: !self.no_masks,
        })
    }
}

/// The checkpoint and the data settings of a command that reads a model and a dataset:
/// with `run` (a `train` run folder) its checkpoint and its recorded data (the flags given
/// must agree with it); else `checkpoint` and the data flags. `verb` says what the command
/// does with the run (`resume`, `score`, `render`), for the error of a flag that disagrees.
pub fn checkpoint_and_data(
    run: Option<&Path>,
    checkpoint: Option<&Path>,
    given: &DataChoice,
    verb: &str,
) -> Result<(PathBuf, DataSettings)> {
    match (run, checkpoint) {
        (Some(run), _) => {
            let record = RunRecord::read(run)?;
            let settings = record.settings_for(run, given, verb)?;
            Ok((run.join(CHECKPOINT_FILE), settings))
        }
        (None, Some(checkpoint)) => {
            let settings = given.settings().ok_or_else(|| {
                HostError::invalid(
                    checkpoint,
                    "--data is needed with --checkpoint (or give --run DIR, a `train` run folder that remembers its data)",
                )
            })?;
            Ok((checkpoint.to_path_buf(), settings))
        }
        (None, None) => Err(HostError::invalid(
            Path::new("--run"),
            "give --run DIR (a `train` run folder) or --checkpoint FILE with --data",
        )),
    }
}

impl RunRecord {
    /// The record of a run on `settings` (its folder made absolute) with `config`.
    pub fn new(settings: &DataSettings, preset: &str, config: &Config) -> Result<RunRecord> {
        let data =
            std::fs::canonicalize(&settings.data).map_err(|e| HostError::io(&settings.data, e))?;
        Ok(RunRecord {
            format: Format::of(&data).folder().to_string(),
            data: DataSettings {
                data,
                ..settings.clone()
            },
            preset: preset.to_string(),
            scene_box: [config.aabb_min, config.aabb_max],
        })
    }

    /// Read `run`'s record; errors name the file and the field.
    pub fn read(run: &Path) -> Result<RunRecord> {
        let path = run.join(RUN_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => HostError::invalid(
                &path,
                "no such file: not a run folder of `train` (give --data and --checkpoint instead)",
            ),
            _ => HostError::io(&path, e),
        })?;
        let record: RunRecord = toml::from_str(&text)
            .map_err(|e| HostError::invalid(&path, format!("not a run record: {}", e.message())))?;
        let settings = &record.data;
        if settings.size == 0 || settings.holdout == 0 {
            let field = if settings.size == 0 {
                "size"
            } else {
                "holdout"
            };
            return Err(HostError::field(
                &path,
                format!("data.{field}"),
                "must be 1 or more",
            ));
        }
        Ok(record)
    }

    /// Write the record into `run` (atomically).
    pub fn write(&self, run: &Path) -> Result<()> {
        let path = run.join(RUN_FILE);
        let text = toml::to_string(self)
            .map_err(|e| HostError::invalid(&path, format!("encoding failed: {e}")))?;
        io::write_atomic(&path, text.as_bytes())
    }

    /// The recorded settings, with the data flags `given` checked against them (a flag
    /// given must say what the run recorded). `run` names the run, `verb` what is done with it.
    pub fn settings_for(&self, run: &Path, given: &DataChoice, verb: &str) -> Result<DataSettings> {
        if let Some(data) = &given.data {
            self.check_data(run, data, verb)?;
        }
        let recorded = &self.data;
        let disagree = |field: &str, given: String, recorded: String| {
            Err(HostError::field(
                run.join(RUN_FILE),
                format!("data.{field}"),
                format!(
                    "the run was trained with {recorded}, not {given}; {verb} with the run's --data, --size, --holdout and masks, or leave them out (the run remembers them)"
                ),
            ))
        };
        if let Some(size) = given.size.filter(|&s| s != recorded.size) {
            return disagree(
                "size",
                format!("--size {size}"),
                format!("--size {}", recorded.size),
            );
        }
        if let Some(holdout) = given.holdout.filter(|&h| h != recorded.holdout) {
            return disagree(
                "holdout",
                format!("--holdout {holdout}"),
                format!("--holdout {}", recorded.holdout),
            );
        }
        if given.no_masks && recorded.masks {
            return disagree("masks", "--no-masks".into(), "masks applied".into());
        }
        Ok(recorded.clone())
    }

    /// Refuse a `data` folder other than the one the run trained on (`run` names the run).
    pub fn check_data(&self, run: &Path, data: &Path, verb: &str) -> Result<()> {
        let given = std::fs::canonicalize(data).map_err(|e| HostError::io(data, e))?;
        if given != self.data.data {
            return Err(HostError::field(
                run.join(RUN_FILE),
                "data.data",
                format!(
                    "the run trained on {}, not {}; {verb} with the run's --data, --size, --holdout and masks, or leave them out (the run remembers them); --checkpoint FILE --data DIR uses a model on other data",
                    self.data.data.display(),
                    data.display()
                ),
            ));
        }
        Ok(())
    }
}

/// A model config and where it came from.
#[derive(Clone, Debug)]
pub struct ChosenConfig {
    /// The config: the preset's, with the config file's fields on top when one was given.
    pub config: Config,
    /// The preset it started from.
    pub preset: &'static str,
    /// One line saying which preset and why, and the file on top.
    pub note: String,
}

/// The config of a run: the preset `chosen`, else `default`, the preset for the run's data
/// (`data` says what data); with a config file's fields on top.
pub fn preset_config(
    chosen: Option<&str>,
    default: &'static str,
    data: &str,
    file: Option<&Path>,
) -> Result<ChosenConfig> {
    let names = || presets::names().collect::<Vec<_>>().join(", ");
    let (name, why) = match chosen {
        Some(name) => (name, "--preset".to_string()),
        None => (
            default,
            format!("{data}; --preset to choose another: {}", names()),
        ),
    };
    let preset = presets::find(name).ok_or_else(|| {
        HostError::invalid(
            Path::new("--preset"),
            format!("{name}: no such preset ({})", names()),
        )
    })?;
    let config = match file {
        Some(path) => train::read_config(path, &preset.config()?)?,
        None => preset.config()?,
    };
    let on_top = file.map_or(String::new(), |path| {
        format!(", with the fields of {} on top", path.display())
    });
    Ok(ChosenConfig {
        config,
        preset: preset.name,
        note: format!("config: preset {} ({why}){on_top}", preset.name),
    })
}

/// [`preset_config`] for a run on the dataset `data`: the preset for its format, told from the
/// folder's layout (nothing is read), unless `chosen`.
pub fn choose_config(
    chosen: Option<&str>,
    data: &Path,
    file: Option<&Path>,
) -> Result<ChosenConfig> {
    let format = Format::of(data);
    preset_config(chosen, presets::for_format(format), format.folder(), file)
}

/// The scene box the user stated: `flag` (`--scene-box`), else a config file's box.
pub fn stated_box(
    flag: Option<([f32; 3], [f32; 3])>,
    config_file: Option<&Path>,
) -> Result<Option<StatedBox>> {
    Ok(match (flag, config_file) {
        (Some((min, max)), _) => Some(StatedBox {
            min,
            max,
            by: "--scene-box".into(),
        }),
        (None, Some(path)) => train::config_scene_box(path)?.map(|(min, max)| StatedBox {
            min,
            max,
            by: format!("the config file {}", path.display()),
        }),
        (None, None) => None,
    })
}

/// Set `dataset`'s scene box by the rule: `flag` (`--scene-box`), else a config file that
/// sets one, else the data's own, else found from the training views `train_idx`. Returns
/// one line saying the box and why.
pub fn choose_box(
    dataset: &mut Dataset,
    flag: Option<([f32; 3], [f32; 3])>,
    config_file: Option<&Path>,
    train_idx: &[usize],
) -> Result<String> {
    let stated = stated_box(flag, config_file)?;
    scene_box::choose_scene_box(dataset, stated, train_idx)
}

/// The fields of a config a user overrides on the command line (`None`: the config's own).
#[derive(Clone, Copy, Debug, Default)]
pub struct Overrides {
    /// Training steps (the warm-up is cut to them).
    pub steps: Option<u32>,
    /// Random seed.
    pub seed: Option<u64>,
    /// Appearance embedding size per frame (0 disables it).
    pub embedding_dim: Option<u16>,
    /// Learn a pose correction per frame.
    pub pose_correction: Option<bool>,
}

impl Overrides {
    /// `config` with these fields set.
    pub fn apply(&self, config: &mut Config) {
        if let Some(steps) = self.steps {
            config.steps = steps;
            config.warmup_steps = config.warmup_steps.min(steps);
        }
        if let Some(seed) = self.seed {
            config.seed = seed;
        }
        if let Some(dim) = self.embedding_dim {
            config.embedding_dim = dim;
        }
        if let Some(on) = self.pose_correction {
            config.pose_correction = on;
        }
    }
}

/// Score `views` of `data` with the checkpoint at `path` (restored with its own config), at
/// their exact poses when the data has them, fitting each view's embedding (and with
/// `align_poses` its pose correction) for `fit_steps`; renders go to `renders` when given.
/// The model, the data and the renders are checked against `memory_limit` together first.
pub fn evaluate_checkpoint(
    path: &Path,
    (threads, memory_limit): (usize, Option<u64>),
    data: &SplitData,
    views: &[usize],
    (fit_steps, align_poses): (u32, bool),
    renders: Option<&Path>,
) -> Result<Vec<ViewScore>> {
    let executor = RayonExecutor::new(threads)?;
    let resident = data.resident_parts();
    with_checkpoint(path, memory_limit, &resident, |trainer| {
        train::evaluate_at(
            trainer,
            &executor,
            &data.dataset,
            views,
            data.truth.as_deref(),
            (fit_steps, align_poses),
            renders,
        )
    })
}

/// The surface of the density of the checkpoint at `checkpoint` as a coloured mesh (the mean
/// training embedding's colours), sampled on `options`' grid with `threads` workers. The
/// model and the grid are checked against `memory_limit` together before either is
/// allocated, and the mesh once its cells are counted; the threshold used goes to `say`.
pub fn extract_surface(
    checkpoint: &Path,
    options: &SurfaceOptions,
    (threads, memory_limit): (usize, Option<u64>),
    say: &mut dyn FnMut(String),
) -> Result<crate::geometry::Mesh> {
    let executor = RayonExecutor::new(threads)?;
    let grid = extract::grid_parts(&checkpoint_config(checkpoint)?, options);
    with_checkpoint(checkpoint, memory_limit, &grid, |trainer| {
        let mut embedding = vec![0.0f32; trainer.config().embedding_dim as usize];
        trainer.mean_embedding(&mut embedding);
        say(format!(
            "surface at density {:.4} on a grid of {} samples along the longest side",
            extract::threshold(trainer, options),
            options.resolution
        ));
        crate::geometry::extract_surface(
            trainer,
            &executor,
            &embedding,
            options,
            checkpoint,
            memory::limit_or_default(memory_limit),
        )
    })
}

/// A trainer over a fresh arena of `config`, with `frames` loaded into slots 0, 1, ...; the
/// arena and the `resident` parts the caller holds beside it (its data, its outputs) are
/// checked against `memory_limit` (or a share of the machine's memory) before the arena is
/// allocated, an error naming `what`.
pub fn with_trainer<R, E: From<HostError>>(
    what: &Path,
    (config, memory_limit): (Config, Option<u64>),
    resident: &[Part],
    frames: &[&Frame],
    f: impl FnOnce(&mut Trainer<'_>) -> std::result::Result<R, E>,
) -> std::result::Result<R, E> {
    let plan = MemoryPlan::new(&config);
    memory::check_plan(
        what,
        &memory::with_arena(resident, &plan),
        memory::limit_or_default(memory_limit),
    )?;
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena)
        .map_err(|e| HostError::invalid(Path::new("config"), e.to_string()))?;
    train::load_frames(&mut trainer, frames.iter().copied())?;
    f(&mut trainer)
}

/// The config of the trainer checkpoint at `path`, from the head of the file alone.
pub fn checkpoint_config(path: &Path) -> Result<Config> {
    let (kind, config, _) = crate::checkpoint::read_head(path)?;
    train::decode_config(path, &kind, &config)
}

/// The memory the model of the checkpoint at `path` takes once restored (its arena's parts),
/// from the head of the file alone: what a command checks beside the data it reads.
pub fn checkpoint_parts(path: &Path) -> Result<Vec<Part>> {
    Ok(memory::with_arena(
        &[],
        &MemoryPlan::new(&checkpoint_config(path)?),
    ))
}

/// A trainer over a fresh arena holding the checkpoint at `path` (built from its own config,
/// restored section by section: no copy of the model), the arena and the `resident` parts a
/// command holds beside it checked against `memory_limit` first. A stream's checkpoint is a
/// model like any other: its stream state is skipped.
pub fn with_checkpoint<R, E: From<HostError>>(
    path: &Path,
    memory_limit: Option<u64>,
    resident: &[Part],
    f: impl FnOnce(&mut Trainer<'_>) -> std::result::Result<R, E>,
) -> std::result::Result<R, E> {
    let config = checkpoint_config(path)?;
    with_trainer(path, (config, memory_limit), resident, &[], |trainer| {
        train::restore_checkpoint(path, trainer, &[crate::stream::STREAM_SECTION])?;
        f(trainer)
    })
}

/// Whether training goes on after a step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Flow {
    /// Take the next step (until the loop's end step).
    Continue,
    /// End training after this step (the run is then checkpointed as stopped).
    Stop,
}

/// Told of every training step: draws progress, scores the model while it trains (it may
/// read the trainer), or asks to stop.
pub trait Observer {
    /// Before the first step, with the trainer at its starting step (a resumed run's).
    fn start(&mut self, _trainer: &Trainer<'_>, _end: u32) {}

    /// After the step that brought the trainer to `trainer.state().step` of `end`.
    fn step(&mut self, trainer: &mut Trainer<'_>, end: u32, report: &StepReport) -> Result<Flow>;

    /// A flag (a signal handler's, say) that stops training within the current step once
    /// raised: it is read before every step and between the passes of its chunks
    /// (`Trainer::step_or_stop`), and the step it interrupts is given up without a trace, so
    /// the trainer is that of the last finished step (a checkpoint of it resumes to the bits
    /// of a run never stopped). `None` (the default): every step runs to its end.
    fn stop_flag(&self) -> Option<&AtomicBool> {
        None
    }
}

/// No observer: train to the end.
impl Observer for () {
    fn step(&mut self, _: &mut Trainer<'_>, _: u32, _: &StepReport) -> Result<Flow> {
        Ok(Flow::Continue)
    }
}

/// What the steps of [`train_steps`] took.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTally {
    /// Finished training steps (a step given up on a stop request is not counted).
    pub steps: u64,
    /// Rays traced over those steps.
    pub rays: u64,
    /// Samples the rays met in the scene box (after early stop).
    pub samples: u64,
    /// Samples marched through the occupancy grid.
    pub marched: u64,
    /// Seconds in the trainer's steps (the observer's time left out).
    pub seconds: f64,
}

impl StepTally {
    /// Add `other`'s steps, rays, samples and seconds to these.
    pub fn add(&mut self, other: &StepTally) {
        self.steps += other.steps;
        self.rays += other.rays;
        self.samples += other.samples;
        self.marched += other.marched;
        self.seconds += other.seconds;
    }

    /// Count one step's `report` (rays, samples) and set the seconds so far to `seconds`.
    pub fn count(&mut self, report: &StepReport, seconds: f64) {
        self.steps += 1;
        self.rays += report.rays as u64;
        self.samples += report.samples as u64;
        self.marched += report.samples_marched as u64;
        self.seconds = seconds;
    }

    /// Samples per ray (after early stop).
    pub fn samples_per_ray(&self) -> f64 {
        self.samples as f64 / self.rays.max(1) as f64
    }
}

/// The one training loop: step `trainer` until its step count reaches `end` (or the observer
/// stops it), telling `observer` after every step. A raised [`Observer::stop_flag`] ends it
/// within the current step, which is given up (the trainer's step count then stays below
/// `end`); the tally counts the finished steps.
pub fn train_steps<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    end: u32,
    observer: &mut dyn Observer,
) -> Result<StepTally> {
    let mut tally = StepTally::default();
    observer.start(trainer, end);
    while trainer.state().step < end {
        let start = Instant::now();
        let flag = observer.stop_flag();
        let stop = || flag.is_some_and(|flag| flag.load(Ordering::SeqCst));
        let Some(report) = trainer
            .step_or_stop(executor, &stop)
            .map_err(|e| HostError::Core(e.to_string()))?
        else {
            break;
        };
        tally.seconds += start.elapsed().as_secs_f64();
        tally.steps += 1;
        tally.rays += report.rays as u64;
        tally.samples += report.samples as u64;
        tally.marched += report.samples_marched as u64;
        if observer.step(trainer, end, &report)? == Flow::Stop {
            break;
        }
    }
    Ok(tally)
}

/// How a [`Pipeline`] trains and scores.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Worker threads (results do not depend on it).
    pub threads: usize,
    /// Stop (and checkpoint) once the run has taken this many steps.
    pub stop_after: Option<u32>,
    /// Replace an earlier run's checkpoint in the output folder.
    pub replace: bool,
    /// Steps fitting each held-out view's embedding on its left half.
    pub fit_steps: u32,
    /// Also fit each held-out view's pose correction and score it there.
    pub align_poses: bool,
}

impl Default for TrainOptions {
    fn default() -> TrainOptions {
        TrainOptions {
            threads: 2,
            stop_after: None,
            replace: false,
            fit_steps: train::DEFAULT_FIT_STEPS,
            align_poses: false,
        }
    }
}

/// A training run on a dataset folder, opened and ready: the data read and split, the config
/// chosen and fitted to it (scene box, capacities).
pub struct Pipeline {
    /// How the dataset folder is read (recorded in `run.toml`).
    pub settings: DataSettings,
    /// The dataset, read and split into training and held-out views.
    pub data: SplitData,
    /// The model config the run trains with: fitted to the data, or a resumed run's own.
    pub config: Config,
    /// Name of the preset the config started from.
    pub preset: String,
    /// Memory limit, bytes, that every stage is checked against (`None`: a share of the
    /// machine's memory).
    pub memory_limit: Option<u64>,
    /// Lines saying what was chosen and why (preset, masks, scene box), in order.
    pub notes: Vec<String>,
    /// The run continues from its checkpoint.
    resumed: bool,
}

/// One stage of a run's memory plan ([`Pipeline::memory_plan`]).
pub struct PlannedStage {
    /// The stage's name: the commands or command line it covers (`train, save, score`).
    pub name: String,
    /// What the stage holds at its peak.
    pub parts: Vec<Part>,
    /// What the parts leave out or how a stage avoids a copy.
    pub note: String,
}

/// How a [`Pipeline::train`] ended.
pub enum Outcome {
    /// Stopped before the last step (by the observer or `stop_after`), checkpointed.
    Stopped {
        /// The trainer's step count when it stopped (that of the checkpoint).
        step: u32,
    },
    /// Reached the last step: poses refined, held-out views scored, `metrics.json` written.
    Finished(Box<FinishedRun>),
}

/// A finished run's figures (also written to `metrics.json`).
pub struct FinishedRun {
    /// What this call's training steps took (a resumed run's earlier steps left out).
    pub tally: StepTally,
    /// Each held-out view's score, in the order of the held-out views.
    pub scores: Vec<ViewScore>,
    /// The held-out views' mean metrics.
    pub mean: ViewMetrics,
    /// The training poses' refinement; `None` without pose correction.
    pub pose_refinement: Option<PoseRefinementFigures>,
}

impl Pipeline {
    /// Open a fresh run: check the images' memory, read the data, choose the scene box by the
    /// rule (`stated`, else the data's own, else found from the training views) and fit the
    /// config to the data.
    pub fn open(
        settings: DataSettings,
        chosen: ChosenConfig,
        stated: Option<StatedBox>,
        memory_limit: Option<u64>,
    ) -> Result<Pipeline> {
        let mut notes = vec![chosen.note.clone()];
        let mut data = open_for_training(&settings, memory_limit, &mut notes)?;
        notes.push(scene_box::choose_scene_box(
            &mut data.dataset,
            stated,
            &data.train,
        )?);
        let config = train::fit_config(&chosen.config, &data.dataset, data.train.len());
        Ok(Pipeline {
            settings,
            data,
            config,
            preset: chosen.preset.to_string(),
            memory_limit,
            notes,
            resumed: false,
        })
    }

    /// Open the run in folder `run` to continue it: its data as `run.toml` records it (the
    /// data flags `given` must agree), its config from its checkpoint.
    pub fn resume(run: &Path, given: &DataChoice, memory_limit: Option<u64>) -> Result<Pipeline> {
        let record = RunRecord::read(run)?;
        let settings = record.settings_for(run, given, "resume")?;
        let path = run.join(CHECKPOINT_FILE);
        if !path.is_file() {
            return Err(HostError::invalid(
                &path,
                "no checkpoint to resume (start a run without --resume)",
            ));
        }
        let config = checkpoint_config(&path)?;
        let mut notes = vec![format!(
            "run {}: data {} (preset {})",
            run.display(),
            settings.data.display(),
            record.preset
        )];
        let data = open_for_training(&settings, memory_limit, &mut notes)?;
        Ok(Pipeline {
            settings,
            data,
            config,
            preset: record.preset,
            memory_limit,
            notes,
            resumed: true,
        })
    }

    /// What a run of this pipeline holds in memory at each stage, from the parts its checks
    /// use: training and scoring (the data, the held-out renders, the model's arena; the
    /// checkpoint is written from the arena as it lies, no copy), then `export` of the
    /// checkpoint with `surface` (the mesh comes on top, checked once its size is known).
    pub fn memory_plan(&self, surface: &SurfaceOptions) -> [PlannedStage; 2] {
        let arena = MemoryPlan::new(&self.config);
        let model = memory::with_arena(&[], &arena);
        [
            PlannedStage {
                name: "train, save, score".into(),
                parts: memory::with_arena(&self.data.resident_parts(), &arena),
                note: format!(
                    "the checkpoint ({} at most) is written from the arena as it lies: no copy",
                    memory::human(memory::total(&model))
                ),
            },
            PlannedStage {
                name: format!("export --resolution {}", surface.resolution),
                parts: memory::with_arena(&extract::grid_parts(&self.config, surface), &arena),
                note: format!(
                    "plus the mesh, {} bytes per grid cell the surface crosses, checked before \
                     it is built",
                    extract::BYTES_PER_SURFACE_VERTEX
                ),
            },
        ]
    }

    /// `plan` as text: the limit, then each stage's parts and note.
    pub fn memory_plan_text(&self, plan: &[PlannedStage]) -> String {
        let limit = memory::limit_or_default(self.memory_limit);
        let mut text = format!(
            "memory plan, limit {}:",
            limit.map_or(
                "none (the machine's memory is unknown)".into(),
                memory::human
            )
        );
        for stage in plan {
            text.push_str(&format!(
                "\n  {}: {}\n    {}",
                stage.name,
                memory::describe(&stage.parts),
                stage.note
            ));
        }
        text
    }

    /// Check every stage of `plan` against the run's memory limit (or the default share of
    /// the machine's memory): the error names the first stage that does not fit.
    pub fn check_memory_plan(&self, plan: &[PlannedStage]) -> Result<()> {
        let limit = memory::limit_or_default(self.memory_limit);
        for stage in plan {
            memory::check_plan(Path::new(&stage.name), &stage.parts, limit)?;
        }
        Ok(())
    }

    /// The record `train` writes beside the checkpoint.
    pub fn record(&self) -> Result<RunRecord> {
        RunRecord::new(&self.settings, &self.preset, &self.config)
    }

    /// Train into folder `out` (checkpoint, `run.toml`, `config.toml`), telling `observer` of
    /// every step; when the run reaches its last step, refine the poses, score the held-out
    /// views (renders in `out/renders`) and write `metrics.json`. A stop before the last step
    /// checkpoints, and [`Pipeline::resume`] continues to the bytes of a run never stopped.
    pub fn train(
        &self,
        out: &Path,
        options: &TrainOptions,
        observer: &mut dyn Observer,
    ) -> Result<Outcome> {
        let checkpoint_path = out.join(CHECKPOINT_FILE);
        if self.resumed {
            io::check_output_folder(out)?;
        } else {
            io::check_fresh_checkpoint(&checkpoint_path, options.replace, "training run")?;
            let renders = train::render_files(&out.join("renders"), &self.data.test);
            let reports = [RUN_FILE, "config.toml", "metrics.json"].map(|f| out.join(f));
            io::check_new_files(
                reports.iter().chain(&renders).map(PathBuf::as_path),
                options.replace,
            )?;
        }
        let record = self.record()?;
        let executor = RayonExecutor::new(options.threads)?;
        let frames = self.data.training_frames();
        let config = self.config;
        // A resumed run's frames come from its checkpoint (and are checked against the data).
        let fresh: &[&Frame] = if self.resumed { &[] } else { &frames };
        let resident = self.data.resident_parts();
        let model = Path::new("the model");
        with_trainer(
            model,
            (config, self.memory_limit),
            &resident,
            fresh,
            |trainer| {
                if self.resumed {
                    train::restore_checkpoint(&checkpoint_path, trainer, &[])?;
                    check_same_frames(&checkpoint_path, trainer, &frames)?;
                }
                let end = options
                    .stop_after
                    .map_or(config.steps, |stop| stop.min(config.steps));
                let tally = train_steps(trainer, &executor, end, observer)?;
                let finished = trainer.state().step >= config.steps;
                // A finished run's last stage: the poses' refinement with the field frozen.
                let pose_fits = if finished {
                    train::refine_poses(trainer, &executor)?
                } else {
                    Vec::new()
                };
                let tally_for_check = train::TrainingTally {
                    steps: tally.steps,
                    samples: tally.samples,
                };
                train::check_trained(out, trainer, tally_for_check)?;
                train::save_checkpoint(&checkpoint_path, trainer, &[])?;
                record.write(out)?;
                io::write_atomic(
                    &out.join("config.toml"),
                    train::config_to_toml(&config)?.as_bytes(),
                )?;
                if !finished {
                    return Ok(Outcome::Stopped {
                        step: trainer.state().step,
                    });
                }
                let scores = train::evaluate_at(
                    trainer,
                    &executor,
                    &self.data.dataset,
                    &self.data.test,
                    self.data.truth.as_deref(),
                    (options.fit_steps, options.align_poses),
                    Some(&out.join("renders")),
                )?;
                let per_view: Vec<ViewMetrics> = scores.iter().map(|s| s.metrics).collect();
                let mean = report::mean_metrics(&per_view);
                let state = trainer.state();
                let pose_refinement = pose_refinement(trainer, &frames, &pose_fits);
                let model = ModelFigures {
                    name: "model".into(),
                    mean,
                    views: train::view_figures(&scores),
                    training: Some(TrainingFigures {
                        steps: state.step as u64,
                        steps_skipped: state.skipped as u64,
                        seconds: tally.seconds,
                        samples_per_ray: tally.samples_per_ray(),
                    }),
                    mean_at: None,
                    pose_refinement: pose_refinement.clone(),
                };
                Figures::new("train", vec![model]).write(out)?;
                Ok(Outcome::Finished(Box::new(FinishedRun {
                    tally,
                    scores,
                    mean,
                    pose_refinement,
                })))
            },
        )
    }
}

/// Check the images' memory, read the data (noting where masks were applied) and refuse a
/// split or data with nothing to train on.
fn open_for_training(
    settings: &DataSettings,
    memory_limit: Option<u64>,
    notes: &mut Vec<String>,
) -> Result<SplitData> {
    settings.check_memory(memory_limit, &[])?;
    let data = settings.open()?;
    notes.extend(data.mask_note());
    if data.train.is_empty() {
        return Err(HostError::invalid(
            &data.dataset.source,
            format!(
                "no training view: --holdout {} holds out every one of its {} views",
                settings.holdout,
                data.dataset.frames.len()
            ),
        ));
    }
    train::check_frames_have_content(&data.dataset.source, data.training_frames())?;
    Ok(data)
}

/// The training poses' refinement figures for `metrics.json` (with pose correction).
fn pose_refinement(
    trainer: &Trainer<'_>,
    frames: &[&Frame],
    fits: &[PoseFit],
) -> Option<PoseRefinementFigures> {
    if fits.is_empty() {
        return None;
    }
    let pivot = trainer.config().pose_pivot_point();
    let names: Vec<String> = frames.iter().map(|f| f.name.clone()).collect();
    let corrected: Vec<_> = (frames.iter().enumerate())
        .map(|(slot, f)| {
            let correction = trainer.pose_correction(slot).unwrap_or_default();
            correction.apply(&f.pose, pivot)
        })
        .collect();
    let frames = report::frame_poses(&names, fits, &corrected, None);
    let summary = report::pose_uncertainty(&frames);
    Some(PoseRefinementFigures { summary, frames })
}

/// A resumed run trains on the frames its checkpoint holds: refuse data whose training views
/// are not those (another folder, size, hold-out or masking).
fn check_same_frames(checkpoint: &Path, trainer: &Trainer<'_>, frames: &[&Frame]) -> Result<()> {
    let store = trainer.frames();
    let differs = |i: usize| {
        store
            .occupied_slot(i)
            .and_then(|slot| store.pixels(slot))
            .is_none_or(|pixels| pixels != frames[i].pixels.as_slice())
    };
    if store.len() != frames.len() {
        return Err(HostError::invalid(
            checkpoint,
            format!(
                "the run trained on {} views, the data gives {}; resume with the run's --data, --size, --holdout and masks",
                store.len(),
                frames.len()
            ),
        ));
    }
    if let Some(i) = (0..frames.len()).find(|&i| differs(i)) {
        return Err(HostError::invalid(
            checkpoint,
            format!(
                "training view {} ({}) is not the one the run trained on; resume with the run's --data, --size, --holdout and masks",
                i, frames[i].name
            ),
        ));
    }
    Ok(())
}
