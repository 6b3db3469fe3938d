//! The configuration of a field and its trainer, validated at construction, and the `const fn`
//! memory plan that sizes every part of the arena from it.

use crate::Error;

/// At most this many plane scales (K-Planes uses four).
pub const MAX_SCALES: usize = 4;
/// Widest hidden layer of the colour MLP (its per-ray terms live on the stack).
pub const MAX_COLOUR_HIDDEN: usize = 256;
/// Samples processed together through the MLPs (structure-of-arrays width).
pub const LANES: usize = 64;
/// At most this many chunks per batch.
pub const MAX_CHUNKS: usize = 16;
/// Every arena part starts on a multiple of this many bytes.
pub const PART_ALIGN: usize = 64;
/// Colour MLP output channels.
pub const RGB: usize = 3;
/// Per-frame pose-correction parameters: translation (3) and quaternion vector part (3).
pub const POSE_PARAMS: usize = 6;
/// The most pixels a ray reservoir keeps (`Config::ray_store`).
pub const MAX_RAY_STORE: u32 = 1 << 28;

/// How small plane updates survive storage in f16.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum TexelUpdate {
    /// Keep an f32 master copy of every texel; the f16 plane is its rounding.
    MasterCopy,
    /// Round each updated f32 value to one of its two f16 neighbours with probability given by
    /// the distance (seeded), so the expected stored value equals the exact update.
    StochasticRounding,
}

/// Which frame a full store gives up when a frame streams in (`Trainer::ingest_frame`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum Replacement {
    /// Every frame is admitted and replaces the oldest one.
    Fifo,
    /// Reservoir sampling weighted by novelty: a frame is admitted with probability
    /// `capacity / seen` scaled by how far it lies from the held frames (view direction and
    /// brightness), and replaces the most redundant held frame (see `replacement.rs`).
    Novelty,
    /// Every frame is admitted and replaces the most redundant held frame.
    Coverage,
}

/// The point a pose correction's rotation turns the camera about. Either way a corrected frame
/// shoots its rays from origin + dt with directions rotated by dq in the world frame; the
/// pivot only decides which coordinates the optimiser moves (the same corrected poses are
/// reachable), so it changes the conditioning, not the model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum PosePivot {
    /// The learned translation is dt itself: turning the directions leaves the camera centre
    /// where it is.
    Camera,
    /// The rotation turns the camera about the world origin (the target's origin, which the
    /// labels' relative position points to), and the learned translation u moves it on top:
    /// dt = u + (R - I) c. This is the paper's update of a relative-pose label,
    /// q~ = dq q^ and t~ = t^ + dt (with dt in the world frame). An attitude error at a known
    /// target position, which moves the camera on a sphere about the target, is then one
    /// coordinate (the rotation) instead of a balance between the rotation and dt, each of
    /// which alone shifts the image by pixels.
    TargetOrigin,
}

/// Most rays one training step may sample (2^20, 104 MiB of the arena): a config with 2^24
/// rays took more than 30 s per step on a small machine (issue 42). A stop request no longer
/// waits for a whole step ([`crate::Trainer::step_or_stop`] hears it between a chunk's
/// passes), but the bound keeps a config's arena and a step's time within reason.
pub const MAX_RAYS_PER_BATCH: u32 = 1 << 20;

/// Everything that decides what the trainer computes. With the `serde` feature it reads from
/// and writes to config files (every field named, no others) and checkpoints; checkpoints
/// encode the fields by position, so their order is part of the checkpoint format.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(deny_unknown_fields)
)]
pub struct Config {
    // --- field ---
    /// Number of plane scales in use (1..=MAX_SCALES).
    pub scales: u8,
    /// Plane side length per scale, in texels (2..=1024).
    pub resolutions: [u16; MAX_SCALES],
    /// Features per plane texel (per scale): 8, 16, 32 or 64.
    pub features: u16,
    /// Hidden width of the density MLP.
    pub density_hidden: u16,
    /// Geometry features the density MLP hands to the colour MLP.
    pub geo_features: u16,
    /// Width of the colour MLP's two hidden layers.
    pub colour_hidden: u16,
    /// Spherical-harmonics bands of the view encoding (1..=4): `b` bands are the degrees
    /// 0..b, giving b² values.
    pub sh_bands: u8,
    /// Per-frame appearance embedding fed to the colour MLP (0 disables it).
    pub embedding_dim: u16,
    /// Planes start uniform in [init_low, init_high] (K-Planes: 0.1, 0.5).
    pub init_low: f32,
    /// Upper bound of the uniform plane initialisation.
    pub init_high: f32,

