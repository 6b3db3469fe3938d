//! The fixed-step trainer: everything lives in one arena, a step samples a ray batch,
//! runs the chunks (on whatever threads the host's [`Executor`] offers), reduces their
//! gradients in chunk order and applies Adam. Rendering uses the same chunk machinery.

use crate::arena::Carver;
use crate::config::{
    COLOUR_HIDDEN1, COLOUR_HIDDEN2, COLOUR_OUT, Config, DENSITY_HIDDEN, DENSITY_OUT, LANES,
    MAX_CHUNKS, MemoryPlan, MlpLayout, RAY_FLOATS, TexelUpdate, activation_floats, sample_floats,
    widest_layer,
};
use crate::field::{self, PlaneGeometry, PlaneGrads, Row};
use crate::frames::{FrameMeta, FrameStore, mean_brightness};
use crate::optim::{self, AdamStep};
use crate::render::{self, Aabb, OccupancyView};
use crate::rng::{self, stream};
use crate::stream::{self as admission, Descriptor, Ingested};
use crate::{Camera, Error, Pose, PoseCorrection};
use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use half::f16;

/// Runs a closure over every item, possibly in parallel. Results must not depend on the
/// order or the thread: the core gives each item its own buffers.
pub trait Executor {
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
    pub rays: u32,
    /// Samples that reached the colour MLP and the backward pass (before the early stop).
    pub samples: u32,
    /// Samples marched through occupied space (all get a density evaluation).
    pub samples_marched: u32,
    /// Rays dropped because their chunk's sample capacity ran out.
    pub dropped_rays: u32,
    /// True if the loss or a gradient was not finite and the update was skipped.
    pub skipped: bool,
}

/// Adam learning rate of `fit_embedding` (only a few dozen steps, on one vector).
const FIT_LEARNING_RATE: f32 = 0.05;

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
}

/// Where the colour MLP's appearance embedding comes from.
#[derive(Clone, Copy)]
enum Embedding<'s> {
    /// Each ray uses the embedding of the frame it was sampled from.
    PerFrame(&'s [f32]),
    /// Every ray uses this one (rendering).
    Fixed(&'s [f32]),
}

/// Read-only state shared by all chunks during a step or a render.
#[derive(Clone, Copy)]
struct Shared<'s> {
    config: &'s Config,
    geometry: &'s PlaneGeometry,
    layout: &'s MlpLayout,
    aabb: Aabb,
    step_size: f32,
    planes: &'s [f16],
    mlp: &'s [f32],
    occupancy: OccupancyView<'s>,
    rays: &'s [f32],
    ray_frames: &'s [u32],
    /// The frame slots' metadata (label poses), for the pose-correction gradients.
    frame_meta: &'s [FrameMeta],
    embedding: Embedding<'s>,
    step: u32,
    /// Offset the sample positions along each ray by a seeded fraction of a step.
    jitter: bool,
    /// Only the fixed embedding is being fitted: the backward pass stops at the colour MLP's
    /// input and sends the embedding's gradient to the chunk's first frame-gradient slot.
    fit_embedding: bool,
    /// The pose corrections learn from this pass: the backward pass carries gradients on to
    /// the rays' origins and directions and folds them into the frames' corrections.
    pose_gradients: bool,
}

/// Activation rows of one mini-batch of `LANES` samples (or their gradients).
struct Rows<'r> {
    feats: &'r mut [Row],
    hidden: &'r mut [Row],
    density_out: &'r mut [Row],
    colour_in: &'r mut [Row],
    colour1: &'r mut [Row],
    colour2: &'r mut [Row],
    rgb: &'r mut [Row],
}

fn split_rows<'r>(c: &Config, rows: &'r mut [Row]) -> Rows<'r> {
    let (feats, rest) = rows.split_at_mut(c.density_inputs());
    let (hidden, rest) = rest.split_at_mut(c.density_hidden as usize);
    let (density_out, rest) = rest.split_at_mut(c.density_outputs());
    let (colour_in, rest) = rest.split_at_mut(c.colour_inputs());
    let (colour1, rest) = rest.split_at_mut(c.colour_hidden as usize);
    let (colour2, rgb) = rest.split_at_mut(c.colour_hidden as usize);
    Rows {
        feats,
        hidden,
        density_out,
        colour_in,
        colour1,
        colour2,
        rgb,
    }
}

/// One chunk's private buffers.
pub struct Chunk<'a> {
    plane_grads: &'a mut [f32],
    touched: &'a mut [u64],
    mlp_grads: &'a mut [f32],
    frame_grads: &'a mut [f32],
    positions: &'a mut [[f32; 3]],
    sigma: &'a mut [f32],
    geo: &'a mut [f32],
    rgb: &'a mut [[f32; 3]],
    d_sigma: &'a mut [f32],
    d_rgb: &'a mut [[f32; 3]],
    sample_ray: &'a mut [u32],
    ray_start: &'a mut [u32],
    activations: &'a mut [Row],
    gradients: &'a mut [Row],
    /// Per-plane bilinear values of each lane's sample (lane-major), kept from the
    /// recomputed forward pass for the plane backward pass.
    plane_values: &'a mut [f32],
    /// d loss / d origin and d loss / d direction of each of the chunk's rays (pose correction).
    ray_grads: &'a mut [f32],
    /// Output gradients of one layer in lane-major order (the weight-gradient kernel's input).
    lane_major: &'a mut [f32],
    /// First ray of the batch this chunk works on, and how many.
    first_ray: usize,
    ray_count: usize,
    report: ChunkReport,
}

#[derive(Clone, Copy, Default)]
struct ChunkReport {
    squared_error: f32,
    rays: u32,
    samples: u32,
    marched: u32,
    dropped: u32,
}

/// The trainer and everything it owns, all borrowed from one arena.
pub struct Trainer<'a> {
    config: Config,
    geometry: PlaneGeometry,
    layout: MlpLayout,
    aabb: Aabb,
    step_size: f32,
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
    rays: &'a mut [f32],
    ray_frames: &'a mut [u32],
    chunks: heapless::Vec<Chunk<'a>, MAX_CHUNKS>,
    state: TrainState,
    used: MemoryPlan,
}

