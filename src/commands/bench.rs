//! `orbit-nerf bench`: training throughput (samples/s, rays/s) on a fixed scene and seed, and
//! with `--profile` where a step's and a rendered view's time goes, stage by stage.

use super::{CliResult, Fallible, choose_box, open_dataset, preset_parser};
use clap::Args;
use orbit_nerf_core::Trainer;
use orbit_nerf_host::pipeline::{self, DataSettings, SplitData};
use orbit_nerf_host::train::{self, RayonExecutor};
use orbit_nerf_host::{machine, presets};
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct BenchArgs {
    /// Dataset to train on (default: the lego scene, relative to the working directory).
    #[arg(long, default_value = "../shared/data/nerf_synthetic/lego")]
    data: PathBuf,
    /// Resize images so the longer side has at most this many pixels (never upsampled); the
    /// benchmark's own default, 100, keeps its figures comparable from one build to the next.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=65_535))]
    size: u32,
    /// Training steps before timing starts (lets the occupancy grid settle).
    #[arg(long, default_value_t = 300, value_parser = clap::value_parser!(u32).range(0..=1_000_000))]
    warmup: u32,
    /// Training steps timed, after the warm-up ones (the run trains warm-up + timed steps).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    timed_steps: u32,
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
    /// Also time each stage of the timed steps and of rendering every held-out view
    /// (embedding fit on the left half, then the whole view), and print the tables. The
    /// throughput rows are then measured with the timers running.
    #[arg(long)]
    profile: bool,
    /// With --profile: write the tables (profile.md) and a stacked bar chart per thread
    /// count (profile_<threads>t.png) into this folder.
    #[arg(long, requires = "profile")]
    out: Option<PathBuf>,
    /// Keep the MLP kernels, plane lookups and transposes to eight lanes (AVX2) on a CPU with
    /// AVX-512, to compare the two on one machine (the results are the same bits either way).
    #[arg(long)]
    no_avx512: bool,
}

pub fn run(args: &BenchArgs) -> CliResult {
    if !args.data.is_dir() {
        return Err(format!(
            "--data {}: no such dataset folder (the default is relative to the working \
             directory: run bench from a checkout beside shared/, or pass --data DIR)",
            args.data.display()
        )
        .into());
    }
    check_profile_build(args)?;
    if let Some(out) = &args.out {
        std::fs::create_dir_all(out).map_err(|e| format!("--out {}: {e}", out.display()))?;
    }
    println!("{}", machine::cpu_summary());
    orbit_nerf_core::allow_wide_vectors(!args.no_avx512);
    println!(
        "MLP kernels and plane lookups: {}",
        if orbit_nerf_core::wide_vectors() {
            "16 lanes per instruction (AVX-512)"
        } else {
            "8 lanes per instruction or fewer"
        }
    );
    let chosen =
        pipeline::choose_config(args.preset.as_deref(), &args.data, args.config.as_deref())?;
    println!("{}", chosen.note);
    let mut base = chosen.config;
    let settings = DataSettings {
        size: args.size,
        ..DataSettings::new(&args.data)
    };
    let SplitData {
        mut dataset,
        train: train_idx,
        test: test_idx,
        ..
    } = open_dataset(&settings, None, &[])?;
    choose_box(&mut dataset, None, args.config.as_deref(), &train_idx)?;
    let steps = Some(args.warmup + args.timed_steps);
    pipeline::Overrides {
        steps,
        ..Default::default()
    }
    .apply(&mut base);
    let config = train::fit_config(&base, &dataset, train_idx.len());
    let frames: Vec<_> = train_idx.iter().map(|&i| &dataset.frames[i]).collect();
    println!("model: {}", presets::describe(&config));
    println!(
        "{:>7}  {:>12}  {:>10}  {:>11}  {:>14}  {:>9}",
        "threads", "samples/s", "rays/s", "samples/ray", "marched/ray", "ms/step"
    );
    let mut report = String::new();
    for &threads in &args.threads {
        let executor = RayonExecutor::new(threads)?;
        pipeline::with_trainer(
            Path::new("the model"),
            (config, None),
            &[],
            &frames,
            |trainer| -> Fallible<()> {
                let warm = trainer.state().step + args.warmup;
                pipeline::train_steps(trainer, &executor, warm, &mut ())?;
                if args.profile {
                    profile(
                        trainer,
                        &executor,
                        (threads, None),
                        (&dataset, &test_idx),
                        args,
                    )?;
                }
                let end = warm + args.timed_steps;
                let t = pipeline::train_steps(trainer, &executor, end, &mut ())?;
                println!(
                    "{threads:>7}  {:>12.0}  {:>10.0}  {:>11.2}  {:>14.2}  {:>9.1}",
                    t.samples as f64 / t.seconds,
                    t.rays as f64 / t.seconds,
                    t.samples_per_ray(),
                    t.marched as f64 / t.rays.max(1) as f64,
                    1000.0 * t.seconds / args.timed_steps as f64
                );
                if args.profile {
                    let timed = (threads, Some((t.seconds * 1e9) as u64));
                    let views = (&dataset, test_idx.as_slice());
                    report.push_str(&profile(trainer, &executor, timed, views, args)?);
                }
                Ok(())
            },
        )?;
    }
    println!("samples/s counts samples through forward + backward + update (after the early stop)");
    if let (Some(out), false) = (&args.out, report.is_empty()) {
        let path = out.join("profile.md");
        orbit_nerf_host::io::write_atomic(&path, report.as_bytes())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

#[cfg(feature = "profile")]
fn check_profile_build(_: &BenchArgs) -> CliResult {
    Ok(())
}

#[cfg(not(feature = "profile"))]
fn check_profile_build(args: &BenchArgs) -> CliResult {
    if args.profile {
        return Err("--profile: this binary was built without the `profile` feature".into());
    }
    Ok(())
}

/// The profile of the timed steps and of rendering `views` (`bench --profile`), printed; its
/// chart written into `--out`. Lends the trainer the clock first when `start`.
#[cfg(feature = "profile")]
fn profile(
    trainer: &mut Trainer<'_>,
    executor: &RayonExecutor,
    (threads, steps_ns): (usize, Option<u64>),
    (dataset, views): (&orbit_nerf_host::dataset::Dataset, &[usize]),
    args: &BenchArgs,
) -> Fallible<String> {
    use orbit_nerf_host::profile::{self, Timed};
    let Some(steps_ns) = steps_ns else {
        profile::start(trainer);
        return Ok(String::new());
    };
    let timed = Timed {
        threads,
        steps: args.timed_steps,
        steps_ns,
        dataset,
        views,
    };
    let name = (args.data.file_name()).map_or_else(
        || args.data.display().to_string(),
        |n| n.to_string_lossy().into(),
    );
    let chart = (args.out.as_ref()).map(|out| out.join(format!("profile_{threads}t.png")));
    let chart_of = chart.as_deref().map(|path| (path, name.as_str()));
    let text = profile::report(trainer, executor, &timed, super::FIT_STEPS, chart_of)?;
    println!("\n{text}");
    if let Some(path) = chart {
        println!("wrote {}", path.display());
    }
    Ok(text)
}

#[cfg(not(feature = "profile"))]
fn profile(
    _: &mut Trainer<'_>,
    _: &RayonExecutor,
    _: (usize, Option<u64>),
    _: (&orbit_nerf_host::dataset::Dataset, &[usize]),
    _: &BenchArgs,
) -> Fallible<String> {
    Ok(String::new())
}
