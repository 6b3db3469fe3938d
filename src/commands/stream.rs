//! `orbit-nerf stream`: ingest frames one at a time from a dataset folder, a watched folder or
//! the simulator into the core's fixed frame store, train a fixed number of steps per frame,
//! report the anytime quality, checkpoint, and resume after Ctrl-C or SIGTERM.

use super::{
    FIT_STEPS, Fallible, STOP, SceneBox, bar_style, config_for_data, parse_scene_box,
    preset_config, preset_parser, stop_on_signal,
};
use indicatif::ProgressBar;
use orbit_nerf_core::{Config, MemoryPlan, Replacement, Trainer};
use orbit_nerf_host::report::{Figures, ModelFigures, TrainingFigures, ViewMetrics};
use orbit_nerf_host::scene_box::box_text;
use orbit_nerf_host::sim::Scene;
use orbit_nerf_host::stream::{
    self, Control, DatasetSource, Event, Fate, FrameSource, MaskedSource, Outcome, SimulatorSource,
    StreamSettings, StreamState, WatchOptions, WatchedFolder,
};
use orbit_nerf_host::train::{self, RayonExecutor};
use orbit_nerf_host::{memory, presets, values};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug, Clone)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["scene", "data", "watch"])))]
pub struct StreamArgs {
    /// Simulate this scene (a preset or a scene file) frame by frame.
    #[arg(long)]
    pub scene: Option<String>,
    /// Stream a SPEED+ / SHIRT / simulator dataset folder in label order.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Watch this folder for new frames (camera.json, NAME.png + NAME.json per frame; ends
    /// on a file named END, after --idle-timeout, or at --max-frames).
    #[arg(long)]
    pub watch: Option<PathBuf>,
    /// Frames to simulate (--scene).
    #[arg(long, default_value_t = 120, value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: u32,
    /// Image size in pixels: the simulated frames' longer side, or the longer side dataset
    /// frames are resized to (never upsampled); at least 22, so that each half of a held-out
    /// view is wide enough for SSIM's 11x11 window.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u16).range(22..))]
    pub size: u16,
    /// Frame slots of the core's store.
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u16).range(1..))]
    pub store: u16,
    /// Replacement policy of a full store.
    #[arg(long, value_enum, default_value_t = Policy::Fifo)]
    pub policy: Policy,
    /// Training steps after each usable frame.
    #[arg(long, default_value_t = 17, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps_per_frame: u32,
    /// Every N-th usable frame is held out for the anytime-quality curve (N >= 2, so that
    /// some frames are trained on).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(2..))]
    pub holdout: u64,
    /// Score the held-out views every K usable frames.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..))]
    pub eval_every: u64,
    /// Write the checkpoint every N arrivals (and always when stopping).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..))]
    pub checkpoint_every: u64,
    /// Steps fitting a held-out view's appearance embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    pub fit_steps: u32,
    /// Pace a dataset folder at this many frames per second, 0.001 to 1e6 (does not change
    /// the result).
    #[arg(long, value_parser = |text: &str| values::number_in(text, stream::source::RATE_RANGE))]
    pub rate: Option<f64>,
    /// Watched folder: listing interval in milliseconds (1 to 60000).
    #[arg(long, default_value_t = 150, value_parser = clap::value_parser!(u64).range(1..=60_000))]
    pub poll_ms: u64,
    /// Watched folder: how long an incomplete frame is waited for before it is reported bad,
    /// in milliseconds (at most an hour).
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(0..=3_600_000))]
    pub grace_ms: u64,
    /// Watched folder: end after this many seconds without a new file; `inf` waits for ever
    /// (until END appears or Ctrl-C).
    #[arg(long, default_value = "30", value_parser = values::timeout_seconds)]
    pub idle_timeout: values::Timeout,
    /// End the stream after this many arrivals.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_frames: Option<u64>,
    /// Stop (and checkpoint) after this many arrivals, as Ctrl-C would; resume with --resume.
    #[arg(long)]
    pub stop_after: Option<u64>,
    /// The scene box, xmin,ymin,zmin,xmax,ymax,zmax (wins over a config file's box and
    /// truth.json's; needed for a SPEED+ folder without truth.json).
    #[arg(long, value_parser = parse_scene_box, allow_hyphen_values = true)]
    pub scene_box: Option<SceneBox>,
    /// Continue the stream saved in OUT/checkpoint.onrf (same source; its config and
    /// settings are used).
    #[arg(long, conflicts_with = "force")]
    pub resume: bool,
    /// Start a fresh stream even though OUT holds an earlier stream's checkpoint, replacing it.
    #[arg(long)]
    pub force: bool,
    /// After the stream, train a model offline on all its training frames with the same
    /// number of steps and compare the held-out quality.
    #[arg(long)]
    pub compare_offline: bool,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    pub no_masks: bool,
    /// Built-in config to start from; default: `spacecraft` (the method) for --scene, --watch
    /// and SPEED+/SHIRT/simulator folders, `default` for NeRF-synthetic folders.
    #[arg(long, value_parser = preset_parser())]
    pub preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config, at the top level or
    /// in a `[config]` table (a full file works too).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Random seed of the model (overrides the config).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Largest memory the model's arena may take (e.g. 8G, 512M); default: 80 % of the
    /// machine's available memory. Checked before anything is allocated.
    #[arg(long, value_parser = values::byte_size)]
    pub memory_limit: Option<u64>,
    /// Worker threads, 1 to 1024 (results do not depend on it).
    #[arg(long, default_value_t = 2, value_parser = |text: &str| values::count_in(text, 1..=1024))]
    pub threads: usize,
    /// Output folder: checkpoint.onrf (and the anytime points' model snapshots in
    /// checkpoint.snapshots/), anytime.csv, anytime.png, anytime_time.png, summary.md,
    /// metrics.json.
    #[arg(long, default_value = "runs/stream")]
    pub out: PathBuf,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Policy {
    Fifo,
    Novelty,
    Coverage,
}

