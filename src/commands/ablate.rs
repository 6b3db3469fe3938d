//! `orbit-nerf ablate`: the paper's ablation (baseline, + appearance, + appearance and pose
//! correction on one scene), its pose-noise sweep on the `synthetic` preset and its
//! image-count study (run as a sweep).

use super::tradeoff::{absolute, scene_reference};
use super::{
    FIT_STEPS, Fallible, SceneBox, choose_box, machine_threads, parse_scene_box, parse_threads,
    preset_config, preset_parser,
};
use orbit_nerf_core::Config;
use orbit_nerf_host::ablation::{
    self, APPEARANCE, APPEARANCE_POSE, BASELINE, Experiment, VariantResult,
};
use orbit_nerf_host::ablation_report::{
    experiment_report, load, simulated, stated_label_noise, true_surface,
};
use orbit_nerf_host::dataset::{split_every, with_test_set};
use orbit_nerf_host::formats::Format;
use orbit_nerf_host::presets;
use orbit_nerf_host::report::{self, ModelOutcome, NoiseLevelResult};
use orbit_nerf_host::sim::scene::LabelNoise;
use orbit_nerf_host::sweep::{FrameCounts, NoiseLevels, SweepDescription};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug, Clone)]
pub struct AblateArgs {
    /// Scene to simulate: a preset (synthetic, lightbox, sunlamp, inspection; lightbox-test: a separate test set) or a scene file.
    #[arg(long, default_value = "lightbox")]
    pub scene: String,
    /// Use this dataset (SPEED+/SHIRT/simulator, NeRF-synthetic or nerfstudio) instead of simulating one.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Frames to simulate.
    #[arg(long, default_value_t = 400)]
    pub frames: u32,
    /// Image size in pixels: the simulated frames' side, or the longer side a --data set's
    /// frames are resized to (never upsampled).
    #[arg(long, default_value_t = orbit_nerf_host::pipeline::DEFAULT_SIZE as u16)]
    pub size: u16,
    /// Training steps of every model (the same budget for all; default: the config's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps: Option<u32>,
    /// Built-in config the three models start from (default: `spacecraft`, the method's).
    #[arg(long, value_parser = preset_parser())]
    pub preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config, at the top level or
    /// in a `[config]` table (a full file works too).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Run the pose-noise sweeps on the `synthetic` preset instead.
    #[arg(long)]
    pub pose_noise: bool,
    /// Which of the paper's two sweeps to run: rotation noise alone, translation noise alone,
    /// or both (sharing the noise-free level).
    #[arg(long, value_enum, default_value_t = Sweep::Both)]
    pub sweep: Sweep,
    /// Rotation-noise levels of the rotation sweep (standard deviation of the label's
    /// rotation angle, degrees); default: the paper's five.
    #[arg(long, value_delimiter = ',', default_values_t = ROTATION_LEVELS_DEG)]
    pub levels: Vec<f32>,
    /// Translation-noise levels of the translation sweep (standard deviation per axis of the
    /// label's position, mm); default: the paper's five.
    #[arg(long, value_delimiter = ',', default_values_t = TRANSLATION_LEVELS_MM)]
    pub translation_levels: Vec<f32>,
    /// The paper's image-count study: baseline and ours + pose trained on each of these
    /// numbers of --scene frames (e.g. 25,50,100,200,400) and scored on the same separate
    /// test set (--test-scene), as a sweep in --out (`image-counts.toml`, its tasks, sweep.md
    /// with the image-count table and plots). Rerunning continues the unfinished tasks.
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["data", "test_data", "pose_noise", "holdout"], value_parser = |text: &str| orbit_nerf_host::values::count_in(text, 2..=100_000))]
    pub image_counts: Vec<usize>,
    /// The separate test set of the image-count study: a scene preset or scene file,
    /// simulated with exact labels.
    #[arg(long, default_value = "lightbox-test")]
    pub test_scene: String,
    /// Frames of the image-count study's test set (default: the test scene's own; the paper
    /// has 200).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub test_frames: Option<u32>,
    /// Every N-th view is held out.
    #[arg(long, default_value_t = 8, value_parser = |text: &str| orbit_nerf_host::values::count_in(text, 1..=1_000_000))]
    pub holdout: usize,
    /// Test on this separate dataset (any format; every view held out, scored at its exact
    /// pose where it has one) and train on every view of the training set, as the paper does
    /// (train on one set, test on another set's viewpoints and lighting); --holdout is then
    /// not used.
    #[arg(long, conflicts_with_all = ["holdout", "pose_noise"])]
    pub test_data: Option<PathBuf>,
    /// Steps fitting each held-out view's embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    pub fit_steps: u32,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    pub threads: usize,
    /// Output folder: ablation.md (or pose_noise.md), metrics.json, pictures, the simulated set.
    #[arg(long, default_value = "runs/ablate")]
    pub out: PathBuf,
    /// The scene box, xmin,ymin,zmin,xmax,ymax,zmax (wins over a config file's box,
    /// truth.json's and the box found from the data).
    #[arg(long, value_parser = parse_scene_box, allow_hyphen_values = true)]
    pub scene_box: Option<SceneBox>,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    pub no_masks: bool,
}