impl<'a> Trainer<'a> {
    /// Validate `config`, lay out `arena` and initialise the parameters from the seed.
    pub fn new(config: Config, arena: &'a mut [u8]) -> Result<Self, Error> {
        config.validate()?;
        let plan = MemoryPlan::new(&config);
        let mut carver = Carver::new(arena, plan.total)?;
        let c = &config;
        let params = c.plane_params();
        let words = c.texels().div_ceil(64);
        let mlp_len = c.mlp().total;
        let frames = c.max_frames as usize;
        let frame_params = c.frame_params();
        let chunks = c.chunks as usize;
        let samples = c.samples_per_chunk as usize;
        let chunk_rays = c.rays_per_chunk();
        let mut used = MemoryPlan { total: 0, ..plan };
        let mut mark = 0;
        let mut tally = |carver: &Carver, part: &mut usize| {
            *part = carver.used() - mark;
            mark = carver.used();
        };

        let planes = carver.take::<f16>(params)?;
        tally(&carver, &mut used.planes);
        let master_len = if c.texel_update == TexelUpdate::MasterCopy {
            params
        } else {
            0
        };
        let plane_master = carver.take::<f32>(master_len)?;
        tally(&carver, &mut used.plane_master);
        let plane_m = carver.take::<f32>(params)?;
        let plane_v = carver.take::<f32>(params)?;
        tally(&carver, &mut used.plane_moments);
        let mut plane_grad_parts: heapless::Vec<(&mut [f32], &mut [u64]), MAX_CHUNKS> =
            heapless::Vec::new();
        for _ in 0..chunks {
            let g = carver.take::<f32>(params)?;
            let t = carver.take::<u64>(words)?;
            let _ = plane_grad_parts.push((g, t));
        }
        let touched_union = carver.take::<u64>(words)?;
        tally(&carver, &mut used.plane_grads);
        let mlp = carver.take::<f32>(mlp_len)?;
        let mlp_m = carver.take::<f32>(mlp_len)?;
        let mlp_v = carver.take::<f32>(mlp_len)?;
        let mut mlp_grad_parts: heapless::Vec<&mut [f32], MAX_CHUNKS> = heapless::Vec::new();
        for _ in 0..chunks {
            let _ = mlp_grad_parts.push(carver.take::<f32>(mlp_len)?);
        }
        tally(&carver, &mut used.mlp);
        let occupancy_bits = carver.take::<u64>(c.occupancy_cells().div_ceil(64))?;
        let occupancy_density = carver.take::<f32>(c.occupancy_cells())?;
        tally(&carver, &mut used.occupancy);
        let pixels = carver.take::<u8>(frames * c.max_pixels_per_frame as usize * 3)?;
        let masks = carver.take::<u8>(frames * c.max_pixels_per_frame as usize)?;
        let meta = carver.take::<FrameMeta>(frames)?;
        let occupied = carver.take::<u16>(frames)?;
        let frame_param_slice = carver.take::<f32>(frames * frame_params)?;
        let frame_m = carver.take::<f32>(frames * frame_params)?;
        let frame_v = carver.take::<f32>(frames * frame_params)?;
        let mut frame_grad_parts: heapless::Vec<&mut [f32], MAX_CHUNKS> = heapless::Vec::new();
        for _ in 0..chunks {
            let _ = frame_grad_parts.push(carver.take::<f32>(frames * frame_params)?);
        }
        tally(&carver, &mut used.frames);
        let rays = carver.take::<f32>(c.rays_per_batch as usize * RAY_FLOATS)?;
        let ray_frames = carver.take::<u32>(c.rays_per_batch as usize)?;
        tally(&carver, &mut used.ray_batch);
        let mut chunk_list = heapless::Vec::new();
        let rows = activation_floats(c);
        let geo_len = c.geo_features as usize;
        for (i, ((plane_grads, touched), (mlp_grads, frame_grads))) in plane_grad_parts
            .into_iter()
            .zip(mlp_grad_parts.into_iter().zip(frame_grad_parts))
            .enumerate()
        {
            let block = carver.take::<f32>(samples * sample_floats(c))?;
            let (positions, block) = block.split_at_mut(3 * samples);
            let (sigma, block) = block.split_at_mut(samples);
            let (geo, block) = block.split_at_mut(geo_len * samples);
            let (rgb, block) = block.split_at_mut(3 * samples);
            let (d_sigma, d_rgb) = block.split_at_mut(samples);
            let sample_ray = carver.take::<u32>(samples)?;
            let ray_start = carver.take::<u32>(chunk_rays + 1)?;
            let act = carver.take::<Row>(2 * rows)?;
            let (activations, gradients) = act.split_at_mut(rows);
            let plane_values = carver.take::<f32>(LANES * 3 * c.density_inputs())?;
            let lane_major = carver.take::<f32>(LANES * widest_layer(c))?;
            let ray_grads = carver.take::<f32>(chunk_rays * 6)?;
            let chunk = Chunk {
                plane_grads,
                touched,
                mlp_grads,
                frame_grads,
                positions: bytemuck::cast_slice_mut(positions),
                sigma,
                geo,
                rgb: bytemuck::cast_slice_mut(rgb),
                d_sigma,
                d_rgb: bytemuck::cast_slice_mut(d_rgb),
                sample_ray,
                ray_start,
                activations,
                gradients,
                plane_values,
                lane_major,
                ray_grads,
                first_ray: i * chunk_rays,
                ray_count: chunk_rays,
                report: ChunkReport::default(),
            };
            if chunk_list.push(chunk).is_err() {
                return Err(Error::InvalidConfig { field: "chunks" });
            }
        }
        tally(&carver, &mut used.samples);
        used.total = carver.used();

        let aabb = Aabb {
            min: Vec3::from_array(c.aabb_min),
            max: Vec3::from_array(c.aabb_max),
        };
        let mut trainer = Trainer {
            config,
            geometry: PlaneGeometry::new(&config),
            layout: config.mlp(),
            aabb,
            step_size: aabb.diagonal() / config.march_steps as f32,
            planes,
            plane_master,
            plane_m,
            plane_v,
            touched_union,
            mlp,
            mlp_m,
            mlp_v,
            occupancy_bits,
            occupancy_density,
            frames: FrameStore {
                meta,
                pixels,
                masks,
                occupied,
                len: 0,
                max_pixels: c.max_pixels_per_frame as usize,
            },
            frame_params: frame_param_slice,
            frame_m,
            frame_v,
            rays,
            ray_frames,
            chunks: chunk_list,
            state: TrainState::default(),
            used,
        };
        trainer.initialise();
        Ok(trainer)
    }

    /// Seeded initial parameters: planes uniform in [init_low, init_high], MLP weights
    /// uniform in ±sqrt(6 / fan_in) (He), zero biases; every occupancy cell occupied.
    fn initialise(&mut self) {
        let c = &self.config;
        let mut rng = rng::Rng::new(rng::hash(c.seed, stream::INIT, 0, 0));
        for (i, t) in self.planes.iter_mut().enumerate() {
            let v = c.init_low + (c.init_high - c.init_low) * rng.uniform();
            *t = f16::from_f32(v);
            if let Some(m) = self.plane_master.get_mut(i) {
                *m = t.to_f32();
            }
        }
        for layer in &self.layout.layers {
            let bound = libm::sqrtf(6.0 / layer.inputs as f32);
            for w in &mut self.mlp[layer.weights..layer.biases] {
                *w = bound * (2.0 * rng.uniform() - 1.0);
            }
        }
        self.occupancy_bits.fill(u64::MAX);
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Bytes actually taken from the arena, per part (equals `MemoryPlan::new(config)`
    /// except for `total`, which here excludes the alignment slack).
    pub fn memory_used(&self) -> MemoryPlan {
        self.used
    }

    pub fn state(&self) -> TrainState {
        self.state
    }

    pub fn frames(&self) -> &FrameStore<'a> {
        &self.frames
    }

    pub fn planes(&self) -> &[f16] {
        self.planes
    }

    pub fn mlp_parameters(&self) -> &[f32] {
        self.mlp
    }

    /// The whole training state as named byte sections (for checkpoints): parameters,
    /// optimizer moments, occupancy, frames and counters.
    pub fn sections(&self) -> [(&'static str, &[u8]); 16] {
        use bytemuck::cast_slice as bytes;
        [
            ("state", bytemuck::bytes_of(&self.state)),
            ("planes", bytes(self.planes)),
            ("plane_master", bytes(self.plane_master)),
            ("plane_m", bytes(self.plane_m)),
            ("plane_v", bytes(self.plane_v)),
            ("mlp", bytes(self.mlp)),
            ("mlp_m", bytes(self.mlp_m)),
            ("mlp_v", bytes(self.mlp_v)),
            ("occupancy_bits", bytes(self.occupancy_bits)),
            ("occupancy_density", bytes(self.occupancy_density)),
            ("frame_meta", bytes(self.frames.meta)),
            ("frame_pixels", self.frames.pixels),
            ("frame_masks", self.frames.masks),
            ("frame_params", bytes(self.frame_params)),
            ("frame_m", bytes(self.frame_m)),
            ("frame_v", bytes(self.frame_v)),
        ]
    }

    /// Restore one section written by `sections` for the same config. The size must match.
    pub fn restore_section(&mut self, name: &str, data: &[u8]) -> Result<(), Error> {
        use bytemuck::cast_slice_mut as bytes;
        let (name, target): (&'static str, &mut [u8]) = match name {
            "state" => ("state", bytemuck::bytes_of_mut(&mut self.state)),
            "planes" => ("planes", bytes(self.planes)),
            "plane_master" => ("plane_master", bytes(self.plane_master)),
            "plane_m" => ("plane_m", bytes(self.plane_m)),
            "plane_v" => ("plane_v", bytes(self.plane_v)),
            "mlp" => ("mlp", bytes(self.mlp)),
            "mlp_m" => ("mlp_m", bytes(self.mlp_m)),
            "mlp_v" => ("mlp_v", bytes(self.mlp_v)),
            "occupancy_bits" => ("occupancy_bits", bytes(self.occupancy_bits)),
            "occupancy_density" => ("occupancy_density", bytes(self.occupancy_density)),
            "frame_meta" => ("frame_meta", bytes(self.frames.meta)),
            "frame_pixels" => ("frame_pixels", &mut *self.frames.pixels),
            "frame_masks" => ("frame_masks", &mut *self.frames.masks),
            "frame_params" => ("frame_params", bytes(self.frame_params)),
            "frame_m" => ("frame_m", bytes(self.frame_m)),
            "frame_v" => ("frame_v", bytes(self.frame_v)),
            _ => {
                return Err(Error::BadSection {
                    name: "unknown",
                    expected: 0,
                    got: data.len(),
                });
            }
        };
        if target.len() != data.len() {
            return Err(Error::BadSection {
                name,
                expected: target.len(),
                got: data.len(),
            });
        }
        if name == "frame_meta" {
            // Slot sizes index the pixel store: reject any that would not fit.
            let size = core::mem::size_of::<FrameMeta>();
            for raw in data.chunks_exact(size) {
                let meta: FrameMeta = bytemuck::pod_read_unaligned(raw);
                let pixels = meta.width as usize * meta.height as usize;
                if meta.occupied != 0
                    && (!meta.camera().is_valid()
                        || pixels > self.frames.max_pixels
                        || meta.width > u16::MAX as u32
                        || meta.height > u16::MAX as u32)
                {
                    return Err(Error::BadSection {
                        name,
                        expected: 0,
                        got: data.len(),
                    });
                }
            }
        }
        target.copy_from_slice(data);
        if name == "frame_meta" {
            self.frames.rebuild_occupied();
        }
        Ok(())
    }

    /// Fraction of occupancy cells marked occupied.
    pub fn occupancy_fraction(&self) -> f32 {
        let ones: u32 = self.occupancy_bits.iter().map(|w| w.count_ones()).sum();
        ones as f32 / self.config.occupancy_cells() as f32
    }

    /// The learnable parameters of a frame slot: appearance embedding, then pose correction.
    pub fn frame_parameters(&self, slot: usize) -> Option<&[f32]> {
        let n = self.config.frame_params();
        self.frame_params.get(slot * n..(slot + 1) * n)
    }

    /// Mean appearance embedding of the occupied frames (zeros without frames).
    pub fn mean_embedding(&self, out: &mut [f32]) {
        let n = self.config.frame_params();
        out.fill(0.0);
        let count = self.frames.len();
        for i in 0..count {
            let Some(slot) = self.frames.occupied_slot(i) else {
                continue;
            };
            for (o, v) in out.iter_mut().zip(&self.frame_params[slot * n..]) {
                *o += v / count as f32;
            }
        }
    }

    /// The read-only view of the model the chunks work with.
    fn shared<'s>(
        &'s self,
        embedding: Embedding<'s>,
        step: u32,
        jitter: bool,
        fit_embedding: bool,
    ) -> Shared<'s> {
        let pose_gradients =
            matches!(embedding, Embedding::PerFrame(_)) && self.config.pose_learns_at(step);
        Shared {
            config: &self.config,
            geometry: &self.geometry,
            layout: &self.layout,
            aabb: self.aabb,
            step_size: self.step_size,
            planes: self.planes,
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
            step,
            jitter,
            fit_embedding,
            pose_gradients,
        }
    }

