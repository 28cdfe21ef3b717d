//! Soak run (issue 8, point 4): N streams at once through the C ABI, each restarted with a
//! new prompt and seed whenever it ends, until every stream has generated the requested
//! minutes of motion. Prints frames, frames/s and resident memory at the start, every few
//! seconds and at the end. A benchmark-style run, not part of `cargo test`:
//!
//! ```text
//! cargo run --release --example soak -- --streams 8 --minutes 10            # embedded default
//! cargo run --release --example soak -- --bundle models/tiny --minutes 1
//! bash scripts/soak.sh                                                      # the same, niced
//! ```
//!
//! Options: `--streams N` (8), `--minutes M` of motion per stream (10), `--bundle DIR`
//! (default: the embedded model, or `COMGRASP_BUNDLE`), `--report-every S` seconds (10),
//! `--ring FRAMES` (256), `--max-rss-growth-mib X` (fail if VmRSS at the end exceeds VmRSS
//! at the warm-up mark, when every stream has generated a fifth of its motion, by more than
//! X MiB; default 64). The warm-up mark is not taken earlier because the first minute
//! still grows the allocator's per-thread arenas and tract's scratch buffers to their
//! working size; a leak shows as growth after it, proportional to the run's length.
//! Exit status 0 when every stream reached its target with no error and memory stayed
//! within the bound; 1 otherwise.
use std::ffi::{CStr, CString};
use std::ptr::{null, null_mut};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::Frame;

const PROMPTS: [&str; 8] = [
    "A woman drinks from the mug",
    "A man lifts the small cube",
    "A woman passes the apple from her left hand to her right",
    "A man pours from the water bottle",
    "A woman inspects the cup",
    "A man holds out the bowl as if offering it",
    "A woman lifts the torus with both hands",
    "A man drinks from the cup",
];

struct Args {
    streams: usize,
    minutes: f64,
    bundle: Option<String>,
    report_every: f64,
    ring: u32,
    max_rss_growth_mib: f64,
}

fn parse_args() -> Args {
    let mut a =
        Args { streams: 8, minutes: 10.0, bundle: None, report_every: 10.0, ring: 256, max_rss_growth_mib: 64.0 };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let mut v = || it.next().unwrap_or_else(|| usage(&format!("{k} needs a value")));
        match k.as_str() {
            "--streams" => a.streams = v().parse().unwrap_or_else(|_| usage("--streams N")),
            "--minutes" => a.minutes = v().parse().unwrap_or_else(|_| usage("--minutes M")),
            "--bundle" => a.bundle = Some(v()),
            "--report-every" => a.report_every = v().parse().unwrap_or_else(|_| usage("--report-every S")),
            "--ring" => a.ring = v().parse().unwrap_or_else(|_| usage("--ring FRAMES")),
            "--max-rss-growth-mib" => {
                a.max_rss_growth_mib = v().parse().unwrap_or_else(|_| usage("--max-rss-growth-mib X"))
            }
            "-h" | "--help" => usage(""),
            other => usage(&format!("unknown argument {other}")),
        }
    }
    if a.streams == 0 || a.minutes <= 0.0 {
        usage("--streams and --minutes must be positive");
    }
    a
}

fn usage(msg: &str) -> ! {
    if !msg.is_empty() {
        eprintln!("soak: {msg}");
    }
    eprintln!("usage: soak [--streams N] [--minutes M] [--bundle DIR] [--report-every S] [--ring FRAMES] [--max-rss-growth-mib X]");
    std::process::exit(2)
}

fn proc_status(key: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with(key) && l[key.len()..].starts_with(':'))
        .and_then(|l| l[key.len() + 1..].split_whitespace().next()?.parse::<u64>().ok())
        .map_or(0, |n| if key.starts_with("Vm") { n * 1024 } else { n })
}

