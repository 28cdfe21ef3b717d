//! `comgrasp bench --streams N[,N...]`: crowds of streams on one engine, the crowd
//! scheduler against a worker thread per stream, measured side by side in interleaved
//! rounds (round r runs every N on both, one after the other, so drift of the machine hits
//! both alike).
//!
//! Per N and scheduling, over the rounds:
//! * **total RTF**: frames of all N streams ÷ the wall time from the first start to the
//!   last frame ÷ fps (the host drains every ring as fast as it can);
//! * **slowest RTF**: the smallest of each stream's frames ÷ (its last frame - its start) ÷ fps;
//! * **TTFF** p50/p99 (a second run of the same crowd, so the probes' work does not count
//!   against the throughput): probe streams started one after the other while the crowd runs
//!   (from the moment every crowd stream has produced a frame), start -> first frame
//!   (the host sleeps 0.2 ms when a sweep over the rings found nothing, as a game would
//!   rather than spin);
//! * **RSS**: the process's resident set while the N streams are alive, and its peak so far.
//!
//! Every stream generates a fixed length (`min_len = max_len = --steps`, default 16 token
//! steps = 256 frames) so both schedulings do the same work; prompts and seeds vary by
//! stream. Never a timing assertion: machines are noisy.
use std::time::{Duration, Instant};

use comgrasp::config::{RuntimeOptions, Scheduling};
use comgrasp::{Engine, EngineConfig, Frame, PollResult, Stream, StreamConfig};
use serde_json::{json, Value};

const PROMPTS: [&str; 4] = [
    "A woman drinks from the mug.",
    "Someone grabs the large cube with their left hand and lifts it up.",
    "The woman hands the sphere over from her right hand to her left.",
    "A man picks up the bowl and inspects it.",
];

/// What one crowd run measured.
struct Run {
    total_rtf: f64,
    slowest_rtf: f64,
    ttff_ms: Vec<f64>,
    rss_live: Option<u64>,
    frames: u64,
}

/// The crowd benchmark's settings.
pub struct Crowd {
    pub counts: Vec<usize>,
    pub rounds: usize,
    pub probes: usize,
    pub steps: Option<usize>,
    pub threads: Option<usize>,
    pub crowd_only: bool,
    /// Every stream's guidance scale (None: the bundle's).
    pub guidance: Option<f64>,
    pub bundle: Option<std::path::PathBuf>,
    pub runtime: RuntimeOptions,
}

