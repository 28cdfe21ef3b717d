//! `cg_poll_frame` never allocates: a counting global allocator watches the polling thread
//! while it takes frames, sees PENDING, END and CANCELLED.
mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::time::Duration;

use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

struct Counting;

thread_local! {
    static TRACK: Cell<bool> = const { Cell::new(false) };
    static ALLOCS: Cell<usize> = const { Cell::new(0) };
}

fn note() {
    let _ = TRACK.try_with(|t| {
        if t.get() {
            let _ = ALLOCS.try_with(|c| c.set(c.get() + 1));
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Runs `f` and returns how many allocations it made on this thread.
fn allocations_in(f: impl FnOnce()) -> usize {
    ALLOCS.with(|c| c.set(0));
    TRACK.with(|t| t.set(true));
    f();
    TRACK.with(|t| t.set(false));
    ALLOCS.with(|c| c.get())
}

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
