//! orbit-nerf-host: the std harness around the `no_std` core (`orbit_nerf_core`).
//!
//! [`pipeline`] is the front door: open a dataset folder of any supported format with its
//! settings ([`pipeline::DataSettings`]), choose the preset and the scene box, check memory
//! against the plan, train with an observer (progress, anytime scoring, stop and resume),
//! evaluate the held-out views and write the run's outputs. The other modules are its parts:
//! dataset [`formats`], [`checkpoint`]s, the core's [`train`]ing glue, [`metrics`] and
//! [`report`]s, [`geometry`] export, new-view [`orbit`]s and online [`stream`]ing.
//!
//! Features (all on by default; `default-features = false` leaves the pipeline, formats,
//! checkpoints, geometry and streaming from folders):
//! - `simulator`: the scene simulator ([`sim`]), the paper's experiments on simulated scenes
//!   ([`ablation_report`]), sweeps ([`sweep`]) and simulated streams.
//! - `plots`: PNG plots in reports (without it the reports' plots are not drawn).
//! - `slurm`: sweeps as Slurm job arrays.
//! - `profile`: per-stage timings of training steps and renders (the `profile` module).
#![warn(missing_docs)]

pub mod ablation;
#[cfg(feature = "simulator")]
pub mod ablation_report;
pub mod checkpoint;
pub mod dataset;
pub mod error;
pub mod formats;
pub mod geometry;
pub mod io;
pub mod machine;
pub mod memory;
pub mod metrics;
pub mod orbit;
pub mod pipeline;
pub mod presets;
#[cfg(feature = "profile")]
pub mod profile;
pub mod progress;
pub mod reference;
pub mod report;
pub mod scene_box;
#[cfg(feature = "simulator")]
pub mod sim;
pub mod stream;
#[cfg(feature = "simulator")]
pub mod sweep;
pub mod train;
pub mod values;

pub use error::{HostError, Result};
