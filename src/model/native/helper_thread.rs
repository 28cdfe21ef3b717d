//! The native path's second thread, shared by the decoder and the step (one helper per
//! loaded model, started at load; a call that finds it busy, because another stream is
//! using it, runs everything on its own thread).
//!
//! * [`Helper::run_split`] (the decoder): the helper runs one job while the caller runs
//!   another, disjoint one; the four decoder components are independent networks.
//! * [`Helper::run_team`] (the step): the caller and the helper run the same work function
//!   as the two [`Member`]s of a team. The work is a sequence of phases, each a number of
//!   independent units; [`Member::phase`] hands the units out (the caller takes them from
//!   the front, the helper from the back, one compare-and-swap each, until they meet) and
//!   returns once all of the phase's units are done. So the split follows the threads'
//!   actual speed: a helper that starts late, or that the OS preempts, leaves its share
//!   to the caller instead of stalling it (the caller waits at most for the one unit the
//!   helper is computing).
//!
//! Handing over a job is a mutex + condvar round trip (no allocation). A member waiting for
//! the end of a phase spins for a short while (phases follow each other within
//! microseconds) and then sleeps on a condvar. The caller blocks until the helper is done
//! before it returns or unwinds (a guard), so the helper's raw pointers into the caller's
//! state never outlive it; a member that panics poisons the team, so the other one stops
//! waiting (panicking in turn) instead of waiting forever.
use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{
    AtomicBool, AtomicU64, AtomicUsize,
    Ordering::{Acquire, SeqCst},
};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

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
    /// The decoder's helper (thread name `comgrasp-decoder`).
    pub(crate) fn start() -> std::io::Result<Helper> {
        Helper::start_named("comgrasp-decoder")
    }

    /// A helper thread named `name`.
    pub(crate) fn start_named(name: &str) -> std::io::Result<Helper> {
        let shared = Arc::new(Shared::default());
        let s = Arc::clone(&shared);
        let handle = std::thread::Builder::new().name(name.into()).spawn(move || loop {
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
        let _busy = self.try_claim()?;
        Some(self.run_claimed(job, mine))
    }

    /// The helper, if no other call is using it.
    fn try_claim(&self) -> Option<MutexGuard<'_, ()>> {
        match self.busy.try_lock() {
            Ok(g) => Some(g),
            Err(TryLockError::Poisoned(e)) => Some(e.into_inner()),
            Err(TryLockError::WouldBlock) => None,
        }
    }

    /// `run_split` once the helper is claimed: returns whether the helper's job panicked.
    ///
    /// # Safety
    /// As `run_split`.
    unsafe fn run_claimed(&self, job: Job, mine: impl FnOnce()) -> bool {
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
        w.wait()
    }

    /// Runs `work` on the caller (member 0) and on the helper (member 1) as a team whose
    /// phases use `phases` (one per phase of the work, at least; they belong to this helper's
    /// users and are reset here), and returns once both are done: `Some(helper_panicked)`;
    /// `None` if the helper was busy (nothing ran: the caller then runs
    /// `work(&mut Member::solo())` itself). A panic of the caller's part propagates after
    /// the helper has finished.
    pub(crate) fn run_team<F: Fn(&mut Member<'_>) + Sync>(&self, phases: &[Phase], work: &F) -> Option<bool> {
        struct Arg<'a, F> {
            work: &'a F,
            team: &'a Team<'a>,
        }
        /// # Safety
        /// `arg` is a live `Arg<F>`.
        unsafe fn member_1<F: Fn(&mut Member<'_>) + Sync>(arg: *const ()) {
            let a = &*(arg as *const Arg<'_, F>);
            a.team.run_member(1, a.work);
        }
        let _busy = self.try_claim()?;
        for p in phases {
            p.claimed.store(0, SeqCst);
            p.done.store(0, SeqCst);
        }
        let team = Team::new(phases);
        let arg = Arg { work, team: &team };
        let job = Job { run: member_1::<F>, arg: &arg as *const Arg<'_, F> as *const () };
        // SAFETY: `arg`, `work` and `team` live on this frame until run_claimed returns,
        // which is after the helper is done; `F: Sync` makes sharing `work` sound, and the
        // members split their writes (the work's contract: each unit is done by one member).
        Some(unsafe { self.run_claimed(job, || team.run_member(0, work)) })
    }
}

/// How long a member waiting for the end of a phase spins before it sleeps.
const SPIN: Duration = Duration::from_micros(50);

/// One phase's hand-out state: units taken from the front (low 32 bits) and from the back
/// (high 32 bits), and units done.
#[derive(Default)]
pub(crate) struct Phase {
    claimed: AtomicU64,
    done: AtomicUsize,
}

/// What the two members of one [`Helper::run_team`] call share.
struct Team<'a> {
    phases: &'a [Phase],
    sleepers: AtomicUsize,
    poisoned: AtomicBool,
    lock: Mutex<()>,
    cv: Condvar,
}

