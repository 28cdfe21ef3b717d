//! The native path's thread team: the caller and one helper thread per loaded model
//! (started at load), shared by the decoder and the step. This is the one module of the
//! native path with `unsafe` for threads; everything it hands the members is a safe
//! borrow.
//!
//! * [`Helper::crew`] lends the helper to the caller for one computation (a step, a
//!   decode). A call that finds the helper busy (another stream's computation has it)
//!   runs alone on a [`Crew::solo`], with the same results.
//! * [`Crew::phase`] runs one phase of that computation: [`Units`] that hand out *items*,
//!   each with disjoint `&mut` slices of the outputs (cut with `split_at_mut`, so the
//!   borrow checker proves them disjoint), and a function both members apply to the items
//!   they take. Inputs are captured by shared reference. The units sit behind a lock: with
//!   [`Order::Split`] cut in two halves, the caller taking its half from the front and the
//!   helper its half from the back, a quarter of what is left at a time, and a member whose
//!   half is empty taking from the other half; with [`Order::Queue`] both take from the
//!   front of one queue. So the split follows the threads' actual speed: a helper that
//!   wakes late, or that the OS preempts, leaves its share to the caller (which waits at
//!   most for the item the helper holds). The phase returns once every item is done and
//!   the helper has let go of the phase; its borrows then end, and the next phase may read
//!   what this one wrote.
//! * Each member has its own scratch `P` (`&mut`, for the whole computation).
//!
//! Soundness rests on two lifetime erasures, both argued where they are made: the
//! computation's [`Session`] handed to the persistent helper thread (the caller waits
//! for the helper to leave it before returning or unwinding, as `std::thread::scope`
//! does), and each phase published to the helper (guarded by one state word: the helper
//! enters the phase by a compare-and-swap from "published" to "inside", and the caller
//! withdraws it by one from "published" to "none", which cannot succeed while the helper
//! is inside, before the phase's borrows end). A panic in the helper's part is
//! caught, its items count as lost, and [`Helper::crew`] reports it; a panic in the
//! caller's part propagates after the helper has let go. Miri runs this module's tests
//! (scripts/sanitize.sh --miri).
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{
    AtomicBool, AtomicPtr, AtomicUsize,
    Ordering::{Relaxed, SeqCst},
};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How long a member waiting for the other (the helper for the next phase, the caller for
/// the helper to let go) spins before it sleeps: phases follow each other within
/// microseconds, a preempted thread takes milliseconds.
const SPIN: Duration = Duration::from_micros(50);

/// Which end of a phase's items each member takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Order {
    /// Two halves, the caller's taken from the front and the helper's from the back (then
    /// the other's, from the same end): each member's items are mostly contiguous (rows of
    /// the same matrices stay in one thread's cache).
    Split,
    /// Both from the front: a queue, for items ordered longest first.
    Queue,
}

/// Work for the helper thread: a function and its argument (a live `Session`), posted by
/// [`Helper::crew`], which keeps the argument alive until the helper reports it done.
struct Job {
    run: unsafe fn(*const ()),
    arg: *const (),
}

// SAFETY: `arg` points at a `Session`, which is `Sync` (checked where the job is made); the
// poster keeps it alive until the job is done.
unsafe impl Send for Job {}

#[derive(Default)]
struct Slot {
    job: Option<Job>,
    /// Set once the posted job finished (and at the start, once the thread runs).
    done: bool,
    quit: bool,
}

#[derive(Default)]
struct Shared {
    slot: Mutex<Slot>,
    job_cv: Condvar,
    done_cv: Condvar,
}

