//! A sweep's results: the folder of each task (`<out>/tasks/<index>/`: `result.json`,
//! `timing.json`, `render.png`, `checkpoint.onrf`, `log.txt`, while it runs `progress.onrf`), the records a task writes, and
//! the merged tables and figures (`sweep.csv`, `sweep.md`, `renders.png`, with noise levels
//! the pose-noise sections and plots, with `[anytime]` the trade-off report). `result.json`
//! holds nothing of where or how a task ran (no path, no thread count, no time), so a task
//! gives the same bytes locally and on a cluster; `timing.json` holds the times. A record also
//! keeps the task's settings ([`TaskSettings`]): a record made with settings other than the
//! description asks of its task is refused wherever records are read ([`read_result`]).

use super::{Source, Sweep, Task, TestSet};
use crate::error::{HostError, Result};
use crate::io::{write_atomic, write_png};
use crate::report::{
    ModelOutcome, NoiseLevelResult, PoseErrors, PoseUncertainty, ViewMetrics, format_or_na,
    markdown_table, mean_metrics, pose_noise_sections, side_by_side,
};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A task's record, written last (atomically): its presence marks the task finished.
pub const RESULT: &str = "result.json";
/// How long the task took on what machine: written just before [`RESULT`].
pub const TIMING: &str = "timing.json";
/// The first held-out view as rendered by the task's model.
pub const RENDER: &str = "render.png";
/// The task's trained model (fingerprinted in its record).
pub const CHECKPOINT: &str = "checkpoint.onrf";
/// The task's output (the local runner and the Slurm script both write it there).
pub const LOG: &str = "log.txt";
/// The state of a task still running or killed (every tenth of its steps): running the task
/// again continues from it; removed when the task finishes.
pub const PROGRESS: &str = "progress.onrf";

/// The folder of task `index` under the sweep's output folder `out`.
pub fn task_dir(out: &Path, index: usize) -> PathBuf {
    out.join("tasks").join(index.to_string())
}

/// What one task gave. Non-finite numbers are written as `null` (shown as n/a).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskResult {
    /// The task's index in the sweep (its folder `tasks/<index>`).
    pub index: usize,
    /// The task's name (`level, variant, seed` in words).
    pub name: String,
    /// The variant's name.
    pub variant: String,
    /// The training seed.
    pub seed: u64,
    /// Standard deviation of the label rotation noise, degrees (0: none).
    pub rotation_noise_deg: f32,
    /// Standard deviation of the label position noise per axis, mm (0: none).
    pub translation_noise_mm: f32,
    /// Training steps of the task's config.
    pub steps: u32,
    /// Number of held-out views scored.
    pub held_out_views: usize,
    /// Means over the held-out views.
    pub metrics: Metrics,
    /// The held-out means after each anytime step (`[anytime]`), then at the end.
    #[serde(default)]
    pub curve: Vec<CurveRecord>,
    /// Image size of the task's frames (px, longer side).
    #[serde(default)]
    pub size: u16,
    /// Bytes of the model's arena (its memory plan).
    #[serde(default)]
    pub arena_bytes: u64,
    /// Samples the training rays met in the scene box, over the run.
    #[serde(default)]
    pub samples: u64,
    /// Pose error of the training labels against the exact poses; `None` without exact poses.
    pub pose_before: Option<Poses>,
    /// Pose error of the corrected training labels against the exact poses; `None` without
    /// exact poses.
    pub pose_after: Option<Poses>,
    /// The held-out means with each view at its exact pose; `None` where the data has no
    /// exact poses (`metrics` is at the labels).
    #[serde(default)]
    pub metrics_exact: Option<Metrics>,
    /// The held-out means with each view at its label aligned by the pose refinement;
    /// `None` in records written before it was kept.
    #[serde(default)]
    pub metrics_aligned: Option<Metrics>,
    /// The refined training poses' uncertainty (with pose correction).
    #[serde(default)]
    pub pose_uncertainty: Option<PoseUncertainty>,
    /// FNV-1a (64 bit) of the checkpoint file's bytes, hex.
    pub checkpoint_fnv1a: String,
    /// What the description asked of the task (absent in records written before they were
    /// kept): a finished task is reused only by a description that asks the same.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settings: Option<TaskSettings>,
}

/// The settings a task was trained and scored with, as its record keeps them. No path (a data
/// folder or scene file is kept by its name), so a task still gives the same bytes locally and
/// on a cluster.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskSettings {
    /// `scene <preset or scene file name>` or `data <folder name>`.
    pub source: String,
    /// Frames simulated (a simulated scene only).
    pub frames: Option<u32>,
    /// The separate test set (`scene <name>, <n> frames`), when the task was scored on one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test: Option<String>,
    /// Every N-th view was held out (unused with a separate test set).
    pub holdout: usize,
    /// Steps fitting each held-out view's embedding.
    pub fit_steps: u32,
    /// Whether the foreground masks were applied.
    pub masks: bool,
    /// The description's `scene_box` (min, max), when it gives one.
    pub scene_box: Option<[[f32; 3]; 2]>,
    /// Every field of the task's config, as a config file names it.
    pub config: serde_json::Map<String, serde_json::Value>,
    /// FNV-1a of the simulated scenes' text (the training scene's, then the test scene's),
    /// so a record of a preset or scene file that has changed since is not taken for one of
    /// the current text; `None` for a dataset folder and in records that predate it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scenes_fnv1a: Option<String>,
}

