//! Stream behaviour through the C ABI: frames in order, end, cancel, wait, errors, panics,
//! concurrency, engine destruction with live streams.
mod common;

use std::ptr::{null, null_mut};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

fn id_of(s: *mut cg_stream) -> u64 {
    let mut id = 0;
    assert_eq!(unsafe { cg_stream_id(s, &mut id) }, cg_status::CG_OK);
    id
}

#[test]
fn frames_arrive_in_order_then_end() {
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=5 frames=16");
    let id = id_of(s);
    assert!(id >= 1);
    let (n, status) = drain_checked(s, id);
    assert_eq!((n, status), (80, cg_status::CG_END));
    // END is sticky, and polling after it is not an error.
    let mut f = Frame { frame_index: 12345, ..Default::default() };
    for _ in 0..3 {
        assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
        assert_eq!(unsafe { cg_stream_wait(s, 10, &mut f) }, cg_status::CG_END);
    }
    assert_eq!(f.frame_index, 12345, "out is written only on CG_OK");
    // Cancelling a finished stream is allowed (idempotent) and changes nothing: END stays.
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
    assert_eq!(unsafe { cg_stream_wait(s, 10, &mut f) }, cg_status::CG_END);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    assert_eq!(e.stream_count(), 0);
    e.destroy();
}

#[test]
fn end_follows_the_last_frame_at_once() {
    // The worker takes 2 s to free its model state after the last chunk: END must not wait
    // for that (it used to come up to 26 ms late with the default bundle).
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=2 drop_delay_ms=2000");
    let mut f = Frame::default();
    loop {
        assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
        if f.is_last == 1 {
            break;
        }
    }
    assert_eq!(f.frame_index, 31);
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
    assert_eq!(e.counters.sources_alive.load(Ordering::SeqCst), 1, "the worker is still freeing its source");
    // A cancel now (the host's clean-up) does not turn the finished stream into a cancelled one.
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    assert_eq!(e.counters.sources_alive.load(Ordering::SeqCst), 0, "destroy joined the worker");
    e.destroy();
}

#[test]
fn cancel_after_the_last_frame_before_end_keeps_end() {
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=1 frames=4");
    let mut f = Frame::default();
    for i in 0..4 {
        assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
        assert_eq!(f.frame_index, i);
    }
    assert_eq!(f.is_last, 1);
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    e.destroy();
}

#[test]
fn pending_before_first_frame_and_wait_wakes_up() {
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=2 delay_ms=150");
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_PENDING);
    // A short wait times out with PENDING.
    let t0 = Instant::now();
    assert_eq!(unsafe { cg_stream_wait(s, 20, &mut f) }, cg_status::CG_PENDING);
    assert!(t0.elapsed() >= Duration::from_millis(15));
    // A long wait returns as soon as the first frame exists, not at the timeout.
    let t0 = Instant::now();
    assert_eq!(unsafe { cg_stream_wait(s, 10_000, &mut f) }, cg_status::CG_OK);
    assert!(t0.elapsed() < Duration::from_secs(5));
    assert_eq!(f.frame_index, 0);
    let mut n = 1;
    loop {
        match unsafe { cg_stream_wait(s, 10_000, &mut f) } {
            cg_status::CG_OK => {
                assert_eq!(f.frame_index, n);
                n += 1;
            }
            st => {
                assert_eq!(st, cg_status::CG_END);
                break;
            }
        }
    }
    assert_eq!(n, 32);
    assert_eq!(f.is_last, 1);
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}

#[test]
fn polling_a_cancelled_stream() {
    let e = TestEngine::new(8, 4);
    let s = e.start("chunks=1000 delay_ms=1");
    let mut f = Frame::default();
    assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    for _ in 0..5 {
        assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
        assert_eq!(unsafe { cg_stream_wait(s, 100, &mut f) }, cg_status::CG_CANCELLED);
    }
    // The worker lets go of its source (model state) within about one step.
    let t0 = Instant::now();
    while e.counters.sources_alive.load(Ordering::SeqCst) != 0 {
        assert!(t0.elapsed() < Duration::from_secs(5), "worker did not release its source");
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    e.destroy();
}

#[test]
fn cancel_from_another_thread_wakes_a_waiter() {
    let e = TestEngine::new(4, 4);
    // Slow source: the waiter will be blocked in cg_stream_wait when the cancel comes.
    let s = e.start("chunks=1000 delay_ms=50 frames=1");
    let addr = s as usize;
    let canceller = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(120));
        assert_eq!(unsafe { cg_cancel(addr as *mut cg_stream) }, cg_status::CG_OK);
        Instant::now()
    });
    let mut f = Frame::default();
    let mut frames = 0;
    let status = loop {
        match unsafe { cg_stream_wait(s, 30_000, &mut f) } {
            cg_status::CG_OK => frames += 1,
            other => break other,
        }
    };
    let cancelled_at = canceller.join().unwrap();
    assert_eq!(status, cg_status::CG_CANCELLED);
    assert!(cancelled_at.elapsed() < Duration::from_secs(2), "waiter woke late");
    assert!(frames < 1000);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    e.destroy();
}

