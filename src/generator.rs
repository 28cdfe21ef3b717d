//! One generation: text → condition → token steps → decoded 16-frame chunks → assembled
//! frames, as a [`ChunkSource`] driven by a stream's worker thread.
//! (Pipeline wiring pending: the bundle, model and sampler modules are being written.)
pub use crate::stream::ChunkSource;

use crate::engine::{EngineConfig, SourceFactory};
use crate::error::{Error, Result};

/// Loads the bundle named by the config and returns the factory that builds one
/// generator per stream.
pub fn source_factory(config: &EngineConfig) -> Result<SourceFactory> {
    let path = config.bundle_path.clone().unwrap_or_default();
    Err(Error::bundle(path, "bundle loading is not wired into the engine yet"))
}
