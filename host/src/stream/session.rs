//! A whole stream in one call, for the CLI and for any program that brings its own frames (a
//! flight computer's camera, a ground station's downlink): [`StreamRequest::run`] chooses the
//! model config and the scene box, checks the memory, creates the trainer (or restores the
//! stream saved in the output folder), runs the stream ([`super::run`]) and, once the source
//! ends, scores the anytime points on all held-out views, trains the offline reference when
//! asked and writes the curve, `summary.md` and `metrics.json`. It prints nothing: what a
//! caller shows, it learns from a [`StreamObserver`].

use super::{
    Control, Event, FixedSetPoint, FrameSource, Keep, OfflineFrames, OfflinePoint, Outcome,
    StreamSettings, StreamState, fixed_set_curve, offline_reference, stream_config, write_curve,
};
use crate::error::Result;
use crate::pipeline::{self, CHECKPOINT_FILE, ChosenConfig};
use crate::report::{Figures, ModelFigures, TrainingFigures};
use crate::scene_box::box_text;
use crate::train::{self, RayonExecutor};
use crate::{io, presets};
use orbit_nerf_core::{Config, MemoryPlan, Replacement, Trainer};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

/// Where a stream's frames come from, as far as choosing its preset goes (a preset named in
/// [`ModelChoice::preset`] wins).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SourceKind {
    /// A dataset folder: the preset for its format, told from the folder's layout.
    DatasetFolder(PathBuf),
    /// The simulator: the `spacecraft` preset.
    Simulator,
    /// A watched folder of SPEED+ frames, or any feed of spacecraft images: the `spacecraft`
    /// preset.
    WatchedFolder,
}

/// The fraction of a stream's schedule (after warm-up) at the peak learning rate before the
/// cosine decay starts, unless the config file sets `lr_decay_start` or the stream settles
/// (then the decay starts after the last arrival: [`settle_decay_start`]).
pub const STREAM_LR_DECAY_START: f32 = 0.75;

/// `lr_decay_start` of a schedule of `arrivals` steps while frames arrive and `settle` steps
/// after them: the peak learning rate until the last arrival, the cosine decay over the settle.
pub fn settle_decay_start(config: &Config, arrivals: u64, settle: u32) -> f32 {
    let warmup = config.warmup_steps as u64;
    let peak = arrivals.saturating_sub(warmup) as f64;
    let span = (arrivals + settle as u64).saturating_sub(warmup).max(1) as f64;
    // `lr_decay_start` lies in [0, 1); an f32 just below 1 still decays in the last step.
    ((peak / span) as f32).clamp(0.0, 0.999_999)
}

/// The model a fresh stream trains (a resumed stream keeps its checkpoint's).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ModelChoice {
    /// Built-in config to start from; `None`: the one for the source's [`SourceKind`].
    pub preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config; a scene box it sets
    /// counts as stated.
    pub config_file: Option<PathBuf>,
    /// Random seed of the model (over the config's).
    pub seed: Option<u64>,
}

