//! The native streaming VQ decoder: what `decoder.onnx` computes (the newest token's F
//! frames given the previous K-1 tokens of every component, models/streaming.py
//! `DecoderStep`), computed *incrementally*.
//!
//! The graph recomputes a window of K tokens per chunk (and its frame-rate stage on the
//! last `crop_tokens`). The decoder is causal, so the same frames come from running the
//! network once over the whole sequence, left-padded with K-1 pad embeddings, exactly as
//! `ComponentVQVAE.decode_latent` does offline (DESIGN §3 deviation 1: the two agree to
//! 1e-4). Run that way, a new token only adds new positions at each layer: 1 at the token
//! rate, 2, 4, ..., F at the frame rates, and every layer needs just a short history of its
//! input (k - 1 positions of a causal conv, the last `window` keys/values of the
//! attention). That history is the stream's state; a new sequence starts from zero
//! histories (`F.pad`'s zeros at the very start) and feeds the manifest's initial state
//! (K-1 pad ids) first, which is done once at load and copied on `reset`. G consecutive
//! tokens decoded in one call add G times those positions, and each layer takes them at
//! once: its weights are read once per call (`model::decode_group`). A batched decode
//! ([`NativeDecoder::decode_batch`], the crowd scheduler's) stacks the new positions of up
//! to [`MAX_BATCH`] streams the same way, each stream with its own histories: one GEMM per
//! layer for all of them, every stream's frames the bits of its own decode.
//!
//! The architecture is read from the tensor names and shapes (`parts.<component>.decoder.
//! layers.<i>.*`, the layer list of `models.vqvae.Decoder`: Conv, ReLU, [AttentionBlock],
//! then per level `depth` ResBlocks, Upsample2, Conv, and a final Conv, ReLU, Conv) plus
//! the manifest (frames per token = 2^levels, slices, codebook sizes, K): every tensor is
//! checked, an unknown decoder tensor or a receptive field that differs from K is an
//! `Error::Bundle` at load.
use std::collections::BTreeSet;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

use super::arena::{Arena, Wm};
use super::decoder_attention::{AttnState, AttnWork, WindowAttention};
pub(crate) use super::decoder_conv::MAX_BATCH;
use super::decoder_conv::{relu, CausalConv, Layer, PerStream, ResBlock, Segs, UpConv};
use super::team::{Crew, Each, Helper, Order};
use super::weights::Tensors;
use crate::bundle::manifest::{Manifest, NativeSpec, CONTACT_CHANNELS, FRAME_DIM, N_STREAMS};
use crate::bundle::BundleSource;
use crate::config::two_threads;
use crate::error::{Error, Result};

/// Below this many weights (all components) one thread is faster than two (the hand-over
/// costs tens of microseconds).
const SPLIT_MIN_WEIGHTS: usize = 1 << 20;
/// Most tokens one decode takes ([`NativeDecoder::decode_with`]); states have scratch for
/// this many.
pub(crate) const MAX_GROUP: usize = 8;

/// The loaded decoders of the four components (shared by every stream).
#[derive(Debug)]
pub(crate) struct NativeDecoder {
    comps: Vec<Component>,
    frames: usize,
    /// The context after the manifest's initial (pad) tokens: what a new sequence starts from.
    initial: Vec<CompCtx>,
    /// The second thread (two-thread decodes).
    helper: Option<Helper>,
    /// Every component's weight matrices (the layers hold their places in it).
    arena: Arena,
    /// Recent time of each job (the components, then the extra job of
    /// [`decode_with`](NativeDecoder::decode_with)), ns: the order jobs are handed out in.
    cost_ns: [AtomicU64; N_STREAMS + 1],
}

/// The extra job's index in [`NativeDecoder::cost_ns`].
const EXTRA: usize = N_STREAMS;

