//! `comgrasp bench`: the engine's speed on one bundle (DESIGN §7), as a report or as JSON
//! for `scripts/bench.sh`, which runs the Python references (onnxruntime, PyTorch with and
//! without KV cache) on the same bundle, prompt and seed and prints the ratios.
//!
//! What is measured, in this order (wall clock, `Instant`; medians and p90 over the runs):
//! 1. **load**: `Bundle::load` (manifest, SHA-256 of every file, three graphs into tract).
//! 2. **text**: `TextEncoder::embed` of the prompt (tokenizer + encoder graph + pooling).
//! 3. **step**: `StepModel::step` with the real, Rust-owned KV cache: `--warmup` steps, a
//!    reset, then the `--steps` steps of the benchmark sequence. The sampler runs between
//!    steps exactly as in a stream (timed apart), so the step loop draws the stream's tokens.
//!    The sequence length is fixed: `min_len = max_len = --steps`, so End is never sampled
//!    early and every runtime does the same number of steps.
//! 4. **decode**: `DecoderModel::decode` of those tokens, one 16-frame chunk per token,
//!    after a warm-up chunk; the frame assembly of a chunk; the contact-consistency stage
//!    on a chunk (timed apart from the assembly, on the prompt's object, as the streams run it).
//! 5. **stream**: `--stream-runs` end-to-end generations through `Engine::start` and
//!    `Stream::wait` on the same loaded bundle: time to first frame (start -> first frame
//!    in the consumer's hands), frames per second over the whole generation and the
//!    real-time factor (frames/s ÷ fps). The frames of the first run are compared with
//!    frames assembled from the step loop's tokens: equal frames mean the stream generated
//!    the same tokens.
//! 6. **poll**: `Stream::poll` cost, timed in batches of [`POLL_BATCH`] calls (so the clock
//!    read is not what is measured): on an empty ring (while the first frame is computed)
//!    and on a ready frame (after the whole generation is buffered).
//! 7. **memory**: peak RSS (`VmHWM`), before the bandwidth probe.
//! 8. **bandwidth**: read bandwidth of a buffer much larger than the L3 (sum of u64, best
//!    of 5), 1 and 2 threads (and `--threads` if more), and the *bandwidth limit* of a
//!    step: the bytes one step must read ÷ that bandwidth. Two byte counts (see
//!    [`StepWeights`]): **fp32** = 4 bytes per element of every step-graph weight, what the
//!    tract (and onnxruntime) path holds and reads per step: int8-stored weights are
//!    dequantized to fp32 at load, so a 10 MB int8 graph reads ~38 MB; **int8** = the
//!    native path's bytes (int8 weights + their per-row scales + the fp32 tensors) when the
//!    bundle has a `transformer.native` section: the whole section, and what the native
//!    step reports it reads per step when it ran (`native_weight_bytes`, used for the
//!    native path's limit). Both add the full fp32 KV cache.
//!
//! Derived, the formula `python -m comgrasp_train.bench` uses for onnxruntime so the two
//! compare like with like: TTFF = text + the condition step (pos 0, whose logits sample the
//! first codes) + the first chunk decode; RTF = frames per token ÷ (median step + median
//! chunk) ÷ fps. The measured stream (5.) is the end-to-end truth; these are the ratios.
//! A stream that overlaps step k+1 with decode k (`model::overlap`, the default bundle) can
//! beat the derived numbers: its step and chunk run at once.
//!
//! Engine paths: the step and decoder graphs may each run on tract or on the native
//! kernels (`COMGRASP_STEP` / `COMGRASP_DECODER` = `tract` | `native`); the report names
//! the path the loaded models run ([`engine_paths`]) and fails when it is not the one asked for.
//!
//! Threads: tract runs single-threaded unless the crate is built with the
//! `multithread-mm` feature (tract-linalg's rayon executor); then `--threads N` installs an
//! N-thread executor. Without the feature `--threads` above 1 is reported, not applied.
//!
//! Never used in tests as a timing assertion; timings depend on the machine and its load.
// `multithread-mm` is an optional crate feature (see `set_tract_threads`); builds without
// it declared must not warn about the cfg.
#![allow(unexpected_cfgs)]
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use comgrasp::assemble::Pose;
use comgrasp::bundle::manifest::FRAME_DIM;
use comgrasp::bundle::{choose_object, N_STREAMS};
use comgrasp::config::RuntimeOptions;
use comgrasp::contact::GraspOnset;
use comgrasp::engine::{SourceFactory, StreamRequest};
use comgrasp::generator::{Generator, Pipeline};
use comgrasp::model::{decode_group, MAX_DECODE_GROUP};
use comgrasp::sampler::{SamplingParams, TokenSampler};
use comgrasp::Bundle;
use comgrasp::{ChunkSource, CoordinateSystem, Engine, EngineConfig, Frame, PollResult, StreamConfig};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

const DEFAULT_PROMPT: &str = "A woman drinks from the mug.";
/// Polls per timed batch in the poll-latency measurement.
const POLL_BATCH: usize = 64;

