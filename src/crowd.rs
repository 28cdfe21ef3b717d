//! The crowd scheduler: one per engine, a few threads that drive every stream's generation
//! instead of a worker thread per stream, with the token steps of all streams batched.
//!
//! **Shape.** Each scheduler thread (a *shard*) owns the streams handed to it (a new stream
//! goes to the shard with the fewest) and runs rounds:
//! 1. streams that were cancelled are dropped (`cg_cancel` takes effect within a round);
//!    frames a full ring did not take are pushed;
//! 2. every stream that needs a token step gets it in **one batched step**
//!    (`StepModel::step_batch_checked`: each block of weight rows is applied to every
//!    stream before the next is read, so the step's weights stream from memory once per
//!    batch instead of once per stream), then samples its token;
//! 3. every stream whose group of tokens is complete decodes it on this thread, and its
//!    frames are assembled and pushed: streams that have not produced a frame yet first,
//!    each alone (a first decode is one token), then the others in **batched decodes** of
//!    up to `MAX_DECODE_BATCH` streams (`DecoderModel::decode_batch_checked`: each layer one
//!    GEMM over the new positions of all of them).
//!
//! A stream's tokens and frames are **bit-identical** to the same stream run alone, on this
//! scheduler or on its own worker thread: every value of the batched step is computed by
//! the kernel, inputs and row blocks of the one-stream step, and the decoder computes the
//! same bits on one thread or two and for a stream alone or in a batch (tests/crowd.rs
//! starts streams at staggered times).
//!
//! **Fairness.** Every stream that can run gets one step or one decode per round, so none
//! starves. A stream whose ring is full (a host that polls slowly) is skipped until the
//! host takes a frame; only that stream waits. New streams do not wait for the round:
//! between decodes and between parts of the batched step the shard looks for new streams
//! and runs their first step and first decode at once, so the time to first frame is
//! about one decode plus one first chunk, not a round. A shard with nothing to do parks;
//! a host's poll that frees room, a cancel and a new stream unpark it.
//!
//! **Threads.** `RuntimeOptions::scheduler_threads` (default: the machine's cores minus
//! one, at least one, so a game keeps a core). A lone stream on the whole scheduler runs as
//! on its own worker thread (`ChunkSource::next_chunk`: its step and decode with the
//! models' helper threads too, its next steps overlapped with its decode), one call per
//! round; the generation's state is the same either way, so it joins batches again when a
//! second stream arrives.
//!
//! **Memory.** A stream's model state (KV cache, decoder context, decode buffer) is
//! allocated once, at its first step; the shard's lists and the batched step's and decode's
//! scratch are allocated at engine creation, so a round allocates nothing.
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Barrier};
use std::thread::{self, JoinHandle};

use parking_lot::Mutex;
use ringbuf::traits::Producer;
use ringbuf::HeapProd;

use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::generator::{ChunkSource, Generator, Need, Pipeline};
use crate::model::{DecodeJob, DecodeJobs, DecodeScratch, StepJob, StepJobs, StepScratch, MAX_DECODE_BATCH};
use crate::stream::{finish, panic_message, Outcome, Stream, StreamSet, StreamShared, StreamSink};

/// Most streams in one batched step; the shard looks for new streams between batches.
const MAX_BATCH: usize = 64;

/// The default number of scheduler threads: the machine's cores minus one (at least one).
pub fn default_threads() -> usize {
    thread::available_parallelism().map_or(1, |n| n.get()).saturating_sub(1).max(1)
}

/// An engine's scheduler: its threads and where new streams go.
pub struct Scheduler {
    shards: Vec<Shard>,
    /// Streams on the scheduler, all shards together.
    live: Arc<AtomicUsize>,
    max_streams: usize,
}

struct Shard {
    shared: Arc<ShardShared>,
    thread: Option<JoinHandle<()>>,
}

/// What a shard's thread and the engine share.
struct ShardShared {
    /// New streams, taken by the shard at its next look.
    inbox: Mutex<Vec<Member>>,
    /// Streams on this shard (new ones included): where the next stream goes.
    load: AtomicUsize,
    stop: AtomicBool,
}

/// One stream on a shard.
struct Member {
    gen: Box<Generator>,
    shared: Arc<StreamShared>,
    prod: HeapProd<Frame>,
    sink: Option<Box<dyn StreamSink>>,
    set: Arc<StreamSet>,
    /// Frames made and not yet in the ring (it was full): `out[sent..]`.
    out: Vec<Frame>,
    sent: usize,
    /// Frames made so far (new streams go first).
    made: u64,
    /// Set when the generation failed or ended: the member leaves at the end of the round.
    outcome: Option<Outcome>,
}

