//! `orbit-nerf eval`: score held-out views of a dataset with a checkpoint.

use super::{CliResult, DataArgs, FIT_STEPS, evaluate_checkpoint, open_dataset, print_scores};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct EvalArgs {
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

pub fn run(args: &EvalArgs) -> CliResult {
    let (dataset, _, test_idx) = open_dataset(&args.data)?;
    let scores = evaluate_checkpoint(
        &args.checkpoint,
        args.threads,
        &dataset,
        &test_idx,
        args.fit_steps,
        args.renders.as_deref(),
    )?;
    print_scores(&scores);
    Ok(())
}
