//! The decoder's token-rate `AttentionBlock(width, heads, window=W)` (models/layers.py), on
//! the new positions only: pre-LN causal local attention over the last `W` positions
//! (itself included) with a learned per-head relative-position bias, then a GELU MLP.
//! The keys and values of the last `W` positions are kept in a ring per stream; at the start
//! of a sequence a position attends to the positions that exist (the graph's mask). The
//! matrix products take the stacked new positions of every stream of a decode at once
//! (`decoder_conv::Segs`), the attention itself runs per stream.
use std::path::Path;

use super::arena::{Arena, Wm};
use super::decoder_conv::{PerStream, Segs};
use super::gemm::gemm;
use super::kernels::{dot, gelu_erf, layer_norm, softmax};
use super::weights::Tensors;
use crate::error::{Error, Result};

const LN_EPS: f32 = 1e-5; // nn.LayerNorm's default

#[derive(Debug)]
pub(crate) struct WindowAttention {
    width: usize,
    heads: usize,
    window: usize,
    norm1: (Vec<f32>, Vec<f32>),
    qkv: Wm,
    qkv_b: Vec<f32>,
    out: Wm,
    out_b: Vec<f32>,
    norm2: (Vec<f32>, Vec<f32>),
    mlp0: Wm,
    mlp0_b: Vec<f32>,
    mlp2: Wm,
    mlp2_b: Vec<f32>,
    /// (heads, window): bias of key offset `query - key`.
    rel_bias: Vec<f32>,
}

/// One stream's attention context.
#[derive(Clone, Debug)]
pub(crate) struct AttnState {
    /// Ring of the last `window` keys / values (`window x width`), slot = position % window.
    k: Vec<f32>,
    v: Vec<f32>,
    /// Positions seen.
    pos: usize,
}

impl AttnState {
    pub(crate) fn copy_from(&mut self, o: &AttnState) {
        self.k.copy_from_slice(&o.k);
        self.v.copy_from_slice(&o.v);
        self.pos = o.pos;
    }
}

/// Scratch of a decode's attention, for up to its `max_pos` positions (all streams).
#[derive(Clone, Debug)]
pub(crate) struct AttnWork {
    ln: Vec<f32>,
    qkv: Vec<f32>,
    y: Vec<f32>,
    t: Vec<f32>,
    hid: Vec<f32>,
    scores: Vec<f32>,
}

impl AttnWork {
    /// Scratch for `max_pos` positions of blocks up to `width` wide with windows up to
    /// `window`.
    pub(crate) fn new(width: usize, window: usize, max_pos: usize) -> AttnWork {
        let n = max_pos * width;
        AttnWork {
            ln: vec![0.0; n],
            qkv: vec![0.0; 3 * n],
            y: vec![0.0; n],
            t: vec![0.0; n],
            hid: vec![0.0; 2 * n],
            scores: vec![0.0; window],
        }
    }
}

impl WindowAttention {
    /// `prefix` = `parts.<name>.decoder.layers.<i>`; heads and window come from `rel_bias`.
    pub(crate) fn load(t: &Tensors, a: &mut Arena, dir: &Path, prefix: &str, width: usize) -> Result<WindowAttention> {
        let name = |s: &str| format!("{prefix}.{s}");
        let rb = name("rel_bias");
        let (heads, window) = match t.shape(&rb)? {
            [h, w] if *h > 0 && *w > 0 && width.is_multiple_of(*h) => (*h, *w),
            s => return Err(Error::bundle(dir, format!(
                "native decoder tensor {rb} has shape {s:?}: expected (heads, window) with heads dividing the width {width}"))),
        };
        let w = width;
        Ok(WindowAttention {
            width,
            heads,
            window,
            norm1: (t.vector(&name("norm1.weight"), w)?, t.vector(&name("norm1.bias"), w)?),
            qkv: a.put(t.matrix(&name("qkv.weight"), 3 * w, w)?),
            qkv_b: t.vector(&name("qkv.bias"), 3 * w)?,
            out: a.put(t.matrix(&name("out.weight"), w, w)?),
            out_b: t.vector(&name("out.bias"), w)?,
            norm2: (t.vector(&name("norm2.weight"), w)?, t.vector(&name("norm2.bias"), w)?),
            mlp0: a.put(t.matrix(&name("mlp.0.weight"), 2 * w, w)?),
            mlp0_b: t.vector(&name("mlp.0.bias"), 2 * w)?,
            mlp2: a.put(t.matrix(&name("mlp.2.weight"), w, 2 * w)?),
            mlp2_b: t.vector(&name("mlp.2.bias"), w)?,
            rel_bias: t.vector(&rb, heads * window)?,
        })
    }

