//! The default bundle compiled into the library (cargo feature `embedded-default`, on by
//! default). `build/embed.rs` turns every file that `models/default/manifest.json` lists,
//! `parity/` left out (the loader treats parity as optional) and the reference graphs of
//! natively-run models left out ([`omitted`]), into one deflated `include_bytes!`.
//!
//! The deflated bytes sit in the binary's read-only data (13 % less than the files: what
//! keeps the plugin under 40 MB) and are inflated once per process, on first use, into
//! memory every engine shares (~35 MB, ~0.1 s); they cannot change while the process runs.
//! So their sizes and SHA-256 digests are checked once per process (`check_files_once`)
//! and the outcome reused; parsing the manifest, the tokenizer and the weights still
//! happens per engine, as for a directory.
use std::path::PathBuf;
use std::sync::OnceLock;

use super::source::{StaticFiles, EMBEDDED_LABEL};
use crate::error::{Error, Result};

#[cfg(feature = "embedded-default")]
mod generated {
    include!(concat!(env!("OUT_DIR"), "/embedded_bundle.rs"));
}

/// The reference graphs `build/embed.rs` left out because their models run natively
/// (`step.onnx` and `decoder.onnx` for the default bundle): the library holds each weight
/// once. Empty in a build without the feature.
pub fn omitted() -> &'static [&'static str] {
    #[cfg(feature = "embedded-default")]
    {
        generated::OMITTED
    }
    #[cfg(not(feature = "embedded-default"))]
    {
        &[]
    }
}

/// The embedded files (`manifest.json` first), inflated on the first call, or `None` in a
/// build without the feature.
pub fn files() -> Option<StaticFiles> {
    #[cfg(feature = "embedded-default")]
    {
        static FILES: OnceLock<Vec<(&'static str, &'static [u8])>> = OnceLock::new();
        let files = FILES.get_or_init(|| {
            generated::PACKED
                .iter()
                .map(|&(name, deflated, len)| {
                    // Only a broken build could fail here; an empty file then fails the
                    // manifest's size check, which names it.
                    let bytes = miniz_oxide::inflate::decompress_to_vec_with_limit(deflated, len)
                        .ok()
                        .filter(|b| b.len() == len)
                        .unwrap_or_default();
                    // Once per process, for its whole life (the bundle is `'static` data).
                    (name, &*Box::leak(bytes.into_boxed_slice()))
                })
                .collect()
        });
        Some(files.as_slice())
    }
    #[cfg(not(feature = "embedded-default"))]
    {
        None
    }
}

/// Runs `check` (the embedded bundle's file checks) the first time it is called in this
/// process and returns that outcome every time. `check` must be a function of the
/// embedded bytes alone, which it is: the manifest it checks against is parsed from them.
pub(crate) fn check_files_once(check: impl FnOnce() -> Result<()>) -> Result<()> {
    // `Error` is not `Clone` (it can hold an `io::Error`); a file check only produces
    // `Error::Bundle`, kept here as its parts.
    static OUTCOME: OnceLock<std::result::Result<(), (PathBuf, String)>> = OnceLock::new();
    let outcome = OUTCOME.get_or_init(|| {
        check().map_err(|e| match e {
            Error::Bundle { path, msg } => (path, msg),
            other => (PathBuf::from(EMBEDDED_LABEL), other.to_string()),
        })
    });
    outcome.clone().map_err(|(path, msg)| Error::Bundle { path, msg })
}
