//! orbit-nerf-host: the std harness around the no_std core.

pub mod dataset;
pub mod error;
pub mod io;

pub use error::{HostError, Result};
