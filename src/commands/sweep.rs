//! `orbit-nerf sweep`: a sweep description (`orbit_nerf_host::sweep`) run on this machine as
//! parallel processes (`run`), or on a cluster as a Slurm job array (`slurm`, then `collect`).
//! Both run each task through the same entry point, `run-task`, which writes the task's
//! results atomically into `<out>/tasks/<index>/`; a task with a result is never run again.

use super::{Fallible, choose_box};
use orbit_nerf_host::ablation::{Experiment, Progress};
use orbit_nerf_host::ablation_report::{load, simulated};
use orbit_nerf_host::dataset::{split_every, with_test_set};
use orbit_nerf_host::error::HostError;
use orbit_nerf_host::io::{check_output_folder, write_atomic, write_png};
use orbit_nerf_host::sim::scene::LabelNoise;
use orbit_nerf_host::sweep::results::{
    self, CHECKPOINT, CurveRecord, LOG, PROGRESS, RENDER, TaskResult, TaskSettings, TaskTiming,
    array_spec, fnv1a_file, read_result, task_dir, unfinished, write_timing,
};
use orbit_nerf_host::sweep::slurm::{self, Resources};
use orbit_nerf_host::sweep::{Source, Sweep, Task, TestSet};
use orbit_nerf_host::train::to_rgb8;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

#[derive(clap::Args, Debug)]
pub struct SweepArgs {
    #[command(subcommand)]
    command: SweepCommand,
}

