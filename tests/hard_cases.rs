//! The hard-case suite (issue 13): inputs an adversarial user would try, each run through the
//! CLI binary or the public API, each with the outcome it must have: one clear error naming
//! the flag, file or field (never a panic, a hang or an abort), a refused save, nothing the
//! user did not name deleted or replaced, or training that stays finite.
//!
//! Cases that need the reference data in `../shared/data` (presets, camera file) say so and
//! pass without it. The README's "Hard cases" section lists every case with its command.

mod common;

use common::{Scratch, orbit_nerf, output_text as text, root};
use orbit_nerf_core::glam::Vec3;
use orbit_nerf_core::{Config, PoseCorrection};
use orbit_nerf_host::checkpoint;
use orbit_nerf_host::formats::speedplus::{self, Label, Truth};
use orbit_nerf_host::sim::scene::{Exposure, LabelNoise, SceneSpec};
use orbit_nerf_host::sim::{self, Scene};
use orbit_nerf_host::stream::{Arrival, FrameSource, WatchOptions, WatchedFolder};
use orbit_nerf_host::train;
use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// The run failed cleanly: a non-zero exit that is not a panic or a signal, no score printed,
/// and a message that contains every one of `needles`.
fn assert_clear_error(case: &str, out: &Output, needles: &[&str]) {
    let text = text(out);
    assert!(
        out.status.code().is_some_and(|code| code != 0),
        "{case}: expected a clean non-zero exit, got {:?}: {text}",
        out.status
    );
    assert!(!text.contains("panicked"), "{case}: panicked: {text}");
    assert!(!text.contains("PSNR"), "{case}: printed a score: {text}");
    for needle in needles {
        assert!(text.contains(needle), "{case}: `{needle}` not in: {text}");
    }
}

fn path_str(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Every numeric flag value (of `stream`, `simulate`, `train` and `eval`) that is out of range,
/// not finite or not a number is refused by the argument parser with an error naming the flag,
/// before any work starts (so these need no data). `inf` is accepted only where it means "for
/// ever" (tested below).
#[test]
fn out_of_range_flag_values_are_refused_naming_the_flag() {
    let scratch = Scratch::new("flags");
    let out = scratch.path("out");
    let cases: &[(&str, &str, &str)] = &[
        ("stream", "--rate", "1e-300"),
        ("stream", "--rate", "1e300"),
        ("stream", "--rate", "0"),
        ("stream", "--rate", "-2"),
        ("stream", "--rate", "nan"),
        ("stream", "--rate", "inf"),
        ("stream", "--poll-ms", "18446744073709551615"),
        ("stream", "--poll-ms", "0"),
        ("stream", "--grace-ms", "18446744073709551615"),
        ("stream", "--idle-timeout", "nan"),
        ("stream", "--idle-timeout", "-1"),
        ("stream", "--idle-timeout", "0"),
        ("stream", "--idle-timeout", "1e300"),
        ("stream", "--idle-timeout", "-inf"),
        ("stream", "--frames", "0"),
        ("stream", "--size", "0"),
        ("stream", "--size", "21"),
        ("stream", "--store", "0"),
        ("stream", "--store", "70000"),
        ("stream", "--steps-per-frame", "0"),
        ("stream", "--settle-steps", "-1"),
        ("stream", "--settle-steps", "10000001"),
        ("stream", "--settle-steps", "inf"),
        ("stream", "--holdout", "0"),
        ("stream", "--holdout", "1"),
        ("stream", "--eval-every", "0"),
        ("stream", "--checkpoint-every", "0"),
        ("stream", "--max-frames", "0"),
        ("stream", "--threads", "0"),
        ("stream", "--threads", "100000"),
        ("simulate", "--frames", "0"),
        ("simulate", "--size", "0"),
        ("simulate", "--size", "-1"),
        ("simulate", "--sheet-columns", "0"),
        ("simulate", "--memory-limit", "0"),
        ("simulate", "--memory-limit", "-1G"),
        ("simulate", "--memory-limit", "99999999999T"),
        ("stream", "--memory-limit", "lots"),
        ("train", "--size", "0"),
        ("train", "--size", "-1"),
        ("train", "--size", "70000"),
        ("train", "--size", "inf"),
        ("train", "--holdout", "0"),
        ("train", "--holdout", "nan"),
        ("train", "--steps", "0"),
        ("train", "--steps", "-5"),
        ("train", "--steps", "1e12"),
        ("train", "--steps", "4294967295"),
        ("train", "--seed", "-1"),
        ("train", "--seed", "1e400"),
        ("train", "--threads", "0"),
        ("train", "--threads", "100000"),
        ("train", "--embedding-dim", "129"),
        ("train", "--embedding-dim", "-1"),
        ("train", "--fit-steps", "-1"),
        ("train", "--fit-steps", "1000000"),
        ("train", "--memory-limit", "0"),
        ("train", "--memory-limit", "inf"),
        ("train", "--stop-after", "0"),
        ("train", "--scene-box", "0,0,0,inf,1,1"),
        ("train", "--scene-box", "1,1,1,0,0,0"),
        ("eval", "--size", "0"),
        ("eval", "--threads", "0"),
        ("eval", "--fit-steps", "nan"),
        ("eval", "--memory-limit", "-1G"),
        ("stream", "--stop-after", "0"),
        ("ablate", "--size", "21"),
        ("ablate", "--frames", "1"),
        ("demo", "--steps", "0"),
        ("train", "--seed", "9223372036854775808"),
        ("stream", "--seed", "-1"),
        ("simulate", "--seed", "18446744073709551615"),
    ];
    for &(command, flag, value) in cases {
        let case = format!("{command} {flag} {value}");
        // `--flag=value`, so that negative values reach the flag's own check.
        let flag_value = format!("{flag}={value}");
        let source = match command {
            "train" => ["--data", "no/such/dataset", "--out", path_str(&out)],
            "eval" => ["--data", "no/such/dataset", "--checkpoint", "no/such.onrf"],
            _ => ["--scene", "synthetic", "--out", path_str(&out)],
        };
        let result = orbit_nerf(&[command, &flag_value])
            .args(source)
            .output()
            .unwrap();
        assert_clear_error(&case, &result, &[flag]);
        assert_eq!(result.status.code(), Some(2), "{case}: a usage error");
        assert!(!text(&result).contains("no/such"), "{case}: read the data");
        assert!(!out.exists(), "{case}: created its output");
    }
}

/// `--idle-timeout inf` waits for ever instead of panicking: the folder's END marker ends
/// the stream. With no frame at all, the stream ends non-zero saying so and saves nothing.
#[test]
fn stream_idle_timeout_inf_waits_until_end_and_an_empty_stream_fails() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("idle-inf");
    let watched = scratch.path("watched");
    std::fs::create_dir_all(&watched).unwrap();
    std::fs::copy(
        root().join("../shared/data/speedplus/camera.json"),
        watched.join("camera.json"),
    )
    .unwrap();
    std::fs::write(watched.join("END"), b"").unwrap();
    let out = scratch.path("out");
    let result = orbit_nerf(&[
        "stream",
        "--watch",
        path_str(&watched),
        "--idle-timeout",
        "inf",
        "--scene-box",
        "-1,-1,-1,1,1,1",
        "--out",
        path_str(&out),
    ])
    .output()
    .unwrap();
    assert_clear_error("idle-timeout inf", &result, &["no usable frame"]);
    assert!(!out.join("checkpoint.onrf").exists(), "saved a checkpoint");
}

/// A stream whose every frame is unusable (all black) ends non-zero, reports each frame and
/// never prints a score or saves the untrained model.
#[test]
fn stream_with_only_black_frames_fails_without_a_score() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("black");
    let (watched, labels) = watched_folder(&scratch, 2);
    for label in &labels {
        let stem = label.filename.trim_end_matches(".png");
        image::GrayImage::new(32, 32)
            .save(watched.join(format!("{stem}.png")))
            .unwrap();
        std::fs::write(
            watched.join(format!("{stem}.json")),
            serde_json::to_vec(label).unwrap(),
        )
        .unwrap();
    }
    std::fs::write(watched.join("END"), b"").unwrap();
    let out = scratch.path("out");
    let result = orbit_nerf(&[
        "stream",
        "--watch",
        path_str(&watched),
        "--scene-box",
        "-1,-1,-1,1,1,1",
        "--out",
    ])
    .arg(&out)
    .output()
    .unwrap();
    assert_clear_error("all black", &result, &["all black", "no usable frame"]);
    assert!(!out.join("checkpoint.onrf").exists(), "saved a checkpoint");
}

/// A simulated dataset of `frames` frames at 32 px in `scratch/data`, and a watched folder
/// `scratch/watched` holding only its camera file; returns the folder and the labels.
fn watched_folder(scratch: &Scratch, frames: u32) -> (PathBuf, Vec<Label>) {
    let data = scratch.path("data");
    common::simulated_lightbox(&data, frames, 32);
    let watched = scratch.path("watched");
    std::fs::create_dir_all(&watched).unwrap();
    std::fs::copy(data.join("camera.json"), watched.join("camera.json")).unwrap();
    let labels = speedplus::read_labels(&data.join("labels.json")).unwrap();
    (watched, labels)
}

/// Put frame `label` of `scratch/data` into the watched folder under the name `stem`.
fn publish_frame(scratch: &Scratch, watched: &Path, label: &Label, stem: &str) {
    let image = scratch.path("data/images").join(&label.filename);
    std::fs::copy(image, watched.join(format!("{stem}.png"))).unwrap();
    let mut label = label.clone();
    label.filename = format!("{stem}.png");
    std::fs::write(
        watched.join(format!("{stem}.json")),
        serde_json::to_vec(&label).unwrap(),
    )
    .unwrap();
}

/// Frames lost without a word: a frame whose name sorts before one already taken (an
/// unpadded counter, a late arrival) is still ingested, and `img2` comes before `img10`.
#[test]
fn watched_folder_takes_late_frames_whose_names_sort_earlier() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("late");
    let (watched, labels) = watched_folder(&scratch, 3);
    let options = WatchOptions {
        poll: Duration::from_millis(10),
        grace: Duration::from_millis(100),
        idle_timeout: Some(Duration::from_millis(300)),
    };
    let mut source = WatchedFolder::open(&watched, None, options).unwrap();
    let stop = AtomicBool::new(false);
    let next_name = |source: &mut WatchedFolder| match source.next(&stop) {
        Some(Arrival::Frame(frame)) => frame.name,
        Some(Arrival::Bad(e)) => panic!("bad frame: {e}"),
        None => String::from("(end)"),
    };
    publish_frame(&scratch, &watched, &labels[0], "img10");
    publish_frame(&scratch, &watched, &labels[1], "img2");
    assert!(next_name(&mut source).ends_with("img2.png"));
    assert!(next_name(&mut source).ends_with("img10.png"));
    // Arrives after img10 was taken, and sorts before it (as text and as a number).
    publish_frame(&scratch, &watched, &labels[2], "img1");
    assert!(next_name(&mut source).ends_with("img1.png"));
    assert_eq!(next_name(&mut source), "(end)");
    assert_eq!(source.arrived(), ["img2", "img10", "img1"]);
}