    // --- scene and rendering ---
    /// Lowest corner of the scene box in world coordinates; rays are marched inside the box.
    pub aabb_min: [f32; 3],
    /// Highest corner of the scene box in world coordinates (above `aabb_min` on every axis).
    pub aabb_max: [f32; 3],
    /// Colour behind the scene, composited where rays leave the box.
    pub background: [f32; 3],
    /// Train the rays of frames that have a foreground mask against a random background
    /// colour per ray (the pixel recomposited from `background` onto it with the mask as
    /// alpha), as instant-ngp does. The field must then make the target opaque wherever the
    /// mask says it is, even where it is as dark as the sky (unlit sides), and empty
    /// elsewhere; with one fixed background colour such regions are free to stay a haze.
    /// Frames without a mask, and rendering, use `background`.
    pub random_background: bool,
    /// Occupancy grid cells per side.
    pub occupancy_res: u16,
    /// Refresh the occupancy grid every this many steps.
    pub occupancy_every: u32,
    /// A cell stays occupied while its (decayed, max-pooled) density times the marching step
    /// (its opacity over one step) exceeds this.
    pub occupancy_threshold: f32,
    /// Per-refresh decay of the running density of each cell.
    pub occupancy_decay: f32,
    /// Ray-marching steps across the box diagonal (sets the sample spacing).
    pub march_steps: u16,
    /// Ray-marching stops after this many samples per ray.
    pub max_samples_per_ray: u16,
    /// A ray stops once its transmittance falls below this.
    pub min_transmittance: f32,

    // --- capacities ---
    /// Frame slots in the arena: the most frames held at once.
    pub max_frames: u16,
    /// What a full frame store does with a streamed-in frame.
    pub replacement: Replacement,
    /// Pixel capacity of one frame slot (width * height of the largest frame).
    pub max_pixels_per_frame: u32,
    /// 0: each frame slot keeps its whole frame. N > 0: the slots keep only camera, label and
    /// learnable parameters, and N pixels of all the frames stored (4 bytes each) are kept
    /// in one reservoir that every frame shares alike (`frames.rs`), so `max_frames` can be
    /// the most frames a stream remembers rather than the most it holds whole. At most
    /// 2^28.
    pub ray_store: u32,
    /// Rays sampled per training step: a multiple of `chunks`, at most 1048576 (each ray
    /// takes 104 bytes of the arena: the ray batch and the chunks' per-ray buffers; a stop
    /// request is heard between a chunk's passes, within a step).
    pub rays_per_batch: u32,
    /// Fraction of the rays drawn inside their frame's foreground box (the mask's box, or the
    /// box of pixels brighter than the sky); the rest cover the whole image, so empty space
    /// stays empty. 0 samples every pixel alike.
    pub foreground_fraction: f32,
    /// Draw each training ray's frame in proportion to that frame's running loss (the mean
    /// squared error of its recent training rays, relative to the largest, at least 1/16)
    /// instead of uniformly: steps go where the field is still wrong, such as the views a
    /// stream took in last. A new frame starts at the largest running loss.
    pub loss_weighted_frames: bool,
    /// The batch is cut into this many equal chunks, each with its own buffers; the host
    /// runs chunks on threads, and results never depend on which thread ran which chunk.
    pub chunks: u8,
    /// Sample capacity of one pass of a chunk: a chunk trains (and renders) its rays in as
    /// many passes as their samples need, each pass as many whole rays as fit. Training
    /// keeps every activation of a pass for the backward pass (about 1.7 KiB per sample with
    /// the default MLPs), so a pass should fit in the L2 cache.
    pub samples_per_chunk: u32,

