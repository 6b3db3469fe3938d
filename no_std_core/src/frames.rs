//! Frame slots: a fixed number of them, each holding a camera, a pose label and, in one of two
//! ways, the frame's pixels. The learnable per-frame parameters (appearance embedding and pose
//! correction) live beside them in the trainer and are reset with the slot.
//!
//! - **Whole frames** (`Config::ray_store` = 0): each slot keeps every RGB8 pixel of its frame
//!   and an optional foreground mask.
//! - **A ray reservoir** (`ray_store` = N > 0): the slots keep only camera, label and
//!   parameters (so a stream can remember many more frames than it could hold whole), and N
//!   pixels of all the frames stored so far sit in one shared reservoir, 4 bytes each (colour
//!   and mask value, [`RayEntry`]). The reservoir has two parts, as the training rays have: a
//!   share `foreground_fraction` of pixels drawn inside their frame's foreground box and the
//!   rest drawn from the whole image. In each part a frame holds one run of entries, the
//!   first pixels of its region in a seeded order that spreads every prefix evenly over the
//!   region ([`PixelSequence`]), so a pixel's position is implied by its place in the run and
//!   costs no bytes. The runs lie in slot order, packed from the part's start. An arriving
//!   frame gets an equal share of the part among the frames remembered (no more than its
//!   region's pixels); the frames already held give up the tail of their runs to make room,
//!   so every frame stored so far holds the same share once the part is full: training sees
//!   the whole past, not only the latest frames. A frame put into an occupied slot replaces
//!   its predecessor's run; an emptied slot's run is removed.

use crate::rng::{self, domain};
use crate::{Camera, Error, Pose};
use bytemuck::{Pod, Zeroable};
use glam::{Mat3, Vec3};

/// Metadata of one slot, stored in the arena.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct FrameMeta {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Camera-to-world rotation, column-major.
    pub rotation: [f32; 9],
    pub center: [f32; 3],
    pub has_mask: u32,
    pub occupied: u32,
    /// Mean pixel value in [0, 1] (the illumination descriptor of the replacement policy).
    pub brightness: f32,
    /// Arrival number of the frame in a stream (0 for frames put in place directly).
    pub arrival: u32,
    /// The foreground box, pixel columns `[x0, x1)` and rows `[y0, y1)`: the mask's box when
    /// there is a mask, else the box of pixels brighter than [`FOREGROUND_LEVEL`], widened by
    /// [`FOREGROUND_MARGIN`] pixels; the whole image when nothing stands out.
    pub foreground: [u32; 4],
    /// Running mean squared error of the frame's training rays (with
    /// `Config::loss_weighted_frames`; 0 otherwise).
    pub loss: f32,
    /// The frame's run in each part of the ray reservoir (whole image, foreground box);
    /// empty for whole frames.
    pub rays: [RayRun; 2],
}

/// A frame's run of entries in one part of the ray reservoir: where it starts in the part,
/// how many entries it holds, and its pixel order (see [`PixelSequence`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RayRun {
    /// The run's first entry, counted from the part's start.
    pub start: u32,
    /// Entries in the run.
    pub count: u32,
    /// The sequence's first pixel, as an index into the region.
    pub offset: u32,
    /// The sequence's step, coprime to the region's pixel count.
    pub stride: u32,
}

impl FrameMeta {
    pub fn camera(&self) -> Camera {
        Camera {
            width: self.width as u16,
            height: self.height as u16,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }
    /// The foreground box, or the whole image if the stored one is empty or does not fit
    /// (a restored checkpoint is not trusted).
    pub fn foreground_box(&self) -> [u32; 4] {
        match self.foreground {
            [x0, x1, y0, y1] if x0 < x1 && x1 <= self.width && y0 < y1 && y1 <= self.height => {
                self.foreground
            }
            _ => [0, self.width, 0, self.height],
        }
    }

    pub fn pose(&self) -> Pose {
        Pose {
            rotation: Mat3::from_cols_array(&self.rotation),
            center: Vec3::from_array(self.center),
        }
    }
}

/// One pixel kept in the ray reservoir: its colour and its mask value (255 without a mask).
/// Its frame and position are implied by its place (see [`RayRun`]). Bytes only, so the
/// reservoir is any byte buffer.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RayEntry {
    /// RGB8 colour.
    pub rgb: [u8; 3],
    /// Mask value (0 sky .. 255 target).
    pub alpha: u8,
}

