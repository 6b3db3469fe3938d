//! Training on the host: the model config as a file, a rayon executor for the core's chunks,
//! loading a dataset into frame slots, evaluation renders, and checkpoints of the core's state.

use crate::checkpoint::{Checkpoint, Section, SectionReader};
use crate::dataset::{Dataset, Frame};
use crate::error::{HostError, Result};
use crate::metrics::MetricError;
use crate::report::{ViewFigures, ViewMetrics, score_view};
use orbit_nerf_core::{Config, Executor, Pose, PoseCorrection, PoseFit, Trainer};
use rayon::prelude::*;
use std::path::Path;
use std::time::Instant;

/// Default steps fitting a held-out view's appearance embedding.
pub const DEFAULT_FIT_STEPS: u32 = 50;

/// Read a config file on top of `base` (a preset): the file names only the fields it changes,
/// either at the top level or in a `[config]` table (as in the budget files, `budgets/*.toml`,
/// which name every field). An unknown field or a bad value is an error naming the file and
/// the field.
pub fn read_config(path: &Path, base: &Config) -> Result<Config> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    parse_config(path, &text, base)
}

/// [`read_config`] of a file's text (`path` names it in errors).
pub fn parse_config(path: &Path, text: &str, base: &Config) -> Result<Config> {
    with_overrides(path, "", base, &config_table(path, text)?)
}

/// The table of config fields in a config file's text: its `[config]` table when it has one,
/// else its top level.
fn config_table(path: &Path, text: &str) -> Result<toml::Table> {
    let mut table: toml::Table = toml::from_str(text)
        .map_err(|e| HostError::invalid(path, format!("not valid TOML: {}", e.message())))?;
    Ok(match table.remove("config") {
        Some(toml::Value::Table(inner)) => inner,
        Some(other) => {
            table.insert("config".into(), other);
            table
        }
        None => table,
    })
}

/// `base` with the fields in `set` replaced, checked; errors name `path` and the field (after
/// `prefix`, e.g. `variants[0].set.`, where the table sits inside a larger file).
pub fn with_overrides(
    path: &Path,
    prefix: &str,
    base: &Config,
    set: &toml::Table,
) -> Result<Config> {
    let mut table = toml::Table::try_from(base)
        .map_err(|e| HostError::invalid(path, format!("config encoding failed: {e}")))?;
    for (key, value) in set {
        if !table.contains_key(key) {
            return Err(HostError::field(
                path,
                format!("{prefix}{key}"),
                "not a config field",
            ));
        }
        table.insert(key.clone(), value.clone());
    }
    let mut config: Config = serde_path_to_error::deserialize(table).map_err(|e| {
        let field = e.path().to_string();
        let reason = e.into_inner().to_string();
        if field == "." {
            HostError::invalid(path, format!("not a valid config: {reason}"))
        } else {
            HostError::field(path, format!("{prefix}{field}"), reason)
        }
    })?;
    // Fewer steps than the base's warm-up keep as much of it as fits, as `--steps` does: the
    // user named `steps`, not the base's `warmup_steps`.
    if set.contains_key("steps") && !set.contains_key("warmup_steps") {
        config.warmup_steps = config.warmup_steps.min(config.steps);
    }
    config.validate().map_err(|e| match e {
        orbit_nerf_core::Error::InvalidConfig { field } => {
            HostError::field(path, format!("{prefix}{field}"), "out of range")
        }
        other => HostError::invalid(path, other.to_string()),
    })?;
    Ok(config)
}

/// Whether a config file sets `key` (at the top level or in a `[config]` table): a field the
/// file leaves to its preset does not count.
pub fn config_file_sets(path: &Path, key: &str) -> Result<bool> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    Ok(config_table(path, &text)?.contains_key(key))
}