/// `simulate --out` over a dataset folder that also holds the user's own files refuses and
/// deletes nothing; over a plain simulated dataset it replaces it.
#[test]
fn simulate_over_a_dataset_with_other_folders_deletes_nothing() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("sim-out");
    let out = scratch.path("set");
    let simulate = |out: &Path| {
        orbit_nerf(&[
            "simulate", "--scene", "lightbox", "--frames", "2", "--size", "16",
        ])
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
    };
    let first = simulate(&out);
    assert!(first.status.success(), "{}", text(&first));
    // A rerun over the simulator's own output replaces it.
    let again = simulate(&out);
    assert!(again.status.success(), "{}", text(&again));

    std::fs::create_dir_all(out.join("runs")).unwrap();
    std::fs::write(out.join("runs/model.onrf"), b"precious").unwrap();
    let refused = simulate(&out);
    assert_clear_error("foreign folder", &refused, &["runs", "refusing"]);
    assert_eq!(
        std::fs::read(out.join("runs/model.onrf")).unwrap(),
        b"precious"
    );
    assert!(out.join("labels.json").is_file(), "the dataset was touched");

    // A file where the folder should be is not replaced either.
    let file = scratch.path("file");
    std::fs::write(&file, b"mine").unwrap();
    assert_clear_error("out is a file", &simulate(&file), &["not a folder"]);
    assert_eq!(std::fs::read(&file).unwrap(), b"mine");
}

/// A killed `simulate` leaves no dataset at `--out` (it stages in a sibling folder), and the
/// next run removes what the dead run left; a sibling with the user's files stays.
#[test]
fn a_killed_simulate_leaves_no_partial_dataset_behind() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("sim-kill");
    let out = scratch.path("set");
    let staging_of = |pid: u32| scratch.path(&format!("set.partial-{pid}"));
    let mut child = orbit_nerf(&["simulate", "--scene", "lightbox", "--frames", "5000"])
        .args(["--size", "64", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let staging = staging_of(child.id());
    while !staging.exists() {
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!out.exists(), "a partial dataset was left at --out");
    assert!(staging.exists());

    // Not ours: a sibling with the same pattern holding something else.
    let foreign = staging_of(999_999_999);
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), b"mine").unwrap();

    let rerun = orbit_nerf(&["simulate", "--scene", "lightbox", "--frames", "2"])
        .args(["--size", "16", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(rerun.status.success(), "{}", text(&rerun));
    assert!(
        !staging.exists(),
        "the dead run's staging folder is still there"
    );
    assert!(
        foreign.join("notes.txt").is_file(),
        "removed a folder it did not write"
    );
    assert!(out.join("labels.json").is_file());
}

/// A scene whose camera stands 1e20 m away is refused naming the field (it used to hang in a
/// rejection loop that could never accept a sun direction).
#[test]
fn simulate_with_a_camera_1e20_m_away_is_refused() {
    let scratch = Scratch::new("far");
    let base = include_str!("../scenes/synthetic.toml");
    let far = base.replace("distance_m = [5.0, 2.8]", "distance_m = [1e20, 2.8]");
    assert_ne!(far, base);
    let scene = scratch.path("far.toml");
    std::fs::write(&scene, far).unwrap();
    let result = orbit_nerf(&["simulate", "--scene", path_str(&scene), "--out"])
        .arg(scratch.path("out"))
        .output()
        .unwrap();
    assert_clear_error("distance 1e20", &result, &["poses.distance_m", "100 km"]);
}

/// A rerun of `stream` without `--resume` does not replace the previous stream's checkpoint
/// (unless `--force`), `--resume` from another source is refused, and an `--out` that is a
/// file, or `--stop-after 0`, fails before any work.
#[test]
fn stream_outputs_are_never_replaced_silently() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("stream-out");
    let out = scratch.path("run");
    let stream = |scene: &str, out: &Path, extra: &[&str]| {
        orbit_nerf(&["stream", "--scene", scene, "--frames", "4", "--size", "24"])
            .args(["--store", "2", "--steps-per-frame", "1", "--holdout", "3"])
            .args(["--eval-every", "100", "--fit-steps", "1", "--out"])
            .arg(out)
            .args(extra)
            .output()
            .unwrap()
    };
    let zero = stream("lightbox", &out, &["--stop-after", "0"]);
    assert_clear_error("stop after 0 steps", &zero, &["--stop-after"]);
    assert!(!out.exists());
    // Stopped once 2 steps are taken (one per frame: after the second frame).
    let stopped = stream("lightbox", &out, &["--stop-after", "2"]);
    assert!(stopped.status.success(), "{}", text(&stopped));
    let checkpoint = out.join("checkpoint.onrf");
    let saved = std::fs::read(&checkpoint).unwrap();

    let rerun = stream("lightbox", &out, &[]);
    assert_clear_error("rerun", &rerun, &["checkpoint.onrf", "--resume", "--force"]);
    assert_eq!(std::fs::read(&checkpoint).unwrap(), saved);

    let other = stream("sunlamp", &out, &["--resume"]);
    assert_clear_error(
        "resume another source",
        &other,
        &["resume with the same source"],
    );
    assert_eq!(std::fs::read(&checkpoint).unwrap(), saved);

    let resumed = stream("lightbox", &out, &["--resume"]);
    assert!(resumed.status.success(), "{}", text(&resumed));

    let forced = stream("lightbox", &out, &["--force"]);
    assert!(forced.status.success(), "{}", text(&forced));

    let file = scratch.path("file");
    std::fs::write(&file, b"mine").unwrap();
    let into_file = stream("lightbox", &file, &[]);
    assert_clear_error("out is a file", &into_file, &["is a file"]);
    assert_eq!(std::fs::read(&file).unwrap(), b"mine");
}

/// `train --out` naming a file (or a folder below a file) fails before the dataset is read
/// or a step is trained, and leaves the file alone.
#[test]
fn train_out_naming_a_file_fails_before_training() {
    let scratch = Scratch::new("train-out");
    let file = scratch.path("file");
    std::fs::write(&file, b"mine").unwrap();
    for out in [file.clone(), file.join("run")] {
        let result = orbit_nerf(&["train", "--data", "no/such/dataset", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        assert_clear_error("train --out file", &result, &["is a file, not a folder"]);
        assert!(
            !text(&result).contains("no/such/dataset"),
            "read the data first"
        );
    }
    assert_eq!(std::fs::read(&file).unwrap(), b"mine");
}

/// Sizes that need tens of GB fail before anything is allocated, with the plan's numbers,
/// instead of aborting with `memory allocation failed`.
#[test]
fn sizes_that_cannot_fit_fail_with_the_memory_plan() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("memory");
    let out = scratch.path("out");
    let cases: [(&str, Vec<&str>, &[&str]); 3] = [
        (
            "simulate --size 65535",
            vec!["simulate", "--scene", "lightbox", "--size", "65535"],
            &["frames being rendered", "dataset read back"],
        ),
        (
            "stream of 1000 frames at 4096 px",
            vec![
                "stream", "--scene", "lightbox", "--size", "4096", "--store", "1000",
            ],
            &["frame store"],
        ),
        (
            "stream --size 65535",
            vec!["stream", "--scene", "lightbox", "--size", "65535"],
            &["frame store"],
        ),
    ];
    for (case, args, needles) in cases {
        let result = orbit_nerf(&args)
            .args(["--memory-limit", "8G", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        let mut expected = vec!["needs", "memory limit of 8.0 GiB", "--memory-limit"];
        expected.extend_from_slice(needles);
        assert_clear_error(case, &result, &expected);
        assert!(!out.exists(), "{case}: wrote output");
    }
}

/// A checkpoint whose parameters hold a NaN (saved with a valid CRC, as a diverged run would
/// write it) is refused on restore, naming the file and the section, instead of stalling every
/// later step of the resumed run.
#[test]
fn a_checkpoint_with_a_nan_parameter_is_refused_naming_the_file_and_section() {
    use orbit_nerf_core::{MemoryPlan, Trainer};
    use orbit_nerf_host::checkpoint;
    let scratch = Scratch::new("nan-checkpoint");
    let mut config =
        train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT).unwrap();
    config.max_frames = 1;
    config.max_pixels_per_frame = 64;
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let path = scratch.path("run.onrf");
    train::save_checkpoint(&path, &Trainer::new(config, &mut arena).unwrap(), &[]).unwrap();
    let mut saved = checkpoint::load(&path).unwrap();
    let mlp = saved.sections.iter_mut().find(|s| s.name == "mlp").unwrap();
    mlp.bytes[8..12].copy_from_slice(&f32::NAN.to_ne_bytes());
    checkpoint::save(&path, &saved).unwrap();

    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    let error = train::restore_checkpoint(&path, &mut trainer, &[])
        .unwrap_err()
        .to_string();
    for needle in ["run.onrf", "`mlp`", "non-finite value (element 2)"] {
        assert!(error.contains(needle), "`{needle}` not in: {error}");
    }
}

/// A simulated lightbox set of 12 frames at 32 px in `scratch/data` and a small training
/// config (the tiny profile with 128 rays per step) in `scratch/model.toml`; returns both.
fn small_training_run(scratch: &Scratch) -> (PathBuf, PathBuf) {
    let data = scratch.path("data");
    common::simulated_lightbox(&data, 12, 32);
    (data, small_config(scratch, "model.toml", |_| {}))
}

/// The tiny profile with 128 rays per step, changed by `edit`, written to `scratch/name`.
fn small_config(scratch: &Scratch, name: &str, edit: impl FnOnce(&mut Config)) -> PathBuf {
    let mut config =
        train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT).unwrap();
    config.rays_per_batch = 128;
    edit(&mut config);
    let path = scratch.path(name);
    std::fs::write(&path, train::config_to_toml(&config).unwrap()).unwrap();
    path
}

/// `train` on the small run of `small_training_run` for 40 steps into `out`, with `extra`.
fn train_small(data: &Path, model: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "train",
        "--data",
        path_str(data),
        "--size",
        "32",
        "--fit-steps",
        "0",
    ];
    if !extra.contains(&"--resume") {
        args.extend_from_slice(&["--config", path_str(model), "--steps", "40"]);
    }
    args.extend_from_slice(&["--out", path_str(out)]);
    args.extend_from_slice(extra);
    orbit_nerf(&args).output().unwrap()
}