#[derive(clap::Subcommand, Debug)]
enum SweepCommand {
    /// List a description's tasks (index and name).
    List {
        /// The sweep description (TOML; see `sweeps/pose-noise.toml`).
        description: PathBuf,
    },
    /// Run the unfinished tasks on this machine, several processes at once, then collect.
    Run {
        /// The sweep description (TOML; see `sweeps/pose-noise.toml`).
        description: PathBuf,
        /// The sweep's folder: `tasks/<index>/` per task, the merged tables and figures.
        #[arg(long, default_value = "runs/sweep")]
        out: PathBuf,
        /// Tasks run at once (default: one per core).
        #[arg(long)]
        jobs: Option<usize>,
        /// Threads of each task (default: the cores shared among the jobs; results do not
        /// depend on it).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Run one task: what `run` starts per task and each Slurm array task calls.
    RunTask {
        /// The sweep description (TOML; see `sweeps/pose-noise.toml`).
        description: PathBuf,
        /// The task's index (`sweep list` shows them).
        index: usize,
        /// The sweep's folder: `tasks/<index>/` per task, the merged tables and figures.
        #[arg(long, default_value = "runs/sweep")]
        out: PathBuf,
        /// Worker threads (results do not depend on it).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Stop after this step, the task's state saved in its folder (`progress.onrf`);
        /// running the task again continues from there to the same bytes. A task killed any
        /// other way continues from its last tenth of the steps.
        #[arg(long)]
        stop_after: Option<u32>,
    },
    /// Write a Slurm job-array script of the unfinished tasks to `<out>/sweep.sbatch` and
    /// submit it with `sbatch`. The binary, the description and `--out` must be on a
    /// filesystem every node sees.
    Slurm {
        /// The sweep description (TOML; see `sweeps/pose-noise.toml`).
        description: PathBuf,
        /// The sweep's folder: `tasks/<index>/` per task, the merged tables and figures.
        #[arg(long, default_value = "runs/sweep")]
        out: PathBuf,
        /// CPUs of each array task (`#SBATCH --cpus-per-task`; its threads).
        #[arg(long, default_value_t = 1)]
        cpus_per_task: u32,
        /// Partition (default: the cluster's default).
        #[arg(long)]
        partition: Option<String>,
        /// Time limit per task, in Slurm's format (`HH:MM:SS`, `D-HH:MM`, minutes).
        #[arg(long)]
        time: Option<String>,
        /// Only write the script.
        #[arg(long)]
        no_submit: bool,
    },
    /// Merge the tasks' results into `sweep.csv`, `sweep.md` and the figures in `--out`.
    Collect {
        /// The sweep description (TOML; see `sweeps/pose-noise.toml`).
        description: PathBuf,
        /// The sweep's folder: `tasks/<index>/` per task, the merged tables and figures.
        #[arg(long, default_value = "runs/sweep")]
        out: PathBuf,
    },
}

/// Largest `--jobs` and `--threads` accepted.
const MAX_WORKERS: usize = 1024;

fn check_workers(flag: &str, value: usize) -> Fallible<usize> {
    if (1..=MAX_WORKERS).contains(&value) {
        Ok(value)
    } else {
        Err(format!("{flag}: {value} is not between 1 and {MAX_WORKERS}").into())
    }
}

pub fn run(args: &SweepArgs) -> Fallible<()> {
    match &args.command {
        SweepCommand::List { description } => {
            let sweep = Sweep::read(description)?;
            for task in &sweep.tasks {
                println!("{:>5}  {}", task.index, task.name);
            }
            Ok(())
        }
        SweepCommand::Run {
            description,
            out,
            jobs,
            threads,
        } => run_local(description, out, *jobs, *threads),
        SweepCommand::RunTask {
            description,
            index,
            out,
            threads,
            stop_after,
        } => run_task(
            description,
            *index,
            out,
            check_workers("--threads", *threads)?,
            *stop_after,
        ),
        SweepCommand::Slurm {
            description,
            out,
            cpus_per_task,
            partition,
            time,
            no_submit,
        } => {
            let resources = Resources {
                cpus_per_task: *cpus_per_task,
                partition: partition.clone(),
                time: time.clone(),
            };
            submit(description, out, &resources, *no_submit)
        }
        SweepCommand::Collect { description, out } => {
            let sweep = Sweep::read(description)?;
            collect(&sweep, out)
        }
    }
}

fn collect(sweep: &Sweep, out: &Path) -> Fallible<()> {
    let text = results::collect(sweep, out)?;
    println!("{text}");
    println!(
        "tables (sweep.csv, sweep.md) and figures in {}",
        out.display()
    );
    Ok(())
}

/// Train and score one task into `<out>/tasks/<index>/` (nothing when it already has a result).
fn run_task(
    description: &Path,
    index: usize,
    out: &Path,
    threads: usize,
    stop_after: Option<u32>,
) -> Fallible<()> {
    let sweep = Sweep::read(description)?;
    let Some(task) = sweep.tasks.get(index) else {
        return Err(format!(
            "task {index}: {} has {} tasks (0 to {})",
            description.display(),
            sweep.tasks.len(),
            sweep.tasks.len().saturating_sub(1)
        )
        .into());
    };
    check_output_folder(out)?;
    if read_result(&sweep, out, task)?.is_some() {
        println!(
            "task {index} ({}) finished earlier: nothing to do",
            task.name
        );
        return Ok(());
    }
    if let Some(step) = stop_after.filter(|&s| s == 0 || s >= task.config.steps) {
        return Err(format!(
            "--stop-after {step}: must be a step before task {index}'s last (1 to {})",
            task.config.steps.saturating_sub(1)
        )
        .into());
    }
    let dir = task_dir(out, index);
    println!("task {index}: {}", task.name);
    let (result, timing) = match train_and_score(&sweep, task, &dir, threads, stop_after) {
        Err(e) if matches!(e.downcast_ref(), Some(HostError::Stopped { .. })) => {
            println!("task {index}: {e}");
            return Ok(());
        }
        outcome => outcome?,
    };
    write_timing(out, &timing)?;
    results::write_result(out, &result)?;
    println!(
        "task {index}: result in {}",
        dir.join(results::RESULT).display()
    );
    Ok(())
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
) -> Fallible<(TaskResult, TaskTiming)> {
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
        return Err(format!(
            "{}: {} frames give no training or no held-out view with holdout {}",
            dataset.source.display(),
            dataset.frames.len(),
            sweep.holdout
        )
        .into());
    }
    choose_box(
        &mut dataset,
        sweep.scene_box,
        sweep.config_file.as_deref(),
        &train_idx,
    )?;
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
                println!("  step {step}: mse {:.5}", report.mse);
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
    println!(
        "  trained in {:.1} s; held-out PSNR {:.2} dB, SSIM {:.4}",
        result.train_seconds, result.metrics.psnr_full, result.metrics.ssim_full
    );
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
        cpu: orbit_nerf_host::machine::cpu_summary(),
    };
    Ok((record, timing))
}