impl From<Policy> for Replacement {
    fn from(policy: Policy) -> Replacement {
        match policy {
            Policy::Fifo => Replacement::Fifo,
            Policy::Novelty => Replacement::Novelty,
            Policy::Coverage => Replacement::Coverage,
        }
    }
}

pub fn run(args: &StreamArgs) -> Fallible<()> {
    stop_on_signal()?;
    let max_side = Some(args.size as u32);
    if let Some(name) = &args.scene {
        let mut scene = Scene::load(name)?;
        scene.spec.frames = args.frames;
        scene.spec.set_width(args.size);
        let mut source = SimulatorSource::new(&scene)?;
        stream_from(args, &mut source)
    } else if let Some(dir) = &args.data {
        stream_from(args, &mut DatasetSource::open(dir, max_side, args.rate)?)
    } else if let Some(dir) = &args.watch {
        let options = WatchOptions {
            poll: Duration::from_millis(args.poll_ms),
            grace: Duration::from_millis(args.grace_ms),
            idle_timeout: args.idle_timeout.0,
        };
        stream_from(args, &mut WatchedFolder::open(dir, max_side, options)?)
    } else {
        Err("give a source: --scene, --data or --watch".into())
    }
}

/// The stream's model config: `--preset` (else the preset for the source), a `--config`
/// file's fields, then `--seed`.
fn model_config(args: &StreamArgs) -> Fallible<Config> {
    let (preset, file) = (args.preset.as_deref(), args.config.as_deref());
    let mut config = match (&args.data, &args.scene) {
        (Some(dir), _) => config_for_data(preset, dir, file)?,
        (None, Some(_)) => preset_config(preset, presets::SPACECRAFT, "a simulated scene", file)?,
        (None, None) => preset_config(
            preset,
            presets::SPACECRAFT,
            "a watched folder of SPEED+ frames",
            file,
        )?,
    };
    if let Some(seed) = args.seed {
        config.seed = seed;
    }
    Ok(config)
}

