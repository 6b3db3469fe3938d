//! Where a training step's and a render's time goes, stage by stage (feature `profile`).
//!
//! The core has no clock, so the host lends one ([`Clock`], nanoseconds from any fixed
//! origin) through `Trainer::set_clock`. Without a clock, or with the feature off, nothing
//! is timed and every type here is empty: the timing points in the kernels compile to
//! nothing. Timing only reads the clock; it never changes what the trainer computes.
//!
//! Stages inside the chunks run in parallel, so they are kept twice: `cpu` sums each chunk's
//! own time over all chunks (CPU time over the threads), and `wall` shares each parallel
//! pass's wall time out over its stages in proportion to their CPU time, so the wall figures
//! of all stages add up to (at most) the elapsed time.

/// Nanoseconds since a fixed origin, from the host (e.g. `Instant` elapsed since start).
#[cfg(feature = "profile")]
pub type Clock = fn() -> u64;

/// A stage of a training step or of rendering a view.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Drawing the batch: frames, pixels, rays through the pose corrections (serial).
    RaySampling,
    /// Marching the occupancy grid into samples (chunks).
    Marching,
    /// Plane lookups and the density MLP on every marched sample (chunks).
    DensityForward,
    /// Cutting each ray where its transmittance runs out, listing the kept samples and (in
    /// training) compacting their density rows (chunks).
    EarlyStop,
    /// The colour MLP on the kept samples (chunks).
    ColourForward,
    /// Compositing, the loss and the compositing's backward pass (chunks).
    Compositing,
    /// Backward through the colour MLP (chunks).
    ColourBackward,
    /// Backward through the density MLP, and the embeddings' gradients (chunks).
    DensityBackward,
    /// Backward into the plane texels and the pose corrections (chunks).
    PlaneBackward,
    /// Summing the chunks' gradients in chunk order and checking them (serial).
    Reduction,
    /// Adam on the MLPs, the embeddings, the poses and the touched texels (serial).
    Adam,
    /// Refreshing the occupancy grid (chunks, then a serial threshold pass).
    Occupancy,
    /// Fitting a held-out view's appearance embedding (evaluation; all its stages).
    FitEmbedding,
}

/// Number of stages.
pub const STAGES: usize = 13;

impl Stage {
    /// Every stage, in the order of a step (then evaluation's).
    pub const ALL: [Stage; STAGES] = [
        Stage::RaySampling,
        Stage::Marching,
        Stage::DensityForward,
        Stage::EarlyStop,
        Stage::ColourForward,
        Stage::Compositing,
        Stage::ColourBackward,
        Stage::DensityBackward,
        Stage::PlaneBackward,
        Stage::Reduction,
        Stage::Adam,
        Stage::Occupancy,
        Stage::FitEmbedding,
    ];

    /// A short name for tables.
    pub const fn name(self) -> &'static str {
        match self {
            Stage::RaySampling => "ray sampling",
            Stage::Marching => "marching",
            Stage::DensityForward => "density forward",
            Stage::EarlyStop => "early stop",
            Stage::ColourForward => "colour forward",
            Stage::Compositing => "compositing + loss",
            Stage::ColourBackward => "backward: colour MLP",
            Stage::DensityBackward => "backward: density MLP",
            Stage::PlaneBackward => "backward: planes + poses",
            Stage::Reduction => "gradient reduction",
            Stage::Adam => "Adam",
            Stage::Occupancy => "occupancy refresh",
            Stage::FitEmbedding => "embedding fit",
        }
    }
}

/// Nanoseconds per stage (empty with the feature off).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StageTimes {
    #[cfg(feature = "profile")]
    ns: [u64; STAGES],
}

#[cfg(feature = "profile")]
impl StageTimes {
    /// Nanoseconds spent in `stage`.
    pub fn get(&self, stage: Stage) -> u64 {
        self.ns[stage as usize]
    }

    /// Sum over all stages.
    pub fn total(&self) -> u64 {
        self.ns.iter().sum()
    }
}

/// Stage times of the training steps and of the renders since the clock was set.
#[cfg(feature = "profile")]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Profile {
    /// Training steps: summed over the chunks for the parallel stages.
    pub train_cpu: StageTimes,
    /// Training steps: elapsed time, parallel passes shared out over their stages.
    pub train_wall: StageTimes,
    /// Rendering and embedding fits: summed over the chunks.
    pub render_cpu: StageTimes,
    /// Rendering and embedding fits: elapsed time.
    pub render_wall: StageTimes,
}