/// `comgrasp bench`: measures load time, text embedding, token step (real KV cache), decoder
/// chunk, end-to-end streams (time to first frame, frames/s, real-time factor), poll latency,
/// peak RSS and memory read bandwidth on one bundle, and prints the generated tokens so other
/// runtimes can be checked against them.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model bundle directory (default: COMGRASP_BUNDLE, else the default bundle embedded in
    /// the library, like generate).
    #[arg(long, value_name = "DIR")]
    bundle: Option<PathBuf>,
    /// The prompt.
    #[arg(long, value_name = "TEXT", default_value = DEFAULT_PROMPT)]
    prompt: String,
    /// Sampler seed (default: the bundle's).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Token steps per sequence, End forbidden before and forced after (default: the
    /// bundle's L_max).
    #[arg(long, value_name = "N", value_parser = at_least_one)]
    steps: Option<usize>,
    /// Untimed steps before the timed ones.
    #[arg(long, value_name = "N", default_value_t = 3)]
    warmup: usize,
    /// tract matmul threads (needs the multithread-mm feature; default 1); also the native
    /// step's and decoder's threads (1 or 2) unless COMGRASP_STEP_THREADS /
    /// COMGRASP_DECODER_THREADS are set (without --threads: their defaults, 2 on 2+ cores for
    /// big models).
    #[arg(long, value_name = "N", value_parser = at_least_one)]
    threads: Option<usize>,
    /// Sampling temperature (default: the bundle's).
    #[arg(long, value_name = "T")]
    temperature: Option<f64>,
    /// Top-k (default: the bundle's).
    #[arg(long, value_name = "K")]
    top_k: Option<u32>,
    /// Classifier-free guidance scale (default: the bundle's): above or below 1, every step
    /// (the step loop's, the streams' and the crowds' of --streams) also runs the null condition.
    #[arg(long, value_name = "S")]
    guidance: Option<f64>,
    /// End-to-end streams to time.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = at_least_one)]
    stream_runs: usize,
    /// Text embeddings to time.
    #[arg(long, value_name = "N", default_value_t = 10, value_parser = at_least_one)]
    text_runs: usize,
    /// Buffer of the bandwidth probe in MiB, 0 = skip.
    #[arg(long, value_name = "N", default_value_t = 512)]
    bandwidth_mib: usize,
    /// Print one JSON object instead of the report.
    #[arg(long)]
    json: bool,
    /// Streams keep the resting object where the model put it (no look-ahead for the first
    /// grasp before the first frame): run with and without it to see what placement costs.
    #[arg(long)]
    no_grasp_placement: bool,
    /// Streams leave the model's legs as they are (no planted feet): run with and without
    /// it to see what the feet cost the contact stage.
    #[arg(long)]
    free_feet: bool,
    /// Instead of the one-stream bench: crowds of N concurrent streams (comma-separated,
    /// e.g. 1,8,64,256) on the crowd scheduler and on a thread per stream, in interleaved
    /// rounds (cli/src/crowd_bench.rs); each stream runs --steps token steps (default 16).
    #[arg(long, value_name = "N,...", value_delimiter = ',', value_parser = at_least_one)]
    streams: Vec<usize>,
    /// Rounds of the crowd bench.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = at_least_one)]
    rounds: usize,
    /// Streams started among each crowd for the time to first frame.
    #[arg(long, value_name = "N", default_value_t = 20)]
    probes: usize,
    /// The crowd bench without the per-stream side (no ratio): profiling the scheduler.
    #[arg(long)]
    crowd_only: bool,
    /// Crowd scheduler threads (default: the engine's, cores minus one).
    #[arg(long, value_name = "N", value_parser = at_least_one)]
    scheduler_threads: Option<usize>,
}

/// A count that must be at least 1.
fn at_least_one(v: &str) -> Result<usize, String> {
    match v.trim().parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("{v:?} is not a whole number >= 1")),
    }
}

pub fn run(opts: Args) -> Result<(), String> {
    if !opts.streams.is_empty() {
        let c = crate::crowd_bench::Crowd {
            counts: opts.streams.clone(),
            rounds: opts.rounds,
            probes: opts.probes,
            steps: opts.steps,
            threads: opts.scheduler_threads,
            crowd_only: opts.crowd_only,
            guidance: opts.guidance,
            bundle: opts.bundle.clone(),
            runtime: runtime_options(&opts)?,
        };
        let report = crate::crowd_bench::run(&c, rss).map_err(|e| format!("bench --streams: {e}"))?;
        if opts.json {
            println!("{}", serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?);
        } else {
            crate::crowd_bench::print(&report);
        }
        return Ok(());
    }
    let report = bench(&opts).map_err(|e| format!("bench: {e}"))?;
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?);
    } else {
        print_report(&report);
    }
    Ok(())
}

// ------------------------------------------------------------------------------ statistics

/// Median, p90 (nearest rank), mean, min and max of a sample, in the unit of the input.
fn stats(xs: &[f64]) -> Value {
    if xs.is_empty() {
        return Value::Null;
    }
    let mut s = xs.to_vec();
    s.sort_by(f64::total_cmp);
    let rank = |q: f64| s[((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1];
    let median = if s.len() % 2 == 1 { s[s.len() / 2] } else { 0.5 * (s[s.len() / 2 - 1] + s[s.len() / 2]) };
    json!({
        "median": median, "p90": rank(0.9), "mean": s.iter().sum::<f64>() / s.len() as f64,
        "min": s[0], "max": s[s.len() - 1], "n": s.len(),
    })
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

// ------------------------------------------------------------------------------ threads

/// The runtime options: the `COMGRASP_*` variables (`RuntimeOptions::from_env`), where
/// `--threads` also sets the native kernels' threads (they take 1 or 2) unless their
/// variables do.
fn runtime_options(o: &Args) -> Result<RuntimeOptions, String> {
    let mut r = RuntimeOptions::from_env().map_err(|e| e.to_string())?;
    if let Some(threads) = o.threads {
        r.step_threads = r.step_threads.or(Some(threads.min(2)));
        r.decoder_threads = r.decoder_threads.or(Some(threads.min(2)));
    }
    Ok(r)
}

fn threads_name(t: Option<usize>) -> String {
    t.map_or_else(|| "auto".into(), |n| n.to_string())
}

/// Installs tract's N-thread matmul executor; returns the thread count tract will use.
#[cfg(feature = "multithread-mm")]
fn set_tract_threads(n: usize) -> (usize, &'static str) {
    use tract_onnx::tract_core::tract_linalg::multithread::{set_default_executor, Executor};
    if n > 1 {
        set_default_executor(Executor::multithread(n));
        (n, "multithread-mm executor")
    } else {
        (1, "single thread")
    }
}

#[cfg(not(feature = "multithread-mm"))]
fn set_tract_threads(n: usize) -> (usize, &'static str) {
    if n > 1 {
        (1, "single thread: this build has no multithread-mm feature, --threads ignored")
    } else {
        (1, "single thread")
    }
}

// ------------------------------------------------------------------------------ memory

/// (peak, current) resident set size in bytes, from /proc/self/status (Linux) or
/// getrusage (peak only) elsewhere.
fn rss() -> (Option<u64>, Option<u64>) {
    if let Ok(s) = std::fs::read_to_string("/proc/self/status") {
        let field = |name: &str| {
            s.lines()
                .find_map(|l| l.strip_prefix(name))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok().map(|kb| kb * 1024))
        };
        return (field("VmHWM:"), field("VmRSS:"));
    }
    // SAFETY: getrusage only writes the struct we pass.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } == 0 {
        let unit = if cfg!(target_os = "macos") { 1 } else { 1024 };
        return (Some(ru.ru_maxrss as u64 * unit), None);
    }
    (None, None)
}

/// Minor page faults of the process so far (0 where getrusage is unavailable).
fn minor_faults() -> u64 {
    // SAFETY: getrusage only writes the struct we pass.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } == 0 {
        ru.ru_minflt as u64
    } else {
        0
    }
}