    // --- optimisation ---
    /// Training steps of the learning-rate schedule (the cosine decay ends here).
    pub steps: u32,
    /// Steps of linear learning-rate warmup before the cosine decay.
    pub warmup_steps: u32,
    /// Peak learning rate of the field (planes and MLP), reached after the warmup.
    pub learning_rate: f32,
    /// The cosine schedule ends at learning_rate * final_lr_factor.
    pub final_lr_factor: f32,
    /// Fraction of the steps after the warm-up that keep the peak rate before the cosine
    /// decay starts, in [0, 1): 0 decays from the warm-up on; a stream sets it so that the
    /// frames arriving late are still learned at a useful rate.
    pub lr_decay_start: f32,
    /// Adam's decay of the first-moment (mean gradient) estimate, in [0, 1).
    pub adam_beta1: f32,
    /// Adam's decay of the second-moment (squared gradient) estimate, in [0, 1).
    pub adam_beta2: f32,
    /// Adam's denominator guard, added to the root of the second moment.
    pub adam_eps: f32,
    /// Weight of K-Planes' total-variation regulariser on the planes (their
    /// `plane_tv_weight`, 1e-4 to 2e-4 there; 0 turns it off): the mean squared difference
    /// of neighbouring texels, per plane, summed over planes and scales. Applied to the
    /// texels a step touches (the others are left as they are, as Adam leaves them).
    pub plane_tv_weight: f32,
    /// How Adam updates reach the f16 plane texels.
    pub texel_update: TexelUpdate,
    /// Pose corrections learn at pose_lr_factor * the field's rate (the paper's beta <= 0.01).
    pub pose_lr_factor: f32,
    /// Learn a pose correction per frame.
    pub pose_correction: bool,
    /// What the pose correction's rotation turns the camera about.
    pub pose_pivot: PosePivot,
    /// Pose corrections stay at zero for this many steps, until the field has formed (early
    /// gradients of a blurry field push poses anywhere).
    pub pose_warmup_steps: u32,
    /// The labels' stated attitude noise (the RMS angle of their rotation error, degrees):
    /// a Gaussian prior holds each corrected pose toward its label, in training and in the
    /// refinement (maximum a posteriori instead of free drift; 0: no prior).
    pub pose_prior_rotation_deg: f32,
    /// The labels' stated position noise (1 sigma per axis, world units) of the target's
    /// position seen from the camera (a relative pose label's translation): the prior's
    /// position part (0: no prior).
    pub pose_prior_position: f32,
    /// Levenberg-Marquardt iterations per frame of the pose refinement with the field frozen
    /// (`Trainer::refine_pose`) after the last step. With 0 the trained corrections are kept
    /// and only their uncertainty is computed: at a few hundred rays per frame the steps
    /// fit the field's own errors about as often as the pose (docs/book/src/pose-correction.md).
    pub pose_refine_iterations: u32,
    /// Rays per frame of each refinement evaluation (run in batches of `rays_per_batch`).
    pub pose_refine_rays: u32,
    /// BARF's coarse-to-fine schedule over the plane scales (0 turns it off): the first scale
    /// is on from the start and each finer one fades in, one after another, over this many
    /// steps, so early pose gradients see a smooth field. Scale `s >= 1` is weighted by
    /// `(1 - cos(pi * clamp(a - (s - 1), 0, 1))) / 2` with `a = (scales - 1) * step /
    /// coarse_to_fine_steps`; every pass (training, occupancy, rendering) uses the weights
    /// of the trainer's current step.
    pub coarse_to_fine_steps: u32,
    /// Seed of every random draw (initialisation, ray picks, jitter, rounding, admission).
    pub seed: u64,
}

impl Config {
    /// Whether the pose corrections learn at training step `step` (they are on and past
    /// their warm-up).
    pub const fn pose_learns_at(&self, step: u32) -> bool {
        self.pose_correction && step >= self.pose_warmup_steps
    }

    /// Weight of each plane scale's features at training step `step` (all 1 without the
    /// coarse-to-fine schedule or after it; see `coarse_to_fine_steps`).
    pub fn scale_weights_at(&self, step: u32) -> [f32; MAX_SCALES] {
        let mut weights = [1.0f32; MAX_SCALES];
        if self.coarse_to_fine_steps == 0 || step >= self.coarse_to_fine_steps {
            return weights;
        }
        let a = (self.scales as f32 - 1.0) * step as f32 / self.coarse_to_fine_steps as f32;
        for (s, w) in weights.iter_mut().enumerate().skip(1) {
            let x = (a - (s as f32 - 1.0)).clamp(0.0, 1.0);
            *w = 0.5 * (1.0 - libm::cosf(core::f32::consts::PI * x));
        }
        weights
    }

