//! Kernels of the native path: GEMV over f32 or int8 rows (one vector or a few at once),
//! dot products, LayerNorm, GELU (erf), softmax.
//!
//! On x86-64 the hot loops have AVX2+FMA and AVX-512F bodies chosen at run time
//! (`is_x86_feature_detected!`, once per process; `RuntimeOptions::max_isa` caps the
//! choice, process-wide, for benchmarks and tests); elsewhere, or without those features, the
//! portable loops run (8 independent partial sums, which the compiler vectorizes). int8
//! rows are converted to f32 in registers (`q as f32 * scale`, the scale applied once per
//! row), so arithmetic stays f32 as in the ONNX graphs while the weights cost a quarter of
//! the memory traffic. The summation order is fixed per kernel and CPU feature set, never
//! data-dependent, so a run is reproducible on one machine.
use std::ops::Range;
use std::sync::atomic::{AtomicU8, Ordering};

use super::weights::Matrix;

const LANES: usize = 8;

/// Instruction sets the kernels have bodies for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Isa {
    Portable = 1,
    Avx2 = 2,
    Avx512 = 3,
}

/// What the CPU supports (0: not detected yet).
static DETECTED: AtomicU8 = AtomicU8::new(0);
/// The cap engines asked for (`RuntimeOptions::max_isa`); only ever lowered.
static CAP: AtomicU8 = AtomicU8::new(Isa::Avx512 as u8);

fn from_u8(v: u8) -> Isa {
    match v {
        1 => Isa::Portable,
        2 => Isa::Avx2,
        _ => Isa::Avx512,
    }
}

/// The instruction set the kernels use now: the best the CPU has, under the cap.
pub(crate) fn isa() -> Isa {
    detected().min(from_u8(CAP.load(Ordering::Relaxed)))
}

/// Lowers the process-wide cap to `cap` (never raises it): the kernels are shared code, so
/// an engine's `max_isa` applies to every engine of the process from then on. A call in
/// flight keeps the instruction set it started with, which the CPU still supports.
pub(crate) fn cap_isa(cap: crate::config::InstructionSet) {
    use crate::config::InstructionSet;
    let cap = match cap {
        InstructionSet::Portable => Isa::Portable,
        InstructionSet::Avx2 => Isa::Avx2,
        InstructionSet::Avx512 => Isa::Avx512,
    };
    CAP.fetch_min(cap as u8, Ordering::Relaxed);
}

/// The best instruction set the CPU supports (detected once).
fn detected() -> Isa {
    match DETECTED.load(Ordering::Relaxed) {
        0 => {
            let isa = detect();
            DETECTED.store(isa as u8, Ordering::Relaxed);
            isa
        }
        v => from_u8(v),
    }
}

fn detect() -> Isa {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
        let avx512 = avx2 && is_x86_feature_detected!("avx512f");
        if avx512 {
            Isa::Avx512
        } else if avx2 {
            Isa::Avx2
        } else {
            Isa::Portable
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        Isa::Portable
    }
}

// ----------------------------------------------------------------------------- portable

mod portable {
    use super::LANES;

    pub(super) fn dot(a: &[f32], b: &[f32]) -> f32 {
        let mut acc = [0.0f32; LANES];
        let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
        let (ra, rb) = (ca.remainder(), cb.remainder());
        for (x, y) in ca.zip(cb) {
            for i in 0..LANES {
                acc[i] += x[i] * y[i];
            }
        }
        let mut s = acc.iter().sum::<f32>();
        for (x, y) in ra.iter().zip(rb) {
            s += x * y;
        }
        s
    }

    pub(super) fn dot_i8(q: &[i8], x: &[f32]) -> f32 {
        let mut acc = [0.0f32; LANES];
        let (cq, cx) = (q.chunks_exact(LANES), x.chunks_exact(LANES));
        let (rq, rx) = (cq.remainder(), cx.remainder());
        for (a, b) in cq.zip(cx) {
            for i in 0..LANES {
                acc[i] += f32::from(a[i]) * b[i];
            }
        }
        let mut s = acc.iter().sum::<f32>();
        for (a, b) in rq.iter().zip(rx) {
            s += f32::from(*a) * b;
        }
        s
    }
}

// ----------------------------------------------------------------------------- x86-64

