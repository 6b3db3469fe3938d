//! Frame slots: a fixed number of them, each holding a camera, a pose label and, in one of two
//! ways, the frame's pixels. The learnable per-frame parameters (appearance embedding and pose
//! correction) live beside them in the trainer and are reset with the slot.
//!
//! - **Whole frames** (`Config::ray_store` = 0): each slot keeps every RGB8 pixel of its frame
//!   and an optional foreground mask.
//! - **A ray reservoir** (`ray_store` = N > 0): the slots keep only camera, label and
//!   parameters (so a stream can remember many more frames than it could hold whole), and N
//!   pixels of all the frames stored so far sit in one shared reservoir, each with its slot,
//!   position and mask value ([`RayEntry`], 10 bytes). The reservoir has two parts, as the
//!   training rays have: a share `foreground_fraction` of pixels drawn inside their frame's
//!   foreground box and the rest drawn from the whole image. Each frame offers each part an
//!   eighth of its size (distinct pixels while the region has that many), and the part keeps
//!   offers by reservoir sampling (Vitter's algorithm R, the seeded RNG deciding), so once the
//!   reservoir is full every frame stored so far holds the same share of it in expectation:
//!   training sees the whole past, not only the latest frames. A frame put into an occupied
//!   slot takes over its predecessor's entries (drawn from the new frame), so the reservoir
//!   stays full; an emptied slot's entries are removed.

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

/// One pixel kept in the ray reservoir: its frame slot, its position, its colour and its mask
/// value (255 without a mask). Bytes only, so the reservoir is any byte buffer.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RayEntry {
    slot: [u8; 2],
    x: [u8; 2],
    y: [u8; 2],
    /// RGB8 colour.
    pub rgb: [u8; 3],
    /// Mask value (0 sky .. 255 target).
    pub alpha: u8,
}

/// Bytes of one [`RayEntry`].
pub const RAY_ENTRY_BYTES: usize = core::mem::size_of::<RayEntry>();
const _: () = assert!(RAY_ENTRY_BYTES == 10);

impl RayEntry {
    /// The frame slot the pixel belongs to.
    pub fn slot(&self) -> usize {
        u16::from_le_bytes(self.slot) as usize
    }
    /// Pixel column and row.
    pub fn position(&self) -> (u32, u32) {
        (
            u16::from_le_bytes(self.x) as u32,
            u16::from_le_bytes(self.y) as u32,
        )
    }
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

    /// The ray reservoir's entries (empty for whole frames): the whole-image part, then the
    /// foreground part, each filled from its start.
    pub fn ray_entries(&self) -> &[RayEntry] {
        if self.keeps_rays() {
            bytemuck::cast_slice(
                &self.pixels[..self.pixels.len() / RAY_ENTRY_BYTES * RAY_ENTRY_BYTES],
            )
        } else {
            &[]
        }
    }

    /// Where each part of the reservoir starts and how many entries it can hold.
    fn ray_parts(&self) -> [(usize, usize); 2] {
        let total = self.pixels.len() / RAY_ENTRY_BYTES;
        let foreground = self.foreground_rays.min(total);
        [(0, total - foreground), (total - foreground, foreground)]
    }

    /// Reservoir entry `index` of `part` (0 whole image, 1 foreground box) among the filled
    /// ones: the `n`-th is `ray_entry(part, n)` for `n < counts.filled[part]`.
    pub(crate) fn ray_entry(&self, part: usize, index: usize) -> Option<RayEntry> {
        let (start, len) = *self.ray_parts().get(part)?;
        if index >= len {
            return None;
        }
        let at = (start + index) * RAY_ENTRY_BYTES;
        Some(bytemuck::pod_read_unaligned(
            self.pixels.get(at..at + RAY_ENTRY_BYTES)?,
        ))
    }

