//! The causal convolutions of the native decoder, computed on the new positions only, for
//! one stream or several at once.
//!
//! Buffers are time-major (`positions x channels`). The new positions of every stream in a
//! decode are *stacked* in one buffer ([`Segs`]), so each layer is one GEMM over all of them
//! and its weights are read once per decode, not once per stream. A causal convolution of
//! kernel `k` reads the `k - 1` previous input positions besides the current one: each
//! stream keeps those as its *history* (a zero history is exactly `F.pad`'s left zeros at
//! the start of a sequence). The window of a new position (`k` rows, from the history or
//! the stream's new rows) is gathered into one row of `k * cin` values (~1/cout of the
//! multiply-adds), and the weights are stored tap-major (`(cout, k * cin)`, column
//! `tap * cin + i`) to match. A position's result is the same bits whichever streams and
//! how many positions are computed with it (`gemm` sums in a fixed order).
//!
//! The convolution after a nearest x2 upsampling ([`UpConv`]) reads every input value
//! twice; it is computed per tap on the *un-upsampled* positions (`Z_tap = W_tap u`, half
//! the products) and the outputs are sums of the right `Z`s.
use super::arena::{Arena, Wm};
use super::gemm::gemm;
use super::weights::{Matrix, Tensors};
use crate::error::Result;

/// Column permutation of a Conv1d weight `(cout, cin, k)` (PyTorch order, column
/// `i * k + tap`) into tap-major order (column `tap * cin + i`).
fn tap_major(m: Matrix, cin: usize, k: usize) -> Matrix {
    fn permute<T: Copy>(v: &[T], rows: usize, cin: usize, k: usize) -> Vec<T> {
        let cols = cin * k;
        let mut out = Vec::with_capacity(v.len());
        for r in 0..rows {
            let row = &v[r * cols..(r + 1) * cols];
            for tap in 0..k {
                out.extend((0..cin).map(|i| row[i * k + tap]));
            }
        }
        out
    }
    match m {
        Matrix::F32 { rows, cols, w } => Matrix::F32 { rows, cols, w: permute(&w, rows, cin, k) },
        Matrix::I8 { rows, cols, q, scale } => Matrix::I8 { rows, cols, q: permute(&q, rows, cin, k), scale },
    }
}

/// A Conv1d weight `(cout, cin, k)` as `k` stacked `(cout, cin)` matrices: row
/// `tap * cout + o` is `W[o, :, tap]` (an int8 row keeps its output channel's scale).
fn taps_stacked(m: Matrix, cin: usize, k: usize) -> Matrix {
    fn stack<T: Copy>(v: &[T], cout: usize, cin: usize, k: usize) -> Vec<T> {
        let mut out = Vec::with_capacity(v.len());
        for tap in 0..k {
            for o in 0..cout {
                out.extend((0..cin).map(|i| v[o * cin * k + i * k + tap]));
            }
        }
        out
    }
    match m {
        Matrix::F32 { rows, w, .. } => Matrix::F32 { rows: rows * k, cols: cin, w: stack(&w, rows, cin, k) },
        Matrix::I8 { rows, q, scale, .. } => Matrix::I8 {
            rows: rows * k,
            cols: cin,
            q: stack(&q, rows, cin, k),
            scale: (0..k).flat_map(|_| scale.iter().copied()).collect(),
        },
    }
}

/// Most streams one batched decode takes ([`Segs`]).
pub(crate) const MAX_BATCH: usize = 16;

/// Where each stream's new positions sit in the *stacked* work buffers of a decode: stream
/// `i`'s tokens are rows `off[i] .. off[i] + g[i]` at the token rate, and every level `l`
/// of upsampling scales both by `2^l`. One stream decoding alone is one segment.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Segs {
    n: usize,
    g: [usize; MAX_BATCH],
    off: [usize; MAX_BATCH],
    total: usize,
}

impl Segs {
    /// Segments of `g[i]` tokens each (at most [`MAX_BATCH`] streams).
    pub(crate) fn new(g: &[usize]) -> Segs {
        assert!((1..=MAX_BATCH).contains(&g.len()), "a decode of {} streams", g.len());
        let mut s = Segs { n: g.len(), g: [0; MAX_BATCH], off: [0; MAX_BATCH], total: 0 };
        for (i, &n) in g.iter().enumerate() {
            s.g[i] = n;
            s.off[i] = s.total;
            s.total += n;
        }
        s
    }

    pub(crate) fn count(&self) -> usize {
        self.n
    }

