//! `orbit-nerf stream`: ingest frames one at a time from a dataset folder, a watched folder or
//! the simulator into the core's fixed frame store, train a fixed number of steps per frame,
//! report the anytime quality, checkpoint, and resume after Ctrl-C or SIGTERM.

use super::{
    FIT_STEPS, Fallible, STOP, SceneBox, bar_style, machine_threads, parse_scene_box,
    parse_threads, preset_parser, stop_on_signal,
};
use indicatif::{ProgressBar, ProgressStyle};
use orbit_nerf_core::Replacement;
use orbit_nerf_host::sim::Scene;
use orbit_nerf_host::stream::{
    self, DatasetSource, Event, FrameSource, Keep, MaskedSource, ModelChoice, SimulatorSource,
    SourceKind, Stage, StreamEnd, StreamObserver, StreamRequest, StreamSettings, WatchOptions,
    WatchedFolder,
};
use orbit_nerf_host::values;
use std::path::PathBuf;
use std::time::Duration;

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
    /// The core's store takes the bytes of this many whole frames (--keep frames holds
    /// that many; --keep rays keeps a reservoir of pixels in the same bytes).
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u16).range(1..))]
    pub store: u16,
    /// What the store keeps in the bytes of --store whole frames: `rays`, a reservoir of
    /// pixels drawn alike from every frame seen (and every frame's camera, label and learned
    /// parameters, up to --remember frames), or `frames`, the latest --store frames whole. A
    /// store too small for a reservoir beside the frames' parameters keeps whole frames
    /// (unless --remember is given); the stream's first lines say which store it got.
    #[arg(long, value_enum, default_value_t = KeepArg::Rays)]
    pub keep: KeepArg,
    /// With --keep rays: the most frames remembered (their parameters take room from the
    /// reservoir) [default: the source's frames when it says how many, else 1024, but no
    /// more than leave the reservoir half the bytes, nor fewer than --store].
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..))]
    pub remember: Option<u16>,
    /// Replacement policy of a full store (whole frames), or of a full table of remembered
    /// frames (rays).
    #[arg(long, value_enum, default_value_t = Policy::Fifo)]
    pub policy: Policy,
    /// Training steps after each usable frame (with --budget-ms: the steps the learning-rate
    /// schedule expects per frame).
    #[arg(long, default_value_t = 9, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps_per_frame: u32,
    /// Training steps on the store after the source ends (the settle, 0 to 10^7; default: as
    /// many as the stream had taken by then; 0: none): the learning rate stays at its peak
    /// until the last arrival and decays over the settle, so the last frames get the steps
    /// the first ones had; the settle gets its own point on the anytime curve.
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=10_000_000))]
    pub settle_steps: Option<u32>,
    /// Real-time mode: after each usable frame, train until this many milliseconds (1 to
    /// 3600000) have passed since it arrived, at least one step; the summary says how many
    /// steps frames managed. The result then depends on the machine's speed and load
    /// (without it the stream is deterministic).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=3_600_000))]
    pub budget_ms: Option<u64>,
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
    /// Stop (and checkpoint) once the stream has taken this many training steps in all (a
    /// resumed stream's count goes on), as Ctrl-C would, possibly within a frame's steps;
    /// continue with --resume.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub stop_after: Option<u32>,
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
    /// Random seed of the model, 0 to 2^63-1 (overrides the config).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=super::MAX_SEED))]
    pub seed: Option<u64>,
    /// Largest memory the model's arena may take (e.g. 8G, 512M); default: 80 % of the
    /// machine's available memory. Checked before anything is allocated.
    #[arg(long, value_parser = values::byte_size)]
    pub memory_limit: Option<u64>,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    pub threads: usize,
    /// Output folder: checkpoint.onrf (and the anytime points' model snapshots in
    /// checkpoint.snapshots/), anytime.csv, anytime.png, anytime_time.png, summary.md,
    /// metrics.json.
    #[arg(long, default_value = "runs/stream")]
    pub out: PathBuf,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeepArg {
    Rays,
    Frames,
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
        stream_from(args, &SourceKind::Simulator, &mut source)
    } else if let Some(dir) = &args.data {
        let mut source = DatasetSource::open(dir, max_side, args.rate)?;
        stream_from(args, &SourceKind::DatasetFolder(dir.clone()), &mut source)
    } else if let Some(dir) = &args.watch {
        let options = WatchOptions {
            poll: Duration::from_millis(args.poll_ms),
            grace: Duration::from_millis(args.grace_ms),
            idle_timeout: args.idle_timeout.0,
        };
        let mut source = WatchedFolder::open(dir, max_side, options)?;
        stream_from(args, &SourceKind::WatchedFolder, &mut source)
    } else {
        Err("give a source: --scene, --data or --watch".into())
    }
}

