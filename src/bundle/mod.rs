//! A model bundle's files (DESIGN §4): `manifest.json`, the tokenizer, the three ONNX
//! graphs, the native weights, the object meshes and (optionally) the parity vectors, and
//! their verification. This floor reads and checks files only; `model::Bundle` turns a
//! verified bundle into models.
//!
//! A bundle is read from a [`BundleSource`]: a directory, the default bundle embedded in
//! the library ([`embedded`]) or another in-memory file set. [`select`] picks the one an
//! engine uses when it is given no path. [`verify`] checks the schema, consistency, files
//! and SHA-256 digests.
pub mod embedded;
pub mod manifest;
pub mod npy;
pub mod obj;
pub mod select;
pub mod source;
pub mod verify;

pub use manifest::{choose_object, Component, Manifest, ObjectEntry, N_STREAMS, STREAMS};
pub use source::BundleSource;

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<BundleSource>();
}