    /// Put a frame into `slot`. Its embedding starts at the mean of the other frames'
    /// embeddings, its pose correction at zero, and its optimizer moments are cleared.
    pub fn set_frame(
        &mut self,
        slot: usize,
        camera: Camera,
        pose: Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<(), Error> {
        self.frames.set(slot, camera, pose, pixels, mask)?;
        let n = self.config.frame_params();
        let dim = self.config.embedding_dim as usize;
        let mut mean = [0.0f32; 128];
        let mut others = 0;
        for i in 0..self.frames.len() {
            let Some(s) = self.frames.occupied_slot(i).filter(|&s| s != slot) else {
                continue;
            };
            for (m, v) in mean.iter_mut().zip(&self.frame_params[s * n..s * n + dim]) {
                *m += v;
            }
            others += 1;
        }
        let params = &mut self.frame_params[slot * n..(slot + 1) * n];
        params.fill(0.0);
        if others > 0 {
            for (p, m) in params.iter_mut().zip(&mean[..dim]) {
                *p = m / others as f32;
            }
        }
        self.frame_m[slot * n..(slot + 1) * n].fill(0.0);
        self.frame_v[slot * n..(slot + 1) * n].fill(0.0);
        Ok(())
    }

    pub fn clear_frame(&mut self, slot: usize) {
        self.frames.clear(slot);
    }

    /// Stream a frame into the store. `arrival` counts the frames offered before it (it keys
    /// the policy's randomness and is kept with the slot). The frame is checked as `set_frame`
    /// checks it and refused if all black or all saturated; then the config's replacement
    /// policy (`stream.rs`) picks its slot or turns it away. A stored frame's per-frame state
    /// is reset as `set_frame` does.
    pub fn ingest_frame(
        &mut self,
        arrival: u32,
        camera: Camera,
        pose: Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<Ingested, Error> {
        self.frames.check(&camera, &pose, pixels, mask)?;
        admission::check_exposure(pixels)?;
        let incoming = Descriptor::new(&self.config, &pose, mean_brightness(pixels));
        let Some(slot) = admission::choose_slot(&self.config, &self.frames, &incoming, arrival)
        else {
            return Ok(Ingested::Rejected);
        };
        self.set_frame(slot, camera, pose, pixels, mask)?;
        self.frames.set_arrival(slot, arrival);
        Ok(Ingested::Stored { slot })
    }

    /// The ray through pixel `(i, j)` of a camera at `pose`: origin and unit direction.
    fn pixel_ray(camera: &Camera, pose: &Pose, i: u32, j: u32) -> (Vec3, Vec3) {
        let d = pose.rotation * camera.pixel_direction(i, j);
        (pose.center, d * (1.0 / libm::sqrtf(d.length_squared())))
    }

    /// Draw the batch: for each ray a frame (uniform over occupied slots) and a pixel.
    fn sample_rays(&mut self) -> Result<(), Error> {
        let count = self.frames.len() as u32;
        if count == 0 {
            return Err(Error::NoFrames);
        }
        let c = &self.config;
        let step = self.state.step as u64;
        for r in 0..c.rays_per_batch as usize {
            let bits = rng::hash(c.seed, stream::RAY_PICK, step, r as u64);
            let slot = self
                .frames
                .occupied_slot(rng::below(bits, count) as usize)
                .unwrap_or(0);
            let meta = self.frames.meta[slot];
            let camera = meta.camera();
            let bits = rng::hash(c.seed, stream::RAY_PICK, step, (r as u64) | 1 << 40);
            let in_foreground = c.foreground_fraction > 0.0
                && rng::unit_f32(rng::hash(
                    c.seed,
                    stream::RAY_PICK,
                    step,
                    (r as u64) | 2 << 40,
                )) < c.foreground_fraction;
            let pixel = if in_foreground {
                let [x0, x1, y0, y1] = meta.foreground_box();
                let i = x0 + rng::below(bits, x1 - x0);
                let j = y0 + rng::below(bits.rotate_right(32), y1 - y0);
                j * meta.width + i
            } else {
                rng::below(bits, camera.pixel_count() as u32)
            };
            let (i, j) = (pixel % meta.width, pixel / meta.width);
            let (o, d) = Self::pixel_ray(&camera, &meta.pose(), i, j);
            let n = c.frame_params();
            let correction = if c.pose_correction {
                PoseCorrection::from_params(
                    &self.frame_params[slot * n + c.embedding_dim as usize..(slot + 1) * n],
                )
            } else {
                PoseCorrection::default()
            };
            let px =
                &self.frames.pixels[(slot * self.frames.max_pixels + pixel as usize) * 3..][..3];
            // The mask as alpha: the pixel was composited onto `background` with it.
            let alpha = match self.frames.mask(slot) {
                Some(mask) if c.random_background => mask
                    .get(pixel as usize)
                    .map_or(1.0, |&m| m as f32 * (1.0 / 255.0)),
                _ => 1.0,
            };
            let background = if alpha < 1.0 {
                let bits = rng::hash(c.seed, stream::RAY_PICK, step, (r as u64) | 3 << 40);
                [0, 21, 42].map(|shift| ((bits >> shift) & 0x1f_ffff) as f32 / 0x1f_ffff as f32)
            } else {
                c.background
            };
            let ray = &mut self.rays[r * RAY_FLOATS..(r + 1) * RAY_FLOATS];
            let origin = correction.origin(o, c.pose_pivot_point());
            ray[..3].copy_from_slice(&origin.to_array());
            ray[3..6].copy_from_slice(&correction.rotate(d).to_array());
            for ch in 0..3 {
                ray[6 + ch] = px[ch] as f32 * (1.0 / 255.0)
                    + (1.0 - alpha) * (background[ch] - c.background[ch]);
            }
            ray[9..12].copy_from_slice(&d.to_array());
            ray[12..15].copy_from_slice(&background);
            self.ray_frames[r] = slot as u32;
        }
        Ok(())
    }

    /// One training step. Returns what it did; a step whose loss or gradients are not finite
    /// is counted and skipped, leaving the parameters untouched.
    pub fn step<E: Executor>(&mut self, executor: &E) -> Result<StepReport, Error> {
        self.forward_backward(executor)?;
        let report = self.reduce_and_apply();
        self.state.step += 1;
        if self.state.step.is_multiple_of(self.config.occupancy_every) {
            self.refresh_occupancy(executor);
        }
        Ok(report)
    }

    /// Sample this step's batch and run every chunk's forward and backward pass, leaving the
    /// gradients in the chunks' buffers.
    fn forward_backward<E: Executor>(&mut self, executor: &E) -> Result<(), Error> {
        self.sample_rays()?;
        let rays_per_chunk = self.config.rays_per_chunk();
        // The chunks are moved out while the shared view borrows the rest of the trainer.
        let mut chunks = core::mem::take(&mut self.chunks);
        for (i, chunk) in chunks.iter_mut().enumerate() {
            chunk.first_ray = i * rays_per_chunk;
            chunk.ray_count = rays_per_chunk;
        }
        let shared = self.shared(
            Embedding::PerFrame(self.frame_params),
            self.state.step,
            true,
            false,
        );
        executor.for_each(&mut chunks, |chunk| chunk.train(&shared));
        self.chunks = chunks;
        Ok(())
    }

    /// Sum the chunks' gradients in chunk order, check them, and apply Adam.
    fn reduce_and_apply(&mut self) -> StepReport {
        let (first, rest) = match self.chunks.split_first_mut() {
            Some(split) => split,
            None => return StepReport::default(),
        };
        let mut report = StepReport::default();
        let mut squared_error = 0.0f32;
        for chunk in core::iter::once(&*first).chain(rest.iter()) {
            squared_error += chunk.report.squared_error;
            report.rays += chunk.report.rays;
            report.samples += chunk.report.samples;
            report.samples_marched += chunk.report.marched;
            report.dropped_rays += chunk.report.dropped;
        }
        report.mse = if report.rays > 0 {
            squared_error / (3 * report.rays) as f32
        } else {
            0.0
        };
        let mut finite = squared_error.is_finite();

        for other in rest.iter_mut() {
            for (a, b) in first.mlp_grads.iter_mut().zip(other.mlp_grads.iter_mut()) {
                *a += *b;
                *b = 0.0;
            }
            for (a, b) in first
                .frame_grads
                .iter_mut()
                .zip(other.frame_grads.iter_mut())
            {
                *a += *b;
                *b = 0.0;
            }
        }
        finite &= first
            .mlp_grads
            .iter()
            .chain(first.frame_grads.iter())
            .all(|g| g.is_finite());
        let f = self.config.features as usize;
        for (w, union) in self.touched_union.iter_mut().enumerate() {
            let mut bits = first.touched[w];
            first.touched[w] = 0;
            for other in rest.iter_mut() {
                bits |= other.touched[w];
                other.touched[w] = 0;
            }
            *union = bits;
            while bits != 0 {
                let texel = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let range = texel * f..(texel + 1) * f;
                for other in rest.iter_mut() {
                    for (a, b) in first.plane_grads[range.clone()]
                        .iter_mut()
                        .zip(&mut other.plane_grads[range.clone()])
                    {
                        *a += *b;
                        *b = 0.0;
                    }
                }
                finite &= first.plane_grads[range].iter().all(|g| g.is_finite());
            }
        }

        let c = &self.config;
        if finite {
            self.state.updates += 1;
            let lr = optim::learning_rate(c, self.state.step);
            let adam = AdamStep::new(c, lr, self.state.updates);
            adam.apply(self.mlp, first.mlp_grads, self.mlp_m, self.mlp_v);
            let n = c.frame_params();
            let dim = c.embedding_dim as usize;
            let pose_adam = AdamStep::new(c, lr * c.pose_lr_factor, self.state.updates);
            for i in 0..self.frames.len() {
                let Some(slot) = self.frames.occupied_slot(i) else {
                    continue;
                };
                let range = slot * n..(slot + 1) * n;
                let (emb, pose) = (range.start..range.start + dim, range.start + dim..range.end);
                adam.apply(
                    &mut self.frame_params[emb.clone()],
                    &first.frame_grads[emb.clone()],
                    &mut self.frame_m[emb.clone()],
                    &mut self.frame_v[emb],
                );
                if c.pose_learns_at(self.state.step) {
                    pose_adam.apply(
                        &mut self.frame_params[pose.clone()],
                        &first.frame_grads[pose.clone()],
                        &mut self.frame_m[pose.clone()],
                        &mut self.frame_v[pose],
                    );
                }
            }
            let master = !self.plane_master.is_empty();
            for (w, &word) in self.touched_union.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let texel = w * 64 + bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    for i in texel * f..(texel + 1) * f {
                        let delta = adam.delta(
                            first.plane_grads[i],
                            &mut self.plane_m[i],
                            &mut self.plane_v[i],
                        );
                        let master = if master {
                            self.plane_master.get_mut(i)
                        } else {
                            None
                        };
                        optim::store_texel(
                            &mut self.planes[i],
                            master,
                            delta,
                            c.seed,
                            self.state.step,
                            i,
                        );
                    }
                }
            }
        } else {
            self.state.skipped += 1;
            report.skipped = true;
        }
        first.mlp_grads.fill(0.0);
        first.frame_grads.fill(0.0);
        for (w, &word) in self.touched_union.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let texel = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                first.plane_grads[texel * f..(texel + 1) * f].fill(0.0);
            }
        }
        report
    }

    /// Re-estimate every occupancy cell's density at a seeded point inside it, keep the
    /// decayed maximum, and mark cells whose opacity over one marching step exceeds the
    /// threshold as occupied.
    pub fn refresh_occupancy<E: Executor>(&mut self, executor: &E) {
        let c = self.config;
        let cells = c.occupancy_cells();
        let mut chunks = core::mem::take(&mut self.chunks);
        let density = core::mem::take(&mut self.occupancy_density);
        let per_chunk = cells.div_ceil(chunks.len());
        let mut jobs: heapless::Vec<(usize, &mut [f32], &mut Chunk<'a>), MAX_CHUNKS> =
            heapless::Vec::new();
        for (i, (part, chunk)) in density
            .chunks_mut(per_chunk)
            .zip(chunks.iter_mut())
            .enumerate()
        {
            let _ = jobs.push((i * per_chunk, part, chunk));
        }
        let shared = self.shared(Embedding::Fixed(&[]), self.state.refreshes, true, false);
        executor.for_each(&mut jobs, |(first_cell, part, chunk)| {
            chunk.refresh_cells(&shared, *first_cell, part)
        });
        drop(jobs);
        self.chunks = chunks;
        self.occupancy_density = density;
        // As in nerfacc, the threshold never exceeds the mean cell opacity, so a field whose
        // densities are all still low (early training) is not culled to nothing.
        let sum = self
            .occupancy_density
            .iter()
            .fold(0.0f64, |a, d| a + *d as f64);
        let mean = (sum / cells as f64) as f32 * self.step_size;
        let threshold = c.occupancy_threshold.min(mean);
        for (w, word) in self.occupancy_bits.iter_mut().enumerate() {
            let mut bits = 0u64;
            for (b, d) in self
                .occupancy_density
                .iter()
                .skip(w * 64)
                .take(64)
                .enumerate()
            {
                bits |= ((*d * self.step_size > threshold) as u64) << b;
            }
            *word = bits;
        }
        self.state.refreshes += 1;
    }

    /// Fit an appearance embedding to one image with the field frozen (the paper's and
    /// K-Planes' evaluation): `steps` Adam steps, each on a batch of rays through the pixels
    /// in columns `columns.0..columns.1` (the left half, in the paper). `embedding` holds the
    /// starting point (the mean training embedding) and receives the result. Returns the
    /// last step's mean squared error.
    #[allow(clippy::too_many_arguments)]
    pub fn fit_embedding<E: Executor>(
        &mut self,
        executor: &E,
        camera: &Camera,
        pose: &Pose,
        pixels: &[u8],
        columns: (u32, u32),
        steps: u32,
        embedding: &mut [f32],
    ) -> Result<f32, Error> {
        let c = self.config;
        let dim = c.embedding_dim as usize;
        if embedding.len() != dim {
            return Err(Error::BufferSize {
                what: "embedding",
                expected: dim,
                got: embedding.len(),
            });
        }
        if !camera.is_valid() || !pose.is_finite() {
            return Err(Error::InvalidFrame { field: "camera" });
        }
        if pixels.len() != camera.pixel_count() * 3 {
            return Err(Error::BufferSize {
                what: "pixels",
                expected: camera.pixel_count() * 3,
                got: pixels.len(),
            });
        }
        let (x0, x1) = (
            columns.0.min(camera.width as u32),
            columns.1.min(camera.width as u32),
        );
        if x0 >= x1 {
            return Err(Error::InvalidFrame { field: "columns" });
        }
        let (mut m, mut v) = ([0.0f32; 128], [0.0f32; 128]);
        let mut mse = 0.0;
        let rays_per_chunk = c.rays_per_chunk();
        for step in 0..steps {
            for r in 0..c.rays_per_batch as usize {
                let bits = rng::hash(c.seed, stream::FIT, step as u64, r as u64);
                let i = x0 + rng::below(bits, x1 - x0);
                let j = rng::below(bits.rotate_right(32), camera.height as u32);
                let (o, d) = Self::pixel_ray(camera, pose, i, j);
                let ray = &mut self.rays[r * RAY_FLOATS..(r + 1) * RAY_FLOATS];
                ray[..3].copy_from_slice(&o.to_array());
                ray[3..6].copy_from_slice(&d.to_array());
                let p = (j as usize * camera.width as usize + i as usize) * 3;
                for ch in 0..3 {
                    ray[6 + ch] = pixels[p + ch] as f32 * (1.0 / 255.0);
                }
                ray[9..12].copy_from_slice(&d.to_array());
                ray[12..15].copy_from_slice(&c.background);
            }
            let mut chunks = core::mem::take(&mut self.chunks);
            for (i, chunk) in chunks.iter_mut().enumerate() {
                chunk.first_ray = i * rays_per_chunk;
                chunk.ray_count = rays_per_chunk;
            }
            let shared = self.shared(Embedding::Fixed(embedding), step, true, true);
            executor.for_each(&mut chunks, |chunk| chunk.train(&shared));
            self.chunks = chunks;
            let mut grad = [0.0f32; 128];
            let (mut squared_error, mut rays) = (0.0f32, 0u32);
            for chunk in self.chunks.iter_mut() {
                for (g, d) in grad.iter_mut().zip(chunk.frame_grads[..dim].iter_mut()) {
                    *g += *d;
                    *d = 0.0;
                }
                chunk.mlp_grads.fill(0.0);
                squared_error += chunk.report.squared_error;
                rays += chunk.report.rays;
            }
            mse = squared_error / (3 * rays.max(1)) as f32;
            if !(mse.is_finite() && grad[..dim].iter().all(|g| g.is_finite())) {
                continue;
            }
            let adam = AdamStep::new(&c, FIT_LEARNING_RATE, step + 1);
            adam.apply(embedding, &grad[..dim], &mut m[..dim], &mut v[..dim]);
        }
        Ok(mse)
    }

    /// Render the image of `camera` at `pose` with a given appearance embedding (length
    /// `embedding_dim`) into `out` (RGB f32, row-major). Returns the mean samples per ray.
    pub fn render<E: Executor>(
        &mut self,
        executor: &E,
        camera: &Camera,
        pose: &Pose,
        embedding: &[f32],
        out: &mut [f32],
    ) -> Result<f32, Error> {
        let c = self.config;
        if !camera.is_valid() || !pose.is_finite() {
            return Err(Error::InvalidFrame { field: "camera" });
        }
        if embedding.len() != c.embedding_dim as usize {
            return Err(Error::BufferSize {
                what: "embedding",
                expected: c.embedding_dim as usize,
                got: embedding.len(),
            });
        }
        let pixels = camera.pixel_count();
        if out.len() != pixels * 3 {
            return Err(Error::BufferSize {
                what: "out",
                expected: pixels * 3,
                got: out.len(),
            });
        }
        let batch = c.rays_per_batch as usize;
        let mut samples = 0u64;
        for first in (0..pixels).step_by(batch) {
            let count = batch.min(pixels - first);
            for r in 0..count {
                let p = (first + r) as u32;
                let (o, d) = Self::pixel_ray(
                    camera,
                    pose,
                    p % camera.width as u32,
                    p / camera.width as u32,
                );
                self.rays[r * RAY_FLOATS..r * RAY_FLOATS + 3].copy_from_slice(&o.to_array());
                self.rays[r * RAY_FLOATS + 3..r * RAY_FLOATS + 6].copy_from_slice(&d.to_array());
            }
            let mut chunks = core::mem::take(&mut self.chunks);
            let per_chunk = count.div_ceil(chunks.len());
            for (i, chunk) in chunks.iter_mut().enumerate() {
                chunk.first_ray = (i * per_chunk).min(count);
                chunk.ray_count = per_chunk.min(count - chunk.first_ray);
            }
            let out_batch = &mut out[first * 3..(first + count) * 3];
            let mut jobs: heapless::Vec<(&mut Chunk<'a>, &mut [f32]), MAX_CHUNKS> =
                heapless::Vec::new();
            let mut rest = out_batch;
            for chunk in chunks.iter_mut() {
                let (mine, tail) = rest.split_at_mut(chunk.ray_count * 3);
                rest = tail;
                let _ = jobs.push((chunk, mine));
            }
            let shared = self.shared(Embedding::Fixed(embedding), 0, false, false);
            executor.for_each(&mut jobs, |(chunk, out)| chunk.render(&shared, out));
            samples += jobs
                .iter()
                .map(|(chunk, _)| chunk.report.samples as u64)
                .sum::<u64>();
            drop(jobs);
            self.chunks = chunks;
        }
        Ok(samples as f32 / pixels as f32)
    }
}

impl Chunk<'_> {
    fn ray(shared: &Shared<'_>, r: usize) -> (Vec3, Vec3) {
        let ray = &shared.rays[r * RAY_FLOATS..(r + 1) * RAY_FLOATS];
        (
            Vec3::new(ray[0], ray[1], ray[2]),
            Vec3::new(ray[3], ray[4], ray[5]),
        )
    }

    /// March rays `first..end` of the batch into the sample buffers, as many as fit.
    /// Returns the number of rays marched (the rest did not fit).
    fn march_rays(&mut self, shared: &Shared<'_>, first: usize, end: usize) -> usize {
        let c = shared.config;
        let capacity = self.positions.len();
        let mut n = 0usize;
        self.ray_start[0] = 0;
        for r in first..end {
            let (o, d) = Self::ray(shared, r);
            let jitter = if shared.jitter {
                rng::unit_f32(rng::hash(
                    c.seed,
                    stream::RAY_JITTER,
                    shared.step as u64,
                    r as u64,
                ))
            } else {
                0.5
            };
            let mut full = false;
            render::march(
                &shared.occupancy,
                o,
                d,
                shared.step_size,
                jitter,
                c.max_samples_per_ray as usize,
                |t| {
                    if n == capacity {
                        full = true;
                        return false;
                    }
                    self.positions[n] = (o + d * t).to_array();
                    self.sample_ray[n] = r as u32;
                    n += 1;
                    true
                },
            );
            if full {
                // Drop this ray's partial samples: the ray did not fit.
                return r - first;
            }
            self.ray_start[r - first + 1] = n as u32;
        }
        end - first
    }

    /// Density (and geometry features) of samples `0..n`.
    fn density_pass(&mut self, shared: &Shared<'_>, n: usize) {
        let c = shared.config;
        let geo_len = c.geo_features as usize;
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let rows = split_rows(c, self.activations);
            load_features(
                shared,
                &self.positions[base..base + lanes],
                rows.feats,
                self.plane_values,
            );
            density_rows(shared, rows.feats, rows.hidden, rows.density_out);
            for l in 0..lanes {
                self.sigma[base + l] = field::trunc_exp(rows.density_out[0][l]);
                for g in 0..geo_len {
                    self.geo[(base + l) * geo_len + g] = rows.density_out[1 + g][l];
                }
            }
        }
    }

    /// Cut each ray after the sample where its transmittance runs out, and compact the
    /// kept samples to the front. Returns the number kept.
    fn keep_visible(&mut self, shared: &Shared<'_>, rays: usize) -> usize {
        let c = shared.config;
        let geo_len = c.geo_features as usize;
        let mut write = 0usize;
        for r in 0..rays {
            let (start, end) = (self.ray_start[r] as usize, self.ray_start[r + 1] as usize);
            let kept = render::kept_samples(
                &self.sigma[start..end],
                shared.step_size,
                c.min_transmittance,
            );
            self.ray_start[r] = write as u32;
            if write != start {
                self.positions.copy_within(start..start + kept, write);
                self.sigma.copy_within(start..start + kept, write);
                self.sample_ray.copy_within(start..start + kept, write);
                self.geo
                    .copy_within(start * geo_len..(start + kept) * geo_len, write * geo_len);
            }
            write += kept;
        }
        self.ray_start[rays] = write as u32;
        write
    }

    /// Colours of samples `0..n`.
    fn colour_pass(&mut self, shared: &Shared<'_>, n: usize) {
        let c = shared.config;
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let rows = split_rows(c, self.activations);
            Self::load_colour_inputs(
                self.sample_ray,
                self.geo,
                shared,
                base,
                lanes,
                rows.colour_in,
            );
            colour_rows(shared, rows.colour_in, rows.colour1, rows.colour2, rows.rgb);
            for l in 0..lanes {
                self.rgb[base + l] = [rows.rgb[0][l], rows.rgb[1][l], rows.rgb[2][l]];
            }
        }
    }

    /// Colour-MLP inputs: view encoding, geometry features (stored by the density pass) and
    /// the appearance embedding. Unused lanes are zero.
    fn load_colour_inputs(
        sample_ray: &[u32],
        geo: &[f32],
        shared: &Shared<'_>,
        base: usize,
        lanes: usize,
        colour_in: &mut [Row],
    ) {
        let c = shared.config;
        let (sh_len, geo_len, dim) = (
            c.sh_values(),
            c.geo_features as usize,
            c.embedding_dim as usize,
        );
        for row in colour_in.iter_mut() {
            row.fill(0.0);
        }
        let mut sh = [0.0f32; 16];
        for l in 0..lanes {
            let s = base + l;
            let r = sample_ray[s] as usize;
            let (_, d) = Self::ray(shared, r);
            field::sh_forward(c.sh_degree as usize, d.to_array(), &mut sh);
            for k in 0..sh_len {
                colour_in[k][l] = sh[k];
            }
            for g in 0..geo_len {
                colour_in[sh_len + g][l] = geo[s * geo_len + g];
            }
            let emb = embedding_of(shared, r);
            for k in 0..dim {
                colour_in[sh_len + geo_len + k][l] = emb.get(k).copied().unwrap_or(0.0);
            }
        }
    }

    /// Forward, loss and backward for this chunk's rays of the batch.
    fn train(&mut self, shared: &Shared<'_>) {
        let c = shared.config;
        self.report = ChunkReport::default();
        let (first, end) = (self.first_ray, self.first_ray + self.ray_count);
        let rays = self.march_rays(shared, first, end);
        let marched = self.ray_start[rays] as usize;
        self.density_pass(shared, marched);
        let n = self.keep_visible(shared, rays);
        self.colour_pass(shared, n);

        // Loss: sum of squared errors over the batch, normalised by the batch capacity so the
        // gradient scale does not depend on how many rays fit.
        let norm = 1.0 / (3.0 * c.rays_per_batch as f32);
        let mut squared_error = 0.0f32;
        for r in 0..rays {
            let (start, end) = (self.ray_start[r] as usize, self.ray_start[r + 1] as usize);
            let ray = &shared.rays[(first + r) * RAY_FLOATS..(first + r + 1) * RAY_FLOATS];
            let (colour, _) = render::composite_forward(
                &self.sigma[start..end],
                &self.rgb[start..end],
                shared.step_size,
                [ray[12], ray[13], ray[14]],
            );
            let target = &ray[6..9];
            let mut d_colour = [0.0f32; 3];
            for ch in 0..3 {
                let e = colour[ch] - target[ch];
                squared_error += e * e;
                d_colour[ch] = 2.0 * e * norm;
            }
            render::composite_backward(
                &self.sigma[start..end],
                &self.rgb[start..end],
                shared.step_size,
                colour,
                d_colour,
                &mut self.d_sigma[start..end],
                &mut self.d_rgb[start..end],
            );
        }
        if shared.pose_gradients {
            self.ray_grads.fill(0.0);
        }
        self.backward(shared, n);
        if shared.pose_gradients {
            self.fold_ray_gradients(shared, rays);
        }
        self.report = ChunkReport {
            squared_error,
            rays: rays as u32,
            samples: n as u32,
            marched: marched as u32,
            dropped: (self.ray_count - rays) as u32,
        };
    }

    /// Move each ray's origin and direction gradients to its frame's pose correction.
    fn fold_ray_gradients(&mut self, shared: &Shared<'_>, rays: usize) {
        let c = shared.config;
        let n = c.frame_params();
        let dim = c.embedding_dim as usize;
        let Embedding::PerFrame(params) = shared.embedding else {
            return;
        };
        let pivot = c.pose_pivot_point();
        for r in 0..rays {
            let ray = self.first_ray + r;
            let slot = shared.ray_frames[ray] as usize;
            let g = &self.ray_grads[r * 6..r * 6 + 6];
            let correction = PoseCorrection::from_params(&params[slot * n + dim..(slot + 1) * n]);
            let label = &shared.rays[ray * RAY_FLOATS + 9..ray * RAY_FLOATS + 12];
            let mut d_v = correction.rotation_vjp(
                Vec3::new(label[0], label[1], label[2]),
                Vec3::new(g[3], g[4], g[5]),
            );
            // With a pivot the origin is p + R (c - p) + u: the rotation also moves it.
            if let (Some(p), Some(meta)) = (pivot, shared.frame_meta.get(slot)) {
                let arm = Vec3::from_array(meta.center) - p;
                d_v += correction.rotation_vjp(arm, Vec3::new(g[0], g[1], g[2]));
            }
            let dst = &mut self.frame_grads[slot * n + dim..(slot + 1) * n];
            for a in 0..3 {
                dst[a] += g[a];
                dst[3 + a] += d_v[a];
            }
        }
    }

    /// Recompute the field for samples `0..n` mini-batch by mini-batch and push the
    /// compositing gradients back to the MLPs, the planes and the embeddings.
    fn backward(&mut self, shared: &Shared<'_>, n: usize) {
        let c = shared.config;
        let layout = shared.layout;
        let (sh_len, geo_len, dim) = (
            c.sh_values(),
            c.geo_features as usize,
            c.embedding_dim as usize,
        );
        let features = c.density_inputs();
        let frame_params = c.frame_params();
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let act = split_rows(c, self.activations);
            let grad = split_rows(c, self.gradients);
            load_features(
                shared,
                &self.positions[base..base + lanes],
                act.feats,
                self.plane_values,
            );
            density_rows(shared, act.feats, act.hidden, act.density_out);
            Self::load_colour_inputs(
                self.sample_ray,
                self.geo,
                shared,
                base,
                lanes,
                act.colour_in,
            );
            colour_rows(shared, act.colour_in, act.colour1, act.colour2, act.rgb);

            // Output gradients; unused lanes stay zero and so contribute nothing.
            for row in grad.rgb.iter_mut().chain(grad.density_out.iter_mut()) {
                row.fill(0.0);
            }
            for l in 0..lanes {
                let s = base + l;
                for ch in 0..3 {
                    grad.rgb[ch][l] = self.d_rgb[s][ch] * field::sigmoid_grad(act.rgb[ch][l]);
                }
                // d sigma / d raw = trunc_exp'(raw), which is sigma itself below the clamp.
                grad.density_out[0][l] =
                    self.d_sigma[s] * field::trunc_exp_grad(act.density_out[0][l]);
            }
            let g = &mut *self.mlp_grads;
            let p = shared.mlp;
            let layer = |i: usize| layout.layers[i];
            let (l_out, l2, l1) = (
                layer(COLOUR_OUT),
                layer(COLOUR_HIDDEN2),
                layer(COLOUR_HIDDEN1),
            );
            backward_layer(
                p,
                g,
                l_out,
                act.colour2,
                grad.rgb,
                Some(grad.colour2),
                self.lane_major,
            );
            field::relu_backward(act.colour2, grad.colour2);
            backward_layer(
                p,
                g,
                l2,
                act.colour1,
                grad.colour2,
                Some(grad.colour1),
                self.lane_major,
            );
            field::relu_backward(act.colour1, grad.colour1);
            backward_layer(
                p,
                g,
                l1,
                act.colour_in,
                grad.colour1,
                Some(grad.colour_in),
                self.lane_major,
            );
            for gi in 0..geo_len {
                grad.density_out[1 + gi] = grad.colour_in[sh_len + gi];
            }
            if shared.fit_embedding {
                for (k, d) in self.frame_grads[..dim].iter_mut().enumerate() {
                    for l in 0..lanes {
                        *d += grad.colour_in[sh_len + geo_len + k][l];
                    }
                }
                continue;
            }
            if dim > 0 && matches!(shared.embedding, Embedding::PerFrame(_)) {
                for l in 0..lanes {
                    let slot = shared.ray_frames[self.sample_ray[base + l] as usize] as usize;
                    let dst = &mut self.frame_grads[slot * frame_params..slot * frame_params + dim];
                    for (k, d) in dst.iter_mut().enumerate() {
                        *d += grad.colour_in[sh_len + geo_len + k][l];
                    }
                }
            }
            backward_layer(
                p,
                g,
                layout.layers[DENSITY_OUT],
                act.hidden,
                grad.density_out,
                Some(grad.hidden),
                self.lane_major,
            );
            field::relu_backward(act.hidden, grad.hidden);
            backward_layer(
                p,
                g,
                layout.layers[DENSITY_HIDDEN],
                act.feats,
                grad.hidden,
                Some(grad.feats),
                self.lane_major,
            );

            let mut sink = PlaneGrads {
                grads: self.plane_grads,
                touched: self.touched,
            };
            let mut d_feat = [0.0f32; 4 * 64];
            let pose = shared.pose_gradients;
            let extent = shared.aabb.max - shared.aabb.min;
            for l in 0..lanes {
                for k in 0..features {
                    d_feat[k] = grad.feats[k][l];
                }
                let x = Vec3::from_array(self.positions[base + l]);
                let u = shared.aabb.normalise(x);
                let values = &self.plane_values[l * 3 * features..(l + 1) * 3 * features];
                let d_u = field::planes_backward(
                    shared.planes,
                    shared.geometry,
                    u,
                    values,
                    &d_feat[..features],
                    &mut sink,
                    pose,
                );
                if pose {
                    // x = o + t d: d loss / d o = d loss / d x, d loss / d d = t d loss / d x,
                    // plus the view encoding's gradient.
                    let r = self.sample_ray[base + l] as usize;
                    let (o, d) = Self::ray(shared, r);
                    let d_x = Vec3::from_array(d_u) / extent;
                    let mut d_sh = [0.0f32; 16];
                    for k in 0..sh_len {
                        d_sh[k] = grad.colour_in[k][l];
                    }
                    let d_view = Vec3::from_array(field::sh_backward(
                        c.sh_degree as usize,
                        d.to_array(),
                        &d_sh[..sh_len],
                    ));
                    let d_d = d_x * (x - o).dot(d) + d_view;
                    let g =
                        &mut self.ray_grads[(r - self.first_ray) * 6..(r - self.first_ray) * 6 + 6];
                    for a in 0..3 {
                        g[a] += d_x[a];
                        g[3 + a] += d_d[a];
                    }
                }
            }
        }
    }

    /// Render this chunk's rays (all of them, in as many passes as the sample capacity
    /// needs) into `out` (RGB per ray).
    fn render(&mut self, shared: &Shared<'_>, out: &mut [f32]) {
        let c = shared.config;
        self.report = ChunkReport::default();
        let (mut first, end) = (self.first_ray, self.first_ray + self.ray_count);
        while first < end {
            // The config guarantees max_samples_per_ray <= samples_per_chunk, so at least
            // one ray always fits and this loop advances.
            let rays = self.march_rays(shared, first, end).max(1);
            let marched = self.ray_start[rays] as usize;
            self.density_pass(shared, marched);
            let n = self.keep_visible(shared, rays);
            self.colour_pass(shared, n);
            for r in 0..rays {
                let (start, stop) = (self.ray_start[r] as usize, self.ray_start[r + 1] as usize);
                let (colour, _) = render::composite_forward(
                    &self.sigma[start..stop],
                    &self.rgb[start..stop],
                    shared.step_size,
                    c.background,
                );
                let o = (first - self.first_ray + r) * 3;
                out[o..o + 3].copy_from_slice(&colour);
            }
            self.report.samples += n as u32;
            first += rays;
        }
    }

    /// Update the running density of `cells` (starting at cell index `first_cell`).
    fn refresh_cells(&mut self, shared: &Shared<'_>, first_cell: usize, cells: &mut [f32]) {
        let c = shared.config;
        let res = c.occupancy_res as usize;
        let size = (shared.aabb.max - shared.aabb.min) / res as f32;
        for base in (0..cells.len()).step_by(LANES) {
            let lanes = LANES.min(cells.len() - base);
            let mut positions = [[0.0f32; 3]; LANES];
            for (l, p) in positions.iter_mut().enumerate().take(lanes) {
                let i = first_cell + base + l;
                let cell = Vec3::new(
                    (i % res) as f32,
                    ((i / res) % res) as f32,
                    (i / (res * res)) as f32,
                );
                let bits = rng::hash(c.seed, stream::OCCUPANCY, shared.step as u64, i as u64);
                let jitter = Vec3::new(
                    rng::unit_f32(bits),
                    rng::unit_f32(bits << 24),
                    rng::unit_f32(bits << 48),
                );
                *p = (shared.aabb.min + (cell + jitter) * size).to_array();
            }
            let rows = split_rows(c, self.activations);
            load_features(shared, &positions[..lanes], rows.feats, self.plane_values);
            density_rows(shared, rows.feats, rows.hidden, rows.density_out);
            for l in 0..lanes {
                let d = &mut cells[base + l];
                let sigma = field::trunc_exp(rows.density_out[0][l]);
                *d = (*d * c.occupancy_decay).max(sigma);
            }
        }
    }
}