    /// Tensor names (after `prefix.`) this block reads.
    pub(crate) const TENSORS: [&'static str; 13] = [
        "rel_bias",
        "norm1.weight",
        "norm1.bias",
        "qkv.weight",
        "qkv.bias",
        "out.weight",
        "out.bias",
        "norm2.weight",
        "norm2.bias",
        "mlp.0.weight",
        "mlp.0.bias",
        "mlp.2.weight",
        "mlp.2.bias",
    ];

    pub(crate) fn window(&self) -> usize {
        self.window
    }

    pub(crate) fn width(&self) -> usize {
        self.width
    }

    /// A new stream's context.
    pub(crate) fn new_state(&self) -> AttnState {
        let w = self.width;
        AttnState { k: vec![0.0; self.window * w], v: vec![0.0; self.window * w], pos: 0 }
    }

    /// `h <- block(h)` for the stacked new positions of every stream (`segs` at the token
    /// rate), at most the scratch's `max_pos`. The matrix products take all positions at
    /// once (each weight read once); position `p` of a stream attends to that stream's
    /// positions before it, in this call or earlier, and gets the same bits as when the
    /// positions come one call at a time.
    pub(crate) fn run(
        &self,
        a: &Arena,
        h: &mut [f32],
        segs: &Segs,
        ctx: &mut dyn PerStream<AttnState>,
        wk: &mut AttnWork,
    ) {
        let (w, nh, win) = (self.width, self.heads, self.window);
        let dh = w / nh;
        let n = segs.total(0);
        let nw = n * w;
        for (x, o) in h[..nw].chunks_exact(w).zip(wk.ln.chunks_exact_mut(w)) {
            layer_norm(x, &self.norm1.0, &self.norm1.1, LN_EPS, o);
        }
        gemm(a.mat(&self.qkv), &wk.ln, w, n, Some(&self.qkv_b), &mut wk.qkv, 3 * w);
        let inv = 1.0 / (dh as f32).sqrt();
        for i in 0..segs.count() {
            let st = ctx.get(i);
            let (o, g) = segs.at(i, 0);
            for p in o..o + g {
                let qkv = &wk.qkv[p * 3 * w..(p + 1) * 3 * w];
                let slot = st.pos % win;
                st.k[slot * w..(slot + 1) * w].copy_from_slice(&qkv[w..2 * w]);
                st.v[slot * w..(slot + 1) * w].copy_from_slice(&qkv[2 * w..3 * w]);
                st.pos += 1;
                let seen = st.pos.min(win);
                for hh in 0..nh {
                    let q = &qkv[hh * dh..(hh + 1) * dh];
                    for o in 0..seen {
                        let s = (st.pos - 1 - o) % win;
                        let k = &st.k[s * w + hh * dh..s * w + (hh + 1) * dh];
                        wk.scores[o] = dot(q, k) * inv + self.rel_bias[hh * win + o];
                    }
                    softmax(&mut wk.scores[..seen]);
                    let y = &mut wk.y[p * w + hh * dh..p * w + (hh + 1) * dh];
                    y.fill(0.0);
                    for o in 0..seen {
                        let s = (st.pos - 1 - o) % win;
                        let pr = wk.scores[o];
                        for (a, b) in y.iter_mut().zip(&st.v[s * w + hh * dh..s * w + (hh + 1) * dh]) {
                            *a += pr * b;
                        }
                    }
                }
            }
        }
        gemm(a.mat(&self.out), &wk.y, w, n, Some(&self.out_b), &mut wk.t, w);
        for (a, b) in h[..nw].iter_mut().zip(&wk.t) {
            *a += b;
        }
        for (x, o) in h[..nw].chunks_exact(w).zip(wk.ln.chunks_exact_mut(w)) {
            layer_norm(x, &self.norm2.0, &self.norm2.1, LN_EPS, o);
        }
        gemm(a.mat(&self.mlp0), &wk.ln, w, n, Some(&self.mlp0_b), &mut wk.hid, 2 * w);
        gelu_erf(&mut wk.hid[..2 * nw]);
        gemm(a.mat(&self.mlp2), &wk.hid, 2 * w, n, Some(&self.mlp2_b), &mut wk.t, w);
        for (a, b) in h[..nw].iter_mut().zip(&wk.t) {
            *a += b;
        }
    }

    pub(crate) fn matrices(&self) -> [Wm; 4] {
        [self.qkv, self.out, self.mlp0, self.mlp2]
    }
}
