//! `orbit-nerf train`: train a field on a dataset, write the checkpoint, score the held-out
//! views. A run stopped by Ctrl-C, SIGTERM or `--stop-after` checkpoints and continues with
//! `--resume` to the same bytes as a run that was never stopped.

use super::{
    CliResult, DataArgs, Fallible, ModelArgs, RunningPsnr, STOP, bar_style, check_dataset_memory,
    choose_box, model_config, open_dataset, print_scores, stop_on_signal, with_trainer,
};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_core::{Executor, Trainer};
use orbit_nerf_host::dataset::Frame;
use orbit_nerf_host::io;
use orbit_nerf_host::report::{
    self, Figures, ModelFigures, PoseRefinementFigures, TrainingFigures,
};
use orbit_nerf_host::train::{self, RayonExecutor};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// The training progress bar (the demo draws the same).
pub(super) const TRAIN_BAR: &str = "train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}";

#[derive(Args)]
pub struct TrainArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    model: ModelArgs,
    /// Output folder: checkpoint.onrf, config.toml (the whole config, every field), metrics.json,
    /// renders/.
    #[arg(long, default_value = "runs/train")]
    out: PathBuf,
    /// Continue the run saved in OUT/checkpoint.onrf with its own config (give the same
    /// --data, --size, --holdout and masks); ends with the bytes of a run never stopped.
    #[arg(long, conflicts_with_all = ["force", "preset", "config", "steps", "seed", "embedding_dim", "pose_correction", "scene_box"])]
    resume: bool,
    /// Start a fresh run even though OUT holds an earlier run's checkpoint, replacing it.
    #[arg(long)]
    force: bool,
    /// Stop (and checkpoint) once the run has taken this many steps, as Ctrl-C would;
    /// continue with --resume.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    stop_after: Option<u32>,
}

pub fn run(args: &TrainArgs) -> CliResult {
    let checkpoint_path = args.out.join("checkpoint.onrf");
    if args.resume {
        io::check_output_folder(&args.out)?;
        if !checkpoint_path.is_file() {
            return Err(format!(
                "{}: no checkpoint to resume (start a run without --resume)",
                checkpoint_path.display()
            )
            .into());
        }
    } else {
        io::check_fresh_checkpoint(&checkpoint_path, args.force, "training run")?;
    }
    stop_on_signal()?;
    // The config (preset, file and flags) is checked before the data is read: the preset for
    // the data comes from the folder's layout alone.
    let base = if args.resume {
        None
    } else {
        Some(model_config(&args.model, &args.data.data)?)
    };
    check_dataset_memory(&args.data, args.model.memory_limit)?;
    let (mut dataset, train_idx, test_idx) = open_dataset(&args.data)?;
    if train_idx.is_empty() {
        return Err(format!(
            "{}: no training view: --holdout {} holds out every one of its {} views",
            dataset.source.display(),
            args.data.holdout,
            dataset.frames.len()
        )
        .into());
    }
    train::check_frames_have_content(
        &dataset.source,
        train_idx.iter().map(|&i| &dataset.frames[i]),
    )?;
    let (config, restored) = if let Some(base) = base {
        choose_box(
            &mut dataset,
            args.model.scene_box,
            args.model.config.as_deref(),
            &train_idx,
        )?;
        (train::fit_config(&base, &dataset, train_idx.len()), None)
    } else {
        let checkpoint = orbit_nerf_host::checkpoint::load(&checkpoint_path)?;
        let config = train::checkpoint_config(&checkpoint_path, &checkpoint)?;
        (config, Some(checkpoint))
    };
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
    // A resumed run's frames come from its checkpoint (and are checked against the data).
    let fresh_frames: &[&Frame] = if restored.is_some() { &[] } else { &frames };
    with_trainer(config, args.model.memory_limit, fresh_frames, |trainer| {
        if let Some(checkpoint) = &restored {
            train::restore_checkpoint(&checkpoint_path, checkpoint, trainer)?;
            check_same_frames(&checkpoint_path, trainer, &frames)?;
            println!(
                "resuming {} at step {} of {}",
                checkpoint_path.display(),
                trainer.state().step,
                config.steps
            );
        }
        let summary = train_loop(trainer, &executor, args.stop_after)?;
        print_summary(&summary);
        // A finished run's last stage: the poses' refinement with the field frozen.
        let pose_fits = if trainer.state().step >= config.steps {
            train::refine_poses(trainer, &executor)?
        } else {
            Vec::new()
        };
        let tally = train::TrainingTally {
            steps: summary.steps,
            samples: summary.samples,
        };
        train::check_trained(&args.out, trainer, tally)?;
        train::save_checkpoint(&checkpoint_path, trainer)?;
        io::write_atomic(
            &args.out.join("config.toml"),
            train::config_to_toml(&config).as_bytes(),
        )?;
        if trainer.state().step < config.steps {
            println!(
                "stopped at step {} of {}; checkpoint {} (continue with --resume)",
                trainer.state().step,
                config.steps,
                checkpoint_path.display()
            );
            return Ok(());
        }
        let scores = train::evaluate(
            trainer,
            &executor,
            &dataset,
            &test_idx,
            args.model.fit_steps,
            args.model.align_poses,
            Some(&args.out.join("renders")),
        )?;
        let mean = print_scores(&scores);
        let state = trainer.state();
        let model = ModelFigures {
            name: "model".into(),
            mean,
            views: train::view_figures(&scores),
            training: Some(TrainingFigures {
                steps: state.step as u64,
                steps_skipped: state.skipped as u64,
                seconds: summary.seconds,
                samples_per_ray: summary.samples as f64 / summary.rays.max(1) as f64,
            }),
            mean_at: None,
            pose_refinement: pose_refinement(trainer, &frames, &pose_fits),
        };
        Figures::new("train", vec![model]).write(&args.out)?;
        println!(
            "checkpoint, config, metrics.json and renders in {}",
            args.out.display()
        );
        Ok(())
    })
}

