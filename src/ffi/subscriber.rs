//! Shared-memory subscriber functions, so C, C++ and C# processes read an engine's frames
//! without Rust: open by publish name, receive frames and stream events (never blocking),
//! read counters, close. Also the publishing engine's counters.
use std::ffi::c_char;
use std::mem::size_of;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use parking_lot::Mutex;

use super::config::read_versioned;
use super::engine::{bounded_strlen, lookup_engine};
use super::handle::{cg_subscriber, SubscriberEntry, SUBSCRIBERS};
use super::panic::{boundary, Failure, PoisonOnUnwind};
use super::status::cg_status;
use crate::frame::cg_frame;
use crate::shm::{
    cg_publisher_stats, cg_stream_event, cg_subscriber_stats, FrameSubscriber, CG_MAX_PUBLISH_NAME_BYTES,
    CG_MAX_SUBSCRIBER_BUFFER,
};

/// Settings of a subscriber. Initialize with `cg_subscriber_config_init`, then change fields.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct cg_subscriber_config {
    /// `sizeof(cg_subscriber_config)` of the host's header (set by the `_init` function).
    pub struct_size: u32,
    /// Frames kept for this subscriber between two reads, 1..=`CG_MAX_SUBSCRIBER_BUFFER`;
    /// when it is full the oldest frame is overwritten and counted in
    /// `cg_subscriber_stats.frames_dropped` (the publisher never waits). Default 256.
    pub buffer_frames: u32,
    /// Reserved, must be 0.
    pub reserved: u64,
}

impl Default for cg_subscriber_config {
    fn default() -> Self {
        cg_subscriber_config {
            struct_size: size_of::<cg_subscriber_config>() as u32,
            buffer_frames: CG_MAX_SUBSCRIBER_BUFFER as u32,
            reserved: 0,
        }
    }
}

fn lookup(sub: *mut cg_subscriber) -> Result<Arc<SubscriberEntry>, Failure> {
    if sub.is_null() {
        return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "subscriber is NULL"));
    }
    let entry = SUBSCRIBERS.get(sub as usize).ok_or_else(|| {
        Failure::new(
            cg_status::CG_ERR_INVALID_HANDLE,
            "subscriber is not a live cg_subscriber handle (closed, or not from cg_subscriber_open)",
        )
    })?;
    if entry.poisoned.load(Ordering::SeqCst) {
        return Err(Failure::new(
            cg_status::CG_ERR_PANIC,
            "subscriber is poisoned by an earlier internal panic; close it",
        ));
    }
    Ok(entry)
}

/// Runs `f` on the subscriber, which one thread at a time may use.
fn with_subscriber<R>(
    sub: *mut cg_subscriber,
    f: impl FnOnce(&mut FrameSubscriber) -> Result<R, Failure>,
) -> Result<R, Failure> {
    let entry = lookup(sub)?;
    let _poison = PoisonOnUnwind(&entry.poisoned);
    let mut guard = entry.subscriber.try_lock().ok_or_else(|| {
        Failure::new(cg_status::CG_ERR_WRONG_STATE, "subscriber is in use by another thread (one thread at a time)")
    })?;
    f(&mut guard)
}

/// Fills `*cfg` with the defaults and the right `struct_size`. `CG_ERR_NULL_POINTER` if
/// `cfg` is NULL. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_config_init(cfg: *mut cg_subscriber_config) -> cg_status {
    boundary("cg_subscriber_config_init", || {
        if cfg.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "cg_subscriber_config_init: cfg is NULL"));
        }
        unsafe { cfg.write_unaligned(cg_subscriber_config::default()) };
        Ok(cg_status::CG_OK)
    })
}

/// Subscribes to the frames and stream events an engine publishes under `name` (its
/// `cg_engine_config.publish_name`), in this or another process. Works before the
/// publisher exists and keeps working when it restarts; frames arrive from now on (no
/// history). `cfg` may be NULL (defaults). On success writes a new handle to `*out`; close
/// it exactly once with `cg_subscriber_close`. Errors: `CG_ERR_NULL_POINTER` (name or out),
/// `CG_ERR_INVALID_UTF8`, `CG_ERR_INVALID_ARGUMENT` (bad name or cfg), `CG_ERR_LIMIT` (the
/// name already has the most subscribers a service allows, 8), `CG_ERR_SHM`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_open(
    name: *const c_char,
    cfg: *const cg_subscriber_config,
    out: *mut *mut cg_subscriber,
) -> cg_status {
    boundary("cg_subscriber_open", || {
        if name.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "name is NULL"));
        }
        if out.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
        }
        let config = if cfg.is_null() {
            cg_subscriber_config::default()
        } else {
            // SAFETY: every field is an integer: any bit pattern is valid.
            unsafe { read_versioned(cfg, size_of::<cg_subscriber_config>(), "cg_subscriber_config")?.assume_init() }
        };
        if config.reserved != 0 {
            return Err(Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, "cg_subscriber_config.reserved must be 0"));
        }
        // Never scan further than one byte past the longest valid name.
        let len = unsafe { bounded_strlen(name, CG_MAX_PUBLISH_NAME_BYTES) }.ok_or_else(|| {
            Failure::new(
                cg_status::CG_ERR_INVALID_ARGUMENT,
                format_args!("name is longer than {CG_MAX_PUBLISH_NAME_BYTES} bytes"),
            )
        })?;
        let bytes = unsafe { std::slice::from_raw_parts(name.cast::<u8>(), len) };
        let name = std::str::from_utf8(bytes)
            .map_err(|_| Failure::new(cg_status::CG_ERR_INVALID_UTF8, "name is not valid UTF-8"))?;
        let subscriber = FrameSubscriber::open(name, config.buffer_frames as usize)?;
        let entry = Arc::new(SubscriberEntry { subscriber: Mutex::new(subscriber), poisoned: AtomicBool::new(false) });
        let handle = SUBSCRIBERS
            .insert(entry)
            .ok_or_else(|| Failure::new(cg_status::CG_ERR_LIMIT, "too many subscriber handles"))?;
        unsafe { out.write(handle as *mut cg_subscriber) };
        Ok(cg_status::CG_OK)
    })
}

