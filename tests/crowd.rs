//! The crowd scheduler (src/crowd.rs) on the embedded default bundle and models/tiny:
//! streams started at staggered times get the frames they get alone, on the scheduler or
//! on a thread each; a cancel, a stream nobody polls, a dropped stream and a dropped engine
//! leave the others alone.
use std::time::{Duration, Instant};

mod bundle_support;

use comgrasp::config::{RuntimeOptions, Scheduling};
use comgrasp::{Engine, EngineConfig, Frame, PollResult, Stream, StreamConfig};

const PROMPTS: [&str; 3] = [
    "A woman drinks from the mug.",
    "Someone grabs the large cube with their left hand and lifts it up.",
    "The man passes the sphere from his right hand to his left.",
];

fn engine(bundle: Option<std::path::PathBuf>, scheduling: Scheduling, threads: Option<usize>) -> Engine {
    let runtime = RuntimeOptions { scheduling, scheduler_threads: threads, ..Default::default() };
    Engine::new(EngineConfig { bundle_path: bundle, max_streams: 64, runtime, ..Default::default() }).unwrap()
}

/// Odd streams are guided (classifier-free guidance: a second, null-condition member in
/// every batched step).
fn opts(i: usize) -> StreamConfig {
    StreamConfig {
        seed: Some(100 + i as u64),
        max_len: Some(6 + (i % 3) as u32),
        guidance: (i % 2 == 1).then_some(2.0),
        ..Default::default()
    }
}

/// Every frame of a stream, polled until it ends.
fn drain(s: &mut Stream) -> Vec<Frame> {
    let mut out = Vec::new();
    let mut f = Frame::default();
    loop {
        match s.wait(&mut f, Duration::from_secs(60)) {
            PollResult::Frame => out.push(f),
            PollResult::End => return out,
            other => panic!("stream {}: {other:?} {:?}", s.id(), s.error()),
        }
    }
}

/// The frames without the stream id (ids differ between engines).
fn bits(frames: &[Frame]) -> Vec<Vec<u8>> {
    frames
        .iter()
        .map(|f| {
            let mut g = *f;
            g.stream_id = 0;
            // SAFETY: Frame is a repr(C) struct of plain numbers; its bytes are initialized
            // (copied from a frame the engine wrote, padding included).
            unsafe { std::slice::from_raw_parts(&g as *const Frame as *const u8, std::mem::size_of::<Frame>()) }
                .to_vec()
        })
        .collect()
}

/// Streams alone on a thread of their own: the reference.
fn alone(bundle: Option<std::path::PathBuf>, n: usize) -> Vec<Vec<Vec<u8>>> {
    let e = engine(bundle, Scheduling::PerStream, None);
    (0..n).map(|i| bits(&drain(&mut e.start(PROMPTS[i % 3], opts(i)).unwrap()))).collect()
}

/// `n` streams on the crowd scheduler with `threads` threads, each started once the one
/// before it has produced its first frame (so they join batches at different positions),
/// polled round-robin by this thread.
fn staggered(bundle: Option<std::path::PathBuf>, n: usize, threads: usize) -> Vec<Vec<Vec<u8>>> {
    let e = engine(bundle, Scheduling::Crowd, Some(threads));
    assert_eq!(e.scheduler_threads(), Some(threads));
    let mut streams: Vec<(Stream, Vec<Frame>, bool)> = Vec::new();
    let mut f = Frame::default();
    let deadline = Instant::now() + Duration::from_secs(120);
    while streams.len() < n || streams.iter().any(|s| !s.2) {
        assert!(Instant::now() < deadline, "the crowd did not finish");
        let last_started = streams.last().is_none_or(|s| !s.1.is_empty() || s.2);
        if streams.len() < n && last_started {
            let i = streams.len();
            streams.push((e.start(PROMPTS[i % 3], opts(i)).unwrap(), Vec::new(), false));
        }
        for (s, frames, ended) in streams.iter_mut().filter(|s| !s.2) {
            match s.poll(&mut f) {
                PollResult::Frame => frames.push(f),
                PollResult::Pending => {}
                PollResult::End => *ended = true,
                other => panic!("stream {}: {other:?} {:?}", s.id(), s.error()),
            }
        }
        std::thread::yield_now();
    }
    streams.iter().map(|s| bits(&s.1)).collect()
}

/// The default bundle: native step (batched) and decoder, decode groups of 4.
#[test]
fn staggered_streams_get_the_frames_they_get_alone() {
    let n = 6;
    let reference = alone(None, n);
    for threads in [1, 2] {
        let got = staggered(None, n, threads);
        for i in 0..n {
            assert!(!reference[i].is_empty());
            assert_eq!(got[i].len(), reference[i].len(), "{threads} threads: stream {i}: frame count");
            let first = got[i].iter().zip(&reference[i]).position(|(a, b)| a != b);
            assert_eq!(first, None, "{threads} threads: stream {i}: first different frame");
        }
    }
}

