//! The thread-local last error: each failing call records its status and a message on the
//! calling thread; successful calls leave it alone (errno style). The buffer is reused, so
//! recording a message allocates only when it is longer than any before it on that thread.
use std::cell::RefCell;
use std::ffi::c_char;
use std::fmt::{Display, Write as _};

use super::panic::boundary_value;
use super::status::cg_status;

struct LastError {
    status: cg_status,
    /// The message followed by a NUL; never contains another NUL.
    text: String,
}

thread_local! {
    static LAST: RefCell<LastError> = RefCell::new(LastError { status: cg_status::CG_OK, text: String::from("\0") });
}

/// Records `status` and `msg` as this thread's last error.
pub(crate) fn record(status: cg_status, msg: &dyn Display) {
    // `try_with`: during thread teardown the slot may be gone; losing a message is fine.
    let _ = LAST.try_with(|cell| {
        if let Ok(mut last) = cell.try_borrow_mut() {
            last.status = status;
            last.text.clear();
            let _ = write!(last.text, "{msg}");
            // Interior NULs would truncate the C string; make them visible instead.
            if last.text.contains('\0') {
                last.text = last.text.replace('\0', "?");
            }
            last.text.push('\0');
        }
    });
}

/// The message of the most recent failing `cg_*` call on the calling thread, as a
/// NUL-terminated UTF-8 string ("" if none failed yet). Never NULL. The pointer stays valid
/// until the next failing `cg_*` call on the same thread (or the thread's exit); copy it if
/// you need it longer. Do not free it.
#[no_mangle]
pub extern "C" fn cg_last_error() -> *const c_char {
    boundary_value("cg_last_error", || {
        LAST.try_with(|cell| cell.borrow().text.as_ptr() as *const c_char).unwrap_or(c"".as_ptr())
    })
}

/// Copies the last error message of the calling thread into `buf` (capacity `len` bytes),
/// truncating if needed; the result is always NUL-terminated when `len > 0`. Returns the
/// size needed for the whole message including its NUL, so `cg_last_error_message(NULL, 0)`
/// asks for the size. Any thread; `buf` may be NULL only when `len` is 0.
#[no_mangle]
pub unsafe extern "C" fn cg_last_error_message(buf: *mut c_char, len: usize) -> usize {
    boundary_value("cg_last_error_message", || {
        LAST.try_with(|cell| {
            let last = cell.borrow();
            let bytes = last.text.as_bytes(); // includes the NUL
            if !buf.is_null() && len > 0 {
                let n = (bytes.len() - 1).min(len - 1);
                // SAFETY: the caller promises `buf` has room for `len` bytes; we write n + 1 <= len.
                unsafe {
                    std::ptr::copy_nonoverlapping(bytes.as_ptr(), buf as *mut u8, n);
                    *buf.add(n) = 0;
                }
            }
            bytes.len()
        })
        .unwrap_or(1)
    })
}

/// The status of the most recent failing `cg_*` call on the calling thread (`CG_OK` if
/// none failed yet). Any thread.
#[no_mangle]
pub extern "C" fn cg_last_error_status() -> cg_status {
    boundary_value("cg_last_error_status", || LAST.try_with(|cell| cell.borrow().status).unwrap_or(cg_status::CG_OK))
}
