//! `cg_poll_frame` never allocates: a counting global allocator watches the polling thread
//! while it takes frames, sees PENDING, END and CANCELLED.
mod alloc_counter;
mod common;

use std::time::Duration;

use alloc_counter::allocations_in;
use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

#[test]
fn poll_does_not_allocate() {
    // The counter works.
    assert!(allocations_in(|| drop(std::hint::black_box(Vec::<u8>::with_capacity(10)))) >= 1);

    let e = TestEngine::new(64, 2);
    let s = e.start("chunks=50 frames=16 delay_ms=1");
    let mut f = Frame::default();
    let mut frames = 0u64;
    let mut pendings = 0u64;
    let mut end = false;
    let n = allocations_in(|| {
        for _ in 0..2_000_000 {
            match unsafe { cg_poll_frame(s, &mut f) } {
                cg_status::CG_OK => frames += 1,
                cg_status::CG_PENDING => {
                    pendings += 1;
                    std::thread::sleep(Duration::from_micros(50));
                }
                cg_status::CG_END => {
                    end = true;
                    break;
                }
                other => panic!("{other:?}"),
            }
        }
        for _ in 0..10 {
            assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_END);
        }
    });
    assert!(end);
    assert_eq!(frames, 800);
    assert!(pendings > 0, "the PENDING path was exercised");
    assert_eq!(n, 0, "cg_poll_frame allocated {n} times");
    unsafe { cg_stream_destroy(s) };

    // The CANCELLED path too (the first poll after a cancel frees the ring; no allocation).
    let s = e.start("chunks=100000 frames=16");
    assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    let n = allocations_in(|| {
        for _ in 0..10 {
            assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
        }
    });
    assert_eq!(n, 0);
    unsafe { cg_stream_destroy(s) };
    e.destroy();
}