/// The host's clock, if it lent one (empty with the feature off).
#[derive(Clone, Copy, Default)]
pub(crate) struct Timer {
    #[cfg(feature = "profile")]
    pub(crate) clock: Option<Clock>,
}

impl Timer {
    /// A stopwatch started now (inert without a clock).
    #[inline(always)]
    pub(crate) fn laps(self) -> Laps {
        Laps {
            #[cfg(feature = "profile")]
            clock: self.clock,
            #[cfg(feature = "profile")]
            last: self.clock.map_or(0, |clock| clock()),
        }
    }
}

/// A running stopwatch: each `lap` charges the time since the previous one to a stage.
#[derive(Clone, Copy)]
pub(crate) struct Laps {
    #[cfg(feature = "profile")]
    clock: Option<Clock>,
    #[cfg(feature = "profile")]
    last: u64,
}

impl Laps {
    /// Nanoseconds since the last lap (or the start), restarting from now; 0 without a clock.
    #[cfg(feature = "profile")]
    #[inline(always)]
    fn split(&mut self) -> u64 {
        match self.clock {
            Some(clock) => {
                let now = clock();
                let elapsed = now.saturating_sub(self.last);
                self.last = now;
                elapsed
            }
            None => 0,
        }
    }

    /// Charge the time since the last lap (or the start) to `stage` in `times`.
    #[inline(always)]
    pub(crate) fn lap(&mut self, stage: Stage, times: &mut StageTimes) {
        #[cfg(feature = "profile")]
        {
            times.ns[stage as usize] += self.split();
        }
        #[cfg(not(feature = "profile"))]
        let _ = (stage, times);
    }
}

/// The trainer's clock and accumulated stage times (empty with the feature off).
#[derive(Clone, Copy, Default)]
pub(crate) struct Profiler {
    pub(crate) timer: Timer,
    #[cfg(feature = "profile")]
    pub(crate) times: Profile,
}

/// Which of the profile's two sets a pass is charged to.
#[derive(Clone, Copy)]
pub(crate) enum Bucket {
    Train,
    Render,
}

impl Profiler {
    /// A stopwatch started now (inert without a clock).
    #[inline(always)]
    pub(crate) fn laps(&self) -> Laps {
        self.timer.laps()
    }

    /// Charge the time since `laps` started (or its last lap) to a serial `stage`, in both
    /// the CPU and the wall set of `bucket`.
    #[inline(always)]
    pub(crate) fn serial(&mut self, laps: &mut Laps, bucket: Bucket, stage: Stage) {
        #[cfg(feature = "profile")]
        {
            let elapsed = laps.split();
            let (cpu, wall) = self.bucket(bucket);
            cpu.ns[stage as usize] += elapsed;
            wall.ns[stage as usize] += elapsed;
        }
        #[cfg(not(feature = "profile"))]
        let _ = (laps, bucket, stage);
    }

    /// Take the stage times the chunks gathered during a parallel pass that `laps` timed
    /// (zeroing them), add them to `bucket`'s CPU set, and share the pass's elapsed time out
    /// over the same stages. With `only`, the whole pass is charged to that one stage.
    pub(crate) fn parallel<'t>(
        &mut self,
        laps: &mut Laps,
        bucket: Bucket,
        chunk_times: impl Iterator<Item = &'t mut StageTimes>,
        only: Option<Stage>,
    ) {
        #[cfg(feature = "profile")]
        {
            let elapsed = laps.split();
            let mut pass = StageTimes::default();
            for times in chunk_times {
                for (sum, t) in pass.ns.iter_mut().zip(times.ns.iter()) {
                    *sum += *t;
                }
                *times = StageTimes::default();
            }
            if let Some(stage) = only {
                let total = pass.total();
                pass = StageTimes::default();
                pass.ns[stage as usize] = total;
            }
            let total = pass.total();
            let (cpu, wall) = self.bucket(bucket);
            for (s, t) in pass.ns.iter().enumerate() {
                cpu.ns[s] += *t;
                if total > 0 {
                    wall.ns[s] += (elapsed as u128 * *t as u128 / total as u128) as u64;
                }
            }
        }
        #[cfg(not(feature = "profile"))]
        let _ = (laps, bucket, chunk_times, only);
    }

    #[cfg(feature = "profile")]
    fn bucket(&mut self, bucket: Bucket) -> (&mut StageTimes, &mut StageTimes) {
        let t = &mut self.times;
        match bucket {
            Bucket::Train => (&mut t.train_cpu, &mut t.train_wall),
            Bucket::Render => (&mut t.render_cpu, &mut t.render_wall),
        }
    }
}