    /// The point pose corrections turn cameras about, if not their own centres.
    pub fn pose_pivot_point(&self) -> Option<glam::Vec3> {
        match self.pose_pivot {
            PosePivot::Camera => None,
            PosePivot::TargetOrigin => Some(glam::Vec3::ZERO),
        }
    }

    /// A CPU-sized K-Planes model for a NeRF-synthetic scene at about 100 px.
    pub const DEFAULT: Config = Config {
        scales: 3,
        resolutions: [32, 64, 128, 0],
        features: 16,
        density_hidden: 64,
        geo_features: 15,
        colour_hidden: 64,
        sh_bands: 4,
        embedding_dim: 0,
        init_low: 0.1,
        init_high: 0.5,
        aabb_min: [-1.5; 3],
        aabb_max: [1.5; 3],
        background: [1.0; 3],
        random_background: false,
        occupancy_res: 64,
        occupancy_every: 16,
        occupancy_threshold: 0.01,
        occupancy_decay: 0.95,
        march_steps: 512,
        max_samples_per_ray: 256,
        min_transmittance: 1e-4,
        max_frames: 128,
        replacement: Replacement::Fifo,
        max_pixels_per_frame: 128 * 128,
        ray_store: 0,
        rays_per_batch: 4096,
        foreground_fraction: 0.0,
        loss_weighted_frames: false,
        chunks: 4,
        samples_per_chunk: 1024,
        steps: 3000,
        warmup_steps: 128,
        learning_rate: 0.01,
        final_lr_factor: 0.03,
        lr_decay_start: 0.0,
        adam_beta1: 0.9,
        adam_beta2: 0.99,
        adam_eps: 1e-15,
        plane_tv_weight: 0.0,
        texel_update: TexelUpdate::MasterCopy,
        pose_lr_factor: 0.01,
        pose_correction: false,
        pose_pivot: PosePivot::Camera,
        pose_warmup_steps: 0,
        pose_prior_rotation_deg: 0.0,
        pose_prior_position: 0.0,
        pose_refine_iterations: 0,
        pose_refine_rays: 512,
        coarse_to_fine_steps: 0,
        seed: 0,
    };

    /// The default for a spacecraft against the black sky (the simulator's presets, SPEED+,
    /// SHIRT): three quarters of the rays on the target's box, pose corrections that turn
    /// cameras about the target and start once the field has formed (300 steps), and a colour
    /// MLP twice as wide (the lamp's direction changes the shading, which the embedding can
    /// only express through it: +0.4 dB held-out on `lightbox` for 1.7x the training time),
    /// and 1536 rays per step: rays through the target march about 40 samples, twice lego's
    /// (on `lightbox`, 500 steps: 1536 rays 30.40 dB in 33.6 s, 2048 rays 30.04 in 48.3 s,
    /// 4096 rays 30.36 in 79.1 s; README). Measured against DEFAULT in the README.
    pub const SPACECRAFT: Config = Config {
        colour_hidden: 128,
        rays_per_batch: 1536,
        foreground_fraction: 0.75,
        pose_pivot: PosePivot::TargetOrigin,
        pose_warmup_steps: 300,
        ..Config::DEFAULT
    };

    /// The length that is one unit for the field's density (a sample's optical depth is
    /// `sigma * step / length_unit`) and for the pose corrections' learned translation: the
    /// scene box's largest half-side over 1.5, so the default box `[-1.5, 1.5]³` (NeRF
    /// synthetic's scale, which K-Planes' initialisation and rates were tuned at) has unit 1.
    /// Training then depends on the scene's shape, not its size: the same images with the
    /// labels and the box scaled by any factor train alike.
    pub fn length_unit(&self) -> f32 {
        let mut half = 0.0f32;
        for a in 0..3 {
            half = half.max(0.5 * (self.aabb_max[a] - self.aabb_min[a]));
        }
        half / 1.5
    }