impl ModelChoice {
    /// The config of a fresh stream from a source of `kind`: the preset, the config file's
    /// fields on top, then the seed; with a note saying which preset and why. `schedule`: the
    /// steps while frames arrive (when the source says how many it has) and of the settle.
    /// The second value says whether the learning rate follows the stream's own schedule
    /// (the config file does not set `lr_decay_start`).
    fn choose(
        &self,
        kind: &SourceKind,
        schedule: (Option<u64>, u32),
    ) -> Result<(ChosenConfig, bool)> {
        let (preset, file) = (self.preset.as_deref(), self.config_file.as_deref());
        let mut chosen = match kind {
            SourceKind::DatasetFolder(dir) => pipeline::choose_config(preset, dir, file)?,
            SourceKind::Simulator => {
                pipeline::preset_config(preset, presets::SPACECRAFT, "a simulated scene", file)?
            }
            SourceKind::WatchedFolder => pipeline::preset_config(
                preset,
                presets::SPACECRAFT,
                "a watched folder of SPEED+ frames",
                file,
            )?,
        };
        if let Some(seed) = self.seed {
            chosen.config.seed = seed;
        }
        // A stream's own schedule, unless the config file says otherwise: rays drawn from
        // frames in proportion to their running loss (new views get the steps), and the peak
        // learning rate held for most of the stream (until the last arrival when it settles)
        // rather than decayed before the last frames arrive.
        let sets = |key: &str| file.map_or(Ok(false), |path| train::config_file_sets(path, key));
        let mut own = Vec::new();
        if !sets("loss_weighted_frames")? {
            chosen.config.loss_weighted_frames = true;
            own.push("loss_weighted_frames = true".to_string());
        }
        let own_schedule = !sets("lr_decay_start")?;
        if own_schedule {
            chosen.config.lr_decay_start = match schedule {
                (Some(arrivals), settle) if settle > 0 => {
                    settle_decay_start(&chosen.config, arrivals, settle)
                }
                _ => STREAM_LR_DECAY_START,
            };
            own.push(format!("lr_decay_start = {}", chosen.config.lr_decay_start));
        }
        if !own.is_empty() {
            let _ = write!(chosen.note, "; the stream's schedule: {}", own.join(", "));
        }
        Ok((chosen, own_schedule))
    }
}

/// Everything about a stream but its frames: how it trains, stops, ends and reports, and
/// where it writes (see [`StreamRequest::run`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StreamRequest {
    /// Output folder: `checkpoint.onrf` (the anytime points' model snapshots beside it, in
    /// `checkpoint.snapshots/`), `anytime.csv`, `anytime.png`, `anytime_time.png`,
    /// `summary.md`, `metrics.json`.
    pub out: PathBuf,
    /// The core's store takes the bytes of this many whole frames (a fresh stream's).
    pub store: u16,
    /// What the store keeps in them (a fresh stream's).
    pub keep: Keep,
    /// Replacement policy of a full store (a fresh stream's).
    pub replacement: Replacement,
    /// How the stream trains and reports (a fresh stream's; a resumed one keeps its own).
    pub settings: StreamSettings,
    /// The model of a fresh stream.
    pub model: ModelChoice,
    /// The scene box, min and max corners, stated by the caller: wins over a config file's
    /// box and the source's.
    pub scene_box: Option<([f32; 3], [f32; 3])>,
    /// Stop (and checkpoint) once the trainer has taken this many steps in all, as the stop
    /// flag would, possibly within a frame's steps; running the request again with `resume`
    /// continues to the bytes of a stream never stopped.
    pub stop_after: Option<u32>,
    /// End the stream after this many arrivals, as if the source ended.
    pub end_after: Option<u64>,
    /// Once the stream ends, train a model on all its training frames at once with the same
    /// number of steps and score it on the same held-out views.
    pub compare_offline: bool,
    /// Largest memory a model's arena may take; `None`: 80 % of the machine's available
    /// memory. Checked before anything is allocated.
    pub memory_limit: Option<u64>,
    /// Worker threads (results do not depend on it).
    pub threads: usize,
    /// Continue the stream saved in the output folder (same source; its config and settings
    /// are used).
    pub resume: bool,
    /// Start a fresh stream even though the output folder holds an earlier stream's
    /// checkpoint, replacing it.
    pub replace: bool,
}

/// What a running stream tells its caller; every method does nothing unless implemented.
pub trait StreamObserver {
    /// A line saying what was chosen or found and why: the preset, the scene box, the
    /// checkpoint resumed, what is streamed into what store, the arena's size.
    fn note(&mut self, _note: &str) {}

    /// The stream begins at arrival `position` (past those a resumed stream had consumed), of
    /// `arrivals` in all when the source or [`StreamRequest::end_after`] says.
    fn start(&mut self, _position: u64, _arrivals: Option<u64>) {}

    /// A frame taken, a bad frame, an anytime point or a checkpoint.
    fn event(&mut self, _event: &Event<'_>) {}

    /// The work after the stream's last frame: `done` of `total` units of `stage` (`done` is 0
    /// as the stage begins).
    fn progress(&mut self, _stage: Stage, _done: u64, _total: u64) {}
}

/// The stages of a finished stream's work after its last frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Scoring every anytime point's snapshot on all held-out views; a unit is a point.
    FixedSet,
    /// Training the offline references (the one on all frames scored on the way, then the one
    /// on the stream's final store); a unit is a step.
    OfflineReference,
}

