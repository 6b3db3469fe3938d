//! Streaming end to end: kill-and-resume equals an uninterrupted run bit for bit (through the
//! host API with a deterministic stop, and through the binary with a real SIGTERM or SIGKILL),
//! a watched folder ingests frames written while it trains, in order, and every kind of bad
//! frame is reported once and skipped while the stream goes on.

mod common;

use common::{orbit_nerf, output_text, root, temp_dir};
use orbit_nerf_core::{Config, MemoryPlan, Replacement, Trainer};
use orbit_nerf_host::checkpoint;
use orbit_nerf_host::formats::speedplus::{self, Label};
use orbit_nerf_host::sim::{self, Scene};
use orbit_nerf_host::stream::{
    self, Control, DatasetSource, Event, FixedSetPoint, FrameSource, Keep, ModelChoice, Outcome,
    SourceKind, StreamEnd, StreamObserver, StreamRequest, StreamSettings, StreamState,
    WatchOptions, WatchedFolder,
};
use orbit_nerf_host::train::{self, RayonExecutor};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// A simulated lightbox set of `frames` frames of 32 px.
fn simulated_set(dir: &Path, frames: u32) {
    let mut scene = Scene::load("lightbox").unwrap();
    scene.spec.frames = frames;
    scene.spec.size = 32;
    sim::simulate(&scene, dir, &|| {}).unwrap();
}

/// The tiny profile with small per-frame embeddings and pose correction, so per-frame state
/// is recycled with the slots.
fn base_config() -> Config {
    let mut config =
        train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT).unwrap();
    config.embedding_dim = 4;
    config.pose_correction = true;
    config
}

fn settings() -> StreamSettings {
    StreamSettings {
        steps_per_frame: 3,
        holdout_every: 8,
        eval_every: 5,
        checkpoint_every: 4,
        fit_steps: 2,
        budget_ms: None,
        settle_steps: Some(SETTLE),
    }
}

/// The settle's steps in [`settings`].
const SETTLE: u32 = 4;

/// Stream `source` into a fresh trainer (or the one saved at `checkpoint` when `resume`),
/// stopping once the trainer has taken `stop_after` steps; returns the outcome and the final
/// state.
fn stream_api(
    source: &mut dyn FrameSource,
    store: (u16, Keep),
    checkpoint: &Path,
    stop_after: Option<u32>,
    resume: bool,
    events: &mut dyn FnMut(&Event<'_>),
) -> (Outcome, StreamState) {
    let stop = AtomicBool::new(false);
    let stops = (&stop, stop_after);
    stream_api_stopped_by(source, store, checkpoint, stops, resume, events)
}

/// [`stream_api`] with a stop flag `stops.0` (a signal handler's, as it were) beside the
/// deterministic `stops.1` (`--stop-after`).
fn stream_api_stopped_by(
    source: &mut dyn FrameSource,
    store: (u16, Keep),
    checkpoint: &Path,
    (stop, stop_after): (&AtomicBool, Option<u32>),
    resume: bool,
    events: &mut dyn FnMut(&Event<'_>),
) -> (Outcome, StreamState) {
    let (config, mut state) = if resume {
        stream::resume(checkpoint, source).unwrap()
    } else {
        let config = stream::stream_config(
            &base_config(),
            source.info(),
            store,
            Replacement::Novelty,
            (settings().steps_per_frame, SETTLE),
        )
        .unwrap();
        let state = StreamState::new(settings(), config.max_frames as usize, source.info());
        (config, state)
    };
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    if resume {
        stream::restore(checkpoint, &mut trainer).unwrap();
    }
    let control = Control {
        stop,
        stop_after,
        end_after: None,
        checkpoint,
    };
    let executor = RayonExecutor::new(2).unwrap();
    let outcome = stream::run(
        &mut trainer,
        &executor,
        source,
        &mut state,
        &control,
        events,
    )
    .unwrap();
    (outcome, state)
}

/// The curve of the stream saved at `checkpoint` scored on all its held-out views.
fn fixed_set(
    checkpoint: &Path,
    state: &StreamState,
    source: &dyn FrameSource,
) -> Vec<FixedSetPoint> {
    let (config, _) = stream::load(checkpoint).unwrap();
    let executor = RayonExecutor::new(2).unwrap();
    stream::fixed_set_curve(
        checkpoint,
        source,
        state,
        &config,
        &executor,
        None,
        &mut |_| {},
    )
    .unwrap()
}

/// The `fixed_*` columns of each row of a stream's anytime.csv (the curve on all held-out
/// views), as text.
fn fixed_set_columns(csv: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let columns: Vec<usize> = (0..header.len())
        .filter(|&i| header[i].starts_with("fixed_"))
        .collect();
    assert_eq!(columns.len(), 5, "{header:?}");
    lines
        .map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            columns.iter().map(|&i| cells[i].to_string()).collect()
        })
        .collect()
}

