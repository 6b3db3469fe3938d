//! The CLI's commands, one file each, and what several of them share: the dataset and model
//! arguments, a dataset with its held-out split, trainers over fresh arenas, progress bars.

pub mod ablate;
pub mod bench;
pub mod demo;
pub mod eval;
pub mod export;
pub mod paper;
pub mod reference;
pub mod render;
pub mod simulate;
pub mod stream;
pub mod sweep;
pub mod tradeoff;
pub mod train;

use clap::Args;
use indicatif::ProgressStyle;
use orbit_nerf_host::dataset::Dataset;
use orbit_nerf_host::memory::Part;
use orbit_nerf_host::pipeline::{
    self, ChosenConfig, DataChoice, DataSettings, Overrides, SplitData,
};
use orbit_nerf_host::progress;
use orbit_nerf_host::report::ViewMetrics;
use orbit_nerf_host::scene_box;
use orbit_nerf_host::train::ViewScore;
use orbit_nerf_host::{presets, values};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

pub type Fallible<T> = Result<T, Box<dyn std::error::Error>>;
pub type CliResult = Fallible<()>;

#[derive(Args, Clone)]
struct DataArgs {
    /// Dataset folder: NeRF-synthetic, nerfstudio or SPEED+/SHIRT (with --run: the run's,
    /// from its run.toml).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Resize images so the longer side has at most this many pixels, 1 to 65535 (smaller
    /// images keep their size: never upsampled), for every format [default: 128, or the run's].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=65_535))]
    size: Option<u32>,
    /// Every N-th view (0, N, 2N, ...) is held out for evaluation (1 holds out every view)
    /// [default: 8, or the run's].
    #[arg(long, value_parser = |text: &str| values::count_in(text, 1..=1_000_000))]
    holdout: Option<usize>,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    no_masks: bool,
}

impl DataArgs {
    /// The flags as given (`None` where left out).
    fn choice(&self) -> DataChoice {
        DataChoice {
            data: self.data.clone(),
            size: self.size,
            holdout: self.holdout,
            no_masks: self.no_masks,
        }
    }
}

/// The model a command reads: a `train` run folder (its checkpoint and its data), or a
/// checkpoint with data flags.
#[derive(Args, Clone)]
struct RunArgs {
    /// A `train` run folder: its checkpoint.onrf, and its data as its run.toml records it
    /// (no data flag needed; one given must agree with the run).
    #[arg(long, conflicts_with = "checkpoint")]
    run: Option<PathBuf>,
    /// A checkpoint (of `train`, `stream` or `ablate`), with --data, instead of --run.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
}

impl RunArgs {
    /// The checkpoint and the data settings (`verb`: what the command does with the run).
    fn checkpoint_and_data(
        &self,
        data: &DataArgs,
        verb: &str,
    ) -> Fallible<(PathBuf, DataSettings)> {
        Ok(pipeline::checkpoint_and_data(
            self.run.as_deref(),
            self.checkpoint.as_deref(),
            &data.choice(),
            verb,
        )?)
    }
}

#[derive(Args, Clone)]
struct ModelArgs {
    /// Built-in config to start from; default by the data's format: `spacecraft` (the method)
    /// for SPEED+/SHIRT/simulator folders, `default` for NeRF-synthetic and nerfstudio.
    #[arg(long, value_parser = preset_parser())]
    preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config, at the top level or
    /// in a `[config]` table (a full file, as budgets/*.toml, works too).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Training steps, 1 to 100 million (overrides the config).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=MAX_STEPS))]
    steps: Option<u32>,
    /// Random seed, 0 to 2^63-1 (overrides the config; config files hold it as a TOML integer).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=MAX_SEED))]
    seed: Option<u64>,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
    /// Appearance embedding size per frame, 0 to 128 (overrides the config; 0 disables it).
    #[arg(long, value_parser = clap::value_parser!(u16).range(0..=MAX_EMBEDDING_DIM))]
    embedding_dim: Option<u16>,
    /// Learn a pose correction per frame (overrides the config).
    #[arg(long)]
    pose_correction: Option<bool>,
    /// Evaluation: steps fitting a held-out view's embedding on its left half (0 to 100000).
    #[arg(long, default_value_t = FIT_STEPS, value_parser = clap::value_parser!(u32).range(0..=MAX_FIT_STEPS))]
    fit_steps: u32,
    /// Evaluation: also fit each held-out view's pose correction in those steps and score it
    /// at its corrected label (BARF's test-time alignment), instead of at its label.
    #[arg(long)]
    align_poses: bool,
    /// Largest memory a run may take: the data, the model's arena and the held-out renders
    /// together (e.g. 8G, 512M); default: 80 % of the machine's available memory. Checked
    /// before anything large is allocated (`train --dry-run` prints the plan).
    #[arg(long, value_parser = values::byte_size)]
    memory_limit: Option<u64>,
    /// The scene box, xmin,ymin,zmin,xmax,ymax,zmax in world units (wins over a config
    /// file's box, truth.json's and the box found from the data).
    #[arg(long, value_parser = parse_scene_box, allow_hyphen_values = true)]
    scene_box: Option<SceneBox>,
}