impl Scheduler {
    /// Starts `threads` scheduler threads (at least one) for up to `max_streams` streams.
    pub fn new(pipeline: &Pipeline, threads: usize, max_streams: usize) -> Result<Scheduler> {
        let live = Arc::new(AtomicUsize::new(0));
        let mut shards = Vec::new();
        for i in 0..threads.max(1) {
            let shared = Arc::new(ShardShared {
                inbox: Mutex::new(Vec::with_capacity(max_streams)),
                load: AtomicUsize::new(0),
                stop: AtomicBool::new(false),
            });
            let round = Round::new(Arc::clone(&shared), Arc::clone(&live), max_streams, pipeline);
            // `new` returns once the thread runs: a thread's start allocates (std's
            // per-thread info), which would otherwise fall into the first streams' generation
            // whenever the OS gets round to starting it (a loaded machine: tests/alloc_free_stream).
            let started = Arc::new(Barrier::new(2));
            let running = Arc::clone(&started);
            let spawned = thread::Builder::new().name(format!("comgrasp-crowd-{i}")).spawn(move || {
                running.wait();
                round.run()
            });
            let mut shard = Shard { shared, thread: None };
            match spawned {
                Ok(j) => {
                    started.wait();
                    shard.thread = Some(j)
                }
                Err(e) => {
                    // (the shards started so far stop when `shards` drops)
                    drop(Scheduler { shards, live, max_streams });
                    return Err(Error::Io(e));
                }
            }
            shards.push(shard);
        }
        Ok(Scheduler { shards, live, max_streams })
    }

    /// Threads the scheduler runs.
    pub fn threads(&self) -> usize {
        self.shards.len()
    }

    /// Hands `gen` to the least loaded shard and returns its stream. `shared` must be
    /// registered in `set` (as for `Stream::spawn`).
    pub(crate) fn start(
        &self,
        gen: Generator,
        shared: Arc<StreamShared>,
        ring_capacity: usize,
        set: Arc<StreamSet>,
        sink: Option<Box<dyn StreamSink>>,
    ) -> Result<Stream> {
        let shard = self
            .shards
            .iter()
            .min_by_key(|s| s.shared.load.load(Ordering::Relaxed))
            .ok_or_else(|| Error::WrongState("the scheduler has no thread".into()))?;
        let thread = shard
            .thread
            .as_ref()
            .map(|j| j.thread().clone())
            .ok_or_else(|| Error::WrongState("the scheduler's thread is gone".into()))?;
        let mut inbox = shard.shared.inbox.lock();
        if inbox.len() >= self.max_streams {
            return Err(Error::LimitReached("the scheduler's inbox is full".into()));
        }
        // Nothing fails from here on: a stream made by `produced_by` waits for the shard
        // when it is dropped, so it must reach the shard.
        let (stream, prod) = Stream::produced_by(Arc::clone(&shared), thread.clone(), ring_capacity, Arc::clone(&set))?;
        let out = Vec::with_capacity(gen.max_chunk_frames());
        let mut sink = sink;
        if let Some(s) = sink.as_mut() {
            s.started();
        }
        // Counted as a worker before the shard can finish it, so the engine's drop waits
        // for it.
        set.worker_started();
        shard.shared.load.fetch_add(1, Ordering::Relaxed);
        self.live.fetch_add(1, Ordering::Relaxed);
        inbox.push(Member { gen: Box::new(gen), shared, prod, sink, set, out, sent: 0, made: 0, outcome: None });
        drop(inbox);
        thread.unpark();
        Ok(stream)
    }
}

impl Drop for Scheduler {
    /// Stops the threads (the engine has cancelled its streams and waited for them first;
    /// a stream still on a shard is released as cancelled).
    fn drop(&mut self) {
        for s in &self.shards {
            s.shared.stop.store(true, Ordering::SeqCst);
            if let Some(j) = &s.thread {
                j.thread().unpark();
            }
        }
        for s in &mut self.shards {
            if let Some(j) = s.thread.take() {
                let _ = j.join();
            }
        }
    }
}

