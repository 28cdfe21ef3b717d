//! A second thread for the native decoder: the four components are independent networks,
//! so one decode runs some of them on a helper thread while the caller runs the others
//! (the split balances their multiply-adds). One helper per loaded decoder, started at
//! load; a decode that finds it busy (another stream is using it) runs everything itself.
//!
//! Handing over a job is a mutex + condvar round trip (no allocation). The caller blocks
//! until the helper is done before it returns or unwinds (a guard), so the helper's raw
//! pointers into the caller's state never outlive it.
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;

/// Work for the helper: a function pointer and an opaque argument the caller keeps alive
/// until the job is done.
#[derive(Clone, Copy)]
pub(crate) struct Job {
    pub(crate) run: unsafe fn(*const ()),
    pub(crate) arg: *const (),
}

// SAFETY: the poster guarantees that `arg` stays valid and is not used concurrently in a
// conflicting way until the job is done (see `Helper::run_split`).
unsafe impl Send for Job {}

#[derive(Default)]
struct Slot {
    job: Option<Job>,
    /// Some(panicked) once the posted job finished.
    done: Option<bool>,
    quit: bool,
}

#[derive(Default)]
struct Shared {
    slot: Mutex<Slot>,
    job_cv: Condvar,
    done_cv: Condvar,
}

fn lock(m: &Mutex<Slot>) -> MutexGuard<'_, Slot> {
    // A panic never happens while the slot is locked (jobs run unlocked), but be robust.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

pub(crate) struct Helper {
    shared: Arc<Shared>,
    /// Held by the one decode using the helper.
    busy: Mutex<()>,
    handle: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Helper {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Helper").finish_non_exhaustive()
    }
}

impl Helper {
    pub(crate) fn start() -> std::io::Result<Helper> {
        let shared = Arc::new(Shared::default());
        let s = Arc::clone(&shared);
        let handle = std::thread::Builder::new().name("comgrasp-decoder".into()).spawn(move || loop {
            let job = {
                let mut g = lock(&s.slot);
                loop {
                    if g.quit {
                        return;
                    }
                    if let Some(j) = g.job.take() {
                        break j;
                    }
                    g = s.job_cv.wait(g).unwrap_or_else(|e| e.into_inner());
                }
            };
            // SAFETY: the poster keeps `arg` valid until it sees `done` (Helper::run_split).
            let panicked = catch_unwind(AssertUnwindSafe(|| unsafe { (job.run)(job.arg) })).is_err();
            lock(&s.slot).done = Some(panicked);
            s.done_cv.notify_one();
        })?;
        Ok(Helper { shared, busy: Mutex::new(()), handle: Some(handle) })
    }

    /// Runs `job` on the helper while the caller runs `mine`, and returns once both are
    /// done: `Some(helper_panicked)`; `None` if the helper was busy and `job` did not run
    /// (the caller then runs it itself; `mine` did not run either).
    ///
    /// # Safety
    /// `job.arg` must stay valid for `job.run` until this returns, and `job` and `mine` must
    /// not touch the same data.
    pub(crate) unsafe fn run_split(&self, job: Job, mine: impl FnOnce()) -> Option<bool> {
        let _busy = match self.busy.try_lock() {
            Ok(g) => g,
            Err(TryLockError::Poisoned(e)) => e.into_inner(),
            Err(TryLockError::WouldBlock) => return None,
        };
        {
            let mut g = lock(&self.shared.slot);
            g.done = None;
            g.job = Some(job);
        }
        self.shared.job_cv.notify_one();
        // Waits for the helper even if `mine` panics (its pointers are into our caller's data).
        struct Wait<'a>(&'a Shared, Option<bool>);
        impl Wait<'_> {
            fn wait(&mut self) -> bool {
                if let Some(p) = self.1 {
                    return p;
                }
                let mut g = lock(&self.0.slot);
                let p = loop {
                    if let Some(p) = g.done.take() {
                        break p;
                    }
                    g = self.0.done_cv.wait(g).unwrap_or_else(|e| e.into_inner());
                };
                self.1 = Some(p);
                p
            }
        }
        impl Drop for Wait<'_> {
            fn drop(&mut self) {
                self.wait();
            }
        }
        let mut w = Wait(&self.shared, None);
        mine();
        Some(w.wait())
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        lock(&self.shared.slot).quit = true;
        self.shared.job_cv.notify_one();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}
