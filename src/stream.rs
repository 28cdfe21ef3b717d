//! One generation = one [`Stream`]: a worker thread that pulls 16-frame chunks from a
//! [`ChunkSource`] and pushes the frames into a lock-free SPSC ring buffer, and a consumer
//! side (the host's thread) that polls frames out of it.
//!
//! Why this shape:
//! * The host polls from its game loop (`Update()`), so [`Stream::poll`] must never block and
//!   never allocate; it is a `try_pop` plus a few atomics.
//! * Backpressure instead of loss: when the ring is full the worker parks (after a short spin)
//!   and the consumer unparks it after taking a frame. Frames are never dropped or reordered.
//! * Cancellation is an atomic flag the worker checks between `next_chunk` calls (a token
//!   step and a decode each, or a few steps and one decode when decodes are grouped: ~8 ms
//!   with the default bundle on 2 cores) and while it waits for room, so a cancel takes effect within
//!   one call; it also unparks the
//!   worker so a parked worker exits at once.
//! * The worker catches panics of its source and reports them as an error through `poll`, so a
//!   bug in inference never takes the host down with it.
//!
//! Wake-up protocol (no lost wake-ups, no locks on the hot path):
//! * producer full: `producer_parked = true; fence(SeqCst); if still full && !cancelled { park }`.
//!   consumer after a pop: `fence(SeqCst); if producer_parked { unpark }`. One of the two sides
//!   always sees the other's write (Dekker with SeqCst fences); `unpark` before `park` leaves a
//!   token, so `park` then returns at once.
//! * consumer waiting ([`Stream::wait`]): same idea with `consumer_waiting` and a condvar whose
//!   mutex the worker takes only when a consumer actually waits.
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{fence, AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, OnceLock};
use std::thread::{self, JoinHandle, Thread};
use std::time::{Duration, Instant};

use parking_lot::{Condvar, Mutex};
use ringbuf::traits::{Consumer, Observer, Producer, Split};
use ringbuf::{HeapCons, HeapProd, HeapRb};

use crate::error::{Error, Result};
use crate::frame::Frame;

pub use crate::config::StreamConfig;
pub use crate::generator::{ChunkSource, StreamObject};

/// How a stream's worker finished, as a [`StreamSink`] hears it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StreamOutcome {
    /// Every frame was produced.
    Ended,
    /// Cancelled (by the host or because the engine was dropped).
    Cancelled,
    /// The source failed or panicked.
    Failed,
}

/// Sees every frame of one stream as its worker produces it, before the frame enters the
/// ring (so it never waits for the host's polling). The engine attaches shared-memory
/// publishing this way. Called on the worker thread: it must not block.
pub trait StreamSink: Send {
    /// Before the first frame.
    fn started(&mut self);
    /// Each frame, in order.
    fn frame(&mut self, frame: &Frame);
    /// Once, after the last frame and after the source's state was freed.
    fn finished(&mut self, outcome: StreamOutcome);
}

/// What [`Stream::poll`] found. Only `Frame` writes the output frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PollResult {
    /// A frame was written to the output.
    Frame,
    /// No frame yet; the worker is still generating.
    Pending,
    /// The stream finished and every frame has been delivered.
    End,
    /// The stream was cancelled (by [`Stream::cancel`] or because its engine was dropped);
    /// undelivered frames were discarded.
    Cancelled,
    /// The worker failed; [`Stream::error`] has the error. Frames produced before the
    /// failure were delivered first.
    Error,
}

/// Worker states, published by the worker after its last push (Release) and read by the
/// consumer before it tries to pop (Acquire), so "terminal + empty" really means drained.
const RUNNING: u8 = 0;
const ENDED: u8 = 1;
const FAILED: u8 = 2;
const CANCELLED: u8 = 3;

/// Spins before parking when the ring is full: a consumer that is actively draining frees a
/// slot within microseconds, which is much cheaper than a park/unpark round trip.
const SPIN_BEFORE_PARK: u32 = 64;

/// The state shared by the consumer side, the worker and the engine (which cancels every live
/// stream when it is dropped).
pub(crate) struct StreamShared {
    id: u64,
    cancelled: AtomicBool,
    state: AtomicU8,
    /// Written once by the worker before it publishes `FAILED`.
    error: OnceLock<Error>,
    /// Set once, before the stream is handed out, so every canceller can unpark the worker.
    worker: OnceLock<Thread>,
    producer_parked: AtomicBool,
    consumer_waiting: AtomicBool,
    wake_lock: Mutex<()>,
    wake: Condvar,
}

