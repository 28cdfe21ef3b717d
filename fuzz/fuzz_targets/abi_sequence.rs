//! A sequence of C ABI calls decoded from the input: create / start / poll / wait / cancel /
//! destroy / query in any order, with handles drawn from live, destroyed, NULL, forged and
//! wrong-type values, `cg_stream_wait` with 0-3 ms timeouts, cancels racing a wait on another
//! thread, and configs with arbitrary field values and `struct_size`s.
//!
//! Engines are test engines (`Engine::with_source_factory` behind `engine_into_handle`)
//! whose streams produce scripted frames instantly, so thousands of calls run per second;
//! `cg_engine_create` is also called with fuzzed configs (there is no loadable bundle, so it
//! must fail cleanly). A model of every handle checks, after every call:
//! * the status is a valid `cg_status` and one that function may return;
//! * NULL, destroyed, forged and wrong-type handles give CG_ERR_NULL_POINTER /
//!   CG_ERR_INVALID_HANDLE (destroy of NULL is CG_OK);
//! * a failure records the same status in `cg_last_error_status` and a UTF-8 message;
//! * frames arrive in order with the right stream id and `is_last` on exactly the last;
//!   END only after every frame; CANCELLED always after `cg_cancel`; terminal states stick;
//! * `cg_engine_stream_count` equals the model's count; `cg_start` gives CG_ERR_LIMIT
//!   exactly at `max_streams`.
//!
//! The input is read as bytes: an op code, then the op's operands (missing bytes read as 0).
#![no_main]

use std::collections::HashMap;
use std::ffi::{c_char, CStr};
use std::mem::size_of;
use std::ptr::{null, null_mut};
use std::sync::Once;

use comgrasp::engine::{Engine, EngineConfig, SourceFactory, StreamRequest};
use comgrasp::ffi::handle::engine_into_handle;
use comgrasp::ffi::*;
use comgrasp::stream::ChunkSource;
use comgrasp::{Error, Frame, Result};
use libfuzzer_sys::fuzz_target;

use cg_status::*;

// ---------------------------------------------------------------------------------------
// The scripted source: "chunks=C frames=F fail_at=K" (as in tests/common), instant.

#[derive(Clone, Copy, Debug, PartialEq)]
struct Script {
    chunks: u64,
    frames: u64,
    fail_at: Option<u64>,
}

impl Script {
    fn text(&self) -> String {
        let mut t = format!("chunks={} frames={}", self.chunks, self.frames);
        if let Some(k) = self.fail_at {
            t.push_str(&format!(" fail_at={k}"));
        }
        t
    }

    fn parse(text: &str) -> Script {
        let mut s = Script { chunks: 2, frames: 4, fail_at: None };
        for word in text.split_whitespace() {
            let (k, v) = word.split_once('=').unwrap_or((word, ""));
            let n = v.parse::<u64>().ok();
            match (k, n) {
                ("chunks", Some(n)) => s.chunks = n.clamp(1, 1 << 40),
                ("frames", Some(n)) => s.frames = n.clamp(1, 64),
                ("fail_at", n) => s.fail_at = n,
                _ => {}
            }
        }
        s
    }

    /// Frames delivered before the end or the failure.
    fn total(&self) -> u64 {
        match self.fail_at {
            Some(k) if k < self.chunks => k * self.frames,
            _ => self.chunks * self.frames,
        }
    }

    fn fails(&self) -> bool {
        matches!(self.fail_at, Some(k) if k < self.chunks)
    }
}

struct Scripted {
    id: u64,
    script: Script,
    next: u64,
}

impl ChunkSource for Scripted {
    fn next_chunk(&mut self, out: &mut Vec<Frame>) -> Result<bool> {
        let k = self.next;
        if self.script.fail_at == Some(k) {
            return Err(Error::Inference(format!("scripted failure at chunk {k}")));
        }
        let last_chunk = k + 1 >= self.script.chunks;
        for i in 0..self.script.frames {
            let mut f = Frame::default();
            f.stream_id = self.id;
            f.frame_index = k * self.script.frames + i;
            f.is_last = (last_chunk && i + 1 == self.script.frames) as u8;
            out.push(f);
        }
        self.next += 1;
        Ok(!last_chunk)
    }
}

