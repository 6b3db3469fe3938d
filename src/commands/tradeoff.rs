//! `orbit-nerf tradeoff`: what accuracy costs in time. Writes a sweep description with an
//! `[anytime]` table (the reference config, then one variant per knob value) to
//! `<out>/tradeoff.toml` and runs it as `sweep run` does: every variant trained and scored at
//! fixed steps, its training seconds measured, then the report (`sweep.md`, `tradeoff.csv`,
//! Pareto plots, anytime curves). One task at a time by default, so the times compare;
//! `orbit-nerf sweep slurm <out>/tradeoff.toml` takes the same description to a cluster.

use super::sweep::run_local;
use super::{FIT_STEPS, Fallible, preset_parser};
use orbit_nerf_host::pipeline;
use orbit_nerf_host::presets;
use orbit_nerf_host::sweep::studies::{self, StudyData, Tradeoff, Written};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct TradeoffArgs {
    /// Scene to simulate: a preset (synthetic, lightbox, sunlamp, inspection, rendezvous; lightbox-test: a separate test set) or a scene file.
    #[arg(long, default_value = "lightbox")]
    scene: String,
    /// Use this dataset (SPEED+/SHIRT/simulator, NeRF-synthetic or nerfstudio) instead.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Frames to simulate (a simulated scene only).
    #[arg(long)]
    frames: Option<u32>,
    /// Image size in pixels of the reference (the frames' side, or the longer side a dataset
    /// is resized to, never upsampled).
    #[arg(long, default_value_t = 128)]
    size: u32,
    /// Built-in config of the reference (default: `spacecraft` for a simulated scene, else
    /// the one for the data's format).
    #[arg(long, value_parser = preset_parser())]
    preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Training steps of the reference (default: the config's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    steps: Option<u32>,
    /// A knob and its values, one variant each: a config field (`features=8,32`,
    /// `resolutions=[16,32,64,0]`, `texel_update=stochastic_rounding`) or `size=64,256` (with
    /// --data at most its images' size: frames are never upsampled). Repeat for more knobs.
    /// Default: every built-in knob one step to either side (sizes above the data's left out).
    #[arg(long, value_name = "KNOB=V1,V2")]
    vary: Vec<String>,
    /// Steps after which the held-out views are also scored (default: 1/16, 1/8, 1/4, 1/2 and
    /// 3/4 of the reference's steps); every variant is also scored at its end.
    #[arg(long, value_delimiter = ',')]
    at: Vec<u32>,
    /// The figure variants are ranked by: psnr_foreground (default), psnr_full, psnr_right,
    /// psnr_foreground_right, ssim_full, ssim_right.
    #[arg(long)]
    quality: Option<String>,
    /// Quality levels whose time to reach the report gives, per variant (e.g. 25,27,28).
    #[arg(long, value_delimiter = ',')]
    targets: Vec<f64>,
    /// Training times (s) within which the report names the best variant.
    #[arg(long, value_delimiter = ',', default_values_t = [30.0, 60.0, 300.0])]
    budgets: Vec<f64>,
    /// Every N-th view is held out.
    #[arg(long, default_value_t = 8)]
    holdout: usize,
    /// Score on this separate test set (a dataset folder of any format; every view scored at
    /// its exact pose where it has one) and train on every frame, as the paper's protocol is;
    /// --holdout is then not used.
    #[arg(long, conflicts_with = "holdout")]
    test_data: Option<PathBuf>,
    /// Steps fitting each held-out view's embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    fit_steps: u32,
    /// Keep the sky as recorded (by default masks give background pixels the background
    /// colour).
    #[arg(long)]
    no_masks: bool,
    /// The sweep's folder: `tradeoff.toml`, `tasks/<index>/`, the report.
    #[arg(long, default_value = "runs/tradeoff")]
    out: PathBuf,
    /// Tasks run at once (default 1: tasks sharing the cores would distort each other's
    /// times).
    #[arg(long, default_value_t = 1)]
    jobs: usize,
    /// Threads of each task (default: the cores shared among the jobs).
    #[arg(long)]
    threads: Option<usize>,
    /// Only write `<out>/tradeoff.toml` (to run it with `sweep run` or `sweep slurm`).
    #[arg(long)]
    write_only: bool,
}

/// The description's file name in `--out`.
const DESCRIPTION: &str = "tradeoff.toml";

pub fn run(args: &TradeoffArgs) -> Fallible<()> {
    let (preset, file) = (args.preset.as_deref(), args.config.as_deref());
    let chosen = match &args.data {
        Some(data) => pipeline::choose_config(preset, data, file)?,
        None => pipeline::preset_config(preset, presets::SPACECRAFT, "a simulated scene", file)?,
    };
    println!("{}", chosen.note);
    let data = StudyData {
        scene: args.scene.clone(),
        data: args.data.clone(),
        preset: args.preset.clone(),
        config: args.config.clone(),
        steps: args.steps,
        size: args.size,
        holdout: args.holdout,
        fit_steps: args.fit_steps,
        masks: !args.no_masks,
    };
    let study = Tradeoff {
        frames: args.frames,
        vary: args.vary.clone(),
        at: args.at.clone(),
        quality: args.quality.clone(),
        targets: args.targets.clone(),
        budgets: args.budgets.clone(),
        test_data: args.test_data.clone(),
    };
    let text = studies::tradeoff_description(&data, &study, chosen.preset, &chosen.config)?;
    let path = args.out.join(DESCRIPTION);
    let (sweep, written) = studies::write_description(&path, &text, "another trade-off")?;
    if written == Written::Continued {
        println!("{} exists with these flags: continuing it", path.display());
    }
    println!(
        "{}: {} variants, scored after steps {:?} and at the end",
        path.display(),
        sweep.tasks.len(),
        (sweep.anytime.as_ref()).map_or(Vec::new(), |a| a.steps.clone())
    );
    if args.write_only {
        println!(
            "run it with `orbit-nerf sweep run {0} --out {1} --jobs 1`, or on a cluster with `orbit-nerf sweep slurm {0} --out <shared folder>`",
            path.display(),
            args.out.display()
        );
        return Ok(());
    }
    run_local(&path, &args.out, Some(args.jobs), args.threads)
}
