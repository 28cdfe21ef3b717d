//! A counting global allocator for the tests that prove a hot path allocation-free.
//! `count_allocs` counts on the calling thread only, so parallel tests don't interfere;
//! `count_allocs_all_threads` counts every thread of the process (for work that runs on a
//! stream's worker), so a binary using it must not run other tests at the same time.
//! Include with `mod alloc_counter;` (it installs itself as the global allocator).
#![allow(dead_code)]
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

struct Counting;

thread_local! {
    static COUNT: Cell<Option<usize>> = const { Cell::new(None) };
}

static ALL_THREADS: AtomicBool = AtomicBool::new(false);
static ALL_COUNT: AtomicUsize = AtomicUsize::new(0);
/// Whether the process's main thread is left out of the all-threads count: when the test
/// runs on a thread of its own, the main thread is libtest's, whose reporting (e.g. its
/// "has been running for over 60 seconds" notice on a loaded machine) allocates.
static SKIP_MAIN: AtomicBool = AtomicBool::new(false);

/// Whether the calling thread is the process's main thread (Linux: its tid is the pid).
fn on_main_thread() -> bool {
    #[cfg(target_os = "linux")]
    // SAFETY: plain system calls without arguments.
    unsafe {
        libc::gettid() == libc::getpid()
    }
    #[cfg(not(target_os = "linux"))]
    false
}

fn note() {
    if ALL_THREADS.load(Ordering::Relaxed) && !(SKIP_MAIN.load(Ordering::Relaxed) && on_main_thread()) {
        ALL_COUNT.fetch_add(1, Ordering::Relaxed);
    }
    let _ = COUNT.try_with(|c| c.set(c.get().map(|n| n + 1)));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(l) }
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(p, l, n) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Runs `f` and returns its result with the number of allocations it made on this thread.
pub fn count_allocs<R>(f: impl FnOnce() -> R) -> (R, usize) {
    COUNT.with(|c| c.set(Some(0)));
    let r = f();
    let n = COUNT.with(|c| c.replace(None)).unwrap_or(0);
    (r, n)
}

/// Allocations made by `f` on this thread.
pub fn allocations_in(f: impl FnOnce()) -> usize {
    count_allocs(f).1
}

/// Runs `f` and returns its result with the number of allocations every thread of the
/// process made meanwhile (except libtest's main thread when `f` runs on another one).
pub fn count_allocs_all_threads<R>(f: impl FnOnce() -> R) -> (R, usize) {
    SKIP_MAIN.store(!on_main_thread(), Ordering::SeqCst);
    ALL_COUNT.store(0, Ordering::SeqCst);
    ALL_THREADS.store(true, Ordering::SeqCst);
    let r = f();
    ALL_THREADS.store(false, Ordering::SeqCst);
    (r, ALL_COUNT.load(Ordering::SeqCst))
}
