//! The whole generation loop allocates nothing after the first token: once a stream's first
//! frames are out, its worker (token step, sampler, decoder, frame assembly and the
//! contact-consistency stage, which is on by default, ring push,
//! parking on a full ring) and the polling host allocate nothing until the stream ends;
//! on a thread per stream, and on the crowd scheduler with six streams at once (batched
//! steps, the shard's rounds, rings that fill and are unparked by polls).
//! Publishing over shared memory adds iceoryx2's one allocation per sample. Counted on every thread of the process (tests/alloc_counter), so this binary
//! holds one test only. Runs the native paths of the bundle `COMGRASP_PARITY_BUNDLE` names
//! (default models/tiny; scripts/test_all.sh also runs models/default, whose streams use
//! the decoder's second thread and overlap the step), which must carry native weights
//! (tract allocates per run).
mod alloc_counter;
mod bundle_support;

use alloc_counter::count_allocs_all_threads;
use bundle_support::tiny_dir;
use comgrasp::config::{RuntimeOptions, Scheduling};
use comgrasp::engine::StreamConfig;
use comgrasp::Bundle;
use comgrasp::{CoordinateSystem, Engine, EngineConfig, Frame, PollResult};

#[test]
fn stream_allocates_nothing_after_the_first_token() {
    let dir = tiny_dir();
    let m = Bundle::load(&dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display())).manifest.clone();
    let (l_max, per_token) = (m.l_max as u32, m.frames_per_token as u64);
    // Plain; with FK in another basis; publishing every frame over shared memory too; a
    // thread per stream; a crowd of streams on the scheduler's two threads.
    let publish = format!("allocfree{}", std::process::id());
    let native = CoordinateSystem::CG_COORDS_NATIVE;
    let runs = [
        (false, native, None, Scheduling::Auto, 1),
        (true, CoordinateSystem::CG_COORDS_UNITY, None, Scheduling::Auto, 1),
        (false, native, Some(publish), Scheduling::Auto, 1),
        (false, native, None, Scheduling::PerStream, 1),
        (false, native, None, Scheduling::Crowd, 6),
    ];
    for (fk, coords, publish_name, scheduling, n) in runs {
        // A ring smaller than a chunk: the worker also parks and is unparked by polls.
        let cfg = EngineConfig {
            bundle_path: Some(dir.clone()),
            coordinate_system: coords,
            enable_fk: fk,
            ring_capacity: 7,
            publish_name: publish_name.clone(),
            runtime: RuntimeOptions { scheduling, scheduler_threads: Some(2), ..Default::default() },
            ..Default::default()
        };
        let engine = Engine::new(cfg).unwrap();
        // The full length: every step runs and the last chunk is forced (the path that
        // emits a held frame and a whole chunk together).
        let opts = |i: u64| StreamConfig {
            min_len: Some(l_max),
            max_len: Some(l_max),
            seed: Some(7 + i),
            ..Default::default()
        };
        let mut streams: Vec<_> =
            (0..n).map(|i| engine.start("A woman drinks from the mug", opts(i as u64)).unwrap()).collect();
        let mut frames: Vec<Frame> = vec![Frame::default(); n];
        // The first token: text encoding and the per-stream model state are made here.
        for (s, f) in streams.iter_mut().zip(&mut frames) {
            while f.frame_index < 1 {
                match s.poll(f) {
                    PollResult::Frame | PollResult::Pending => {}
                    other => panic!("before the first frames: {other:?} {:?}", s.error()),
                }
            }
        }
        let published = |e: &Engine| e.publisher_stats().map_or(0, |p| p.frames_published + p.events_published);
        let before = published(&engine);
        let (ends, allocs) = count_allocs_all_threads(|| drain(&mut streams, &mut frames));
        let samples = published(&engine) - before;
        let expected = u64::from(l_max) * per_token;
        for (i, ((count, end), f)) in ends.iter().zip(&frames).enumerate() {
            assert_eq!(*end, PollResult::End, "stream {i}: {:?}", streams[i].error());
            assert_eq!(f.is_last, 1);
            assert_eq!(f.frame_index + 1, expected, "stream {i} did not run its full length");
            assert!(count + 2 >= expected - per_token, "stream {i}: only {count} frames counted");
        }
        let what = format!(
            "{allocs} allocations over {n} stream(s) (fk {fk}, {coords:?}, publishing {publish_name:?}, {scheduling:?})"
        );
        if publish_name.is_none() {
            assert_eq!(allocs, 0, "{what}");
        } else {
            // iceoryx2 0.10's `loan_uninit` boxes a small shared state per sample (an Arc in
            // SampleMutUninit::new): one allocation per sample published in the window
            // (frames and the ENDED event, counted by the publisher), nothing of ours.
            assert!(allocs as u64 <= samples, "{what}, {samples} samples published");
        }
    }
}

/// Polls every stream without blocking, round-robin, until all end; the frames each
/// received and how it ended (`last`: each stream's latest frame). Allocation-free.
fn drain(streams: &mut [comgrasp::Stream], last: &mut [Frame]) -> [(u64, PollResult); 8] {
    let mut out = [(0, PollResult::Pending); 8];
    let mut left = streams.len();
    while left > 0 {
        for (i, s) in streams.iter_mut().enumerate() {
            if out[i].1 != PollResult::Pending {
                continue;
            }
            match s.poll(&mut last[i]) {
                PollResult::Frame => out[i].0 += 1,
                PollResult::Pending => std::hint::spin_loop(),
                other => {
                    out[i].1 = other;
                    left -= 1;
                }
            }
        }
    }
    out
}
