//! The Rust API under the C ABI: Engine / Stream / PollResult / StreamCanceller.
mod common;

use std::sync::Arc;
use std::time::Duration;

use comgrasp::engine::{validate_text, StreamConfig};
use comgrasp::{Engine, EngineConfig, Error, Frame, PollResult};
use common::{factory, Counters};

fn engine(ring: usize, max: usize) -> (Engine, Arc<Counters>) {
    let counters = Arc::new(Counters::default());
    let cfg = EngineConfig { ring_capacity: ring, max_streams: max, ..Default::default() };
    (Engine::with_source_factory(cfg, factory(Arc::clone(&counters))).unwrap(), counters)
}

#[test]
fn stream_lifecycle() {
    let (e, counters) = engine(8, 2);
    let mut s = e.start("chunks=3", StreamConfig::default()).unwrap();
    assert_eq!(e.live_streams(), 1);
    let mut f = Frame::default();
    let mut n = 0;
    loop {
        match s.wait(&mut f, Duration::from_secs(10)) {
            PollResult::Frame => {
                assert_eq!(f.frame_index, n);
                n += 1;
            }
            PollResult::End => break,
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(n, 48);
    assert!(s.error().is_none());
    drop(s);
    assert_eq!(e.live_streams(), 0);
    assert_eq!(counters.sources_alive.load(std::sync::atomic::Ordering::SeqCst), 0);
}

#[test]
fn canceller_from_another_thread_and_errors() {
    let (e, _) = engine(4, 4);
    let mut s = e.start("chunks=100000 delay_ms=5 frames=1", StreamConfig::default()).unwrap();
    let c = s.canceller();
    let t = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(30));
        c.cancel();
    });
    let mut f = Frame::default();
    let r = loop {
        match s.wait(&mut f, Duration::from_secs(10)) {
            PollResult::Frame => {}
            other => break other,
        }
    };
    t.join().unwrap();
    assert_eq!(r, PollResult::Cancelled);
    assert!(s.is_cancelled());

    let mut s = e.start("chunks=5 fail_at=1", StreamConfig::default()).unwrap();
    let r = loop {
        match s.wait(&mut f, Duration::from_secs(10)) {
            PollResult::Frame => {}
            other => break other,
        }
    };
    assert_eq!(r, PollResult::Error);
    assert!(matches!(s.error(), Some(Error::Inference(_))));
}

#[test]
fn limits_and_validation() {
    let (e, _) = engine(4, 1);
    let _a = e.start("chunks=1", StreamConfig::default()).unwrap();
    assert!(matches!(e.start("chunks=1", StreamConfig::default()), Err(Error::LimitReached(_))));
    assert!(validate_text("").is_err());
    assert!(validate_text(" \n").is_err());
    assert!(validate_text(&"a".repeat(4097)).is_err());
    assert!(validate_text(&"a".repeat(4096)).is_ok());
    let bad = StreamConfig { temperature: Some(-0.5), ..Default::default() };
    assert!(matches!(e.start("x", bad), Err(Error::InvalidArgument(_))));
    for cfg in
        [EngineConfig { ring_capacity: 0, ..Default::default() }, EngineConfig { max_streams: 0, ..Default::default() }]
    {
        assert!(Engine::with_source_factory(cfg, factory(Arc::default())).is_err());
    }
    // Engine defaults merge under stream settings.
    let merged = StreamConfig { seed: Some(1), ..Default::default() }.or(&StreamConfig {
        seed: Some(2),
        top_k: Some(3),
        ..Default::default()
    });
    assert_eq!(merged, StreamConfig { seed: Some(1), top_k: Some(3), ..Default::default() });
}