/// Training that survives (issue 18): a run stopped at step 20 (`--stop-after`, as Ctrl-C
/// would) and continued with `--resume` ends with the checkpoint bytes of a run never
/// stopped; a rerun without `--resume` or `--force` does not replace the checkpoint, and a
/// resume on other data is refused.
#[test]
fn a_resumed_train_gives_the_checkpoint_bytes_of_an_uninterrupted_one() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("train-resume");
    let (data, model) = small_training_run(&scratch);
    let whole = scratch.path("whole");
    let result = train_small(&data, &model, &whole, &[]);
    assert!(result.status.success(), "{}", text(&result));

    let part = scratch.path("part");
    let result = train_small(&data, &model, &part, &["--stop-after", "20"]);
    let printed = text(&result);
    assert!(result.status.success(), "{printed}");
    assert!(printed.contains("stopped at step 20 of 40"), "{printed}");
    // Without a terminal the bar is hidden and plain progress lines say how far it is.
    assert!(printed.contains("step 1/20: loss "), "{printed}");
    assert!(printed.contains("rays/s, ETA"), "{printed}");
    assert!(!printed.contains("PSNR"), "scored a stopped run: {printed}");
    let checkpoint = part.join("checkpoint.onrf");
    let stopped = std::fs::read(&checkpoint).unwrap();

    let again = train_small(&data, &model, &part, &[]);
    assert_clear_error(
        "train over an earlier run",
        &again,
        &["earlier training run", "--resume", "--force"],
    );
    assert_eq!(std::fs::read(&checkpoint).unwrap(), stopped, "replaced");
    let other = train_small(&data, &model, &part, &["--resume", "--holdout", "3"]);
    assert_clear_error(
        "resume on other views",
        &other,
        &["resume with the run's --data"],
    );
    assert_eq!(std::fs::read(&checkpoint).unwrap(), stopped, "replaced");

    let resumed = train_small(&data, &model, &part, &["--resume"]);
    let printed = text(&resumed);
    assert!(resumed.status.success(), "{printed}");
    assert!(
        printed.contains("resuming") && printed.contains("at step 20 of 40"),
        "{printed}"
    );
    assert!(
        std::fs::read(&checkpoint).unwrap()
            == std::fs::read(whole.join("checkpoint.onrf")).unwrap(),
        "the resumed run's checkpoint differs from the uninterrupted one"
    );
    let forced = train_small(&data, &model, &whole, &["--force", "--stop-after", "1"]);
    assert!(forced.status.success(), "{}", text(&forced));
}

/// SIGTERM during `train` (as Ctrl-C) stops within the current step (given up) and writes a
/// checkpoint of the last finished one that a later run can load, without scoring.
#[test]
fn sigterm_during_train_writes_a_checkpoint() {
    if common::shared_data().is_none() {
        return;
    }
    use std::io::{BufRead as _, Read as _};
    let scratch = Scratch::new("train-sigterm");
    let (data, model) = small_training_run(&scratch);
    let out = scratch.path("out");
    let mut child = orbit_nerf(&[
        "train",
        "--data",
        path_str(&data),
        "--size",
        "32",
        "--config",
        path_str(&model),
        "--steps",
        "1000000",
        "--out",
        path_str(&out),
    ])
    .stdout(std::process::Stdio::piped())
    .stderr(std::process::Stdio::piped())
    .spawn()
    .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut printed = String::new();
    // The handler is in place before training starts (and before this line is printed).
    while !printed.contains("training on") {
        assert!(stdout.read_line(&mut printed).unwrap() > 0, "{printed}");
    }
    let killed = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    stdout.read_to_string(&mut printed).unwrap();
    let result = child.wait_with_output().unwrap();
    printed.push_str(&text(&result));
    assert!(result.status.success(), "{printed}");
    assert!(printed.contains("stopped at step"), "{printed}");
    assert!(!printed.contains("PSNR"), "scored a stopped run: {printed}");
    let path = out.join("checkpoint.onrf");
    let saved = orbit_nerf_host::checkpoint::load(&path).unwrap();
    let config = train::checkpoint_config(&path, &saved).unwrap();
    assert_eq!(config.steps, 1_000_000);
}

/// A config file's values are checked as the flags are, before the data is read: the error
/// names the file and the field.
#[test]
fn out_of_range_config_file_values_are_refused_naming_the_file_and_field() {
    let scratch = Scratch::new("config-values");
    let tiny = std::fs::read_to_string(root().join("budgets/tiny.toml")).unwrap();
    let cases = [
        ("adam_eps = 1e-15", "adam_eps = nan", "adam_eps"),
        ("adam_eps = 1e-15", "adam_eps = -1.0", "adam_eps"),
        (
            "plane_tv_weight = 0.0",
            "plane_tv_weight = inf",
            "plane_tv_weight",
        ),
        (
            "plane_tv_weight = 0.0",
            "plane_tv_weight = -0.0001",
            "plane_tv_weight",
        ),
        (
            "plane_tv_weight = 0.0",
            "plane_tv_weight = 1e30",
            "plane_tv_weight",
        ),
        (
            "coarse_to_fine_steps = 0",
            "coarse_to_fine_steps = 99999999999",
            "coarse_to_fine_steps",
        ),
        (
            "learning_rate = 0.01",
            "learning_rate = inf",
            "learning_rate",
        ),
        (
            "learning_rate = 0.01",
            "learning_rate = 0.0",
            "learning_rate",
        ),
        ("steps = 2000", "steps = 0", "steps"),
        ("steps = 2000", "steps = -3", "steps"),
        (
            "rays_per_batch = 1024",
            "rays_per_batch = 99999999999",
            "rays_per_batch",
        ),
        // A step so long that a stop request would wait for it (issue 42, fifth group).
        (
            "rays_per_batch = 1024",
            "rays_per_batch = 16777216",
            "rays_per_batch",
        ),
        (
            "occupancy_threshold = 0.01",
            "occupancy_threshold = -inf",
            "occupancy_threshold",
        ),
        ("march_steps = 256", "march_steps = 0", "march_steps"),
    ];
    for (line, bad, field) in cases {
        assert!(tiny.contains(line), "{line}");
        let path = scratch.path(&format!("{field}.toml"));
        std::fs::write(&path, tiny.replace(line, bad)).unwrap();
        let result = orbit_nerf(&["train", "--data", "no/such/dataset", "--config"])
            .arg(&path)
            .arg("--out")
            .arg(scratch.path("out"))
            .output()
            .unwrap();
        assert_clear_error(bad, &result, &[path_str(&path), field]);
        assert!(!text(&result).contains("no/such"), "{bad}: read the data");
    }
}

/// Garbage with exit 0 no more: a run whose parameters go non-finite (a tiny `adam_eps`),
/// one whose scene box no ray meets (0 samples per ray), one whose every frame is black
/// and one that holds out every view end non-zero with the cause, and save no checkpoint.
#[test]
fn garbage_training_runs_fail_with_the_cause_and_save_nothing() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("garbage");
    let (data, model) = small_training_run(&scratch);
    let tiny_eps = small_config(&scratch, "eps.toml", |c| c.adam_eps = 1e-45);
    let far_box = small_config(&scratch, "far.toml", |c| {
        c.aabb_min = [100.0; 3];
        c.aabb_max = [101.0; 3];
    });
    let black = scratch.path("black");
    copy_with_uniform_images(&data, &black, 0);
    type Case<'a> = (&'a str, &'a Path, &'a Path, &'a [&'a str], &'a [&'a str]);
    let cases: [Case; 4] = [
        (
            "tiny adam_eps",
            &data,
            &tiny_eps,
            &[],
            &["training diverged", "adam_eps"],
        ),
        (
            "no ray in the box",
            &data,
            &far_box,
            &[],
            &["0 samples per ray"],
        ),
        (
            "all-black frames",
            &black,
            &model,
            &[],
            &["training views is black"],
        ),
        (
            "every view held out",
            &data,
            &model,
            &["--holdout", "1"],
            &["--holdout 1"],
        ),
    ];
    for (case, data, config, extra, needles) in cases {
        let out = scratch.path("out");
        let result = train_small(data, config, &out, extra);
        assert_clear_error(case, &result, needles);
        assert!(!out.join("checkpoint.onrf").exists(), "{case}: saved");
    }
}

/// Every step skipped (non-finite loss or gradients each time) is garbage too: the check
/// every training command runs refuses the model, naming the cause.
#[test]
fn a_run_whose_every_step_was_skipped_is_refused() {
    use orbit_nerf_core::{MemoryPlan, Trainer};
    use orbit_nerf_host::train::TrainingTally;
    let mut config =
        train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT).unwrap();
    config.max_frames = 1;
    config.max_pixels_per_frame = 64;
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    let tally = TrainingTally {
        steps: 5,
        samples: 100,
    };
    assert!(train::check_trained(Path::new("run"), &trainer, tally).is_ok());
    // The state of a run of 5 steps, all skipped: step, updates, skipped, refreshes, pose
    // updates, padding, then the ray reservoir's counts (none).
    let mut state: Vec<u8> = [5u32, 0, 5, 0, 0, 0]
        .iter()
        .flat_map(|v| v.to_ne_bytes())
        .collect();
    state.extend([0u8; size_of::<orbit_nerf_core::RayCounts>()]);
    trainer.restore_section("state", &state).unwrap();
    let error = train::check_trained(Path::new("run"), &trainer, tally)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("every one of the 5 steps was skipped"),
        "{error}"
    );
}

/// Copy the dataset folder `from` (files and one level of folders) to `to`.
fn copy_dataset(from: &Path, to: &Path) {
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let target = to.join(path.file_name().unwrap());
        if path.is_dir() {
            copy_dataset(&path, &target);
        } else {
            std::fs::create_dir_all(to).unwrap();
            std::fs::copy(&path, &target).unwrap();
        }
    }
}

/// Copy the dataset folder `from` to `to` with every image replaced by one of its size whose
/// every pixel is `value` (0: black, 255: saturated).
fn copy_with_uniform_images(from: &Path, to: &Path, value: u8) {
    copy_dataset(from, to);
    for entry in std::fs::read_dir(to.join("images")).unwrap() {
        let path = entry.unwrap().path();
        let (w, h) = image::image_dimensions(&path).unwrap();
        image::GrayImage::from_pixel(w, h, image::Luma([value]))
            .save(&path)
            .unwrap();
    }
}

/// `train` and `eval` check the model's arena against `--memory-limit` before allocating it,
/// failing with the plan's numbers.
#[test]
fn train_and_eval_over_the_memory_limit_fail_with_the_plan() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("train-memory");
    let (data, model) = small_training_run(&scratch);
    let out = scratch.path("out");
    let expected = [
        "needs",
        "frame store",
        "memory limit of 1.0 MiB",
        "--memory-limit",
    ];
    let result = train_small(&data, &model, &out, &["--memory-limit", "1M"]);
    assert_clear_error("train --memory-limit 1M", &result, &expected);
    // The images (12 of 32 x 32 px) are checked from their headers before they are read.
    let result = train_small(&data, &model, &out, &["--memory-limit", "16K"]);
    let images = ["needs", "images loaded", "memory limit of 16.0 KiB"];
    assert_clear_error("train --memory-limit 16K", &result, &images);
    assert!(!out.join("checkpoint.onrf").exists(), "saved");
    let result = train_small(&data, &model, &out, &["--stop-after", "1"]);
    assert!(result.status.success(), "{}", text(&result));
    let checkpoint = out.join("checkpoint.onrf");
    let result = orbit_nerf(&["eval", "--data", path_str(&data), "--size", "32"])
        .args(["--memory-limit", "1M", "--checkpoint"])
        .arg(&checkpoint)
        .output()
        .unwrap();
    assert_clear_error("eval --memory-limit 1M", &result, &expected);
}

