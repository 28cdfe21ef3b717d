//! One decode step of the four coordinated Transformers (`step.onnx`) with a KV cache the
//! engine owns.
//!
//! The graph (export/step_graph.py) takes `tokens (1,4)`, `pos (1,)`, `text_emb (1,d)` and
//! per stream a full, fixed-size cache `cache_k_<s>`/`cache_v_<s>` of shape
//! `(L, 1, H, S, D_s)`; it returns the four logits vectors and the new k/v rows
//! `(L, 1, H, 1, D_s)` for slot `pos`, which this runner writes into the cache. The graph
//! never sees a growing tensor, so tract runs it with static shapes.
//!
//! Two implementations behind one API, chosen at load ([`StepBackend`]):
//! * **native** (when the bundle has `transformer.native`): the Rust kernels of
//!   `model::native::step` on the exporter's weight files (int8 where the graph stores
//!   int8). `step.onnx` is still read and its inputs/outputs checked against the manifest
//!   (it stays the reference), but it is not run. `step` allocates nothing.
//! * **tract**: the graph itself. The cache tensors, the small input tensors and the logits
//!   vectors live in [`StepState`] and are reused every step; tract gets cheap `Arc` clones
//!   of them and drops its references when the run ends, so they are updated in place.
//!   tract still allocates its own intermediates (and the 12 output tensors) inside a run.
//!
//! `RuntimeOptions::step_backend` (default `Auto` = native when the bundle has native
//! weights) forces one, e.g. to benchmark both; [`StepModel::load_with`] takes just the
//! backend.
//!
//! **Classifier-free guidance** ([`StepModel::new_guided_state`], DESIGN §4): a guided
//! state runs every step twice, on the prompt and on the null condition (a zero text
//! embedding, which `train-gpt --text-dropout` trains the model on), each with its own
//! cache, and its logits are `u + scale * (c - u)` per element in f32. In a batch the null
//! steps are members of their own, so their weights stream once with the others'.
use std::sync::Arc;

#[cfg(feature = "onnx")]
use parking_lot::Mutex;

#[cfg(feature = "onnx")]
use tract_onnx::prelude::Tensor;

#[cfg(feature = "onnx")]
use super::graph::{self, Plan, PlanState};
use super::native::step::{BatchScratch, Member, Members, NativeStep, NativeStepState};
use crate::bundle::manifest::{Manifest, N_STREAMS};
use crate::bundle::BundleSource;
use crate::config::RuntimeOptions;
use crate::error::{Error, Result};

pub use crate::config::StepBackend;

#[cfg(feature = "onnx")]
const TOKENS: usize = 0;
#[cfg(feature = "onnx")]
const POS: usize = 1;
#[cfg(feature = "onnx")]
const TEXT: usize = 2;
#[cfg(feature = "onnx")]
const FIRST_CACHE: usize = 3;

/// The error for a model without native weights in a build without tract.
#[cfg(not(feature = "onnx"))]
pub(super) fn no_onnx(src: &BundleSource, file: &str) -> Error {
    Error::bundle(
        src.path_of(file),
        "this library was built without the ONNX runtime (cargo feature `onnx`), and the bundle has no \
         native weights for this model",
    )
}

/// The loaded step; shared by all streams of an engine.
pub struct StepModel {
    imp: Imp,
    /// Identity of this model: states remember it, so a state is only run by its model.
    owner: Arc<()>,
    n_layers: usize,
    n_heads: usize,
    slots: usize,
    head_dims: [usize; N_STREAMS],
    vocab: [usize; N_STREAMS],
    d_text: usize,
    /// The null condition of classifier-free guidance: d_text zeros.
    null_text: Vec<f32>,
}

// One per loaded model: a couple of hundred bytes inline is nothing, and boxing the tract
// side would only add an indirection.
#[allow(clippy::large_enum_variant)]
enum Imp {
    #[cfg(feature = "onnx")]
    Tract(TractStep),
    Native(Box<NativeStep>),
}

#[cfg(feature = "onnx")]
struct TractStep {
    plan: Plan,
    /// Zeroed inputs and a spawned run state, cloned by `new_state` (made at load so that
    /// creating a stream cannot fail).
    template_inputs: Vec<Arc<Tensor>>,
    template_run: Mutex<PlanState>,
}

/// One generation's KV cache, logits and run state. Create with [`StepModel::new_state`];
/// reuse for a new generation with [`StepState::reset`].
pub struct StepState {
    owner: Arc<()>,
    imp: StateImp,
    logits: [Vec<f32>; N_STREAMS],
    /// Slots 0..filled hold k/v rows.
    filled: usize,
    /// Classifier-free guidance: the null condition's state (None: the prompt alone).
    guide: Option<Box<Guide>>,
}