impl StreamShared {
    pub(crate) fn new(id: u64) -> Self {
        StreamShared {
            id,
            cancelled: AtomicBool::new(false),
            state: AtomicU8::new(RUNNING),
            error: OnceLock::new(),
            worker: OnceLock::new(),
            producer_parked: AtomicBool::new(false),
            consumer_waiting: AtomicBool::new(false),
            wake_lock: Mutex::new(()),
            wake: Condvar::new(),
        }
    }

    pub(crate) fn id(&self) -> u64 {
        self.id
    }

    pub(crate) fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::SeqCst)
    }

    /// Sets the flag, unparks the worker (if it waits for room) and wakes a waiting consumer.
    /// Allocation-free and non-blocking apart from the tiny condvar critical section.
    pub(crate) fn cancel(&self) {
        self.cancelled.store(true, Ordering::SeqCst);
        if let Some(t) = self.worker.get() {
            t.unpark();
        }
        self.wake_consumer_always();
    }

    /// What the engine does when it is dropped: stop the compute, but leave a stream that
    /// already finished alone so its buffered frames can still be drained.
    pub(crate) fn cancel_if_running(&self) {
        if self.state.load(Ordering::Acquire) == RUNNING {
            self.cancel();
        }
    }

    fn wake_consumer_always(&self) {
        let _g = self.wake_lock.lock();
        self.wake.notify_all();
    }

    /// A producer that is not this stream's own worker (the crowd scheduler) found the ring
    /// full: the consumer's next pop unparks the producer's thread. The producer looks at
    /// the ring once more after this (the Dekker pair of the module doc); a stale request
    /// only costs a spurious unpark.
    pub(crate) fn request_room(&self) {
        self.producer_parked.store(true, Ordering::SeqCst);
        fence(Ordering::SeqCst);
    }

    /// The producer that asked for room no longer waits for it.
    pub(crate) fn room_taken(&self) {
        self.producer_parked.store(false, Ordering::SeqCst);
    }

    /// Called by the worker after every push: cheap unless a consumer is blocked in `wait`.
    pub(crate) fn wake_consumer_if_waiting(&self) {
        fence(Ordering::SeqCst);
        if self.consumer_waiting.load(Ordering::Relaxed) {
            self.wake_consumer_always();
        }
    }
}

/// A cloneable, thread-safe handle that can only cancel its stream. Use it to cancel from a
/// thread other than the one that polls.
#[derive(Clone)]
pub struct StreamCanceller {
    shared: Arc<StreamShared>,
}

impl StreamCanceller {
    /// Same as [`Stream::cancel`].
    pub fn cancel(&self) {
        self.shared.cancel()
    }
}

/// A running (or finished) generation. Owned by one consumer; `poll`/`wait` take `&mut self`.
/// Dropping it cancels the worker and joins it (waits at most one generator call).
pub struct Stream {
    shared: Arc<StreamShared>,
    /// `None` once the stream was cancelled and its buffer released.
    cons: Option<HeapCons<Frame>>,
    /// Who produces the frames; `None` once closed.
    producer: Option<Source>,
    /// Lets the engine know the stream is gone (live count, `max_streams`).
    set: Arc<StreamSet>,
    /// `End` once the `is_last` frame was delivered, `Error` once the error was reported:
    /// from then on `poll` returns it without looking at the worker, so `End` follows the
    /// last frame at once (not after the worker freed its model) and a later cancel cannot
    /// turn a finished stream into a cancelled one.
    finished: Option<PollResult>,
    object: Option<StreamObject>,
}

impl Stream {
    /// Spawns the worker. `shared` must already be registered in `set` (the engine does
    /// that so the `max_streams` check and the registration are one step).
    pub(crate) fn spawn(
        shared: Arc<StreamShared>,
        source: Box<dyn ChunkSource>,
        ring_capacity: usize,
        set: Arc<StreamSet>,
        sink: Option<Box<dyn StreamSink>>,
    ) -> Result<Stream> {
        if ring_capacity == 0 {
            return Err(Error::InvalidArgument("ring capacity must be at least 1 frame".into()));
        }
        let (prod, cons) = HeapRb::<Frame>::new(ring_capacity).split();
        let worker_shared = Arc::clone(&shared);
        let worker_set = Arc::clone(&set);
        // Count the worker before it exists so the engine's drop cannot miss it.
        set.worker_started();
        let spawned = thread::Builder::new()
            .name(format!("comgrasp-stream-{}", shared.id))
            .spawn(move || worker_main(worker_shared, source, prod, worker_set, sink));
        let join = match spawned {
            Ok(j) => j,
            Err(e) => {
                set.worker_finished();
                return Err(Error::Io(e));
            }
        };
        let _ = shared.worker.set(join.thread().clone());
        Ok(Stream { shared, cons: Some(cons), producer: Some(Source::Thread(join)), set, finished: None, object: None })
    }