    /// Inputs of the density MLP: the plane features of every scale.
    pub const fn density_inputs(&self) -> usize {
        self.scales as usize * self.features as usize
    }
    /// Outputs of the density MLP: the density and the geometry features.
    pub const fn density_outputs(&self) -> usize {
        1 + self.geo_features as usize
    }
    /// Spherical-harmonics values of the view encoding (`sh_bands²`).
    pub const fn sh_values(&self) -> usize {
        self.sh_bands as usize * self.sh_bands as usize
    }
    /// Inputs of the colour MLP: SH values, geometry features and the appearance embedding.
    pub const fn colour_inputs(&self) -> usize {
        self.sh_values() + self.geo_features as usize + self.embedding_dim as usize
    }
    /// Texels of all planes (3 per scale).
    pub const fn texels(&self) -> usize {
        let mut n = 0;
        let mut s = 0;
        while s < self.scales as usize {
            let r = self.resolutions[s] as usize;
            n += 3 * r * r;
            s += 1;
        }
        n
    }
    /// Learnable plane values: texels times features per texel.
    pub const fn plane_params(&self) -> usize {
        self.texels() * self.features as usize
    }
    /// Rays of one chunk (`rays_per_batch / chunks`).
    pub const fn rays_per_chunk(&self) -> usize {
        self.rays_per_batch as usize / self.chunks as usize
    }
    /// Cells of the occupancy grid (`occupancy_res³`).
    pub const fn occupancy_cells(&self) -> usize {
        let r = self.occupancy_res as usize;
        r * r * r
    }
    /// Bytes of the frame store's pixels and of its masks: whole frames, or the ray
    /// reservoir (no separate masks).
    pub const fn frame_pixel_bytes(&self) -> (usize, usize) {
        let frames = self.max_frames as usize;
        if self.ray_store > 0 {
            (self.ray_store as usize * crate::frames::RAY_ENTRY_BYTES, 0)
        } else {
            (
                frames * self.max_pixels_per_frame as usize * 3,
                frames * self.max_pixels_per_frame as usize,
            )
        }
    }
    /// Entries of the ray reservoir's foreground part: `foreground_fraction` of it.
    pub fn foreground_rays(&self) -> usize {
        (self.ray_store as f32 * self.foreground_fraction.clamp(0.0, 1.0)) as usize
    }
    /// Per-frame learnable parameters: appearance embedding and pose correction.
    pub const fn frame_params(&self) -> usize {
        self.embedding_dim as usize + POSE_PARAMS
    }
    /// Where each MLP layer's weights and biases sit in the parameter vector.
    pub const fn mlp(&self) -> MlpLayout {
        MlpLayout::new(self)
    }

