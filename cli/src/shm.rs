//! Shared-memory commands: `publish` (an engine that publishes over iceoryx2 while a host
//! polls), `subscribe` (a consumer in its own process) and `shm-bench` (what publishing
//! costs: frames per second through iceoryx2 with 1 and N subscriber processes, latency,
//! and the producer's generation time with and without publishing, as a ratio).
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use comgrasp::shm::{cg_stream_event, FramePublisher, FrameSubscriber, CG_MAX_SUBSCRIBER_BUFFER};
use comgrasp::{Engine, EngineConfig, Frame, PollResult, StreamConfig};

use crate::Failure;

/// `comgrasp publish`: runs one generation in an engine that also publishes every frame over
/// iceoryx2 shared memory on comgrasp/NAME/frames (and stream events on comgrasp/NAME/events),
/// while this process polls the frames like a host would.
#[derive(clap::Args)]
pub struct PublishArgs {
    /// Publish name (ASCII letters, digits, _ - .).
    #[arg(long, value_name = "NAME")]
    name: String,
    /// The prompt.
    #[arg(long, value_name = "PROMPT")]
    text: String,
    /// Model bundle (default: COMGRASP_BUNDLE, else the built-in one).
    #[arg(long, value_name = "DIR")]
    bundle: Option<PathBuf>,
    /// Sampler seed (default: the bundle's).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// No end before N token steps (default: the bundle's).
    #[arg(long, value_name = "N")]
    min_len: Option<u32>,
    /// End at N token steps at the latest (default: the bundle's).
    #[arg(long, value_name = "N")]
    max_len: Option<u32>,
    /// Wait (up to 30 s) until N subscribers are connected first.
    #[arg(long, value_name = "N", default_value_t = 0)]
    wait_subscribers: u64,
    /// Sleep MS between polls, like a game tick (default: wait for frames).
    #[arg(long, value_name = "MS", default_value_t = 0)]
    poll_interval_ms: u64,
    /// Frames the stream buffers before its worker waits.
    #[arg(long, value_name = "N", default_value_t = 256)]
    ring: usize,
    /// Write the bytes of every polled cg_frame to FILE.
    #[arg(long, value_name = "FILE")]
    raw: Option<String>,
    /// The same run without shared memory (for comparisons).
    #[arg(long)]
    no_publish: bool,
}

/// `comgrasp subscribe`: reads the frames an engine publishes under NAME (in any process).
/// Prints `ready` once subscribed, one line per stream event and a summary line.
#[derive(clap::Args)]
pub struct SubscribeArgs {
    /// The publish name.
    #[arg(long, value_name = "NAME")]
    name: String,
    /// Write the bytes of every received cg_frame to FILE.
    #[arg(long, value_name = "FILE")]
    raw: Option<String>,
    /// Stop after K frames with is_last = 1.
    #[arg(long, value_name = "K", default_value_t = 1)]
    streams: u64,
    /// Give up after T seconds (exit code 3).
    #[arg(long, value_name = "T", default_value_t = 60.0)]
    timeout_s: f64,
    /// Frames kept between reads, 1..=256.
    #[arg(long, value_name = "N", default_value_t = CG_MAX_SUBSCRIBER_BUFFER)]
    buffer: usize,
    /// Sleep D microseconds after every frame (a slow consumer).
    #[arg(long, value_name = "D", default_value_t = 0)]
    read_delay_us: u64,
    /// Report publish-to-receive latency (needs frames whose time_s is a CLOCK_MONOTONIC
    /// stamp, as shm-bench sends).
    #[arg(long)]
    latency: bool,
}

/// `comgrasp shm-bench`: (1) synthetic frames published as fast as possible with each number
/// of subscriber processes in LIST: frames/s, received, dropped, latency; (2) the engine's
/// generation time per frame with and without publishing (R interleaved runs each, one
/// subscriber attached), and their ratio.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Synthetic frames per subscriber count.
    #[arg(long, value_name = "N", default_value_t = 200_000)]
    frames: u64,
    /// Subscriber process counts, comma-separated.
    #[arg(long, value_name = "LIST", value_delimiter = ',', default_value = "1,4")]
    subscribers: Vec<usize>,
    /// Model bundle (default: COMGRASP_BUNDLE, else the built-in one).
    #[arg(long, value_name = "DIR")]
    bundle: Option<PathBuf>,
    /// Interleaved runs with and without publishing.
    #[arg(long, value_name = "R", default_value_t = 5)]
    runs: usize,
}