/// `--preset`'s values: the built-in presets, each with what it is.
fn preset_parser() -> clap::builder::PossibleValuesParser {
    presets::PRESETS
        .map(|p| clap::builder::PossibleValue::new(p.name).help(p.about))
        .into()
}

/// A scene box as min and max corners.
type SceneBox = ([f32; 3], [f32; 3]);

fn parse_scene_box(text: &str) -> Result<SceneBox, String> {
    scene_box::parse_box(text)
}

/// Set `dataset`'s scene box by the rule (`--scene-box`, else a config file that sets one,
/// else the data's own, else found from the training views) and print it and why.
fn choose_box(
    dataset: &mut Dataset,
    flag: Option<SceneBox>,
    config: Option<&Path>,
    train_idx: &[usize],
) -> CliResult {
    println!(
        "{}",
        pipeline::choose_box(dataset, flag, config, train_idx)?
    );
    Ok(())
}

/// Raised by Ctrl-C / SIGTERM once [`stop_on_signal`] is installed: `train` and `stream` stop
/// within the current step (read between the passes of its chunks; the step is given up) and
/// checkpoint the last finished step; a resumed stream first takes the rest of its frame's
/// steps.
static STOP: AtomicBool = AtomicBool::new(false);

/// Make Ctrl-C and SIGTERM raise [`STOP`] instead of ending the process.
fn stop_on_signal() -> CliResult {
    Ok(ctrlc::set_handler(|| STOP.store(true, Ordering::SeqCst))?)
}

/// Most training steps a flag accepts.
const MAX_STEPS: i64 = 100_000_000;
/// Largest seed a flag accepts: config and scene files hold seeds as TOML integers (i64).
const MAX_SEED: u64 = i64::MAX as u64;
/// The machine's cores: every command's default worker threads.
fn machine_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get().min(MAX_THREADS))
}

/// `--threads`: 1 to [`MAX_THREADS`].
fn parse_threads(text: &str) -> Result<usize, String> {
    values::count_in(text, 1..=MAX_THREADS)
}

/// Most worker threads a flag accepts.
const MAX_THREADS: usize = 1024;
/// Largest appearance embedding (the core's limit).
const MAX_EMBEDDING_DIM: i64 = 128;
/// Most steps fitting a held-out view's embedding.
const MAX_FIT_STEPS: i64 = 100_000;

/// Default steps fitting a held-out view's appearance embedding.
const FIT_STEPS: u32 = orbit_nerf_host::train::DEFAULT_FIT_STEPS;

/// Read the dataset of `settings` (its memory checked first against `memory_limit`) and
/// print where masks were applied.
fn open_dataset(
    settings: &DataSettings,
    memory_limit: Option<u64>,
    beside: &[Part],
) -> Fallible<SplitData> {
    settings.check_memory(memory_limit, beside)?;
    let data = settings.open()?;
    if let Some(note) = data.mask_note() {
        println!("{note}");
    }
    Ok(data)
}

/// The model config of a run on `data`: the preset (`--preset`, else the one for the data's
/// format, told from the folder's layout before the data is read), a `--config` file's fields,
/// then the flags.
fn model_config(model: &ModelArgs, data: &Path) -> Fallible<ChosenConfig> {
    let mut chosen =
        pipeline::choose_config(model.preset.as_deref(), data, model.config.as_deref())?;
    let overrides = Overrides {
        steps: model.steps,
        seed: model.seed,
        embedding_dim: model.embedding_dim,
        pose_correction: model.pose_correction,
    };
    overrides.apply(&mut chosen.config);
    Ok(chosen)
}

/// Print the held-out scores, one line per view and the mean; returns the mean's metrics.
fn print_scores(scores: &[ViewScore]) -> ViewMetrics {
    let (text, mean) = progress::scores_table(scores);
    println!("{text}");
    mean
}

/// The style of every command's progress bars: `template` in indicatif's syntax.
fn bar_style(template: &str) -> Fallible<ProgressStyle> {
    Ok(ProgressStyle::with_template(template)?.progress_chars("=> "))
}