    /// Check every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), Error> {
        let bad = |field: &'static str| Err(Error::InvalidConfig { field });
        if self.scales == 0 || self.scales as usize > MAX_SCALES {
            return bad("scales");
        }
        for s in 0..self.scales as usize {
            if !(2..=1024).contains(&self.resolutions[s]) {
                return bad("resolutions");
            }
        }
        if !matches!(self.features, 8 | 16 | 32 | 64) {
            return bad("features");
        }
        if !(1..=256).contains(&self.density_hidden) {
            return bad("density_hidden");
        }
        if !(1..=64).contains(&self.geo_features) {
            return bad("geo_features");
        }
        if !(1..=MAX_COLOUR_HIDDEN as u16).contains(&self.colour_hidden) {
            return bad("colour_hidden");
        }
        if !(1..=4).contains(&self.sh_bands) {
            return bad("sh_bands");
        }
        if self.embedding_dim > 128 {
            return bad("embedding_dim");
        }
        if !(self.init_low.is_finite()
            && self.init_high.is_finite()
            && self.init_low <= self.init_high)
        {
            return bad("init_low");
        }
        for a in 0..3 {
            if !(self.aabb_min[a].is_finite() && self.aabb_max[a].is_finite())
                || self.aabb_max[a] <= self.aabb_min[a]
            {
                return bad("aabb");
            }
            if !(0.0..=1.0).contains(&self.background[a]) {
                return bad("background");
            }
        }
        if !(4..=512).contains(&self.occupancy_res) {
            return bad("occupancy_res");
        }
        if self.occupancy_every == 0 {
            return bad("occupancy_every");
        }
        if !(self.occupancy_threshold.is_finite() && self.occupancy_threshold >= 0.0) {
            return bad("occupancy_threshold");
        }
        if !(self.occupancy_decay.is_finite() && (0.0..=1.0).contains(&self.occupancy_decay)) {
            return bad("occupancy_decay");
        }
        if !(8..=8192).contains(&self.march_steps) {
            return bad("march_steps");
        }
        if self.max_samples_per_ray == 0 || self.max_samples_per_ray as u32 > self.samples_per_chunk
        {
            return bad("max_samples_per_ray");
        }
        if !(self.min_transmittance.is_finite() && (0.0..1.0).contains(&self.min_transmittance)) {
            return bad("min_transmittance");
        }
        if self.max_frames == 0 {
            return bad("max_frames");
        }
        if self.max_pixels_per_frame == 0 || self.max_pixels_per_frame > (1 << 26) {
            return bad("max_pixels_per_frame");
        }
        if self.ray_store > MAX_RAY_STORE {
            return bad("ray_store");
        }
        if self.chunks == 0 || self.chunks as usize > MAX_CHUNKS {
            return bad("chunks");
        }
        if self.rays_per_batch == 0
            || !self.rays_per_batch.is_multiple_of(self.chunks as u32)
            || self.rays_per_batch > MAX_RAYS_PER_BATCH
        {
            return bad("rays_per_batch");
        }
        if !(self.foreground_fraction.is_finite()
            && (0.0..=1.0).contains(&self.foreground_fraction))
        {
            return bad("foreground_fraction");
        }
        if (self.samples_per_chunk as usize) < LANES || self.samples_per_chunk > (1 << 20) {
            return bad("samples_per_chunk");
        }
        if self.steps == 0 {
            return bad("steps");
        }
        if self.warmup_steps > self.steps {
            return bad("warmup_steps");
        }
        if !(self.learning_rate.is_finite()
            && self.learning_rate > 0.0
            && self.learning_rate <= 1.0)
        {
            return bad("learning_rate");
        }
        if !(self.final_lr_factor.is_finite() && (0.0..=1.0).contains(&self.final_lr_factor)) {
            return bad("final_lr_factor");
        }
        if !(self.lr_decay_start.is_finite() && (0.0..1.0).contains(&self.lr_decay_start)) {
            return bad("lr_decay_start");
        }
        if !(self.adam_beta1.is_finite() && (0.0..1.0).contains(&self.adam_beta1)) {
            return bad("adam_beta1");
        }
        if !(self.adam_beta2.is_finite() && (0.0..1.0).contains(&self.adam_beta2)) {
            return bad("adam_beta2");
        }
        if !(self.adam_eps.is_finite() && self.adam_eps > 0.0) {
            return bad("adam_eps");
        }
        if !(self.plane_tv_weight.is_finite() && (0.0..=1.0).contains(&self.plane_tv_weight)) {
            return bad("plane_tv_weight");
        }
        if !(self.pose_lr_factor.is_finite() && (0.0..=0.01).contains(&self.pose_lr_factor)) {
            return bad("pose_lr_factor");
        }
        if !(self.pose_prior_rotation_deg.is_finite()
            && (0.0..=180.0).contains(&self.pose_prior_rotation_deg))
        {
            return bad("pose_prior_rotation_deg");
        }
        if !(self.pose_prior_position.is_finite()
            && (0.0..=1e6).contains(&self.pose_prior_position))
        {
            return bad("pose_prior_position");
        }
        if self.pose_refine_iterations > 100 {
            return bad("pose_refine_iterations");
        }
        if self.pose_refine_rays == 0 || self.pose_refine_rays > (1 << 24) {
            return bad("pose_refine_rays");
        }
        if self.coarse_to_fine_steps > self.steps {
            return bad("coarse_to_fine_steps");
        }
        Ok(())
    }
}

/// Offsets of each layer's weights and biases in the one f32 vector of MLP parameters.
/// Weights are stored input-major: `w[k * outputs + n]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpLayout {
    /// The five layers in evaluation order, indexed by `DENSITY_HIDDEN` .. `COLOUR_OUT`.
    pub layers: [Layer; 5],
    /// Length of the parameter vector (all weights and biases).
    pub total: usize,
}

/// One fully connected layer of an MLP: its shape and where its parameters start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layer {
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
    /// Offset of the first of its `inputs * outputs` weights in the parameter vector.
    pub weights: usize,
    /// Offset of the first of its `outputs` biases in the parameter vector.
    pub biases: usize,
}