/// Leading columns summed one by one before the vector loop. Always 0: peeling up to an
/// aligned address would make the summation order, hence the last bits of every result,
/// depend on where the allocator put the weights, and the same seed and prompt must give
/// the same frames in every run (tests/cli.rs compares two runs). Aligned weight storage
/// would bring the aligned loads back.
#[cfg(target_arch = "x86_64")]
const HEAD: usize = 0;

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_movehdup_ps(s));
        _mm_cvtss_f32(s)
    }

    /// The four sums of four accumulators.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum4(a: [__m256; 4]) -> [f32; 4] {
        let t = _mm256_hadd_ps(_mm256_hadd_ps(a[0], a[1]), _mm256_hadd_ps(a[2], a[3]));
        let s = _mm_add_ps(_mm256_castps256_ps128(t), _mm256_extractf128_ps(t, 1));
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(out.as_mut_ptr(), s);
        out
    }

    /// 8 int8 at `p` as 8 f32.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn load_i8(p: *const i8) -> __m256 {
        _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64(p as *const __m128i)))
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn load_f32(p: *const f32) -> __m256 {
        _mm256_loadu_ps(p)
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn dot(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let (pa, pb) = (a.as_ptr(), b.as_ptr());
        let (mut s0, mut s1) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        let mut c = 0;
        while c + 16 <= n {
            s0 = _mm256_fmadd_ps(_mm256_loadu_ps(pa.add(c)), _mm256_loadu_ps(pb.add(c)), s0);
            s1 = _mm256_fmadd_ps(_mm256_loadu_ps(pa.add(c + 8)), _mm256_loadu_ps(pb.add(c + 8)), s1);
            c += 16;
        }
        if c + 8 <= n {
            s0 = _mm256_fmadd_ps(_mm256_loadu_ps(pa.add(c)), _mm256_loadu_ps(pb.add(c)), s0);
            c += 8;
        }
        let mut s = hsum(_mm256_add_ps(s0, s1));
        while c < n {
            s += *pa.add(c) * *pb.add(c);
            c += 1;
        }
        s
    }

    /// `y[r] = sum_c W[r][c] x[c]` for every row of a row-major `rows x cols` matrix whose
    /// elements `load` turns into 8 f32 at a time (f32 or int8), `elem` one at a time; four
    /// rows share each load of `x`, two accumulators per row hide the FMA latency.
    macro_rules! gemv_body {
        ($w:expr, $cols:expr, $x:expr, $y:expr, $load:ident, $elem:expr) => {{
            let (w, cols, x, y) = ($w, $cols, $x, $y);
            let rows = y.len();
            let px = x.as_ptr();
            let mut r = 0;
            let head = super::HEAD;
            while r + 4 <= rows {
                let p = [w.add(r * cols), w.add((r + 1) * cols), w.add((r + 2) * cols), w.add((r + 3) * cols)];
                let mut a = [_mm256_setzero_ps(); 4];
                let mut b = [_mm256_setzero_ps(); 4];
                let mut h = [0.0f32; 4];
                for c in 0..head {
                    for i in 0..4 {
                        h[i] += ($elem)(*p[i].add(c)) * *px.add(c);
                    }
                }
                let mut c = head;
                while c + 16 <= cols {
                    let x0 = _mm256_loadu_ps(px.add(c));
                    let x1 = _mm256_loadu_ps(px.add(c + 8));
                    for i in 0..4 {
                        a[i] = _mm256_fmadd_ps($load(p[i].add(c)), x0, a[i]);
                        b[i] = _mm256_fmadd_ps($load(p[i].add(c + 8)), x1, b[i]);
                    }
                    c += 16;
                }
                if c + 8 <= cols {
                    let x0 = _mm256_loadu_ps(px.add(c));
                    for i in 0..4 {
                        a[i] = _mm256_fmadd_ps($load(p[i].add(c)), x0, a[i]);
                    }
                    c += 8;
                }
                for i in 0..4 {
                    a[i] = _mm256_add_ps(a[i], b[i]);
                }
                let mut s = hsum4(a);
                for i in 0..4 {
                    s[i] += h[i];
                }
                while c < cols {
                    for i in 0..4 {
                        s[i] += ($elem)(*p[i].add(c)) * *px.add(c);
                    }
                    c += 1;
                }
                y[r..r + 4].copy_from_slice(&s);
                r += 4;
            }
            while r < rows {
                let p = w.add(r * cols);
                let mut a = _mm256_setzero_ps();
                let mut c = 0;
                while c + 8 <= cols {
                    a = _mm256_fmadd_ps($load(p.add(c)), _mm256_loadu_ps(px.add(c)), a);
                    c += 8;
                }
                let mut s = hsum(a);
                while c < cols {
                    s += ($elem)(*p.add(c)) * *px.add(c);
                    c += 1;
                }
                y[r] = s;
                r += 1;
            }
        }};
    }

    /// The same over `n` (1..=4) vectors at once (`x`: n x cols, `y`: n x rows, both
    /// row-major): each weight row is read once for all of them.
    macro_rules! gemm_body {
        ($w:expr, $cols:expr, $x:expr, $n:expr, $y:expr, $load:ident, $elem:expr) => {{
            let (w, cols, x, n, y) = ($w, $cols, $x, $n, $y);
            let rows = y.len() / n;
            let px = x.as_ptr();
            for r in 0..rows {
                let p = w.add(r * cols);
                let mut a = [_mm256_setzero_ps(); 4];
                let mut c = 0;
                while c + 8 <= cols {
                    let wv = $load(p.add(c));
                    for j in 0..n {
                        a[j] = _mm256_fmadd_ps(wv, _mm256_loadu_ps(px.add(j * cols + c)), a[j]);
                    }
                    c += 8;
                }
                let mut s = hsum4(a);
                while c < cols {
                    let wv = ($elem)(*p.add(c));
                    for j in 0..n {
                        s[j] += wv * *px.add(j * cols + c);
                    }
                    c += 1;
                }
                for j in 0..n {
                    y[j * rows + r] = s[j];
                }
            }
        }};
    }

    /// f32 rows one at a time, each summed exactly as `gemv_body` sums it (the rows of
    /// whole blocks of 4 with two accumulators and `hsum4`'s order, the last `rows % 4` with
    /// one): one sequential stream through the weights instead of four (see avx512's).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemv_f32(w: &[f32], cols: usize, x: &[f32], y: &mut [f32]) {
        let rows = y.len();
        let blocked = rows / 4 * 4;
        let px = x.as_ptr();
        let head = super::HEAD;
        for (r, out) in y[..blocked].iter_mut().enumerate() {
            let p = w.as_ptr().add(r * cols);
            let (mut a, mut b) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            let mut h = 0.0f32;
            for c in 0..head {
                h += *p.add(c) * *px.add(c);
            }
            let mut c = head;
            while c + 16 <= cols {
                a = _mm256_fmadd_ps(_mm256_loadu_ps(p.add(c)), _mm256_loadu_ps(px.add(c)), a);
                b = _mm256_fmadd_ps(_mm256_loadu_ps(p.add(c + 8)), _mm256_loadu_ps(px.add(c + 8)), b);
                c += 16;
            }
            if c + 8 <= cols {
                a = _mm256_fmadd_ps(_mm256_loadu_ps(p.add(c)), _mm256_loadu_ps(px.add(c)), a);
                c += 8;
            }
            let mut s = hsum4_one(_mm256_add_ps(a, b)) + h;
            while c < cols {
                s += *p.add(c) * *px.add(c);
                c += 1;
            }
            *out = s;
        }
        if blocked < rows {
            gemv_body!(w.as_ptr().add(blocked * cols), cols, x, &mut y[blocked..], load_f32, |v: f32| v)
        }
    }

    /// The four-rows-at-once body on f32 (what `gemv_f32` computed before; for tests).
    #[cfg(test)]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemv_f32_by_blocks(w: &[f32], cols: usize, x: &[f32], y: &mut [f32]) {
        gemv_body!(w.as_ptr(), cols, x, y, load_f32, |v: f32| v)
    }

    /// One row's sum in `hsum4`'s order.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum4_one(a: __m256) -> f32 {
        let t = _mm256_hadd_ps(_mm256_hadd_ps(a, a), _mm256_hadd_ps(a, a));
        _mm_cvtss_f32(_mm_add_ps(_mm256_castps256_ps128(t), _mm256_extractf128_ps(t, 1)))
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemv_i8(q: &[i8], cols: usize, x: &[f32], y: &mut [f32]) {
        gemv_body!(q.as_ptr(), cols, x, y, load_i8, f32::from)
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemm_f32(w: &[f32], cols: usize, x: &[f32], n: usize, y: &mut [f32]) {
        gemm_body!(w.as_ptr(), cols, x, n, y, load_f32, |v: f32| v)
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemm_i8(q: &[i8], cols: usize, x: &[f32], n: usize, y: &mut [f32]) {
        gemm_body!(q.as_ptr(), cols, x, n, y, load_i8, f32::from)
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn load_i8(p: *const i8) -> __m512 {
        _mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(_mm_loadu_si128(p as *const __m128i)))
    }

    /// As avx2's `gemv_body` with 16 lanes: four rows share each load of `x`.
    macro_rules! gemv_body {
        ($w:expr, $cols:expr, $x:expr, $y:expr, $load:ident, $elem:expr, $pf:expr) => {{
            let (w, cols, x, y) = ($w, $cols, $x, $y);
            let rows = y.len();
            let px = x.as_ptr();
            let mut r = 0;
            let head = super::HEAD;
            while r < rows {
                let k = (rows - r).min(4);
                let p = [0, 1, 2, 3].map(|i| w.add((r + i.min(k - 1)) * cols));
                let mut a = [_mm512_setzero_ps(); 4];
                let mut b = [_mm512_setzero_ps(); 4];
                let mut h = [0.0f32; 4];
                for c in 0..head {
                    for i in 0..4 {
                        h[i] += ($elem)(*p[i].add(c)) * *px.add(c);
                    }
                }
                let mut c = head;
                while c + 32 <= cols {
                    let x0 = _mm512_loadu_ps(px.add(c));
                    let x1 = _mm512_loadu_ps(px.add(c + 16));
                    for i in 0..4 {
                        if $pf {
                            // the same columns of the next block of rows (never faults)
                            let ahead = p[i].wrapping_add(4 * cols + c) as *const i8;
                            _mm_prefetch::<_MM_HINT_T0>(ahead);
                            _mm_prefetch::<_MM_HINT_T0>(ahead.wrapping_add(64));
                        }
                        a[i] = _mm512_fmadd_ps($load(p[i].add(c)), x0, a[i]);
                        b[i] = _mm512_fmadd_ps($load(p[i].add(c + 16)), x1, b[i]);
                    }
                    c += 32;
                }
                if c + 16 <= cols {
                    let x0 = _mm512_loadu_ps(px.add(c));
                    for i in 0..4 {
                        a[i] = _mm512_fmadd_ps($load(p[i].add(c)), x0, a[i]);
                    }
                    c += 16;
                }
                let mut s = [0.0f32; 4];
                for i in 0..4 {
                    s[i] = _mm512_reduce_add_ps(_mm512_add_ps(a[i], b[i])) + h[i];
                }
                while c < cols {
                    for i in 0..4 {
                        s[i] += ($elem)(*p[i].add(c)) * *px.add(c);
                    }
                    c += 1;
                }
                y[r..r + k].copy_from_slice(&s[..k]);
                r += k;
            }
        }};
    }

    /// f32 rows one at a time (a row's sums exactly as in `gemv_body`): one sequential
    /// stream through the weights. Four rows at once are four streams 4 KiB or more apart,
    /// which the prefetchers serve at ~15 GB/s on Zen 4 against ~24 GB/s for one stream
    /// (measured on the 2-core machine, weights in 2 MiB pages).
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn gemv_f32(w: &[f32], cols: usize, x: &[f32], y: &mut [f32]) {
        let px = x.as_ptr();
        let head = super::HEAD;
        for (r, out) in y.iter_mut().enumerate() {
            let p = w.as_ptr().add(r * cols);
            let mut a = _mm512_setzero_ps();
            let mut b = _mm512_setzero_ps();
            let mut h = 0.0f32;
            for c in 0..head {
                h += *p.add(c) * *px.add(c);
            }
            let mut c = head;
            while c + 32 <= cols {
                a = _mm512_fmadd_ps(_mm512_loadu_ps(p.add(c)), _mm512_loadu_ps(px.add(c)), a);
                b = _mm512_fmadd_ps(_mm512_loadu_ps(p.add(c + 16)), _mm512_loadu_ps(px.add(c + 16)), b);
                c += 32;
            }
            if c + 16 <= cols {
                a = _mm512_fmadd_ps(_mm512_loadu_ps(p.add(c)), _mm512_loadu_ps(px.add(c)), a);
                c += 16;
            }
            let mut s = _mm512_reduce_add_ps(_mm512_add_ps(a, b)) + h;
            while c < cols {
                s += *p.add(c) * *px.add(c);
                c += 1;
            }
            *out = s;
        }
    }

    /// `gemv_many_f32` / `gemv_many_i8`: `y[j * rows + r] = row r . x_j` for the `n` inputs
    /// of `x` (`cols` each), every value the bits `gemv_f32`/`gemv_i8` give for that input
    /// alone (lanes over 32 columns into two accumulators, a 16-column step into the first,
    /// `reduce_add(a + b) + head`, the scalar tail). Tiles of 2 rows x up to 6 inputs: each
    /// weight vector is loaded and widened once per 6 inputs and each input vector once per
    /// 2 rows (one row per input vector left the kernel bound by loads).
    macro_rules! gemv_many {
        ($many:ident, $row:ident, $t:ty, $load:ident, $elem:expr) => {
            #[inline]
            #[target_feature(enable = "avx512f")]
            unsafe fn $row<const R: usize, const K: usize>(
                p: *const $t,
                cols: usize,
                px: *const f32,
                out: *mut f32,
                stride: usize,
            ) {
                const { assert!(super::HEAD == 0, "the batched GEMV assumes no head columns, as gemv_body") };
                let mut a = [[_mm512_setzero_ps(); K]; R];
                let mut b = [[_mm512_setzero_ps(); K]; R];
                let mut c = 0;
                while c + 32 <= cols {
                    let mut w0 = [_mm512_setzero_ps(); R];
                    let mut w1 = [_mm512_setzero_ps(); R];
                    for i in 0..R {
                        w0[i] = $load(p.add(i * cols + c));
                        w1[i] = $load(p.add(i * cols + c + 16));
                    }
                    for j in 0..K {
                        let xj = px.add(j * cols + c);
                        let (x0, x1) = (_mm512_loadu_ps(xj), _mm512_loadu_ps(xj.add(16)));
                        for i in 0..R {
                            a[i][j] = _mm512_fmadd_ps(w0[i], x0, a[i][j]);
                            b[i][j] = _mm512_fmadd_ps(w1[i], x1, b[i][j]);
                        }
                    }
                    c += 32;
                }
                if c + 16 <= cols {
                    let mut w0 = [_mm512_setzero_ps(); R];
                    for i in 0..R {
                        w0[i] = $load(p.add(i * cols + c));
                    }
                    for j in 0..K {
                        let x0 = _mm512_loadu_ps(px.add(j * cols + c));
                        for i in 0..R {
                            a[i][j] = _mm512_fmadd_ps(w0[i], x0, a[i][j]);
                        }
                    }
                    c += 16;
                }
                let head = 0.0f32;
                for i in 0..R {
                    for j in 0..K {
                        let mut s = _mm512_reduce_add_ps(_mm512_add_ps(a[i][j], b[i][j])) + head;
                        for t in c..cols {
                            s += ($elem)(*p.add(i * cols + t)) * *px.add(j * cols + t);
                        }
                        *out.add(j * stride + i) = s;
                    }
                }
            }

            #[target_feature(enable = "avx512f")]
            pub(super) unsafe fn $many(w: &[$t], cols: usize, x: &[f32], n: usize, y: &mut [f32]) {
                let rows = y.len() / n;
                let (px, py) = (x.as_ptr(), y.as_mut_ptr());
                let mut r0 = 0;
                while r0 < rows {
                    // A block of rows (in L2) against each group of inputs in turn (in L1):
                    // the inputs stream from L2 once per block, not once per row pair.
                    let r1 = (r0 + MANY_ROW_BLOCK).min(rows);
                    let mut j = 0;
                    while j < n {
                        let k = match n - j {
                            1 => 1,
                            2 => 2,
                            3 => 3,
                            4 | 5 => 4,
                            _ => 6,
                        };
                        let mut r = r0;
                        while r < r1 {
                            let two = r + 2 <= r1;
                            let (p, xj, out) = (w.as_ptr().add(r * cols), px.add(j * cols), py.add(j * rows + r));
                            match (two, k) {
                                (true, 1) => $row::<2, 1>(p, cols, xj, out, rows),
                                (true, 2) => $row::<2, 2>(p, cols, xj, out, rows),
                                (true, 3) => $row::<2, 3>(p, cols, xj, out, rows),
                                (true, 4) => $row::<2, 4>(p, cols, xj, out, rows),
                                (true, _) => $row::<2, 6>(p, cols, xj, out, rows),
                                (false, 1) => $row::<1, 1>(p, cols, xj, out, rows),
                                (false, 2) => $row::<1, 2>(p, cols, xj, out, rows),
                                (false, 3) => $row::<1, 3>(p, cols, xj, out, rows),
                                (false, 4) => $row::<1, 4>(p, cols, xj, out, rows),
                                (false, _) => $row::<1, 6>(p, cols, xj, out, rows),
                            }
                            r += if two { 2 } else { 1 };
                        }
                        j += k;
                    }
                    r0 = r1;
                }
            }
        };
    }

    /// Rows of a block of `gemv_many_*`.
    const MANY_ROW_BLOCK: usize = 32;

    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn load_f32(p: *const f32) -> __m512 {
        _mm512_loadu_ps(p)
    }

    gemv_many!(gemv_many_f32, many_row_f32, f32, load_f32, |v: f32| v);
    gemv_many!(gemv_many_i8, many_row_i8, i8, load_i8, f32::from);

    /// int8 rows are short streams (a 1024-wide row is 16 cache lines, too few for the
    /// hardware prefetcher to ramp up), so the next block of rows is prefetched.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn gemv_i8(q: &[i8], cols: usize, x: &[f32], y: &mut [f32]) {
        gemv_body!(q.as_ptr(), cols, x, y, load_i8, f32::from, true)
    }
}

