//! orbit-nerf-core: a K-Planes radiance field trained inside one caller-provided byte arena.
//!
//! No heap, no panics on input, bit-identical results for the same config, frames and seed
//! on every target. The host brings threads through [`Executor`]; the core never depends on
//! which thread ran which chunk.
#![no_std]
#![deny(unsafe_code)]
#![warn(missing_docs)]
// The kernels index several structure-of-arrays rows by the same lane or feature.
#![allow(clippy::needless_range_loop)]

mod arena;
pub mod camera;
pub mod config;
pub(crate) mod field;
pub(crate) mod frames;
pub(crate) mod fused;
pub(crate) mod optim;
pub mod profile;
pub(crate) mod render;
pub mod replacement;
pub mod rng;
pub mod trainer;

pub use camera::{Camera, Pose, PoseCorrection};
pub use config::{Config, MAX_RAY_STORE, MemoryPlan, PosePivot, Replacement, TexelUpdate};
pub use frames::{RAY_ENTRY_BYTES, RayCounts, RayEntry, RayPixel, RayRun};
pub use fused::{allow_wide_vectors, wide_vectors};
pub use glam;
pub use replacement::Ingested;
pub use trainer::{Executor, PoseFit, Sequential, StepReport, Trainer};

/// Everything that can go wrong in the core; each names what was wrong.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// A config field is out of range.
    InvalidConfig {
        /// Name of the first bad field (or group, such as `aabb`).
        field: &'static str,
    },
    /// The arena is smaller than the memory plan.
    ArenaTooSmall {
        /// Bytes the plan needs (`MemoryPlan::total`).
        needed: usize,
        /// Bytes the caller gave.
        got: usize,
    },
    /// A frame was rejected; `field` names the bad part.
    InvalidFrame {
        /// The bad part: `camera`, `pixels`, `mask`, `pose`, `slot` or `columns`.
        field: &'static str,
    },
    /// A frame has more pixels than a slot holds.
    FrameTooLarge {
        /// Pixels of the frame.
        pixels: usize,
        /// Pixels a slot holds (`Config::max_pixels_per_frame`).
        capacity: usize,
    },
    /// Training needs at least one frame.
    NoFrames,
    /// A caller buffer has the wrong length.
    BufferSize {
        /// Name of the buffer.
        what: &'static str,
        /// Length it must have, in elements.
        expected: usize,
        /// Length it has.
        got: usize,
    },
    /// A render-only trainer was asked to train, fit, refresh occupancy or take a frame.
    RenderOnly,
    /// A checkpoint section has the wrong size.
    BadSection {
        /// Section name.
        name: &'static str,
        /// Bytes the section has in this trainer.
        expected: usize,
        /// Bytes given.
        got: usize,
    },
    /// A checkpoint section holds a NaN or an infinity (at element `index`), which would
    /// stall every step after the restore.
    NonFiniteSection {
        /// Section name.
        name: &'static str,
        /// Index of the first non-finite element.
        index: usize,
    },
    /// A checkpoint section name is not one of `Trainer::sections`.
    UnknownSection,
    /// The caller could not supply a section's bytes (a read failed part-way).
    SectionNotRead {
        /// Section name.
        name: &'static str,
    },
    /// A checkpoint's frame slot holds an invalid camera or a frame larger than a slot.
    BadFrameSlot {
        /// Index of the bad slot.
        slot: usize,
    },
    /// An arena part cannot hold values of this alignment (a part starts on `part_align`).
    Misaligned {
        /// Alignment in bytes that every arena part starts on (`PART_ALIGN`).
        part_align: usize,
        /// Alignment in bytes the value type needs.
        type_align: usize,
    },
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Error::InvalidConfig { field } => write!(f, "invalid config field `{field}`"),
            Error::ArenaTooSmall { needed, got } => {
                write!(f, "arena too small: {needed} bytes needed, {got} given")
            }
            Error::InvalidFrame { field } => write!(f, "invalid frame: `{field}`"),
            Error::FrameTooLarge { pixels, capacity } => {
                write!(
                    f,
                    "frame has {pixels} pixels but a slot holds {capacity} (max_pixels_per_frame)"
                )
            }
            Error::NoFrames => write!(f, "no frames to train on"),
            Error::RenderOnly => write!(f, "this trainer was built render-only"),
            Error::BufferSize {
                what,
                expected,
                got,
            } => write!(f, "`{what}` has length {got}, expected {expected}"),
            Error::BadSection {
                name,
                expected,
                got,
            } => {
                write!(
                    f,
                    "checkpoint section `{name}` has {got} bytes, expected {expected}"
                )
            }
            Error::NonFiniteSection { name, index } => write!(
                f,
                "checkpoint section `{name}` holds a non-finite value (element {index})"
            ),
            Error::UnknownSection => write!(f, "checkpoint section is not one of the trainer's"),
            Error::SectionNotRead { name } => {
                write!(f, "checkpoint section `{name}` could not be read")
            }
            Error::BadFrameSlot { slot } => write!(
                f,
                "checkpoint frame slot {slot} holds an invalid camera or a frame larger than a slot"
            ),
            Error::Misaligned {
                part_align,
                type_align,
            } => write!(
                f,
                "arena parts start on {part_align} bytes, values need {type_align}"
            ),
        }
    }
}

impl core::error::Error for Error {}
