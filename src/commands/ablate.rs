//! `orbit-nerf ablate`: the paper's ablation (baseline, + appearance, + appearance and pose
//! correction on one scene) and its pose-noise sweep on the `synthetic` preset.

use super::{FIT_STEPS, Fallible, SceneBox, choose_box, parse_scene_box};
use orbit_nerf_core::{Config, Pose};
use orbit_nerf_host::ablation::{self, APPEARANCE, APPEARANCE_POSE, BASELINE, VariantResult};
use orbit_nerf_host::dataset::{Dataset, split_every};
use orbit_nerf_host::formats::speedplus::{self, LoadOptions};
use orbit_nerf_host::geometry::{self, Triangle};
use orbit_nerf_host::report::{self, ModelRow, format_or_na};
use orbit_nerf_host::sim::{self, Scene, scene::LabelNoise};
use orbit_nerf_host::train::to_rgb8;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug, Clone)]
pub struct AblateArgs {
    /// Scene to simulate: a preset (synthetic, lightbox, sunlamp) or a scene file.
    #[arg(long, default_value = "lightbox")]
    pub scene: String,
    /// Use this SPEED+-format dataset instead of simulating one.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Frames to simulate.
    #[arg(long, default_value_t = 400)]
    pub frames: u32,
    /// Image size in pixels.
    #[arg(long, default_value_t = 128)]
    pub size: u16,
    /// Training steps of every model (the same budget for all; the default config's).
    #[arg(long, default_value_t = Config::DEFAULT.steps)]
    pub steps: u32,
    /// Model and training config (TOML; default: the built-in default config).
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
    /// Every N-th view is held out.
    #[arg(long, default_value_t = 8)]
    pub holdout: usize,
    /// Steps fitting each held-out view's embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    pub fit_steps: u32,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
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

/// Simulate `scene` (with optional label noise) into `out` and load it with its exact poses.
pub fn simulated(
    scene: &str,
    frames: u32,
    size: u16,
    noise: Option<LabelNoise>,
    out: &Path,
    masks: bool,
) -> Fallible<(Dataset, Option<Vec<Pose>>)> {
    let mut scene = Scene::load(scene)?;
    scene.spec.frames = frames;
    scene.spec.size = size;
    if let Some(noise) = noise {
        scene.spec.effects.label_noise =
            (noise.rotation_deg > 0.0 || noise.translation_m > 0.0).then_some(noise);
    }
    sim::simulate(&scene, out, &|| {})?;
    load(out, size, masks)
}

/// The true surface of a simulated scene: the target's triangles in metres, in its body
/// frame, which is the world frame of the dataset the simulator writes.
pub fn true_surface(scene: &str) -> Fallible<Vec<Triangle>> {
    Ok(sim::Target::build(&Scene::load(scene)?)?.surface())
}

/// The report's geometry section: each model's surface against the true one.
pub fn geometry_section(results: &[&VariantResult], truth: &[Triangle]) -> String {
    let rows: Vec<_> = results
        .iter()
        .map(|r| ablation::geometry_row(r, truth))
        .collect();
    format!(
        "\n## Geometry: Chamfer distance to the true shape\n\nEach field's surface at the default \
         density threshold on a {}-sample grid (as `orbit-nerf export mesh` writes it) against the \
         simulated target's mesh: {} points drawn uniformly by area on each, each point's \
         distance to the nearest point drawn on the other, both directions pooled.\n\n{}",
        geometry::extract::DEFAULT_RESOLUTION,
        geometry::chamfer::DEFAULT_SAMPLES,
        report::geometry_table(&rows)
    )
}

/// Load a SPEED+ folder with its exact poses (when it has `truth.json`), its masks applied
/// when `masks`.
fn load(path: &Path, size: u16, masks: bool) -> Fallible<(Dataset, Option<Vec<Pose>>)> {
    let set = speedplus::load(
        path,
        &LoadOptions {
            width: Some(size as u32),
            domain: None,
        },
    )?;
    let truth = set.true_poses()?;
    let mut dataset = set.dataset;
    if masks {
        dataset.apply_masks();
    }
    Ok((dataset, truth))
}

pub fn run(args: &AblateArgs) -> Fallible<()> {
    if args.pose_noise {
        sweep(args)
    } else {
        ablate(args)
    }
}

fn base_config(args: &AblateArgs) -> Fallible<Config> {
    let mut config = match &args.config {
        Some(path) => orbit_nerf_host::train::read_config(path)?,
        None => Config::SPACECRAFT,
    };
    config.steps = args.steps;
    config.warmup_steps = config.warmup_steps.min(args.steps);
    Ok(config)
}

fn ablate(args: &AblateArgs) -> Fallible<()> {
    let (mut dataset, truth) = match &args.data {
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
    let (train_idx, test_idx) = split_every(dataset.frames.len(), args.holdout);
    let base = base_config(args)?;
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
            &mut |_| {},
        )?;
        println!(
            "  {:.1} s, held-out PSNR {:.2} dB",
            result.train_seconds, result.metrics.psnr_full
        );
        results.push(result);
    }
    let rows: Vec<ModelRow> = results
        .iter()
        .map(|r| ModelRow {
            name: r.variant.name.to_string(),
            metrics: r.metrics,
            train_seconds: r.train_seconds,
        })
        .collect();
    let mut text = String::new();
    writeln!(
        text,
        "# Ablation on `{}`\n",
        args.data
            .as_ref()
            .map_or(args.scene.clone(), |p| p.display().to_string())
    )?;
    writeln!(
        text,
        "{} frames of {} px, every {}th held out ({} views), {} steps per model; held-out embeddings fitted for {} steps on the left half.\n",
        dataset.frames.len(),
        args.size,
        args.holdout,
        test_idx.len(),
        base.steps,
        args.fit_steps
    )?;
    writeln!(text, "{}", report::ablation_table(&rows))?;
    let pose_rows: Vec<_> = results
        .iter()
        .filter_map(|r| Some((r.variant.name.to_string(), r.pose_before?, r.pose_after?)))
        .collect();
    if !pose_rows.is_empty() {
        writeln!(
            text,
            "\n## Pose error of the training labels against the exact poses\n"
        )?;
        writeln!(text, "{}", report::pose_error_table(&pose_rows))?;
    }
    if args.data.is_none() {
        let truth = true_surface(&args.scene)?;
        let all: Vec<&VariantResult> = results.iter().collect();
        text.push_str(&geometry_section(&all, &truth));
    }
    writeln!(text, "\n## Renders (truth, baseline, ours, ours + pose)\n")?;
    for (k, &index) in test_idx.iter().enumerate().take(4) {
        let frame = &dataset.frames[index];
        let (w, h) = (frame.camera.width as u32, frame.camera.height as u32);
        let renders: Vec<Vec<u8>> = results.iter().map(|r| to_rgb8(&r.renders[k])).collect();
        let mut tiles: Vec<(&str, &[u8])> = vec![("truth", &frame.pixels)];
        for (r, px) in results.iter().zip(&renders) {
            tiles.push((r.variant.name, px));
        }
        let (sw, sh, strip) = report::side_by_side(&tiles, w, h);
        let name = format!("compare_view_{index:03}.png");
        orbit_nerf_host::io::write_png(&args.out.join(&name), sw, sh, 3, &strip)?;
        writeln!(text, "![view {index}]({name})")?;
    }
    orbit_nerf_host::io::write_atomic(&args.out.join("ablation.md"), text.as_bytes())?;
    println!("{text}");
    println!("report and pictures in {}", args.out.display());
    Ok(())
}