impl TaskSettings {
    /// What `sweep` asks of `task`.
    pub fn of(sweep: &Sweep, task: &Task) -> TaskSettings {
        let name = |p: &Path| {
            p.file_name()
                .map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into())
        };
        // A preset by its name, a scene file by its file name.
        let scene_name = |scene: &str| {
            if crate::sim::scene::preset_names().any(|p| p == scene) {
                scene.to_string()
            } else {
                name(Path::new(scene))
            }
        };
        let (source, frames) = match &sweep.source {
            Source::Scene(scene) => (format!("scene {}", scene_name(scene)), Some(task.frames)),
            Source::Data(data) => (format!("data {}", name(data)), None),
        };
        TaskSettings {
            source,
            frames,
            test: sweep.test.as_ref().map(|test| match test {
                TestSet::Scene { scene, frames } => {
                    format!("scene {}, {frames} frames", scene_name(scene))
                }
                TestSet::Data(data) => format!("data {}", name(data)),
            }),
            holdout: sweep.holdout,
            fit_steps: sweep.fit_steps,
            masks: sweep.masks,
            scene_box: sweep.scene_box.map(|(min, max)| [min, max]),
            config: config_fields(&task.config),
            scenes_fnv1a: scenes_fingerprint(sweep),
        }
    }
}

/// FNV-1a of the text of the sweep's simulated scenes (training, then test); `None` when it
/// simulates none or a scene's text cannot be read (the task reports that itself).
fn scenes_fingerprint(sweep: &Sweep) -> Option<String> {
    let mut texts = Vec::new();
    if let Source::Scene(scene) = &sweep.source {
        texts.push(crate::sim::Scene::text(scene).ok()?);
    }
    if let Some(TestSet::Scene { scene, .. }) = &sweep.test {
        texts.push(crate::sim::Scene::text(scene).ok()?);
    }
    (!texts.is_empty()).then(|| format!("{:016x}", fnv1a(texts.join("\n").as_bytes())))
}

/// The config's fields as the record's JSON holds them (through the text, so that a field
/// read back from a record compares equal).
fn config_fields(config: &orbit_nerf_core::Config) -> serde_json::Map<String, serde_json::Value> {
    serde_json::to_string(config)
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or_default()
}

/// Where a record differs from what the description asks of its task: `(field of the record,
/// recorded, asked)`. Records written before the settings were kept are compared on the fields
/// they hold.
pub fn differences(
    sweep: &Sweep,
    task: &Task,
    record: &TaskResult,
) -> Vec<(String, String, String)> {
    let mut found = Vec::new();
    let mut differ = |field: &str, recorded: String, asked: String| {
        if recorded != asked {
            found.push((field.to_string(), recorded, asked));
        }
    };
    differ("variant", record.variant.clone(), task.variant.clone());
    differ("seed", record.seed.to_string(), task.seed.to_string());
    let (rotation_deg, translation_m) = task
        .noise
        .map_or((0.0, 0.0), |n| (n.rotation_deg, n.translation_m));
    differ(
        "rotation_noise_deg",
        record.rotation_noise_deg.to_string(),
        rotation_deg.to_string(),
    );
    differ(
        "translation_noise_mm",
        record.translation_noise_mm.to_string(),
        (translation_m * 1000.0).to_string(),
    );
    differ(
        "steps",
        record.steps.to_string(),
        task.config.steps.to_string(),
    );
    // Older records hold no size (0).
    if record.size != 0 {
        differ("size", record.size.to_string(), task.size.to_string());
    }
    if !record.curve.is_empty() {
        let asked: Vec<u32> = (sweep.score_at(task).into_iter())
            .chain([task.config.steps])
            .collect();
        let recorded: Vec<u32> = record.curve.iter().map(|p| p.step).collect();
        differ(
            "curve[].step",
            format!("{recorded:?}"),
            format!("{asked:?}"),
        );
    }
    if let Some(settings) = &record.settings {
        let asked = TaskSettings::of(sweep, task);
        differ(
            "settings.source",
            settings.source.clone(),
            asked.source.clone(),
        );
        let frames = |f: Option<u32>| f.map_or("none".into(), |f| f.to_string());
        differ(
            "settings.frames",
            frames(settings.frames),
            frames(asked.frames),
        );
        let test = |t: &Option<String>| t.clone().unwrap_or_else(|| "none".into());
        differ("settings.test", test(&settings.test), test(&asked.test));
        differ(
            "settings.holdout",
            settings.holdout.to_string(),
            asked.holdout.to_string(),
        );
        differ(
            "settings.fit_steps",
            settings.fit_steps.to_string(),
            asked.fit_steps.to_string(),
        );
        differ(
            "settings.masks",
            settings.masks.to_string(),
            asked.masks.to_string(),
        );
        // Records from before the fingerprint are compared on the scene's name alone.
        if let (Some(recorded), Some(asked)) = (&settings.scenes_fnv1a, &asked.scenes_fnv1a) {
            differ(
                "settings.scenes_fnv1a (the scene's text has changed)",
                recorded.clone(),
                asked.clone(),
            );
        }
        let scene_box = |b: Option<[[f32; 3]; 2]>| b.map_or("none".into(), |b| format!("{b:?}"));
        differ(
            "settings.scene_box",
            scene_box(settings.scene_box),
            scene_box(asked.scene_box),
        );
        let keys: std::collections::BTreeSet<&String> =
            settings.config.keys().chain(asked.config.keys()).collect();
        let value = |v: Option<&serde_json::Value>| v.map_or("none".into(), |v| v.to_string());
        for key in keys {
            differ(
                &format!("settings.config.{key}"),
                value(settings.config.get(key)),
                value(asked.config.get(key)),
            );
        }
    }
    found
}

