//! The shared-memory C ABI in one process: an engine with a publish name (scripted source,
//! so frames are known) and `cg_subscriber_*` handles on the same name. The cross-process
//! behaviour (other processes, a killed subscriber, a late joiner) is in tests/shm_ipc.rs.
mod common;

use std::ffi::CString;
use std::ptr::{null, null_mut};
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::{EngineConfig, Frame};
use common::*;

/// A name no other test (or test run) uses.
fn unique(tag: &str) -> String {
    format!("t-{}-{tag}", std::process::id())
}

fn open(name: &str, buffer_frames: u32) -> *mut cg_subscriber {
    let mut cfg = cg_subscriber_config { struct_size: 0, buffer_frames: 0, reserved: 0 };
    assert_eq!(unsafe { cg_subscriber_config_init(&mut cfg) }, cg_status::CG_OK);
    cfg.buffer_frames = buffer_frames;
    let c = CString::new(name).unwrap();
    let mut sub = null_mut();
    let st = unsafe { cg_subscriber_open(c.as_ptr(), &cfg, &mut sub) };
    assert_eq!(st, cg_status::CG_OK, "cg_subscriber_open({name}): {}", last_error());
    sub
}

fn publishing_engine(name: &str, ring: usize) -> TestEngine {
    TestEngine::with_config(EngineConfig { ring_capacity: ring, publish_name: Some(name.into()), ..Default::default() })
}

fn publisher_stats(e: &TestEngine) -> cg_publisher_stats {
    let mut s = cg_publisher_stats::default();
    assert_eq!(unsafe { cg_engine_publisher_stats(e.handle, &mut s) }, cg_status::CG_OK, "{}", last_error());
    s
}

fn stats(sub: *mut cg_subscriber) -> cg_subscriber_stats {
    let mut s = cg_subscriber_stats::default();
    assert_eq!(unsafe { cg_subscriber_get_stats(sub, &mut s) }, cg_status::CG_OK, "{}", last_error());
    s
}

/// Receives until `n` frames arrived (or `limit` passed).
fn receive_n(sub: *mut cg_subscriber, n: usize, limit: Duration) -> Vec<Frame> {
    let t0 = Instant::now();
    let mut got = Vec::new();
    let mut f = Frame::default();
    while got.len() < n {
        match unsafe { cg_subscriber_receive(sub, &mut f) } {
            cg_status::CG_OK => got.push(f),
            cg_status::CG_PENDING => {
                assert!(t0.elapsed() < limit, "only {} of {n} frames after {limit:?}", got.len());
                std::thread::sleep(Duration::from_micros(100));
            }
            other => panic!("cg_subscriber_receive: {other:?}: {}", last_error()),
        }
    }
    got
}

fn events(sub: *mut cg_subscriber) -> Vec<cg_stream_event> {
    let mut out = Vec::new();
    let mut e = cg_stream_event { stream_id: 0, frame_count: 0, kind: 0, fps: 0.0, text: [0; CG_EVENT_TEXT_BYTES] };
    while unsafe { cg_subscriber_receive_event(sub, &mut e) } == cg_status::CG_OK {
        out.push(e);
    }
    out
}

/// Events until `n` arrived (or `limit` passed): a stream's ENDED event is published by its
/// worker as it finishes, which may be just after the poller saw `CG_END`.
fn events_n(sub: *mut cg_subscriber, n: usize, limit: Duration) -> Vec<cg_stream_event> {
    let t0 = Instant::now();
    let mut out = events(sub);
    while out.len() < n && t0.elapsed() < limit {
        std::thread::sleep(Duration::from_millis(1));
        out.extend(events(sub));
    }
    out
}

