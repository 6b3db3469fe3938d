//! Running a sweep's tasks: one task trained and scored into `<out>/tasks/<index>/`
//! ([`run_task`], what each process of `sweep run` and each Slurm array task does), the
//! unfinished tasks as child processes of this machine ([`run_local`]); `slurm::submit` runs
//! them as a Slurm job array. Every line worth showing goes to the caller's `say`.

use super::results::{
    self, CHECKPOINT, CurveRecord, LOG, PROGRESS, RENDER, TaskResult, TaskSettings, TaskTiming,
    array_spec, fnv1a_file, read_result, task_dir, unfinished, write_timing,
};
use super::{Source, Sweep, Task, TestSet};
use crate::ablation::{Experiment, Progress};
use crate::ablation_report::{load, simulated};
use crate::dataset::{split_every, with_test_set};
use crate::error::{HostError, Result};
use crate::io::{check_output_folder, write_png};
use crate::sim::scene::LabelNoise;
use crate::train::to_rgb8;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Largest number of parallel tasks or threads per task accepted.
pub const MAX_WORKERS: usize = 1024;

/// `value` of the flag `flag` (named in the error) if it is 1 to [`MAX_WORKERS`].
pub fn check_workers(flag: &str, value: usize) -> Result<usize> {
    if (1..=MAX_WORKERS).contains(&value) {
        Ok(value)
    } else {
        Err(HostError::invalid(
            flag,
            format!("{value} is not between 1 and {MAX_WORKERS}"),
        ))
    }
}

/// What became of one task.
#[derive(Debug, PartialEq)]
pub enum TaskOutcome {
    /// It had a result from an earlier run: nothing was done.
    FinishedEarlier,
    /// Trained and scored; its result file.
    Done(PathBuf),
    /// Stopped at `--stop-after` with its state saved (the error says where).
    Stopped(String),
}

/// Train and score task `index` of the description at `description` into
/// `<out>/tasks/<index>/` (nothing when it already has a result), with `threads` workers,
/// stopping after step `stop_after` when given (its state kept to continue from).
pub fn run_task(
    description: &Path,
    index: usize,
    out: &Path,
    threads: usize,
    stop_after: Option<u32>,
    say: &mut dyn FnMut(String),
) -> Result<TaskOutcome> {
    let threads = check_workers("--threads", threads)?;
    let sweep = Sweep::read(description)?;
    let Some(task) = sweep.tasks.get(index) else {
        return Err(HostError::invalid(
            description,
            format!(
                "task {index}: the description has {} tasks (0 to {})",
                sweep.tasks.len(),
                sweep.tasks.len().saturating_sub(1)
            ),
        ));
    };
    check_output_folder(out)?;
    if read_result(&sweep, out, task)?.is_some() {
        return Ok(TaskOutcome::FinishedEarlier);
    }
    if let Some(step) = stop_after.filter(|&s| s == 0 || s >= task.config.steps) {
        return Err(HostError::invalid(
            description,
            format!(
                "--stop-after {step}: must be a step before task {index}'s last (1 to {})",
                task.config.steps.saturating_sub(1)
            ),
        ));
    }
    say(format!("task {index}: {}", task.name));
    let (result, timing) = match train_and_score(
        &sweep,
        task,
        &task_dir(out, index),
        threads,
        stop_after,
        say,
    ) {
        Err(e @ HostError::Stopped { .. }) => return Ok(TaskOutcome::Stopped(e.to_string())),
        outcome => outcome?,
    };
    write_timing(out, &timing)?;
    results::write_result(out, &result)?;
    Ok(TaskOutcome::Done(
        task_dir(out, index).join(results::RESULT),
    ))
}

