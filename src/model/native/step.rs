//! The native decode step: `ComGraspTransformer.step` (training/.../models/transformer.py)
//! in Rust, on the weights of `transformer.native`, into buffers allocated once per state.
//!
//! Per step, for the four streams s (widths w_s, H heads of d_s = w_s / H):
//! * input: pos 0 `cond_s(text_emb)`, else `tok_s[token]`; plus `pos_s[pos]`;
//! * per layer l: before every layer but the first, part coordination
//!   `h_i <- LN_i(h_i + out_i(MLP(concat_{j != i} in_j(h_j))))` (the shared MLP runs on the
//!   four concatenations at once, so its weights are read once); then the pre-LN block
//!   `h += proj(attn(LN1 h)); h += fc2(GELU(fc1(LN2 h)))`, the attention writing the new
//!   k/v row into slot `pos` of the state's cache and attending over slots `0..=pos`;
//! * `logits_s = head_s(LN_f h_s)`.
//!
//! The graph instead attends over the cache's slots `< pos` plus the new row as a separate
//! score; that is the same softmax (masked slots weigh exactly 0), up to float rounding.
//! LayerNorm eps is PyTorch's default 1e-5.
//!
//! **Two threads.** A step is a fixed sequence of phases, each over all four streams at
//! once: the input; per layer the coordination's input projections, its three MLP layers,
//! its output projections and its norms, then the blocks' LN1 + qkv, attention, proj,
//! LN2 + fc1 + GELU, fc2; the heads (2 + 5 L + 6 (L - 1) phases, 150 on the paper model).
//! Each phase is cut into units (blocks of rows of its products, ~32 KB of weights each
//! and a multiple of 4 rows, the GEMV kernels' row blocks; or attention heads). With two
//! threads the caller and a helper thread (team.rs, one per loaded model, started at
//! load) take the units of each phase from both ends and meet before the next phase. Each
//! unit carries its own parts of the phase's outputs, cut with `split_at_mut`
//! ([`RowUnits`]), and reads the phase's inputs by shared reference; a thread the OS preempts, or a helper that wakes late, leaves its share to the
//! other instead of stalling it. Every output value is computed by the same kernel in the
//! same order whoever computes it, so logits and caches are bit-identical for any thread
//! count (tests/native_step.rs, and the unit tests below). A step that finds the helper
//! busy (another stream's step has it) runs alone, and no step allocates.
//!
//! `RuntimeOptions::step_threads` (1 or 2, read at load) picks the count; the default is 2 when the
//! machine has two or more cores and the step reads at least [`SPLIT_MIN_BYTES`] of
//! weights. Measured on the 2-core machine: models/tiny (0.5 MB, 16 us per step) is slower
//! on two threads (~25 us: the hand-over costs ~10 us), models/default (10 MB int8) goes
//! from 0.60 to 0.37 ms, int8 models of default's shape with the widths scaled down gain
//! 1.3-1.6x down to 0.3 MB; the paper model is bound by the memory bandwidth, which one
//! thread nearly saturates (63 -> 54 ms in one run of scripts/bench.sh).
//!
//! **Weights.** The step's matrices are copied at load into one arena (see [`Arena`]) in
//! 2 MiB pages where the system allows: a fp32 GEMV streams ~28 GB/s through them on one
//! core against ~15-20 GB/s through 4 KiB pages.
use std::ops::Range;

use super::arena::{Arena, Wm};
use super::kernels::{add_assign, dot, gelu_erf, gemm_rows, gemv_rows, layer_norm, layer_norm_rows, softmax};
use super::team::{Crew, Helper, Order, Units};
use super::weights::{Matrix, Tensors};
use crate::bundle::manifest::{Manifest, NativeSpec, N_STREAMS};
use crate::bundle::BundleSource;
use crate::config::two_threads;
use crate::error::{Error, Result};

mod batch;
pub(crate) use batch::{BatchScratch, Member, Members};

const LN_EPS: f32 = 1e-5;

/// Below this many weight bytes per step one thread is faster than two (the module doc's
/// measurements: models/tiny's 0.5 MB lose, 0.3 MB models of default's shape gain, so the
/// line is drawn conservatively).
pub(crate) const SPLIT_MIN_BYTES: usize = 1 << 20;
/// Team members a state has scratch buffers for.
const MAX_THREADS: usize = 2;

struct Linear {
    w: Wm,
    b: Option<Vec<f32>>,
}

impl Linear {
    fn load(t: &Tensors, arena: &mut Arena, name: &str, rows: usize, cols: usize, bias: bool) -> Result<Linear> {
        Ok(Linear {
            w: arena.put(t.matrix(&format!("{name}.weight"), rows, cols)?),
            b: if bias { Some(t.vector(&format!("{name}.bias"), rows)?) } else { None },
        })
    }

    /// Rows `r` of the product (`y.len() == r.len()`).
    fn rows(&self, a: &Arena, x: &[f32], r: Range<usize>, y: &mut [f32]) {
        gemv_rows(a.mat(&self.w), x, self.b.as_deref(), r, y)
    }
}

struct Norm {
    w: Vec<f32>,
    b: Vec<f32>,
}

impl Norm {
    fn load(t: &Tensors, name: &str, n: usize) -> Result<Norm> {
        Ok(Norm { w: t.vector(&format!("{name}.weight"), n)?, b: t.vector(&format!("{name}.bias"), n)? })
    }

    fn run(&self, x: &[f32], out: &mut [f32]) {
        layer_norm(x, &self.w, &self.b, LN_EPS, out)
    }

    /// Elements `r` of `run`.
    fn rows(&self, x: &[f32], r: Range<usize>, out: &mut [f32]) {
        layer_norm_rows(x, &self.w, &self.b, LN_EPS, r, out)
    }
}

struct Block {
    ln1: Norm,
    qkv: Linear,
    proj: Linear,
    ln2: Norm,
    fc1: Linear,
    fc2: Linear,
}

struct Stream {
    cond: Linear,
    tok: Matrix,
    pos: Vec<f32>,
    blocks: Vec<Block>,
    ln_f: Norm,
    head: Wm,
}

struct Coord {
    inp: Vec<Linear>,
    mlp: [Linear; 3],
    out: Vec<Linear>,
    norm: Vec<Norm>,
}

/// Sizes of the network (from the manifest; the hidden widths from the tensors' shapes).
#[derive(Clone, Copy, Debug)]
struct Dims {
    n_layers: usize,
    n_heads: usize,
    slots: usize,
    d_text: usize,
    widths: [usize; N_STREAMS],
    head_dims: [usize; N_STREAMS],
    vocab: [usize; N_STREAMS],
    /// The blocks' MLP width per stream (mlp_ratio x width).
    hidden: [usize; N_STREAMS],
    coord_width: usize,
    coord_hidden: usize,
}

