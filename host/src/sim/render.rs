//! Ray casting and the effects, as separate passes so that each effect's time can be measured
//! and an effect the scene does not ask for never runs.
//!
//! Radiometry is linear: a white Lambertian surface facing the sun at irradiance 1 has value 1
//! at exposure 1. The exposure scales the linear image, which is then gamma-encoded (1/2.2) and
//! clipped to 8 bits: values above 1 saturate to white.

use super::scene::{Effects, Flare, SensorNoise};
use super::target::{Target, TraversalStack};
use super::trajectory::{FrameView, Stream, frame_rng, gaussian};
use super::{Stage, StageTimes};
use crate::formats::speedplus::SpeedCamera;
use orbit_nerf_core::Camera;
use orbit_nerf_core::glam::Vec3;

/// Rows of pixels traced together: the per-sample buffers stay small at any image size.
const BAND_ROWS: usize = 16;
/// Shadow rays start this far (metres) off the surface so they do not hit it again.
const SHADOW_BIAS: f32 = 1e-4;
const DISPLAY_GAMMA: f32 = 1.0 / 2.2;

/// A rendered frame: 8-bit pixels (1 channel if grayscale, else RGB) and the foreground mask.
pub struct RenderedImage {
    /// Channels per pixel: 1 (grayscale) or 3 (RGB).
    pub channels: u8,
    /// Row-major, gamma-encoded 8-bit samples, `channels` per pixel.
    pub pixels: Vec<u8>,
    /// Row-major foreground mask, one byte per pixel: 255 where at least half the pixel's
    /// samples hit the target, else 0.
    pub mask: Vec<u8>,
}

/// A visible surface point seen by one sub-pixel ray.
#[derive(Clone, Copy)]
struct SurfaceSample {
    position: Vec3,
    /// Unit normal, turned towards the camera.
    normal: Vec3,
    to_camera: Vec3,
    albedo: Vec3,
    material: u16,
}

pub struct Renderer<'a> {
    pub target: &'a Target,
    pub effects: &'a Effects,
    /// Output intrinsics (pinhole part).
    pub camera: Camera,
    /// The lens distortion to render with, when the scene asks for it.
    pub lens: Option<&'a SpeedCamera>,
    pub antialias: u32,
    pub seed: u64,
}