/// One job of a decode: a component's network on its own state, or the caller's extra work.
enum DecodeJob<'a> {
    Component(usize, &'a mut CompState),
    Extra(&'a mut (dyn FnMut() + Send)),
}

impl DecodeJob<'_> {
    /// Its index in [`NativeDecoder::cost_ns`].
    fn index(&self) -> usize {
        match self {
            DecodeJob::Component(c, _) => *c,
            DecodeJob::Extra(_) => EXTRA,
        }
    }
}

/// One stream's decoder context: every layer's history, plus scratch for decodes alone.
#[derive(Clone, Debug)]
pub(crate) struct NativeState {
    comps: Vec<CompState>,
}

#[derive(Debug)]
struct Component {
    /// First channel of the component in the 335-D frame, and its width there.
    offset: usize,
    dim: usize,
    /// Contact channels of this component (local indices): sigmoid on output.
    contact: Vec<usize>,
    code_dim: usize,
    width: usize,
    /// (codebook_size + 1) x code_dim: the codes, then the pad embedding (id = codebook_size).
    table: Vec<f32>,
    conv_in: CausalConv,
    attn: Option<WindowAttention>,
    depth: usize,
    levels: Vec<Level>,
    final_a: CausalConv,
    final_b: CausalConv,
}

/// One upsampling level: `depth` ResBlocks at `2^l` positions, then Upsample2 + Conv.
#[derive(Debug)]
struct Level {
    res: Vec<ResBlock>,
    up: UpConv,
}

#[derive(Clone, Debug)]
struct CompState {
    ctx: CompCtx,
    /// Scratch of this stream's own decodes (a batched decode brings its own).
    work: Work,
}

/// A component's context in one stream: every layer's history.
#[derive(Clone, Debug)]
struct CompCtx {
    emb: Vec<f32>,
    attn: Option<AttnState>,
    /// The ResBlock convs' (level-major), the UpConvs' `Z`s, the final convs'.
    res: Vec<Vec<f32>>,
    z: Vec<Vec<f32>>,
    fa: Vec<f32>,
    fb: Vec<f32>,
}

/// Which history of a [`CompCtx`] a layer reads.
#[derive(Clone, Copy)]
enum Slot {
    Emb,
    Res(usize),
    Z(usize),
    Fa,
    Fb,
}

impl CompCtx {
    fn slot(&mut self, s: Slot) -> &mut [f32] {
        match s {
            Slot::Emb => &mut self.emb,
            Slot::Res(i) => &mut self.res[i],
            Slot::Z(l) => &mut self.z[l],
            Slot::Fa => &mut self.fa,
            Slot::Fb => &mut self.fb,
        }
    }

    /// Copies `o` (the same component's) into `self` without allocating.
    fn copy_from(&mut self, o: &CompCtx) {
        self.emb.copy_from_slice(&o.emb);
        if let (Some(a), Some(b)) = (self.attn.as_mut(), o.attn.as_ref()) {
            a.copy_from(b);
        }
        for (d, s) in self.res.iter_mut().zip(&o.res).chain(self.z.iter_mut().zip(&o.z)) {
            d.copy_from_slice(s);
        }
        self.fa.copy_from_slice(&o.fa);
        self.fb.copy_from_slice(&o.fb);
    }
}

/// One stream alone.
struct One<'a>(&'a mut CompCtx);

impl PerStream<CompCtx> for One<'_> {
    fn get(&mut self, _: usize) -> &mut CompCtx {
        self.0
    }
}

/// One layer's histories: `slot` of every stream's context.
struct Hist<'a> {
    ctxs: &'a mut dyn PerStream<CompCtx>,
    slot: Slot,
}

impl PerStream<[f32]> for Hist<'_> {
    fn get(&mut self, i: usize) -> &mut [f32] {
        self.ctxs.get(i).slot(self.slot)
    }
}