fn mib(b: Option<u64>) -> Value {
    b.map_or(Value::Null, |b| json!(b as f64 / (1 << 20) as f64))
}

// ------------------------------------------------------------------------------ bandwidth

/// Sum of a slice with 8 independent accumulators (vectorizes; reads every byte).
fn sum_u64(xs: &[u64]) -> u64 {
    let mut acc = [0u64; 8];
    let mut chunks = xs.chunks_exact(8);
    for c in &mut chunks {
        for i in 0..8 {
            acc[i] = acc[i].wrapping_add(c[i]);
        }
    }
    let tail = chunks.remainder().iter().fold(0u64, |a, &x| a.wrapping_add(x));
    acc.iter().fold(tail, |a, &x| a.wrapping_add(x))
}

/// Best and median read bandwidth (bytes/s) of `buf` with `threads` threads over `reps` passes.
fn read_bandwidth(buf: &[u64], threads: usize, reps: usize) -> (f64, f64) {
    let bytes = std::mem::size_of_val(buf) as f64;
    let mut rates = Vec::with_capacity(reps);
    for _ in 0..reps {
        let t = Instant::now();
        let total = std::thread::scope(|s| {
            let per = buf.len().div_ceil(threads);
            let hs: Vec<_> = buf.chunks(per).map(|c| s.spawn(move || sum_u64(std::hint::black_box(c)))).collect();
            hs.into_iter().map(|h| h.join().unwrap_or(0)).fold(0u64, u64::wrapping_add)
        });
        std::hint::black_box(total);
        rates.push(bytes / t.elapsed().as_secs_f64());
    }
    rates.sort_by(f64::total_cmp);
    (rates[rates.len() - 1], rates[rates.len() / 2])
}

// ------------------------------------------------------------------------------ the bench

fn cpu_model() -> Option<String> {
    let s = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    s.lines().find_map(|l| l.strip_prefix("model name").map(|v| v.trim_start_matches([' ', '\t', ':']).to_string()))
}

/// Bytes of the step graph's files (the .onnx and any external data beside it).
fn step_graph_bytes(bundle: &Bundle) -> u64 {
    let file = &bundle.manifest.transformer.file;
    bundle.manifest.files.iter().filter(|(p, _)| p.starts_with(file.as_str())).map(|(_, e)| e.bytes).sum()
}