/// Copies the oldest unread frame to `*out` and returns `CG_OK`, or returns `CG_PENDING`
/// when there is none (nothing written). Never blocks. Frames of all the publisher's
/// streams arrive interleaved in the order they were generated; tell them apart by
/// `stream_id`. Errors: `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_HANDLE`,
/// `CG_ERR_WRONG_STATE` (another thread is using the subscriber), `CG_ERR_SHM`.
/// One thread at a time per subscriber.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_receive(sub: *mut cg_subscriber, out: *mut cg_frame) -> cg_status {
    boundary("cg_subscriber_receive", || unsafe { receive_with(sub, out, FrameSubscriber::receive) })
}

/// Like `cg_subscriber_receive`, for the stream events (`CG_STREAM_EVENT_*`: started,
/// ended, cancelled, failed). Events and frames are separate queues: a stream's ENDED event
/// may be read before its last frames.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_receive_event(sub: *mut cg_subscriber, out: *mut cg_stream_event) -> cg_status {
    boundary("cg_subscriber_receive_event", || unsafe { receive_with(sub, out, FrameSubscriber::receive_event) })
}

/// Shared body of the two receive functions: `CG_OK` when `receive` copied a sample into
/// `*out`, `CG_PENDING` when there was none.
///
/// SAFETY: `out` is NULL or a valid, writable, aligned `T`.
unsafe fn receive_with<T>(
    sub: *mut cg_subscriber,
    out: *mut T,
    receive: fn(&mut FrameSubscriber, &mut T) -> crate::Result<bool>,
) -> Result<cg_status, Failure> {
    if out.is_null() {
        return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
    }
    with_subscriber(sub, |s| {
        let got = receive(s, unsafe { &mut *out })?;
        Ok(if got { cg_status::CG_OK } else { cg_status::CG_PENDING })
    })
}

/// Writes the subscriber's counters to `*out`. One thread at a time per subscriber.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_get_stats(sub: *mut cg_subscriber, out: *mut cg_subscriber_stats) -> cg_status {
    boundary("cg_subscriber_get_stats", || {
        if out.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
        }
        let stats = with_subscriber(sub, |s| Ok(s.stats()))?;
        unsafe { out.write(stats) };
        Ok(cg_status::CG_OK)
    })
}

/// Closes a subscriber and frees its shared-memory resources. After it the handle is
/// invalid (a second close gives `CG_ERR_INVALID_HANDLE`). NULL is accepted and ignored.
/// Any thread, but not while another thread still uses the subscriber.
#[no_mangle]
pub unsafe extern "C" fn cg_subscriber_close(sub: *mut cg_subscriber) -> cg_status {
    boundary("cg_subscriber_close", || {
        if sub.is_null() {
            return Ok(cg_status::CG_OK);
        }
        let entry = SUBSCRIBERS.remove(sub as usize).ok_or_else(|| {
            Failure::new(
                cg_status::CG_ERR_INVALID_HANDLE,
                "subscriber is not a live cg_subscriber handle (already closed?)",
            )
        })?;
        drop(entry);
        Ok(cg_status::CG_OK)
    })
}

/// Writes the counters of the engine's shared-memory publisher to `*out`.
/// `CG_ERR_WRONG_STATE` if the engine was created without a `publish_name`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_publisher_stats(
    engine: *mut super::cg_engine,
    out: *mut cg_publisher_stats,
) -> cg_status {
    boundary("cg_engine_publisher_stats", || {
        if out.is_null() {
            return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, "out is NULL"));
        }
        let entry = lookup_engine(engine)?;
        let _poison = PoisonOnUnwind(&entry.poisoned);
        let stats = entry.engine.publisher_stats().ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_WRONG_STATE, "the engine was created without cg_engine_config.publish_name")
        })?;
        unsafe { out.write(stats) };
        Ok(cg_status::CG_OK)
    })
}
