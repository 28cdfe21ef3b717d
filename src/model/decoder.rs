//! The four streaming VQ decoders as one graph (`decoder.onnx`, export/decoder_graph.py):
//! `state (1,4,K-1)` + `tokens (1,4)` -> `frames (1,F,335)` normalized features (contact
//! channels already probabilities) + `next_state`. Decoding chunk by chunk equals decoding
//! the whole sequence (DESIGN §3 deviation 1), so the engine emits F frames per token as
//! soon as the token is sampled.
use std::sync::Arc;

use parking_lot::Mutex;
use tract_onnx::prelude::Tensor;

use super::graph::{self, Plan, PlanState};
use crate::bundle::manifest::{Manifest, FRAME_DIM, N_STREAMS};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

/// The loaded decoder graph; shared by all streams of an engine.
pub struct DecoderModel {
    plan: Plan,
    frames_per_token: usize,
    state_tokens: usize,
    codebook: [usize; N_STREAMS],
    /// (1, 4, K-1) initial state from the manifest.
    initial: Arc<Tensor>,
    /// (1, 4) token buffer and a spawned run state, cloned by `new_state`.
    template_tokens: Arc<Tensor>,
    template_run: Mutex<PlanState>,
}

/// One generation's decoder context (the previous K-1 tokens of every component).
pub struct DecoderState {
    plan: Plan,
    run: PlanState,
    /// [state, tokens], as the graph takes them.
    inputs: [Arc<Tensor>; 2],
    /// The model's initial state (shared, read-only), for `reset`.
    initial: Arc<Tensor>,
    /// Tokens decoded so far.
    decoded: usize,
}

impl std::fmt::Debug for DecoderModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecoderModel").field("frames_per_token", &self.frames_per_token)
            .field("state_tokens", &self.state_tokens).field("codebook", &self.codebook).finish_non_exhaustive()
    }
}

impl std::fmt::Debug for DecoderState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecoderState").field("decoded", &self.decoded).finish_non_exhaustive()
    }
}

impl DecoderModel {
    /// Loads `decoder.file`; the manifest was verified (shapes and initial state).
    pub fn load(src: &BundleSource, m: &Manifest) -> Result<DecoderModel> {
        let d = &m.decoder;
        let path = src.path_of(&d.file);
        let plan = graph::load(src, &d.file, &d.inputs, &d.outputs)?;
        let k1 = d.state_tokens;
        let flat: Vec<i64> = d.initial_state.iter().flatten().flatten().copied().collect();
        let initial = Tensor::from_shape::<i64>(&[1, N_STREAMS, k1], &flat)
            .map_err(|e| Error::bundle(&path, format!("decoder initial_state: {e:#}")))?;
        let template_tokens = Tensor::zero::<i64>(&[1, N_STREAMS])
            .map_err(|e| Error::bundle(&path, format!("{e:#}")))?;
        let template_run = Mutex::new(graph::spawn(&plan, "decoder.onnx").map_err(|e| Error::bundle(&path, e.to_string()))?);
        Ok(DecoderModel {
            plan,
            frames_per_token: d.frames_per_token,
            state_tokens: k1,
            codebook: m.codebook_sizes(),
            initial: Arc::new(initial),
            template_tokens: Arc::new(template_tokens),
            template_run,
        })
    }

    /// Frames one token decodes to (F).
    pub fn frames_per_token(&self) -> usize {
        self.frames_per_token
    }

    /// Length of the `out` buffer [`DecoderModel::decode`] fills: F * 335.
    pub fn chunk_len(&self) -> usize {
        self.frames_per_token * FRAME_DIM
    }

    /// The state of a new sequence.
    pub fn new_state(&self) -> DecoderState {
        DecoderState {
            plan: Arc::clone(&self.plan),
            run: self.template_run.lock().clone(),
            inputs: [Arc::new(Tensor::clone(&self.initial)), Arc::new(Tensor::clone(&self.template_tokens))],
            initial: Arc::clone(&self.initial),
            decoded: 0,
        }
    }

    /// Decodes one token per component (codes, `0 <= tokens[i] < codebook_size[i]`; End
    /// and Pad are not codes) into `out`: F frames x 335 normalized features, row-major,
    /// contact channels 240 and 334 as probabilities. Advances `state`.
    pub fn decode(&self, state: &mut DecoderState, tokens: [i64; N_STREAMS], out: &mut [f32]) -> Result<()> {
        if !Arc::ptr_eq(&state.plan, &self.plan) {
            return Err(Error::WrongState("this DecoderState was created by another DecoderModel".into()));
        }
        if out.len() != self.chunk_len() {
            return Err(Error::InvalidArgument(format!(
                "decode output buffer has {} values, needs {} ({} frames x {FRAME_DIM})",
                out.len(), self.chunk_len(), self.frames_per_token)));
        }
        for (s, (&t, &j)) in tokens.iter().zip(&self.codebook).enumerate() {
            if t < 0 || t as u64 >= j as u64 {
                return Err(Error::InvalidArgument(format!("code {t} of component {s} outside the codebook 0..{j}")));
            }
        }
        graph::slice_mut::<i64>(&mut state.inputs[1], "decoder tokens")?.copy_from_slice(&tokens);
        let res = graph::run(&mut state.run, &state.inputs, "decoder.onnx")?;
        if res.len() != 2 {
            return Err(Error::Inference(format!("decoder.onnx returned {} outputs, expected 2", res.len())));
        }
        out.copy_from_slice(graph::slice::<f32>(&res[0], "decoder frames", self.chunk_len())?);
        let next = graph::slice::<i64>(&res[1], "decoder next_state", N_STREAMS * self.state_tokens)?;
        graph::slice_mut::<i64>(&mut state.inputs[0], "decoder state")?.copy_from_slice(next);
        state.decoded += 1;
        Ok(())
    }
}

impl DecoderState {
    /// Tokens decoded since the state was created or reset.
    pub fn decoded(&self) -> usize {
        self.decoded
    }

    /// Starts a new sequence (no allocation).
    pub fn reset(&mut self) -> Result<()> {
        let init = graph::slice::<i64>(&self.initial, "decoder initial state", self.initial.len())?;
        graph::slice_mut::<i64>(&mut self.inputs[0], "decoder state")?.copy_from_slice(init);
        self.decoded = 0;
        Ok(())
    }
}

#[allow(dead_code)]
fn _assert_send() {
    fn is_send<T: Send>() {}
    fn is_send_sync<T: Send + Sync>() {}
    is_send::<DecoderState>();
    is_send_sync::<DecoderModel>();
}
