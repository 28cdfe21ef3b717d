//! Backpressure and lifecycle stress through the C ABI. One test per concern; the
//! thread-count check runs alone in this binary's single test to avoid interference.
mod common;

use std::ptr::null;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

fn threads_in_process() -> Option<usize> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status.lines().find_map(|l| l.strip_prefix("Threads:")).and_then(|v| v.trim().parse().ok())
}

#[test]
fn backpressure_and_start_cancel_cycles() {
    full_ring_makes_the_worker_wait_without_losing_frames();
    thousand_start_cancel_cycles();
}

fn full_ring_makes_the_worker_wait_without_losing_frames() {
    // Ring of 5 frames, chunks of 16: every chunk overfills it, so the worker must wait
    // inside a chunk as well as between chunks.
    let e = TestEngine::new(5, 2);
    let s = e.start("chunks=40 frames=16");
    std::thread::sleep(Duration::from_millis(100));
    // The consumer has not polled: the worker produced at most one chunk and is parked.
    let produced = e.counters.chunks_produced.load(Ordering::SeqCst);
    assert!(produced <= 1, "worker ran ahead of a full ring: {produced} chunks");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(e.counters.chunks_produced.load(Ordering::SeqCst), produced, "worker is waiting");

    // A slow consumer: every frame arrives, strictly consecutive, is_last on the last.
    let mut f = Frame::default();
    let mut n = 0u64;
    let t0 = Instant::now();
    loop {
        match unsafe { cg_poll_frame(s, &mut f) } {
            cg_status::CG_OK => {
                assert_eq!(f.frame_index, n, "lost or reordered frame");
                assert_eq!(f.root_translation[0], n as f32);
                assert_eq!(f.is_last == 1, n == 40 * 16 - 1);
                n += 1;
                if n.is_multiple_of(97) {
                    std::thread::sleep(Duration::from_millis(2));
                }
            }
            cg_status::CG_PENDING => std::thread::yield_now(),
            st => {
                assert_eq!(st, cg_status::CG_END);
                break;
            }
        }
        assert!(t0.elapsed() < Duration::from_secs(30));
    }
    assert_eq!(n, 640);
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}

fn thousand_start_cancel_cycles() {
    let e = TestEngine::new(8, 4);
    let threads_before = threads_in_process();
    let t0 = Instant::now();
    let mut f = Frame::default();
    for i in 0..1000 {
        let s = e.start("chunks=100000 frames=16");
        match i % 4 {
            // Cancel at once, before the worker ran.
            0 => {}
            // Cancel after the first frame.
            1 => {
                assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
            }
            // Cancel while the worker is parked on a full ring.
            2 => std::thread::sleep(Duration::from_micros(300)),
            // Destroy without cancelling (destroy cancels).
            _ => {
                assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
                continue;
            }
        }
        assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
        assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
        assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    }
    let elapsed = t0.elapsed();
    assert!(elapsed < Duration::from_secs(60), "1000 cycles took {elapsed:?}");
    assert_eq!(e.stream_count(), 0);
    assert_eq!(e.counters.sources_alive.load(Ordering::SeqCst), 0, "a source leaked");
    if let (Some(before), Some(after)) = (threads_before, threads_in_process()) {
        assert!(after <= before, "threads leaked: {before} -> {after}");
    }
    // The engine still works.
    let s = e.start("chunks=2");
    assert_eq!(
        drain_checked(s, {
            let mut id = 0;
            unsafe { cg_stream_id(s, &mut id) };
            id
        }),
        (32, cg_status::CG_END)
    );
    unsafe { cg_stream_destroy(s) };
    let _ = null::<u8>();
    e.destroy();
    eprintln!("1000 start/cancel/destroy cycles: {elapsed:?}");
}
