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

/// Two task folders hold the same record, render and model, byte for byte.
fn same_task_files(a: &Path, b: &Path) {
    for file in ["result.json", "render.png", "checkpoint.onrf"] {
        assert_eq!(bytes(&a.join(file)), bytes(&b.join(file)), "{file}");
    }
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
    same_task_files(&other.join("tasks/0"), &out.join("tasks/0"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A task stopped part-way (`--stop-after`, as a killed task stops at its last progress
/// checkpoint) continues from its `progress.onrf` to the bytes of a run never stopped, also
/// across an anytime point; a progress file of another task's config is refused.
#[test]
fn a_stopped_task_continues_to_the_bytes_of_a_run_never_stopped() {
    let dir = temp_dir("resume");
    let description = dir.join("sweep.toml");
    let text = DESCRIPTION.replace(
        "[[variants]]\nname = \"baseline\"",
        "[anytime]\nsteps = [4, 9]\nquality = \"psnr_full\"\ntargets = [20]\nbudgets_s = [30]\n\n[[variants]]\nname = \"baseline\"",
    );
    assert!(text.contains("[anytime]"));
    std::fs::write(&description, text).unwrap();
    let description = description.to_str().unwrap();
    let (whole, stopped) = (dir.join("whole"), dir.join("stopped"));
    let run_task = |index: &str, out: &Path, extra: &[&str]| {
        sweep(
            &[
                &[
                    "run-task",
                    description,
                    index,
                    "--out",
                    out.to_str().unwrap(),
                ],
                extra,
            ]
            .concat(),
        )
    };
    let (ok, text) = run_task("1", &whole, &[]);
    assert!(ok, "{text}");
    assert!(
        !whole.join("tasks/1/progress.onrf").exists(),
        "left its progress file"
    );

    for bad in ["0", "12"] {
        let (ok, text) = run_task("1", &stopped, &["--stop-after", bad]);
        assert!(
            !ok && text.contains(&format!("--stop-after {bad}")),
            "{text}"
        );
    }
    let (ok, text) = run_task("1", &stopped, &["--stop-after", "7"]);
    assert!(ok && text.contains("stopped after step 7"), "{text}");
    let progress = stopped.join("tasks/1/progress.onrf");
    assert!(progress.is_file() && !stopped.join("tasks/1/result.json").exists());

    // Another task (another config) refuses the state.
    std::fs::create_dir_all(stopped.join("tasks/0")).unwrap();
    std::fs::copy(&progress, stopped.join("tasks/0/progress.onrf")).unwrap();
    let (ok, text) = run_task("0", &stopped, &[]);
    assert!(!ok && text.contains("another config"), "{text}");

    let (ok, text) = run_task("1", &stopped, &[]);
    assert!(ok, "{text}");
    // It goes on from step 8, and its progress lines say so.
    assert!(
        text.contains("  step 8: mse") && !text.contains("  step 1: mse"),
        "{text}"
    );
    assert!(!progress.exists(), "left its progress file");
    same_task_files(&stopped.join("tasks/1"), &whole.join("tasks/1"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The held-out means of a `metrics.json` (`train`'s or `eval`'s) as the sweep records them.
fn metrics_json_mean(dir: &Path) -> serde_json::Value {
    let json: serde_json::Value =
        serde_json::from_slice(&bytes(&dir.join("metrics.json"))).unwrap();
    json["models"][0]["mean"].clone()
}

/// The figures of a task record's metrics that `metrics.json` also holds.
fn same_figures(record: &serde_json::Value, mean: &serde_json::Value, what: &str) {
    for key in [
        "psnr_full",
        "psnr_right",
        "psnr_foreground",
        "psnr_foreground_right",
        "ssim_full",
        "ssim_right",
    ] {
        assert_eq!(record[key], mean[key], "{what}: {key}");
    }
}

/// `tradeoff` (issue 15): a small trade-off writes its description, the CSV, the table and
/// the plots; each variant's figures, at its end and at an anytime step, and its checkpoint
/// equal those of `train` (stopped at that step, then `eval`) run on its own.
#[test]
fn a_small_tradeoff_writes_its_report_and_equals_its_variants_trained_one_by_one() {
    let dir = temp_dir("tradeoff");
    let out = dir.join("out");
    let flags = [
        "tradeoff",
        "--scene",
        "synthetic",
        "--frames",
        "16",
        "--size",
        "32",
        "--preset",
        "tiny",
        "--steps",
        "30",
        "--vary",
        "features=16",
        "--vary",
        "size=24",
        "--at",
        "10,20",
        "--targets",
        "5,99",
        "--budgets",
        "0.001,1000",
        "--fit-steps",
        "5",
        "--out",
    ];
    let (ok, text) = common::run_orbit_nerf(&[&flags[..], &[out.to_str().unwrap()]].concat());
    assert!(ok, "{text}");
    for file in [
        "tradeoff.toml",
        "tradeoff.csv",
        "sweep.md",
        "sweep.csv",
        "pareto_time.png",
        "pareto_memory.png",
        "anytime_features.png",
        "anytime_features_steps.png",
        "anytime_size.png",
        "anytime_size_steps.png",
    ] {
        assert!(out.join(file).is_file(), "{file} missing: {text}");
        if file.ends_with(".png") {
            image::open(out.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        }
    }
    let report = std::fs::read_to_string(out.join("sweep.md")).unwrap();
    assert!(
        report.contains("## What accuracy costs in time"),
        "{report}"
    );
    // Every variant reaches 5 dB; none reaches 99 dB; nothing is scored within 1 ms.
    for variant in ["reference", "features=16", "size=24"] {
        let row = (report.lines())
            .find(|l| l.starts_with(&format!("| {variant} ")) && l.contains("not reached"))
            .unwrap_or_else(|| panic!("no trade-off row of {variant}: {report}"));
        assert_eq!(row.matches("not reached").count(), 1, "{row}");
    }
    assert!(report.contains("- 0.001 s: no variant"), "{report}");
    assert!(report.contains("- 1000 s: `"), "{report}");
    // Three variants, each scored at steps 10, 20 and its end (30).
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 3 * 3, "{csv}");

    // Each variant on its own: `train` to the end and to step 20 (`--stop-after`, then
    // `eval`), on the frames the sweep simulated for it.
    let config = dir.join("features.toml");
    std::fs::write(&config, "features = 16\n").unwrap();
    for (index, size, extra) in [
        (0, "32", vec![]),
        (1, "32", vec!["--config", config.to_str().unwrap()]),
        (2, "24", vec![]),
    ] {
        let task = out.join("tasks").join(index.to_string());
        let record: serde_json::Value =
            serde_json::from_slice(&bytes(&task.join("result.json"))).unwrap();
        let data = task.join("data");
        let data = data.to_str().unwrap();
        let common_flags = [
            "--data",
            data,
            "--size",
            size,
            "--preset",
            "tiny",
            "--steps",
            "30",
            "--fit-steps",
            "5",
        ];
        let end = dir.join(format!("train-{index}"));
        let args = [
            &["train"][..],
            &common_flags,
            &extra,
            &["--out", end.to_str().unwrap()],
        ];
        let (ok, text) = common::run_orbit_nerf(&args.concat());
        assert!(ok, "{text}");
        let checkpoint = bytes(&end.join("checkpoint.onrf"));
        let fnv = orbit_nerf_host::sweep::results::fnv1a(&checkpoint);
        assert_eq!(
            record["checkpoint_fnv1a"],
            format!("{fnv:016x}"),
            "task {index}"
        );
        same_figures(&record["metrics"], &metrics_json_mean(&end), "end");
        let curve = record["curve"].as_array().unwrap();
        let steps: Vec<u64> = curve.iter().map(|p| p["step"].as_u64().unwrap()).collect();
        assert_eq!(steps, [10, 20, 30], "task {index}");
        same_figures(&curve[2]["metrics"], &metrics_json_mean(&end), "end point");

        let stopped = dir.join(format!("stopped-{index}"));
        let args = [
            &["train"][..],
            &common_flags,
            &extra,
            &["--stop-after", "20", "--out", stopped.to_str().unwrap()],
        ];
        let (ok, text) = common::run_orbit_nerf(&args.concat());
        assert!(ok, "{text}");
        let scored = dir.join(format!("eval-{index}"));
        let checkpoint = stopped.join("checkpoint.onrf");
        let (ok, text) = common::run_orbit_nerf(&[
            "eval",
            "--data",
            data,
            "--size",
            size,
            "--fit-steps",
            "5",
            "--checkpoint",
            checkpoint.to_str().unwrap(),
            "--metrics",
            scored.to_str().unwrap(),
        ]);
        assert!(ok, "{text}");
        same_figures(&curve[1]["metrics"], &metrics_json_mean(&scored), "step 20");
    }

    // A bad knob value is refused before anything is written.
    let refused = dir.join("refused");
    let mut bad = flags.to_vec();
    bad[14] = "size=4";
    let (ok, text) = common::run_orbit_nerf(&[&bad[..], &[refused.to_str().unwrap()]].concat());
    assert!(!ok && text.contains("variants[2].size"), "{text}");
    assert!(!refused.join("tradeoff.toml").exists(), "{text}");

    // The same flags continue the folder; other flags are refused without touching it.
    let (ok, text) = common::run_orbit_nerf(&[&flags[..], &[out.to_str().unwrap()]].concat());
    assert!(
        ok && text.contains("3 finished earlier (skipped), 0 to run"),
        "{text}"
    );
    let description = bytes(&out.join("tradeoff.toml"));
    let mut other = flags.to_vec();
    other[10] = "31";
    let (ok, text) = common::run_orbit_nerf(&[&other[..], &[out.to_str().unwrap()]].concat());
    assert!(!ok && text.contains("holds another trade-off"), "{text}");
    assert_eq!(bytes(&out.join("tradeoff.toml")), description);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The image-count study (issue 41): `ablate --image-counts` writes its sweep description into
/// `--out` and runs one task per count and model. Each model holds only its own count of
/// training frames (the test set's never enter its frame store, so never a training batch),
/// every task is scored on all views of the same separate test set, the tasks of a model differ
/// only in the count, and `sweep.md` has the image-count table and its plots.
#[test]
fn an_image_count_study_trains_each_count_and_scores_one_separate_test_set() {
    use orbit_nerf_core::{MemoryPlan, Trainer};
    let dir = temp_dir("image-counts");
    let out = dir.join("out");
    let study = || {
        orbit_nerf(&[
            "ablate",
            "--image-counts",
            "6,3",
            "--test-frames",
            "8",
            "--scene",
            "synthetic",
            "--size",
            "32",
            "--preset",
            "tiny",
            "--steps",
            "6",
            "--fit-steps",
            "2",
            "--threads",
            "1",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap()
    };
    let run = study();
    let text = output_text(&run);
    assert!(run.status.success(), "{text}");
    assert!(out.join("image-counts.toml").is_file());
    let report = std::fs::read_to_string(out.join("sweep.md")).unwrap();
    assert!(report.contains("## Image-count study"), "{report}");
    assert!(
        report.contains("separate test set `lightbox-test`"),
        "{report}"
    );
    for metric in ["psnr", "ssim", "jnb"] {
        assert!(out.join(format!("image_counts_{metric}.png")).is_file());
    }
    let records: Vec<serde_json::Value> = (0..4)
        .map(|i| {
            serde_json::from_slice(&bytes(&out.join(format!("tasks/{i}/result.json")))).unwrap()
        })
        .collect();
    for (i, record) in records.iter().enumerate() {
        let settings = &record["settings"];
        let frames = settings["frames"].as_u64().unwrap() as usize;
        // Tasks 0 and 1 train on 3 frames (the counts ascending), 2 and 3 on 6.
        assert_eq!(frames, if i < 2 { 3 } else { 6 }, "task {i}");
        assert_eq!(
            settings["test"], "scene lightbox-test, 8 frames",
            "task {i}"
        );
        assert_eq!(record["held_out_views"], 8, "task {i}");
        let checkpoint = out.join(format!("tasks/{i}/checkpoint.onrf"));
        let config = orbit_nerf_host::pipeline::checkpoint_config(&checkpoint).unwrap();
        let mut arena = vec![0u8; MemoryPlan::new(&config).total];
        let mut trainer = Trainer::new(config, &mut arena).unwrap();
        orbit_nerf_host::train::restore_checkpoint(&checkpoint, &mut trainer, &[]).unwrap();
        assert_eq!(trainer.frames().len(), frames, "task {i}'s frame store");
    }
    // The same model at both counts: the same settings but the count.
    for (small, large) in [(0, 2), (1, 3)] {
        let mut a = records[small]["settings"].clone();
        let b = &records[large]["settings"];
        a["frames"] = b["frames"].clone();
        assert_eq!(&a, b, "tasks {small} and {large}");
        assert_eq!(records[small]["variant"], records[large]["variant"]);
    }
    // Run again: every task finished, nothing retrained; another study in the folder is refused.
    let again = study();
    assert!(
        output_text(&again).contains("4 finished earlier"),
        "{}",
        output_text(&again)
    );
    let other = orbit_nerf(&[
        "ablate",
        "--image-counts",
        "3,12",
        "--scene",
        "synthetic",
        "--size",
        "32",
        "--out",
        out.to_str().unwrap(),
    ])
    .output()
    .unwrap();
    assert!(!other.status.success());
    assert!(output_text(&other).contains("another image-count study"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// `tradeoff --test-data` (issue 41): every variant trains on all of the data's frames and is
/// scored on every view of the separate test set, which the description and each record name;
/// with `--holdout` it is a usage error.
#[test]
fn a_tradeoff_on_a_separate_test_set_scores_every_test_view() {
    let dir = temp_dir("tradeoff-test-data");
    let (train, test, out) = (dir.join("train"), dir.join("test"), dir.join("out"));
    for (folder, scene, frames) in [(&train, "synthetic", "6"), (&test, "lightbox-test", "5")] {
        let (ok, text) = common::run_orbit_nerf(&[
            "simulate",
            "--scene",
            scene,
            "--frames",
            frames,
            "--size",
            "32",
            "--out",
            folder.to_str().unwrap(),
        ]);
        assert!(ok, "{text}");
    }
    let tradeoff = |extra: &[&str]| {
        let flags = [
            "tradeoff",
            "--data",
            train.to_str().unwrap(),
            "--test-data",
            test.to_str().unwrap(),
            "--size",
            "32",
            "--preset",
            "tiny",
            "--steps",
            "4",
            "--vary",
            "features=16",
            "--fit-steps",
            "2",
            "--out",
            out.to_str().unwrap(),
        ];
        orbit_nerf(&[&flags[..], extra].concat()).output().unwrap()
    };
    let conflict = tradeoff(&["--holdout", "4"]);
    assert_eq!(
        conflict.status.code(),
        Some(2),
        "{}",
        output_text(&conflict)
    );
    assert!(!out.exists());
    let run = tradeoff(&[]);
    assert!(run.status.success(), "{}", output_text(&run));
    let description = std::fs::read_to_string(out.join("tradeoff.toml")).unwrap();
    assert!(description.contains("test_data = "), "{description}");
    assert!(!description.contains("holdout"), "{description}");
    for index in 0..2 {
        let record: serde_json::Value =
            serde_json::from_slice(&bytes(&out.join(format!("tasks/{index}/result.json"))))
                .unwrap();
        assert_eq!(record["held_out_views"], 5, "task {index}");
        assert_eq!(record["settings"]["test"], "data test", "task {index}");
    }
    let report = std::fs::read_to_string(out.join("sweep.md")).unwrap();
    assert!(report.contains("separate test set `test`"), "{report}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `orbit-nerf paper --tables main`: each training set's description written into the folder
/// and run there, `paper.md`'s main table holds a row per training set and model scored on
/// every view of the one separate test set, and a rerun continues (nothing trained again). A
/// replacement for a sweep no table asked for is refused naming the flag.
#[test]
fn the_paper_command_runs_the_main_table_on_each_training_set() {
    let dir = temp_dir("paper");
    let out = dir.join("out");
    let mut flags = Vec::new();
    for scene in ["synthetic", "lightbox", "sunlamp"] {
        let path = dir.join(format!("{scene}.toml"));
        let text = format!(
            "scene = \"{scene}\"\nframes = 6\ntest_scene = \"lightbox-test\"\ntest_frames = 3\nsize = 32\nconfig = \"tiny\"\nsteps = 6\nfit_steps = 2\n\n[[variants]]\nname = \"baseline\"\nset = {{ embedding_dim = 0 }}\n\n[[variants]]\nname = \"ours + pose\"\nset = {{ embedding_dim = 8, pose_correction = true }}\n"
        );
        std::fs::write(&path, text).unwrap();
        flags.push(format!("main-{scene}={}", path.display()));
    }
    let paper = |extra: &[&str]| {
        let mut args = vec![
            "paper",
            "--tables",
            "main",
            "--threads",
            "1",
            "--out",
            out.to_str().unwrap(),
        ];
        for flag in &flags {
            args.extend(["--description", flag.as_str()]);
        }
        args.extend(extra);
        let run = orbit_nerf(&args).output().unwrap();
        (run.status.success(), output_text(&run))
    };
    // The cluster's route: the descriptions only, one sweep's tasks run as its Slurm array
    // runs them, then the gathering runs the rest and skips those.
    let (ok, text) = paper(&["--write-only"]);
    assert!(ok && text.contains("sweep slurm"), "{text}");
    assert!(out.join("main-synthetic.toml").is_file() && !out.join("main-synthetic").exists());
    let description = out.join("main-synthetic.toml");
    let folder = out.join("main-synthetic");
    for index in ["0", "1"] {
        let (description, folder) = (description.to_str().unwrap(), folder.to_str().unwrap());
        let args = ["sweep", "run-task", description, index, "--out", folder];
        let run = orbit_nerf(&args).output().unwrap();
        assert!(run.status.success(), "{}", output_text(&run));
    }
    let (ok, text) = paper(&[]);
    assert!(ok, "{text}");
    assert!(
        text.contains("main-synthetic:\n2 tasks: 2 finished earlier (skipped), 0 to run")
            && text.contains("main-lightbox:\n2 tasks: 0 finished earlier (skipped), 2 to run"),
        "{text}"
    );
    let report = std::fs::read_to_string(out.join("paper.md")).unwrap();
    assert!(
        report.contains("3 views of `lightbox-test` (exact poses)"),
        "{report}"
    );
    // The paper's own figures beside ours (its baseline on Lightbox, its method on Sunlamp).
    assert!(
        report.lines().any(|l| l.starts_with("| `lightbox` ")
            && l.contains("| baseline ")
            && l.contains("| 24.35 / 0.944 / - ")),
        "{report}"
    );
    assert!(report.contains("| 27.14 / 0.951 / 0.0389 "), "{report}");
    for scene in ["synthetic", "lightbox", "sunlamp"] {
        assert!(out.join(format!("main-{scene}.toml")).is_file());
        for model in ["baseline", "ours + pose"] {
            let row = format!("| `{scene}` ");
            assert!(
                report.lines().any(|l| l.starts_with(&row)
                    && l.contains(&format!("| {model} "))
                    && l.contains("| 3 ")),
                "no row for {scene}, {model}:\n{report}"
            );
        }
    }
    let (ok, text) = paper(&[]);
    assert!(
        ok && text.contains("2 finished earlier (skipped), 0 to run"),
        "{text}"
    );
    let (ok, text) = paper(&["--description", "pose-noise=x.toml"]);
    assert!(
        !ok && text.contains("--description pose-noise=x.toml"),
        "{text}"
    );
}
