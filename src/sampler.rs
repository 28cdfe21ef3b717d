//! The cross-language deterministic token sampler (DESIGN §4).
//!
//! This is a bit-for-bit port of the Python reference
//! `training/src/comgrasp_train/models/sampling.py`; its module docstring is the
//! specification and this file follows it step by step. Same seed + same logits (bit
//! identical `f32`) => same tokens in PyTorch and in the engine, on every platform.
//!
//! Why it is exact: everything is IEEE-754 `f64` `+ - * /`, `floor` and comparisons (each
//! correctly rounded) plus wrapping `u64` arithmetic. Rust never contracts `a * b + c`
//! into a fused multiply-add (only an explicit `mul_add` does), and on every supported
//! target `f64` arithmetic is plain binary64 (SSE2 / NEON, no x87 extended precision).
//! `exp` is our own [`exp_det`] because libm `exp` differs by an ulp between platforms.
//! Sums are strictly sequential in token-id order, as `numpy.cumsum` is.
//!
//! Random numbers: one [`SplitMix64`] per sequence; at every step exactly four uniforms
//! are drawn, in the order global, body, lhand, rhand, *always* (also when greedy), so a
//! seed's stream stays aligned whatever the parameters.

use crate::error::{Error, Result};
use std::cmp::Ordering;

/// Smallest non-zero temperature (below it `x / t` can overflow the useful range).
pub const MIN_TEMPERATURE: f64 = 1e-4;
/// `exp_det(d)` returns exactly 0 below this.
pub const EXP_UNDERFLOW: f64 = -700.0;
/// 1 / ln 2, the `f64` nearest to it (= `std::f64::consts::LOG2_E`; spelled as the same
/// literal as the Python reference on purpose).
#[allow(clippy::approx_constant)]
pub const INV_LN2: f64 = 1.4426950408889634;
/// fdlibm `ln2_hi`: its low 32 bits are zero, so `k * LN2_HI` is exact for |k| < 2^20.
pub const LN2_HI: f64 = 0.6931471803691238;
/// fdlibm `ln2_lo` = ln 2 − `LN2_HI`.
pub const LN2_LO: f64 = 1.9082149292705877e-10;
/// 1/n!, n = 0..13, each the `f64` nearest to it (same literals as the Python reference;
/// they round-trip, so both languages get the same bits).
pub const EXP_COEFFS: [f64; 14] = [
    1.0,
    1.0,
    0.5,
    0.16666666666666666,
    0.041666666666666664,
    0.008333333333333333,
    0.001388888888888889,
    0.0001984126984126984,
    2.48015873015873e-05,
    2.7557319223985893e-06,
    2.755731922398589e-07,
    2.505210838544172e-08,
    2.08767569878681e-09,
    1.6059043836821613e-10,
];

/// Deterministic `exp(d)` for `d <= 0` (the sampler only calls it with `z - max z`).
///
/// `k = floor(d / ln2 + 1/2)`, `r = (d − k·ln2_hi) − k·ln2_lo` (Cody–Waite reduction,
/// |r| ≤ ln2/2), a degree-13 Taylor polynomial in Horner form (no FMA), times `2^k` built
/// from the exponent bits. Relative error vs the true `exp` is ~1e-16; the point is not
/// accuracy but that Python (`sampling.exp_det`) and Rust produce the same bits.
/// `exp_det(0) == 1` exactly; `d < -700` gives 0; NaN gives NaN. Outside the domain
/// (`d > 0`) the same formula is used up to overflow (returns +inf for `d > ~709`).
pub fn exp_det(d: f64) -> f64 {
    if d.is_nan() {
        return f64::NAN;
    }
    if d < EXP_UNDERFLOW {
        return 0.0;
    }
    let k = (d * INV_LN2 + 0.5).floor();
    let r = (d - k * LN2_HI) - k * LN2_LO;
    let mut p = EXP_COEFFS[13];
    for n in (0..13).rev() {
        // Plain multiply then add: two roundings, exactly as numpy does it.
        p = p * r + EXP_COEFFS[n];
    }
    let k = k as i64; // in [-1010, 0] on the domain
    if k > 1023 {
        return f64::INFINITY;
    }
    // 2^k exactly (k >= -1010 > -1022, so always a normal number); p * 2^k is exact.
    p * f64::from_bits(((k + 1023) as u64) << 52)
}