#[test]
fn every_polled_frame_is_published_identically_with_events() {
    let name = unique("same");
    let e = publishing_engine(&name, 64);
    let sub = open(&name, 256);
    assert_eq!(publisher_stats(&e).subscribers, 1);

    let s = e.start("chunks=5 frames=16");
    let (n, st) = drain_checked(s, 1);
    assert_eq!((n, st), (80, cg_status::CG_END));
    let got = receive_n(sub, 80, Duration::from_secs(10));
    for (i, f) in got.iter().enumerate() {
        assert_eq!(*f, expected_frame(1, i as u64, i == 79), "frame {i}");
    }
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_subscriber_receive(sub, &mut f) }, cg_status::CG_PENDING, "nothing more");

    let ev = events_n(sub, 2, Duration::from_secs(10));
    let kinds: Vec<u32> = ev.iter().map(|e| e.kind).collect();
    assert_eq!(kinds, [CG_STREAM_EVENT_STARTED, CG_STREAM_EVENT_ENDED]);
    assert_eq!((ev[0].stream_id, ev[0].frame_count, ev[1].frame_count), (1, 0, 80));
    let text = std::ffi::CStr::from_bytes_until_nul(&ev[0].text).unwrap();
    assert_eq!(text.to_str().unwrap(), "chunks=5 frames=16");

    let p = publisher_stats(&e);
    assert_eq!((p.frames_published, p.frames_skipped, p.events_published), (80, 0, 2));
    let st = stats(sub);
    assert_eq!((st.frames_received, st.frames_dropped, st.events_received, st.publishers), (80, 0, 2, 1));

    // A cancelled stream announces itself with the frames it had generated.
    let s2 = e.start("chunks=1000 frames=16 delay_ms=2");
    receive_n(sub, 16, Duration::from_secs(10));
    assert_eq!(unsafe { cg_cancel(s2) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_stream_destroy(s2) }, cg_status::CG_OK);
    let ev = events(sub);
    assert_eq!(ev.len(), 2, "{ev:?}");
    assert_eq!((ev[1].kind, ev[1].stream_id), (CG_STREAM_EVENT_CANCELLED, 2));
    assert!(ev[1].frame_count >= 16);

    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_subscriber_close(sub) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_subscriber_close(sub) }, cg_status::CG_ERR_INVALID_HANDLE, "double close");
    assert_eq!(unsafe { cg_subscriber_receive(sub, &mut f) }, cg_status::CG_ERR_INVALID_HANDLE, "use after close");
    e.destroy();
}

#[test]
fn a_slow_subscriber_loses_its_oldest_frames_counted_and_never_slows_the_producer() {
    let name = unique("slow");
    let e = publishing_engine(&name, 1024);
    let slow = open(&name, 4);
    let fast = open(&name, 256);
    // A first stream both read as it goes: nothing lost.
    let s0 = e.start("chunks=1 frames=4");
    assert_eq!(drain_checked(s0, 1), (4, cg_status::CG_END));
    for sub in [slow, fast] {
        receive_n(sub, 4, Duration::from_secs(10));
        assert_eq!(stats(sub).frames_dropped, 0);
    }
    // 240 frames while the slow subscriber reads nothing: the producer finishes anyway.
    let s = e.start("chunks=15 frames=16");
    let (n, st) = drain_checked(s, 2);
    assert_eq!((n, st), (240, cg_status::CG_END));
    // The one with room for them all gets everything in order.
    let got = receive_n(fast, 240, Duration::from_secs(10));
    assert!(got.iter().enumerate().all(|(i, f)| f.frame_index == i as u64 && f.stream_id == 2));
    assert_eq!(stats(fast).frames_dropped, 0);
    // The slow one keeps the newest 4, and knows it lost the 236 before them.
    let kept = receive_n(slow, 4, Duration::from_secs(1));
    let idx: Vec<u64> = kept.iter().map(|f| f.frame_index).collect();
    assert_eq!(idx, [236, 237, 238, 239]);
    let st = stats(slow);
    assert_eq!((st.frames_received, st.frames_dropped), (8, 236));
    assert_eq!(publisher_stats(&e).frames_skipped, 0);
    for sub in [slow, fast] {
        assert_eq!(unsafe { cg_subscriber_close(sub) }, cg_status::CG_OK);
    }
    for st in [s0, s] {
        assert_eq!(unsafe { cg_stream_destroy(st) }, cg_status::CG_OK);
    }
    e.destroy();
}

