//! `orbit-nerf tradeoff`: what accuracy costs in time. Writes a sweep description with an
//! `[anytime]` table (the reference config, then one variant per knob value) to
//! `<out>/tradeoff.toml` and runs it as `sweep run` does: every variant trained and scored at
//! fixed steps, its training seconds measured, then the report (`sweep.md`, `tradeoff.csv`,
//! Pareto plots, anytime curves). One task at a time by default, so the times compare;
//! `orbit-nerf sweep slurm <out>/tradeoff.toml` takes the same description to a cluster.

use super::sweep::run_local;
use super::{FIT_STEPS, Fallible, config_for_data, preset_config, preset_parser};
use orbit_nerf_host::io::{check_output_folder, write_atomic};
use orbit_nerf_host::presets;
use orbit_nerf_host::sweep::tradeoff::{Knob, default_knobs, parse_vary};
use orbit_nerf_host::sweep::{Sweep, above_data_side, data_image_side};
use orbit_nerf_host::train::with_overrides;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct TradeoffArgs {
    /// Scene to simulate: a preset (synthetic, lightbox, sunlamp, inspection; lightbox-test: a separate test set) or a scene file.
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
    check_output_folder(&args.out)?;
    let text = description(args)?;
    let path = args.out.join(DESCRIPTION);
    // Checked before anything is written: a bad knob value leaves no description behind.
    let sweep = Sweep::parse(&path, &text)?;
    // A folder holding another trade-off is never overwritten: its tasks would not match.
    match std::fs::read_to_string(&path) {
        Ok(existing) if existing != text => {
            return Err(format!(
                "{}: holds another trade-off (other flags); choose another --out, or remove the folder",
                path.display()
            )
            .into());
        }
        Ok(_) => println!("{} exists with these flags: continuing it", path.display()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            std::fs::create_dir_all(&args.out)
                .map_err(|e| format!("{}: {e}", args.out.display()))?;
            write_atomic(&path, text.as_bytes())?;
        }
        Err(e) => return Err(format!("{}: {e}", path.display()).into()),
    }
    println!(
        "{}: {} variants, scored after steps {:?} and at the end",
        path.display(),
        sweep.tasks.len(),
        sweep
            .anytime
            .as_ref()
            .map(|a| a.steps.clone())
            .unwrap_or_default()
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

/// The sweep description the flags give: paths absolute, so it runs from any folder.
fn description(args: &TradeoffArgs) -> Fallible<String> {
    let mut table = toml::Table::new();
    let base = match &args.data {
        Some(data) => {
            table.insert("data".into(), absolute(data)?.into());
            config_for_data(args.preset.as_deref(), data, args.config.as_deref())?
        }
        None => {
            table.insert("scene".into(), scene_reference(&args.scene)?.into());
            preset_config(
                args.preset.as_deref(),
                presets::SPACECRAFT,
                "a simulated scene",
                args.config.as_deref(),
            )?
        }
    };
    let preset = args.preset.clone().unwrap_or_else(|| match &args.data {
        Some(data) => presets::for_format(orbit_nerf_host::formats::Format::of(data)).into(),
        None => presets::SPACECRAFT.into(),
    });
    table.insert("preset".into(), preset.into());
    if let Some(config) = &args.config {
        table.insert("config".into(), absolute(config)?.into());
    }
    if let Some(frames) = args.frames {
        table.insert("frames".into(), (frames as i64).into());
    }
    table.insert("size".into(), (args.size as i64).into());
    let mut base = base;
    if let Some(steps) = args.steps {
        base.steps = steps;
        base.warmup_steps = base.warmup_steps.min(steps);
    }
    table.insert("steps".into(), (base.steps as i64).into());
    match &args.test_data {
        Some(test) => table.insert("test_data".into(), absolute(test)?.into()),
        None => table.insert("holdout".into(), (args.holdout as i64).into()),
    };
    table.insert("fit_steps".into(), (args.fit_steps as i64).into());
    table.insert("masks".into(), (!args.no_masks).into());

    let at: Vec<u32> = if args.at.is_empty() {
        let mut at: Vec<u32> = [16, 8, 4]
            .map(|d| base.steps / d)
            .into_iter()
            .chain([base.steps / 2, base.steps * 3 / 4])
            .filter(|&s| s > 0 && s < base.steps)
            .collect();
        at.dedup();
        at
    } else {
        args.at.clone()
    };
    let mut anytime = toml::Table::new();
    anytime.insert(
        "steps".into(),
        at.iter().map(|&s| s as i64).collect::<Vec<_>>().into(),
    );
    if let Some(quality) = &args.quality {
        anytime.insert("quality".into(), quality.clone().into());
    }
    anytime.insert("targets".into(), args.targets.clone().into());
    anytime.insert("budgets_s".into(), args.budgets.clone().into());
    table.insert("anytime".into(), anytime.into());

    // Frames are never upsampled: a size above the data's images repeats a smaller one.
    // (The image headers are read once, when a knob sets a size.)
    let side = std::cell::OnceCell::new();
    let above_data = |size: u32| -> Option<String> {
        let data = args.data.as_deref()?;
        above_data_side(size, *side.get_or_init(|| data_image_side(data)), data)
    };
    let knobs = if args.vary.is_empty() {
        let mut knobs = default_knobs(&base, args.size);
        knobs.retain(|k| k.size.is_none_or(|s| above_data(s).is_none()));
        knobs
    } else {
        let mut knobs = Vec::new();
        for flag in &args.vary {
            let (key, values) = parse_vary(flag).map_err(|e| format!("--vary: {e}"))?;
            for value in values {
                let knob = Knob::new(&key, value);
                // Checked here, so the error names the flag.
                let origin = PathBuf::from(format!("--vary {flag}"));
                if knob.size.is_none() {
                    with_overrides(&origin, "", &base, &knob.set)?;
                }
                if let Some(why) = knob.size.and_then(above_data) {
                    return Err(format!("--vary {flag}: {why}").into());
                }
                knobs.push(knob);
            }
        }
        knobs
    };
    let mut variants = vec![variant("reference", &toml::Table::new(), None)];
    for knob in &knobs {
        if variants
            .iter()
            .any(|v| v.get("name") == Some(&knob.name.clone().into()))
        {
            return Err(format!("--vary: `{}` is given twice", knob.name).into());
        }
        variants.push(variant(&knob.name, &knob.set, knob.size));
    }
    table.insert(
        "variants".into(),
        toml::Value::Array(variants.into_iter().map(Into::into).collect()),
    );
    let text = toml::to_string(&table).map_err(|e| format!("writing the description: {e}"))?;
    Ok(format!(
        "# Written by `orbit-nerf tradeoff`: the reference, then one variant per knob value.\n{text}"
    ))
}

fn variant(name: &str, set: &toml::Table, size: Option<u32>) -> toml::Table {
    let mut table = toml::Table::new();
    table.insert("name".into(), name.into());
    if !set.is_empty() {
        table.insert("set".into(), set.clone().into());
    }
    if let Some(size) = size {
        table.insert("size".into(), (size as i64).into());
    }
    table
}

/// `path` made absolute (links resolved), for a description run from any folder.
pub(super) fn absolute(path: &Path) -> Fallible<String> {
    Ok(std::fs::canonicalize(path)
        .map_err(|e| format!("{}: {e}", path.display()))?
        .display()
        .to_string())
}

/// A scene preset's name as it is, a scene file's path made absolute.
pub(super) fn scene_reference(scene: &str) -> Fallible<String> {
    if orbit_nerf_host::sim::scene::preset_names().any(|p| p == scene) {
        return Ok(scene.to_string());
    }
    Ok(std::fs::canonicalize(scene)
        .map_err(|e| {
            format!(
                "--scene {scene}: no such preset ({}) and no such file: {e}",
                orbit_nerf_host::sim::scene::preset_names()
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?
        .display()
        .to_string())
}
