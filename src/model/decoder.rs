//! The four streaming VQ decoders: `state (1,4,K-1)` + `tokens (1,4)` -> `frames (1,F,335)`
//! normalized features (contact channels already probabilities). Decoding chunk by chunk
//! equals decoding the whole sequence (DESIGN §3 deviation 1), so the engine emits F frames
//! per token as soon as the token is sampled.
//!
//! Two implementations of the same function:
//! * **native** (`native::decoder`, when the bundle has `decoder.native` weights): an
//!   incremental decoder that keeps every layer's history and computes only the new
//!   positions, allocation-free;
//! * **tract** on `decoder.onnx` (export/decoder_graph.py), which recomputes the K-token
//!   window per chunk; the reference the parity tests compare with.
//!
//! The native path is used when available; `RuntimeOptions::decoder_backend` forces one,
//! and [`DecoderModel::load_backend`] takes just the backend.
use std::sync::Arc;

#[cfg(feature = "onnx")]
use parking_lot::Mutex;
#[cfg(feature = "onnx")]
use tract_onnx::prelude::Tensor;

#[cfg(feature = "onnx")]
use super::graph::{self, Plan, PlanState};
use super::native::decoder::{NativeDecoder, NativeState, MAX_GROUP};
use crate::bundle::manifest::{Manifest, FRAME_DIM, MANIFEST_FILE, N_STREAMS};
use crate::bundle::BundleSource;
use crate::config::RuntimeOptions;
use crate::error::{Error, Result};

/// Most tokens one [`DecoderModel::decode_group`] takes.
pub const MAX_DECODE_GROUP: usize = crate::config::MAX_DECODE_GROUP;
const _: () = assert!(MAX_DECODE_GROUP == MAX_GROUP);

pub use crate::config::DecoderBackend;

/// The loaded decoder; shared by all streams of an engine.
pub struct DecoderModel {
    frames_per_token: usize,
    state_tokens: usize,
    codebook: [usize; N_STREAMS],
    imp: Imp,
}

#[allow(clippy::large_enum_variant)] // one per loaded bundle
enum Imp {
    #[cfg(feature = "onnx")]
    Tract(TractDecoder),
    Native(Arc<NativeDecoder>),
}

#[cfg(feature = "onnx")]
struct TractDecoder {
    plan: Plan,
    /// (1, 4, K-1) initial state from the manifest.
    initial: Arc<Tensor>,
    /// (1, 4) token buffer and a spawned run state, cloned by `new_state`.
    template_tokens: Arc<Tensor>,
    template_run: Mutex<PlanState>,
}

/// One generation's decoder context (the previous K-1 tokens of every component, or the
/// native decoder's layer histories).
pub struct DecoderState {
    imp: StateImp,
    /// Tokens decoded so far.
    decoded: usize,
}

enum StateImp {
    #[cfg(feature = "onnx")]
    Tract {
        plan: Plan,
        run: PlanState,
        /// [state, tokens], as the graph takes them.
        inputs: [Arc<Tensor>; 2],
        /// The model's initial state (shared, read-only), for `reset`.
        initial: Arc<Tensor>,
    },
    Native {
        model: Arc<NativeDecoder>,
        state: NativeState,
    },
}

impl std::fmt::Debug for DecoderModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecoderModel")
            .field("backend", &self.backend())
            .field("frames_per_token", &self.frames_per_token)
            .field("state_tokens", &self.state_tokens)
            .field("codebook", &self.codebook)
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for DecoderState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecoderState").field("decoded", &self.decoded).finish_non_exhaustive()
    }
}

impl DecoderModel {
    /// Loads the decoder as `options` say (`decoder_backend`, `None`: native when the
    /// bundle has `decoder.native` weights, else `decoder.file` in tract; `decoder_threads`).
    /// Asking for `Native` from a bundle without `decoder.native` is an `Error::Bundle`. The
    /// manifest was verified (shapes and initial state).
    pub fn load(src: &BundleSource, m: &Manifest, options: &RuntimeOptions) -> Result<DecoderModel> {
        let d = &m.decoder;
        let native = match (options.decoder_backend, &d.native) {
            (Some(DecoderBackend::Tract), _) | (None, None) => None,
            (_, Some(spec)) => Some(spec),
            (Some(DecoderBackend::Native), None) => {
                return Err(Error::bundle(
                    src.path_of(MANIFEST_FILE),
                    "the decoder backend is native, but the manifest has no decoder.native weights",
                ));
            }
        };
        let imp = match native {
            Some(spec) => {
                // decoder.onnx stays the bundle's reference graph: it must still match its manifest.
                #[cfg(feature = "onnx")]
                graph::check(src, &d.file, &d.inputs, &d.outputs)?;
                Imp::Native(Arc::new(NativeDecoder::load(src, m, spec, options.decoder_threads)?))
            }
            #[cfg(feature = "onnx")]
            None => Imp::Tract(TractDecoder::load(src, m)?),
            #[cfg(not(feature = "onnx"))]
            None => return Err(super::step::no_onnx(src, &d.file)),
        };
        Ok(DecoderModel {
            frames_per_token: d.frames_per_token,
            state_tokens: d.state_tokens,
            codebook: m.codebook_sizes(),
            imp,
        })
    }