/// The step's weights, shared by all states of a model.
pub(crate) struct NativeStep {
    /// Every weight matrix but the token tables (`Wm`s point into it).
    arena: Arena,
    d: Dims,
    streams: Vec<Stream>,
    coord: Vec<Coord>,
    /// 1/sqrt(head_dim) per stream, as the graph's constant (computed in f64, then rounded).
    scale: [f32; N_STREAMS],
    bytes: usize,
    /// The second thread, when steps use two.
    helper: Option<Helper>,
    /// Weight bytes per unit of a phase ([`UNIT_BYTES`]; tests use smaller units).
    unit_bytes: usize,
}

/// One generation's KV cache and scratch buffers (everything `step` writes).
pub(crate) struct NativeStepState {
    bufs: Bufs,
    /// Per team member (caller, helper): what each computes in full for itself.
    own: [Own; MAX_THREADS],
}

/// The buffers the members of a step's team share: each phase hands out disjoint parts
/// of the ones it writes and lets every member read the others.
struct Bufs {
    /// Per stream, (L, H, S, D) row-major: the layout of the graph's cache inputs.
    k: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    /// Per stream: the residual stream, qkv, attention output, a product's output, the MLP's
    /// hidden activations.
    h: Vec<Vec<f32>>,
    qkv: Vec<Vec<f32>>,
    att: Vec<Vec<f32>>,
    tmp: Vec<Vec<f32>>,
    mlp: Vec<Vec<f32>>,
    /// Coordination: the four projections, their four concatenations, the MLP's
    /// activations (four rows each).
    cp: Vec<f32>,
    ccat: Vec<f32>,
    ch1: Vec<f32>,
    ch2: Vec<f32>,
    cm: Vec<f32>,
}

/// A team member's private buffers.
struct Own {
    /// Per stream, a LayerNorm's output (the input of the next product), and whether this
    /// member computed it in the current phase.
    x: Vec<Vec<f32>>,
    have: [bool; N_STREAMS],
    scores: Vec<f32>,
    /// This member's rows of a coordination MLP product, four rows.
    part: Vec<f32>,
}

impl NativeStep {
    /// Loads every tensor of `spec`, checking it against the manifest's sizes; any missing,
    /// extra, misshapen, mistyped or non-finite tensor is an `Error::Bundle`.
    /// `threads`: `RuntimeOptions::step_threads` (`None`: two when it pays).
    pub(crate) fn load(
        src: &BundleSource,
        m: &Manifest,
        spec: &NativeSpec,
        threads: Option<usize>,
    ) -> Result<NativeStep> {
        let t = &m.transformer;
        let tensors = Tensors::new(src, spec);
        let err = |msg: String| Error::bundle(src.path_of(&spec.dir), msg);
        if t.widths.len() != N_STREAMS || t.head_dims.len() != N_STREAMS {
            return Err(err(format!(
                "the transformer has {} widths, the native step needs {N_STREAMS}",
                t.widths.len()
            )));
        }
        let widths: [usize; N_STREAMS] = std::array::from_fn(|i| t.widths[i]);
        let head_dims: [usize; N_STREAMS] = std::array::from_fn(|i| t.head_dims[i]);
        for s in 0..N_STREAMS {
            if widths[s] == 0 || head_dims[s] * t.n_heads != widths[s] {
                return Err(err(format!(
                    "stream {s}: width {} is not n_heads {} x head_dim {}",
                    widths[s], t.n_heads, head_dims[s]
                )));
            }
        }
        if t.n_layers == 0 || t.cache_slots == 0 || t.d_text == 0 {
            return Err(err("the transformer needs at least one layer, one slot and a text width".into()));
        }
        // Hidden widths are not in the manifest: read them from the first tensors' shapes
        // (every other tensor is then checked against them).
        let first_axis = |name: &str| -> Result<usize> {
            tensors.shape(name)?.first().copied().ok_or_else(|| err(format!("native tensor {name} is a scalar")))
        };
        let hidden: [usize; N_STREAMS] = {
            let mut h = [0; N_STREAMS];
            for (s, hs) in h.iter_mut().enumerate() {
                *hs = first_axis(&format!("streams.{s}.blocks.0.mlp.0.weight"))?;
            }
            h
        };
        let (coord_width, coord_hidden) = if t.n_layers > 1 {
            (first_axis("coord.0.inp.0.weight")?, first_axis("coord.0.mlp.0.weight")?)
        } else {
            (0, 0)
        };
        let d = Dims {
            n_layers: t.n_layers,
            n_heads: t.n_heads,
            slots: t.cache_slots,
            d_text: t.d_text,
            widths,
            head_dims,
            vocab: m.vocab_sizes(),
            hidden,
            coord_width,
            coord_hidden,
        };
        // Guard the products used for buffer sizes against absurd manifests.
        d.n_layers
            .checked_mul(d.slots)
            .and_then(|v| v.checked_mul(widths.iter().max().copied()?))
            .filter(|&v| v <= 1 << 32)
            .ok_or_else(|| err("the KV cache would be absurdly large".into()))?;

        let mut arena = Arena::new(arena_bytes(&d))
            .ok_or_else(|| Error::bundle(src.path_of(&spec.dir), "no memory for the native step's weights"))?;
        let mut expected = std::collections::BTreeSet::new();
        let mut note = |n: String| -> String {
            expected.insert(n.clone());
            n
        };
        let mut streams = Vec::with_capacity(N_STREAMS);
        for s in 0..N_STREAMS {
            let (w, v, hid) = (widths[s], d.vocab[s], hidden[s]);
            let p = |n: &str| format!("streams.{s}.{n}");
            let mut lin =
                |n: String, rows, cols| -> Result<Linear> { Linear::load(&tensors, &mut arena, &n, rows, cols, true) };
            let mut blocks = Vec::with_capacity(d.n_layers);
            for l in 0..d.n_layers {
                let b = |n: &str| format!("streams.{s}.blocks.{l}.{n}");
                for n in ["ln1", "attn.qkv", "attn.proj", "ln2", "mlp.0", "mlp.2"] {
                    note(b(&format!("{n}.weight")));
                    note(b(&format!("{n}.bias")));
                }
                blocks.push(Block {
                    ln1: Norm::load(&tensors, &b("ln1"), w)?,
                    qkv: lin(b("attn.qkv"), 3 * w, w)?,
                    proj: lin(b("attn.proj"), w, w)?,
                    ln2: Norm::load(&tensors, &b("ln2"), w)?,
                    fc1: lin(b("mlp.0"), hid, w)?,
                    fc2: lin(b("mlp.2"), w, hid)?,
                });
            }
            for n in ["pos", "cond.weight", "cond.bias", "tok.weight", "ln_f.weight", "ln_f.bias", "head.weight"] {
                note(p(n));
            }
            let pos_shape = tensors.shape(&p("pos"))?;
            if pos_shape != [d.slots, w] {
                return Err(err(format!(
                    "native tensor {} has shape {pos_shape:?}, expected [{}, {w}]",
                    p("pos"),
                    d.slots
                )));
            }
            streams.push(Stream {
                cond: lin(p("cond"), w, d.d_text)?,
                tok: tensors.matrix(&p("tok.weight"), v, w)?,
                pos: tensors.vector(&p("pos"), d.slots * w)?,
                blocks,
                ln_f: Norm::load(&tensors, &p("ln_f"), w)?,
                head: arena.put(tensors.matrix(&p("head.weight"), v, w)?),
            });
        }
        let (cw, ch) = (coord_width, coord_hidden);
        let mut coord = Vec::with_capacity(d.n_layers.saturating_sub(1));
        for c in 0..d.n_layers.saturating_sub(1) {
            let n = |x: &str| format!("coord.{c}.{x}");
            for x in ["mlp.0", "mlp.2", "mlp.4"] {
                note(n(&format!("{x}.weight")));
                note(n(&format!("{x}.bias")));
            }
            let mut inp = Vec::new();
            let mut out = Vec::new();
            let mut norm = Vec::new();
            for (s, &width) in widths.iter().enumerate() {
                for x in ["inp", "out", "norm"] {
                    note(n(&format!("{x}.{s}.weight")));
                    note(n(&format!("{x}.{s}.bias")));
                }
                inp.push(Linear::load(&tensors, &mut arena, &n(&format!("inp.{s}")), cw, width, true)?);
                out.push(Linear::load(&tensors, &mut arena, &n(&format!("out.{s}")), width, cw, true)?);
                norm.push(Norm::load(&tensors, &n(&format!("norm.{s}")), width)?);
            }
            coord.push(Coord {
                inp,
                mlp: [
                    Linear::load(&tensors, &mut arena, &n("mlp.0"), ch, (N_STREAMS - 1) * cw, true)?,
                    Linear::load(&tensors, &mut arena, &n("mlp.2"), ch, ch, true)?,
                    Linear::load(&tensors, &mut arena, &n("mlp.4"), cw, ch, true)?,
                ],
                out,
                norm,
            });
        }
        if let Some(extra) = tensors.names().find(|n| !expected.contains(*n)) {
            return Err(err(format!("native weights hold tensor {extra}, which the step does not use")));
        }
        arena.trim();
        let mut step = NativeStep::assemble(arena, d, streams, coord);
        step.set_threads(if two_threads(threads, step.bytes >= SPLIT_MIN_BYTES) { 2 } else { 1 });
        Ok(step)
    }

