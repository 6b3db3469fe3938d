//! `orbit-nerf sweep`: a sweep description (`orbit_nerf_host::sweep`) run on this machine as
//! parallel processes (`run`), or on a cluster as a Slurm job array (`slurm`, then `collect`).
//! Both run each task through the same entry point, `run-task`, which writes the task's
//! results atomically into `<out>/tasks/<index>/`; a task with a result is never run again.

use super::Fallible;
use orbit_nerf_host::sweep::Sweep;
use orbit_nerf_host::sweep::run::{self, TaskOutcome};
use orbit_nerf_host::sweep::slurm::{self, Resources};
use std::path::{Path, PathBuf};

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

pub fn run(args: &SweepArgs) -> Fallible<()> {
    let exe = std::env::current_exe()?;
    match &args.command {
        SweepCommand::List { description } => {
            let sweep = Sweep::read(description)?;
            for task in &sweep.tasks {
                println!("{:>5}  {}", task.index, task.name);
            }
        }
        SweepCommand::Run {
            description,
            out,
            jobs,
            threads,
        } => run_local(description, out, *jobs, *threads)?,
        SweepCommand::RunTask {
            description,
            index,
            out,
            threads,
            stop_after,
        } => {
            let say = &mut |line: String| println!("{line}");
            match run::run_task(description, *index, out, *threads, *stop_after, say)? {
                TaskOutcome::FinishedEarlier => {
                    println!("task {index} finished earlier: nothing to do")
                }
                TaskOutcome::Done(result) => {
                    println!("task {index}: result in {}", result.display())
                }
                TaskOutcome::Stopped(why) => println!("task {index}: {why}"),
            }
        }
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
            let submission = slurm::submit(&exe, description, out, &resources, *no_submit)?;
            println!("{}", submission.report(description, out));
        }
        SweepCommand::Collect { description, out } => {
            let text = orbit_nerf_host::sweep::results::collect(&Sweep::read(description)?, out)?;
            print_collected(&text, out);
        }
    }
    Ok(())
}

fn print_collected(text: &str, out: &Path) {
    println!("{text}");
    println!(
        "tables (sweep.csv, sweep.md) and figures in {}",
        out.display()
    );
}

/// Run the unfinished tasks of `description` on this machine (each a `run-task` child
/// process), then print the merged tables.
pub(super) fn run_local(
    description: &Path,
    out: &Path,
    jobs: Option<usize>,
    threads: Option<usize>,
) -> Fallible<()> {
    let exe = std::env::current_exe()?;
    let say = |line: String| println!("{line}");
    let text = run::run_local(&exe, description, out, (jobs, threads), &say)?;
    print_collected(&text, out);
    Ok(())
}