    /// Stream `i`'s first row and rows at level `l` (positions `2^l` per token).
    pub(crate) fn at(&self, i: usize, l: usize) -> (usize, usize) {
        (self.off[i] << l, self.g[i] << l)
    }

    /// Rows of all streams at level `l`.
    pub(crate) fn total(&self, l: usize) -> usize {
        self.total << l
    }
}

/// One layer's share of a decode: each stream's history of the layer, where the streams'
/// new rows are, and the level (`2^l` positions per token).
pub(crate) struct Layer<'a, H> {
    pub(crate) hist: H,
    pub(crate) segs: &'a Segs,
    pub(crate) l: usize,
}

/// Each stream's part of a layer's context (its history), by stream index.
pub(crate) trait PerStream<T: ?Sized> {
    fn get(&mut self, i: usize) -> &mut T;
}

/// `hist` (rows of `w` values) becomes the last rows of `[hist | new]` (`new` ReLU'd
/// first when `relu`): the context the next call continues from.
fn roll(hist: &mut [f32], w: usize, new: &[f32], relu: bool) {
    let (h, n) = (hist.len() / w, new.len() / w);
    let keep = h.saturating_sub(n);
    hist.copy_within((h - keep) * w.., 0);
    put(&mut hist[keep * w..], &new[(n - (h - keep)) * w..], relu);
}

/// Copies `src` into `dst`, ReLU'd when `relu`.
fn put(dst: &mut [f32], src: &[f32], relu: bool) {
    for (d, &v) in dst.iter_mut().zip(src) {
        *d = if relu { v.max(0.0) } else { v };
    }
}

pub(crate) fn relu(x: &mut [f32]) {
    for v in x {
        *v = v.max(0.0);
    }
}

/// `Conv(cin, cout, k, causal=True)` (`<prefix>.weight` `(cout, cin, k)`, `<prefix>.bias`).
#[derive(Debug)]
pub(crate) struct CausalConv {
    pub(crate) cin: usize,
    pub(crate) cout: usize,
    pub(crate) k: usize,
    w: Wm,
    b: Vec<f32>,
}

impl CausalConv {
    pub(crate) fn load(
        t: &Tensors,
        a: &mut Arena,
        prefix: &str,
        cin: usize,
        cout: usize,
        k: usize,
    ) -> Result<CausalConv> {
        let w = a.put(tap_major(t.matrix(&format!("{prefix}.weight"), cout, cin * k)?, cin, k));
        let b = t.vector(&format!("{prefix}.bias"), cout)?;
        Ok(CausalConv { cin, cout, k, w, b })
    }

    /// Values of a stream's history (`k - 1` input positions).
    pub(crate) fn hist_len(&self) -> usize {
        (self.k - 1) * self.cin
    }

    /// `y (rows x cout) = conv(x)` for the new rows `x` of every stream of `at` (ReLU'd
    /// first when `relu_in`), each after its own history, which then moves on; `win` is
    /// scratch of `rows x k cin`.
    pub(crate) fn run<H: PerStream<[f32]>>(
        &self,
        a: &Arena,
        at: Layer<H>,
        x: &[f32],
        relu_in: bool,
        win: &mut [f32],
        y: &mut [f32],
    ) {
        let Layer { mut hist, segs, l } = at;
        let (cin, k) = (self.cin, self.k);
        let kc = k * cin;
        for i in 0..segs.count() {
            let (o, n) = segs.at(i, l);
            let h = hist.get(i);
            let xs = &x[o * cin..(o + n) * cin];
            for p in 0..n {
                for (tap, dst) in win[(o + p) * kc..(o + p + 1) * kc].chunks_exact_mut(cin).enumerate() {
                    // input position p - (k - 1) + tap: the history's rows, then the new ones
                    match (p + tap).checked_sub(k - 1) {
                        None => dst.copy_from_slice(&h[(p + tap) * cin..(p + tap + 1) * cin]),
                        Some(r) => put(dst, &xs[r * cin..(r + 1) * cin], relu_in),
                    }
                }
            }
            roll(h, cin, xs, relu_in);
        }
        gemm(a.mat(&self.w), win, kc, segs.total(l), Some(&self.b), y, self.cout);
    }

    pub(crate) fn matrices(&self) -> [Wm; 1] {
        [self.w]
    }
}

