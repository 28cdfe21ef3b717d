//! The native (hand-written) inference path: the same networks as the bundle's ONNX graphs,
//! computed by Rust kernels on weights the exporter writes beside the graphs
//! (`<section>.native` in the manifest, one `.npy` per tensor).
//!
//! Why: tract allocates its intermediates on every run and pays a per-node overhead that
//! dominates a batch-1 decode step (DESIGN §7); these kernels work in buffers allocated once
//! per stream, and read int8 weights directly (a quarter of the memory traffic of fp32).
//! The ONNX graphs stay the reference: parity tests compare both paths.
mod arena;
pub(crate) mod kernels;
pub(crate) mod step;
pub(crate) mod text;
pub(crate) mod weights;
// The incremental streaming decoder (decoder*.rs) and its multi-position products.
pub(crate) mod decoder;
mod decoder_attention;
mod decoder_conv;
mod gemm;
// The thread team of the decoder and of the step (one helper thread per loaded model).
mod team;
