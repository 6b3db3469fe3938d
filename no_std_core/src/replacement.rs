//! The replacement policy of the fixed-capacity frame store: which slot an arriving frame
//! takes once the store is full, or whether it is turned away.
//!
//! Each frame is described by its view direction (the unit vector from the centre of the
//! scene box to the camera) and its mean brightness (a cheap illumination descriptor). The
//! distance between two frames is the angle between their views divided by pi plus the
//! difference of their brightness, both in [0, 1].
//!
//! - [`Replacement::Fifo`]: every frame is admitted and replaces the oldest held frame.
//! - [`Replacement::Novelty`]: reservoir sampling weighted by novelty. The `n`-th frame offered
//!   (counting from 1) is admitted with probability `min(1, capacity / n * novelty / spacing)`,
//!   where `novelty` is its distance to the nearest held frame and `spacing` the mean
//!   nearest-neighbour distance among the held frames; so a frame like the typical held one
//!   gets plain reservoir odds, a near-duplicate almost none, a new viewpoint or lighting more.
//!   An admitted frame replaces the most redundant held frame: the one whose nearest neighbour
//!   (among the other held frames and the new one) is closest, the oldest on ties.
//! - [`Replacement::Coverage`]: every frame is admitted (so every frame is trained on for a
//!   while, as with FIFO) and replaces the most redundant held frame, as above: distinct views
//!   and lighting stay, near-duplicates cycle.
//!
//! The admission draw comes from the core's seeded RNG (its own domain), keyed by the arrival
//! number, so the held set depends only on the config, the seed and the arrival order.

use crate::config::{Config, Replacement};
use crate::frames::{FrameMeta, FrameStore};
use crate::rng::{self, domain};
use crate::{Error, Pose};
use glam::Vec3;

/// What `Trainer::ingest_frame` did with a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Ingested {
    /// Stored in `slot`, replacing whatever it held.
    Stored {
        /// Index of the frame slot that now holds the frame.
        slot: usize,
    },
    /// The policy kept the held frames instead.
    Rejected,
}

/// Where a frame was seen from and how bright it was: what the policy compares.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Descriptor {
    /// Unit vector from the scene box's centre to the camera.
    pub view: Vec3,
    /// Mean pixel value in [0, 1].
    pub brightness: f32,
}

impl Descriptor {
    /// Describe a frame taken from `pose` with mean pixel value `brightness`.
    pub fn new(config: &Config, pose: &Pose, brightness: f32) -> Descriptor {
        let centre = 0.5 * (Vec3::from_array(config.aabb_min) + Vec3::from_array(config.aabb_max));
        let offset = pose.center - centre;
        let length = libm::sqrtf(offset.length_squared());
        // A camera at the centre has no direction to the scene: use its optical axis reversed.
        let view = if length > 0.0 {
            offset * (1.0 / length)
        } else {
            -(pose.rotation * Vec3::Z)
        };
        Descriptor { view, brightness }
    }

    fn of(config: &Config, meta: &FrameMeta) -> Descriptor {
        Descriptor::new(config, &meta.pose(), meta.brightness)
    }

    /// Angle between the views over pi plus the brightness difference.
    pub fn distance(&self, other: &Descriptor) -> f32 {
        let cos = self.view.dot(other.view).clamp(-1.0, 1.0);
        libm::acosf(cos) * core::f32::consts::FRAC_1_PI + (self.brightness - other.brightness).abs()
    }
}

/// Refuse images that carry nothing to learn: every value 0 (black) or every value 255
/// (saturated).
pub fn check_exposure(pixels: &[u8]) -> Result<(), Error> {
    if pixels.iter().all(|&v| v == 0) {
        return Err(Error::InvalidFrame {
            field: "pixels (all black)",
        });
    }
    if pixels.iter().all(|&v| v == u8::MAX) {
        return Err(Error::InvalidFrame {
            field: "pixels (all saturated)",
        });
    }
    Ok(())
}

/// The slot an arriving frame goes to, or `None` to turn it away. `arrival` counts the frames
/// offered to the store before this one. A free slot (the lowest) is always taken first.
pub fn choose_slot(
    config: &Config,
    frames: &FrameStore<'_>,
    incoming: &Descriptor,
    arrival: u32,
) -> Option<usize> {
    if frames.len() < frames.capacity() {
        return (0..frames.capacity()).find(|&slot| frames.meta(slot).is_none());
    }
    match config.replacement {
        Replacement::Fifo => oldest(frames),
        Replacement::Novelty => novelty_reservoir(config, frames, incoming, arrival),
        Replacement::Coverage => redundancy(config, frames, incoming).victim,
    }
}

