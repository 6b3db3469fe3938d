//! One error type for the host: every variant names the file, and where it applies the field.

use std::path::PathBuf;

/// Every failure of the host library; each message starts with the file (or dataset) at fault.
#[derive(Debug, thiserror::Error)]
pub enum HostError {
    /// Reading or writing a file failed.
    #[error("{}: {source}", file.display())]
    Io {
        /// The file that could not be read or written.
        file: PathBuf,
        /// What the operating system reported.
        #[source]
        source: std::io::Error,
    },
    /// One field of a file holds a value that is refused (out of range, wrong type, missing).
    #[error("{}: field `{field}`: {reason}", file.display())]
    Field {
        /// The file that holds the field.
        file: PathBuf,
        /// The field's name or path within the file (e.g. `frames[3].transform_matrix`).
        field: String,
        /// Why the value is refused.
        reason: String,
    },
    /// A file, folder or other input is refused as a whole rather than for one field.
    #[error("{}: {reason}", file.display())]
    Invalid {
        /// The file or folder at fault, or a description of the input (e.g. a checkpoint's kind).
        file: PathBuf,
        /// Why it is refused.
        reason: String,
    },
    /// Renders that hold NaN or infinite pixels: the model (its parameters, or a config that
    /// overflows) produced garbage, and garbage is never scored.
    #[error(
        "{}: the renders of {} held non-finite pixels (NaN or infinite): the model is broken, no score is reported",
        dataset.display(),
        views.join(", ")
    )]
    NonFiniteRender {
        /// The dataset whose views were rendered.
        dataset: PathBuf,
        /// Names of the views whose renders held non-finite pixels.
        views: Vec<String>,
    },
    /// A failure reported by the core crate or the runtime around it (e.g. the thread pool),
    /// as its message.
    #[error("core: {0}")]
    Core(String),
    /// A run stopped on request before its last step, its state saved in `progress` (running it
    /// again continues from there).
    #[error(
        "stopped after step {step}; the run's state is in {}: run it again to continue",
        progress.display()
    )]
    Stopped {
        /// The file that holds the saved state.
        progress: PathBuf,
        /// The training step the run had completed when it stopped.
        step: u32,
    },
}

impl HostError {
    /// An [`HostError::Io`] failure of `file`.
    pub fn io(file: impl Into<PathBuf>, source: std::io::Error) -> Self {
        HostError::Io {
            file: file.into(),
            source,
        }
    }
    /// A [`HostError::Field`] failure: `field` of `file` is refused for `reason`.
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
    /// A [`HostError::Invalid`] failure: `file` is refused as a whole for `reason`.
    pub fn invalid(file: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        HostError::Invalid {
            file: file.into(),
            reason: reason.into(),
        }
    }
}

/// The host library's result, [`HostError`] unless stated otherwise.
pub type Result<T, E = HostError> = std::result::Result<T, E>;
