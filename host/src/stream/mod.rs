//! Streaming: frames arrive one at a time from a [`FrameSource`] and go into the core's
//! fixed frame store through its replacement policy (`Trainer::ingest_frame`), with a fixed
//! number of training steps after each usable frame, so the result depends only on the config,
//! the arrival order and the seed (not on timing, pacing, polling or thread count).
//!
//! - Every `holdout_every`-th usable frame is held out for the anytime-quality curve: every
//!   `eval_every` usable frames the held-out views seen so far are scored as `train::evaluate`
//!   scores them (embedding fitted on the left half), with the frames seen and held, the steps,
//!   the wall time and the resident memory of the process. Those views differ from point to
//!   point, so each point also saves a snapshot of the model (what rendering and the
//!   embedding fit read: planes, MLP, occupancy bits, the slots' embeddings; next to the
//!   checkpoint, in `<checkpoint>.snapshots/`), and at the end [`fixed_set_curve`] scores
//!   every snapshot on all the stream's held-out views: the curve on one fixed set.
//! - Bad frames (unreadable or wrong-size image, missing or malformed label, non-finite pose,
//!   all-black or all-saturated image) are reported once and skipped; nothing learned is lost.
//! - The checkpoint holds the trainer's whole state plus a `stream` section ([`StreamState`]),
//!   written atomically every `checkpoint_every` frames and when the stream stops; resuming
//!   from it with the same source skips the frames already seen and ends bit-identical to an
//!   uninterrupted run. A stop request is heard within a training step (the step is given
//!   up), and a stop at a step count ([`Control::stop_after`]) ends where that count falls;
//!   either way the resumed stream first takes the rest of the interrupted frame's steps.
//! - [`StreamRequest::run`] is the whole stream in one call (config, scene box, memory,
//!   resume, scoring on all held-out views, the offline reference, the output files), for the
//!   CLI and for any program that brings its own frames.
//! - No score and no checkpoint from a model that learned nothing: before every anytime point
//!   and checkpoint the model is checked by `train`'s rule ([`train::check_trained`]: no
//!   training ray met the scene box, every step skipped, a non-finite parameter).

pub mod session;
pub mod source;

pub use session::{
    FinishedStream, ModelChoice, OfflineReference, STREAM_LR_DECAY_START, SourceKind, Stage,
    StreamEnd, StreamObserver, StreamRequest,
};
#[cfg(feature = "simulator")]
pub use source::SimulatorSource;
pub use source::{
    Arrival, DatasetSource, FrameSource, MaskedSource, SourceInfo, WatchOptions, WatchedFolder,
};

use crate::checkpoint;
use crate::dataset::{Dataset, Frame, SceneBoxOrigin};
use crate::error::{HostError, Result};
use crate::pipeline::StepTally;
use crate::report::{self, ViewMetrics};
use crate::train;
use orbit_nerf_core::{Config, Executor, Ingested, MemoryPlan, Replacement, Trainer};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// How a stream trains and reports (stored in its checkpoints, so a resumed stream keeps them).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StreamSettings {
    /// Training steps after each usable frame (with `budget_ms`: the steps the schedule
    /// expects per frame).
    pub steps_per_frame: u32,
    /// Real-time mode: after each usable frame, train until this many milliseconds have
    /// passed since it arrived (at least one step) instead of `steps_per_frame` steps. The
    /// result then depends on the machine's speed and load; `None` (the default) keeps the
    /// stream deterministic.
    #[serde(default)]
    pub budget_ms: Option<u64>,
    /// Every this many usable frames, one is held out (the `n`-th, `2n`-th, ...).
    pub holdout_every: u64,
    /// Score the held-out views every this many usable frames.
    pub eval_every: u64,
    /// Write the checkpoint every this many arrivals.
    pub checkpoint_every: u64,
    /// Steps fitting a held-out view's embedding on its left half.
    pub fit_steps: u32,
    /// Steps trained on the store after the source ends (the settle), with the learning rate
    /// decaying over them: the frames that came last get the steps the first ones had, and
    /// the schedule need not decay while frames still arrive. `None`: as many as the stream
    /// had taken when the source ended ([`StreamSettings::settle`]); 0: no settle.
    pub settle_steps: Option<u32>,
}

impl StreamSettings {
    /// The settle's steps after a stream that had taken `arrival_steps` when its source ended.
    pub fn settle(&self, arrival_steps: u32) -> u32 {
        self.settle_steps.unwrap_or(arrival_steps)
    }
}

/// The training steps frames managed in a real-time stream's budget
/// ([`StreamSettings::budget_ms`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct BudgetSteps {
    /// Frames trained on in their budget.
    pub frames: u64,
    /// Steps they took in all.
    pub steps: u64,
    /// Fewest steps a frame took.
    pub min: u32,
    /// Most steps a frame took.
    pub max: u32,
}

impl BudgetSteps {
    fn add(&mut self, steps: u32) {
        self.min = if self.frames == 0 {
            steps
        } else {
            self.min.min(steps)
        };
        self.max = self.max.max(steps);
        self.frames += 1;
        self.steps += steps as u64;
    }

    /// Mean steps per frame (0 before a frame).
    pub fn mean(&self) -> f64 {
        self.steps as f64 / self.frames.max(1) as f64
    }
}

/// A frame that was reported and skipped.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BadFrame {
    /// Its arrival number (0 for the first arrival).
    pub position: u64,
    /// What is wrong with it, naming its file (one line).
    pub message: String,
}

/// `bad frame POSITION: MESSAGE`, as the summary and the CLI report it.
impl std::fmt::Display for BadFrame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "bad frame {}: {}", self.position, self.message)
    }
}

/// One point of the anytime-quality curve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnytimePoint {
    /// Arrivals so far (usable or not).
    pub frames_seen: u64,
    /// Frames in the store.
    pub frames_held: usize,
    /// Held-out views scored (those seen so far that still read).
    pub held_out_views: usize,
    /// Training steps taken.
    pub steps: u32,
    /// Mean PSNR over the held-out views, whole image.
    pub psnr: f64,
    /// Mean SSIM, whole image.
    pub ssim: f64,
    /// Mean PSNR of the right halves (the left halves fit the embeddings).
    pub psnr_right: f64,
    /// Mean SSIM of the right halves.
    pub ssim_right: f64,
    /// Mean PSNR of the foreground (NaN without masks).
    pub psnr_foreground: f64,
    /// Mean wall time per arrival since the previous point (ingest and training, not
    /// waiting); NaN for the point after the settle, which had no arrival.
    pub seconds_per_frame: f64,
    /// Wall time of ingest and training since the stream started (across resumes; not
    /// waiting, scoring or checkpointing).
    pub seconds: f64,
    /// Resident memory of the process (MiB), NaN where it cannot be read.
    pub rss_mib: f64,
}

impl AnytimePoint {
    /// The point's held-out means as view metrics; what a point does not keep (JNB, the
    /// right half's foreground PSNR) is NaN.
    pub fn metrics(&self) -> ViewMetrics {
        ViewMetrics {
            psnr_right: self.psnr_right,
            ssim_right: self.ssim_right,
            jnb_right: f64::NAN,
            psnr_full: self.psnr,
            ssim_full: self.ssim,
            jnb_full: f64::NAN,
            psnr_foreground: self.psnr_foreground,
            psnr_foreground_right: f64::NAN,
            cpbd_full: f64::NAN,
        }
    }
}