/// Refuse a record `differences` finds differing from what `sweep` asks of `task`: the error
/// names the record file and every differing field.
fn check_settings(path: &Path, sweep: &Sweep, task: &Task, record: &TaskResult) -> Result<()> {
    let found = differences(sweep, task, record);
    let Some((field, recorded, asked)) = found.first() else {
        return Ok(());
    };
    let description = sweep.origin.display();
    let mut reason = format!(
        "recorded {recorded}, but {description} asks {asked} of task {} ({})",
        task.index, task.name
    );
    if found.len() > 1 {
        let others: Vec<String> = (found[1..].iter())
            .map(|(f, r, a)| format!("`{f}` ({r}, not {a})"))
            .collect();
        reason.push_str(&format!("; also {}", others.join(", ")));
    }
    reason.push_str(&format!(
        ". The folder holds another description's results, which are neither mixed in nor replaced: give {description} another --out (or run the description these records were made with)"
    ));
    Err(HostError::field(path, field.clone(), reason))
}

/// A point of a task's anytime curve: the held-out means after `step` steps.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurveRecord {
    /// Training steps taken.
    pub step: u32,
    /// The held-out views' means at that step, at their labels.
    pub metrics: Metrics,
}

/// A task's times: the training seconds at each point of its curve (scoring left out), and
/// the machine.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskTiming {
    /// The task's index in the sweep (as in its [`TaskResult`]).
    pub index: usize,
    /// The task's name (as in its [`TaskResult`]).
    pub name: String,
    /// Training seconds at each curve point (as `TaskResult::curve`), the last the whole run.
    pub seconds: Vec<f64>,
    /// Worker threads the task trained with.
    pub threads: usize,
    /// The machine's CPU model and caches ("unknown" where they cannot be read).
    pub cpu: String,
}

/// [`ViewMetrics`] as stored.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Metrics {
    /// PSNR of the whole image, dB; `None` (`null`) where not finite, as for every field here.
    pub psnr_full: Option<f64>,
    /// PSNR of the right half, dB.
    pub psnr_right: Option<f64>,
    /// PSNR over the target pixels of the whole image, dB.
    pub psnr_foreground: Option<f64>,
    /// PSNR over the target pixels of the right half, dB.
    pub psnr_foreground_right: Option<f64>,
    /// SSIM of the whole image, at most 1.
    pub ssim_full: Option<f64>,
    /// SSIM of the right half, at most 1.
    pub ssim_right: Option<f64>,
    /// JNB blur per edge of the whole image (lower is sharper).
    pub jnb_full: Option<f64>,
    /// JNB blur per edge of the right half (lower is sharper).
    pub jnb_right: Option<f64>,
    /// CPBD of the whole image, 0 to 1 (higher is sharper); absent in records written
    /// before CPBD was reported.
    #[serde(default)]
    pub cpbd_full: Option<f64>,
}

/// [`PoseErrors`] as stored.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Poses {
    /// Mean rotation error, degrees; `None` (`null`) where not finite, as for every error here.
    pub rotation_deg_mean: Option<f64>,
    /// Median rotation error, degrees.
    pub rotation_deg_median: Option<f64>,
    /// Mean camera-centre distance, dataset units (metres for the simulator and SPEED+/SHIRT).
    pub translation_mean: Option<f64>,
    /// Median camera-centre distance, dataset units.
    pub translation_median: Option<f64>,
    /// Mean rotation error about the optical axis, degrees.
    pub about_view_axis_deg_mean: Option<f64>,
    /// Mean rotation error across the optical axis, degrees.
    pub across_view_axis_deg_mean: Option<f64>,
    /// Number of frames compared.
    pub frames: usize,
}

fn stored(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

fn loaded(v: Option<f64>) -> f64 {
    v.unwrap_or(f64::NAN)
}

impl From<ViewMetrics> for Metrics {
    fn from(m: ViewMetrics) -> Self {
        Metrics {
            psnr_full: stored(m.psnr_full),
            psnr_right: stored(m.psnr_right),
            psnr_foreground: stored(m.psnr_foreground),
            psnr_foreground_right: stored(m.psnr_foreground_right),
            ssim_full: stored(m.ssim_full),
            ssim_right: stored(m.ssim_right),
            jnb_full: stored(m.jnb_full),
            jnb_right: stored(m.jnb_right),
            cpbd_full: stored(m.cpbd_full),
        }
    }
}

impl From<Metrics> for ViewMetrics {
    fn from(m: Metrics) -> Self {
        ViewMetrics {
            psnr_full: loaded(m.psnr_full),
            psnr_right: loaded(m.psnr_right),
            psnr_foreground: loaded(m.psnr_foreground),
            psnr_foreground_right: loaded(m.psnr_foreground_right),
            ssim_full: loaded(m.ssim_full),
            ssim_right: loaded(m.ssim_right),
            jnb_full: loaded(m.jnb_full),
            jnb_right: loaded(m.jnb_right),
            cpbd_full: loaded(m.cpbd_full),
        }
    }
}

impl From<PoseErrors> for Poses {
    fn from(e: PoseErrors) -> Self {
        Poses {
            rotation_deg_mean: stored(e.rotation_deg_mean),
            rotation_deg_median: stored(e.rotation_deg_median),
            translation_mean: stored(e.translation_mean),
            translation_median: stored(e.translation_median),
            about_view_axis_deg_mean: stored(e.about_view_axis_deg_mean),
            across_view_axis_deg_mean: stored(e.across_view_axis_deg_mean),
            frames: e.frames,
        }
    }
}

impl From<Poses> for PoseErrors {
    fn from(e: Poses) -> Self {
        PoseErrors {
            rotation_deg_mean: loaded(e.rotation_deg_mean),
            rotation_deg_median: loaded(e.rotation_deg_median),
            translation_mean: loaded(e.translation_mean),
            translation_median: loaded(e.translation_median),
            about_view_axis_deg_mean: loaded(e.about_view_axis_deg_mean),
            across_view_axis_deg_mean: loaded(e.across_view_axis_deg_mean),
            frames: e.frames,
        }
    }
}

/// FNV-1a, 64 bit: the checkpoint fingerprint of the records.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    fnv1a_on(FNV1A_OFFSET, bytes)
}

