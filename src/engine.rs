//! The [`Engine`]: a loaded model bundle plus configuration, from which any number of
//! [`Stream`]s are started (each with its own worker thread and ring buffer).
//!
//! Ownership and lifetime (why it is safe to drop an engine with live streams):
//! * The engine owns the *source factory* (for the real pipeline: an `Arc` of the loaded
//!   bundle, its graphs and the frame assembler). Each stream's worker owns its own
//!   [`ChunkSource`] (KV caches, decoder state, sampler), which holds another `Arc` of the
//!   bundle, so workers never borrow from the engine.
//! * Streams and the engine share only a small [`StreamSet`] (ids, the live list, a worker
//!   count). Dropping the engine **cancels every stream that is still generating and waits
//!   until all workers have exited** (at most one generator call each: ~8 ms with the default
//!   bundle on 2 cores). So after
//!   `Engine::drop` returns, no inference runs and the bundle's memory is freed. The `Stream`
//!   objects stay valid and are freed by their owner: a cancelled one reports
//!   [`PollResult::Cancelled`](crate::stream::PollResult::Cancelled); one that had already
//!   finished still delivers its buffered frames and then `End`. This suits game engines: tearing down the engine stops all
//!   compute immediately, without forcing the host to destroy streams first.
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use parking_lot::{Condvar, Mutex};

use crate::bundle::Bundle;
use crate::error::{Error, Result};
use crate::frame::CoordinateSystem;
use crate::shm::publisher::StreamPublication;
use crate::shm::{FramePublisher, PublisherStats};
use crate::stream::{ChunkSource, Stream, StreamShared};

/// Longest accepted prompt, in UTF-8 bytes. (C: `CG_MAX_TEXT_BYTES`.)
/// cbindgen:ignore
pub const MAX_TEXT_BYTES: usize = 4096;
/// Largest accepted ring capacity, in frames (~1.6 KiB each).
/// cbindgen:ignore
pub const MAX_RING_CAPACITY: usize = 1 << 16;
/// Largest accepted `max_streams`.
/// cbindgen:ignore
pub const MAX_STREAMS_LIMIT: usize = 1024;

/// Engine-wide settings, fixed at creation.
#[derive(Clone, Debug, PartialEq)]
pub struct EngineConfig {
    /// The model bundle directory; a path given here always wins. `None` selects, in order:
    /// the directory in the `COMGRASP_BUNDLE` environment variable when it is set (set but
    /// empty or not a valid bundle: `Engine::new` fails, with no fallback); else the default
    /// bundle embedded in the library (cargo feature `embedded-default`, on by default), so
    /// an engine works from any working directory; else `Engine::new` fails with an
    /// [`Error::Bundle`] saying so. See [`crate::bundle::select`].
    pub bundle_path: Option<PathBuf>,
    /// Coordinate system of every frame.
    pub coordinate_system: CoordinateSystem,
    /// Fill `joint_positions` by forward kinematics on the bundle's skeleton.
    pub enable_fk: bool,
    /// Frames each stream buffers before its worker waits for the host to poll. 256 frames
    /// are ~8.5 s of motion at 30 fps; more only costs memory (~1.6 KiB per frame).
    pub ring_capacity: usize,
    /// Most streams alive at once (started and not yet dropped); `start` fails with
    /// [`Error::LimitReached`] beyond it. Bounds threads and memory.
    pub max_streams: usize,
    /// Sampling settings every stream inherits unless its own [`StreamConfig`] sets them;
    /// unset here too means the bundle's defaults.
    pub default_stream: StreamConfig,
    /// Also publish every frame and stream event over iceoryx2 shared memory on
    /// `comgrasp/<name>/frames` and `comgrasp/<name>/events` ([`crate::shm`]). `None`: no
    /// shared memory is touched.
    pub publish_name: Option<String>,
}

impl Default for EngineConfig {
    fn default() -> Self {
        EngineConfig {
            bundle_path: None,
            coordinate_system: CoordinateSystem::default(),
            enable_fk: false,
            ring_capacity: 256,
            max_streams: 16,
            default_stream: StreamConfig::default(),
            publish_name: None,
        }
    }
}