/// Layer `slot` of a decode at level `l`.
fn layer<'a>(ctxs: &'a mut dyn PerStream<CompCtx>, slot: Slot, segs: &'a Segs, l: usize) -> Layer<'a, Hist<'a>> {
    Layer { hist: Hist { ctxs, slot }, segs, l }
}

/// The attention block's contexts.
struct Attns<'a>(&'a mut dyn PerStream<CompCtx>);

impl PerStream<AttnState> for Attns<'_> {
    fn get(&mut self, i: usize) -> &mut AttnState {
        // (a context is made by its component: it has the attention's iff the component has one)
        self.0.get(i).attn.as_mut().expect("a component with attention has its context")
    }
}

/// Scratch of a decode: the new positions of all its streams, stacked (`Segs`).
#[derive(Clone, Debug)]
pub(crate) struct Work {
    e: Vec<f32>,
    x: Vec<f32>,
    y: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
    win: Vec<f32>,
    z: Vec<f32>,
    out: Vec<f32>,
    attn: Option<AttnWork>,
}

impl Work {
    /// For decodes of up to `tokens` tokens (all streams) by any of `comps`.
    fn new<'c>(comps: impl Iterator<Item = &'c Component> + Clone, frames: usize, tokens: usize) -> Work {
        let max = |f: fn(&Component) -> usize| comps.clone().map(f).max().unwrap_or(0);
        let pos = tokens * frames;
        let w = max(|c| c.width);
        let win = max(|c| c.conv_in.k * c.code_dim.max(c.width));
        let attn = comps
            .clone()
            .filter_map(|c| c.attn.as_ref())
            .map(|a| (a.width(), a.window()))
            .reduce(|a, b| (a.0.max(b.0), a.1.max(b.1)));
        Work {
            e: vec![0.0; tokens * max(|c| c.code_dim)],
            x: vec![0.0; pos * w],
            y: vec![0.0; pos * w],
            a: vec![0.0; pos * w],
            b: vec![0.0; pos * w],
            win: vec![0.0; pos * win],
            z: vec![0.0; pos / 2 * max(|c| c.levels.first().map_or(0, |l| l.up.k * l.up.c))],
            out: vec![0.0; pos * max(|c| c.dim)],
            attn: attn.map(|(w, win)| AttnWork::new(w, win, tokens)),
        }
    }
}

/// Names `parts.<c>.decoder.layers.<i>` tensors are read under, collected while loading.
struct Names<'a> {
    known: BTreeSet<String>,
    t: &'a Tensors<'a>,
}

impl Names<'_> {
    fn has(&self, name: &str) -> bool {
        self.t.shape(name).is_ok()
    }
    fn note(&mut self, prefix: &str, suffixes: &[&str]) {
        for s in suffixes {
            self.known.insert(format!("{prefix}.{s}"));
        }
    }
}

