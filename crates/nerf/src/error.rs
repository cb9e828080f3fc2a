//! The library's error type. Every variant names the file or value at fault so the
//! binary can print it as is.

use std::path::PathBuf;

/// Everything that can go wrong in the library, each case naming what was wrong and where.
#[derive(Debug, thiserror::Error)]
pub enum NerfError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: malformed JSON: {source}")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: cannot decode image: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{path}: checkpoint problem: {message}")]
    Checkpoint { path: PathBuf, message: String },
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Something a command needs is not where it was looked for (the message says where).
    #[error("{0}")]
    NotFound(String),
    /// No such device, or the device failed (driver, out of device memory, lost device).
    #[error("GPU: {0}")]
    Device(String),
    #[error("training diverged at step {step}: {what} (the last good checkpoint is kept)")]
    Diverged { step: u64, what: String },
    #[error("{stage} produced a non-finite value at step {step}: {buffer}[{index}] = {value} (NERF_CHECK_FINITE)")]
    NonFinite {
        stage: &'static str,
        buffer: &'static str,
        step: u64,
        index: usize,
        value: f32,
    },
}

pub type Result<T, E = NerfError> = std::result::Result<T, E>;

impl NerfError {
    pub(crate) fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        NerfError::Format {
            path: path.into(),
            message: message.into(),
        }
    }
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        NerfError::Io {
            path: path.into(),
            source,
        }
    }
    pub(crate) fn write(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        NerfError::Write {
            path: path.into(),
            source,
        }
    }
}
