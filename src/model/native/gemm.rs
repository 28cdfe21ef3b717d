//! Multi-position matrix products for the native decoder: `Y = W X` for a few positions
//! (1 to 16) at once, so each weight row is read (and, for int8 rows, widened to f32) once
//! per block of positions instead of once per position as repeated GEMVs would.
//!
//! The input positions are rows of `x` at a stride `xs` that may be *smaller* than the
//! row length: a causal convolution's im2col is then free, the window of position `p` being
//! the contiguous `x[p * xs .. p * xs + cols]` of a time-major buffer (see
//! `decoder_conv`).
//!
//! x86-64 with AVX2 + FMA (detected at run time) gets a register-blocked kernel (2 rows x
//! 4 positions of 8-lane accumulators); other targets a portable loop over
//! [`kernels::dot`]/[`kernels::dot_i8`]. Results equal the naive product up to fp32
//! rounding (summation order), which is all the parity tolerance asks.
//!
//! Every output is summed in the same order whatever `npos` and the block shape are (one
//! position goes through the same tiles, not a separate GEMV, and every tile reduces its
//! lanes with the same tree), so a position's result does not depend on how many are
//! computed with it: the decoder gives the same bits decoding tokens one at a time or
//! several at once (`NativeDecoder::decode_with`).
use super::kernels::{self, Isa, MatRef};
#[cfg(test)]
use super::weights::Matrix;

/// `y[p * ys + r] = W[r] · x[p * xs .. p * xs + cols] (+ bias[r])` for `p < npos`,
/// `r < rows` (`W = m`, int8 rows times their scale). Panics if a slice is too short
/// (caller bug; the decoder sizes every buffer at load).
pub(crate) fn gemm(m: MatRef<'_>, x: &[f32], xs: usize, npos: usize, bias: Option<&[f32]>, y: &mut [f32], ys: usize) {
    let (rows, cols) = (m.rows(), m.cols());
    if npos == 0 || rows == 0 {
        return;
    }
    assert!(x.len() >= (npos - 1) * xs + cols, "gemm: x has {} values, needs {}", x.len(), (npos - 1) * xs + cols);
    assert!(ys >= rows && y.len() >= (npos - 1) * ys + rows, "gemm: y too short");
    if let Some(b) = bias {
        assert_eq!(b.len(), rows, "gemm: bias length");
    }
    #[cfg(target_arch = "x86_64")]
    {
        let isa = kernels::isa();
        if isa >= Isa::Avx512 {
            // SAFETY: the CPU has AVX-512F (detected); every index the kernel reads or
            // writes is inside the bounds asserted above.
            unsafe { x86::gemm512(m, x, xs, npos, bias, y, ys) };
            return;
        }
        if isa >= Isa::Avx2 {
            // SAFETY: as above, with AVX2 and FMA.
            unsafe { x86::gemm(m, x, xs, npos, bias, y, ys) };
            return;
        }
    }
    portable(m, x, xs, npos, bias, y, ys);
}

