//! How a stream schedules its work changes nothing but the time.
//!
//! * Overlap (`model::overlap`): on the default bundle (native step and decoder, two
//!   threads) the overlapped call gives bit-identical logits and frames to a decode
//!   followed by a step, and leaves both states untouched on bad input.
//! * Decode groups (`model::decode_group`): decoding G consecutive tokens in one call gives
//!   the same bits as G calls, on the native decoder (each weight read once per call) and
//!   on tract (one token per run), for every G up to `MAX_DECODE_GROUP`; bad groups are
//!   refused without touching the state.
//! * Whole streams with overlap on and off and every decode group give identical frames,
//!   including `is_last`, for sampled End (inside a group too) and the forced End of
//!   `max_len`.
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use comgrasp::bundle::N_STREAMS;
use comgrasp::engine::{SourceFactory, StreamConfig, StreamRequest};
use comgrasp::generator::{ChunkSource, Generator, Pipeline};
use comgrasp::model::overlap::{decode_and_step, decode_and_steps};
use comgrasp::model::{decode_group, DecoderBackend, DecoderModel, MAX_DECODE_GROUP};
use comgrasp::Bundle;
use comgrasp::{Engine, EngineConfig, Error, Frame, PollResult};

fn tiny_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/tiny")
}

fn default_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default")
}

fn load(dir: &Path) -> Arc<Bundle> {
    Bundle::load(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()))
}

/// Codes for step k: a fixed walk through every codebook (End and Pad are not codes).
fn codes(b: &Bundle, k: usize) -> [i64; N_STREAMS] {
    std::array::from_fn(|s| ((k * 37 + s * 11) % b.manifest.components[s].codebook_size) as i64)
}

#[test]
fn overlapped_decode_and_step_equal_the_two_calls_bit_for_bit() {
    let b = load(&default_dir());
    let emb = b.text.embed("A man passes the bowl.").unwrap();
    let (mut ds_a, mut ss_a) = (b.decoder.new_state(), b.step.new_state());
    let (mut ds_b, mut ss_b) = (b.decoder.new_state(), b.step.new_state());
    let (mut ds_c, mut ss_c) = (b.decoder.new_state(), b.step.new_state());
    let pad = b.manifest.pad_ids();
    for st in [&mut ss_a, &mut ss_b, &mut ss_c] {
        b.step.step(st, pad, 0, &emb).unwrap();
    }
    let n = b.decoder.chunk_len();
    let (mut fa, mut fb, mut fc) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for k in 0..24 {
        let c = codes(&b, k);
        // reference: the public calls one after the other
        b.decoder.decode(&mut ds_a, c, &mut fa).unwrap();
        let la: Vec<Vec<f32>> = b.step.step(&mut ss_a, c, k + 1, &emb).unwrap().iter().map(|l| l.to_vec()).collect();
        let lb = decode_and_step(&b.decoder, &mut ds_b, &[c], &mut fb, &b.step, &mut ss_b, k + 1, &emb, true).unwrap();
        let lb: Vec<Vec<f32>> = lb.iter().map(|l| l.to_vec()).collect();
        let lc = decode_and_step(&b.decoder, &mut ds_c, &[c], &mut fc, &b.step, &mut ss_c, k + 1, &emb, false).unwrap();
        let lc: Vec<Vec<f32>> = lc.iter().map(|l| l.to_vec()).collect();
        assert_eq!(fa, fb, "frames of token {k}, overlapped");
        assert_eq!(fa, fc, "frames of token {k}, one after the other");
        assert_eq!(la, lb, "logits of step {}, overlapped", k + 1);
        assert_eq!(la, lc, "logits of step {}, one after the other", k + 1);
        assert!(fa.iter().all(|v| v.is_finite()) && fa.iter().any(|&v| v != 0.0));
    }
    assert_eq!((ds_b.decoded(), ss_b.filled()), (24, 25));
}