pub fn run(c: &Crowd, rss: fn() -> (Option<u64>, Option<u64>)) -> Result<Value, String> {
    let err = |e: comgrasp::Error| e.to_string();
    let most = c.counts.iter().max().copied().unwrap_or(1);
    let engine = |scheduling| {
        let runtime = RuntimeOptions { scheduling, scheduler_threads: c.threads, ..c.runtime };
        Engine::new(EngineConfig {
            bundle_path: c.bundle.clone(),
            max_streams: (most + c.probes + 1).min(comgrasp::engine::MAX_STREAMS_LIMIT),
            runtime,
            ..Default::default()
        })
        .map_err(err)
    };
    let crowd = engine(Scheduling::Crowd)?;
    let per_stream = if c.crowd_only { None } else { Some(engine(Scheduling::PerStream)?) };
    let m = &crowd.bundle().ok_or("no bundle")?.manifest;
    let (fps, steps) = (m.fps, c.steps.unwrap_or(16).min(m.l_max));
    let each = Each { steps, guidance: c.guidance };
    let mut runs: Vec<[Vec<Run>; 2]> = c.counts.iter().map(|_| [Vec::new(), Vec::new()]).collect();
    for round in 0..c.rounds {
        for (i, &n) in c.counts.iter().enumerate() {
            for (k, e) in std::iter::once(&crowd).chain(&per_stream).enumerate() {
                // throughput alone, then the time to first frame of probes among the crowd
                // (the probes' own work would otherwise count against small crowds)
                let mut r = crowd_run(e, n, each, 0, round, fps, rss).map_err(|e| format!("N={n}: {e}"))?;
                if c.probes > 0 {
                    let p = crowd_run(e, n, each, c.probes, round, fps, rss).map_err(|e| format!("N={n}: {e}"))?;
                    r.ttff_ms = p.ttff_ms;
                }
                runs[i][k].push(r);
            }
        }
    }
    let median = |mut v: Vec<f64>| -> f64 {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let pct = |mut v: Vec<f64>, p: f64| -> f64 {
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            return f64::NAN;
        }
        v[((v.len() as f64 - 1.0) * p).round() as usize]
    };
    let mut rows = Vec::new();
    for (i, &n) in c.counts.iter().enumerate() {
        let side = |runs: &[Run]| {
            let ttff: Vec<f64> = runs.iter().flat_map(|r| r.ttff_ms.iter().copied()).collect();
            json!({
                "total_rtf": median(runs.iter().map(|r| r.total_rtf).collect()),
                "frames_per_s": median(runs.iter().map(|r| r.total_rtf * fps).collect()),
                "slowest_rtf": median(runs.iter().map(|r| r.slowest_rtf).collect()),
                "ttff_p50_ms": pct(ttff.clone(), 0.5),
                "ttff_p99_ms": pct(ttff.clone(), 0.99),
                "ttff_probes": ttff.len(),
                "rss_live_mib": runs.iter().filter_map(|r| r.rss_live).max().map(|b| b as f64 / (1 << 20) as f64),
                "frames": runs.first().map_or(0, |r| r.frames),
            })
        };
        let (cr, ps) = (side(&runs[i][0]), side(&runs[i][1]));
        let ratio = cr["total_rtf"].as_f64().unwrap_or(f64::NAN) / ps["total_rtf"].as_f64().unwrap_or(f64::NAN);
        rows.push(json!({ "streams": n, "crowd": cr, "per_stream": ps, "crowd_over_per_stream": ratio }));
    }
    let (peak, _) = rss();
    Ok(json!({
        "fps": fps,
        "steps_per_stream": steps,
        "guidance": c.guidance.unwrap_or(m.sampling.guidance),
        "frames_per_stream": steps * m.frames_per_token,
        "rounds": c.rounds,
        "scheduler_threads": crowd.scheduler_threads(),
        "rss_peak_mib": peak.map(|b| b as f64 / (1 << 20) as f64),
        "rows": rows,
    }))
}

/// Prints the crowd report.
pub fn print(r: &Value) {
    println!(
        "crowd: {} frames per stream at {} fps, guidance {}, {} rounds, crowd scheduler threads {}, peak RSS {:.0} MiB",
        r["frames_per_stream"],
        r["fps"],
        r["guidance"],
        r["rounds"],
        r["scheduler_threads"],
        r["rss_peak_mib"].as_f64().unwrap_or(0.0)
    );
    println!(
        "{:>7} | {:>22} | {:>22} | {:>22} | {:>10} | {:>10}",
        "streams", "total RTF crowd / thr", "slowest RTF crowd / thr", "TTFF p50/p99 ms crowd", "RSS MiB", "crowd/thr"
    );
    for row in r["rows"].as_array().into_iter().flatten() {
        let (c, p) = (&row["crowd"], &row["per_stream"]);
        let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
        println!(
            "{:>7} | {:>10.1} / {:>9.1} | {:>10.2} / {:>9.2} | {:>9.1} / {:>9.1} | {:>10.0} | {:>9.2}x",
            row["streams"],
            f(&c["total_rtf"]),
            f(&p["total_rtf"]),
            f(&c["slowest_rtf"]),
            f(&p["slowest_rtf"]),
            f(&c["ttff_p50_ms"]),
            f(&c["ttff_p99_ms"]),
            f(&c["rss_live_mib"]),
            f(&row["crowd_over_per_stream"]),
        );
        println!("{:>7} | per-stream TTFF p50/p99 {:.1} / {:.1} ms", "", f(&p["ttff_p50_ms"]), f(&p["ttff_p99_ms"]));
    }
}

