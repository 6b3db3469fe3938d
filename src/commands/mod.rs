//! The CLI's commands, one file each, and what several of them share: the dataset and model
//! arguments, a dataset with its held-out split, trainers over fresh arenas, progress bars.

pub mod ablate;
pub mod bench;
pub mod demo;
pub mod eval;
pub mod export;
pub mod render;
pub mod simulate;
pub mod stream;
pub mod sweep;
pub mod tradeoff;
pub mod train;

use clap::Args;
use indicatif::ProgressStyle;
use orbit_nerf_core::MemoryPlan;
use orbit_nerf_core::{Config, Trainer};
use orbit_nerf_host::dataset::{self, Dataset, Frame};
use orbit_nerf_host::formats::{self, Format};
use orbit_nerf_host::report::{ViewMetrics, mean_metrics};
use orbit_nerf_host::scene_box::{self, StatedBox};
use orbit_nerf_host::train::{
    RayonExecutor, ViewScore, checkpoint_config, config_scene_box, evaluate, load_frames,
    read_config, restore_checkpoint,
};
use orbit_nerf_host::{memory, presets, values};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

pub type Fallible<T> = Result<T, Box<dyn std::error::Error>>;
pub type CliResult = Fallible<()>;
/// A dataset with its training and held-out view indices.
type SplitDataset = (Dataset, Vec<usize>, Vec<usize>);