/// The second half of a guided state: the same steps on the null condition.
struct Guide {
    scale: f32,
    imp: StateImp,
    logits: [Vec<f32>; N_STREAMS],
}

// One per stream, made once (see `Imp`).
#[allow(clippy::large_enum_variant)]
enum StateImp {
    #[cfg(feature = "onnx")]
    Tract {
        run: PlanState,
        /// tokens, pos, text_emb, then cache_k/cache_v per stream, as the graph takes them.
        inputs: Vec<Arc<Tensor>>,
    },
    Native(Box<NativeStepState>),
}

impl std::fmt::Debug for StepState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StepState").field("filled", &self.filled).finish_non_exhaustive()
    }
}

impl std::fmt::Debug for StepModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StepModel")
            .field("backend", &self.backend())
            .field("n_layers", &self.n_layers)
            .field("n_heads", &self.n_heads)
            .field("slots", &self.slots)
            .field("head_dims", &self.head_dims)
            .field("vocab", &self.vocab)
            .finish_non_exhaustive()
    }
}

impl StepModel {
    /// Loads the step of a verified manifest as `options` say (`step_backend`: `Auto` is
    /// native when the bundle has `transformer.native`; `step_threads`). Either way
    /// `transformer.file` is checked against the manifest.
    pub fn load(src: &BundleSource, m: &Manifest, options: &RuntimeOptions) -> Result<StepModel> {
        let t = &m.transformer;
        let native = match (options.step_backend, &t.native) {
            (StepBackend::Tract, _) | (StepBackend::Auto, None) => None,
            (_, Some(spec)) => Some(spec),
            (StepBackend::Native, None) => {
                return Err(Error::bundle(
                    src.path_of(crate::bundle::manifest::MANIFEST_FILE),
                    "the step backend is native, but the bundle has no transformer.native weights",
                ));
            }
        };
        let imp = match native {
            Some(spec) => {
                #[cfg(feature = "onnx")]
                graph::check(src, &t.file, &t.inputs, &t.outputs)?;
                Imp::Native(Box::new(NativeStep::load(src, m, spec, options.step_threads)?))
            }
            #[cfg(not(feature = "onnx"))]
            None => return Err(no_onnx(src, &t.file)),
            #[cfg(feature = "onnx")]
            None => {
                let plan = graph::load(src, &t.file, &t.inputs, &t.outputs)?;
                let path = src.path_of(&t.file);
                let template_inputs = t
                    .inputs
                    .iter()
                    .map(graph::zeros)
                    .collect::<Result<Vec<_>>>()
                    .map_err(|e| Error::bundle(&path, e.to_string()))?;
                let template_run =
                    Mutex::new(graph::spawn(&plan, "step.onnx").map_err(|e| Error::bundle(&path, e.to_string()))?);
                Imp::Tract(TractStep { plan, template_inputs, template_run })
            }
        };
        Ok(StepModel {
            imp,
            owner: Arc::new(()),
            n_layers: t.n_layers,
            n_heads: t.n_heads,
            slots: t.cache_slots,
            head_dims: std::array::from_fn(|i| t.head_dims[i]),
            vocab: m.vocab_sizes(),
            d_text: t.d_text,
            null_text: vec![0.0; t.d_text],
        })
    }

    /// [`load`](Self::load) with `backend` and the other options automatic.
    pub fn load_with(src: &BundleSource, m: &Manifest, backend: StepBackend) -> Result<StepModel> {
        StepModel::load(src, m, &RuntimeOptions { step_backend: backend, ..RuntimeOptions::default() })
    }

    /// The implementation that runs the step: `Native` or `Tract` (never `Auto`).
    pub fn backend(&self) -> StepBackend {
        match self.imp {
            #[cfg(feature = "onnx")]
            Imp::Tract(_) => StepBackend::Tract,
            Imp::Native(_) => StepBackend::Native,
        }
    }

    /// Number of cache slots S (= L_max + 2): positions 0..S.
    pub fn cache_slots(&self) -> usize {
        self.slots
    }

    /// Width of the text embedding the step takes.
    pub fn d_text(&self) -> usize {
        self.d_text
    }

    /// Vocabulary sizes (logits lengths) of the four streams.
    pub fn vocab_sizes(&self) -> [usize; N_STREAMS] {
        self.vocab
    }

