//! `orbit-nerf train`: train a field on a dataset, write the checkpoint, score the held-out
//! views.

use super::{
    CliResult, DataArgs, Fallible, ModelArgs, RunningPsnr, bar_style, choose_box, model_config,
    open_dataset, print_scores, with_trainer,
};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_core::{Executor, Trainer};
use orbit_nerf_host::train::{self, RayonExecutor};
use std::path::PathBuf;
use std::time::Instant;

/// The training progress bar (the demo draws the same).
pub(super) const TRAIN_BAR: &str = "train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}";

#[derive(Args)]
pub struct TrainArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    model: ModelArgs,
    /// Output folder: checkpoint.onrf, config.toml, renders/.
    #[arg(long, default_value = "runs/train")]
    out: PathBuf,
}

pub fn run(args: &TrainArgs) -> CliResult {
    orbit_nerf_host::io::check_output_folder(&args.out)?;
    let (mut dataset, train_idx, test_idx) = open_dataset(&args.data)?;
    let base = model_config(&args.model)?;
    choose_box(
        &mut dataset,
        args.model.scene_box,
        args.model.config.as_deref(),
        &train_idx,
    )?;
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
    let bar = ProgressBar::new(steps as u64).with_style(bar_style(TRAIN_BAR)?);
    let start = Instant::now();
    let mut summary = TrainSummary {
        seconds: 0.0,
        rays: 0,
        samples: 0,
        marched: 0,
        skipped: 0,
    };
    let mut running = RunningPsnr::default();
    for i in 0..steps {
        let report = trainer.step(executor)?;
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