    /// A stream whose frames another thread produces (the crowd scheduler, running as
    /// `thread`): returns the stream and the ring's producer half. `shared` must already
    /// be registered in `set`; the producer counts itself as a worker of `set`
    /// ([`StreamSet::worker_started`]) and ends with [`finish`].
    pub(crate) fn produced_by(
        shared: Arc<StreamShared>,
        thread: Thread,
        ring_capacity: usize,
        set: Arc<StreamSet>,
    ) -> Result<(Stream, HeapProd<Frame>)> {
        if ring_capacity == 0 {
            return Err(Error::InvalidArgument("ring capacity must be at least 1 frame".into()));
        }
        let (prod, cons) = HeapRb::<Frame>::new(ring_capacity).split();
        let _ = shared.worker.set(thread);
        let stream =
            Stream { shared, cons: Some(cons), producer: Some(Source::Scheduler), set, finished: None, object: None };
        Ok((stream, prod))
    }

    /// The stream's id (unique per engine, starting at 1); frames carry it as `stream_id`.
    pub fn id(&self) -> u64 {
        self.shared.id
    }

    /// The catalogue object the frames' object is (the engine sets it from the prompt);
    /// `None` for a stream without a model bundle (a test source).
    pub fn object(&self) -> Option<&StreamObject> {
        self.object.as_ref()
    }

    pub(crate) fn set_object(&mut self, object: Option<StreamObject>) {
        self.object = object;
    }

    /// Takes the next frame if there is one. Never blocks, never allocates. `out` is written
    /// only when the result is [`PollResult::Frame`]. `End` comes on the call after the
    /// `is_last` frame. After a cancel it returns `Cancelled` (and frees the ring buffer);
    /// once it returned `End` or `Error` it keeps returning that, also after a cancel.
    pub fn poll(&mut self, out: &mut Frame) -> PollResult {
        if let Some(done) = self.finished {
            return done;
        }
        if self.shared.is_cancelled() {
            // Release the ring now (the worker drops its half within one call); a cancelled
            // stream holds no frame memory even if the host keeps the handle for a while.
            self.cons = None;
            return PollResult::Cancelled;
        }
        // Read the state BEFORE popping: the worker publishes a terminal state only after its
        // last push, so "terminal (seen first) and then empty" means fully drained.
        let state = self.shared.state.load(Ordering::Acquire);
        let Some(cons) = self.cons.as_mut() else {
            return PollResult::Cancelled;
        };
        if let Some(frame) = cons.try_pop() {
            if frame.is_last != 0 {
                self.finished = Some(PollResult::End);
            }
            *out = frame;
            fence(Ordering::SeqCst);
            if self.shared.producer_parked.load(Ordering::Relaxed) {
                if let Some(t) = self.shared.worker.get() {
                    t.unpark();
                }
            }
            return PollResult::Frame;
        }
        match state {
            RUNNING => PollResult::Pending,
            ENDED => *self.finished.insert(PollResult::End),
            FAILED => *self.finished.insert(PollResult::Error),
            _ => PollResult::Cancelled,
        }
    }

    /// Like [`poll`](Self::poll) but blocks up to `timeout` while the result would be
    /// `Pending`. Returns `Pending` only when the timeout expired. Wakes early on a frame,
    /// end, error or cancel (also a cancel from another thread).
    pub fn wait(&mut self, out: &mut Frame, timeout: Duration) -> PollResult {
        let deadline = Instant::now().checked_add(timeout);
        loop {
            let r = self.poll(out);
            if r != PollResult::Pending {
                return r;
            }
            let shared = Arc::clone(&self.shared);
            let mut guard = shared.wake_lock.lock();
            shared.consumer_waiting.store(true, Ordering::SeqCst);
            fence(Ordering::SeqCst);
            let ready = shared.is_cancelled()
                || shared.state.load(Ordering::Acquire) != RUNNING
                || self.cons.as_ref().is_none_or(|c| !c.is_empty());
            let timed_out = if ready {
                false
            } else {
                match deadline {
                    Some(d) => shared.wake.wait_until(&mut guard, d).timed_out(),
                    None => {
                        shared.wake.wait(&mut guard);
                        false
                    }
                }
            };
            shared.consumer_waiting.store(false, Ordering::SeqCst);
            drop(guard);
            if timed_out {
                return self.poll(out);
            }
        }
    }