    /// [`load`](Self::load) with `backend` and the other options automatic.
    pub fn load_backend(src: &BundleSource, m: &Manifest, backend: Option<DecoderBackend>) -> Result<DecoderModel> {
        DecoderModel::load(src, m, &RuntimeOptions { decoder_backend: backend, ..RuntimeOptions::default() })
    }

    /// The implementation in use.
    pub fn backend(&self) -> DecoderBackend {
        match self.imp {
            #[cfg(feature = "onnx")]
            Imp::Tract(_) => DecoderBackend::Tract,
            Imp::Native(_) => DecoderBackend::Native,
        }
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
        let imp = match &self.imp {
            #[cfg(feature = "onnx")]
            Imp::Tract(t) => StateImp::Tract {
                plan: Arc::clone(&t.plan),
                run: t.template_run.lock().clone(),
                inputs: [Arc::new(Tensor::clone(&t.initial)), Arc::new(Tensor::clone(&t.template_tokens))],
                initial: Arc::clone(&t.initial),
            },
            Imp::Native(n) => StateImp::Native { model: Arc::clone(n), state: n.new_state() },
        };
        DecoderState { imp, decoded: 0 }
    }

    /// Decodes one token per component (codes, `0 <= tokens[i] < codebook_size[i]`; End
    /// and Pad are not codes) into `out`: F frames x 335 normalized features, row-major,
    /// contact channels 240 and 334 as probabilities. Advances `state`. The native path
    /// allocates nothing.
    pub fn decode(&self, state: &mut DecoderState, tokens: [i64; N_STREAMS], out: &mut [f32]) -> Result<()> {
        self.decode_group(state, &[tokens], out)
    }

    /// [`decode`](Self::decode) of 1 to [`MAX_DECODE_GROUP`] consecutive tokens in one
    /// call: `out` holds `tokens.len()` chunks, the same values as one call per token (the
    /// same bits on the native path, which reads each weight once per call instead of once
    /// per token; tract decodes them one by one).
    pub fn decode_group(&self, state: &mut DecoderState, tokens: &[[i64; N_STREAMS]], out: &mut [f32]) -> Result<()> {
        self.check(state, tokens, out)?;
        self.decode_checked(state, tokens, out, None, true)
    }

    /// [`decode_group`](Self::decode_group) on the calling thread alone (the native
    /// decoder's helper is left to others: the crowd scheduler runs one decode per
    /// thread), the same bits.
    pub(crate) fn decode_group_solo(
        &self,
        state: &mut DecoderState,
        tokens: &[[i64; N_STREAMS]],
        out: &mut [f32],
    ) -> Result<()> {
        self.check(state, tokens, out)?;
        self.decode_checked(state, tokens, out, None, false)
    }

    /// The errors [`decode_group`](Self::decode_group) reports before it touches `state`.
    pub(crate) fn check(&self, state: &DecoderState, tokens: &[[i64; N_STREAMS]], out: &[f32]) -> Result<()> {
        let same = match (&self.imp, &state.imp) {
            #[cfg(feature = "onnx")]
            (Imp::Tract(t), StateImp::Tract { plan, .. }) => Arc::ptr_eq(plan, &t.plan),
            (Imp::Native(n), StateImp::Native { model, .. }) => Arc::ptr_eq(model, n),
            #[cfg(feature = "onnx")]
            _ => false,
        };
        if !same {
            return Err(Error::WrongState("this DecoderState was created by another DecoderModel".into()));
        }
        let g = tokens.len();
        if !(1..=MAX_DECODE_GROUP).contains(&g) {
            return Err(Error::InvalidArgument(format!("a decode takes 1 to {MAX_DECODE_GROUP} tokens, got {g}")));
        }
        if out.len() != g * self.chunk_len() {
            return Err(Error::InvalidArgument(format!(
                "decode output buffer has {} values, needs {} ({g} x {} frames x {FRAME_DIM})",
                out.len(),
                g * self.chunk_len(),
                self.frames_per_token
            )));
        }
        for t in tokens {
            for (s, (&t, &j)) in t.iter().zip(&self.codebook).enumerate() {
                if t < 0 || t as u64 >= j as u64 {
                    return Err(Error::InvalidArgument(format!(
                        "code {t} of component {s} outside the codebook 0..{j}"
                    )));
                }
            }
        }
        Ok(())
    }

