//! `orbit-nerf eval`: score held-out views of a dataset with a checkpoint.

use super::{
    CliResult, DataArgs, FIT_STEPS, MAX_FIT_STEPS, RunArgs, machine_threads, open_dataset,
    parse_threads, print_scores,
};
use clap::Args;
use orbit_nerf_host::pipeline::DataSettings;
use orbit_nerf_host::report::{Figures, ModelFigures};
use orbit_nerf_host::{io, pipeline, train, values};
use std::path::PathBuf;

#[derive(Args)]
pub struct EvalArgs {
    #[command(flatten)]
    model: RunArgs,
    #[command(flatten)]
    data: DataArgs,
    /// Score every view of this separate test set (any format; read at the run's size and
    /// masks) instead of the data's held-out views: the paper's protocol.
    #[arg(long)]
    test_data: Option<PathBuf>,
    /// Write renders and ground truth of the held-out views here.
    #[arg(long)]
    renders: Option<PathBuf>,
    /// Write the printed figures as JSON to METRICS/metrics.json (default: into the --renders
    /// folder when one is given).
    #[arg(long)]
    metrics: Option<PathBuf>,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
    /// Steps fitting each view's appearance embedding on its left half (0 to 100000).
    #[arg(long, default_value_t = FIT_STEPS, value_parser = clap::value_parser!(u32).range(0..=MAX_FIT_STEPS))]
    fit_steps: u32,
    /// Also fit each view's pose correction in those steps and score it at its corrected
    /// label (BARF's test-time alignment), instead of at its label.
    #[arg(long)]
    align_poses: bool,
    /// Replace renders and metrics.json already in --renders / --metrics.
    #[arg(long)]
    force: bool,
    /// Largest memory the model, the data and the renders may take together (e.g. 8G, 512M);
    /// default: 80 % of the machine's available memory. Checked before anything large is
    /// allocated.
    #[arg(long, value_parser = values::byte_size)]
    memory_limit: Option<u64>,
}

pub fn run(args: &EvalArgs) -> CliResult {
    for dir in [&args.metrics, &args.renders].into_iter().flatten() {
        orbit_nerf_host::io::check_output_folder(dir)?;
    }
    let (checkpoint, settings) = args.model.checkpoint_and_data(&args.data, "score")?;
    // A separate test set: every view held out, read as the run's data is.
    let settings = match &args.test_data {
        Some(test) => DataSettings {
            data: test.clone(),
            holdout: 1,
            ..settings
        },
        None => settings,
    };
    let model = pipeline::checkpoint_parts(&checkpoint)?;
    let data = open_dataset(&settings, args.memory_limit, &model)?;
    let mut outputs: Vec<PathBuf> = Vec::new();
    if let Some(dir) = &args.renders {
        outputs.extend(train::render_files(dir, &data.test));
    }
    if let Some(dir) = args.metrics.as_ref().or(args.renders.as_ref()) {
        outputs.push(dir.join("metrics.json"));
    }
    io::check_new_files(outputs.iter().map(PathBuf::as_path), args.force)?;
    println!("{}", data.scored_at());
    let scores = pipeline::evaluate_checkpoint(
        &checkpoint,
        (args.threads, args.memory_limit),
        &data,
        &data.test,
        (args.fit_steps, args.align_poses),
        args.renders.as_deref(),
    )?;
    let mean = print_scores(&scores);
    if let Some(dir) = args.metrics.as_ref().or(args.renders.as_ref()) {
        let model = ModelFigures {
            name: checkpoint.display().to_string(),
            mean,
            views: train::view_figures(&scores),
            training: None,
            mean_at: None,
            pose_refinement: None,
        };
        Figures::new("eval", vec![model]).write(dir)?;
        println!("metrics.json in {}", dir.display());
    }
    Ok(())
}
