//! Engine functions: create, destroy, start a stream.
use std::ffi::c_char;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use super::config::{cg_engine_config, cg_stream_config, engine_config_from_c, optional_str, stream_config_from_c};
use super::handle::{cg_engine, cg_stream, EngineEntry, StreamEntry, ENGINES, STREAMS};
use super::panic::{boundary, Failure, PoisonOnUnwind};
use super::status::cg_status;
use crate::engine::{Engine, MAX_TEXT_BYTES};
use crate::frame::cg_frame;
use parking_lot::Mutex;

fn null(what: &str) -> Failure {
    Failure::new(cg_status::CG_ERR_NULL_POINTER, format_args!("{what} is NULL"))
}

pub(crate) fn lookup_engine(engine: *mut cg_engine) -> Result<Arc<EngineEntry>, Failure> {
    if engine.is_null() {
        return Err(null("engine"));
    }
    let entry = ENGINES.get(engine as usize).ok_or_else(|| {
        Failure::new(
            cg_status::CG_ERR_INVALID_HANDLE,
            "engine is not a live cg_engine handle (destroyed, or not from cg_engine_create)",
        )
    })?;
    if entry.poisoned.load(Ordering::SeqCst) {
        return Err(Failure::new(
            cg_status::CG_ERR_PANIC,
            "engine is poisoned by an earlier internal panic; destroy it",
        ));
    }
    Ok(entry)
}

/// Creates an engine: loads and verifies the model bundle selected by `cfg->bundle_path`
/// (NULL: `COMGRASP_BUNDLE`, else the embedded default; see `cg_engine_config`) and
/// prepares its graphs (takes a fraction of a second; do it once, not per stream).
/// On success writes a new handle to `*out`; the caller owns it and must destroy it exactly
/// once with `cg_engine_destroy`. On failure `*out` is left untouched.
/// Errors: `CG_ERR_NULL_POINTER` (cfg or out NULL), `CG_ERR_INVALID_ARGUMENT` (bad field or
/// struct_size), `CG_ERR_INVALID_UTF8` (bundle_path), `CG_ERR_BUNDLE`, `CG_ERR_IO`.
/// Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_create(cfg: *const cg_engine_config, out: *mut *mut cg_engine) -> cg_status {
    boundary("cg_engine_create", || {
        if cfg.is_null() {
            return Err(null("cfg"));
        }
        if out.is_null() {
            return Err(null("out"));
        }
        let config = unsafe { engine_config_from_c(cfg)? };
        let engine = Engine::new(config)?;
        let entry = Arc::new(EngineEntry { engine, poisoned: AtomicBool::new(false) });
        let handle =
            ENGINES.insert(entry).ok_or_else(|| Failure::new(cg_status::CG_ERR_LIMIT, "too many engine handles"))?;
        unsafe { out.write(handle as *mut cg_engine) };
        Ok(cg_status::CG_OK)
    })
}

/// Destroys an engine. Streams still generating are cancelled (they then report
/// `CG_CANCELLED`) and this call waits until their workers have stopped (at most about one
/// token step each), so no inference runs afterwards and the model memory is released.
/// Stream handles stay valid and must still be destroyed with `cg_stream_destroy`; streams
/// that had already finished keep their buffered frames. NULL is accepted and ignored
/// (`CG_OK`). A stale or already destroyed handle gives `CG_ERR_INVALID_HANDLE`.
/// Any thread; calls on this engine running concurrently on other threads finish safely
/// (the engine is freed when the last of them returns).
#[no_mangle]
pub unsafe extern "C" fn cg_engine_destroy(engine: *mut cg_engine) -> cg_status {
    boundary("cg_engine_destroy", || {
        if engine.is_null() {
            return Ok(cg_status::CG_OK);
        }
        let entry = ENGINES.remove(engine as usize).ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_INVALID_HANDLE, "engine is not a live cg_engine handle (already destroyed?)")
        })?;
        drop(entry); // Engine::drop: cancel running streams, wait for their workers.
        Ok(cg_status::CG_OK)
    })
}