    fn assemble(arena: Arena, d: Dims, streams: Vec<Stream>, coord: Vec<Coord>) -> NativeStep {
        let mut bytes = 0;
        for s in &streams {
            bytes += s.cond.w.bytes() + s.head.bytes();
            for b in &s.blocks {
                bytes += b.qkv.w.bytes() + b.proj.w.bytes() + b.fc1.w.bytes() + b.fc2.w.bytes();
            }
        }
        for c in &coord {
            bytes += c.mlp.iter().chain(&c.inp).chain(&c.out).map(|l| l.w.bytes()).sum::<usize>();
        }
        let scale = std::array::from_fn(|s| (1.0 / (d.head_dims[s] as f64).sqrt()) as f32);
        NativeStep { arena, d, streams, coord, scale, bytes, helper: None, unit_bytes: UNIT_BYTES }
    }

    /// Steps use `n` threads (1 or 2; 1 if no thread can be started).
    fn set_threads(&mut self, n: usize) {
        self.helper = if n >= 2 { Helper::start_named("comgrasp-step").ok() } else { None };
    }

    /// Threads a step uses (when the helper is not busy).
    #[allow(dead_code)]
    pub(crate) fn threads(&self) -> usize {
        if self.helper.is_some() {
            2
        } else {
            1
        }
    }

    /// Bytes of weight matrices one step reads.
    pub(crate) fn weight_bytes(&self) -> usize {
        self.bytes
    }

    /// A state with a zero cache and every scratch buffer allocated.
    pub(crate) fn new_state(&self) -> NativeStepState {
        let d = &self.d;
        let cache = |s: usize| vec![0.0f32; d.n_layers * d.slots * d.widths[s]];
        let per_stream = |f: &dyn Fn(usize) -> usize| (0..N_STREAMS).map(|s| vec![0.0f32; f(s)]).collect::<Vec<_>>();
        NativeStepState {
            bufs: Bufs {
                k: (0..N_STREAMS).map(cache).collect(),
                v: (0..N_STREAMS).map(cache).collect(),
                h: per_stream(&|s| d.widths[s]),
                qkv: per_stream(&|s| 3 * d.widths[s]),
                att: per_stream(&|s| d.widths[s]),
                tmp: per_stream(&|s| d.widths[s]),
                mlp: per_stream(&|s| d.hidden[s]),
                cp: vec![0.0; N_STREAMS * d.coord_width],
                ccat: vec![0.0; N_STREAMS * (N_STREAMS - 1) * d.coord_width],
                ch1: vec![0.0; N_STREAMS * d.coord_hidden],
                ch2: vec![0.0; N_STREAMS * d.coord_hidden],
                cm: vec![0.0; N_STREAMS * d.coord_width],
            },
            own: std::array::from_fn(|_| Own {
                x: per_stream(&|s| d.widths[s]),
                have: [false; N_STREAMS],
                scores: vec![0.0; d.slots],
                part: vec![0.0; N_STREAMS * d.coord_width.max(d.coord_hidden)],
            }),
        }
    }

    /// One step at `pos` (validated by the caller: `pos < slots`, rows `0..pos` filled,
    /// tokens inside the vocabularies, `text_emb` of `d_text` finite values); writes the
    /// logits into `logits` and the new k/v rows into the state's cache. No allocation.
    /// On two threads when the model has a helper and it is free (see the module doc);
    /// panics if the helper thread panicked (after it has stopped touching the state).
    pub(crate) fn step(
        &self,
        st: &mut NativeStepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
        logits: &mut [Vec<f32>; N_STREAMS],
    ) {
        self.step_on(st, tokens, pos, text_emb, logits, true)
    }

    /// [`step`](Self::step) on the calling thread alone (the helper is left alone: the
    /// caller's other thread is busy with a decode), bit-identical.
    pub(crate) fn step_solo(
        &self,
        st: &mut NativeStepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
        logits: &mut [Vec<f32>; N_STREAMS],
    ) {
        self.step_on(st, tokens, pos, text_emb, logits, false)
    }