/// A shard's thread: its members and scratch lists, all allocated once.
struct Round {
    sh: Arc<ShardShared>,
    live: Arc<AtomicUsize>,
    members: Vec<Member>,
    /// Members of this round's batched step / decodes (indices into `members`).
    batch: Vec<usize>,
    work: Vec<usize>,
    /// Members that joined during the round (indices), served at once.
    fresh: Vec<usize>,
    /// The batched step's and the batched decode's buffers.
    scratch: StepScratch,
    decode: DecodeScratch,
}

impl Round {
    fn new(sh: Arc<ShardShared>, live: Arc<AtomicUsize>, max_streams: usize, pipeline: &Pipeline) -> Round {
        Round {
            sh,
            live,
            members: Vec::with_capacity(max_streams),
            batch: Vec::with_capacity(max_streams),
            work: Vec::with_capacity(max_streams),
            fresh: Vec::with_capacity(max_streams),
            scratch: pipeline.bundle().step.batch_scratch(MAX_BATCH),
            decode: pipeline.bundle().decoder.batch_scratch(),
        }
    }

    fn run(mut self) {
        loop {
            self.take_new();
            let stop = self.sh.stop.load(Ordering::SeqCst);
            if stop {
                for m in &mut self.members {
                    m.outcome.get_or_insert(Outcome::Cancelled);
                }
                self.retire();
                return;
            }
            // Generation errors and panics are caught per stream inside the round; this
            // catches the rest, so no stream is left waiting for a thread that died.
            let progressed = match catch_unwind(AssertUnwindSafe(|| self.round())) {
                Ok(p) => p,
                Err(p) => {
                    let msg = panic_message(&*p);
                    for m in &mut self.members {
                        m.fail(Error::Panic(format!("crowd scheduler: {msg}")));
                    }
                    true
                }
            };
            self.retire();
            if !progressed && self.sh.inbox.lock().is_empty() {
                // Unparked by a poll that frees room, a cancel, a new stream or the stop.
                thread::park();
            }
        }
    }

    /// Moves new streams from the inbox to the members; returns where they start.
    fn take_new(&mut self) -> usize {
        let first = self.members.len();
        let mut inbox = self.sh.inbox.lock();
        self.members.extend(inbox.drain(..));
        first
    }

    /// One round (module doc); whether any member made progress.
    fn round(&mut self) -> bool {
        let mut progressed = false;
        for m in &mut self.members {
            progressed |= m.flush();
        }
        if let [m] = &mut self.members[..] {
            if self.live.load(Ordering::Relaxed) == 1 {
                m.check_done();
                return progressed | alone(m);
            }
        }
        self.batch.clear();
        for (i, m) in self.members.iter().enumerate() {
            if m.runnable() && m.gen.need() == Need::Step {
                self.batch.push(i);
            }
        }
        let mut at = 0;
        while at < self.batch.len() {
            let end = (at + MAX_BATCH).min(self.batch.len());
            progressed |= step(&mut self.members, &self.batch[at..end], &self.live, &mut self.scratch);
            at = end;
            self.serve_new();
        }
        self.work.clear();
        for (i, m) in self.members.iter().enumerate() {
            if m.runnable() && matches!(m.gen.need(), Need::Decode | Need::Finish) {
                self.work.push(i);
            }
        }
        // the ones without a frame yet first, otherwise in join order (unstable: no buffer)
        let members = &self.members;
        self.work.sort_unstable_by_key(|&i| (members[i].made > 0, i));
        // Streams without a frame yet (a first decode of one token) and ends alone, first;
        // the others in batches.
        self.batch.clear();
        for w in 0..self.work.len() {
            let i = self.work[w];
            let m = &mut self.members[i];
            if m.made > 0 && m.gen.need() == Need::Decode {
                self.batch.push(i);
                continue;
            }
            progressed |= decode(m, &self.live);
            self.serve_new();
        }
        let mut at = 0;
        while at < self.batch.len() {
            let end = (at + MAX_DECODE_BATCH).min(self.batch.len());
            progressed |= decode_batch(&mut self.members, &self.batch[at..end], &mut self.decode);
            at = end;
            self.serve_new();
        }
        for m in &mut self.members {
            m.check_done();
        }
        progressed
    }

    /// New streams get their first step and first decode now, not after the round.
    fn serve_new(&mut self) {
        if self.sh.inbox.lock().is_empty() {
            return;
        }
        let first = self.take_new();
        self.fresh.clear();
        for (i, m) in self.members.iter_mut().enumerate().skip(first) {
            m.flush();
            if m.runnable() && m.gen.need() == Need::Step {
                self.fresh.push(i);
            }
        }
        for part in self.fresh.chunks(MAX_BATCH) {
            step(&mut self.members, part, &self.live, &mut self.scratch);
        }
        for m in &mut self.members[first..] {
            if m.runnable() && matches!(m.gen.need(), Need::Decode | Need::Finish) {
                decode(m, &self.live);
            }
        }
    }