/// SplitMix64 (Vigna), the engine's only random number generator.
///
/// `state += 0x9E3779B97F4A7C15; z = state; z = (z ^ z>>30) * 0xBF58476D1CE4E5B9;
/// z = (z ^ z>>27) * 0x94D049BB133111EB; return z ^ z>>31` (all wrapping mod 2^64).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A generator seeded with `seed` (the state is the seed itself). A C host's signed
    /// seed maps to `seed as u64` (mod 2^64), as the Python reference does.
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1): the top 53 bits times 2^-53 (both steps exact).
    pub fn next_uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}

/// Sampling parameters (DESIGN §4; the manifest's `sampling` defaults).
///
/// * `temperature`: 0 = greedy (arg max, lowest id on ties), else ≥ [`MIN_TEMPERATURE`].
/// * `top_k`: 0 = off; otherwise keep the `top_k` best allowed ids (ties: lower id).
/// * `min_len`: End is forbidden at steps `k < min_len`.
/// * `max_len`: End is forced at step `k == max_len`, so a sequence has at most
///   `max_len <= L_max` codes. (Python's `max_len=None` is `l_max` here.)
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SamplingParams {
    pub temperature: f64,
    pub top_k: u32,
    pub min_len: u32,
    pub max_len: u32,
}

impl SamplingParams {
    /// Validated parameters: `temperature` finite and 0 or ≥ 1e-4, `min_len <= max_len
    /// <= l_max`; anything else is [`Error::InvalidArgument`].
    pub fn new(temperature: f64, top_k: u32, min_len: u32, max_len: u32, l_max: u32) -> Result<Self> {
        let p = SamplingParams { temperature, top_k, min_len, max_len };
        p.validate(l_max)?;
        Ok(p)
    }

    /// The checks of [`SamplingParams::new`], for values built field by field.
    pub fn validate(&self, l_max: u32) -> Result<()> {
        self.check_temperature()?;
        if self.max_len > l_max {
            return Err(Error::InvalidArgument(format!(
                "max_len {} exceeds the model's L_max {}",
                self.max_len, l_max
            )));
        }
        if self.min_len > self.max_len {
            return Err(Error::InvalidArgument(format!("min_len {} exceeds max_len {}", self.min_len, self.max_len)));
        }
        Ok(())
    }

    fn check_temperature(&self) -> Result<()> {
        let t = self.temperature;
        if t == 0.0 || (t >= MIN_TEMPERATURE && t.is_finite()) {
            Ok(())
        } else {
            Err(Error::InvalidArgument(format!(
                "temperature must be 0 (greedy) or finite and >= {MIN_TEMPERATURE}, got {t}"
            )))
        }
    }
}

/// Samples one token per stream per step for one sequence.
///
/// Holds the sequence's RNG and reusable scratch; [`TokenSampler::sample_step`] does not
/// allocate once the scratch has the size of the largest vocabulary. The scratch is
/// sized in [`TokenSampler::new`] from the ids (`max(end, pad) + 1`, which is the
/// vocabulary size under the bundle convention End = J, Pad = J + 1 = V − 1); a larger
/// logits slice grows it once, on its first use.
#[derive(Clone, Debug)]
pub struct TokenSampler {
    rng: SplitMix64,
    params: SamplingParams,
    end_ids: [usize; 4],
    pad_ids: [usize; 4],
    /// Weights `w_i` of the current stream (length V).
    weights: Vec<f64>,
    /// Allowed ids, partially ordered by the top-k selection.
    order: Vec<u32>,
}

/// Stream order of the four components (and of the four uniforms of a step).
pub const STREAMS: [&str; 4] = ["global", "body", "lhand", "rhand"];