/// The trainer's sections of a checkpoint (everything but the stream's own record, which
/// also holds wall times).
fn trainer_sections(path: &Path) -> Vec<(String, Vec<u8>)> {
    checkpoint::load(path)
        .unwrap()
        .sections
        .into_iter()
        .filter(|s| s.name != stream::STREAM_SECTION)
        .map(|s| (s.name, s.bytes))
        .collect()
}

/// The parts of a stream's state that must not depend on where it was interrupted.
fn deterministic_part(state: &StreamState) -> impl PartialEq + std::fmt::Debug {
    (
        state.position,
        state.usable,
        state.offered,
        state.stored,
        state.rejected,
        state.held_out.clone(),
        state.slot_positions.clone(),
        state.settle_from,
        state
            .curve
            .iter()
            .map(|p| (p.frames_seen, p.frames_held, p.steps, p.psnr.to_bits()))
            .collect::<Vec<_>>(),
    )
}

/// For whole frames and for a ray reservoir remembering 12 frames (in the bytes of 6 whole
/// ones): a stream stopped part-way and resumed ends bit for bit where the uninterrupted one
/// does, and pacing the source changes nothing.
#[test]
fn stopping_and_resuming_gives_the_uninterrupted_result_bit_for_bit() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("resume");
    let data = dir.join("data");
    simulated_set(&data, 30);
    for keep in [Keep::Frames, Keep::Rays { remember: Some(12) }] {
        stop_and_resume(&data, &dir.join(format!("{keep:?}")), keep);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn stop_and_resume(data: &Path, dir: &Path, keep: Keep) {
    std::fs::create_dir_all(dir).unwrap();
    let open = || DatasetSource::open(data, None, None).unwrap();

    let whole = dir.join("whole.onrf");
    let (outcome, whole_state) =
        stream_api(&mut open(), (6, keep), &whole, None, false, &mut |_| {});
    assert_eq!(outcome, Outcome::Finished);
    // The store filled and the policy had to choose; held-out views were scored on the way.
    assert_eq!(whole_state.position, 30);
    assert_eq!(whole_state.held_out.len(), 3);
    assert!(
        whole_state.stored > 6 && whole_state.rejected > 0,
        "{whole_state:?}"
    );
    assert!(whole_state.curve.len() >= 6);
    // 3 steps for each of the 30 usable frames, then the SETTLE steps of the settle, with a point
    // before it and one after.
    let settle_from = 30 * settings().steps_per_frame;
    assert_eq!(whole_state.settle_from, Some(settle_from));
    let ends: Vec<(u64, u32)> = (whole_state.curve[whole_state.curve.len() - 2..].iter())
        .map(|p| (p.frames_seen, p.steps))
        .collect();
    assert_eq!(ends, [(30, settle_from), (30, settle_from + SETTLE)]);
    if let Keep::Rays { remember } = keep {
        let (config, _) = stream::load(&whole).unwrap();
        let saved = checkpoint::load(&whole).unwrap();
        assert!(config.ray_store > 0 && saved.section("frame_masks").unwrap().is_empty());
        assert_eq!(Some(whole_state.slot_positions.len() as u16), remember);
    }

    // Stopped at step 38, within the 13th arrival's steps (3 per usable frame), past two
    // scorings and three checkpoints; then resumed, first taking the frame's last step.
    let parts = dir.join("parts.onrf");
    let (outcome, stopped) =
        stream_api(&mut open(), (6, keep), &parts, Some(38), false, &mut |_| {});
    assert_eq!(
        (outcome, stopped.position, saved_step(&parts)),
        (Outcome::Stopped, 13, 38)
    );
    // Stopped again within the settle, then resumed to the end.
    let (outcome, stopped) = stream_api(
        &mut open(),
        (6, keep),
        &parts,
        Some(settle_from + 2),
        true,
        &mut |_| {},
    );
    assert_eq!(
        (outcome, stopped.position, stopped.settle_from),
        (Outcome::Stopped, 30, Some(settle_from))
    );
    assert_eq!(saved_step(&parts), settle_from + 2);
    let (outcome, resumed) = stream_api(&mut open(), (6, keep), &parts, None, true, &mut |_| {});
    assert_eq!(outcome, Outcome::Finished);
    assert_eq!(
        deterministic_part(&resumed),
        deterministic_part(&whole_state)
    );
    assert!(
        trainer_sections(&parts) == trainer_sections(&whole),
        "the resumed run's parameters, moments, occupancy or frames differ"
    );
    // Every point of the curve is scored again on the same views, all three held out; the
    // snapshots the stopped run wrote serve the resumed one, and give the same figures.
    let whole_fixed = fixed_set(&whole, &whole_state, &open());
    assert_eq!(whole_fixed.len(), whole_state.curve.len());
    assert!(whole_fixed.iter().all(|p| p.views == 3), "{whole_fixed:?}");
    let last = (
        &whole_fixed[whole_fixed.len() - 1],
        &whole_state.curve[whole_state.curve.len() - 1],
    );
    assert_eq!(last.1.held_out_views, 3);
    assert_eq!(
        last.0.metrics.psnr_full.to_bits(),
        last.1.psnr.to_bits(),
        "the last point already saw every view"
    );
    let bits = |points: &[FixedSetPoint]| -> Vec<[u64; 3]> {
        points
            .iter()
            .map(|p| {
                [
                    p.metrics.psnr_full.to_bits(),
                    p.metrics.ssim_full.to_bits(),
                    p.metrics.psnr_right.to_bits(),
                ]
            })
            .collect()
    };
    let resumed_fixed = fixed_set(&parts, &resumed, &open());
    assert_eq!(bits(&resumed_fixed), bits(&whole_fixed));
    // Pacing the source changes nothing either.
    let paced = dir.join("paced.onrf");
    let mut paced_source = DatasetSource::open(data, None, Some(200.0)).unwrap();
    stream_api(
        &mut paced_source,
        (6, keep),
        &paced,
        None,
        false,
        &mut |_| {},
    );
    assert!(trainer_sections(&paced) == trainer_sections(&whole));
}

#[test]
fn sigterm_or_sigkill_then_resume_matches_an_uninterrupted_run_of_the_binary() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("sigterm");
    let config = dir.join("model.toml");
    std::fs::write(&config, train::config_to_toml(&base_config()).unwrap()).unwrap();
    let run = |extra: &[&str], out: &Path| {
        let config = config.to_str().unwrap();
        let mut args = vec![
            "stream",
            "--scene",
            "lightbox",
            "--frames",
            "40",
            "--size",
            "32",
            "--store",
            "8",
            "--steps-per-frame",
            "3",
            "--eval-every",
            "10",
            "--checkpoint-every",
            "2",
            "--fit-steps",
            "2",
            "--config",
            config,
            "--out",
        ];
        args.push(out.to_str().unwrap());
        args.extend_from_slice(extra);
        orbit_nerf(&args)
    };

    let whole = dir.join("whole");
    let out = run(&[], &whole).output().unwrap();
    assert!(out.status.success(), "{}", output_text(&out));
    // metrics.json holds the summary's held-out figures (issue 12).
    let summary = std::fs::read_to_string(whole.join("summary.md")).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(whole.join("metrics.json")).unwrap()).unwrap();
    let streamed = &json["models"][0];
    assert_eq!(
        (&json["command"], &streamed["name"]),
        (&"stream".into(), &"streamed".into())
    );
    let psnr = streamed["mean"]["psnr_full"].as_f64().unwrap();
    let ssim = streamed["mean"]["ssim_full"].as_f64().unwrap();
    let line = format!("held-out PSNR {psnr:.2} dB");
    assert!(
        summary.contains(&line) && summary.contains(&format!("SSIM {ssim:.4}")),
        "{summary}"
    );

    // Start a run and send it `signal` once its first checkpoint is there (the run is under
    // way), after `delay`; returns what it printed and whether it exited cleanly.
    let interrupt = |signal: &str, delay: Duration, out: &Path| {
        let child = run(&[], out)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        while !out.join("checkpoint.onrf").is_file() {
            std::thread::sleep(Duration::from_millis(20));
        }
        std::thread::sleep(delay);
        let killed = Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let out = child.wait_with_output().unwrap();
        (out.status.success(), output_text(&out))
    };
    let resume_and_compare = |out: &Path| {
        let resumed = run(&["--resume"], out).output().unwrap();
        let text = output_text(&resumed);
        assert!(
            resumed.status.success() && text.contains("resuming"),
            "{text}"
        );
        assert!(
            trainer_sections(&out.join("checkpoint.onrf"))
                == trainer_sections(&whole.join("checkpoint.onrf")),
            "{}: the resumed binary's final state differs from the uninterrupted one",
            out.display()
        );
        let fixed = fixed_set_columns(&out.join("anytime.csv"));
        assert_eq!(fixed, fixed_set_columns(&whole.join("anytime.csv")));
        let views: Vec<&str> = fixed.iter().map(|row| row[0].as_str()).collect();
        assert!(
            views
                .iter()
                .all(|v| *v == views[0] && *v != "0" && !v.is_empty()),
            "every point scores the same held-out views: {views:?}"
        );
    };

    // SIGTERM: the run gives up the step under way, checkpoints the last finished one and
    // exits cleanly; resumed, it first takes the rest of the frame's steps. (40 frames make
    // sure the signal arrives mid-stream.)
    let terminated = dir.join("terminated");
    let (clean, text) = interrupt("-TERM", Duration::ZERO, &terminated);
    assert!(clean && text.contains("stopped after"), "{text}");
    resume_and_compare(&terminated);
    assert!(terminated.join("anytime.csv").is_file() && terminated.join("anytime.png").is_file());

    // SIGKILL, possibly in the middle of a checkpoint write: the last complete checkpoint is
    // still there and loads (checkpoints are written to a temporary file, then renamed).
    let killed = dir.join("killed");
    let (clean, text) = interrupt("-KILL", Duration::from_millis(150), &killed);
    assert!(!clean, "{text}");
    stream::load(&killed.join("checkpoint.onrf")).unwrap();
    resume_and_compare(&killed);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Write `bytes` to `path` the way a careful producer does: a temporary name, then rename.
