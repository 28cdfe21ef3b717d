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

use super::{
    add_assign, concat_others, gelu_erf, gemm_rows, gemv_rows, layer, row_part, Bufs, Coord, Linear, NativeStep,
    NativeStepState, Norm, N_STREAMS,
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

/// The input and output buffers of a phase in a member's buffers.
type Pair = for<'a> fn(&'a mut Bufs) -> (&'a [Vec<f32>], &'a mut [Vec<f32>]);
/// A residual phase's input, scratch and residual stream.
type Triple = for<'a> fn(&'a mut Bufs) -> (&'a [Vec<f32>], &'a mut [Vec<f32>], &'a mut [Vec<f32>]);
/// A coordination MLP layer's four inputs and four outputs (rows one after the other).
type Flat = for<'a> fn(&'a mut Bufs) -> (&'a [f32], &'a mut [f32]);

impl NativeStep {
    /// One step for every member of `m` (see the module doc). No allocation.
    pub(crate) fn step_batch(&self, m: &mut dyn Members) {
        let (d, n) = (&self.d, m.count());
        for i in 0..n {
            let Member { st, tokens, pos, text_emb, .. } = m.member(i);
            self.check_state(st);
            for s in 0..N_STREAMS {
                let (sw, w, h) = (&self.streams[s], d.widths[s], &mut st.bufs.h[s]);
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
                self.coordinate_batch(&self.coord[l - 1], m);
            }
            self.blocks_batch(l, m);
        }
        for i in 0..n {
            let st = m.member(i).st;
            for s in 0..N_STREAMS {
                self.streams[s].ln_f.run(&st.bufs.h[s], &mut st.own[0].x[s]);
            }
        }
        let heads = self.blocks_of(|s| &self.streams[s].head);
        each_unit(d.vocab, heads, |s, r| {
            let w = self.arena.mat(&self.streams[s].head);
            for i in 0..n {
                let Member { st, logits, .. } = m.member(i);
                gemv_rows(w, &st.own[0].x[s], None, r.clone(), &mut logits[s][r.clone()]);
            }
        });
    }

    /// Layer `l`'s blocks of every member.
    fn blocks_batch(&self, l: usize, m: &mut dyn Members) {
        let (d, n) = (&self.d, m.count());
        let block = |s: usize| &self.streams[s].blocks[l];
        self.normed_batch(m, |s| (&block(s).ln1, &block(s).qkv), |b| (&b.h, &mut b.qkv), false);
        for i in 0..n {
            let Member { st, pos, .. } = m.member(i);
            let (b, own) = (&mut st.bufs, &mut st.own[0]);
            for s in 0..N_STREAMS {
                let (w, hd, region) = (d.widths[s], d.head_dims[s], d.slots * d.head_dims[s]);
                let (q, kv) = b.qkv[s].split_at(w);
                let (k, v) = kv.split_at(w);
                let (ck, cv) = (layer(&mut b.k[s], l, d.n_layers), layer(&mut b.v[s], l, d.n_layers));
                let parts = ck.chunks_exact_mut(region).zip(cv.chunks_exact_mut(region)).zip(b.att[s].chunks_exact_mut(hd));
                for (head, ((ck, cv), out)) in parts.enumerate() {
                    let hs = head * hd..(head + 1) * hd;
                    let qkv = [&q[hs.clone()], &k[hs.clone()], &v[hs]];
                    self.attend(s, pos, qkv, [ck, cv, out], &mut own.scores);
                }
            }
        }
        self.residual_batch(m, |s| &block(s).proj, |b| (&b.att, &mut b.tmp, &mut b.h));
        self.normed_batch(m, |s| (&block(s).ln2, &block(s).fc1), |b| (&b.h, &mut b.mlp), true);
        self.residual_batch(m, |s| &block(s).fc2, |b| (&b.mlp, &mut b.tmp, &mut b.h));
    }