impl TokenSampler {
    /// `params` should come from [`SamplingParams::new`]; an invalid temperature is
    /// reported by [`TokenSampler::sample_step`]. `end_ids` / `pad_ids` per stream in the
    /// order global, body, lhand, rhand.
    pub fn new(seed: u64, params: SamplingParams, end_ids: [usize; 4], pad_ids: [usize; 4]) -> Self {
        let cap = end_ids.iter().chain(pad_ids.iter()).copied().max().unwrap_or(0) + 1;
        TokenSampler {
            rng: SplitMix64::new(seed),
            params,
            end_ids,
            pad_ids,
            weights: Vec::with_capacity(cap),
            order: Vec::with_capacity(cap),
        }
    }

    pub fn params(&self) -> &SamplingParams {
        &self.params
    }

    /// Tokens of step `k` (k = 0 is the step whose input is the condition token) for the
    /// four streams, from their logits (length V_i = J_i + 2 each).
    ///
    /// Draws exactly four uniforms first, whatever happens next. Errors:
    /// [`Error::Inference`] for a non-finite logit (the step graph produced garbage),
    /// [`Error::InvalidArgument`] for an invalid temperature, End/Pad ids outside the
    /// vocabulary, or no allowed id (a vocabulary of only End and Pad before `min_len`).
    ///
    /// The caller decides the end: if any stream's token equals its End id at step `k`,
    /// the sequence has `k` codes and the step's other tokens are discarded. At
    /// `k >= max_len` every stream returns its End id.
    pub fn sample_step(&mut self, k: usize, logits: [&[f32]; 4]) -> Result<[usize; 4]> {
        let mut u = [0.0f64; 4];
        for v in u.iter_mut() {
            *v = self.rng.next_uniform();
        }
        self.params.check_temperature()?;
        let mut out = [0usize; 4];
        for s in 0..4 {
            out[s] = self.sample_stream(s, k, logits[s], u[s])?;
        }
        Ok(out)
    }