/// One line of the point: the frames seen and held, the steps, the held-out score (or that no
/// held-out view has arrived yet: nothing to score), the seconds per frame and the memory.
impl std::fmt::Display for AnytimePoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:>4} frames seen, {:>3} held, {:>5} steps: ",
            self.frames_seen, self.frames_held, self.steps
        )?;
        if self.held_out_views == 0 {
            f.write_str("no held-out view yet")?;
        } else {
            write!(
                f,
                "PSNR {:.2} dB, SSIM {:.4} on the {} held-out views seen so far",
                self.psnr, self.ssim, self.held_out_views
            )?;
        }
        if self.seconds_per_frame.is_nan() {
            f.write_str(" (after the settle)")?;
        } else {
            write!(f, ", {:.2} s/frame", self.seconds_per_frame)?;
        }
        write!(f, ", RSS {:.1} MiB", self.rss_mib)
    }
}

/// Everything about a stream beyond the trainer's state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StreamState {
    /// How the stream trains and reports.
    pub settings: StreamSettings,
    /// The source's [`SourceInfo::identity`]: a resume from another source is refused.
    pub source: String,
    /// [`FrameSource::arrived`] at the last checkpoint.
    pub arrived: Vec<String>,
    /// Arrivals consumed: the source position to resume from.
    pub position: u64,
    /// Arrivals that were usable frames (held out or offered to the store).
    pub usable: u64,
    /// Frames offered to the store (the core's arrival numbers).
    pub offered: u32,
    /// Frames the store took.
    pub stored: u64,
    /// Frames the replacement policy turned away.
    pub rejected: u64,
    /// Source positions of the held-out frames.
    pub held_out: Vec<u64>,
    /// Source position of the frame in each slot.
    pub slot_positions: Vec<Option<u64>>,
    /// The bad frames, reported and skipped.
    pub bad: Vec<BadFrame>,
    /// The anytime-quality curve so far.
    pub curve: Vec<AnytimePoint>,
    /// Real-time mode: the steps each frame managed in its budget.
    #[serde(default)]
    pub budget_steps: BudgetSteps,
    /// The trainer's step count when the settle began (the source had ended); `None` before.
    pub settle_from: Option<u32>,
    /// The learning rate follows the stream's own schedule (the config file did not set
    /// `lr_decay_start`): when the settle begins it is planned anew, to decay over the settle
    /// from the step the source ended at ([`settle_schedule`]), whatever the stream expected
    /// (a watched folder, a real-time stream or bad frames take other step counts).
    pub decay_over_settle: bool,
    /// Wall time of ingest and training so far (the curve's `seconds`).
    pub seconds: f64,
    /// This session's training steps, rays and samples (since the stream started or
    /// resumed; not saved: a resumed stream counts afresh, as `train --resume` does).
    #[serde(skip)]
    pub session: StepTally,
}

impl StreamState {
    /// A stream that has seen nothing yet, into a store of `capacity` slots, from `source`.
    pub fn new(settings: StreamSettings, capacity: usize, source: &SourceInfo) -> StreamState {
        StreamState {
            settings,
            source: source.identity.clone(),
            arrived: Vec::new(),
            position: 0,
            usable: 0,
            offered: 0,
            stored: 0,
            rejected: 0,
            held_out: Vec::new(),
            slot_positions: vec![None; capacity],
            bad: Vec::new(),
            curve: Vec::new(),
            budget_steps: BudgetSteps::default(),
            settle_from: None,
            decay_over_settle: false,
            seconds: 0.0,
            session: StepTally::default(),
        }
    }
}

/// What happened to an arriving frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fate {
    /// Into `slot`, replacing whatever it held.
    Stored {
        /// The store's slot.
        slot: usize,
    },
    /// The policy kept the held frames.
    Rejected,
    /// Held out for the anytime-quality curve.
    HeldOut,
}

/// `-> slot N`, `rejected` or `held out` (padded to a given width).
impl std::fmt::Display for Fate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Fate::Stored { slot } => f.pad(&format!("-> slot {slot}")),
            Fate::Rejected => f.pad("rejected"),
            Fate::HeldOut => f.pad("held out"),
        }
    }
}

/// Progress reports of a running stream.
pub enum Event<'e> {
    /// A usable frame went in (or was held out or turned away) and its steps were taken.
    Frame {
        /// Its arrival number.
        position: u64,
        /// Its name (the source's: a file, a simulated frame).
        name: &'e str,
        /// What became of it.
        fate: Fate,
        /// Mean squared error of the last training step.
        mse: f32,
    },
    /// A bad frame, reported once and skipped.
    Bad(&'e BadFrame),
    /// A point of the anytime-quality curve, scored and its snapshot saved.
    Anytime(&'e AnytimePoint),
    /// The checkpoint, written to this path.
    Checkpoint(&'e Path),
}

/// How a stream is stopped and where it saves itself.
pub struct Control<'c> {
    /// Raised (by a signal handler) to stop within the current training step: the step is
    /// given up, the stream checkpoints its last finished step and, resumed, first takes the
    /// rest of the frame's steps.
    pub stop: &'c AtomicBool,
    /// Stop once the trainer has taken this many steps in all (a resumed stream's count goes
    /// on), as `stop` would: within a frame's steps when the count falls there, the resumed
    /// stream first taking the rest of them (deterministic interruption).
    pub stop_after: Option<u32>,
    /// End the stream (as if the source ended) after this many arrivals.
    pub end_after: Option<u64>,
    /// Where the stream's checkpoint is written (its snapshots beside it).
    pub checkpoint: &'c Path,
}

/// How [`run`] ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// The source ended.
    Finished,
    /// Stopped early; the checkpoint resumes it.
    Stopped,
}

/// What a stream's frame store keeps in the bytes of `store` whole frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Keep {
    /// `store` whole frames: the store forgets a frame's pixels (and its learned parameters)
    /// when the replacement policy gives up its slot.
    Frames,
    /// A ray reservoir in the same bytes, shared alike by every frame seen, and the camera,
    /// label and learned parameters (appearance embedding, pose correction) of up to
    /// `remember` frames; past that the replacement policy gives up a frame's slot and its
    /// pixels (`Config::ray_store`).
    Rays {
        /// The most frames remembered; `None`: all the source's frames when it says how
        /// many (at most 65535), else [`DEFAULT_REMEMBER`], but no more than leave the
        /// reservoir half the bytes the whole frames' pixels would take, nor fewer than
        /// `store`.
        remember: Option<u16>,
    },
}

/// Frames a ray reservoir remembers when neither the caller nor the source says how many.
pub const DEFAULT_REMEMBER: u16 = 1024;