/// How a [`StreamRequest::run`] ended.
#[derive(Clone, Debug, PartialEq)]
pub enum StreamEnd {
    /// Stopped by the stop flag or [`StreamRequest::stop_after`]: the checkpoint and the curve
    /// so far are written; the request run again with `resume` continues the stream.
    Stopped {
        /// Arrivals consumed.
        position: u64,
        /// Training steps taken, across resumes.
        step: u32,
    },
    /// The source ended (or [`StreamRequest::end_after`] came): everything is scored and
    /// written.
    Finished(Box<FinishedStream>),
}

/// A finished stream's results, as written to its output folder.
#[derive(Clone, Debug, PartialEq)]
pub struct FinishedStream {
    /// The stream's record: counts, held-out and bad frames, the anytime curve.
    pub state: StreamState,
    /// The anytime curve on all the stream's held-out views, a point per curve point.
    pub fixed_set: Vec<FixedSetPoint>,
    /// The offline reference, when asked for.
    pub offline: Option<OfflineReference>,
    /// The text of `summary.md`.
    pub summary: String,
}

/// The offline reference of a finished stream ([`StreamRequest::compare_offline`]).
#[derive(Clone, Debug, PartialEq)]
pub struct OfflineReference {
    /// Its scores at the step counts of the stream's anytime points and at its last step.
    pub points: Vec<OfflinePoint>,
    /// Wall time of its training and scoring.
    pub seconds: f64,
    /// The reference trained on what the stream's store holds at its end
    /// ([`OfflineFrames::StreamStore`]), scored after its last step.
    pub store: Option<OfflinePoint>,
}

impl StreamRequest {
    /// Where the stream's checkpoint is (in the output folder).
    pub fn checkpoint_path(&self) -> PathBuf {
        self.out.join(CHECKPOINT_FILE)
    }