    /// Rules 1-7 of the reference for one stream.
    fn sample_stream(&mut self, s: usize, k: usize, x: &[f32], u: f64) -> Result<usize> {
        let (end, pad) = (self.end_ids[s], self.pad_ids[s]);
        let v = x.len();
        if end >= v || pad >= v || end == pad {
            return Err(Error::InvalidArgument(format!(
                "{} stream: end id {end} / pad id {pad} do not fit a vocabulary of {v}",
                STREAMS[s]
            )));
        }
        if let Some(i) = x.iter().position(|l| !l.is_finite()) {
            return Err(Error::Inference(format!(
                "{} stream: non-finite logit {} at id {i}, step {k}",
                STREAMS[s], x[i]
            )));
        }
        // Rule 1: the allowed set.
        let (min_len, max_len) = (self.params.min_len as usize, self.params.max_len as usize);
        if k >= max_len {
            return Ok(end);
        }
        let end_allowed = k >= min_len;
        let allowed = |i: usize| i != pad && (end_allowed || i != end);
        let n_allowed = v - 1 - usize::from(!end_allowed);
        if n_allowed == 0 {
            return Err(Error::InvalidArgument(format!(
                "{} stream: no token allowed at step {k} (vocabulary of {v})",
                STREAMS[s]
            )));
        }

        // Rule 2: greedy, the first (lowest-id) maximum of float64(x).
        let t = self.params.temperature;
        if t == 0.0 {
            let mut best = usize::MAX;
            let mut best_x = f64::NEG_INFINITY;
            for (i, &xi) in x.iter().enumerate() {
                if allowed(i) && (best == usize::MAX || xi as f64 > best_x) {
                    best = i;
                    best_x = xi as f64;
                }
            }
            return Ok(best);
        }

        // Rule 3: z_i = float64(x_i) / t (recomputed where needed: same bits every time).
        let z = |i: usize| x[i] as f64 / t;

        // Rule 4: top-k. The k-th allowed id in the order (z descending, id ascending) is
        // the threshold; `partial_cmp` makes -0.0 == 0.0 as numpy's sort does, and the id
        // tie-break makes the order total, so the selection is unique.
        let top_k = self.params.top_k as usize;
        let threshold = if top_k > 0 && top_k < n_allowed {
            self.order.clear();
            self.order.extend((0..v as u32).filter(|&i| allowed(i as usize)));
            let cmp = |a: &u32, b: &u32| -> Ordering {
                let (za, zb) = (z(*a as usize), z(*b as usize));
                zb.partial_cmp(&za).unwrap_or(Ordering::Equal).then(a.cmp(b))
            };
            let (_, nth, _) = self.order.select_nth_unstable_by(top_k - 1, cmp);
            let id = *nth as usize;
            Some((z(id), id))
        } else {
            None
        };
        let keep = |i: usize| {
            allowed(i)
                && match threshold {
                    None => true,
                    Some((zt, it)) => {
                        let zi = z(i);
                        zi > zt || (zi == zt && i <= it)
                    }
                }
        };

        // Rule 5: m = max z over kept ids; w_i = exp_det(z_i - m).
        let mut m = f64::NEG_INFINITY;
        for i in 0..v {
            if keep(i) {
                let zi = z(i);
                if zi > m {
                    m = zi;
                }
            }
        }
        // Rule 6: c_i = c_{i-1} + w_i in id order; total = c_{V-1}.
        self.weights.clear();
        let mut total = 0.0f64;
        for i in 0..v {
            let w = if keep(i) { exp_det(z(i) - m) } else { 0.0 };
            self.weights.push(w);
            total += w;
        }
        // Rule 7: the first id with c_i > u * total; else the largest id with w_i > 0.
        let target = u * total;
        let mut c = 0.0f64;
        for (i, &w) in self.weights.iter().enumerate() {
            c += w;
            if c > target {
                return Ok(i);
            }
        }
        Ok(self.weights.iter().rposition(|&w| w > 0.0).unwrap_or(end))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TINY_VOCAB: [usize; 4] = [18, 34, 18, 26];
    const TINY_END: [usize; 4] = [16, 32, 16, 24];
    const TINY_PAD: [usize; 4] = [17, 33, 17, 25];

    #[test]
    fn splitmix64_reference_values() {
        // Vigna's splitmix64.c / Java SplittableRandom, as in test_sampling.py.
        let mut r = SplitMix64::new(0);
        assert_eq!(r.next_u64(), 0xE220A8397B1DCDAF);
        assert_eq!(r.next_u64(), 0x6E789E6AA1B965F4);
        let mut r = SplitMix64::new(1234567);
        let got: Vec<u64> = (0..5).map(|_| r.next_u64()).collect();
        assert_eq!(
            got,
            [6457827717110365317, 3203168211198807973, 9817491932198370423, 4593380528125082431, 16408922859458223821]
        );
        let mut r = SplitMix64::new(42);
        let got: Vec<u64> = (0..4).map(|_| r.next_u64()).collect();
        assert_eq!(got, [13679457532755275413, 2949826092126892291, 5139283748462763858, 6349198060258255764]);
        // Seed 7: models/tiny/parity/rng/u64.npy.
        let mut r = SplitMix64::new(7);
        let got: Vec<u64> = (0..8).map(|_| r.next_u64()).collect();
        assert_eq!(
            got,
            [
                7191089600892374487,
                309689372594955804,
                16616101746815609346,
                10753165928301472203,
                8346079845500723674,
                4601199455465548305,
                8632209307422871798,
                6051947643683389182
            ]
        );
        // Negative seeds wrap: -1 -> 2^64 - 1.
        let mut r = SplitMix64::new(-1i64 as u64);
        let mut s = 0u64.wrapping_sub(1).wrapping_add(0x9E3779B97F4A7C15);
        s = (s ^ (s >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        s = (s ^ (s >> 27)).wrapping_mul(0x94D049BB133111EB);
        assert_eq!(r.next_u64(), s ^ (s >> 31));
    }

    #[test]
    fn uniform_bits() {
        let mut r = SplitMix64::new(42);
        let u0 = r.next_uniform();
        let u1 = r.next_uniform();
        // float.fromhex("0x1.7bae644c5fd6dp-1"), float.fromhex("0x1.477f199d93378p-3")
        assert_eq!(u0.to_bits(), 0x3FE7BAE644C5FD6D);
        assert_eq!(u1.to_bits(), 0x3FC477F199D93378);
        assert_eq!(u0, (13679457532755275413u64 >> 11) as f64 * 2f64.powi(-53));
        let mut r = SplitMix64::new(9);
        for _ in 0..10_000 {
            let u = r.next_uniform();
            assert!((0.0..1.0).contains(&u));
        }
    }

    /// (input bits, output bits) computed with `sampling.exp_det` (numpy) in Python.
    const EXP_DET_BITS: [(u64, u64); 20] = [
        (0xbfe0000000000000, 0x3fe368b2fc6f960a), // -0.5
        (0xbff0000000000000, 0x3fd78b56362cef38), // -1.0
        (0xc00e000000000000, 0x3f981509354f0d29), // -3.75
        (0xc059000000000000, 0x36ea8c1f14e2af5d), // -100.0
        (0xbddb7cdfd9d7bdbb, 0x3feffffffff24190), // -1e-10
        (0xbfd62e42fefa39ef, 0x3fe6a09e667f3bcc), // -ln2/2
        (0xbfe62e42fefa39ef, 0x3fe0000000000000), // -ln2
        (0xc085df3333333333, 0x00d32132bfae6577), // -699.9
        (0xc085e00000000000, 0x00d14f2b0fb9307f), // -700.0
        (0xc042c00000000000, 0x3c8dd5c566301ec8), // -37.5
        (0xbefa36e2eb1c432d, 0x3fefffcb92651cce), // -2.5e-05
        (0xc028b0fcd32f707a, 0x3ed23d2b69da2f77), // -12.345678901234567
        (0xbff0a2b23f3bab73, 0x3fd6a09e667f3bcd), // -1.0397207708399179
        (0xc07f440000000000, 0x12d39634f3ad26d0), // -500.25
        (0xc03b4b4877e89e1c, 0x3d78a407ee433857), // random
        (0xc0013904927dbe42, 0x3fbdbc4020fb8dbd),
        (0xc021a0f85ea8ba18, 0x3f23797a6a80e538),
        (0xc01d7fde8ec8d075, 0x3f448a090b848baf),
        (0xc01c251b0fb560ec, 0x3f4cd1329286f4ea),
        (0xc0403dec8302f4bf, 0x3d01945176461297),
    ];

    #[test]
    fn exp_det_matches_python_bits() {
        for (d, e) in EXP_DET_BITS {
            let got = exp_det(f64::from_bits(d));
            assert_eq!(got.to_bits(), e, "exp_det({})", f64::from_bits(d));
        }
        assert_eq!(exp_det(0.0), 1.0);
        assert_eq!(exp_det(-0.0), 1.0);
        for d in [-700.5, -1e300, f64::NEG_INFINITY] {
            assert_eq!(exp_det(d), 0.0);
        }
        assert!(exp_det(f64::NAN).is_nan());
        // Accuracy against libm over the domain.
        let mut d = 0.0;
        while d > -700.0 {
            let (a, b) = (exp_det(d), d.exp());
            assert!(((a - b) / b).abs() < 1e-15, "{d}: {a} vs {b}");
            d -= 0.0137;
        }
    }

    /// `_integer_logits` of test_sampling.py for one batch element `b`.
    fn integer_logits(k: usize, b: usize) -> [Vec<f32>; 4] {
        std::array::from_fn(|s| {
            (0..TINY_VOCAB[s]).map(|i| ((i * 37 + k * 11 + s * 5 + b * 3) % 17) as f32 / 4.0 - 2.0).collect()
        })
    }

    fn run(params: SamplingParams, seed: u64, b: usize, steps: usize) -> Vec<[usize; 4]> {
        let mut s = TokenSampler::new(seed, params, TINY_END, TINY_PAD);
        (0..steps)
            .map(|k| {
                let lg = integer_logits(k, b);
                s.sample_step(k, [&lg[0], &lg[1], &lg[2], &lg[3]]).unwrap()
            })
            .collect()
    }

    #[test]
    fn regression_vectors_match_python() {
        // test_sampling.py REGRESSION: seeds 42 (b = 0) and 7 (b = 1), 11 steps.
        let p1 = SamplingParams::new(1.0, 0, 0, 18, 18).unwrap();
        let want_42 = [
            [11, 8, 2, 6],
            [0, 28, 4, 19],
            [8, 19, 3, 10],
            [9, 19, 8, 6],
            [1, 16, 3, 14],
            [15, 2, 11, 16],
            [0, 10, 13, 18],
            [13, 23, 16, 20],
            [10, 25, 10, 10],
            [0, 10, 13, 1],
            [8, 1, 5, 19],
        ];
        let want_7 = [
            [8, 1, 12, 16],
            [6, 10, 7, 7],
            [2, 12, 4, 23],
            [16, 30, 12, 11],
            [12, 10, 9, 18],
            [11, 1, 8, 9],
            [16, 31, 1, 10],
            [12, 14, 15, 1],
            [7, 10, 10, 15],
            [4, 32, 2, 5],
            [12, 28, 4, 1],
        ];
        assert_eq!(run(p1, 42, 0, 11), want_42);
        assert_eq!(run(p1, 7, 1, 11), want_7);

        let p2 = SamplingParams::new(0.7, 5, 2, 9, 18).unwrap();
        let want_42 = [
            [11, 9, 2, 6],
            [1, 28, 4, 19],
            [9, 19, 0, 10],
            [5, 15, 8, 6],
            [1, 11, 4, 14],
            [15, 2, 11, 16],
            [0, 10, 14, 18],
            [13, 23, 16, 20],
            [10, 31, 6, 5],
            [16, 32, 16, 24],
            [16, 32, 16, 24],
        ];
        let want_7 = [
            [9, 2, 12, 16],
            [6, 10, 3, 7],
            [2, 12, 4, 20],
            [16, 31, 12, 11],
            [12, 10, 9, 18],
            [13, 1, 10, 14],
            [16, 26, 1, 11],
            [12, 11, 15, 2],
            [8, 7, 10, 15],
            [16, 32, 16, 24],
            [16, 32, 16, 24],
        ];
        assert_eq!(run(p2, 42, 0, 11), want_42);
        assert_eq!(run(p2, 7, 1, 11), want_7);
    }

    /// One stream with a chosen uniform: drive `sample_stream` directly.
    fn pick(x: &[f32], u: f64, end: usize, pad: usize, k: usize, params: SamplingParams) -> usize {
        let mut s = TokenSampler::new(0, params, [end; 4], [pad; 4]);
        s.sample_stream(0, k, x, u).unwrap()
    }

    fn p(t: f64, top_k: u32, min_len: u32, max_len: u32) -> SamplingParams {
        SamplingParams { temperature: t, top_k, min_len, max_len }
    }

    #[test]
    fn inverse_cdf_boundaries() {
        // Ids 0..2 allowed (weights 1, 1, 1, total 3), id 3 plays Pad, End = 2.
        let x = [0.0f32; 4];
        let got: Vec<usize> = [0.0, 1.0 / 3.0 - 1e-12, 1.0 / 3.0, 2.0 / 3.0, 1.0 - 2f64.powi(-53)]
            .iter()
            .map(|&u| pick(&x, u, 2, 3, 0, p(1.0, 0, 0, 10)))
            .collect();
        assert_eq!(got, [0, 0, 1, 2, 2]);
    }

    #[test]
    fn greedy_lowest_id_on_ties_and_disallowed_never_chosen() {
        let x = [1.0f32, 3.0, 3.0, 9.0]; // id 3 = Pad, the largest
        assert_eq!(pick(&x, 0.99, 2, 3, 0, p(0.0, 0, 0, 10)), 1);
        // -0.0 and 0.0 are a tie: the lower id wins whichever sign it has.
        let x = [-1.0f32, -0.0, 0.0, 5.0];
        assert_eq!(pick(&x, 0.5, 0, 3, 0, p(0.0, 0, 0, 10)), 1);
        // Greedy ignores the seed (and top_k).
        let lg = integer_logits(3, 0);
        let mut a = TokenSampler::new(1, p(0.0, 3, 0, 18), TINY_END, TINY_PAD);
        let mut b = TokenSampler::new(99, p(0.0, 0, 0, 18), TINY_END, TINY_PAD);
        let l = [&lg[0][..], &lg[1], &lg[2], &lg[3]];
        assert_eq!(a.sample_step(0, l).unwrap(), b.sample_step(0, l).unwrap());
    }

    #[test]
    fn top_k_ties_keep_lower_ids() {
        let x = [2.0f32, 1.0, 2.0, 2.0, 0.0, -9.0]; // End 4, Pad 5
        let us: Vec<f64> = (0..7).map(|i| i as f64 * 0.999 / 6.0).collect();
        let mut seen2 = std::collections::BTreeSet::new();
        let mut seen1 = std::collections::BTreeSet::new();
        for &u in &us {
            seen2.insert(pick(&x, u, 4, 5, 0, p(1.0, 2, 0, 10)));
            seen1.insert(pick(&x, u, 4, 5, 0, p(1.0, 1, 0, 10)));
        }
        assert_eq!(seen2.into_iter().collect::<Vec<_>>(), [0, 2]);
        assert_eq!(seen1.into_iter().collect::<Vec<_>>(), [0]);
        // top_k >= number of allowed ids: off.
        assert_eq!(pick(&x, 0.999, 4, 5, 0, p(1.0, 5, 0, 10)), 4);
        assert_eq!(pick(&x, 0.999, 4, 5, 0, p(1.0, 0, 0, 10)), 4);
    }

    #[test]
    fn min_and_max_length_rules() {
        let (end, pad) = (4, 5);
        let x = [0.0f32, 0.0, 0.0, 0.0, 50.0, 60.0]; // End and Pad dominate
        assert_ne!(pick(&x, 0.5, end, pad, 1, p(1.0, 0, 2, 5)), end);
        assert_ne!(pick(&x, 0.5, end, pad, 1, p(0.0, 0, 2, 5)), end);
        assert_eq!(pick(&x, 0.5, end, pad, 2, p(1.0, 0, 2, 5)), end);
        let x = [9.0f32, 0.0, 0.0, 0.0, -50.0, 0.0];
        assert_eq!(pick(&x, 0.5, end, pad, 5, p(0.0, 0, 2, 5)), end);
        assert_eq!(pick(&x, 0.5, end, pad, 6, p(1.0, 3, 2, 5)), end);
        // max_len = 0: End at once.
        assert_eq!(pick(&x, 0.5, end, pad, 0, p(1.0, 0, 0, 0)), end);
        // Pad is never sampled, even with all the mass.
        let x = [-80.0f32, -80.0, -80.0, -80.0, -80.0, 80.0];
        for i in 0..20 {
            assert_ne!(pick(&x, i as f64 / 20.0, end, pad, 3, p(1.0, 0, 0, 5)), pad);
        }
    }

    #[test]
    fn temperature_and_top_k_shape_the_distribution() {
        // Frequencies over seeds 5..5+n, first uniform each (as in test_sampling.py).
        let n = 20_000;
        let x = [0.0f32, 1.0, 2.0, 0.5, 0.0, 0.0]; // End 4 forbidden (k < min_len), Pad 5
        let freq = |params: SamplingParams| {
            let mut f = [0.0f64; 4];
            for s in 0..n {
                let u = SplitMix64::new(5 + s as u64).next_uniform();
                f[pick(&x, u, 4, 5, 0, params)] += 1.0 / n as f64;
            }
            f
        };
        let base = freq(p(1.0, 0, 1, 10));
        let ez: Vec<f64> = [0.0f64, 1.0, 2.0, 0.5].iter().map(|v| (v - 2.0).exp()).collect();
        let sum: f64 = ez.iter().sum();
        for i in 0..4 {
            assert!((base[i] - ez[i] / sum).abs() < 0.015);
        }
        let hot = freq(p(5.0, 0, 1, 10));
        let cold = freq(p(0.2, 0, 1, 10));
        assert!(cold[2] > base[2] && base[2] > hot[2]);
        assert!(hot.iter().all(|&f| f > 0.15));
        let top2 = freq(p(1.0, 2, 1, 10));
        assert_eq!((top2[0], top2[3]), (0.0, 0.0));
        assert!((top2[2] - 1.0 / (1.0 + (-1.0f64).exp())).abs() < 0.015);
    }

    #[test]
    fn errors() {
        let mut s = TokenSampler::new(3, p(1.0, 0, 0, 18), TINY_END, TINY_PAD);
        let mut lg = integer_logits(0, 0);
        lg[2][5] = f32::NAN;
        let r = s.sample_step(0, [&lg[0], &lg[1], &lg[2], &lg[3]]);
        assert!(matches!(r, Err(Error::Inference(_))), "{r:?}");
        lg[2][5] = f32::INFINITY;
        assert!(matches!(s.sample_step(0, [&lg[0], &lg[1], &lg[2], &lg[3]]), Err(Error::Inference(_))));
        // The four uniforms were still drawn at each call: the stream stays aligned.
        let mut r = SplitMix64::new(3);
        for _ in 0..8 {
            r.next_u64();
        }
        assert_eq!(s.rng, r);
        // Greedy also rejects NaN.
        let mut g = TokenSampler::new(3, p(0.0, 0, 0, 18), TINY_END, TINY_PAD);
        lg[2][5] = f32::NAN;
        assert!(g.sample_step(0, [&lg[0], &lg[1], &lg[2], &lg[3]]).is_err());
        // Vocabulary too small for the ids.
        let lg = integer_logits(0, 0);
        let mut s = TokenSampler::new(3, p(1.0, 0, 0, 18), TINY_END, [17, 33, 17, 26]);
        assert!(matches!(s.sample_step(0, [&lg[0], &lg[1], &lg[2], &lg[3]]), Err(Error::InvalidArgument(_))));
        // Unvalidated bad temperature.
        let mut s = TokenSampler::new(3, p(1e-9, 0, 0, 18), TINY_END, TINY_PAD);
        assert!(matches!(s.sample_step(0, [&lg[0], &lg[1], &lg[2], &lg[3]]), Err(Error::InvalidArgument(_))));
    }

    #[test]
    fn params_validation() {
        assert!(SamplingParams::new(1.0, 8, 4, 18, 18).is_ok());
        assert!(SamplingParams::new(0.0, 0, 0, 0, 18).is_ok());
        assert!(SamplingParams::new(1e-4, 0, 0, 0, 18).is_ok());
        for t in [1e-9, -1.0, f64::NAN, f64::INFINITY, -0.5e-4] {
            assert!(matches!(SamplingParams::new(t, 0, 0, 10, 18), Err(Error::InvalidArgument(_))), "{t}");
        }
        assert!(matches!(SamplingParams::new(1.0, 0, 0, 19, 18), Err(Error::InvalidArgument(_))));
        assert!(matches!(SamplingParams::new(1.0, 0, 10, 5, 18), Err(Error::InvalidArgument(_))));
    }

    #[test]
    fn sample_step_does_not_grow_scratch() {
        let mut s = TokenSampler::new(1, p(0.9, 7, 0, 18), TINY_END, TINY_PAD);
        let (c0, c1) = (s.weights.capacity(), s.order.capacity());
        assert!(c0 >= 34 && c1 >= 34);
        for k in 0..18 {
            let lg = integer_logits(k, 1);
            s.sample_step(k, [&lg[0], &lg[1], &lg[2], &lg[3]]).unwrap();
        }
        assert_eq!((s.weights.capacity(), s.order.capacity()), (c0, c1));
    }
}
