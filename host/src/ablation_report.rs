//! The data and the report of the paper's experiments, shared by `ablate` and `demo`: the
//! simulated set with its exact poses, the label noise a scene states, the target's true
//! surface, and the report's markdown sections (the ablation table, pose errors and
//! uncertainty, geometry, side-by-side renders).

use crate::ablation::{self, VariantResult};
use crate::dataset::Dataset;
use crate::geometry::{self, Triangle};
use crate::report::{self, ModelRow};
use crate::sim::{self, Scene, scene::LabelNoise};
use crate::train::to_rgb8;
use crate::{Result, formats, pipeline};
use orbit_nerf_core::Pose;
use std::fmt::Write as _;
use std::path::Path;

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