    /// Stream from `source` (a source of `kind`) until it ends, `stop` is raised (by a signal
    /// handler, say: heard within a training step) or [`StreamRequest::stop_after`] steps are
    /// taken, telling `observer` as it goes. A fresh stream refuses to replace an earlier
    /// stream's checkpoint unless [`StreamRequest::replace`]; a resumed one continues the
    /// checkpoint in the output folder, which must be from the same source.
    ///
    /// The scene box is the rule of `scene_box::choose_scene_box` less finding one from the
    /// frames (a stream sees one frame at a time): [`StreamRequest::scene_box`], else the
    /// config file's, else the source's. The model's arena is checked against the memory
    /// limit before it is allocated. A stopped stream writes its checkpoint and its curve so
    /// far; a finished one scores its snapshots on all held-out views, trains the offline
    /// reference when asked, and writes the curve, `summary.md` and `metrics.json`, each
    /// atomically.
    pub fn run(
        &self,
        kind: &SourceKind,
        source: &mut dyn FrameSource,
        stop: &AtomicBool,
        observer: &mut dyn StreamObserver,
    ) -> Result<StreamEnd> {
        let checkpoint_path = self.checkpoint_path();
        let (config, mut state) = if self.resume {
            super::resume(&checkpoint_path, source)?
        } else {
            self.fresh(kind, source, &checkpoint_path, observer)?
        };
        let executor = RayonExecutor::new(self.threads)?;
        let what = PathBuf::from(format!("the model for {}", source.info().name));
        pipeline::with_trainer(&what, (config, self.memory_limit), &[], &[], |trainer| {
            if self.resume {
                super::restore(&checkpoint_path, trainer)?;
                observer.note(&format!(
                    "resuming {} at arrival {} ({} steps done)",
                    checkpoint_path.display(),
                    state.position,
                    trainer.state().step
                ));
            }
            observer.note(&format!(
                "streaming {} into {} ({:?} replacement), {} steps per frame, {} thread{}; arena {:.1} MiB",
                source.info().name,
                store_text(&config),
                config.replacement,
                state.settings.steps_per_frame,
                self.threads,
                if self.threads == 1 { "" } else { "s" },
                MemoryPlan::new(&config).total as f64 / (1 << 20) as f64
            ));
            observer.start(state.position, source.info().frames.or(self.end_after));
            let start = Instant::now();
            let control = Control {
                stop,
                stop_after: self.stop_after,
                end_after: self.end_after,
                checkpoint: &checkpoint_path,
            };
            let outcome = super::run(
                trainer,
                &executor,
                source,
                &mut state,
                &control,
                &mut |event| observer.event(event),
            )?;
            let seconds = start.elapsed().as_secs_f64();
            if outcome == Outcome::Stopped {
                write_curve(&self.out, &state.curve, None, None)?;
                return Ok(StreamEnd::Stopped {
                    position: state.position,
                    step: trainer.state().step,
                });
            }
            let source = &*source;
            let total = state.curve.len() as u64;
            observer.progress(Stage::FixedSet, 0, total);
            let fixed_set = fixed_set_curve(
                &checkpoint_path,
                source,
                &state,
                &config,
                &executor,
                self.memory_limit,
                &mut |index| observer.progress(Stage::FixedSet, index as u64 + 1, total),
            )?;
            let offline = if self.compare_offline {
                let steps = trainer.state().step;
                let total = 2 * steps as u64;
                observer.progress(Stage::OfflineReference, 0, total);
                let started = Instant::now();
                let at_steps: Vec<u32> = state.curve.iter().map(|p| p.steps).collect();
                let points = offline_reference(
                    source,
                    &state,
                    (&config, OfflineFrames::AllWhole),
                    steps,
                    &at_steps,
                    &executor,
                    &mut |step| observer.progress(Stage::OfflineReference, step as u64 + 1, total),
                )?;
                let seconds = started.elapsed().as_secs_f64();
                let store = offline_reference(
                    source,
                    &state,
                    (&config, OfflineFrames::StreamStore),
                    steps,
                    &[],
                    &executor,
                    &mut |step| {
                        let done = steps as u64 + step as u64 + 1;
                        observer.progress(Stage::OfflineReference, done, total)
                    },
                )?
                .pop();
                Some(OfflineReference {
                    points,
                    seconds,
                    store,
                })
            } else {
                None
            };
            write_curve(
                &self.out,
                &state.curve,
                Some(&fixed_set),
                offline.as_ref().map(|o| o.points.as_slice()),
            )?;
            let scored_at = if source.info().exact_poses {
                "their exact poses"
            } else {
                "their labels"
            };
            let summary = summary(
                &state,
                (trainer, seconds),
                scored_at,
                &fixed_set,
                offline.as_ref(),
            );
            io::write_atomic(&self.out.join("summary.md"), summary.as_bytes())?;
            figures(&state, trainer, seconds, offline.as_ref()).write(&self.out)?;
            Ok(StreamEnd::Finished(Box::new(FinishedStream {
                state,
                fixed_set,
                offline,
                summary,
            })))
        })
    }