/// The config of a stream: `base` with the source's scene box and background, a store of the
/// bytes of `store` whole frames of the source's frame size kept as `keep` says, the
/// replacement policy, and a schedule over the steps the source's frames will get and the
/// settle after them (when it says how many it has; otherwise `base.steps`). With
/// [`Keep::Rays`] the reservoir takes what the whole frames would have taken less what
/// remembering `remember` frames' parameters adds, so the arena is no larger than the whole
/// frames' one; refused when no pixel is left.
pub fn stream_config(
    base: &Config,
    info: &SourceInfo,
    (store, keep): (u16, Keep),
    replacement: Replacement,
    (steps_per_frame, settle_steps): (u32, u32),
) -> Result<Config> {
    let (aabb_min, aabb_max) = info.scene_box.ok_or_else(|| {
        HostError::invalid(
            &info.name,
            "no scene box: the source has no truth.json and a stream cannot find the box from \
             one frame at a time; state it with --scene-box xmin,ymin,zmin,xmax,ymax,zmax",
        )
    })?;
    let mut c = *base;
    c.aabb_min = aabb_min;
    c.aabb_max = aabb_max;
    c.background = info.background;
    c.max_frames = store;
    c.max_pixels_per_frame = info.max_pixels.min(u32::MAX as usize) as u32;
    c.ray_store = 0;
    if let Keep::Rays { remember } = keep {
        let stated = remember.is_some();
        let mut remember = remember.unwrap_or_else(|| {
            info.frames
                .map_or(DEFAULT_REMEMBER, |n| n.clamp(1, u16::MAX as u64) as u16)
        });
        // Unless stated, remember no more frames than leave the reservoir half the bytes the
        // whole frames' pixels took (small frames, a long or unknown stream), nor fewer than
        // the whole frames would have held.
        let half = c.frame_pixel_bytes().0 / 2;
        while !stated
            && remember > store
            && ray_store_in_the_bytes_of(&c, remember)
                .is_none_or(|r| (r.ray_store as usize) * orbit_nerf_core::RAY_ENTRY_BYTES < half)
        {
            remember = (remember / 2).max(store);
        }
        match ray_store_in_the_bytes_of(&c, remember) {
            Some(rays) => c = rays,
            // A store too small for a reservoir beside the frames' parameters and the
            // training's own buffers (a few frames of a few hundred pixels) keeps whole frames
            // unless a number of frames to remember was asked for; the stream's opening line
            // says which store it got.
            None if !stated => {}
            None => {
                return Err(HostError::invalid(
                    &info.name,
                    format!(
                        "the parameters of {remember} remembered frames do not leave a ray reservoir any room in the bytes of {store} whole frames: remember fewer (--remember), store more (--store) or keep whole frames (--keep frames)"
                    ),
                ));
            }
        }
    }
    c.replacement = replacement;
    if let Some(frames) = info.frames {
        let steps = frames.saturating_mul(steps_per_frame as u64) + settle_steps as u64;
        c.steps = steps.clamp(1, u32::MAX as u64) as u32;
    }
    c.warmup_steps = c.warmup_steps.min(c.steps);
    Ok(c)
}

/// `whole` (a store of whole frames) turned into a ray reservoir remembering `remember` frames,
/// the largest whose memory plan is no larger than `whole`'s as plain training carves it (no
/// loss-weighting buffers, no running loss per frame slot): the reservoir pays for those, so
/// the arena is never larger than a store of whole frames without them. `None` if not even
/// one pixel fits.
fn ray_store_in_the_bytes_of(whole: &Config, remember: u16) -> Option<Config> {
    let plain = Config {
        loss_weighted_frames: false,
        ..*whole
    };
    let running_losses = whole.max_frames as usize * core::mem::size_of::<f32>();
    let budget = MemoryPlan::new(&plain).total.checked_sub(running_losses)?;
    let mut c = *whole;
    c.max_frames = remember.max(1);
    c.ray_store = 1;
    let spare = budget.checked_sub(MemoryPlan::new(&c).total)?;
    let entry = orbit_nerf_core::RAY_ENTRY_BYTES;
    c.ray_store = (1 + spare / entry).min(orbit_nerf_core::MAX_RAY_STORE as usize) as u32;
    // Parts start on aligned offsets: step down until the plan fits.
    while MemoryPlan::new(&c).total > budget && c.ray_store > 1 {
        c.ray_store -= 1;
    }
    (MemoryPlan::new(&c).total <= budget).then_some(c)
}

/// Resident memory of this process in MiB (Linux `/proc/self/status`), NaN elsewhere.
pub fn resident_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
            let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib / 1024.0)
        })
        .unwrap_or(f64::NAN)
}

fn core_error(what: impl AsRef<Path>, e: orbit_nerf_core::Error) -> HostError {
    HostError::invalid(what.as_ref(), e.to_string())
}