/// One noise level of a sweep: the two models (ours, ours + pose) trained on the same
/// simulated labels.
struct Level {
    noise: LabelNoise,
    ours: VariantResult,
    pose: VariantResult,
}

fn run_level(args: &AblateArgs, base: &Config, noise: LabelNoise, dir: &Path) -> Fallible<Level> {
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
    let run = |variant| -> Fallible<VariantResult> {
        let r = ablation::run_variant(
            &dataset,
            truth.as_deref(),
            &train_idx,
            &test_idx,
            base,
            variant,
            args.threads,
            args.fit_steps,
            &mut |_| {},
        )?;
        let after = r.pose_after.unwrap_or_default();
        println!(
            "  {}: SSIM {:.4}, rotation error {:.3} deg, position error {:.1} mm",
            variant.name,
            r.metrics.ssim_full,
            after.rotation_deg_mean,
            after.translation_mean * 1000.0
        );
        Ok(r)
    };
    let ours = run(APPEARANCE)?;
    let pose = run(APPEARANCE_POSE)?;
    Ok(Level { noise, ours, pose })
}

/// One of the two sweeps: its levels, its section of the report and its plots.
struct SweepSpec {
    on: bool,
    noises: Vec<LabelNoise>,
    title: &'static str,
    column: &'static str,
    /// File name stem of its plots.
    name: &'static str,
    axis: &'static str,
    level: fn(&LabelNoise) -> f32,
    error_label: &'static str,
    error: fn(&report::PoseErrors) -> f64,
}