// ----------------------------------------------------------------------------- API

/// A borrowed row-major weight matrix, what the GEMV kernels read: a [`Matrix`], or a
/// matrix of the native step's weight arena (step.rs).
#[derive(Clone, Copy, Debug)]
pub(crate) enum MatRef<'a> {
    F32 {
        rows: usize,
        cols: usize,
        w: &'a [f32],
    },
    /// int8 rows times one scale per row.
    I8 {
        rows: usize,
        cols: usize,
        q: &'a [i8],
        scale: &'a [f32],
    },
}

impl MatRef<'_> {
    pub(crate) fn rows(&self) -> usize {
        match self {
            MatRef::F32 { rows, .. } | MatRef::I8 { rows, .. } => *rows,
        }
    }

    pub(crate) fn cols(&self) -> usize {
        match self {
            MatRef::F32 { cols, .. } | MatRef::I8 { cols, .. } => *cols,
        }
    }
}

impl<'a> From<&'a Matrix> for MatRef<'a> {
    fn from(m: &'a Matrix) -> MatRef<'a> {
        match m {
            Matrix::F32 { rows, cols, w } => MatRef::F32 { rows: *rows, cols: *cols, w },
            Matrix::I8 { rows, cols, q, scale } => MatRef::I8 { rows: *rows, cols: *cols, q, scale },
        }
    }
}