fn factory() -> SourceFactory {
    Box::new(|req: &StreamRequest<'_>| -> Result<Box<dyn ChunkSource>> {
        if req.text.contains("factory_fail") {
            return Err(Error::InvalidArgument("scripted factory failure".into()));
        }
        Ok(Box::new(Scripted { id: req.stream_id, script: Script::parse(req.text), next: 0 }))
    })
}

// ---------------------------------------------------------------------------------------
// Input decoding.

struct Input<'a> {
    data: &'a [u8],
}

impl Input<'_> {
    fn u8(&mut self) -> u8 {
        match self.data.split_first() {
            Some((b, rest)) => {
                self.data = rest;
                *b
            }
            None => 0,
        }
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.u8(), self.u8(), self.u8(), self.u8()])
    }
    fn u64(&mut self) -> u64 {
        u64::from(self.u32()) | (u64::from(self.u32()) << 32)
    }
    fn bytes(&mut self, n: usize) -> &[u8] {
        let n = n.min(self.data.len());
        let (a, b) = self.data.split_at(n);
        self.data = b;
        a
    }
    fn done(&self) -> bool {
        self.data.is_empty()
    }
}

// ---------------------------------------------------------------------------------------
// The model.

struct EngineModel {
    live: bool,
    max_streams: u32,
}

#[derive(Debug)]
struct StreamModel {
    engine: usize,
    script: Script,
    id: u64,
    live: bool,
    /// Frames delivered so far.
    next: u64,
    cancelled: bool,
    /// Its engine was destroyed: a running stream was cancelled, a finished one was not,
    /// and which of the two is a race, so both outcomes are accepted.
    engine_gone: bool,
    /// END or an error was seen (sticky).
    terminal: Option<cg_status>,
}

impl StreamModel {
    /// `cg_cancel` on it: a stream whose outcome a poll already saw (END, an error, or the
    /// `is_last` frame, after which END is due) keeps that outcome; any other is cancelled.
    fn cancel(&mut self) {
        let last_frame_seen = !self.script.fails() && self.next == self.script.total();
        if self.terminal.is_none() && !last_frame_seen {
            self.cancelled = true;
        }
    }
}

#[derive(Default)]
struct World {
    engines: HashMap<usize, EngineModel>,
    /// In creation order (for picking).
    engine_order: Vec<usize>,
    streams: HashMap<usize, StreamModel>,
    stream_order: Vec<usize>,
}

/// What a handle operand resolved to.
#[derive(Clone, Copy, Debug)]
enum Pick {
    Null,
    /// Not a live handle of the expected type (destroyed, forged, or the other type).
    Invalid(usize),
    Live(usize),
}

impl Pick {
    fn ptr<T>(self) -> *mut T {
        match self {
            Pick::Null => null_mut(),
            Pick::Invalid(h) | Pick::Live(h) => h as *mut T,
        }
    }
}

impl World {
    fn pick_engine(&self, inp: &mut Input) -> Pick {
        let sel = inp.u8();
        let h = match sel % 8 {
            0 => return Pick::Null,
            1 => inp.u64() as usize, // forged
            2 => match self.stream_order.get(usize::from(inp.u8())) {
                // wrong type
                Some(&s) => s,
                None => return Pick::Null,
            },
            _ => match self.engine_order.len() {
                0 => return Pick::Null,
                n => self.engine_order[usize::from(inp.u8()) % n],
            },
        };
        match self.engines.get(&h) {
            _ if h == 0 => Pick::Null, // a forged 0 is NULL
            Some(e) if e.live => Pick::Live(h),
            _ => Pick::Invalid(h),
        }
    }

    fn pick_stream(&self, inp: &mut Input) -> Pick {
        let sel = inp.u8();
        let h = match sel % 8 {
            0 => return Pick::Null,
            1 => inp.u64() as usize,
            2 => match self.engine_order.get(usize::from(inp.u8())) {
                Some(&e) => e,
                None => return Pick::Null,
            },
            _ => match self.stream_order.len() {
                0 => return Pick::Null,
                n => self.stream_order[usize::from(inp.u8()) % n],
            },
        };
        match self.streams.get(&h) {
            _ if h == 0 => Pick::Null,
            Some(s) if s.live => Pick::Live(h),
            _ => Pick::Invalid(h),
        }
    }