/// The figures a printed line of `print_scores` shows, as the JSON values they came from
/// would print: `(index, [PSNR, right, fg, SSIM, JNB])` per view line.
fn printed_view_lines(printed: &str) -> Vec<(usize, Vec<String>)> {
    printed
        .lines()
        .filter_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let index = fields.first()?.parse().ok()?;
            (fields.len() == 8)
                .then(|| (index, fields[1..6].iter().map(|f| f.to_string()).collect()))
        })
        .collect()
}

/// A JSON number as `print_scores` prints it with `decimals` (null: a NaN, printed `NaN`).
fn as_printed(value: &serde_json::Value, decimals: usize) -> String {
    value
        .as_f64()
        .map_or("NaN".to_owned(), |v| format!("{v:.decimals$}"))
}

/// `train` and `eval` write `metrics.json` (issue 12) holding the figures they print: each
/// view's PSNR (whole, right half, foreground), SSIM and JNB, and the mean.
#[test]
fn train_and_eval_write_metrics_json_with_the_printed_figures() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("metrics-json");
    let (data, model) = small_training_run(&scratch);
    let out = scratch.path("out");
    let trained = train_small(&data, &model, &out, &[]);
    let evaluated = orbit_nerf(&["eval", "--data", path_str(&data), "--size", "32"])
        .args(["--fit-steps", "0", "--checkpoint"])
        .arg(out.join("checkpoint.onrf"))
        .arg("--metrics")
        .arg(scratch.path("eval"))
        .output()
        .unwrap();
    for (command, result, dir) in [
        ("train", trained, out.clone()),
        ("eval", evaluated, scratch.path("eval")),
    ] {
        let printed = text(&result);
        assert!(result.status.success(), "{printed}");
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(json["command"], command);
        let model = &json["models"][0];
        let views = model["views"].as_array().unwrap();
        let lines = printed_view_lines(&printed);
        assert_eq!(lines.len(), views.len(), "{printed}");
        assert_eq!(lines.len(), 2, "two held-out views: {printed}");
        for ((index, figures), view) in lines.iter().zip(views) {
            assert_eq!(view["index"], *index as u64);
            let from_json = vec![
                as_printed(&view["psnr_full"], 2),
                as_printed(&view["psnr_right"], 2),
                as_printed(&view["psnr_foreground"], 2),
                as_printed(&view["ssim_full"], 4),
                as_printed(&view["jnb_full"], 3),
            ];
            assert_eq!(figures, &from_json, "{command} view {index}");
        }
        let mean = format!(
            "mean PSNR over 2 held-out views: {} dB",
            as_printed(&model["mean"]["psnr_full"], 2)
        );
        assert!(printed.contains(&mean), "`{mean}` not in: {printed}");
    }
}

/// Rays exactly in a face plane of the scene box, along its edges and through its corners,
/// rendered through [`Trainer::render_rays`] and trained on (frames whose pixel rows and
/// columns lie in the faces), and the density read on faces, edges and corners: every value
/// is finite and nothing panics (a position on the box's upper faces normalises to exactly 1,
/// the last texel and occupancy cell).
#[test]
fn grazing_rays_along_the_box_faces_edges_and_corners_stay_finite() {
    use orbit_nerf_core::glam::Mat3;
    use orbit_nerf_core::{Camera, MemoryPlan, Pose, Sequential, Trainer};
    let mut config =
        train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT).unwrap();
    config.max_frames = 2;
    config.max_pixels_per_frame = 64;
    config.rays_per_batch = 64;
    config.occupancy_every = 4;
    let (lo, hi) = (config.aabb_min[0], config.aabb_max[0]);
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();

    // Cameras looking along +x from outside the box: pixel row 0 has no vertical component
    // and the last column (or the first) no horizontal one, so with the camera on an edge line
    // row 0 lies in a face plane, that column in another, and their pixel along the edge.
    let camera = |cx: f32, cy: f32| Camera {
        width: 8,
        height: 8,
        fx: 8.0,
        fy: 8.0,
        cx,
        cy,
    };
    let along_x = Mat3::from_cols(Vec3::Z, -Vec3::Y, Vec3::X);
    let frames = [
        (camera(7.5, 0.5), Vec3::new(lo - 3.0, hi, hi)),
        (camera(0.5, 7.5), Vec3::new(lo - 3.0, lo, lo)),
    ];
    for (slot, (camera, center)) in frames.into_iter().enumerate() {
        let pose = Pose {
            rotation: along_x,
            center,
        };
        let pixels: Vec<u8> = (0..64 * 3).map(|i| (i * 37 % 251) as u8).collect();
        trainer
            .set_frame(slot, camera, pose, &pixels, None)
            .unwrap();
    }
    let mut samples = 0;
    for step in 0..12 {
        let report = trainer.step(&Sequential).unwrap();
        assert!(report.mse.is_finite(), "step {step}: loss {}", report.mse);
        assert!(!report.skipped, "step {step} skipped");
        samples += report.samples;
    }
    assert!(samples > 0, "the grazing frames' rays sampled nothing");
    assert_eq!(trainer.first_non_finite_section(), None);

    let (l, h) = (lo, hi);
    let rays: [([f32; 3], [f32; 3]); 10] = [
        ([l - 5.0, h, 0.3], [1.0, 0.0, 0.0]),     // in the face y = max
        ([l - 5.0, l - 5.0, l], [1.0, 1.0, 0.0]), // in the face z = min, diagonally
        ([l - 5.0, h, h], [1.0, 0.0, 0.0]),       // along an upper edge
        ([l - 5.0, l, l], [1.0, 0.0, 0.0]),       // along a lower edge
        ([l - 5.0, l - 5.0, l - 5.0], [1.0, 1.0, 1.0]), // through two corners
        ([0.5 * (l + h), h + 1.0, h - 1.0], [1.0, -1.0, 1.0]), // touching a corner only
        ([h, h, h], [-1.0, -1.0, -1.0]),          // from a corner inwards
        ([h, 0.0, 0.0], [1.0, 0.0, 0.0]),         // from a face outwards
        ([l - 5.0, h, 0.0], [1.0, 1e-13, 0.0]),   // almost in the face
        ([0.0, h, h], [0.0, 0.0, -1.0]),          // inside, along an edge
    ];
    let origins: Vec<[f32; 3]> = rays.iter().map(|r| r.0).collect();
    let directions: Vec<[f32; 3]> = rays.iter().map(|r| r.1).collect();
    let mut rgb = vec![0.0f32; rays.len() * 3];
    let samples = trainer
        .render_rays(&Sequential, &origins, &directions, &[], &mut rgb)
        .unwrap();
    assert!(samples.is_finite(), "mean samples per ray {samples}");
    assert!(rgb.iter().all(|v| v.is_finite()), "{rgb:?}");

    let corners_and_faces: Vec<[f32; 3]> = [l, 0.0, h]
        .into_iter()
        .flat_map(|x| [l, 0.0, h].map(|y| (x, y)))
        .flat_map(|(x, y)| [l, 0.0, h].map(|z| [x, y, z]))
        .collect();
    let mut sigma = vec![0.0f32; corners_and_faces.len()];
    trainer
        .density_at(&Sequential, &corners_and_faces, &mut sigma)
        .unwrap();
    assert!(sigma.iter().all(|v| v.is_finite()), "{sigma:?}");
}

/// A lightbox set of 12 frames at 32 px in `out`, its scene changed by `edit` first (needs
/// the reference data).
fn simulated_lightbox_with(out: &Path, edit: impl FnOnce(&mut SceneSpec)) {
    let mut scene = Scene::load("lightbox").unwrap();
    scene.spec.frames = 12;
    scene.spec.size = 32;
    edit(&mut scene.spec);
    sim::simulate(&scene, out, &|| {}).unwrap();
}

/// The mean held-out PSNR a successful run printed (finite: a NaN or an infinity fails).
fn printed_mean_psnr(case: &str, out: &Output) -> f64 {
    let printed = text(out);
    assert!(out.status.success(), "{case}: {printed}");
    let psnr: f64 = printed
        .lines()
        .find_map(|line| line.strip_prefix("mean PSNR over "))
        .and_then(|rest| rest.split(": ").nth(1))
        .and_then(|value| value.strip_suffix(" dB"))
        .and_then(|value| value.parse().ok())
        .unwrap_or_else(|| panic!("{case}: no mean PSNR in: {printed}"));
    assert!(psnr.is_finite(), "{case}: mean PSNR {psnr}");
    psnr
}

/// The pose corrections (translation, rotation vector part) of every frame slot of the
/// checkpoint at `path`, restored into a trainer of its config.
fn pose_corrections(path: &Path) -> Vec<PoseCorrection> {
    use orbit_nerf_core::{MemoryPlan, Trainer};
    let config = orbit_nerf_host::pipeline::checkpoint_config(path).unwrap();
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    train::restore_checkpoint(path, &mut trainer, &[]).unwrap();
    (0..config.max_frames as usize)
        .filter_map(|slot| trainer.pose_correction(slot))
        .collect()
}

/// Pose labels 5 degrees (and 5 cm) off, trained with pose correction: the run scores a
/// finite PSNR, and the learnt corrections move off zero but stay finite and bounded.
#[test]
fn five_degree_pose_label_noise_trains_with_bounded_corrections() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("pose-noise");
    let data = scratch.path("data");
    simulated_lightbox_with(&data, |spec| {
        spec.effects.label_noise = Some(LabelNoise {
            rotation_deg: 5.0,
            translation_m: 0.05,
        });
    });
    let model = small_config(&scratch, "model.toml", |c| c.pose_correction = true);
    let out = scratch.path("out");
    let result = train_small(&data, &model, &out, &[]);
    let psnr = printed_mean_psnr("5 degree pose noise", &result);
    assert!(psnr > 10.0, "5 degree pose noise: mean PSNR {psnr} dB");
    let corrections = pose_corrections(&out.join("checkpoint.onrf"));
    assert!(
        corrections
            .iter()
            .any(|c| c.dt != Vec3::ZERO || c.v != Vec3::ZERO),
        "no correction was learnt"
    );
    for c in &corrections {
        assert!(c.dt.is_finite() && c.v.is_finite(), "{c:?}");
        // Within 0.5 m and 30 degrees (|v| = sin(angle / 2)).
        assert!(c.dt.length() < 0.5 && c.v.length() < 0.26, "{c:?}");
    }
}

/// Frames exposed at 0.01x (nearly black, not all black) and 100x (the target saturated):
/// training stays finite and the run scores a finite PSNR (an all-black set is refused, as
/// `garbage_training_runs_fail_with_the_cause_and_save_nothing` checks).
#[test]
fn exposure_of_a_hundredth_and_a_hundred_times_trains_finite_and_scores() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("exposure");
    let model = small_config(&scratch, "model.toml", |_| {});
    for exposure in [0.01f32, 100.0] {
        let data = scratch.path(&format!("data-{exposure}"));
        simulated_lightbox_with(&data, |spec| {
            spec.effects.exposure = Some(Exposure {
                range: [exposure; 2],
                black_level: 0.0,
            });
        });
        let out = scratch.path(&format!("out-{exposure}"));
        let result = train_small(&data, &model, &out, &[]);
        printed_mean_psnr(&format!("exposure {exposure}x"), &result);
    }
}

