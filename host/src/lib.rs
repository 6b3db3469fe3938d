//! orbit-nerf-host: the std harness around the no_std core.

pub mod dataset;
pub mod error;

pub use error::{HostError, Result};