    /// A fresh stream's config and state: the model chosen for `kind`, with the scene box by
    /// the rule, fitted to the source (its frame size, and its frames or `end_after` for the
    /// schedule). Refuses to replace an earlier stream's checkpoint unless `replace`.
    fn fresh(
        &self,
        kind: &SourceKind,
        source: &dyn FrameSource,
        checkpoint_path: &Path,
        observer: &mut dyn StreamObserver,
    ) -> Result<(Config, StreamState)> {
        io::check_fresh_checkpoint(checkpoint_path, self.replace, "stream")?;
        let mut info = source.info().clone();
        info.frames = info.frames.or(self.end_after);
        let settings = &self.settings;
        let arrivals = (info.frames).map(|n| n.saturating_mul(settings.steps_per_frame as u64));
        // The settle a source of known length will get (by default as long as its arrivals).
        let arrival_steps = arrivals.map_or(0, |n| n.min(u32::MAX as u64) as u32);
        let settle = settings.settle(arrival_steps);
        let (chosen, own_schedule) = self.model.choose(kind, (arrivals, settle))?;
        observer.note(&chosen.note);
        let config_file = self.model.config_file.as_deref();
        if let Some(stated) = pipeline::stated_box(self.scene_box, config_file)? {
            info.scene_box = Some((stated.min, stated.max));
            observer.note(&format!(
                "scene box {}, given by {}",
                box_text(stated.min, stated.max),
                stated.by
            ));
        } else if let Some((min, max)) = info.scene_box {
            observer.note(&format!(
                "scene box {}, from the source (truth.json or the format)",
                box_text(min, max)
            ));
        }
        let mut config = stream_config(
            &chosen.config,
            &info,
            (self.store, self.keep),
            self.replacement,
            (settings.steps_per_frame, settle),
        )?;
        // A stream that cannot know the step its frames end at (a watched folder, real time)
        // holds the peak learning rate until they do; the settle plans its decay then.
        if own_schedule && (info.frames.is_none() || settings.budget_ms.is_some()) {
            config.steps = u32::MAX;
        }
        // The store takes the bytes of `store` whole frames, which must fit the memory limit
        // even where a ray reservoir (at most MAX_RAY_STORE pixels) would need fewer: so the
        // frame in hand, the host's, fits too.
        let whole = Config {
            ray_store: 0,
            max_frames: self.store,
            ..config
        };
        let what = PathBuf::from(format!("the store of the stream of {}", source.info().name));
        crate::memory::check_arena(
            &what,
            &MemoryPlan::new(&whole),
            crate::memory::limit_or_default(self.memory_limit),
        )?;
        let capacity = config.max_frames as usize;
        let mut state = StreamState::new(self.settings.clone(), capacity, source.info());
        state.decay_over_settle = own_schedule;
        Ok((config, state))
    }
}

/// What the store keeps, in words: `a store of N frames` or `a ray reservoir of N pixels
/// remembering up to K frames`.
pub fn store_text(config: &Config) -> String {
    if config.ray_store > 0 {
        format!(
            "a ray reservoir of {} pixels remembering up to {} frames",
            config.ray_store, config.max_frames
        )
    } else {
        format!("a store of {} frames", config.max_frames)
    }
}

/// The summary's models for `metrics.json`: the streamed model at its last held-out score,
/// and the offline reference when there is one (no per-view figures: a stream keeps means).
fn figures(
    state: &StreamState,
    trainer: &Trainer<'_>,
    seconds: f64,
    offline: Option<&OfflineReference>,
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
    if let Some(last) = offline.and_then(|o| o.points.last()) {
        models.push(ModelFigures {
            name: "offline reference".into(),
            mean: last.metrics,
            views: Vec::new(),
            training: None,
            mean_at: None,
            pose_refinement: None,
        });
    }
    if let Some(store) = offline.and_then(|o| o.store.as_ref()) {
        models.push(ModelFigures {
            name: "offline on the stream's final store".into(),
            mean: store.metrics,
            views: Vec::new(),
            training: None,
            mean_at: None,
            pose_refinement: None,
        });
    }
    Figures::new("stream", models)
}