/// Every frame all white (saturated): unlike all-black frames there is something to learn
/// (a white target, or with masks a white target on the background colour), so the run
/// trains finite and scores. Without masks the model renders the white frames exactly and
/// the PSNR is +infinity (as scikit-image gives for a perfect match), never NaN.
#[test]
fn all_saturated_frames_train_finite_and_score() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("white");
    let (data, model) = small_training_run(&scratch);
    let white = scratch.path("white");
    copy_with_uniform_images(&data, &white, 255);
    let result = train_small(&white, &model, &scratch.path("masked"), &[]);
    printed_mean_psnr("all-white frames", &result);
    let result = train_small(&white, &model, &scratch.path("unmasked"), &["--no-masks"]);
    let printed = text(&result);
    assert!(result.status.success(), "{printed}");
    assert!(
        printed.contains("mean PSNR over 2 held-out views: inf dB"),
        "{printed}"
    );
}

/// The same images with the labels' translations and the scene box scaled by 1e-3 (a 1 mm
/// target) and 1e3 (1 km): the held-out PSNR should be within 1 dB of the unscaled run's.
/// Density and the learned translations are per length unit (the box's largest half-side over
/// 1.5), so the optical depth of a step does not depend on the scene's scale (before that
/// change: 25.4 dB unscaled, 19.9 dB at 1 mm, 20.6 dB at 1 km).
#[test]
fn a_target_of_a_millimetre_and_of_a_kilometre_scores_as_the_unscaled_one() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("scale");
    let (data, model) = small_training_run(&scratch);
    let truth = Truth::read(&data.join("truth.json")).unwrap();
    let mut psnr = Vec::new();
    for scale in [1.0f64, 1e-3, 1e3] {
        let scaled = scratch.path(&format!("data-{scale}"));
        copy_dataset(&data, &scaled);
        let mut labels = speedplus::read_labels(&data.join("labels.json")).unwrap();
        for label in &mut labels {
            label.r_vo2to_vbs = label.r_vo2to_vbs.map(|r| r * scale);
        }
        speedplus::write_labels(&scaled.join("labels.json"), &labels).unwrap();
        let mut scaled_truth = truth.clone();
        scaled_truth.target_box_min = truth.target_box_min.map(|v| v * scale as f32);
        scaled_truth.target_box_max = truth.target_box_max.map(|v| v * scale as f32);
        for frame in &mut scaled_truth.frames {
            frame.r_vo2to_vbs_true = frame.r_vo2to_vbs_true.map(|r| r * scale);
        }
        scaled_truth.write(&scaled.join("truth.json")).unwrap();
        let scene_box = scaled_truth
            .target_box_min
            .iter()
            .chain(&scaled_truth.target_box_max)
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(",");
        let out = scratch.path(&format!("out-{scale}"));
        let result = train_small(&scaled, &model, &out, &["--scene-box", &scene_box]);
        let scored = printed_mean_psnr(&format!("scale {scale}"), &result);
        eprintln!("scale {scale}: {scored:.2} dB");
        psnr.push(scored);
    }
    // A trained model, well above a blank render, so "within 1 dB" is not met trivially.
    assert!(psnr[0] > 20.0, "unscaled: {} dB", psnr[0]);
    for (scale, scaled) in [1e-3, 1e3].iter().zip(&psnr[1..]) {
        assert!(
            (scaled - psnr[0]).abs() < 1.0,
            "scale {scale}: {scaled:.2} dB, unscaled {:.2} dB",
            psnr[0]
        );
    }
}

/// Steps of the tiny profile in CI; `ORBIT_NERF_TINY_STEPS` sets a longer run (README).
const TINY_PROFILE_STEPS: u32 = 150;

/// A long run of the tiny profile (`budgets/tiny.toml`, 1024 rays per step) stays finite:
/// every step's loss finite, none skipped, the parameters finite (`train` checks them before
/// saving) and a finite score.
#[test]
fn a_long_run_of_the_tiny_profile_stays_finite() {
    if common::shared_data().is_none() {
        return;
    }
    let steps = std::env::var("ORBIT_NERF_TINY_STEPS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(TINY_PROFILE_STEPS)
        .to_string();
    let scratch = Scratch::new("tiny-long");
    let data = scratch.path("data");
    common::simulated_lightbox(&data, 12, 32);
    let tiny = root().join("budgets/tiny.toml");
    let result = orbit_nerf(&["train", "--data", path_str(&data), "--size", "32"])
        .args([
            "--fit-steps",
            "0",
            "--steps",
            &steps,
            "--config",
            path_str(&tiny),
        ])
        .args(["--out", path_str(&scratch.path("out"))])
        .output()
        .unwrap();
    printed_mean_psnr("tiny profile", &result);
    let printed = text(&result);
    assert!(printed.contains(", 0 steps skipped"), "{printed}");
    let losses: Vec<f64> = printed
        .split(['\r', '\n'])
        .filter_map(|line| line.split("loss ").nth(1)?.split(',').next()?.parse().ok())
        .collect();
    assert!(!losses.is_empty(), "no progress line: {printed}");
    assert!(losses.iter().all(|loss| loss.is_finite()), "{losses:?}");
}

/// Output into a pipe whose reader has gone (`orbit-nerf ... | head -1`) ends the process
/// quietly by SIGPIPE; it was a panic in `println!` ("failed printing to stdout").
#[cfg(unix)]
#[test]
fn output_into_a_closed_pipe_ends_quietly_without_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    let scratch = Scratch::new("closed-pipe");
    let out = scratch.path("set");
    // The reader is closed before the process starts, so its first line meets a broken pipe.
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let output = orbit_nerf(&[
        "simulate",
        "--scene",
        "synthetic",
        "--frames",
        "2",
        "--size",
        "32",
        "--out",
        out.to_str().unwrap(),
    ])
    .stdout(writer)
    .output()
    .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        output.status.signal(),
        Some(13),
        "{:?}: {stderr}",
        output.status
    );
}

/// No score from a model that sampled nothing (issue 42, first group): `eval` of a
/// checkpoint on views whose rays all miss its scene box (every label has the target behind
/// the camera) exits non-zero naming the 0 samples per ray, and writes no render.
#[test]
fn eval_where_no_ray_meets_the_box_gives_no_score_and_no_render() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("eval-no-samples");
    let (data, model) = small_training_run(&scratch);
    let run = scratch.path("run");
    let trained = train_small(&data, &model, &run, &[]);
    assert!(trained.status.success(), "{}", text(&trained));
    // The same views with every target moved behind its camera.
    let behind = scratch.path("behind");
    copy_images_and_camera(&data, &behind);
    let mut labels = read_json(&data.join("labels.json"));
    for label in labels.as_array_mut().unwrap() {
        label["r_Vo2To_vbs_true"] = serde_json::json!([0.0, 0.0, -5.0]);
    }
    std::fs::write(behind.join("labels.json"), labels.to_string()).unwrap();
    let renders = scratch.path("renders");
    let out = orbit_nerf(&[
        "eval",
        "--checkpoint",
        path_str(&run.join("checkpoint.onrf")),
        "--data",
        path_str(&behind),
        "--size",
        "32",
        "--fit-steps",
        "0",
        "--renders",
        path_str(&renders),
    ])
    .output()
    .unwrap();
    assert_clear_error(
        "eval with every ray outside the box",
        &out,
        &["0 samples per ray", "no score"],
    );
    let written = std::fs::read_dir(&renders).map_or(0, |d| d.count());
    assert_eq!(written, 0, "renders written for a refused evaluation");
}

/// Files replaced without `--force` (issue 42, sixth group): `train`'s report files, `eval`'s
/// renders and metrics.json, `render`'s views and `simulate`'s contact sheet are refused
/// before any work when they exist, naming the file and `--force`, and left as they were.
#[test]
fn outputs_that_exist_are_never_replaced_without_force() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("no-replace");
    let (data, model) = small_training_run(&scratch);
    let keep = b"the user's own file".as_slice();
    let unchanged =
        |path: &Path| assert_eq!(std::fs::read(path).unwrap(), keep, "{}", path.display());

    // A run folder that holds a config.toml of the user's (no checkpoint).
    let run = scratch.path("run");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(run.join("config.toml"), keep).unwrap();
    let out = train_small(&data, &model, &run, &[]);
    assert_clear_error("train over config.toml", &out, &["config.toml", "--force"]);
    unchanged(&run.join("config.toml"));
    assert!(!run.join("checkpoint.onrf").exists());
    let out = train_small(&data, &model, &run, &["--force"]);
    assert!(out.status.success(), "{}", text(&out));
    let run_flag = path_str(&run);

    // eval's renders and metrics.json, render's views.
    let renders = scratch.path("renders");
    std::fs::create_dir_all(&renders).unwrap();
    std::fs::write(renders.join("view_000.png"), keep).unwrap();
    let eval = |extra: &[&str]| {
        let mut args = vec!["eval", "--run", run_flag, "--renders", path_str(&renders)];
        args.extend_from_slice(extra);
        orbit_nerf(&args).output().unwrap()
    };
    assert_clear_error(
        "eval over a render",
        &eval(&[]),
        &["view_000.png", "--force"],
    );
    unchanged(&renders.join("view_000.png"));
    let metrics = scratch.path("metrics");
    std::fs::create_dir_all(&metrics).unwrap();
    std::fs::write(metrics.join("metrics.json"), keep).unwrap();
    let out = orbit_nerf(&["eval", "--run", run_flag, "--metrics", path_str(&metrics)])
        .output()
        .unwrap();
    assert_clear_error("eval over metrics.json", &out, &["metrics.json", "--force"]);
    unchanged(&metrics.join("metrics.json"));
    let out = orbit_nerf(&["render", "--run", run_flag, "--out", path_str(&renders)])
        .output()
        .unwrap();
    assert_clear_error("render over a view", &out, &["view_000.png", "--force"]);
    unchanged(&renders.join("view_000.png"));
    let out = eval(&["--force"]);
    assert!(out.status.success(), "{}", text(&out));

    // simulate's contact sheet, checked before anything is rendered.
    let sheet = scratch.path("sheet.png");
    std::fs::write(&sheet, keep).unwrap();
    let sim_out = scratch.path("sim");
    let out = orbit_nerf(&[
        "simulate",
        "--scene",
        "lightbox",
        "--frames",
        "2",
        "--size",
        "16",
        "--out",
        path_str(&sim_out),
        "--contact-sheet",
        path_str(&sheet),
    ])
    .output()
    .unwrap();
    assert_clear_error(
        "simulate over a contact sheet",
        &out,
        &["sheet.png", "--force"],
    );
    unchanged(&sheet);
    assert!(
        !sim_out.exists(),
        "simulated although the sheet was refused"
    );
}