/// Bytes of one [`RayEntry`].
pub const RAY_ENTRY_BYTES: usize = core::mem::size_of::<RayEntry>();
const _: () = assert!(RAY_ENTRY_BYTES == 4);

/// A reservoir entry with where it came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RayPixel {
    /// The frame slot the pixel belongs to.
    pub slot: usize,
    /// Pixel column and row.
    pub position: (u32, u32),
    /// Colour and mask value.
    pub entry: RayEntry,
}

/// How full each part of the ray reservoir is and how many frames were offered to it: whole
/// image first, foreground box second. Kept in the training state (and so in checkpoints).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RayCounts {
    /// Entries held by each part.
    pub filled: [u32; 2],
    /// Frames ever offered to each part (the key of the part's draws).
    pub offered: [u64; 2],
}

/// The frame slots, borrowed from the arena.
pub struct FrameStore<'a> {
    pub(crate) meta: &'a mut [FrameMeta],
    /// Whole frames: `max_pixels` RGB8 pixels per slot. Ray reservoir: its [`RayEntry`]s.
    pub(crate) pixels: &'a mut [u8],
    pub(crate) masks: &'a mut [u8],
    /// Indices of the occupied slots, in slot order; the first `len` entries are valid.
    pub(crate) occupied: &'a mut [u16],
    pub(crate) len: usize,
    pub(crate) max_pixels: usize,
    /// Entries in the foreground part of the ray reservoir (the rest of it is the whole-image
    /// part); unused for whole frames.
    pub(crate) foreground_rays: usize,
    /// Whether `pixels` is a ray reservoir (`Config::ray_store` > 0).
    pub(crate) keep_rays: bool,
}

/// A pixel whose brightest channel exceeds this (of 255) counts as foreground when a frame
/// has no mask: the target against the black sky, above the sensor's dark noise.
pub const FOREGROUND_LEVEL: u8 = 40;
/// The foreground box is widened by this many pixels on every side, so the silhouette's
/// edges (and the sky just outside them) are sampled too.
pub const FOREGROUND_MARGIN: u32 = 4;

/// The box `[x0, x1, y0, y1)` of the pixels for which `is_foreground(index)` holds, widened by
/// the margin and clipped to the image; the whole image if there are none.
fn foreground_box(width: u32, height: u32, is_foreground: impl Fn(usize) -> bool) -> [u32; 4] {
    let (mut x0, mut x1, mut y0, mut y1) = (width, 0, height, 0);
    for y in 0..height {
        for x in 0..width {
            if is_foreground((y * width + x) as usize) {
                x0 = x0.min(x);
                x1 = x1.max(x + 1);
                y0 = y0.min(y);
                y1 = y1.max(y + 1);
            }
        }
    }
    if x0 >= x1 {
        return [0, width, 0, height];
    }
    [
        x0.saturating_sub(FOREGROUND_MARGIN),
        (x1 + FOREGROUND_MARGIN).min(width),
        y0.saturating_sub(FOREGROUND_MARGIN),
        (y1 + FOREGROUND_MARGIN).min(height),
    ]
}

/// Whether a pixel without a mask counts as foreground (see [`FOREGROUND_LEVEL`]).
pub(crate) fn is_bright(rgb: &[u8]) -> bool {
    rgb.iter().any(|&v| v > FOREGROUND_LEVEL)
}

