//! The [`Engine`]: a loaded model bundle plus configuration, from which any number of
//! [`Stream`]s are started, each with its own ring buffer; their generations run on the
//! engine's crowd scheduler ([`crate::crowd`], the default) or on a worker thread each
//! (`RuntimeOptions::scheduling`; an engine of [`Engine::with_source_factory`] always uses
//! worker threads). Below, "worker" is either.
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
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use crate::config::Scheduling;
use crate::crowd::Scheduler;
use crate::error::{Error, Result};
use crate::frame::{Frame, CG_NUM_JOINTS};
use crate::generator::{ChunkSource, Generator, Pipeline};
use crate::model::Bundle;
use crate::shm::publisher::StreamPublication;
use crate::shm::{FramePublisher, PublisherStats};
use crate::stream::{Stream, StreamSet, StreamShared, StreamSink};

pub use crate::config::{EngineConfig, StreamConfig, MAX_RING_CAPACITY, MAX_STREAMS_LIMIT, MAX_TEXT_BYTES};
pub use crate::generator::{SourceFactory, StreamRequest};

/// The config's ranges and its publish name, before anything is loaded.
fn validate(config: &EngineConfig) -> Result<()> {
    config.validate()?;
    if let Some(name) = &config.publish_name {
        crate::shm::service_names(name)?;
    }
    Ok(())
}

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
    /// The crowd scheduler and the pipeline its generations run on (`None`: a worker
    /// thread per stream).
    crowd: Option<(Scheduler, Arc<Pipeline>)>,
}

impl Engine {
    /// Loads the bundle named by `config.bundle_path` (verifying every file) and prepares
    /// the graphs once, so starting a stream is cheap.
    pub fn new(config: EngineConfig) -> Result<Engine> {
        validate(&config)?;
        let (pipeline, factory) = crate::generator::source_factory(&config)?;
        let mut engine = Engine::from_parts(config, Some(Arc::clone(pipeline.bundle())), factory)?;
        let r = &engine.config.runtime;
        if r.scheduling != Scheduling::PerStream {
            let threads = r.scheduler_threads.unwrap_or_else(crate::crowd::default_threads);
            engine.crowd = Some((Scheduler::new(&pipeline, threads, engine.config.max_streams)?, pipeline));
        }
        Ok(engine)
    }

    /// An engine whose streams come from `factory` instead of a bundle. For tests and
    /// tools; `config.bundle_path` is ignored.
    #[doc(hidden)]
    pub fn with_source_factory(config: EngineConfig, factory: SourceFactory) -> Result<Engine> {
        validate(&config)?;
        Engine::from_parts(config, None, factory)
    }

    fn from_parts(config: EngineConfig, bundle: Option<Arc<Bundle>>, factory: SourceFactory) -> Result<Engine> {
        let streams = Arc::new(StreamSet::new(config.max_streams));
        let publisher = match &config.publish_name {
            Some(name) => Some(Arc::new(FramePublisher::new(name)?)),
            None => None,
        };
        Ok(Engine { config, bundle, factory, streams, publisher, crowd: None })
    }

    /// The loaded bundle (manifest: fps, skeleton, object catalogue; files such as the
    /// object meshes through [`Bundle::file_bytes`]). `None` for a test engine built with
    /// [`Engine::with_source_factory`].
    pub fn bundle(&self) -> Option<&Arc<Bundle>> {
        self.bundle.as_ref()
    }

    /// The bundle's rest skeleton (SMPL-X joint order) in the engine's coordinate system
    /// and units: the rest pose a host's skeleton must have for the frames' local rotations
    /// to mean the same motion, and what [`crate::retarget::Retargeter`] transfers from.
    /// `None` for a test engine without a bundle.
    pub fn rest_joints(&self) -> Option<[[f32; 3]; CG_NUM_JOINTS]> {
        let rest = &self.bundle.as_ref()?.manifest.skeleton.rest_joints;
        let coords = self.config.coordinate_system;
        Some(std::array::from_fn(|j| coords.from_native_point(&rest[j].map(f64::from)).map(|v| v as f32)))
    }

    /// Writes `frames` (this engine's, in its coordinate system) as BVH: the body to
    /// `body_path` and, when given, the object's track to `object_path` (see [`crate::bvh`]).
    /// Errors: an engine without a bundle (`WrongState`), a non-finite frame value
    /// (`InvalidArgument`), a file that cannot be written (`Io`). Nothing is written unless
    /// both texts could be made.
    pub fn write_bvh(&self, frames: &[Frame], body_path: &Path, object_path: Option<&Path>) -> Result<()> {
        let b = self.bundle.as_ref().ok_or_else(|| Error::WrongState("the engine has no model bundle".into()))?;
        let r = &b.manifest.skeleton.rest_joints;
        let rest: [[f32; 3]; CG_NUM_JOINTS] = std::array::from_fn(|j| r[j]);
        let (coords, fps) = (self.config.coordinate_system, b.manifest.fps);
        let body = crate::bvh::body(&rest, frames, coords, fps)?;
        let object = object_path.map(|_| crate::bvh::object(frames, coords, fps)).transpose()?;
        std::fs::write(body_path, body)?;
        if let (Some(path), Some(text)) = (object_path, object) {
            std::fs::write(path, text)?;
        }
        Ok(())
    }

    /// The configuration the engine was created with.
    pub fn config(&self) -> &EngineConfig {
        &self.config
    }

    /// Shared-memory publishing counters; `None` without a publish name.
    pub fn publisher_stats(&self) -> Option<PublisherStats> {
        self.publisher.as_ref().map(|p| p.stats())
    }

    /// Threads of the crowd scheduler; `None` when each stream has its own worker thread.
    pub fn scheduler_threads(&self) -> Option<usize> {
        self.crowd.as_ref().map(|(s, _)| s.threads())
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
        let sink = self.publisher.as_ref().map(|p| -> Box<dyn StreamSink> {
            let fps = self.bundle.as_ref().map_or(0.0, |b| b.manifest.fps as f32);
            Box::new(StreamPublication::new(Arc::clone(p), id, text, fps))
        });
        let (ring, set) = (self.config.ring_capacity, Arc::clone(&self.streams));
        let (mut stream, object) = match &self.crowd {
            Some((scheduler, pipeline)) => {
                let gen = Generator::new(Arc::clone(pipeline), &request)?;
                let object = gen.object();
                (scheduler.start(gen, shared, ring, set, sink)?, object)
            }
            None => {
                let source = (self.factory)(&request)?;
                let object = source.object();
                (Stream::spawn(shared, source, ring, set, sink)?, object)
            }
        };
        stream.set_object(object);
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