/// The occupied slot with the lowest arrival number (the lowest slot on ties).
fn oldest(frames: &FrameStore<'_>) -> Option<usize> {
    let mut best: Option<(u32, usize)> = None;
    for i in 0..frames.len() {
        let Some(slot) = frames.occupied_slot(i) else {
            continue;
        };
        let Some(meta) = frames.meta(slot) else {
            continue;
        };
        if best.is_none_or(|(arrival, _)| meta.arrival < arrival) {
            best = Some((meta.arrival, slot));
        }
    }
    best.map(|(_, slot)| slot)
}

/// What the held frames look like from an incoming one.
struct Redundancy {
    /// The held frame whose nearest neighbour (among the other held frames and the incoming
    /// one) is closest, the oldest on ties.
    victim: Option<usize>,
    /// Distance from the incoming frame to the nearest held frame.
    novelty: f32,
    /// Mean nearest-neighbour distance among the held frames.
    spacing: f32,
}

fn redundancy(config: &Config, frames: &FrameStore<'_>, incoming: &Descriptor) -> Redundancy {
    let held = frames.len();
    let descriptor = |i: usize| {
        let slot = frames.occupied_slot(i)?;
        Some((slot, frames.meta(slot)?))
    };
    let mut novelty = f32::INFINITY;
    let mut spacing_sum = 0.0f32;
    let mut spaced = 0u32;
    // (nearest-neighbour distance, arrival, slot) of the most redundant held frame.
    let mut victim: Option<(f32, u32, usize)> = None;
    for i in 0..held {
        let Some((slot, meta)) = descriptor(i) else {
            continue;
        };
        let own = Descriptor::of(config, meta);
        let to_incoming = own.distance(incoming);
        novelty = novelty.min(to_incoming);
        let mut nearest_held = f32::INFINITY;
        for j in (0..held).filter(|&j| j != i) {
            if let Some((_, other)) = descriptor(j) {
                nearest_held = nearest_held.min(own.distance(&Descriptor::of(config, other)));
            }
        }
        if nearest_held.is_finite() {
            spacing_sum += nearest_held;
            spaced += 1;
        }
        let nearest = nearest_held.min(to_incoming);
        let more_redundant =
            victim.is_none_or(|(d, a, _)| nearest < d || (nearest == d && meta.arrival < a));
        if more_redundant && !nearest.is_nan() {
            victim = Some((nearest, meta.arrival, slot));
        }
    }
    Redundancy {
        victim: victim.map(|(_, _, slot)| slot),
        novelty,
        spacing: spacing_sum / spaced.max(1) as f32,
    }
}