/// Dot product with a fixed summation order (independent partial sums, vectorized).
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    debug_assert_eq!(a.len(), b.len());
    #[cfg(target_arch = "x86_64")]
    if isa() >= Isa::Avx2 {
        // SAFETY: AVX2 and FMA were detected; the kernel reads min(len) elements of each.
        return unsafe { avx2::dot(a, b) };
    }
    portable::dot(a, b)
}

/// Dot product of an int8 row with f32 values (the row's scale is applied by the caller).
pub(crate) fn dot_i8(q: &[i8], x: &[f32]) -> f32 {
    debug_assert_eq!(q.len(), x.len());
    portable::dot_i8(q, x)
}

fn add_bias(y: &mut [f32], bias: Option<&[f32]>) {
    if let Some(b) = bias {
        for (o, b) in y.iter_mut().zip(b) {
            *o += b;
        }
    }
}

/// Rows `rows` of `y = M x (+ bias)`: `y[i] = (M x + bias)[rows.start + i]`. Each row's value is
/// bit-identical to the whole product's as long as `rows.start` is a multiple of 4 (the
/// kernels' row blocks).
pub(crate) fn gemv_rows(m: MatRef<'_>, x: &[f32], bias: Option<&[f32]>, rows: Range<usize>, y: &mut [f32]) {
    gemv_with(isa(), m, x, bias, rows, y)
}