    /// Asks the worker to stop. Takes effect within one generator call (~8 ms with the
    /// default bundle on 2 cores); from then on `poll` returns `Cancelled`, unless it had
    /// already returned `End` or `Error` (or delivered the `is_last` frame), which stays.
    /// Idempotent.
    pub fn cancel(&self) {
        self.shared.cancel()
    }

    /// A handle another thread can use to cancel this stream.
    pub fn canceller(&self) -> StreamCanceller {
        StreamCanceller { shared: Arc::clone(&self.shared) }
    }

    /// The worker's error once `poll` returned [`PollResult::Error`].
    pub fn error(&self) -> Option<&Error> {
        if self.shared.state.load(Ordering::Acquire) == FAILED {
            self.shared.error.get()
        } else {
            None
        }
    }

    /// Whether `cancel` was called (or the engine was dropped).
    pub fn is_cancelled(&self) -> bool {
        self.shared.is_cancelled()
    }

    /// Cancels (unless already finished) and joins the worker, then frees the ring. Waits at
    /// most one generator call (~8 ms with the default bundle on 2 cores). Idempotent; `Drop` calls it.
    pub fn close(&mut self) {
        if let Some(producer) = self.producer.take() {
            let shared = &self.shared;
            if shared.state.load(Ordering::Acquire) == RUNNING {
                shared.cancel();
            }
            match producer {
                // The worker catches its own panics, so join only fails if the runtime
                // itself failed while unwinding; nothing useful to do with that here.
                Source::Thread(join) => drop(join.join()),
                // The scheduler drops the generation within one round, then publishes the
                // terminal state and wakes this condvar (under its lock: no lost wake-up).
                Source::Scheduler => {
                    let mut guard = shared.wake_lock.lock();
                    while shared.state.load(Ordering::Acquire) == RUNNING {
                        shared.wake.wait(&mut guard);
                    }
                }
            }
            self.set.remove(shared.id);
        }
        self.cons = None;
    }
}

impl Drop for Stream {
    fn drop(&mut self) {
        self.close();
    }
}

/// Who produces a stream's frames.
enum Source {
    /// Its own worker thread.
    Thread(JoinHandle<()>),
    /// The engine's crowd scheduler (`crate::crowd`), which publishes a terminal state
    /// once it has dropped the stream's generation.
    Scheduler,
}

/// What a producer ended with.
pub(crate) enum Outcome {
    Ended,
    Cancelled,
    Failed(Error),
}

fn worker_main(
    shared: Arc<StreamShared>,
    source: Box<dyn ChunkSource>,
    prod: HeapProd<Frame>,
    set: Arc<StreamSet>,
    sink: Option<Box<dyn StreamSink>>,
) {
    // Decrement the engine's worker count even if something below panics.
    struct Finished(Arc<StreamSet>);
    impl Drop for Finished {
        fn drop(&mut self) {
            self.0.worker_finished();
        }
    }
    let _finished = Finished(set);

    let mut source = source;
    let mut prod = prod;
    let mut sink = sink;
    if let Some(s) = sink.as_mut() {
        s.started();
    }
    let outcome = match catch_unwind(AssertUnwindSafe(|| run(&shared, &mut *source, &mut prod, sink.as_deref_mut()))) {
        Ok(o) => o,
        Err(payload) => Outcome::Failed(Error::Panic(panic_message(&*payload))),
    };
    // Free the model state (KV cache etc.) and our half of the ring before announcing the
    // end, so a host that sees End/Cancelled can rely on the memory being released.
    drop(catch_unwind(AssertUnwindSafe(move || drop(source))));
    drop(prod);
    finish(&shared, outcome, sink.as_deref_mut());
}