/// Layer index in `MlpLayout::layers`: the density MLP's hidden layer.
pub const DENSITY_HIDDEN: usize = 0;
/// Layer index: the density MLP's output (density and geometry features).
pub const DENSITY_OUT: usize = 1;
/// Layer index: the colour MLP's first hidden layer.
pub const COLOUR_HIDDEN1: usize = 2;
/// Layer index: the colour MLP's second hidden layer.
pub const COLOUR_HIDDEN2: usize = 3;
/// Layer index: the colour MLP's output (RGB).
pub const COLOUR_OUT: usize = 4;

impl MlpLayout {
    /// Lay out the five layers of `c`'s MLPs back to back, each as weights then biases.
    pub const fn new(c: &Config) -> MlpLayout {
        let dims = [
            (c.density_inputs(), c.density_hidden as usize),
            (c.density_hidden as usize, c.density_outputs()),
            (c.colour_inputs(), c.colour_hidden as usize),
            (c.colour_hidden as usize, c.colour_hidden as usize),
            (c.colour_hidden as usize, RGB),
        ];
        let empty = Layer {
            inputs: 0,
            outputs: 0,
            weights: 0,
            biases: 0,
        };
        let mut layers = [empty; 5];
        let mut at = 0;
        let mut i = 0;
        while i < 5 {
            let (inputs, outputs) = dims[i];
            layers[i] = Layer {
                inputs,
                outputs,
                weights: at,
                biases: at + inputs * outputs,
            };
            at += inputs * outputs + outputs;
            i += 1;
        }
        MlpLayout { layers, total: at }
    }
}

/// Bytes of each part of the arena for a config. Parts are laid out in this order, each
/// starting on a `PART_ALIGN` boundary; `total` adds the slack to align an arbitrary buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MemoryPlan {
    /// f16 texels of every plane.
    pub planes: usize,
    /// f32 master texels (MasterCopy only).
    pub plane_master: usize,
    /// Adam first and second moments of the texels.
    pub plane_moments: usize,
    /// Per-chunk f32 texel gradients and touched-texel bitmaps.
    pub plane_grads: usize,
    /// MLP weights, their Adam moments and per-chunk gradients.
    pub mlp: usize,
    /// Occupancy bitfield and running density per cell.
    pub occupancy: usize,
    /// Frame slots: pixels, masks, cameras, pose labels, per-frame parameters and moments.
    pub frames: usize,
    /// The ray batch: origins, directions, targets and frame indices.
    pub ray_batch: usize,
    /// Per-chunk sample buffers, per-ray results and MLP activation scratch.
    pub samples: usize,
    /// Sum of the aligned parts plus `PART_ALIGN` bytes of slack to align the buffer's start.
    pub total: usize,
}

const fn align(n: usize) -> usize {
    n.div_ceil(PART_ALIGN) * PART_ALIGN
}

/// Widest layer output (or the density MLP's inputs, if more), rounded up to a multiple of 8:
/// the lane-major scratch, which holds a layer's output gradients and the planes' feature
/// gradients.
pub const fn widest_layer(c: &Config) -> usize {
    let mut w = c.density_hidden as usize;
    if c.density_inputs() > w {
        w = c.density_inputs();
    }
    if c.density_outputs() > w {
        w = c.density_outputs();
    }
    if c.colour_hidden as usize > w {
        w = c.colour_hidden as usize;
    }
    w.div_ceil(8) * 8
}

/// Activation rows of the density MLP per mini-batch: plane features, hidden layer, outputs.
pub const fn density_activation_rows(c: &Config) -> usize {
    c.density_inputs() + c.density_hidden as usize + c.density_outputs()
}

/// Activation rows of the colour MLP per mini-batch. Of its inputs only the geometry
/// features vary per sample; the rest go in once per ray.
pub const fn colour_activation_rows(c: &Config) -> usize {
    c.geo_features as usize + 2 * c.colour_hidden as usize + RGB
}

/// Floats of activation (or gradient) per lane in the MLP scratch.
pub const fn activation_floats(c: &Config) -> usize {
    density_activation_rows(c) + colour_activation_rows(c)
}

/// f32 values stored per sample for training: the forward ones, the gradients of the
/// density and the colour, and the activations the backward pass reads instead of
/// recomputing them: the density MLP's rows, each plane's bilinear value (3 per feature)
/// and the colour MLP's rows.
pub const fn sample_floats(c: &Config) -> usize {
    forward_sample_floats(c) + 1 + RGB + activation_floats(c) + 3 * c.density_inputs()
}