impl Component {
    fn load(t: &Tensors, ar: &mut Arena, names: &mut Names, dir: &Path, m: &Manifest, ci: usize) -> Result<Component> {
        let spec = &m.components[ci];
        let bad = |msg: String| Error::bundle(dir, msg);
        let part = format!("parts.{}", spec.name);
        let layer = |i: usize| format!("{part}.decoder.layers.{i}");
        let levels_n = m.decoder.frames_per_token.trailing_zeros() as usize;

        let first = format!("{}.conv.weight", layer(0));
        let (width, code_dim, k) = match t.shape(&first)? {
            [w, d, k] if *w > 0 && *d > 0 && *k > 0 => (*w, *d, *k),
            s => {
                return Err(bad(format!(
                    "native decoder tensor {first} has shape {s:?}, expected (width, code_dim, kernel)"
                )))
            }
        };
        let [start, stop] = spec.slice;
        let dim = stop - start;

        // Embedding table: the codebook, then the pad embedding.
        let j = spec.codebook_size;
        let book = t.matrix(&format!("{part}.quantizer.codebook"), j, code_dim)?;
        let pad = t.vector(&format!("{part}.pad_embedding"), code_dim)?;
        let mut table = vec![0.0; (j + 1) * code_dim];
        for r in 0..j {
            book.row_into(r, &mut table[r * code_dim..(r + 1) * code_dim]);
        }
        table[j * code_dim..].copy_from_slice(&pad);

        let conv_in = CausalConv::load(t, ar, &format!("{}.conv", layer(0)), code_dim, width, k)?;
        names.note(&format!("{}.conv", layer(0)), &["weight", "bias"]);
        // layer 1: ReLU
        let mut i = 2;
        let attn = if names.has(&format!("{}.qkv.weight", layer(2))) {
            let a = WindowAttention::load(t, ar, dir, &layer(2), width)?;
            names.note(&layer(2), &WindowAttention::TENSORS);
            i = 3;
            Some(a)
        } else {
            None
        };
        let mut depth = 0;
        while names.has(&format!("{}.conv.conv.weight", layer(i + depth))) {
            depth += 1;
        }
        let mut levels = Vec::with_capacity(levels_n);
        for _ in 0..levels_n {
            let mut res = Vec::with_capacity(depth);
            for _ in 0..depth {
                res.push(ResBlock::load(t, ar, &layer(i), width, k)?);
                names.note(&layer(i), &["conv.conv.weight", "conv.conv.bias", "proj.weight", "proj.bias"]);
                i += 1;
            }
            // layer i: Upsample2, then the Conv
            let up = UpConv::load(t, ar, &format!("{}.conv", layer(i + 1)), width, k)?;
            names.note(&format!("{}.conv", layer(i + 1)), &["weight", "bias"]);
            i += 2;
            levels.push(Level { res, up });
        }
        let final_a = CausalConv::load(t, ar, &format!("{}.conv", layer(i)), width, width, k)?;
        names.note(&format!("{}.conv", layer(i)), &["weight", "bias"]);
        // layer i + 1: ReLU
        let final_b = CausalConv::load(t, ar, &format!("{}.conv", layer(i + 2)), width, dim, k)?;
        names.note(&format!("{}.conv", layer(i + 2)), &["weight", "bias"]);

        let contact = CONTACT_CHANNELS.iter().filter(|&&c| (start..stop).contains(&c)).map(|&c| c - start).collect();
        Ok(Component {
            offset: start,
            dim,
            contact,
            code_dim,
            width,
            table,
            conv_in,
            attn,
            depth,
            levels,
            final_a,
            final_b,
        })
    }

    /// Tokens the newest token's frames depend on (models.vqvae.Decoder._receptive_field).
    fn context_tokens(&self, frames: usize) -> usize {
        // (lookback, upsample) of every layer, in order
        let k1 = self.conv_in.k - 1;
        let mut layers = vec![(k1, 1), (0, 1)];
        if let Some(a) = &self.attn {
            layers.push((a.window() - 1, 1));
        }
        for _ in &self.levels {
            layers.extend(std::iter::repeat_n((k1, 1), self.depth));
            layers.extend([(0, 2), (k1, 1)]);
        }
        layers.extend([(k1, 1), (0, 1), (k1, 1)]);
        let n: i64 = 1 << 20;
        let mut pos = n * frames as i64;
        for &(look, up) in layers.iter().rev() {
            pos = pos.div_euclid(up) - look as i64;
        }
        (n - pos + 1) as usize
    }

    /// A zero context (the start of a sequence, before the initial tokens).
    fn new_ctx(&self) -> CompCtx {
        let res = self.levels.iter().flat_map(|l| &l.res).map(|r| vec![0.0; r.conv.hist_len()]).collect();
        CompCtx {
            emb: vec![0.0; self.conv_in.hist_len()],
            attn: self.attn.as_ref().map(|a| a.new_state()),
            res,
            z: self.levels.iter().map(|l| vec![0.0; l.up.hist_len()]).collect(),
            fa: vec![0.0; self.final_a.hist_len()],
            fb: vec![0.0; self.final_b.hist_len()],
        }
    }

