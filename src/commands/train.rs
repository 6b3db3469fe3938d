//! `orbit-nerf train`: train a field on a dataset, write the checkpoint, score the held-out
//! views. A run stopped by Ctrl-C, SIGTERM or `--stop-after` checkpoints and continues with
//! `--resume` to the same bytes as a run that was never stopped.

use super::{
    CliResult, DataArgs, ModelArgs, STOP, bar_style, model_config, print_scores, stop_on_signal,
};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_core::{StepReport, Trainer};
use orbit_nerf_host::geometry::extract::SurfaceOptions;
use orbit_nerf_host::io;
use orbit_nerf_host::pipeline::{
    self, CHECKPOINT_FILE, Flow, Observer, Outcome, Pipeline, TrainOptions,
};
use orbit_nerf_host::progress::SessionProgress;
use std::path::PathBuf;
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
    let mut progress = ProgressLines {
        bar: ProgressBar::new(0).with_style(bar_style(TRAIN_BAR)?),
        resumed: args.resume,
        session: SessionProgress::default(),
        last_line: None,
    };
    let outcome = pipeline.train(&args.out, &options, &mut progress)?;
    progress.bar.finish_and_clear();
    match outcome {
        Outcome::Stopped { step } => {
            println!("{}", progress.session.summary());
            println!(
                "stopped at step {step} of {}; checkpoint {} (continue with --resume)",
                pipeline.config.steps,
                args.out.join(CHECKPOINT_FILE).display()
            );
        }
        Outcome::Finished(run) => {
            println!("{}", progress.session.summary());
            if let Some(poses) = &run.pose_refinement {
                println!("{}", poses.summary_line());
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
    let plan = pipeline.memory_plan(&SurfaceOptions::default());
    println!("{}", pipeline.memory_plan_text(&plan));
    pipeline.check_memory_plan(&plan)?;
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
    session: SessionProgress,
    last_line: Option<Instant>,
}

impl Observer for ProgressLines {
    fn start(&mut self, trainer: &Trainer<'_>, end: u32) {
        let step = trainer.state().step;
        if self.resumed {
            println!("resuming at step {step} of {}", trainer.config().steps);
        }
        self.bar.set_length((end - step.min(end)) as u64);
        self.session.restart_clock();
    }

    fn step(
        &mut self,
        trainer: &mut Trainer<'_>,
        end: u32,
        report: &StepReport,
    ) -> orbit_nerf_host::Result<Flow> {
        self.session.add(report);
        let step = trainer.state().step;
        if self.session.tally.steps % 10 == 1 || step == end {
            self.bar.set_message(self.session.bar_message(report));
        }
        self.bar.inc(1);
        // Without a terminal (logs, CI) the bar is hidden: a plain line says how far it is.
        let due = (self.last_line).is_none_or(|t| t.elapsed() >= PLAIN_PROGRESS_EVERY);
        if self.bar.is_hidden() && due {
            self.last_line = Some(Instant::now());
            println!("{}", self.session.line(step, end, report));
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
