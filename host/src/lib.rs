//! orbit-nerf-host: the std harness around the no_std core.

pub mod ablation;
pub mod checkpoint;
pub mod dataset;
pub mod error;
pub mod io;
pub mod metrics;
pub mod nerf_formats;
pub mod report;
pub mod scene_box;
pub mod sim;
pub mod speedplus;
pub mod stream;
pub mod train;

pub use error::{HostError, Result};
