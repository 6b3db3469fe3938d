//! `orbit-nerf demo`: the built-in default. Simulate the lightbox preset, train the method,
//! evaluate and write a report.

use super::train::TRAIN_BAR;
use super::{CliResult, MAX_STEPS, bar_style, machine_threads, parse_threads};
use clap::Args;
use indicatif::ProgressBar;
use orbit_nerf_host::ablation_report::{self, DEMO_FRAMES, DEMO_SIZE, DEMO_STEPS};
use orbit_nerf_host::progress::RunningPsnr;
use std::path::PathBuf;

#[derive(Args)]
pub struct DemoArgs {
    /// Output folder: report.md, metrics.json, renders, the simulated set (data/).
    #[arg(long, default_value = "runs/demo")]
    out: PathBuf,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
    /// Training steps, 1 to 100 million (default: the demo's budget, 2000).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=MAX_STEPS))]
    steps: Option<u32>,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    no_masks: bool,
}

pub fn run(args: &DemoArgs) -> CliResult {
    println!("simulating the lightbox preset: {DEMO_FRAMES} frames of {DEMO_SIZE} px");
    let steps = args.steps.unwrap_or(DEMO_STEPS);
    let bar = ProgressBar::new(steps as u64).with_style(bar_style(TRAIN_BAR)?);
    let mut running = RunningPsnr::default();
    let text = ablation_report::run_demo(
        &args.out,
        (Some(steps), args.threads, !args.no_masks),
        &mut |_, step| {
            running.add(step);
            let psnr = running.db();
            bar.set_message(format!("loss {:.5} train-loss PSNR {psnr:.2} dB", step.mse));
            bar.inc(1);
        },
    )?;
    bar.finish_and_clear();
    println!("{text}");
    println!("report, metrics.json and renders in {}", args.out.display());
    Ok(())
}
