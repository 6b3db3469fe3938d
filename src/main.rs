//! orbit-nerf: train, evaluate and render K-Planes radiance fields of spacecraft (and of
//! NeRF scenes), benchmark the core, and simulate datasets.

mod ablate;
mod simulate;
mod stream;

use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use orbit_nerf_core::{Config, Executor, MemoryPlan, Trainer};
use orbit_nerf_host::dataset::{self, Dataset};
use orbit_nerf_host::train::{self, RayonExecutor, ViewScore};
use std::path::{Path, PathBuf};
use std::time::Instant;

type Fallible<T> = Result<T, Box<dyn std::error::Error>>;
type CliResult = Fallible<()>;
/// A dataset with its training and held-out view indices.
type SplitDataset = (Dataset, Vec<usize>, Vec<usize>);

#[derive(Parser)]
#[command(name = "orbit-nerf", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a field on a dataset and write a checkpoint.
    Train(TrainArgs),
    /// Score held-out views of a dataset with a checkpoint (PSNR per view and the mean).
    Eval(EvalArgs),
    /// Render views of a dataset's cameras with a checkpoint to PNG.
    Render(RenderArgs),
    /// Measure training throughput (samples/s, rays/s) on a fixed scene and seed.
    Bench(BenchArgs),
    /// The built-in default: simulate the lightbox preset, train the method, evaluate, report.
    Demo(DemoArgs),
    /// Render a spacecraft scene into a SPEED+-format dataset.
    Simulate(simulate::SimulateArgs),
    /// The paper's ablation (baseline, + appearance, + pose) or its pose-noise sweep.
    Ablate(ablate::AblateArgs),
    /// Ingest frames one at a time (dataset folder, watched folder, simulator) into a fixed
    /// frame store, training as they arrive; anytime quality, checkpoints, resume.
    Stream(stream::StreamArgs),
}

#[derive(Args, Clone)]
struct DataArgs {
    /// Dataset folder: NeRF-synthetic, nerfstudio or SPEED+/SHIRT.
    #[arg(long)]
    data: PathBuf,
    /// Resize images so the longer side has this many pixels.
    #[arg(long, default_value_t = 100)]
    size: u32,
    /// Every N-th view (0, N, 2N, ...) is held out for evaluation.
    #[arg(long, default_value_t = 8)]
    holdout: usize,
}

#[derive(Args, Clone)]
struct ModelArgs {
    /// Full model and training config (TOML, every field; see budgets/).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Training steps (overrides the config).
    #[arg(long)]
    steps: Option<u32>,
    /// Random seed (overrides the config).
    #[arg(long)]
    seed: Option<u64>,
    /// Worker threads (results do not depend on it).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Appearance embedding size per frame (overrides the config; 0 disables it).
    #[arg(long)]
    embedding_dim: Option<u16>,
    /// Learn a pose correction per frame (overrides the config).
    #[arg(long)]
    pose_correction: Option<bool>,
    /// Evaluation: steps fitting a held-out view's embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    fit_steps: u32,
}

/// Default steps fitting a held-out view's appearance embedding.
const FIT_STEPS: u32 = 50;

#[derive(Args)]
struct TrainArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    model: ModelArgs,
    /// Output folder: checkpoint.onrf, config.toml, renders/.
    #[arg(long, default_value = "runs/train")]
    out: PathBuf,
}

#[derive(Args)]
struct EvalArgs {
    #[command(flatten)]
    data: DataArgs,
    #[arg(long)]
    checkpoint: PathBuf,
    /// Write renders and ground truth of the held-out views here.
    #[arg(long)]
    renders: Option<PathBuf>,
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Steps fitting each view's appearance embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    fit_steps: u32,
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    data: DataArgs,
    #[arg(long)]
    checkpoint: PathBuf,
    /// Views to render (dataset indices); default: the held-out views.
    #[arg(long, value_delimiter = ',')]
    views: Vec<usize>,
    #[arg(long, default_value = "runs/render")]
    out: PathBuf,
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Steps fitting each view's appearance embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    fit_steps: u32,
}