/// Stream frames from `source` into `trainer` until the source ends or `control` stops it,
/// continuing from `state` (fresh, or restored from a checkpoint with the source already
/// positioned by [`FrameSource::seek`]).
///
/// A stop request is heard within a training step (the step is given up) and checkpoints the
/// last finished step, as does reaching `control.stop_after` steps; a stream stopped in the middle of a frame's steps takes the rest of
/// them first when it resumes ([`steps_owed`]), so it ends bit-identical to one never
/// stopped. Before every anytime point and every checkpoint the model is checked as `train`
/// checks it ([`train::check_trained`] over this session's steps): a stream none of whose
/// training rays met the scene box, whose every step was skipped or whose parameters went
/// non-finite ends with that error, unscored and unsaved.
pub fn run<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &mut S,
    state: &mut StreamState,
    control: &Control<'_>,
    on_event: &mut dyn FnMut(&Event<'_>),
) -> Result<Outcome> {
    // Arrivals and their ingest + training seconds since the last anytime point.
    let (mut window_frames, mut window_seconds) = (0u64, 0.0f64);
    let owed = steps_owed(trainer, state);
    if owed > 0 {
        let started = Instant::now();
        let name = source.info().name.clone();
        let (_, stopped) = train_frame(trainer, executor, state, control, owed, &name)?;
        let seconds = started.elapsed().as_secs_f64();
        state.seconds += seconds;
        if stopped {
            checkpoint(control, trainer, source, state, on_event)?;
            return Ok(Outcome::Stopped);
        }
        (window_frames, window_seconds) = (1, seconds);
        after_frame(
            trainer,
            executor,
            source,
            state,
            control,
            (true, &mut window_frames, &mut window_seconds),
            on_event,
        )?;
    }
    loop {
        if control.stop.load(Ordering::SeqCst)
            || control
                .stop_after
                .is_some_and(|n| trainer.state().step >= n)
        {
            checkpoint(control, trainer, source, state, on_event)?;
            return Ok(Outcome::Stopped);
        }
        if control.end_after.is_some_and(|n| state.position >= n) {
            break;
        }
        let Some(arrival) = source.next(control.stop) else {
            if control.stop.load(Ordering::SeqCst) {
                continue;
            }
            break;
        };
        let started = Instant::now();
        let position = state.position;
        state.position += 1;
        let usable = match arrival {
            Arrival::Frame(frame) => check(trainer, &frame).map(|()| frame),
            Arrival::Bad(e) => Err(e),
        };
        let was_usable = usable.is_ok();
        let mut stopped = false;
        match usable {
            Err(e) => {
                let bad = BadFrame {
                    position,
                    message: e.to_string(),
                };
                on_event(&Event::Bad(&bad));
                state.bad.push(bad);
            }
            Ok(frame) => {
                let fate = ingest(trainer, state, position, &frame)?;
                let mut mse = f32::NAN;
                if !trainer.frames().is_empty() {
                    (mse, stopped) = match state.settings.budget_ms {
                        None => {
                            let steps = state.settings.steps_per_frame;
                            train_frame(trainer, executor, state, control, steps, &frame.name)?
                        }
                        Some(ms) => {
                            let due = started + std::time::Duration::from_millis(ms);
                            train_until(trainer, executor, state, control, due, &frame.name)?
                        }
                    };
                }
                on_event(&Event::Frame {
                    position,
                    name: &frame.name,
                    fate,
                    mse,
                });
            }
        }
        window_frames += 1;
        let seconds = started.elapsed().as_secs_f64();
        window_seconds += seconds;
        state.seconds += seconds;
        if stopped {
            checkpoint(control, trainer, source, state, on_event)?;
            return Ok(Outcome::Stopped);
        }
        after_frame(
            trainer,
            executor,
            source,
            state,
            control,
            (was_usable, &mut window_frames, &mut window_seconds),
            on_event,
        )?;
    }
    // A finished stream that never trained holds nothing worth scoring or saving.
    if state.usable == 0 {
        return Err(HostError::invalid(
            &source.info().name,
            format!(
                "no usable frame in {} arrivals ({} bad); nothing was learned",
                state.position,
                state.bad.len()
            ),
        ));
    }
    if trainer.state().step == 0 {
        return Err(HostError::invalid(
            &source.info().name,
            format!(
                "no training step: all {} usable frames were held out or turned away",
                state.usable
            ),
        ));
    }
    if state.settle_from.is_none()
        && state
            .curve
            .last()
            .is_none_or(|p| p.frames_seen < state.position)
    {
        let per_frame = window_seconds / window_frames.max(1) as f64;
        add_point(
            trainer, executor, source, state, control, per_frame, on_event,
        )?;
    }
    // The settle: the store trained on once the source has ended (a resumed stream finishes
    // the one it began, on the schedule saved with it), then its own point on the curve.
    let from = match state.settle_from {
        Some(from) => from,
        None => {
            let from = trainer.state().step;
            state.settle_from = Some(from);
            if state.decay_over_settle {
                settle_schedule(trainer, from, state.settings.settle(from))
                    .map_err(|e| core_error(&source.info().name, e))?;
            }
            from
        }
    };
    let settle = state.settings.settle(from);
    if settle > 0 {
        let owed = (from.saturating_add(settle)).saturating_sub(trainer.state().step);
        if owed > 0 {
            let started = Instant::now();
            let name = format!("{} (settle)", source.info().name);
            let (_, stopped) = train_frame(trainer, executor, state, control, owed, &name)?;
            state.seconds += started.elapsed().as_secs_f64();
            if stopped {
                checkpoint(control, trainer, source, state, on_event)?;
                return Ok(Outcome::Stopped);
            }
        }
        if state
            .curve
            .last()
            .is_none_or(|p| p.steps < trainer.state().step)
        {
            add_point(
                trainer,
                executor,
                source,
                state,
                control,
                f64::NAN,
                on_event,
            )?;
        }
    }
    checkpoint(control, trainer, source, state, on_event)?;
    Ok(Outcome::Finished)
}

/// Plan the learning rate anew when the settle begins at step `from`: `settle` more steps in
/// all, the peak held until `from` and the cosine decay over the settle
/// ([`session::settle_decay_start`]). A stream of known length that took the steps it
/// expected gets the schedule it was planned with, bit for bit.
pub fn settle_schedule(
    trainer: &mut Trainer<'_>,
    from: u32,
    settle: u32,
) -> core::result::Result<(), orbit_nerf_core::Error> {
    let config = trainer.config();
    let steps = from
        .saturating_add(settle)
        .max(config.warmup_steps)
        .max(config.coarse_to_fine_steps)
        .max(1);
    let decay_start = session::settle_decay_start(config, from as u64, settle);
    trainer.reschedule(steps, decay_start)
}

/// The steps the frame the stream took last still owes: a stop heard within a frame's steps
/// leaves the rest of them to the resumed stream. Every usable frame gets `steps_per_frame`
/// steps once the store holds a frame, and the first usable frame offered is stored (a store
/// with a free slot takes it); so after a whole frame the trainer's step count is
/// `usable * steps_per_frame`, or 0 while nothing was stored. A count that is not short of
/// that by at most one frame's steps owes nothing.
pub fn steps_owed(trainer: &Trainer<'_>, state: &StreamState) -> u32 {
    if state.settings.budget_ms.is_some() {
        // A real-time stream's frames take what their budget allows: nothing is owed.
        return 0;
    }
    let per_frame = state.settings.steps_per_frame as u64;
    let due = if state.stored == 0 {
        0
    } else {
        state.usable.saturating_mul(per_frame)
    };
    let owed = due.saturating_sub(trainer.state().step as u64);
    if owed <= per_frame { owed as u32 } else { 0 }
}

/// Train `steps` steps of the frame named `name` (or the rest of them), hearing
/// `control.stop` within a step and ending at `control.stop_after`'s step count; the steps
/// are added to `state.session`. Returns the last step's loss (NaN before one) and whether a
/// stop cut the steps short.
fn train_frame<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    state: &mut StreamState,
    control: &Control<'_>,
    steps: u32,
    name: &str,
) -> Result<(f32, bool)> {
    let frame_end = trainer.state().step.saturating_add(steps);
    let end = control.stop_after.map_or(frame_end, |n| n.min(frame_end));
    let mut observer = FrameSteps {
        mse: f32::NAN,
        stop: control.stop,
    };
    let tally = crate::pipeline::train_steps(trainer, executor, end, &mut observer).map_err(
        |e| match e {
            HostError::Core(reason) => HostError::invalid(name, reason),
            other => other,
        },
    )?;
    state.session.add(&tally);
    Ok((observer.mse, trainer.state().step < frame_end))
}

/// Real-time mode: train the frame named `name` a step at a time until `due` (at least one
/// step), hearing stops as [`train_frame`] does; the steps taken go into
/// `state.budget_steps`. Returns the last step's loss and whether a stop cut it short.
fn train_until<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    state: &mut StreamState,
    control: &Control<'_>,
    due: Instant,
    name: &str,
) -> Result<(f32, bool)> {
    let first = trainer.state().step;
    let result = loop {
        let (mse, stopped) = train_frame(trainer, executor, state, control, 1, name)?;
        if stopped || Instant::now() >= due {
            break (mse, stopped);
        }
    };
    state.budget_steps.add(trainer.state().step - first);
    Ok(result)
}

