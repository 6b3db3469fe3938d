//! One error type for the host: every variant names the file, and where it applies the field.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum HostError {
    #[error("{}: {source}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: field `{field}`: {reason}", file.display())]
    Field {
        file: PathBuf,
        field: String,
        reason: String,
    },
    #[error("{}: {reason}", file.display())]
    Invalid { file: PathBuf, reason: String },
    /// Renders that hold NaN or infinite pixels: the model (its parameters, or a config that
    /// overflows) produced garbage, and garbage is never scored.
    #[error(
        "{}: the renders of {} held non-finite pixels (NaN or infinite): the model is broken, no score is reported",
        dataset.display(),
        views.join(", ")
    )]
    NonFiniteRender {
        dataset: PathBuf,
        views: Vec<String>,
    },
    #[error("core: {0}")]
    Core(String),
    /// A run stopped on request before its last step, its state saved in `progress` (running it
    /// again continues from there).
    #[error(
        "stopped after step {step}; the run's state is in {}: run it again to continue",
        progress.display()
    )]
    Stopped { progress: PathBuf, step: u32 },
}

impl HostError {
    pub fn io(file: impl Into<PathBuf>, source: std::io::Error) -> Self {
        HostError::Io {
            file: file.into(),
            source,
        }
    }
    pub fn field(
        file: impl Into<PathBuf>,
        field: impl Into<String>,
        reason: impl Into<String>,
    ) -> Self {
        HostError::Field {
            file: file.into(),
            field: field.into(),
            reason: reason.into(),
        }
    }
    pub fn invalid(file: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        HostError::Invalid {
            file: file.into(),
            reason: reason.into(),
        }
    }
}

pub type Result<T, E = HostError> = std::result::Result<T, E>;