fn check_levels(flag: &str, levels: &[f32]) -> Fallible<()> {
    match levels.iter().find(|l| !(l.is_finite() && **l >= 0.0)) {
        Some(bad) => Err(format!("{flag}: {bad} is not a noise level").into()),
        None => Ok(()),
    }
}

/// Both sweeps of the paper: rotation noise alone, then translation noise alone (the noise-free
/// level is trained once and shared). Per level: SSIM and JNB of ours with and without pose
/// correction, and the pose error of the labels before and after correction.
fn sweep(args: &AblateArgs) -> Fallible<()> {
    check_levels("--levels", &args.levels)?;
    check_levels("--translation-levels", &args.translation_levels)?;
    let base = base_config(args)?;
    let rotation_noise = |deg: f32| LabelNoise {
        rotation_deg: deg,
        translation_m: 0.0,
    };
    let translation_noise = |mm: f32| LabelNoise {
        rotation_deg: 0.0,
        translation_m: mm / 1000.0,
    };
    let sweeps = [
        SweepSpec {
            on: args.sweep != Sweep::Translation,
            noises: args.levels.iter().map(|&d| rotation_noise(d)).collect(),
            title: "Rotation noise (exact positions)",
            column: "E_R deg",
            name: "rotation",
            axis: "rotation noise (deg)",
            level: |n| n.rotation_deg,
            error_label: "rotation error (deg)",
            error: |e| e.rotation_deg_mean,
        },
        SweepSpec {
            on: args.sweep != Sweep::Rotation,
            noises: (args.translation_levels.iter())
                .map(|&mm| translation_noise(mm))
                .collect(),
            title: "Translation noise (exact attitudes)",
            column: "E_T mm",
            name: "translation",
            axis: "translation noise (mm)",
            level: |n| n.translation_m * 1000.0,
            error_label: "camera position error (mm)",
            error: |e| e.translation_mean * 1000.0,
        },
    ];
    let mut levels: Vec<Level> = Vec::new();
    for &noise in sweeps.iter().filter(|s| s.on).flat_map(|s| &s.noises) {
        if levels.iter().any(|l| l.noise == noise) {
            continue;
        }
        let dir = args.out.join(format!(
            "noise_r{}deg_t{}mm",
            noise.rotation_deg,
            noise.translation_m * 1000.0
        ));
        levels.push(run_level(args, &base, noise, &dir)?);
    }
    let find = |noise: LabelNoise| levels.iter().find(|l| l.noise == noise);
    let mut text = format!(
        "# Pose-noise sweeps on `synthetic`\n\n{} frames of {} px, every {}th held out, {} steps per model, held-out embeddings fitted for {} steps; JNB: paper variant, lower is sharper. Pose errors are the means over the training frames, against the simulator's exact poses.\n",
        args.frames, args.size, args.holdout, base.steps, args.fit_steps
    );
    for sweep in sweeps.iter().filter(|s| s.on) {
        let rows: Vec<&Level> = sweep.noises.iter().filter_map(|&n| find(n)).collect();
        let name = sweep.name;
        writeln!(text, "\n## {}\n", sweep.title)?;
        text.push_str(&sweep_table(sweep.column, &rows, sweep.level));
        writeln!(
            text,
            "\n![SSIM]({name}_ssim.png)\n![{}]({name}_error.png)",
            sweep.error_label
        )?;
        plot_sweep(&args.out, sweep, &rows)?;
    }
    orbit_nerf_host::io::write_atomic(&args.out.join("pose_noise.md"), text.as_bytes())?;
    println!("{text}");
    Ok(())
}