/// After an arrival (its steps taken, when it was `usable`): the anytime point when one is
/// due, then the checkpoint when one is due. `window` holds the arrivals and their seconds
/// since the last point.
fn after_frame<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &S,
    state: &mut StreamState,
    control: &Control<'_>,
    (usable, window_frames, window_seconds): (bool, &mut u64, &mut f64),
    on_event: &mut dyn FnMut(&Event<'_>),
) -> Result<()> {
    if usable
        && state
            .usable
            .is_multiple_of(state.settings.eval_every.max(1))
        && state
            .curve
            .last()
            .is_none_or(|p| p.frames_seen < state.position)
    {
        let per_frame = *window_seconds / (*window_frames).max(1) as f64;
        add_point(
            trainer, executor, source, state, control, per_frame, on_event,
        )?;
        (*window_frames, *window_seconds) = (0, 0.0);
    }
    if state
        .position
        .is_multiple_of(state.settings.checkpoint_every.max(1))
    {
        checkpoint(control, trainer, source, state, on_event)?;
    }
    Ok(())
}

/// Score the model on the held-out views so far (once [`check_model`] lets it), save its
/// snapshot and add the point to the curve.
fn add_point<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &S,
    state: &mut StreamState,
    control: &Control<'_>,
    seconds_per_frame: f64,
    on_event: &mut dyn FnMut(&Event<'_>),
) -> Result<()> {
    check_model(control, trainer, state)?;
    let point = anytime_point(trainer, executor, source, state, seconds_per_frame)?;
    save_snapshot(control.checkpoint, state.curve.len(), trainer)?;
    on_event(&Event::Anytime(&point));
    state.curve.push(point);
    Ok(())
}

/// The loss of the last training step (NaN before one), and the stop flag heard within a
/// step.
struct FrameSteps<'s> {
    mse: f32,
    stop: &'s AtomicBool,
}

impl crate::pipeline::Observer for FrameSteps<'_> {
    fn step(
        &mut self,
        _: &mut Trainer<'_>,
        _: u32,
        report: &orbit_nerf_core::StepReport,
    ) -> Result<crate::pipeline::Flow> {
        self.mse = report.mse;
        Ok(crate::pipeline::Flow::Continue)
    }

    fn stop_flag(&self) -> Option<&AtomicBool> {
        Some(self.stop)
    }
}

/// Refuse to score or save a model that learned nothing or is garbage: `train`'s rule
/// ([`train::check_trained`]) over this session's steps, naming the stream's output folder.
fn check_model(control: &Control<'_>, trainer: &Trainer<'_>, state: &StreamState) -> Result<()> {
    let out = control
        .checkpoint
        .parent()
        .filter(|dir| !dir.as_os_str().is_empty())
        .unwrap_or(control.checkpoint);
    let tally = train::TrainingTally {
        steps: state.session.steps,
        samples: state.session.samples,
    };
    train::check_trained(out, trainer, tally)
}

/// Save the stream (with the source's arrival names) and report it, once [`check_model`]
/// lets it.
fn checkpoint<S: FrameSource + ?Sized>(
    control: &Control<'_>,
    trainer: &Trainer<'_>,
    source: &S,
    state: &mut StreamState,
    on_event: &mut dyn FnMut(&Event<'_>),
) -> Result<()> {
    check_model(control, trainer, state)?;
    state.arrived = source.arrived().to_vec();
    save(control.checkpoint, trainer, state)?;
    on_event(&Event::Checkpoint(control.checkpoint));
    Ok(())
}

/// The core's checks of a frame (camera, pose, sizes) and of its exposure, as a host error
/// naming the frame.
fn check(trainer: &Trainer<'_>, frame: &Frame) -> Result<()> {
    trainer
        .frames()
        .check(
            &frame.camera,
            &frame.pose,
            &frame.pixels,
            frame.mask.as_deref(),
        )
        .and_then(|()| orbit_nerf_core::replacement::check_exposure(&frame.pixels))
        .map_err(|e| core_error(&frame.name, e))
}

/// Hold a usable frame out, or offer it to the store.
fn ingest(
    trainer: &mut Trainer<'_>,
    state: &mut StreamState,
    position: u64,
    frame: &Frame,
) -> Result<Fate> {
    state.usable += 1;
    if state
        .usable
        .is_multiple_of(state.settings.holdout_every.max(1))
    {
        state.held_out.push(position);
        return Ok(Fate::HeldOut);
    }
    let arrival = state.offered;
    state.offered += 1;
    let ingested = trainer
        .ingest_frame(
            arrival,
            frame.camera,
            frame.pose,
            &frame.pixels,
            frame.mask.as_deref(),
        )
        .map_err(|e| core_error(&frame.name, e))?;
    Ok(match ingested {
        Ingested::Stored { slot } => {
            state.stored += 1;
            if let Some(held) = state.slot_positions.get_mut(slot) {
                *held = Some(position);
            }
            Fate::Stored { slot }
        }
        Ingested::Rejected => {
            state.rejected += 1;
            Fate::Rejected
        }
    })
}

/// Mean held-out quality of the current model on the frames at `positions`, read again from
/// the source one at a time (so the memory it takes does not grow with the stream), each at
/// its exact pose where the source knows it (else at its label); views that no longer read are
/// left out. Returns the mean (NaN without views) and each view scored:
/// its source position and whole-image PSNR.
pub fn held_out_quality<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &S,
    positions: &[u64],
    fit_steps: u32,
) -> Result<(ViewMetrics, Vec<(u64, f64)>)> {
    let info = source.info();
    let mut per_view = Vec::with_capacity(positions.len());
    let mut scored = Vec::with_capacity(positions.len());
    for &position in positions {
        let Ok(frame) = source.reload(position) else {
            continue;
        };
        let view = Dataset {
            source: info.name.clone().into(),
            frames: vec![frame],
            scene_min: trainer.config().aabb_min,
            scene_max: trainer.config().aabb_max,
            scene_box: SceneBoxOrigin::Stated("the stream's config".into()),
            background: info.background,
            target_centred: false,
        };
        let exact = source.exact_pose(position)?;
        let scores = train::evaluate_at(
            trainer,
            executor,
            &view,
            &[0],
            exact.as_ref().map(std::slice::from_ref),
            (fit_steps, false),
            None,
        )?;
        per_view.extend(scores.iter().map(|s| s.metrics));
        scored.extend(scores.iter().map(|s| (position, s.metrics.psnr_full)));
    }
    Ok((report::mean_metrics(&per_view), scored))
}

/// [`held_out_quality`] on the stream's held-out views so far, with its fit steps.
fn held_out_views_quality<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &S,
    state: &StreamState,
) -> Result<(ViewMetrics, Vec<(u64, f64)>)> {
    held_out_quality(
        trainer,
        executor,
        source,
        &state.held_out,
        state.settings.fit_steps,
    )
}

fn anytime_point<E: Executor, S: FrameSource + ?Sized>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    source: &S,
    state: &StreamState,
    seconds_per_frame: f64,
) -> Result<AnytimePoint> {
    let (metrics, views) = held_out_views_quality(trainer, executor, source, state)?;
    Ok(AnytimePoint {
        frames_seen: state.position,
        frames_held: trainer.frames().len(),
        held_out_views: views.len(),
        steps: trainer.state().step,
        psnr: metrics.psnr_full,
        ssim: metrics.ssim_full,
        psnr_right: metrics.psnr_right,
        ssim_right: metrics.ssim_right,
        psnr_foreground: metrics.psnr_foreground,
        seconds_per_frame,
        seconds: state.seconds,
        rss_mib: resident_mib(),
    })
}