/// The appearance embedding of the frame ray `r` was drawn from (or the fixed one).
fn embedding_of<'s>(shared: &Shared<'s>, r: usize) -> &'s [f32] {
    let c = shared.config;
    match shared.embedding {
        Embedding::Fixed(e) => e,
        Embedding::PerFrame(all) => {
            let slot = shared.ray_frames.get(r).copied().unwrap_or(0) as usize;
            let n = c.frame_params();
            all.get(slot * n..slot * n + c.embedding_dim as usize)
                .unwrap_or(&[])
        }
    }
}

/// Plane features of up to `LANES` positions into `feats` (unused lanes zero), and each
/// lane's per-plane values into `values` (lane-major).
fn load_features(
    shared: &Shared<'_>,
    positions: &[[f32; 3]],
    feats: &mut [Row],
    values: &mut [f32],
) {
    let n = feats.len();
    let mut out = [0.0f32; 4 * 64];
    for row in feats.iter_mut() {
        row.fill(0.0);
    }
    for (l, (p, values)) in positions
        .iter()
        .zip(values.chunks_exact_mut(3 * n))
        .enumerate()
    {
        let u = shared.aabb.normalise(Vec3::from_array(*p));
        field::planes_forward(shared.planes, shared.geometry, u, &mut out[..n], values);
        for k in 0..n {
            feats[k][l] = out[k];
        }
    }
}

