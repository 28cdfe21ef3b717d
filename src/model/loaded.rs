//! A loaded bundle: the verified files of a [`BundleSource`] with its three models (text
//! encoder, step, decoder) ready to run, shared read-only by every stream of an engine
//! through an `Arc<Bundle>`. The files, the manifest and their verification are the floor
//! below (`crate::bundle`); this is where they become models.
//!
//! [`Bundle::load_with`] does everything that can fail up front: schema, consistency,
//! files and SHA-256 digests (`bundle::verify`), the graphs loaded into tract and checked
//! against the manifest's declared inputs/outputs, the tokenizer's padding and kind. After
//! it returns, a stream can only fail on its own inputs.
//!
//! Cost: every listed file is hashed (streamed, ~0.3-1 GB/s; for the embedded bundle once
//! per process), and each graph takes 0.1-0.2 s to load in tract; load once per engine,
//! never per stream.
use std::path::Path;
use std::sync::Arc;

use super::text::TextEncoder;
use super::{DecoderModel, StepModel};
use crate::bundle::manifest::Manifest;
use crate::bundle::{embedded, select, verify, BundleSource};
use crate::config::RuntimeOptions;
use crate::error::{Error, Result};

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
        Bundle::load_with(source, &RuntimeOptions::default())
    }

    /// [`load_source`](Self::load_source), running the models as `options` say (an
    /// instruction-set cap applies process-wide from here on, see `RuntimeOptions::max_isa`).
    pub fn load_with(source: BundleSource, options: &RuntimeOptions) -> Result<Arc<Bundle>> {
        options.validate()?;
        if let Some(cap) = options.max_isa {
            super::cap_instruction_set(cap);
        }
        let manifest = verify::read_manifest(&source)?;
        verify::check_manifest(&source, &manifest)?;
        if source.is_embedded() {
            embedded::check_files_once(|| verify::check_files(&source, &manifest))?;
        } else {
            verify::check_files(&source, &manifest)?;
        }
        let text = TextEncoder::load(&source, &manifest)?;
        verify::check_tokenizer(&source, &manifest)?;
        let step = StepModel::load(&source, &manifest, options)?;
        let decoder = DecoderModel::load(&source, &manifest, options)?;
        verify::check_parity_index(&source, &manifest)?;
        Ok(Arc::new(Bundle { manifest, source, text, step, decoder }))
    }

    /// Loads the bundle at `explicit`, or the one `bundle::select` picks (`COMGRASP_BUNDLE`,
    /// else the embedded default), running its models as `options` say. An error of a
    /// bundle chosen by the variable says so.
    pub fn select(explicit: Option<&Path>, options: &RuntimeOptions) -> Result<Arc<Bundle>> {
        let (source, by_env) = select::source(explicit)?;
        Bundle::load_with(source, options).map_err(|e| match e {
            Error::Bundle { path, msg } if by_env => {
                Error::Bundle { path, msg: format!("{msg} (bundle selected by {})", select::BUNDLE_ENV) }
            }
            other => other,
        })
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
}