/// [`gemv_rows`] with the given instruction set (which the CPU must support).
fn gemv_with(isa: Isa, m: MatRef<'_>, x: &[f32], bias: Option<&[f32]>, rows: Range<usize>, y: &mut [f32]) {
    assert!(
        x.len() == m.cols() && rows.end <= m.rows() && y.len() == rows.len() && isa <= detected(),
        "gemv: {}x{} matrix, x {}, rows {rows:?}, y {}",
        m.rows(),
        m.cols(),
        x.len(),
        y.len()
    );
    let (r0, r1) = (rows.start, rows.end);
    match m {
        MatRef::F32 { cols, w, .. } => {
            let w = &w[r0 * cols..r1 * cols];
            match isa {
                // SAFETY (all arms): the features were detected; the kernels read
                // y.len()*cols weights (the slice holds exactly that) and cols of x.
                #[cfg(target_arch = "x86_64")]
                Isa::Avx512 => unsafe { avx512::gemv_f32(w, cols, x, y) },
                #[cfg(target_arch = "x86_64")]
                Isa::Avx2 => unsafe { avx2::gemv_f32(w, cols, x, y) },
                _ => {
                    for (r, out) in y.iter_mut().enumerate() {
                        *out = portable::dot(&w[r * cols..(r + 1) * cols], x);
                    }
                }
            }
        }
        MatRef::I8 { cols, q, scale, .. } => {
            let q = &q[r0 * cols..r1 * cols];
            match isa {
                #[cfg(target_arch = "x86_64")]
                Isa::Avx512 => unsafe { avx512::gemv_i8(q, cols, x, y) },
                #[cfg(target_arch = "x86_64")]
                Isa::Avx2 => unsafe { avx2::gemv_i8(q, cols, x, y) },
                _ => {
                    for (r, out) in y.iter_mut().enumerate() {
                        *out = portable::dot_i8(&q[r * cols..(r + 1) * cols], x);
                    }
                }
            }
            for (o, s) in y.iter_mut().zip(&scale[r0..r1]) {
                *o *= s;
            }
        }
    }
    add_bias(y, bias.map(|b| &b[r0..r1]));
}

/// `n` (1..=4) GEMVs with the same matrix, rows `rows` of them: `x` holds n inputs of
/// `M.cols()` one after the other, `y` n outputs of `rows.len()`,
/// `y[j * rows.len() + i] = (M x_j + bias)[rows.start + i]`; each weight row is read once
/// for all of them, and every value is bit-identical to the whole product's (the kernels
/// compute each row on its own).
pub(crate) fn gemm_rows(m: MatRef<'_>, x: &[f32], n: usize, bias: Option<&[f32]>, rows: Range<usize>, y: &mut [f32]) {
    gemm_with(isa(), m, x, n, bias, rows, y)
}

