//! The engine side: one [`FramePublisher`] per engine with a publish name, shared by all its
//! stream workers; each worker owns a [`StreamPublication`] for its stream.
use std::fmt::Debug;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;

use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use parking_lot::Mutex;

use super::node::{create_node, open_services, shm_error, EventService, FrameService, Ipc};
use super::records::*;
use crate::error::Result;
use crate::frame::cg_frame;
use crate::stream::{StreamOutcome, StreamSink};

/// Counters of an engine's shared-memory publisher since the engine was created
/// (`cg_engine_publisher_stats`). Fixed layout.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct cg_publisher_stats {
    /// Frames published (each reaches every subscriber connected at that moment).
    pub frames_published: u64,
    /// Frames skipped because no shared-memory sample was free (never waited for;
    /// subscribers see the gap in the sequence and count it as dropped).
    pub frames_skipped: u64,
    /// Stream events published.
    pub events_published: u64,
    /// Stream events skipped (as `frames_skipped`).
    pub events_skipped: u64,
    /// Frame subscribers connected right now, in all processes.
    pub subscribers: u64,
}

pub type PublisherStats = cg_publisher_stats;

struct Port<T: Debug + ZeroCopySend + 'static> {
    publisher: Publisher<Ipc, T, cg_sample_header>,
    next_sequence: u64,
}

impl<T: Debug + ZeroCopySend + Copy + 'static> Port<T> {
    /// Loans, fills and sends one sample; never waits. The sequence number advances even
    /// when the sample is skipped, so subscribers count it as lost.
    fn send(&mut self, publisher_id: u64, value: &T) -> bool {
        let sequence = self.next_sequence;
        self.next_sequence += 1;
        let Ok(mut sample) = self.publisher.loan_uninit() else { return false };
        *sample.user_header_mut() = cg_sample_header { publisher_id, sequence };
        sample.write_payload(*value).send().is_ok()
    }
}

/// Publishes frames and stream events of one engine on `comgrasp/<name>/{frames,events}`.
pub struct FramePublisher {
    // Fields drop in order: ports before their services, services before the node.
    frames: Mutex<Port<cg_frame>>,
    events: Mutex<Port<cg_stream_event>>,
    frame_service: FrameService,
    _event_service: EventService,
    node: Mutex<Node<Ipc>>,
    id: u64,
    name: String,
    frames_published: AtomicU64,
    frames_skipped: AtomicU64,
    events_published: AtomicU64,
    events_skipped: AtomicU64,
}

impl FramePublisher {
    /// Opens (or creates) the services of `name` and a publisher on each.
    pub fn new(name: &str) -> Result<FramePublisher> {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let node = create_node()?;
        let (frame_service, event_service) = open_services(&node, name)?;
        let frames = frame_service
            .publisher_builder()
            .max_loaned_samples(1)
            .create()
            .map_err(|e| shm_error(&format!("creating the frame publisher of {name:?}"), e))?;
        let events = event_service
            .publisher_builder()
            .max_loaned_samples(1)
            .create()
            .map_err(|e| shm_error(&format!("creating the event publisher of {name:?}"), e))?;
        let id = (u64::from(std::process::id()) << 32) | u64::from(NEXT.fetch_add(1, Ordering::Relaxed));
        Ok(FramePublisher {
            frames: Mutex::new(Port { publisher: frames, next_sequence: 0 }),
            events: Mutex::new(Port { publisher: events, next_sequence: 0 }),
            frame_service,
            _event_service: event_service,
            node: Mutex::new(node),
            id,
            name: name.to_string(),
            frames_published: AtomicU64::new(0),
            frames_skipped: AtomicU64::new(0),
            events_published: AtomicU64::new(0),
            events_skipped: AtomicU64::new(0),
        })
    }

    /// The publish name (`<name>` of `comgrasp/<name>/frames`).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Publishes one frame. Never blocks on subscribers. One heap allocation: iceoryx2 0.10
    /// boxes a small shared state per loaned sample (tests/alloc_free_stream.rs counts it).
    pub fn publish_frame(&self, frame: &cg_frame) {
        let ok = self.frames.lock().send(self.id, frame);
        let counter = if ok { &self.frames_published } else { &self.frames_skipped };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Publishes one stream event.
    pub fn publish_event(&self, event: &cg_stream_event) {
        let ok = self.events.lock().send(self.id, event);
        let counter = if ok { &self.events_published } else { &self.events_skipped };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Reclaims what processes that died left in shared memory (their samples, their
    /// subscriber slots). Cheap enough per stream, not per frame.
    pub fn reclaim_dead(&self) {
        self.node.lock().try_cleanup_dead_nodes();
    }

    pub fn stats(&self) -> PublisherStats {
        PublisherStats {
            frames_published: self.frames_published.load(Ordering::Relaxed),
            frames_skipped: self.frames_skipped.load(Ordering::Relaxed),
            events_published: self.events_published.load(Ordering::Relaxed),
            events_skipped: self.events_skipped.load(Ordering::Relaxed),
            subscribers: self.frame_service.dynamic_config().number_of_subscribers() as u64,
        }
    }
}

/// What one stream's worker publishes: a STARTED event, every frame, and a final event.
pub(crate) struct StreamPublication {
    publisher: Arc<FramePublisher>,
    event: cg_stream_event,
}

impl StreamPublication {
    pub(crate) fn new(publisher: Arc<FramePublisher>, stream_id: u64, text: &str, fps: f32) -> Self {
        let mut event = cg_stream_event { stream_id, fps, ..Default::default() };
        event.set_text(text);
        StreamPublication { publisher, event }
    }
}

/// The engine attaches it to each stream of a publishing engine.
impl StreamSink for StreamPublication {
    fn started(&mut self) {
        self.publisher.reclaim_dead();
        self.event.kind = CG_STREAM_EVENT_STARTED;
        self.publisher.publish_event(&self.event);
    }

    fn frame(&mut self, frame: &cg_frame) {
        self.publisher.publish_frame(frame);
        self.event.frame_count += 1;
    }

    fn finished(&mut self, outcome: StreamOutcome) {
        self.event.kind = match outcome {
            StreamOutcome::Ended => CG_STREAM_EVENT_ENDED,
            StreamOutcome::Cancelled => CG_STREAM_EVENT_CANCELLED,
            StreamOutcome::Failed => CG_STREAM_EVENT_FAILED,
        };
        self.publisher.publish_event(&self.event);
    }
}
