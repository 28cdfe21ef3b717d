//! The causal convolutions of the native decoder, computed on the new positions only.
//!
//! Buffers are time-major (`positions x channels`). A causal convolution of kernel `k` reads
//! the `k - 1` previous input positions besides the current one; its input buffer keeps
//! those as a *history* prefix, so the window of new position `p` is the contiguous slice
//! `buf[p * cin .. (p + k) * cin]`, and the weights are stored tap-major (`(cout, k * cin)`,
//! column `tap * cin + i`) to match. After a call the last `k - 1` positions become the
//! history of the next call. A zero history is exactly `F.pad`'s left zeros at the start
//! of a sequence.
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

    /// Values of an input buffer for `npos` new positions (history included).
    pub(crate) fn buf_len(&self, npos: usize) -> usize {
        (self.k - 1 + npos) * self.cin
    }

    /// Where the caller writes the `npos` new input positions of `buf`.
    pub(crate) fn input<'b>(&self, buf: &'b mut [f32], npos: usize) -> &'b mut [f32] {
        &mut buf[(self.k - 1) * self.cin..(self.k - 1 + npos) * self.cin]
    }

    /// `y (npos x cout) = conv(buf)`, then the history moves to the front of `buf`.
    pub(crate) fn run(&self, a: &Arena, buf: &mut [f32], npos: usize, y: &mut [f32]) {
        gemm(a.mat(&self.w), buf, self.cin, npos, Some(&self.b), y, self.cout);
        shift_history(buf, self.cin, self.k - 1, npos);
    }

    pub(crate) fn matrices(&self) -> [Wm; 1] {
        [self.w]
    }
}

/// Moves the last `hist` of `hist + npos` positions to the front.
fn shift_history(buf: &mut [f32], c: usize, hist: usize, npos: usize) {
    if hist > 0 {
        buf.copy_within(npos * c..(npos + hist) * c, 0);
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

    /// Values of the `Z` buffer for `npos` input positions (history included).
    pub(crate) fn z_len(&self, npos: usize) -> usize {
        (self.hist() + npos) * self.k * self.c
    }

    /// `y (2 npos x c)` from `x (npos x c)`; `z` is this layer's `Z` buffer.
    pub(crate) fn run(&self, a: &Arena, x: &[f32], npos: usize, z: &mut [f32], y: &mut [f32]) {
        let (c, k, h) = (self.c, self.k, self.hist());
        let kc = k * c;
        gemm(a.mat(&self.taps), x, c, npos, None, &mut z[h * kc..], kc);
        for t in 0..2 * npos {
            let yo = &mut y[t * c..(t + 1) * c];
            yo.copy_from_slice(&self.b);
            for tap in 0..k {
                // upsampled position m = t - (k - 1) + tap >= -2h; its input row (+h)
                let row = (t + tap + 2 * h - (k - 1)) / 2;
                let zr = &z[row * kc + tap * c..row * kc + (tap + 1) * c];
                for (o, v) in yo.iter_mut().zip(zr) {
                    *o += v;
                }
            }
        }
        shift_history(z, kc, h, npos);
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

    /// In place on `x (npos x c)`; `buf` is the conv's input buffer, `a` and `b` scratch of
    /// `npos x c`.
    pub(crate) fn run(&self, ar: &Arena, x: &mut [f32], npos: usize, buf: &mut [f32], a: &mut [f32], b: &mut [f32]) {
        let n = npos * self.conv.cin;
        let inp = self.conv.input(buf, npos);
        for (d, s) in inp.iter_mut().zip(&x[..n]) {
            *d = s.max(0.0);
        }
        self.conv.run(ar, buf, npos, &mut a[..n]);
        relu(&mut a[..n]);
        gemm(ar.mat(&self.proj), &a[..n], self.conv.cin, npos, Some(&self.proj_b), &mut b[..n], self.conv.cin);
        for (d, s) in x[..n].iter_mut().zip(&b[..n]) {
            *d += s;
        }
    }

    pub(crate) fn matrices(&self) -> [Wm; 2] {
        [self.conv.w, self.proj]
    }
}
