//! A training step's ray batch.

use super::*;

/// One ray of the batch, as the chunks read it (`RAY_FLOATS` floats).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct BatchRay {
    /// Where the ray starts, with the frame's pose correction applied.
    pub(super) origin: [f32; 3],
    /// Unit direction, with the frame's pose correction applied.
    pub(super) direction: [f32; 3],
    /// The pixel's colour, moved onto `background` where the mask lets the sky through.
    pub(super) target: [f32; 3],
    /// The direction through the frame's label pose (the pose-correction gradients start
    /// from it).
    pub(super) label_direction: [f32; 3],
    /// The colour behind the field along this ray.
    pub(super) background: [f32; 3],
}

const _: () = assert!(core::mem::size_of::<BatchRay>() == RAY_FLOATS * 4);

impl<'a> Trainer<'a> {
    /// The ray through pixel `(i, j)` of a camera at `pose`: origin and unit direction.
    pub(super) fn pixel_ray(camera: &Camera, pose: &Pose, i: u32, j: u32) -> (Vec3, Vec3) {
        let d = pose.rotation * camera.pixel_direction(i, j);
        (pose.center, d * (1.0 / libm::sqrtf(d.length_squared())))
    }

    /// Draw the batch: for each ray a frame (uniform over occupied slots) and a pixel.
    /// The chunks' shares of the batch are drawn in parallel: every ray's draw depends only
    /// on the seed, the step and its index.
    pub(super) fn sample_rays<E: Executor>(&mut self, executor: &E) -> Result<(), Error> {
        if self.frames.is_empty() {
            return Err(Error::NoFrames);
        }
        let rays = core::mem::take(&mut self.rays);
        let frames = core::mem::take(&mut self.ray_frames);
        let per_part = rays.len().div_ceil(self.chunks.len().max(1)).max(1);
        let mut parts: heapless::Vec<(usize, &mut [BatchRay], &mut [u32]), MAX_CHUNKS> =
            heapless::Vec::new();
        for (i, (rays, frames)) in rays
            .chunks_mut(per_part)
            .zip(frames.chunks_mut(per_part))
            .enumerate()
        {
            let _ = parts.push((i * per_part, rays, frames));
        }
        let this = &*self;
        executor.for_each(&mut parts, |(first, rays, frames)| {
            for (k, (ray, frame)) in rays.iter_mut().zip(frames.iter_mut()).enumerate() {
                (*ray, *frame) = this.draw_ray(*first + k);
            }
        });
        drop(parts);
        self.rays = rays;
        self.ray_frames = frames;
        Ok(())
    }

    /// Ray `r` of this step's batch and the frame slot it was drawn from.
    fn draw_ray(&self, r: usize) -> (BatchRay, u32) {
        let c = &self.config;
        let count = self.frames.len() as u32;
        let step = self.state.step as u64;
        let bits = rng::hash(c.seed, domain::RAY_PICK, step, r as u64);
        let slot = self
            .frames
            .occupied_slot(rng::below(bits, count) as usize)
            .unwrap_or(0);
        let meta = self.frames.meta[slot];
        let camera = meta.camera();
        let bits = rng::hash(c.seed, domain::RAY_PICK, step, (r as u64) | 1 << 40);
        let in_foreground = c.foreground_fraction > 0.0
            && rng::unit_f32(rng::hash(
                c.seed,
                domain::RAY_PICK,
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
        let correction = self.pose_correction(slot).unwrap_or_default();
        let px = &self.frames.pixels[(slot * self.frames.max_pixels + pixel as usize) * 3..][..3];
        // The mask as alpha: the pixel was composited onto `background` with it.
        let alpha = match self.frames.mask(slot) {
            Some(mask) if c.random_background => mask
                .get(pixel as usize)
                .map_or(1.0, |&m| m as f32 * (1.0 / 255.0)),
            _ => 1.0,
        };
        let background = if alpha < 1.0 {
            let bits = rng::hash(c.seed, domain::RAY_PICK, step, (r as u64) | 3 << 40);
            [0, 21, 42].map(|shift| ((bits >> shift) & 0x1f_ffff) as f32 / 0x1f_ffff as f32)
        } else {
            c.background
        };
        let ray = BatchRay {
            origin: correction.origin(o, c.pose_pivot_point()).to_array(),
            direction: correction.rotate(d).to_array(),
            target: core::array::from_fn(|ch| {
                px[ch] as f32 * (1.0 / 255.0) + (1.0 - alpha) * (background[ch] - c.background[ch])
            }),
            label_direction: d.to_array(),
            background,
        };
        (ray, slot as u32)
    }
}
