//! The native step for a batch of generations at once (the crowd scheduler's step): every
//! generation keeps its own [`NativeStepState`] (KV cache, position, tokens), and each block
//! of a product's weight rows (the units of the one-generation step, ~32 KB) is applied to
//! every member before the next block is read, so the weights stream from memory once per
//! batch instead of once per member: the step turns from a memory-bound GEMV per member
//! into a cache-resident one per block.
//!
//! Every value is computed by the same kernel, on the same inputs and row blocks, as the
//! one-generation step computes it (the row blocks start at multiples of 4, where a row's
//! sum does not depend on its neighbours), so a member's logits and cache are bit-identical
//! to the ones it gets alone, whatever the batch around it (tests below and
//! tests/crowd.rs). One thread: the scheduler runs one batch per thread.
use std::ops::Range;

use super::super::arena::Wm;
use super::super::kernels::{gemm_rows, gemv_rows_many};
use super::{
    add_assign, concat_others, gelu_erf, layer, row_part, Bufs, Coord, Linear, NativeStep, NativeStepState, Norm,
    N_STREAMS,
};

/// One member of a batch: its state, the logits it gets, and its step's input (validated by
/// the caller as for [`NativeStep::step`]).
pub(crate) struct Member<'a> {
    pub(crate) st: &'a mut NativeStepState,
    pub(crate) logits: &'a mut [Vec<f32>; N_STREAMS],
    pub(crate) tokens: [i64; N_STREAMS],
    pub(crate) pos: usize,
    pub(crate) text_emb: &'a [f32],
}

/// The members of a batch, by index (an accessor instead of a slice, so a caller whose
/// generations live in its own structures needs no per-batch vector).
pub(crate) trait Members {
    fn count(&self) -> usize;
    fn member(&mut self, i: usize) -> Member<'_>;
}

/// A coordination MLP layer's four inputs and four outputs (rows one after the other).
type Flat = for<'a> fn(&'a mut Bufs) -> (&'a [f32], &'a mut [f32]);

/// What a product reads of a member for component stream `s` (`k` inputs one after the
/// other: 1, or the coordination's 4 concatenations).
type Input = for<'a> fn(&'a NativeStepState, usize) -> &'a [f32];

/// The batch's own buffers, made once per scheduler thread ([`NativeStep::batch_scratch`]):
/// the members' inputs of a product side by side, and one unit's outputs.
pub(crate) struct BatchScratch {
    x: Vec<f32>,
    y: Vec<f32>,
    /// Most members a batch may have.
    cap: usize,
}

impl NativeStep {
    /// Scratch for batches of up to `cap` members.
    pub(crate) fn batch_scratch(&self, cap: usize) -> BatchScratch {
        let d = &self.d;
        let cols = [d.d_text, (N_STREAMS - 1) * d.coord_width, d.coord_hidden, d.coord_width]
            .into_iter()
            .chain(d.widths)
            .chain(d.hidden)
            .max()
            .unwrap_or(0);
        // a unit is at most a block of rows of one matrix (coordination: of four outputs)
        let rows = (0..N_STREAMS).map(|s| d.vocab[s].max(3 * d.widths[s]).max(d.hidden[s])).max().unwrap_or(0);
        let rows = rows.max(d.coord_hidden).max(d.coord_width);
        BatchScratch { x: vec![0.0; cap * N_STREAMS * cols], y: vec![0.0; cap * N_STREAMS * rows], cap }
    }

    /// One step for every member of `m` (see the module doc), at most `sc`'s capacity. No
    /// allocation.
    pub(crate) fn step_batch(&self, m: &mut dyn Members, sc: &mut BatchScratch) {
        let (d, n) = (&self.d, m.count());
        assert!(n <= sc.cap, "a batch of {n} members, scratch for {}", sc.cap);
        for i in 0..n {
            let Member { st, tokens, pos, text_emb, .. } = m.member(i);
            self.check_state(st);
            for (s, (sw, h)) in self.streams.iter().zip(&mut st.bufs.h).enumerate() {
                let w = d.widths[s];
                if pos == 0 {
                    sw.cond.rows(&self.arena, text_emb, 0..w, h);
                } else {
                    row_part(&sw.tok, tokens[s] as usize, 0..w, h);
                }
                add_assign(h, &sw.pos[pos * w..(pos + 1) * w]);
            }
        }
        for l in 0..d.n_layers {
            if l > 0 {
                self.coordinate_batch(&self.coord[l - 1], m, sc);
            }
            self.blocks_batch(l, m, sc);
        }
        self.norm_each(m, |s| &self.streams[s].ln_f, |st, s| &st.bufs.h[s]);
        for s in 0..N_STREAMS {
            let head = &self.streams[s].head;
            self.product(
                m,
                sc,
                s,
                (head, None, 1),
                |st, s| &st.own[0].x[s],
                |o, s, r, y| o.logits[s][r].copy_from_slice(y),
            );
        }
    }

