//! Per-frame geometry and randomness: the camera pose, the target attitude, the sun and Earth
//! directions, the exposure and the label noise of frame `i` are pure functions of
//! `(scene, seed, i)`, so frames can be rendered in any order, in parallel, with the same result.
//!
//! Frames: the orbit frame has x along track and z towards the Earth (nadir); the target body
//! frame is the dataset's world frame; the camera frame is OpenCV's (x right, y down, z forward).

use super::scene::{LabelNoise, PoseSpec, SceneSpec, SunPath};
use crate::error::{HostError, Result};
use orbit_nerf_core::Camera;
use orbit_nerf_core::glam::{Mat3, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use std::f32::consts::TAU;

/// The independent random streams of a frame: turning one effect on or off never changes the
/// numbers another one draws.
#[derive(Clone, Copy, Debug)]
pub enum Stream {
    Pose = 1,
    Sun = 2,
    Exposure = 3,
    SensorNoise = 4,
    LabelNoise = 5,
}

/// The generator of one stream of one frame.
pub fn frame_rng(seed: u64, frame: u32, stream: Stream) -> Pcg64Mcg {
    // splitmix64 finaliser over (seed, stream, frame): nearby inputs give unrelated seeds.
    let mix = |mut z: u64| {
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    };
    let key =
        mix(mix(seed ^ (stream as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)) ^ u64::from(frame));
    Pcg64Mcg::seed_from_u64(key)
}

/// Everything about one frame's viewing and lighting geometry.
#[derive(Clone, Copy, Debug)]
pub struct FrameView {
    /// Exact rotation body -> camera (the label's `q_vbs2tango`).
    pub body_to_camera: Quat,
    /// Exact target origin in camera axes, metres (the label's `r_Vo2To_vbs`).
    pub target_in_camera: Vec3,
    /// Unit direction towards the sun, body frame.
    pub sun_body: Vec3,
    /// Unit direction towards the Earth, body frame.
    pub earth_body: Vec3,
    /// Exposure multiplier (1 when the scene has no `exposure` effect).
    pub exposure: f32,
}

impl FrameView {
    pub fn camera_to_body(&self) -> Quat {
        self.body_to_camera.inverse()
    }

    /// Camera centre in the body frame.
    pub fn camera_center_body(&self) -> Vec3 {
        -(self.camera_to_body() * self.target_in_camera)
    }
}

/// Draws a rejection loop makes before it gives up: the sun cap (>= 10 degrees) accepts at
/// least 0.76 % of the draws, so a sound geometry fails this often with probability < 1e-30.
const MAX_DRAWS: u32 = 10_000;

/// The view of frame `index` of `spec`, for a target whose bounding sphere is
/// (`target_center`, `target_radius`) in the body frame, seen through `camera`. Fails (naming
/// the frame) when the geometry is degenerate, e.g. not finite, so that no draw can succeed.
pub fn frame_view(
    spec: &SceneSpec,
    target_center: Vec3,
    target_radius: f32,
    camera: &Camera,
    index: u32,
) -> Result<FrameView> {
    let (orbit_from_body, body_to_camera, target_in_camera) = match &spec.poses {
        PoseSpec::Approach {
            distance_m,
            elevation_deg,
            turns,
            attitude,
            spin_axis,
            spin_deg_per_frame,
        } => {
            let progress = index as f32 / spec.frames.saturating_sub(1).max(1) as f32;
            let lerp = |[a, b]: [f32; 2]| a + (b - a) * progress;
            let distance = lerp(*distance_m);
            let elevation = lerp(*elevation_deg).to_radians();
            let azimuth = TAU * turns * progress;
            let [w, x, y, z] = *attitude;
            let spin = Quat::from_axis_angle(
                Vec3::from(*spin_axis).normalize(),
                (spin_deg_per_frame * index as f32).to_radians(),
            );
            let orbit_from_body = Quat::from_xyzw(x, y, z, w).normalize() * spin;
            let aim = orbit_from_body * target_center;
            // Elevation is measured towards zenith (-z in the orbit frame).
            let offset = Vec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                -elevation.sin(),
            );
            let camera_orbit = aim + distance * offset;
            let orbit_from_camera = look_at(camera_orbit, aim);
            let body_from_camera = orbit_from_body.inverse() * orbit_from_camera;
            let camera_body = orbit_from_body.inverse() * camera_orbit;
            let body_to_camera = body_from_camera.inverse();
            (
                orbit_from_body,
                body_to_camera,
                -(body_to_camera * camera_body),
            )
        }
        PoseSpec::Random { distance_m } => {
            let mut rng = frame_rng(spec.seed, index, Stream::Pose);
            let body_to_camera = random_rotation(&mut rng);
            let orbit_from_body = random_rotation(&mut rng);
            let distance = rng.random_range(distance_m[0]..=distance_m[1]);
            // Keep the whole bounding sphere in the image: its centre may move by what is left
            // once its projected radius (plus 10 %) is kept clear of each border.
            let radius_px =
                |focal: f32| 1.1 * focal * (target_radius / distance).min(1.0).asin().tan();
            let mut place = |focal: f32, size: u16, principal: f32| {
                let r = radius_px(focal).min(size as f32 / 2.0);
                let pixel = rng.random_range(r..=(size as f32 - r).max(r));
                (pixel - principal) / focal
            };
            let direction = Vec3::new(
                place(camera.fx, camera.width, camera.cx),
                place(camera.fy, camera.height, camera.cy),
                1.0,
            );
            let center_in_camera = distance * direction.normalize();
            (
                orbit_from_body,
                body_to_camera,
                center_in_camera - body_to_camera * target_center,
            )
        }
    };
    let sun_orbit = match spec.sun.path {
        SunPath::Fixed => Vec3::from(spec.sun.direction).normalize(),
        SunPath::Orbit => {
            let angle = (spec.sun.deg_per_frame * index as f32).to_radians();
            Quat::from_axis_angle(Vec3::from(spec.sun.axis).normalize(), angle)
                * Vec3::from(spec.sun.direction).normalize()
        }
        SunPath::Random => {
            let mut rng = frame_rng(spec.seed, index, Stream::Sun);
            let camera_orbit =
                (orbit_from_body * -(body_to_camera.inverse() * target_in_camera)).normalize();
            let min_cos = spec.sun.max_phase_deg.to_radians().cos();
            // Rejection sampling, uniform over the allowed cap (wide enough, >= 10 deg, to end
            // soon); bounded, since a non-finite camera direction accepts nothing.
            (0..MAX_DRAWS)
                .filter_map(|_| random_unit_vector(&mut rng))
                .find(|sun| sun.dot(camera_orbit) >= min_cos)
                .ok_or_else(|| degenerate(index, "no sun direction within sun.max_phase_deg"))?
        }
    };
    let earth_orbit = spec.effects.albedo.as_ref().map_or(Vec3::Z, |albedo| {
        Vec3::from(albedo.earth_direction).normalize()
    });
    let exposure = spec.effects.exposure.as_ref().map_or(1.0, |exposure| {
        let [low, high] = exposure.range.map(f32::ln);
        let mut rng = frame_rng(spec.seed, index, Stream::Exposure);
        rng.random_range(low..=high).exp()
    });
    let body_from_orbit = orbit_from_body.inverse();
    let view = FrameView {
        body_to_camera,
        target_in_camera,
        sun_body: body_from_orbit * sun_orbit,
        earth_body: body_from_orbit * earth_orbit,
        exposure,
    };
    let finite = view.body_to_camera.is_finite()
        && view.target_in_camera.is_finite()
        && view.sun_body.is_finite()
        && view.earth_body.is_finite()
        && view.exposure.is_finite();
    if !finite {
        return Err(degenerate(index, "the pose or lighting is not finite"));
    }
    Ok(view)
}

