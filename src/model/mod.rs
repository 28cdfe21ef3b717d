//! The bundle's two token-level networks, run with tract: the 4-stream Transformer step
//! with a Rust-owned KV cache ([`StepModel`] / [`StepState`]) and the streaming VQ decoder
//! ([`DecoderModel`] / [`DecoderState`]). A model is loaded once per bundle and shared by
//! every stream; each stream owns its states. [`overlap`] runs a stream's decode of
//! chunk k and its step k+1 at once; [`decode_group`] says how many tokens one decode takes.
pub mod decode_group;
mod decoder;
pub(crate) mod graph;
pub(crate) mod native;
pub mod overlap;
mod step;

pub use decoder::{DecoderBackend, DecoderModel, DecoderState, DECODER_ENV, MAX_DECODE_GROUP};
pub use step::{StepBackend, StepModel, StepState, STEP_ENV};