    /// Members that were cancelled, failed or are done (every frame in the ring) leave:
    /// their generation is dropped, then the stream hears the outcome.
    fn retire(&mut self) {
        let mut i = 0;
        while i < self.members.len() {
            let m = &mut self.members[i];
            if m.outcome.is_none() && m.shared.is_cancelled() {
                m.outcome = Some(Outcome::Cancelled);
            }
            if m.outcome.is_some() {
                let m = self.members.swap_remove(i);
                self.sh.load.fetch_sub(1, Ordering::Relaxed);
                self.live.fetch_sub(1, Ordering::Relaxed);
                m.leave();
            } else {
                i += 1;
            }
        }
    }
}

impl Member {
    /// Whether the member can take work: not cancelled, not finished, every frame it made
    /// already in the ring.
    fn runnable(&self) -> bool {
        self.outcome.is_none() && self.sent == self.out.len() && !self.shared.is_cancelled()
    }

    /// Pushes what the ring takes of the frames not yet in it; whether any went in.
    fn flush(&mut self) -> bool {
        if self.sent == self.out.len() {
            return false;
        }
        let mut n = self.prod.push_slice(&self.out[self.sent..]);
        if self.sent + n < self.out.len() {
            // Full: ask the host's next poll to unpark this shard (stream.rs wake-up
            // protocol), then look once more in case it polled in between.
            self.shared.request_room();
            n += self.prod.push_slice(&self.out[self.sent + n..]);
        }
        if n > 0 {
            self.shared.wake_consumer_if_waiting();
        }
        self.sent += n;
        if self.sent == self.out.len() {
            self.out.clear();
            self.sent = 0;
            // no more wake-ups needed from the host's polls
            self.shared.room_taken();
        }
        n > 0
    }

    /// Hands the frames `out[from..]` just made to the sink, then to the ring.
    fn produced(&mut self, from: usize) {
        if let Some(s) = self.sink.as_mut() {
            for f in &self.out[from..] {
                s.frame(f);
            }
        }
        self.made += (self.out.len() - from) as u64;
        self.flush();
    }

    /// A generation that ended with every frame in the ring is done.
    fn check_done(&mut self) {
        if self.outcome.is_none() && self.gen.need() == Need::Done && self.sent == self.out.len() {
            self.outcome = Some(Outcome::Ended);
        }
    }

    fn fail(&mut self, e: Error) {
        self.outcome.get_or_insert(Outcome::Failed(e));
    }

    /// Drops the generation and the ring's producer half, then publishes the outcome.
    fn leave(self) {
        let Member { gen, shared, prod, mut sink, set, outcome, .. } = self;
        drop(catch_unwind(AssertUnwindSafe(move || drop(gen))));
        drop(prod);
        finish(&shared, outcome.unwrap_or(Outcome::Cancelled), sink.as_deref_mut());
        set.worker_finished();
    }
}

/// The batched token step of `batch` (indices into `members`, each needing a step), then
/// each member samples its token.
fn step(members: &mut [Member], batch: &[usize], live: &AtomicUsize, scratch: &mut StepScratch) -> bool {
    batched::<MAX_BATCH>(
        members,
        batch,
        "batched step",
        |g| g.step_job().map(|_| ()),
        |members, good| {
            let pipe = Arc::clone(members[good[0]].gen.pipeline());
            let step = &pipe.bundle().step;
            // A lone stream on the whole scheduler: the step may use the model's helper thread.
            if good.len() == 1 && live.load(Ordering::Relaxed) == 1 {
                let j = members[good[0]].gen.job();
                step.run_checked(j.state, j.tokens, j.pos, j.text_emb, false)
            } else {
                step.step_batch_checked(&mut Jobs { members, idx: good }, scratch)
            }
        },
        |g, out| g.sampled(out),
    )
}

/// The batched decode of `batch` (indices into `members`, each needing a decode and
/// having made frames before), then each member's frames are assembled and pushed.
fn decode_batch(members: &mut [Member], batch: &[usize], scratch: &mut DecodeScratch) -> bool {
    batched::<MAX_DECODE_BATCH>(
        members,
        batch,
        "batched decode",
        |g| g.decode_job().map(|_| ()),
        |members, good| {
            let pipe = Arc::clone(members[good[0]].gen.pipeline());
            pipe.bundle().decoder.decode_batch_checked(&mut Decodes { members, idx: good }, scratch)
        },
        |g, out| {
            g.decoded(out);
            Ok(())
        },
    )
}

