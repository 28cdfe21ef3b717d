//! Which bundle an engine loads (`EngineConfig::bundle_path`, C `cg_engine_config.bundle_path`):
//!
//! 1. an explicit path always wins;
//! 2. else the directory named by the `COMGRASP_BUNDLE` environment variable, if it is set;
//! 3. else the default bundle embedded in the library (feature `embedded-default`);
//! 4. else an error saying all three were missing.
//!
//! A set but empty or unusable `COMGRASP_BUNDLE` is an error, never a silent fallback to the
//! embedded bundle: a user who sets it means that bundle, and quietly getting another model
//! would be much harder to notice than a failed engine creation.
use std::path::Path;

use super::source::BundleSource;
use crate::error::{Error, Result};

/// Environment variable naming a bundle directory, used when no path is given.
pub const BUNDLE_ENV: &str = "COMGRASP_BUNDLE";

/// The source the selection order above picks, and whether [`BUNDLE_ENV`] picked it (so
/// the loader's errors can say so). Reads the variable only when `explicit` is `None`.
pub fn source(explicit: Option<&Path>) -> Result<(BundleSource, bool)> {
    if let Some(path) = explicit {
        return Ok((BundleSource::dir(path), false));
    }
    match std::env::var_os(BUNDLE_ENV) {
        Some(v) if v.is_empty() => Err(Error::bundle(
            "",
            format!(
                "the {BUNDLE_ENV} environment variable is set but empty: set it to a bundle directory, \
                     or unset it to use the default bundle"
            ),
        )),
        Some(v) => Ok((BundleSource::dir(Path::new(&v)), true)),
        None => match BundleSource::embedded() {
            Some(source) => Ok((source, false)),
            None => Err(Error::bundle(
                "",
                format!(
                    "no bundle_path given, {BUNDLE_ENV} is not set, and this build has no embedded default \
                         bundle (feature `embedded-default`)"
                ),
            )),
        },
    }
}