/// f32 values per sample that rendering uses: position (3), density, geometry features,
/// colour (3).
pub const fn forward_sample_floats(c: &Config) -> usize {
    3 + 1 + c.geo_features as usize + RGB
}

/// f32 values stored per ray of the batch: origin and direction (pose-corrected), target
/// colour, the direction from the pose label (for the pose-correction gradient) and the
/// background colour the ray is composited on.
pub const RAY_FLOATS: usize = 15;

/// f32 values per ray of a chunk for the pose gradients: d loss / d origin and d loss /
/// d direction (6), then, in a pose refinement's Jacobian pass, the ray's weighted residual
/// and its robust weight.
pub const RAY_GRAD_FLOATS: usize = 8;

impl MemoryPlan {
    /// Everything training needs.
    pub const fn new(c: &Config) -> MemoryPlan {
        Self::plan(c, true)
    }

    /// Only what rendering reads and writes: the planes, the MLP weights, the occupancy bits,
    /// the ray batch's rays and each chunk's forward buffers; no optimiser state, gradients,
    /// frame store or running densities ([`crate::Trainer::new_render_only`]).
    pub const fn render_only(c: &Config) -> MemoryPlan {
        Self::plan(c, false)
    }

    /// `training`: the whole plan; otherwise the render-only one. Each part the render-only
    /// plan leaves out is zero there (`t` below), so both come from one list.
    const fn plan(c: &Config, training: bool) -> MemoryPlan {
        let t = if training { 1 } else { 0 };
        let texels = c.texels();
        let params = c.plane_params();
        let chunks = c.chunks as usize;
        let bitmap = texels.div_ceil(64) * 8;
        let mlp = c.mlp().total;
        let frames = c.max_frames as usize;
        let frame_params = c.frame_params();
        let rays = c.rays_per_batch as usize;
        let chunk_rays = c.rays_per_chunk();
        let samples = c.samples_per_chunk as usize;

        let planes = align(params * 2);
        let plane_master = match c.texel_update {
            TexelUpdate::MasterCopy => t * align(params * 4),
            TexelUpdate::StochasticRounding => 0,
        };
        let plane_moments = t * 2 * align(params * 4);
        let plane_grads = t * (chunks * (align(params * 4) + align(bitmap)) + align(bitmap));
        let mlp_bytes = align(mlp * 4) + t * (2 * align(mlp * 4) + chunks * align(mlp * 4));
        let occupancy =
            align(c.occupancy_cells().div_ceil(64) * 8) + t * align(c.occupancy_cells() * 4);
        let (pixel_bytes, mask_bytes) = c.frame_pixel_bytes();
        let frame_bytes = t
            * (align(pixel_bytes)
                + align(mask_bytes)
                + align(frames * core::mem::size_of::<crate::frames::FrameMeta>())
                + align(frames * 2)
                + 3 * align(frames * frame_params * 4)
                + chunks * align(frames * frame_params * 4));
        let ray_batch = align(rays * RAY_FLOATS * 4) + t * align(rays * 4);
        let sample_block = if training {
            sample_floats(c)
        } else {
            forward_sample_floats(c)
        };
        // Whole mini-batches: the stored activations are kept per mini-batch of LANES.
        let samples = samples.div_ceil(LANES) * LANES;
        let per_chunk = align(samples * sample_block * 4)
            + 2 * align(samples * 4)
            + align((chunk_rays + 1) * 4)
            + align(chunk_rays * 4)
            + align((1 + t) * LANES * activation_floats(c) * 4)
            + t * align(LANES * widest_layer(c) * 4)
            + t * align(chunk_rays * RAY_GRAD_FLOATS * 4)
            + t * align(chunk_rays * 4 * c.loss_weighted_frames as usize);
        let sample_bytes = chunks * per_chunk;

        let total = planes
            + plane_master
            + plane_moments
            + plane_grads
            + mlp_bytes
            + occupancy
            + frame_bytes
            + ray_batch
            + sample_bytes
            + PART_ALIGN;
        MemoryPlan {
            planes,
            plane_master,
            plane_moments,
            plane_grads,
            mlp: mlp_bytes,
            occupancy,
            frames: frame_bytes,
            ray_batch,
            samples: sample_bytes,
            total,
        }
    }
}