    /// Decodes the tokens of every stream of `segs` (`id(i, t)`: stream `i`'s token `t`, a
    /// code or the pad id = codebook size) into `wk.out` (stacked, raw). Every layer takes
    /// the new positions of all the tokens of all the streams at once, so a weight is read
    /// once per call, not once per token or stream; a stream's results are the bits one
    /// token per call alone gives (the layers are causal, each stream has its own context
    /// and `gemm` does not depend on the positions computed with one).
    fn run(
        &self,
        ar: &Arena,
        ctxs: &mut dyn PerStream<CompCtx>,
        segs: &Segs,
        id: &dyn Fn(usize, usize) -> usize,
        wk: &mut Work,
    ) {
        let (d, w) = (self.code_dim, self.width);
        let n = segs.total(0);
        for i in 0..segs.count() {
            let (o, g) = segs.at(i, 0);
            for t in 0..g {
                let id = id(i, t);
                wk.e[(o + t) * d..(o + t + 1) * d].copy_from_slice(&self.table[id * d..(id + 1) * d]);
            }
        }
        self.conv_in.run(ar, layer(ctxs, Slot::Emb, segs, 0), &wk.e[..n * d], false, &mut wk.win, &mut wk.x[..n * w]);
        relu(&mut wk.x[..n * w]);
        if let (Some(a), Some(aw)) = (&self.attn, wk.attn.as_mut()) {
            a.run(ar, &mut wk.x[..n * w], segs, &mut Attns(&mut *ctxs), aw);
        }
        for (l, lev) in self.levels.iter().enumerate() {
            for (j, r) in lev.res.iter().enumerate() {
                let at = layer(ctxs, Slot::Res(l * self.depth + j), segs, l);
                r.run(ar, at, &mut wk.x, &mut wk.win, &mut wk.a, &mut wk.b);
            }
            let n = segs.total(l);
            lev.up.run(ar, layer(ctxs, Slot::Z(l), segs, l), &wk.x[..n * w], &mut wk.z, &mut wk.y[..2 * n * w]);
            std::mem::swap(&mut wk.x, &mut wk.y);
        }
        let (top, dim) = (self.levels.len(), self.dim);
        let n = segs.total(top);
        let fa = layer(ctxs, Slot::Fa, segs, top);
        self.final_a.run(ar, fa, &wk.x[..n * w], false, &mut wk.win, &mut wk.y[..n * w]);
        let fb = layer(ctxs, Slot::Fb, segs, top);
        self.final_b.run(ar, fb, &wk.y[..n * w], true, &mut wk.win, &mut wk.out[..n * dim]);
    }

    /// Writes `rows` (`frames` x dim, raw) into the component's channels of `out` (F x
    /// 335), contact as probability.
    fn emit(&self, rows: &[f32], frames: usize, out: &mut [f32]) {
        for f in 0..frames {
            let dst = &mut out[f * FRAME_DIM + self.offset..f * FRAME_DIM + self.offset + self.dim];
            dst.copy_from_slice(&rows[f * self.dim..(f + 1) * self.dim]);
            for &c in &self.contact {
                dst[c] = 1.0 / (1.0 + (-dst[c]).exp());
            }
        }
    }

    fn matrices(&self) -> Vec<Wm> {
        let mut v: Vec<Wm> = self.conv_in.matrices().to_vec();
        if let Some(a) = &self.attn {
            v.extend(a.matrices());
        }
        for l in &self.levels {
            for r in &l.res {
                v.extend(r.matrices());
            }
            v.extend(l.up.matrices());
        }
        v.extend(self.final_a.matrices());
        v.extend(self.final_b.matrices());
        v
    }
}