/// The paper's rotation sweep: rotation noise on the labels, in degrees (exact positions).
const ROTATION_LEVELS_DEG: [f32; 5] = [0.0, 0.2, 0.4, 0.8, 1.6];
/// The paper's translation sweep: position noise on the labels, in mm (exact attitudes). The
/// simulated target is TANGO at its real size, as in the paper, so no scaling is needed.
const TRANSLATION_LEVELS_MM: [f32; 5] = [0.0, 2.0, 4.0, 8.0, 16.0];

/// The paper's two pose-noise sweeps.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sweep {
    Rotation,
    Translation,
    Both,
}

pub fn run(args: &AblateArgs) -> Fallible<()> {
    if args.pose_noise {
        sweep(args)
    } else if !args.image_counts.is_empty() {
        image_counts(args)
    } else {
        ablate(args)
    }
}

/// The models' base config: `--preset` (default `spacecraft`: the data is a spacecraft's), a
/// `--config` file's fields, then `--steps`.
fn base_config(args: &AblateArgs) -> Fallible<Config> {
    let data = if args.data.is_some() {
        Format::SpeedPlus.folder()
    } else {
        "a simulated scene"
    };
    let mut config = preset_config(
        args.preset.as_deref(),
        presets::SPACECRAFT,
        data,
        args.config.as_deref(),
    )?;
    if let Some(steps) = args.steps {
        config.steps = steps;
        config.warmup_steps = config.warmup_steps.min(steps);
    }
    Ok(config)
}

fn ablate(args: &AblateArgs) -> Fallible<()> {
    // The config is checked before the data is simulated or read.
    let mut base = base_config(args)?;
    if args.data.is_none() {
        stated_label_noise(&args.scene)?.state_in(&mut base);
    }
    let (dataset, truth) = match &args.data {
        Some(path) => load(path, args.size, !args.no_masks)?,
        None => simulated(
            &args.scene,
            args.frames,
            args.size,
            None,
            &args.out.join("data"),
            !args.no_masks,
        )?,
    };
    let (mut dataset, truth, train_idx, test_idx) = match &args.test_data {
        Some(test) => with_test_set((dataset, truth), load(test, args.size, !args.no_masks)?),
        None => {
            let (train_idx, test_idx) = split_every(dataset.frames.len(), args.holdout);
            (dataset, truth, train_idx, test_idx)
        }
    };
    choose_box(
        &mut dataset,
        args.scene_box,
        args.config.as_deref(),
        &train_idx,
    )?;
    let mut results: Vec<VariantResult> = Vec::new();
    for variant in [BASELINE, APPEARANCE, APPEARANCE_POSE] {
        println!(
            "training {} ({} views, {} steps)",
            variant.name,
            train_idx.len(),
            base.steps
        );
        let result = ablation::run_variant(
            &dataset,
            truth.as_deref(),
            &train_idx,
            &test_idx,
            &base,
            variant,
            args.threads,
            args.fit_steps,
            &mut |_, _| {},
        )?;
        println!(
            "  {:.1} s, held-out PSNR {:.2} dB",
            result.train_seconds, result.metrics.psnr_full
        );
        results.push(result);
    }
    let held_out = match &args.test_data {
        Some(test) => format!(
            "trained on all {} frames, tested on the {} views of the separate test set `{}`",
            train_idx.len(),
            test_idx.len(),
            test.display()
        ),
        None => format!(
            "{} frames, every {}th held out ({} views)",
            dataset.frames.len(),
            args.holdout,
            test_idx.len()
        ),
    };
    let surface = match &args.data {
        Some(_) => None,
        None => Some(true_surface(&args.scene)?),
    };
    let source = (args.data.as_ref()).map_or(args.scene.clone(), |p| p.display().to_string());
    let text = experiment_report(
        &format!("Ablation on `{source}`"),
        &format!(
            "{held_out}, {} px, {} steps per model; held-out embeddings fitted for {} steps on the left half.",
            args.size, base.steps, args.fit_steps
        ),
        &results,
        surface.as_deref(),
        (&dataset, &test_idx),
        (&args.out, "compare_view_"),
    )?;
    orbit_nerf_host::io::write_atomic(&args.out.join("ablation.md"), text.as_bytes())?;
    let models = results.iter().map(VariantResult::figures).collect();
    report::Figures::new("ablate", models).write(&args.out)?;
    println!("{text}");
    println!(
        "report, metrics.json and pictures in {}",
        args.out.display()
    );
    Ok(())
}

