//! `orbit-nerf paper`: the paper's tables (the main table on the three training sets, the
//! image-count study, the pose-noise sweeps) as sweeps run in one folder and gathered into
//! `paper.md` (`orbit_nerf_host::sweep::paper`).

use super::{Fallible, parse_threads};
use orbit_nerf_host::sweep::paper::{self, PaperSweep, Table};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct PaperArgs {
    /// Output folder: a folder per sweep with its description beside it (`main-synthetic`,
    /// `main-lightbox`, `main-sunlamp`, `image-counts`, `pose-noise`), and paper.md. Rerun the
    /// same command to continue unfinished tasks.
    #[arg(long, default_value = "runs/paper")]
    out: PathBuf,
    /// The tables to make (default: all three).
    #[arg(long, value_enum, value_delimiter = ',', default_values = ["main", "image-counts", "pose-noise"])]
    tables: Vec<TableArg>,
    /// Replace a built-in description, NAME=FILE (NAME: main-synthetic, main-lightbox,
    /// main-sunlamp, image-counts, pose-noise); repeat for more. The built-in ones are the
    /// repository's sweeps/paper-main-*.toml, image-counts-quick.toml and paper-pose-noise.toml.
    #[arg(long, value_name = "NAME=FILE")]
    description: Vec<String>,
    /// Tasks run at once (default 1: tasks sharing the cores would distort each other's
    /// times).
    #[arg(long, default_value_t = 1, value_parser = parse_threads)]
    jobs: usize,
    /// Threads of each task (default: the cores shared among the jobs; results do not depend
    /// on it).
    #[arg(long, value_parser = parse_threads)]
    threads: Option<usize>,
    /// Only write the descriptions into --out (to run each with `sweep slurm` on a cluster,
    /// or `sweep run`); the same command without this flag then gathers paper.md, running
    /// only the tasks that have no result yet.
    #[arg(long)]
    write_only: bool,
}

/// `--tables`' values.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum TableArg {
    Main,
    ImageCounts,
    PoseNoise,
}

pub fn run(args: &PaperArgs) -> Fallible<()> {
    let tables: Vec<Table> = (args.tables.iter())
        .map(|t| match t {
            TableArg::Main => Table::Main,
            TableArg::ImageCounts => Table::ImageCounts,
            TableArg::PoseNoise => Table::PoseNoise,
        })
        .collect();
    let mut sweeps = PaperSweep::built_in(&tables);
    for given in &args.description {
        PaperSweep::replace(&mut sweeps, given)?;
    }
    let say = |line: String| println!("{line}");
    if args.write_only {
        for (sweep, described) in paper::describe(&sweeps, &args.out, &mut |line| say(line))? {
            let (description, folder) = (sweep.description(&args.out), sweep.folder(&args.out));
            println!(
                "{}: {} tasks; on a cluster: `orbit-nerf sweep slurm {} --out {}`",
                description.display(),
                described.tasks.len(),
                description.display(),
                folder.display()
            );
        }
        println!(
            "once the tasks are done, `orbit-nerf paper` with the same --out and --tables (and --description) gathers paper.md"
        );
        return Ok(());
    }
    let exe = std::env::current_exe()?;
    let mut run_local = |description: &Path, out: &Path| {
        let jobs = (Some(args.jobs), args.threads);
        orbit_nerf_host::sweep::run::run_local(&exe, description, out, jobs, &say)
    };
    let text = paper::run(&sweeps, &args.out, &mut run_local, &mut |line| say(line))?;
    println!("{text}");
    println!("paper.md in {}", args.out.display());
    Ok(())
}