    /// `y_j = W x_j (+ bias)` for every member j, `x_j` = `input(member, s)` (`k` inputs of
    /// W's columns each), in the units of the one-generation step: the inputs are gathered
    /// side by side once, each unit's rows computed for all of them
    /// ([`gemv_rows_many`](super::gemv_rows_many): each weight row read once per group of
    /// inputs), then handed to `out(member, s, rows, its k outputs of those rows)`.
    fn product(
        &self,
        m: &mut dyn Members,
        sc: &mut BatchScratch,
        s: usize,
        (wm, bias, k): (&Wm, Option<&[f32]>, usize),
        input: Input,
        mut out: impl FnMut(&mut Outs<'_>, usize, Range<usize>, &[f32]),
    ) {
        let w = self.arena.mat(wm);
        let (n, cols) = (m.count(), w.cols());
        let x = &mut sc.x[..n * k * cols];
        for (i, xi) in x.chunks_exact_mut(k * cols).enumerate() {
            xi.copy_from_slice(input(m.member(i).st, s));
        }
        each_unit(w.rows(), self.block_of(wm), |r| {
            let y = &mut sc.y[..n * k * r.len()];
            gemv_rows_many(w, &sc.x[..n * k * cols], n * k, bias, r.clone(), y);
            for (i, yi) in y.chunks_exact(k * r.len()).enumerate() {
                let Member { st, logits, .. } = m.member(i);
                out(&mut Outs { st, logits }, s, r.clone(), yi);
            }
        });
    }

    /// `own.x[s] = norm(s)(input(member, s))` for every member and stream.
    fn norm_each<'w>(&self, m: &mut dyn Members, norm: impl Fn(usize) -> &'w Norm, input: Input) {
        for i in 0..m.count() {
            let st = m.member(i).st;
            for s in 0..N_STREAMS {
                let mut x = std::mem::take(&mut st.own[0].x[s]);
                norm(s).run(input(st, s), &mut x);
                st.own[0].x[s] = x;
            }
        }
    }