/// One sweep's table: a row per level, the level in the first column.
fn sweep_table(level_header: &str, rows: &[&Level], level: fn(&LabelNoise) -> f32) -> String {
    let header = [
        level_header,
        "SSIM ours",
        "SSIM ours+pose",
        "JNB ours",
        "JNB ours+pose",
        "rot. error labels / corrected deg",
        "about view axis labels / corrected deg",
        "across view axis labels / corrected deg",
        "position error labels / corrected mm",
    ];
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|l| {
            let (ours, pose) = (&l.ours, &l.pose);
            let before = pose.pose_before.unwrap_or_default();
            let after = pose.pose_after.unwrap_or_default();
            vec![
                format!("{}", level(&l.noise)),
                format_or_na(ours.metrics.ssim_full, 4),
                format_or_na(pose.metrics.ssim_full, 4),
                format_or_na(ours.metrics.jnb_full, 4),
                format_or_na(pose.metrics.jnb_full, 4),
                format!(
                    "{:.3} / {:.3}",
                    before.rotation_deg_mean, after.rotation_deg_mean
                ),
                format!(
                    "{:.3} / {:.3}",
                    before.about_view_axis_deg_mean, after.about_view_axis_deg_mean
                ),
                format!(
                    "{:.3} / {:.3}",
                    before.across_view_axis_deg_mean, after.across_view_axis_deg_mean
                ),
                format!(
                    "{:.1} / {:.1}",
                    before.translation_mean * 1000.0,
                    after.translation_mean * 1000.0
                ),
            ]
        })
        .collect();
    report::markdown_table(&header, &rows)
}

/// `NAME_ssim.png` (held-out SSIM with and without pose correction) and `NAME_error.png` (the
/// labels' pose error before and after correction) against the noise level.
fn plot_sweep(out: &Path, sweep: &SweepSpec, rows: &[&Level]) -> Fallible<()> {
    let points = |f: &dyn Fn(&Level) -> f64| -> Vec<(f64, f64)> {
        rows.iter()
            .map(|l| ((sweep.level)(&l.noise) as f64, f(l)))
            .collect()
    };
    let error = |errors: Option<report::PoseErrors>| (sweep.error)(&errors.unwrap_or_default());
    report::line_plot(
        &out.join(format!("{}_ssim.png", sweep.name)),
        &format!("held-out SSIM vs {}", sweep.axis),
        sweep.axis,
        "SSIM",
        &[
            ("ours", points(&|l| l.ours.metrics.ssim_full)),
            ("ours + pose", points(&|l| l.pose.metrics.ssim_full)),
        ],
    )?;
    report::line_plot(
        &out.join(format!("{}_error.png", sweep.name)),
        &format!("{} of the training poses", sweep.error_label),
        sweep.axis,
        sweep.error_label,
        &[
            ("labels", points(&|l| error(l.pose.pose_before))),
            ("corrected", points(&|l| error(l.pose.pose_after))),
        ],
    )?;
    Ok(())
}
