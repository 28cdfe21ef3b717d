//! Test doubles shared by the `ffi_*` tests: a deterministic [`ChunkSource`] whose behaviour
//! is scripted by the prompt text, so every path can be driven through the C ABI.
//!
//! Prompt words (any order, unknown words ignored):
//! `chunks=N` (default 4), `frames=N` per chunk (default 16), `delay_ms=N` before each
//! chunk, `fail_at=K` (chunk K returns an inference error), `panic_at=K` (chunk K panics),
//! `drop_delay_ms=N` (dropping the source, i.e. freeing its model state, takes N ms),
//! `factory_panic` (the factory itself panics), `factory_fail` (the factory returns an error).
#![allow(dead_code)]

use std::ffi::CString;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use comgrasp::engine::{Engine, EngineConfig, SourceFactory, StreamRequest};
use comgrasp::ffi::*;
use comgrasp::stream::ChunkSource;
use comgrasp::{Error, Frame, Result};

#[derive(Clone, Debug, Default)]
pub struct Script {
    pub chunks: u64,
    pub frames: u64,
    pub delay_ms: u64,
    pub drop_delay_ms: u64,
    pub fail_at: Option<u64>,
    pub panic_at: Option<u64>,
}

impl Script {
    pub fn parse(text: &str) -> Script {
        let mut s = Script { chunks: 4, frames: 16, ..Default::default() };
        for word in text.split_whitespace() {
            let (k, v) = word.split_once('=').unwrap_or((word, ""));
            let n = v.parse::<u64>().ok();
            match k {
                "chunks" => s.chunks = n.unwrap(),
                "frames" => s.frames = n.unwrap(),
                "delay_ms" => s.delay_ms = n.unwrap(),
                "drop_delay_ms" => s.drop_delay_ms = n.unwrap(),
                "fail_at" => s.fail_at = n,
                "panic_at" => s.panic_at = n,
                _ => {}
            }
        }
        s
    }
}

/// Counts what all sources of one factory did, so tests can observe the workers.
#[derive(Default)]
pub struct Counters {
    pub chunks_produced: AtomicUsize,
    pub sources_alive: AtomicUsize,
}

pub struct ScriptedSource {
    stream_id: u64,
    script: Script,
    next: u64,
    counters: Arc<Counters>,
}

impl Drop for ScriptedSource {
    fn drop(&mut self) {
        std::thread::sleep(Duration::from_millis(self.script.drop_delay_ms));
        self.counters.sources_alive.fetch_sub(1, Ordering::SeqCst);
    }
}

/// The frame a scripted stream emits at `index`: values derived from the index, so a test
/// can check content as well as order.
pub fn expected_frame(stream_id: u64, index: u64, is_last: bool) -> Frame {
    Frame {
        stream_id,
        frame_index: index,
        time_s: index as f64 / 30.0,
        root_translation: [index as f32, 1.0, 2.0],
        is_last: is_last as u8,
        ..Default::default()
    }
}

impl ChunkSource for ScriptedSource {
    fn next_chunk(&mut self, out: &mut Vec<Frame>) -> Result<bool> {
        if self.script.delay_ms > 0 {
            std::thread::sleep(Duration::from_millis(self.script.delay_ms));
        }
        let k = self.next;
        if self.script.fail_at == Some(k) {
            return Err(Error::Inference(format!("scripted failure at chunk {k}")));
        }
        if self.script.panic_at == Some(k) {
            panic!("scripted panic at chunk {k}");
        }
        let last_chunk = k + 1 >= self.script.chunks;
        for i in 0..self.script.frames {
            let index = k * self.script.frames + i;
            out.push(expected_frame(self.stream_id, index, last_chunk && i + 1 == self.script.frames));
        }
        self.next += 1;
        self.counters.chunks_produced.fetch_add(1, Ordering::SeqCst);
        Ok(!last_chunk)
    }
}