#[derive(Args)]
struct BenchArgs {
    /// Dataset to train on (default: the lego scene).
    #[arg(long, default_value = "../shared/data/nerf_synthetic/lego")]
    data: PathBuf,
    #[arg(long, default_value_t = 100)]
    size: u32,
    /// Steps before timing starts (lets the occupancy grid settle).
    #[arg(long, default_value_t = 300)]
    warmup: u32,
    /// Timed steps.
    #[arg(long, default_value_t = 200)]
    steps: u32,
    /// Thread counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(Args)]
struct DemoArgs {
    #[arg(long, default_value = "runs/demo")]
    out: PathBuf,
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Training steps (default: the demo's budget).
    #[arg(long)]
    steps: Option<u32>,
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Train(args) => run_train(&args),
        Command::Eval(args) => run_eval(&args),
        Command::Render(args) => run_render(&args),
        Command::Bench(args) => run_bench(&args),
        Command::Demo(args) => run_demo(&args),
        Command::Simulate(args) => simulate::run(&args),
        Command::Ablate(args) => ablate::run(&args),
        Command::Stream(args) => stream::run(&args),
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// NeRF-synthetic is composited on white; spacecraft scenes have a black sky (the loader
/// sets that itself).
const NERF_BACKGROUND: [f32; 3] = [1.0; 3];

fn open_dataset(data: &DataArgs) -> Fallible<SplitDataset> {
    let dataset = dataset::open(&data.data, Some(data.size), NERF_BACKGROUND)?;
    if dataset.frames.is_empty() {
        return Err(format!("{}: no frames", data.data.display()).into());
    }
    let (train, test) = dataset::split_every(dataset.frames.len(), data.holdout);
    Ok((dataset, train, test))
}

fn model_config(model: &ModelArgs) -> Fallible<Config> {
    let mut config = match &model.config {
        Some(path) => train::read_config(path)?,
        None => Config::DEFAULT,
    };
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

/// A trainer over a fresh arena, with the training frames loaded.
fn with_trainer<R>(
    config: Config,
    frames: &[&orbit_nerf_host::dataset::Frame],
    f: impl FnOnce(&mut Trainer<'_>) -> Fallible<R>,
) -> Fallible<R> {
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).map_err(|e| format!("config: {e}"))?;
    train::load_frames(&mut trainer, frames.iter().copied())?;
    f(&mut trainer)
}

struct TrainSummary {
    seconds: f64,
    rays: u64,
    samples: u64,
    marched: u64,
    skipped: u32,
}

/// Run the configured number of steps with a progress bar (steps/s, loss, running PSNR).
fn train_loop<E: Executor>(trainer: &mut Trainer<'_>, executor: &E) -> Fallible<TrainSummary> {
    let steps = trainer.config().steps - trainer.state().step.min(trainer.config().steps);
    let bar = ProgressBar::new(steps as u64).with_style(
        ProgressStyle::with_template("train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}")?
            .progress_chars("=> "),
    );
    let start = Instant::now();
    let mut summary = TrainSummary {
        seconds: 0.0,
        rays: 0,
        samples: 0,
        marched: 0,
        skipped: 0,
    };
    let mut running_mse = None::<f64>;
    for i in 0..steps {
        let report = trainer.step(executor)?;
        summary.rays += report.rays as u64;
        summary.samples += report.samples as u64;
        summary.marched += report.samples_marched as u64;
        if !report.skipped {
            let mse = report.mse as f64;
            running_mse = Some(running_mse.map_or(mse, |r| 0.95 * r + 0.05 * mse));
        }
        if i % 10 == 0 || i + 1 == steps {
            let psnr = running_mse.map_or(0.0, |m| -10.0 * m.max(1e-12).log10());
            bar.set_message(format!(
                "loss {:.5} psnr {psnr:.2} dB {:.1} samples/ray",
                report.mse,
                report.samples as f32 / report.rays.max(1) as f32
            ));
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    summary.seconds = start.elapsed().as_secs_f64();
    summary.skipped = trainer.state().skipped;
    Ok(summary)
}

fn print_scores(scores: &[ViewScore]) -> f64 {
    println!(
        "{:>6}  {:>8}  {:>11}  view",
        "index", "PSNR dB", "samples/ray"
    );
    for s in scores {
        println!(
            "{:>6}  {:>8.2}  {:>11.1}  {}",
            s.index, s.psnr, s.samples_per_ray, s.name
        );
    }
    let mean = scores.iter().map(|s| s.psnr).sum::<f64>() / scores.len().max(1) as f64;
    println!(
        "mean PSNR over {} held-out views: {mean:.2} dB",
        scores.len()
    );
    mean
}

fn run_train(args: &TrainArgs) -> CliResult {
    let (dataset, train_idx, test_idx) = open_dataset(&args.data)?;
    let base = model_config(&args.model)?;
    let config = train::fit_config(&base, &dataset, train_idx.len());
    let executor = RayonExecutor::new(args.model.threads)?;
    let frames: Vec<_> = train_idx.iter().map(|&i| &dataset.frames[i]).collect();
    println!(
        "training on {} views ({} held out) of {} for {} steps, {} threads",
        train_idx.len(),
        test_idx.len(),
        dataset.source.display(),
        config.steps,
        args.model.threads
    );
    with_trainer(config, &frames, |trainer| {
        let summary = train_loop(trainer, &executor)?;
        print_summary(&summary);
        train::save_checkpoint(&args.out.join("checkpoint.onrf"), trainer)?;
        orbit_nerf_host::io::write_atomic(
            &args.out.join("config.toml"),
            train::config_to_toml(&config).as_bytes(),
        )?;
        let scores = train::evaluate(
            trainer,
            &executor,
            &dataset,
            &test_idx,
            args.model.fit_steps,
            Some(&args.out.join("renders")),
        )?;
        print_scores(&scores);
        println!("checkpoint, config and renders in {}", args.out.display());
        Ok(())
    })
}

fn print_summary(s: &TrainSummary) {
    println!(
        "trained in {:.1} s: {:.0} rays/s, {:.0} samples/s ({:.1} samples/ray after early stop, {:.1} marched), {} steps skipped",
        s.seconds,
        s.rays as f64 / s.seconds,
        s.samples as f64 / s.seconds,
        s.samples as f64 / s.rays.max(1) as f64,
        s.marched as f64 / s.rays.max(1) as f64,
        s.skipped
    );
}

/// Load a checkpoint into a trainer (with its own config) and run `f`.
fn with_checkpoint<R>(path: &Path, f: impl FnOnce(&mut Trainer<'_>) -> Fallible<R>) -> Fallible<R> {
    let checkpoint = orbit_nerf_host::checkpoint::load(path)?;
    let config = train::checkpoint_config(path, &checkpoint)?;
    with_trainer(config, &[], |trainer| {
        train::restore_checkpoint(path, &checkpoint, trainer)?;
        f(trainer)
    })
}

fn run_eval(args: &EvalArgs) -> CliResult {
    let (dataset, _, test_idx) = open_dataset(&args.data)?;
    let executor = RayonExecutor::new(args.threads)?;
    with_checkpoint(&args.checkpoint, |trainer| {
        let scores = train::evaluate(
            trainer,
            &executor,
            &dataset,
            &test_idx,
            args.fit_steps,
            args.renders.as_deref(),
        )?;
        print_scores(&scores);
        Ok(())
    })
}

fn run_render(args: &RenderArgs) -> CliResult {
    let (dataset, _, test_idx) = open_dataset(&args.data)?;
    let views = if args.views.is_empty() {
        test_idx
    } else {
        args.views.clone()
    };
    let executor = RayonExecutor::new(args.threads)?;
    with_checkpoint(&args.checkpoint, |trainer| {
        let scores = train::evaluate(
            trainer,
            &executor,
            &dataset,
            &views,
            args.fit_steps,
            Some(&args.out),
        )?;
        for s in &scores {
            println!(
                "view {:>3}: {:.2} dB -> {}",
                s.index,
                s.psnr,
                args.out.join(format!("view_{:03}.png", s.index)).display()
            );
        }
        Ok(())
    })
}

fn run_bench(args: &BenchArgs) -> CliResult {
    let data = DataArgs {
        data: args.data.clone(),
        size: args.size,
        holdout: 8,
    };
    let (dataset, train_idx, _) = open_dataset(&data)?;
    let mut base = match &args.config {
        Some(path) => train::read_config(path)?,
        None => Config::DEFAULT,
    };
    base.steps = args.warmup + args.steps;
    let config = train::fit_config(&base, &dataset, train_idx.len());
    let frames: Vec<_> = train_idx.iter().map(|&i| &dataset.frames[i]).collect();
    println!(
        "model: {} scales {:?} x {} features, density MLP {}->{}->{}, colour MLP {}->{}->{}->3, SH bands {}, occupancy {}^3, {} rays/step",
        config.scales,
        &config.resolutions[..config.scales as usize],
        config.features,
        config.density_inputs(),
        config.density_hidden,
        config.density_outputs(),
        config.colour_inputs(),
        config.colour_hidden,
        config.colour_hidden,
        config.sh_bands,
        config.occupancy_res,
        config.rays_per_batch
    );
    println!(
        "{:>7}  {:>12}  {:>10}  {:>11}  {:>14}  {:>9}",
        "threads", "samples/s", "rays/s", "samples/ray", "marched/ray", "ms/step"
    );
    for &threads in &args.threads {
        let executor = RayonExecutor::new(threads)?;
        with_trainer(config, &frames, |trainer| {
            for _ in 0..args.warmup {
                trainer.step(&executor)?;
            }
            let (mut rays, mut samples, mut marched) = (0u64, 0u64, 0u64);
            let start = Instant::now();
            for _ in 0..args.steps {
                let r = trainer.step(&executor)?;
                rays += r.rays as u64;
                samples += r.samples as u64;
                marched += r.samples_marched as u64;
            }
            let seconds = start.elapsed().as_secs_f64();
            println!(
                "{threads:>7}  {:>12.0}  {:>10.0}  {:>11.2}  {:>14.2}  {:>9.1}",
                samples as f64 / seconds,
                rays as f64 / seconds,
                samples as f64 / rays.max(1) as f64,
                marched as f64 / rays.max(1) as f64,
                1000.0 * seconds / args.steps as f64
            );
            Ok(())
        })?;
    }
    println!("samples/s counts samples through forward + backward + update (after the early stop)");
    Ok(())
}

/// The demo's budget: the lightbox preset at 128 px, trained with appearance embeddings and
/// pose correction (under 4 minutes from start to report on the idle 2-core machine; timed in
/// the README).
const DEMO_FRAMES: u32 = 200;
const DEMO_SIZE: u16 = 128;
const DEMO_STEPS: u32 = 2000;

fn run_demo(args: &DemoArgs) -> CliResult {
    use orbit_nerf_host::ablation::{self, APPEARANCE_POSE};
    use orbit_nerf_host::report;
    use std::fmt::Write as _;
    let start = Instant::now();
    println!("simulating the lightbox preset: {DEMO_FRAMES} frames of {DEMO_SIZE} px");
    let (dataset, truth) = ablate::simulated(
        "lightbox",
        DEMO_FRAMES,
        DEMO_SIZE,
        None,
        &args.out.join("data"),
    )?;
    let (train_idx, test_idx) = dataset::split_every(dataset.frames.len(), 8);
    let mut config = Config::SPACECRAFT;
    config.steps = args.steps.unwrap_or(DEMO_STEPS);
    config.warmup_steps = config.warmup_steps.min(config.steps);
    let bar = ProgressBar::new(config.steps as u64).with_style(
        ProgressStyle::with_template("train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}")?
            .progress_chars("=> "),
    );
    let mut running_mse = None::<f64>;
    let result = ablation::run_variant(
        &dataset,
        truth.as_deref(),
        &train_idx,
        &test_idx,
        &config,
        APPEARANCE_POSE,
        args.threads,
        FIT_STEPS,
        &mut |step| {
            if !step.skipped {
                let mse = step.mse as f64;
                running_mse = Some(running_mse.map_or(mse, |r| 0.95 * r + 0.05 * mse));
            }
            let psnr = running_mse.map_or(0.0, |m| -10.0 * m.max(1e-12).log10());
            bar.set_message(format!("loss {:.5} psnr {psnr:.2} dB", step.mse));
            bar.inc(1);
        },
    )?;
    bar.finish_and_clear();
    let mut text = format!(
        "# orbit-nerf demo\n\nThe `lightbox` preset ({DEMO_FRAMES} frames of {DEMO_SIZE} px, every 8th of them held out), \
         trained for {} steps with appearance embeddings and pose correction in {:.1} s; held-out \
         embeddings fitted for {FIT_STEPS} steps on the left half of each view.\n\n",
        config.steps, result.train_seconds
    );
    let row = report::ModelRow {
        name: "ours + pose".into(),
        metrics: result.metrics,
        train_seconds: result.train_seconds,
    };
    text.push_str(&report::ablation_table(&[row]));
    if let (Some(before), Some(after)) = (result.pose_before, result.pose_after) {
        text.push_str("\n## Pose error of the training labels\n\n");
        text.push_str(&report::pose_error_table(&[(
            "ours + pose".into(),
            before,
            after,
        )]));
    }
    text.push_str("\n## Held-out views (truth, render)\n\n");
    for (k, &index) in test_idx.iter().enumerate().take(4) {
        let frame = &dataset.frames[index];
        let (w, h) = (frame.camera.width as u32, frame.camera.height as u32);
        let render = train::to_rgb8(&result.renders[k]);
        let (sw, sh, strip) =
            report::side_by_side(&[("truth", &frame.pixels), ("ours + pose", &render)], w, h);
        let name = format!("view_{index:03}.png");
        orbit_nerf_host::io::write_png(&args.out.join(&name), sw, sh, 3, &strip)?;
        writeln!(text, "![view {index}]({name})")?;
    }
    writeln!(
        text,
        "\nTotal wall time (simulate, train, evaluate, report): {:.1} s",
        start.elapsed().as_secs_f64()
    )?;
    orbit_nerf_host::io::write_atomic(&args.out.join("report.md"), text.as_bytes())?;
    println!("{text}");
    println!("report and renders in {}", args.out.display());
    Ok(())
}