fn novelty_reservoir(
    config: &Config,
    frames: &FrameStore<'_>,
    incoming: &Descriptor,
    arrival: u32,
) -> Option<usize> {
    let Redundancy {
        victim,
        novelty,
        spacing,
    } = redundancy(config, frames, incoming);
    let ratio = if spacing > 0.0 {
        novelty / spacing
    } else if novelty > 0.0 {
        f32::INFINITY
    } else {
        1.0
    };
    let odds = frames.capacity() as f32 / (arrival as f32 + 1.0) * ratio;
    let draw = rng::unit_f32(rng::hash(config.seed, domain::ADMIT, arrival as u64, 0));
    // A NaN descriptor compares false here and keeps the held frames.
    if draw < odds { victim } else { None }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Camera;
    use glam::Mat3;

    const CAPACITY: usize = 4;

    /// A store of 2x2-pixel slots over caller arrays (what the trainer carves from its arena).
    struct Slots {
        meta: [FrameMeta; CAPACITY],
        pixels: [u8; CAPACITY * 12],
        masks: [u8; CAPACITY * 4],
        occupied: [u16; CAPACITY],
    }

    impl Slots {
        fn new() -> Slots {
            Slots {
                meta: [FrameMeta::default(); CAPACITY],
                pixels: [0; CAPACITY * 12],
                masks: [0; CAPACITY * 4],
                occupied: [0; CAPACITY],
            }
        }
        fn store(&mut self) -> FrameStore<'_> {
            let mut store = FrameStore {
                meta: &mut self.meta,
                pixels: &mut self.pixels,
                masks: &mut self.masks,
                occupied: &mut self.occupied,
                len: 0,
                max_pixels: 4,
                foreground_rays: 0,
                keep_rays: false,
            };
            store.rebuild_occupied();
            store
        }
    }

    fn config(replacement: Replacement) -> Config {
        let mut c = Config::DEFAULT;
        c.max_frames = CAPACITY as u16;
        c.replacement = replacement;
        c
    }

    /// A camera 3 units from the origin in the direction at `azimuth_deg` around z.
    fn pose(azimuth_deg: f32) -> Pose {
        let a = azimuth_deg.to_radians();
        Pose {
            rotation: Mat3::from_rotation_z(a),
            center: Vec3::new(3.0 * libm::cosf(a), 3.0 * libm::sinf(a), 0.0),
        }
    }

    /// Offer frames seen from `azimuths` (all equally bright) in order; returns the arrival
    /// number held by each slot at the end and the slot chosen for each frame.
    fn stream_views(
        replacement: Replacement,
        azimuths: &[f32],
    ) -> ([u32; CAPACITY], [Option<usize>; 64]) {
        let c = config(replacement);
        let camera = Camera {
            width: 2,
            height: 2,
            fx: 2.0,
            fy: 2.0,
            cx: 1.0,
            cy: 1.0,
        };
        let pixels = [100u8; 12];
        let mut slots = Slots::new();
        let mut store = slots.store();
        let mut chosen = [None; 64];
        for (arrival, &azimuth) in azimuths.iter().enumerate() {
            let p = pose(azimuth);
            let incoming = Descriptor::new(&c, &p, 100.0 / 255.0);
            let slot = choose_slot(&c, &store, &incoming, arrival as u32);
            if let Some(slot) = slot {
                store.set(slot, camera, p, &pixels, None).unwrap();
                store.set_arrival(slot, arrival as u32);
            }
            assert!(store.len() <= CAPACITY);
            chosen[arrival] = slot;
        }
        let mut held = [u32::MAX; CAPACITY];
        for (slot, h) in held.iter_mut().enumerate() {
            if let Some(m) = store.meta(slot) {
                *h = m.arrival;
            }
        }
        (held, chosen)
    }

    #[test]
    fn fifo_fills_free_slots_then_evicts_the_oldest() {
        let azimuths: [f32; 10] = core::array::from_fn(|i| i as f32 * 10.0);
        let (held, chosen) = stream_views(Replacement::Fifo, &azimuths);
        // Slots 0..3 fill in order, then arrivals 4..9 replace the oldest each time.
        assert_eq!(&chosen[..10], &[0, 1, 2, 3, 0, 1, 2, 3, 0, 1].map(Some));
        let mut sorted = held;
        sorted.sort_unstable();
        assert_eq!(sorted, [6, 7, 8, 9]);
    }

    #[test]
    fn novelty_keeps_distinct_views_among_near_duplicates() {
        // Three distinct views (0, 120, 240 degrees), then 40 near-copies of the view at 60
        // degrees interleaved with repeats of the distinct ones.
        let mut azimuths = [0.0f32; 43];
        azimuths[..3].copy_from_slice(&[0.0, 120.0, 240.0]);
        for (k, a) in azimuths[3..].iter_mut().enumerate() {
            *a = 60.0 + 0.01 * k as f32;
        }
        let (held, _) = stream_views(Replacement::Novelty, &azimuths);
        for distinct in 0..3 {
            assert!(held.contains(&distinct), "lost view {distinct}: {held:?}");
        }
        assert!(held.iter().all(|&a| a != u32::MAX), "the store is full");
        // Coverage admits every frame and keeps the distinct ones too.
        let (coverage, chosen) = stream_views(Replacement::Coverage, &azimuths);
        for distinct in 0..3 {
            assert!(
                coverage.contains(&distinct),
                "lost view {distinct}: {coverage:?}"
            );
        }
        assert!(coverage.contains(&42) && chosen[..43].iter().all(Option::is_some));
        // FIFO keeps only the last four near-duplicates.
        let (fifo, _) = stream_views(Replacement::Fifo, &azimuths);
        assert!(fifo.iter().all(|&a| a >= 39), "{fifo:?}");
    }

    #[test]
    fn the_policy_is_deterministic_and_turns_near_duplicates_away() {
        let azimuths: [f32; 64] = core::array::from_fn(|i| (i * 37 % 360) as f32);
        let first = stream_views(Replacement::Novelty, &azimuths);
        assert_eq!(first, stream_views(Replacement::Novelty, &azimuths));
        // An exact copy of a held view has no novelty and is never admitted.
        let mut copies = [0.0f32; 20];
        copies[..CAPACITY].copy_from_slice(&[0.0, 90.0, 180.0, 270.0]);
        for (k, a) in copies[CAPACITY..].iter_mut().enumerate() {
            *a = 90.0 * (k % 4) as f32;
        }
        let (held, chosen) = stream_views(Replacement::Novelty, &copies);
        assert_eq!(held, [0, 1, 2, 3]);
        assert!(chosen[CAPACITY..20].iter().all(Option::is_none));
    }

    #[test]
    fn black_and_saturated_images_are_refused() {
        assert!(check_exposure(&[0; 12]).is_err());
        assert!(check_exposure(&[255; 12]).is_err());
        assert!(check_exposure(&[0, 255, 0]).is_ok());
        let far = Descriptor::new(&config(Replacement::Novelty), &pose(180.0), 1.0);
        let near = Descriptor::new(&config(Replacement::Novelty), &pose(0.0), 0.0);
        assert!((far.distance(&near) - 2.0).abs() < 1e-5);
    }
}
