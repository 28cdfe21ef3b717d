//! ComGrasp Engine: streaming text-to-whole-body-grasp motion with a C ABI.
//!
//! **Floors**, bottom up. A module imports only from floors below its own (or its own
//! module); `tests/layers.rs` reads every `crate::` path and fails on one that points up.
//!
//! 1. [`error`], [`frame`] (the C frame, coordinate systems), [`config`] (engine, stream and
//!    runtime options: plain data);
//! 2. [`bundle`]: a bundle's files, manifest and verification, from a directory or the
//!    default embedded in the library (feature `embedded-default`); files only;
//! 3. [`sampler`] (the cross-language deterministic sampler), [`skeleton`] (FK) and
//!    [`assemble`] (335-D features -> frames), then [`feet`] (planted feet, leg IK), then
//!    [`contact`] (the contact-consistency stage: debounced grasps, reach IK, an object that
//!    obeys the hands, the character on the ground), then [`anchor`]
//!    (frames in the host's world), [`retarget`] (frames on a host's skeleton) and [`bvh`]
//!    (BVH files);
//! 4. [`model`]: the loaded [`Bundle`] and its models (text encoder, step with a
//!    Rust-owned KV cache, streaming VQ decoder; native kernels or tract (cargo feature
//!    `onnx`); graph rewrites in `model::graph` and `model::text_graph` only);
//! 5. [`generator`]: one generation, text -> tokens -> 16-frame chunks (a [`ChunkSource`]);
//! 6. [`stream`]: a worker thread, its ring buffer, cancellation, [`stream::StreamSink`]s;
//!    then [`crowd`]: the scheduler that drives many streams' generations on a few threads,
//!    their token steps batched;
//! 7. [`shm`]: frames shared with other processes over iceoryx2 (a sink the engine attaches);
//! 8. [`engine`]: the bundle, the streams, the publisher;
//! 9. [`ffi`]: the C ABI, a thin wrapper with a panic boundary.
//!
//! **Public API.** Rust hosts use the re-exports below and [`ffi`] is the C ABI. The
//! other modules are public for the `comgrasp` CLI, the examples and the tests (hidden
//! from the docs): no stability promise.
#![allow(non_camel_case_types)]

pub mod error;
pub mod frame;
pub mod config;
#[doc(hidden)]
pub mod bundle;
#[doc(hidden)]
pub mod sampler;
#[doc(hidden)]
pub mod skeleton;
#[doc(hidden)]
pub mod assemble;
#[doc(hidden)]
pub mod feet;
#[doc(hidden)]
pub mod contact;
#[doc(hidden)]
pub mod anchor;
pub mod retarget;
pub mod bvh;
#[doc(hidden)]
pub mod model;
#[doc(hidden)]
pub mod generator;
pub mod stream;
pub mod crowd;
pub mod shm;
pub mod engine;
pub mod ffi;

pub use bundle::BundleSource;
pub use config::{
    Anchor, DecoderBackend, EngineConfig, InstructionSet, Placement, RuntimeOptions, StepBackend, StreamConfig,
};
pub use engine::Engine;
pub use error::{Error, Result};
pub use frame::{CoordinateSystem, Frame};
pub use generator::ChunkSource;
pub use model::Bundle;
pub use shm::{FrameSubscriber, PublisherStats, SubscriberStats};
pub use stream::{PollResult, Stream, StreamCanceller, StreamObject};