/// What every stream of a crowd runs: token steps and guidance scale (None: the bundle's).
#[derive(Clone, Copy)]
struct Each {
    steps: usize,
    guidance: Option<f64>,
}

/// One crowd of `n` streams on `engine`, drained by this thread, with `probes` streams
/// started among them for the time to first frame.
fn crowd_run(
    engine: &Engine,
    n: usize,
    each: Each,
    probes: usize,
    round: usize,
    fps: f64,
    rss: fn() -> (Option<u64>, Option<u64>),
) -> Result<Run, String> {
    let err = |e: comgrasp::Error| e.to_string();
    let opts = |seed: u64, len: usize| StreamConfig {
        seed: Some(seed),
        min_len: Some(len as u32),
        max_len: Some(len as u32),
        guidance: each.guidance,
        ..Default::default()
    };
    let steps = each.steps;
    let t0 = Instant::now();
    let mut streams: Vec<(Stream, Instant, Option<Instant>, u64, bool)> = Vec::with_capacity(n);
    for i in 0..n {
        let s = engine.start(PROMPTS[i % PROMPTS.len()], opts((round * 1000 + i) as u64, steps)).map_err(err)?;
        streams.push((s, Instant::now(), None, 0, false));
    }
    let mut f = Frame::default();
    let mut probe: Option<(Stream, Instant)> = None;
    let mut done_probes: Vec<Stream> = Vec::with_capacity(probes);
    let mut ttff = Vec::with_capacity(probes);
    let mut rss_live = None;
    let mut left = n;
    let deadline = t0 + Duration::from_secs(600);
    while left > 0 {
        if Instant::now() > deadline {
            return Err("the crowd did not finish within 600 s".into());
        }
        let mut any = false;
        for (s, _, last, frames, ended) in streams.iter_mut().filter(|s| !s.4) {
            loop {
                match s.poll(&mut f) {
                    PollResult::Frame => {
                        *frames += 1;
                        *last = Some(Instant::now());
                        any = true;
                    }
                    PollResult::Pending => break,
                    PollResult::End => {
                        *ended = true;
                        left -= 1;
                        break;
                    }
                    other => return Err(format!("stream {}: {other:?} {:?}", s.id(), s.error())),
                }
            }
        }
        let all_started = streams.iter().all(|s| s.3 > 0);
        if rss_live.is_none() && all_started {
            rss_live = rss().1;
        }
        // probes: one at a time, once every crowd stream is under way, while it runs
        if let Some((p, at)) = &mut probe {
            match p.poll(&mut f) {
                PollResult::Frame => {
                    ttff.push(at.elapsed().as_secs_f64() * 1e3);
                    p.cancel();
                    if let Some((p, _)) = probe.take() {
                        done_probes.push(p);
                    }
                }
                PollResult::Pending => {}
                other => return Err(format!("probe: {other:?} {:?}", p.error())),
            }
        } else if all_started && ttff.len() < probes {
            let seed = (round * 1000 + n + ttff.len()) as u64;
            let p = engine.start(PROMPTS[ttff.len() % PROMPTS.len()], opts(seed, 2)).map_err(err)?;
            probe = Some((p, Instant::now()));
        }
        if !any {
            // A host polls once a frame, not in a busy loop: spinning here would take a
            // core from the schedulers (the probes' TTFF is then good to ~0.2 ms).
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    let wall = streams.iter().filter_map(|s| s.2).max().map_or(0.0, |t| (t - t0).as_secs_f64());
    let total: u64 = streams.iter().map(|s| s.3).sum();
    let slowest = streams
        .iter()
        .map(|(_, start, last, frames, _)| {
            *frames as f64 / last.map_or(f64::INFINITY, |l| (l - *start).as_secs_f64()) / fps
        })
        .fold(f64::INFINITY, f64::min);
    drop(probe);
    drop(done_probes);
    Ok(Run { total_rtf: total as f64 / wall / fps, slowest_rtf: slowest, ttff_ms: ttff, rss_live, frames: total })
}