impl NativeDecoder {
    /// Loads `decoder.native`; the manifest was verified (components, K, initial state).
    /// `threads`: `RuntimeOptions::decoder_threads` (`None`: two when it pays).
    pub(crate) fn load(
        src: &BundleSource,
        m: &Manifest,
        spec: &NativeSpec,
        threads: Option<usize>,
    ) -> Result<NativeDecoder> {
        let dir = src.path_of(&spec.dir);
        let d = &m.decoder;
        let frames = d.frames_per_token;
        if frames < 2 || !frames.is_power_of_two() {
            return Err(Error::bundle(
                &dir,
                format!(
                    "the native decoder needs frames_per_token = 2^levels (levels >= 1), the manifest says {frames}"
                ),
            ));
        }
        if m.components.len() != N_STREAMS {
            return Err(Error::bundle(&dir, format!("{} components, expected {N_STREAMS}", m.components.len())));
        }
        let t = Tensors::new(src, spec);
        let mut names = Names { known: BTreeSet::new(), t: &t };
        let mut arena = Arena::new(Arena::bound(spec.tensors.values().map(|v| v.shape.as_slice())))
            .ok_or_else(|| Error::bundle(&dir, "no memory for the native decoder's weights"))?;
        let mut comps = Vec::with_capacity(N_STREAMS);
        for ci in 0..N_STREAMS {
            let c = Component::load(&t, &mut arena, &mut names, &dir, m, ci)?;
            let k = c.context_tokens(frames);
            if k != d.context_tokens {
                return Err(Error::bundle(
                    &dir,
                    format!(
                    "the native decoder of {} reads {k} tokens (from its layers), the manifest's context_tokens is {}",
                    m.components[ci].name, d.context_tokens),
                ));
            }
            comps.push(c);
        }
        // Every decoder tensor must be one the architecture reads (a layer we would ignore
        // means a different network), and every tensor must belong to a known component.
        for name in t.names() {
            let comp_ok = m.components.iter().any(|c| name.starts_with(&format!("parts.{}.", c.name)));
            if !comp_ok || (name.contains(".decoder.") && !names.known.contains(name)) {
                return Err(Error::bundle(
                    &dir,
                    format!(
                    "native decoder tensor {name} is not part of the decoder architecture the other tensors describe"),
                ));
            }
        }
        let helper = start_helper(&comps, threads);
        arena.trim();
        let cost_ns = std::array::from_fn(|_| AtomicU64::new(0));
        let mut dec = NativeDecoder { comps, frames, initial: Vec::new(), helper, arena, cost_ns };
        // The context of a new sequence: zero histories, then the initial state's tokens.
        let init = d.initial_state.first().ok_or_else(|| Error::bundle(&dir, "decoder initial_state is empty"))?;
        let mut initial = Vec::with_capacity(N_STREAMS);
        for (ci, c) in dec.comps.iter().enumerate() {
            let mut ctx = c.new_ctx();
            let mut work = Work::new(std::iter::once(c), frames, 1);
            let ids = init.get(ci).ok_or_else(|| Error::bundle(&dir, "decoder initial_state lacks a component"))?;
            for &id in ids {
                let id =
                    usize::try_from(id).ok().filter(|&i| i <= m.components[ci].codebook_size).ok_or_else(|| {
                        Error::bundle(&dir, format!("decoder initial_state id {id} is neither a code nor the pad id"))
                    })?;
                // timed: the first decodes' job order
                let t = Instant::now();
                c.run(&dec.arena, &mut One(&mut ctx), &Segs::new(&[1]), &|_, _| id, &mut work);
                dec.note_cost(ci, t.elapsed().as_nanos() as u64);
            }
            initial.push(ctx);
        }
        dec.initial = initial;
        Ok(dec)
    }

    /// A new sequence's state (allocates; `reset` does not).
    pub(crate) fn new_state(&self) -> NativeState {
        let comps = self
            .comps
            .iter()
            .zip(&self.initial)
            .map(|(c, ctx)| CompState { ctx: ctx.clone(), work: Work::new(std::iter::once(c), self.frames, MAX_GROUP) })
            .collect();
        NativeState { comps }
    }

