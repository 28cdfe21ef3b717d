//! Replays the sampler parity vectors that Python recorded in the tiny bundle
//! (`models/tiny/parity/rng`, `parity/step`): same seed + same logits => same tokens.
//! A counting allocator also checks that `sample_step` does not allocate.

use comgrasp::sampler::{SamplingParams, SplitMix64, TokenSampler};

mod alloc_counter;
use alloc_counter::count_allocs;

#[test]
fn allocation_counter_works() {
    let (_, n) = count_allocs(|| std::hint::black_box(Vec::<u8>::with_capacity(16)));
    assert!(n > 0);
}

mod bundle_support;
use bundle_support::{load_f32, load_f64, load_u64, tiny_dir};

// The tiny bundle's End and Pad ids per stream (codebooks 16/32/16/24).
const END: [usize; 4] = [16, 32, 16, 24];
const PAD: [usize; 4] = [17, 33, 17, 25];
const STREAMS: [&str; 4] = ["global", "body", "lhand", "rhand"];

#[test]
fn rng_matches_python() {
    let u64s = load_u64(&tiny_dir(), "parity/rng/u64.npy");
    let unif = load_f64(&tiny_dir(), "parity/rng/uniform.npy");
    let mut r = SplitMix64::new(7);
    assert_eq!((0..8).map(|_| r.next_u64()).collect::<Vec<_>>(), u64s);
    let mut r = SplitMix64::new(7);
    let got: Vec<u64> = (0..8).map(|_| r.next_uniform().to_bits()).collect();
    assert_eq!(got, unif.iter().map(|u| u.to_bits()).collect::<Vec<_>>());
}

/// Steps 0..4 of each step case: the recorded logits (teacher-forced with the sampled
/// codes) and the manifest's sampling params (T 1.0, top-k 8, min_len 4, max_len 18,
/// seed 7) give back the codes PyTorch sampled. Greedy can only be checked at step 0
/// (later greedy steps saw other inputs).
#[test]
fn step_cases_replay_python_tokens() {
    for case in 0..2 {
        let loaded: Vec<(Vec<usize>, Vec<f32>)> =
            STREAMS.iter().map(|s| load_f32(&tiny_dir(), &format!("parity/step/case{case}_logits_{s}.npy"))).collect();
        let vocab: Vec<usize> = loaded.iter().map(|(shape, _)| *shape.last().unwrap()).collect();
        let logits: Vec<Vec<f32>> = loaded.into_iter().map(|(_, v)| v).collect();
        assert_eq!(vocab, [18, 34, 18, 26]);
        let steps = logits[0].len() / vocab[0];
        let tokens = load_u64(&tiny_dir(), &format!("parity/step/case{case}_tokens.npy"));
        let greedy = load_u64(&tiny_dir(), &format!("parity/step/case{case}_greedy_tokens.npy"));
        let row = |k: usize, s: usize| &logits[s][k * vocab[s]..(k + 1) * vocab[s]];

        let params = SamplingParams::new(1.0, 8, 4, 18, 18).unwrap();
        let mut sampler = TokenSampler::new(7, params, END, PAD);
        for k in 0..steps {
            let l = [row(k, 0), row(k, 1), row(k, 2), row(k, 3)];
            let (got, allocs) = count_allocs(|| sampler.sample_step(k, l).unwrap());
            assert_eq!(allocs, 0, "sample_step allocated");
            let want: Vec<usize> = tokens[k * 4..k * 4 + 4].iter().map(|&t| t as usize).collect();
            assert_eq!(got.to_vec(), want, "case {case} step {k}");
        }
        let mut g = TokenSampler::new(7, SamplingParams::new(0.0, 8, 4, 18, 18).unwrap(), END, PAD);
        let got = g.sample_step(0, [row(0, 0), row(0, 1), row(0, 2), row(0, 3)]).unwrap();
        let want: Vec<usize> = greedy[..4].iter().map(|&t| t as usize).collect();
        assert_eq!(got.to_vec(), want, "case {case} greedy step 0");
    }
}