    fn put_ray_entry(&mut self, part: usize, index: usize, entry: RayEntry) {
        let (start, len) = self.ray_parts()[part];
        if index < len {
            let at = (start + index) * RAY_ENTRY_BYTES;
            self.pixels[at..at + RAY_ENTRY_BYTES].copy_from_slice(bytemuck::bytes_of(&entry));
        }
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
        };
        self.rebuild_occupied();
        Ok(())
    }

    /// Empty a slot (no-op if it is already empty or out of range), removing its reservoir
    /// entries.
    pub fn clear(&mut self, slot: usize, counts: &mut RayCounts) {
        if let Some(m) = self.meta.get_mut(slot) {
            *m = FrameMeta::default();
            self.rebuild_occupied();
            self.remove_rays(slot, counts);
        }
    }

    /// Remove the reservoir entries of `slot`, moving the last filled entry of the part into
    /// each hole (the order of entries carries no meaning).
    fn remove_rays(&mut self, slot: usize, counts: &mut RayCounts) {
        for part in 0..2 {
            let mut index = 0;
            while index < counts.filled[part] as usize {
                match self.ray_entry(part, index) {
                    Some(entry) if entry.slot() == slot => {
                        self.swap_remove_ray(part, index, counts)
                    }
                    Some(_) => index += 1,
                    None => break,
                }
            }
        }
    }

    /// Remove entry `index` of `part`, moving the part's last filled entry into its place.
    fn swap_remove_ray(&mut self, part: usize, index: usize, counts: &mut RayCounts) {
        counts.filled[part] -= 1;
        let last = counts.filled[part] as usize;
        if let Some(moved) = self.ray_entry(part, last) {
            self.put_ray_entry(part, index, moved);
        }
    }

    /// Give the frame just put into `slot` (by [`FrameStore::set`]) its share of the ray
    /// reservoir: in each part, an equal share of the part among the frames remembered (one
    /// over their number), but never more pixels than the part's region of the frame holds
    /// (each pixel once, in a seeded stride permutation). First it takes over the entries of
    /// the frame the slot held before (the rest of them leave the part), then it fills free
    /// places, then it overwrites places drawn uniformly, so every earlier frame gives up
    /// the same fraction of its entries and the first frames and the last are held alike.
    /// Every choice comes from the seeded RNG keyed by the frames offered so far, so the
    /// reservoir depends only on the seed and the frames in order. A no-op for whole frames.
    /// Allocates nothing.
    pub(crate) fn offer_rays(
        &mut self,
        slot: usize,
        pixels: &[u8],
        mask: Option<&[u8]>,
        seed: u64,
        counts: &mut RayCounts,
        replaced: bool,
    ) {
        let Some(meta) = self.meta(slot).copied() else {
            return;
        };
        if !self.keeps_rays() {
            return;
        }
        let [fx0, fx1, fy0, fy1] = meta.foreground_box();
        let regions = [[0, meta.width, 0, meta.height], [fx0, fx1, fy0, fy1]];
        let remembered = self.len.max(1);
        for (part, region) in regions.into_iter().enumerate() {
            let (_, capacity) = self.ray_parts()[part];
            if capacity == 0 {
                continue;
            }
            let offer = counts.offered[part];
            counts.offered[part] = offer.saturating_add(1);
            let key = rng::hash(seed, domain::RESERVOIR, offer, part as u64);
            let mut pick = PixelPicker::new(region, key);
            // Past its area the picker would repeat pixels: a pixel kept twice is a byte
            // wasted.
            let share = (capacity.div_ceil(remembered) as u64).min(pick.area) as usize;
            let entry_of = |picker: &mut PixelPicker| {
                let (x, y) = picker.next();
                let at = (y * meta.width + x) as usize;
                RayEntry {
                    slot: (slot as u16).to_le_bytes(),
                    x: (x as u16).to_le_bytes(),
                    y: (y as u16).to_le_bytes(),
                    rgb: core::array::from_fn(|ch| pixels.get(at * 3 + ch).copied().unwrap_or(0)),
                    alpha: mask.map_or(u8::MAX, |m| m.get(at).copied().unwrap_or(0)),
                }
            };
            let mut placed = 0;
            if replaced {
                // The predecessor's entries, as many as the share; the rest leave the part
                // (swap-removed: the entry moved into the hole is looked at next).
                let mut index = 0;
                while index < counts.filled[part] as usize {
                    match self.ray_entry(part, index) {
                        Some(e) if e.slot() == slot && placed < share => {
                            let entry = entry_of(&mut pick);
                            self.put_ray_entry(part, index, entry);
                            placed += 1;
                            index += 1;
                        }
                        Some(e) if e.slot() == slot => self.swap_remove_ray(part, index, counts),
                        Some(_) => index += 1,
                        None => break,
                    }
                }
            }
            for n in placed..share {
                let filled = counts.filled[part] as usize;
                let index = if filled < capacity {
                    counts.filled[part] += 1;
                    filled
                } else {
                    // A place drawn uniformly: every frame held gives up entries in
                    // proportion to those it holds (this frame's own new ones included).
                    rng::below(rng::hash(key, n as u64, 1, 0), capacity as u32) as usize
                };
                let entry = entry_of(&mut pick);
                self.put_ray_entry(part, index, entry);
            }
        }
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

/// Distinct pixels of a region `[x0, x1, y0, y1)` in a seeded order: `(stride * k + offset) mod
/// area` with the stride coprime to the area visits every pixel once per `area` draws.
struct PixelPicker {
    region: [u32; 4],
    area: u64,
    stride: u64,
    next: u64,
}

impl PixelPicker {
    fn new(region: [u32; 4], bits: u64) -> PixelPicker {
        let [x0, x1, y0, y1] = region;
        let area = (x1.saturating_sub(x0) as u64 * y1.saturating_sub(y0) as u64).max(1);
        let mut stride = ((bits >> 32) % area) | 1;
        while gcd(stride, area) != 1 {
            stride += 1;
        }
        PixelPicker {
            region,
            area,
            stride,
            next: (bits & 0xffff_ffff) % area,
        }
    }

    /// The next pixel's column and row.
    fn next(&mut self) -> (u32, u32) {
        let [x0, x1, y0, _] = self.region;
        let index = self.next;
        self.next = (self.next + self.stride) % self.area;
        let width = x1.saturating_sub(x0).max(1) as u64;
        (x0 + (index % width) as u32, y0 + (index / width) as u32)
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
}