/// models/tiny (decode group 1, other sizes), and a lone stream on the scheduler (which
/// also uses the models' helper threads).
#[test]
fn tiny_bundle_and_a_lone_stream() {
    let dir = Some(bundle_support::tiny_dir());
    let reference = alone(dir.clone(), 4);
    assert_eq!(staggered(dir.clone(), 4, 2), reference);
    let e = engine(dir, Scheduling::Auto, None);
    assert!(e.scheduler_threads().is_some(), "the crowd scheduler is the default");
    assert_eq!(bits(&drain(&mut e.start(PROMPTS[0], opts(0)).unwrap())), reference[0]);
    let unguided = StreamConfig { guidance: None, ..opts(1) };
    assert_ne!(bits(&drain(&mut e.start(PROMPTS[1], unguided).unwrap())), reference[1], "guidance changed nothing");
}

/// A cancelled stream, one nobody polls (a ring of 8 frames, full at once), one dropped
/// while running: the others run to their end, each cancel within a round.
#[test]
fn cancel_and_slow_hosts_touch_only_their_stream() {
    let runtime = RuntimeOptions { scheduling: Scheduling::Crowd, scheduler_threads: Some(1), ..Default::default() };
    let e = Engine::new(EngineConfig { ring_capacity: 8, max_streams: 16, runtime, ..Default::default() }).unwrap();
    let long = StreamConfig { seed: Some(1), min_len: Some(40), max_len: Some(40), ..Default::default() };
    let mut parked = e.start(PROMPTS[0], long.clone()).unwrap();
    let mut cancelled = e.start(PROMPTS[1], long.clone()).unwrap();
    let dropped = e.start(PROMPTS[2], long.clone()).unwrap();
    let mut others: Vec<Stream> = (0..3).map(|i| e.start(PROMPTS[i], opts(i)).unwrap()).collect();
    let mut f = Frame::default();
    assert_eq!(cancelled.wait(&mut f, Duration::from_secs(30)), PollResult::Frame);
    let t = Instant::now();
    cancelled.cancel();
    drop(dropped);
    assert_eq!(cancelled.poll(&mut f), PollResult::Cancelled);
    for s in &mut others {
        assert!(!drain(s).is_empty());
    }
    assert!(t.elapsed() < Duration::from_secs(30));
    // the stream nobody polled waited with a full ring and still has every frame
    assert_eq!(parked.poll(&mut f), PollResult::Frame);
    assert_eq!(f.frame_index, 0);
    let rest = drain(&mut parked);
    assert_eq!(rest.len() as u64 + 1, 40 * 16);
    assert_eq!(rest.last().map(|f| f.is_last), Some(1));
    drop(others);
    drop(parked);
    drop(cancelled);
    assert_eq!(e.live_streams(), 0);
}

/// Dropping the engine cancels what still runs and returns once the scheduler let go of
/// every stream; the streams stay valid.
#[test]
fn dropping_the_engine_cancels_the_crowd() {
    let e = engine(None, Scheduling::Crowd, Some(2));
    let long = StreamConfig { min_len: Some(40), max_len: Some(40), ..Default::default() };
    let mut streams: Vec<Stream> = (0..8).map(|i| e.start(PROMPTS[i % 3], long.clone()).unwrap()).collect();
    let mut f = Frame::default();
    assert_eq!(streams[0].wait(&mut f, Duration::from_secs(30)), PollResult::Frame);
    drop(e);
    for s in &mut streams {
        let r = loop {
            match s.poll(&mut f) {
                PollResult::Frame => {}
                r => break r,
            }
        };
        assert!(matches!(r, PollResult::Cancelled | PollResult::End), "{r:?}");
    }
}

/// A prompt many streams share is encoded once: the pipeline keeps the embeddings of its
/// last `KEEP_EMBEDDINGS` prompts (the same values the encoder gives), least recently used
/// forgotten first.
#[test]
fn repeated_prompts_are_encoded_once() {
    use comgrasp::generator::{Pipeline, KEEP_EMBEDDINGS};
    use std::sync::Arc;
    let config = EngineConfig::default();
    let bundle = comgrasp::Bundle::select(None, &config.runtime).unwrap();
    let pipe = Pipeline::new(Arc::clone(&bundle), &config).unwrap();
    let a = pipe.embedding(PROMPTS[0]).unwrap();
    assert_eq!(&a[..], &bundle.text.embed(PROMPTS[0]).unwrap()[..]);
    assert!(Arc::ptr_eq(&a, &pipe.embedding(PROMPTS[0]).unwrap()), "kept");
    let b = pipe.embedding(PROMPTS[1]).unwrap();
    assert_ne!(&a[..], &b[..]);
    // PROMPTS[0] used again (now the newest), then enough others to forget PROMPTS[1] only
    pipe.embedding(PROMPTS[0]).unwrap();
    for i in 0..KEEP_EMBEDDINGS - 1 {
        pipe.embedding(&format!("Someone picks up the mug, take {i}.")).unwrap();
    }
    assert!(Arc::ptr_eq(&a, &pipe.embedding(PROMPTS[0]).unwrap()), "the most recently used stays");
    let b2 = pipe.embedding(PROMPTS[1]).unwrap();
    assert!(!Arc::ptr_eq(&b, &b2), "the least recently used was forgotten");
    assert_eq!(&b[..], &b2[..]);
}