fn density_rows(shared: &Shared<'_>, feats: &[Row], hidden: &mut [Row], out: &mut [Row]) {
    let (l1, l2) = (
        shared.layout.layers[DENSITY_HIDDEN],
        shared.layout.layers[DENSITY_OUT],
    );
    let p = shared.mlp;
    field::layer_forward(
        &p[l1.weights..l1.biases],
        &p[l1.biases..l1.biases + l1.outputs],
        feats,
        hidden,
    );
    field::relu_forward(hidden);
    field::layer_forward(
        &p[l2.weights..l2.biases],
        &p[l2.biases..l2.biases + l2.outputs],
        hidden,
        out,
    );
}

fn colour_rows(
    shared: &Shared<'_>,
    input: &[Row],
    h1: &mut [Row],
    h2: &mut [Row],
    rgb: &mut [Row],
) {
    let layers = &shared.layout.layers;
    let p = shared.mlp;
    let wb = |i: usize| {
        let l = layers[i];
        (&p[l.weights..l.biases], &p[l.biases..l.biases + l.outputs])
    };
    let (w, b) = wb(COLOUR_HIDDEN1);
    field::layer_forward(w, b, input, h1);
    field::relu_forward(h1);
    let (w, b) = wb(COLOUR_HIDDEN2);
    field::layer_forward(w, b, h1, h2);
    field::relu_forward(h2);
    let (w, b) = wb(COLOUR_OUT);
    field::layer_forward(w, b, h2, rgb);
    for row in rgb.iter_mut() {
        for v in row.iter_mut() {
            *v = field::sigmoid(*v);
        }
    }
}