fn mib(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

fn last_error() -> String {
    unsafe { CStr::from_ptr(cg_last_error()) }.to_string_lossy().into_owned()
}

/// What one stream slot did, shared with the reporter.
#[derive(Default)]
struct Slot {
    frames: AtomicU64,
    /// Generated motion in microseconds (frames / fps).
    motion_us: AtomicU64,
    streams: AtomicU64,
    errors: AtomicU64,
    done: AtomicBool,
}

struct EngineHandle(*mut cg_engine);
unsafe impl Send for EngineHandle {}
unsafe impl Sync for EngineHandle {}

/// Runs streams one after another on `engine` until `target_s` seconds of motion.
fn run_slot(engine: &EngineHandle, index: usize, target_s: f64, slot: &Slot) {
    let mut f = Frame::default();
    let mut round = 0u64;
    let dt = &mut 0.0f64;
    while (slot.motion_us.load(Ordering::Relaxed) as f64) / 1e6 < target_s {
        let text = CString::new(PROMPTS[(index + round as usize) % PROMPTS.len()]).unwrap();
        let mut cfg = cg_stream_config::default();
        unsafe { cg_stream_config_init(&mut cfg) };
        cfg.seed = (index as u64) << 32 | round;
        cfg.use_defaults &= !CG_USE_DEFAULT_SEED;
        let mut s = null_mut();
        let st = unsafe { cg_start(engine.0, text.as_ptr(), &cfg, &mut s) };
        if st != cg_status::CG_OK {
            eprintln!("stream slot {index}: cg_start failed: {st:?}: {}", last_error());
            slot.errors.fetch_add(1, Ordering::Relaxed);
            std::thread::sleep(Duration::from_millis(100));
            continue;
        }
        slot.streams.fetch_add(1, Ordering::Relaxed);
        // Motion is counted as it arrives, one frame period per frame; the period comes
        // from the first two frames' timestamps (the bundle's fps).
        let mut n = 0u64;
        let mut t_first = 0.0;
        let end = loop {
            match unsafe { cg_stream_wait(s, 100, &mut f) } {
                cg_status::CG_OK => {
                    slot.frames.fetch_add(1, Ordering::Relaxed);
                    n += 1;
                    match n {
                        1 => t_first = f.time_s,
                        2 => {
                            *dt = f.time_s - t_first;
                            slot.motion_us.fetch_add((2.0 * *dt * 1e6) as u64, Ordering::Relaxed);
                        }
                        _ => {
                            slot.motion_us.fetch_add((*dt * 1e6) as u64, Ordering::Relaxed);
                        }
                    }
                }
                cg_status::CG_PENDING => {}
                other => break other,
            }
        };
        if n == 1 {
            slot.motion_us.fetch_add((*dt * 1e6) as u64, Ordering::Relaxed);
        }
        if end != cg_status::CG_END {
            eprintln!("stream slot {index}: ended with {end:?}: {}", last_error());
            slot.errors.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { cg_stream_destroy(s) };
        round += 1;
    }
    slot.done.store(true, Ordering::Relaxed);
}

fn main() {
    let args = parse_args();
    let rss_process_start = proc_status("VmRSS");
    let mut ecfg = cg_engine_config::default();
    unsafe { cg_engine_config_init(&mut ecfg) };
    let bundle_c = args.bundle.as_ref().map(|b| CString::new(b.as_str()).unwrap());
    ecfg.bundle_path = bundle_c.as_ref().map_or(null(), |c| c.as_ptr());
    ecfg.max_streams = args.streams as u32;
    ecfg.ring_capacity = args.ring;
    let t_load = Instant::now();
    let mut e = null_mut();
    if unsafe { cg_engine_create(&ecfg, &mut e) } != cg_status::CG_OK {
        eprintln!("cg_engine_create failed: {}", last_error());
        std::process::exit(1);
    }
    let load_s = t_load.elapsed().as_secs_f64();
    let engine = Arc::new(EngineHandle(e));
    let rss_start = proc_status("VmRSS");
    let target_s = args.minutes * 60.0;
    println!(
        "soak: {} streams x {:.1} min of motion each, bundle {}, ring {} frames, {} CPU cores",
        args.streams,
        args.minutes,
        args.bundle.as_deref().unwrap_or("(embedded default or COMGRASP_BUNDLE)"),
        args.ring,
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    println!(
        "engine loaded in {load_s:.2} s; VmRSS {:.1} MiB before, {:.1} MiB after loading",
        mib(rss_process_start),
        mib(rss_start)
    );

    let slots: Arc<Vec<Slot>> = Arc::new((0..args.streams).map(|_| Slot::default()).collect());
    let t0 = Instant::now();
    let workers: Vec<_> = (0..args.streams)
        .map(|i| {
            let (engine, slots) = (Arc::clone(&engine), Arc::clone(&slots));
            std::thread::Builder::new()
                .name(format!("soak-consumer-{i}"))
                .spawn(move || run_slot(&engine, i, target_s, &slots[i]))
                .unwrap()
        })
        .collect();

    let mut rss_peak = rss_start;
    let mut rss_warm: Option<u64> = None;
    let mut timeline: Vec<(f64, u64)> = Vec::new();
    let mut last_report = Instant::now();
    let mut last_frames = 0u64;
    loop {
        std::thread::sleep(Duration::from_millis(200));
        let all_done = slots.iter().all(|s| s.done.load(Ordering::Relaxed));
        let rss = proc_status("VmRSS");
        rss_peak = rss_peak.max(rss);
        let min_motion_s = slots.iter().map(|s| s.motion_us.load(Ordering::Relaxed)).min().unwrap_or(0) as f64 / 1e6;
        if rss_warm.is_none() && min_motion_s >= 0.2 * target_s {
            rss_warm = Some(rss);
            println!(
                "[{:7.1} s] warm-up mark (every stream has a fifth of its motion): VmRSS {:.1} MiB",
                t0.elapsed().as_secs_f64(),
                mib(rss)
            );
        }
        if last_report.elapsed().as_secs_f64() >= args.report_every || all_done {
            let frames: u64 = slots.iter().map(|s| s.frames.load(Ordering::Relaxed)).sum();
            let motion: Vec<f64> = slots.iter().map(|s| s.motion_us.load(Ordering::Relaxed) as f64 / 1e6).collect();
            let min_motion = motion.iter().cloned().fold(f64::INFINITY, f64::min);
            let interval = last_report.elapsed().as_secs_f64();
            println!(
                "[{:7.1} s] frames {frames:>9}  {:8.0} frames/s now  motion per stream min {:6.1} s / {:.0} s  streams started {:>5}  \
                 errors {}  VmRSS {:.1} MiB  threads {}",
                t0.elapsed().as_secs_f64(),
                (frames - last_frames) as f64 / interval,
                min_motion,
                target_s,
                slots.iter().map(|s| s.streams.load(Ordering::Relaxed)).sum::<u64>(),
                slots.iter().map(|s| s.errors.load(Ordering::Relaxed)).sum::<u64>(),
                mib(rss),
                proc_status("Threads"),
            );
            last_frames = frames;
            last_report = Instant::now();
            timeline.push((t0.elapsed().as_secs_f64(), rss));
        }
        if all_done {
            break;
        }
    }
    for w in workers {
        w.join().unwrap();
    }
    let wall = t0.elapsed().as_secs_f64();
    let frames: u64 = slots.iter().map(|s| s.frames.load(Ordering::Relaxed)).sum();
    let motion_total: f64 = slots.iter().map(|s| s.motion_us.load(Ordering::Relaxed) as f64 / 1e6).sum();
    let streams: u64 = slots.iter().map(|s| s.streams.load(Ordering::Relaxed)).sum();
    let errors: u64 = slots.iter().map(|s| s.errors.load(Ordering::Relaxed)).sum();
    let mut live = u32::MAX;
    unsafe { cg_engine_stream_count(engine.0, &mut live) };
    let rss_end = proc_status("VmRSS");
    let baseline = rss_warm.unwrap_or(rss_start);
    let growth = rss_end.saturating_sub(baseline);
    println!("---");
    println!("streams: {} at once, {streams} started in all, {errors} errors, {live} alive at the end", args.streams);
    println!("frames: {frames} in {wall:.1} s wall = {:.0} frames/s", frames as f64 / wall);
    println!(
        "motion: {motion_total:.0} s generated ({:.1} min per stream), {:.1}x real time overall, {:.2}x real time per stream",
        motion_total / args.streams as f64 / 60.0,
        motion_total / wall,
        motion_total / wall / args.streams as f64
    );
    println!(
        "VmRSS: {:.1} MiB after load, {:.1} MiB at the warm-up mark, {:.1} MiB peak (sampled every 0.2 s), {:.1} MiB at \
         the end (growth since the warm-up mark {:.1} MiB, bound {:.0} MiB); VmHWM {:.1} MiB",
        mib(rss_start), mib(baseline), mib(rss_peak), mib(rss_end), mib(growth), args.max_rss_growth_mib,
        mib(proc_status("VmHWM"))
    );
    let line: Vec<String> = timeline.iter().map(|(t, r)| format!("{t:.0}s {:.0}", mib(*r))).collect();
    println!("VmRSS timeline (MiB): {}", line.join(", "));
    let ok = errors == 0 && live == 0 && mib(growth) <= args.max_rss_growth_mib;
    unsafe { cg_engine_destroy(engine.0) };
    println!("{}", if ok { "soak: OK" } else { "soak: FAILED" });
    std::process::exit(if ok { 0 } else { 1 });
}
