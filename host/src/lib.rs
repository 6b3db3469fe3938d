//! orbit-nerf-host: the std harness around the no_std core.

pub mod dataset;
pub mod error;
pub mod io;
pub mod sim;
pub mod speedplus;
pub mod checkpoint;
pub mod metrics;
pub mod nerf_formats;

pub use error::{HostError, Result};