/// The library's request for the flags.
fn request(args: &StreamArgs) -> StreamRequest {
    StreamRequest {
        out: args.out.clone(),
        store: args.store,
        keep: match args.keep {
            KeepArg::Rays => Keep::Rays {
                remember: args.remember,
            },
            KeepArg::Frames => Keep::Frames,
        },
        replacement: args.policy.into(),
        settings: StreamSettings {
            steps_per_frame: args.steps_per_frame,
            budget_ms: args.budget_ms,
            holdout_every: args.holdout,
            eval_every: args.eval_every,
            checkpoint_every: args.checkpoint_every,
            fit_steps: args.fit_steps,
            settle_steps: args.settle_steps,
        },
        model: ModelChoice {
            preset: args.preset.clone(),
            config_file: args.config.clone(),
            seed: args.seed,
        },
        scene_box: args.scene_box,
        stop_after: args.stop_after,
        end_after: args.max_frames,
        compare_offline: args.compare_offline,
        memory_limit: args.memory_limit,
        threads: args.threads,
        resume: args.resume,
        replace: args.force,
    }
}

/// Stream from `source` (with its masks applied unless `--no-masks`) and print the outcome.
fn stream_from(args: &StreamArgs, kind: &SourceKind, source: &mut dyn FrameSource) -> Fallible<()> {
    let request = request(args);
    let mut printer = Printer {
        bar: ProgressBar::hidden(),
        styles: [
            bar_style("stream [{bar:30}] {pos}/{len} frames {per_sec} {msg}")?,
            bar_style(
                "scoring the snapshots on all held-out views [{bar:30}] {pos}/{len} {per_sec} eta {eta}",
            )?,
            bar_style("offline [{bar:30}] {pos}/{len} steps {per_sec} eta {eta}")?,
        ],
        last_quality: String::from("no held-out score yet"),
    };
    let end = if args.no_masks {
        request.run(kind, source, &STOP, &mut printer)
    } else {
        request.run(kind, &mut MaskedSource::new(source), &STOP, &mut printer)
    };
    printer.bar.finish_and_clear();
    match end? {
        StreamEnd::Stopped { position, step } => println!(
            "stopped after {position} arrivals ({step} training steps); checkpoint {} (continue with --resume)",
            request.checkpoint_path().display()
        ),
        StreamEnd::Finished(finished) => {
            print!("{}", finished.summary);
            println!(
                "checkpoint (snapshots beside it), anytime.csv, anytime.png, anytime_time.png, summary.md and metrics.json in {}",
                args.out.display()
            );
        }
    }
    Ok(())
}

/// Prints the stream's notes and events and draws its progress bars: the arrivals, then the
/// scoring of the snapshots and the offline reference's training.
struct Printer {
    /// The bar of the stage under way (hidden before the stream starts).
    bar: ProgressBar,
    /// Styles of the bars of the stream, the scoring and the offline reference.
    styles: [ProgressStyle; 3],
    /// The last held-out score, shown beside the stream's bar.
    last_quality: String,
}

impl Printer {
    /// Clear the bar shown and show `bar` instead.
    fn replace_bar(&mut self, bar: ProgressBar) {
        self.bar.finish_and_clear();
        self.bar = bar;
    }
}

impl StreamObserver for Printer {
    fn note(&mut self, note: &str) {
        println!("{note}");
    }

    fn start(&mut self, position: u64, arrivals: Option<u64>) {
        let bar = arrivals.map_or_else(ProgressBar::no_length, ProgressBar::new);
        self.replace_bar(bar.with_style(self.styles[0].clone()));
        self.bar.set_position(position);
    }

    fn event(&mut self, event: &Event<'_>) {
        match event {
            Event::Frame { fate, mse, .. } => {
                let quality = &self.last_quality;
                self.bar
                    .set_message(format!("{fate:>12}, loss {mse:.5}, {quality}"));
                self.bar.inc(1);
            }
            Event::Bad(bad) => {
                // `suspend` prints also when the bar is hidden (output not a terminal).
                self.bar.suspend(|| println!("{bad}"));
                self.bar.inc(1);
            }
            Event::Anytime(point) => {
                if point.held_out_views > 0 {
                    self.last_quality = format!("held-out so far {:.2} dB", point.psnr);
                }
                self.bar.suspend(|| println!("{point}"));
            }
            Event::Checkpoint(_) => {}
        }
    }

    fn progress(&mut self, stage: Stage, done: u64, total: u64) {
        if done == 0 {
            let style = match stage {
                Stage::FixedSet => &self.styles[1],
                Stage::OfflineReference => &self.styles[2],
            };
            self.replace_bar(ProgressBar::new(total).with_style(style.clone()));
        }
        self.bar.set_position(done);
    }
}
