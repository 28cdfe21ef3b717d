//! A model bundle (DESIGN §4): `manifest.json`, the tokenizer, the three ONNX graphs, the
//! object meshes and (optionally) the parity vectors, loaded and verified once and then
//! shared read-only by every stream through an `Arc<Bundle>`.
//!
//! A bundle is read from a [`BundleSource`]: a directory, the default bundle embedded in
//! the library ([`embedded`]) or another in-memory file set. [`select`] picks the one an
//! engine uses when it is given no path.
//!
//! [`Bundle::load_source`] does everything that can fail up front: schema, consistency,
//! files and SHA-256 digests ([`verify`]), the graphs loaded into tract and checked against
//! the manifest's declared inputs/outputs, the tokenizer's padding and kind. After it returns, a
//! stream can only fail on its own inputs.
//!
//! Cost: every listed file is hashed (streamed, ~0.3-1 GB/s; for the embedded bundle once
//! per process), and each graph takes 0.1-0.2 s to load in tract; load once per engine,
//! never per stream.
use std::path::Path;
use std::sync::Arc;

use crate::error::{Error, Result};
use crate::model::{DecoderModel, StepModel};
use crate::text::TextEncoder;

pub mod embedded;
pub mod manifest;
pub mod npy;
pub mod select;
pub mod source;
pub mod verify;

pub use manifest::{Component, Manifest, ObjectEntry, N_STREAMS, STREAMS};
pub use source::BundleSource;

/// A loaded, verified bundle. `Send + Sync`; share it with `Arc`.
#[derive(Debug)]
pub struct Bundle {
    pub manifest: Manifest,
    /// Where the files came from (meshes are read with [`Bundle::file_bytes`]).
    source: BundleSource,
    pub text: TextEncoder,
    pub step: StepModel,
    pub decoder: DecoderModel,
}

impl Bundle {
    /// Loads and verifies the bundle in directory `dir`. Every problem is an
    /// `Error::Bundle` naming the file at fault.
    pub fn load(dir: &Path) -> Result<Arc<Bundle>> {
        Bundle::load_source(BundleSource::dir(dir))
    }

    /// Loads and verifies the bundle in `source`, with the same checks and messages for
    /// every kind of source (errors name `<dir>/file`, `<embedded>/file` or `<memory>/file`).
    pub fn load_source(source: BundleSource) -> Result<Arc<Bundle>> {
        let manifest = verify::read_manifest(&source)?;
        verify::check_manifest(&source, &manifest)?;
        if source.is_embedded() {
            embedded::check_files_once(|| verify::check_files(&source, &manifest))?;
        } else {
            verify::check_files(&source, &manifest)?;
        }
        let text = TextEncoder::load(&source, &manifest)?;
        verify::check_tokenizer(&source, &manifest)?;
        let step = StepModel::load(&source, &manifest)?;
        let decoder = DecoderModel::load(&source, &manifest)?;
        verify::check_parity_index(&source, &manifest)?;
        Ok(Arc::new(Bundle { manifest, source, text, step, decoder }))
    }

    /// Where the bundle came from: its directory ([`BundleSource::directory`]), the
    /// embedded default ([`BundleSource::is_embedded`]) or another in-memory set. Its
    /// `Display` is the directory, `<embedded>` or `<memory>`.
    pub fn origin(&self) -> &BundleSource {
        &self.source
    }

    /// The bytes of a file the manifest lists (e.g. an object mesh `objects/mug.obj`), from
    /// whichever source the bundle came from. Names the manifest does not list are an
    /// error, so a host cannot read outside it.
    pub fn file_bytes(&self, rel: &str) -> Result<Vec<u8>> {
        if !self.manifest.files.contains_key(rel) {
            return Err(Error::bundle(self.source.path_of(rel), "not a file the manifest lists"));
        }
        Ok(self.source.read_file(rel)?.into_owned())
    }
}

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<Bundle>();
    is_send_sync::<BundleSource>();
}