impl Shared {
    /// Blocks (holding `g`, the slot's lock) until the slot says `done`.
    fn wait_done(&self, mut g: MutexGuard<'_, Slot>) {
        while !g.done {
            g = self.done_cv.wait(g).unwrap_or_else(|e| e.into_inner());
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Nothing panics while these locks are held (work runs unlocked); be robust anyway.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The helper thread of one loaded model.
pub(crate) struct Helper {
    shared: Arc<Shared>,
    /// Held by the one computation using the helper.
    busy: Mutex<()>,
    handle: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Helper {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Helper").finish_non_exhaustive()
    }
}

impl Helper {
    /// A helper thread named `name`.
    pub(crate) fn start_named(name: &str) -> std::io::Result<Helper> {
        let shared = Arc::new(Shared::default());
        let s = Arc::clone(&shared);
        let handle = std::thread::Builder::new().name(name.into()).spawn(move || {
            lock(&s.slot).done = true; // running (see below)
            s.done_cv.notify_one();
            loop {
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
                // SAFETY: the poster keeps `arg` alive until it sees `done` (Helper::crew). The
                // session catches the work's panics itself; this only guards the thread.
                let _ = catch_unwind(AssertUnwindSafe(|| unsafe { (job.run)(job.arg) }));
                lock(&s.slot).done = true;
                s.done_cv.notify_one();
            }
        })?;
        // Wait until the thread runs: its start-up allocates, which belongs to the load,
        // not to the first computation (a crew that finds its job not taken takes it back).
        shared.wait_done(lock(&shared.slot));
        Ok(Helper { shared, busy: Mutex::new(()), handle: Some(handle) })
    }

    /// Runs `body` on the caller with a two-member [`Crew`] (the helper joins every phase
    /// `body` runs; `helper_scratch` is its scratch meanwhile), or with [`Crew::solo`] if
    /// another computation has the helper. Returns `body`'s result and whether the
    /// helper's part panicked (then some items were not done: the outputs are not to be
    /// trusted).
    pub(crate) fn crew<P: Send, R>(
        &self,
        helper_scratch: &mut P,
        body: impl FnOnce(&mut Crew<'_, P>) -> R,
    ) -> (R, bool) {
        let _busy = match self.busy.try_lock() {
            Ok(g) => g,
            Err(TryLockError::Poisoned(e)) => e.into_inner(),
            Err(TryLockError::WouldBlock) => return (body(&mut Crew::solo()), false),
        };
        let session = Session {
            scratch: Mutex::new(Some(helper_scratch)),
            state: AtomicUsize::new(0),
            phase: AtomicPtr::new(std::ptr::null_mut()),
            run: AtomicPtr::new(std::ptr::null_mut()),
            panicked: AtomicBool::new(false),
            sleeping: AtomicBool::new(false),
            lock: Mutex::new(()),
            cv: Condvar::new(),
        };
        fn sync<T: Sync>(t: &T) -> &T {
            t
        }
        {
            let mut g = lock(&self.shared.slot);
            g.done = false;
            g.job = Some(Job { run: helper_session::<P>, arg: sync(&session) as *const Session<'_, P> as *const () });
        }
        self.shared.job_cv.notify_one();
        // Ends the session and waits for the helper to finish its job, even if `body`
        // panics: the job points at `session`, on this frame. This is the first lifetime
        // erasure's guarantee.
        struct End<'a, 's, P> {
            shared: &'a Shared,
            session: &'a Session<'s, P>,
        }
        impl<P> Drop for End<'_, '_, P> {
            fn drop(&mut self) {
                self.session.post(END);
                let mut g = lock(&self.shared.slot);
                if g.job.take().is_some() {
                    return; // the helper never started it
                }
                self.shared.wait_done(g);
            }
        }
        let end = End { shared: &self.shared, session: &session };
        let r = body(&mut Crew { session: Some(&session), seq: 0 });
        drop(end);
        (r, session.panicked.load(SeqCst))
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

/// `state` once the session is over (even, so no phase's).
const END: usize = usize::MAX - 1;
/// The bit of `state` set while the helper is inside the published phase.
const INSIDE: usize = 1;

/// What the caller and the helper share during one [`Helper::crew`] call.
struct Session<'s, P> {
    /// The helper's scratch; it takes it when the session starts.
    scratch: Mutex<Option<&'s mut P>>,
    /// 0: no phase published; `2 seq`: phase `seq` published, the helper not inside;
    /// `2 seq + INSIDE`: the helper inside it; [`END`]: the session is over. One word, so
    /// that the helper enters with one compare-and-swap and the caller withdraws with
    /// another (phase numbers are never reused: no ABA).
    state: AtomicUsize,
    /// The published phase while `state` names it: the phase (on the caller's stack,
    /// type and lifetime erased) and its [`RunPhase`] (a fn pointer): two thin pointers
    /// beside `state` (one cache line), not a `&dyn` behind one.
    phase: AtomicPtr<()>,
    run: AtomicPtr<()>,
    panicked: AtomicBool,
    /// The helper sleeps (or is about to) on `cv`, waiting for a phase.
    sleeping: AtomicBool,
    lock: Mutex<()>,
    cv: Condvar,
}

impl<P> Session<'_, P> {
    /// Publishes `state` (a phase, or [`END`]) and wakes the helper if it sleeps.
    fn post(&self, state: usize) {
        self.state.store(state, SeqCst);
        // The helper sets `sleeping` before its last check of `state` (both SeqCst), so it
        // either sees the new state or is seen sleeping here.
        if self.sleeping.load(SeqCst) {
            let _g = lock(&self.lock);
            self.cv.notify_one();
        }
    }

    /// Withdraws the published phase `posted` (a state), waiting until the helper has let
    /// go of it: once this returns, the helper can no longer enter it.
    fn withdraw(&self, posted: usize) {
        let start = Instant::now();
        let mut spins = 0u32;
        while self.state.compare_exchange(posted, 0, SeqCst, SeqCst).is_err() {
            // The helper is inside: wait (reading only, so its exit is not slowed) until it
            // stores `posted` back.
            while self.state.load(SeqCst) != posted {
                std::hint::spin_loop();
                spins += 1;
                if spins.is_multiple_of(64) && start.elapsed() > SPIN {
                    // it holds items and was preempted: give it the core
                    std::thread::yield_now();
                }
            }
        }
    }
}

/// How the helper runs a published phase: [`run_phase`] for the phase's type.
type RunPhase<P> = unsafe fn(*const (), &mut P, usize);

/// # Safety
/// `phase` points at a live `W`.
unsafe fn run_phase<P, W: PhaseWork<P>>(phase: *const (), scratch: &mut P, me: usize) {
    (*(phase as *const W)).run(scratch, me)
}

/// The helper's side of a session.
///
/// # Safety
/// `arg` is a live `Session<'_, P>` that stays alive until this returns.
unsafe fn helper_session<P: Send>(arg: *const ()) {
    let s = &*(arg as *const Session<'_, P>);
    let Some(scratch) = lock(&s.scratch).take() else { return };
    let mut last = 0;
    loop {
        let posted = wait_for_phase(s, last);
        if posted == END {
            return;
        }
        last = posted;
        if s.state.compare_exchange(posted, posted | INSIDE, SeqCst, SeqCst).is_err() {
            continue; // withdrawn meanwhile
        }
        // SAFETY (second erasure): while `state` has INSIDE, the caller's `withdraw` cannot
        // succeed, so the phase (and the pointers read here, written before the phase was
        // posted) stays alive until the store below.
        let (phase, run) = (s.phase.load(SeqCst), s.run.load(SeqCst));
        // SAFETY: `run` was made from a `RunPhase<P>` for the type `phase` points at.
        let run = std::mem::transmute::<*mut (), RunPhase<P>>(run);
        let ok = catch_unwind(AssertUnwindSafe(|| run(phase, scratch, 1))).is_ok();
        if !ok {
            s.panicked.store(true, SeqCst);
        }
        s.state.store(posted, SeqCst);
        if !ok {
            return;
        }
    }
}

/// The next state after `last` that publishes a phase (or [`END`]): spins, then sleeps.
fn wait_for_phase<P>(s: &Session<'_, P>, last: usize) -> usize {
    // (a state with INSIDE is the helper's own, never seen here)
    let fresh = |p: usize| p != 0 && p != last;
    let start = Instant::now();
    let mut spins = 0u32;
    loop {
        let p = s.state.load(SeqCst);
        if fresh(p) {
            return p;
        }
        std::hint::spin_loop();
        spins += 1;
        if spins.is_multiple_of(64) && start.elapsed() > SPIN {
            break;
        }
    }
    let mut g = lock(&s.lock);
    s.sleeping.store(true, SeqCst);
    let p = loop {
        let p = s.state.load(SeqCst);
        if fresh(p) {
            break p;
        }
        g = s.cv.wait(g).unwrap_or_else(|e| e.into_inner());
    };
    s.sleeping.store(false, SeqCst);
    p
}

/// One phase as the helper sees it: run member `me`'s share with its scratch.
trait PhaseWork<P>: Sync {
    fn run(&self, scratch: &mut P, me: usize);
}

/// Member `me` of a team of one.
const ALONE: usize = usize::MAX;

/// What a phase hands out: units, a few at a time from either end, each take one item
/// (e.g. a block of consecutive rows with its parts of the outputs).
pub(crate) trait Units: Send {
    type Item;
    /// Units not taken yet (a lower bound will do: only the sizes of takes depend on it).
    fn left(&self) -> usize;
    /// Up to `n` (at least 1) of the next units, from the front or the back, as one item;
    /// `None` once none is left.
    fn take(&mut self, n: usize, back: bool) -> Option<Self::Item>;
    /// The last `n` units, split off (for [`Order::Split`]'s second member), or `None` if
    /// these units cannot be split (the members then share one queue).
    fn split_back(&mut self, _n: usize) -> Option<Self>
    where
        Self: Sized,
    {
        None
    }
}

/// The items of an iterator as units, one per take.
pub(crate) struct Each<I>(pub(crate) I);

impl<I: DoubleEndedIterator + Send> Units for Each<I> {
    type Item = I::Item;

    fn left(&self) -> usize {
        self.0.size_hint().0
    }

    fn take(&mut self, _n: usize, back: bool) -> Option<I::Item> {
        if back {
            self.0.next_back()
        } else {
            self.0.next()
        }
    }
}

/// A phase's units and work. With [`Order::Split`] the units are cut in two halves, one
/// per member, each behind its own lock (so a member's takes mostly touch memory its
/// core already holds); a member whose half is empty takes from the other half (the
/// caller from its front, the helper from its back), so the split still follows the
/// threads' actual speed.
struct Phase<U, G, F> {
    front: Mutex<U>,
    back: Option<Mutex<U>>,
    order: Order,
    init: G,
    f: F,
}

impl<U: Units, G, F> Phase<U, G, F> {
    fn new(mut units: U, order: Order, alone: bool, init: G, f: F) -> Self {
        let back = if order == Order::Split && !alone {
            let half = units.left() / 2;
            units.split_back(half).map(Mutex::new)
        } else {
            None
        };
        Phase { front: Mutex::new(units), back, order, init, f }
    }
}

/// One take of up to a quarter of what `q` has left (everything when `all`).
fn take_from<U: Units>(q: &Mutex<U>, all: bool, back: bool) -> Option<U::Item> {
    let mut g = lock(q);
    // few takes, and small last ones
    let n = if all { usize::MAX } else { (g.left() / 4).max(1) };
    g.take(n, back)
}

impl<P, U, G, F> PhaseWork<P> for Phase<U, G, F>
where
    U: Units,
    G: Fn(&mut P) + Sync,
    F: Fn(&mut P, U::Item) + Sync,
{
    fn run(&self, scratch: &mut P, me: usize) {
        let back = me == 1 && self.order == Order::Split;
        let (own, other) = match (&self.back, me) {
            (Some(b), 1) => (b, Some(&self.front)),
            (b, _) => (&self.front, b.as_ref().filter(|_| me == 0)),
        };
        let (mut own_empty, mut joined) = (false, false);
        loop {
            let mut item = None;
            if !own_empty {
                item = take_from(own, me == ALONE, back);
                own_empty = item.is_none();
            }
            if item.is_none() {
                item = other.and_then(|o| take_from(o, false, back));
            }
            let Some(item) = item else { return };
            if !std::mem::replace(&mut joined, true) {
                (self.init)(scratch);
            }
            (self.f)(scratch, item);
        }
    }
}

/// The caller's handle on a computation's team (or a team of one).
pub(crate) struct Crew<'s, P> {
    session: Option<&'s Session<'s, P>>,
    seq: usize,
}

impl<P> Crew<'_, P> {
    /// A team of one: every phase runs on the caller, items in order.
    pub(crate) fn solo<'s>() -> Crew<'s, P> {
        Crew { session: None, seq: 0 }
    }

    /// Runs one phase: `f(scratch, item)` for every item taken from `units` until none is
    /// left, each on one member, after `init(scratch)` on each member that takes any;
    /// returns once all are done and nothing of the phase is in use. `scratch` is the
    /// caller's.
    pub(crate) fn phase<U, G, F>(&mut self, scratch: &mut P, order: Order, units: U, init: G, f: F)
    where
        U: Units,
        G: Fn(&mut P) + Sync,
        F: Fn(&mut P, U::Item) + Sync,
    {
        let Some(s) = self.session.filter(|s| !s.panicked.load(Relaxed)) else {
            return Phase::new(units, order, true, init, f).run(scratch, ALONE);
        };
        let phase = Phase::new(units, order, false, init, f);
        self.seq += 1;
        let posted = 2 * self.seq;
        // Only the type and the lifetime are erased: `Withdraw` below keeps `phase` alive
        // until the helper has let go of it (see `helper_session`).
        let run: RunPhase<P> = run_phase::<P, Phase<U, G, F>>;
        s.phase.store(&phase as *const Phase<U, G, F> as *mut (), SeqCst);
        s.run.store(run as *mut (), SeqCst);
        s.post(posted);
        struct Withdraw<'a, 's, P>(&'a Session<'s, P>, usize);
        impl<P> Drop for Withdraw<'_, '_, P> {
            fn drop(&mut self) {
                self.0.withdraw(self.1);
            }
        }
        let w = Withdraw(s, posted);
        phase.run(scratch, 0);
        drop(w);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Phases whose items are the disjoint chunks of a buffer; every phase reads what the
    /// previous one wrote. Small sizes keep it quick under Miri.
    fn run_phases(crew: &mut Crew<'_, Vec<usize>>, mine: &mut Vec<usize>, buf: &mut [u64], phases: usize) {
        for p in 0..phases {
            let prev: Vec<u64> = buf.to_vec();
            crew.phase(
                mine,
                if p % 2 == 0 { Order::Split } else { Order::Queue },
                Each(buf.chunks_mut(3).enumerate()),
                |seen: &mut Vec<usize>| seen.push(usize::MAX),
                |seen: &mut Vec<usize>, (i, chunk): (usize, &mut [u64])| {
                    seen.push(i);
                    // long enough for the helper to join (it wakes within tens of us)
                    std::thread::sleep(Duration::from_micros(if cfg!(miri) { 1 } else { 20 }));
                    for (j, v) in chunk.iter_mut().enumerate() {
                        // depends on the previous phase's values of other chunks
                        *v = prev[(i * 3 + j + 1) % prev.len()] + 1;
                    }
                },
            );
        }
    }

    #[test]
    fn a_crew_does_every_item_once_and_matches_a_team_of_one() {
        let h = Helper::start_named("test-helper").unwrap();
        let phases = if cfg!(miri) { 20 } else { 500 };
        let mut solo = vec![0u64; 20];
        let (mut s0, mut s1) = (Vec::new(), Vec::new());
        run_phases(&mut Crew::solo(), &mut s0, &mut solo, phases);
        s0.clear();
        let mut team = vec![0u64; 20];
        let (_, panicked) = h.crew(&mut s1, |c| run_phases(c, &mut s0, &mut team, phases));
        assert!(!panicked);
        assert_eq!(team, solo, "the team's results differ from one thread's");
        // every item of every phase once, by either member; `init` once per member and phase joined
        let items = |v: &[usize]| v.iter().filter(|&&i| i != usize::MAX).count();
        assert_eq!(items(&s0) + items(&s1), phases * 7);
        println!("the helper did {} of {} items", items(&s1), phases * 7);
        assert!(s1.first().is_none_or(|&i| i == usize::MAX), "init runs before a member's first item");
    }

    #[test]
    fn a_busy_helper_leaves_the_caller_alone_and_panics_are_reported() {
        let h = Helper::start_named("test-helper").unwrap();
        // (to tell the members apart)
        let caller = std::thread::current().name().map(str::to_owned);
        // A nested crew on the same helper runs alone while the first holds the helper.
        let (mut a, mut b) = ((), ());
        let ((inner_solo, _), _) = h.crew(&mut a, |_| h.crew(&mut b, |c| c.session.is_none()));
        assert!(inner_solo);

        // The helper's part panics: the caller finishes, learns it, and the helper still works.
        let mut out = vec![0u32; 64];
        let ((), panicked) = h.crew(&mut (), |c| {
            c.phase(
                &mut (),
                Order::Split,
                Each(out.iter_mut()),
                |_| {},
                |_, v| {
                    if std::thread::current().name().map(str::to_owned) != caller {
                        panic!("the helper fails");
                    }
                    std::thread::sleep(Duration::from_micros(200));
                    *v = 1;
                },
            );
            // later phases run on the caller alone
            c.phase(&mut (), Order::Split, Each(out.iter_mut()), |_| {}, |_, v| *v += 1);
        });
        // Whether the helper took an item before the caller took them all depends on timing.
        if panicked {
            assert!(out.iter().filter(|&&v| v == 1).count() >= 1, "the lost item stays undone");
        } else {
            assert!(out.iter().all(|&v| v == 2));
        }
        let mut n = 0u32;
        let (_, p) = h.crew(&mut (), |c| c.phase(&mut (), Order::Queue, Each(0..4u32), |_| {}, |_, _| {}));
        assert!(!p);
        Crew::solo().phase(&mut n, Order::Queue, Each(0..3u32), |_| {}, |n: &mut u32, i| *n += i);
        assert_eq!(n, 3);

        // The caller's part panics: the panic propagates once the helper has let go.
        let r = catch_unwind(AssertUnwindSafe(|| {
            h.crew(&mut (), |c| {
                c.phase(
                    &mut (),
                    Order::Queue,
                    Each(0..8u32),
                    |_| {},
                    |_, _| {
                        std::thread::sleep(Duration::from_micros(100));
                        if std::thread::current().name().map(str::to_owned) == caller {
                            panic!("the caller fails");
                        }
                    },
                )
            })
        }));
        assert!(r.is_err());
        let (_, p) = h.crew(&mut (), |c| c.phase(&mut (), Order::Queue, Each(0..2u32), |_| {}, |_, _| {}));
        assert!(!p);
    }
}

#[cfg(test)]
mod speed {
    use super::*;

    /// The cost of a phase hand-over: many phases of 8 tiny items, on a crew and alone
    /// (`cargo test --release --lib phase_overhead -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn phase_overhead() {
        let h = Helper::start_named("bench-helper").unwrap();
        let mut buf = vec![0f32; 64];
        for _ in 0..3 {
            for team in [false, true] {
                let n = 20_000;
                let t = Instant::now();
                let mut work = |c: &mut Crew<'_, ()>| {
                    for _ in 0..n {
                        c.phase(
                            &mut (),
                            Order::Split,
                            Each(buf.chunks_mut(8)),
                            |_| {},
                            |_, ch| {
                                for v in ch {
                                    *v += 1.0;
                                }
                            },
                        );
                    }
                };
                if team {
                    h.crew(&mut (), work);
                } else {
                    work(&mut Crew::solo());
                }
                println!("team {team}: {:.3} us per phase", t.elapsed().as_secs_f64() * 1e6 / n as f64);
            }
        }
    }
}