    /// Back to the start of a sequence, without allocating.
    pub(crate) fn reset(&self, st: &mut NativeState) {
        for (a, b) in st.comps.iter_mut().zip(&self.initial) {
            a.ctx.copy_from(b);
        }
    }

    /// Scratch for [`decode_batch`](Self::decode_batch) (allocated once per scheduler thread).
    pub(crate) fn batch_work(&self) -> Work {
        Work::new(self.comps.iter(), self.frames, MAX_BATCH * MAX_GROUP)
    }

    /// Decodes the tokens of up to [`MAX_BATCH`] streams at once on the calling thread:
    /// each layer is one GEMM over the new positions of all of them (its weights read once
    /// per call, not once per stream), with each stream's own context. Every stream gets
    /// the bits of its own [`decode_with`](Self::decode_with). Allocation-free.
    pub(crate) fn decode_batch(&self, b: &mut dyn Batch, wk: &mut Work) {
        let n = b.count();
        let mut g = [0; MAX_BATCH];
        for (i, g) in g.iter_mut().enumerate().take(n) {
            *g = b.ids(i).len();
            assert!((1..=MAX_GROUP).contains(g), "decode of {g} tokens");
            assert_eq!(b.state(i).comps.len(), self.comps.len(), "a NativeState of another decoder");
        }
        let segs = Segs::new(&g[..n]);
        let top = self.frames.trailing_zeros() as usize;
        for (ci, c) in self.comps.iter().enumerate() {
            let mut ids = [[0; MAX_GROUP]; MAX_BATCH];
            for (i, row) in ids.iter_mut().enumerate().take(n) {
                for (d, t) in row.iter_mut().zip(b.ids(i)) {
                    *d = t[ci];
                }
            }
            c.run(&self.arena, &mut Comps { b: &mut *b, c: ci }, &segs, &|i, t| ids[i][t], wk);
            for i in 0..n {
                let (o, rows) = segs.at(i, top);
                c.emit(&wk.out[o * c.dim..(o + rows) * c.dim], rows, b.out(i));
            }
        }
    }