    /// `out_s = lin_s(norm_s(h_s))` (then GELU) for every member: the one-generation
    /// step's `normed`.
    fn normed_batch<'w>(
        &'w self,
        m: &mut dyn Members,
        sc: &mut BatchScratch,
        norm_lin: impl Fn(usize) -> (&'w Norm, &'w Linear),
        out: for<'a> fn(&'a mut Bufs, usize) -> &'a mut [f32],
        gelu: bool,
    ) {
        self.norm_each(m, |s| norm_lin(s).0, |st, s| &st.bufs.h[s]);
        for s in 0..N_STREAMS {
            let lin = norm_lin(s).1;
            self.product(
                m,
                sc,
                s,
                (&lin.w, lin.b.as_deref(), 1),
                |st, s| &st.own[0].x[s],
                |o, s, r, y| {
                    let dst = &mut out(&mut o.st.bufs, s)[r];
                    dst.copy_from_slice(y);
                    if gelu {
                        gelu_erf(dst);
                    }
                },
            );
        }
    }

    /// Layer `l`'s blocks of every member.
    fn blocks_batch<'w>(&'w self, l: usize, m: &mut dyn Members, sc: &mut BatchScratch) {
        let (d, n) = (&self.d, m.count());
        let block = |s: usize| &self.streams[s].blocks[l];
        let lin = |x: &'w Linear| (&x.w, x.b.as_deref(), 1);
        self.normed_batch(m, sc, |s| (&block(s).ln1, &block(s).qkv), |b, s| &mut b.qkv[s], false);
        for i in 0..n {
            let Member { st, pos, .. } = m.member(i);
            let (b, own) = (&mut st.bufs, &mut st.own[0]);
            for s in 0..N_STREAMS {
                let (w, hd, region) = (d.widths[s], d.head_dims[s], d.slots * d.head_dims[s]);
                let (q, kv) = b.qkv[s].split_at(w);
                let (k, v) = kv.split_at(w);
                let (ck, cv) = (layer(&mut b.k[s], l, d.n_layers), layer(&mut b.v[s], l, d.n_layers));
                let parts =
                    ck.chunks_exact_mut(region).zip(cv.chunks_exact_mut(region)).zip(b.att[s].chunks_exact_mut(hd));
                for (head, ((ck, cv), out)) in parts.enumerate() {
                    let hs = head * hd..(head + 1) * hd;
                    let qkv = [&q[hs.clone()], &k[hs.clone()], &v[hs]];
                    self.attend(s, pos, qkv, [ck, cv, out], &mut own.scores);
                }
            }
        }
        for s in 0..N_STREAMS {
            self.product(m, sc, s, lin(&block(s).proj), |st, s| &st.bufs.att[s], residual);
        }
        self.normed_batch(m, sc, |s| (&block(s).ln2, &block(s).fc1), |b, s| &mut b.mlp[s], true);
        for s in 0..N_STREAMS {
            self.product(m, sc, s, lin(&block(s).fc2), |st, s| &st.bufs.mlp[s], residual);
        }
    }

    /// The coordination before a layer, for every member.
    fn coordinate_batch<'w>(&'w self, co: &'w Coord, m: &mut dyn Members, sc: &mut BatchScratch) {
        let (n, cw) = (m.count(), self.d.coord_width);
        let lin = |x: &'w Linear, k: usize| (&x.w, x.b.as_deref(), k);
        for s in 0..N_STREAMS {
            self.product(
                m,
                sc,
                s,
                lin(&co.inp[s], 1),
                |st, s| &st.bufs.h[s],
                |o, s, r, y| o.st.bufs.cp[s * cw + r.start..s * cw + r.end].copy_from_slice(y),
            );
        }
        for i in 0..n {
            let b = &mut m.member(i).st.bufs;
            concat_others(&b.cp, &mut b.ccat, cw);
        }
        // The shared MLP on each member's four concatenations: `gemm_rows` as the
        // one-generation step runs it (its kernel, not the GEMV's, sums these rows).
        let layers: [(&Linear, Flat, bool); 3] = [
            (&co.mlp[0], |b| (&b.ccat, &mut b.ch1), true),
            (&co.mlp[1], |b| (&b.ch1, &mut b.ch2), true),
            (&co.mlp[2], |b| (&b.ch2, &mut b.cm), false),
        ];
        for (l, io, gelu) in layers {
            let width = l.w.rows;
            each_unit(width, self.block_of(&l.w), |r| {
                for i in 0..n {
                    let st = m.member(i).st;
                    let part = &mut st.own[0].part[..N_STREAMS * r.len()];
                    let (x, out) = io(&mut st.bufs);
                    gemm_rows(self.arena.mat(&l.w), x, N_STREAMS, l.b.as_deref(), r.clone(), part);
                    for (j, pj) in part.chunks_exact(r.len()).enumerate() {
                        let dst = &mut out[j * width + r.start..j * width + r.end];
                        dst.copy_from_slice(pj);
                        if gelu {
                            gelu_erf(dst);
                        }
                    }
                }
            });
        }
        for s in 0..N_STREAMS {
            self.product(
                m,
                sc,
                s,
                lin(&co.out[s], 1),
                |st, s| st.bufs.cm.chunks_exact(st.bufs.cm.len() / N_STREAMS).nth(s).unwrap_or_default(),
                |o, s, r, y| {
                    let b = &mut o.st.bufs;
                    let t = &mut b.tmp[s][r.clone()];
                    t.copy_from_slice(y);
                    add_assign(t, &b.h[s][r]);
                },
            );
        }
        for i in 0..n {
            let b = &mut m.member(i).st.bufs;
            for s in 0..N_STREAMS {
                co.norm[s].run(&b.tmp[s], &mut b.h[s]);
            }
        }
    }
}

/// Where a product's outputs go: a member's state and logits.
struct Outs<'a> {
    st: &'a mut NativeStepState,
    logits: &'a mut [Vec<f32>; N_STREAMS],
}