fn degenerate(index: u32, reason: &str) -> HostError {
    HostError::field(
        super::frame_filename(index),
        "poses",
        format!("degenerate frame geometry: {reason}"),
    )
}

/// The label written for training: the exact pose rotated about a random axis by a Gaussian
/// angle and shifted by Gaussian metres per axis.
pub fn noisy_label(
    view: &FrameView,
    noise: &LabelNoise,
    seed: u64,
    index: u32,
) -> Result<(Quat, Vec3)> {
    let mut rng = frame_rng(seed, index, Stream::LabelNoise);
    let axis = (0..MAX_DRAWS)
        .find_map(|_| random_unit_vector(&mut rng))
        .ok_or_else(|| degenerate(index, "no label-noise axis drawn"))?;
    let angle = noise.rotation_deg.to_radians() * gaussian(&mut rng);
    let shift =
        noise.translation_m * Vec3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng));
    Ok((
        (Quat::from_axis_angle(axis, angle) * view.body_to_camera).normalize(),
        view.target_in_camera + shift,
    ))
}

pub fn gaussian(rng: &mut Pcg64Mcg) -> f32 {
    StandardNormal.sample(rng)
}

/// Camera-to-orbit rotation of a camera at `eye` looking at `target`, image "up" towards zenith.
fn look_at(eye: Vec3, target: Vec3) -> Quat {
    let forward = (target - eye).normalize();
    let zenith = if forward.dot(-Vec3::Z).abs() > 0.999 {
        Vec3::X
    } else {
        -Vec3::Z
    };
    let right = forward.cross(zenith).normalize();
    let down = forward.cross(right);
    Quat::from_mat3(&Mat3::from_cols(right, down, forward))
}

/// Uniform random rotation (Shoemake).
fn random_rotation(rng: &mut Pcg64Mcg) -> Quat {
    let (u1, u2, u3): (f32, f32, f32) = (rng.random(), rng.random(), rng.random());
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    Quat::from_xyzw(
        a * (TAU * u2).sin(),
        a * (TAU * u2).cos(),
        b * (TAU * u3).sin(),
        b * (TAU * u3).cos(),
    )
    .normalize()
}

/// One draw of a uniform unit vector: `None` (draw again) when the Gaussian sample is too
/// short to normalise.
fn random_unit_vector(rng: &mut Pcg64Mcg) -> Option<Vec3> {
    let v = Vec3::new(gaussian(rng), gaussian(rng), gaussian(rng));
    (v.length_squared() > 1e-6).then(|| v.normalize())
}
