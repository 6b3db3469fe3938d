//! orbit-nerf: train, evaluate and render K-Planes radiance fields of spacecraft (and of
//! NeRF scenes), benchmark the core, and simulate datasets. One file per command in
//! `commands/`; this file holds the command line's entry and the dispatch.

mod commands;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use commands::{
    ablate, bench, demo, eval, export, paper, reference, render, simulate, stream, sweep, tradeoff,
    train,
};

#[derive(Parser)]
#[command(name = "orbit-nerf", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a field on a dataset and write a checkpoint.
    Train(train::TrainArgs),
    /// Score held-out views of a dataset with a checkpoint (PSNR per view and the mean).
    Eval(eval::EvalArgs),
    /// Render views of a dataset's cameras with a checkpoint to PNG, or an orbit around the
    /// target (or a path file) to PNG frames and an animated GIF.
    Render(render::RenderArgs),
    /// Export the trained field's geometry: a coloured mesh (PLY, OBJ) or point cloud (PLY).
    #[command(subcommand)]
    Export(export::ExportCommand),
    /// Measure training throughput (samples/s, rays/s) on a fixed scene and seed.
    Bench(bench::BenchArgs),
    /// The built-in default: simulate the lightbox preset, train the method, evaluate, report.
    Demo(demo::DemoArgs),
    /// Render a spacecraft scene into a SPEED+-format dataset.
    Simulate(simulate::SimulateArgs),
    /// The paper's ablation (baseline, + appearance, + pose) or its pose-noise sweep.
    Ablate(ablate::AblateArgs),
    /// Ingest frames one at a time (dataset folder, watched folder, simulator) into a fixed
    /// frame store, training as they arrive; anytime quality, checkpoints, resume.
    Stream(stream::StreamArgs),
    /// Run a sweep description: locally as parallel processes, or as a Slurm job array.
    Sweep(sweep::SweepArgs),
    /// What accuracy costs in time: every knob's variants trained and scored while they
    /// train (anytime curves), Pareto plots of quality against time and memory.
    Tradeoff(tradeoff::TradeoffArgs),
    /// The paper's tables: the main table on the three training sets, the image-count study
    /// and the pose-noise sweeps, run as sweeps in one folder and gathered into paper.md.
    Paper(paper::PaperArgs),
    /// Shell completions, man pages and the docs book's reference chapters, generated from
    /// the program's own definitions.
    Docs(reference::DocsArgs),
}

/// The command line with the exit codes at the end of every command's `--help`, nested
/// ones included.
fn cli_command() -> clap::Command {
    fn with_exit_codes(command: clap::Command) -> clap::Command {
        command
            .after_help(reference::EXIT_CODES)
            .mut_subcommands(with_exit_codes)
    }
    with_exit_codes(Cli::command())
}

fn main() {
    restore_default_sigpipe();
    let cli = Cli::from_arg_matches(&cli_command().get_matches()).unwrap_or_else(|e| e.exit());
    let result = match cli.command {
        Command::Train(args) => train::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Render(args) => render::run(&args),
        Command::Export(command) => export::run(&command),
        Command::Bench(args) => bench::run(&args),
        Command::Demo(args) => demo::run(&args),
        Command::Simulate(args) => simulate::run(&args),
        Command::Ablate(args) => ablate::run(&args),
        Command::Stream(args) => stream::run(&args),
        Command::Sweep(args) => sweep::run(&args),
        Command::Tradeoff(args) => tradeoff::run(&args),
        Command::Paper(args) => paper::run(&args),
        Command::Docs(args) => reference::run(&args, cli_command()),
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// Rust ignores SIGPIPE, so printing into a closed pipe (`orbit-nerf ... | head`) would panic
/// in `println!`; with the default action the process ends quietly, as other Unix tools do.
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called first in `main`, before any other thread exists; sets a signal's action.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(test)]
mod tests {
    use super::{Cli, cli_command, reference};
    use clap::CommandFactory;

    /// The book's reference chapters are what `orbit-nerf docs reference` writes today: a
    /// flag, a help text, a config field or a preset's value changed without them fails here
    /// (regenerate with `cargo run --release -- docs reference --out
    /// docs/book/src/reference --force`).
    #[test]
    fn the_books_reference_chapters_are_current() {
        let folder =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/book/src/reference");
        let read = |name: &str| {
            std::fs::read_to_string(folder.join(name))
                .unwrap_or_else(|e| panic!("{}: {e}", folder.join(name).display()))
        };
        assert!(
            read("commands.md") == reference::commands_chapter(&mut cli_command()),
            "docs/book/src/reference/commands.md is stale: regenerate it"
        );
        assert!(
            read("config.md") == orbit_nerf_host::reference::config_chapter().unwrap(),
            "docs/book/src/reference/config.md is stale: regenerate it"
        );
    }

    /// Every option of every subcommand, nested ones included (`export mesh`, `sweep run`),
    /// says what it does in `--help`.
    #[test]
    fn every_option_has_help_text() {
        fn missing_help(command: &clap::Command, path: &str, missing: &mut Vec<String>) {
            for arg in command.get_arguments() {
                if arg.get_help().is_none() && arg.get_id() != "help" && arg.get_id() != "version" {
                    missing.push(format!("{path} --{}", arg.get_id()));
                }
            }
            for sub in command.get_subcommands() {
                missing_help(sub, &format!("{path} {}", sub.get_name()), missing);
            }
        }
        let mut missing = Vec::new();
        missing_help(&Cli::command(), "orbit-nerf", &mut missing);
        assert!(missing.is_empty(), "options without help: {missing:?}");
    }
}