impl EngineConfig {
    fn validate(&self) -> Result<()> {
        if self.ring_capacity == 0 || self.ring_capacity > MAX_RING_CAPACITY {
            return Err(Error::InvalidArgument(format!(
                "ring_capacity must be 1..={MAX_RING_CAPACITY} frames, got {}",
                self.ring_capacity
            )));
        }
        if self.max_streams == 0 || self.max_streams > MAX_STREAMS_LIMIT {
            return Err(Error::InvalidArgument(format!(
                "max_streams must be 1..={MAX_STREAMS_LIMIT}, got {}",
                self.max_streams
            )));
        }
        if let Some(name) = &self.publish_name {
            crate::shm::service_names(name)?;
        }
        self.default_stream.validate()
    }
}

/// Per-stream sampling overrides. `None` = inherit (engine default, then bundle default).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StreamConfig {
    /// Seed of the SplitMix64 sampler. Unset = the bundle's default seed, so identical calls
    /// give identical motion; pass a seed for variety.
    pub seed: Option<u64>,
    /// Softmax temperature, >= 0 (0 = greedy).
    pub temperature: Option<f64>,
    /// Keep the k most likely tokens (0 = no top-k filtering).
    pub top_k: Option<u32>,
    /// End is forbidden before this many token steps.
    pub min_len: Option<u32>,
    /// End is forced at this many token steps (each step = 16 frames).
    pub max_len: Option<u32>,
}

impl StreamConfig {
    /// Fields set in `self` win; the rest come from `fallback`.
    pub fn or(&self, fallback: &StreamConfig) -> StreamConfig {
        StreamConfig {
            seed: self.seed.or(fallback.seed),
            temperature: self.temperature.or(fallback.temperature),
            top_k: self.top_k.or(fallback.top_k),
            min_len: self.min_len.or(fallback.min_len),
            max_len: self.max_len.or(fallback.max_len),
        }
    }

    /// Checks what can be checked without the bundle (the generator checks the rest, e.g.
    /// `max_len` against the bundle's L_max).
    pub fn validate(&self) -> Result<()> {
        if let Some(t) = self.temperature {
            if !t.is_finite() || t < 0.0 {
                return Err(Error::InvalidArgument(format!("temperature must be finite and >= 0, got {t}")));
            }
        }
        if let Some(m) = self.max_len {
            if m == 0 {
                return Err(Error::InvalidArgument("max_len must be at least 1".into()));
            }
        }
        if let (Some(lo), Some(hi)) = (self.min_len, self.max_len) {
            if lo > hi {
                return Err(Error::InvalidArgument(format!("min_len {lo} > max_len {hi}")));
            }
        }
        Ok(())
    }
}

/// What a [`SourceFactory`] gets for one new stream.
#[derive(Debug)]
pub struct StreamRequest<'a> {
    /// The new stream's id; every frame must carry it.
    pub stream_id: u64,
    /// The prompt, already validated (non-blank, at most [`MAX_TEXT_BYTES`]).
    pub text: &'a str,
    /// The stream's settings merged with the engine defaults (bundle defaults not applied).
    pub config: &'a StreamConfig,
}