fn gemm_with(isa: Isa, m: MatRef<'_>, x: &[f32], n: usize, bias: Option<&[f32]>, rows: Range<usize>, y: &mut [f32]) {
    let cols = m.cols();
    let part = rows.len();
    assert!(
        (1..=4).contains(&n) && x.len() == n * cols && rows.end <= m.rows() && y.len() == n * part && isa <= detected(),
        "gemm: {}x{cols} matrix, n {n}, x {}, rows {rows:?}, y {}",
        m.rows(),
        x.len(),
        y.len()
    );
    let (r0, r1) = (rows.start, rows.end);
    #[cfg(target_arch = "x86_64")]
    if isa >= Isa::Avx2 {
        match m {
            // SAFETY: AVX2+FMA detected; part*cols weights, n*cols inputs, n*part outputs.
            MatRef::F32 { w, .. } => unsafe { avx2::gemm_f32(&w[r0 * cols..r1 * cols], cols, x, n, y) },
            MatRef::I8 { q, .. } => unsafe { avx2::gemm_i8(&q[r0 * cols..r1 * cols], cols, x, n, y) },
        }
        for j in 0..n {
            let yj = &mut y[j * part..(j + 1) * part];
            if let MatRef::I8 { scale, .. } = m {
                for (o, s) in yj.iter_mut().zip(&scale[r0..r1]) {
                    *o *= s;
                }
            }
            add_bias(yj, bias.map(|b| &b[r0..r1]));
        }
        return;
    }
    for j in 0..n {
        gemv_with(isa, m, &x[j * cols..(j + 1) * cols], bias, rows.clone(), &mut y[j * part..(j + 1) * part]);
    }
}

/// `n` GEMVs with the same matrix, rows `rows` of them (`x`: n inputs of `M.cols()`; `y`:
/// n outputs of `rows.len()`, `y[j * rows.len() + i] = (M x_j + bias)[rows.start + i]`),
/// every value bit-identical to [`gemv_rows`] on that input alone: what the batched step
/// of many generations needs. With AVX-512 each weight row is read and widened once per
/// group of up to 6 inputs (the int8 -> f32 conversion, not the memory, bounds a GEMV from
/// cache); otherwise it is `n` GEMVs.
pub(crate) fn gemv_rows_many(
    m: MatRef<'_>,
    x: &[f32],
    n: usize,
    bias: Option<&[f32]>,
    rows: Range<usize>,
    y: &mut [f32],
) {
    let (cols, part, isa) = (m.cols(), rows.len(), isa());
    assert!(
        x.len() == n * cols && rows.end <= m.rows() && y.len() == n * part,
        "gemv_many: {}x{cols} matrix, n {n}, x {}, rows {rows:?}, y {}",
        m.rows(),
        x.len(),
        y.len()
    );
    if n == 0 || part == 0 {
        return;
    }
    let (r0, r1) = (rows.start, rows.end);
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 {
        match m {
            // SAFETY: AVX-512F detected (isa() never exceeds it); part*cols weights, n*cols
            // inputs, n*part outputs, as the slices hold.
            MatRef::F32 { w, .. } => unsafe { avx512::gemv_many_f32(&w[r0 * cols..r1 * cols], cols, x, n, y) },
            MatRef::I8 { q, .. } => unsafe { avx512::gemv_many_i8(&q[r0 * cols..r1 * cols], cols, x, n, y) },
        }
        for yj in y.chunks_exact_mut(part) {
            if let MatRef::I8 { scale, .. } = m {
                for (o, s) in yj.iter_mut().zip(&scale[r0..r1]) {
                    *o *= s;
                }
            }
            add_bias(yj, bias.map(|b| &b[r0..r1]));
        }
        return;
    }
    for (xj, yj) in x.chunks_exact(cols).zip(y.chunks_exact_mut(part)) {
        gemv_with(isa, m, xj, bias, rows.clone(), yj);
    }
}

/// `y += x` element-wise.
pub(crate) fn add_assign(y: &mut [f32], x: &[f32]) {
    for (a, b) in y.iter_mut().zip(x) {
        *a += b;
    }
}

/// LayerNorm over the whole slice (PyTorch's biased variance): `out = (x - mean) / sqrt(var + eps) * w + b`.
pub(crate) fn layer_norm(x: &[f32], w: &[f32], b: &[f32], eps: f32, out: &mut [f32]) {
    layer_norm_rows(x, w, b, eps, 0..x.len(), out)
}

/// Elements `rows` of [`layer_norm`] (the statistics over all of `x`): `out[i]` is element
/// `rows.start + i`, bit-identical to the whole LayerNorm's.
pub(crate) fn layer_norm_rows(x: &[f32], w: &[f32], b: &[f32], eps: f32, rows: Range<usize>, out: &mut [f32]) {
    let n = x.len() as f32;
    let mut acc = [0.0f32; LANES];
    let cx = x.chunks_exact(LANES);
    let mut tail = 0.0;
    for v in cx.remainder() {
        tail += v;
    }
    for c in cx {
        for i in 0..LANES {
            acc[i] += c[i];
        }
    }
    let mean = (acc.iter().sum::<f32>() + tail) / n;
    let mut acc = [0.0f32; LANES];
    let cx = x.chunks_exact(LANES);
    let mut tail = 0.0;
    for v in cx.remainder() {
        tail += (v - mean) * (v - mean);
    }
    for c in cx {
        for i in 0..LANES {
            acc[i] += (c[i] - mean) * (c[i] - mean);
        }
    }
    let var = (acc.iter().sum::<f32>() + tail) / n;
    let inv = 1.0 / (var + eps).sqrt();
    let (x, w, b) = (&x[rows.clone()], &w[rows.clone()], &b[rows]);
    for i in 0..out.len() {
        out[i] = (x[i] - mean) * inv * w[i] + b[i];
    }
}