pub fn factory(counters: Arc<Counters>) -> SourceFactory {
    Box::new(move |req: &StreamRequest<'_>| -> Result<Box<dyn ChunkSource>> {
        if req.text.contains("factory_panic") {
            panic!("scripted factory panic");
        }
        if req.text.contains("factory_fail") {
            return Err(Error::InvalidArgument("scripted factory failure".into()));
        }
        counters.sources_alive.fetch_add(1, Ordering::SeqCst);
        Ok(Box::new(ScriptedSource {
            stream_id: req.stream_id,
            script: Script::parse(req.text),
            next: 0,
            counters: Arc::clone(&counters),
        }))
    })
}

/// A test engine behind a real C handle.
pub struct TestEngine {
    pub handle: *mut cg_engine,
    pub counters: Arc<Counters>,
}

unsafe impl Send for TestEngine {}
unsafe impl Sync for TestEngine {}

impl TestEngine {
    pub fn new(ring_capacity: usize, max_streams: usize) -> TestEngine {
        TestEngine::with_config(EngineConfig { ring_capacity, max_streams, ..Default::default() })
    }

    pub fn with_config(config: EngineConfig) -> TestEngine {
        let counters = Arc::new(Counters::default());
        let engine = Engine::with_source_factory(config, factory(Arc::clone(&counters))).unwrap();
        let handle = comgrasp::ffi::handle::engine_into_handle(engine).unwrap();
        TestEngine { handle, counters }
    }

    pub fn start(&self, text: &str) -> *mut cg_stream {
        let mut s = std::ptr::null_mut();
        let c = CString::new(text).unwrap();
        let st = unsafe { cg_start(self.handle, c.as_ptr(), std::ptr::null(), &mut s) };
        assert_eq!(st, cg_status::CG_OK, "cg_start({text:?}): {}", last_error());
        s
    }

    pub fn stream_count(&self) -> u32 {
        let mut n = u32::MAX;
        assert_eq!(unsafe { cg_engine_stream_count(self.handle, &mut n) }, cg_status::CG_OK);
        n
    }

    pub fn destroy(self) {
        assert_eq!(unsafe { cg_engine_destroy(self.handle) }, cg_status::CG_OK);
    }
}

pub fn last_error() -> String {
    unsafe { std::ffi::CStr::from_ptr(cg_last_error()) }.to_string_lossy().into_owned()
}

/// Polls until a non-PENDING status, sleeping briefly between polls; panics after `limit`.
pub fn poll_until_ready(s: *mut cg_stream, out: &mut Frame, limit: Duration) -> cg_status {
    let t0 = std::time::Instant::now();
    loop {
        let st = unsafe { cg_poll_frame(s, out) };
        if st != cg_status::CG_PENDING {
            return st;
        }
        assert!(t0.elapsed() < limit, "stream made no progress within {limit:?}");
        std::thread::sleep(Duration::from_micros(200));
    }
}

/// Drains a stream to its terminal status, checking order, content and `is_last` (set on
/// exactly the final frame when the stream ends normally). Returns (frames, status).
pub fn drain_checked(s: *mut cg_stream, stream_id: u64) -> (u64, cg_status) {
    let mut f = Frame::default();
    let mut n = 0u64;
    let mut seen_last = false;
    loop {
        match poll_until_ready(s, &mut f, Duration::from_secs(20)) {
            cg_status::CG_OK => {
                assert!(!seen_last, "a frame followed the is_last frame");
                assert_eq!(f.stream_id, stream_id);
                assert_eq!(f.frame_index, n, "frames must be consecutive");
                assert_eq!(f.root_translation[0], n as f32);
                seen_last = f.is_last == 1;
                n += 1;
            }
            cg_status::CG_END => {
                assert!(n == 0 || seen_last, "the final frame must have is_last = 1");
                return (n, cg_status::CG_END);
            }
            other => return (n, other),
        }
    }
}
