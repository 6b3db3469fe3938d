//! `orbit-nerf train`: train a field on a dataset, write the checkpoint, score the held-out
//! views. A run stopped by Ctrl-C, SIGTERM or `--stop-after` checkpoints and continues with
//! `--resume` to the same bytes as a run that was never stopped.

use super::{
    CliResult, DataArgs, Fallible, ModelArgs, RunningPsnr, STOP, bar_style, model_config,
    print_scores, stop_on_signal,
};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_core::{StepReport, Trainer};
use orbit_nerf_host::geometry::extract::SurfaceOptions;
use orbit_nerf_host::pipeline::{
    self, CHECKPOINT_FILE, Flow, Observer, Outcome, Pipeline, StepTally, TrainOptions,
};
use orbit_nerf_host::{io, memory};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The training progress bar (the demo draws the same).
pub(super) const TRAIN_BAR: &str = "train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}";

#[derive(Args)]
pub struct TrainArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    model: ModelArgs,
    /// The run folder: checkpoint.onrf, run.toml (the data settings, which `eval`, `render`,
    /// `export` and `--resume` reuse), config.toml (the whole config, every field),
    /// metrics.json, renders/.
    #[arg(long, visible_alias = "run", default_value = "runs/train")]
    out: PathBuf,
    /// Continue the run saved in OUT with its own config and data (run.toml; data flags given
    /// must agree with it); ends with the bytes of a run never stopped.
    #[arg(long, conflicts_with_all = ["force", "preset", "config", "steps", "seed", "embedding_dim", "pose_correction", "scene_box"])]
    resume: bool,
    /// Start a fresh run even though OUT holds an earlier run's checkpoint, replacing it.
    #[arg(long)]
    force: bool,
    /// Stop (and checkpoint) once the run has taken this many steps, as Ctrl-C would;
    /// continue with --resume.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    stop_after: Option<u32>,
    /// Read the data, choose the config and print the memory plan of every stage (training,
    /// saving, scoring, exporting) against the limit, then stop: nothing is trained or
    /// written. Exits non-zero when a stage does not fit.
    #[arg(long)]
    dry_run: bool,
}

pub fn run(args: &TrainArgs) -> CliResult {
    stop_on_signal()?;
    let given = args.data.choice();
    let options = TrainOptions {
        threads: args.model.threads,
        stop_after: args.stop_after,
        replace: args.force,
        fit_steps: args.model.fit_steps,
        align_poses: args.model.align_poses,
    };
    let pipeline = if args.resume {
        Pipeline::resume(&args.out, &given, args.model.memory_limit)?
    } else {
        // Refused before anything is read: a fresh run over an earlier run's checkpoint.
        io::check_fresh_checkpoint(&args.out.join(CHECKPOINT_FILE), args.force, "training run")?;
        let settings = given
            .settings()
            .ok_or("--data DIR is needed (or --run DIR --resume to continue a run)")?;
        // The config (preset, file and flags) is checked before the data is read: the preset
        // for the data comes from the folder's layout alone.
        let chosen = model_config(&args.model, &settings.data)?;
        let stated = pipeline::stated_box(args.model.scene_box, args.model.config.as_deref())?;
        Pipeline::open(settings, chosen, stated, args.model.memory_limit)?
    };
    for note in &pipeline.notes {
        println!("{note}");
    }
    let data = &pipeline.data;
    println!(
        "training on {} views ({} held out) of {} for {} steps, {} threads",
        data.train.len(),
        data.test.len(),
        data.dataset.source.display(),
        pipeline.config.steps,
        args.model.threads
    );
    println!("{}", data.scored_at());
    if args.dry_run {
        return print_memory_plan(&pipeline);
    }
    let mut progress = ProgressLines::new(args.resume)?;
    let outcome = pipeline.train(&args.out, &options, &mut progress)?;
    progress.bar.finish_and_clear();
    match outcome {
        Outcome::Stopped { step } => {
            print_summary(&progress);
            println!(
                "stopped at step {step} of {}; checkpoint {} (continue with --resume)",
                pipeline.config.steps,
                args.out.join(CHECKPOINT_FILE).display()
            );
        }
        Outcome::Finished(run) => {
            print_summary(&progress);
            if let Some(poses) = &run.pose_refinement {
                let summary = &poses.summary;
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
            }
            print_scores(&run.scores);
            println!(
                "checkpoint, run.toml, config, metrics.json and renders in {}",
                args.out.display()
            );
        }
    }
    Ok(())
}