fn portable(m: MatRef<'_>, x: &[f32], xs: usize, npos: usize, bias: Option<&[f32]>, y: &mut [f32], ys: usize) {
    let (rows, cols) = (m.rows(), m.cols());
    for p in 0..npos {
        let xp = &x[p * xs..p * xs + cols];
        let yp = &mut y[p * ys..p * ys + rows];
        match m {
            MatRef::F32 { w, .. } => {
                for (r, o) in yp.iter_mut().enumerate() {
                    *o = kernels::dot(&w[r * cols..(r + 1) * cols], xp);
                }
            }
            MatRef::I8 { q, scale, .. } => {
                for (r, o) in yp.iter_mut().enumerate() {
                    *o = kernels::dot_i8(&q[r * cols..(r + 1) * cols], xp) * scale[r];
                }
            }
        }
        if let Some(b) = bias {
            for (o, b) in yp.iter_mut().zip(b) {
                *o += b;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
mod x86 {
    use std::arch::x86_64::*;

    use super::MatRef;

    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_movehdup_ps(s));
        _mm_cvtss_f32(s)
    }

    /// One weight element type: how 8 of them become an f32 vector.
    macro_rules! kernel {
        ($name:ident, $tile:ident, $elem:ty, $load8:ident) => {
            /// R rows x P positions, all columns; returns the raw dot products.
            #[target_feature(enable = "avx2,fma")]
            #[inline]
            unsafe fn $tile<const R: usize, const P: usize>(
                w: *const $elem,
                cols: usize,
                r0: usize,
                x: *const f32,
                xs: usize,
                p0: usize,
            ) -> [[f32; P]; R] {
                let mut acc = [[_mm256_setzero_ps(); P]; R];
                let n8 = cols & !7;
                let mut c = 0;
                while c < n8 {
                    let mut wv = [_mm256_setzero_ps(); R];
                    for i in 0..R {
                        wv[i] = $load8(w.add((r0 + i) * cols + c));
                    }
                    for p in 0..P {
                        let xv = _mm256_loadu_ps(x.add((p0 + p) * xs + c));
                        for i in 0..R {
                            acc[i][p] = _mm256_fmadd_ps(wv[i], xv, acc[i][p]);
                        }
                    }
                    c += 8;
                }
                let mut out = [[0.0f32; P]; R];
                for i in 0..R {
                    for p in 0..P {
                        let mut s = hsum(acc[i][p]);
                        for cc in n8..cols {
                            s += (*w.add((r0 + i) * cols + cc) as f32) * *x.add((p0 + p) * xs + cc);
                        }
                        out[i][p] = s;
                    }
                }
                out
            }

            #[target_feature(enable = "avx2,fma")]
            unsafe fn $name(
                w: *const $elem,
                scale: Option<&[f32]>,
                rows: usize,
                cols: usize,
                x: *const f32,
                xs: usize,
                npos: usize,
                bias: Option<&[f32]>,
                y: *mut f32,
                ys: usize,
            ) {
                let mut r = 0;
                while r + 2 <= rows {
                    let mut p = 0;
                    while p + 4 <= npos {
                        store::<2, 4>($tile::<2, 4>(w, cols, r, x, xs, p), r, p, scale, bias, y, ys);
                        p += 4;
                    }
                    if p + 2 <= npos {
                        store::<2, 2>($tile::<2, 2>(w, cols, r, x, xs, p), r, p, scale, bias, y, ys);
                        p += 2;
                    }
                    if p < npos {
                        store::<2, 1>($tile::<2, 1>(w, cols, r, x, xs, p), r, p, scale, bias, y, ys);
                    }
                    r += 2;
                }
                if r < rows {
                    for p in 0..npos {
                        store::<1, 1>($tile::<1, 1>(w, cols, r, x, xs, p), r, p, scale, bias, y, ys);
                    }
                }
            }
        };
    }

    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn load8_i8(p: *const i8) -> __m256 {
        _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64(p as *const __m128i)))
    }

    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn load8_f32(p: *const f32) -> __m256 {
        _mm256_loadu_ps(p)
    }

    kernel!(gemm_i8, tile_i8, i8, load8_i8);
    kernel!(gemm_f32, tile_f32, f32, load8_f32);

    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn load16_i8(p: *const i8) -> __m512 {
        _mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(_mm_loadu_si128(p as *const __m128i)))
    }

    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn load16_f32(p: *const f32) -> __m512 {
        _mm512_loadu_ps(p)
    }

    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn half(v: __m512) -> __m256 {
        _mm256_add_ps(_mm512_castps512_ps256(v), _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(v))))
    }

    /// The sums of 8 vectors' lanes, `[sum a[0], ..., sum a[7]]` (a shuffle tree instead
    /// of 8 separate reductions).
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn hsum8(a: [__m512; 8]) -> [f32; 8] {
        let h01 = _mm256_hadd_ps(half(a[0]), half(a[1]));
        let h23 = _mm256_hadd_ps(half(a[2]), half(a[3]));
        let h45 = _mm256_hadd_ps(half(a[4]), half(a[5]));
        let h67 = _mm256_hadd_ps(half(a[6]), half(a[7]));
        let h0123 = _mm256_hadd_ps(h01, h23);
        let h4567 = _mm256_hadd_ps(h45, h67);
        let s =
            _mm256_add_ps(_mm256_permute2f128_ps::<0x20>(h0123, h4567), _mm256_permute2f128_ps::<0x31>(h0123, h4567));
        let mut out = [0.0f32; 8];
        _mm256_storeu_ps(out.as_mut_ptr(), s);
        out
    }

    /// AVX-512 (32 registers): tiles of 3 rows x 8 positions (24 accumulators) or 4 x 4.
    macro_rules! kernel512 {
        ($name:ident, $tile:ident, $elem:ty, $load16:ident) => {
            #[target_feature(enable = "avx512f")]
            #[inline]
            unsafe fn $tile<const R: usize, const P: usize>(
                w: *const $elem,
                cols: usize,
                r0: usize,
                x: *const f32,
                xs: usize,
                p0: usize,
            ) -> [[f32; P]; R] {
                let mut acc = [[_mm512_setzero_ps(); P]; R];
                let n16 = cols & !15;
                let mut c = 0;
                while c < n16 {
                    let mut wv = [_mm512_setzero_ps(); R];
                    for i in 0..R {
                        wv[i] = $load16(w.add((r0 + i) * cols + c));
                    }
                    for p in 0..P {
                        let xv = _mm512_loadu_ps(x.add((p0 + p) * xs + c));
                        for i in 0..R {
                            acc[i][p] = _mm512_fmadd_ps(wv[i], xv, acc[i][p]);
                        }
                    }
                    c += 16;
                }
                let mut out = [[0.0f32; P]; R];
                for i in 0..R {
                    // one reduction tree for up to 8 positions' sums, the same tree
                    // whatever P is (npos-invariant results)
                    let v: [__m512; 8] = std::array::from_fn(|p| if p < P { acc[i][p] } else { _mm512_setzero_ps() });
                    let s = hsum8(v);
                    out[i][..P].copy_from_slice(&s[..P]);
                    for p in 0..P {
                        let mut s = out[i][p];
                        for cc in n16..cols {
                            s += (*w.add((r0 + i) * cols + cc) as f32) * *x.add((p0 + p) * xs + cc);
                        }
                        out[i][p] = s;
                    }
                }
                out
            }

            #[target_feature(enable = "avx512f")]
            unsafe fn $name(
                w: *const $elem,
                scale: Option<&[f32]>,
                rows: usize,
                cols: usize,
                x: *const f32,
                xs: usize,
                npos: usize,
                bias: Option<&[f32]>,
                y: *mut f32,
                ys: usize,
            ) {
                macro_rules! rows_of {
                    ($r:literal, $p:literal, $p0:expr) => {{
                        let mut r = 0;
                        while r + $r <= rows {
                            store::<$r, $p>($tile::<$r, $p>(w, cols, r, x, xs, $p0), r, $p0, scale, bias, y, ys);
                            r += $r;
                        }
                        while r < rows {
                            store::<1, $p>($tile::<1, $p>(w, cols, r, x, xs, $p0), r, $p0, scale, bias, y, ys);
                            r += 1;
                        }
                    }};
                }
                let mut p = 0;
                while p + 8 <= npos {
                    rows_of!(3, 8, p);
                    p += 8;
                }
                if p + 4 <= npos {
                    rows_of!(4, 4, p);
                    p += 4;
                }
                if p + 2 <= npos {
                    rows_of!(4, 2, p);
                    p += 2;
                }
                if p < npos {
                    rows_of!(4, 1, p);
                }
            }
        };
    }

    #[inline(always)]
    unsafe fn store<const R: usize, const P: usize>(
        out: [[f32; P]; R],
        r0: usize,
        p0: usize,
        scale: Option<&[f32]>,
        bias: Option<&[f32]>,
        y: *mut f32,
        ys: usize,
    ) {
        for i in 0..R {
            let s = scale.map_or(1.0, |s| s[r0 + i]);
            let b = bias.map_or(0.0, |b| b[r0 + i]);
            for p in 0..P {
                *y.add((p0 + p) * ys + r0 + i) = out[i][p] * s + b;
            }
        }
    }

    kernel512!(gemm512_i8, tile512_i8, i8, load16_i8);
    kernel512!(gemm512_f32, tile512_f32, f32, load16_f32);

    /// # Safety
    /// AVX-512F is available; the bounds `super::gemm` asserts hold.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn gemm512(
        m: MatRef<'_>,
        x: &[f32],
        xs: usize,
        npos: usize,
        bias: Option<&[f32]>,
        y: &mut [f32],
        ys: usize,
    ) {
        let (rows, cols) = (m.rows(), m.cols());
        match m {
            MatRef::F32 { w, .. } => {
                gemm512_f32(w.as_ptr(), None, rows, cols, x.as_ptr(), xs, npos, bias, y.as_mut_ptr(), ys)
            }
            MatRef::I8 { q, scale, .. } => {
                gemm512_i8(q.as_ptr(), Some(scale), rows, cols, x.as_ptr(), xs, npos, bias, y.as_mut_ptr(), ys)
            }
        }
    }

    /// # Safety
    /// AVX2 and FMA are available; the bounds `super::gemm` asserts hold.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemm(
        m: MatRef<'_>,
        x: &[f32],
        xs: usize,
        npos: usize,
        bias: Option<&[f32]>,
        y: &mut [f32],
        ys: usize,
    ) {
        let (rows, cols) = (m.rows(), m.cols());
        match m {
            MatRef::F32 { w, .. } => {
                gemm_f32(w.as_ptr(), None, rows, cols, x.as_ptr(), xs, npos, bias, y.as_mut_ptr(), ys)
            }
            MatRef::I8 { q, scale, .. } => {
                gemm_i8(q.as_ptr(), Some(scale), rows, cols, x.as_ptr(), xs, npos, bias, y.as_mut_ptr(), ys)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(w: &[f32], rows: usize, cols: usize, x: &[f32], xs: usize, npos: usize, bias: &[f32]) -> Vec<f32> {
        let mut y = vec![0.0; npos * rows];
        for p in 0..npos {
            for r in 0..rows {
                y[p * rows + r] = (0..cols).map(|c| w[r * cols + c] * x[p * xs + c]).sum::<f32>() + bias[r];
            }
        }
        y
    }

    #[test]
    fn gemm_matches_the_naive_product_for_every_block_shape() {
        for (rows, cols, xs, npos) in [
            (5, 19, 7, 7),
            (8, 64, 32, 16),
            (3, 16, 16, 1),
            (7, 40, 20, 5),
            (1, 8, 8, 3),
            (10, 48, 48, 13),
            (4, 32, 40, 2),
        ] {
            let q: Vec<i8> = (0..rows * cols).map(|i| ((i * 37 % 255) as i32 - 127) as i8).collect();
            let scale: Vec<f32> = (0..rows).map(|r| 0.01 * (r + 1) as f32).collect();
            let w: Vec<f32> = (0..rows * cols).map(|i| f32::from(q[i]) * scale[i / cols]).collect();
            let x: Vec<f32> = (0..(npos - 1) * xs + cols).map(|c| (c as f32 * 0.37).sin()).collect();
            let bias: Vec<f32> = (0..rows).map(|r| r as f32 * 0.5).collect();
            let want = naive(&w, rows, cols, &x, xs, npos, &bias);
            for m in [
                Matrix::F32 { rows, cols, w: w.clone() },
                Matrix::I8 { rows, cols, q: q.clone(), scale: scale.clone() },
            ] {
                // output stride wider than rows: the untouched gap stays as it was
                let ys = rows + 2;
                let mut y = vec![-9.0; npos * ys];
                gemm((&m).into(), &x, xs, npos, Some(&bias), &mut y, ys);
                // every kernel this CPU has, not only the one gemm picks
                let mut ys_all = vec![y];
                let mut y2 = vec![-9.0; npos * ys];
                portable((&m).into(), &x, xs, npos, Some(&bias), &mut y2, ys);
                ys_all.push(y2);
                #[cfg(target_arch = "x86_64")]
                {
                    let isa = kernels::isa();
                    if isa >= Isa::Avx2 {
                        let mut y3 = vec![-9.0; npos * ys];
                        unsafe { x86::gemm((&m).into(), &x, xs, npos, Some(&bias), &mut y3, ys) };
                        ys_all.push(y3);
                    }
                    if isa >= Isa::Avx512 {
                        let mut y4 = vec![-9.0; npos * ys];
                        unsafe { x86::gemm512((&m).into(), &x, xs, npos, Some(&bias), &mut y4, ys) };
                        ys_all.push(y4);
                    }
                }
                for (k, y) in ys_all.iter().enumerate() {
                    for p in 0..npos {
                        for r in 0..rows {
                            let (a, c) = (y[p * ys + r], want[p * rows + r]);
                            assert!((a - c).abs() < 1e-4, "kernel {k}: {rows}x{cols} p{p} r{r}: {a} vs {c}");
                        }
                        assert_eq!(&y[p * ys + rows..p * ys + ys], &[-9.0, -9.0]);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod invariance {
    use super::*;

    /// Each position's result is the same bits whatever else is computed with it.
    #[test]
    fn results_do_not_depend_on_the_number_of_positions() {
        let (rows, cols, xs) = (11, 70, 35);
        let q: Vec<i8> = (0..rows * cols).map(|i| ((i * 53 % 251) as i32 - 125) as i8).collect();
        let scale: Vec<f32> = (0..rows).map(|r| 0.003 * (r + 1) as f32).collect();
        let w: Vec<f32> = (0..rows * cols).map(|i| (i as f32 * 0.71).cos()).collect();
        let bias: Vec<f32> = (0..rows).map(|r| r as f32 * 0.25 - 1.0).collect();
        let npos = 19; // every tile shape: 8, 4, 2 and 1 positions
        let x: Vec<f32> = (0..(npos - 1) * xs + cols).map(|c| (c as f32 * 0.37).sin() * 3.0).collect();
        for m in [Matrix::F32 { rows, cols, w }, Matrix::I8 { rows, cols, q, scale }] {
            let mut all = vec![0.0; npos * rows];
            gemm((&m).into(), &x, xs, npos, Some(&bias), &mut all, rows);
            for start in 0..npos {
                for n in 1..=(npos - start).min(9) {
                    let mut part = vec![0.0; n * rows];
                    gemm((&m).into(), &x[start * xs..], xs, n, Some(&bias), &mut part, rows);
                    let want = &all[start * rows..(start + n) * rows];
                    assert!(
                        part.iter().zip(want).all(|(a, b)| a.to_bits() == b.to_bits()),
                        "positions {start}..{}: computed {n} at once differ from {npos} at once",
                        start + n
                    );
                }
            }
        }
    }
}

#[cfg(test)]
mod speed {
    use super::*;

    /// `cargo test --release --lib gemm_speed -- --ignored --nocapture`: GMAC/s of the
    /// kernels on an L2-resident int8 matrix (printed only).
    #[test]
    #[ignore]
    fn gemm_speed() {
        let (rows, cols) = (512, 1024);
        let q: Vec<i8> = (0..rows * cols).map(|i| ((i * 37 % 255) as i32 - 127) as i8).collect();
        let m = Matrix::I8 { rows, cols, q, scale: vec![0.01; rows] };
        for npos in [1, 2, 4, 8, 16, 32, 64] {
            let x: Vec<f32> = (0..(npos + 1) * 512).map(|c| (c as f32 * 0.37).sin()).collect();
            let mut y = vec![0.0; npos * rows];
            let reps = 2000 / npos;
            let t = std::time::Instant::now();
            for _ in 0..reps {
                gemm((&m).into(), &x, 512, npos, None, &mut y, rows);
            }
            let s = t.elapsed().as_secs_f64();
            println!(
                "npos {npos:2}: {:.1} GMAC/s, {:.1} us/call",
                (reps * rows * cols * npos) as f64 / s / 1e9,
                s / reps as f64 * 1e6
            );
        }
    }
}