/// The dataset of `task` (simulated into `dir/data` for a scene), its model trained and
/// scored (also after the sweep's anytime steps); writes the checkpoint and the first
/// held-out view's render into `dir`.
fn train_and_score(
    sweep: &Sweep,
    task: &Task,
    dir: &Path,
    threads: usize,
    stop_after: Option<u32>,
    say: &mut dyn FnMut(String),
) -> Result<(TaskResult, TaskTiming)> {
    let training = match &sweep.source {
        Source::Scene(scene) => simulated(
            scene,
            task.frames,
            task.size,
            task.noise,
            &dir.join("data"),
            sweep.masks,
        )?,
        Source::Data(path) => load(path, task.size, sweep.masks)?,
    };
    let (mut dataset, truth, train_idx, test_idx) = match &sweep.test {
        // The same test set for every task (the scene's own seed), with exact labels.
        Some(TestSet::Scene { scene, frames }) => {
            let exact = LabelNoise {
                rotation_deg: 0.0,
                translation_m: 0.0,
            };
            let test_set = simulated(
                scene,
                *frames,
                task.size,
                Some(exact),
                &dir.join("test-data"),
                sweep.masks,
            )?;
            with_test_set(training, test_set)
        }
        Some(TestSet::Data(data)) => with_test_set(training, load(data, task.size, sweep.masks)?),
        None => {
            let (train_idx, test_idx) = split_every(training.0.frames.len(), sweep.holdout);
            (training.0, training.1, train_idx, test_idx)
        }
    };
    if train_idx.is_empty() || test_idx.is_empty() {
        return Err(HostError::invalid(
            &dataset.source,
            format!(
                "{} frames give no training or no held-out view with holdout {}",
                dataset.frames.len(),
                sweep.holdout
            ),
        ));
    }
    say(crate::pipeline::choose_box(
        &mut dataset,
        sweep.scene_box,
        sweep.config_file.as_deref(),
        &train_idx,
    )?);
    // A progress line and a progress checkpoint every tenth of the steps.
    let every = (task.config.steps / 10).max(1);
    let experiment = Experiment {
        dataset: &dataset,
        truth: truth.as_deref(),
        train_idx: &train_idx,
        test_idx: &test_idx,
        threads,
        fit_steps: sweep.fit_steps,
        score_at: &sweep.score_at(task),
        progress: Some(Progress {
            path: &dir.join(PROGRESS),
            every,
            stop_after,
        }),
    };
    let checkpoint = dir.join(CHECKPOINT);
    let result = experiment.run(
        &task.config,
        &mut |step, report| {
            if step % every == 0 {
                say(format!("  step {step}: mse {:.5}", report.mse));
            }
        },
        Some(&checkpoint),
    )?;
    let first = &dataset.frames[test_idx[0]];
    write_png(
        &dir.join(RENDER),
        first.camera.width as u32,
        first.camera.height as u32,
        3,
        &to_rgb8(&result.renders[0]),
    )?;
    say(format!(
        "  trained in {:.1} s; held-out PSNR {:.2} dB, SSIM {:.4}",
        result.train_seconds, result.metrics.psnr_full, result.metrics.ssim_full
    ));
    let (rotation_deg, translation_m) = task
        .noise
        .map_or((0.0, 0.0), |n| (n.rotation_deg, n.translation_m));
    let record = TaskResult {
        index: task.index,
        name: task.name.clone(),
        variant: task.variant.clone(),
        seed: task.seed,
        rotation_noise_deg: rotation_deg,
        translation_noise_mm: translation_m * 1000.0,
        steps: task.config.steps,
        held_out_views: test_idx.len(),
        metrics: result.metrics.into(),
        curve: (result.curve.iter())
            .map(|p| CurveRecord {
                step: p.step,
                metrics: p.metrics.into(),
            })
            .collect(),
        size: task.size,
        arena_bytes: result.arena_bytes as u64,
        samples: result.samples,
        pose_before: result.pose_before.map(Into::into),
        pose_after: result.pose_after.map(Into::into),
        metrics_exact: result.metrics_exact.map(Into::into),
        metrics_aligned: Some(result.metrics_aligned.into()),
        pose_uncertainty: result.pose_uncertainty,
        checkpoint_fnv1a: format!("{:016x}", fnv1a_file(&checkpoint)?),
        settings: Some(TaskSettings::of(sweep, task)),
    };
    let timing = TaskTiming {
        index: task.index,
        name: task.name.clone(),
        seconds: result.curve.iter().map(|p| p.seconds).collect(),
        threads,
        cpu: crate::machine::cpu_summary(),
    };
    Ok((record, timing))
}