impl Renderer<'_> {
    pub fn render(&self, view: &FrameView, index: u32, times: &mut StageTimes) -> RenderedImage {
        let (width, height) = (self.camera.width as usize, self.camera.height as usize);
        let samples_per_pixel = (self.antialias * self.antialias) as usize;
        let mut linear = vec![0.0f32; width * height * 3];
        let mut mask = vec![0u8; width * height];
        let mut surfaces: Vec<Option<SurfaceSample>> = Vec::new();
        let mut sun_visible: Vec<bool> = Vec::new();
        let mut radiance: Vec<Vec3> = Vec::new();
        let mut stack = TraversalStack::new();

        for band_start in (0..height).step_by(BAND_ROWS) {
            let rows = band_start..(band_start + BAND_ROWS).min(height);
            times.time(Stage::Geometry, || {
                self.trace_band(view, rows.clone(), &mut surfaces, &mut stack)
            });
            radiance.clear();
            radiance.resize(surfaces.len(), Vec3::ZERO);
            if self.effects.shadows.is_some() {
                times.time(Stage::Shadows, || {
                    self.shadow_band(view, &surfaces, &mut sun_visible, &mut stack)
                });
            }
            let visible = |k: usize| self.effects.shadows.is_none() || sun_visible[k];
            if let Some(sun) = &self.effects.sun {
                times.time(Stage::Sun, || {
                    for (k, surface) in surfaces.iter().enumerate() {
                        if let Some(s) = surface {
                            let cos = s.normal.dot(view.sun_body);
                            if cos > 0.0 && visible(k) {
                                radiance[k] += s.albedo * (sun.irradiance * cos);
                            }
                        }
                    }
                });
                if self.effects.specular.is_some() {
                    times.time(Stage::Specular, || {
                        for (k, surface) in surfaces.iter().enumerate() {
                            if let Some(s) = surface {
                                let cos = s.normal.dot(view.sun_body);
                                if cos > 0.0 && visible(k) {
                                    let material = &self.target.materials[s.material as usize];
                                    let half = (view.sun_body + s.to_camera).normalize();
                                    // Normalised Blinn-Phong: the lobe keeps its energy as it sharpens.
                                    let lobe = (material.shininess + 8.0) / 8.0
                                        * s.normal.dot(half).max(0.0).powf(material.shininess);
                                    radiance[k] +=
                                        material.specular * (sun.irradiance * cos * lobe);
                                }
                            }
                        }
                    });
                }
            }
            if let Some(albedo) = &self.effects.albedo {
                times.time(Stage::Albedo, || {
                    // The Earth is fully lit seen from the target when the sun is behind the target.
                    let lit_fraction = 0.5 * (1.0 - view.sun_body.dot(view.earth_body));
                    let strength = albedo.strength * lit_fraction;
                    for (k, surface) in surfaces.iter().enumerate() {
                        if let Some(s) = surface {
                            // A hemisphere light: full when facing the Earth, none facing away.
                            let facing = 0.5 * (1.0 + s.normal.dot(view.earth_body));
                            radiance[k] += s.albedo * (strength * facing);
                        }
                    }
                });
            }
            times.time(Stage::Resolve, || {
                let band_pixels = rows.len() * width;
                let first = rows.start * width;
                for p in 0..band_pixels {
                    let samples = p * samples_per_pixel..(p + 1) * samples_per_pixel;
                    let sum: Vec3 = radiance[samples.clone()].iter().sum();
                    let covered = surfaces[samples].iter().filter(|s| s.is_some()).count();
                    let value = sum / samples_per_pixel as f32;
                    linear[(first + p) * 3..(first + p) * 3 + 3].copy_from_slice(&value.to_array());
                    mask[first + p] = if 2 * covered >= samples_per_pixel {
                        255
                    } else {
                        0
                    };
                }
            });
        }

        let mut channels = 3;
        if self.effects.grayscale.is_some() {
            times.time(Stage::Grayscale, || {
                linear = linear
                    .chunks_exact(3)
                    .map(|c| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])
                    .collect();
            });
            channels = 1;
        }
        if let Some(exposure) = &self.effects.exposure {
            times.time(Stage::Exposure, || {
                let (gain, black) = (view.exposure, exposure.black_level);
                linear
                    .iter_mut()
                    .for_each(|v| *v = ((*v * gain - black) / (1.0 - black)).max(0.0));
            });
        }
        if let Some(flare) = &self.effects.flare {
            times.time(Stage::Flare, || {
                add_bloom(&mut linear, width, height, channels, flare)
            });
        }
        if let Some(noise) = &self.effects.noise {
            times.time(Stage::Noise, || {
                add_sensor_noise(&mut linear, noise, self.seed, index)
            });
        }
        let pixels = times.time(Stage::Encode, || {
            linear
                .iter()
                .map(|v| (255.0 * v.clamp(0.0, 1.0).powf(DISPLAY_GAMMA)).round() as u8)
                .collect()
        });
        RenderedImage {
            channels: channels as u8,
            pixels,
            mask,
        }
    }

    /// Closest hits of the sub-pixel rays of `rows`, pixel by pixel, sub-sample by sub-sample.
    fn trace_band(
        &self,
        view: &FrameView,
        rows: std::ops::Range<usize>,
        surfaces: &mut Vec<Option<SurfaceSample>>,
        stack: &mut TraversalStack,
    ) {
        let n = self.antialias;
        let camera = &self.camera;
        let origin = view.camera_center_body();
        let camera_to_body = view.camera_to_body();
        surfaces.clear();
        for j in rows {
            for i in 0..camera.width as usize {
                for sy in 0..n {
                    for sx in 0..n {
                        let u = i as f32 + (sx as f32 + 0.5) / n as f32;
                        let v = j as f32 + (sy as f32 + 0.5) / n as f32;
                        let (xd, yd) = ((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy);
                        let (x, y) = self.lens.map_or((xd, yd), |lens| lens.undistort(xd, yd));
                        let dir = camera_to_body * Vec3::new(x, y, 1.0).normalize();
                        surfaces.push(self.target.closest_hit(origin, dir, stack).map(|hit| {
                            let position = origin + hit.distance * dir;
                            let normal = if hit.normal.dot(dir) > 0.0 {
                                -hit.normal
                            } else {
                                hit.normal
                            };
                            let material = &self.target.materials[hit.material as usize];
                            SurfaceSample {
                                position,
                                normal,
                                to_camera: -dir,
                                albedo: material.diffuse_at(position, normal),
                                material: hit.material,
                            }
                        }));
                    }
                }
            }
        }
    }

    /// Whether each surface sample that faces the sun sees it past the rest of the target.
    fn shadow_band(
        &self,
        view: &FrameView,
        surfaces: &[Option<SurfaceSample>],
        sun_visible: &mut Vec<bool>,
        stack: &mut TraversalStack,
    ) {
        sun_visible.clear();
        sun_visible.extend(surfaces.iter().map(|surface| match surface {
            Some(s) if s.normal.dot(view.sun_body) > 0.0 => {
                let start = s.position + SHADOW_BIAS * s.normal;
                !self.target.occluded(start, view.sun_body, 0.0, stack)
            }
            _ => false,
        }));
    }
}

