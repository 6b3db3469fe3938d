//! orbit-nerf-core: a K-Planes radiance field trained inside one caller-provided byte arena.
//!
//! No heap, no panics on input, bit-identical results for the same config, frames and seed
//! on every target. The host brings threads through [`Executor`]; the core never depends on
//! which thread ran which chunk.
#![no_std]
#![deny(unsafe_code)]
// The kernels index several structure-of-arrays rows by the same lane or feature.
#![allow(clippy::needless_range_loop)]

mod arena;
pub mod camera;
pub mod config;
pub(crate) mod field;
pub(crate) mod frames;
pub(crate) mod optim;
pub(crate) mod render;
pub mod replacement;
pub mod rng;
pub mod trainer;

pub use camera::{Camera, Pose, PoseCorrection};
pub use config::{Config, MemoryPlan, PosePivot, Replacement, TexelUpdate};
pub use glam;
pub use replacement::Ingested;
pub use trainer::{Executor, Sequential, StepReport, Trainer};

/// Everything that can go wrong in the core; each names what was wrong.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// A config field is out of range.
    InvalidConfig { field: &'static str },
    /// The arena is smaller than the memory plan.
    ArenaTooSmall { needed: usize, got: usize },
    /// A frame was rejected; `field` names the bad part.
    InvalidFrame { field: &'static str },
    /// A frame has more pixels than a slot holds.
    FrameTooLarge { pixels: usize, capacity: usize },
    /// Training needs at least one frame.
    NoFrames,
    /// A caller buffer has the wrong length.
    BufferSize {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// A render-only trainer was asked to train, fit, refresh occupancy or take a frame.
    RenderOnly,
    /// A checkpoint section has the wrong size.
    BadSection {
        name: &'static str,
        expected: usize,
        got: usize,
    },
    /// A checkpoint section holds a NaN or an infinity (at element `index`), which would
    /// stall every step after the restore.
    NonFiniteSection { name: &'static str, index: usize },
    /// A checkpoint section name is not one of `Trainer::sections`.
    UnknownSection,
    /// A checkpoint's frame slot holds an invalid camera or a frame larger than a slot.
    BadFrameSlot { slot: usize },
    /// An arena part cannot hold values of this alignment (a part starts on `part_align`).
    Misaligned {
        part_align: usize,
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
