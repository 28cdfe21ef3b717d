//! Overlapping chunk k's decode with step k+1 (`model::overlap`) changes nothing but the
//! time: on the default bundle (native step and decoder, two threads) the overlapped call
//! gives bit-identical logits and frames to a decode followed by a step, leaves both states
//! untouched on bad input, and whole streams with overlap on and off give identical frames
//! (including `is_last`, which the overlapped stream knows without holding a frame back).
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use comgrasp::bundle::{Bundle, N_STREAMS};
use comgrasp::engine::{SourceFactory, StreamConfig, StreamRequest};
use comgrasp::generator::{ChunkSource, Generator, Pipeline};
use comgrasp::model::overlap::decode_and_step;
use comgrasp::{Engine, EngineConfig, Frame, PollResult};

fn default_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default")
}

fn load(dir: &PathBuf) -> Arc<Bundle> {
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
        let lb = decode_and_step(&b.decoder, &mut ds_b, c, &mut fb, &b.step, &mut ss_b, k + 1, &emb, true).unwrap();
        let lb: Vec<Vec<f32>> = lb.iter().map(|l| l.to_vec()).collect();
        let lc = decode_and_step(&b.decoder, &mut ds_c, c, &mut fc, &b.step, &mut ss_c, k + 1, &emb, false).unwrap();
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
    for (what, c, pos, e, len) in cases {
        for overlap in [true, false] {
            let err = decode_and_step(&b.decoder, &mut ds, c, &mut f[..len], &b.step, &mut ss, pos, &e, overlap);
            assert!(err.is_err(), "{what} (overlap {overlap}) was accepted");
            assert_eq!((ds.decoded(), ss.filled()), (0, 1), "{what} (overlap {overlap}) changed a state");
        }
    }
    // and the states still work
    decode_and_step(&b.decoder, &mut ds, good, &mut f, &b.step, &mut ss, 1, &emb, true).unwrap();
    assert_eq!((ds.decoded(), ss.filled()), (1, 2));
}

/// Every frame of one stream (seeded), with overlap on or off.
fn stream_frames(b: &Arc<Bundle>, overlap: bool, opts: &StreamConfig) -> Vec<Frame> {
    let config = EngineConfig { ring_capacity: 64, ..Default::default() };
    let pipe = Arc::new(Pipeline::new(Arc::clone(b), &config).unwrap().with_overlap(overlap));
    assert_eq!(pipe.overlap(), overlap);
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

#[test]
fn streams_with_and_without_overlap_give_the_same_frames() {
    let b = load(&default_dir());
    let fpt = b.manifest.frames_per_token;
    // sampled End (short sequences from a few seeds), and the forced End of max_len
    let mut lengths = Vec::new();
    for opts in [
        StreamConfig { seed: Some(1), ..Default::default() },
        StreamConfig { seed: Some(2), temperature: Some(1.5), ..Default::default() },
        StreamConfig { seed: Some(3), min_len: Some(2), max_len: Some(5), ..Default::default() },
    ] {
        let on = stream_frames(&b, true, &opts);
        let off = stream_frames(&b, false, &opts);
        assert!(!on.is_empty() && on.len() % fpt == 0, "{} frames", on.len());
        assert_eq!(on, off, "seed {:?}", opts.seed);
        let last: Vec<usize> = on.iter().enumerate().filter(|(_, f)| f.is_last != 0).map(|(i, _)| i).collect();
        assert_eq!(last, vec![on.len() - 1], "exactly the final frame is marked last");
        lengths.push(on.len() / fpt);
    }
    assert_eq!(lengths[2], 5, "max_len forces End at step 5");
}
