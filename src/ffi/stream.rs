//! Stream functions: poll, wait, cancel, destroy.
//!
//! A stream is used by one thread at a time (its mutex is only ever `try_lock`ed, so
//! concurrent use is reported as `CG_ERR_WRONG_STATE` instead of blocking), except
//! `cg_cancel`, which works from any thread at any time.
use std::ffi::c_char;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::handle::{cg_stream, StreamEntry, STREAMS};
use super::last_error::record;
use super::panic::{boundary, Failure, PoisonOnUnwind};
use super::status::cg_status;
use crate::frame::cg_frame;
use crate::stream::{PollResult, Stream};

fn lookup_stream(stream: *mut cg_stream) -> Result<Arc<StreamEntry>, Failure> {
    if stream.is_null() {
        return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "stream is NULL"));
    }
    let entry = STREAMS.get(stream as usize).ok_or_else(|| {
        Failure::new(
            cg_status::CG_ERR_INVALID_HANDLE,
            "stream is not a live cg_stream handle (destroyed, or not from cg_start)",
        )
    })?;
    if entry.poisoned.load(Ordering::SeqCst) {
        return Err(Failure::new(
            cg_status::CG_ERR_PANIC,
            "stream is poisoned by an earlier internal panic; destroy it",
        ));
    }
    Ok(entry)
}

/// Maps a poll result to a status; for an error, records the worker's message.
fn poll_status(r: PollResult, stream: &Stream) -> cg_status {
    match r {
        PollResult::Frame => cg_status::CG_OK,
        PollResult::Pending => cg_status::CG_PENDING,
        PollResult::End => cg_status::CG_END,
        PollResult::Cancelled => cg_status::CG_CANCELLED,
        PollResult::Error => match stream.error() {
            Some(e) => {
                let s = cg_status::from_error(e);
                record(s, e);
                s
            }
            None => {
                record(cg_status::CG_ERR_INFERENCE, &"the stream's worker failed");
                cg_status::CG_ERR_INFERENCE
            }
        },
    }
}

/// Shared body of `cg_poll_frame` and `cg_stream_wait`.
fn poll_with(
    stream: *mut cg_stream,
    out: *mut cg_frame,
    f: impl FnOnce(&mut Stream, &mut cg_frame) -> PollResult,
) -> Result<cg_status, Failure> {
    if out.is_null() {
        return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
    }
    let entry = lookup_stream(stream)?;
    let _poison = PoisonOnUnwind(&entry.poisoned);
    let mut guard = entry.stream.try_lock().ok_or_else(|| {
        Failure::new(
            cg_status::CG_ERR_WRONG_STATE,
            "stream is in use by another thread (one thread at a time; only cg_cancel may run concurrently)",
        )
    })?;
    // SAFETY: the caller passes a valid, writable, aligned cg_frame; written only on CG_OK.
    let out = unsafe { &mut *out };
    let r = f(&mut guard, out);
    Ok(poll_status(r, &guard))
}

/// Takes the next frame of the stream if one is ready. **Never blocks and never
/// allocates**: call it every game tick. Returns `CG_OK` and writes `*out` (the caller owns
/// the memory; nothing is written for any other status); `CG_PENDING` when no frame is
/// ready yet; `CG_END` on the first call after the frame with `is_last = 1` (further
/// calls keep returning `CG_END`, also after a `cg_cancel`); `CG_CANCELLED` after
/// `cg_cancel` or engine destruction (undelivered frames are discarded and the stream's
/// buffers are freed; further calls keep returning `CG_CANCELLED`); or the worker's error
/// (e.g. `CG_ERR_INFERENCE`, message in `cg_last_error`) after the frames produced before
/// it. Misuse: `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_HANDLE` (destroyed stream),
/// `CG_ERR_WRONG_STATE` (another thread is using the stream).
/// One thread at a time per stream.
#[no_mangle]
pub unsafe extern "C" fn cg_poll_frame(stream: *mut cg_stream, out: *mut cg_frame) -> cg_status {
    boundary("cg_poll_frame", || poll_with(stream, out, |s, out| s.poll(out)))
}

/// Like `cg_poll_frame`, but when no frame is ready it blocks up to `timeout_ms`
/// milliseconds for one (or for the end, an error or a cancel, also a `cg_cancel` from
/// another thread). Returns `CG_PENDING` only when the timeout expired; `timeout_ms = 0`
/// behaves like `cg_poll_frame`. For hosts with their own consumer thread; never call it
/// on a game's main thread. One thread at a time per stream.
#[no_mangle]
pub unsafe extern "C" fn cg_stream_wait(stream: *mut cg_stream, timeout_ms: u32, out: *mut cg_frame) -> cg_status {
    boundary("cg_stream_wait", || {
        poll_with(stream, out, |s, out| s.wait(out, Duration::from_millis(u64::from(timeout_ms))))
    })
}