/// [`foreground_box`] of the pixels in columns `columns.0..columns.1`, clipped to them (the
/// columns themselves if none is foreground).
pub(crate) fn foreground_box_within(
    width: u32,
    height: u32,
    columns: (u32, u32),
    is_foreground: impl Fn(usize) -> bool,
) -> [u32; 4] {
    let (c0, c1) = (columns.0.min(width), columns.1.min(width));
    let [x0, x1, y0, y1] = foreground_box(width, height, |i| {
        let x = (i % width.max(1) as usize) as u32;
        (c0..c1).contains(&x) && is_foreground(i)
    });
    let (x0, x1) = (x0.max(c0), x1.min(c1));
    if x0 < x1 {
        [x0, x1, y0, y1]
    } else {
        [c0, c1.max(c0 + 1), 0, height]
    }
}

/// Largest deviation of R^T R from the identity accepted for a pose label.
const ORTHONORMAL_TOLERANCE: f32 = 1e-3;

impl<'a> FrameStore<'a> {
    pub fn capacity(&self) -> usize {
        self.meta.len()
    }

    /// Occupied slots.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Slot index of the `i`-th occupied slot.
    pub fn occupied_slot(&self, i: usize) -> Option<usize> {
        self.occupied.get(..self.len)?.get(i).map(|&s| s as usize)
    }

    pub fn meta(&self, slot: usize) -> Option<&FrameMeta> {
        self.meta.get(slot).filter(|m| m.occupied != 0)
    }

    /// Whether the store keeps a ray reservoir instead of whole frames.
    pub fn keeps_rays(&self) -> bool {
        self.keep_rays
    }

    /// Where each part of the reservoir starts and how many entries it can hold.
    fn ray_parts(&self) -> [(usize, usize); 2] {
        let total = self.pixels.len() / RAY_ENTRY_BYTES;
        let foreground = self.foreground_rays.min(total);
        [(0, total - foreground), (total - foreground, foreground)]
    }

    /// The region of a frame that a part draws its pixels from: the whole image (part 0) or
    /// the foreground box (part 1).
    fn ray_region(meta: &FrameMeta, part: usize) -> [u32; 4] {
        match part {
            0 => [0, meta.width, 0, meta.height],
            _ => meta.foreground_box(),
        }
    }

    /// Reservoir entry `index` of `part` (0 whole image, 1 foreground box) among the filled
    /// ones (`index < counts.filled[part]`), with its slot and position: the run holding it
    /// is found by bisection over the runs, which lie in slot order.
    pub fn ray(&self, part: usize, index: usize) -> Option<RayPixel> {
        let (start, capacity) = *self.ray_parts().get(part)?;
        if index >= capacity {
            return None;
        }
        let occupied = self.occupied.get(..self.len)?;
        let run_of = |s: u16| {
            self.meta
                .get(s as usize)
                .map_or(RayRun::default(), |m| m.rays[part])
        };
        let i = occupied.partition_point(|&s| {
            let run = run_of(s);
            (run.start as usize).saturating_add(run.count as usize) <= index
        });
        let slot = *occupied.get(i)? as usize;
        let run = run_of(slot as u16);
        let k = index.checked_sub(run.start as usize)?;
        if k >= run.count as usize {
            return None;
        }
        let meta = self.meta.get(slot)?;
        let position = PixelSequence::of(Self::ray_region(meta, part), run).nth(k as u64);
        let at = (start + index) * RAY_ENTRY_BYTES;
        let entry = bytemuck::pod_read_unaligned(self.pixels.get(at..at + RAY_ENTRY_BYTES)?);
        Some(RayPixel {
            slot,
            position,
            entry,
        })
    }

    /// RGB8 pixels of an occupied slot (`None` when the store keeps a ray reservoir).
    pub fn pixels(&self, slot: usize) -> Option<&[u8]> {
        if self.keeps_rays() {
            return None;
        }
        let m = self.meta(slot)?;
        let n = m.width as usize * m.height as usize;
        self.pixels.get(slot * self.max_pixels * 3..)?.get(..n * 3)
    }

