//! The paper's experiments, run by `ablate` and `demo`: the simulated set with its exact
//! poses, the label noise a scene states, the target's true surface, the ablation and the
//! pose-noise sweeps, and the report's markdown sections (the ablation table, pose errors and
//! uncertainty, geometry, side-by-side renders).

use crate::ablation::{self, APPEARANCE, APPEARANCE_POSE, BASELINE, Experiment, VariantResult};
use crate::dataset::{Dataset, split_every, with_test_set};
use crate::geometry::{self, Triangle};
use crate::report::{self, ModelOutcome, ModelRow, NoiseLevelResult};
use crate::sim::{self, Scene, scene::LabelNoise};
use crate::sweep::{FrameCounts, NoiseLevels, Sweep, SweepDescription};
use crate::train::to_rgb8;
use crate::{HostError, Result, formats, pipeline};
use orbit_nerf_core::{Config, Pose};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Simulate `scene` (with `noise` on its labels when given) into `out` at `frames` frames of
/// `size` px (longer side) and load it with its exact poses, masks applied when `masks`.
pub fn simulated(
    scene: &str,
    frames: u32,
    size: u16,
    noise: Option<LabelNoise>,
    out: &Path,
    masks: bool,
) -> Result<(Dataset, Option<Vec<Pose>>)> {
    let mut scene = Scene::load(scene)?;
    scene.spec.frames = frames;
    scene.spec.set_longer_side(size);
    if let Some(noise) = noise {
        scene.spec.effects.label_noise =
            (noise.rotation_deg > 0.0 || noise.translation_m > 0.0).then_some(noise);
    }
    sim::simulate(&scene, out, &|| {})?;
    load(out, size, masks)
}

/// Load a dataset folder of any format with its exact poses when it has them, masks applied
/// when `masks`.
pub fn load(path: &Path, size: u16, masks: bool) -> Result<(Dataset, Option<Vec<Pose>>)> {
    let (mut dataset, truth) =
        formats::open_with_truth(path, Some(size as u32), pipeline::NERF_BACKGROUND)?;
    if masks {
        dataset.apply_masks();
    }
    Ok((dataset, truth))
}

/// The label noise a scene states (none: exact labels), for the pose correction's prior.
pub fn stated_label_noise(scene: &str) -> Result<LabelNoise> {
    Ok(Scene::load(scene)?
        .spec
        .effects
        .label_noise
        .unwrap_or(LabelNoise {
            rotation_deg: 0.0,
            translation_m: 0.0,
        }))
}

/// The true surface of a simulated scene: the target's triangles in metres, in its body
/// frame, which is the world frame of the dataset the simulator writes.
pub fn true_surface(scene: &str) -> Result<Vec<Triangle>> {
    Ok(sim::Target::build(&Scene::load(scene)?)?.surface())
}

