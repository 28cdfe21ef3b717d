//! The panic boundary. Since Rust 1.81 a panic that reaches an `extern "C"` function aborts
//! the process; for a Unity or Unreal editor that is a crash, so every exported body runs in
//! [`boundary`], which turns a panic into `CG_ERR_PANIC` (or a neutral value for functions
//! that do not return a status). Requires `panic = "unwind"` (set in Cargo.toml).
use std::ffi::c_char;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, Ordering};

use super::last_error::record;
use super::status::cg_status;
use crate::stream::panic_message;

/// What an exported function returns when its body panicked.
pub trait Fallback {
    /// The value returned after a caught panic.
    fn on_panic() -> Self;
}

impl Fallback for cg_status {
    fn on_panic() -> Self {
        cg_status::CG_ERR_PANIC
    }
}

impl Fallback for *const c_char {
    fn on_panic() -> Self {
        c"(panic)".as_ptr()
    }
}

impl Fallback for u32 {
    fn on_panic() -> Self {
        0
    }
}

impl Fallback for usize {
    fn on_panic() -> Self {
        0
    }
}

impl Fallback for () {
    fn on_panic() -> Self {}
}

/// A failure that has already been recorded as this thread's last error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Failure(pub cg_status);

impl Failure {
    /// Records `msg` as the last error and carries `status` out of the function.
    pub fn new(status: cg_status, msg: impl std::fmt::Display) -> Failure {
        record(status, &msg);
        Failure(status)
    }
}

impl From<crate::Error> for Failure {
    fn from(e: crate::Error) -> Failure {
        let status = cg_status::from_error(&e);
        record(status, &e);
        Failure(status)
    }
}

/// Runs an exported function's body: a status on success, the recorded failure's status on
/// error, `CG_ERR_PANIC` (message recorded) on a panic.
pub fn boundary(name: &'static str, f: impl FnOnce() -> Result<cg_status, Failure>) -> cg_status {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(s)) => s,
        Ok(Err(Failure(s))) => s,
        Err(payload) => {
            record(cg_status::CG_ERR_PANIC, &format_args!("panic in {name}: {}", panic_message(&*payload)));
            cg_status::CG_ERR_PANIC
        }
    }
}

/// [`boundary`] for functions that return a plain value instead of a status.
pub fn boundary_value<R: Fallback>(name: &'static str, f: impl FnOnce() -> R) -> R {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            record(cg_status::CG_ERR_PANIC, &format_args!("panic in {name}: {}", panic_message(&*payload)));
            R::on_panic()
        }
    }
}

/// Marks a handle poisoned if dropped during unwinding: create one before working on a
/// handle, and a panic in that work poisons it (its state may be inconsistent).
pub struct PoisonOnUnwind<'a>(pub &'a AtomicBool);

impl Drop for PoisonOnUnwind<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.store(true, Ordering::SeqCst);
        }
    }
}