/// Memory the plan forgot (issue 42, fourth group): `export` checks the model it restores
/// (its arena) and the density grid against `--memory-limit` before reading the file, as
/// `eval` does, and writes nothing.
#[test]
fn export_checks_the_models_memory_before_reading_it() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("export-memory");
    let (data, model) = small_training_run(&scratch);
    let run = scratch.path("run");
    let out = train_small(&data, &model, &run, &[]);
    assert!(out.status.success(), "{}", text(&out));
    let mesh = scratch.path("mesh.ply");
    let out = orbit_nerf(&[
        "export",
        "mesh",
        "--run",
        path_str(&run),
        "--out",
        path_str(&mesh),
        "--memory-limit",
        "64K",
    ])
    .output()
    .unwrap();
    assert_clear_error(
        "export over the memory limit",
        &out,
        &["checkpoint.onrf", "memory limit", "density grid", "planes"],
    );
    assert!(!mesh.exists());
}

/// Address space a process of the binary takes beside its memory plan: code, thread stacks,
/// small allocations. glibc's malloc would reserve 64 MiB of (untouched) address space per
/// thread arena on top, so the capped runs use one arena (`MALLOC_ARENA_MAX=1`).
const PROCESS_ALLOWANCE_MIB: u64 = 128;

/// The total of the plan's stage `stage` as `train --dry-run` prints it, in MiB.
fn planned_mib(printed: &str, stage: &str) -> f64 {
    let line = (printed.lines())
        .find_map(|l| l.trim().strip_prefix(&format!("{stage}: ")))
        .unwrap_or_else(|| panic!("no `{stage}` line in: {printed}"));
    let (value, unit) = line.split_once(' ').unwrap();
    let value: f64 = value.parse().unwrap();
    match &unit[..3] {
        "KiB" => value / 1024.0,
        "MiB" => value,
        "GiB" => value * 1024.0,
        _ => panic!("unit of {line}"),
    }
}

/// No command aborts on an allocation (issue 42, fourth group): a model planned at about 90 %
/// of `--memory-limit` goes through `train` (with its save and scoring), `eval` and `export`
/// under an address-space cap of the limit plus [`PROCESS_ALLOWANCE_MIB`], which leaves no
/// room for a copy of the checkpoint: restoring and saving work in the arena itself. The
/// printed plan (`train --dry-run`) is what sizes the model.
#[test]
fn a_model_at_nine_tenths_of_its_limit_trains_saves_scores_and_exports_under_a_cap() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("address-space");
    let data = scratch.path("data");
    common::simulated_lightbox(&data, 12, 32);
    let limit_mib = 768u64;
    let limit = format!("{limit_mib}M");
    let config = scratch.path("model.toml");
    let run = scratch.path("run");
    let base = |resolution: u32| {
        let fields =
            format!("resolutions = [32, 64, {resolution}, 0]\nsteps = 3\nwarmup_steps = 1\n");
        std::fs::write(&config, fields).unwrap();
        vec![
            "train".to_string(),
            "--data".into(),
            path_str(&data).into(),
            "--size".into(),
            "32".into(),
            "--config".into(),
            path_str(&config).into(),
            "--memory-limit".into(),
            limit.clone(),
            "--out".into(),
            path_str(&run).into(),
        ]
    };
    let dry_run = |resolution: u32| {
        let mut args = base(resolution);
        args.push("--dry-run".into());
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        orbit_nerf(&args).output().unwrap()
    };
    // The finest plane resolution whose plan stays within 90 % of the limit (the plan grows
    // with its square).
    let (mut low, mut high) = (64u32, 1024u32);
    while high - low > 1 {
        let middle = (low + high) / 2;
        let out = dry_run(middle);
        let fits = out.status.success()
            && planned_mib(&text(&out), "train, save, score") <= 0.9 * limit_mib as f64;
        *(if fits { &mut low } else { &mut high }) = middle;
    }
    let out = dry_run(low);
    let printed = text(&out);
    assert!(out.status.success(), "{printed}");
    assert!(printed.contains("every stage fits"), "{printed}");
    assert!(!run.exists(), "the dry run wrote {}", run.display());
    let planned = planned_mib(&printed, "train, save, score");
    assert!(planned > 0.85 * limit_mib as f64, "{printed}");

    let capped = |args: &[String]| {
        let mut command = std::process::Command::new("sh");
        command
            .arg("-c")
            .arg(format!(
                "ulimit -v {} && exec \"$0\" \"$@\"",
                (limit_mib + PROCESS_ALLOWANCE_MIB) * 1024
            ))
            .arg(env!("CARGO_BIN_EXE_orbit-nerf"))
            .args(args)
            .env("MALLOC_ARENA_MAX", "1")
            .current_dir(root());
        command.output().unwrap()
    };
    let succeeded = |args: &[String]| {
        let out = capped(args);
        assert!(out.status.success(), "{args:?}: {}", text(&out));
        text(&out)
    };
    succeeded(&base(low));
    let checkpoint = std::fs::metadata(run.join("checkpoint.onrf"))
        .unwrap()
        .len();
    // The cap leaves less room than a second copy of the model would take.
    let room = (limit_mib as f64 - planned + PROCESS_ALLOWANCE_MIB as f64) * (1 << 20) as f64;
    assert!(room < checkpoint as f64, "{room} vs {checkpoint}");
    let strings = |args: &[&str]| args.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let scored = succeeded(&strings(&[
        "eval",
        "--run",
        path_str(&run),
        "--memory-limit",
        &limit,
        "--renders",
        path_str(&scratch.path("eval")),
    ]));
    assert!(scored.contains("mean PSNR"), "{scored}");
    let mesh = scratch.path("mesh.ply");
    let export = |threshold: &str| {
        strings(&[
            "export",
            "mesh",
            "--run",
            path_str(&run),
            "--out",
            path_str(&mesh),
            "--resolution",
            "64",
            "--threshold",
            threshold,
            "--memory-limit",
            &limit,
        ])
    };
    // Three steps leave no surface at the default density: the refusal says where the
    // densities lie, and the export at their middle has a surface.
    let refused = text(&capped(&export("1e9")));
    let range = refused.split("run from ").nth(1).expect(&refused);
    let (lowest, highest) = range.split_once(" to ").expect(&refused);
    let highest = highest.split(';').next().unwrap();
    let middle = (lowest.parse::<f64>().unwrap() + highest.parse::<f64>().unwrap()) / 2.0;
    succeeded(&export(&middle.to_string()));
    assert!(mesh.is_file());
}

/// A SPEED+ folder's camera, images and masks copied into `to` (labels and truth left out).
fn copy_images_and_camera(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in ["camera.json", "images", "masks"] {
        let source = from.join(entry);
        if source.is_dir() {
            std::fs::create_dir_all(to.join(entry)).unwrap();
            for file in std::fs::read_dir(&source).unwrap() {
                let file = file.unwrap().path();
                std::fs::copy(&file, to.join(entry).join(file.file_name().unwrap())).unwrap();
            }
        } else {
            std::fs::copy(&source, to.join(entry)).unwrap();
        }
    }
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Duplicates and inconsistent truth (issue 42, second group) and values no camera has
/// (seventh): labels that name an image twice (same or other pose), a truth file that names
/// one twice, a truth quaternion that is not unit, a target 1e30 m away or at the camera, an
/// inverted truth box: each refused by `train` naming the file and the field, nothing written.
#[test]
fn duplicate_labels_and_impossible_poses_are_refused_naming_the_file_and_field() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("bad-poses");
    let (data, model) = small_training_run(&scratch);
    let labels = read_json(&data.join("labels.json"));
    let truth = read_json(&data.join("truth.json"));
    type Edit = fn(&mut serde_json::Value, &mut serde_json::Value);
    let cases: [(&str, Edit, &str, &str); 7] = [
        (
            "same image twice, same pose",
            |l, _| {
                let first = l[0].clone();
                l.as_array_mut().unwrap().push(first);
            },
            "labels.json",
            "filename",
        ),
        (
            "same image twice, other pose",
            |l, _| {
                let mut first = l[0].clone();
                first["r_Vo2To_vbs_true"] = serde_json::json!([0.1, 0.0, 4.0]);
                l.as_array_mut().unwrap().push(first);
            },
            "labels.json",
            "filename",
        ),
        (
            "truth names an image twice",
            |_, t| {
                let first = t["frames"][0].clone();
                t["frames"].as_array_mut().unwrap().push(first);
            },
            "truth.json",
            "frames[12].filename",
        ),
        (
            "truth quaternion not unit",
            |_, t| {
                t["frames"][2]["q_vbs2tango_true"] = serde_json::json!([0.9, 0.1, 0.1, 0.1]);
            },
            "truth.json",
            "frames[2].q_vbs2tango_true",
        ),
        (
            "target 1e30 m away",
            |l, _| {
                l[3]["r_Vo2To_vbs_true"] = serde_json::json!([0.0, 0.0, 1e30]);
            },
            "labels.json",
            "[3].r_Vo2To_vbs_true",
        ),
        (
            "camera at the target's origin",
            |l, _| {
                l[1]["r_Vo2To_vbs_true"] = serde_json::json!([0.0, 0.0, 0.0]);
            },
            "labels.json",
            "[1].r_Vo2To_vbs_true",
        ),
        (
            "inverted truth box",
            |_, t| {
                let (min, max) = (t["target_box_min"].clone(), t["target_box_max"].clone());
                (t["target_box_min"], t["target_box_max"]) = (max, min);
            },
            "truth.json",
            "target_box_min",
        ),
    ];
    for (k, (case, edit, file, field)) in cases.into_iter().enumerate() {
        let folder = scratch.path(&format!("case{k}"));
        copy_images_and_camera(&data, &folder);
        let (mut l, mut t) = (labels.clone(), truth.clone());
        edit(&mut l, &mut t);
        std::fs::write(folder.join("labels.json"), l.to_string()).unwrap();
        std::fs::write(folder.join("truth.json"), t.to_string()).unwrap();
        let out = scratch.path(&format!("run{k}"));
        let result = train_small(&folder, &model, &out, &[]);
        assert_clear_error(case, &result, &[file, field]);
        assert!(!out.exists(), "{case}: wrote {}", out.display());
    }
}

/// Errors that name the right thing (issue 42, eighth group): an image whose header is a
/// GIF's (with a huge declared size) is named as a GIF, not as the decoder's memory limit;
/// an OBJ target with a vertex at 1e30 is named as such, not as a mesh without triangles.
#[test]
fn a_gif_named_png_and_a_far_vertex_are_named_for_what_they_are() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("named-errors");
    let (data, model) = small_training_run(&scratch);
    let mut gif = b"GIF89a".to_vec();
    gif.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0x3b]);
    std::fs::write(data.join("images/img000002.png"), &gif).unwrap();
    let out = scratch.path("run");
    let result = train_small(&data, &model, &out, &[]);
    assert_clear_error("GIF-headed PNG", &result, &["img000002.png", "GIF"]);
    assert!(!text(&result).contains("Memory limit"), "{}", text(&result));

    let mesh = scratch.path("far.obj");
    std::fs::write(
        &mesh,
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1e30 0 1\nf 1 2 3\nf 1 2 4\n",
    )
    .unwrap();
    let base = std::fs::read_to_string(root().join("scenes/synthetic.toml")).unwrap();
    let scene = base
        .replace(
            "model = \"tango\"\nlandmarks = \"tango-landmarks.csv\"",
            &format!("model = \"mesh\"\npath = \"{}\"", mesh.display()),
        )
        .replace(
            "[target.materials]\nbody = \"mli\"\npanel = \"solar_cell\"\nantenna = \"metal\"\n",
            "",
        );
    let scene_path = scratch.path("far.toml");
    std::fs::write(&scene_path, scene).unwrap();
    let sim_out = scratch.path("sim");
    let result = orbit_nerf(&[
        "simulate",
        "--scene",
        path_str(&scene_path),
        "--frames",
        "2",
    ])
    .args(["--size", "16", "--out", path_str(&sim_out)])
    .output()
    .unwrap();
    assert_clear_error("OBJ vertex at 1e30", &result, &["far.obj", "farther than"]);
    assert!(!sim_out.exists());
}

