//! Status codes. Values are part of the ABI: never renumber or reuse one.
//! `>= 0` is not an error (`CG_OK`, `CG_PENDING`, `CG_END`, `CG_CANCELLED`); `< 0` is.
use std::ffi::c_char;

use super::panic::boundary_value;
use crate::Error;

/// Result of every `cg_*` function that can fail. Non-negative values are normal outcomes,
/// negative values are errors; after an error, `cg_last_error()` on the same thread has a
/// human-readable message. Passed across the ABI as a 32-bit signed integer.
/// cbindgen:rename-all=None
#[repr(i32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum cg_status {
    /// Success (`cg_poll_frame`: a frame was written).
    CG_OK = 0,
    /// No frame available yet; the stream is still generating. Poll again later.
    CG_PENDING = 1,
    /// The stream finished and every frame has been delivered.
    CG_END = 2,
    /// The stream was cancelled (`cg_cancel`, or its engine was destroyed while it ran).
    CG_CANCELLED = 3,
    /// A required pointer argument was NULL.
    CG_ERR_NULL_POINTER = -1,
    /// The text is not valid UTF-8.
    CG_ERR_INVALID_UTF8 = -2,
    /// An argument is out of range: empty or whitespace-only text, text longer than
    /// `CG_MAX_TEXT_BYTES`, a bad config value or a `struct_size` that is too small.
    CG_ERR_INVALID_ARGUMENT = -3,
    /// The handle is not a live object of the expected type (destroyed, double-destroyed,
    /// never created by this library, or an engine passed as a stream or vice versa).
    CG_ERR_INVALID_HANDLE = -4,
    /// The call is not allowed now (e.g. the stream is in use by another thread).
    CG_ERR_WRONG_STATE = -5,
    /// The model bundle is missing, corrupt or inconsistent.
    CG_ERR_BUNDLE = -6,
    /// Running the model failed.
    CG_ERR_INFERENCE = -7,
    /// An operating-system I/O error (reading files, starting a thread).
    CG_ERR_IO = -8,
    /// A limit is reached (e.g. the engine's `max_streams`); destroy something and retry.
    CG_ERR_LIMIT = -9,
    /// A panic (a bug in the library) was caught. The handle involved is poisoned: further
    /// calls on it return this code; destroy it.
    CG_ERR_PANIC = -10,
    /// Shared memory (iceoryx2) failed: the publish or subscribe service could not be
    /// created or opened (another process uses the name with incompatible settings, or
    /// /dev/shm is unavailable), or receiving failed.
    CG_ERR_SHM = -11,
}

impl cg_status {
    /// The code for an engine error.
    pub fn from_error(e: &Error) -> cg_status {
        match e {
            Error::Bundle { .. } => cg_status::CG_ERR_BUNDLE,
            Error::InvalidArgument(_) => cg_status::CG_ERR_INVALID_ARGUMENT,
            Error::WrongState(_) => cg_status::CG_ERR_WRONG_STATE,
            Error::Inference(_) => cg_status::CG_ERR_INFERENCE,
            Error::Cancelled => cg_status::CG_CANCELLED,
            Error::Io(_) => cg_status::CG_ERR_IO,
            Error::LimitReached(_) => cg_status::CG_ERR_LIMIT,
            Error::Panic(_) => cg_status::CG_ERR_PANIC,
            Error::SharedMemory(_) => cg_status::CG_ERR_SHM,
        }
    }

    fn text(code: i32) -> &'static std::ffi::CStr {
        match code {
            0 => c"CG_OK: success",
            1 => c"CG_PENDING: no frame yet, the stream is still generating",
            2 => c"CG_END: the stream finished and all frames were delivered",
            3 => c"CG_CANCELLED: the stream was cancelled",
            -1 => c"CG_ERR_NULL_POINTER: a required pointer argument was NULL",
            -2 => c"CG_ERR_INVALID_UTF8: the text is not valid UTF-8",
            -3 => c"CG_ERR_INVALID_ARGUMENT: an argument is out of range",
            -4 => c"CG_ERR_INVALID_HANDLE: not a live handle of the expected type",
            -5 => c"CG_ERR_WRONG_STATE: the call is not allowed in the current state",
            -6 => c"CG_ERR_BUNDLE: the model bundle is missing, corrupt or inconsistent",
            -7 => c"CG_ERR_INFERENCE: running the model failed",
            -8 => c"CG_ERR_IO: an operating-system I/O error",
            -9 => c"CG_ERR_LIMIT: a limit is reached",
            -10 => c"CG_ERR_PANIC: internal error (panic); the handle is poisoned",
            -11 => c"CG_ERR_SHM: shared memory (iceoryx2) failed",
            _ => c"unknown cg_status value",
        }
    }
}

/// A static, NUL-terminated description of a status code. Takes a plain integer so any
/// value is safe to pass; unknown values give "unknown cg_status value". Never returns NULL;
/// the string lives for the whole program and must not be freed. Any thread.
#[no_mangle]
pub extern "C" fn cg_status_string(status: i32) -> *const c_char {
    boundary_value("cg_status_string", || cg_status::text(status).as_ptr())
}