/// Train and score `sweep`'s tasks of one noise level (the two models, ours and ours + pose,
/// on the same simulated labels).
fn run_level(
    args: &AblateArgs,
    sweep: &orbit_nerf_host::sweep::Sweep,
    noise: LabelNoise,
    dir: &Path,
) -> Fallible<NoiseLevelResult> {
    let (dataset, truth) = simulated(
        "synthetic",
        args.frames,
        args.size,
        Some(noise),
        dir,
        !args.no_masks,
    )?;
    let (train_idx, test_idx) = split_every(dataset.frames.len(), args.holdout);
    println!(
        "noise {} deg / {} mm",
        noise.rotation_deg,
        noise.translation_m * 1000.0
    );
    let experiment = Experiment {
        dataset: &dataset,
        truth: truth.as_deref(),
        train_idx: &train_idx,
        test_idx: &test_idx,
        threads: args.threads,
        fit_steps: args.fit_steps,
        score_at: &[],
        progress: None,
    };
    let run = |variant: &str| -> Fallible<ModelOutcome> {
        let task = (sweep.tasks.iter())
            .find(|t| t.noise == Some(noise) && t.variant == variant)
            .ok_or_else(|| format!("the sweep has no task `{variant}` at this level"))?;
        let r = experiment.run(&task.config, &mut |_, _| {}, None)?;
        let after = r.pose_after.unwrap_or_default();
        println!(
            "  {}: SSIM {:.4}, rotation error {:.3} deg, position error {:.1} mm",
            variant,
            r.metrics.ssim_full,
            after.rotation_deg_mean,
            after.translation_mean * 1000.0
        );
        Ok(ModelOutcome {
            metrics: r.metrics,
            metrics_exact: r.metrics_exact,
            metrics_aligned: Some(r.metrics_aligned),
            pose_before: r.pose_before,
            pose_after: r.pose_after,
        })
    };
    let ours = run(APPEARANCE.name)?;
    let pose = run(APPEARANCE_POSE.name)?;
    Ok(NoiseLevelResult { noise, ours, pose })
}