#[derive(Args, Clone)]
struct DataArgs {
    /// Dataset folder: NeRF-synthetic, nerfstudio or SPEED+/SHIRT.
    #[arg(long)]
    data: PathBuf,
    /// Resize images so the longer side has at most this many pixels, 1 to 65535 (smaller
    /// images keep their size: never upsampled), for every format.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=65_535))]
    size: u32,
    /// Every N-th view (0, N, 2N, ...) is held out for evaluation (1 holds out every view).
    #[arg(long, default_value_t = 8, value_parser = |text: &str| values::count_in(text, 1..=1_000_000))]
    holdout: usize,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    no_masks: bool,
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
    /// Random seed (overrides the config).
    #[arg(long)]
    seed: Option<u64>,
    /// Worker threads, 1 to 1024 (results do not depend on it).
    #[arg(long, default_value_t = 2, value_parser = |text: &str| values::count_in(text, 1..=MAX_THREADS))]
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
    /// Largest memory the model's arena may take (e.g. 8G, 512M); default: 80 % of the
    /// machine's available memory. Checked before anything large is allocated.
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

/// The config a run starts from: the preset `chosen` by `--preset`, else `default`, the
/// preset for the run's data (`data` says what data); with a config file's fields on top.
/// Prints one line saying which and why.
fn preset_config(
    chosen: Option<&str>,
    default: &str,
    data: &str,
    file: Option<&Path>,
) -> Fallible<Config> {
    let (name, why) = match chosen {
        Some(name) => (name, "--preset".to_string()),
        None => (
            default,
            format!(
                "{data}; --preset to choose another: {}",
                presets::names().collect::<Vec<_>>().join(", ")
            ),
        ),
    };
    let preset = presets::find(name).ok_or_else(|| {
        format!(
            "--preset {name}: no such preset ({})",
            presets::names().collect::<Vec<_>>().join(", ")
        )
    })?;
    let config = match file {
        Some(path) => read_config(path, &preset.config()?)?,
        None => preset.config()?,
    };
    let on_top = file.map_or(String::new(), |path| {
        format!(", with the fields of {} on top", path.display())
    });
    println!("config: preset {name} ({why}){on_top}");
    Ok(config)
}

/// [`preset_config`] for a run on the dataset `data`: the preset for its format, told from the
/// folder's layout (nothing is read), unless `chosen`.
fn config_for_data(chosen: Option<&str>, data: &Path, file: Option<&Path>) -> Fallible<Config> {
    let format = Format::of(data);
    preset_config(chosen, presets::for_format(format), format.folder(), file)
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
    let stated = match (flag, config) {
        (Some((min, max)), _) => Some(StatedBox {
            min,
            max,
            by: "--scene-box".into(),
        }),
        (None, Some(path)) => config_scene_box(path)?.map(|(min, max)| StatedBox {
            min,
            max,
            by: format!("the config file {}", path.display()),
        }),
        (None, None) => None,
    };
    println!(
        "{}",
        scene_box::choose_scene_box(dataset, stated, train_idx)?
    );
    Ok(())
}

/// Raised by Ctrl-C / SIGTERM once [`stop_on_signal`] is installed: `train` stops after the
/// current step and `stream` after the current frame, and both checkpoint.
static STOP: AtomicBool = AtomicBool::new(false);

/// Make Ctrl-C and SIGTERM raise [`STOP`] instead of ending the process.
fn stop_on_signal() -> CliResult {
    Ok(ctrlc::set_handler(|| STOP.store(true, Ordering::SeqCst))?)
}

/// Most training steps a flag accepts.
const MAX_STEPS: i64 = 100_000_000;
/// Most worker threads a flag accepts.
const MAX_THREADS: usize = 1024;
/// Largest appearance embedding (the core's limit).
const MAX_EMBEDDING_DIM: i64 = 128;
/// Most steps fitting a held-out view's embedding.
const MAX_FIT_STEPS: i64 = 100_000;

/// Default steps fitting a held-out view's appearance embedding.
const FIT_STEPS: u32 = orbit_nerf_host::train::DEFAULT_FIT_STEPS;

/// NeRF-synthetic is composited on white; spacecraft scenes have a black sky (the loader
/// sets that itself).
const NERF_BACKGROUND: [f32; 3] = [1.0; 3];

/// Check the memory the dataset's images will take (from their headers) against
/// `memory_limit` (default: a share of the machine's memory) before they are read.
fn check_dataset_memory(data: &DataArgs, memory_limit: Option<u64>) -> CliResult {
    Ok(memory::check_plan(
        &data.data,
        &memory::dataset_parts(&data.data, Some(data.size)),
        memory::limit_or_default(memory_limit),
    )?)
}

fn open_dataset(data: &DataArgs) -> Fallible<SplitDataset> {
    let mut dataset = formats::open(&data.data, Some(data.size), NERF_BACKGROUND)?;
    if dataset.frames.is_empty() {
        return Err(format!("{}: no frames", data.data.display()).into());
    }
    if !data.no_masks {
        let masked = dataset.apply_masks();
        if masked > 0 {
            println!(
                "masks applied: background colour where the mask is 0 on {masked} views (--no-masks keeps the sky)"
            );
        }
    }
    let (train, test) = dataset::split_every(dataset.frames.len(), data.holdout);
    Ok((dataset, train, test))
}

/// The model config of a run on `data`: the preset (`--preset`, else the one for the data's
/// format, told from the folder's layout before the data is read), a `--config` file's fields,
/// then the flags.
fn model_config(model: &ModelArgs, data: &Path) -> Fallible<Config> {
    let mut config = config_for_data(model.preset.as_deref(), data, model.config.as_deref())?;
    if let Some(steps) = model.steps {
        config.steps = steps;
        config.warmup_steps = config.warmup_steps.min(steps);
    }
    if let Some(seed) = model.seed {
        config.seed = seed;
    }
    if let Some(dim) = model.embedding_dim {
        config.embedding_dim = dim;
    }
    if let Some(on) = model.pose_correction {
        config.pose_correction = on;
    }
    Ok(config)
}

/// A trainer over a fresh arena (checked against `memory_limit`, or a share of the
/// machine's memory, before it is allocated), with the training frames loaded.
fn with_trainer<R>(
    config: Config,
    memory_limit: Option<u64>,
    frames: &[&Frame],
    f: impl FnOnce(&mut Trainer<'_>) -> Fallible<R>,
) -> Fallible<R> {
    let plan = MemoryPlan::new(&config);
    memory::check_arena(
        Path::new("the model"),
        &plan,
        memory::limit_or_default(memory_limit),
    )?;
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).map_err(|e| format!("config: {e}"))?;
    load_frames(&mut trainer, frames.iter().copied())?;
    f(&mut trainer)
}

/// The held-out scores, one line per view and the mean (metrics as `report::score_view`
/// defines them), and the mean's metrics.
fn print_scores(scores: &[ViewScore]) -> ViewMetrics {
    println!(
        "{:>6}  {:>8}  {:>8}  {:>8}  {:>6}  {:>6}  {:>11}  view",
        "index", "PSNR dB", "right dB", "fg dB", "SSIM", "JNB", "samples/ray"
    );
    for s in scores {
        let m = &s.metrics;
        println!(
            "{:>6}  {:>8.2}  {:>8.2}  {:>8.2}  {:>6.4}  {:>6.3}  {:>11.1}  {}",
            s.index,
            m.psnr_full,
            m.psnr_right,
            m.psnr_foreground,
            m.ssim_full,
            m.jnb_full,
            s.samples_per_ray,
            s.name
        );
    }
    let per_view: Vec<ViewMetrics> = scores.iter().map(|s| s.metrics).collect();
    let mean = mean_metrics(&per_view);
    println!(
        "mean PSNR over {} held-out views: {:.2} dB",
        scores.len(),
        mean.psnr_full
    );
    println!(
        "mean right-half PSNR {:.2} dB, foreground PSNR {:.2} dB (right half {:.2} dB), SSIM {:.4}, JNB {:.3}",
        mean.psnr_right,
        mean.psnr_foreground,
        mean.psnr_foreground_right,
        mean.ssim_full,
        mean.jnb_full
    );
    mean
}

/// Check the arena the checkpoint at `path` needs against `memory_limit` (default: a share of
/// the machine's memory) before its data is read.
fn check_checkpoint_memory(path: &Path, memory_limit: Option<u64>) -> CliResult {
    let checkpoint = orbit_nerf_host::checkpoint::load(path)?;
    let plan = MemoryPlan::new(&checkpoint_config(path, &checkpoint)?);
    Ok(memory::check_arena(
        path,
        &plan,
        memory::limit_or_default(memory_limit),
    )?)
}

/// Score `views` of `dataset` with the checkpoint at `path` (restored with its own config),
/// fitting each view's embedding (and with `align_poses` its pose correction) for
/// `fit_steps`; renders go to `renders` when given.
fn evaluate_checkpoint(
    path: &Path,
    threads: usize,
    dataset: &Dataset,
    views: &[usize],
    (fit_steps, align_poses): (u32, bool),
    renders: Option<&Path>,
) -> Fallible<Vec<ViewScore>> {
    let executor = RayonExecutor::new(threads)?;
    with_checkpoint(path, |trainer| {
        Ok(evaluate(
            trainer,
            &executor,
            dataset,
            views,
            fit_steps,
            align_poses,
            renders,
        )?)
    })
}

/// A trainer over a fresh arena holding the checkpoint at `path` (built from its own config).
fn with_checkpoint<R>(path: &Path, f: impl FnOnce(&mut Trainer<'_>) -> Fallible<R>) -> Fallible<R> {
    let checkpoint = orbit_nerf_host::checkpoint::load(path)?;
    let config = checkpoint_config(path, &checkpoint)?;
    with_trainer(config, None, &[], |trainer| {
        restore_checkpoint(path, &checkpoint, trainer)?;
        f(trainer)
    })
}

/// The style of every command's progress bars: `template` in indicatif's syntax.
fn bar_style(template: &str) -> Fallible<ProgressStyle> {
    Ok(ProgressStyle::with_template(template)?.progress_chars("=> "))
}

/// The figure shown while training: the PSNR of an exponential average of the training
/// batches' loss (skipped steps left out), in dB. It is labelled "train-loss PSNR": it is not
/// the held-out PSNR, which only `report::score_view` defines.
#[derive(Default)]
struct RunningPsnr(Option<f64>);

impl RunningPsnr {
    fn add(&mut self, mse: f32) {
        let mse = mse as f64;
        self.0 = Some(self.0.map_or(mse, |r| 0.95 * r + 0.05 * mse));
    }

    /// 0 before the first step.
    fn db(&self) -> f64 {
        self.0.map_or(0.0, |m| -10.0 * m.max(1e-12).log10())
    }
}
