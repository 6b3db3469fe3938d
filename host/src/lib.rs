//! orbit-nerf-host: the std harness around the no_std core.

pub mod ablation;
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
pub mod report;
pub mod scene_box;
pub mod sim;
pub mod stream;
pub mod sweep;
pub mod train;
pub mod values;

pub use error::{HostError, Result};
