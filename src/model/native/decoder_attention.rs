//! The decoder's token-rate `AttentionBlock(width, heads, window=W)` (models/layers.py), on
//! the new positions only: pre-LN causal local attention over the last `W` positions
//! (itself included) with a learned per-head relative-position bias, then a GELU MLP.
//! The keys and values of the last `W` positions are kept in a ring; at the start of a
//! sequence a position attends to the positions that exist (the graph's mask).
use std::path::Path;

use super::arena::{Arena, Wm};
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

/// One stream's attention context and scratch.
#[derive(Clone, Debug)]
pub(crate) struct AttnState {
    /// Ring of the last `window` keys / values (`window x width`), slot = position % window.
    k: Vec<f32>,
    v: Vec<f32>,
    /// Positions seen.
    pos: usize,
    ln: Vec<f32>,
    qkv: Vec<f32>,
    y: Vec<f32>,
    t: Vec<f32>,
    hid: Vec<f32>,
    scores: Vec<f32>,
}

impl AttnState {
    pub(crate) fn copy_from(&mut self, o: &AttnState) {
        self.k.copy_from_slice(&o.k);
        self.v.copy_from_slice(&o.v);
        self.pos = o.pos;
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

    /// A new stream's context, with scratch for up to `max_pos` positions per call.
    pub(crate) fn new_state(&self, max_pos: usize) -> AttnState {
        let w = self.width;
        AttnState {
            k: vec![0.0; self.window * w],
            v: vec![0.0; self.window * w],
            pos: 0,
            ln: vec![0.0; max_pos * w],
            qkv: vec![0.0; max_pos * 3 * w],
            y: vec![0.0; max_pos * w],
            t: vec![0.0; max_pos * w],
            hid: vec![0.0; max_pos * 2 * w],
            scores: vec![0.0; self.window],
        }
    }

    /// `h (n x width) <- block(h)` for the next `n` positions (at most the state's
    /// `max_pos`). The matrix products take the `n` positions at once (each weight read
    /// once); position `p` attends to the positions before it, in this call or earlier,
    /// and gets the same bits as when the positions come one call at a time.
    pub(crate) fn run(&self, a: &Arena, h: &mut [f32], n: usize, st: &mut AttnState) {
        let (w, nh, win) = (self.width, self.heads, self.window);
        let dh = w / nh;
        let nw = n * w;
        for (x, o) in h[..nw].chunks_exact(w).zip(st.ln.chunks_exact_mut(w)) {
            layer_norm(x, &self.norm1.0, &self.norm1.1, LN_EPS, o);
        }
        gemm(a.mat(&self.qkv), &st.ln, w, n, Some(&self.qkv_b), &mut st.qkv, 3 * w);
        let inv = 1.0 / (dh as f32).sqrt();
        for p in 0..n {
            let qkv = &st.qkv[p * 3 * w..(p + 1) * 3 * w];
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
                    st.scores[o] = dot(q, k) * inv + self.rel_bias[hh * win + o];
                }
                softmax(&mut st.scores[..seen]);
                let y = &mut st.y[p * w + hh * dh..p * w + (hh + 1) * dh];
                y.fill(0.0);
                for o in 0..seen {
                    let s = (st.pos - 1 - o) % win;
                    let pr = st.scores[o];
                    for (a, b) in y.iter_mut().zip(&st.v[s * w + hh * dh..s * w + (hh + 1) * dh]) {
                        *a += pr * b;
                    }
                }
            }
        }
        gemm(a.mat(&self.out), &st.y, w, n, Some(&self.out_b), &mut st.t, w);
        for (a, b) in h[..nw].iter_mut().zip(&st.t) {
            *a += b;
        }
        for (x, o) in h[..nw].chunks_exact(w).zip(st.ln.chunks_exact_mut(w)) {
            layer_norm(x, &self.norm2.0, &self.norm2.1, LN_EPS, o);
        }
        gemm(a.mat(&self.mlp0), &st.ln, w, n, Some(&self.mlp0_b), &mut st.hid, 2 * w);
        gelu_erf(&mut st.hid[..2 * nw]);
        gemm(a.mat(&self.mlp2), &st.hid, 2 * w, n, Some(&self.mlp2_b), &mut st.t, w);
        for (a, b) in h[..nw].iter_mut().zip(&st.t) {
            *a += b;
        }
    }

    pub(crate) fn matrices(&self) -> [Wm; 4] {
        [self.qkv, self.out, self.mlp0, self.mlp2]
    }
}
