//! `orbit-nerf ablate`: the paper's ablation (baseline, + appearance, + appearance and pose
//! correction on one scene) and its pose-noise sweep on the `synthetic` preset.

use orbit_nerf_core::{Config, Pose};
use orbit_nerf_host::ablation::{self, APPEARANCE, APPEARANCE_POSE, BASELINE, VariantResult};
use orbit_nerf_host::dataset::{Dataset, split_every};
use orbit_nerf_host::report::{self, ModelRow};
use orbit_nerf_host::sim::{self, Scene, scene::LabelNoise};
use orbit_nerf_host::speedplus::{self, LoadOptions};
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
    /// Run the pose-noise sweep on the `synthetic` preset instead.
    #[arg(long)]
    pub pose_noise: bool,
    /// Rotation-noise levels of the sweep, in degrees (each with 10 mm of translation noise
    /// per degree, as in the paper); default: the paper's five.
    #[arg(long, value_delimiter = ',', default_values_t = NOISE_LEVELS_DEG)]
    pub levels: Vec<f32>,
    /// Every N-th view is held out.
    #[arg(long, default_value_t = 8)]
    pub holdout: usize,
    /// Steps fitting each held-out view's embedding on its left half.
    #[arg(long, default_value_t = 50)]
    pub fit_steps: u32,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    #[arg(long, default_value = "runs/ablate")]
    pub out: PathBuf,
}

type Fallible<T> = Result<T, Box<dyn std::error::Error>>;

/// The paper's sweep: rotation noise on the labels, in degrees.
const NOISE_LEVELS_DEG: [f32; 5] = [0.0, 0.2, 0.4, 0.8, 1.6];
/// Translation noise per degree of rotation noise (the paper's pairs: 0.2 deg with 2 mm, ...).
const TRANSLATION_M_PER_DEG: f32 = 0.01;

/// Simulate `scene` (with optional label noise) into `out` and load it with its exact poses.
pub fn simulated(
    scene: &str,
    frames: u32,
    size: u16,
    noise: Option<LabelNoise>,
    out: &Path,
) -> Fallible<(Dataset, Option<Vec<Pose>>)> {
    let mut scene = Scene::load(scene)?;
    scene.spec.frames = frames;
    scene.spec.size = size;
    if let Some(noise) = noise {
        scene.spec.effects.label_noise =
            (noise.rotation_deg > 0.0 || noise.translation_m > 0.0).then_some(noise);
    }
    sim::simulate(&scene, out, &|| {})?;
    load(out, size)
}

fn load(path: &Path, size: u16) -> Fallible<(Dataset, Option<Vec<Pose>>)> {
    let set = speedplus::load(
        path,
        &LoadOptions {
            width: Some(size as u32),
            domain: None,
        },
    )?;
    let truth = set.truth.and_then(|t| {
        t.frames
            .iter()
            .map(|f| f.label().pose())
            .collect::<Option<Vec<_>>>()
    });
    Ok((set.dataset, truth))
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
    let (dataset, truth) = match &args.data {
        Some(path) => load(path, args.size)?,
        None => simulated(
            &args.scene,
            args.frames,
            args.size,
            None,
            &args.out.join("data"),
        )?,
    };
    let (train_idx, test_idx) = split_every(dataset.frames.len(), args.holdout);
    let base = base_config(args)?;
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

fn sweep(args: &AblateArgs) -> Fallible<()> {
    let base = base_config(args)?;
    let mut rows = Vec::new();
    let (mut ssim_ours, mut ssim_pose, mut rot_labels, mut rot_pose) =
        (vec![], vec![], vec![], vec![]);
    for (i, &rotation_deg) in args.levels.iter().enumerate() {
        if !(rotation_deg.is_finite() && rotation_deg >= 0.0) {
            return Err(
                format!("--levels: {rotation_deg} is not a rotation noise in degrees").into(),
            );
        }
        let translation_m = rotation_deg * TRANSLATION_M_PER_DEG;
        let noise = LabelNoise {
            rotation_deg,
            translation_m,
        };
        let (dataset, truth) = simulated(
            "synthetic",
            args.frames,
            args.size,
            Some(noise),
            &args.out.join(format!("noise_{i}")),
        )?;
        let (train_idx, test_idx) = split_every(dataset.frames.len(), args.holdout);
        println!(
            "noise {rotation_deg} deg / {:.0} mm",
            translation_m * 1000.0
        );
        let mut level = Vec::new();
        for variant in [APPEARANCE, APPEARANCE_POSE] {
            let r = ablation::run_variant(
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
                "  {}: SSIM {:.4}, rotation error {:.3} deg",
                variant.name,
                r.metrics.ssim_full,
                r.pose_after.unwrap_or_default().rotation_deg_mean
            );
            level.push(r);
        }
        let (ours, pose) = (&level[0], &level[1]);
        let before = pose.pose_before.unwrap_or_default();
        let after = pose.pose_after.unwrap_or_default();
        ssim_ours.push((rotation_deg as f64, ours.metrics.ssim_full));
        ssim_pose.push((rotation_deg as f64, pose.metrics.ssim_full));
        rot_labels.push((rotation_deg as f64, before.rotation_deg_mean));
        rot_pose.push((rotation_deg as f64, after.rotation_deg_mean));
        rows.push(vec![
            format!("{rotation_deg}"),
            format!("{:.0}", translation_m * 1000.0),
            format!("{:.4}", ours.metrics.ssim_full),
            format!("{:.4}", pose.metrics.ssim_full),
            format!("{:.4}", ours.metrics.jnb_full),
            format!("{:.4}", pose.metrics.jnb_full),
            format!("{:.3}", before.rotation_deg_mean),
            format!("{:.3}", after.rotation_deg_mean),
            format!("{:.1}", before.translation_mean * 1000.0),
            format!("{:.1}", after.translation_mean * 1000.0),
            format!(
                "{:.3} / {:.3}",
                before.about_view_axis_deg_mean, after.about_view_axis_deg_mean
            ),
            format!(
                "{:.3} / {:.3}",
                before.across_view_axis_deg_mean, after.across_view_axis_deg_mean
            ),
        ]);
    }
    let header = [
        "E_R deg",
        "E_T mm",
        "SSIM ours",
        "SSIM ours+pose",
        "JNB ours",
        "JNB ours+pose",
        "rot. error labels deg",
        "rot. error corrected deg",
        "trans. error labels mm",
        "trans. error corrected mm",
        "rot. about view axis labels / corrected deg",
        "rot. across view axis labels / corrected deg",
    ];
    let mut text = format!(
        "# Pose-noise sweep on `synthetic`\n\n{} frames of {} px, {} steps per model; JNB: paper variant, lower is sharper.\n\n",
        args.frames, args.size, base.steps
    );
    text.push_str(&report::markdown_table(&header, &rows));
    text.push_str("\n![SSIM](pose_noise_ssim.png)\n![rotation error](pose_noise_rotation.png)\n");
    report::line_plot(
        &args.out.join("pose_noise_ssim.png"),
        "held-out SSIM vs label rotation noise",
        "rotation noise (deg)",
        "SSIM",
        &[("ours", ssim_ours), ("ours + pose", ssim_pose)],
    )?;
    report::line_plot(
        &args.out.join("pose_noise_rotation.png"),
        "mean rotation error of the training poses",
        "rotation noise (deg)",
        "error (deg)",
        &[("labels", rot_labels), ("corrected", rot_pose)],
    )?;
    orbit_nerf_host::io::write_atomic(&args.out.join("pose_noise.md"), text.as_bytes())?;
    println!("{text}");
    Ok(())
}