#[test]
fn bad_input_changes_neither_state() {
    let b = load(&default_dir());
    let emb = b.text.embed("A woman drinks from the mug.").unwrap();
    let (mut ds, mut ss) = (b.decoder.new_state(), b.step.new_state());
    b.step.step(&mut ss, b.manifest.pad_ids(), 0, &emb).unwrap();
    let mut f = vec![0.0; b.decoder.chunk_len()];
    let good = codes(&b, 3);
    let mut bad_code = good;
    bad_code[1] = b.manifest.components[1].codebook_size as i64; // End is not a code
    let cases: Vec<(&str, [i64; N_STREAMS], usize, Vec<f32>, usize)> = vec![
        ("End id as a code", bad_code, 1, emb.clone(), f.len()),
        ("negative code", [-1, 0, 0, 0], 1, emb.clone(), f.len()),
        ("skipped position", good, 2, emb.clone(), f.len()),
        ("short embedding", good, 1, emb[..10].to_vec(), f.len()),
        ("NaN embedding", good, 1, vec![f32::NAN; emb.len()], f.len()),
        ("short frame buffer", good, 1, emb.clone(), f.len() - 1),
    ];
    let mut ahead = [[0i64; N_STREAMS]; 3];
    for (what, c, pos, e, len) in cases {
        for overlap in [true, false] {
            let err = decode_and_step(&b.decoder, &mut ds, &[c], &mut f[..len], &b.step, &mut ss, pos, &e, overlap);
            assert!(err.is_err(), "{what} (overlap {overlap}) was accepted");
            assert_eq!((ds.decoded(), ss.filled()), (0, 1), "{what} (overlap {overlap}) changed a state");
            let sample = |_: usize, _: [&[f32]; N_STREAMS]| Ok(Some(good));
            let err = decode_and_steps(
                &b.decoder,
                &mut ds,
                &[c],
                &mut f[..len],
                &b.step,
                &mut ss,
                pos,
                &e,
                &mut ahead,
                sample,
                overlap,
            );
            assert!(err.is_err(), "{what} (overlap {overlap}, next group's steps) was accepted");
            assert_eq!((ds.decoded(), ss.filled()), (0, 1), "{what} (overlap {overlap}, steps) changed a state");
        }
    }
    // and the states still work
    decode_and_step(&b.decoder, &mut ds, &[good], &mut f, &b.step, &mut ss, 1, &emb, true).unwrap();
    assert_eq!((ds.decoded(), ss.filled()), (1, 2));
}

/// Every frame of one stream (seeded), with overlap on or off and `group` tokens per decode.
fn stream_frames(b: &Arc<Bundle>, overlap: bool, group: usize, opts: &StreamConfig) -> Vec<Frame> {
    let config = EngineConfig { ring_capacity: 64, ..Default::default() };
    let pipe = Arc::new(Pipeline::new(Arc::clone(b), &config).unwrap().with_overlap(overlap).with_group(group));
    assert_eq!((pipe.overlap(), pipe.group()), (overlap, group));
    let factory: SourceFactory = Box::new(move |req: &StreamRequest<'_>| {
        Ok(Box::new(Generator::new(Arc::clone(&pipe), req)?) as Box<dyn ChunkSource>)
    });
    let engine = Engine::with_source_factory(config, factory).unwrap();
    let mut s = engine.start("A woman drinks from the mug.", opts.clone()).unwrap();
    let (mut f, mut out) = (Frame::default(), Vec::new());
    loop {
        match s.wait(&mut f, Duration::from_secs(120)) {
            PollResult::Frame => out.push(f),
            PollResult::End => return out,
            other => panic!("stream ended with {other:?}: {:?}", s.error()),
        }
    }
}

/// Stream options covering sampled End and the forced End of `max_len`.
fn end_cases() -> [StreamConfig; 3] {
    [
        StreamConfig { seed: Some(1), ..Default::default() },
        StreamConfig { seed: Some(2), temperature: Some(1.5), ..Default::default() },
        StreamConfig { seed: Some(3), min_len: Some(2), max_len: Some(5), ..Default::default() },
    ]
}

/// Asserts one stream's frames are whole chunks with exactly the final frame marked last;
/// returns the number of tokens.
fn tokens_of(frames: &[Frame], fpt: usize) -> usize {
    assert!(!frames.is_empty() && frames.len().is_multiple_of(fpt), "{} frames", frames.len());
    let last: Vec<usize> = frames.iter().enumerate().filter(|(_, f)| f.is_last != 0).map(|(i, _)| i).collect();
    assert_eq!(last, vec![frames.len() - 1], "exactly the final frame is marked last");
    frames.len() / fpt
}

#[test]
fn streams_with_and_without_overlap_give_the_same_frames() {
    let b = load(&default_dir());
    let fpt = b.manifest.frames_per_token;
    let group = Pipeline::new(Arc::clone(&b), &EngineConfig::default()).unwrap().group();
    let mut lengths = Vec::new();
    for opts in end_cases() {
        let on = stream_frames(&b, true, group, &opts);
        let off = stream_frames(&b, false, 1, &opts);
        assert_eq!(on, off, "seed {:?}: overlap + groups of {group} vs neither", opts.seed);
        lengths.push(tokens_of(&on, fpt));
    }
    assert_eq!(lengths[2], 5, "max_len forces End at step 5");
}

#[test]
fn streams_give_the_same_frames_for_every_decode_group() {
    let b = load(&tiny_dir());
    let fpt = b.manifest.frames_per_token;
    let mut ends_inside_a_group = false;
    for opts in end_cases() {
        let reference = stream_frames(&b, false, 1, &opts);
        let n = tokens_of(&reference, fpt);
        for group in [1, 2, 3, 4, MAX_DECODE_GROUP] {
            for overlap in [false, true] {
                let got = stream_frames(&b, overlap, group, &opts);
                assert_eq!(got, reference, "seed {:?}, groups of {group}, overlap {overlap}", opts.seed);
            }
            // after the first chunk, the groups cover tokens 1.., so a sequence of n tokens
            // ends inside a group when n - 1 is not a multiple of it
            ends_inside_a_group |= opts.max_len.is_none() && group > 1 && !(n - 1).is_multiple_of(group);
        }
    }
    assert!(ends_inside_a_group, "no case had its sampled End inside a group");
}

