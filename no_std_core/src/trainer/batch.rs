//! A training step's ray batch.

use super::*;

/// The least weight a frame's running loss gives it in a loss-weighted draw.
const LEAST_FRAME_WEIGHT: f32 = 1.0 / 16.0;
/// Draws a loss-weighted ray takes at most (the last is kept whatever its weight).
const FRAME_DRAWS: u32 = 32;

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
        let largest_loss = self.largest_frame_loss();
        executor.for_each(&mut parts, |(first, rays, frames)| {
            for (k, (ray, frame)) in rays.iter_mut().zip(frames.iter_mut()).enumerate() {
                (*ray, *frame) = this.draw_ray(*first + k, largest_loss);
            }
        });
        drop(parts);
        self.rays = rays;
        self.ray_frames = frames;
        Ok(())
    }

    /// The largest running loss of the occupied frames with `Config::loss_weighted_frames`
    /// (0 without it, or before any loss is known: frames are then drawn uniformly).
    pub(super) fn largest_frame_loss(&self) -> f32 {
        if !self.config.loss_weighted_frames {
            return 0.0;
        }
        (0..self.frames.len())
            .filter_map(|i| self.frames.meta(self.frames.occupied_slot(i)?))
            .map(|m| m.loss)
            .fold(0.0, f32::max)
    }

    /// Ray `r` of this step's batch and the frame slot it was drawn from. With a largest
    /// running loss above zero, a drawn pixel is kept with probability its frame's loss over
    /// the largest (at least [`LEAST_FRAME_WEIGHT`]) and drawn again otherwise, up to
    /// [`FRAME_DRAWS`] times (the last draw is kept): frames are drawn in proportion to
    /// their running loss.
    fn draw_ray(&self, r: usize, largest_loss: f32) -> (BatchRay, u32) {
        let c = &self.config;
        let step = self.state.step as u64;
        let in_foreground = c.foreground_fraction > 0.0
            && rng::unit_f32(rng::hash(
                c.seed,
                domain::RAY_PICK,
                step,
                (r as u64) | 2 << 40,
            )) < c.foreground_fraction;
        let draws = if largest_loss > 0.0 { FRAME_DRAWS } else { 1 };
        let mut draw = 0;
        let (slot, (i, j), px, mask) = loop {
            // The first draw is keyed as an unweighted draw is.
            let key = (r as u64) | (draw as u64) << 48;
            let bits = rng::hash(c.seed, domain::RAY_PICK, step, key);
            let pick = if self.frames.keeps_rays() {
                self.reservoir_pixel(bits, in_foreground)
            } else {
                self.frame_pixel(key, bits, in_foreground)
            };
            draw += 1;
            if draw == draws {
                break pick;
            }
            let loss = self.frames.meta.get(pick.0).map_or(0.0, |m| m.loss);
            let weight = (loss / largest_loss).max(LEAST_FRAME_WEIGHT);
            let keep = rng::hash(c.seed, domain::RAY_PICK, step, key | 4 << 40);
            if rng::unit_f32(keep) < weight {
                break pick;
            }
        };
        let meta = self.frames.meta.get(slot).copied().unwrap_or_default();
        let camera = meta.camera();
        let (o, d) = Self::pixel_ray(&camera, &meta.pose(), i, j);
        let correction = self.pose_correction(slot).unwrap_or_default();
        // The mask as alpha: the pixel was composited onto `background` with it.
        let alpha = match mask {
            Some(m) if c.random_background => m as f32 * (1.0 / 255.0),
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

    /// A whole frame's pixel for the draw `key` (the ray's index, and the draw's above bit
    /// 48): a frame uniform over the occupied slots, then a pixel in its foreground box or
    /// anywhere. Slot, column and row, colour, mask value.
    fn frame_pixel(
        &self,
        key: u64,
        bits: u64,
        in_foreground: bool,
    ) -> (usize, (u32, u32), [u8; 3], Option<u8>) {
        let c = &self.config;
        let slot = self
            .frames
            .occupied_slot(rng::below(bits, self.frames.len() as u32) as usize)
            .unwrap_or(0);
        let meta = self.frames.meta[slot];
        let bits = rng::hash(
            c.seed,
            domain::RAY_PICK,
            self.state.step as u64,
            key | 1 << 40,
        );
        let pixel = if in_foreground {
            let [x0, x1, y0, y1] = meta.foreground_box();
            let i = x0 + rng::below(bits, x1 - x0);
            let j = y0 + rng::below(bits.rotate_right(32), y1 - y0);
            j * meta.width + i
        } else {
            rng::below(bits, meta.camera().pixel_count() as u32)
        };
        let at = (slot * self.frames.max_pixels + pixel as usize) * 3;
        let px = core::array::from_fn(|ch| self.frames.pixels.get(at + ch).copied().unwrap_or(0));
        let mask = self
            .frames
            .mask(slot)
            .and_then(|m| m.get(pixel as usize).copied());
        (slot, (pixel % meta.width, pixel / meta.width), px, mask)
    }

    /// A pixel of the ray reservoir: an entry uniform over the foreground part or the
    /// whole-image part (the other one if that part is empty).
    fn reservoir_pixel(
        &self,
        bits: u64,
        in_foreground: bool,
    ) -> (usize, (u32, u32), [u8; 3], Option<u8>) {
        let filled = self.state.rays.filled;
        let part = match (in_foreground, filled) {
            (true, [_, f]) if f > 0 => 1,
            (_, [0, _]) => 1,
            _ => 0,
        };
        // A restored reservoir is not trusted: an entry no run holds is a black sky pixel of
        // the first slot.
        let ray = self
            .frames
            .ray(part, rng::below(bits, filled[part]) as usize);
        let (slot, position, entry) = ray.map_or((0, (0, 0), crate::RayEntry::default()), |r| {
            (r.slot, r.position, r.entry)
        });
        (slot, position, entry.rgb, Some(entry.alpha))
    }
}