/// The trainer's sections a snapshot keeps: all that rendering and fitting a held-out view's
/// embedding read (the slots' metadata and parameters give the mean starting embedding).
const SNAPSHOT_SECTIONS: [&str; 6] = [
    "state",
    "planes",
    "mlp",
    "occupancy_bits",
    "frame_meta",
    "frame_params",
];

/// Where the snapshot of anytime point `index` of the stream checkpointed at `checkpoint` is.
pub fn snapshot_path(checkpoint: &Path, index: usize) -> std::path::PathBuf {
    checkpoint
        .with_extension("snapshots")
        .join(format!("point_{index:03}.onrf"))
}

/// Save the model as anytime point `index` sees it (written atomically; a resumed stream
/// writes the same bytes again for a point it repeats).
fn save_snapshot(checkpoint_path: &Path, index: usize, trainer: &Trainer<'_>) -> Result<()> {
    let path = snapshot_path(checkpoint_path, index);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| HostError::io(dir, e))?;
    }
    let config = postcard::to_allocvec(trainer.config())
        .map_err(|e| HostError::invalid(&path, format!("config encoding failed: {e}")))?;
    let sections: Vec<(&str, &[u8])> = (trainer.sections().into_iter())
        .filter(|(name, _)| SNAPSHOT_SECTIONS.contains(name))
        .collect();
    checkpoint::save_parts(&path, train::CHECKPOINT_KIND, &config, &sections)
}

/// A point of the curve on the fixed set: every held-out view of the stream, scored with the
/// model as the stream's point `index` saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct FixedSetPoint {
    /// Means over the views (`report::mean_metrics`).
    pub metrics: ViewMetrics,
    /// Views scored (all the stream's held-out views that still read).
    pub views: usize,
    /// Each view's source position and whole-image PSNR.
    pub per_view: Vec<(u64, f64)>,
}

/// How a held-out view's score moved from the first anytime point after it arrived to the
/// last: what the stream forgot of (or learned since about) that view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewForgetting {
    /// The view's source position.
    pub position: u64,
    /// Frames seen at the first point after it arrived.
    pub first_frames_seen: u64,
    /// Its whole-image PSNR there, dB.
    pub first_psnr: f64,
    /// Its whole-image PSNR at the last point, dB.
    pub last_psnr: f64,
}

/// [`ViewForgetting`] of every held-out view scored on the fixed set (`fixed` holds a point
/// per point of `curve`) before the last point, in source order (a view first scored at the
/// last point has had no time to be forgotten).
pub fn forgetting(curve: &[AnytimePoint], fixed: &[FixedSetPoint]) -> Vec<ViewForgetting> {
    let Some((last, earlier)) = fixed.split_last() else {
        return Vec::new();
    };
    last.per_view
        .iter()
        .filter_map(|&(position, last_psnr)| {
            let (point, fixed) = curve
                .iter()
                .zip(earlier)
                .find(|(p, _)| p.frames_seen > position)?;
            let &(_, first_psnr) = fixed.per_view.iter().find(|(p, _)| *p == position)?;
            Some(ViewForgetting {
                position,
                first_frames_seen: point.frames_seen,
                first_psnr,
                last_psnr,
            })
        })
        .collect()
}

/// Score every anytime point's snapshot on all the stream's held-out views (read again from
/// the source), one point after another in one extra arena of the stream's config (checked
/// against `memory_limit` before it is allocated).
pub fn fixed_set_curve<E: Executor, S: FrameSource + ?Sized>(
    checkpoint_path: &Path,
    source: &S,
    state: &StreamState,
    config: &Config,
    executor: &E,
    memory_limit: Option<u64>,
    on_point: &mut dyn FnMut(usize),
) -> Result<Vec<FixedSetPoint>> {
    let plan = MemoryPlan::new(config);
    crate::memory::check_arena(
        Path::new("the model scoring the stream's snapshots"),
        &plan,
        crate::memory::limit_or_default(memory_limit),
    )?;
    let mut arena = vec![0u8; plan.total];
    let mut points = Vec::with_capacity(state.curve.len());
    for index in 0..state.curve.len() {
        let path = snapshot_path(checkpoint_path, index);
        // A snapshot from before the settle holds the schedule the settle planned anew.
        let snapshot_config = crate::pipeline::checkpoint_config(&path)?;
        if !same_model(&snapshot_config, config) {
            return Err(HostError::invalid(
                &path,
                "written by a stream with another config",
            ));
        }
        arena.fill(0);
        let mut trainer =
            Trainer::new(snapshot_config, &mut arena).map_err(|e| core_error(&path, e))?;
        train::restore_sections(&path, &mut trainer, &[], &SNAPSHOT_SECTIONS)?;
        let (metrics, per_view) = held_out_views_quality(&mut trainer, executor, source, state)?;
        points.push(FixedSetPoint {
            metrics,
            views: per_view.len(),
            per_view,
        });
        on_point(index);
    }
    Ok(points)
}

/// Whether two configs describe the same model and training but for the learning-rate
/// schedule, which a stream plans anew when its settle begins ([`settle_schedule`]).
fn same_model(a: &Config, b: &Config) -> bool {
    let unscheduled = |c: &Config| Config {
        steps: 1,
        lr_decay_start: 0.0,
        ..*c
    };
    unscheduled(a) == unscheduled(b)
}

/// Name of the checkpoint section holding the [`StreamState`].
pub const STREAM_SECTION: &str = "stream";

/// Write the trainer's state and the stream's state to `path` atomically.
pub fn save(path: &Path, trainer: &Trainer<'_>, state: &StreamState) -> Result<()> {
    let bytes = postcard::to_allocvec(state)
        .map_err(|e| HostError::invalid(path, format!("cannot encode the stream state: {e}")))?;
    train::save_checkpoint(path, trainer, &[(STREAM_SECTION, &bytes)])
}

/// A stream checkpoint's config and the stream's state, read without the model (restore it
/// with [`restore`]).
pub fn load(path: &Path) -> Result<(Config, StreamState)> {
    let mut reader = checkpoint::SectionReader::open(path)?;
    let config = train::decode_config(path, &reader.kind, &reader.config)?;
    let missing = || HostError::field(path, STREAM_SECTION, "missing: not a stream checkpoint");
    let bytes = loop {
        match reader.next_section()? {
            Some((name, _)) if name == STREAM_SECTION => break reader.read_section_vec()?,
            Some(_) => continue,
            None => return Err(missing()),
        }
    };
    let state: StreamState = postcard::from_bytes(&bytes)
        .map_err(|e| HostError::field(path, STREAM_SECTION, format!("cannot decode: {e}")))?;
    if state.slot_positions.len() != config.max_frames as usize {
        return Err(HostError::field(
            path,
            STREAM_SECTION,
            "slot count differs from the config's max_frames",
        ));
    }
    Ok((config, state))
}

/// Restore the model of the stream checkpoint `path` into `trainer` (built from its config),
/// section by section.
pub fn restore(path: &Path, trainer: &mut Trainer<'_>) -> Result<()> {
    train::restore_checkpoint(path, trainer, &[STREAM_SECTION]).map(drop)
}

