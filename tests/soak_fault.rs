//! Soak and fault tests through the C ABI (issue 8, point 4), run by plain `cargo test`:
//!
//! * 10,000 start/cancel cycles with the frames polled on another thread, resident memory
//!   (VmRSS) sampled every [`RSS_SAMPLE_EVERY`] cycles: the end may exceed the highest sample
//!   of the first half by at most [`RSS_GROWTH_BOUND`]; threads, streams and sources must all
//!   be back to zero.
//! * A consumer that stops polling: the worker fills the ring and then waits (no more
//!   chunks produced, no CPU burnt, memory flat), and `cg_cancel` from another thread still
//!   returns at once, after which polling gives CG_CANCELLED and destroy joins promptly.
//!   Once with scripted streams (exact chunk counts) and once with the real tiny bundle.
//!
//! One `#[test]` runs the parts in sequence: RSS, thread counts and per-thread CPU time are
//! process-wide, so parallel tests in this binary would disturb each other.
mod common;

use std::ffi::CString;
use std::ptr::{null, null_mut};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

/// Allowed VmRSS growth over the second half of the cycles (5,000), against the highest
/// sample of the first half. A leak grows linearly, so it shows in the second half as in the
/// first; the allocator's (and under valgrind, the tool's own) warm-up does not: on a loaded
/// machine under valgrind it went on for thousands of cycles to a plateau (117.7 MiB after
/// the 500-cycle warm-up, 124.8 MiB from then on), which a single after-warm-up baseline
/// read as 7–8.6 MiB of growth. 4 MiB over 5,000 cycles is 0.8 KiB per cycle.
const RSS_GROWTH_BOUND: u64 = 4 << 20;
const CYCLES: usize = if cfg!(miri) { 20 } else { 10_000 };
const WARMUP: usize = if cfg!(miri) { 4 } else { 500 };
const RSS_SAMPLE_EVERY: usize = if cfg!(miri) { 4 } else { 500 };

/// A field of /proc/self/status in bytes (`VmRSS`, `VmHWM`) or as a count (`Threads`).
fn proc_status(key: &str) -> Option<u64> {
    if cfg!(miri) {
        return None; // no file system under Miri's isolation
    }
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key) && l[key.len()..].starts_with(':'))?;
    let mut parts = line[key.len() + 1..].split_whitespace();
    let n: u64 = parts.next()?.parse().ok()?;
    Some(if parts.next() == Some("kB") { n * 1024 } else { n })
}

fn rss() -> u64 {
    proc_status("VmRSS").unwrap_or(0)
}

fn mib(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

/// CPU time (user + system, in clock ticks) of every thread named `comgrasp-stream*`.
fn worker_cpu_ticks() -> Vec<u64> {
    let mut out = Vec::new();
    if cfg!(miri) {
        return out;
    }
    let Ok(rd) = std::fs::read_dir("/proc/self/task") else { return out };
    for t in rd.flatten() {
        let comm = std::fs::read_to_string(t.path().join("comm")).unwrap_or_default();
        // a stream's worker, or the crowd scheduler's thread that drives it
        if !comm.starts_with("comgrasp-stream") && !comm.starts_with("comgrasp-crowd") {
            continue;
        }
        let stat = std::fs::read_to_string(t.path().join("stat")).unwrap_or_default();
        // Fields after the parenthesised name: state is field 3, utime 14, stime 15.
        if let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) {
            let f: Vec<&str> = rest.split_whitespace().collect();
            if let (Some(u), Some(s)) =
                (f.get(11).and_then(|v| v.parse::<u64>().ok()), f.get(12).and_then(|v| v.parse::<u64>().ok()))
            {
                out.push(u + s);
            }
        }
    }
    out
}

#[test]
fn soak_and_fault() {
    start_cancel_cycles_keep_memory_flat();
    stalled_consumer_with_scripted_streams();
    if cfg!(miri) {
        return; // tract is not interpretable; the scripted parts above are the point there
    }
    stalled_consumer_with_the_tiny_bundle();
}