#[test]
fn cancel_mid_stream_from_another_thread_while_polling() {
    let e = TestEngine::new(16, 4);
    let s = e.start("chunks=100000 frames=16");
    let addr = s as usize;
    let poller = std::thread::spawn(move || {
        let s = addr as *mut cg_stream;
        let mut f = Frame::default();
        let mut n = 0u64;
        let t0 = Instant::now();
        loop {
            match unsafe { cg_poll_frame(s, &mut f) } {
                cg_status::CG_OK => {
                    assert_eq!(f.frame_index, n);
                    n += 1;
                }
                cg_status::CG_PENDING => std::thread::yield_now(),
                st => return (st, n),
            }
            assert!(t0.elapsed() < Duration::from_secs(20));
        }
    });
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    let (status, n) = poller.join().unwrap();
    assert_eq!(status, cg_status::CG_CANCELLED);
    assert!(n > 0, "some frames before the cancel");
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    e.destroy();
}

#[test]
fn eight_concurrent_streams_complete() {
    let e = Arc::new(TestEngine::new(32, 8));
    let threads: Vec<_> = (0..8)
        .map(|i| {
            let e = Arc::clone(&e);
            std::thread::spawn(move || {
                let s = e.start(&format!("stream {i} chunks={} frames=16", 3 + i));
                let id = id_of(s);
                let (n, st) = drain_checked(s, id);
                assert_eq!(st, cg_status::CG_END);
                assert_eq!(n, 16 * (3 + i as u64));
                assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
                id
            })
        })
        .collect();
    let mut ids: Vec<u64> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 8, "stream ids are unique");
    assert_eq!(e.stream_count(), 0);
    Arc::try_unwrap(e).ok().unwrap().destroy();
}

#[test]
fn worker_error_after_frames() {
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=10 fail_at=2");
    let (n, status) = drain_checked(s, id_of(s));
    assert_eq!(n, 32, "frames produced before the failure are delivered first");
    assert_eq!(status, cg_status::CG_ERR_INFERENCE);
    assert!(last_error().contains("scripted failure at chunk 2"), "{}", last_error());
    // The error is sticky.
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_ERR_INFERENCE);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    e.destroy();
}

#[test]
fn worker_panic_becomes_an_error() {
    let e = TestEngine::new(256, 4);
    let s = e.start("chunks=10 panic_at=1");
    let (n, status) = drain_checked(s, id_of(s));
    assert_eq!(n, 16);
    assert_eq!(status, cg_status::CG_ERR_PANIC);
    assert!(last_error().contains("scripted panic at chunk 1"), "{}", last_error());
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    // The engine is unaffected.
    let s = e.start("chunks=1");
    assert_eq!(drain_checked(s, id_of(s)), (16, cg_status::CG_END));
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}

#[test]
fn panic_at_the_boundary_poisons_the_engine() {
    let e = TestEngine::new(256, 4);
    let mut s = null_mut();
    let st = unsafe { cg_start(e.handle, c"factory_panic".as_ptr(), null(), &mut s) };
    assert_eq!(st, cg_status::CG_ERR_PANIC);
    assert!(s.is_null());
    assert!(last_error().contains("scripted factory panic"), "{}", last_error());
    // Poisoned: later calls fail fast, destroy still works.
    let st = unsafe { cg_start(e.handle, c"chunks=1".as_ptr(), null(), &mut s) };
    assert_eq!(st, cg_status::CG_ERR_PANIC);
    assert!(last_error().contains("poisoned"));
    e.destroy();
}