    /// Foreground mask of an occupied slot, if it has one (`None` for a ray reservoir).
    pub fn mask(&self, slot: usize) -> Option<&[u8]> {
        let m = self.meta(slot).filter(|m| m.has_mask != 0)?;
        let n = m.width as usize * m.height as usize;
        self.masks.get(slot * self.max_pixels..)?.get(..n)
    }

    /// Check a frame as `set` would, without storing it.
    pub fn check(
        &self,
        camera: &Camera,
        pose: &Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<(), Error> {
        if !camera.is_valid() {
            return Err(Error::InvalidFrame { field: "camera" });
        }
        let n = camera.pixel_count();
        if n > self.max_pixels {
            return Err(Error::FrameTooLarge {
                pixels: n,
                capacity: self.max_pixels,
            });
        }
        if pixels.len() != n * 3 {
            return Err(Error::InvalidFrame { field: "pixels" });
        }
        if mask.is_some_and(|m| m.len() != n) {
            return Err(Error::InvalidFrame { field: "mask" });
        }
        if !pose.is_finite() {
            return Err(Error::InvalidFrame { field: "pose" });
        }
        let rtr = pose.rotation.transpose() * pose.rotation;
        let off = (rtr - Mat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()));
        if off.is_nan() || off >= ORTHONORMAL_TOLERANCE || pose.rotation.determinant() < 0.0 {
            return Err(Error::InvalidFrame {
                field: "pose.rotation",
            });
        }
        Ok(())
    }