    fn live_streams_of(&self, engine: usize) -> u32 {
        self.streams.values().filter(|s| s.live && s.engine == engine).count() as u32
    }
}

// ---------------------------------------------------------------------------------------
// Checks shared by every call.

/// What polling a live stream may return.
const POLL: [cg_status; 5] = [CG_OK, CG_PENDING, CG_END, CG_CANCELLED, CG_ERR_INFERENCE];

/// A valid `cg_status` value is one the library can name (checked on the raw integer, so
/// the check keeps up with codes added later).
fn is_status(raw: i32) -> bool {
    let name = unsafe { CStr::from_ptr(cg_status_string(raw)) }.to_bytes();
    !name.is_empty() && name != b"unknown cg_status value"
}

fn last_error() -> String {
    let p = cg_last_error();
    assert!(!p.is_null());
    unsafe { CStr::from_ptr(p) }.to_str().expect("cg_last_error is UTF-8").to_string()
}

/// Every status: a valid value (checked on the raw integer), allowed for the function,
/// and a failure leaves the same status and a message as the thread's last error.
fn check(name: &str, st: cg_status, allowed: &[cg_status]) -> cg_status {
    let raw = st as i32;
    assert!(is_status(raw), "{name}: {raw} is not a cg_status value");
    assert!(allowed.contains(&st), "{name} returned {st:?}, allowed {allowed:?}: {}", last_error());
    if raw < 0 {
        assert_eq!(cg_last_error_status(), st, "{name}: last error status");
        assert!(!last_error().is_empty(), "{name}: empty last error message");
    }
    st
}

fn expect(name: &str, st: cg_status, want: cg_status) {
    check(name, st, &[want]);
}

/// The result of polling a live stream, checked against the model (and the frame).
fn check_poll(name: &str, st: cg_status, f: &Frame, s: &mut StreamModel) {
    if s.cancelled {
        expect(name, st, CG_CANCELLED);
        return;
    }
    let total = s.script.total();
    match st {
        CG_OK => {
            assert!(s.terminal.is_none(), "{name}: a frame after {:?}", s.terminal);
            assert_eq!(f.stream_id, s.id, "{name}: stream id");
            assert_eq!(f.frame_index, s.next, "{name}: frames out of order");
            assert!(s.next < total, "{name}: more frames than scripted");
            let last = !s.script.fails() && s.next + 1 == total;
            assert_eq!(f.is_last == 1, last, "{name}: is_last on frame {}", s.next);
            s.next += 1;
        }
        CG_PENDING => assert!(s.terminal.is_none(), "{name}: PENDING after {:?}", s.terminal),
        CG_END => {
            assert!(!s.script.fails(), "{name}: END from a failing script");
            assert_eq!(s.next, total, "{name}: END before every frame was delivered");
            s.terminal = Some(CG_END);
        }
        CG_ERR_INFERENCE => {
            assert!(s.script.fails(), "{name}: inference error from a good script");
            assert_eq!(s.next, total, "{name}: error before the frames produced before it");
            s.terminal = Some(st);
        }
        CG_CANCELLED => {
            assert!(s.engine_gone, "{name}: CANCELLED without a cancel");
            s.cancelled = true; // sticky from now on
        }
        other => panic!("{name}: unexpected {other:?} on a live stream: {}", last_error()),
    }
}

// ---------------------------------------------------------------------------------------
// Configs with arbitrary contents, written as raw integers where C could put anything.

/// A buffer larger than any config, so a declared struct_size up to 64 bytes stays readable
/// (the caller's promise the ABI relies on).
#[repr(C, align(8))]
struct Padded<T> {
    value: T,
    tail: [u8; 64],
}

fn struct_size(inp: &mut Input, real: usize) -> u32 {
    match inp.u8() % 7 {
        0 => 0,
        1 => 4,
        2 => (real - 8) as u32,
        3 => (real + 16) as u32,
        4 => 32, // cg_engine_config v1 (before fields were appended)
        _ => real as u32,
    }
}