    /// [`decode`](Self::decode) after [`check`](Self::check) passed. The native decoder
    /// runs `extra` as one more job of its two threads; otherwise it runs after the decode.
    /// `team`: the native decoder may use its helper thread.
    pub(crate) fn decode_checked(
        &self,
        state: &mut DecoderState,
        tokens: &[[i64; N_STREAMS]],
        out: &mut [f32],
        extra: Option<&mut (dyn FnMut() + Send)>,
        team: bool,
    ) -> Result<()> {
        match &mut state.imp {
            #[cfg(feature = "onnx")]
            StateImp::Tract { run, inputs, .. } => {
                for (t, o) in tokens.iter().zip(out.chunks_exact_mut(self.chunk_len())) {
                    self.decode_tract(run, inputs, *t, o)?;
                    state.decoded += 1;
                }
                if let Some(f) = extra {
                    f();
                }
            }
            StateImp::Native { model, state: st } => {
                let mut ids = [[0; N_STREAMS]; MAX_GROUP];
                for (d, t) in ids.iter_mut().zip(tokens) {
                    *d = t.map(|c| c as usize);
                }
                model.decode_with(st, &ids[..tokens.len()], out, extra, team)?;
                state.decoded += tokens.len();
            }
        }
        Ok(())
    }

    /// Native decoders only: whether a decode uses two threads, and the bytes of weights
    /// it reads.
    pub(crate) fn native_threads_and_bytes(&self) -> Option<(usize, usize)> {
        match &self.imp {
            Imp::Native(n) => Some((if n.has_helper() { 2 } else { 1 }, n.weight_bytes())),
            #[cfg(feature = "onnx")]
            Imp::Tract(_) => None,
        }
    }

    #[cfg(feature = "onnx")]
    fn decode_tract(
        &self,
        run: &mut PlanState,
        inputs: &mut [Arc<Tensor>; 2],
        tokens: [i64; N_STREAMS],
        out: &mut [f32],
    ) -> Result<()> {
        graph::slice_mut::<i64>(&mut inputs[1], "decoder tokens")?.copy_from_slice(&tokens);
        let res = graph::run(run, inputs, "decoder.onnx")?;
        if res.len() != 2 {
            return Err(Error::Inference(format!("decoder.onnx returned {} outputs, expected 2", res.len())));
        }
        out.copy_from_slice(graph::slice::<f32>(&res[0], "decoder frames", self.chunk_len())?);
        let next = graph::slice::<i64>(&res[1], "decoder next_state", N_STREAMS * self.state_tokens)?;
        graph::slice_mut::<i64>(&mut inputs[0], "decoder state")?.copy_from_slice(next);
        Ok(())
    }
}

#[cfg(feature = "onnx")]
impl TractDecoder {
    fn load(src: &BundleSource, m: &Manifest) -> Result<TractDecoder> {
        let d = &m.decoder;
        let path = src.path_of(&d.file);
        let plan = graph::load(src, &d.file, &d.inputs, &d.outputs)?;
        let k1 = d.state_tokens;
        let flat: Vec<i64> = d.initial_state.iter().flatten().flatten().copied().collect();
        let initial = Tensor::from_shape::<i64>(&[1, N_STREAMS, k1], &flat)
            .map_err(|e| Error::bundle(&path, format!("decoder initial_state: {e:#}")))?;
        let template_tokens =
            Tensor::zero::<i64>(&[1, N_STREAMS]).map_err(|e| Error::bundle(&path, format!("{e:#}")))?;
        let template_run =
            Mutex::new(graph::spawn(&plan, "decoder.onnx").map_err(|e| Error::bundle(&path, e.to_string()))?);
        Ok(TractDecoder { plan, initial: Arc::new(initial), template_tokens: Arc::new(template_tokens), template_run })
    }
}

impl DecoderState {
    /// Tokens decoded since the state was created or reset.
    pub fn decoded(&self) -> usize {
        self.decoded
    }

    /// Starts a new sequence (no allocation).
    pub fn reset(&mut self) -> Result<()> {
        match &mut self.imp {
            #[cfg(feature = "onnx")]
            StateImp::Tract { inputs, initial, .. } => {
                let init = graph::slice::<i64>(initial, "decoder initial state", initial.len())?;
                graph::slice_mut::<i64>(&mut inputs[0], "decoder state")?.copy_from_slice(init);
            }
            StateImp::Native { model, state } => model.reset(state),
        }
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