/// Values no camera has (issue 42, seventh group): a distortion coefficient of -50, a focal
/// length of 1e9 px, a skewed or projective camera matrix, each refused by `train` naming
/// `camera.json` and the field; a camera inside the target's stated box refused naming the
/// frame; label noise of 1e30 degrees in a scene file refused by `simulate`. Nothing written.
#[test]
fn camera_values_no_lens_has_are_refused_naming_the_file_and_field() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("bad-camera");
    let (data, model) = small_training_run(&scratch);
    let camera = read_json(&data.join("camera.json"));
    type Edit = fn(&mut serde_json::Value);
    let cases: [(&str, Edit, &str); 5] = [
        (
            "k1 = -50",
            |c| c["distCoeffs"][0] = serde_json::json!(-50.0),
            "distCoeffs[0]",
        ),
        (
            "fx = 1e9 px",
            |c| {
                c["cameraMatrix"][0][0] = serde_json::json!(1e9);
                c.as_object_mut().unwrap().remove("fx");
            },
            "cameraMatrix[0][0]",
        ),
        (
            "skewed matrix",
            |c| c["cameraMatrix"][0][1] = serde_json::json!(10.0),
            "cameraMatrix[0][1]",
        ),
        (
            "projective last row",
            |c| c["cameraMatrix"][2] = serde_json::json!([0.0, 1.0, 1.0]),
            "cameraMatrix[2][1]",
        ),
        (
            "a row of two numbers",
            |c| c["cameraMatrix"][1] = serde_json::json!([0.0, 1.0]),
            "cameraMatrix[1]",
        ),
    ];
    for (k, (case, edit, field)) in cases.into_iter().enumerate() {
        let folder = scratch.path(&format!("case{k}"));
        copy_images_and_camera(&data, &folder);
        for file in ["labels.json", "truth.json"] {
            std::fs::copy(data.join(file), folder.join(file)).unwrap();
        }
        let mut c = camera.clone();
        edit(&mut c);
        std::fs::write(folder.join("camera.json"), c.to_string()).unwrap();
        let out = scratch.path(&format!("run{k}"));
        let result = train_small(&folder, &model, &out, &[]);
        assert_clear_error(case, &result, &["camera.json", field]);
        assert!(!out.exists(), "{case}: wrote {}", out.display());
    }

    let out = scratch.path("inside");
    let result = train_small(
        &data,
        &model,
        &out,
        &["--scene-box=-100,-100,-100,100,100,100"],
    );
    assert_clear_error(
        "camera inside the box",
        &result,
        &["inside", "--scene-box", "frame `img"],
    );
    assert!(
        !out.exists(),
        "camera inside the box: wrote {}",
        out.display()
    );

    let scene = scratch.path("scene.toml");
    let text = std::fs::read_to_string(data.join("scene.toml")).unwrap();
    let text = if text.contains("[effects.label_noise]") {
        text.replacen(
            "[effects.label_noise]\nrotation_deg = ",
            "[effects.label_noise]\nrotation_deg = 1e30 # ",
            1,
        )
    } else {
        format!("{text}\n[effects.label_noise]\nrotation_deg = 1e30\ntranslation_m = 0.01\n")
    };
    std::fs::write(&scene, text).unwrap();
    let out = scratch.path("simulated");
    let result = orbit_nerf(&[
        "simulate",
        "--scene",
        path_str(&scene),
        "--out",
        path_str(&out),
    ])
    .output()
    .unwrap();
    assert_clear_error(
        "label noise 1e30 deg",
        &result,
        &["scene.toml", "effects.label_noise.rotation_deg"],
    );
    assert!(
        !out.exists(),
        "label noise 1e30 deg: wrote {}",
        out.display()
    );
}

/// Every file below `dir` with its bytes, in path order: what a refused command must leave as
/// it was.
fn folder_bytes(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(folder) = pending.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                pending.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                files.push((path, bytes));
            }
        }
    }
    files.sort();
    files
}

/// A sweep of one tiny task (4 steps of the tiny profile on 8 simulated frames of 32 px).
const ONE_TASK_SWEEP: &str = "scene = \"synthetic\"\nframes = 8\nsize = 32\nconfig = \"tiny\"\nsteps = 4\nholdout = 4\nfit_steps = 2\n\n[[variants]]\nname = \"baseline\"\nset = { embedding_dim = 0 }\n";

/// Results reused from a different description (issue 42, third group): a finished task whose
/// record was made with other settings than the description now asks (other steps, another
/// config field) is refused by `sweep run` and `sweep collect`, naming the record file and the
/// field, and nothing in the folder changes (was: skipped as finished, and the merged table
/// said "6 steps per model" over 4-step models). `collect` on a folder that does not exist says
/// so (was: "their logs: .../log.txt", files that do not exist either).
#[test]
fn sweep_results_of_another_description_are_refused_not_reused() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("sweep-reuse");
    let description = scratch.path("sweep.toml");
    std::fs::write(&description, ONE_TASK_SWEEP).unwrap();
    let out = scratch.path("out");
    let sweep = |command: &str, description: &Path, out: &Path| {
        let mut command = orbit_nerf(&["sweep", command, path_str(description)]);
        command.args(["--out", path_str(out)]);
        if command.get_args().any(|a| a == "run") {
            command.args(["--jobs", "1"]);
        }
        command.output().unwrap()
    };
    let result = sweep("run", &description, &out);
    assert!(result.status.success(), "{}", text(&result));
    let record = out.join("tasks/0/result.json");
    assert!(record.is_file());
    let before = folder_bytes(&out);

    for (name, from, to, field) in [
        ("steps.toml", "steps = 4", "steps = 6", "steps"),
        (
            "features.toml",
            "embedding_dim = 0 }",
            "embedding_dim = 0, features = 16 }",
            "settings.config.features",
        ),
        (
            "holdout.toml",
            "holdout = 4",
            "holdout = 2",
            "settings.holdout",
        ),
    ] {
        let other = scratch.path(name);
        std::fs::write(&other, ONE_TASK_SWEEP.replace(from, to)).unwrap();
        for command in ["run", "collect"] {
            let case = format!("sweep {command} {name} over sweep.toml's results");
            let result = sweep(command, &other, &out);
            assert_clear_error(
                &case,
                &result,
                &[
                    path_str(&record),
                    &format!("field `{field}`"),
                    path_str(&other),
                    "another --out",
                ],
            );
            assert!(!text(&result).contains("steps per model"), "{case}");
            assert_eq!(folder_bytes(&out), before, "{case}: the folder changed");
        }
    }
    // The description the records were made with still collects them.
    let result = sweep("collect", &description, &out);
    assert!(result.status.success(), "{}", text(&result));

    let missing = scratch.path("no-such-run");
    let result = sweep("collect", &description, &missing);
    assert_clear_error(
        "sweep collect on a missing folder",
        &result,
        &[path_str(&missing), "no such folder"],
    );
    assert!(!text(&result).contains("log.txt"), "{}", text(&result));
    assert!(!missing.exists());
}

/// A sweep's records name the text of the scene they simulated: after the scene file (or a
/// built-in preset, with a new binary) changes, its old records are refused by `sweep run` and
/// `sweep collect` naming the fingerprint, not reused as results of the new scene.
#[test]
fn sweep_results_of_a_scene_whose_text_changed_are_refused() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("sweep-scene-changed");
    let scene = scratch.path("scene.toml");
    let scene_text = std::fs::read_to_string(root().join("scenes/synthetic.toml")).unwrap();
    std::fs::write(&scene, &scene_text).unwrap();
    let description = scratch.path("sweep.toml");
    std::fs::write(
        &description,
        ONE_TASK_SWEEP.replace("scene = \"synthetic\"", "scene = \"scene.toml\""),
    )
    .unwrap();
    let out = scratch.path("out");
    let sweep = |command: &str| {
        let mut command = orbit_nerf(&["sweep", command, path_str(&description)]);
        command.args(["--out", path_str(&out)]);
        command.output().unwrap()
    };
    let result = sweep("run");
    assert!(result.status.success(), "{}", text(&result));
    let record = out.join("tasks/0/result.json");
    // The same text collects; another text does not.
    assert!(sweep("collect").status.success());
    let before = folder_bytes(&out);
    let changed = scene_text.replace("deg_per_frame = 0.9", "deg_per_frame = 0.5");
    assert_ne!(changed, scene_text);
    std::fs::write(&scene, changed).unwrap();
    for command in ["run", "collect"] {
        let result = sweep(command);
        assert_clear_error(
            &format!("sweep {command} after the scene changed"),
            &result,
            &[
                path_str(&record),
                "scenes_fnv1a",
                "the scene's text has changed",
            ],
        );
        assert_eq!(
            folder_bytes(&out),
            before,
            "sweep {command}: the folder changed"
        );
    }
}

/// `tradeoff --vary size=N` above the data's images (issue 42, eighth group): frames are never
/// upsampled, so the variant would silently repeat the reference. Refused before anything is
/// trained or written, naming the flag, the value and the data's size; the same size of a
/// variant in a sweep description is refused naming the field; the default knobs leave such a
/// size out.
#[test]
fn tradeoff_sizes_above_the_datas_images_are_refused_before_training() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("tradeoff-size");
    let data = scratch.path("data");
    common::simulated_lightbox(&data, 8, 32);
    // An earlier folder of the user's at --out: left as it was.
    let out = scratch.path("out");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("notes.txt"), b"the user's own file").unwrap();
    let before = folder_bytes(&out);
    let tradeoff = |extra: &[&str], out: &Path| {
        orbit_nerf(&["tradeoff", "--data", path_str(&data), "--size", "32"])
            .args(["--steps", "2", "--out", path_str(out)])
            .args(extra)
            .output()
            .unwrap()
    };
    let result = tradeoff(&["--vary", "size=16,64"], &out);
    assert_clear_error(
        "tradeoff --vary size=64 on 32 px data",
        &result,
        &["--vary size=16,64", "64 px", "32 px", path_str(&data)],
    );
    assert_eq!(folder_bytes(&out), before);

    let description = scratch.path("sweep.toml");
    std::fs::write(
        &description,
        format!(
            "data = \"{}\"\nsize = 32\nconfig = \"tiny\"\nsteps = 2\nholdout = 4\n\n[[variants]]\nname = \"reference\"\n\n[[variants]]\nname = \"size=64\"\nsize = 64\n",
            data.display()
        ),
    )
    .unwrap();
    let result = orbit_nerf(&[
        "sweep",
        "run",
        path_str(&description),
        "--out",
        path_str(&out),
    ])
    .output()
    .unwrap();
    assert_clear_error(
        "a sweep variant of 64 px on 32 px data",
        &result,
        &[path_str(&description), "field `variants[1].size`", "32 px"],
    );
    assert_eq!(folder_bytes(&out), before);

    let written = scratch.path("written");
    let result = tradeoff(&["--write-only"], &written);
    assert!(result.status.success(), "{}", text(&result));
    let toml = std::fs::read_to_string(written.join("tradeoff.toml")).unwrap();
    assert!(
        toml.contains("name = \"size=16\"") && !toml.contains("name = \"size=64\""),
        "{toml}"
    );
}