    /// Put a frame into `slot`, replacing what was there. The input is checked first; on error
    /// the slot is unchanged.
    pub fn set(
        &mut self,
        slot: usize,
        camera: Camera,
        pose: Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<(), Error> {
        if slot >= self.capacity() {
            return Err(Error::InvalidFrame { field: "slot" });
        }
        self.check(&camera, &pose, pixels, mask)?;
        let n = camera.pixel_count();
        if !self.keeps_rays() {
            let base = slot * self.max_pixels;
            self.pixels[base * 3..base * 3 + n * 3].copy_from_slice(pixels);
            if let Some(mask) = mask {
                self.masks[base..base + n].copy_from_slice(mask);
            }
        }
        let (w, h) = (camera.width as u32, camera.height as u32);
        let foreground = match mask {
            Some(mask) => foreground_box(w, h, |i| mask[i] != 0),
            None => foreground_box(w, h, |i| is_bright(&pixels[i * 3..i * 3 + 3])),
        };
        self.meta[slot] = FrameMeta {
            width: camera.width as u32,
            height: camera.height as u32,
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            rotation: pose.rotation.to_cols_array(),
            center: pose.center.to_array(),
            has_mask: mask.is_some() as u32,
            occupied: 1,
            brightness: mean_brightness(pixels),
            arrival: 0,
            foreground,
            loss: 0.0,
            // The predecessor's runs stay until `offer_rays` replaces them.
            rays: self.meta[slot].rays,
        };
        self.rebuild_occupied();
        Ok(())
    }

    /// Empty a slot (no-op if it is already empty or out of range), removing its reservoir
    /// runs.
    pub fn clear(&mut self, slot: usize, counts: &mut RayCounts) {
        if self.meta.get(slot).is_some_and(|m| m.occupied != 0) {
            for part in 0..2 {
                self.meta[slot].rays[part].count = 0;
                self.pack_runs(part, None, counts);
            }
            self.meta[slot] = FrameMeta::default();
            self.rebuild_occupied();
        }
    }

    /// Lay the runs of `part` out in slot order from the part's start, moving each to its
    /// place (their counts may have shrunk; a run that does not fit the part, as a restored
    /// checkpoint's might not, is dropped), and leave a gap of `gap.1` entries where slot
    /// `gap.0`'s run goes (its old run is dropped). Updates the part's fill and returns where
    /// the gap starts. Allocates
    /// nothing: runs only move towards the start in the first pass, then those after the gap
    /// towards the end, each with one `copy_within`.
    fn pack_runs(
        &mut self,
        part: usize,
        gap: Option<(usize, usize)>,
        counts: &mut RayCounts,
    ) -> usize {
        let (base, capacity) = self.ray_parts()[part];
        let gap_slot = gap.map(|(slot, _)| slot);
        let (mut cursor, mut gap_start) = (0usize, 0usize);
        for i in 0..self.len {
            let slot = self.occupied[i] as usize;
            let run = &mut self.meta[slot].rays[part];
            let (from, count) = (run.start as usize, run.count as usize);
            if Some(slot) == gap_slot {
                gap_start = cursor;
            }
            if Some(slot) == gap_slot
                || from.saturating_add(count) > capacity
                || cursor + count > capacity
            {
                *run = RayRun {
                    start: cursor as u32,
                    count: 0,
                    ..*run
                };
                continue;
            }
            run.start = cursor as u32;
            let bytes = (base + from) * RAY_ENTRY_BYTES..(base + from + count) * RAY_ENTRY_BYTES;
            self.pixels
                .copy_within(bytes, (base + cursor) * RAY_ENTRY_BYTES);
            cursor += count;
        }
        let mut end = cursor;
        if let Some((gap_slot, gap)) = gap {
            let gap = gap.min(capacity - cursor);
            end = cursor + gap;
            // The runs after the gap's slot move up by the gap, the last first.
            for i in (0..self.len).rev() {
                let slot = self.occupied[i] as usize;
                let run = &mut self.meta[slot].rays[part];
                if slot <= gap_slot {
                    break;
                }
                let from = run.start as usize;
                let count = run.count as usize;
                run.start = (from + gap) as u32;
                let bytes =
                    (base + from) * RAY_ENTRY_BYTES..(base + from + count) * RAY_ENTRY_BYTES;
                self.pixels
                    .copy_within(bytes, (base + from + gap) * RAY_ENTRY_BYTES);
            }
        }
        counts.filled[part] = end as u32;
        gap_start
    }

    /// Give the frame just put into `slot` (by [`FrameStore::set`]) its run in each part of
    /// the ray reservoir, replacing the run of the frame the slot held before: the largest
    /// share such that every frame remembered can hold that many entries (or all its region's
    /// pixels, or what it holds now, whichever is fewer); the others give up the tail of their
    /// runs down to the share, and the new frame takes the first pixels of its
    /// [`PixelSequence`] into the places left, up to its region's pixels. The sequence is
    /// keyed by the seeded RNG and the frames offered so far, so the reservoir depends only on
    /// the seed and the frames in order. A no-op for whole frames. Allocates nothing.
    pub(crate) fn offer_rays(
        &mut self,
        slot: usize,
        pixels: &[u8],
        mask: Option<&[u8]>,
        seed: u64,
        counts: &mut RayCounts,
    ) {
        let Some(meta) = self.meta(slot).copied() else {
            return;
        };
        if !self.keeps_rays() {
            return;
        }
        for part in 0..2 {
            let (base, capacity) = self.ray_parts()[part];
            if capacity == 0 {
                continue;
            }
            let offer = counts.offered[part];
            counts.offered[part] = offer.saturating_add(1);
            let key = rng::hash(seed, domain::RESERVOIR, offer, part as u64);
            let region = Self::ray_region(&meta, part);
            let sequence = PixelSequence::new(region, key);
            let area = sequence.area as usize;
            let share = self.fair_share(part, slot, capacity, area);
            for i in 0..self.len {
                let other = self.occupied[i] as usize;
                let run = &mut self.meta[other].rays[part];
                run.count = (run.count as usize).min(share) as u32;
            }
            let held: usize = (0..self.len)
                .map(|i| self.occupied[i] as usize)
                .filter(|&other| other != slot)
                .map(|other| self.meta[other].rays[part].count as usize)
                .sum();
            let take = area.min(capacity.saturating_sub(held));
            let start = self.pack_runs(part, Some((slot, take)), counts);
            self.meta[slot].rays[part] = RayRun {
                start: start as u32,
                count: take as u32,
                offset: sequence.offset as u32,
                stride: sequence.stride as u32,
            };
            for k in 0..take {
                let (x, y) = sequence.nth(k as u64);
                let at = (y * meta.width + x) as usize;
                let entry = RayEntry {
                    rgb: core::array::from_fn(|ch| pixels.get(at * 3 + ch).copied().unwrap_or(0)),
                    alpha: mask.map_or(u8::MAX, |m| m.get(at).copied().unwrap_or(0)),
                };
                let to = (base + start + k) * RAY_ENTRY_BYTES;
                self.pixels[to..to + RAY_ENTRY_BYTES].copy_from_slice(bytemuck::bytes_of(&entry));
            }
        }
    }

    /// The largest share `s` of a part of `capacity` entries such that the frames remembered,
    /// each holding the fewer of `s` and what it holds now (`area` and `s` for the frame
    /// arriving in `slot`), fit the part: found by bisection, as the total only grows with `s`.
    fn fair_share(&self, part: usize, slot: usize, capacity: usize, area: usize) -> usize {
        let total = |share: usize| {
            (0..self.len)
                .map(|i| self.occupied[i] as usize)
                .map(|other| match other == slot {
                    true => area.min(share),
                    false => (self.meta[other].rays[part].count as usize).min(share),
                })
                .fold(0usize, usize::saturating_add)
        };
        let (mut fits, mut too_many) = (0usize, capacity + 1);
        while too_many - fits > 1 {
            let mid = fits + (too_many - fits) / 2;
            match total(mid) <= capacity {
                true => fits = mid,
                false => too_many = mid,
            }
        }
        fits
    }

    /// Record the stream arrival number of an occupied slot's frame.
    pub(crate) fn set_arrival(&mut self, slot: usize, arrival: u32) {
        if let Some(m) = self.meta.get_mut(slot).filter(|m| m.occupied != 0) {
            m.arrival = arrival;
        }
    }

    pub(crate) fn rebuild_occupied(&mut self) {
        let mut len = 0;
        for (slot, m) in self.meta.iter().enumerate() {
            if m.occupied != 0 {
                self.occupied[len] = slot as u16;
                len += 1;
            }
        }
        self.len = len;
    }
}

/// Distinct pixels of a region `[x0, x1, y0, y1)` in a seeded order whose every prefix is
/// spread evenly over the region: the `k`-th is index `(offset + k * stride) mod area` of the
/// region's pixels in row order, with the stride coprime to the area (so `area` draws visit
/// every pixel once) and chosen so that each step moves about 0.755 of the width across and
/// 0.570 of the height down: the R2 sequence's steps (the plastic number's powers), whose
/// points keep their distance at every length. A random stride could be 1 and keep a band
/// of rows.
pub(crate) struct PixelSequence {
    region: [u32; 4],
    width: u64,
    area: u64,
    offset: u64,
    stride: u64,
}

/// The R2 sequence's steps in 32-bit fixed point: 1/p and 1/p^2 of the plastic number p.
const R2_STEPS: [u64; 2] = [3_242_174_890, 2_447_445_414];

impl PixelSequence {
    /// The sequence of `region` with the offset drawn from `key`.
    fn new(region: [u32; 4], key: u64) -> PixelSequence {
        let mut sequence = PixelSequence::of(region, RayRun::default());
        let (width, area) = (sequence.width, sequence.area);
        let across = (width * R2_STEPS[0]) >> 32;
        let down = ((area / width) * R2_STEPS[1]) >> 32;
        let mut stride = (down * width + across) % area;
        // The step count to the next coprime stride is small (Jacobsthal's function).
        while gcd(stride, area) != 1 {
            stride = (stride + 1) % area;
        }
        sequence.offset = key % area;
        sequence.stride = stride;
        sequence
    }