    fn step_on(
        &self,
        st: &mut NativeStepState,
        tokens: [i64; N_STREAMS],
        pos: usize,
        text_emb: &[f32],
        logits: &mut [Vec<f32>; N_STREAMS],
        team: bool,
    ) {
        self.check_state(st);
        let b = &mut st.bufs;
        let [mine, theirs] = &mut st.own;
        let input = Input { tokens, pos, text_emb };
        let mut work = |c: &mut Crew<'_, Own>| self.run(c, mine, b, logits, &input);
        match self.helper.as_ref().filter(|_| team) {
            Some(h) => {
                // (alone if another stream's step has the helper)
                if h.crew(theirs, work).1 {
                    panic!("the native step's helper thread panicked");
                }
            }
            None => work(&mut Crew::solo()),
        }
    }

    /// Panics unless `st` was made by a model of this one's sizes.
    fn check_state(&self, st: &NativeStepState) {
        let (d, b) = (&self.d, &st.bufs);
        assert!(
            b.h.len() == N_STREAMS
                && (0..N_STREAMS)
                    .all(|s| b.h[s].len() == d.widths[s] && b.k[s].len() == d.n_layers * d.slots * d.widths[s]),
            "a NativeStepState of another model"
        );
    }

    /// A step on crew `c` (`me`: the caller's scratch). Every phase hands out units (blocks
    /// of rows of the four streams' products, or attention heads) with their parts of the
    /// phase's outputs; a member computes the LayerNorm feeding a product itself (into its
    /// own buffer) before its first unit of that stream in the phase.
    fn run(&self, c: &mut Crew<'_, Own>, me: &mut Own, b: &mut Bufs, logits: &mut [Vec<f32>; N_STREAMS], x: &Input) {
        let (d, Input { tokens, pos, text_emb }) = (&self.d, *x);
        let u = RowUnits::new(per_stream([&mut b.h]), d.widths, d.widths.map(|_| self.row_block(d.d_text * 4)));
        c.phase(
            me,
            Order::Split,
            u,
            |_| {},
            |_, (s, r, [h])| {
                let (sw, w) = (&self.streams[s], d.widths[s]);
                if pos == 0 {
                    sw.cond.rows(&self.arena, text_emb, r.clone(), h);
                } else {
                    row_part(&sw.tok, tokens[s] as usize, r.clone(), h);
                }
                add_assign(h, &sw.pos[pos * w + r.start..pos * w + r.end]);
            },
        );
        for l in 0..d.n_layers {
            if l > 0 {
                self.coordinate(&self.coord[l - 1], c, me, b);
            }
            self.blocks(l, pos, c, me, b);
        }
        let u = RowUnits::new(per_stream([&mut logits[..]]), d.vocab, self.blocks_of(|s| &self.streams[s].head));
        let h = &b.h;
        c.phase(me, Order::Split, u, reset_have, |me, (s, r, [out])| {
            let sw = &self.streams[s];
            if !std::mem::replace(&mut me.have[s], true) {
                sw.ln_f.run(&h[s], &mut me.x[s]);
            }
            gemv_rows(self.arena.mat(&sw.head), &me.x[s], None, r, out);
        });
    }