/// Asks the stream's worker to stop; it stops within one generator call (~8 ms with the
/// default bundle on 2 cores) and releases its model state. From then on `cg_poll_frame`
/// returns `CG_CANCELLED` (undelivered frames are discarded), except on a stream that has
/// already delivered its `is_last` frame or returned `CG_END` or its error: that result
/// stays (a cancel after the end changes nothing). Never blocks. Idempotent (cancelling twice, or a finished
/// stream, is `CG_OK`). The handle stays valid: destroy it with `cg_stream_destroy`. **Any
/// thread**, also while another thread is inside `cg_poll_frame` or `cg_stream_wait` on the
/// same stream (that call then returns `CG_CANCELLED`).
#[no_mangle]
pub unsafe extern "C" fn cg_cancel(stream: *mut cg_stream) -> cg_status {
    boundary("cg_cancel", || {
        let entry = lookup_stream(stream)?;
        let _poison = PoisonOnUnwind(&entry.poisoned);
        entry.canceller.cancel();
        Ok(cg_status::CG_OK)
    })
}

/// Destroys a stream: cancels its worker if it is still running, joins it (waits at most
/// one generator call, ~8 ms with the default bundle on 2 cores) and frees everything.
/// After this call the handle is invalid and any use of it, including a second destroy,
/// returns `CG_ERR_INVALID_HANDLE`. NULL is accepted and ignored (`CG_OK`). Works on a
/// poisoned stream and after its engine was destroyed. Any thread, but not while another
/// thread still uses the stream (a concurrent `cg_stream_wait` is woken and finishes
/// first).
#[no_mangle]
pub unsafe extern "C" fn cg_stream_destroy(stream: *mut cg_stream) -> cg_status {
    boundary("cg_stream_destroy", || {
        if stream.is_null() {
            return Ok(cg_status::CG_OK);
        }
        let entry = STREAMS.remove(stream as usize).ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_INVALID_HANDLE, "stream is not a live cg_stream handle (already destroyed?)")
        })?;
        // Wake a concurrent cg_stream_wait so the lock below is free promptly; then join the
        // worker here, so no thread outlives the handle (matters in Unity, which never
        // unloads a native plugin).
        entry.canceller.cancel();
        entry.stream.lock().close();
        Ok(cg_status::CG_OK)
    })
}

/// Writes the stream's id (unique per engine, starting at 1; frames carry it as
/// `stream_id`) to `*out`. Any thread (it only reads an immutable value).
#[no_mangle]
pub unsafe extern "C" fn cg_stream_id(stream: *mut cg_stream, out: *mut u64) -> cg_status {
    boundary("cg_stream_id", || {
        if out.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
        }
        let entry = lookup_stream(stream)?;
        unsafe { out.write(entry.id) };
        Ok(cg_status::CG_OK)
    })
}

/// Longest catalogue name `cg_stream_info.object_name` holds, NUL excluded (bundle
/// verification rejects longer names).
pub const CG_OBJECT_NAME_MAX: usize = 63;
const _: () = assert!(CG_OBJECT_NAME_MAX == crate::bundle::manifest::OBJECT_NAME_MAX);

/// What a stream is about (`cg_stream_get_info`). Fixed layout.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct cg_stream_info {
    /// The stream's id, as `cg_stream_id`.
    pub stream_id: u64,
    /// Index of the stream's object in the bundle's catalogue (manifest `objects`): the
    /// object the frames' `object_*` fields pose and the contact stage rests and carries.
    pub object_index: u32,
    /// 1 when the prompt names that object (its name or one of its aliases); 0 when the
    /// prompt names no catalogue object and the catalogue's first object stands in.
    pub object_named: u32,
    /// The object's catalogue name, NUL-terminated (e.g. "mug", "cubelarge").
    pub object_name: [c_char; 64],
}

/// Writes what `stream` is about to `*out`: its id and the catalogue object its prompt
/// names (or the stand-in when it names none, `object_named` 0). Errors:
/// `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_HANDLE`, `CG_ERR_WRONG_STATE` for a stream whose
/// engine has no model bundle. Any thread (it reads values fixed at `cg_start`).
#[no_mangle]
pub unsafe extern "C" fn cg_stream_get_info(stream: *mut cg_stream, out: *mut cg_stream_info) -> cg_status {
    boundary("cg_stream_get_info", || {
        if out.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
        }
        let entry = lookup_stream(stream)?;
        let o = entry.object.as_ref().ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_WRONG_STATE, "the stream has no catalogue object (no bundle)")
        })?;
        let mut info = cg_stream_info {
            stream_id: entry.id,
            object_index: o.index as u32,
            object_named: u32::from(o.alias.is_some()),
            object_name: [0; 64],
        };
        // Verified at bundle load: at most CG_OBJECT_NAME_MAX bytes, no NUL.
        for (d, s) in info.object_name.iter_mut().zip(o.name.bytes().take(CG_OBJECT_NAME_MAX)) {
            *d = s as c_char;
        }
        unsafe { out.write(info) };
        Ok(cg_status::CG_OK)
    })
}