/// Run the unfinished tasks of the description at `description` as child processes of
/// `exe` (`exe sweep run-task ...`, the `orbit-nerf` binary), `jobs` at a time with `threads`
/// each (default: one job per core, the cores shared among them), each logging to its
/// folder; fail naming every failed task and its log, else merge the results
/// ([`results::collect`]) and return the merged table's text.
pub fn run_local(
    exe: &Path,
    description: &Path,
    out: &Path,
    (jobs, threads): (Option<usize>, Option<usize>),
    say: &(dyn Fn(String) + Sync),
) -> Result<String> {
    let sweep = Sweep::read(description)?;
    check_output_folder(out)?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = check_workers("--jobs", jobs.unwrap_or(cores))?;
    let threads = check_workers("--threads", threads.unwrap_or((cores / jobs).max(1)))?;
    let pending = unfinished(&sweep, out)?;
    say(format!(
        "{} tasks: {} finished earlier (skipped), {} to run, {jobs} at a time with {threads} threads each",
        sweep.tasks.len(),
        sweep.tasks.len() - pending.len(),
        pending.len()
    ));
    let next = AtomicUsize::new(0);
    let failed: Mutex<Vec<(usize, String)>> = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(pending.len()) {
            scope.spawn(|| {
                while let Some(&index) = pending.get(next.fetch_add(1, Ordering::SeqCst)) {
                    let task = &sweep.tasks[index];
                    let outcome = run_child(exe, description, out, index, threads);
                    let outcome = outcome.and_then(|()| match read_result(&sweep, out, task) {
                        Ok(Some(_)) => Ok(()),
                        Ok(None) => Err("it wrote no result".to_string()),
                        Err(e) => Err(e.to_string()),
                    });
                    match outcome {
                        Ok(()) => say(format!("task {index} ({}): done", task.name)),
                        Err(why) => {
                            let log = task_dir(out, index).join(LOG);
                            say(format!(
                                "task {index} ({}) FAILED: {why}; log: {}",
                                task.name,
                                log.display()
                            ));
                            if let Ok(mut failed) = failed.lock() {
                                failed.push((index, why));
                            }
                        }
                    }
                }
            });
        }
    });
    let mut failed = failed.into_inner().unwrap_or_default();
    if !failed.is_empty() {
        failed.sort();
        let lines: Vec<String> = (failed.iter())
            .map(|(index, why)| {
                format!(
                    "task {index} ({}): {why}; log: {}",
                    sweep.tasks[*index].name,
                    task_dir(out, *index).join(LOG).display()
                )
            })
            .collect();
        return Err(HostError::invalid(
            out,
            format!(
                "{} of {} tasks failed (indices {}); the same command runs only the unfinished ones again:\n  {}",
                failed.len(),
                sweep.tasks.len(),
                array_spec(&failed.iter().map(|(i, _)| *i).collect::<Vec<_>>()),
                lines.join("\n  ")
            ),
        ));
    }
    results::collect(&sweep, out)
}

/// `exe sweep run-task` of `index` as a child process, its output into the task's log.
fn run_child(
    exe: &Path,
    description: &Path,
    out: &Path,
    index: usize,
    threads: usize,
) -> std::result::Result<(), String> {
    let dir = task_dir(out, index);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let log_path = dir.join(LOG);
    let log =
        std::fs::File::create(&log_path).map_err(|e| format!("{}: {e}", log_path.display()))?;
    let err = log
        .try_clone()
        .map_err(|e| format!("{}: {e}", log_path.display()))?;
    let status = Command::new(exe)
        .arg("sweep")
        .arg("run-task")
        .arg(description)
        .arg(index.to_string())
        .arg("--out")
        .arg(out)
        .arg("--threads")
        .arg(threads.to_string())
        .stdin(Stdio::null())
        .stdout(log)
        .stderr(err)
        .status()
        .map_err(|e| format!("could not start {}: {e}", exe.display()))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("exited with {status}"))
    }
}
