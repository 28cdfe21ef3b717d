//! A model bundle (DESIGN §4): `manifest.json`, the tokenizer, the three ONNX graphs, the
//! object meshes and (optionally) the parity vectors, loaded and verified once and then
//! shared read-only by every stream through an `Arc<Bundle>`.
//!
//! [`Bundle::load`] does everything that can fail up front: schema, consistency, files and
//! SHA-256 digests ([`verify`]), the graphs loaded into tract and checked against the
//! manifest's declared inputs/outputs, the tokenizer's padding. After it returns, a stream
//! can only fail on its own inputs.
//!
//! Cost: every listed file is hashed (streamed, ~0.3-1 GB/s), and each graph takes
//! 0.1-0.2 s to load in tract; load once per engine, never per stream.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::Result;
use crate::model::{DecoderModel, StepModel};
use crate::text::TextEncoder;

pub mod manifest;
pub mod npy;
pub mod verify;

pub use manifest::{Component, Manifest, ObjectEntry, N_STREAMS, STREAMS};

/// A loaded, verified bundle. `Send + Sync`; share it with `Arc`.
#[derive(Debug)]
pub struct Bundle {
    pub manifest: Manifest,
    /// The bundle directory (meshes are `dir.join(object.mesh)`).
    pub dir: PathBuf,
    pub text: TextEncoder,
    pub step: StepModel,
    pub decoder: DecoderModel,
}

impl Bundle {
    /// Loads and verifies the bundle in `dir`. Every problem is an `Error::Bundle` naming
    /// the file at fault.
    pub fn load(dir: &Path) -> Result<Arc<Bundle>> {
        let dir = dir.to_path_buf();
        let manifest = verify::read_manifest(&dir)?;
        verify::check_manifest(&dir, &manifest)?;
        verify::check_files(&dir, &manifest)?;
        let text = TextEncoder::load(&dir, &manifest)?;
        let step = StepModel::load(&dir, &manifest)?;
        let decoder = DecoderModel::load(&dir, &manifest)?;
        verify::check_parity_index(&dir, &manifest)?;
        Ok(Arc::new(Bundle { manifest, dir, text, step, decoder }))
    }

    /// Path of a file named in the manifest (relative, '/'-separated).
    pub fn path(&self, rel: &str) -> PathBuf {
        self.dir.join(rel)
    }

    /// The bytes of a file the manifest lists (e.g. an object mesh `objects/mug.obj`).
    /// Names the manifest does not list are an error, so a host cannot read outside it.
    pub fn file_bytes(&self, rel: &str) -> Result<Vec<u8>> {
        if !self.manifest.files.contains_key(rel) {
            return Err(crate::error::Error::bundle(self.path(rel), "not a file the manifest lists"));
        }
        std::fs::read(self.path(rel)).map_err(|e| crate::error::Error::bundle(self.path(rel), format!("cannot read: {e}")))
    }
}

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<Bundle>();
}