    /// Rows per unit of the products `mat(s)` of the four streams.
    fn blocks_of<'a>(&'a self, mat: impl Fn(usize) -> &'a Wm) -> [usize; N_STREAMS] {
        std::array::from_fn(|s| self.block_of(mat(s)))
    }

    /// Rows per unit of a product by `m`.
    fn block_of(&self, m: &Wm) -> usize {
        self.row_block(m.bytes() / m.rows.max(1))
    }

    /// Rows per unit for rows of `row_bytes`: a multiple of 4 (the GEMV kernels' row
    /// blocks, so a row's sum does not depend on how rows are shared out).
    fn row_block(&self, row_bytes: usize) -> usize {
        (self.unit_bytes / row_bytes.max(1)).max(4) / 4 * 4
    }

    /// Layer `l`'s blocks of the four streams, phase by phase (see `run`).
    fn blocks(&self, l: usize, pos: usize, c: &mut Crew<'_, Own>, me: &mut Own, b: &mut Bufs) {
        let d = &self.d;
        let block = |s: usize| &self.streams[s].blocks[l];
        let widths3 = d.widths.map(|w| 3 * w);
        self.normed(c, me, (&mut b.qkv, widths3), &b.h, |s| (&block(s).ln1, &block(s).qkv), false);
        // heads as units: this layer's region of the k and v caches, (H, S, D), and the
        // head's columns of the attention output
        let nh = d.n_heads;
        let mut kv = b.k.iter_mut().zip(b.v.iter_mut()).zip(b.att.iter_mut());
        let bufs = std::array::from_fn(|_| {
            let ((k, v), att) = kv.next().expect("one buffer per stream");
            [layer(k, l, d.n_layers), layer(v, l, d.n_layers), &mut att[..]]
        });
        let u = RowUnits::new(bufs, [nh; N_STREAMS], [1; N_STREAMS]);
        let qkv = &b.qkv;
        c.phase(
            me,
            Order::Split,
            u,
            |_| {},
            |me, (s, heads, [ck, cv, out])| {
                let (w, hd) = (d.widths[s], d.head_dims[s]);
                let (q, kv) = qkv[s].split_at(w);
                let (k, vv) = kv.split_at(w);
                let region = d.slots * hd;
                let parts = ck.chunks_exact_mut(region).zip(cv.chunks_exact_mut(region)).zip(out.chunks_exact_mut(hd));
                for (head, ((ck, cv), out)) in heads.zip(parts) {
                    let hs = head * hd..(head + 1) * hd;
                    let qkv = [&q[hs.clone()], &k[hs.clone()], &vv[hs]];
                    self.attend(s, pos, qkv, [ck, cv, out], &mut me.scores);
                }
            },
        );
        self.residual(c, me, (&mut b.tmp, &mut b.h), &b.att, |s| &block(s).proj);
        self.normed(c, me, (&mut b.mlp, d.hidden), &b.h, |s| (&block(s).ln2, &block(s).fc1), true);
        self.residual(c, me, (&mut b.tmp, &mut b.h), &b.mlp, |s| &block(s).fc2);
    }

    /// One attention head of stream `s` at `pos`: writes the head's new k/v row into its
    /// cache region `ck`/`cv` (S x D), then `out` (D) = softmax(q K^T scale) V over slots
    /// `0..=pos`. `q`, `k`, `v`: the head's columns of the qkv product.
    fn attend(&self, s: usize, pos: usize, [q, k, v]: [&[f32]; 3], [ck, cv, out]: [&mut [f32]; 3], scores: &mut [f32]) {
        let hd = self.d.head_dims[s];
        ck[pos * hd..(pos + 1) * hd].copy_from_slice(k);
        cv[pos * hd..(pos + 1) * hd].copy_from_slice(v);
        let scores = &mut scores[..=pos];
        for (t, sc) in scores.iter_mut().enumerate() {
            *sc = dot(q, &ck[t * hd..(t + 1) * hd]) * self.scale[s];
        }
        softmax(scores);
        out.fill(0.0);
        for (t, &p) in scores.iter().enumerate() {
            for (o, &vv) in out.iter_mut().zip(&cv[t * hd..(t + 1) * hd]) {
                *o += p * vv;
            }
        }
    }

    /// `out_s = lin_s(norm_s(h_s))` (`rows[s]` rows; then GELU) for the four streams, as one
    /// phase: a member norms a stream's `h` once, into its own buffer, before its first unit.
    fn normed<'a>(
        &'a self,
        c: &mut Crew<'_, Own>,
        me: &mut Own,
        (out, rows): (&mut [Vec<f32>], [usize; N_STREAMS]),
        h: &[Vec<f32>],
        norm_lin: impl Fn(usize) -> (&'a Norm, &'a Linear) + Sync,
        gelu: bool,
    ) {
        let u = RowUnits::new(per_stream([out]), rows, self.blocks_of(|s| &norm_lin(s).1.w));
        c.phase(me, Order::Split, u, reset_have, |me, (s, r, [out])| {
            let ((norm, lin), x) = (norm_lin(s), &mut me.x[s]);
            if !std::mem::replace(&mut me.have[s], true) {
                norm.run(&h[s], x);
            }
            lin.rows(&self.arena, x, r, out);
            if gelu {
                gelu_erf(out);
            }
        });
    }

    /// `h += lin_s(x_s)` for the four streams (a block's two residual products), by way of
    /// `tmp`, as one phase.
    fn residual<'a>(
        &'a self,
        c: &mut Crew<'_, Own>,
        me: &mut Own,
        (tmp, h): (&mut [Vec<f32>], &mut [Vec<f32>]),
        x: &[Vec<f32>],
        lin: impl Fn(usize) -> &'a Linear + Sync,
    ) {
        let u = RowUnits::new(per_stream([tmp, h]), self.d.widths, self.blocks_of(|s| &lin(s).w));
        c.phase(
            me,
            Order::Split,
            u,
            |_| {},
            |_, (s, r, [tmp, h])| {
                lin(s).rows(&self.arena, &x[s], r, tmp);
                add_assign(h, tmp);
            },
        );
    }

    /// The coordination before a layer, phase by phase (see `run`).
    fn coordinate(&self, co: &Coord, c: &mut Crew<'_, Own>, me: &mut Own, b: &mut Bufs) {
        let d = &self.d;
        let cw = d.coord_width;
        let mut cp = b.cp.chunks_mut(cw.max(1));
        let u = RowUnits::new(
            std::array::from_fn(|_| [cp.next().unwrap_or_default()]),
            [cw; N_STREAMS],
            self.blocks_of(|s| &co.inp[s].w),
        );
        let h = &b.h;
        c.phase(
            me,
            Order::Split,
            u,
            |_| {},
            |_, (s, r, [out])| {
                co.inp[s].rows(&self.arena, &h[s], r, out);
            },
        );
        concat_others(&b.cp, &mut b.ccat, cw);
        // The shared MLP on the four concatenations at once (rows of one matrix as units,
        // each with its rows of the four outputs).
        let mlp = |c: &mut Crew<'_, Own>, me: &mut Own, lin: &Linear, x: &[f32], out: &mut [f32], gelu: bool| {
            let width = lin.w.rows;
            let mut rows = out.chunks_mut(width.max(1));
            let outs: [&mut [f32]; N_STREAMS] = std::array::from_fn(|_| rows.next().unwrap_or_default());
            let none = || std::array::from_fn(|_| <&mut [f32]>::default());
            let u = RowUnits::new([outs, none(), none(), none()], [width, 0, 0, 0], [self.block_of(&lin.w), 1, 1, 1]);
            c.phase(
                me,
                Order::Split,
                u,
                |_| {},
                |me, (_, r, outs)| {
                    let part = &mut me.part[..N_STREAMS * r.len()];
                    gemm_rows(self.arena.mat(&lin.w), x, N_STREAMS, lin.b.as_deref(), r.clone(), part);
                    for (dst, pj) in outs.into_iter().zip(part.chunks_exact(r.len())) {
                        dst.copy_from_slice(pj);
                        if gelu {
                            gelu_erf(dst);
                        }
                    }
                },
            );
        };
        mlp(c, me, &co.mlp[0], &b.ccat, &mut b.ch1, true);
        mlp(c, me, &co.mlp[1], &b.ch1, &mut b.ch2, true);
        mlp(c, me, &co.mlp[2], &b.ch2, &mut b.cm, false);
        let u = RowUnits::new(per_stream([&mut b.tmp]), d.widths, self.blocks_of(|s| &co.out[s].w));
        let (cm, h) = (&b.cm, &b.h);
        c.phase(
            me,
            Order::Split,
            u,
            |_| {},
            |_, (s, r, [tmp])| {
                co.out[s].rows(&self.arena, &cm[s * cw..(s + 1) * cw], r.clone(), tmp);
                add_assign(tmp, &h[s][r]);
            },
        );
        let u = RowUnits::new(per_stream([&mut b.h]), d.widths, d.widths);
        let tmp = &b.tmp;
        c.phase(me, Order::Split, u, |_| {}, |_, (s, r, [h])| co.norm[s].rows(&tmp[s], r, h));
    }
}

/// Layer `l`'s region of a per-stream cache of `n_layers` layers.
fn layer(c: &mut [f32], l: usize, n_layers: usize) -> &mut [f32] {
    let n = c.len() / n_layers;
    &mut c[l * n..(l + 1) * n]
}

/// Concatenation i of the coordination's input: the other streams' projections (`cp`, four
/// rows of `cw`) in stream order, into `ccat`.
fn concat_others(cp: &[f32], ccat: &mut [f32], cw: usize) {
    let cat_len = (N_STREAMS - 1) * cw;
    for i in 0..N_STREAMS {
        let mut at = i * cat_len;
        for j in (0..N_STREAMS).filter(|&j| j != i) {
            ccat[at..at + cw].copy_from_slice(&cp[j * cw..(j + 1) * cw]);
            at += cw;
        }
    }
}

/// What one step reads besides the state.
#[derive(Clone, Copy)]
struct Input<'a> {
    tokens: [i64; N_STREAMS],
    pos: usize,
    text_emb: &'a [f32],
}

/// A phase's `init`: no LayerNorm output of this phase yet.
fn reset_have(me: &mut Own) {
    me.have = [false; N_STREAMS];
}