fn publish(path: &Path, bytes: &[u8]) {
    let tmp = path.with_extension("part");
    std::fs::write(&tmp, bytes).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

fn label_json(label: &Label) -> Vec<u8> {
    serde_json::to_vec(label).unwrap()
}

/// A simulated set of `frames` frames in `dir/data`, its labels, and an empty watched folder
/// `dir/watched` with the set's camera file and its truth file (a stream takes the scene box
/// from it; without one the box must be stated).
fn empty_watched_folder(dir: &Path, frames: u32) -> (PathBuf, Vec<Label>, PathBuf) {
    let data = dir.join("data");
    simulated_set(&data, frames);
    let labels = speedplus::read_labels(&data.join("labels.json")).unwrap();
    let watched = dir.join("watched");
    std::fs::create_dir_all(&watched).unwrap();
    for file in ["camera.json", "truth.json"] {
        std::fs::copy(data.join(file), watched.join(file)).unwrap();
    }
    (data, labels, watched)
}

fn watch_options(grace_ms: u64) -> WatchOptions {
    WatchOptions {
        poll: Duration::from_millis(20),
        grace: Duration::from_millis(grace_ms),
        idle_timeout: Some(Duration::from_secs(30)),
    }
}

#[test]
fn a_watched_folder_ingests_frames_that_appear_while_it_trains_in_order() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("watch");
    let (data, labels, watched) = empty_watched_folder(&dir, 12);

    let writer = {
        let (data, watched, labels) = (data.clone(), watched.clone(), labels.clone());
        std::thread::spawn(move || {
            for (k, label) in labels.iter().enumerate() {
                std::thread::sleep(Duration::from_millis(60));
                let stem = label.filename.trim_end_matches(".png");
                let image = std::fs::read(data.join("images").join(&label.filename)).unwrap();
                publish(&watched.join(&label.filename), &image);
                // Every third frame's label comes late: the frame is waited for, not bad.
                if k % 3 == 0 {
                    std::thread::sleep(Duration::from_millis(150));
                }
                publish(&watched.join(format!("{stem}.json")), &label_json(label));
            }
            publish(&watched.join("END"), b"");
        })
    };
    let mut source = WatchedFolder::open(&watched, None, watch_options(5000)).unwrap();
    let mut names = Vec::new();
    let mut bad = Vec::new();
    let (outcome, state) = stream_api(
        &mut source,
        (4, Keep::Frames),
        &dir.join("watch.onrf"),
        None,
        false,
        &mut |event| match event {
            Event::Frame { name, .. } => names.push(name.to_string()),
            Event::Bad(b) => bad.push(b.message.clone()),
            _ => {}
        },
    );
    writer.join().unwrap();
    assert_eq!(outcome, Outcome::Finished);
    assert!(bad.is_empty(), "{bad:?}");
    let expected: Vec<String> = labels
        .iter()
        .map(|l| watched.join(&l.filename).display().to_string())
        .collect();
    assert_eq!(names, expected, "every frame, in the order written");
    assert_eq!((state.position, state.usable), (12, 12));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_frames_are_reported_once_and_skipped_while_the_stream_goes_on() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("bad");
    let (data, labels, watched) = empty_watched_folder(&dir, 10);
    let png = |width: u32, value: u8| {
        let mut bytes = Vec::new();
        image::GrayImage::from_pixel(width, width, image::Luma([value]))
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .unwrap();
        bytes
    };
    // Frames 1, 3, 5, ... are broken, each in its own way; the even ones are good.
    let problems: [(&str, &str); 7] = [
        ("unreadable image", "neither a PNG nor a JPEG"),
        ("wrong size", "image is 20x20"),
        ("missing label", "missing label"),
        ("malformed label", "malformed JSON"),
        ("NaN pose", "q_vbs2tango_true"),
        ("all black", "all black"),
        ("all saturated", "all saturated"),
    ];
    let mut frame = 0;
    let mut expected_bad = Vec::new();
    for (k, (problem, _)) in problems.iter().enumerate() {
        for broken in [false, true] {
            let label = &labels[frame % labels.len()];
            let stem = format!("img{:06}", frame + 1);
            let image_path = watched.join(format!("{stem}.png"));
            let label_path = watched.join(format!("{stem}.json"));
            let mut image = std::fs::read(data.join("images").join(&label.filename)).unwrap();
            let mut label_text = label_json(label);
            if broken {
                match *problem {
                    "unreadable image" => image = b"not a png".to_vec(),
                    "wrong size" => image = png(20, 128),
                    "malformed label" => label_text = b"{\"filename\": ".to_vec(),
                    "NaN pose" => {
                        label_text = format!(
                            "{{\"filename\": \"{stem}.png\", \"q_vbs2tango_true\": [NaN, 0, 0, 1], \"r_Vo2To_vbs_true\": [0, 0, 5]}}"
                        )
                        .into_bytes()
                    }
                    "all black" => image = png(32, 0),
                    "all saturated" => image = png(32, 255),
                    _ => {}
                }
                expected_bad.push((frame as u64, k));
            }
            std::fs::write(&image_path, &image).unwrap();
            if !(broken && *problem == "missing label") {
                std::fs::write(&label_path, &label_text).unwrap();
            }
            frame += 1;
        }
    }
    std::fs::write(watched.join("END"), b"").unwrap();

    let mut source = WatchedFolder::open(&watched, None, watch_options(200)).unwrap();
    let mut reported = Vec::new();
    let (outcome, state) = stream_api(
        &mut source,
        (4, Keep::Frames),
        &dir.join("bad.onrf"),
        None,
        false,
        &mut |event| {
            if let Event::Bad(b) = event {
                reported.push((b.position, b.message.clone()));
            }
        },
    );
    assert_eq!(outcome, Outcome::Finished);
    assert_eq!(reported.len(), problems.len(), "{reported:#?}");
    for ((position, message), (expected_position, k)) in reported.iter().zip(&expected_bad) {
        let (problem, needle) = problems[*k];
        assert_eq!(position, expected_position, "{problem}: {message}");
        let stem = format!("img{:06}", position + 1);
        assert!(
            message.contains(&stem),
            "{problem}: names the file: {message}"
        );
        assert!(
            message.contains(needle),
            "{problem}: names the problem: {message}"
        );
        assert_eq!(message.lines().count(), 1, "{problem}: one line: {message}");
    }
    // The good frames all went in, and the stream trained after each of them.
    assert_eq!(state.position, 14);
    assert_eq!(state.usable, 7);
    assert_eq!(state.bad.len(), 7);
    let (config, _) = stream::load(&dir.join("bad.onrf")).unwrap();
    assert_eq!(config.max_frames, 4);
    let steps = checkpoint::load(&dir.join("bad.onrf"))
        .unwrap()
        .section("state")
        .map(|bytes| u32::from_le_bytes(bytes[..4].try_into().unwrap()))
        .unwrap();
    assert_eq!(steps, 7 * settings().steps_per_frame + SETTLE);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_nerf_synthetic_folder_streams_its_training_split_in_file_order() {
    let lego = root().join("../shared/data/nerf_synthetic/lego");
    if !lego.is_dir() {
        eprintln!("skipping: {} not found", lego.display());
        return;
    }
    let mut source = DatasetSource::open(&lego, Some(40), None).unwrap();
    // NeRF-synthetic has no exact poses beside its labels: held-out views are scored there.
    assert!(!source.info().exact_poses);
    assert_eq!(source.exact_pose(0).unwrap(), None);
    assert_eq!(source.info().max_pixels, 40 * 40);
    assert_eq!(source.info().background, [1.0; 3]);
    let stop = AtomicBool::new(false);
    let mut names = Vec::new();
    for _ in 0..3 {
        match source.next(&stop) {
            Some(stream::Arrival::Frame(frame)) => {
                assert_eq!(frame.pixels.len(), 40 * 40 * 3);
                names.push(frame.name);
            }
            _ => panic!("lego frames read"),
        }
    }
    assert_eq!(
        names,
        ["./train/r_0.png", "./train/r_1.png", "./train/r_2.png"]
    );
    assert_eq!(source.position(), 3);
    // A held-out view reads again identically.
    let first = source.reload(1).unwrap();
    source.seek(1, &[]).unwrap();
    match source.next(&stop) {
        Some(stream::Arrival::Frame(again)) => assert_eq!(again.pixels, first.pixels),
        _ => panic!("lego frame 1 reads again"),
    }
}

/// A dataset source that raises `stop` as it hands out the frame at `raise_at`, so that the
/// stream hears the stop before that frame's first step.
struct StopAt<'s> {
    inner: DatasetSource,
    raise_at: u64,
    stop: &'s AtomicBool,
}