/// The report's sections on poses: the training labels' error against the exact poses, the
/// held-out views scored at their labels, exact poses and aligned, and the refined training
/// poses' uncertainty (with pose correction).
pub fn pose_sections(results: &[&VariantResult]) -> String {
    let mut text = String::new();
    let pose_rows: Vec<_> = results
        .iter()
        .filter_map(|r| Some((r.variant.name.to_string(), r.pose_before?, r.pose_after?)))
        .collect();
    if !pose_rows.is_empty() {
        text.push_str("\n## Pose error of the training labels against the exact poses\n\n");
        text.push_str(&report::pose_error_table(&pose_rows));
    }
    let scored: Vec<_> = results
        .iter()
        .map(|r| {
            let name = r.variant.name.to_string();
            (name, r.metrics, r.metrics_exact, r.metrics_aligned)
        })
        .collect();
    let _ = write!(
        text,
        "\n## Held-out views at their labels, exact poses and aligned\n\nEach view's embedding \
         fitted on its left half, then rendered at its label (the protocol on noisy labels), at \
         its exact pose (where the data has one, as the paper's test set) and at its label \
         aligned by the pose refinement on the same half.\n\n{}",
        report::held_out_poses_table(&scored)
    );
    let uncertain: Vec<_> = results
        .iter()
        .filter_map(|r| Some((r.variant.name.to_string(), r.pose_uncertainty?, *r)))
        .collect();
    if !uncertain.is_empty() {
        let times: Vec<String> = (uncertain.iter())
            .map(|(name, _, r)| {
                format!(
                    "{name} {:.1} s of {:.1} s",
                    r.pose_refine_seconds, r.train_seconds
                )
            })
            .collect();
        let rows: Vec<_> = (uncertain.iter())
            .map(|(name, u, _)| (name.clone(), *u))
            .collect();
        let _ = write!(
            text,
            "\n## Uncertainty of the refined training poses\n\nEach frame's 1-sigma from the pose \
             refinement's information matrix (per-frame figures in metrics.json), and how often \
             the true error lies within 3 sigma. The refinement's share of the training time: \
             {}.\n\n{}",
            times.join(", "),
            report::pose_uncertainty_table(&rows)
        );
    }
    text
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

/// An experiment's report: `heading` and `setup` (what was trained on what), the table of
/// `results`, their pose and geometry sections (geometry against `surface` when the true shape
/// is known), and the first four held-out views (`test_idx` of `dataset`) side by side with
/// the truth, written as PNGs `{prefix}NNN.png` into `out` and linked from the text.
pub fn experiment_report(
    heading: &str,
    setup: &str,
    results: &[VariantResult],
    surface: Option<&[Triangle]>,
    (dataset, test_idx): (&Dataset, &[usize]),
    (out, prefix): (&Path, &str),
) -> Result<String> {
    let rows: Vec<ModelRow> = results
        .iter()
        .map(|r| ModelRow {
            name: r.variant.name.to_string(),
            metrics: r.metrics,
            train_seconds: r.train_seconds,
        })
        .collect();
    let all: Vec<&VariantResult> = results.iter().collect();
    let mut text = format!(
        "# {heading}\n\n{setup}\n\n{}",
        report::ablation_table(&rows)
    );
    text.push_str(&pose_sections(&all));
    if let Some(truth) = surface {
        text.push_str(&geometry_section(&all, truth));
    }
    let names: Vec<&str> = results.iter().map(|r| r.variant.name).collect();
    let _ = write!(
        text,
        "\n## Held-out views (truth, {})\n\n",
        names.join(", ")
    );
    for (k, &index) in test_idx.iter().enumerate().take(4) {
        let frame = &dataset.frames[index];
        let (w, h) = (frame.camera.width as u32, frame.camera.height as u32);
        let renders: Vec<Vec<u8>> = results.iter().map(|r| to_rgb8(&r.renders[k])).collect();
        let mut tiles: Vec<(&str, &[u8])> = vec![("truth", &frame.pixels)];
        tiles.extend(names.iter().copied().zip(renders.iter().map(Vec::as_slice)));
        let (sw, sh, strip) = report::side_by_side(&tiles, w, h);
        let name = format!("{prefix}{index:03}.png");
        crate::io::write_png(&out.join(&name), sw, sh, 3, &strip)?;
        let _ = writeln!(text, "![view {index}]({name})");
    }
    Ok(text)
}

/// The data of an ablation: a simulated scene or a dataset folder, split into training and
/// held-out views, or trained on every view and tested on a separate set.
#[derive(Clone, Debug)]
pub struct AblationData {
    /// The scene simulated when `data` is `None` (a preset or a scene file).
    pub scene: String,
    /// A dataset folder of any format instead of a simulated scene.
    pub data: Option<PathBuf>,
    /// Frames simulated.
    pub frames: u32,
    /// Image size, pixels (longer side; datasets are never upsampled).
    pub size: u16,
    /// Every N-th view held out (unused with `test_data`).
    pub holdout: usize,
    /// A separate test set (every view scored, at its exact pose where it has one).
    pub test_data: Option<PathBuf>,
    /// Apply the frames' masks.
    pub masks: bool,
    /// The scene box the user stated (wins over a config file's and the data's).
    pub scene_box: Option<([f32; 3], [f32; 3])>,
    /// The config file the base config took fields from (a box it sets is used).
    pub config_file: Option<PathBuf>,
}

/// The paper's ablation: baseline, + appearance, + appearance and pose correction, each
/// trained from `base` for its steps with `threads` workers on the training views of `data`
/// and scored on its held-out views (embeddings fitted for `fit_steps`). Writes the simulated
/// set (if any), `ablation.md`, `metrics.json` and the side-by-side renders into `out`, and
/// returns the report's text; progress lines go to `say`.
pub fn run_ablation(
    data: &AblationData,
    base: &Config,
    (threads, fit_steps): (usize, u32),
    out: &Path,
    say: &mut dyn FnMut(String),
) -> Result<String> {
    let mut base = *base;
    if data.data.is_none() {
        stated_label_noise(&data.scene)?.state_in(&mut base);
    }
    let (dataset, truth) = match &data.data {
        Some(path) => load(path, data.size, data.masks)?,
        None => simulated(
            &data.scene,
            data.frames,
            data.size,
            None,
            &out.join("data"),
            data.masks,
        )?,
    };
    let (mut dataset, truth, train_idx, test_idx) = match &data.test_data {
        Some(test) => with_test_set((dataset, truth), load(test, data.size, data.masks)?),
        None => {
            let (train_idx, test_idx) = split_every(dataset.frames.len(), data.holdout);
            (dataset, truth, train_idx, test_idx)
        }
    };
    say(pipeline::choose_box(
        &mut dataset,
        data.scene_box,
        data.config_file.as_deref(),
        &train_idx,
    )?);
    let mut results: Vec<VariantResult> = Vec::new();
    for variant in [BASELINE, APPEARANCE, APPEARANCE_POSE] {
        say(format!(
            "training {} ({} views, {} steps)",
            variant.name,
            train_idx.len(),
            base.steps
        ));
        let result = ablation::run_variant(
            &dataset,
            truth.as_deref(),
            &train_idx,
            &test_idx,
            &base,
            variant,
            threads,
            fit_steps,
            &mut |_, _| {},
        )?;
        say(format!(
            "  {:.1} s, held-out PSNR {:.2} dB",
            result.train_seconds, result.metrics.psnr_full
        ));
        results.push(result);
    }
    let held_out = match &data.test_data {
        Some(test) => format!(
            "trained on all {} frames, tested on the {} views of the separate test set `{}`",
            train_idx.len(),
            test_idx.len(),
            test.display()
        ),
        None => format!(
            "{} frames, every {}th held out ({} views)",
            dataset.frames.len(),
            data.holdout,
            test_idx.len()
        ),
    };
    let surface = match &data.data {
        Some(_) => None,
        None => Some(true_surface(&data.scene)?),
    };
    let source = (data.data.as_ref()).map_or(data.scene.clone(), |p| p.display().to_string());
    let text = experiment_report(
        &format!("Ablation on `{source}`"),
        &format!(
            "{held_out}, {} px, {} steps per model; held-out embeddings fitted for {fit_steps} steps on the left half.",
            data.size, base.steps
        ),
        &results,
        surface.as_deref(),
        (&dataset, &test_idx),
        (out, "compare_view_"),
    )?;
    crate::io::write_atomic(&out.join("ablation.md"), text.as_bytes())?;
    let models = results.iter().map(VariantResult::figures).collect();
    report::Figures::new("ablate", models).write(out)?;
    Ok(text)
}

/// The paper's two pose-noise sweeps as a sweep's levels and models: rotation noise alone at
/// `rotation_deg` (degrees, exact positions), then translation noise alone at
/// `translation_mm` (mm per axis, exact attitudes), the noise-free level shared; the
/// `synthetic` preset at `data`'s frames, size, holdout and masks, the models from `preset`
/// (default `spacecraft`) and `data.config_file` with `steps`.
pub fn pose_noise_sweep(
    data: &AblationData,
    (preset, steps): (Option<String>, Option<u32>),
    fit_steps: u32,
    (rotation_deg, translation_mm): (Vec<f32>, Vec<f32>),
) -> Result<Sweep> {
    let description = SweepDescription {
        scene: Some("synthetic".into()),
        frames: Some(FrameCounts::One(data.frames)),
        size: Some(data.size.into()),
        preset,
        config: (data.config_file.as_ref()).map(|p| p.display().to_string()),
        steps,
        holdout: Some(data.holdout),
        fit_steps: Some(fit_steps),
        masks: Some(data.masks),
        noise: Some(NoiseLevels {
            rotation_deg,
            translation_mm,
        }),
        ..SweepDescription::default()
    };
    description.check(Path::new("ablate --pose-noise"), Path::new(""))
}

/// The paper's two pose-noise sweeps on the `synthetic` preset: `sweep`'s noise levels (the
/// noise-free one shared), each simulated into its own folder of `out` with `data`'s frames,
/// size, holdout and masks, and its two models (ours, ours + pose) trained and scored. Writes
/// `pose_noise.md` with its tables and plots into `out` and returns its text.
pub fn run_pose_noise_sweeps(
    data: &AblationData,
    sweep: &Sweep,
    (threads, fit_steps): (usize, u32),
    out: &Path,
    say: &mut dyn FnMut(String),
) -> Result<String> {
    let mut levels = Vec::new();
    for noise in sweep.levels().into_iter().flatten() {
        let dir = out.join(format!(
            "noise_r{}deg_t{}mm",
            noise.rotation_deg,
            noise.translation_m * 1000.0
        ));
        let (dataset, truth) = simulated(
            "synthetic",
            data.frames,
            data.size,
            Some(noise),
            &dir,
            data.masks,
        )?;
        let (train_idx, test_idx) = split_every(dataset.frames.len(), data.holdout);
        say(format!(
            "noise {} deg / {} mm",
            noise.rotation_deg,
            noise.translation_m * 1000.0
        ));
        let experiment = Experiment {
            dataset: &dataset,
            truth: truth.as_deref(),
            train_idx: &train_idx,
            test_idx: &test_idx,
            threads,
            fit_steps,
            score_at: &[],
            progress: None,
        };
        let mut run = |variant: &str| -> Result<ModelOutcome> {
            let task = (sweep.tasks.iter())
                .find(|t| t.noise == Some(noise) && t.variant == variant)
                .ok_or_else(|| {
                    HostError::invalid(
                        &sweep.origin,
                        format!("the sweep has no task `{variant}` at this level"),
                    )
                })?;
            let r = experiment.run(&task.config, &mut |_, _| {}, None)?;
            let after = r.pose_after.unwrap_or_default();
            say(format!(
                "  {variant}: SSIM {:.4}, rotation error {:.3} deg, position error {:.1} mm",
                r.metrics.ssim_full,
                after.rotation_deg_mean,
                after.translation_mean * 1000.0
            ));
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
        levels.push(NoiseLevelResult { noise, ours, pose });
    }
    let mut text = format!(
        "# Pose-noise sweeps on `synthetic`\n\n{} frames of {} px, every {}th held out, {} steps per model, held-out embeddings fitted for {fit_steps} steps; JNB: paper variant, lower is sharper. Pose errors are the means over the training frames, against the simulator's exact poses.\n",
        data.frames, data.size, data.holdout, sweep.base.steps
    );
    text.push_str(&report::pose_noise_sections(
        out,
        &sweep.rotation,
        &sweep.translation,
        &levels,
    )?);
    crate::io::write_atomic(&out.join("pose_noise.md"), text.as_bytes())?;
    Ok(text)
}

/// The demo's budget: the lightbox preset, 200 frames of 128 px, 2000 steps of the method
/// (appearance embeddings and pose correction).
pub const DEMO_FRAMES: u32 = 200;
/// The demo's image size, pixels.
pub const DEMO_SIZE: u16 = 128;
/// The demo's training steps.
pub const DEMO_STEPS: u32 = 2000;

/// The built-in default (`orbit-nerf demo`): simulate the lightbox preset into `out/data`,
/// train the method for `steps` (default [`DEMO_STEPS`]) with `threads` workers, calling
/// `on_step` after each step, score every 8th view held out, and write `report.md`,
/// `metrics.json` and the renders into `out`. Returns the report's text.
pub fn run_demo(
    out: &Path,
    (steps, threads, masks): (Option<u32>, usize, bool),
    on_step: &mut dyn FnMut(u32, &orbit_nerf_core::StepReport),
) -> Result<String> {
    let start = std::time::Instant::now();
    let (dataset, truth) = simulated(
        "lightbox",
        DEMO_FRAMES,
        DEMO_SIZE,
        None,
        &out.join("data"),
        masks,
    )?;
    let (train_idx, test_idx) = split_every(dataset.frames.len(), 8);
    let mut config = Config::SPACECRAFT;
    stated_label_noise("lightbox")?.state_in(&mut config);
    let steps = steps.or(Some(DEMO_STEPS));
    crate::pipeline::Overrides {
        steps,
        ..Default::default()
    }
    .apply(&mut config);
    let fit_steps = crate::train::DEFAULT_FIT_STEPS;
    let result = ablation::run_variant(
        &dataset,
        truth.as_deref(),
        &train_idx,
        &test_idx,
        &config,
        APPEARANCE_POSE,
        threads,
        fit_steps,
        on_step,
    )?;
    let mut text = experiment_report(
        "orbit-nerf demo",
        &format!(
            "The `lightbox` preset ({DEMO_FRAMES} frames of {DEMO_SIZE} px, every 8th of them held out), \
             trained for {} steps with appearance embeddings and pose correction in {:.1} s; held-out \
             embeddings fitted for {fit_steps} steps on the left half of each view.",
            config.steps, result.train_seconds
        ),
        std::slice::from_ref(&result),
        Some(&true_surface("lightbox")?),
        (&dataset, &test_idx),
        (out, "view_"),
    )?;
    let _ = writeln!(
        text,
        "\nTotal wall time (simulate, train, evaluate, report): {:.1} s",
        start.elapsed().as_secs_f64()
    );
    crate::io::write_atomic(&out.join("report.md"), text.as_bytes())?;
    report::Figures::new("demo", vec![result.figures()]).write(out)?;
    Ok(text)
}