impl<'a> Team<'a> {
    fn new(phases: &'a [Phase]) -> Team<'a> {
        Team {
            phases,
            sleepers: AtomicUsize::new(0),
            poisoned: AtomicBool::new(false),
            lock: Mutex::new(()),
            cv: Condvar::new(),
        }
    }

    /// Runs member `me`'s part; a panic poisons the team first (so the other member does
    /// not wait for it) and then propagates.
    fn run_member<F: Fn(&mut Member<'_>)>(&self, me: usize, work: &F) {
        struct Poison<'t, 'a>(&'t Team<'a>);
        impl Drop for Poison<'_, '_> {
            fn drop(&mut self) {
                if std::thread::panicking() {
                    self.0.poisoned.store(true, SeqCst);
                    let _g = self.0.lock.lock().unwrap_or_else(|e| e.into_inner());
                    self.0.cv.notify_all();
                }
            }
        }
        let _p = Poison(self);
        work(&mut Member { team: Some(self), me, phase: 0 });
    }

    fn check_poison(&self) {
        if self.poisoned.load(SeqCst) {
            panic!("the other thread of this native computation panicked");
        }
    }

    /// The next units of `phase` (of `total`) for member `me`: 0 takes them from the front,
    /// 1 from the back; a quarter of what is left at a time (at least one), so that there
    /// are few claims and the last ones are small.
    fn claim(&self, phase: &Phase, me: usize, total: usize) -> Option<Range<usize>> {
        let mut cur = phase.claimed.load(SeqCst);
        loop {
            let (front, back) = ((cur & 0xffff_ffff) as usize, (cur >> 32) as usize);
            let left = total.saturating_sub(front + back);
            if left == 0 {
                return None;
            }
            let k = (left / 4).max(1);
            let (next, units) = if me == 0 {
                (cur + k as u64, front..front + k)
            } else {
                (cur + ((k as u64) << 32), total - back - k..total - back)
            };
            match phase.claimed.compare_exchange_weak(cur, next, SeqCst, SeqCst) {
                Ok(_) => return Some(units),
                Err(now) => cur = now,
            }
        }
    }

    /// Adds `n` units done to `phase`, then blocks until all `total` are. Panics if the
    /// other member panicked.
    fn finish(&self, phase: &Phase, n: usize, total: usize) {
        if phase.done.fetch_add(n, SeqCst) + n == total {
            // A sleeper registers before it re-checks the count (both SeqCst), so either it
            // sees the final count or this sees it registered.
            if self.sleepers.load(SeqCst) > 0 {
                let _g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
                self.cv.notify_all();
            }
            return;
        }
        let start = Instant::now();
        let mut spins = 0u32;
        loop {
            if phase.done.load(Acquire) == total {
                return;
            }
            std::hint::spin_loop();
            spins += 1;
            if spins.is_multiple_of(64) {
                self.check_poison();
                if start.elapsed() > SPIN {
                    break;
                }
            }
        }
        let mut g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        self.sleepers.fetch_add(1, SeqCst);
        while phase.done.load(SeqCst) != total && !self.poisoned.load(SeqCst) {
            g = self.cv.wait(g).unwrap_or_else(|e| e.into_inner());
        }
        self.sleepers.fetch_sub(1, SeqCst);
        drop(g);
        self.check_poison();
    }
}

/// One thread's view of a team (or a team of one).
pub(crate) struct Member<'t> {
    team: Option<&'t Team<'t>>,
    me: usize,
    phase: usize,
}