extern "C" {
    // The C library's erff (glibc, musl, the MSVC UCRT and macOS libSystem all have it);
    // Rust's std has no erf, and PyTorch's exact GELU needs one.
    fn erff(x: f32) -> f32;
}

/// Exact GELU, `x * 0.5 * (1 + erf(x / sqrt 2))` (PyTorch's default `nn.GELU()`), in place.
pub(crate) fn gelu_erf(x: &mut [f32]) {
    for v in x.iter_mut() {
        // SAFETY: erff is a pure function of a float, defined for every input.
        let e = unsafe { erff(*v * std::f32::consts::FRAC_1_SQRT_2) };
        *v = *v * 0.5 * (1.0 + e);
    }
}

/// Softmax in place (max-subtracted, so large logits do not overflow).
pub(crate) fn softmax(x: &mut [f32]) {
    let max = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0;
    for v in x.iter_mut() {
        *v = (*v - max).exp();
        sum += *v;
    }
    let inv = 1.0 / sum;
    for v in x.iter_mut() {
        *v *= inv;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn matrices(rows: usize, cols: usize) -> (Vec<f32>, [Matrix; 2]) {
        let q: Vec<i8> = (0..rows * cols).map(|i| ((i * 37 % 255) as i32 - 127) as i8).collect();
        let scale: Vec<f32> = (0..rows).map(|r| 0.01 * (r + 1) as f32).collect();
        let w: Vec<f32> = (0..rows * cols).map(|i| f32::from(q[i]) * scale[i / cols]).collect();
        (w.clone(), [Matrix::F32 { rows, cols, w }, Matrix::I8 { rows, cols, q, scale }])
    }

    #[test]
    fn gemv_f32_and_i8_agree_with_a_naive_product() {
        // Shapes that exercise the 4-row blocks, the leftover rows and every column tail.
        for (rows, cols) in [(5, 19), (1, 1), (4, 16), (7, 33), (9, 64), (13, 200), (3, 7)] {
            let (w, ms) = matrices(rows, cols);
            let x: Vec<f32> = (0..cols).map(|c| (c as f32 * 0.37).sin()).collect();
            let bias: Vec<f32> = (0..rows).map(|r| r as f32).collect();
            let naive: Vec<f32> =
                (0..rows).map(|r| (0..cols).map(|c| w[r * cols + c] * x[c]).sum::<f32>() + bias[r]).collect();
            for (m, isa) in ms
                .iter()
                .flat_map(|m| [Isa::Portable, Isa::Avx2, Isa::Avx512].map(|i| (m, i)))
                .filter(|(_, i)| *i <= super::isa())
            {
                let mut y = vec![0.0; rows];
                gemv_with(isa, m.into(), &x, Some(&bias), 0..rows, &mut y);
                for (a, b) in y.iter().zip(&naive) {
                    assert!((a - b).abs() < 1e-4 * (1.0 + b.abs()), "{rows}x{cols}: {a} vs {b}");
                }
                for n in 1..=4 {
                    let xs: Vec<f32> = (0..n).flat_map(|j| x.iter().map(move |v| v * (j + 1) as f32)).collect();
                    let mut ys = vec![0.0; n * rows];
                    gemm_with(isa, m.into(), &xs, n, Some(&bias), 0..rows, &mut ys);
                    for j in 0..n {
                        for r in 0..rows {
                            let want = (naive[r] - bias[r]) * (j + 1) as f32 + bias[r];
                            let got = ys[j * rows + r];
                            assert!((got - want).abs() < 1e-4 * (1.0 + want.abs()), "gemm n {n}: {got} vs {want}");
                        }
                    }
                }
            }
        }
        for n in [0, 1, 7, 8, 15, 16, 17, 40] {
            let a: Vec<f32> = (0..n).map(|i| i as f32 * 0.5 - 3.0).collect();
            let b: Vec<f32> = (0..n).map(|i| (i as f32).cos()).collect();
            let want: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            assert!((dot(&a, &b) - want).abs() < 1e-4 * (1.0 + want.abs()));
            assert!((portable::dot(&a, &b) - want).abs() < 1e-4 * (1.0 + want.abs()));
        }
    }

    /// The batched GEMV gives each input the bits of a GEMV of it alone, for every group
    /// size (1 to 13 inputs: the groups of 6, 4, 3, 2, 1), row part and column tail.
    #[test]
    fn many_inputs_get_the_bits_of_one() {
        for (rows, cols) in [(5, 19), (13, 200), (8, 48), (31, 64), (2, 7), (9, 257), (4, 16)] {
            let (_, ms) = matrices(rows, cols);
            let bias: Vec<f32> = (0..rows).map(|r| r as f32 * 0.3 - 1.0).collect();
            for m in &ms {
                for n in 1..=13 {
                    let xs: Vec<f32> = (0..n * cols).map(|c| (c as f32 * 0.11).cos() * 2.0).collect();
                    for r in [0..rows, rows / 4 * 4..rows] {
                        let mut ys = vec![0.0; n * r.len()];
                        gemv_rows_many(m.into(), &xs, n, Some(&bias), r.clone(), &mut ys);
                        for j in 0..n {
                            let mut one = vec![0.0; r.len()];
                            gemv_rows(m.into(), &xs[j * cols..(j + 1) * cols], Some(&bias), r.clone(), &mut one);
                            let got = &ys[j * r.len()..(j + 1) * r.len()];
                            assert_eq!(
                                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                                one.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                                "{rows}x{cols}, n {n}, input {j}, rows {r:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn row_parts_are_bit_identical_to_the_whole_product() {
        for (rows, cols) in [(5, 19), (13, 200), (16, 33), (31, 64), (2, 7), (130, 47)] {
            let (_, ms) = matrices(rows, cols);
            let x: Vec<f32> = (0..cols).map(|c| (c as f32 * 0.37).sin()).collect();
            let xs: Vec<f32> = (0..4 * cols).map(|c| (c as f32 * 0.11).cos()).collect();
            let bias: Vec<f32> = (0..rows).map(|r| r as f32 * 0.3).collect();
            for (m, isa) in ms
                .iter()
                .flat_map(|m| [Isa::Portable, Isa::Avx2, Isa::Avx512].map(|i| (m, i)))
                .filter(|(_, i)| *i <= super::isa())
            {
                let mut whole = vec![0.0; rows];
                gemv_with(isa, m.into(), &x, Some(&bias), 0..rows, &mut whole);
                let mut whole4 = vec![0.0; 4 * rows];
                gemm_with(isa, m.into(), &xs, 4, Some(&bias), 0..rows, &mut whole4);
                for block in [4, 8, 12, rows] {
                    let mut got = Vec::new();
                    let mut got4 = vec![0.0; 4 * rows];
                    for r in (0..rows).step_by(block).map(|a| a..(a + block).min(rows)) {
                        let mut y = vec![0.0; r.len()];
                        gemv_with(isa, m.into(), &x, Some(&bias), r.clone(), &mut y);
                        got.extend(y);
                        let mut y4 = vec![0.0; 4 * r.len()];
                        gemm_with(isa, m.into(), &xs, 4, Some(&bias), r.clone(), &mut y4);
                        for j in 0..4 {
                            got4[j * rows + r.start..j * rows + r.end]
                                .copy_from_slice(&y4[j * r.len()..(j + 1) * r.len()]);
                        }
                    }
                    let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&got), bits(&whole), "{isa:?} {rows}x{cols} in blocks of {block}");
                    assert_eq!(bits(&got4), bits(&whole4), "{isa:?} gemm {rows}x{cols} in blocks of {block}");
                }
            }
        }
        // The row-at-a-time AVX2 f32 kernel sums every row as the 4-row body does.
        #[cfg(target_arch = "x86_64")]
        if super::isa() >= Isa::Avx2 {
            for (rows, cols) in [(5, 19), (13, 200), (16, 33), (31, 64), (2, 7), (130, 47), (9, 1024)] {
                let (w, _) = matrices(rows, cols);
                let x: Vec<f32> = (0..cols).map(|c| (c as f32 * 0.37).sin()).collect();
                let (mut a, mut b) = (vec![0.0f32; rows], vec![0.0f32; rows]);
                // SAFETY: AVX2 detected; rows*cols weights, cols inputs.
                unsafe {
                    avx2::gemv_f32(&w, cols, &x, &mut a);
                    avx2::gemv_f32_by_blocks(&w, cols, &x, &mut b);
                }
                assert_eq!(
                    a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "{rows}x{cols}"
                );
            }
        }
        let x: Vec<f32> = (0..37).map(|i| (i as f32).sin() * 3.0).collect();
        let w: Vec<f32> = (0..37).map(|i| 1.0 + i as f32 * 0.01).collect();
        let mut whole = vec![0.0; 37];
        layer_norm(&x, &w, &w, 1e-5, &mut whole);
        let mut part = vec![0.0; 17];
        layer_norm_rows(&x, &w, &w, 1e-5, 20..37, &mut part);
        assert_eq!(part, whole[20..]);
    }

    #[test]
    fn layer_norm_softmax_and_gelu_match_their_definitions() {
        let x = [1.0f32, 2.0, 4.0, -3.0];
        let mut out = [0.0; 4];
        layer_norm(&x, &[1.0; 4], &[0.5; 4], 1e-5, &mut out);
        let mean = out.iter().sum::<f32>() / 4.0;
        let var = out.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / 4.0;
        assert!((mean - 0.5).abs() < 1e-6 && (var - 1.0).abs() < 1e-3, "{mean} {var}");

        let mut p = [1000.0f32, 1000.0, 0.0];
        softmax(&mut p);
        assert!((p[0] - 0.5).abs() < 1e-6 && p[2] == 0.0);

        let mut g = [0.0f32, 1.0, -1.0, 3.0];
        gelu_erf(&mut g);
        // PyTorch: gelu(1) = 0.8413447, gelu(-1) = -0.1586553, gelu(3) = 2.9959502
        for (a, b) in g.iter().zip([0.0, 0.841_344_7, -0.158_655_3, 2.995_950_2]) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
    }
}

/// Throughput of the GEMV bodies on a matrix far larger than the caches (run with
/// `cargo test --release --lib gemv_throughput -- --ignored --nocapture`).
#[cfg(test)]
mod throughput {
    use super::*;

    #[test]
    #[ignore]
    fn gemv_throughput() {
        let (rows, cols) = (4096 * 6, 1024); // 100 MB as f32, 25 MB as int8
        let x: Vec<f32> = (0..cols).map(|c| (c as f32).sin()).collect();
        let mut y = vec![0.0; rows];
        let mf = Matrix::F32 { rows, cols, w: vec![0.01; rows * cols] };
        let mq = Matrix::I8 { rows, cols, q: vec![3; rows * cols], scale: vec![0.01; rows] };
        for m in [&mf, &mq] {
            for isa in [Isa::Avx512, Isa::Avx2, Isa::Portable].into_iter().filter(|i| *i <= super::isa()) {
                let mut best = f64::MAX;
                for _ in 0..8 {
                    let t = std::time::Instant::now();
                    gemv_with(isa, m.into(), &x, None, 0..rows, &mut y);
                    best = best.min(t.elapsed().as_secs_f64());
                }
                println!(
                    "{isa:?} {}: {:.2} ms, {:.1} GB/s",
                    if matches!(m, Matrix::F32 { .. }) { "f32" } else { "i8" },
                    best * 1e3,
                    m.bytes() as f64 / best / 1e9
                );
            }
        }
    }
}