/// One batched piece of work for up to `N` of `batch`'s members: each is prepared
/// (`prepare`; one that fails, fails alone), `run` takes the good ones at once (an error
/// or panic there fails them all: their state is not to be trusted), then `after` gives
/// each member's frames. Whether anything ran. No allocation.
fn batched<const N: usize>(
    members: &mut [Member],
    batch: &[usize],
    what: &str,
    prepare: impl Fn(&mut Generator) -> Result<()>,
    run: impl FnOnce(&mut [Member], &[usize]) -> Result<()>,
    after: impl Fn(&mut Generator, &mut Vec<Frame>) -> Result<()>,
) -> bool {
    let mut good = [0usize; N];
    let mut ok = 0usize;
    for &i in batch.iter().take(N) {
        let m = &mut members[i];
        match catch_unwind(AssertUnwindSafe(|| prepare(&mut m.gen))) {
            Ok(Ok(())) => {
                good[ok] = i;
                ok += 1;
            }
            Ok(Err(e)) => m.fail(e),
            Err(p) => m.fail(Error::Panic(panic_message(&*p))),
        }
    }
    let good = &good[..ok];
    if good.is_empty() {
        return false;
    }
    let err = match catch_unwind(AssertUnwindSafe(|| run(members, good))) {
        Ok(Ok(())) => None,
        Ok(Err(e)) => Some(e),
        Err(p) => Some(Error::Panic(panic_message(&*p))),
    };
    for &i in good {
        let m = &mut members[i];
        if let Some(e) = &err {
            m.fail(Error::Inference(format!("{what}: {e}")));
            continue;
        }
        let from = m.out.len();
        match catch_unwind(AssertUnwindSafe(|| after(&mut m.gen, &mut m.out))) {
            Ok(Ok(())) => m.produced(from),
            Ok(Err(e)) => m.fail(e),
            Err(p) => m.fail(Error::Panic(panic_message(&*p))),
        }
    }
    true
}

/// The only stream on the whole scheduler: one call of the worker thread's loop
/// (`ChunkSource::next_chunk`: its steps and decode on the models' helper threads too, the
/// next steps overlapped with the decode), the same bits as a round's step and decode.
fn alone(m: &mut Member) -> bool {
    if !m.runnable() || m.gen.need() == Need::Done {
        return false;
    }
    let from = m.out.len();
    match catch_unwind(AssertUnwindSafe(|| m.gen.next_chunk(&mut m.out))) {
        Ok(Ok(_)) => m.produced(from),
        Ok(Err(e)) => m.fail(e),
        Err(p) => m.fail(Error::Panic(panic_message(&*p))),
    }
    true
}

/// The member's decode (or its end), its frames assembled and pushed.
fn decode(m: &mut Member, live: &AtomicUsize) -> bool {
    let team = live.load(Ordering::Relaxed) == 1;
    let from = m.out.len();
    let ran = catch_unwind(AssertUnwindSafe(|| match m.gen.need() {
        Need::Decode => m.gen.decode(team, &mut m.out),
        Need::Finish => {
            m.gen.finish(&mut m.out);
            Ok(())
        }
        _ => Ok(()),
    }));
    match ran {
        Ok(Ok(())) => m.produced(from),
        Ok(Err(e)) => m.fail(e),
        Err(p) => m.fail(Error::Panic(panic_message(&*p))),
    }
    true
}

/// The members of a batched step as the step model's jobs.
struct Jobs<'a> {
    members: &'a mut [Member],
    idx: &'a [usize],
}

impl StepJobs for Jobs<'_> {
    fn count(&self) -> usize {
        self.idx.len()
    }

    fn job(&mut self, i: usize) -> StepJob<'_> {
        self.members[self.idx[i]].gen.job()
    }
}

/// The members of a batched decode as the decoder's jobs.
struct Decodes<'a> {
    members: &'a mut [Member],
    idx: &'a [usize],
}

impl DecodeJobs for Decodes<'_> {
    fn count(&self) -> usize {
        self.idx.len()
    }

    fn job(&mut self, i: usize) -> DecodeJob<'_> {
        self.members[self.idx[i]].gen.decode_job_unchecked()
    }
}
