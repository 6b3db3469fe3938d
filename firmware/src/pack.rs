//! What the firmware renders, shared word for word with the host's reference render
//! (`examples/onboard_pack.rs` includes this file): the config, the view, the layout of the
//! render pack in flash and the image fingerprint.
//!
//! The render pack holds the sections of a checkpoint that rendering reads, in this order,
//! each as a little-endian `u32` byte count followed by the bytes, after the 8-byte [`MAGIC`]:
//! [`SECTIONS`]. The host writes it from a trained checkpoint (scripts/onboard.sh).

use orbit_nerf_core::glam::{Mat3, Vec3};
use orbit_nerf_core::{Camera, Config, Pose, PosePivot, Replacement, TexelUpdate};

/// First bytes of a render pack.
pub const MAGIC: [u8; 8] = *b"ONRFPAK1";

/// The checkpoint sections rendering reads: texels, MLP weights, occupancy bits.
pub const SECTIONS: [&str; 3] = ["planes", "mlp", "occupancy_bits"];

/// The render profile, budgets/render.toml (tests/core_runtime.rs checks they are equal): the
/// model scripts/onboard/train.toml trains, with the capacities of a renderer.
pub const CONFIG: Config = Config {
    scales: 3,
    resolutions: [8, 16, 32, 0],
    features: 8,
    density_hidden: 32,
    geo_features: 7,
    colour_hidden: 32,
    sh_bands: 3,
    embedding_dim: 0,
    init_low: 0.1,
    init_high: 0.5,
    aabb_min: [-1.5, -1.5, -1.5],
    aabb_max: [1.5, 1.5, 1.5],
    background: [1.0, 1.0, 1.0],
    random_background: false,
    occupancy_res: 32,
    occupancy_every: 16,
    occupancy_threshold: 0.01,
    occupancy_decay: 0.95,
    march_steps: 256,
    max_samples_per_ray: 128,
    min_transmittance: 0.0001,
    max_frames: 1,
    replacement: Replacement::Fifo,
    max_pixels_per_frame: 1,
    ray_store: 0,
    rays_per_batch: 64,
    foreground_fraction: 0.0,
    loss_weighted_frames: false,
    chunks: 1,
    samples_per_chunk: 1024,
    steps: 8,
    warmup_steps: 4,
    learning_rate: 0.01,
    final_lr_factor: 0.03,
    lr_decay_start: 0.0,
    adam_beta1: 0.9,
    adam_beta2: 0.99,
    adam_eps: 1e-15,
    plane_tv_weight: 0.0,
    texel_update: TexelUpdate::StochasticRounding,
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

/// The rendered view: 32 x 32 pixels, 40 degrees across.
pub const CAMERA: Camera = Camera {
    width: 32,
    height: 32,
    fx: 44.0,
    fy: 44.0,
    cx: 16.0,
    cy: 16.0,
};

/// Four units out on -y, looking along +y with +z up (camera axes: x right, y down, z ahead).
pub fn pose() -> Pose {
    Pose {
        rotation: Mat3::from_cols(Vec3::X, Vec3::NEG_Z, Vec3::Y),
        center: Vec3::new(0.0, -4.0, 0.0),
    }
}

/// The sections of a render pack in [`SECTIONS`] order, or `None` if it is not one.
pub fn sections(pack: &[u8]) -> Option<[&[u8]; 3]> {
    let mut rest = pack.strip_prefix(&MAGIC)?;
    let mut out: [&[u8]; 3] = [&[]; 3];
    for section in &mut out {
        let (len, tail) = rest.split_first_chunk::<4>()?;
        let len = u32::from_le_bytes(*len) as usize;
        if tail.len() < len {
            return None;
        }
        (*section, rest) = tail.split_at(len);
    }
    rest.is_empty().then_some(out)
}

/// FNV-1a (64 bits) of the image's little-endian f32 bytes: the fingerprint both sides print.
pub fn fnv1a(image: &[f32]) -> u64 {
    image
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .fold(0xcbf2_9ce4_8422_2325, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        })
}