/// Writes the number of streams of this engine that are alive (started and not yet
/// destroyed) to `*out`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_stream_count(engine: *mut cg_engine, out: *mut u32) -> cg_status {
    boundary("cg_engine_stream_count", || {
        if out.is_null() {
            return Err(null("out"));
        }
        let entry = lookup_engine(engine)?;
        let _poison = PoisonOnUnwind(&entry.poisoned);
        let n = entry.engine.live_streams() as u32;
        unsafe { out.write(n) };
        Ok(cg_status::CG_OK)
    })
}

/// Bounded `strlen`: the length of a NUL-terminated string, or `None` if no NUL appears in
/// the first `limit + 1` bytes (so an over-long or unterminated text is never scanned far).
///
/// SAFETY: `p` points to a NUL-terminated string or at least `limit + 1` readable bytes.
pub(crate) unsafe fn bounded_strlen(p: *const c_char, limit: usize) -> Option<usize> {
    (0..=limit).find(|&i| unsafe { *p.add(i) } == 0)
}

/// Starts generating motion for `text` (NUL-terminated UTF-8, 1..=`CG_MAX_TEXT_BYTES`
/// bytes, not only whitespace) on a new worker thread and returns at once; poll the
/// frames with `cg_poll_frame`. `cfg` may be NULL (all defaults). On success writes a new
/// stream handle to `*out`; the caller owns it and must destroy it exactly once with
/// `cg_stream_destroy` (which also stops the worker). `text` and `cfg` are only read during
/// the call. Errors: `CG_ERR_NULL_POINTER` (engine, text or out NULL),
/// `CG_ERR_INVALID_HANDLE`, `CG_ERR_INVALID_UTF8`, `CG_ERR_INVALID_ARGUMENT` (empty or
/// over-long text, bad cfg), `CG_ERR_LIMIT` (`max_streams` streams alive), `CG_ERR_IO`.
/// Any thread, concurrently with other calls on the same engine.
#[no_mangle]
pub unsafe extern "C" fn cg_start(
    engine: *mut cg_engine,
    text: *const c_char,
    cfg: *const cg_stream_config,
    out: *mut *mut cg_stream,
) -> cg_status {
    boundary("cg_start", || {
        if text.is_null() {
            return Err(null("text"));
        }
        let len = unsafe { bounded_strlen(text, MAX_TEXT_BYTES) }.ok_or_else(|| {
            Failure::new(
                cg_status::CG_ERR_INVALID_ARGUMENT,
                format_args!("text is longer than CG_MAX_TEXT_BYTES ({MAX_TEXT_BYTES}) bytes"),
            )
        })?;
        let bytes = unsafe { std::slice::from_raw_parts(text as *const u8, len) };
        unsafe { start(engine, bytes, cfg, out) }
    })
}

/// Same as `cg_start`, with the text given as `len` bytes of UTF-8 (no NUL needed; an
/// embedded NUL is rejected as `CG_ERR_INVALID_ARGUMENT`). Convenient from C#
/// (`fixed (byte* p = utf8)`) and other languages with counted strings. A NULL `text`
/// gives `CG_ERR_NULL_POINTER` even when `len` is 0.
#[no_mangle]
pub unsafe extern "C" fn cg_start_utf8(
    engine: *mut cg_engine,
    text: *const u8,
    len: usize,
    cfg: *const cg_stream_config,
    out: *mut *mut cg_stream,
) -> cg_status {
    boundary("cg_start_utf8", || {
        if text.is_null() {
            return Err(null("text"));
        }
        if len > MAX_TEXT_BYTES {
            return Err(Failure::new(
                cg_status::CG_ERR_INVALID_ARGUMENT,
                format_args!("text is {len} bytes, longer than CG_MAX_TEXT_BYTES ({MAX_TEXT_BYTES})"),
            ));
        }
        let bytes = unsafe { std::slice::from_raw_parts(text, len) };
        if bytes.contains(&0) {
            return Err(Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, "text contains a NUL byte"));
        }
        unsafe { start(engine, bytes, cfg, out) }
    })
}