/// The text of `summary.md`: the arrivals and what became of them, the steps and wall time,
/// the bad frames, the streamed model's last held-out score, the offline reference's, and the
/// resident memory once the store was full and at the end. `scored_at`: where the held-out
/// views were rendered.
fn summary(
    state: &StreamState,
    (trainer, seconds): (&Trainer<'_>, f64),
    scored_at: &str,
    fixed_set: &[FixedSetPoint],
    offline: Option<&OfflineReference>,
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
    if let Some(ms) = state.settings.budget_ms {
        let budget = &state.budget_steps;
        let _ = writeln!(
            text,
            "- real-time mode: {ms} ms per frame ({:.2} frames per second); training steps a frame managed: {:.1} on average, {} to {} (the result depends on this machine's speed and load)",
            1000.0 / ms as f64,
            budget.mean(),
            budget.min,
            budget.max
        );
    }
    for bad in &state.bad {
        let _ = writeln!(text, "- {bad}");
    }
    if let Some(last) = state.curve.last() {
        let _ = writeln!(
            text,
            "- streamed model: held-out PSNR {:.2} dB (right half {:.2} dB, foreground {:.2} dB), SSIM {:.4}, on {} views (every held-out view rendered at {scored_at})",
            last.psnr, last.psnr_right, last.psnr_foreground, last.ssim, last.held_out_views
        );
    }
    if let Some(last) = fixed_set.last() {
        let psnr: Vec<String> = fixed_set
            .iter()
            .map(|p| format!("{:.2}", p.metrics.psnr_full))
            .collect();
        let fall = fixed_set
            .windows(2)
            .map(|w| w[0].metrics.psnr_full - w[1].metrics.psnr_full)
            .fold(0.0f64, f64::max);
        let settle = match state.settle_from {
            Some(from) if state.settings.settle(from) > 0 => format!(
                " (the last after a settle of {} steps on the store from step {from})",
                state.settings.settle(from)
            ),
            _ => String::new(),
        };
        let _ = writeln!(
            text,
            "- fixed set (all {} held-out views) at each point: PSNR {} dB{settle}; largest fall from one point to the next {:.2} dB",
            last.views,
            psnr.join(", "),
            fall
        );
    }
    let views = super::forgetting(&state.curve, fixed_set);
    let change = |v: &super::ViewForgetting| v.last_psnr - v.first_psnr;
    if let Some(worst) = views.iter().min_by(|a, b| change(a).total_cmp(&change(b))) {
        let mean = views.iter().map(change).sum::<f64>() / views.len() as f64;
        // The same view in the offline reference tells forgetting from a model that spreads
        // what it holds over more views.
        let offline_view = (offline.and_then(|o| o.points.last()))
            .and_then(|p| p.per_view.iter().find(|(at, _)| *at == worst.position))
            .map_or(String::new(), |(_, psnr)| {
                format!("; the offline reference scores it {psnr:.2} dB")
            });
        let _ = writeln!(
            text,
            "- forgetting: each held-out view scored at the first point after it arrived and at the end: mean change {:+.2} dB; worst {:+.2} dB (arrival {}, first scored at {} frames seen: {:.2} -> {:.2} dB{offline_view}); {} views scored before the last point",
            mean,
            change(worst),
            worst.position,
            worst.first_frames_seen,
            worst.first_psnr,
            worst.last_psnr,
            views.len()
        );
    }
    if let Some((reference, last)) = offline.and_then(|o| Some((o, o.points.last()?))) {
        // The last point's seconds are the training time; the reference's add its scoring.
        let metrics = &last.metrics;
        let _ = writeln!(
            text,
            "- offline reference (all training frames at once, same steps, {:.1} s of training, {:.1} s with scoring): held-out PSNR {:.2} dB (right half {:.2} dB, foreground {:.2} dB), SSIM {:.4}",
            last.seconds,
            reference.seconds,
            metrics.psnr_full,
            metrics.psnr_right,
            metrics.psnr_foreground,
            metrics.ssim_full
        );
        if let Some(store) = &reference.store {
            let m = &store.metrics;
            let _ = writeln!(
                text,
                "- offline on the stream's final store ({}, same steps, {:.1} s of training): held-out PSNR {:.2} dB (right half {:.2} dB, foreground {:.2} dB), SSIM {:.4}; the stream is {:+.2} dB from it (the cost of learning while frames arrive) and it is {:+.2} dB from the offline reference (the cost of the store)",
                store_text(trainer.config()),
                store.seconds,
                m.psnr_full,
                m.psnr_right,
                m.psnr_foreground,
                m.ssim_full,
                state.curve.last().map_or(f64::NAN, |p| p.psnr) - m.psnr_full,
                m.psnr_full - metrics.psnr_full
            );
        }
    }
    // Memory from the first point on: the arena is allocated once before the first frame
    // (a ray reservoir, the store and its table of frames included), so any growth after it
    // would be the host's.
    if let (Some(first), Some(last)) = (state.curve.first(), state.curve.last()) {
        let _ = writeln!(
            text,
            "- resident memory: {:.1} MiB at {} frames seen, {:.1} MiB at {}",
            first.rss_mib, first.frames_seen, last.rss_mib, last.frames_seen
        );
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stream takes its own schedule (loss-weighted frame draws, the peak rate held for
    /// most of the stream) for every field the config file leaves to the preset, and the
    /// file's value for a field it sets, even one equal to the preset's.
    #[test]
    fn a_stream_takes_its_own_schedule_unless_the_config_file_sets_it() {
        let dir = tempfile::tempdir().unwrap();
        let choose = |text: Option<&str>| {
            let file = text.map(|text| {
                let path = dir.path().join("config.toml");
                std::fs::write(&path, text).unwrap();
                path
            });
            let choice = ModelChoice {
                preset: Some("spacecraft".into()),
                config_file: file,
                seed: None,
            };
            choice
                .choose(&SourceKind::WatchedFolder, (None, 0))
                .unwrap()
        };
        let (own, own_schedule) = choose(None);
        assert!(own_schedule);
        assert!(own.config.loss_weighted_frames);
        assert_eq!(own.config.lr_decay_start, STREAM_LR_DECAY_START);
        assert!(own.note.contains("the stream's schedule"), "{}", own.note);
        let preset = pipeline::preset_config(Some("spacecraft"), presets::SPACECRAFT, "", None)
            .unwrap()
            .config;
        assert!(!preset.loss_weighted_frames && preset.lr_decay_start == 0.0);

        let (stated, own_schedule) = choose(Some(
            "[config]\nlr_decay_start = 0.0\nloss_weighted_frames = false\n",
        ));
        assert!(!own_schedule);
        assert!(!stated.config.loss_weighted_frames);
        assert_eq!(stated.config.lr_decay_start, 0.0);
        assert!(
            !stated.note.contains("the stream's schedule"),
            "{}",
            stated.note
        );

        let (one, own_schedule) = choose(Some("lr_decay_start = 0.5\n"));
        assert!(!own_schedule);
        assert!(one.config.loss_weighted_frames);
        assert_eq!(one.config.lr_decay_start, 0.5);
    }

    /// A stream that settles holds the peak learning rate until its last arrival and decays
    /// over the settle: the core's decay (after warm-up, at `lr_decay_start` of the rest of
    /// the schedule) starts within a step of the last arrival, whatever the warm-up; a
    /// warm-up longer than the arrivals decays from its end. Unless the config file sets it.
    #[test]
    fn a_settling_stream_decays_its_learning_rate_over_the_settle_only() {
        for (warmup, arrivals, settle) in [(100, 1560, 480), (0, 2040, 1), (250, 300, 10_000)] {
            let config = Config {
                warmup_steps: warmup,
                steps: arrivals + settle,
                ..Config::DEFAULT
            };
            let start = settle_decay_start(&config, arrivals as u64, settle);
            assert!((0.0..1.0).contains(&start));
            let decay_from = warmup as f64 + start as f64 * (config.steps - warmup) as f64;
            assert!(
                (decay_from - arrivals as f64).abs() < 1.0,
                "{warmup} {arrivals} {settle}: decay from step {decay_from}"
            );
        }
        let config = Config {
            warmup_steps: 500,
            ..Config::DEFAULT
        };
        assert_eq!(settle_decay_start(&config, 400, 100), 0.0);

        let choice = ModelChoice {
            preset: Some("spacecraft".into()),
            ..ModelChoice::default()
        };
        let settles = choice.choose(&SourceKind::WatchedFolder, (Some(1560), 480));
        let settles = settles.unwrap().0.config;
        let expected = settle_decay_start(&settles, 1560, 480);
        assert!(expected > STREAM_LR_DECAY_START - 0.1 && expected != STREAM_LR_DECAY_START);
        assert_eq!(settles.lr_decay_start, expected);
        // An unknown length (a watched folder) keeps the stream's fraction.
        let unknown = choice
            .choose(&SourceKind::WatchedFolder, (None, 480))
            .unwrap()
            .0;
        assert_eq!(unknown.config.lr_decay_start, STREAM_LR_DECAY_START);
    }
}