/// `stream` on the small run's data (`--size 32`, `--fit-steps 0`) into `out`, with `extra`,
/// and by default 4 slots, 2 steps per frame, a point every 3 usable frames, a checkpoint
/// every 2 arrivals and every 3rd frame held out (`extra` may set these flags instead).
fn stream_small(data: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut command = orbit_nerf(&["stream", "--data", path_str(data), "--size", "32"]);
    for (flag, value) in [
        ("--store", "4"),
        ("--steps-per-frame", "2"),
        ("--eval-every", "3"),
        ("--checkpoint-every", "2"),
        ("--holdout", "3"),
    ] {
        if !extra.contains(&flag) {
            command.args([flag, value]);
        }
    }
    command
        .args(["--fit-steps", "0", "--out", path_str(out)])
        .args(extra)
        .output()
        .unwrap()
}

/// The files a stream writes: none must exist after a refused stream.
fn assert_stream_wrote_nothing(case: &str, out: &Path) {
    for file in [
        "checkpoint.onrf",
        "checkpoint.snapshots",
        "anytime.csv",
        "summary.md",
        "metrics.json",
    ] {
        assert!(!out.join(file).exists(), "{case}: wrote {file}");
    }
}

/// No score from a stream that learned nothing (issue 42, first group): `stream` applies
/// `train`'s rule (`train::check_trained`) before every anytime point and every checkpoint.
/// Labels with every target behind its camera, a `--scene-box` no ray crosses and a config
/// file's box far from every camera end non-zero naming the 0 samples per ray, print no
/// PSNR and write no checkpoint, snapshot, curve, summary or metrics.json; a model that
/// diverges (a tiny `adam_eps`) is refused the same way, naming the non-finite section.
#[test]
fn a_stream_that_learned_nothing_fails_without_a_score_or_a_checkpoint() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("stream-no-samples");
    let (data, model) = small_training_run(&scratch);
    let behind = scratch.path("behind");
    copy_images_and_camera(&data, &behind);
    let mut labels = read_json(&data.join("labels.json"));
    for label in labels.as_array_mut().unwrap() {
        label["r_Vo2To_vbs_true"] = serde_json::json!([0.0, 0.0, -5.0]);
    }
    std::fs::write(behind.join("labels.json"), labels.to_string()).unwrap();
    let far_box = small_config(&scratch, "far.toml", |c| {
        c.aabb_min = [100.0; 3];
        c.aabb_max = [101.0; 3];
    });
    let tiny_eps = small_config(&scratch, "eps.toml", |c| c.adam_eps = 1e-45);
    let nothing = [
        "no training ray met the scene box",
        "0 samples per ray",
        "not saved and not scored",
    ];
    let model = path_str(&model);
    type Case<'a> = (&'a str, &'a Path, Vec<&'a str>, &'a [&'a str]);
    let cases: [Case; 4] = [
        (
            "labels behind the camera",
            &behind,
            vec!["--config", model, "--scene-box=-1,-1,-1,1,1,1"],
            &nothing,
        ),
        (
            "a --scene-box no ray crosses",
            &data,
            vec!["--config", model, "--scene-box", "100,100,100,101,101,101"],
            &nothing,
        ),
        (
            "a config file's box far from every camera",
            &data,
            vec!["--config", path_str(&far_box)],
            &nothing,
        ),
        (
            "a diverged model",
            &data,
            // 48 steps before the one check at the end, as `train`'s 40 diverge.
            vec![
                "--config",
                path_str(&tiny_eps),
                "--steps-per-frame",
                "4",
                "--eval-every",
                "100",
                "--checkpoint-every",
                "100",
            ],
            &["training diverged", "adam_eps", "not saved and not scored"],
        ),
    ];
    for (case, data, extra, needles) in cases {
        let out = scratch.path("out");
        let result = stream_small(data, &out, &extra);
        assert_clear_error(case, &result, needles);
        assert_stream_wrote_nothing(case, &out);
    }
    // The same data and config with the box where the cameras look: a stream that learns,
    // and reports its samples per ray.
    let out = scratch.path("learns");
    let result = stream_small(&data, &out, &["--config", model]);
    assert!(result.status.success(), "{}", text(&result));
    let metrics = read_json(&out.join("metrics.json"));
    let samples = &metrics["models"][0]["training"]["samples_per_ray"];
    assert!(samples.as_f64().is_some_and(|s| s > 0.0), "{metrics}");
}

/// A config asking for more than the memory plan allows (issue 42, fifth group): the arena is
/// planned from the config (`MemoryPlan`), so the most rays a step may take (2^20) with a
/// `--memory-limit` below their plan is refused before anything is allocated, naming the
/// field that sizes the parts; more rays than 2^20, or more samples per ray than a chunk's
/// pass holds (`samples_per_chunk`), are refused naming the file and the field.
#[test]
fn a_config_asking_more_than_the_plan_allows_is_refused_naming_the_field() {
    if common::shared_data().is_none() {
        return;
    }
    let scratch = Scratch::new("plan-bounds");
    let (data, _) = small_training_run(&scratch);
    let most_rays = small_config(&scratch, "most-rays.toml", |c| c.rays_per_batch = 1 << 20);
    let out = scratch.path("out");
    let over_limit = [
        "needs 10",
        "ray batch (rays_per_batch) 64.0 MiB",
        "chunk buffers (samples_per_chunk, rays_per_batch)",
        "memory limit of 64.0 MiB",
    ];
    let result = train_small(&data, &most_rays, &out, &["--memory-limit", "64M"]);
    assert_clear_error("train, 2^20 rays in 64 MiB", &result, &over_limit);
    assert!(!out.exists(), "train wrote {}", out.display());
    let result = stream_small(
        &data,
        &out,
        &["--config", path_str(&most_rays), "--memory-limit", "64M"],
    );
    assert_clear_error("stream, 2^20 rays in 64 MiB", &result, &over_limit);
    assert!(!out.exists(), "stream wrote {}", out.display());

    let too_many_rays = small_config(&scratch, "rays.toml", |c| c.rays_per_batch = (1 << 20) + 2);
    let too_many_samples = small_config(&scratch, "samples.toml", |c| {
        c.max_samples_per_ray = c.samples_per_chunk as u16 + 1
    });
    for (config, field) in [
        (&too_many_rays, "rays_per_batch"),
        (&too_many_samples, "max_samples_per_ray"),
    ] {
        for command in ["train", "stream"] {
            let result = orbit_nerf(&[command, "--data", path_str(&data), "--size", "32"])
                .args(["--config", path_str(config), "--out", path_str(&out)])
                .output()
                .unwrap();
            let case = format!("{command} {field}");
            assert_clear_error(&case, &result, &[path_str(config), field, "out of range"]);
            assert!(!out.exists(), "{case}: wrote {}", out.display());
        }
    }
}

/// The step a trainer checkpoint was saved at (the `state` section's first counter).
fn checkpoint_step(path: &Path) -> u32 {
    let saved = checkpoint::load(path).unwrap();
    let state = saved.section("state").unwrap();
    u32::from_ne_bytes(state[..4].try_into().unwrap())
}

/// A stop heard within a step (issue 42, fifth group): with 2^20 rays per step (the most a
/// config may ask; about 40 s a step of the tiny profile on 2 shared cores, 0.3 s when the
/// rays were 128), SIGTERM two seconds into the first step of `train` and of `stream` ends
/// each cleanly with the checkpoint of the last finished step (step 0: the step under way is
/// given up, not finished), no score, and well before the step would have finished.
#[test]
fn sigterm_within_a_long_step_stops_before_the_step_ends() {
    if common::shared_data().is_none() {
        return;
    }
    use std::io::{BufRead as _, Read as _};
    use std::time::Instant;
    let scratch = Scratch::new("long-step-sigterm");
    let (data, _) = small_training_run(&scratch);
    let most_rays = small_config(&scratch, "most-rays.toml", |c| c.rays_per_batch = 1 << 20);
    // Start `args`, wait for `started` on its output and two seconds more (the first step is
    // under way), send SIGTERM; returns what it printed, whether it exited cleanly and how
    // long it took to exit after the signal.
    let interrupt = |args: &[&str], started: &str| {
        let mut child = orbit_nerf(args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
        let mut printed = String::new();
        while !printed.contains(started) {
            assert!(stdout.read_line(&mut printed).unwrap() > 0, "{printed}");
        }
        std::thread::sleep(Duration::from_secs(2));
        let signalled = Instant::now();
        let killed = std::process::Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        stdout.read_to_string(&mut printed).unwrap();
        let result = child.wait_with_output().unwrap();
        let seconds = signalled.elapsed().as_secs_f64();
        printed.push_str(&text(&result));
        (printed, result.status.success(), seconds)
    };
    let train_out = scratch.path("train");
    let (printed, clean, seconds) = interrupt(
        &[
            "train",
            "--data",
            path_str(&data),
            "--size",
            "32",
            "--config",
            path_str(&most_rays),
            "--steps",
            "1000",
            "--threads",
            "2",
            "--out",
            path_str(&train_out),
        ],
        "training on",
    );
    assert!(clean, "{printed}");
    assert!(printed.contains("stopped at step 0 of 1000"), "{printed}");
    assert!(!printed.contains("PSNR"), "scored a stopped run: {printed}");
    assert_eq!(checkpoint_step(&train_out.join("checkpoint.onrf")), 0);
    assert!(seconds < 20.0, "{seconds:.1} s after SIGTERM: {printed}");

    let stream_out = scratch.path("stream");
    let (printed, clean, seconds) = interrupt(
        &[
            "stream",
            "--data",
            path_str(&data),
            "--size",
            "32",
            "--store",
            "4",
            "--steps-per-frame",
            "2",
            "--config",
            path_str(&most_rays),
            "--threads",
            "2",
            "--out",
            path_str(&stream_out),
        ],
        "streaming",
    );
    assert!(clean, "{printed}");
    assert!(printed.contains("stopped after 1 arrivals"), "{printed}");
    assert!(
        !printed.contains("PSNR"),
        "scored a stopped stream: {printed}"
    );
    // The frame is in the store and owes its 2 steps to the resumed stream.
    assert_eq!(checkpoint_step(&stream_out.join("checkpoint.onrf")), 0);
    assert!(seconds < 20.0, "{seconds:.1} s after SIGTERM: {printed}");
}