/// Run the unfinished tasks as child processes (`run-task`), `jobs` at a time, each logging
/// to its folder; report every failed task with its log and fail, else collect.
pub(super) fn run_local(
    description: &Path,
    out: &Path,
    jobs: Option<usize>,
    threads: Option<usize>,
) -> Fallible<()> {
    let sweep = Sweep::read(description)?;
    check_output_folder(out)?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = check_workers("--jobs", jobs.unwrap_or(cores))?;
    let threads = check_workers("--threads", threads.unwrap_or((cores / jobs).max(1)))?;
    let pending = unfinished(&sweep, out)?;
    println!(
        "{} tasks: {} finished earlier (skipped), {} to run, {jobs} at a time with {threads} threads each",
        sweep.tasks.len(),
        sweep.tasks.len() - pending.len(),
        pending.len()
    );
    let exe = std::env::current_exe()?;
    let next = AtomicUsize::new(0);
    let failed: Mutex<Vec<(usize, String)>> = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(pending.len()) {
            scope.spawn(|| {
                while let Some(&index) = pending.get(next.fetch_add(1, Ordering::SeqCst)) {
                    let task = &sweep.tasks[index];
                    let outcome = run_child(&exe, description, out, index, threads);
                    let outcome = outcome.and_then(|()| match read_result(&sweep, out, task) {
                        Ok(Some(_)) => Ok(()),
                        Ok(None) => Err("it wrote no result".to_string()),
                        Err(e) => Err(e.to_string()),
                    });
                    match outcome {
                        Ok(()) => println!("task {index} ({}): done", task.name),
                        Err(why) => {
                            let log = task_dir(out, index).join(LOG);
                            eprintln!(
                                "task {index} ({}) FAILED: {why}; log: {}",
                                task.name,
                                log.display()
                            );
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
        for (index, why) in &failed {
            eprintln!(
                "failed: task {index} ({}): {why}; log: {}",
                sweep.tasks[*index].name,
                task_dir(out, *index).join(LOG).display()
            );
        }
        return Err(format!(
            "{} of {} tasks failed (indices {}); the same command runs only the unfinished ones again",
            failed.len(),
            sweep.tasks.len(),
            array_spec(&failed.iter().map(|(i, _)| *i).collect::<Vec<_>>())
        )
        .into());
    }
    collect(&sweep, out)
}

/// `run-task` of `index` as a child process, its output into the task's log.
fn run_child(
    exe: &Path,
    description: &Path,
    out: &Path,
    index: usize,
    threads: usize,
) -> Result<(), String> {
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

/// Write the array script of the unfinished tasks and submit it (unless `no_submit`).
fn submit(description: &Path, out: &Path, resources: &Resources, no_submit: bool) -> Fallible<()> {
    slurm::check(resources)?;
    let sweep = Sweep::read(description)?;
    check_output_folder(out)?;
    let pending = unfinished(&sweep, out)?;
    if pending.is_empty() {
        println!(
            "all {} tasks have results: nothing to submit; merge them with `orbit-nerf sweep collect {} --out {}`",
            sweep.tasks.len(),
            description.display(),
            out.display()
        );
        return Ok(());
    }
    std::fs::create_dir_all(out.join("slurm")).map_err(|e| format!("{}: {e}", out.display()))?;
    let absolute = |p: &Path| std::fs::canonicalize(p).map_err(|e| format!("{}: {e}", p.display()));
    let (exe, description_abs, out_abs) = (
        absolute(&std::env::current_exe()?)?,
        absolute(description)?,
        absolute(out)?,
    );
    slurm::check_output_folder(&out_abs)?;
    let array = array_spec(&pending);
    let script_path = out.join("sweep.sbatch");
    let text = slurm::script(&exe, &description_abs, &out_abs, &array, resources);
    write_atomic(&script_path, text.as_bytes())?;
    println!(
        "wrote {} ({} of {} tasks: --array={array})",
        script_path.display(),
        pending.len(),
        sweep.tasks.len()
    );
    if no_submit {
        println!("submit it with `sbatch {}`", script_path.display());
        return Ok(());
    }
    let output = Command::new("sbatch")
        .arg("--parsable")
        .arg(&script_path)
        .output()
        .map_err(|e| {
            format!("sbatch: {e} (is Slurm installed here? --no-submit only writes the script)")
        })?;
    if !output.status.success() {
        return Err(format!(
            "sbatch refused {}: {}",
            script_path.display(),
            String::from_utf8_lossy(&output.stderr).trim()
        )
        .into());
    }
    println!(
        "submitted job array {}; when it has finished: orbit-nerf sweep collect {} --out {}",
        String::from_utf8_lossy(&output.stdout).trim(),
        description.display(),
        out.display()
    );
    Ok(())
}
