//! The fixed-step trainer: everything lives in one arena, a step samples a ray batch,
//! runs the chunks (on whatever threads the host's [`Executor`] offers), reduces their
//! gradients in chunk order and applies Adam. Rendering uses the same chunk machinery.
//!
//! One type, [`Trainer`], its `impl` split by stage:
//! - `layout`: carving the arena into the trainer's buffers and the seeded initial values;
//! - `slots`: putting frames into slots (directly or through the replacement policy);
//! - `batch`: drawing a step's ray batch;
//! - `step`: one training step (forward and backward in the chunks, reduction, Adam);
//! - `occupancy`: refreshing the occupancy grid;
//! - `inference`: rendering and fitting an appearance embedding to a held-out image;
//! - `checkpoint`: the state as named byte sections, saved and restored from one table;
//! - `chunk` and `backward`: the kernels one chunk runs on its own buffers.

use crate::arena::Carver;
use crate::config::{
    COLOUR_HIDDEN1, COLOUR_HIDDEN2, COLOUR_OUT, Config, DENSITY_HIDDEN, DENSITY_OUT, LANES,
    MAX_CHUNKS, MAX_COLOUR_HIDDEN, MAX_SCALES, MemoryPlan, MlpLayout, POSE_PARAMS, RAY_FLOATS,
    RAY_GRAD_FLOATS, TexelUpdate, activation_floats, colour_activation_rows,
    density_activation_rows, forward_sample_floats, sample_floats, widest_layer,
};
use crate::field::{self, PlaneGeometry, PlaneGrads, Row};
use crate::frames::{FrameMeta, FrameStore, RayCounts, mean_brightness};
use crate::fused;
use crate::optim::{self, AdamStep};
use crate::profile::{Bucket, Laps, Profiler, Stage, StageTimes, Timer};
use crate::render::{self, Aabb, OccupancyView};
use crate::replacement::{self, Descriptor, Ingested};
use crate::rng::{self, domain};
use crate::{Camera, Error, Pose, PoseCorrection};
use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use half::f16;

mod backward;
mod batch;
mod checkpoint;
mod chunk;
mod inference;
mod layout;
mod occupancy;
mod pose;
mod slots;
mod step;
#[cfg(test)]
mod tests;

use batch::BatchRay;
use chunk::Chunk;
pub use pose::PoseFit;
use pose::PoseSystem;
#[cfg(test)]
use pose::{RaySet, View};

/// Runs a closure over every item, possibly in parallel. Results must not depend on the
/// order or the thread: the core gives each item its own buffers.
pub trait Executor {
    /// Call `f` once on every element of `items`, in any order and on any thread.
    fn for_each<T: Send, F: Fn(&mut T) + Sync>(&self, items: &mut [T], f: F);
}

/// Runs items one after another on the calling thread.
pub struct Sequential;

impl Executor for Sequential {
    fn for_each<T: Send, F: Fn(&mut T) + Sync>(&self, items: &mut [T], f: F) {
        items.iter_mut().for_each(f);
    }
}

/// What one training step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StepReport {
    /// Mean squared error per channel over the rays that were rendered.
    pub mse: f32,
    /// Rays rendered and trained on (the whole batch).
    pub rays: u32,
    /// Samples that reached the colour MLP and the backward pass (before the early stop).
    pub samples: u32,
    /// Samples marched through occupied space (all get a density evaluation).
    pub samples_marched: u32,
    /// True if the loss or a gradient was not finite and the update was skipped.
    pub skipped: bool,
}

/// Counters that belong to the training state (and to checkpoints).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct TrainState {
    /// Steps taken (applied or skipped).
    pub step: u32,
    /// Updates applied (Adam's time step).
    pub updates: u32,
    /// Steps skipped because the loss or a gradient was not finite.
    pub skipped: u32,
    /// Occupancy refreshes done.
    pub refreshes: u32,
    /// Updates applied to the pose corrections (their Adam's time step: their moments
    /// start at zero when they start learning, after `pose_warmup_steps`).
    pub pose_updates: u32,
    /// Keeps the counts below on 8 bytes (the state is stored as its bytes).
    pub padding: u32,
    /// How full the ray reservoir is and how much it was offered (zero for whole frames).
    pub rays: RayCounts,
}