/// A producer's last word, after it dropped the stream's generation and its half of the
/// ring: tells the sink, publishes the terminal state and wakes the consumer.
pub(crate) fn finish(shared: &StreamShared, outcome: Outcome, sink: Option<&mut (dyn StreamSink + 'static)>) {
    if let Some(s) = sink {
        s.finished(match outcome {
            Outcome::Ended => StreamOutcome::Ended,
            Outcome::Cancelled => StreamOutcome::Cancelled,
            Outcome::Failed(_) => StreamOutcome::Failed,
        });
    }
    let state = match outcome {
        Outcome::Ended => ENDED,
        Outcome::Cancelled => CANCELLED,
        Outcome::Failed(e) => {
            let _ = shared.error.set(e);
            FAILED
        }
    };
    shared.state.store(state, Ordering::Release);
    shared.wake_consumer_always();
}

fn run(
    shared: &StreamShared,
    source: &mut dyn ChunkSource,
    prod: &mut HeapProd<Frame>,
    mut sink: Option<&mut (dyn StreamSink + 'static)>,
) -> Outcome {
    // Reused for every chunk: the steady state allocates nothing.
    let mut chunk: Vec<Frame> = Vec::with_capacity(source.max_chunk_frames());
    loop {
        if shared.is_cancelled() {
            return Outcome::Cancelled;
        }
        chunk.clear();
        let more = match source.next_chunk(&mut chunk) {
            Ok(more) => more,
            Err(e) => return Outcome::Failed(e),
        };
        for frame in chunk.drain(..) {
            // Published before it enters the ring: subscribers never wait for the host.
            if let Some(s) = sink.as_deref_mut() {
                s.frame(&frame);
            }
            if !push_waiting(shared, prod, frame) {
                return Outcome::Cancelled;
            }
        }
        if !more {
            return Outcome::Ended;
        }
    }
}

/// Pushes one frame, waiting for room as long as needed. Returns false if cancelled while
/// waiting (the frame is then discarded along with the stream).
fn push_waiting(shared: &StreamShared, prod: &mut HeapProd<Frame>, frame: Frame) -> bool {
    let mut frame = frame;
    let mut spins = 0u32;
    loop {
        match prod.try_push(frame) {
            Ok(()) => {
                shared.wake_consumer_if_waiting();
                return true;
            }
            Err(back) => frame = back,
        }
        if shared.is_cancelled() {
            return false;
        }
        if spins < SPIN_BEFORE_PARK {
            spins += 1;
            std::hint::spin_loop();
            continue;
        }
        shared.producer_parked.store(true, Ordering::SeqCst);
        fence(Ordering::SeqCst);
        if prod.is_full() && !shared.is_cancelled() {
            thread::park();
        }
        shared.producer_parked.store(false, Ordering::SeqCst);
    }
}

/// The text of a panic payload (`&str` or `String`; anything else gets a generic text).
pub(crate) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "non-string panic payload".to_string()
    }
}

/// The part of the engine that streams share: id counter, live list, worker count.
pub(crate) struct StreamSet {
    pub(crate) next_id: AtomicU64,
    max: usize,
    /// Small (at most `max_streams`), so a Vec with linear removal is the simplest fit.
    pub(crate) live: Mutex<Vec<Arc<StreamShared>>>,
    workers: Mutex<usize>,
    workers_idle: Condvar,
}

impl StreamSet {
    pub(crate) fn new(max: usize) -> Self {
        StreamSet {
            next_id: AtomicU64::new(1),
            max,
            live: Mutex::new(Vec::with_capacity(max)),
            workers: Mutex::new(0),
            workers_idle: Condvar::new(),
        }
    }

    /// Registers a new stream if the limit allows; the returned guard unregisters it again
    /// unless [`Reservation::keep`] is called (so a failing or panicking factory leaks nothing).
    pub(crate) fn reserve<'a>(self: &'a Arc<Self>, shared: &Arc<StreamShared>) -> Result<Reservation<'a>> {
        let mut live = self.live.lock();
        if live.len() >= self.max {
            return Err(Error::LimitReached(format!(
                "{} streams are alive, max_streams is {}; destroy finished streams first",
                live.len(),
                self.max
            )));
        }
        live.push(Arc::clone(shared));
        Ok(Reservation { set: self, id: shared.id(), armed: true })
    }

    pub(crate) fn remove(&self, id: u64) {
        let mut live = self.live.lock();
        if let Some(i) = live.iter().position(|s| s.id() == id) {
            live.swap_remove(i);
        }
    }

    pub(crate) fn worker_started(&self) {
        *self.workers.lock() += 1;
    }

    pub(crate) fn worker_finished(&self) {
        let mut n = self.workers.lock();
        *n -= 1;
        if *n == 0 {
            self.workers_idle.notify_all();
        }
    }

    /// Cancels every live stream and waits until every worker has exited.
    pub(crate) fn shutdown(&self) {
        // Clone the list so no lock is held while cancelling (cancel takes the stream's
        // own condvar lock).
        let live: Vec<Arc<StreamShared>> = self.live.lock().clone();
        for s in &live {
            s.cancel_if_running();
        }
        drop(live);
        let mut n = self.workers.lock();
        while *n > 0 {
            self.workers_idle.wait(&mut n);
        }
    }
}

pub(crate) struct Reservation<'a> {
    set: &'a StreamSet,
    id: u64,
    armed: bool,
}

impl Reservation<'_> {
    pub(crate) fn keep(mut self) {
        self.armed = false;
    }
}

impl Drop for Reservation<'_> {
    fn drop(&mut self) {
        if self.armed {
            self.set.remove(self.id);
        }
    }
}