/// Builds the [`ChunkSource`] of a new stream. Runs on the thread that calls
/// [`Engine::start`], so it should only set up state (cheap); heavy work (text encoding,
/// token steps) belongs in `next_chunk`, on the worker.
pub type SourceFactory = Box<dyn Fn(&StreamRequest<'_>) -> Result<Box<dyn ChunkSource>> + Send + Sync>;

/// Checks a prompt: non-empty, not only whitespace, at most [`MAX_TEXT_BYTES`] bytes.
pub fn validate_text(text: &str) -> Result<()> {
    if text.len() > MAX_TEXT_BYTES {
        return Err(Error::InvalidArgument(format!("text is {} bytes, the limit is {MAX_TEXT_BYTES}", text.len())));
    }
    if text.trim().is_empty() {
        return Err(Error::InvalidArgument("text is empty or only whitespace".into()));
    }
    Ok(())
}

/// A loaded model and its settings. `Send + Sync`: share it (e.g. in an `Arc`) and start
/// streams from any thread.
pub struct Engine {
    config: EngineConfig,
    bundle: Option<Arc<Bundle>>,
    factory: SourceFactory,
    streams: Arc<StreamSet>,
    publisher: Option<Arc<FramePublisher>>,
}

impl Engine {
    /// Loads the bundle named by `config.bundle_path` (verifying every file) and prepares
    /// the graphs once, so starting a stream is cheap.
    pub fn new(config: EngineConfig) -> Result<Engine> {
        config.validate()?;
        let (bundle, factory) = crate::generator::source_factory(&config)?;
        Engine::from_parts(config, Some(bundle), factory)
    }

    /// An engine whose streams come from `factory` instead of a bundle. For tests and
    /// tools; `config.bundle_path` is ignored.
    #[doc(hidden)]
    pub fn with_source_factory(config: EngineConfig, factory: SourceFactory) -> Result<Engine> {
        config.validate()?;
        Engine::from_parts(config, None, factory)
    }

    fn from_parts(config: EngineConfig, bundle: Option<Arc<Bundle>>, factory: SourceFactory) -> Result<Engine> {
        let streams = Arc::new(StreamSet::new(config.max_streams));
        let publisher = match &config.publish_name {
            Some(name) => Some(Arc::new(FramePublisher::new(name)?)),
            None => None,
        };
        Ok(Engine { config, bundle, factory, streams, publisher })
    }

    /// The loaded bundle (manifest: fps, skeleton, object catalogue; files such as the
    /// object meshes through [`Bundle::file_bytes`]). `None` for a test engine built with
    /// [`Engine::with_source_factory`].
    pub fn bundle(&self) -> Option<&Arc<Bundle>> {
        self.bundle.as_ref()
    }

    /// The configuration the engine was created with.
    pub fn config(&self) -> &EngineConfig {
        &self.config
    }

    /// Shared-memory publishing counters; `None` without a publish name.
    pub fn publisher_stats(&self) -> Option<PublisherStats> {
        self.publisher.as_ref().map(|p| p.stats())
    }

    /// Streams alive right now (started and not yet dropped).
    pub fn live_streams(&self) -> usize {
        self.streams.live.lock().len()
    }

    /// Starts generating motion for `text` on a new worker thread and returns at once.
    /// Errors: invalid text or settings (`InvalidArgument`), too many live streams
    /// (`LimitReached`), whatever the source factory reports, or a failed thread spawn (`Io`).
    pub fn start(&self, text: &str, opts: StreamConfig) -> Result<Stream> {
        validate_text(text)?;
        opts.validate()?;
        let config = opts.or(&self.config.default_stream);
        config.validate()?;

        let id = self.streams.next_id.fetch_add(1, Ordering::Relaxed);
        let shared = Arc::new(StreamShared::new(id));
        let reservation = self.streams.reserve(&shared)?;
        let request = StreamRequest { stream_id: id, text, config: &config };
        let source = (self.factory)(&request)?;
        let publication = self.publisher.as_ref().map(|p| {
            let fps = self.bundle.as_ref().map_or(0.0, |b| b.manifest.fps as f32);
            StreamPublication::new(Arc::clone(p), id, text, fps)
        });
        let stream = Stream::spawn(shared, source, self.config.ring_capacity, Arc::clone(&self.streams), publication)?;
        // From here on the stream removes itself from the set when it is dropped.
        reservation.keep();
        Ok(stream)
    }
}

impl Drop for Engine {
    fn drop(&mut self) {
        self.streams.shutdown();
    }
}

/// The part of the engine that streams share: id counter, live list, worker count.
pub(crate) struct StreamSet {
    next_id: AtomicU64,
    max: usize,
    /// Small (at most `max_streams`), so a Vec with linear removal is the simplest fit.
    live: Mutex<Vec<Arc<StreamShared>>>,
    workers: Mutex<usize>,
    workers_idle: Condvar,
}

impl StreamSet {
    fn new(max: usize) -> Self {
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
    fn reserve<'a>(self: &'a Arc<Self>, shared: &Arc<StreamShared>) -> Result<Reservation<'a>> {
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
    fn shutdown(&self) {
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

struct Reservation<'a> {
    set: &'a StreamSet,
    id: u64,
    armed: bool,
}

impl Reservation<'_> {
    fn keep(mut self) {
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