/// The scene box a config file sets (`aabb_min` and `aabb_max`, at the top level or in a
/// `[config]` table), `None` when it sets none. Only a box written in the file counts: the one
/// a file leaves to its preset does not. A box the user wrote wins over the data's own (see
/// [`crate::scene_box::choose_scene_box`]).
pub fn config_scene_box(path: &Path) -> Result<Option<([f32; 3], [f32; 3])>> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    let table = config_table(path, &text)?;
    let corner = |key: &str| -> Result<Option<[f32; 3]>> {
        table
            .get(key)
            .map(|value| {
                value
                    .clone()
                    .try_into::<[f32; 3]>()
                    .ok()
                    .filter(|c| c.iter().all(|v| v.is_finite()))
                    .ok_or_else(|| HostError::field(path, key, "expected three finite numbers"))
            })
            .transpose()
    };
    match (corner("aabb_min")?, corner("aabb_max")?) {
        (Some(min), Some(max)) => {
            if let Some(axis) = (0..3).find(|&a| min[a] >= max[a]) {
                return Err(HostError::field(
                    path,
                    "aabb_min",
                    format!(
                        "axis {axis}: {} is not below aabb_max's {}",
                        min[axis], max[axis]
                    ),
                ));
            }
            Ok(Some((min, max)))
        }
        (None, None) => Ok(None),
        (Some(_), None) => Err(HostError::field(
            path,
            "aabb_max",
            "missing (aabb_min is set)",
        )),
        (None, Some(_)) => Err(HostError::field(
            path,
            "aabb_min",
            "missing (aabb_max is set)",
        )),
    }
}

/// `config` as TOML, every field written (what runs store as `config.toml`).
pub fn config_to_toml(config: &Config) -> Result<String> {
    to_toml(Path::new("config.toml"), config)
}

/// `value` as the TOML text of `file`, which the error names when TOML cannot hold a value.
fn to_toml<T: serde::Serialize + ?Sized>(file: &Path, value: &T) -> Result<String> {
    toml::to_string(value)
        .map_err(|e| HostError::invalid(file, format!("cannot be written as TOML: {e}")))
}

/// Runs the core's chunks on a rayon pool of a fixed size.
pub struct RayonExecutor {
    pool: rayon::ThreadPool,
}

impl RayonExecutor {
    /// A pool of `threads` worker threads (0 counts as 1).
    pub fn new(threads: usize) -> Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .build()
            .map_err(|e| HostError::Core(format!("thread pool: {e}")))?;
        Ok(RayonExecutor { pool })
    }
}

impl Executor for RayonExecutor {
    fn for_each<T: Send, F: Fn(&mut T) + Sync>(&self, items: &mut [T], f: F) {
        self.pool
            .install(|| items.par_iter_mut().with_max_len(1).for_each(&f));
    }
}

/// The config with the dataset's scene box, background and frame capacities filled in.
pub fn fit_config(base: &Config, dataset: &Dataset, frames: usize) -> Config {
    let mut c = *base;
    c.aabb_min = dataset.scene_min;
    c.aabb_max = dataset.scene_max;
    c.background = dataset.background;
    c.max_frames = c.max_frames.max(frames.min(u16::MAX as usize) as u16);
    let largest = dataset
        .frames
        .iter()
        .map(|f| f.camera.pixel_count())
        .max()
        .unwrap_or(1);
    c.max_pixels_per_frame = c.max_pixels_per_frame.max(largest as u32);
    c
}

fn core_error(file: &Path, e: orbit_nerf_core::Error) -> HostError {
    HostError::invalid(file, e.to_string())
}

/// Put `frames` into slots 0, 1, ... of the trainer.
pub fn load_frames<'f>(
    trainer: &mut Trainer<'_>,
    frames: impl IntoIterator<Item = &'f Frame>,
) -> Result<()> {
    for (slot, frame) in frames.into_iter().enumerate() {
        trainer
            .set_frame(
                slot,
                frame.camera,
                frame.pose,
                &frame.pixels,
                frame.mask.as_deref(),
            )
            .map_err(|e| core_error(Path::new(&frame.name), e))?;
    }
    Ok(())
}

/// Refine every training frame's pose correction with the field frozen
/// (`Trainer::refine_pose`, slot by slot; with `pose_refine_iterations = 0` only their
/// uncertainty): the last stage of a training run with pose correction. Returns each slot's
/// fit, in slot order (none without pose correction).
pub fn refine_poses<E: Executor>(trainer: &mut Trainer<'_>, executor: &E) -> Result<Vec<PoseFit>> {
    let config = *trainer.config();
    if !config.pose_correction {
        return Ok(Vec::new());
    }
    let slots: Vec<usize> = (0..trainer.frames().len())
        .filter_map(|i| trainer.frames().occupied_slot(i))
        .collect();
    slots
        .into_iter()
        .map(|slot| {
            trainer
                .refine_pose(executor, slot)
                .map_err(|e| core_error(Path::new("pose refinement"), e))
        })
        .collect()
}