fn hash_tokens(tokens: &[[usize; N_STREAMS]]) -> String {
    // SHA-256 of the tokens as little-endian int64, row-major (steps, 4): what numpy's
    // `np.asarray(tokens, '<i8').tobytes()` hashes to on the Python side.
    let mut h = Sha256::new();
    for row in tokens {
        for &t in row {
            h.update((t as i64).to_le_bytes());
        }
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// Bytes one token step reads in weights (module doc, 8.).
struct StepWeights {
    /// 4 bytes per element of every weight initializer of the step graph.
    fp32: u64,
    /// The native section's bytes (int8 + scales + fp32 tensors), if the bundle has one.
    int8: Option<u64>,
    /// 4 bytes per element of the native section's tensors (a cross-check of `fp32`).
    native_fp32: Option<u64>,
    /// Stored int8 elements in the step graph (0: an fp32 graph).
    graph_int8_elems: u64,
}

/// ONNX data types of weights the runtimes hold as fp32 (FLOAT, UINT8, INT8, FLOAT16,
/// DOUBLE, BFLOAT16); int64/int32 initializers are shapes and indices.
const WEIGHT_DTYPES: [i32; 6] = [1, 2, 3, 10, 11, 16];

/// `step_onnx`: the step graph's bytes, `None` when the bundle has none (the embedded
/// default keeps only the native weights): the graph's figures then come from those.
fn step_weights(step_onnx: Option<&[u8]>, m: &comgrasp::bundle::manifest::Manifest) -> Result<StepWeights, String> {
    use comgrasp::bundle::manifest::NativeDtype;
    use tract_onnx::prelude::Framework;

    // Decodes the .onnx protobuf only (external data is not read), after the bundle is dropped.
    let proto = match step_onnx {
        Some(bytes) => Some(
            tract_onnx::onnx()
                .proto_model_for_read(&mut &bytes[..])
                .map_err(|e| format!("{}: {e:#}", m.transformer.file))?,
        ),
        None => None,
    };
    let (mut fp32, mut int8_elems) = (0u64, 0u64);
    for t in proto.iter().flat_map(|p| &p.graph).flat_map(|g| &g.initializer) {
        if WEIGHT_DTYPES.contains(&t.data_type) {
            let n = t.dims.iter().map(|&d| d.max(0) as u64).product::<u64>();
            fp32 += 4 * n;
            if t.data_type == 3 || t.data_type == 2 {
                int8_elems += n;
            }
        }
    }
    let (int8, native_fp32) = match &m.transformer.native {
        Some(nat) => {
            let (mut bytes, mut f) = (0u64, 0u64);
            for t in nat.tensors.values() {
                let n = t.shape.iter().map(|&d| d as u64).product::<u64>();
                f += 4 * n;
                bytes += match t.dtype {
                    NativeDtype::Int8 => n + 4 * t.shape.first().copied().unwrap_or(1) as u64,
                    NativeDtype::Int4 => n.div_ceil(2) + 4 * t.shape.first().copied().unwrap_or(1) as u64,
                    NativeDtype::Float32 => 4 * n,
                };
                if proto.is_none() && t.dtype == NativeDtype::Int8 {
                    int8_elems += n;
                }
            }
            if proto.is_none() {
                fp32 = f;
            }
            (Some(bytes), Some(f))
        }
        None => (None, None),
    };
    Ok(StepWeights { fp32, int8, native_fp32, graph_int8_elems: int8_elems })
}

/// The implementation that runs the step and the decoder graph, as the loaded models report
/// it: ("tract" | "native", same). `COMGRASP_STEP` / `COMGRASP_DECODER` choose at load
/// (unset: native when the bundle has native weights); a path that was asked for but did
/// not run is an error, so no benchmark row is labelled with a path that did not run.
fn engine_paths(bundle: &Bundle, r: &RuntimeOptions) -> Result<(String, String), String> {
    let step = bundle.step.backend().name();
    let decoder = bundle.decoder.backend().name();
    let asked = [r.step_backend.name(), r.decoder_backend.map_or("auto", |b| b.name())];
    for ((var, ran), asked) in [("COMGRASP_STEP", step), ("COMGRASP_DECODER", decoder)].into_iter().zip(asked) {
        if asked != "auto" && asked != ran {
            return Err(format!("{var}={asked} was asked for but the {ran} path was loaded"));
        }
    }
    Ok((step.to_string(), decoder.to_string()))
}

fn bench(o: &Args) -> Result<Value, String> {
    let err = |e: comgrasp::Error| e.to_string();
    let (tract_threads, thread_note) = set_tract_threads(o.threads.unwrap_or(1));
    let runtime = runtime_options(o)?;
    let native_threads = [threads_name(runtime.step_threads), threads_name(runtime.decoder_threads)];
    let rss_before = rss();

    // 1. load
    let t = Instant::now();
    let bundle = comgrasp::Bundle::select(o.bundle.as_deref(), &runtime).map_err(err)?;
    let load_ms = ms(t.elapsed());
    let (step_path, decoder_path) = engine_paths(&bundle, &runtime)?;
    let native_reported = bundle.step.native_weight_bytes().map(|b| b as u64);
    let rss_loaded = rss();
    let m = &bundle.manifest;
    let l_max = m.l_max;
    let steps = o.steps.unwrap_or(l_max);
    if steps > l_max {
        return Err(format!("--steps {steps} exceeds the bundle's L_max {l_max}"));
    }
    let seed = o.seed.unwrap_or(m.sampling.seed);
    let temperature = o.temperature.unwrap_or(m.sampling.temperature);
    let top_k = o.top_k.unwrap_or(m.sampling.top_k as u32);
    let guidance = comgrasp::config::guidance_scale(o.guidance.unwrap_or(m.sampling.guidance)).map_err(err)?;
    let params = SamplingParams::new(temperature, top_k, steps as u32, steps as u32, l_max as u32).map_err(err)?;
    let end_ids = m.end_ids();
    let pad_ids = m.pad_ids();
    let pad_usize = pad_ids.map(|p| p as usize);

    // 2. text
    let text_ids = bundle.text.tokenize(&o.prompt).map_err(err)?.input_ids;
    let emb = bundle.text.embed(&o.prompt).map_err(err)?; // warm-up
    let mut text_ms = Vec::with_capacity(o.text_runs);
    for _ in 0..o.text_runs {
        let t = Instant::now();
        let e = bundle.text.embed(&o.prompt).map_err(err)?;
        text_ms.push(ms(t.elapsed()));
        if e != emb {
            return Err("the text embedding differs between two runs".into());
        }
    }

    // 3. steps with the real cache (guided as the streams below are)
    let mut st = bundle.step.new_guided_state(guidance);
    let mut prev = pad_ids;
    let mut warm_sampler = TokenSampler::new(seed, params, end_ids, pad_usize);
    for k in 0..o.warmup.min(steps) {
        let logits = bundle.step.step(&mut st, prev, k, &emb).map_err(err)?;
        prev = warm_sampler.sample_step(k, logits).map_err(err)?.map(|c| c as i64);
    }
    st.reset().map_err(err)?;
    let mut sampler = TokenSampler::new(seed, params, end_ids, pad_usize);
    let mut prev = pad_ids;
    let mut tokens: Vec<[usize; N_STREAMS]> = Vec::with_capacity(steps);
    let (mut step_ms, mut sample_us) = (Vec::with_capacity(steps), Vec::with_capacity(steps));
    let faults0 = minor_faults();
    for k in 0..steps {
        let t = Instant::now();
        let logits = bundle.step.step(&mut st, prev, k, &emb).map_err(err)?;
        let t_step = t.elapsed();
        let t = Instant::now();
        let codes = sampler.sample_step(k, logits).map_err(err)?;
        sample_us.push(t.elapsed().as_secs_f64() * 1e6);
        step_ms.push(ms(t_step));
        if codes.iter().zip(&end_ids).any(|(c, e)| c == e) {
            return Err(format!("End sampled at step {k} although min_len = {steps}"));
        }
        prev = codes.map(|c| c as i64);
        tokens.push(codes);
    }
    let step_faults = minor_faults() - faults0;
    drop(st);

    // 4. decode + assembly
    let f = bundle.decoder.frames_per_token();
    let mut ds = bundle.decoder.new_state();
    let mut chunk = vec![0f32; bundle.decoder.chunk_len()];
    bundle.decoder.decode(&mut ds, tokens[0].map(|c| c as i64), &mut chunk).map_err(err)?; // warm-up
    ds.reset().map_err(err)?;
    let mut normalized = Vec::with_capacity(steps * chunk.len());
    let mut decode_ms = Vec::with_capacity(steps);
    let faults0 = minor_faults();
    for codes in &tokens {
        let t = Instant::now();
        bundle.decoder.decode(&mut ds, codes.map(|c| c as i64), &mut chunk).map_err(err)?;
        decode_ms.push(ms(t.elapsed()));
        normalized.extend_from_slice(&chunk);
    }
    let decode_faults = minor_faults() - faults0;
    // the same tokens as a stream decodes them: the first alone, then in groups
    let group = decode_group::tokens_per_decode(&bundle.step, &bundle.decoder, runtime.decode_group);
    ds.reset().map_err(err)?;
    let mut grouped = vec![0f32; MAX_DECODE_GROUP * chunk.len()];
    let mut group_ms_per_token = Vec::with_capacity(steps);
    let mut group_same = true;
    let mut k = 0;
    while k < tokens.len() {
        let g = decode_group::tokens_at(k, group).min(tokens.len() - k);
        let mut ids = [[0i64; N_STREAMS]; MAX_DECODE_GROUP];
        for (d, t) in ids.iter_mut().zip(&tokens[k..k + g]) {
            *d = t.map(|c| c as i64);
        }
        let out = &mut grouped[..g * chunk.len()];
        let t = Instant::now();
        bundle.decoder.decode_group(&mut ds, &ids[..g], out).map_err(err)?;
        group_ms_per_token.push(ms(t.elapsed()) / g as f64);
        let want = &normalized[k * chunk.len()..(k + g) * chunk.len()];
        group_same &= out.iter().zip(want).all(|(a, b)| a.to_bits() == b.to_bits());
        k += g;
    }
    drop(ds);
    let config = EngineConfig {
        bundle_path: o.bundle.clone(),
        coordinate_system: CoordinateSystem::CG_COORDS_NATIVE,
        enable_fk: false,
        ring_capacity: (steps * f + 16).max(256),
        max_streams: 2,
        default_stream: StreamConfig::default(),
        publish_name: None,
        runtime,
    };
    // The streams' own pipeline (5. below), so the expected frames are assembled exactly as theirs.
    let pipeline = Arc::new(Pipeline::new(Arc::clone(&bundle), &config).map_err(err)?);
    let assembler = pipeline.assembler();
    let n_frames = steps * f;
    let mut expected = vec![Frame::default(); n_frames];
    let mut assemble_us = Vec::with_capacity(steps);
    let mut contact_us = Vec::with_capacity(steps);
    // The streams run the contact-consistency stage on the prompt's object: so do these frames.
    let objects = &bundle.manifest.objects;
    let (object, _) = choose_object(objects, &o.prompt).ok_or("the bundle's object catalogue is empty")?;
    let mut stage = pipeline.contact_stage(object);
    if o.free_feet {
        stage = stage.with_free_feet();
    }
    // Placement from the grasp, as the streams do it (from the frames up to the first grasp).
    let mut onset = GraspOnset::default();
    if !o.no_grasp_placement {
        onset.feed_features(assembler, &normalized[..n_frames * FRAME_DIM]);
    }
    for (c, frames) in expected.chunks_mut(f).enumerate() {
        let (mut stage_time, t) = (Duration::ZERO, Instant::now());
        for (i, fr) in frames.iter_mut().enumerate() {
            let idx = c * f + i;
            let mut pose = Pose::default();
            assembler.decode(&normalized[idx * FRAME_DIM..(idx + 1) * FRAME_DIM], &mut pose);
            stage.ground(assembler.skeleton(), &mut pose);
            if let (0, Some(centre)) = (idx, onset.centre()) {
                stage.place(&mut pose, &centre);
            }
            let ts = Instant::now();
            stage.apply(assembler.skeleton(), &mut pose);
            if idx + 1 == n_frames {
                stage.finish(assembler.skeleton(), &mut pose);
            }
            stage_time += ts.elapsed();
            // Stream ids start at 1 and the first stream of the engine below is compared.
            assembler.emit(&pose, 1, idx as u64, idx + 1 == n_frames, fr);
        }
        assemble_us.push((t.elapsed() - stage_time).as_secs_f64() * 1e6);
        contact_us.push(stage_time.as_secs_f64() * 1e6);
    }

    // 5. end-to-end streams on the same loaded bundle
    let overlap = pipeline.overlap();
    let factory: SourceFactory = Box::new(move |req: &StreamRequest<'_>| {
        Ok(Box::new(Generator::new(Arc::clone(&pipeline), req)?) as Box<dyn ChunkSource>)
    });
    let engine = Engine::with_source_factory(config, factory).map_err(err)?;
    let stream_cfg = StreamConfig {
        seed: Some(seed),
        temperature: Some(temperature),
        top_k: Some(top_k),
        min_len: Some(steps as u32),
        max_len: Some(steps as u32),
        guidance: Some(guidance as f64),
        raw_output: None,
        grasp_placement: o.no_grasp_placement.then_some(false),
        foot_lock: o.free_feet.then_some(false),
        anchor: None,
        continue_from: None,
    };
    let mut ttff_ms = Vec::new();
    let mut total_ms = Vec::new();
    let mut fps_runs = Vec::new();
    let mut stream_matches = None;
    let mut frames: Vec<Frame> = Vec::with_capacity(n_frames);
    let faults0 = minor_faults();
    for run in 0..o.stream_runs {
        frames.clear();
        let mut fr = Frame::default();
        let t0 = Instant::now();
        let mut stream = engine.start(&o.prompt, stream_cfg.clone()).map_err(err)?;
        let mut first = None;
        loop {
            match stream.wait(&mut fr, Duration::from_secs(60)) {
                PollResult::Frame => {
                    first.get_or_insert_with(|| t0.elapsed());
                    frames.push(fr);
                }
                PollResult::Pending => return Err("no frame for 60 s".into()),
                PollResult::End => break,
                PollResult::Cancelled => return Err("the stream was cancelled".into()),
                PollResult::Error => {
                    return Err(stream.error().map_or_else(|| "the stream failed".into(), |e| e.to_string()))
                }
            }
        }
        let total = t0.elapsed();
        let sid = stream.id();
        drop(stream);
        if frames.len() != n_frames {
            return Err(format!("the stream gave {} frames, expected {n_frames}", frames.len()));
        }
        ttff_ms.push(ms(first.unwrap_or(total)));
        total_ms.push(ms(total));
        fps_runs.push(n_frames as f64 / total.as_secs_f64());
        if run == 0 {
            // Same frames as the step loop's tokens decoded and assembled => same tokens.
            stream_matches = Some(sid == 1 && frames == expected);
        }
    }
    let stream_faults = minor_faults() - faults0;
    let gen_s = total_ms.iter().copied().fold(0.0, f64::max) / 1e3;

    // 6. poll latency: empty ring while the first frame is computed, then ready frames
    let mut empty_ns = Vec::new();
    let mut ready_ns = Vec::new();
    {
        let mut fr = Frame::default();
        let mut stream = engine.start(&o.prompt, stream_cfg.clone()).map_err(err)?;
        let mut got = 0usize;
        'empty: while empty_ns.len() < 20_000 {
            let t = Instant::now();
            let mut all_pending = true;
            for _ in 0..POLL_BATCH {
                match stream.poll(&mut fr) {
                    PollResult::Pending => {}
                    PollResult::Frame => {
                        got += 1;
                        all_pending = false;
                        break;
                    }
                    _ => break 'empty,
                }
            }
            let dt = t.elapsed();
            if !all_pending {
                break;
            }
            empty_ns.push(dt.as_secs_f64() * 1e9 / POLL_BATCH as f64);
        }
        // Let the worker buffer everything (the ring holds the whole sequence), then drain.
        std::thread::sleep(Duration::from_secs_f64(gen_s * 1.5 + 0.05));
        let mut done = false;
        while !done {
            let t = Instant::now();
            let mut n = 0;
            for _ in 0..POLL_BATCH {
                match stream.poll(&mut fr) {
                    PollResult::Frame => n += 1,
                    _ => {
                        done = true;
                        break;
                    }
                }
            }
            let dt = t.elapsed();
            got += n;
            if n == POLL_BATCH {
                ready_ns.push(dt.as_secs_f64() * 1e9 / POLL_BATCH as f64);
            }
        }
        if got != n_frames {
            // The generation was slower than the sleep (the ready numbers only count full
            // batches of frames anyway): drain the rest so the worker can finish.
            while let PollResult::Frame = stream.wait(&mut fr, Duration::from_secs(60)) {}
        }
    }
    drop(engine);

    // 7. memory
    let rss_end = rss();

    // 8. bandwidth (with the bundle's memory released first)
    let step_bytes = step_graph_bytes(&bundle);
    let t = &m.transformer;
    let cache_bytes = (2 * t.n_layers * t.n_heads * t.cache_slots * t.head_dims.iter().sum::<usize>() * 4) as u64;
    let fps = m.fps;
    let manifest = m.clone();
    let files_bytes = m.files.values().map(|e| e.bytes).sum::<u64>();
    let step_onnx = if bundle.origin().omits(&manifest.transformer.file) {
        None
    } else {
        Some(bundle.file_bytes(&manifest.transformer.file).map_err(err)?)
    };
    let origin = bundle.origin().root();
    drop(bundle);
    let t = &manifest.transformer;
    let w = step_weights(step_onnx.as_deref(), &manifest)?;
    drop(step_onnx);
    let model = json!({
        "step_graph_bytes": step_bytes, "kv_cache_bytes": cache_bytes,
        "weights": {
            "fp32_bytes": w.fp32, "int8_bytes": w.int8, "native_fp32_bytes": w.native_fp32,
            "native_step_reported_bytes": native_reported,
            "graph_int8_elements": w.graph_int8_elems,
            "note": "fp32 = 4 B per step-graph weight element (tract/ORT read, int8-stored weights dequantized at \
                     load); int8 = transformer.native int8 weights + scales + fp32 tensors (the native path)",
        },
        "n_layers": t.n_layers, "n_heads": t.n_heads, "widths": t.widths, "cache_slots": t.cache_slots,
        "files_bytes": files_bytes,
    });
    let step_med = stats(&step_ms)["median"].as_f64().unwrap_or(f64::NAN);
    let step_basis = if step_path == "native" { native_reported.or(w.int8).unwrap_or(w.fp32) } else { w.fp32 };
    let bandwidth = if o.bandwidth_mib > 0 {
        let n = o.bandwidth_mib * (1 << 20) / 8;
        let buf: Vec<u64> = (0..n as u64).collect();
        let (b1, m1) = read_bandwidth(&buf, 1, 5);
        let (b2, m2) = read_bandwidth(&buf, 2, 5);
        let (br, _) = if o.threads.unwrap_or(1) > 2 {
            read_bandwidth(&buf, o.threads.unwrap_or(1), 5)
        } else if o.threads == Some(2) {
            (b2, m2)
        } else {
            (b1, m1)
        };
        let limit = |bytes: u64, bw: f64| (bytes + cache_bytes) as f64 / bw * 1e3;
        let int8 = |bw: f64| w.int8.map(|b| limit(b, bw));
        json!({
            "buffer_mib": o.bandwidth_mib,
            "gb_per_s_1t": b1 / 1e9, "gb_per_s_1t_median": m1 / 1e9,
            "gb_per_s_2t": b2 / 1e9, "gb_per_s_2t_median": m2 / 1e9,
            "gb_per_s_run": br / 1e9, "run_threads": o.threads,
            "step_limit_ms_1t": limit(w.fp32, b1), "step_limit_ms_2t": limit(w.fp32, b2),
            "step_limit_int8_ms_1t": int8(b1), "step_limit_int8_ms_2t": int8(b2),
            "step_limit_ms_run": limit(w.fp32, br), "step_limit_int8_ms_run": int8(br),
            "step_over_limit_run": step_med / limit(step_basis, br),
            "step_over_limit_basis": if step_path == "native" && w.int8.is_some() { "int8" } else { "fp32" },
        })
    } else {
        Value::Null
    };
    let text_med = stats(&text_ms)["median"].as_f64().unwrap_or(f64::NAN);
    let decode_med = stats(&decode_ms)["median"].as_f64().unwrap_or(f64::NAN);
    let per_token = step_med + decode_med;
    let derived = json!({
        "ttff_ms": text_med + step_ms[0] + decode_ms[0],
        "ms_per_token": per_token,
        "rtf": f as f64 * 1e3 / per_token / fps,
    });

    let step_stats = stats(&step_ms);
    let tokens_json: Vec<Vec<usize>> = tokens.iter().map(|r| r.to_vec()).collect();
    Ok(json!({
        "runtime": format!("comgrasp (step: {step_path}, decoder: {decoder_path}; tract-onnx 0.23)"),
        "engine_path": {"step": step_path, "decoder": decoder_path, "overlap": overlap, "decode_group": group},
        "bundle": origin.display().to_string(),
        "machine": {"cpu": cpu_model(), "logical_cpus": std::thread::available_parallelism().map(|n| n.get()).ok()},
        "threads": {"requested": o.threads, "tract": tract_threads, "note": thread_note,
                    "native_step": native_threads[0], "native_decoder": native_threads[1]},
        "config": {
            "prompt": o.prompt, "seed": seed, "steps": steps, "warmup": o.warmup,
            "temperature": temperature, "top_k": top_k, "guidance": guidance, "min_len": steps, "max_len": steps,
            "fps": fps, "frames_per_token": f, "l_max": l_max,
        },
        "model": model,
        "load_ms": load_ms,
        "text_ms": stats(&text_ms),
        "text_input_ids": text_ids,
        "step_ms": step_stats,
        "first_step_ms": step_ms[0],
        "sample_us": stats(&sample_us),
        "decode_ms": stats(&decode_ms),
        "first_decode_ms": decode_ms[0],
        "decode_group": {"tokens": group, "ms_per_token": stats(&group_ms_per_token),
                         "same_bits_as_one_by_one": group_same},
        "derived": derived,
        "assemble_us_per_chunk": stats(&assemble_us),
        "contact_stage_us_per_chunk": stats(&contact_us),
        "stream": {
            "runs": o.stream_runs, "frames": n_frames,
            "ttff_ms": stats(&ttff_ms), "total_ms": stats(&total_ms),
            "frames_per_s": stats(&fps_runs),
            "rtf": stats(&fps_runs.iter().map(|x| x / fps).collect::<Vec<_>>()),
            "ms_per_token": stats(&total_ms.iter().map(|x| x / steps as f64).collect::<Vec<_>>()),
            "matches_step_loop": stream_matches,
        },
        "minor_page_faults_per_token": {
            "step_loop": step_faults as f64 / steps as f64,
            "decode_loop": decode_faults as f64 / steps as f64,
            "stream": stream_faults as f64 / (steps * o.stream_runs) as f64,
        },
        "poll_ns": {"batch": POLL_BATCH, "empty": stats(&empty_ns), "ready": stats(&ready_ns)},
        "rss_mib": {
            "before_load": mib(rss_before.1), "after_load": mib(rss_loaded.1),
            "end": mib(rss_end.1), "peak": mib(rss_end.0),
        },
        "bandwidth": bandwidth,
        "tokens_sha256": hash_tokens(&tokens),
        "tokens": tokens_json,
    }))
}