/// Blur the light above the threshold and add it back (bloom around saturated highlights).
fn add_bloom(image: &mut [f32], width: usize, height: usize, channels: usize, flare: &Flare) {
    let bright: Vec<f32> = image
        .iter()
        .map(|v| (v - flare.threshold).max(0.0))
        .collect();
    if bright.iter().all(|v| *v == 0.0) {
        return;
    }
    let radius = (3.0 * flare.sigma_px).ceil() as isize;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|d| (-0.5 * (d as f32 / flare.sigma_px).powi(2)).exp())
        .collect();
    let norm: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / norm).collect();
    // Horizontal then vertical pass, edges clamped.
    let mut horizontal = vec![0.0f32; bright.len()];
    for y in 0..height {
        for x in 0..width {
            for c in 0..channels {
                let mut sum = 0.0;
                for (k, weight) in kernel.iter().enumerate() {
                    let sx =
                        (x as isize + k as isize - radius).clamp(0, width as isize - 1) as usize;
                    sum += weight * bright[(y * width + sx) * channels + c];
                }
                horizontal[(y * width + x) * channels + c] = sum;
            }
        }
    }
    for y in 0..height {
        for x in 0..width {
            for c in 0..channels {
                let mut sum = 0.0;
                for (k, weight) in kernel.iter().enumerate() {
                    let sy =
                        (y as isize + k as isize - radius).clamp(0, height as isize - 1) as usize;
                    sum += weight * horizontal[(sy * width + x) * channels + c];
                }
                image[(y * width + x) * channels + c] += flare.strength * sum;
            }
        }
    }
}

/// Shot noise (Gaussian approximation of Poisson) plus read noise, in electrons.
fn add_sensor_noise(image: &mut [f32], noise: &SensorNoise, seed: u64, index: u32) {
    let mut rng = frame_rng(seed, index, Stream::SensorNoise);
    let read_variance = noise.read_noise * noise.read_noise;
    for v in image.iter_mut() {
        let electrons = v.max(0.0) * noise.full_well;
        *v += gaussian(&mut rng) * (electrons + read_variance).sqrt() / noise.full_well;
    }
}
