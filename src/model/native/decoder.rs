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
//! once: its weights are read once per call (`model::decode_group`).
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
use super::decoder_attention::{AttnState, WindowAttention};
use super::decoder_conv::{relu, CausalConv, ResBlock, UpConv};
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
    /// The state after the manifest's initial (pad) tokens: what a new sequence starts from.
    initial: NativeState,
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

/// One stream's decoder context: every layer's history, plus scratch.
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
    emb: Vec<f32>,
    attn: Option<AttnState>,
    /// Input buffers of the ResBlock convs (level-major) and the Z buffers of the UpConvs.
    res: Vec<Vec<f32>>,
    z: Vec<Vec<f32>>,
    fa: Vec<f32>,
    fb: Vec<f32>,
    // scratch, F x width (x, y, a, b) and F x dim (out)
    x: Vec<f32>,
    y: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
    out: Vec<f32>,
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

    /// A zero context with scratch for [`MAX_GROUP`] tokens per decode.
    fn new_state(&self, frames: usize) -> CompState {
        let (w, g) = (self.width, MAX_GROUP);
        let mut res = Vec::new();
        let mut z = Vec::new();
        for (l, lev) in self.levels.iter().enumerate() {
            for r in &lev.res {
                res.push(vec![0.0; r.conv.buf_len(g << l)]);
            }
            z.push(vec![0.0; lev.up.z_len(g << l)]);
        }
        CompState {
            emb: vec![0.0; self.conv_in.buf_len(g)],
            attn: self.attn.as_ref().map(|a| a.new_state(g)),
            res,
            z,
            fa: vec![0.0; self.final_a.buf_len(g * frames)],
            fb: vec![0.0; self.final_b.buf_len(g * frames)],
            x: vec![0.0; g * frames * w],
            y: vec![0.0; g * frames * w],
            a: vec![0.0; g * frames * w],
            b: vec![0.0; g * frames * w],
            out: vec![0.0; g * frames * self.dim],
        }
    }

    /// Copies the context of `o` into `s` (every buffer's history and the attention's keys
    /// and values, not the scratch after them), without allocating.
    fn copy_context(&self, s: &mut CompState, o: &CompState) {
        fn prefix(d: &mut [f32], o: &[f32], n: usize) {
            d[..n].copy_from_slice(&o[..n]);
        }
        prefix(&mut s.emb, &o.emb, self.conv_in.buf_len(0));
        if let (Some(a), Some(b)) = (s.attn.as_mut(), o.attn.as_ref()) {
            a.copy_from(b);
        }
        let res = self.levels.iter().flat_map(|l| &l.res);
        for ((d, src), r) in s.res.iter_mut().zip(&o.res).zip(res) {
            prefix(d, src, r.conv.buf_len(0));
        }
        for ((d, src), l) in s.z.iter_mut().zip(&o.z).zip(&self.levels) {
            prefix(d, src, l.up.z_len(0));
        }
        prefix(&mut s.fa, &o.fa, self.final_a.buf_len(0));
        prefix(&mut s.fb, &o.fb, self.final_b.buf_len(0));
    }

    /// Decodes `ids` (1 to [`MAX_GROUP`] tokens, in order; each a code or the pad id =
    /// codebook size) into `s.out` (`ids.len()` x F x dim, raw). Every layer takes the new
    /// positions of all the tokens at once, so a weight is read once per call, not once
    /// per token; the results are the bits one token per call gives (the layers are
    /// causal and `gemm` does not depend on the number of positions).
    fn run(&self, ar: &Arena, s: &mut CompState, ids: &[usize]) {
        let (d, w, g) = (self.code_dim, self.width, ids.len());
        for (dst, &id) in self.conv_in.input(&mut s.emb, g).chunks_exact_mut(d).zip(ids) {
            dst.copy_from_slice(&self.table[id * d..(id + 1) * d]);
        }
        self.conv_in.run(ar, &mut s.emb, g, &mut s.x[..g * w]);
        relu(&mut s.x[..g * w]);
        if let (Some(a), Some(st)) = (&self.attn, s.attn.as_mut()) {
            a.run(ar, &mut s.x[..g * w], g, st);
        }
        let mut n = g;
        for (l, lev) in self.levels.iter().enumerate() {
            for (r, buf) in lev.res.iter().zip(&mut s.res[l * self.depth..(l + 1) * self.depth]) {
                r.run(ar, &mut s.x, n, buf, &mut s.a, &mut s.b);
            }
            lev.up.run(ar, &s.x[..n * w], n, &mut s.z[l], &mut s.y[..2 * n * w]);
            std::mem::swap(&mut s.x, &mut s.y);
            n *= 2;
        }
        self.final_a.input(&mut s.fa, n).copy_from_slice(&s.x[..n * w]);
        self.final_a.run(ar, &mut s.fa, n, &mut s.y[..n * w]);
        for (d, v) in self.final_b.input(&mut s.fb, n).iter_mut().zip(&s.y[..n * w]) {
            *d = v.max(0.0);
        }
        self.final_b.run(ar, &mut s.fb, n, &mut s.out[..n * self.dim]);
    }

    /// Writes `s.out` into the component's channels of `out` (F x 335), contact as probability.
    fn emit(&self, s: &CompState, frames: usize, out: &mut [f32]) {
        for f in 0..frames {
            let dst = &mut out[f * FRAME_DIM + self.offset..f * FRAME_DIM + self.offset + self.dim];
            dst.copy_from_slice(&s.out[f * self.dim..(f + 1) * self.dim]);
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
        let mut dec =
            NativeDecoder { comps, frames, initial: NativeState { comps: Vec::new() }, helper, arena, cost_ns };
        // The context of a new sequence: zero histories, then the initial state's tokens.
        let mut st = NativeState { comps: dec.comps.iter().map(|c| c.new_state(frames)).collect() };
        let init = d.initial_state.first().ok_or_else(|| Error::bundle(&dir, "decoder initial_state is empty"))?;
        for (ci, c) in dec.comps.iter().enumerate() {
            let ids = init.get(ci).ok_or_else(|| Error::bundle(&dir, "decoder initial_state lacks a component"))?;
            for &id in ids {
                let id =
                    usize::try_from(id).ok().filter(|&i| i <= m.components[ci].codebook_size).ok_or_else(|| {
                        Error::bundle(&dir, format!("decoder initial_state id {id} is neither a code nor the pad id"))
                    })?;
                // timed: the first decodes' job order
                let t = Instant::now();
                c.run(&dec.arena, &mut st.comps[ci], &[id]);
                dec.note_cost(ci, t.elapsed().as_nanos() as u64);
            }
        }
        dec.initial = st;
        Ok(dec)
    }

    /// A new sequence's state (allocates; `reset` does not).
    pub(crate) fn new_state(&self) -> NativeState {
        let mut st = NativeState { comps: self.comps.iter().map(|c| c.new_state(self.frames)).collect() };
        self.reset(&mut st);
        st
    }

    /// Back to the start of a sequence, without allocating.
    pub(crate) fn reset(&self, st: &mut NativeState) {
        for ((c, a), b) in self.comps.iter().zip(&mut st.comps).zip(&self.initial.comps) {
            c.copy_context(a, b);
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
                            let mut col = [0; MAX_GROUP];
                            for (d, t) in col.iter_mut().zip(ids) {
                                *d = t[c];
                            }
                            self.comps[c].run(&self.arena, cs, &col[..ids.len()]);
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
        for (c, s) in self.comps.iter().zip(&st.comps) {
            c.emit(s, ids.len() * self.frames, out);
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