    /// Bytes of weights the native step reads per step (`None` on tract).
    pub fn native_weight_bytes(&self) -> Option<usize> {
        match &self.imp {
            Imp::Native(n) => Some(n.weight_bytes()),
            #[cfg(feature = "onnx")]
            Imp::Tract(_) => None,
        }
    }

    /// A fresh state: zero cache, nothing filled.
    pub fn new_state(&self) -> StepState {
        StepState {
            owner: Arc::clone(&self.owner),
            imp: self.new_imp(),
            logits: self.zero_logits(),
            filled: 0,
            guide: None,
        }
    }

    /// A fresh state whose steps are guided with `scale` (classifier-free guidance, see the
    /// module doc; `SamplingParams::guidance` validates it): 1 is the prompt alone (a plain
    /// state), 0 the null condition alone.
    pub fn new_guided_state(&self, scale: f32) -> StepState {
        let mut state = self.new_state();
        if scale != 1.0 {
            state.guide = Some(Box::new(Guide { scale, imp: self.new_imp(), logits: self.zero_logits() }));
        }
        state
    }

    fn new_imp(&self) -> StateImp {
        match &self.imp {
            #[cfg(feature = "onnx")]
            Imp::Tract(t) => StateImp::Tract {
                run: t.template_run.lock().clone(),
                inputs: t.template_inputs.iter().map(|t| Arc::new(Tensor::clone(t))).collect(),
            },
            Imp::Native(n) => StateImp::Native(Box::new(n.new_state())),
        }
    }

    fn zero_logits(&self) -> [Vec<f32>; N_STREAMS] {
        std::array::from_fn(|i| vec![0.0; self.vocab[i]])
    }