/// What the polling thread is told to do with the next stream.
enum Job {
    /// Poll this stream (handle value) until CANCELLED; report the first frame.
    Poll(usize),
    Stop,
}

fn start_cancel_cycles_keep_memory_flat() {
    let e = TestEngine::new(8, 2);
    let handle = e.handle as usize;
    let (job_tx, job_rx) = mpsc::channel::<Job>();
    let (first_tx, first_rx) = mpsc::channel::<()>();
    let (done_tx, done_rx) = mpsc::channel::<(u64, cg_status)>();
    let frames_total = Arc::new(AtomicUsize::new(0));
    let ft = Arc::clone(&frames_total);
    // The consumer: polls (and sometimes waits on) each stream it is given, from its own
    // thread, until the main thread's cancel shows up as CG_CANCELLED.
    let poller = std::thread::spawn(move || {
        let mut f = Frame::default();
        while let Ok(Job::Poll(h)) = job_rx.recv() {
            let s = h as *mut cg_stream;
            let mut n = 0u64;
            let mut told_first = false;
            let end = loop {
                let st = if n % 3 == 2 {
                    unsafe { cg_stream_wait(s, 1, &mut f) }
                } else {
                    unsafe { cg_poll_frame(s, &mut f) }
                };
                match st {
                    cg_status::CG_OK => {
                        assert_eq!(f.frame_index, n, "frames out of order");
                        n += 1;
                        if !told_first {
                            told_first = true;
                            let _ = first_tx.send(());
                        }
                    }
                    cg_status::CG_PENDING => std::thread::yield_now(),
                    other => break other,
                }
            };
            ft.fetch_add(n as usize, Ordering::Relaxed);
            if !told_first {
                let _ = first_tx.send(());
            }
            done_tx.send((n, end)).unwrap();
        }
    });

    let threads_before = proc_status("Threads");
    // (cycle, VmRSS) every RSS_SAMPLE_EVERY cycles from the end of the warm-up on
    let mut samples: Vec<(usize, u64)> = Vec::new();
    let t0 = Instant::now();
    let mut t_measured = t0;
    for i in 0..WARMUP + CYCLES {
        if i == WARMUP {
            t_measured = Instant::now();
        }
        if i >= WARMUP && (i - WARMUP).is_multiple_of(RSS_SAMPLE_EVERY) {
            samples.push((i - WARMUP, rss()));
        }
        let mut s = null_mut();
        let text = CString::new("chunks=100000 frames=16").unwrap();
        assert_eq!(
            unsafe { cg_start(handle as *mut cg_engine, text.as_ptr(), null(), &mut s) },
            cg_status::CG_OK,
            "{}",
            last_error()
        );
        job_tx.send(Job::Poll(s as usize)).unwrap();
        match i % 4 {
            0 => {}                                                                    // cancel at once
            1 => first_rx.recv_timeout(Duration::from_secs(10)).expect("first frame"), // after a frame
            2 => std::thread::sleep(Duration::from_micros(200)),                       // mid-stream
            _ => std::thread::yield_now(),
        }
        assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
        let (_, end) = done_rx.recv_timeout(Duration::from_secs(10)).expect("the poller saw the cancel");
        assert_eq!(end, cg_status::CG_CANCELLED);
        if i % 4 != 1 {
            // Drain a late "first frame" notice so the next cycle's wait is not satisfied early.
            while first_rx.try_recv().is_ok() {}
        }
        assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    }
    job_tx.send(Job::Stop).unwrap();
    poller.join().unwrap();
    let elapsed = t_measured.elapsed();
    let rss_end = rss();
    let first_half_peak = samples.iter().filter(|(c, _)| *c <= CYCLES / 2).map(|(_, r)| *r).max().unwrap_or(0);
    let growth = rss_end.saturating_sub(first_half_peak);
    let curve: Vec<String> = samples.iter().map(|(c, r)| format!("{c}:{:.1}", mib(*r))).collect();
    eprintln!(
        "{CYCLES} start/poll-on-another-thread/cancel/destroy cycles in {elapsed:.2?} ({:.0} µs each), {} frames polled; \
         VmRSS highest in the first half {:.1} MiB, at the end {:.1} MiB (growth {:.2} MiB, bound {:.0} MiB); \
         VmRSS by cycle after the {WARMUP}-cycle warm-up (MiB): {}",
        elapsed.as_secs_f64() * 1e6 / CYCLES as f64,
        frames_total.load(Ordering::Relaxed),
        mib(first_half_peak),
        mib(rss_end),
        mib(growth),
        mib(RSS_GROWTH_BOUND),
        curve.join(" ")
    );
    if !cfg!(miri) {
        assert!(first_half_peak > 0, "VmRSS not readable");
        assert!(
            growth < RSS_GROWTH_BOUND,
            "VmRSS grew by {:.2} MiB over the last {} cycles",
            mib(growth),
            CYCLES - CYCLES / 2
        );
    }
    assert_eq!(e.stream_count(), 0);
    assert_eq!(e.counters.sources_alive.load(Ordering::SeqCst), 0, "a source leaked");
    if let (Some(before), Some(after)) = (threads_before, proc_status("Threads")) {
        // The poller thread was alive in `before` and has exited now.
        assert!(after < before, "threads leaked: {before} -> {after}");
    }
    e.destroy();
}

