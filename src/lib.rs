//! ComGrasp Engine: streaming text-to-whole-body-grasp motion with a C ABI.
//!
//! Layers, bottom up: [`bundle`] (load and verify a model bundle from a directory or the
//! default one embedded in the library, feature `embedded-default`), [`text`] (tokenizer +
//! text encoder), [`model`] (the Transformer step graph with a Rust-owned KV cache and the
//! streaming VQ decoder), [`sampler`] (the cross-language deterministic sampler),
//! [`frame`] (the C frame and its assembly from 335-D features), [`generator`] (one
//! generation: text -> tokens -> 16-frame chunks), [`engine`] / [`stream`] (threads, ring
//! buffers, cancellation), [`shm`] (frames shared with other processes over iceoryx2) and
//! [`ffi`], the C ABI, a thin wrapper with a panic boundary.
#![allow(non_camel_case_types)]

pub mod assemble;
pub mod bundle;
pub mod engine;
pub mod error;
pub mod ffi;
pub mod frame;
pub mod generator;
pub mod model;
pub mod sampler;
pub mod shm;
pub mod skeleton;
pub mod stream;
pub mod text;

pub use engine::{Engine, EngineConfig};
pub use error::{Error, Result};
pub use frame::{CoordinateSystem, Frame};
pub use stream::{ChunkSource, PollResult, Stream, StreamConfig};