/// The common part of `cg_start` and `cg_start_utf8`, after the text bytes are bounded.
unsafe fn start(
    engine: *mut cg_engine,
    bytes: &[u8],
    cfg: *const cg_stream_config,
    out: *mut *mut cg_stream,
) -> Result<cg_status, Failure> {
    if out.is_null() {
        return Err(null("out"));
    }
    let entry = lookup_engine(engine)?;
    let text = std::str::from_utf8(bytes)
        .map_err(|e| Failure::new(cg_status::CG_ERR_INVALID_UTF8, format_args!("text is not valid UTF-8: {e}")))?;
    let opts = unsafe { stream_config_from_c(cfg)? };
    let stream = {
        let _poison = PoisonOnUnwind(&entry.poisoned);
        entry.engine.start(text, opts)?
    };
    let (id, object) = (stream.id(), stream.object().cloned());
    let canceller = stream.canceller();
    let stream_entry =
        Arc::new(StreamEntry { id, object, canceller, stream: Mutex::new(stream), poisoned: AtomicBool::new(false) });
    // If registration fails, dropping the entry stops and joins the worker.
    let handle =
        STREAMS.insert(stream_entry).ok_or_else(|| Failure::new(cg_status::CG_ERR_LIMIT, "too many stream handles"))?;
    unsafe { out.write(handle as *mut cg_stream) };
    Ok(cg_status::CG_OK)
}

/// Writes the bundle's rest skeleton to `out` (`n` = `CG_NUM_JOINTS` rows of x, y, z, in
/// SMPL-X joint order) in the engine's coordinate system and units: the pose the frames'
/// local rotations are relative to (a host's skeleton in that pose reproduces
/// `joint_positions` from the rotations alone), and what retargeting starts from. Errors:
/// `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_HANDLE`, `CG_ERR_INVALID_ARGUMENT` (`n` is not
/// `CG_NUM_JOINTS`), `CG_ERR_WRONG_STATE` (an engine without a bundle). Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_get_rest_joints(engine: *mut cg_engine, out: *mut [f32; 3], n: usize) -> cg_status {
    boundary("cg_engine_get_rest_joints", || {
        if out.is_null() {
            return Err(null("out"));
        }
        let entry = lookup_engine(engine)?;
        if n != crate::frame::CG_NUM_JOINTS {
            return Err(Failure::new(
                cg_status::CG_ERR_INVALID_ARGUMENT,
                format_args!("n is {n}; the skeleton has CG_NUM_JOINTS = {} joints", crate::frame::CG_NUM_JOINTS),
            ));
        }
        let rest = entry.engine.rest_joints().ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_WRONG_STATE, "the engine has no model bundle (no rest skeleton)")
        })?;
        unsafe { std::ptr::copy_nonoverlapping(rest.as_ptr(), out, n) };
        Ok(cg_status::CG_OK)
    })
}

/// Writes `n_frames` frames of this engine (polled from its streams, in its coordinate
/// system) as BVH files for animation tools: the body (SMPL-X skeleton with fingers, y up,
/// centimetres, ZXY rotation channels, the bundle's fps) to `body_path`, and the object's
/// track (one root joint) to `object_path` unless it is NULL (docs/retargeting.md, "BVH").
/// Paths are UTF-8. Errors: `CG_ERR_NULL_POINTER` (`frames` with `n_frames` > 0, or
/// `body_path`), `CG_ERR_INVALID_HANDLE`, `CG_ERR_INVALID_UTF8` / `CG_ERR_INVALID_ARGUMENT`
/// (a path not UTF-8 or empty; a non-finite frame value), `CG_ERR_WRONG_STATE` (an engine
/// without a bundle), `CG_ERR_IO` (a file that cannot be written). Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_write_bvh(
    engine: *mut cg_engine,
    frames: *const cg_frame,
    n_frames: usize,
    body_path: *const c_char,
    object_path: *const c_char,
) -> cg_status {
    boundary("cg_engine_write_bvh", || {
        if frames.is_null() && n_frames > 0 {
            return Err(null("frames"));
        }
        let body = unsafe { optional_str(body_path, "body_path")? }.ok_or_else(|| null("body_path"))?;
        let object = unsafe { optional_str(object_path, "object_path")? };
        let entry = lookup_engine(engine)?;
        // SAFETY: the caller passes `n_frames` readable frames (NULL only with none).
        let frames = if n_frames == 0 { &[][..] } else { unsafe { std::slice::from_raw_parts(frames, n_frames) } };
        entry.engine.write_bvh(frames, Path::new(body), object.map(Path::new))?;
        Ok(cg_status::CG_OK)
    })
}