    /// The sequence a stored run describes (a restored checkpoint is not trusted: any offset
    /// and stride give positions inside the region).
    fn of(region: [u32; 4], run: RayRun) -> PixelSequence {
        let [x0, x1, y0, y1] = region;
        let width = x1.saturating_sub(x0).max(1) as u64;
        let area = width * y1.saturating_sub(y0).max(1) as u64;
        PixelSequence {
            region,
            width,
            area,
            offset: run.offset as u64 % area,
            stride: run.stride as u64 % area,
        }
    }

    /// The `k`-th pixel's column and row.
    fn nth(&self, k: u64) -> (u32, u32) {
        let [x0, _, y0, _] = self.region;
        let index = (self.offset + (k % self.area) * self.stride) % self.area;
        (
            x0 + (index % self.width) as u32,
            y0 + (index / self.width) as u32,
        )
    }
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Mean of the 8-bit values in [0, 1] (0 for no pixels).
pub fn mean_brightness(pixels: &[u8]) -> f32 {
    let sum: u64 = pixels.iter().map(|&v| v as u64).sum();
    sum as f32 / (255.0 * pixels.len().max(1) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn foreground_box_covers_the_bright_pixels_with_a_margin() {
        let (w, h) = (32u32, 24u32);
        let lit = |i: usize| {
            let (x, y) = (i as u32 % w, i as u32 / w);
            (10..14).contains(&x) && (6..9).contains(&y)
        };
        let m = FOREGROUND_MARGIN;
        assert_eq!(foreground_box(w, h, lit), [10 - m, 14 + m, 6 - m, 9 + m]);
        // Clipped at the image border, and the whole image when nothing is lit.
        assert_eq!(foreground_box(w, h, |i| i == 0), [0, 1 + m, 0, 1 + m]);
        assert_eq!(foreground_box(w, h, |_| false), [0, w, 0, h]);
        // A stored box that does not fit its frame is not used.
        let meta = FrameMeta {
            width: w,
            height: h,
            foreground: [5, 40, 0, 3],
            ..FrameMeta::default()
        };
        assert_eq!(meta.foreground_box(), [0, w, 0, h]);
    }

    /// A frame's pixel sequence visits every pixel of its region once, and every prefix of it
    /// is spread over the region: each quarter of a 24 x 17 region (odd sides, to test the
    /// uneven split) holds its share of the first `m` pixels within a few pixels, where a
    /// stride of 1 would fill the top rows first.
    #[test]
    fn a_pixel_sequence_is_a_permutation_whose_prefixes_cover_the_region() {
        let region = [3, 27, 5, 22];
        for key in [0u64, 1, 0x9e37_79b9_7f4a_7c15, u64::MAX] {
            let sequence = PixelSequence::new(region, key);
            let mut seen = [false; 24 * 17];
            let mut quarters = [0i64; 4];
            for k in 0..sequence.area {
                let (x, y) = sequence.nth(k);
                assert!((3..27).contains(&x) && (5..22).contains(&y));
                let pixel = &mut seen[((y - 5) * 24 + x - 3) as usize];
                assert!(
                    !core::mem::replace(pixel, true),
                    "key {key}: ({x}, {y}) twice"
                );
                quarters[(x >= 15) as usize + 2 * (y >= 13) as usize] += 1;
                let m = k as i64 + 1;
                if m >= 16 {
                    // Quarter areas: 12 x 8 or 12 x 9 of the 24 x 17 pixels.
                    for (q, &n) in quarters.iter().enumerate() {
                        let expected = m * [96, 96, 108, 108][q] / 408;
                        assert!(
                            (n - expected).abs() <= 4 + m / 40,
                            "key {key}, {m}: {quarters:?}"
                        );
                    }
                }
            }
            assert!(seen.iter().all(|&s| s));
        }
    }
}