/// Refuse training frames with nothing to learn from: every pixel of every one black (an
/// exposure of 0, a target that is never lit). `source` names the dataset in the error.
pub fn check_frames_have_content<'f>(
    source: &Path,
    frames: impl IntoIterator<Item = &'f Frame>,
) -> Result<()> {
    let mut count = 0;
    for frame in frames {
        if frame.pixels.iter().any(|&v| v > 0) {
            return Ok(());
        }
        count += 1;
    }
    Err(HostError::invalid(
        source,
        format!("every one of the {count} training views is black: nothing to train on"),
    ))
}

/// What a training run took: steps, and the samples its rays met in the scene box.
#[derive(Clone, Copy, Debug, Default)]
pub struct TrainingTally {
    /// Training steps run.
    pub steps: u64,
    /// Samples the steps' rays took inside the scene box, summed over all rays.
    pub samples: u64,
}

/// Refuse a trained model that is garbage, naming the cause, before it is saved or scored:
/// parameters that are not finite (a diverged run, e.g. an `adam_eps` so small that Adam
/// divides 0 by 0), every step skipped, or no training ray that met the scene box. `run`
/// names the run in the error.
pub fn check_trained(run: &Path, trainer: &Trainer<'_>, tally: TrainingTally) -> Result<()> {
    let refuse = |why: String| {
        Err(HostError::invalid(
            run,
            format!("{why}; the model is garbage, not saved and not scored"),
        ))
    };
    if let Some((section, index)) = trainer.first_non_finite_section() {
        return refuse(format!(
            "training diverged: `{section}` holds a non-finite value (element {index}) after step {} (check learning_rate and adam_eps)",
            trainer.state().step
        ));
    }
    let state = trainer.state();
    if state.step > 0 && state.skipped == state.step {
        return refuse(format!(
            "every one of the {} steps was skipped (non-finite loss or gradients)",
            state.step
        ));
    }
    if tally.steps > 0 && tally.samples == 0 {
        return refuse(format!(
            "no training ray met the scene box in {} steps (0 samples per ray): the box {} is not where the cameras look",
            tally.steps,
            crate::scene_box::box_text(trainer.config().aabb_min, trainer.config().aabb_max)
        ));
    }
    Ok(())
}

/// f32 RGB in [0, 1] to RGB8.
pub fn to_rgb8(image: &[f32]) -> Vec<u8> {
    image
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect()
}

/// Kind tag of training checkpoints.
pub const CHECKPOINT_KIND: &str = "orbit-nerf trainer";

/// Save the trainer's whole state (and its config) atomically, with a command's own
/// `extra` sections after the trainer's, streamed from the arena (no copy of the model).
pub fn save_checkpoint(path: &Path, trainer: &Trainer<'_>, extra: &[(&str, &[u8])]) -> Result<()> {
    let config = postcard::to_allocvec(trainer.config())
        .map_err(|e| HostError::invalid(path, format!("config encoding failed: {e}")))?;
    let mut sections = trainer.sections().to_vec();
    sections.extend_from_slice(extra);
    crate::checkpoint::save_parts(path, CHECKPOINT_KIND, &config, &sections)
}

/// The config stored in a checkpoint.
pub fn checkpoint_config(path: &Path, checkpoint: &Checkpoint) -> Result<Config> {
    decode_config(path, &checkpoint.kind, &checkpoint.config)
}

/// A trainer checkpoint's config from its `kind` and encoded `config` (`path` names it).
pub fn decode_config(path: &Path, kind: &str, config: &[u8]) -> Result<Config> {
    if kind != CHECKPOINT_KIND {
        return Err(HostError::invalid(
            path,
            format!("checkpoint holds `{kind}`, not a trainer"),
        ));
    }
    let config: Config = postcard::from_bytes(config)
        .map_err(|e| HostError::field(path, "config", format!("cannot decode: {e}")))?;
    config
        .validate()
        .map_err(|e| HostError::field(path, "config", e.to_string()))?;
    Ok(config)
}

/// Restore the checkpoint file at `path` into `trainer` (built from the config it holds),
/// each section read straight into the arena, so restoring takes no copy of the model. The
/// sections named in `extra` (a command's own state) are returned in file order; any other
/// section the trainer does not have, a missing one or one named twice is refused naming it.
pub fn restore_checkpoint(
    path: &Path,
    trainer: &mut Trainer<'_>,
    extra: &[&str],
) -> Result<Vec<Section>> {
    let names: Vec<&str> = trainer.sections().iter().map(|(name, _)| *name).collect();
    restore_sections(path, trainer, extra, &names)
}