/// Read the stream checkpoint at `path` (config and state; the model is restored with
/// [`restore`]) and position `source` to continue it. Refused when the
/// checkpoint was written by a stream from another source.
pub fn resume<S: FrameSource + ?Sized>(
    path: &Path,
    source: &mut S,
) -> Result<(Config, StreamState)> {
    let (config, state) = load(path)?;
    let identity = &source.info().identity;
    if state.source != *identity {
        return Err(HostError::field(
            path,
            STREAM_SECTION,
            format!(
                "written by a stream from {}, not from {identity}; resume with the same source",
                state.source
            ),
        ));
    }
    source.seek(state.position, &state.arrived)?;
    Ok((config, state))
}

/// A point of the offline reference's curve: its quality on the stream's held-out views
/// after `steps` steps, and the wall time its training had taken by then.
#[derive(Clone, Debug, PartialEq)]
pub struct OfflinePoint {
    /// Training steps taken.
    pub steps: u32,
    /// Training wall time up to `steps` (not the scoring).
    pub seconds: f64,
    /// Means over the stream's held-out views.
    pub metrics: ViewMetrics,
    /// Each view's source position and whole-image PSNR.
    pub per_view: Vec<(u64, f64)>,
}

/// The anytime curve as CSV: each point's seen-so-far scores, then (when given, else empty
/// cells) its scores on the fixed set of all held-out views and the offline reference's at
/// the same step count.
pub fn curve_csv(
    curve: &[AnytimePoint],
    fixed: Option<&[FixedSetPoint]>,
    offline: Option<&[OfflinePoint]>,
) -> String {
    let mut csv = String::from(
        "frames_seen,frames_held,held_out_views,steps,psnr,ssim,psnr_right,ssim_right,psnr_foreground,seconds_per_frame,seconds,rss_mib,\
         fixed_views,fixed_psnr,fixed_ssim,fixed_psnr_right,fixed_psnr_foreground,\
         offline_seconds,offline_psnr,offline_ssim,offline_psnr_right,offline_psnr_foreground\n",
    );
    for (i, p) in curve.iter().enumerate() {
        let _ = write!(
            csv,
            "{},{},{},{},{:.4},{:.5},{:.4},{:.5},{:.4},{:.5},{:.3},{:.2}",
            p.frames_seen,
            p.frames_held,
            p.held_out_views,
            p.steps,
            p.psnr,
            p.ssim,
            p.psnr_right,
            p.ssim_right,
            p.psnr_foreground,
            p.seconds_per_frame,
            p.seconds,
            p.rss_mib
        );
        let cells = |first: String, m: &ViewMetrics| {
            format!(
                ",{first},{:.4},{:.5},{:.4},{:.4}",
                m.psnr_full, m.ssim_full, m.psnr_right, m.psnr_foreground
            )
        };
        let empty = ",,,,,".to_string();
        csv.push_str(&match fixed.and_then(|f| f.get(i)) {
            Some(f) => cells(f.views.to_string(), &f.metrics),
            None => empty.clone(),
        });
        csv.push_str(
            &match offline.and_then(|o| o.iter().find(|o| o.steps == p.steps)) {
                Some(o) => cells(format!("{:.3}", o.seconds), &o.metrics),
                None => empty,
            },
        );
        csv.push('\n');
    }
    csv
}

/// Write `anytime.csv`, `anytime.png` (held-out PSNR against frames seen) and
/// `anytime_time.png` (against wall time) into `dir`, atomically. The plots show the
/// seen-so-far scores, and the fixed set's and the offline reference's when given (the
/// offline reference placed at the frames the stream had seen after as many steps).
pub fn write_curve(
    dir: &Path,
    curve: &[AnytimePoint],
    fixed: Option<&[FixedSetPoint]>,
    offline: Option<&[OfflinePoint]>,
) -> Result<()> {
    crate::io::write_atomic(
        &dir.join("anytime.csv"),
        curve_csv(curve, fixed, offline).as_bytes(),
    )?;
    let fixed_points = |x: fn(&AnytimePoint) -> f64| -> Vec<(f64, f64)> {
        curve
            .iter()
            .zip(fixed.unwrap_or(&[]))
            .map(|(p, f)| (x(p), f.metrics.psnr_full))
            .collect()
    };
    let offline_points = |x: fn(&AnytimePoint, &OfflinePoint) -> f64| -> Vec<(f64, f64)> {
        curve
            .iter()
            .filter_map(|p| {
                let o = offline?.iter().find(|o| o.steps == p.steps)?;
                Some((x(p, o), o.metrics.psnr_full))
            })
            .collect()
    };
    let seen_so_far: Vec<(f64, f64)> = curve
        .iter()
        .map(|p| (p.frames_seen as f64, p.psnr))
        .collect();
    let mut by_frames = vec![("seen so far", seen_so_far)];
    let mut by_time = Vec::new();
    if fixed.is_some() {
        by_frames.push(("all held-out views", fixed_points(|p| p.frames_seen as f64)));
        by_time.push(("stream, all held-out views", fixed_points(|p| p.seconds)));
    }
    if offline.is_some() {
        by_frames.push((
            "offline, same steps",
            offline_points(|p, _| p.frames_seen as f64),
        ));
        by_time.push(("offline, same steps", offline_points(|_, o| o.seconds)));
    }
    report::line_plot(
        &dir.join("anytime.png"),
        "Anytime quality of a stream",
        "frames seen",
        "held-out PSNR, whole image (dB)",
        &by_frames,
    )?;
    if by_time.is_empty() {
        by_time.push((
            "seen so far",
            curve.iter().map(|p| (p.seconds, p.psnr)).collect(),
        ));
    }
    report::line_plot(
        &dir.join("anytime_time.png"),
        "Anytime quality of a stream",
        "training wall time (s)",
        "held-out PSNR, whole image (dB)",
        &by_time,
    )
}

/// What an offline reference trains on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OfflineFrames {
    /// Every usable, not-held-out frame of the stream, whole, at once: what the stream would
    /// learn with unlimited memory and its steps.
    AllWhole,
    /// What the stream's store holds at its end (the same frames offered in the same order to
    /// a store of the stream's config, which keeps what the stream's kept): what the stream
    /// would learn from its own memory with its steps spent after the last frame.
    StreamStore,
}