    /// Runs one step at position `pos` and returns the four logits vectors (global, body,
    /// lhand, rhand), valid until the next call on `state`.
    ///
    /// `pos` 0 is the condition step: `text_emb` is projected into the condition token and
    /// `tokens` must still be valid ids (feed the pad ids). At `pos` k >= 1 `tokens` are the
    /// codes sampled at step k-1. `pos` may go back to an earlier position (the rows
    /// from there on are then recomputed) but never skip one: the cache must hold rows 0..pos.
    pub fn step<'s>(
        &self,
        state: &'s mut StepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
    ) -> Result<[&'s [f32]; N_STREAMS]> {
        self.check(state, tokens, pos, text_emb)?;
        self.run_checked(state, tokens, pos, text_emb, false)?;
        Ok(state.logits())
    }

    /// The errors [`step`](Self::step) reports before it touches `state`.
    pub(crate) fn check(
        &self,
        state: &StepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
    ) -> Result<()> {
        if !Arc::ptr_eq(&state.owner, &self.owner) {
            return Err(Error::WrongState("this StepState was created by another StepModel".into()));
        }
        if pos >= self.slots {
            return Err(Error::InvalidArgument(format!("step position {pos} beyond the cache's {} slots", self.slots)));
        }
        if pos > state.filled {
            return Err(Error::WrongState(format!(
                "step position {pos} skips positions: cache holds 0..{}",
                state.filled
            )));
        }
        if text_emb.len() != self.d_text {
            return Err(Error::InvalidArgument(format!(
                "text embedding has {} values, the model takes {}",
                text_emb.len(),
                self.d_text
            )));
        }
        if !text_emb.iter().all(|v| v.is_finite()) {
            return Err(Error::InvalidArgument("text embedding contains a non-finite value".into()));
        }
        for (s, (&t, &v)) in tokens.iter().zip(&self.vocab).enumerate() {
            if t < 0 || t as u64 >= v as u64 {
                return Err(Error::InvalidArgument(format!("token {t} of stream {s} outside the vocabulary 0..{v}")));
            }
        }
        Ok(())
    }

    /// [`step`](Self::step) after [`check`](Self::check) passed; `solo`: the native step
    /// stays on the calling thread.
    pub(crate) fn run_checked(
        &self,
        state: &mut StepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
        solo: bool,
    ) -> Result<()> {
        self.run_imp(&mut state.imp, &mut state.logits, tokens, pos, text_emb, solo)?;
        if let Some(g) = &mut state.guide {
            self.run_imp(&mut g.imp, &mut g.logits, tokens, pos, &self.null_text, solo)?;
            guide_logits(&mut state.logits, &g.logits, g.scale);
        }
        // Rows after `pos` (from an earlier, longer run) are stale now.
        state.filled = pos + 1;
        Ok(())
    }

    fn run_imp(
        &self,
        imp: &mut StateImp,
        logits: &mut [Vec<f32>; N_STREAMS],
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
        solo: bool,
    ) -> Result<()> {
        match (&self.imp, imp) {
            (Imp::Native(n), StateImp::Native(st)) if solo => n.step_solo(st, tokens, pos, text_emb, logits),
            (Imp::Native(n), StateImp::Native(st)) => n.step(st, tokens, pos, text_emb, logits),
            #[cfg(feature = "onnx")]
            (Imp::Tract(t), StateImp::Tract { run, inputs }) => {
                self.tract_step(t, run, inputs, logits, tokens, pos, text_emb)?
            }
            #[cfg(feature = "onnx")]
            _ => return Err(Error::WrongState("this StepState belongs to another implementation".into())),
        }
        Ok(())
    }

    /// One step for every job, as [`step`](Self::step) on each (the same bits: each job's
    /// logits and cache are the ones it gets alone), every job already passed
    /// [`check`](Self::check). Native: one batched step on the calling thread, each weight
    /// block read once for all jobs (`model::native::step::batch`); tract: one after the other.
    /// `scratch`: from [`batch_scratch`](Self::batch_scratch), for at least `jobs.count()`.
    pub(crate) fn step_batch_checked(&self, jobs: &mut dyn StepJobs, scratch: &mut StepScratch) -> Result<()> {
        match (&self.imp, &mut scratch.native) {
            (Imp::Native(n), Some(sc)) => {
                // guided jobs' null steps are members after the jobs (the scratch has room)
                let guided = &mut scratch.guided;
                guided.clear();
                guided.extend((0..jobs.count()).filter(|&i| jobs.job(i).state.guide.is_some()));
                n.step_batch(&mut NativeJobs { jobs: &mut *jobs, guided, null_text: &self.null_text }, sc);
                for i in 0..jobs.count() {
                    let j = jobs.job(i);
                    // Rows after `pos` (from an earlier, longer run) are stale now.
                    j.state.filled = j.pos + 1;
                    if let Some(g) = &j.state.guide {
                        guide_logits(&mut j.state.logits, &g.logits, g.scale);
                    }
                }
            }
            (Imp::Native(_), None) => return Err(Error::WrongState("step scratch of another model".into())),
            // (run_checked sets `filled` itself)
            #[cfg(feature = "onnx")]
            (Imp::Tract(_), _) => {
                for i in 0..jobs.count() {
                    let j = jobs.job(i);
                    self.run_checked(j.state, j.tokens, j.pos, j.text_emb, true)?;
                }
            }
        }
        Ok(())
    }

    /// Scratch for batched steps of up to `cap` jobs, guided or not (allocated here, once).
    pub(crate) fn batch_scratch(&self, cap: usize) -> StepScratch {
        StepScratch {
            native: match &self.imp {
                // a guided job is two members
                Imp::Native(n) => Some(n.batch_scratch(2 * cap)),
                #[cfg(feature = "onnx")]
                Imp::Tract(_) => None,
            },
            guided: Vec::with_capacity(cap),
        }
    }

    #[cfg(feature = "onnx")]
    #[allow(clippy::too_many_arguments)]
    fn tract_step(
        &self,
        t: &TractStep,
        run: &mut PlanState,
        inputs: &mut [Arc<Tensor>],
        logits: &mut [Vec<f32>; N_STREAMS],
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
    ) -> Result<()> {
        let _ = &t.plan;
        graph::slice_mut::<i64>(&mut inputs[TOKENS], "tokens")?.copy_from_slice(&tokens);
        graph::slice_mut::<i64>(&mut inputs[POS], "pos")?[0] = pos as i64;
        graph::slice_mut::<f32>(&mut inputs[TEXT], "text_emb")?.copy_from_slice(text_emb);

        let out = graph::run(run, inputs, "step.onnx")?;
        if out.len() != 3 * N_STREAMS {
            return Err(Error::Inference(format!(
                "step.onnx returned {} outputs, expected {}",
                out.len(),
                3 * N_STREAMS
            )));
        }
        for s in 0..N_STREAMS {
            let lg = graph::slice::<f32>(&out[s], "step.onnx logits", self.vocab[s])?;
            logits[s].copy_from_slice(lg);
        }
        let (l, h, slots) = (self.n_layers, self.n_heads, self.slots);
        for s in 0..N_STREAMS {
            let d = self.head_dims[s];
            for kv in 0..2 {
                let row = graph::slice::<f32>(&out[N_STREAMS + 2 * s + kv], "step.onnx new k/v", l * h * d)?;
                let cache = graph::slice_mut::<f32>(&mut inputs[FIRST_CACHE + 2 * s + kv], "kv cache")?;
                // cache (L, 1, H, S, D)[.., .., .., pos, ..] = row (L, 1, H, 1, D)[.., .., .., 0, ..]
                for lh in 0..l * h {
                    let dst = (lh * slots + pos) * d;
                    cache[dst..dst + d].copy_from_slice(&row[lh * d..(lh + 1) * d]);
                }
            }
        }
        drop(out);
        Ok(())
    }
}