#[test]
fn factory_error_is_reported_and_releases_the_slot() {
    let e = TestEngine::new(256, 1);
    let mut s = null_mut();
    for _ in 0..3 {
        let st = unsafe { cg_start(e.handle, c"factory_fail".as_ptr(), null(), &mut s) };
        assert_eq!(st, cg_status::CG_ERR_INVALID_ARGUMENT);
    }
    assert_eq!(e.stream_count(), 0);
    let s = e.start("chunks=1");
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}

#[test]
fn max_streams_limit() {
    let e = TestEngine::new(16, 2);
    let a = e.start("chunks=1");
    let b = e.start("chunks=1");
    let mut s = null_mut();
    assert_eq!(unsafe { cg_start(e.handle, c"chunks=1".as_ptr(), null(), &mut s) }, cg_status::CG_ERR_LIMIT);
    // Finished but not destroyed streams still count; destroying one frees a slot.
    drain_checked(a, id_of(a));
    assert_eq!(unsafe { cg_start(e.handle, c"chunks=1".as_ptr(), null(), &mut s) }, cg_status::CG_ERR_LIMIT);
    unsafe { cg_stream_destroy(a) };
    let c = e.start("chunks=1");
    unsafe {
        cg_stream_destroy(b);
        cg_stream_destroy(c);
    }
    e.destroy();
}

#[test]
fn concurrent_use_of_one_stream_is_rejected() {
    let e = TestEngine::new(16, 2);
    let s = e.start("chunks=100000 delay_ms=20 frames=1");
    let addr = s as usize;
    // Thread A waits (holding the stream); thread B's poll must not block or race.
    let waiter = std::thread::spawn(move || {
        let mut f = Frame::default();
        unsafe { cg_stream_wait(addr as *mut cg_stream, 2_000, &mut f) }
    });
    std::thread::sleep(Duration::from_millis(5));
    let mut f = Frame::default();
    let mut saw_wrong_state = false;
    for _ in 0..200 {
        match unsafe { cg_poll_frame(s, &mut f) } {
            cg_status::CG_ERR_WRONG_STATE => {
                saw_wrong_state = true;
                break;
            }
            _ => std::thread::sleep(Duration::from_micros(100)),
        }
    }
    let _ = waiter.join().unwrap();
    assert!(saw_wrong_state);
    assert!(last_error().contains("another thread"));
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}

#[test]
fn destroying_the_engine_with_live_streams() {
    let e = TestEngine::new(16, 4);
    let running = e.start("chunks=100000 delay_ms=2");
    let finished = e.start("chunks=1");
    let mut f = Frame::default();
    // Let `finished` finish (its 16 frames fit in the ring) without draining it.
    let t0 = Instant::now();
    while e.counters.chunks_produced.load(Ordering::SeqCst) < 3 {
        assert!(t0.elapsed() < Duration::from_secs(10));
        std::thread::sleep(Duration::from_millis(1));
    }
    std::thread::sleep(Duration::from_millis(20));
    let counters = Arc::clone(&e.counters);
    e.destroy(); // waits for the workers
    assert_eq!(counters.sources_alive.load(Ordering::SeqCst), 0, "all model state released");
    // The running stream was cancelled; the finished one still delivers its frames.
    assert_eq!(unsafe { cg_poll_frame(running, &mut f) }, cg_status::CG_CANCELLED);
    assert_eq!(drain_checked(finished, id_of(finished)), (16, cg_status::CG_END));
    unsafe {
        assert_eq!(cg_stream_destroy(running), cg_status::CG_OK);
        assert_eq!(cg_stream_destroy(finished), cg_status::CG_OK);
    }
}

#[test]
fn destroying_a_stream_while_another_thread_waits() {
    let e = TestEngine::new(16, 4);
    let s = e.start("chunks=100000 delay_ms=30 frames=1");
    let addr = s as usize;
    let waiter = std::thread::spawn(move || {
        let mut f = Frame::default();
        let mut last = cg_status::CG_OK;
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(10) {
            last = unsafe { cg_stream_wait(addr as *mut cg_stream, 1_000, &mut f) };
            if last != cg_status::CG_OK && last != cg_status::CG_ERR_WRONG_STATE {
                break;
            }
        }
        last
    });
    std::thread::sleep(Duration::from_millis(60));
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    let last = waiter.join().unwrap();
    assert!(last == cg_status::CG_CANCELLED || last == cg_status::CG_ERR_INVALID_HANDLE, "waiter ended with {last:?}");
    e.destroy();
}