/// Both sweeps of the paper: rotation noise alone, then translation noise alone (the noise-free
/// level is trained once and shared), as a sweep description's levels and models. Per level:
/// SSIM and JNB of ours with and without pose correction, and the pose error of the labels
/// before and after correction.
fn sweep(args: &AblateArgs) -> Fallible<()> {
    let description = SweepDescription {
        scene: Some("synthetic".into()),
        frames: Some(FrameCounts::One(args.frames)),
        size: Some(args.size.into()),
        preset: args.preset.clone(),
        config: (args.config.as_ref()).map(|p| p.display().to_string()),
        steps: args.steps,
        holdout: Some(args.holdout),
        fit_steps: Some(args.fit_steps),
        masks: Some(!args.no_masks),
        noise: Some(NoiseLevels {
            rotation_deg: match args.sweep {
                Sweep::Translation => Vec::new(),
                _ => args.levels.clone(),
            },
            translation_mm: match args.sweep {
                Sweep::Rotation => Vec::new(),
                _ => args.translation_levels.clone(),
            },
        }),
        ..SweepDescription::default()
    };
    let sweep = description.check(Path::new("ablate --pose-noise"), Path::new(""))?;
    let mut levels = Vec::new();
    for noise in sweep.levels().into_iter().flatten() {
        let dir = args.out.join(format!(
            "noise_r{}deg_t{}mm",
            noise.rotation_deg,
            noise.translation_m * 1000.0
        ));
        levels.push(run_level(args, &sweep, noise, &dir)?);
    }
    let mut text = format!(
        "# Pose-noise sweeps on `synthetic`\n\n{} frames of {} px, every {}th held out, {} steps per model, held-out embeddings fitted for {} steps; JNB: paper variant, lower is sharper. Pose errors are the means over the training frames, against the simulator's exact poses.\n",
        args.frames, args.size, args.holdout, sweep.base.steps, args.fit_steps
    );
    text.push_str(&report::pose_noise_sections(
        &args.out,
        &sweep.rotation,
        &sweep.translation,
        &levels,
    )?);
    orbit_nerf_host::io::write_atomic(&args.out.join("pose_noise.md"), text.as_bytes())?;
    println!("{text}");
    Ok(())
}

/// The image-count study as a sweep description in `--out` (`image-counts.toml`), run here
/// by the sweep runner: one task per count and model, every task scored on the same test set.
fn image_counts(args: &AblateArgs) -> Fallible<()> {
    let mut table = toml::Table::new();
    table.insert("scene".into(), scene_reference(&args.scene)?.into());
    let counts: Vec<i64> = args.image_counts.iter().map(|&n| n as i64).collect();
    table.insert("frames".into(), counts.into());
    table.insert(
        "test_scene".into(),
        scene_reference(&args.test_scene)?.into(),
    );
    if let Some(frames) = args.test_frames {
        table.insert("test_frames".into(), (frames as i64).into());
    }
    table.insert("size".into(), (args.size as i64).into());
    table.insert("fit_steps".into(), (args.fit_steps as i64).into());
    table.insert("masks".into(), (!args.no_masks).into());
    if let Some(preset) = &args.preset {
        table.insert("preset".into(), preset.clone().into());
    }
    if let Some(config) = &args.config {
        table.insert("config".into(), absolute(config)?.into());
    }
    if let Some(steps) = args.steps {
        table.insert("steps".into(), (steps as i64).into());
    }
    if let Some(([x0, y0, z0], [x1, y1, z1])) = args.scene_box {
        table.insert(
            "scene_box".into(),
            format!("{x0},{y0},{z0},{x1},{y1},{z1}").into(),
        );
    }
    let variants: Vec<toml::Value> = [BASELINE, APPEARANCE_POSE]
        .iter()
        .map(|model| {
            let set = toml::Table::from_iter([
                (
                    "embedding_dim".to_string(),
                    i64::from(model.embedding_dim).into(),
                ),
                ("pose_correction".to_string(), model.pose_correction.into()),
            ]);
            toml::Table::from_iter([
                ("name".to_string(), model.name.into()),
                ("set".to_string(), set.into()),
            ])
            .into()
        })
        .collect();
    table.insert("variants".into(), variants.into());
    let description = format!(
        "# Written by `orbit-nerf ablate --image-counts`: baseline and ours + pose per training-image count.\n{}",
        toml::to_string(&table).map_err(|e| format!("writing the description: {e}"))?
    );
    let path = args.out.join("image-counts.toml");
    // The description is checked before it is written: a bad value names its field.
    orbit_nerf_host::sweep::Sweep::parse(&path, &description)?;
    orbit_nerf_host::io::check_output_folder(&args.out)?;
    match std::fs::read_to_string(&path) {
        Ok(earlier) if earlier != description => {
            return Err(format!(
                "{}: holds the description of another image-count study; give another --out",
                path.display()
            )
            .into());
        }
        Ok(_) => {}
        Err(_) => orbit_nerf_host::io::write_atomic(&path, description.as_bytes())?,
    }
    super::sweep::run_local(&path, &args.out, Some(1), Some(args.threads))
}