fn op_engine_create(inp: &mut Input) {
    let real = size_of::<cg_engine_config>();
    let paths: [&[u8]; 4] = [b"\0", b"/nonexistent/comgrasp-fuzz-bundle\0", b"\xff\xfe\0", b"/proc\0"];
    let path_sel = inp.u8();
    let mut padded = Padded { value: cg_engine_config::default(), tail: [0; 64] };
    let c = &mut padded.value;
    c.struct_size = struct_size(inp, real);
    c.bundle_path = if path_sel % 5 == 4 { null() } else { paths[usize::from(path_sel % 5)].as_ptr() as *const c_char };
    c.enable_fk = u32::from(inp.u8() % 3);
    c.ring_capacity = inp.u32() % 70_000;
    c.max_streams = inp.u32() % 1100;
    c.reserved = u32::from(inp.u8() % 4 == 0);
    // A C caller can store any integer in the enum field: write it as one (values 4 and 5
    // are not cg_coordinate_system values). Other fields keep their defaults (NULL).
    let coords = u32::from(inp.u8() % 6);
    unsafe {
        let base = c as *mut cg_engine_config as *mut u8;
        base.add(std::mem::offset_of!(cg_engine_config, coordinate_system)).cast::<u32>().write(coords);
    }
    let cfg_ptr = if inp.u8() % 8 == 0 { null() } else { &padded.value as *const cg_engine_config };
    let mut out: *mut cg_engine = 0x55 as *mut cg_engine; // must stay untouched
    let out_ptr = if inp.u8() % 8 == 0 { null_mut() } else { &mut out as *mut *mut cg_engine };
    let st = unsafe { cg_engine_create(cfg_ptr, out_ptr) };
    // No bundle can load here (no embedded default, COMGRASP_BUNDLE removed): never CG_OK.
    check(
        "cg_engine_create",
        st,
        &[CG_ERR_NULL_POINTER, CG_ERR_INVALID_ARGUMENT, CG_ERR_INVALID_UTF8, CG_ERR_BUNDLE, CG_ERR_IO],
    );
    assert_eq!(out as usize, 0x55, "cg_engine_create wrote *out on failure");
    let _ = padded.tail;
}

fn stream_config(inp: &mut Input) -> Padded<cg_stream_config> {
    let real = size_of::<cg_stream_config>();
    let mut c = cg_stream_config::default();
    c.struct_size = if inp.u8() % 5 == 0 { 40 } else { struct_size(inp, real) }; // 40: v1
    c.use_defaults = u32::from(inp.u8());
    c.seed = inp.u64();
    c.temperature = match inp.u8() % 6 {
        0 => f64::NAN,
        1 => f64::INFINITY,
        2 => -1.0,
        3 => 0.0,
        _ => f64::from(inp.u8()) / 64.0,
    };
    c.top_k = u32::from(inp.u8());
    c.min_len = u32::from(inp.u8() % 8);
    c.max_len = u32::from(inp.u8() % 8);
    // flags: 0, the raw-output flag, or an unknown bit
    c.flags = [0, 0, CG_STREAM_NO_GRASP_PLACEMENT, CG_STREAM_FREE_FEET, CG_STREAM_RAW_OUTPUT, 1 << 9]
        [usize::from(inp.u8() % 6)];
    // version 2: scene anchoring, mostly off; placements good, NaN or not unit
    if inp.u8() % 4 == 0 {
        c.anchor = u32::from(inp.u8() % 16);
        c.reserved = u32::from(inp.u8() % 8 == 0);
        let rotation = |inp: &mut Input| match inp.u8() % 4 {
            0 => [0.0, 0.0, 0.5, 0.5],
            1 => [f32::NAN, 0.0, 0.0, 1.0],
            _ => [0.0, 0.0, 0.0, 1.0],
        };
        c.character_rotation = rotation(inp);
        c.object_rotation = rotation(inp);
        c.object_position = [0.0, if inp.u8() % 8 == 0 { f32::INFINITY } else { 0.5 }, 0.8];
    }
    Padded { value: c, tail: [0; 64] }
}