impl FrameSource for StopAt<'_> {
    fn info(&self) -> &stream::SourceInfo {
        self.inner.info()
    }
    fn next(&mut self, stop: &AtomicBool) -> Option<stream::Arrival> {
        let position = self.inner.position();
        let arrival = self.inner.next(stop);
        if position == self.raise_at {
            self.stop.store(true, Ordering::SeqCst);
        }
        arrival
    }
    fn position(&self) -> u64 {
        self.inner.position()
    }
    fn seek(&mut self, position: u64, arrived: &[String]) -> orbit_nerf_host::Result<()> {
        self.inner.seek(position, arrived)
    }
    fn reload(&self, position: u64) -> orbit_nerf_host::Result<orbit_nerf_host::dataset::Frame> {
        self.inner.reload(position)
    }
    fn exact_pose(&self, position: u64) -> orbit_nerf_host::Result<Option<orbit_nerf_core::Pose>> {
        self.inner.exact_pose(position)
    }
}

/// The step a stream checkpoint was saved at (its `state` section's first counter).
fn saved_step(path: &Path) -> u32 {
    let saved = checkpoint::load(path).unwrap();
    u32::from_ne_bytes(saved.section("state").unwrap()[..4].try_into().unwrap())
}

/// A stop heard within a frame's steps (issue 42, fifth group: a signal is heard between the
/// passes of a step, which is given up) checkpoints the last finished step with the frame in
/// the store; the resumed stream first takes the rest of that frame's steps (then its anytime
/// point and checkpoint, when due) and ends bit-identical to a stream never stopped. Stops
/// raised as frames arrive (the frame owes all its steps: at the first frame, before a
/// checkpoint is due, before a point is due, at a held-out frame), then stops raised by a
/// timer part-way through steps, each resumed in turn.
#[test]
fn a_stop_within_a_frames_steps_resumes_to_the_uninterrupted_result_bit_for_bit() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("stop-in-frame");
    let data = dir.join("data");
    simulated_set(&data, 24);
    let open = || DatasetSource::open(&data, None, None).unwrap();
    let whole = dir.join("whole.onrf");
    let (outcome, whole_state) = stream_api(
        &mut open(),
        (6, Keep::Frames),
        &whole,
        None,
        false,
        &mut |_| {},
    );
    assert_eq!(outcome, Outcome::Finished);

    let parts = dir.join("parts.onrf");
    let mut resume = false;
    // Arrival 3 ends with a checkpoint (every 4), 4 with a point (every 5 usable), 7 is
    // held out (every 8th).
    for raise_at in [0, 3, 4, 7] {
        let stop = AtomicBool::new(false);
        let mut source = StopAt {
            inner: open(),
            raise_at,
            stop: &stop,
        };
        let stops = (&stop, None);
        let (outcome, state) = stream_api_stopped_by(
            &mut source,
            (6, Keep::Frames),
            &parts,
            stops,
            resume,
            &mut |_| {},
        );
        assert_eq!((outcome, state.position), (Outcome::Stopped, raise_at + 1));
        // The frame is in (or held out) and owes its 3 steps.
        assert_eq!(state.usable, raise_at + 1);
        assert_eq!(saved_step(&parts), 3 * raise_at as u32);
        resume = true;
    }
    // Then stops at times that fall part-way through a frame's steps, or between frames.
    let mut stops_heard = 0;
    for delay_ms in (5..).step_by(7) {
        let stop = AtomicBool::new(false);
        let (outcome, _) = std::thread::scope(|scope| {
            scope.spawn(|| {
                std::thread::sleep(Duration::from_millis(delay_ms));
                stop.store(true, Ordering::SeqCst);
            });
            stream_api_stopped_by(
                &mut open(),
                (6, Keep::Frames),
                &parts,
                (&stop, None),
                true,
                &mut |_| {},
            )
        });
        if outcome == Outcome::Finished {
            break;
        }
        stops_heard += 1;
    }
    // (On this machine 13 timed stops, 10 of them part-way through a frame's steps.)
    assert!(stops_heard > 0);
    let (_, resumed) = stream::load(&parts).unwrap();
    assert_eq!(
        deterministic_part(&resumed),
        deterministic_part(&whole_state)
    );
    assert!(
        trainer_sections(&parts) == trainer_sections(&whole),
        "the resumed stream's parameters, moments, occupancy or frames differ"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Anytime points before the first held-out view has arrived say so instead of printing a
/// score of nothing ("PSNR NaN dB on 0 views").
#[test]
fn anytime_points_before_any_held_out_view_print_no_score() {
    let dir = temp_dir("no-view-yet");
    let out = orbit_nerf(&[
        "stream",
        "--scene",
        "synthetic",
        "--frames",
        "6",
        "--size",
        "32",
        "--holdout",
        "4",
        "--eval-every",
        "1",
        "--store",
        "4",
        "--steps-per-frame",
        "2",
        "--fit-steps",
        "1",
        "--preset",
        "tiny",
        "--out",
        dir.join("out").to_str().unwrap(),
    ])
    .output()
    .unwrap();
    let text = output_text(&out);
    assert!(out.status.success(), "{text}");
    let points: Vec<&str> = text.lines().filter(|l| l.contains(" steps: ")).collect();
    assert_eq!(points.len(), 7, "{text}");
    for line in &points[..3] {
        assert!(line.contains("no held-out view yet"), "{line}");
    }
    assert!(points[3].contains("PSNR") && points[3].contains("on the 1 held-out views"));
    assert!(!text.contains("NaN"), "{text}");
    // Without --settle-steps the settle is as long as the arrivals: their 2 steps per frame.
    let steps = |line: &str| -> u32 {
        let before = line.split(" steps: ").next().unwrap();
        before.rsplit(' ').next().unwrap().parse().unwrap()
    };
    assert!(points[6].contains("(after the settle)"), "{}", points[6]);
    assert_eq!(steps(points[6]), 2 * steps(points[5]), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--budget-ms`: each usable frame trains until its budget has passed since it arrived (at
/// least one step), the steps frames managed are counted and the summary says the result
/// depends on the machine; the fixed-set curve and the forgetting line are reported. The
/// store here is a ray reservoir remembering every frame.
#[test]
fn a_real_time_stream_trains_until_each_frame_is_due_and_says_how_many_steps_it_managed() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("budget");
    let data = dir.join("data");
    simulated_set(&data, 12);
    let request = StreamRequest {
        out: dir.join("out"),
        store: 4,
        keep: Keep::Rays { remember: None },
        replacement: Replacement::Fifo,
        settings: StreamSettings {
            budget_ms: Some(60),
            holdout_every: 4,
            ..settings()
        },
        model: ModelChoice {
            preset: Some("tiny".into()),
            ..ModelChoice::default()
        },
        scene_box: None,
        stop_after: None,
        end_after: None,
        compare_offline: false,
        memory_limit: None,
        threads: 2,
        resume: false,
        replace: false,
    };
    struct Quiet;
    impl StreamObserver for Quiet {}
    let mut source = DatasetSource::open(&data, None, None).unwrap();
    let kind = SourceKind::DatasetFolder(data.clone());
    let end = request
        .run(&kind, &mut source, &AtomicBool::new(false), &mut Quiet)
        .unwrap();
    let StreamEnd::Finished(finished) = end else {
        panic!("the stream did not finish");
    };
    let budget = finished.state.budget_steps;
    // Every usable frame trains (the held-out ones too, once the store holds a frame).
    assert_eq!(budget.frames, 12);
    assert!(budget.min >= 1 && budget.max >= budget.min, "{budget:?}");
    // Then the settle's steps, as many as asked, whatever the budget.
    assert_eq!(
        Some(budget.steps as u32 + SETTLE),
        finished.state.curve.last().map(|p| p.steps)
    );
    // The schedule, open while frames arrived (a real-time stream cannot know how many steps
    // they take), was planned anew when the settle began: the decay spans the settle.
    let (config, _) = stream::load(&request.checkpoint_path()).unwrap();
    let arrivals = budget.steps as u32;
    assert_eq!(finished.state.settle_from, Some(arrivals));
    assert_eq!(config.steps, (arrivals + SETTLE).max(config.warmup_steps));
    assert_eq!(
        config.lr_decay_start,
        stream::session::settle_decay_start(&config, arrivals as u64, SETTLE)
    );
    let summary = &finished.summary;
    assert!(
        summary.contains("real-time mode: 60 ms per frame"),
        "{summary}"
    );
    assert!(
        summary.contains("depends on this machine's speed"),
        "{summary}"
    );
    assert!(
        summary.contains("fixed set (all 3 held-out views)"),
        "{summary}"
    );
    assert!(
        summary.contains(&format!("the last after a settle of {SETTLE} steps")),
        "{summary}"
    );
    assert!(summary.contains("- forgetting: "), "{summary}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Held-out views of a source that knows its frames' exact poses (a simulator folder's
/// `truth.json`, the simulator itself) are scored there, not at their noisy labels, as the
/// paper's test set is; a NeRF-synthetic folder, which has none, is scored at its labels.
#[test]
fn held_out_views_are_scored_at_exact_poses_where_the_source_knows_them() {
    if common::shared_data().is_none() {
        return;
    }
    let dir = temp_dir("exact-poses");
    let data = dir.join("data");
    simulated_set(&data, 10);
    let mut source = DatasetSource::open(&data, None, None).unwrap();
    assert!(source.info().exact_poses);
    let truth = speedplus::load(&data, &Default::default())
        .unwrap()
        .true_poses()
        .unwrap()
        .unwrap();
    let mut scene = Scene::load("lightbox").unwrap();
    scene.spec.frames = 10;
    scene.spec.size = 32;
    let simulator = stream::SimulatorSource::new(&scene).unwrap();
    assert!(simulator.info().exact_poses);
    for (position, exact) in truth.iter().enumerate() {
        let position = position as u64;
        assert_eq!(source.exact_pose(position).unwrap(), Some(*exact));
        assert_eq!(simulator.exact_pose(position).unwrap(), Some(*exact));
        // The lightbox preset's labels are noisy.
        assert_ne!(source.reload(position).unwrap().pose, *exact);
    }

    let checkpoint = dir.join("stream.onrf");
    let (outcome, state) = stream_api(
        &mut source,
        (6, Keep::Frames),
        &checkpoint,
        None,
        false,
        &mut |_| {},
    );
    assert_eq!(outcome, Outcome::Finished);
    let held_out = state.held_out[0];
    let (config, _) = stream::load(&checkpoint).unwrap();
    let mut arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    stream::restore(&checkpoint, &mut trainer).unwrap();
    let executor = RayonExecutor::new(2).unwrap();
    let fit = settings().fit_steps;
    let (_, scored) =
        stream::held_out_quality(&mut trainer, &executor, &source, &[held_out], fit).unwrap();
    let view = orbit_nerf_host::dataset::Dataset {
        source: data.clone(),
        frames: vec![source.reload(held_out).unwrap()],
        scene_min: config.aabb_min,
        scene_max: config.aabb_max,
        scene_box: orbit_nerf_host::dataset::SceneBoxOrigin::Stated("the stream's config".into()),
        background: source.info().background,
        target_centred: false,
    };
    let at = |poses: Option<&[orbit_nerf_core::Pose]>, trainer: &mut Trainer<'_>| {
        train::evaluate_at(trainer, &executor, &view, &[0], poses, (fit, false), None).unwrap()[0]
            .metrics
            .psnr_full
    };
    let exact = at(Some(&truth[held_out as usize..][..1]), &mut trainer);
    let label = at(None, &mut trainer);
    assert_eq!(scored, vec![(held_out, exact)]);
    assert_ne!(exact, label);
    // `eval`, `render` and `mesh` take a stream's checkpoint as the model it holds.
    let reloaded = orbit_nerf_host::pipeline::with_checkpoint(&checkpoint, None, &[], |trainer| {
        Ok::<_, orbit_nerf_host::HostError>(at(Some(&truth[held_out as usize..][..1]), trainer))
    });
    assert_eq!(reloaded.unwrap(), exact);
    let _ = std::fs::remove_dir_all(&dir);
}
