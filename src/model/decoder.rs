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
use super::native::decoder::{Batch, NativeDecoder, NativeState, Work, MAX_BATCH, MAX_GROUP};
use crate::bundle::manifest::{Manifest, FRAME_DIM, MANIFEST_FILE, N_STREAMS};
use crate::bundle::BundleSource;
use crate::config::RuntimeOptions;
use crate::error::{Error, Result};

/// Most tokens one [`DecoderModel::decode_group`] takes.
pub const MAX_DECODE_GROUP: usize = crate::config::MAX_DECODE_GROUP;
const _: () = assert!(MAX_DECODE_GROUP == MAX_GROUP);

/// Most streams one [`DecoderModel::decode_batch_checked`] takes.
pub(crate) const MAX_DECODE_BATCH: usize = MAX_BATCH;

/// One stream of a batched decode: its state, its tokens (checked) and where its frames go.
pub(crate) struct DecodeJob<'a> {
    pub state: &'a mut DecoderState,
    pub tokens: &'a [[i64; N_STREAMS]],
    pub out: &'a mut [f32],
}

/// The streams of a batched decode (as `StepJobs` for the batched step).
pub(crate) trait DecodeJobs {
    fn count(&self) -> usize;
    fn job(&mut self, i: usize) -> DecodeJob<'_>;
}