    /// Decodes `ids` (1 to [`MAX_GROUP`] tokens in order, one code per component each,
    /// checked by the caller: `0 <= id < codebook size`) into `out` (`ids.len()` x F x 335
    /// normalized features, contact as probability: the same bits as one call per token),
    /// and runs `extra`
    /// (independent work, once, on either thread) as one more job for the two threads: how
    /// a stream overlaps the next token step with a decode (`model::overlap`).
    /// `team`: the helper may take jobs. Allocation-free. Fails only if the helper thread panicked (`Error::Panic`; the state
    /// is then not to be trusted).
    pub(crate) fn decode_with(
        &self,
        st: &mut NativeState,
        ids: &[[usize; N_STREAMS]],
        out: &mut [f32],
        extra: Option<&mut (dyn FnMut() + Send)>,
        team: bool,
    ) -> Result<()> {
        assert_eq!(st.comps.len(), self.comps.len(), "a NativeState of another decoder");
        assert!((1..=MAX_GROUP).contains(&ids.len()), "decode of {} tokens", ids.len());
        // The jobs, longest recent time first (each thread takes the next one: the two
        // split the work by how fast they actually go).
        let mut jobs: [Option<DecodeJob<'_>>; N_STREAMS + 1] = std::array::from_fn(|_| None);
        for (slot, (c, cs)) in jobs.iter_mut().zip(st.comps.iter_mut().enumerate()) {
            *slot = Some(DecodeJob::Component(c, cs));
        }
        if let Some(f) = extra {
            // (a coercion site: the closure's lifetime shortens to the states' borrow)
            jobs[EXTRA] = Some(DecodeJob::Extra(f));
        }
        let cost = |j: &Option<DecodeJob<'_>>| j.as_ref().map(|j| self.cost_ns[j.index()].load(Relaxed));
        // descending, the empty extra slot last (an in-place sort: no allocation)
        jobs.sort_unstable_by_key(|j| std::cmp::Reverse(cost(j)));
        let run = |crew: &mut Crew<'_, ()>| {
            crew.phase(
                &mut (),
                Order::Queue,
                Each(jobs.into_iter().flatten()),
                |_| {},
                |_, job: DecodeJob<'_>| {
                    let (i, t) = (job.index(), Instant::now());
                    match job {
                        DecodeJob::Extra(f) => f(),
                        DecodeJob::Component(c, cs) => {
                            let segs = Segs::new(&[ids.len()]);
                            let id = |_: usize, t: usize| ids[t][c];
                            self.comps[c].run(&self.arena, &mut One(&mut cs.ctx), &segs, &id, &mut cs.work);
                        }
                    }
                    self.note_cost(i, t.elapsed().as_nanos() as u64);
                },
            )
        };
        // (alone if another stream's decode has the helper)
        let ((), helper_panicked) = match self.helper.as_ref().filter(|_| team) {
            Some(h) => h.crew(&mut (), run),
            None => (run(&mut Crew::solo()), false),
        };
        if helper_panicked {
            return Err(Error::Panic("the native decoder's helper thread panicked".into()));
        }
        let frames = ids.len() * self.frames;
        for (c, s) in self.comps.iter().zip(&st.comps) {
            c.emit(&s.work.out[..frames * c.dim], frames, out);
        }
        Ok(())
    }

    /// Whether decodes run on two threads (when the helper is free).
    pub(crate) fn has_helper(&self) -> bool {
        self.helper.is_some()
    }

    /// Bytes of weights one decode reads.
    pub(crate) fn weight_bytes(&self) -> usize {
        self.comps.iter().flat_map(|c| c.matrices()).map(|m| m.bytes()).sum()
    }

    /// Folds a job's time into its recent time (a quarter of the new one: follows a change
    /// of load within a few tokens).
    fn note_cost(&self, job: usize, ns: u64) {
        let old = self.cost_ns[job].load(Relaxed);
        let new = if old == 0 { ns.max(1) } else { (3 * old + ns) / 4 };
        self.cost_ns[job].store(new, Relaxed);
    }
}

/// The streams of a [`NativeDecoder::decode_batch`].
pub(crate) trait Batch {
    fn count(&self) -> usize;
    /// Stream `i`'s tokens (1 to [`MAX_GROUP`], in order; one code per component each,
    /// checked by the caller).
    fn ids(&self, i: usize) -> &[[usize; N_STREAMS]];
    fn state(&mut self, i: usize) -> &mut NativeState;
    /// Where stream `i`'s frames go (`ids(i).len()` x F x 335).
    fn out(&mut self, i: usize) -> &mut [f32];
}

/// Component `c`'s contexts in the streams of a batch.
struct Comps<'a> {
    b: &'a mut dyn Batch,
    c: usize,
}

impl PerStream<CompCtx> for Comps<'_> {
    fn get(&mut self, i: usize) -> &mut CompCtx {
        &mut self.b.state(i).comps[self.c].ctx
    }
}

/// The helper thread, if decodes should use two threads (`threads`, else: two or more
/// cores and a model big enough for the hand-over to pay).
fn start_helper(comps: &[Component], threads: Option<usize>) -> Option<Helper> {
    let total: usize = comps.iter().flat_map(|c| c.matrices()).map(|m| m.rows * m.cols).sum();
    if !two_threads(threads, total >= SPLIT_MIN_WEIGHTS) {
        return None;
    }
    // no thread to be had: decode on the caller's alone
    Helper::start_named("comgrasp-decoder").ok()
}