/// An offline reference of a finished stream: a fresh model trained on `frames` for the same
/// number of steps, scored on the same held-out views after each of `at_steps` steps (and
/// after the last). [`OfflineFrames::AllWhole`] reads every training frame into memory (it is
/// the comparison, not the stream).
pub fn offline_reference<E: Executor, S: FrameSource + ?Sized>(
    source: &S,
    state: &StreamState,
    (stream_config, frames): (&Config, OfflineFrames),
    steps: u32,
    at_steps: &[u32],
    executor: &E,
    on_step: &mut dyn FnMut(u32),
) -> Result<Vec<OfflinePoint>> {
    let skipped: Vec<u64> = state
        .bad
        .iter()
        .map(|b| b.position)
        .chain(state.held_out.iter().copied())
        .collect();
    let positions: Vec<u64> = (0..state.position)
        .filter(|p| !skipped.contains(p))
        .collect();
    let mut config = *stream_config;
    if frames == OfflineFrames::AllWhole {
        config.max_frames = positions.len().clamp(1, u16::MAX as usize) as u16;
        config.ray_store = 0;
    }
    config.steps = steps.max(1);
    config.warmup_steps = config.warmup_steps.min(config.steps);
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer =
        Trainer::new(config, &mut arena).map_err(|e| core_error(&source.info().name, e))?;
    match frames {
        OfflineFrames::AllWhole => {
            let frames = (positions.iter())
                .map(|&p| source.reload(p))
                .collect::<Result<Vec<_>>>()?;
            train::load_frames(&mut trainer, &frames)?;
        }
        OfflineFrames::StreamStore => {
            for (arrival, &position) in positions.iter().enumerate() {
                let frame = source.reload(position)?;
                let (pixels, mask) = (&frame.pixels, frame.mask.as_deref());
                trainer
                    .ingest_frame(arrival as u32, frame.camera, frame.pose, pixels, mask)
                    .map_err(|e| core_error(&frame.name, e))?;
            }
        }
    }
    let mut points = Vec::new();
    let mut seconds = 0.0f64;
    for step in 0..config.steps {
        let started = Instant::now();
        trainer
            .step(executor)
            .map_err(|e| core_error(&source.info().name, e))?;
        seconds += started.elapsed().as_secs_f64();
        on_step(step);
        let done = step + 1;
        if at_steps.contains(&done) || done == config.steps {
            let (metrics, per_view) =
                held_out_views_quality(&mut trainer, executor, source, state)?;
            points.push(OfflinePoint {
                steps: done,
                seconds,
                metrics,
                per_view,
            });
        }
    }
    Ok(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ray reservoir takes the bytes of the store of whole frames it replaces, as plain
    /// training carves that store (no loss-weighting buffers, no running loss per slot): never
    /// more, and all but the last entry's worth and the running losses' bytes. Remembering more
    /// frames leaves fewer pixels; by default a source that says its frame count is remembered
    /// whole, unless that leaves the reservoir less than half the frames' pixel bytes.
    #[test]
    fn a_ray_reservoir_takes_the_bytes_of_the_whole_frames_it_replaces() {
        let spacecraft = crate::presets::config_of(Path::new("test"), "preset", "spacecraft");
        let base = Config {
            loss_weighted_frames: true,
            ..spacecraft.unwrap()
        };
        for (side, frames, store) in [(64usize, 120u64, 40u16), (240, 120, 40), (128, 5000, 8)] {
            let info = SourceInfo {
                name: "test".into(),
                identity: "test".into(),
                scene_box: Some(([-1.0; 3], [1.0; 3])),
                background: [0.0; 3],
                max_pixels: side * side,
                frames: Some(frames),
                exact_poses: false,
            };
            let whole = stream_config(
                &Config {
                    loss_weighted_frames: false,
                    ..base
                },
                &info,
                (store, Keep::Frames),
                Replacement::Fifo,
                (17, 0),
            )
            .unwrap();
            let rays = stream_config(
                &base,
                &info,
                (store, Keep::Rays { remember: None }),
                Replacement::Fifo,
                (17, 0),
            )
            .unwrap();
            let (whole_bytes, ray_bytes) =
                (MemoryPlan::new(&whole).total, MemoryPlan::new(&rays).total);
            assert!(
                ray_bytes <= whole_bytes,
                "{side} px: {ray_bytes} > {whole_bytes}"
            );
            let slack = 64 + orbit_nerf_core::RAY_ENTRY_BYTES + 4 * store as usize;
            assert!(
                whole_bytes - ray_bytes <= slack,
                "{side} px: {whole_bytes} - {ray_bytes}"
            );
            assert!(rays.loss_weighted_frames && rays.ray_store > 0);
            let pixel_bytes = rays.ray_store as usize * orbit_nerf_core::RAY_ENTRY_BYTES;
            assert!(2 * pixel_bytes >= whole.frame_pixel_bytes().0, "{side} px");
            if frames <= 1024 {
                assert_eq!(rays.max_frames as u64, frames, "{side} px");
            } else {
                assert!(
                    (store..1024).contains(&rays.max_frames),
                    "{}",
                    rays.max_frames
                );
            }
            let fewer = stream_config(
                &base,
                &info,
                (
                    store,
                    Keep::Rays {
                        remember: Some(store),
                    },
                ),
                Replacement::Fifo,
                (17, 0),
            )
            .unwrap();
            assert!(fewer.ray_store > rays.ray_store || rays.max_frames == store);
        }
        // Two frames of 24 x 24 px cannot pay for the loss weighting's buffers: whole frames,
        // unless a number of frames to remember was asked for.
        let info = SourceInfo {
            name: "tiny".into(),
            identity: "tiny".into(),
            scene_box: Some(([-1.0; 3], [1.0; 3])),
            background: [0.0; 3],
            max_pixels: 24 * 24,
            frames: Some(4),
            exact_poses: false,
        };
        let rays = |remember| {
            stream_config(
                &base,
                &info,
                (2, Keep::Rays { remember }),
                Replacement::Fifo,
                (1, 0),
            )
        };
        let whole = rays(None).unwrap();
        assert_eq!((whole.ray_store, whole.max_frames), (0, 2));
        let refused = rays(Some(2)).unwrap_err().to_string();
        assert!(refused.contains("--keep frames"), "{refused}");
    }

    /// The settle plans the schedule of a stream that took the steps it expected exactly as
    /// the stream was planned (the same bits), and one that took fewer or an open number
    /// (real time, a watched folder) anew, decaying from where the frames ended.
    #[test]
    fn the_settle_keeps_a_schedule_that_was_right_and_plans_one_that_was_not() {
        let tiny = crate::presets::config_of(Path::new("test"), "preset", "tiny").unwrap();
        let (arrivals, settle) = (1080u32, 1080u32);
        let planned = Config {
            steps: arrivals + settle,
            lr_decay_start: session::settle_decay_start(&tiny, arrivals as u64, settle),
            ..tiny
        };
        let mut arena = vec![0u8; MemoryPlan::new(&planned).total];
        let mut trainer = Trainer::new(planned, &mut arena).unwrap();
        settle_schedule(&mut trainer, arrivals, settle).unwrap();
        assert_eq!(*trainer.config(), planned);
        assert_eq!(
            trainer.config().lr_decay_start.to_bits(),
            planned.lr_decay_start.to_bits()
        );

        let open = Config {
            steps: u32::MAX,
            ..planned
        };
        let mut arena = vec![0u8; MemoryPlan::new(&open).total];
        let mut trainer = Trainer::new(open, &mut arena).unwrap();
        settle_schedule(&mut trainer, 490, 490).unwrap();
        let replanned = *trainer.config();
        assert_eq!(replanned.steps, 980);
        assert_eq!(
            replanned.lr_decay_start,
            session::settle_decay_start(&replanned, 490, 490)
        );
        assert!(same_model(&replanned, &open) && same_model(&replanned, &planned));
        assert!(!same_model(&replanned, &Config { seed: 7, ..open }));
    }
}