/// Decodes `tokens` as a stream does (the first alone, then groups of `group`).
fn decode_in_groups(d: &DecoderModel, tokens: &[[i64; N_STREAMS]], group: usize) -> Vec<f32> {
    let mut st = d.new_state();
    let n = d.chunk_len();
    let mut out = vec![0.0; tokens.len() * n];
    let mut k = 0;
    while k < tokens.len() {
        let g = decode_group::tokens_at(k, group).min(tokens.len() - k);
        d.decode_group(&mut st, &tokens[k..k + g], &mut out[k * n..(k + g) * n]).unwrap();
        k += g;
    }
    assert_eq!(st.decoded(), tokens.len());
    out
}

#[test]
fn grouped_decodes_equal_one_token_at_a_time_bit_for_bit() {
    for dir in [tiny_dir(), default_dir()] {
        let b = load(&dir);
        let tokens: Vec<[i64; N_STREAMS]> = (0..23).map(|k| codes(&b, k)).collect();
        for backend in [DecoderBackend::Native, DecoderBackend::Tract] {
            let d = DecoderModel::load_backend(b.origin(), &b.manifest, Some(backend)).unwrap();
            let one = decode_in_groups(&d, &tokens, 1);
            assert!(one.iter().all(|v| v.is_finite()) && one.iter().any(|&v| v != 0.0));
            for group in 2..=MAX_DECODE_GROUP {
                let got = decode_in_groups(&d, &tokens, group);
                let same = got.iter().zip(&one).all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "{}: {backend:?} decoder, groups of {group} differ from one by one", dir.display());
            }
        }
    }
}

#[test]
fn a_grouped_decode_overlaps_the_step_after_its_last_token() {
    let b = load(&default_dir());
    let emb = b.text.embed("A man passes the bowl.").unwrap();
    let pad = b.manifest.pad_ids();
    let n = b.decoder.chunk_len();
    let tokens: Vec<[i64; N_STREAMS]> = (0..4).map(|k| codes(&b, k)).collect();
    // reference: one decode per token, the step on the last
    let (mut ds, mut ss) = (b.decoder.new_state(), b.step.new_state());
    b.step.step(&mut ss, pad, 0, &emb).unwrap();
    let mut want = vec![0.0; 4 * n];
    for (t, o) in tokens.iter().zip(want.chunks_exact_mut(n)) {
        b.decoder.decode(&mut ds, *t, o).unwrap();
    }
    let want_logits: Vec<Vec<f32>> =
        b.step.step(&mut ss, tokens[3], 1, &emb).unwrap().iter().map(|l| l.to_vec()).collect();
    for overlap in [true, false] {
        let (mut ds, mut ss) = (b.decoder.new_state(), b.step.new_state());
        b.step.step(&mut ss, pad, 0, &emb).unwrap();
        let mut got = vec![0.0; 4 * n];
        let logits =
            decode_and_step(&b.decoder, &mut ds, &tokens, &mut got, &b.step, &mut ss, 1, &emb, overlap).unwrap();
        let logits: Vec<Vec<f32>> = logits.iter().map(|l| l.to_vec()).collect();
        assert_eq!(got, want, "frames, overlap {overlap}");
        assert_eq!(logits, want_logits, "logits, overlap {overlap}");
        assert_eq!(ds.decoded(), 4);
    }
}

#[test]
fn bad_groups_are_refused_and_change_nothing() {
    let b = load(&tiny_dir());
    let n = b.decoder.chunk_len();
    let good: Vec<[i64; N_STREAMS]> = (0..MAX_DECODE_GROUP + 1).map(|k| codes(&b, k)).collect();
    let mut bad_second = good[..3].to_vec();
    bad_second[1][2] = b.manifest.components[2].codebook_size as i64; // End is not a code
    let mut st = b.decoder.new_state();
    let mut out = vec![0.0; (MAX_DECODE_GROUP + 1) * n];
    let cases: [(&str, &[[i64; N_STREAMS]], usize); 4] = [
        ("no token", &good[..0], 0),
        ("more than MAX_DECODE_GROUP tokens", &good[..], good.len() * n),
        ("an End id in the second token", &bad_second[..], 3 * n),
        ("room for one chunk of two", &good[..2], n),
    ];
    for (what, tokens, len) in cases {
        let err = b.decoder.decode_group(&mut st, tokens, &mut out[..len]);
        assert!(matches!(err, Err(Error::InvalidArgument(_))), "{what}: {err:?}");
        assert_eq!(st.decoded(), 0, "{what} changed the state");
    }
    // the state is still at the start: the same frames as a fresh one
    let mut fresh = b.decoder.new_state();
    let mut a = vec![0.0; 2 * n];
    let mut c = vec![0.0; 2 * n];
    b.decoder.decode_group(&mut st, &good[..2], &mut a).unwrap();
    b.decoder.decode_group(&mut fresh, &good[..2], &mut c).unwrap();
    assert_eq!(a, c);
}
