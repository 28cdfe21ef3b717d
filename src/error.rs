//! The engine's error type. Every failure is a value with a precise message; the C ABI maps
//! each variant to a status code (`ffi::status`) and keeps the message as the last error.
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A bundle file is missing, unreadable, corrupt, or disagrees with the manifest.
    /// `path` is the file at fault, or empty when no file is (e.g. no bundle selected).
    #[error("bundle{}: {msg}", at(.path))]
    Bundle { path: PathBuf, msg: String },
    /// An argument is invalid (empty or over-long text, bad config value...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A call made in the wrong state (e.g. polling a finished stream's worker twice).
    #[error("wrong call order: {0}")]
    WrongState(String),
    /// The inference runtime failed while running a graph.
    #[error("inference failed: {0}")]
    Inference(String),
    /// The stream was cancelled.
    #[error("cancelled")]
    Cancelled,
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
    /// A fixed limit is reached (e.g. the engine's `max_streams`); retry after releasing something.
    #[error("limit reached: {0}")]
    LimitReached(String),
    /// A panic was caught (on a stream's worker thread or at the C boundary); the text is the
    /// panic message. The object it happened in is no longer trusted.
    #[error("internal panic: {0}")]
    Panic(String),
    /// Shared memory (iceoryx2) failed: a service could not be created or opened (e.g. its
    /// settings disagree with an existing one of the same name), or receiving failed.
    #[error("shared memory: {0}")]
    SharedMemory(String),
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn bundle(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Error::Bundle { path: path.into(), msg: msg.into() }
    }
}

/// ` <path>`, or nothing for an empty path (so the message does not read "bundle : ...").
fn at(path: &Path) -> String {
    if path.as_os_str().is_empty() {
        String::new()
    } else {
        format!(" {}", path.display())
    }
}
