//! The C ABI (`include/comgrasp.h` is generated from this module by cbindgen).
//!
//! A thin layer over [`crate::engine::Engine`] and [`crate::stream::Stream`]: it validates
//! every input, maps errors to [`cg_status`] codes with a thread-local message, and keeps
//! panics inside the library. The rules every function follows:
//!
//! * **Panic boundary**: every body runs inside `catch_unwind` ([`panic`]); a panic returns
//!   `CG_ERR_PANIC` and poisons the handle it happened on (later calls on it return
//!   `CG_ERR_PANIC`; destroying it still works).
//! * **Validated handles**: `cg_engine*` / `cg_stream*` are opaque tokens resolved through a
//!   registry ([`handle`]), never dereferenced, so NULL, stale (destroyed), double-destroyed,
//!   foreign or wrong-type handles give `CG_ERR_INVALID_HANDLE`/`CG_ERR_NULL_POINTER` instead
//!   of undefined behaviour.
//! * **Out-params last, written only on success.**
//! * **Versioned configs**: structs start with `struct_size`; only the bytes the caller
//!   declares are read, so the structs can grow by appending fields ([`config`]).
//! * **Threads**: an engine may be used from any number of threads at once; a stream from
//!   one thread at a time (concurrent use is detected and gives `CG_ERR_WRONG_STATE`),
//!   except `cg_cancel`, which may be called from any thread at any time.
#![deny(missing_docs)]
// Every function here is `unsafe extern "C"` for its pointer arguments, and their contract is
// one for all of them: the header's "Pointers" rules (NULL is checked, everything else must
// be valid for the declared size during the call; SECURITY.md). cbindgen copies doc comments
// into comgrasp.h, so a `# Safety` section per function would repeat it 21 times there.
#![allow(clippy::missing_safety_doc)]

pub mod config;
pub mod engine;
pub mod handle;
pub mod last_error;
pub mod panic;
pub mod retarget;
pub mod status;
pub mod stream;
pub mod subscriber;
pub mod version;

pub use crate::shm::records::{
    cg_stream_event, CG_EVENT_TEXT_BYTES, CG_MAX_PUBLISH_NAME_BYTES, CG_MAX_SUBSCRIBER_BUFFER,
    CG_STREAM_EVENT_CANCELLED, CG_STREAM_EVENT_ENDED, CG_STREAM_EVENT_FAILED, CG_STREAM_EVENT_STARTED,
};
pub use crate::shm::{cg_publisher_stats, cg_subscriber_stats};
pub use config::*;
pub use engine::*;
pub use handle::{cg_engine, cg_stream, cg_subscriber};
pub use last_error::*;
pub use status::*;
pub use stream::*;
pub use subscriber::*;
pub use version::*;