impl Member<'_> {
    /// The only member of a team of one: `phase` runs every unit in order.
    pub(crate) fn solo() -> Member<'static> {
        Member { team: None, me: 0, phase: 0 }
    }

    /// 0 for the caller, 1 for the helper.
    pub(crate) fn index(&self) -> usize {
        self.me
    }

    /// Runs the next phase: `f(units)` for the ranges of units of `0..total` this member
    /// gets (`0..total` at once on a team of one); returns once every unit of the phase is
    /// done, by either member, so what they wrote is visible. Both members must run the same
    /// sequence of phases with the same totals (below 2^32).
    pub(crate) fn phase(&mut self, total: usize, mut f: impl FnMut(Range<usize>)) {
        let Some(team) = self.team else {
            if total > 0 {
                f(0..total);
            }
            return;
        };
        let phase = team.phases.get(self.phase).expect("more phases than the team was given");
        self.phase += 1;
        let mut n = 0;
        while let Some(units) = team.claim(phase, self.me, total) {
            n += units.len();
            f(units);
        }
        team.finish(phase, n, total);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_team_shares_out_every_unit_once_and_survives_a_panic_of_either_member() {
        let h = Helper::start_named("test-helper").unwrap();
        let phases: Vec<Phase> = (0..1000).map(|_| Phase::default()).collect();
        // Each phase's units are done exactly once, and each phase sees the previous one done.
        let hits: Vec<AtomicUsize> = (0..1000 * 7).map(|_| AtomicUsize::new(0)).collect();
        let by_helper = AtomicUsize::new(0);
        let work = |m: &mut Member<'_>| {
            for p in 0..1000 {
                m.phase(7, |units| {
                    if p > 0 {
                        assert!((0..7).all(|v| hits[(p - 1) * 7 + v].load(SeqCst) == 1), "phase {p} started early");
                    }
                    for u in units {
                        hits[p * 7 + u].fetch_add(1, SeqCst);
                        if m_is_helper() {
                            by_helper.fetch_add(1, SeqCst);
                        }
                    }
                });
            }
        };
        fn m_is_helper() -> bool {
            std::thread::current().name() == Some("test-helper")
        }
        assert_eq!(h.run_team(&phases, &work), Some(false));
        assert!(hits.iter().all(|c| c.load(SeqCst) == 1));
        println!("the helper did {} of 7000 units", by_helper.load(SeqCst));
        // A team of one runs every unit, in order.
        let mut seen = Vec::new();
        Member::solo().phase(5, |u| seen.push(u));
        assert_eq!(seen, vec![0..5usize]);

        // Either member panics (unit 0 usually goes to the caller, unit 1 to the helper):
        // the other stops waiting, and the caller sees a panic (after the helper is done).
        for bad in [0, 1] {
            let work = |m: &mut Member<'_>| {
                m.phase(2, |_| {});
                m.phase(2, |units| {
                    if units.contains(&bad) {
                        panic!("unit {bad} fails");
                    }
                    std::thread::sleep(Duration::from_millis(20));
                });
                m.phase(2, |_| {});
            };
            let r = catch_unwind(AssertUnwindSafe(|| h.run_team(&phases, &work)));
            assert!(matches!(r, Err(_) | Ok(Some(true))), "unit {bad} panicked, the caller must see it: {r:?}");
        }
        // The helper still works.
        let n = AtomicUsize::new(0);
        assert_eq!(
            h.run_team(&phases, &|m: &mut Member<'_>| m.phase(4, |units| {
                n.fetch_add(units.len(), SeqCst);
            })),
            Some(false)
        );
        assert_eq!(n.load(SeqCst), 4);
    }
}
