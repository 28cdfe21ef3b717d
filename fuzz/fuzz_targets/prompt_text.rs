//! The text path through the C ABI: arbitrary bytes as a prompt, into `cg_start` (as a
//! NUL-terminated string) or `cg_start_utf8` (counted bytes), on one engine made from the
//! real tiny bundle (`models/tiny`, or `$COMGRASP_FUZZ_BUNDLE`) and kept for the whole run.
//!
//! Input: byte 0 picks the entry point (bit 0) and whether to wait for the first frame
//! (bit 1; the tokenizer and text encoder then run on the prompt); the rest is the text.
//! Asserted for every input:
//! * the status is exactly what the documented rules give (CG_ERR_INVALID_ARGUMENT for
//!   over-long, blank or NUL-containing text, CG_ERR_INVALID_UTF8 for bad UTF-8, else
//!   CG_OK), and a failure leaves a matching `cg_last_error_status` and a message;
//! * an accepted prompt yields a first frame (or a clean end) within 20 s: never an
//!   inference error, a panic or a hang; the frame is the stream's frame 0, with finite values;
//! * cancel, poll (CG_CANCELLED) and destroy then succeed, and the engine has no stream left.
#![no_main]

use std::ffi::{c_char, CStr, CString};
use std::ptr::{null, null_mut};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use comgrasp::ffi::*;
use comgrasp::Frame;
use libfuzzer_sys::fuzz_target;

const MAX_TEXT: usize = CG_MAX_TEXT_BYTES as usize;

struct Engine(*mut cg_engine);
// The handle is an opaque id, valid from any thread.
unsafe impl Send for Engine {}
unsafe impl Sync for Engine {}

fn engine() -> *mut cg_engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE
        .get_or_init(|| {
            let dir = std::env::var("COMGRASP_FUZZ_BUNDLE")
                .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/../models/tiny").to_string());
            let path = CString::new(dir.clone()).unwrap();
            let mut cfg = cg_engine_config::default();
            assert_eq!(unsafe { cg_engine_config_init(&mut cfg) }, cg_status::CG_OK);
            cfg.bundle_path = path.as_ptr();
            cfg.max_streams = 2;
            let mut e = null_mut();
            let st = unsafe { cg_engine_create(&cfg, &mut e) };
            assert_eq!(st, cg_status::CG_OK, "cannot load the bundle {dir}: {}", last_error());
            Engine(e)
        })
        .0
}

fn last_error() -> String {
    unsafe { CStr::from_ptr(cg_last_error()) }.to_string_lossy().into_owned()
}

/// What the documented rules say `cg_start`/`cg_start_utf8` returns for these bytes.
fn expected(bytes: &[u8], counted: bool) -> cg_status {
    if bytes.len() > MAX_TEXT {
        return cg_status::CG_ERR_INVALID_ARGUMENT;
    }
    if counted && bytes.contains(&0) {
        return cg_status::CG_ERR_INVALID_ARGUMENT;
    }
    match std::str::from_utf8(bytes) {
        Err(_) => cg_status::CG_ERR_INVALID_UTF8,
        Ok(t) if t.trim().is_empty() => cg_status::CG_ERR_INVALID_ARGUMENT,
        Ok(_) => cg_status::CG_OK,
    }
}

fn frame_is_finite(f: &Frame) -> bool {
    let mut v: Vec<f32> = Vec::new();
    v.extend(f.root_translation);
    v.extend(f.root_rotation);
    f.body_rotations.iter().chain(&f.left_hand_rotations).chain(&f.right_hand_rotations).for_each(|q| v.extend(q));
    v.extend(f.object_translation);
    v.extend(f.object_rotation);
    v.extend(f.object_centre);
    v.extend(f.left_wrist_to_object);
    v.extend(f.right_wrist_to_object);
    v.extend(f.contact_probability);
    f.time_s.is_finite() && v.iter().all(|x| x.is_finite())
}

fuzz_target!(|data: &[u8]| {
    let e = engine();
    let (mode, text) = data.split_first().map_or((0, &[][..]), |(m, t)| (*m, t));
    let counted = mode & 1 == 1;
    let wait_first = mode & 2 == 2;
    let mut s = null_mut();
    let (st, want) = if counted {
        let st = unsafe { cg_start_utf8(e, text.as_ptr(), text.len(), null(), &mut s) };
        (st, expected(text, true))
    } else {
        // A C caller's string ends at the first NUL.
        let c_text = &text[..text.iter().position(|&b| b == 0).unwrap_or(text.len())];
        let mut buf = c_text.to_vec();
        buf.push(0);
        let st = unsafe { cg_start(e, buf.as_ptr() as *const c_char, null(), &mut s) };
        (st, expected(c_text, false))
    };
    assert_eq!(st, want, "cg_start on {} bytes: {}", text.len(), last_error());
    if st != cg_status::CG_OK {
        assert!(s.is_null(), "out written on failure");
        assert_eq!(cg_last_error_status(), st);
        assert!(!last_error().is_empty());
        return;
    }
    let mut id = 0u64;
    assert_eq!(unsafe { cg_stream_id(s, &mut id) }, cg_status::CG_OK);
    if wait_first {
        let mut f = Frame::default();
        let t0 = Instant::now();
        let r = loop {
            let r = unsafe { cg_stream_wait(s, 100, &mut f) };
            if r != cg_status::CG_PENDING {
                break r;
            }
            assert!(t0.elapsed() < Duration::from_secs(20), "no first frame within 20 s (hang?)");
        };
        match r {
            cg_status::CG_OK => {
                assert_eq!((f.stream_id, f.frame_index), (id, 0), "first frame");
                assert!(frame_is_finite(&f), "non-finite values in the first frame");
            }
            cg_status::CG_END => {}
            other => panic!("an accepted prompt failed: {other:?}: {}", last_error()),
        }
    }
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    let mut n = u32::MAX;
    assert_eq!(unsafe { cg_engine_stream_count(e, &mut n) }, cg_status::CG_OK);
    assert_eq!(n, 0, "a stream outlived cg_stream_destroy");
});