/// One generation's step in [`StepModel::step_batch_checked`]: what [`StepModel::step`] takes.
pub(crate) struct StepJob<'a> {
    pub(crate) state: &'a mut StepState,
    pub(crate) tokens: [i64; N_STREAMS],
    pub(crate) pos: usize,
    pub(crate) text_emb: &'a [f32],
}

/// A batched step's buffers ([`StepModel::batch_scratch`]; none on tract) and the indices
/// of its guided jobs.
pub(crate) struct StepScratch {
    native: Option<BatchScratch>,
    guided: Vec<usize>,
}

/// Classifier-free guidance: `cond <- u + scale * (cond - u)` per element in f32, each
/// operation rounded (Rust contracts no multiply-add), as `sampling.guide_logits`.
fn guide_logits(cond: &mut [Vec<f32>; N_STREAMS], null: &[Vec<f32>; N_STREAMS], scale: f32) {
    for (c, u) in cond.iter_mut().zip(null) {
        for (c, &u) in c.iter_mut().zip(u) {
            *c = u + scale * (*c - u);
        }
    }
}

/// The jobs of a batched step, by index (the caller keeps them in its own structures).
pub(crate) trait StepJobs {
    fn count(&self) -> usize;
    fn job(&mut self, i: usize) -> StepJob<'_>;
}

/// Checked jobs of a native model as the native batch's members: the jobs, then the null
/// steps of the guided ones (`guided`: their job indices).
struct NativeJobs<'j> {
    jobs: &'j mut dyn StepJobs,
    guided: &'j [usize],
    null_text: &'j [f32],
}

impl Members for NativeJobs<'_> {
    fn count(&self) -> usize {
        self.jobs.count() + self.guided.len()
    }

    fn member(&mut self, i: usize) -> Member<'_> {
        let n = self.jobs.count();
        let null = i >= n;
        let StepJob { state, tokens, pos, text_emb } = self.jobs.job(if null { self.guided[i - n] } else { i });
        let (imp, logits, text_emb) = match (null, &mut state.guide) {
            (true, Some(g)) => (&mut g.imp, &mut g.logits, self.null_text),
            // `guided` lists only jobs with a guide
            (true, None) => unreachable!("a null member of an unguided job"),
            (false, _) => (&mut state.imp, &mut state.logits, text_emb),
        };
        match imp {
            StateImp::Native(st) => Member { st, logits, tokens, pos, text_emb },
            // `check` (the same model made the state) rules this out
            #[cfg(feature = "onnx")]
            StateImp::Tract { .. } => panic!("a tract StepState in a native batch"),
        }
    }
}

impl StepState {
    /// Starts a new generation: zero cache, nothing filled (no allocation).
    pub fn reset(&mut self) -> Result<()> {
        reset_imp(&mut self.imp)?;
        if let Some(g) = &mut self.guide {
            reset_imp(&mut g.imp)?;
        }
        self.filled = 0;
        Ok(())
    }

    /// The classifier-free guidance scale of this state (1 = unguided).
    pub fn guidance(&self) -> f32 {
        self.guide.as_ref().map_or(1.0, |g| g.scale)
    }

    /// The logits of the last step (zeros before the first).
    pub fn logits(&self) -> [&[f32]; N_STREAMS] {
        std::array::from_fn(|i| self.logits[i].as_slice())
    }

    /// Number of positions whose k/v rows are in the cache.
    pub fn filled(&self) -> usize {
        self.filled
    }
}

fn reset_imp(imp: &mut StateImp) -> Result<()> {
    match imp {
        #[cfg(feature = "onnx")]
        StateImp::Tract { inputs, .. } => {
            for t in inputs.iter_mut() {
                graph::fill_zero(t)?;
            }
        }
        StateImp::Native(st) => st.reset(),
    }
    Ok(())
}

#[allow(dead_code)]
fn _assert_send() {
    fn is_send<T: Send>() {}
    fn is_send_sync<T: Send + Sync>() {}
    is_send::<StepState>();
    is_send_sync::<StepModel>();
}