fn stalled_consumer_with_scripted_streams() {
    const RING: usize = 32;
    let e = TestEngine::new(RING, 2);
    let s = e.start("chunks=1000000 frames=16");
    let mut f = Frame::default();
    // Take 10 frames, then stop polling.
    for n in 0..10 {
        assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(10)), cg_status::CG_OK);
        assert_eq!(f.frame_index, n);
    }
    std::thread::sleep(Duration::from_millis(100));
    let produced = e.counters.chunks_produced.load(Ordering::SeqCst);
    let rss_stalled = rss();
    let cpu_before = worker_cpu_ticks();
    let watch = Duration::from_millis(if cfg!(miri) { 50 } else { 700 });
    std::thread::sleep(watch);
    let produced_later = e.counters.chunks_produced.load(Ordering::SeqCst);
    let cpu_after = worker_cpu_ticks();
    let rss_later = rss();
    // 10 taken + RING buffered + one chunk in hand: at most ceil(42 / 16) + 1 chunks.
    let bound = (10 + RING).div_ceil(16) + 1;
    eprintln!(
        "stalled consumer (scripted, ring {RING}): {produced} chunks produced then {produced_later} after {watch:?} \
         (bound {bound}); worker CPU ticks {cpu_before:?} -> {cpu_after:?}; VmRSS {:.1} -> {:.1} MiB",
        mib(rss_stalled),
        mib(rss_later)
    );
    assert!(produced <= bound, "the worker ran past a full ring: {produced} chunks");
    assert_eq!(produced_later, produced, "the worker kept producing while nobody polled");
    if !cfg!(miri) {
        assert_eq!(cpu_before.len(), 1, "one worker thread expected");
        assert!(cpu_after[0] <= cpu_before[0] + 2, "a waiting worker burnt CPU: {cpu_before:?} -> {cpu_after:?} ticks");
        assert!(rss_later <= rss_stalled + (1 << 20), "memory grew while stalled");
    }
    cancel_from_another_thread_promptly(s);
    assert_eq!(e.counters.sources_alive.load(Ordering::SeqCst), 0);
    e.destroy();
}