/// [`restore_checkpoint`] of a file that holds some of the trainer's sections: those named in
/// `required` must be there, the others keep what the trainer has.
pub fn restore_sections(
    path: &Path,
    trainer: &mut Trainer<'_>,
    extra: &[&str],
    required: &[&str],
) -> Result<Vec<Section>> {
    let mut reader = SectionReader::open(path)?;
    restore_from(&mut reader, trainer, extra, required)
}

/// [`restore_sections`] from an opened checkpoint (a file, or bytes in memory).
pub fn restore_from<R: std::io::Read + std::io::Seek>(
    reader: &mut SectionReader<R>,
    trainer: &mut Trainer<'_>,
    extra: &[&str],
    required: &[&str],
) -> Result<Vec<Section>> {
    let path = reader.path().to_path_buf();
    let path = path.as_path();
    if decode_config(path, &reader.kind, &reader.config)? != *trainer.config() {
        return Err(HostError::invalid(
            path,
            "holds a model of another config than the one restoring it",
        ));
    }
    let mut seen: Vec<String> = Vec::new();
    let mut kept = Vec::new();
    while let Some((name, len)) = reader.next_section()? {
        if seen.contains(&name) {
            return Err(HostError::field(path, &name, "named twice"));
        }
        seen.push(name.clone());
        if extra.contains(&name.as_str()) {
            let bytes = reader.read_section_vec()?;
            kept.push(Section { name, bytes });
            continue;
        }
        let mut failed = None;
        let len = usize::try_from(len).unwrap_or(usize::MAX);
        let restored = trainer.restore_section_with(&name, len, |target| {
            reader
                .read_section(target)
                .map_err(|e| failed = Some(e))
                .is_ok()
        });
        if let Some(error) = failed {
            return Err(error);
        }
        restored.map_err(|e| HostError::field(path, &name, e.to_string()))?;
    }
    if let Some(missing) = required
        .iter()
        .find(|name| !seen.iter().any(|s| s == *name))
    {
        return Err(HostError::field(path, *missing, "missing section"));
    }
    Ok(kept)
}

/// Held-out quality of one view.
#[derive(Clone, Debug)]
pub struct ViewScore {
    /// The view's frame index in the dataset.
    pub index: usize,
    /// The view's image file name.
    pub name: String,
    /// The image metrics of the render against the view's reference (`report::score_view`,
    /// the one definition every command reports).
    pub metrics: ViewMetrics,
    /// Mean samples per ray of the rendering.
    pub samples_per_ray: f32,
    /// Wall time of fitting the view's embedding and rendering it, seconds.
    pub seconds: f64,
    /// The rendering, row-major RGB f32 in [0, 1].
    pub render: Vec<f32>,
}

/// The views' figures for `metrics.json`.
pub fn view_figures(scores: &[ViewScore]) -> Vec<ViewFigures> {
    scores
        .iter()
        .map(|s| ViewFigures {
            index: s.index,
            name: s.name.clone(),
            metrics: s.metrics,
            samples_per_ray: s.samples_per_ray as f64,
            seconds: s.seconds,
        })
        .collect()
}

/// A held-out view's appearance embedding and the pose to render it at: the embedding fitted
/// on the view's left half for `fit_steps` steps from `mean` (the mean training embedding),
/// and with `align_pose` the label corrected by a pose correction fitted with it
/// (`Trainer::fit_view`, BARF's test-time alignment); otherwise the label itself (the
/// paper's protocol).
pub fn fit_held_out<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    frame: &Frame,
    fit_steps: u32,
    align_pose: bool,
    mean: &[f32],
) -> std::result::Result<(Vec<f32>, Pose), orbit_nerf_core::Error> {
    fit_held_out_at(
        trainer,
        executor,
        frame,
        &frame.pose,
        fit_steps,
        align_pose,
        mean,
    )
}

/// [`fit_held_out`] at `pose` instead of the frame's label (its exact pose, say).
pub fn fit_held_out_at<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    frame: &Frame,
    pose: &Pose,
    fit_steps: u32,
    align_pose: bool,
    mean: &[f32],
) -> std::result::Result<(Vec<f32>, Pose), orbit_nerf_core::Error> {
    let frame = &Frame {
        pose: *pose,
        ..frame.clone()
    };
    let config = *trainer.config();
    let dim = config.embedding_dim as usize;
    let mut params = mean.to_vec();
    params.resize(config.frame_params(), 0.0);
    if fit_steps == 0 || (dim == 0 && !align_pose) {
        return Ok((params[..dim].to_vec(), frame.pose));
    }
    let half = frame.camera.width as u32 / 2;
    trainer.fit_view(
        executor,
        &frame.camera,
        &frame.pose,
        &frame.pixels,
        (0, half),
        fit_steps,
        align_pose,
        &mut params,
    )?;
    let pose = if align_pose {
        PoseCorrection::from_params(&params[dim..], config.length_unit())
            .apply(&frame.pose, config.pose_pivot_point())
    } else {
        frame.pose
    };
    Ok((params[..dim].to_vec(), pose))
}