/// Print the run's memory plan against its limit (`train --dry-run`); fail naming the first
/// stage that does not fit.
fn print_memory_plan(pipeline: &Pipeline) -> CliResult {
    let limit = memory::limit_or_default(pipeline.memory_limit);
    let plan = pipeline.memory_plan(&SurfaceOptions::default());
    println!(
        "memory plan, limit {}:",
        limit.map_or(
            "none (the machine's memory is unknown)".into(),
            memory::human
        )
    );
    for stage in &plan {
        println!("  {}: {}", stage.name, memory::describe(&stage.parts));
        println!("    {}", stage.note);
    }
    for stage in &plan {
        memory::check_plan(Path::new(&stage.name), &stage.parts, limit)?;
    }
    println!("dry run: every stage fits; nothing was trained or written");
    Ok(())
}

/// How often a run without a terminal prints its progress line.
const PLAIN_PROGRESS_EVERY: Duration = Duration::from_secs(5);

/// The training progress: a bar on a terminal, else a plain line at the first step and then
/// every few seconds. Ctrl-C / SIGTERM stops training within the step it arrives in (the
/// step is given up: the checkpoint is that of the last finished step).
struct ProgressLines {
    bar: ProgressBar,
    resumed: bool,
    running: RunningPsnr,
    tally: StepTally,
    skipped: u32,
    started: Instant,
    last_line: Option<Instant>,
}

impl ProgressLines {
    fn new(resumed: bool) -> Fallible<ProgressLines> {
        Ok(ProgressLines {
            bar: ProgressBar::new(0).with_style(bar_style(TRAIN_BAR)?),
            resumed,
            running: RunningPsnr::default(),
            tally: StepTally::default(),
            skipped: 0,
            started: Instant::now(),
            last_line: None,
        })
    }
}

impl Observer for ProgressLines {
    fn start(&mut self, trainer: &Trainer<'_>, end: u32) {
        let step = trainer.state().step;
        if self.resumed {
            println!("resuming at step {step} of {}", trainer.config().steps);
        }
        self.bar.set_length((end - step.min(end)) as u64);
        self.started = Instant::now();
    }

    fn step(
        &mut self,
        trainer: &mut Trainer<'_>,
        end: u32,
        report: &StepReport,
    ) -> orbit_nerf_host::Result<Flow> {
        let tally = &mut self.tally;
        tally.steps += 1;
        tally.rays += report.rays as u64;
        tally.samples += report.samples as u64;
        tally.marched += report.samples_marched as u64;
        tally.seconds = self.started.elapsed().as_secs_f64();
        if report.skipped {
            self.skipped += 1;
        } else {
            self.running.add(report.mse);
        }
        let step = trainer.state().step;
        if tally.steps % 10 == 1 || step == end {
            self.bar.set_message(format!(
                "loss {:.5} train-loss PSNR {:.2} dB {:.1} samples/ray",
                report.mse,
                self.running.db(),
                report.samples as f32 / report.rays.max(1) as f32
            ));
        }
        self.bar.inc(1);
        // Without a terminal (logs, CI) the bar is hidden: a plain line says how far it is.
        if self.bar.is_hidden()
            && self
                .last_line
                .is_none_or(|t| t.elapsed() >= PLAIN_PROGRESS_EVERY)
        {
            self.last_line = Some(Instant::now());
            let per_step = tally.seconds / tally.steps as f64;
            println!(
                "step {step}/{end}: loss {:.5}, {:.0} rays/s, ETA {:.0} s",
                report.mse,
                tally.rays as f64 / tally.seconds.max(1e-9),
                per_step * end.saturating_sub(step) as f64
            );
        }
        Ok(if STOP.load(Ordering::SeqCst) {
            Flow::Stop
        } else {
            Flow::Continue
        })
    }

    fn stop_flag(&self) -> Option<&AtomicBool> {
        Some(&STOP)
    }
}

/// Speed, samples per ray and skipped steps of this session's training steps.
fn print_summary(progress: &ProgressLines) {
    let s = &progress.tally;
    if s.steps == 0 {
        // Stopped within the first step of the session, which was given up.
        println!("no training step finished in this session");
        return;
    }
    println!(
        "trained in {:.1} s: {:.0} rays/s, {:.0} samples/s ({:.1} samples/ray after early stop, {:.1} marched), {} steps skipped",
        s.seconds,
        s.rays as f64 / s.seconds,
        s.samples as f64 / s.seconds,
        s.samples_per_ray(),
        s.marched as f64 / s.rays.max(1) as f64,
        progress.skipped
    );
}