/// The training poses' refinement figures for `metrics.json` (with pose correction), and
/// their mean 1-sigma printed.
fn pose_refinement(
    trainer: &Trainer<'_>,
    frames: &[&Frame],
    fits: &[orbit_nerf_core::PoseFit],
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
    println!(
        "pose uncertainty (1 sigma, mean over {} frames): attitude {} deg, position {}",
        summary.frames,
        summary
            .rotation_sigma_deg_mean
            .map_or("n/a".into(), |v| format!("{v:.3}")),
        summary
            .position_sigma_mean
            .map_or("n/a".into(), |v| format!("{v:.4}"))
    );
    Some(PoseRefinementFigures { summary, frames })
}

/// A resumed run trains on the frames its checkpoint holds: refuse data whose training views
/// are not those (another folder, size, hold-out or masking).
fn check_same_frames(checkpoint: &Path, trainer: &Trainer<'_>, frames: &[&Frame]) -> CliResult {
    let store = trainer.frames();
    let differs = |i: usize| {
        store
            .occupied_slot(i)
            .and_then(|slot| store.pixels(slot))
            .is_none_or(|pixels| pixels != frames[i].pixels.as_slice())
    };
    if store.len() != frames.len() {
        return Err(format!(
            "{}: the run trained on {} views, the data gives {}; resume with the run's --data, --size, --holdout and masks",
            checkpoint.display(),
            store.len(),
            frames.len()
        )
        .into());
    }
    if let Some(i) = (0..frames.len()).find(|&i| differs(i)) {
        return Err(format!(
            "{}: training view {} ({}) is not the one the run trained on; resume with the run's --data, --size, --holdout and masks",
            checkpoint.display(),
            i,
            frames[i].name
        )
        .into());
    }
    Ok(())
}

/// How often a run without a terminal prints its progress line.
const PLAIN_PROGRESS_EVERY: Duration = Duration::from_secs(5);

struct TrainSummary {
    steps: u64,
    seconds: f64,
    rays: u64,
    samples: u64,
    marched: u64,
    skipped: u32,
}

/// Run the remaining steps with a progress bar (steps/s, loss, running PSNR), stopping early
/// at step `stop_after` or after the step during which Ctrl-C / SIGTERM arrived.
fn train_loop<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    stop_after: Option<u32>,
) -> Fallible<TrainSummary> {
    let end = stop_after.map_or(trainer.config().steps, |stop| {
        stop.min(trainer.config().steps)
    });
    let steps = end - trainer.state().step.min(end);
    let bar = ProgressBar::new(steps as u64).with_style(bar_style(TRAIN_BAR)?);
    let start = Instant::now();
    let mut summary = TrainSummary {
        steps: 0,
        seconds: 0.0,
        rays: 0,
        samples: 0,
        marched: 0,
        skipped: 0,
    };
    let mut running = RunningPsnr::default();
    let mut last_line = start;
    for i in 0..steps {
        let report = trainer.step(executor)?;
        summary.steps += 1;
        summary.rays += report.rays as u64;
        summary.samples += report.samples as u64;
        summary.marched += report.samples_marched as u64;
        if !report.skipped {
            running.add(report.mse);
        }
        if i % 10 == 0 || i + 1 == steps {
            let psnr = running.db();
            bar.set_message(format!(
                "loss {:.5} train-loss PSNR {psnr:.2} dB {:.1} samples/ray",
                report.mse,
                report.samples as f32 / report.rays.max(1) as f32
            ));
        }
        bar.inc(1);
        // Without a terminal (logs, CI) the bar is hidden: a plain line at the first step and
        // then every few seconds says how far the run is.
        if bar.is_hidden() && (i == 0 || last_line.elapsed() >= PLAIN_PROGRESS_EVERY) {
            last_line = Instant::now();
            let seconds = start.elapsed().as_secs_f64();
            let per_step = seconds / (i + 1) as f64;
            println!(
                "step {}/{}: loss {:.5}, {:.0} rays/s, ETA {:.0} s",
                trainer.state().step,
                end,
                report.mse,
                summary.rays as f64 / seconds.max(1e-9),
                per_step * (steps - i - 1) as f64
            );
        }
        if STOP.load(Ordering::SeqCst) {
            break;
        }
    }
    bar.finish_and_clear();
    summary.seconds = start.elapsed().as_secs_f64();
    summary.skipped = trainer.state().skipped;
    Ok(summary)
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