/// A block's residual product: `tmp = y; h += tmp` (the one-generation step's order).
fn residual(o: &mut Outs<'_>, s: usize, r: Range<usize>, y: &[f32]) {
    let b = &mut o.st.bufs;
    let t = &mut b.tmp[s][r.clone()];
    t.copy_from_slice(y);
    add_assign(&mut b.h[s][r], t);
}

/// Calls `f(rows)` for the blocks of `block` rows of `rows`: the units of the
/// one-generation step, so every row block starts where it starts there (a multiple of 4).
fn each_unit(rows: usize, block: usize, mut f: impl FnMut(Range<usize>)) {
    let b = block.max(1);
    let mut r0 = 0;
    while r0 < rows {
        let r1 = (r0 + b).min(rows);
        f(r0..r1);
        r0 = r1;
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{odd_dims, random_model};
    use super::*;

    fn tokens(k: usize, i: usize, vocab: &[usize; N_STREAMS]) -> [i64; N_STREAMS] {
        std::array::from_fn(|s| ((k * 5 + s * 3 + i * 7) % vocab[s]) as i64)
    }

    /// Some generations (`ids`: which ones), each at its own position with its own tokens
    /// and text.
    struct Batch<'a> {
        states: &'a mut [NativeStepState],
        logits: &'a mut [[Vec<f32>; N_STREAMS]],
        ids: &'a [usize],
        pos: &'a [usize],
        emb: &'a [Vec<f32>],
        vocab: [usize; N_STREAMS],
    }

    impl Members for Batch<'_> {
        fn count(&self) -> usize {
            self.ids.len()
        }
        fn member(&mut self, j: usize) -> Member<'_> {
            let i = self.ids[j];
            Member {
                st: &mut self.states[i],
                logits: &mut self.logits[i],
                tokens: tokens(self.pos[j], i, &self.vocab),
                pos: self.pos[j],
                text_emb: &self.emb[i],
            }
        }
    }

    /// Members at staggered positions (member i starts i steps late), stepped in batches,
    /// get the bits each gets stepped alone, on both f32 and int8 weights.
    #[test]
    fn a_batch_gives_each_member_its_own_bits() {
        for int8 in [false, true] {
            let m = random_model(odd_dims(), int8, 11);
            let d = m.d;
            let n = 5;
            let emb: Vec<Vec<f32>> =
                (0..n).map(|i| (0..d.d_text).map(|j| ((i * 13 + j) as f32 * 0.37).sin()).collect()).collect();
            let fresh = || -> [Vec<f32>; N_STREAMS] { std::array::from_fn(|s| vec![0.0; d.vocab[s]]) };
            let bits = |v: &[Vec<f32>]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
            let steps = |i: usize| d.slots - i;
            let mut alone = Vec::new();
            for (i, e) in emb.iter().enumerate() {
                let (mut st, mut lg) = (m.new_state(), fresh());
                let mut seen = Vec::new();
                for k in 0..steps(i) {
                    m.step_solo(&mut st, tokens(k, i, &d.vocab), k, e, &mut lg);
                    seen.push(bits(&lg));
                }
                alone.push((seen, bits(&st.bufs.k), bits(&st.bufs.v)));
            }
            let mut states: Vec<_> = (0..n).map(|_| m.new_state()).collect();
            let mut logits: Vec<_> = (0..n).map(|_| fresh()).collect();
            let mut seen = vec![Vec::new(); n];
            let mut sc = m.batch_scratch(n);
            for t in 0..d.slots + n {
                let ids: Vec<usize> = (0..n).filter(|&i| t >= i && t - i < steps(i)).collect();
                let pos: Vec<usize> = ids.iter().map(|&i| t - i).collect();
                let (states, logits, emb, vocab) = (&mut states[..], &mut logits[..], &emb[..], d.vocab);
                m.step_batch(&mut Batch { states, logits, ids: &ids, pos: &pos, emb, vocab }, &mut sc);
                for &i in &ids {
                    seen[i].push(bits(&logits[i]));
                }
            }
            for i in 0..n {
                assert_eq!(seen[i], alone[i].0, "int8 {int8}: member {i}: logits differ");
                assert_eq!(bits(&states[i].bufs.k), alone[i].1, "int8 {int8}: member {i}: k cache");
                assert_eq!(bits(&states[i].bufs.v), alone[i].2, "int8 {int8}: member {i}: v cache");
            }
        }
    }
}