/// Stream from `source`, with its masks applied unless `--no-masks`.
fn stream_from(args: &StreamArgs, source: &mut dyn FrameSource) -> Fallible<()> {
    if args.no_masks {
        stream_over(args, source)
    } else {
        stream_over(args, &mut MaskedSource::new(source))
    }
}

fn stream_over(args: &StreamArgs, source: &mut dyn FrameSource) -> Fallible<()> {
    let checkpoint_path = args.out.join("checkpoint.onrf");
    let (config, mut state, resumed) = if args.resume {
        let (config, state) = stream::resume(&checkpoint_path, source)?;
        (config, state, true)
    } else {
        orbit_nerf_host::io::check_fresh_checkpoint(&checkpoint_path, args.force, "stream")?;
        let mut info = source.info().clone();
        info.frames = info.frames.or(args.max_frames);
        let base = model_config(args)?;
        let config_box = match &args.config {
            Some(path) => train::config_scene_box(path)?
                .map(|b| (b, format!("the config file {}", path.display()))),
            None => None,
        };
        // The rule of `choose_box`, less finding: a stream sees one frame at a time.
        if let Some((stated, by)) = args
            .scene_box
            .map(|b| (b, "--scene-box".to_owned()))
            .or(config_box)
        {
            info.scene_box = Some(stated);
            println!("scene box {}, given by {by}", box_text(stated.0, stated.1));
        } else if let Some(known) = info.scene_box {
            println!(
                "scene box {}, from the source (truth.json or the format)",
                box_text(known.0, known.1)
            );
        }
        let config = stream::stream_config(
            &base,
            &info,
            args.store,
            args.policy.into(),
            args.steps_per_frame,
        )?;
        let settings = StreamSettings {
            steps_per_frame: args.steps_per_frame,
            holdout_every: args.holdout,
            eval_every: args.eval_every,
            checkpoint_every: args.checkpoint_every,
            fit_steps: args.fit_steps,
        };
        (
            config,
            StreamState::new(settings, config.max_frames as usize, source.info()),
            false,
        )
    };
    let executor = RayonExecutor::new(args.threads)?;
    let plan = MemoryPlan::new(&config);
    memory::check_arena(
        Path::new(&format!("the model for {}", source.info().name)),
        &plan,
        memory::limit_or_default(args.memory_limit),
    )?;
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).map_err(|e| format!("config: {e}"))?;
    if resumed {
        stream::restore(&checkpoint_path, &mut trainer)?;
        println!(
            "resuming {} at arrival {} ({} steps done)",
            checkpoint_path.display(),
            state.position,
            trainer.state().step
        );
    }
    println!(
        "streaming {} into a store of {} frames ({:?} replacement), {} steps per frame, {} threads; arena {:.1} MiB",
        source.info().name,
        config.max_frames,
        config.replacement,
        state.settings.steps_per_frame,
        args.threads,
        plan.total as f64 / (1 << 20) as f64
    );
    let bar = match source.info().frames.or(args.max_frames) {
        Some(frames) => ProgressBar::new(frames),
        None => ProgressBar::no_length(),
    }
    .with_style(bar_style(
        "stream [{bar:30}] {pos}/{len} frames {per_sec} {msg}",
    )?);
    bar.set_position(state.position);
    let start = Instant::now();
    let control = Control {
        stop: &STOP,
        stop_after: args.stop_after,
        end_after: args.max_frames,
        checkpoint: &checkpoint_path,
    };
    let mut last_quality = String::from("no held-out score yet");
    let outcome = stream::run(
        &mut trainer,
        &executor,
        source,
        &mut state,
        &control,
        &mut |event| match event {
            Event::Frame { fate, mse, .. } => {
                let fate = match fate {
                    Fate::Stored { slot } => format!("-> slot {slot}"),
                    Fate::Rejected => "rejected".into(),
                    Fate::HeldOut => "held out".into(),
                };
                bar.set_message(format!("{fate:>12}, loss {mse:.5}, {last_quality}"));
                bar.inc(1);
            }
            Event::Bad(bad) => {
                // `suspend` prints also when the bar is hidden (output not a terminal).
                bar.suspend(|| println!("bad frame {}: {}", bad.position, bad.message));
                bar.inc(1);
            }
            Event::Anytime(point) => {
                // Before the first held-out view arrives there is nothing to score.
                let quality = if point.held_out_views == 0 {
                    "no held-out view yet".to_string()
                } else {
                    last_quality = format!("held-out so far {:.2} dB", point.psnr);
                    format!(
                        "PSNR {:.2} dB, SSIM {:.4} on the {} held-out views seen so far",
                        point.psnr, point.ssim, point.held_out_views
                    )
                };
                bar.suspend(|| println!(
                    "{:>4} frames seen, {:>3} held, {:>5} steps: {quality}, {:.2} s/frame, RSS {:.1} MiB",
                    point.frames_seen,
                    point.frames_held,
                    point.steps,
                    point.seconds_per_frame,
                    point.rss_mib
                ));
            }
            Event::Checkpoint(_) => {}
        },
    )?;
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    if outcome == Outcome::Stopped {
        stream::write_curve(&args.out, &state.curve, None, None)?;
        println!(
            "stopped after {} arrivals; checkpoint {} (continue with --resume)",
            state.position,
            checkpoint_path.display()
        );
        return Ok(());
    }
    let fixed = fixed_set(args, source, &state, &config, &checkpoint_path, &executor)?;
    let offline = if args.compare_offline {
        Some(offline(
            source,
            &state,
            &config,
            trainer.state().step,
            &executor,
        )?)
    } else {
        None
    };
    stream::write_curve(
        &args.out,
        &state.curve,
        Some(&fixed),
        offline.as_ref().map(|(points, _)| points.as_slice()),
    )?;
    // The last point's seconds are the offline training time; `seconds` adds its scoring.
    let offline = offline.and_then(|(points, seconds)| {
        let last = points.last()?;
        Some((last.metrics, last.seconds, seconds))
    });
    let summary = summary(&state, &trainer, seconds, offline.as_ref());
    orbit_nerf_host::io::write_atomic(&args.out.join("summary.md"), summary.as_bytes())?;
    figures(&state, &trainer, seconds, offline.as_ref()).write(&args.out)?;
    print!("{summary}");
    println!(
        "checkpoint (snapshots beside it), anytime.csv, anytime.png, anytime_time.png, summary.md and metrics.json in {}",
        args.out.display()
    );
    Ok(())
}