/// Backward of one MLP layer: its slices of the parameters and of the chunk's gradients,
/// then `field::layer_backward`.
fn backward_layer(
    params: &[f32],
    grads: &mut [f32],
    l: crate::config::Layer,
    x: &[Row],
    dy: &[Row],
    dx: Option<&mut [Row]>,
    lane_major: &mut [f32],
) {
    let (dw, db) = grads[l.weights..l.biases + l.outputs].split_at_mut(l.biases - l.weights);
    field::layer_backward(&params[l.weights..l.biases], x, dy, dx, dw, db, lane_major);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PosePivot;
    use glam::Mat3;

    /// A small field with embeddings and pose correction, one 8x8 frame seen from inside the
    /// box (so every ray starts at t = 0 and the sample lattice does not move with the pose;
    /// the gradient treats sample distances as fixed, which is exact here).
    fn small_config() -> Config {
        let mut c = Config::DEFAULT;
        c.scales = 2;
        c.resolutions = [8, 16, 0, 0];
        c.features = 8;
        c.density_hidden = 16;
        c.geo_features = 7;
        c.colour_hidden = 16;
        c.sh_degree = 3;
        c.embedding_dim = 4;
        c.pose_correction = true;
        c.occupancy_res = 8;
        c.march_steps = 128;
        // 24 steps of 3 * sqrt(3) / 128 end before any ray from the camera below can leave
        // the box, so every ray keeps exactly 24 samples whatever the pose perturbation.
        c.max_samples_per_ray = 24;
        c.max_frames = 2;
        c.max_pixels_per_frame = 64;
        c.rays_per_batch = 32;
        c.chunks = 2;
        c.samples_per_chunk = 16 * 24;
        c
    }

    /// Loss of the current batch (sum of squared errors / (3 * rays_per_batch), the quantity
    /// the step differentiates) and the frame gradients of slot 0; no update is applied.
    fn loss_and_frame_gradients(trainer: &mut Trainer<'_>) -> (f64, [f32; 10]) {
        trainer.forward_backward(&Sequential).unwrap();
        let mut sse = 0.0f64;
        let mut grads = [0.0f32; 10];
        for chunk in trainer.chunks.iter_mut() {
            sse += chunk.report.squared_error as f64;
            for (g, c) in grads.iter_mut().zip(chunk.frame_grads.iter()) {
                *g += c;
            }
            chunk.frame_grads.fill(0.0);
            chunk.mlp_grads.fill(0.0);
            chunk.plane_grads.fill(0.0);
            chunk.touched.fill(0);
        }
        (sse / (3.0 * trainer.config.rays_per_batch as f64), grads)
    }

    #[test]
    fn embedding_and_pose_correction_gradients_match_finite_differences() {
        for pivot in [PosePivot::Camera, PosePivot::TargetOrigin] {
            let mut config = small_config();
            config.pose_pivot = pivot;
            check_frame_gradients(config);
        }
    }

    #[test]
    fn pose_corrections_neither_learn_nor_get_gradients_during_the_warm_up() {
        let mut config = small_config();
        config.pose_warmup_steps = 3;
        let mut arena = [0u8; 1 << 20];
        let arena = &mut arena[..MemoryPlan::new(&config).total];
        let mut trainer = Trainer::new(config, arena).unwrap();
        put_test_frame(&mut trainer);
        let dim = config.embedding_dim as usize;
        for _ in 0..3 {
            let (_, grads) = loss_and_frame_gradients(&mut trainer);
            assert!(grads[dim..].iter().all(|&g| g == 0.0), "{grads:?}");
            assert!(grads[..dim].iter().any(|&g| g != 0.0), "{grads:?}");
            trainer.step(&Sequential).unwrap();
            assert!(trainer.frame_params[dim..dim + 6].iter().all(|&p| p == 0.0));
        }
        let (_, grads) = loss_and_frame_gradients(&mut trainer);
        assert!(grads[dim..].iter().any(|&g| g != 0.0), "{grads:?}");
        trainer.step(&Sequential).unwrap();
        assert!(trainer.frame_params[dim..dim + 6].iter().any(|&p| p != 0.0));
    }

    #[test]
    fn masked_out_pixels_train_against_a_random_background_per_ray() {
        let mut config = small_config();
        config.background = [1.0; 3];
        config.rays_per_batch = 256;
        for random_background in [false, true] {
            config.random_background = random_background;
            let mut arena = [0u8; 1 << 20];
            let arena = &mut arena[..MemoryPlan::new(&config).total];
            let mut trainer = Trainer::new(config, arena).unwrap();
            let camera = test_camera();
            let pose = Pose {
                rotation: Mat3::IDENTITY,
                center: Vec3::new(0.0, 0.0, -3.0),
            };
            // Left half: the target (grey 100, mask 255); right half: white sky (mask 0).
            let mask: [u8; 64] = core::array::from_fn(|p| if p % 8 < 4 { 255 } else { 0 });
            let pixels: [u8; 192] =
                core::array::from_fn(|k| if mask[k / 3] != 0 { 100 } else { 255 });
            trainer
                .set_frame(0, camera, pose, &pixels, Some(&mask))
                .unwrap();
            trainer.sample_rays().unwrap();
            let (mut target_rays, mut sky_rays, mut lowest, mut highest) = (0, 0, 1.0f32, 0.0f32);
            for ray in trainer.rays.chunks_exact(RAY_FLOATS) {
                let (target, background) = (&ray[6..9], &ray[12..15]);
                if (target[0] - 100.0 / 255.0).abs() < 1e-6 {
                    // On the target the pixel is the target, whatever the background.
                    target_rays += 1;
                    assert_eq!(background, [1.0; 3]);
                } else {
                    // In the sky the target colour is the ray's background.
                    sky_rays += 1;
                    for (t, b) in target.iter().zip(background) {
                        assert!((t - b).abs() < 1e-6, "{target:?} {background:?}");
                    }
                    for &b in background {
                        assert!((0.0..=1.0).contains(&b));
                        lowest = lowest.min(b);
                        highest = highest.max(b);
                    }
                }
            }
            assert!(
                target_rays > 50 && sky_rays > 50,
                "{target_rays} {sky_rays}"
            );
            if random_background {
                assert!(lowest < 0.1 && highest > 0.9, "{lowest} {highest}");
            } else {
                assert_eq!((lowest, highest), (1.0, 1.0));
            }
        }
    }

    /// The 8x8 camera of the tests' frames.
    fn test_camera() -> Camera {
        Camera {
            width: 8,
            height: 8,
            fx: 6.0,
            fy: 6.0,
            cx: 4.0,
            cy: 4.0,
        }
    }

    /// One 8x8 frame of random pixels in slot 0, seen from inside the box.
    fn put_test_frame(trainer: &mut Trainer<'_>) {
        let camera = test_camera();
        let rotation = Mat3::from_rotation_y(0.4) * Mat3::from_rotation_x(-0.3);
        let pose = Pose {
            rotation,
            center: Vec3::new(0.2, -0.1, 0.3),
        };
        let mut rng = rng::Rng::new(11);
        let mut pixels = [0u8; 8 * 8 * 3];
        for p in pixels.iter_mut() {
            *p = (rng.uniform() * 255.0) as u8;
        }
        trainer.set_frame(0, camera, pose, &pixels, None).unwrap();
    }

    fn check_frame_gradients(config: Config) {
        let plan = MemoryPlan::new(&config);
        let mut arena = [0u8; 1 << 20];
        let Some(arena) = arena.get_mut(..plan.total) else {
            panic!("test arena too small: {}", plan.total)
        };
        let mut trainer = Trainer::new(config, arena).unwrap();
        put_test_frame(&mut trainer);
        let start = [0.3, -0.2, 0.1, 0.25, 0.01, -0.02, 0.015, 0.02, -0.01, 0.03];
        trainer.frame_params[..10].copy_from_slice(&start);
        let (_, analytic) = loss_and_frame_gradients(&mut trainer);
        for i in 0..10 {
            let h = if i < 4 { 1e-2 } else { 1e-3 };
            let mut at = |x: f32| {
                trainer.frame_params[i] = x;
                let (loss, _) = loss_and_frame_gradients(&mut trainer);
                trainer.frame_params[i] = start[i];
                loss
            };
            let numeric = ((at(start[i] + h) - at(start[i] - h)) / (2.0 * h as f64)) as f32;
            let scale = numeric.abs().max(analytic[i].abs()).max(1e-4);
            assert!(
                (analytic[i] - numeric).abs() / scale < 0.05,
                "{:?}, parameter {i}: analytic {} vs numeric {numeric}",
                config.pose_pivot,
                analytic[i]
            );
        }
    }
}
