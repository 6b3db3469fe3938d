//! `orbit-nerf bench`: training throughput (samples/s, rays/s) on a fixed scene and seed.

use super::{
    CliResult, DataArgs, choose_box, config_for_data, open_dataset, preset_parser, with_trainer,
};
use clap::Args;
use orbit_nerf_host::train::{self, RayonExecutor};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct BenchArgs {
    /// Dataset to train on (default: the lego scene).
    #[arg(long, default_value = "../shared/data/nerf_synthetic/lego")]
    data: PathBuf,
    /// Resize images so the longer side has at most this many pixels (never upsampled).
    #[arg(long, default_value_t = 100)]
    size: u32,
    /// Steps before timing starts (lets the occupancy grid settle).
    #[arg(long, default_value_t = 300)]
    warmup: u32,
    /// Timed steps.
    #[arg(long, default_value_t = 200)]
    steps: u32,
    /// Thread counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    /// Built-in config to start from; default by the data's format: `spacecraft` for
    /// SPEED+/SHIRT/simulator folders, `default` for NeRF-synthetic and nerfstudio.
    #[arg(long, value_parser = preset_parser())]
    preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config (see budgets/).
    #[arg(long)]
    config: Option<PathBuf>,
}

pub fn run(args: &BenchArgs) -> CliResult {
    let mut base = config_for_data(args.preset.as_deref(), &args.data, args.config.as_deref())?;
    let data = DataArgs {
        data: args.data.clone(),
        size: args.size,
        holdout: 8,
        no_masks: false,
    };
    let (mut dataset, train_idx, _) = open_dataset(&data)?;
    choose_box(&mut dataset, None, args.config.as_deref(), &train_idx)?;
    base.steps = args.warmup + args.steps;
    let config = train::fit_config(&base, &dataset, train_idx.len());
    let frames: Vec<_> = train_idx.iter().map(|&i| &dataset.frames[i]).collect();
    println!(
        "model: {} scales {:?} x {} features, density MLP {}->{}->{}, colour MLP {}->{}->{}->3, SH degree {}, occupancy {}^3, {} rays/step",
        config.scales,
        &config.resolutions[..config.scales as usize],
        config.features,
        config.density_inputs(),
        config.density_hidden,
        config.density_outputs(),
        config.colour_inputs(),
        config.colour_hidden,
        config.colour_hidden,
        config.sh_bands,
        config.occupancy_res,
        config.rays_per_batch
    );
    println!(
        "{:>7}  {:>12}  {:>10}  {:>11}  {:>14}  {:>9}",
        "threads", "samples/s", "rays/s", "samples/ray", "marched/ray", "ms/step"
    );
    for &threads in &args.threads {
        let executor = RayonExecutor::new(threads)?;
        with_trainer(config, None, &frames, |trainer| {
            for _ in 0..args.warmup {
                trainer.step(&executor)?;
            }
            let (mut rays, mut samples, mut marched) = (0u64, 0u64, 0u64);
            let start = Instant::now();
            for _ in 0..args.steps {
                let r = trainer.step(&executor)?;
                rays += r.rays as u64;
                samples += r.samples as u64;
                marched += r.samples_marched as u64;
            }
            let seconds = start.elapsed().as_secs_f64();
            println!(
                "{threads:>7}  {:>12.0}  {:>10.0}  {:>11.2}  {:>14.2}  {:>9.1}",
                samples as f64 / seconds,
                rays as f64 / seconds,
                samples as f64 / rays.max(1) as f64,
                marched as f64 / rays.max(1) as f64,
                1000.0 * seconds / args.steps as f64
            );
            Ok(())
        })?;
    }
    println!("samples/s counts samples through forward + backward + update (after the early stop)");
    Ok(())
}