/// Score every anytime point's snapshot on all the stream's held-out views, with a progress
/// bar.
fn fixed_set(
    args: &StreamArgs,
    source: &dyn FrameSource,
    state: &StreamState,
    config: &Config,
    checkpoint_path: &Path,
    executor: &RayonExecutor,
) -> Fallible<Vec<stream::FixedSetPoint>> {
    let bar = ProgressBar::new(state.curve.len() as u64).with_style(bar_style(
        "scoring the snapshots on all held-out views [{bar:30}] {pos}/{len} {per_sec} eta {eta}",
    )?);
    let points = stream::fixed_set_curve(
        checkpoint_path,
        source,
        state,
        config,
        executor,
        args.memory_limit,
        &mut |_| bar.inc(1),
    )?;
    bar.finish_and_clear();
    Ok(points)
}

/// Train the offline reference, scoring it at the step counts of the stream's points, with a
/// progress bar. Returns its points and its wall time (training and scoring).
fn offline(
    source: &dyn FrameSource,
    state: &StreamState,
    config: &Config,
    steps: u32,
    executor: &RayonExecutor,
) -> Fallible<(Vec<stream::OfflinePoint>, f64)> {
    let bar = ProgressBar::new(steps as u64).with_style(bar_style(
        "offline [{bar:30}] {pos}/{len} steps {per_sec} eta {eta}",
    )?);
    let start = Instant::now();
    let at_steps: Vec<u32> = state.curve.iter().map(|p| p.steps).collect();
    let points = stream::offline_reference(
        source,
        state,
        config,
        steps,
        &at_steps,
        executor,
        &mut |_| bar.inc(1),
    )?;
    bar.finish_and_clear();
    Ok((points, start.elapsed().as_secs_f64()))
}