/// Scratch of batched decodes, made once per scheduler thread (the native decoder's
/// stacked buffers; nothing for tract).
pub(crate) struct DecodeScratch(Option<Work>);

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

    /// Scratch for [`decode_batch_checked`](Self::decode_batch_checked).
    pub(crate) fn batch_scratch(&self) -> DecodeScratch {
        DecodeScratch(match &self.imp {
            Imp::Native(n) => Some(n.batch_work()),
            #[cfg(feature = "onnx")]
            Imp::Tract(_) => None,
        })
    }

    /// [`decode_checked`](Self::decode_checked) of 1 to [`MAX_DECODE_BATCH`] streams, each
    /// job [`check`](Self::check)ed first (a bad one fails the batch before anything is
    /// decoded), on the calling thread. The native decoder runs them as one decode (each
    /// layer one GEMM over all their new positions: its weights read once, not once per
    /// stream), tract one after another; every stream gets the bits of its own decode.
    /// Allocation-free. Also fails when `scratch` is not this decoder's.
    pub(crate) fn decode_batch_checked(&self, jobs: &mut dyn DecodeJobs, scratch: &mut DecodeScratch) -> Result<()> {
        let n = jobs.count();
        if !(1..=MAX_DECODE_BATCH).contains(&n) {
            return Err(Error::InvalidArgument(format!(
                "a batched decode takes 1 to {MAX_DECODE_BATCH} streams, got {n}"
            )));
        }
        for i in 0..n {
            let j = jobs.job(i);
            self.check(j.state, j.tokens, j.out)?;
        }
        match (&self.imp, &mut scratch.0) {
            (Imp::Native(model), Some(wk)) => {
                let mut ids = [[[0; N_STREAMS]; MAX_GROUP]; MAX_BATCH];
                let mut g = [0; MAX_BATCH];
                for i in 0..n {
                    let j = jobs.job(i);
                    g[i] = j.tokens.len();
                    for (d, t) in ids[i].iter_mut().zip(j.tokens) {
                        *d = t.map(|c| c as usize);
                    }
                }
                model.decode_batch(&mut NativeJobs { jobs: &mut *jobs, ids: &ids, g: &g[..n] }, wk);
                for (i, &g) in g[..n].iter().enumerate() {
                    jobs.job(i).state.decoded += g;
                }
            }
            (Imp::Native(_), None) => return Err(Error::WrongState("decode scratch of another decoder".into())),
            #[cfg(feature = "onnx")]
            (Imp::Tract(_), _) => {
                for i in 0..n {
                    let j = jobs.job(i);
                    self.decode_checked(j.state, j.tokens, j.out, None, false)?;
                }
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

/// A batch's jobs as the native decoder's [`Batch`] (their tokens copied as ids).
struct NativeJobs<'a> {
    jobs: &'a mut dyn DecodeJobs,
    ids: &'a [[[usize; N_STREAMS]; MAX_GROUP]; MAX_BATCH],
    g: &'a [usize],
}

impl Batch for NativeJobs<'_> {
    fn count(&self) -> usize {
        self.g.len()
    }

    fn ids(&self, i: usize) -> &[[usize; N_STREAMS]] {
        &self.ids[i][..self.g[i]]
    }

    fn state(&mut self, i: usize) -> &mut NativeState {
        let st: &mut DecoderState = self.jobs.job(i).state;
        match &mut st.imp {
            StateImp::Native { state, .. } => state,
            // (decode_batch_checked checked every job's state first)
            #[cfg(feature = "onnx")]
            StateImp::Tract { .. } => unreachable!("a tract state in a native batch"),
        }
    }

    fn out(&mut self, i: usize) -> &mut [f32] {
        self.jobs.job(i).out
    }
}

#[allow(dead_code)]
fn _assert_send() {
    fn is_send<T: Send>() {}
    fn is_send_sync<T: Send + Sync>() {}
    is_send::<DecoderState>();
    is_send_sync::<DecoderModel>();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Bundle;

    /// Stream `i`'s group sizes and codes: every size 1 ..= 8 turns up, starts staggered.
    fn plan(i: usize, books: [usize; N_STREAMS]) -> Vec<Vec<[i64; N_STREAMS]>> {
        let mut s = (i as u64 + 7).wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        (0..6 + i)
            .map(|k| {
                let g = (i + 3 * k) % MAX_GROUP + 1;
                (0..g).map(|_| std::array::from_fn(|c| (next() % books[c] as u64) as i64)).collect()
            })
            .collect()
    }

    struct Jobs<'a> {
        states: &'a mut [DecoderState],
        tokens: Vec<&'a [[i64; N_STREAMS]]>,
        outs: &'a mut [Vec<f32>],
        idx: Vec<usize>,
        len: usize,
    }

    impl DecodeJobs for Jobs<'_> {
        fn count(&self) -> usize {
            self.idx.len()
        }
        fn job(&mut self, j: usize) -> DecodeJob<'_> {
            let i = self.idx[j];
            let n = self.tokens[j].len() * self.len;
            DecodeJob { state: &mut self.states[i], tokens: self.tokens[j], out: &mut self.outs[i][..n] }
        }
    }

    /// Streams at staggered positions with group sizes 1 to 8, decoded in batches of
    /// changing members, get the bits each gets decoded alone, native and tract.
    #[test]
    fn a_batched_decode_gives_each_stream_its_own_bits() {
        for dir in ["models/tiny", "models/default"] {
            let b = Bundle::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(dir)).unwrap();
            let backends: &[DecoderBackend] = if cfg!(feature = "onnx") && dir == "models/tiny" {
                &[DecoderBackend::Native, DecoderBackend::Tract]
            } else {
                &[DecoderBackend::Native]
            };
            for &backend in backends {
                let m = DecoderModel::load_backend(b.origin(), &b.manifest, Some(backend)).unwrap();
                let n = MAX_DECODE_BATCH + 1;
                let plans: Vec<_> = (0..n).map(|i| plan(i, m.codebook)).collect();
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let alone: Vec<Vec<u32>> = plans
                    .iter()
                    .map(|p| {
                        let mut st = m.new_state();
                        let mut all = Vec::new();
                        for g in p {
                            let mut out = vec![0.0; g.len() * m.chunk_len()];
                            m.decode_group(&mut st, g, &mut out).unwrap();
                            all.extend(bits(&out));
                        }
                        all
                    })
                    .collect();
                let mut states: Vec<_> = (0..n).map(|_| m.new_state()).collect();
                let mut outs = vec![vec![0.0; MAX_GROUP * m.chunk_len()]; n];
                let mut got = vec![Vec::new(); n];
                let mut sc = m.batch_scratch();
                // stream i starts at round i; a round's batches take up to MAX_DECODE_BATCH
                for round in 0..40 {
                    let live: Vec<usize> = (0..n).filter(|&i| round >= i && round - i < plans[i].len()).collect();
                    for part in live.chunks(MAX_DECODE_BATCH) {
                        let tokens = part.iter().map(|&i| &plans[i][round - i][..]).collect();
                        let len = m.chunk_len();
                        let mut jobs = Jobs { states: &mut states, tokens, outs: &mut outs, idx: part.to_vec(), len };
                        m.decode_batch_checked(&mut jobs, &mut sc).unwrap();
                        for &i in part {
                            got[i].extend(bits(&outs[i][..plans[i][round - i].len() * len]));
                        }
                    }
                }
                for i in 0..n {
                    assert_eq!(got[i], alone[i], "{dir} {backend:?}: stream {i}");
                    assert_eq!(states[i].decoded(), plans[i].iter().map(Vec::len).sum::<usize>());
                }
                // Wrong use fails before anything is decoded.
                let other = DecoderModel::load_backend(b.origin(), &b.manifest, Some(backend)).unwrap();
                let mut foreign = vec![other.new_state(), m.new_state()];
                let g = &plans[0][0][..];
                let mut jobs = Jobs {
                    states: &mut foreign,
                    tokens: vec![g, g],
                    outs: &mut outs,
                    idx: vec![1, 0],
                    len: m.chunk_len(),
                };
                if backend == DecoderBackend::Native {
                    assert!(matches!(m.decode_batch_checked(&mut jobs, &mut sc), Err(Error::WrongState(_))));
                    assert_eq!(foreign[1].decoded(), 0);
                }
                let mut none = Jobs { states: &mut states, tokens: vec![], outs: &mut outs, idx: vec![], len: 1 };
                assert!(matches!(m.decode_batch_checked(&mut none, &mut sc), Err(Error::InvalidArgument(_))));
            }
        }
    }
}