/// `comgrasp shm-clean`: reclaims what killed processes left in shared memory.
pub fn clean() -> Result<(), Failure> {
    let (cleaned, failed) = comgrasp::shm::reclaim_dead_nodes().map_err(run_err)?;
    println!("dead iceoryx2 nodes cleaned: {cleaned}, could not be cleaned: {failed}");
    if failed > 0 {
        return Err(run_err("some dead nodes could not be cleaned (permissions? run as their user)"));
    }
    Ok(())
}

fn run_err(e: impl std::fmt::Display) -> Failure {
    Failure::Run(e.to_string())
}

/// CLOCK_MONOTONIC in seconds: one clock for every process on the machine.
fn monotonic_s() -> f64 {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: valid out-pointer; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut t) };
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

fn frame_bytes(f: &Frame) -> &[u8] {
    // SAFETY: cg_frame is repr(C) plain data without implicit padding (a test checks the
    // layout), so all its bytes are initialized.
    unsafe { std::slice::from_raw_parts(f as *const Frame as *const u8, std::mem::size_of::<Frame>()) }
}

fn create_raw(path: Option<&str>) -> Result<Option<BufWriter<File>>, Failure> {
    path.map(|p| File::create(p).map(BufWriter::new).map_err(|e| run_err(format!("cannot create {p}: {e}"))))
        .transpose()
}