/// Whether the library must accept this stream config (mirrors the documented rules).
fn stream_config_ok(c: &cg_stream_config) -> bool {
    if (c.struct_size as usize) < 40 {
        return false;
    }
    // What the library reads: the host's first struct_size bytes over the defaults (fields
    // a shorter struct lacks, or only partly has, keep their default bytes).
    let mut e = cg_stream_config::default();
    let n = (c.struct_size as usize).min(size_of::<cg_stream_config>());
    // SAFETY: both are plain-data structs of at least n bytes.
    unsafe { std::ptr::copy_nonoverlapping(c as *const _ as *const u8, &mut e as *mut _ as *mut u8, n) };
    if e.flags & !CG_STREAM_FLAGS_ALL != 0 || e.anchor & !CG_ANCHOR_ALL != 0 || e.reserved != 0 {
        return false;
    }
    let good = |p: &[f32], q: &[f32; 4]| {
        p.iter().chain(q).all(|v| v.is_finite()) && (q.iter().map(|v| v * v).sum::<f32>().sqrt() - 1.0).abs() <= 1e-3
    };
    let (character, object) = (e.anchor & CG_ANCHOR_CHARACTER != 0, e.anchor & CG_ANCHOR_OBJECT != 0);
    if (character && !good(&e.character_position, &e.character_rotation))
        || (object && !good(&e.object_position, &e.object_rotation))
        || (e.anchor & CG_ANCHOR_PLACE_CHARACTER != 0 && (!object || character))
    {
        return false;
    }
    let set = |bit: u32| e.use_defaults & bit == 0;
    let temp_ok = !set(CG_USE_DEFAULT_TEMPERATURE) || (e.temperature.is_finite() && e.temperature >= 0.0);
    let max_ok = !set(CG_USE_DEFAULT_MAX_LEN) || e.max_len >= 1;
    let order_ok = !(set(CG_USE_DEFAULT_MIN_LEN) && set(CG_USE_DEFAULT_MAX_LEN)) || e.min_len <= e.max_len;
    temp_ok && max_ok && order_ok
}

// ---------------------------------------------------------------------------------------

const MAX_OPS: usize = 96;
const MAX_STREAMS_PER_RUN: usize = 24;