/// The summary's models for `metrics.json`: the streamed model at its last held-out score,
/// and the offline reference when there is one (no per-view figures: a stream keeps means).
fn figures(
    state: &StreamState,
    trainer: &Trainer<'_>,
    seconds: f64,
    offline: Option<&(ViewMetrics, f64, f64)>,
) -> Figures {
    let mut models = Vec::new();
    if let Some(last) = state.curve.last() {
        models.push(ModelFigures {
            name: "streamed".into(),
            mean: last.metrics(),
            views: Vec::new(),
            training: Some(TrainingFigures {
                steps: trainer.state().step as u64,
                steps_skipped: trainer.state().skipped as u64,
                seconds,
                // This session's steps (a resumed stream's since it resumed, as `train`'s).
                samples_per_ray: if state.session.steps > 0 {
                    state.session.samples_per_ray()
                } else {
                    f64::NAN
                },
            }),
            mean_at: None,
            pose_refinement: None,
        });
    }
    if let Some((metrics, _, _)) = offline {
        models.push(ModelFigures {
            name: "offline reference".into(),
            mean: *metrics,
            views: Vec::new(),
            training: None,
            mean_at: None,
            pose_refinement: None,
        });
    }
    Figures::new("stream", models)
}

fn summary(
    state: &StreamState,
    trainer: &Trainer<'_>,
    seconds: f64,
    offline: Option<&(ViewMetrics, f64, f64)>,
) -> String {
    let mut text = String::from("# Stream summary\n\n");
    let _ = writeln!(
        text,
        "- {} arrivals: {} usable ({} held out, {} offered to the store: {} stored, {} turned away), {} bad",
        state.position,
        state.usable,
        state.held_out.len(),
        state.offered,
        state.stored,
        state.rejected,
        state.bad.len()
    );
    let _ = writeln!(
        text,
        "- {} frames held at the end, {} training steps, {:.1} s wall time ({:.2} s per arrival)",
        trainer.frames().len(),
        trainer.state().step,
        seconds,
        seconds / state.position.max(1) as f64
    );
    for bad in &state.bad {
        let _ = writeln!(text, "- bad frame {}: {}", bad.position, bad.message);
    }
    if let Some(last) = state.curve.last() {
        let _ = writeln!(
            text,
            "- streamed model: held-out PSNR {:.2} dB (right half {:.2} dB, foreground {:.2} dB), SSIM {:.4}, on {} views",
            last.psnr, last.psnr_right, last.psnr_foreground, last.ssim, last.held_out_views
        );
    }
    if let Some((metrics, training_seconds, offline_seconds)) = offline {
        let _ = writeln!(
            text,
            "- offline reference (all training frames at once, same steps, {training_seconds:.1} s of training, {offline_seconds:.1} s with scoring): held-out PSNR {:.2} dB (right half {:.2} dB, foreground {:.2} dB), SSIM {:.4}",
            metrics.psnr_full, metrics.psnr_right, metrics.psnr_foreground, metrics.ssim_full
        );
    }
    if let (Some(first), Some(last)) = (
        state
            .curve
            .iter()
            .find(|p| p.frames_seen >= trainer.config().max_frames as u64),
        state.curve.last(),
    ) {
        let _ = writeln!(
            text,
            "- resident memory: {:.1} MiB at {} frames seen, {:.1} MiB at {}",
            first.rss_mib, first.frames_seen, last.rss_mib, last.frames_seen
        );
    }
    text
}