/// The render and reference files an evaluation of `views` with a render folder `dir` writes
/// (checked before the work, so none is replaced unasked).
pub fn render_files(dir: &Path, views: &[usize]) -> Vec<std::path::PathBuf> {
    (views.iter())
        .flat_map(|i| ["view", "truth"].map(|kind| dir.join(format!("{kind}_{i:03}.png"))))
        .collect()
}

/// Evaluate held-out views as in the paper and K-Planes: with the field frozen, start a
/// fresh appearance embedding at the mean of the training embeddings, fit it for
/// `fit_steps` steps on the left half of the view's pixels (skipped without embeddings),
/// render the whole view and score it. With `render_dir`, writes `view_NNN.png` renders
/// beside `truth_NNN.png`.
///
/// A render holding NaN or infinite pixels is not scored: after every view is rendered, the
/// error [`HostError::NonFiniteRender`] names each such view.
pub fn evaluate<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    dataset: &Dataset,
    indices: &[usize],
    fit_steps: u32,
    align_poses: bool,
    render_dir: Option<&Path>,
) -> Result<Vec<ViewScore>> {
    evaluate_at(
        trainer,
        executor,
        dataset,
        indices,
        None,
        (fit_steps, align_poses),
        render_dir,
    )
}

/// [`evaluate`] with each view at `poses[index]` (its exact pose, where the data has one)
/// instead of its label when `poses` is given.
pub fn evaluate_at<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    dataset: &Dataset,
    indices: &[usize],
    poses: Option<&[Pose]>,
    (fit_steps, align_poses): (u32, bool),
    render_dir: Option<&Path>,
) -> Result<Vec<ViewScore>> {
    let mut mean = vec![0.0f32; trainer.config().embedding_dim as usize];
    trainer.mean_embedding(&mut mean);
    let mut scores = Vec::with_capacity(indices.len());
    let mut non_finite = Vec::new();
    for &index in indices {
        let frame = dataset
            .frames
            .get(index)
            .ok_or_else(|| HostError::invalid(&dataset.source, format!("no view {index}")))?;
        let start = Instant::now();
        let (w, h) = (frame.camera.width as u32, frame.camera.height as u32);
        let at = match poses {
            Some(poses) => poses.get(index).ok_or_else(|| {
                HostError::invalid(&dataset.source, format!("no exact pose of view {index}"))
            })?,
            None => &frame.pose,
        };
        let (embedding, pose) =
            fit_held_out_at(trainer, executor, frame, at, fit_steps, align_poses, &mean)
                .map_err(|e| core_error(Path::new(&frame.name), e))?;
        let mut out = vec![0.0f32; frame.camera.pixel_count() * 3];
        let samples_per_ray = trainer
            .render(executor, &frame.camera, &pose, &embedding, &mut out)
            .map_err(|e| core_error(Path::new(&frame.name), e))?;
        let seconds = start.elapsed().as_secs_f64();
        let metrics = match score_view(
            &out,
            &frame.pixels,
            frame.mask.as_deref(),
            w as usize,
            h as usize,
        ) {
            Ok(metrics) => metrics,
            Err(MetricError::NonFinite { .. }) => {
                non_finite.push(format!("view {index} ({})", frame.name));
                continue;
            }
            Err(e) => return Err(HostError::invalid(&frame.name, e.to_string())),
        };
        scores.push(ViewScore {
            index,
            name: frame.name.clone(),
            metrics,
            samples_per_ray,
            seconds,
            render: out,
        });
    }
    if !non_finite.is_empty() {
        return Err(HostError::NonFiniteRender {
            dataset: dataset.source.clone(),
            views: non_finite,
        });
    }
    // The background scores itself where no ray meets the field: no score without a sample.
    if !scores.is_empty() && scores.iter().all(|s| s.samples_per_ray == 0.0) {
        return Err(HostError::invalid(
            &dataset.source,
            format!(
                "no ray of the {} held-out views met the scene box {} (0 samples per ray): the model sees nothing there, no score is reported",
                scores.len(),
                crate::scene_box::box_text(trainer.config().aabb_min, trainer.config().aabb_max)
            ),
        ));
    }
    // Written once every view is scored, so a refused evaluation leaves no renders behind.
    if let Some(dir) = render_dir {
        for s in &scores {
            let frame = &dataset.frames[s.index];
            let (w, h) = (frame.camera.width as u32, frame.camera.height as u32);
            let index = s.index;
            crate::io::write_png(
                &dir.join(format!("view_{index:03}.png")),
                w,
                h,
                3,
                &to_rgb8(&s.render),
            )?;
            crate::io::write_png(
                &dir.join(format!("truth_{index:03}.png")),
                w,
                h,
                3,
                &frame.pixels,
            )?;
        }
    }
    Ok(scores)
}
#[cfg(test)]
mod tests {
    use super::*;