// ------------------------------------------------------------------------------ report

fn print_report(r: &Value) {
    let g = |path: &[&str]| {
        let mut v = r;
        for p in path {
            v = &v[*p];
        }
        v.as_f64().unwrap_or(f64::NAN)
    };
    let s = |path: &[&str]| r.pointer(&format!("/{}", path.join("/"))).cloned().unwrap_or(Value::Null);
    println!("comgrasp bench: {}", r["bundle"].as_str().unwrap_or("?"));
    println!(
        "  machine   {} ({} logical CPUs); tract: {}",
        r["machine"]["cpu"].as_str().unwrap_or("?"),
        s(&["machine", "logical_cpus"]),
        r["threads"]["note"].as_str().unwrap_or("?")
    );
    println!(
        "  sequence  {} steps x {} frames, seed {}, temperature {}, top-k {}, guidance {}, prompt {}",
        s(&["config", "steps"]),
        s(&["config", "frames_per_token"]),
        s(&["config", "seed"]),
        s(&["config", "temperature"]),
        s(&["config", "top_k"]),
        s(&["config", "guidance"]),
        s(&["config", "prompt"])
    );
    println!(
        "  paths     step {}, decoder {}, streams overlap step k+1 with decode k: {}",
        r["engine_path"]["step"].as_str().unwrap_or("?"),
        r["engine_path"]["decoder"].as_str().unwrap_or("?"),
        if r["engine_path"]["overlap"].as_bool().unwrap_or(false) { "yes" } else { "no" }
    );
    println!(
        "  load      {:.1} ms (verify + 3 graphs); step graph files {:.1} MB, KV cache {:.1} MB",
        g(&["load_ms"]),
        g(&["model", "step_graph_bytes"]) / 1e6,
        g(&["model", "kv_cache_bytes"]) / 1e6
    );
    println!(
        "  weights   read per step: {:.1} MB as fp32 (tract path){}",
        g(&["model", "weights", "fp32_bytes"]) / 1e6,
        r["model"]["weights"]["int8_bytes"]
            .as_f64()
            .map_or(String::new(), |b| format!(", {:.1} MB int8 (native path)", b / 1e6))
    );
    let line = |label: &str, key: &str, unit: &str| {
        println!(
            "  {label:<9} median {:.3} {unit}, p90 {:.3} {unit} (n = {})",
            g(&[key, "median"]),
            g(&[key, "p90"]),
            s(&[key, "n"])
        );
    };
    line("text", "text_ms", "ms");
    line("step", "step_ms", "ms");
    line("sample", "sample_us", "us");
    line("decode", "decode_ms", "ms");
    println!(
        "  grouped   {} tokens per decode after the first: median {:.3} ms per token, p90 {:.3} \
              (same bits as one by one: {})",
        s(&["decode_group", "tokens"]),
        g(&["decode_group", "ms_per_token", "median"]),
        g(&["decode_group", "ms_per_token", "p90"]),
        s(&["decode_group", "same_bits_as_one_by_one"])
    );
    line("assemble", "assemble_us_per_chunk", "us");
    line("contact", "contact_stage_us_per_chunk", "us");
    println!(
        "  derived   TTFF {:.2} ms (text + step 0 + chunk 0), RTF {:.1} (frames per token / (step + chunk))",
        g(&["derived", "ttff_ms"]),
        g(&["derived", "rtf"])
    );
    println!(
        "  stream    TTFF median {:.2} ms (p90 {:.2}), {:.0} frames/s, RTF {:.1}, {:.2} ms/token; \
              frames match the step loop: {}",
        g(&["stream", "ttff_ms", "median"]),
        g(&["stream", "ttff_ms", "p90"]),
        g(&["stream", "frames_per_s", "median"]),
        g(&["stream", "rtf", "median"]),
        g(&["stream", "ms_per_token", "median"]),
        s(&["stream", "matches_step_loop"])
    );
    println!(
        "  poll      empty {:.1} ns, ready frame {:.1} ns (median per call, batches of {})",
        g(&["poll_ns", "empty", "median"]),
        g(&["poll_ns", "ready", "median"]),
        POLL_BATCH
    );
    println!(
        "  RSS       peak {:.1} MiB (before load {:.1}, after load {:.1})",
        g(&["rss_mib", "peak"]),
        g(&["rss_mib", "before_load"]),
        g(&["rss_mib", "after_load"])
    );
    if !r["bandwidth"].is_null() {
        println!(
            "  bandwidth {:.1} GB/s (1 thread), {:.1} GB/s (2 threads), {:.1} GB/s at {} thread(s); step limit \
                  {:.3} ms (fp32 weights + KV){}; step / limit {:.2} ({})",
            g(&["bandwidth", "gb_per_s_1t"]),
            g(&["bandwidth", "gb_per_s_2t"]),
            g(&["bandwidth", "gb_per_s_run"]),
            s(&["bandwidth", "run_threads"]),
            g(&["bandwidth", "step_limit_ms_run"]),
            r["bandwidth"]["step_limit_int8_ms_run"]
                .as_f64()
                .map_or(String::new(), |v| format!(", {v:.3} ms (int8 weights + KV)")),
            g(&["bandwidth", "step_over_limit_run"]),
            r["bandwidth"]["step_over_limit_basis"].as_str().unwrap_or("?")
        );
    }
    let toks = r["tokens"].as_array().map_or(0, Vec::len);
    let head: Vec<String> = r["tokens"].as_array().into_iter().flatten().take(4).map(|t| t.to_string()).collect();
    println!(
        "  tokens    {toks} steps, sha256 {}, first {}",
        r["tokens_sha256"].as_str().unwrap_or("?"),
        head.join(" ")
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(a: &[&str]) -> Result<Args, clap::Error> {
        #[derive(clap::Parser)]
        struct Bench {
            #[command(flatten)]
            args: Args,
        }
        use clap::Parser;
        Bench::try_parse_from(std::iter::once("bench").chain(a.iter().copied())).map(|b| b.args)
    }

    #[test]
    fn parses_options() {
        let o = parse(&["--bundle", "b", "--steps=5", "--json", "--prompt", "x y", "--threads", "2"]).unwrap();
        assert_eq!(o.bundle, Some(PathBuf::from("b")));
        assert_eq!(o.steps, Some(5));
        assert!(o.json);
        assert_eq!(o.prompt, "x y");
        assert_eq!(o.threads, Some(2));
        let d = parse(&["--steps", "5"]).unwrap();
        assert_eq!(d.bundle, None, "the engine's default bundle");
        assert_eq!((d.prompt.as_str(), d.warmup, d.stream_runs, d.threads), (DEFAULT_PROMPT, 3, 3, None));
        assert!(parse(&["--bundle", "b", "--nope"]).is_err());
        assert!(parse(&["--bundle", "b", "--steps", "0"]).is_err());
        assert!(parse(&["--stream-runs", "0"]).is_err());
        assert!(parse(&["--bundle", "b", "--seed"]).is_err());
        assert_eq!(parse(&["--guidance", "2"]).unwrap().guidance, Some(2.0));
    }

    #[test]
    fn stats_median_and_p90() {
        let v = stats(&[5.0, 1.0, 3.0, 2.0, 4.0, 6.0, 7.0, 8.0, 9.0, 10.0]);
        assert_eq!(v["median"].as_f64(), Some(5.5));
        assert_eq!(v["p90"].as_f64(), Some(9.0));
        assert_eq!(v["min"].as_f64(), Some(1.0));
        assert!(stats(&[]).is_null());
    }

    #[test]
    fn token_hash_is_sha256_of_le_int64() {
        // sha256 of 32 zero bytes (one step of four zero tokens).
        assert_eq!(hash_tokens(&[[0, 0, 0, 0]]), "66687aadf862bd776c8fc18b8e9f8e20089714856ee233b3902a591d0d5f2925");
    }

    #[test]
    fn sum_reads_everything() {
        let v: Vec<u64> = (0..1003).collect();
        assert_eq!(sum_u64(&v), 1003 * 1002 / 2);
    }
}