const FNV1A_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// FNV-1a continued from `hash` over `bytes`.
fn fnv1a_on(hash: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(hash, |hash, &b| {
        (hash ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// [`fnv1a`] of the file at `path`, read a buffer at a time (no copy of a model in memory).
pub fn fnv1a_file(path: &Path) -> Result<u64> {
    use std::io::Read;
    let mut file = std::fs::File::open(path).map_err(|e| HostError::io(path, e))?;
    let mut buffer = vec![0u8; 1 << 20];
    let mut hash = FNV1A_OFFSET;
    loop {
        let n = file.read(&mut buffer).map_err(|e| HostError::io(path, e))?;
        if n == 0 {
            return Ok(hash);
        }
        hash = fnv1a_on(hash, &buffer[..n]);
    }
}

/// Write `result` as [`RESULT`] (pretty JSON) into its task's folder under `out`,
/// atomically: the mark that the task is finished.
pub fn write_result(out: &Path, result: &TaskResult) -> Result<()> {
    let path = task_dir(out, result.index).join(RESULT);
    let mut text = serde_json::to_string_pretty(result)
        .map_err(|e| HostError::invalid(&path, format!("encoding failed: {e}")))?;
    text.push('\n');
    write_atomic(&path, text.as_bytes())
}

/// Write `timing` as [`TIMING`] (pretty JSON) into its task's folder under `out`, atomically.
pub fn write_timing(out: &Path, timing: &TaskTiming) -> Result<()> {
    let path = task_dir(out, timing.index).join(TIMING);
    let mut text = serde_json::to_string_pretty(timing)
        .map_err(|e| HostError::invalid(&path, format!("encoding failed: {e}")))?;
    text.push('\n');
    write_atomic(&path, text.as_bytes())
}

/// Task `task`'s timing record under `out` (of a finished task), checked against its result:
/// one time per curve point.
pub fn read_timing(out: &Path, task: &Task, result: &TaskResult) -> Result<TaskTiming> {
    let path = task_dir(out, task.index).join(TIMING);
    let text = std::fs::read_to_string(&path).map_err(|e| HostError::io(&path, e))?;
    let timing: TaskTiming = serde_json::from_str(&text)
        .map_err(|e| HostError::invalid(&path, format!("not a task timing record: {e}")))?;
    if timing.index != task.index || timing.name != task.name {
        return Err(HostError::invalid(
            &path,
            format!("holds task `{}`, not `{}`", timing.name, task.name),
        ));
    }
    if timing.seconds.len() != result.curve.len()
        || timing.seconds.iter().any(|s| !(s.is_finite() && *s >= 0.0))
    {
        return Err(HostError::invalid(
            &path,
            format!(
                "`seconds` must hold {} finite times, one per point of the task's curve",
                result.curve.len()
            ),
        ));
    }
    Ok(timing)
}

/// Task `task` of `sweep`: its record under `out`, `None` when the task has not finished; an
/// error when the record is unreadable, belongs to another task or was made with other
/// settings than `sweep` asks of the task (another description wrote into `out`).
pub fn read_result(sweep: &Sweep, out: &Path, task: &Task) -> Result<Option<TaskResult>> {
    let path = task_dir(out, task.index).join(RESULT);
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(HostError::io(&path, e)),
    };
    let result: TaskResult = serde_json::from_str(&text)
        .map_err(|e| HostError::invalid(&path, format!("not a task record: {e}")))?;
    if result.index != task.index || result.name != task.name {
        return Err(HostError::invalid(
            &path,
            format!(
                "holds task `{}`, but task {} of this description is `{}`: the folder belongs to another sweep",
                result.name, task.index, task.name
            ),
        ));
    }
    check_settings(&path, sweep, task, &result)?;
    Ok(Some(result))
}

/// Indices of the tasks without a record under `out`: not run yet, failed or running.
pub fn unfinished(sweep: &Sweep, out: &Path) -> Result<Vec<usize>> {
    let mut missing = Vec::new();
    for task in &sweep.tasks {
        if read_result(sweep, out, task)?.is_none() {
            missing.push(task.index);
        }
    }
    Ok(missing)
}

/// Merge every task's record under `out` into `sweep.csv`, `sweep.md` and `renders.png` (and
/// with noise levels the pose-noise sections and their plots); returns the markdown. Errors
/// naming the unfinished tasks and their logs when any is.
pub fn collect(sweep: &Sweep, out: &Path) -> Result<String> {
    if !out.is_dir() {
        let what = if out.exists() {
            "is not a folder"
        } else {
            "no such folder"
        };
        return Err(HostError::invalid(
            out,
            format!(
                "{what}: there is no sweep to collect here; run {} into it first (`orbit-nerf sweep run` or `sweep slurm` with this --out)",
                sweep.origin.display()
            ),
        ));
    }
    let mut results = Vec::new();
    let mut missing = Vec::new();
    for task in &sweep.tasks {
        match read_result(sweep, out, task)? {
            Some(result) => results.push(result),
            None => missing.push(task.index),
        }
    }
    if !missing.is_empty() {
        // Only the logs that exist: a task never started has none.
        let logs: Vec<String> = (missing.iter())
            .map(|&i| task_dir(out, i).join(LOG))
            .filter(|log| log.is_file())
            .take(5)
            .map(|log| log.display().to_string())
            .collect();
        let logs = if logs.is_empty() {
            "none of them has a log (never started)".to_string()
        } else {
            format!("their logs: {}", logs.join(", "))
        };
        return Err(HostError::invalid(
            out,
            format!(
                "{} of {} tasks have no result (indices {}); {logs}",
                missing.len(),
                sweep.tasks.len(),
                array_spec(&missing),
            ),
        ));
    }
    write_atomic(&out.join("sweep.csv"), csv(&results).as_bytes())?;
    let mut text = format!(
        "# Sweep `{}` on `{}`\n\n{}, {}, {} steps per model, held-out embeddings fitted for {} steps; {} tasks. JNB: paper variant, lower is sharper. Pose errors: mean over the training frames, against the exact poses.\n\n",
        sweep
            .origin
            .file_name()
            .unwrap_or_default()
            .to_string_lossy(),
        match &sweep.source {
            Source::Scene(scene) => scene.clone(),
            Source::Data(data) => data
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into(),
        },
        match &sweep.source {
            Source::Scene(_) => format!(
                "{} frames of {} px",
                (sweep.frames.iter().map(u32::to_string))
                    .collect::<Vec<_>>()
                    .join(", "),
                sweep.size
            ),
            Source::Data(_) => format!("{} px", sweep.size),
        },
        match &sweep.test {
            Some(TestSet::Scene { scene, frames }) => format!(
                "trained on every frame and scored on the {frames} views of the separate test set `{scene}` (exact poses)"
            ),
            Some(TestSet::Data(data)) => format!(
                "trained on every frame and scored on every view of the separate test set `{}`",
                data.file_name().unwrap_or_default().to_string_lossy()
            ),
            None => format!("every {}th view held out", sweep.holdout),
        },
        sweep.base.steps,
        sweep.fit_steps,
        results.len()
    );
    text.push_str(&table(
        &results,
        !sweep.rotation.is_empty() || !sweep.translation.is_empty(),
        sweep.frames.len() > 1,
    ));
    if sweep.frames.len() > 1 {
        text.push_str(&image_count_section(sweep, &results, out)?);
    }
    if write_renders(sweep, out)? {
        text.push_str("\n## First held-out view, every task\n\n![renders](renders.png)\n");
    }
    let levels = noise_levels(sweep, &results);
    if !levels.is_empty() {
        if sweep.tasks.iter().any(|t| t.seed != sweep.tasks[0].seed) {
            text.push_str("\nThe pose-noise tables and plots show the mean over the seeds.\n");
        }
        text.push_str(&pose_noise_sections(
            out,
            &sweep.rotation,
            &sweep.translation,
            &levels,
        )?);
    }
    if let Some(anytime) = &sweep.anytime {
        let mut timings = Vec::with_capacity(results.len());
        for (task, result) in sweep.tasks.iter().zip(&results) {
            timings.push(read_timing(out, task, result)?);
        }
        text.push_str(&super::tradeoff::report(
            sweep, anytime, &results, &timings, out,
        )?);
    }
    write_atomic(&out.join("sweep.md"), text.as_bytes())?;
    Ok(text)
}

/// A stored number with `decimals` decimals, `n/a` where none.
pub(super) fn fixed(value: Option<f64>, decimals: usize) -> String {
    format_or_na(loaded(value), decimals)
}

fn pose_pair(
    before: Option<Poses>,
    after: Option<Poses>,
    f: fn(&Poses) -> Option<f64>,
    scale: f64,
) -> String {
    match (before, after) {
        (Some(b), Some(a)) => format!(
            "{} / {}",
            format_or_na(loaded(f(&b)) * scale, 3),
            format_or_na(loaded(f(&a)) * scale, 3)
        ),
        _ => "n/a".into(),
    }
}

/// A metric of the image-count study: file stem, label, the stored mean, decimals.
type StudyMetric = (
    &'static str,
    &'static str,
    fn(&Metrics) -> Option<f64>,
    usize,
);

/// The heading of the image-count section (`paper.md` takes the section by it).
pub const IMAGE_COUNT_TITLE: &str = "Image-count study";

/// The image-count study: per frame count and variant, the held-out PSNR, SSIM and JNB
/// (means over the seeds) as a table laid out like the paper's, and their plots against the
/// count (`image_counts_<metric>.png` in `out`).
fn image_count_section(sweep: &Sweep, results: &[TaskResult], out: &Path) -> Result<String> {
    let mut variants: Vec<&str> = Vec::new();
    for task in &sweep.tasks {
        if !variants.contains(&task.variant.as_str()) {
            variants.push(&task.variant);
        }
    }
    let mean = |count: u32, variant: &str, f: fn(&Metrics) -> Option<f64>| {
        let values: Vec<f64> = (sweep.tasks.iter().zip(results))
            .filter(|(t, _)| t.frames == count && t.variant == variant)
            .map(|(_, r)| loaded(f(&r.metrics)))
            .collect();
        values.iter().sum::<f64>() / values.len().max(1) as f64
    };
    let metrics: [StudyMetric; 3] = [
        ("psnr", "PSNR (dB)", |m| m.psnr_full, 2),
        ("ssim", "SSIM", |m| m.ssim_full, 4),
        ("jnb", "JNB (lower is sharper)", |m| m.jnb_full, 4),
    ];
    let mut header = vec!["training images".to_string()];
    for variant in &variants {
        header.extend(
            metrics
                .iter()
                .map(|(_, label, _, _)| format!("{variant}: {label}")),
        );
    }
    let rows: Vec<Vec<String>> = (sweep.frames.iter())
        .map(|&count| {
            let mut row = vec![count.to_string()];
            for variant in &variants {
                row.extend(
                    (metrics.iter()).map(|&(_, _, f, d)| format_or_na(mean(count, variant, f), d)),
                );
            }
            row
        })
        .collect();
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut text = format!("\n## {IMAGE_COUNT_TITLE}\n\n");
    text.push_str(&markdown_table(&header, &rows));
    for (name, label, f, _) in metrics {
        let series: Vec<(&str, Vec<(f64, f64)>)> = (variants.iter())
            .map(|&variant| {
                let points = (sweep.frames.iter())
                    .map(|&count| (count as f64, mean(count, variant, f)))
                    .collect();
                (variant, points)
            })
            .collect();
        let file = format!("image_counts_{name}.png");
        crate::report::line_plot(
            &out.join(&file),
            &format!("{label} against the training images"),
            "training images",
            label,
            &series,
        )?;
        text.push_str(&format!("\n![{label}]({file})\n"));
    }
    Ok(text)
}

/// The markdown table: a row per task (with its frame count when the sweep has several).
fn table(results: &[TaskResult], noise: bool, counts: bool) -> String {
    let mut header = vec!["task", "variant", "seed"];
    if counts {
        header.push("frames");
    }
    if noise {
        header.extend(["rot. noise deg", "pos. noise mm"]);
    }
    header.extend([
        "PSNR dB",
        "right dB",
        "fg dB",
        "SSIM",
        "JNB",
        "PSNR exact / aligned dB",
        "rot. error labels / corrected deg",
        "position error labels / corrected mm",
        "1-sigma rot. deg / pos. mm",
        "within 3 sigma rot. / pos.",
        "checkpoint fnv1a",
    ]);
    let rows: Vec<Vec<String>> = results
        .iter()
        .map(|r| {
            let mut row = vec![r.index.to_string(), r.variant.clone(), r.seed.to_string()];
            if counts {
                let frames = r.settings.as_ref().and_then(|s| s.frames);
                row.push(frames.map_or("n/a".into(), |f| f.to_string()));
            }
            if noise {
                row.push(r.rotation_noise_deg.to_string());
                row.push(r.translation_noise_mm.to_string());
            }
            let m = &r.metrics;
            row.extend([
                fixed(m.psnr_full, 2),
                fixed(m.psnr_right, 2),
                fixed(m.psnr_foreground, 2),
                fixed(m.ssim_full, 4),
                fixed(m.jnb_full, 4),
                format!(
                    "{} / {}",
                    fixed(r.metrics_exact.and_then(|m| m.psnr_full), 2),
                    fixed(r.metrics_aligned.and_then(|m| m.psnr_full), 2)
                ),
                pose_pair(r.pose_before, r.pose_after, |p| p.rotation_deg_mean, 1.0),
                pose_pair(r.pose_before, r.pose_after, |p| p.translation_mean, 1000.0),
                match r.pose_uncertainty {
                    Some(u) => format!(
                        "{} / {}",
                        fixed(u.rotation_sigma_deg_mean, 3),
                        fixed(u.position_sigma_mean.map(|v| v * 1000.0), 1)
                    ),
                    None => "n/a".into(),
                },
                match r.pose_uncertainty {
                    Some(u) => format!(
                        "{} / {}",
                        fixed(u.rotation_within_3_sigma, 2),
                        fixed(u.position_within_3_sigma, 2)
                    ),
                    None => "n/a".into(),
                },
                r.checkpoint_fnv1a.clone(),
            ]);
            row
        })
        .collect();
    markdown_table(&header, &rows)
}

/// The CSV header of [`metric_cells`].
pub const METRICS_CSV_HEADER: &str = "psnr_full,psnr_right,psnr_foreground,psnr_foreground_right,ssim_full,ssim_right,jnb_full,jnb_right";

/// The stored metrics as CSV cells (empty where n/a), in [`METRICS_CSV_HEADER`]'s order.
pub fn metric_cells(m: &Metrics) -> [String; 8] {
    [
        m.psnr_full,
        m.psnr_right,
        m.psnr_foreground,
        m.psnr_foreground_right,
        m.ssim_full,
        m.ssim_right,
        m.jnb_full,
        m.jnb_right,
    ]
    .map(|v| v.map_or(String::new(), |v| v.to_string()))
}

/// The CSV: a row per task, every stored number (empty where n/a).
fn csv(results: &[TaskResult]) -> String {
    let number = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
    let poses = |p: Option<Poses>| -> [String; 4] {
        match p {
            Some(p) => [
                number(p.rotation_deg_mean),
                number(p.about_view_axis_deg_mean),
                number(p.across_view_axis_deg_mean),
                number(p.translation_mean),
            ],
            None => Default::default(),
        }
    };
    let mut text = format!(
        "index,name,variant,seed,rotation_noise_deg,translation_noise_mm,steps,held_out_views,{METRICS_CSV_HEADER},labels_rotation_deg,labels_about_view_axis_deg,labels_across_view_axis_deg,labels_position_m,corrected_rotation_deg,corrected_about_view_axis_deg,corrected_across_view_axis_deg,corrected_position_m,checkpoint_fnv1a\n",
    );
    for r in results {
        let m = &r.metrics;
        let cells: Vec<String> = [
            r.index.to_string(),
            format!("\"{}\"", r.name),
            format!("\"{}\"", r.variant),
            r.seed.to_string(),
            r.rotation_noise_deg.to_string(),
            r.translation_noise_mm.to_string(),
            r.steps.to_string(),
            r.held_out_views.to_string(),
        ]
        .into_iter()
        .chain(metric_cells(m))
        .chain(poses(r.pose_before))
        .chain(poses(r.pose_after))
        .chain([r.checkpoint_fnv1a.clone()])
        .collect();
        text.push_str(&cells.join(","));
        text.push('\n');
    }
    text
}

/// `renders.png`: every task's first held-out view side by side, captioned with the task's
/// index and variant; false (and nothing written) when the tasks' renders differ in size.
fn write_renders(sweep: &Sweep, out: &Path) -> Result<bool> {
    let mut images = Vec::new();
    for task in &sweep.tasks {
        let path = task_dir(out, task.index).join(RENDER);
        let image = image::open(&path)
            .map_err(|e| HostError::invalid(&path, format!("not a readable PNG: {e}")))?
            .to_rgb8();
        images.push((format!("{}: {}", task.index, task.variant), image));
    }
    let Some((_, first)) = images.first() else {
        return Ok(false);
    };
    let (w, h) = first.dimensions();
    if images.iter().any(|(_, image)| image.dimensions() != (w, h)) {
        return Ok(false);
    }
    let tiles: Vec<(&str, &[u8])> = (images.iter())
        .map(|(label, image)| (label.as_str(), image.as_raw().as_slice()))
        .collect();
    let (sw, sh, strip) = side_by_side(&tiles, w, h);
    write_png(&out.join("renders.png"), sw, sh, 3, &strip)?;
    Ok(true)
}

/// Per noise level, the means over the seeds of `ours` and `ours + pose` (the pose-noise
/// report's two models); empty when the sweep has no noise levels or lacks either model.
fn noise_levels(sweep: &Sweep, results: &[TaskResult]) -> Vec<NoiseLevelResult> {
    let (ours, pose) = (
        crate::ablation::APPEARANCE.name,
        crate::ablation::APPEARANCE_POSE.name,
    );
    let mut levels: Vec<NoiseLevelResult> = Vec::new();
    for task in &sweep.tasks {
        let Some(noise) = task.noise else {
            return Vec::new();
        };
        if levels.iter().any(|l| l.noise == noise) {
            continue;
        }
        let outcome = |variant: &str| -> Option<ModelOutcome> {
            let runs: Vec<&TaskResult> = (sweep.tasks.iter().zip(results))
                .filter(|(t, _)| t.noise == Some(noise) && t.variant == variant)
                .map(|(_, r)| r)
                .collect();
            if runs.is_empty() {
                return None;
            }
            let metrics: Vec<ViewMetrics> = runs.iter().map(|r| r.metrics.into()).collect();
            let mean_poses = |f: fn(&TaskResult) -> Option<Poses>| -> Option<PoseErrors> {
                let all: Vec<PoseErrors> = runs
                    .iter()
                    .filter_map(|r| f(r))
                    .map(PoseErrors::from)
                    .collect();
                (all.len() == runs.len()).then(|| mean_pose_errors(&all))
            };
            let mean_of = |f: fn(&TaskResult) -> Option<Metrics>| -> Option<ViewMetrics> {
                let all: Vec<ViewMetrics> =
                    runs.iter().filter_map(|r| f(r)).map(Into::into).collect();
                (all.len() == runs.len()).then(|| mean_metrics(&all))
            };
            Some(ModelOutcome {
                metrics: mean_metrics(&metrics),
                metrics_exact: mean_of(|r| r.metrics_exact),
                metrics_aligned: mean_of(|r| r.metrics_aligned),
                pose_before: mean_poses(|r| r.pose_before),
                pose_after: mean_poses(|r| r.pose_after),
            })
        };
        match (outcome(ours), outcome(pose)) {
            (Some(ours), Some(pose)) => levels.push(NoiseLevelResult { noise, ours, pose }),
            _ => return Vec::new(),
        }
    }
    levels
}

/// Field-wise mean of non-empty `errors`.
fn mean_pose_errors(errors: &[PoseErrors]) -> PoseErrors {
    let mean = |f: fn(&PoseErrors) -> f64| errors.iter().map(f).sum::<f64>() / errors.len() as f64;
    PoseErrors {
        rotation_deg_mean: mean(|e| e.rotation_deg_mean),
        rotation_deg_median: mean(|e| e.rotation_deg_median),
        translation_mean: mean(|e| e.translation_mean),
        translation_median: mean(|e| e.translation_median),
        about_view_axis_deg_mean: mean(|e| e.about_view_axis_deg_mean),
        across_view_axis_deg_mean: mean(|e| e.across_view_axis_deg_mean),
        frames: errors[0].frames,
    }
}

/// Indices as a Slurm `--array` list: runs of consecutive indices as ranges (`0-3,5,7-8`).
pub fn array_spec(indices: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < indices.len() {
        let start = indices[i];
        let mut end = start;
        while i + 1 < indices.len() && indices[i + 1] == end + 1 {
            i += 1;
            end += 1;
        }
        parts.push(if end == start {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        i += 1;
    }
    parts.join(",")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_lists_compress_runs_into_ranges() {
        assert_eq!(array_spec(&[]), "");
        assert_eq!(array_spec(&[4]), "4");
        assert_eq!(array_spec(&[0, 1, 2, 3, 5, 7, 8]), "0-3,5,7-8");
        assert_eq!(array_spec(&[1, 3]), "1,3");
    }

    #[test]
    fn records_keep_non_finite_numbers_as_null_and_read_back_equal() {
        let metrics = ViewMetrics {
            psnr_right: 30.5,
            ssim_right: 0.9,
            jnb_right: f64::NAN,
            psnr_full: 29.25,
            ssim_full: f64::NAN,
            jnb_full: 1.5,
            psnr_foreground: 20.0,
            psnr_foreground_right: 21.0,
            cpbd_full: 0.5,
        };
        let stored = Metrics::from(metrics);
        let text = serde_json::to_string(&stored).unwrap();
        assert!(text.contains("\"ssim_full\":null"), "{text}");
        let back: Metrics = serde_json::from_str(&text).unwrap();
        assert_eq!(back, stored);
        let loaded = ViewMetrics::from(back);
        assert!(loaded.ssim_full.is_nan() && loaded.jnb_right.is_nan());
        assert_eq!(loaded.psnr_full, 29.25);
    }

    /// A sweep of one task from `text`, with `description` as its file name.
    fn sweep_of(dir: &Path, text: &str) -> Sweep {
        Sweep::parse(&dir.join("sweep.toml"), text).unwrap()
    }

    /// The record `sweep`'s first task writes (its figures left out).
    fn record_of(sweep: &Sweep) -> TaskResult {
        let task = &sweep.tasks[0];
        let none = Metrics {
            psnr_full: None,
            psnr_right: None,
            psnr_foreground: None,
            psnr_foreground_right: None,
            ssim_full: None,
            ssim_right: None,
            jnb_full: None,
            jnb_right: None,
            cpbd_full: None,
        };
        TaskResult {
            index: task.index,
            name: task.name.clone(),
            variant: task.variant.clone(),
            seed: task.seed,
            rotation_noise_deg: 0.0,
            translation_noise_mm: 0.0,
            steps: task.config.steps,
            held_out_views: 2,
            metrics: none,
            curve: (sweep.score_at(task).into_iter())
                .chain([task.config.steps])
                .map(|step| CurveRecord {
                    step,
                    metrics: none,
                })
                .collect(),
            size: task.size,
            arena_bytes: 0,
            samples: 0,
            pose_before: None,
            pose_after: None,
            metrics_exact: None,
            metrics_aligned: None,
            pose_uncertainty: None,
            checkpoint_fnv1a: "0".into(),
            settings: Some(TaskSettings::of(sweep, task)),
        }
    }

    const ONE_TASK: &str = "scene = \"synthetic\"\nframes = 8\nsize = 32\nconfig = \"tiny\"\nsteps = 4\nholdout = 4\n[[variants]]\nname = \"a\"\nset = { embedding_dim = 0 }\n";

    #[test]
    fn a_record_made_with_other_settings_is_refused_naming_the_file_and_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let sweep = sweep_of(dir.path(), ONE_TASK);
        std::fs::create_dir_all(task_dir(&out, 0)).unwrap();
        write_result(&out, &record_of(&sweep)).unwrap();
        let path = task_dir(&out, 0).join(RESULT);
        let before = std::fs::read(&path).unwrap();
        let task = &sweep.tasks[0];
        assert_eq!(
            read_result(&sweep, &out, task).unwrap(),
            Some(record_of(&sweep))
        );
        for (change, field) in [
            (("steps = 4", "steps = 6"), "steps"),
            (("size = 32", "size = 48"), "size"),
            (("holdout = 4", "holdout = 2"), "settings.holdout"),
            (("frames = 8", "frames = 16"), "settings.frames"),
            (("\"synthetic\"", "\"lightbox\""), "settings.source"),
            (
                ("embedding_dim = 0", "embedding_dim = 0, features = 16"),
                "settings.config.features",
            ),
            (
                ("steps = 4\n", "steps = 4\nfit_steps = 3\n"),
                "settings.fit_steps",
            ),
            (
                ("steps = 4\n", "steps = 4\nmasks = false\n"),
                "settings.masks",
            ),
            (
                ("[[variants]]", "[anytime]\nsteps = [2]\n[[variants]]"),
                "curve[].step",
            ),
        ] {
            let text = ONE_TASK.replace(change.0, change.1);
            assert_ne!(text, ONE_TASK);
            let other = sweep_of(dir.path(), &text);
            let error = read_result(&other, &out, &other.tasks[0])
                .unwrap_err()
                .to_string();
            assert!(
                error.starts_with(&path.display().to_string())
                    && error.contains(&format!("field `{field}`"))
                    && error.contains("another --out"),
                "{field}: {error}"
            );
            // Every reader refuses it: the local runner's, the Slurm script's and collect.
            assert!(unfinished(&other, &out).is_err(), "{field}");
            assert!(collect(&other, &out).is_err(), "{field}");
        }
        assert_eq!(
            std::fs::read(&path).unwrap(),
            before,
            "the record was changed"
        );
        assert!(!out.join("sweep.md").exists());

        // A record written before the settings were kept is compared on what it holds.
        let mut old = record_of(&sweep);
        (old.settings, old.size, old.curve) = (None, 0, Vec::new());
        write_result(&out, &old).unwrap();
        let holdout = sweep_of(dir.path(), &ONE_TASK.replace("holdout = 4", "holdout = 2"));
        assert!(
            read_result(&holdout, &out, &holdout.tasks[0])
                .unwrap()
                .is_some()
        );
        let steps = sweep_of(dir.path(), &ONE_TASK.replace("steps = 4", "steps = 6"));
        let error = read_result(&steps, &out, &steps.tasks[0])
            .unwrap_err()
            .to_string();
        assert!(error.contains("field `steps`: recorded 4"), "{error}");
    }

    #[test]
    fn collecting_a_missing_folder_says_so_and_names_no_log() {
        let dir = tempfile::tempdir().unwrap();
        let sweep = sweep_of(dir.path(), ONE_TASK);
        let out = dir.path().join("no-such-run");
        let error = collect(&sweep, &out).unwrap_err().to_string();
        assert!(
            error.starts_with(&out.display().to_string()) && error.contains("no such folder"),
            "{error}"
        );
        assert!(!error.contains(LOG) && !out.exists(), "{error}");
        // A folder whose tasks never started names no log either.
        std::fs::create_dir_all(&out).unwrap();
        let error = collect(&sweep, &out).unwrap_err().to_string();
        assert!(
            error.contains("1 of 1 tasks have no result") && !error.contains(LOG),
            "{error}"
        );
    }

    #[test]
    fn fnv1a_is_the_reference_hash() {
        // Reference values of FNV-1a 64.
        assert_eq!(fnv1a(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("large");
        let bytes: Vec<u8> = (0..3_000_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(fnv1a_file(&path).unwrap(), fnv1a(&bytes));
    }
}