    /// An encoding failure is an error naming the file, never an empty file written as if
    /// all went well; a config encodes and reads back whole.
    #[test]
    fn a_value_toml_cannot_hold_is_an_error_not_an_empty_text() {
        let config = Config {
            // The largest seed a TOML integer (i64) holds.
            seed: i64::MAX as u64,
            replacement: orbit_nerf_core::Replacement::Coverage,
            ..Config::SPACECRAFT
        };
        let text = config_to_toml(&config).unwrap();
        let path = Path::new("config.toml");
        assert_eq!(parse_config(path, &text, &Config::DEFAULT).unwrap(), config);
        // A TOML document is a table: a bare number cannot be one.
        let error = to_toml(path, &5u32).unwrap_err().to_string();
        assert!(
            error.starts_with("config.toml: cannot be written as TOML"),
            "{error}"
        );
    }

    #[test]
    fn a_partial_config_file_changes_only_its_fields() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.toml");
        let base = Config::SPACECRAFT;
        let changed = Config {
            steps: 123,
            warmup_steps: 123,
            learning_rate: 0.02,
            replacement: orbit_nerf_core::Replacement::Novelty,
            ..base
        };
        // Both layouts: the top level and a `[config]` table beside other tables.
        for text in [
            "steps = 123\nlearning_rate = 0.02\nreplacement = \"novelty\"\n",
            "max_total_bytes = 1\n[bytes]\nplanes = 1\n[config]\nsteps = 123\nlearning_rate = 0.02\nreplacement = \"novelty\"\n",
        ] {
            std::fs::write(&path, text).unwrap();
            assert_eq!(read_config(&path, &base).unwrap(), changed, "{text}");
        }
        // An empty file is the base; a full file is itself whatever the base.
        std::fs::write(&path, "").unwrap();
        assert_eq!(read_config(&path, &base).unwrap(), base);
        std::fs::write(&path, config_to_toml(&changed).unwrap()).unwrap();
        assert_eq!(read_config(&path, &Config::DEFAULT).unwrap(), changed);
        // An unknown field, a value of the wrong type or out of range: the file and the field.
        for (text, field) in [
            ("lerning_rate = 0.1\n", "lerning_rate"),
            ("[config]\nsteps = \"many\"\n", "steps"),
            ("learning_rate = inf\n", "learning_rate"),
            ("features = 0\n", "features"),
        ] {
            std::fs::write(&path, text).unwrap();
            match read_config(&path, &base) {
                Err(HostError::Field { field: named, .. }) => assert_eq!(named, field, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
    }

    #[test]
    fn a_config_file_sets_the_box_only_when_it_names_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.toml");
        type Expected = std::result::Result<Option<([f32; 3], [f32; 3])>, &'static str>;
        let cases: [(&str, Expected); 5] = [
            ("steps = 10\n", Ok(None)),
            (
                "[config]\naabb_min = [-1, -2, -3]\naabb_max = [1, 2, 3]\n",
                Ok(Some(([-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]))),
            ),
            ("aabb_min = [-1, -2, -3]\n", Err("aabb_max")),
            (
                "aabb_min = [1, 0, 0]\naabb_max = [1, 1, 1]\n",
                Err("aabb_min"),
            ),
            ("aabb_min = [0, 0]\naabb_max = [1, 1, 1]\n", Err("aabb_min")),
        ];
        for (text, expected) in cases {
            std::fs::write(&path, text).unwrap();
            match (config_scene_box(&path), expected) {
                (Ok(found), Ok(expected)) => assert_eq!(found, expected, "{text}"),
                (Err(HostError::Field { field, .. }), Err(expected)) => {
                    assert_eq!(field, expected, "{text}")
                }
                (other, _) => panic!("{text}: {other:?}"),
            }
        }
    }
}
