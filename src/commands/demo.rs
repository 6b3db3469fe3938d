//! `orbit-nerf demo`: the built-in default. Simulate the lightbox preset, train the method,
//! evaluate and write a report.

use super::train::TRAIN_BAR;
use super::{CliResult, FIT_STEPS, RunningPsnr, bar_style, machine_threads, parse_threads};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_core::Config;
use orbit_nerf_host::ablation::{self, APPEARANCE_POSE};
use orbit_nerf_host::ablation_report::{
    experiment_report, simulated, stated_label_noise, true_surface,
};
use orbit_nerf_host::dataset;
use orbit_nerf_host::report;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct DemoArgs {
    /// Output folder: report.md, metrics.json, renders, the simulated set (data/).
    #[arg(long, default_value = "runs/demo")]
    out: PathBuf,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
    /// Training steps (default: the demo's budget).
    #[arg(long)]
    steps: Option<u32>,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    no_masks: bool,
}

/// The demo's budget: the lightbox preset at 128 px, trained with appearance embeddings and
/// pose correction (under 4 minutes from start to report on the idle 2-core machine; timed in
/// the README).
const DEMO_FRAMES: u32 = 200;
const DEMO_SIZE: u16 = 128;
const DEMO_STEPS: u32 = 2000;

pub fn run(args: &DemoArgs) -> CliResult {
    let start = Instant::now();
    println!("simulating the lightbox preset: {DEMO_FRAMES} frames of {DEMO_SIZE} px");
    let (dataset, truth) = simulated(
        "lightbox",
        DEMO_FRAMES,
        DEMO_SIZE,
        None,
        &args.out.join("data"),
        !args.no_masks,
    )?;
    let (train_idx, test_idx) = dataset::split_every(dataset.frames.len(), 8);
    let mut config = Config::SPACECRAFT;
    stated_label_noise("lightbox")?.state_in(&mut config);
    config.steps = args.steps.unwrap_or(DEMO_STEPS);
    config.warmup_steps = config.warmup_steps.min(config.steps);
    let bar = ProgressBar::new(config.steps as u64).with_style(bar_style(TRAIN_BAR)?);
    let mut running = RunningPsnr::default();
    let result = ablation::run_variant(
        &dataset,
        truth.as_deref(),
        &train_idx,
        &test_idx,
        &config,
        APPEARANCE_POSE,
        args.threads,
        FIT_STEPS,
        &mut |_, step| {
            if !step.skipped {
                running.add(step.mse);
            }
            let psnr = running.db();
            bar.set_message(format!("loss {:.5} train-loss PSNR {psnr:.2} dB", step.mse));
            bar.inc(1);
        },
    )?;
    bar.finish_and_clear();
    let mut text = experiment_report(
        "orbit-nerf demo",
        &format!(
            "The `lightbox` preset ({DEMO_FRAMES} frames of {DEMO_SIZE} px, every 8th of them held out), \
             trained for {} steps with appearance embeddings and pose correction in {:.1} s; held-out \
             embeddings fitted for {FIT_STEPS} steps on the left half of each view.",
            config.steps, result.train_seconds
        ),
        std::slice::from_ref(&result),
        Some(&true_surface("lightbox")?),
        (&dataset, &test_idx),
        (&args.out, "view_"),
    )?;
    writeln!(
        text,
        "\nTotal wall time (simulate, train, evaluate, report): {:.1} s",
        start.elapsed().as_secs_f64()
    )?;
    orbit_nerf_host::io::write_atomic(&args.out.join("report.md"), text.as_bytes())?;
    report::Figures::new("demo", vec![result.figures()]).write(&args.out)?;
    println!("{text}");
    println!("report, metrics.json and renders in {}", args.out.display());
    Ok(())
}