fn run(data: &[u8]) {
    let mut inp = Input { data };
    let mut w = World::default();
    let mut f = Frame::default();
    let mut streams_started = 0usize;
    for _ in 0..MAX_OPS {
        if inp.done() {
            break;
        }
        match inp.u8() % 16 {
            // A test engine.
            0 => {
                let ring = usize::from(inp.u8() % 8) + 1;
                let max = u32::from(inp.u8() % 4) + 1;
                let cfg = EngineConfig { ring_capacity: ring, max_streams: max as usize, ..Default::default() };
                let e = Engine::with_source_factory(cfg, factory()).expect("valid test engine config");
                let h = engine_into_handle(e).expect("engine handle") as usize;
                assert!(!w.engines.contains_key(&h), "a handle value was reused");
                w.engines.insert(h, EngineModel { live: true, max_streams: max });
                w.engine_order.push(h);
            }
            1 => op_engine_create(&mut inp),
            2 => {
                let p = w.pick_engine(&mut inp);
                let st = unsafe { cg_engine_destroy(p.ptr()) };
                match p {
                    Pick::Null => expect("cg_engine_destroy(NULL)", st, CG_OK),
                    Pick::Invalid(_) => expect("cg_engine_destroy", st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        expect("cg_engine_destroy", st, CG_OK);
                        w.engines.get_mut(&h).unwrap().live = false;
                        for s in w.streams.values_mut().filter(|s| s.engine == h) {
                            s.engine_gone = true;
                        }
                    }
                }
            }
            // Start (scripted text, NULL or fuzzed config, NULL or real out).
            3 | 4 => {
                let p = w.pick_engine(&mut inp);
                let script = Script {
                    chunks: match inp.u8() % 4 {
                        0 => 1 << 40, // effectively endless
                        n => u64::from(n) * u64::from(inp.u8() % 4 + 1),
                    },
                    frames: u64::from(inp.u8() % 20) + 1,
                    fail_at: match inp.u8() % 4 {
                        0 => Some(u64::from(inp.u8() % 4)),
                        _ => None,
                    },
                };
                let mode = inp.u8();
                let text_bytes: Vec<u8> = match mode % 8 {
                    0 => inp.bytes(12).to_vec(), // arbitrary text (mostly invalid prompts)
                    1 => b"factory_fail".to_vec(),
                    _ => script.text().into_bytes(),
                };
                let cfg = stream_config(&mut inp);
                let use_cfg = mode & 8 != 0;
                let cfg_ptr = if use_cfg { &cfg.value as *const cg_stream_config } else { null() };
                let out_null = mode & 16 != 0 && mode & 32 != 0;
                let mut out: *mut cg_stream = 0x77 as *mut cg_stream;
                let out_ptr = if out_null { null_mut() } else { &mut out as *mut *mut cg_stream };
                if streams_started >= MAX_STREAMS_PER_RUN {
                    continue;
                }
                let counted = mode & 64 != 0;
                let st = if counted {
                    unsafe { cg_start_utf8(p.ptr(), text_bytes.as_ptr(), text_bytes.len(), cfg_ptr, out_ptr) }
                } else {
                    let mut c = text_bytes.clone();
                    c.push(0);
                    unsafe { cg_start(p.ptr(), c.as_ptr() as *const c_char, cfg_ptr, out_ptr) }
                };
                // The effective text (a C string ends at its first NUL).
                let text = if counted {
                    &text_bytes[..]
                } else {
                    &text_bytes[..text_bytes.iter().position(|&b| b == 0).unwrap_or(text_bytes.len())]
                };
                let text_ok =
                    std::str::from_utf8(text).is_ok_and(|t| !t.trim().is_empty()) && !(counted && text.contains(&0));
                let cfg_ok = !use_cfg || stream_config_ok(&cfg.value);
                let factory_fails = text.windows(12).any(|x| x == b"factory_fail");
                // cg_start_utf8 rejects an embedded NUL before looking at anything else.
                let nul_in_counted = counted && text.contains(&0);
                let allowed: Vec<cg_status> = match p {
                    _ if nul_in_counted => vec![CG_ERR_INVALID_ARGUMENT],
                    _ if out_null => vec![CG_ERR_NULL_POINTER],
                    Pick::Null => vec![CG_ERR_NULL_POINTER],
                    Pick::Invalid(_) => vec![CG_ERR_INVALID_HANDLE],
                    Pick::Live(h) => {
                        let full = w.live_streams_of(h) >= w.engines[&h].max_streams;
                        if !text_ok {
                            vec![CG_ERR_INVALID_UTF8, CG_ERR_INVALID_ARGUMENT]
                        } else if !cfg_ok {
                            vec![CG_ERR_INVALID_ARGUMENT]
                        } else if full {
                            vec![CG_ERR_LIMIT]
                        } else if factory_fails {
                            vec![CG_ERR_INVALID_ARGUMENT]
                        } else {
                            vec![CG_OK]
                        }
                    }
                };
                let st = check(if counted { "cg_start_utf8" } else { "cg_start" }, st, &allowed);
                if st == CG_OK {
                    let Pick::Live(eh) = p else { unreachable!() };
                    let h = out as usize;
                    assert!(h != 0x77 && !w.streams.contains_key(&h), "cg_start: bad or reused handle");
                    let mut id = 0u64;
                    expect("cg_stream_id", unsafe { cg_stream_id(out, &mut id) }, CG_OK);
                    let script = Script::parse(std::str::from_utf8(text).unwrap());
                    w.streams.insert(
                        h,
                        StreamModel {
                            engine: eh,
                            script,
                            id,
                            live: true,
                            next: 0,
                            cancelled: false,
                            engine_gone: false,
                            terminal: None,
                        },
                    );
                    w.stream_order.push(h);
                    streams_started += 1;
                } else {
                    assert_eq!(out as usize, 0x77, "cg_start wrote *out on failure");
                }
            }
            // Poll / wait.
            5 | 6 | 7 => {
                let op = inp.u8();
                let p = w.pick_stream(&mut inp);
                let out_null = op % 16 == 0;
                let out_ptr: *mut Frame = if out_null { null_mut() } else { &mut f };
                let (name, st) = if op & 1 == 0 {
                    ("cg_poll_frame", unsafe { cg_poll_frame(p.ptr(), out_ptr) })
                } else {
                    let ms = u32::from(op >> 1) % 4;
                    ("cg_stream_wait", unsafe { cg_stream_wait(p.ptr(), ms, out_ptr) })
                };
                match p {
                    _ if out_null => expect(name, st, CG_ERR_NULL_POINTER),
                    Pick::Null => expect(name, st, CG_ERR_NULL_POINTER),
                    Pick::Invalid(_) => expect(name, st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        check(name, st, &POLL);
                        check_poll(name, st, &f, w.streams.get_mut(&h).unwrap());
                    }
                }
            }
            // Drain a live stream for a while (gets streams to their end).
            8 => {
                let p = w.pick_stream(&mut inp);
                if let Pick::Live(h) = p {
                    for _ in 0..64 {
                        let st = unsafe { cg_stream_wait(h as *mut cg_stream, 2, &mut f) };
                        check("cg_stream_wait", st, &POLL);
                        check_poll("cg_stream_wait", st, &f, w.streams.get_mut(&h).unwrap());
                        if st != CG_OK && st != CG_PENDING {
                            break;
                        }
                    }
                }
            }
            9 => {
                let p = w.pick_stream(&mut inp);
                let st = unsafe { cg_cancel(p.ptr()) };
                match p {
                    Pick::Null => expect("cg_cancel", st, CG_ERR_NULL_POINTER),
                    Pick::Invalid(_) => expect("cg_cancel", st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        expect("cg_cancel", st, CG_OK);
                        w.streams.get_mut(&h).unwrap().cancel();
                    }
                }
            }
            10 => {
                let p = w.pick_stream(&mut inp);
                let st = unsafe { cg_stream_destroy(p.ptr()) };
                match p {
                    Pick::Null => expect("cg_stream_destroy(NULL)", st, CG_OK),
                    Pick::Invalid(_) => expect("cg_stream_destroy", st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        expect("cg_stream_destroy", st, CG_OK);
                        w.streams.get_mut(&h).unwrap().live = false;
                    }
                }
            }
            // A cancel racing a wait on another thread (cg_cancel is any-thread; the
            // waiter wakes up with CANCELLED, or had already taken a frame).
            11 => {
                let p = w.pick_stream(&mut inp);
                let ms = u32::from(inp.u8() % 4);
                if let Pick::Live(h) = p {
                    let waiter = std::thread::spawn(move || {
                        let mut f = Frame::default();
                        let st = unsafe { cg_stream_wait(h as *mut cg_stream, ms, &mut f) };
                        (st, f, cg_last_error_status())
                    });
                    let st = unsafe { cg_cancel(h as *mut cg_stream) };
                    expect("cg_cancel (racing)", st, CG_OK);
                    let (wst, wf, wlast) = waiter.join().expect("waiter thread");
                    let s = w.streams.get_mut(&h).unwrap();
                    // The wait ran before or after the cancel: either outcome is checked
                    // against the model as it was before the cancel.
                    if wst != CG_CANCELLED && wst as i32 >= 0 {
                        check_poll("cg_stream_wait (racing)", wst, &wf, s);
                    } else if (wst as i32) < 0 {
                        assert!(matches!(wst, CG_ERR_INFERENCE), "racing wait: {wst:?}");
                        assert_eq!(wlast, wst);
                        check_poll("cg_stream_wait (racing)", wst, &wf, s);
                    }
                    s.cancel();
                }
            }
            12 => {
                let p = w.pick_stream(&mut inp);
                let mut id = 0u64;
                let out_null = inp.u8() % 8 == 0;
                let st = unsafe { cg_stream_id(p.ptr(), if out_null { null_mut() } else { &mut id }) };
                match p {
                    _ if out_null => expect("cg_stream_id", st, CG_ERR_NULL_POINTER),
                    Pick::Null => expect("cg_stream_id", st, CG_ERR_NULL_POINTER),
                    Pick::Invalid(_) => expect("cg_stream_id", st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        expect("cg_stream_id", st, CG_OK);
                        assert_eq!(id, w.streams[&h].id);
                    }
                }
            }
            13 => {
                let p = w.pick_engine(&mut inp);
                let mut n = u32::MAX;
                let out_null = inp.u8() % 8 == 0;
                let st = unsafe { cg_engine_stream_count(p.ptr(), if out_null { null_mut() } else { &mut n }) };
                match p {
                    _ if out_null => expect("cg_engine_stream_count", st, CG_ERR_NULL_POINTER),
                    Pick::Null => expect("cg_engine_stream_count", st, CG_ERR_NULL_POINTER),
                    Pick::Invalid(_) => expect("cg_engine_stream_count", st, CG_ERR_INVALID_HANDLE),
                    Pick::Live(h) => {
                        expect("cg_engine_stream_count", st, CG_OK);
                        assert_eq!(n, w.live_streams_of(h), "cg_engine_stream_count");
                    }
                }
            }
            // Error and status queries.
            14 => {
                let code = inp.u32() as i32;
                let s = unsafe { CStr::from_ptr(cg_status_string(code)) }.to_str().expect("UTF-8");
                assert!(!s.is_empty());
                let whole = last_error();
                let len = usize::from(inp.u8() % 40);
                let mut buf = [0x7fu8; 48];
                let need = unsafe {
                    cg_last_error_message(
                        if len == 0 && inp.u8() % 2 == 0 { null_mut() } else { buf.as_mut_ptr() as *mut c_char },
                        len,
                    )
                };
                assert_eq!(need, whole.len() + 1, "cg_last_error_message size");
                if len > 0 {
                    let n = whole.len().min(len - 1);
                    assert_eq!(&buf[..n], &whole.as_bytes()[..n]);
                    assert_eq!(buf[n], 0, "not NUL-terminated");
                    assert!(buf[len..].iter().all(|&b| b == 0x7f), "wrote past len");
                }
                assert_eq!(cg_abi_version(), CG_ABI_VERSION);
                assert_eq!(cg_frame_size(), size_of::<Frame>());
                assert!(!cg_version_string().is_null());
            }
            _ => {
                let mut e = cg_engine_config::default();
                let mut s = cg_stream_config::default();
                expect(
                    "cg_engine_config_init(NULL)",
                    unsafe { cg_engine_config_init(null_mut()) },
                    CG_ERR_NULL_POINTER,
                );
                expect(
                    "cg_stream_config_init(NULL)",
                    unsafe { cg_stream_config_init(null_mut()) },
                    CG_ERR_NULL_POINTER,
                );
                expect("cg_engine_config_init", unsafe { cg_engine_config_init(&mut e) }, CG_OK);
                expect("cg_stream_config_init", unsafe { cg_stream_config_init(&mut s) }, CG_OK);
                // The init functions write a struct the library accepts (struct_size between
                // the first version's size and the library's own): creating an engine from
                // it fails only on the bundle.
                assert!(
                    e.struct_size >= 32 && e.struct_size as usize <= size_of::<cg_engine_config>(),
                    "{}",
                    e.struct_size
                );
                assert_eq!(s.struct_size, 40, "cg_stream_config_init is the first version's entry point");
                assert_eq!(s.use_defaults, CG_USE_DEFAULT_ALL);
                e.bundle_path = c"/nonexistent/comgrasp-fuzz-bundle".as_ptr();
                let mut out = null_mut();
                expect("cg_engine_create(initialized cfg)", unsafe { cg_engine_create(&e, &mut out) }, CG_ERR_BUNDLE);
            }
        }
    }
    // Tear down: every live stream, then every live engine, is destroyed, and each destroy
    // succeeds exactly once (streams outliving their engine happen through op 2 above).
    for h in w.stream_order.iter().chain(&w.engine_order) {
        if let Some(s) = w.streams.get(h) {
            if s.live {
                expect("cg_stream_destroy (teardown)", unsafe { cg_stream_destroy(*h as *mut cg_stream) }, CG_OK);
            }
        } else if w.engines[h].live {
            expect("cg_engine_destroy (teardown)", unsafe { cg_engine_destroy(*h as *mut cg_engine) }, CG_OK);
        }
    }
}

fuzz_target!(|data: &[u8]| {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        // No bundle may be found by cg_engine_create (the fuzz build has no embedded one).
        std::env::remove_var("COMGRASP_BUNDLE");
    });
    run(data);
});