    /// `out_s = lin_s(norm_s(x_s))` (then GELU) for every member; `io` picks `x` and `out`.
    fn normed_batch<'w>(
        &'w self,
        m: &mut dyn Members,
        norm_lin: impl Fn(usize) -> (&'w Norm, &'w Linear),
        io: Pair,
        gelu: bool,
    ) {
        let n = m.count();
        for i in 0..n {
            let st = m.member(i).st;
            let (x, _) = io(&mut st.bufs);
            for s in 0..N_STREAMS {
                norm_lin(s).0.run(&x[s], &mut st.own[0].x[s]);
            }
        }
        let rows = std::array::from_fn(|s| norm_lin(s).1.w.rows);
        each_unit(rows, self.blocks_of(|s| &norm_lin(s).1.w), |s, r| {
            let lin = norm_lin(s).1;
            for i in 0..n {
                let st = m.member(i).st;
                let (_, out) = io(&mut st.bufs);
                let y = &mut out[s][r.clone()];
                lin.rows(&self.arena, &st.own[0].x[s], r.clone(), y);
                if gelu {
                    gelu_erf(y);
                }
            }
        });
    }

    /// `h_s += lin_s(x_s)` by way of `tmp` for every member; `io` picks `x`, `tmp`, `h`.
    fn residual_batch<'w>(&'w self, m: &mut dyn Members, lin: impl Fn(usize) -> &'w Linear, io: Triple) {
        let n = m.count();
        each_unit(self.d.widths, self.blocks_of(|s| &lin(s).w), |s, r| {
            for i in 0..n {
                let (x, tmp, h) = io(&mut m.member(i).st.bufs);
                let t = &mut tmp[s][r.clone()];
                lin(s).rows(&self.arena, &x[s], r.clone(), t);
                add_assign(&mut h[s][r.clone()], t);
            }
        });
    }

    /// The coordination before a layer, for every member.
    fn coordinate_batch(&self, co: &Coord, m: &mut dyn Members) {
        let (d, n, cw) = (&self.d, m.count(), self.d.coord_width);
        each_unit([cw; N_STREAMS], self.blocks_of(|s| &co.inp[s].w), |s, r| {
            for i in 0..n {
                let b = &mut m.member(i).st.bufs;
                co.inp[s].rows(&self.arena, &b.h[s], r.clone(), &mut b.cp[s * cw + r.start..s * cw + r.end]);
            }
        });
        for i in 0..n {
            let b = &mut m.member(i).st.bufs;
            concat_others(&b.cp, &mut b.ccat, cw);
        }
        let layers: [(&Linear, Flat, bool); 3] = [
            (&co.mlp[0], |b| (&b.ccat, &mut b.ch1), true),
            (&co.mlp[1], |b| (&b.ch1, &mut b.ch2), true),
            (&co.mlp[2], |b| (&b.ch2, &mut b.cm), false),
        ];
        for (lin, io, gelu) in layers {
            let width = lin.w.rows;
            each_unit([width, 0, 0, 0], [self.block_of(&lin.w), 1, 1, 1], |_, r| {
                for i in 0..n {
                    let st = m.member(i).st;
                    let part = &mut st.own[0].part[..N_STREAMS * r.len()];
                    let (x, out) = io(&mut st.bufs);
                    gemm_rows(self.arena.mat(&lin.w), x, N_STREAMS, lin.b.as_deref(), r.clone(), part);
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
        each_unit(d.widths, self.blocks_of(|s| &co.out[s].w), |s, r| {
            for i in 0..n {
                let b = &mut m.member(i).st.bufs;
                let t = &mut b.tmp[s][r.clone()];
                co.out[s].rows(&self.arena, &b.cm[s * cw..(s + 1) * cw], r.clone(), t);
                add_assign(t, &b.h[s][r.clone()]);
            }
        });
        for i in 0..n {
            let b = &mut m.member(i).st.bufs;
            for s in 0..N_STREAMS {
                co.norm[s].run(&b.tmp[s], &mut b.h[s]);
            }
        }
    }
}

/// Calls `f(s, rows)` for the blocks of `block[s]` rows of `rows[s]`, stream after stream:
/// the units of the one-generation step, so every row block starts where it starts there.
fn each_unit(rows: [usize; N_STREAMS], block: [usize; N_STREAMS], mut f: impl FnMut(usize, Range<usize>)) {
    for s in 0..N_STREAMS {
        let b = block[s].max(1);
        let mut r0 = 0;
        while r0 < rows[s] {
            let r1 = (r0 + b).min(rows[s]);
            f(s, r0..r1);
            r0 = r1;
        }
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
            for i in 0..n {
                let (mut st, mut lg) = (m.new_state(), fresh());
                let mut seen = Vec::new();
                for k in 0..steps(i) {
                    m.step_solo(&mut st, tokens(k, i, &d.vocab), k, &emb[i], &mut lg);
                    seen.push(bits(&lg));
                }
                alone.push((seen, bits(&st.bufs.k), bits(&st.bufs.v)));
            }
            let mut states: Vec<_> = (0..n).map(|_| m.new_state()).collect();
            let mut logits: Vec<_> = (0..n).map(|_| fresh()).collect();
            let mut seen = vec![Vec::new(); n];
            for t in 0..d.slots + n {
                let ids: Vec<usize> = (0..n).filter(|&i| t >= i && t - i < steps(i)).collect();
                let pos: Vec<usize> = ids.iter().map(|&i| t - i).collect();
                let (states, logits, emb, vocab) = (&mut states[..], &mut logits[..], &emb[..], d.vocab);
                m.step_batch(&mut Batch { states, logits, ids: &ids, pos: &pos, emb, vocab });
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
