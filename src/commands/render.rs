//! `orbit-nerf render`: render views of a dataset's cameras with a checkpoint to PNG.

use super::{CliResult, DataArgs, FIT_STEPS, evaluate_checkpoint, open_dataset};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct RenderArgs {
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

pub fn run(args: &RenderArgs) -> CliResult {
    let (dataset, _, test_idx) = open_dataset(&args.data)?;
    let views = if args.views.is_empty() {
        test_idx
    } else {
        args.views.clone()
    };
    let scores = evaluate_checkpoint(
        &args.checkpoint,
        args.threads,
        &dataset,
        &views,
        args.fit_steps,
        Some(&args.out),
    )?;
    for s in &scores {
        println!(
            "view {:>3}: {:.2} dB -> {}",
            s.index,
            s.metrics.psnr_full,
            args.out.join(format!("view_{:03}.png", s.index)).display()
        );
    }
    Ok(())
}
