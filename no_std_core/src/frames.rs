//! Frame slots: a fixed number of them, each holding a camera, a pose label, RGB8 pixels and
//! an optional foreground mask. The learnable per-frame parameters (appearance embedding and
//! pose correction) live beside them in the trainer and are reset with the slot.

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

/// The frame slots, borrowed from the arena.
pub struct FrameStore<'a> {
    pub(crate) meta: &'a mut [FrameMeta],
    pub(crate) pixels: &'a mut [u8],
    pub(crate) masks: &'a mut [u8],
    /// Indices of the occupied slots, in slot order; the first `len` entries are valid.
    pub(crate) occupied: &'a mut [u16],
    pub(crate) len: usize,
    pub(crate) max_pixels: usize,
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

    /// RGB8 pixels of an occupied slot.
    pub fn pixels(&self, slot: usize) -> Option<&[u8]> {
        let m = self.meta(slot)?;
        let n = m.width as usize * m.height as usize;
        self.pixels.get(slot * self.max_pixels * 3..)?.get(..n * 3)
    }

    /// Foreground mask of an occupied slot, if it has one.
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
        let base = slot * self.max_pixels;
        self.pixels[base * 3..base * 3 + n * 3].copy_from_slice(pixels);
        if let Some(mask) = mask {
            self.masks[base..base + n].copy_from_slice(mask);
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
        };
        self.rebuild_occupied();
        Ok(())
    }

    /// Empty a slot (no-op if it is already empty or out of range).
    pub fn clear(&mut self, slot: usize) {
        if let Some(m) = self.meta.get_mut(slot) {
            *m = FrameMeta::default();
            self.rebuild_occupied();
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
