//! `orbit-nerf bench`: training throughput (samples/s, rays/s) on a fixed scene and seed, and
//! with `--profile` where a step's and a rendered view's time goes, stage by stage.

use super::{CliResult, Fallible, choose_box, config_for_data, open_dataset, preset_parser};
use clap::Args;
use orbit_nerf_core::Trainer;
use orbit_nerf_host::dataset::Dataset;
use orbit_nerf_host::machine;
use orbit_nerf_host::pipeline::{self, DataSettings, SplitData};
use orbit_nerf_host::train::{self, RayonExecutor};
use std::path::{Path, PathBuf};
use std::time::Instant;

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
    let mut base = config_for_data(args.preset.as_deref(), &args.data, args.config.as_deref())?;
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
    base.steps = args.warmup + args.timed_steps;
    base.warmup_steps = base.warmup_steps.min(base.steps);
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
                start_profile(trainer, args.profile);
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
                    let timed = Timed {
                        threads,
                        steps: args.timed_steps,
                        steps_ns: (t.seconds * 1e9) as u64,
                        dataset: &dataset,
                        views: &test_idx,
                    };
                    report.push_str(&profile_report(trainer, &executor, &timed, args)?);
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

/// What the timed steps were, for the profile report (read only by the `profile` build).
#[cfg_attr(not(feature = "profile"), allow(dead_code))]
struct Timed<'d> {
    threads: usize,
    steps: u32,
    steps_ns: u64,
    dataset: &'d Dataset,
    views: &'d [usize],
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

/// Lend the trainer the host's clock (forgetting the warm-up's times) when profiling.
#[cfg(feature = "profile")]
fn start_profile(trainer: &mut Trainer<'_>, profile: bool) {
    if profile {
        trainer.set_clock(Some(orbit_nerf_host::profile::clock_ns));
        trainer.reset_profile();
    }
}

#[cfg(not(feature = "profile"))]
fn start_profile(_: &mut Trainer<'_>, _: bool) {}

/// The timed steps' stage times, then every held-out view fitted and rendered with the
/// clock running: both tables printed (and, with `--out`, a chart written), as markdown.
#[cfg(feature = "profile")]
fn profile_report(
    trainer: &mut Trainer<'_>,
    executor: &RayonExecutor,
    timed: &Timed<'_>,
    args: &BenchArgs,
) -> Fallible<String> {
    use super::FIT_STEPS;
    use orbit_nerf_host::profile::{Breakdown, write_chart};
    let profile = trainer.profile();
    let step = Breakdown {
        cpu: profile.train_cpu,
        wall: profile.train_wall,
        elapsed_ns: timed.steps_ns,
        count: timed.steps,
    };
    trainer.reset_profile();
    let mut mean = vec![0.0f32; trainer.config().embedding_dim as usize];
    trainer.mean_embedding(&mut mean);
    let start = Instant::now();
    for &index in timed.views {
        let frame = &timed.dataset.frames[index];
        let (embedding, pose) =
            train::fit_held_out(trainer, executor, frame, FIT_STEPS, false, &mean)?;
        let mut out = vec![0.0f32; frame.camera.pixel_count() * 3];
        trainer.render(executor, &frame.camera, &pose, &embedding, &mut out)?;
    }
    let profile = trainer.profile();
    let view = Breakdown {
        cpu: profile.render_cpu,
        wall: profile.render_wall,
        elapsed_ns: start.elapsed().as_nanos() as u64,
        count: timed.views.len() as u32,
    };
    trainer.set_clock(None);
    let threads = timed.threads;
    let fit = if mean.is_empty() {
        "no appearance embedding to fit".to_string()
    } else {
        format!("{FIT_STEPS} embedding-fit steps on the left half")
    };
    let text = format!(
        "### {threads} thread(s): a training step (mean of {} steps)\n\n{}\n\
         ### {threads} thread(s): a held-out view ({fit}, then the whole view; mean of {} \
         views)\n\n{}\n",
        step.count,
        step.table("step"),
        view.count,
        view.table("view"),
    );
    println!("\n{text}");
    if let Some(out) = &args.out {
        let path = out.join(format!("profile_{threads}t.png"));
        let title = format!(
            "{}: where the time goes, {threads} thread(s)",
            args.data.file_name().map_or_else(
                || args.data.display().to_string(),
                |n| n.to_string_lossy().into()
            )
        );
        write_chart(&path, &title, &step, &view)?;
        println!("wrote {}", path.display());
    }
    Ok(text)
}

#[cfg(not(feature = "profile"))]
fn profile_report(
    _: &mut Trainer<'_>,
    _: &RayonExecutor,
    _: &Timed<'_>,
    _: &BenchArgs,
) -> Fallible<String> {
    Err("--profile: this binary was built without the `profile` feature".into())
}