pub fn publish(o: PublishArgs) -> Result<(), Failure> {
    let (name, text) = (o.name, o.text);
    let stream = StreamConfig { seed: o.seed, min_len: o.min_len, max_len: o.max_len, ..Default::default() };
    let wait_subscribers = o.wait_subscribers;
    let interval = Duration::from_millis(o.poll_interval_ms);
    let engine = Engine::new(EngineConfig {
        bundle_path: o.bundle,
        ring_capacity: o.ring,
        publish_name: (!o.no_publish).then_some(name),
        runtime: comgrasp::config::RuntimeOptions::from_env().map_err(run_err)?,
        ..Default::default()
    })
    .map_err(run_err)?;
    let mut raw = create_raw(o.raw.as_deref())?;

    let deadline = Instant::now() + Duration::from_secs(30);
    while engine.publisher_stats().map_or(0, |s| s.subscribers) < wait_subscribers {
        if Instant::now() > deadline {
            return Err(run_err(format!("fewer than {wait_subscribers} subscribers after 30 s")));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    println!("ready");
    let _ = std::io::stdout().flush();

    let t0 = Instant::now();
    let mut s = engine.start(&text, stream).map_err(run_err)?;
    let mut f = Frame::default();
    let mut frames = 0u64;
    loop {
        let r = if interval.is_zero() { s.wait(&mut f, Duration::from_millis(100)) } else { s.poll(&mut f) };
        match r {
            PollResult::Frame => {
                frames += 1;
                if let Some(w) = raw.as_mut() {
                    w.write_all(frame_bytes(&f)).map_err(run_err)?;
                }
            }
            PollResult::Pending => std::thread::sleep(interval),
            PollResult::End => break,
            PollResult::Cancelled => return Err(run_err("the stream was cancelled")),
            PollResult::Error => return Err(run_err(s.error().map_or("the stream failed".into(), |e| e.to_string()))),
        }
        if !interval.is_zero() && r == PollResult::Frame {
            std::thread::sleep(interval);
        }
    }
    let generation = t0.elapsed();
    drop(s);
    if let Some(mut w) = raw {
        w.flush().map_err(run_err)?;
    }
    let mut line = format!(
        "frames: {frames} generation_ms: {:.1} per_frame_us: {:.1}",
        generation.as_secs_f64() * 1e3,
        generation.as_secs_f64() * 1e6 / frames.max(1) as f64
    );
    if let Some(p) = engine.publisher_stats() {
        line += &format!(
            " published: {} skipped: {} events: {} subscribers: {}",
            p.frames_published, p.frames_skipped, p.events_published, p.subscribers
        );
    }
    println!("{line}");
    Ok(())
}

pub fn subscribe(o: SubscribeArgs) -> Result<(), Failure> {
    let name = o.name.as_str();
    let streams = o.streams;
    let timeout = Duration::try_from_secs_f64(o.timeout_s)
        .map_err(|_| Failure::Usage(format!("subscribe: --timeout-s {} is not a duration", o.timeout_s)))?;
    let delay = Duration::from_micros(o.read_delay_us);
    let latency = o.latency;
    let mut sub = FrameSubscriber::open(name, o.buffer).map_err(run_err)?;
    let mut raw = create_raw(o.raw.as_deref())?;
    println!("ready");
    let _ = std::io::stdout().flush();

    let deadline = Instant::now() + timeout;
    let (mut finished, mut frames) = (0u64, 0u64);
    let mut lat_us: Vec<f64> = Vec::new();
    let mut first: Option<Instant> = None;
    let mut f = Frame::default();
    let mut e = cg_stream_event::default();
    while finished < streams {
        let mut idle = true;
        while sub.receive_event(&mut e).map_err(run_err)? {
            println!("event {} stream {} frames {} text {:?}", e.kind, e.stream_id, e.frame_count, e.text_str());
            idle = false;
        }
        while finished < streams && sub.receive(&mut f).map_err(run_err)? {
            if latency {
                lat_us.push((monotonic_s() - f.time_s) * 1e6);
            }
            first.get_or_insert_with(Instant::now);
            frames += 1;
            finished += u64::from(f.is_last);
            if let Some(w) = raw.as_mut() {
                w.write_all(frame_bytes(&f)).map_err(run_err)?;
            }
            if !delay.is_zero() {
                std::thread::sleep(delay);
            }
            idle = false;
        }
        if Instant::now() > deadline {
            eprintln!("subscribe: timeout: {finished} of {streams} streams finished, {frames} frames");
            std::process::exit(3);
        }
        if idle {
            std::thread::sleep(Duration::from_micros(100));
        }
    }
    if let Some(mut w) = raw {
        w.flush().map_err(run_err)?;
    }
    let s = sub.stats();
    let secs = first.map_or(0.0, |t| t.elapsed().as_secs_f64());
    let mut line =
        format!("frames: {frames} dropped: {} events: {} seconds: {secs:.4}", s.frames_dropped, s.events_received);
    if !lat_us.is_empty() {
        lat_us.sort_by(f64::total_cmp);
        let q = |p: f64| lat_us[((lat_us.len() - 1) as f64 * p) as usize];
        line += &format!(" latency_us_p50: {:.1} latency_us_p99: {:.1}", q(0.5), q(0.99));
    }
    println!("{line}");
    Ok(())
}

/// A subscriber child process (`comgrasp subscribe ...`), started and waited for "ready".
fn spawn_subscriber(args: &[&str]) -> Result<(Child, BufReader<std::process::ChildStdout>), Failure> {
    let exe = std::env::current_exe().map_err(run_err)?;
    let mut child = Command::new(exe).arg("subscribe").args(args).stdout(Stdio::piped()).spawn().map_err(run_err)?;
    let mut out = BufReader::new(child.stdout.take().ok_or_else(|| run_err("no stdout"))?);
    let mut line = String::new();
    out.read_line(&mut line).map_err(run_err)?;
    if line.trim() != "ready" {
        let _ = child.kill();
        return Err(run_err(format!("subscriber did not start: {line:?}")));
    }
    Ok((child, out))
}

fn finish_subscriber((mut child, mut out): (Child, BufReader<std::process::ChildStdout>)) -> Result<String, Failure> {
    let mut last = String::new();
    let mut line = String::new();
    while out.read_line(&mut line).map_err(run_err)? > 0 {
        if line.starts_with("frames:") {
            last = line.trim().to_string();
        }
        line.clear();
    }
    let status = child.wait().map_err(run_err)?;
    if !status.success() {
        return Err(run_err(format!("subscriber failed: {status}")));
    }
    Ok(last)
}

fn field(line: &str, key: &str) -> f64 {
    line.split_whitespace().skip_while(|w| *w != key).nth(1).and_then(|v| v.parse().ok()).unwrap_or(f64::NAN)
}

pub fn bench(o: BenchArgs) -> Result<(), Failure> {
    let (n, runs, counts) = (o.frames, o.runs, o.subscribers);
    let pid = std::process::id();

    println!(
        "# throughput: {n} synthetic frames ({} bytes each) published as fast as possible",
        std::mem::size_of::<Frame>()
    );
    for &k in &counts {
        let name = format!("shm-bench-{pid}-{k}");
        let publisher = FramePublisher::new(&name).map_err(run_err)?;
        let subs = (0..k)
            .map(|_| spawn_subscriber(&["--name", &name, "--latency", "--timeout-s", "120"]))
            .collect::<Result<Vec<_>, _>>()?;
        while publisher.stats().subscribers < k as u64 {
            std::thread::sleep(Duration::from_millis(1));
        }
        let mut f = Frame::default();
        let t0 = Instant::now();
        for i in 0..n {
            f.frame_index = i;
            f.time_s = monotonic_s();
            f.is_last = u8::from(i + 1 == n);
            publisher.publish_frame(&f);
        }
        let secs = t0.elapsed().as_secs_f64();
        let lines = subs.into_iter().map(finish_subscriber).collect::<Result<Vec<_>, _>>()?;
        let st = publisher.stats();
        println!(
            "subscribers: {k} publish_fps: {:.0} per_frame_us: {:.2} skipped: {}",
            n as f64 / secs,
            secs * 1e6 / n as f64,
            st.frames_skipped
        );
        for l in &lines {
            println!("  subscriber {l} receive_fps: {:.0}", field(l, "frames:") / field(l, "seconds:"));
        }
    }

    println!("# producer: generation time per frame, {runs} interleaved runs each");
    let name = format!("shm-bench-{pid}-engine");
    let mut base = EngineConfig {
        bundle_path: o.bundle,
        runtime: comgrasp::config::RuntimeOptions::from_env().map_err(run_err)?,
        ..Default::default()
    };
    let plain = Engine::new(base.clone()).map_err(run_err)?;
    base.publish_name = Some(name.clone());
    let publishing = Engine::new(base).map_err(run_err)?;
    let sub = spawn_subscriber(&["--name", &name, "--streams", &runs.to_string(), "--timeout-s", "600"])?;
    while publishing.publisher_stats().map_or(0, |s| s.subscribers) < 1 {
        std::thread::sleep(Duration::from_millis(1));
    }
    let opts = StreamConfig { seed: Some(1), ..Default::default() };
    let one = |e: &Engine| -> Result<(f64, u64), Failure> {
        let t0 = Instant::now();
        let mut s = e.start("A woman drinks from the mug", opts.clone()).map_err(run_err)?;
        let mut f = Frame::default();
        let mut frames = 0u64;
        loop {
            match s.wait(&mut f, Duration::from_millis(100)) {
                PollResult::Frame => frames += 1,
                PollResult::Pending => {}
                PollResult::End => break,
                r => return Err(run_err(format!("stream: {r:?}"))),
            }
        }
        Ok((t0.elapsed().as_secs_f64() * 1e6 / frames as f64, frames))
    };
    let (mut without, mut with) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        without.push(one(&plain)?.0);
        let (us, frames) = one(&publishing)?;
        with.push(us);
        println!(
            "  run: frames {frames} without_us_per_frame {:.1} with_us_per_frame {us:.1}",
            without.last().unwrap()
        );
    }
    let line = finish_subscriber(sub)?;
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (a, b) = (median(&mut without), median(&mut with));
    println!("producer: without_us_per_frame {a:.1} with_us_per_frame {b:.1} ratio_with_over_without {:.3}", b / a);
    println!("  subscriber {line}");
    Ok(())
}