/// Cancels `s` from another thread (timing the call), then checks the documented aftermath.
fn cancel_from_another_thread_promptly(s: *mut cg_stream) {
    let h = s as usize;
    let started = Arc::new(AtomicBool::new(false));
    let st2 = Arc::clone(&started);
    let canceller = std::thread::spawn(move || {
        st2.store(true, Ordering::SeqCst);
        let t0 = Instant::now();
        let st = unsafe { cg_cancel(h as *mut cg_stream) };
        (st, t0.elapsed())
    });
    let (st, took) = canceller.join().unwrap();
    assert!(started.load(Ordering::SeqCst));
    assert_eq!(st, cg_status::CG_OK);
    // (Miri's clock is virtual, so only the real run checks durations.)
    assert!(cfg!(miri) || took < Duration::from_millis(50), "cg_cancel took {took:?}");
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
    assert_eq!(
        unsafe { cg_stream_wait(s, 1000, &mut f) },
        cg_status::CG_CANCELLED,
        "wait must not block after a cancel"
    );
    let t0 = Instant::now();
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    let joined = t0.elapsed();
    eprintln!("cg_cancel from another thread took {took:?}; cg_stream_destroy joined the worker in {joined:?}");
    assert!(cfg!(miri) || joined < Duration::from_secs(2), "destroy took {joined:?}");
}

fn stalled_consumer_with_the_tiny_bundle() {
    let dir = CString::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/tiny")).unwrap();
    let mut cfg = cg_engine_config::default();
    assert_eq!(unsafe { cg_engine_config_init(&mut cfg) }, cg_status::CG_OK);
    cfg.bundle_path = dir.as_ptr();
    cfg.ring_capacity = 20;
    // one scheduler thread whatever the machine's cores: the stream's only producer
    cfg.scheduler_threads = 1;
    let mut e = null_mut();
    assert_eq!(unsafe { cg_engine_create(&cfg, &mut e) }, cg_status::CG_OK, "{}", last_error());
    // Force a long generation (the bundle's L_max) so the ring, not the end, stops the worker.
    let mut scfg = cg_stream_config::default();
    assert_eq!(unsafe { cg_stream_config_init(&mut scfg) }, cg_status::CG_OK);
    scfg.use_defaults &= !(CG_USE_DEFAULT_MIN_LEN | CG_USE_DEFAULT_MAX_LEN);
    scfg.min_len = 18;
    scfg.max_len = 18;
    let text = CString::new("A woman drinks from the mug").unwrap();
    let mut s = null_mut();
    assert_eq!(unsafe { cg_start(e, text.as_ptr(), &scfg, &mut s) }, cg_status::CG_OK, "{}", last_error());
    let mut f = Frame::default();
    assert_eq!(poll_until_ready(s, &mut f, Duration::from_secs(30)), cg_status::CG_OK);
    // Stop polling. Give the worker time to fill the ring (until its CPU time stops growing:
    // under valgrind on a loaded machine that takes seconds, not the 500 ms of a plain run; a
    // worker that spins never settles and fails below), then watch it for a while.
    let settle = Instant::now();
    let mut ticks = worker_cpu_ticks();
    loop {
        std::thread::sleep(Duration::from_millis(500));
        let now = worker_cpu_ticks();
        if now == ticks || settle.elapsed() > Duration::from_secs(60) {
            break;
        }
        ticks = now;
    }
    let rss0 = rss();
    let cpu0 = worker_cpu_ticks();
    std::thread::sleep(Duration::from_millis(700));
    let cpu1 = worker_cpu_ticks();
    let rss1 = rss();
    eprintln!(
        "stalled consumer (tiny bundle, ring 20, 288-frame stream): worker CPU ticks {cpu0:?} -> {cpu1:?} over 700 ms; \
         VmRSS {:.1} -> {:.1} MiB",
        mib(rss0), mib(rss1)
    );
    assert_eq!(cpu0.len(), 1, "one producer thread expected");
    assert!(cpu1[0] <= cpu0[0] + 2, "a waiting worker burnt CPU: {cpu0:?} -> {cpu1:?} ticks");
    assert!(rss1 <= rss0 + (1 << 20), "memory grew while stalled");
    cancel_from_another_thread_promptly(s);
    assert_eq!(unsafe { cg_engine_destroy(e) }, cg_status::CG_OK);
}
