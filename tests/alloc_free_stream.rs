//! The whole generation loop allocates nothing after the first token: once a stream's first
//! frames are out, its worker (token step, sampler, decoder, frame assembly and the
//! contact-consistency stage, which is on by default, ring push,
//! parking on a full ring) and the polling host allocate nothing until the stream ends.
//! Publishing over shared memory adds iceoryx2's one allocation per sample. Counted on every thread of the process (tests/alloc_counter), so this binary
//! holds one test only. Runs the native paths of the bundle `COMGRASP_PARITY_BUNDLE` names
//! (default models/tiny; scripts/test_all.sh also runs models/default, whose streams use
//! the decoder's second thread and overlap the step), which must carry native weights
//! (tract allocates per run).
mod alloc_counter;
mod bundle_support;

use alloc_counter::count_allocs_all_threads;
use bundle_support::tiny_dir;
use comgrasp::engine::StreamConfig;
use comgrasp::Bundle;
use comgrasp::{CoordinateSystem, Engine, EngineConfig, Frame, PollResult};

/// Polls without blocking until the stream ends; returns the frames received.
fn drain(s: &mut comgrasp::Stream, f: &mut Frame) -> (u64, PollResult) {
    let mut n = 0;
    loop {
        match s.poll(f) {
            PollResult::Frame => n += 1,
            PollResult::Pending => std::hint::spin_loop(),
            other => return (n, other),
        }
    }
}

#[test]
fn stream_allocates_nothing_after_the_first_token() {
    let dir = tiny_dir();
    let m = Bundle::load(&dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display())).manifest.clone();
    let (l_max, per_token) = (m.l_max as u32, m.frames_per_token as u64);
    // Plain; with FK in another basis; publishing every frame over shared memory too.
    let publish = format!("allocfree{}", std::process::id());
    let runs = [
        (false, CoordinateSystem::CG_COORDS_NATIVE, None),
        (true, CoordinateSystem::CG_COORDS_UNITY, None),
        (false, CoordinateSystem::CG_COORDS_NATIVE, Some(publish)),
    ];
    for (fk, coords, publish_name) in runs {
        // A ring smaller than a chunk: the worker also parks and is unparked by polls.
        let cfg = EngineConfig {
            bundle_path: Some(dir.clone()),
            coordinate_system: coords,
            enable_fk: fk,
            ring_capacity: 7,
            publish_name: publish_name.clone(),
            ..Default::default()
        };
        let engine = Engine::new(cfg).unwrap();
        // The full length: every step runs and the last chunk is forced (the path that
        // emits a held frame and a whole chunk together).
        let opts = StreamConfig { min_len: Some(l_max), max_len: Some(l_max), seed: Some(7), ..Default::default() };
        let mut s = engine.start("A woman drinks from the mug", opts).unwrap();
        let mut f = Frame::default();
        // The first token: text encoding and the per-stream model state are made here.
        while f.frame_index < 1 {
            match s.poll(&mut f) {
                PollResult::Frame | PollResult::Pending => {}
                other => panic!("before the first frames: {other:?} {:?}", s.error()),
            }
        }
        let published = |e: &Engine| e.publisher_stats().map_or(0, |p| p.frames_published + p.events_published);
        let before = published(&engine);
        let ((frames, end), allocs) = count_allocs_all_threads(|| drain(&mut s, &mut f));
        let samples = published(&engine) - before;
        assert_eq!(end, PollResult::End, "{:?}", s.error());
        assert_eq!(f.is_last, 1);
        let expected = u64::from(l_max) * per_token;
        assert_eq!(f.frame_index + 1, expected, "the stream did not run its full length");
        assert!(frames + 2 >= expected - per_token, "only {frames} frames counted");
        let what =
            format!("{allocs} allocations over {frames} frames (fk {fk}, {coords:?}, publishing {publish_name:?})");
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