/// The trainer and everything it owns, all borrowed from one arena.
pub struct Trainer<'a> {
    config: Config,
    geometry: PlaneGeometry,
    layout: MlpLayout,
    aabb: Aabb,
    /// Distance between samples along a ray, in world units.
    step_size: f32,
    /// Optical depth of one step per unit density: `step_size / length_unit`.
    optical_step: f32,
    /// `Config::length_unit`.
    length_unit: f32,
    planes: &'a mut [f16],
    plane_master: &'a mut [f32],
    plane_m: &'a mut [f32],
    plane_v: &'a mut [f32],
    touched_union: &'a mut [u64],
    mlp: &'a mut [f32],
    mlp_m: &'a mut [f32],
    mlp_v: &'a mut [f32],
    occupancy_bits: &'a mut [u64],
    occupancy_density: &'a mut [f32],
    frames: FrameStore<'a>,
    frame_params: &'a mut [f32],
    frame_m: &'a mut [f32],
    frame_v: &'a mut [f32],
    rays: &'a mut [BatchRay],
    ray_frames: &'a mut [u32],
    chunks: heapless::Vec<Chunk<'a>, MAX_CHUNKS>,
    state: TrainState,
    used: MemoryPlan,
    /// False for a render-only trainer ([`Trainer::new_render_only`]).
    training: bool,
    /// The host's clock and the stage times (feature `profile`; empty without it).
    profile: Profiler,
}

