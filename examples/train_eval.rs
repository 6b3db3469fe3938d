//! Train and score a model through the host library alone, as a ground-segment or
//! flight-software team would embed it: simulate a small spacecraft set, open it with its
//! settings, train with a progress observer, and read the held-out scores.
//!
//! `cargo run --release --example train_eval [-- OUT_FOLDER]` (default: a temporary folder).

use orbit_nerf_core::{StepReport, Trainer};
use orbit_nerf_host::pipeline::{
    self, DataSettings, Flow, Observer, Outcome, Pipeline, TrainOptions,
};
use orbit_nerf_host::sim::{self, Scene};
use std::path::PathBuf;

/// Prints the loss every 100 steps.
struct EveryHundred;

impl Observer for EveryHundred {
    fn step(
        &mut self,
        trainer: &mut Trainer<'_>,
        end: u32,
        report: &StepReport,
    ) -> orbit_nerf_host::Result<Flow> {
        let step = trainer.state().step;
        if step % 100 == 0 || step == end {
            println!("step {step}/{end}: loss {:.5}", report.mse);
        }
        Ok(Flow::Continue)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args_os().nth(1).map_or_else(
        || std::env::temp_dir().join("orbit-nerf-train-eval"),
        PathBuf::from,
    );
    // A small lightbox set: 24 frames of 48 px with noisy pose labels and exact truth.
    let data = out.join("data");
    let mut scene = Scene::load("lightbox")?;
    scene.spec.frames = 24;
    scene.spec.size = 48;
    sim::simulate(&scene, &data, &|| {})?;

    // The dataset's settings (size, hold-out, masks) and the preset for its format.
    let settings = DataSettings {
        size: 48,
        holdout: 6,
        ..DataSettings::new(&data)
    };
    let mut chosen = pipeline::choose_config(None, &settings.data, None)?;
    chosen.config.steps = 300;
    chosen.config.warmup_steps = chosen.config.warmup_steps.min(300);
    let pipeline = Pipeline::open(settings, chosen, None, None)?;
    for note in &pipeline.notes {
        println!("{note}");
    }
    let options = TrainOptions {
        replace: true,
        fit_steps: 20,
        ..TrainOptions::default()
    };
    match pipeline.train(&out.join("run"), &options, &mut EveryHundred)? {
        Outcome::Finished(run) => {
            for score in &run.scores {
                println!("{}: {:.2} dB", score.name, score.metrics.psnr_full);
            }
            println!(
                "mean over {} held-out views: PSNR {:.2} dB, SSIM {:.4}; run folder {}",
                run.scores.len(),
                run.mean.psnr_full,
                run.mean.ssim_full,
                out.join("run").display()
            );
        }
        Outcome::Stopped { step } => println!("stopped at step {step}"),
    }
    Ok(())
}
