//! `orbit-nerf sweep` end to end on a tiny simulated scene (built-in preset, no reference data):
//! the local runner runs every task in its own process, a failed task is reported with its log
//! and fails the run, a re-run runs only the unfinished tasks, the Slurm script lists only
//! those, and a task gives the same bytes whatever its thread count.

mod common;

use common::{orbit_nerf, output_text, temp_dir};
use std::path::Path;

const DESCRIPTION: &str = r#"
scene = "synthetic"
frames = 8
size = 32
config = "tiny"
steps = 12
holdout = 4
fit_steps = 2

[[variants]]
name = "baseline"
set = { embedding_dim = 0 }

[[variants]]
name = "ours"
set = { embedding_dim = 8 }
"#;

fn sweep(args: &[&str]) -> (bool, String) {
    let out = orbit_nerf(&[&["sweep"], args].concat())
        .output()
        .expect("the binary runs");
    (out.status.success(), output_text(&out))
}

fn bytes(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_local_sweep_reports_a_failed_task_and_a_rerun_runs_only_the_unfinished_ones() {
    let dir = temp_dir("local");
    let description = dir.join("sweep.toml");
    std::fs::write(&description, DESCRIPTION).unwrap();
    let (description, out) = (description.to_str().unwrap(), dir.join("out"));
    let out_arg = out.to_str().unwrap();
    // Task 1 cannot simulate its frames: a file stands where its data folder goes.
    std::fs::create_dir_all(out.join("tasks/1")).unwrap();
    std::fs::write(out.join("tasks/1/data"), "in the way").unwrap();

    let (ok, text) = sweep(&["run", description, "--out", out_arg, "--jobs", "2"]);
    assert!(!ok, "{text}");
    let log = out.join("tasks/1/log.txt");
    assert!(text.contains("task 1 (ours, seed 0) FAILED"), "{text}");
    assert!(text.contains(&log.display().to_string()), "{text}");
    assert!(text.contains("1 of 2 tasks failed"), "{text}");
    let log_text = std::fs::read_to_string(&log).unwrap();
    assert!(log_text.contains("not a folder"), "{log_text}");
    assert!(out.join("tasks/0/result.json").is_file());
    assert!(!out.join("tasks/1/result.json").exists());
    assert!(
        !out.join("sweep.md").exists(),
        "collected despite a failure"
    );
    // Collecting now names the missing task; the array script lists only it.
    let (ok, text) = sweep(&["collect", description, "--out", out_arg]);
    assert!(
        !ok && text.contains("1 of 2 tasks have no result (indices 1)"),
        "{text}"
    );
    let (ok, text) = sweep(&["slurm", description, "--out", out_arg, "--no-submit"]);
    assert!(ok, "{text}");
    let script = std::fs::read_to_string(out.join("sweep.sbatch")).unwrap();
    assert!(script.lines().any(|l| l == "#SBATCH --array=1"), "{script}");
    let (ok, text) = sweep(&[
        "slurm",
        description,
        "--out",
        out_arg,
        "--time",
        "0",
        "--no-submit",
    ]);
    assert!(!ok && text.contains("--time"), "{text}");

    // Cleared, the re-run runs task 1 only and collects.
    std::fs::remove_file(out.join("tasks/1/data")).unwrap();
    let finished = bytes(&out.join("tasks/0/result.json"));
    let (ok, text) = sweep(&["run", description, "--out", out_arg, "--jobs", "2"]);
    assert!(ok, "{text}");
    assert!(
        text.contains("2 tasks: 1 finished earlier (skipped), 1 to run"),
        "{text}"
    );
    assert!(!text.contains("task 0 (baseline, seed 0): done"), "{text}");
    assert_eq!(bytes(&out.join("tasks/0/result.json")), finished);
    for file in ["sweep.csv", "sweep.md", "renders.png"] {
        assert!(out.join(file).is_file(), "{file}");
    }
    let table = std::fs::read_to_string(out.join("sweep.md")).unwrap();
    assert!(table.contains("| 1    | ours     | 0    |"), "{table}");
    let csv = std::fs::read_to_string(out.join("sweep.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3, "{csv}");
    let (ok, text) = sweep(&["run", description, "--out", out_arg]);
    assert!(
        ok && text.contains("2 finished earlier (skipped), 0 to run"),
        "{text}"
    );

    // The same task with another thread count elsewhere: the same bytes.
    let other = dir.join("other");
    let (ok, text) = sweep(&[
        "run-task",
        description,
        "0",
        "--out",
        other.to_str().unwrap(),
        "--threads",
        "3",
    ]);
    assert!(ok, "{text}");
    for file in ["result.json", "render.png", "checkpoint.onrf"] {
        assert_eq!(
            bytes(&other.join("tasks/0").join(file)),
            bytes(&out.join("tasks/0").join(file)),
            "{file}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
