//! The models of a loaded [`Bundle`]: the text encoder ([`text`]), the 4-stream
//! Transformer step with a Rust-owned KV cache ([`StepModel`] / [`StepState`]) and the
//! streaming VQ decoder ([`DecoderModel`] / [`DecoderState`]), each native or in tract. A model is loaded once per bundle and shared by
//! every stream; each stream owns its states. [`overlap`] runs a stream's decode of
//! chunk k and its step k+1 at once; [`decode_group`] says how many tokens one decode takes.
pub mod decode_group;
mod decoder;
#[cfg(feature = "onnx")]
pub(crate) mod graph;
mod loaded;
pub(crate) mod native;
pub mod overlap;
mod step;
pub mod text;
#[cfg(feature = "onnx")]
mod text_graph;

pub(crate) use decoder::{DecodeJob, DecodeJobs, DecodeScratch, MAX_DECODE_BATCH};
pub use decoder::{DecoderBackend, DecoderModel, DecoderState, MAX_DECODE_GROUP};
pub use loaded::Bundle;
pub use step::{StepBackend, StepModel, StepState};
pub(crate) use step::{StepJob, StepJobs, StepScratch};

/// Lowers the native kernels' instruction set, process-wide (`RuntimeOptions::max_isa`).
pub fn cap_instruction_set(cap: crate::config::InstructionSet) {
    native::kernels::cap_isa(cap)
}