/// `Upsample2` followed by `Conv(c, c, k, causal=True)`: `npos` input positions in, `2 npos`
/// out. Output `t` reads upsampled positions `t - k + 1 ..= t`, i.e. input positions
/// `floor((t - k + 1 + tap) / 2)`; `Z_tap` of the last `hist = k / 2` input positions
/// before the new ones is kept (zero before the start, as `F.pad`'s zeros give 0).
#[derive(Debug)]
pub(crate) struct UpConv {
    pub(crate) c: usize,
    pub(crate) k: usize,
    taps: Wm,
    b: Vec<f32>,
}

impl UpConv {
    pub(crate) fn load(t: &Tensors, a: &mut Arena, prefix: &str, c: usize, k: usize) -> Result<UpConv> {
        let taps = a.put(taps_stacked(t.matrix(&format!("{prefix}.weight"), c, c * k)?, c, k));
        let b = t.vector(&format!("{prefix}.bias"), c)?;
        Ok(UpConv { c, k, taps, b })
    }

    fn hist(&self) -> usize {
        self.k / 2
    }

    /// Values of a stream's history (`Z` of its last `k / 2` input positions).
    pub(crate) fn hist_len(&self) -> usize {
        self.hist() * self.k * self.c
    }

    /// `y (2 rows x c)` from `x (rows x c)`, the stacked new rows of every stream of `at`;
    /// `z` is scratch of `rows x k c`.
    pub(crate) fn run<H: PerStream<[f32]>>(&self, a: &Arena, at: Layer<H>, x: &[f32], z: &mut [f32], y: &mut [f32]) {
        let Layer { mut hist, segs, l } = at;
        let (c, k, h) = (self.c, self.k, self.hist());
        let kc = k * c;
        gemm(a.mat(&self.taps), x, c, segs.total(l), None, z, kc);
        for i in 0..segs.count() {
            let (o, n) = segs.at(i, l);
            let zh = hist.get(i);
            let zs = &z[o * kc..(o + n) * kc];
            for t in 0..2 * n {
                let yo = &mut y[(2 * o + t) * c..(2 * o + t + 1) * c];
                yo.copy_from_slice(&self.b);
                for tap in 0..k {
                    // upsampled position m = t - (k - 1) + tap >= -2h; its input row, the
                    // history's rows first
                    let row = (t + tap + 2 * h - (k - 1)) / 2;
                    let zr = match row.checked_sub(h) {
                        None => &zh[row * kc + tap * c..row * kc + (tap + 1) * c],
                        Some(r) => &zs[r * kc + tap * c..r * kc + (tap + 1) * c],
                    };
                    for (o, v) in yo.iter_mut().zip(zr) {
                        *o += v;
                    }
                }
            }
            roll(zh, kc, zs, false);
        }
    }

    pub(crate) fn matrices(&self) -> [Wm; 1] {
        [self.taps]
    }
}

/// `ResBlock(c, k, dilation 1, causal)`: `x + proj(relu(conv(relu(x))))`.
#[derive(Debug)]
pub(crate) struct ResBlock {
    pub(crate) conv: CausalConv,
    proj: Wm,
    proj_b: Vec<f32>,
}

impl ResBlock {
    pub(crate) fn load(t: &Tensors, ar: &mut Arena, prefix: &str, c: usize, k: usize) -> Result<ResBlock> {
        let conv = CausalConv::load(t, ar, &format!("{prefix}.conv.conv"), c, c, k)?;
        let proj = ar.put(t.matrix(&format!("{prefix}.proj.weight"), c, c)?);
        let proj_b = t.vector(&format!("{prefix}.proj.bias"), c)?;
        Ok(ResBlock { conv, proj, proj_b })
    }

    /// In place on `x` (the stacked new rows of `at`'s streams); `at` is the conv's, `win`,
    /// `a` and `b` scratch.
    pub(crate) fn run<H: PerStream<[f32]>>(
        &self,
        ar: &Arena,
        at: Layer<H>,
        x: &mut [f32],
        win: &mut [f32],
        a: &mut [f32],
        b: &mut [f32],
    ) {
        let (c, rows) = (self.conv.cin, at.segs.total(at.l));
        let n = rows * c;
        self.conv.run(ar, at, &x[..n], true, win, &mut a[..n]);
        relu(&mut a[..n]);
        gemm(ar.mat(&self.proj), &a[..n], c, rows, Some(&self.proj_b), &mut b[..n], c);
        for (d, s) in x[..n].iter_mut().zip(&b[..n]) {
            *d += s;
        }
    }

    pub(crate) fn matrices(&self) -> [Wm; 2] {
        [self.conv.w, self.proj]
    }
}