/// The four streams' buffers of each of `vs` (one `Vec` per stream each), for [`RowUnits`].
fn per_stream<const K: usize>(vs: [&mut [Vec<f32>]; K]) -> [[&mut [f32]; K]; N_STREAMS] {
    let mut its = vs.map(|v| v.iter_mut());
    std::array::from_fn(|_| std::array::from_fn(|k| its[k].next().expect("one buffer per stream").as_mut_slice()))
}

/// Weight bytes per unit of work a step's team hands out: small enough that the last
/// units of a phase balance the two threads, large enough that one unit is one kernel
/// call's worth of streaming (members take several consecutive units at once anyway).
const UNIT_BYTES: usize = 32 << 10;

/// The units of a phase over the four streams: stream s's rows `0..rows[s]` in blocks of
/// `block[s]`, stream after stream, each with its rows of K output buffers per stream (a
/// buffer of stream s holds `len / rows[s]` elements per row). Items are `(s, rows,
/// [the rows' elements of each buffer])`, cut off the front or the back by `split_at_mut`:
/// disjoint by construction. A block taken from the back is the same block as from the
/// front (the last one may be short), so a unit's rows never depend on who takes it.
struct RowUnits<'a, const K: usize> {
    /// What is left of each buffer: the rows `lo[s]..hi[s]`.
    rest: [[&'a mut [f32]; K]; N_STREAMS],
    per_row: [[usize; K]; N_STREAMS],
    lo: [usize; N_STREAMS],
    hi: [usize; N_STREAMS],
    block: [usize; N_STREAMS],
}

impl<'a, const K: usize> RowUnits<'a, K> {
    fn new(bufs: [[&'a mut [f32]; K]; N_STREAMS], rows: [usize; N_STREAMS], block: [usize; N_STREAMS]) -> Self {
        let per_row = std::array::from_fn(|s| {
            std::array::from_fn(|k| {
                let len = bufs[s][k].len();
                assert!(len.is_multiple_of(rows[s]), "stream {s}: a buffer of {len} for {} rows", rows[s]);
                len.checked_div(rows[s]).unwrap_or(0)
            })
        });
        RowUnits { rest: bufs, per_row, lo: [0; N_STREAMS], hi: rows, block: block.map(|b| b.max(1)) }
    }

    /// Cuts rows `r` of stream `s` off the front (`front`) or the back of what is left.
    fn cut(&mut self, s: usize, r: Range<usize>, front: bool) -> (usize, Range<usize>, [&'a mut [f32]; K]) {
        let n = r.len();
        let parts = std::array::from_fn(|k| {
            let buf = std::mem::take(&mut self.rest[s][k]);
            let at = if front { n * self.per_row[s][k] } else { buf.len() - n * self.per_row[s][k] };
            let (a, b) = buf.split_at_mut(at);
            let (part, rest) = if front { (a, b) } else { (b, a) };
            self.rest[s][k] = rest;
            part
        });
        (s, r, parts)
    }
}

impl<'a, const K: usize> Units for RowUnits<'a, K> {
    type Item = (usize, Range<usize>, [&'a mut [f32]; K]);

    fn left(&self) -> usize {
        (0..N_STREAMS).map(|s| (self.hi[s] - self.lo[s]).div_ceil(self.block[s])).sum()
    }

    /// Up to `n` blocks of one stream: the first stream with rows left from the front, the
    /// last from the back.
    fn take(&mut self, n: usize, back: bool) -> Option<Self::Item> {
        let b = |s: usize| self.block[s];
        if back {
            let s = (0..N_STREAMS).rev().find(|&s| self.lo[s] < self.hi[s])?;
            let first = ((self.hi[s] - 1) / b(s)).saturating_sub(n - 1);
            let r = (first * b(s)).max(self.lo[s])..self.hi[s];
            self.hi[s] = r.start;
            Some(self.cut(s, r, false))
        } else {
            let s = (0..N_STREAMS).find(|&s| self.lo[s] < self.hi[s])?;
            let r = self.lo[s]..self.lo[s].saturating_add(n.saturating_mul(b(s))).min(self.hi[s]);
            self.lo[s] = r.end;
            Some(self.cut(s, r, true))
        }
    }

    /// The last `n` units: streams after the split whole, the split stream's rows from a
    /// unit boundary on.
    fn split_back(&mut self, n: usize) -> Option<Self> {
        let mut keep = self.left().saturating_sub(n);
        let mut back = RowUnits {
            rest: std::array::from_fn(|_| std::array::from_fn(|_| <&mut [f32]>::default())),
            per_row: self.per_row,
            lo: self.hi,
            hi: self.hi,
            block: self.block,
        };
        for s in 0..N_STREAMS {
            let units = (self.hi[s] - self.lo[s]).div_ceil(self.block[s]);
            if keep >= units {
                keep -= units;
                continue;
            }
            let mid = self.lo[s] + keep * self.block[s];
            keep = 0;
            for k in 0..K {
                let buf = std::mem::take(&mut self.rest[s][k]);
                let (a, b) = buf.split_at_mut((mid - self.lo[s]) * self.per_row[s][k]);
                (self.rest[s][k], back.rest[s][k]) = (a, b);
            }
            (back.lo[s], self.hi[s]) = (mid, mid);
        }
        Some(back)
    }
}

/// Bytes an [`Arena`] needs at most for a model of sizes `d` (every matrix as f32, plus
/// int8 scales and alignment).
fn arena_bytes(d: &Dims) -> usize {
    let mut shapes = Vec::new();
    for s in 0..N_STREAMS {
        let (w, hid) = (d.widths[s], d.hidden[s]);
        shapes.extend([(w, d.d_text), (d.vocab[s], w)]);
        for _ in 0..d.n_layers {
            shapes.extend([(3 * w, w), (w, w), (hid, w), (w, hid)]);
        }
    }
    let (cw, ch) = (d.coord_width, d.coord_hidden);
    for _ in 1..d.n_layers {
        shapes.extend([(ch, (N_STREAMS - 1) * cw), (ch, ch), (cw, ch)]);
        for s in 0..N_STREAMS {
            shapes.extend([(cw, d.widths[s]), (d.widths[s], cw)]);
        }
    }
    shapes.iter().map(|&(r, c)| Arena::size(r * c * 4) + Arena::size(r * 4)).sum()
}

/// Elements `cols` of row `r` of `m`, as f32 (`Matrix::row_into` on a part of the row).
fn row_part(m: &Matrix, r: usize, cols: Range<usize>, out: &mut [f32]) {
    match m {
        Matrix::F32 { cols: c, w, .. } => out.copy_from_slice(&w[r * c + cols.start..r * c + cols.end]),
        Matrix::I8 { cols: c, q, scale, .. } => {
            for (o, &v) in out.iter_mut().zip(&q[r * c + cols.start..r * c + cols.end]) {
                *o = f32::from(v) * scale[r];
            }
        }
    }
}

impl NativeStepState {
    /// Zeroes the cache (a new generation; no allocation).
    pub(crate) fn reset(&mut self) {
        for c in self.bufs.k.iter_mut().chain(self.bufs.v.iter_mut()) {
            c.fill(0.0);
        }
    }

    /// The cache of stream `s` as (k, v), each (L, H, S, D) row-major.
    #[allow(dead_code)]
    pub(crate) fn cache(&self, s: usize) -> (&[f32], &[f32]) {
        (&self.bufs.k[s], &self.bufs.v[s])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random source (xorshift64*), values in [-1, 1).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            ((self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 40) as f32 / (1u64 << 23) as f32) - 1.0
        }

        fn vec(&mut self, n: usize, amp: f32) -> Vec<f32> {
            (0..n).map(|_| self.next() * amp).collect()
        }

        fn matrix(&mut self, rows: usize, cols: usize, int8: bool) -> Matrix {
            let amp = 1.0 / (cols as f32).sqrt();
            if int8 {
                let q = (0..rows * cols).map(|_| (self.next() * 127.0) as i8).collect();
                Matrix::I8 {
                    rows,
                    cols,
                    q,
                    scale: (0..rows).map(|_| amp / 127.0 * (1.0 + 0.5 * self.next())).collect(),
                }
            } else {
                Matrix::F32 { rows, cols, w: self.vec(rows * cols, amp) }
            }
        }

        fn linear(&mut self, a: &mut Arena, rows: usize, cols: usize, int8: bool) -> Linear {
            Linear { w: a.put(self.matrix(rows, cols, int8)), b: Some(self.vec(rows, 0.1)) }
        }

        fn norm(&mut self, n: usize) -> Norm {
            Norm { w: (0..n).map(|_| 1.0 + 0.2 * self.next()).collect(), b: self.vec(n, 0.1) }
        }
    }

    /// A model of the given sizes with random weights (int8 matrices or f32).
    pub(super) fn random_model(d: Dims, int8: bool, seed: u64) -> NativeStep {
        let mut g = Rng(seed | 1);
        let mut a = Arena::new(arena_bytes(&d)).expect("arena");
        let a = &mut a;
        let streams = (0..N_STREAMS)
            .map(|s| {
                let (w, hid) = (d.widths[s], d.hidden[s]);
                Stream {
                    cond: g.linear(a, w, d.d_text, int8),
                    tok: g.matrix(d.vocab[s], w, int8),
                    pos: g.vec(d.slots * w, 0.5),
                    blocks: (0..d.n_layers)
                        .map(|_| Block {
                            ln1: g.norm(w),
                            qkv: g.linear(a, 3 * w, w, int8),
                            proj: g.linear(a, w, w, int8),
                            ln2: g.norm(w),
                            fc1: g.linear(a, hid, w, int8),
                            fc2: g.linear(a, w, hid, int8),
                        })
                        .collect(),
                    ln_f: g.norm(w),
                    head: a.put(g.matrix(d.vocab[s], w, int8)),
                }
            })
            .collect();
        let (cw, ch) = (d.coord_width, d.coord_hidden);
        let coord = (1..d.n_layers)
            .map(|_| Coord {
                inp: (0..N_STREAMS).map(|s| g.linear(a, cw, d.widths[s], int8)).collect(),
                mlp: [
                    g.linear(a, ch, (N_STREAMS - 1) * cw, int8),
                    g.linear(a, ch, ch, int8),
                    g.linear(a, cw, ch, int8),
                ],
                out: (0..N_STREAMS).map(|s| g.linear(a, d.widths[s], cw, int8)).collect(),
                norm: (0..N_STREAMS).map(|s| g.norm(d.widths[s])).collect(),
            })
            .collect();
        let arena = std::mem::replace(a, Arena::new(64).expect("arena"));
        NativeStep::assemble(arena, d, streams, coord)
    }

    /// Odd sizes: no width, hidden width or vocabulary a multiple of 4 or 8 everywhere, so
    /// the row splits fall inside and beside the kernels' row blocks and column tails.
    pub(super) fn odd_dims() -> Dims {
        let widths = [20, 36, 28, 12];
        Dims {
            n_layers: 3,
            n_heads: 4,
            slots: 9,
            d_text: 11,
            widths,
            head_dims: widths.map(|w| w / 4),
            vocab: [13, 30, 7, 9],
            hidden: [60, 110, 84, 35],
            coord_width: 10,
            coord_hidden: 22,
        }
    }

    /// Logits and caches of a generation of `steps` steps on one state.
    fn generate(m: &NativeStep, steps: usize) -> Vec<Vec<f32>> {
        let mut st = m.new_state();
        let mut logits: [Vec<f32>; N_STREAMS] = std::array::from_fn(|s| vec![0.0; m.d.vocab[s]]);
        let emb: Vec<f32> = (0..m.d.d_text).map(|i| (i as f32 * 0.7).sin()).collect();
        let mut out = Vec::new();
        for k in 0..steps {
            let tokens = std::array::from_fn(|s| ((k * 5 + s * 3) % m.d.vocab[s]) as i64);
            m.step(&mut st, tokens, k, &emb, &mut logits);
            out.extend(logits.iter().cloned());
        }
        out.extend(st.bufs.k.iter().chain(&st.bufs.v).cloned());
        out
    }

    fn bits(v: &[Vec<f32>]) -> Vec<Vec<u32>> {
        v.iter().map(|x| x.iter().map(|f| f.to_bits()).collect()).collect()
    }

    #[test]
    fn two_threads_give_bit_identical_logits_and_caches() {
        for int8 in [false, true] {
            let mut m = random_model(odd_dims(), int8, 7);
            m.unit_bytes = 1; // units of 4 rows: many per product
            let steps = m.d.slots;
            let one = generate(&m, steps);
            assert!(one.iter().flatten().all(|v| v.is_finite()));
            m.set_threads(2);
            assert_eq!(m.threads(), 2);
            assert_eq!(bits(&generate(&m, steps)), bits(&one), "int8 {int8}: 2 threads differ from 1");
            // Two streams at once: one gets the helper, the other finds it busy and runs
            // alone; both give the same results.
            std::thread::scope(|sc| {
                let hs: Vec<_> =
                    (0..2).map(|_| sc.spawn(|| (0..20).map(|_| generate(&m, steps)).collect::<Vec<_>>())).collect();
                for h in hs {
                    for g in h.join().unwrap() {
                        assert_eq!(bits(&g), bits(&one), "int8 {int8}: concurrent streams differ");
                    }
                }
            });
        }
    }

    #[test]
    fn row_units_cut_the_same_units_from_either_end() {
        // Buffers holding their own element indices, so a part shows where it was cut.
        let rows = [10, 0, 7, 4];
        let block = [4, 3, 2, 8];
        let per_row = [[1, 3], [1, 2], [2, 1], [5, 1]];
        let mut data: Vec<Vec<Vec<f32>>> = (0..N_STREAMS)
            .map(|s| (0..2).map(|k| (0..rows[s] * per_row[s][k]).map(|i| i as f32).collect()).collect())
            .collect();
        let expected: Vec<(usize, Range<usize>)> = (0..N_STREAMS)
            .flat_map(|s| (0..rows[s]).step_by(block[s]).map(move |r0| (s, r0..(r0 + block[s]).min(rows[s]))))
            .collect();
        for pattern in 0u32..64 {
            let mut it = data.iter_mut();
            let bufs = std::array::from_fn(|_| {
                let mut b = it.next().unwrap().iter_mut();
                std::array::from_fn(|_| b.next().unwrap().as_mut_slice())
            });
            let mut front = RowUnits::<2>::new(bufs, rows, block);
            assert_eq!(front.left(), expected.len());
            // split off the back at every unit boundary in turn
            let cut = pattern as usize % (expected.len() + 1);
            let mut back = front.split_back(cut).unwrap();
            assert_eq!((front.left(), back.left()), (expected.len() - cut, cut));
            let mut got = Vec::new();
            for i in 0.. {
                // one unit at a time, or a few (split below into units), from either end of either half
                let n = 1 + i % 3;
                let from_back = pattern >> (i % 6) & 1 == 1;
                let item = if i % 2 == 0 { front.take(n, from_back) } else { back.take(n, from_back) };
                let Some((s, r, parts)) = item.or_else(|| front.take(n, from_back)).or_else(|| back.take(n, from_back))
                else {
                    break;
                };
                for (k, p) in parts.iter().enumerate() {
                    let want: Vec<f32> = (r.start * per_row[s][k]..r.end * per_row[s][k]).map(|i| i as f32).collect();
                    assert_eq!(p.to_vec(), want, "stream {s} rows {r:?} buffer {k}");
                }
                assert!(r.len() <= n * block[s]);
                for r0 in r.clone().step_by(block[s]) {
                    // every take starts and ends at a unit boundary (or the end of the rows)
                    assert_eq!(r0 % block[s], 0, "stream {s} rows {r:?}");
                    got.push((s, r0..(r0 + block[s]).min(r.end)));
                }
            }
            assert_eq!(front.left() + back.left(), 0);
            got.sort_by_key(|(s, r)| (*s, r.start));
            assert_eq!(got, expected, "pattern {pattern:b}");
        }
    }

    /// Where two threads start to pay: int8 models shaped like models/default (4 layers,
    /// 4 heads) with the widths scaled, median step over a generation on 1 and 2 threads
    /// (`cargo test --release --lib step_crossover -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn step_crossover() {
        for f in [0.125, 0.25, 0.375, 0.5, 0.75, 1.0] {
            let widths = [128, 256, 192, 192].map(|w: usize| ((w as f64 * f) as usize).max(4) / 4 * 4);
            let d = Dims {
                n_layers: 4,
                n_heads: 4,
                slots: 76,
                d_text: 384,
                widths,
                head_dims: widths.map(|w| w / 4),
                vocab: [514, 1026, 514, 514],
                hidden: widths.map(|w| 4 * w),
                coord_width: ((128.0 * f) as usize).max(4),
                coord_hidden: ((256.0 * f) as usize).max(4),
            };
            let mut m = random_model(d, true, 3);
            let mut med = [0.0f64; 2];
            for _round in 0..3 {
                for threads in [1, 2] {
                    m.set_threads(threads);
                    let mut st = m.new_state();
                    let mut logits: [Vec<f32>; N_STREAMS] = std::array::from_fn(|s| vec![0.0; m.d.vocab[s]]);
                    let emb = vec![0.1; d.d_text];
                    let mut times = Vec::new();
                    for k in 0..d.slots {
                        let t = std::time::Instant::now();
                        m.step(&mut st, [(k % 500) as i64; N_STREAMS], k, &emb, &mut logits);
                        times.push(t.elapsed().as_secs_f64() * 1e3);
                    }
                    times.sort_by(f64::total_cmp);
                    med[threads - 1] += times[times.len() / 2] / 3.0;
                }
            }
            println!(
                "widths {widths:?}: {:.2} MB, 1 thread {:.3} ms, 2 threads {:.3} ms ({:.2}x)",
                m.weight_bytes() as f64 / 1e6,
                med[0],
                med[1],
                med[0] / med[1]
            );
        }
    }

    /// One step of the paper-size model (random f32 weights, ~1.8 GB) on 1 and 2 threads,
    /// averaged over a generation (run with `cargo test --release --lib step_throughput --
    /// --ignored --nocapture`; `COMGRASP_STEP_BENCH_INT8=1` for int8 weights,
    /// `COMGRASP_STEP_BENCH_THREADS="1 2"` for the thread counts, in order).
    #[test]
    #[ignore]
    fn step_throughput() {
        let widths = [512, 1024, 768, 768];
        let d = Dims {
            n_layers: 14,
            n_heads: 16,
            slots: 76,
            d_text: 384,
            widths,
            head_dims: widths.map(|w| w / 16),
            vocab: [514, 1026, 514, 514],
            hidden: widths.map(|w| 4 * w),
            coord_width: 256,
            coord_hidden: 512,
        };
        let int8 = std::env::var("COMGRASP_STEP_BENCH_INT8").is_ok_and(|v| v == "1");
        let mut m = random_model(d, int8, 1);
        println!("weights {:.1} MB per step", m.weight_bytes() as f64 / 1e6);
        let steps = 74;
        let counts = std::env::var("COMGRASP_STEP_BENCH_THREADS").unwrap_or_else(|_| "1 2 1 2".into());
        for threads in counts.split_whitespace().map(|t| t.parse::<usize>().expect("thread counts")) {
            m.set_threads(threads);
            let mut st = m.new_state();
            let mut logits: [Vec<f32>; N_STREAMS] = std::array::from_fn(|s| vec![0.0; m.d.vocab[s]]);
            let emb = vec![0.1; d.d_text];
            m.step(&mut st, [0; N_STREAMS], 0, &emb, &mut logits);
            let mut times = Vec::new();
            for k in 0..steps {
                let t = std::time::Instant::now();
                m.step(&mut st, [(k % 500) as i64; N_STREAMS], k, &emb, &mut logits);
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            times.sort_by(f64::total_cmp);
            println!(
                "{threads} thread(s): median {:.2} ms/step, min {:.2}, mean {:.2}",
                times[steps / 2],
                times[0],
                times.iter().sum::<f64>() / steps as f64
            );
        }
    }
}