/// What the chunks are run for. It decides the appearance embedding they use, the counter
/// that keys their random draws, and which gradients their backward pass produces.
#[derive(Clone, Copy)]
enum Pass<'s> {
    /// A training step: each ray uses its frame's embedding; draws are keyed by the step.
    /// The chunks ask `stop` between their passes whether to give the step up.
    Train { stop: &'s (dyn Fn() -> bool + Sync) },
    /// One step of fitting a held-out view's frame parameters (`params`: embedding, then
    /// the pose correction its rays went through) to its image with the field frozen;
    /// `center` is the label's camera centre; the pose correction gets gradients with
    /// `align_pose`.
    FitView {
        params: &'s [f32],
        center: [f32; 3],
        step: u32,
        align_pose: bool,
    },
    /// Rendering with `embedding`: no jitter, samples at the middle of each marching step.
    Render { embedding: &'s [f32] },
    /// Re-estimating the occupancy grid; draws are keyed by the refresh count.
    Occupancy,
    /// One Jacobian pass of a pose refinement (`refine`): a view's frame parameters
    /// (`params`: embedding, then pose correction) with the field frozen, the label's camera
    /// centre, and the colour channel whose Jacobian rows the backward pass gives.
    PoseJacobian {
        params: &'s [f32],
        center: [f32; 3],
        channel: usize,
    },
}

/// Where the colour MLP's appearance embedding comes from.
#[derive(Clone, Copy)]
enum Embedding<'s> {
    /// Each ray uses the embedding of the frame it was sampled from.
    PerFrame(&'s [f32]),
    /// Every ray uses this one (rendering, embedding fit).
    Fixed(&'s [f32]),
}

/// Read-only state shared by all chunks during a pass.
#[derive(Clone, Copy)]
struct Shared<'s> {
    config: &'s Config,
    geometry: &'s PlaneGeometry,
    layout: &'s MlpLayout,
    aabb: Aabb,
    step_size: f32,
    optical_step: f32,
    length_unit: f32,
    planes: &'s [f16],
    /// Each scale's weight at the trainer's step (the coarse-to-fine schedule).
    scale_weights: [f32; MAX_SCALES],
    mlp: &'s [f32],
    occupancy: OccupancyView<'s>,
    rays: &'s [BatchRay],
    ray_frames: &'s [u32],
    /// The frame slots' metadata (label poses), for the pose-correction gradients.
    frame_meta: &'s [FrameMeta],
    embedding: Embedding<'s>,
    /// Keys the pass's random draws: the training step, the fit step or the refresh count.
    draw_counter: u32,
    /// Offset the sample positions along each ray by a seeded fraction of a step.
    jitter: bool,
    /// One view's parameters are being fitted with the field frozen: the embedding's
    /// gradient goes to the chunk's first frame-gradient slot, and without `fit_pose` the
    /// backward pass stops at the colour MLP's input.
    fitting_view: bool,
    /// While fitting a view's pose correction: its six parameters and the label's camera
    /// centre (the pose gradients fold into the first frame-gradient slot's correction).
    fit_pose: Option<([f32; POSE_PARAMS], [f32; 3])>,
    /// The pose corrections learn from this pass: the backward pass carries gradients on to
    /// the rays' origins and directions and folds them into the frames' corrections.
    pose_gradients: bool,
    /// A pose refinement's Jacobian pass for this colour channel: the backward pass starts
    /// from the channel's robustly weighted colour instead of the loss, and each ray's row
    /// goes into the chunk's normal equations.
    jacobian_channel: Option<usize>,
    /// The host's clock, for the chunks' stage times (feature `profile`).
    timer: Timer,
    /// A training step's stop request, asked between a chunk's passes (`Pass::Train`).
    stop: Option<&'s (dyn Fn() -> bool + Sync)>,
}

impl<'a> Trainer<'a> {
    /// The config the trainer was built with.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Plan the learning-rate schedules anew for a run of `steps` steps in all, the cosine
    /// decay starting at `lr_decay_start` of them after warm-up (`Config::steps` and
    /// `Config::lr_decay_start`): a stream that did not know its length decays over the
    /// steps it takes once its source has ended. Nothing else of the config changes; refused
    /// (and nothing changed) where the config would not validate, e.g. `steps` below the
    /// warm-up.
    pub fn reschedule(&mut self, steps: u32, lr_decay_start: f32) -> Result<(), Error> {
        let config = Config {
            steps,
            lr_decay_start,
            ..self.config
        };
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// Bytes actually taken from the arena, per part (equals `MemoryPlan::new(config)`
    /// except for `total`, which here excludes the alignment slack).
    pub fn memory_used(&self) -> MemoryPlan {
        self.used
    }

    /// Step, update, skip and refresh counters.
    pub fn state(&self) -> TrainState {
        self.state
    }

    /// The frame slots: pixels, cameras, poses and which slots are occupied.
    pub fn frames(&self) -> &FrameStore<'a> {
        &self.frames
    }

    /// The f16 texels of every plane, scale by scale.
    pub fn planes(&self) -> &[f16] {
        self.planes
    }

    /// All MLP weights and biases, laid out as `Config::mlp`.
    pub fn mlp_parameters(&self) -> &[f32] {
        self.mlp
    }

    /// Lend the trainer a clock (or take it back with `None`): from now on each training
    /// step and render adds its stage times to [`Trainer::profile`]. Timing never changes
    /// the results.
    #[cfg(feature = "profile")]
    pub fn set_clock(&mut self, clock: Option<crate::profile::Clock>) {
        self.profile.timer.clock = clock;
    }

    /// Stage times gathered since the clock was set or the profile last reset.
    #[cfg(feature = "profile")]
    pub fn profile(&self) -> crate::profile::Profile {
        self.profile.times
    }

    /// Forget the stage times gathered so far (e.g. after warm-up steps).
    #[cfg(feature = "profile")]
    pub fn reset_profile(&mut self) {
        self.profile.times = crate::profile::Profile::default();
    }

    /// `Err(RenderOnly)` for a render-only trainer: the guard of every training operation.
    fn require_training(&self) -> Result<(), Error> {
        if self.training {
            Ok(())
        } else {
            Err(Error::RenderOnly)
        }
    }

    /// The read-only view of the model the chunks work with during `pass`.
    fn shared<'s>(&'s self, pass: Pass<'s>) -> Shared<'s> {
        let dim = self.config.embedding_dim as usize;
        let fit_pose = match pass {
            Pass::FitView {
                params,
                center,
                align_pose: true,
                ..
            }
            | Pass::PoseJacobian { params, center, .. } => {
                let pose = core::array::from_fn(|i| params.get(dim + i).copied().unwrap_or(0.0));
                Some((pose, center))
            }
            _ => None,
        };
        let (embedding, draw_counter) = match pass {
            Pass::Train { .. } => (Embedding::PerFrame(&*self.frame_params), self.state.step),
            Pass::FitView { params, step, .. } => {
                (Embedding::Fixed(params.get(..dim).unwrap_or(&[])), step)
            }
            Pass::PoseJacobian { params, .. } => {
                (Embedding::Fixed(params.get(..dim).unwrap_or(&[])), 0)
            }
            Pass::Render { embedding } => (Embedding::Fixed(embedding), 0),
            Pass::Occupancy => (Embedding::Fixed(&[]), self.state.refreshes),
        };
        Shared {
            config: &self.config,
            geometry: &self.geometry,
            layout: &self.layout,
            aabb: self.aabb,
            step_size: self.step_size,
            optical_step: self.optical_step,
            length_unit: self.length_unit,
            planes: self.planes,
            scale_weights: self.config.scale_weights_at(self.state.step),
            mlp: self.mlp,
            occupancy: OccupancyView {
                bits: self.occupancy_bits,
                res: self.config.occupancy_res as usize,
                aabb: self.aabb,
            },
            rays: self.rays,
            ray_frames: self.ray_frames,
            frame_meta: self.frames.meta,
            embedding,
            draw_counter,
            // A refinement samples each ray at fixed places, so that its evaluations at
            // nearby poses differ only by the poses.
            jitter: !matches!(pass, Pass::Render { .. } | Pass::PoseJacobian { .. }),
            fitting_view: matches!(pass, Pass::FitView { .. } | Pass::PoseJacobian { .. }),
            fit_pose,
            pose_gradients: match pass {
                Pass::Train { .. } => self.config.pose_learns_at(self.state.step),
                _ => fit_pose.is_some(),
            },
            jacobian_channel: match pass {
                Pass::PoseJacobian { channel, .. } => Some(channel),
                _ => None,
            },
            timer: self.profile.timer,
            stop: match pass {
                Pass::Train { stop } => Some(stop),
                _ => None,
            },
        }
    }

    /// Move the chunks out, give them consecutive runs of the batch's first `rays` rays
    /// (none for the occupancy pass), hand them to `run` beside the shared view for `pass`,
    /// and put them back. The view borrows the rest of the trainer while the chunks work.
    fn with_chunks<R>(
        &mut self,
        pass: Pass<'_>,
        rays: usize,
        run: impl FnOnce(&Shared<'_>, &mut [Chunk<'a>]) -> R,
    ) -> R {
        let mut chunks = core::mem::take(&mut self.chunks);
        let per_chunk = rays.div_ceil(chunks.len());
        for (i, chunk) in chunks.iter_mut().enumerate() {
            chunk.first_ray = (i * per_chunk).min(rays);
            chunk.ray_count = per_chunk.min(rays - chunk.first_ray);
        }
        let result = run(&self.shared(pass), &mut chunks);
        self.chunks = chunks;
        result
    }
}

/// Indices of the set bits of a bitmap, in increasing order (the touched texels).
fn set_bits(words: &[u64]) -> impl Iterator<Item = usize> + '_ {
    words.iter().enumerate().flat_map(|(w, &word)| {
        let mut bits = word;
        core::iter::from_fn(move || {
            if bits == 0 {
                return None;
            }
            let bit = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            Some(w * 64 + bit)
        })
    })
}