#[test]
fn misuse_gives_clear_errors() {
    let mut sub = null_mut();
    let name = CString::new(unique("misuse")).unwrap();
    unsafe {
        assert_eq!(cg_subscriber_open(null(), null(), &mut sub), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_subscriber_open(name.as_ptr(), null(), null_mut()), cg_status::CG_ERR_NULL_POINTER);
        for bad in [&b"\0"[..], b"a/b\0", b"with space\0", b"..\0"] {
            let st = cg_subscriber_open(bad.as_ptr().cast(), null(), &mut sub);
            assert_eq!(st, cg_status::CG_ERR_INVALID_ARGUMENT, "{bad:?}");
        }
        let long = CString::new("n".repeat(10_000)).unwrap();
        assert_eq!(cg_subscriber_open(long.as_ptr(), null(), &mut sub), cg_status::CG_ERR_INVALID_ARGUMENT);
        assert_eq!(cg_subscriber_open(c"\xff\xfe".as_ptr(), null(), &mut sub), cg_status::CG_ERR_INVALID_UTF8);
        let mut cfg = cg_subscriber_config { struct_size: 0, buffer_frames: 0, reserved: 0 };
        assert_eq!(cg_subscriber_config_init(null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(
            cg_subscriber_open(name.as_ptr(), &cfg, &mut sub),
            cg_status::CG_ERR_INVALID_ARGUMENT,
            "struct_size 0"
        );
        cg_subscriber_config_init(&mut cfg);
        for frames in [0, CG_MAX_SUBSCRIBER_BUFFER as u32 + 1] {
            cfg.buffer_frames = frames;
            assert_eq!(cg_subscriber_open(name.as_ptr(), &cfg, &mut sub), cg_status::CG_ERR_INVALID_ARGUMENT);
        }
        assert!(sub.is_null(), "out written on failure");
        // Nothing published yet: pending, not an error.
        let s = cg_subscriber_open(name.as_ptr(), null(), &mut sub);
        assert_eq!(s, cg_status::CG_OK, "{}", last_error());
        let mut f = Frame::default();
        assert_eq!(cg_subscriber_receive(sub, &mut f), cg_status::CG_PENDING);
        assert_eq!(cg_subscriber_receive(sub, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_subscriber_receive_event(sub, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_subscriber_get_stats(sub, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_subscriber_receive(null_mut(), &mut f), cg_status::CG_ERR_NULL_POINTER);
        // Handles of other kinds, and forged ones, are not subscribers.
        let e = TestEngine::new(16, 1);
        assert_eq!(cg_subscriber_receive(e.handle.cast(), &mut f), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_subscriber_close(0x1234 as *mut cg_subscriber), cg_status::CG_ERR_INVALID_HANDLE);
        let mut p = cg_publisher_stats::default();
        assert_eq!(cg_engine_publisher_stats(e.handle, &mut p), cg_status::CG_ERR_WRONG_STATE, "no publish name");
        e.destroy();
        // The 9th subscriber of a name is refused with CG_ERR_LIMIT; closing one makes room.
        let mut more = vec![sub];
        for _ in 1..8 {
            more.push(open(name.to_str().unwrap(), 8));
        }
        let mut ninth = null_mut();
        assert_eq!(cg_subscriber_open(name.as_ptr(), null(), &mut ninth), cg_status::CG_ERR_LIMIT, "{}", last_error());
        assert_eq!(cg_subscriber_close(more.pop().unwrap()), cg_status::CG_OK);
        more.push(open(name.to_str().unwrap(), 8));
        for s in more {
            assert_eq!(cg_subscriber_close(s), cg_status::CG_OK);
        }
        assert_eq!(cg_subscriber_close(null_mut()), cg_status::CG_OK, "NULL close is a no-op");
    }
    // A bad publish name fails engine creation cleanly.
    let mut cfg = cg_engine_config::default();
    unsafe { cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()) };
    cfg.publish_name = c"no/slash".as_ptr();
    cfg.bundle_path = c"/nonexistent".as_ptr();
    let mut eng = null_mut();
    assert_eq!(unsafe { cg_engine_create(&cfg, &mut eng) }, cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("publish name"), "{}", last_error());
}
