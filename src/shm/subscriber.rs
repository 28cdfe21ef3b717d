//! The consumer side, for processes that read an engine's frames without running it.
use std::fmt::Debug;

use iceoryx2::port::subscriber::{Subscriber, SubscriberCreateError};
use iceoryx2::prelude::*;

use super::node::{create_node, open_services, shm_error, EventService, FrameService, Ipc};
use super::records::*;
use crate::error::{Error, Result};
use crate::frame::cg_frame;

/// Counters of a subscriber since it was opened (`cg_subscriber_get_stats`). Fixed layout.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct cg_subscriber_stats {
    /// Frames received.
    pub frames_received: u64,
    /// Frames lost: overwritten in this subscriber's full buffer (it read too slowly) or
    /// skipped by the publisher. Counted from gaps in each publisher's sequence numbers,
    /// so from the first frame received from that publisher on: a loss before it cannot be
    /// told from frames sent before the subscriber joined.
    pub frames_dropped: u64,
    /// Stream events received.
    pub events_received: u64,
    /// Stream events lost (as `frames_dropped`).
    pub events_dropped: u64,
    /// Times the frames came from a different publisher than the one before (a publisher
    /// restarted, or several engines publish under one name).
    pub publisher_changes: u64,
    /// Frame publishers connected to the service right now.
    pub publishers: u64,
}

pub type SubscriberStats = cg_subscriber_stats;

/// Counts lost samples from the (publisher, sequence) header of each received one.
#[derive(Default)]
struct SequenceTracker {
    publisher: u64,
    expected: u64,
    received: u64,
    dropped: u64,
    publisher_changes: u64,
}

impl SequenceTracker {
    fn see(&mut self, h: &cg_sample_header) {
        self.received += 1;
        if h.publisher_id == self.publisher {
            // Older than expected cannot happen with one publisher (its sequence only
            // grows); ignore rather than count a negative gap.
            self.dropped = self.dropped.saturating_add(h.sequence.saturating_sub(self.expected));
        } else if self.publisher != 0 {
            // A new publisher: what it sent before we saw it is not ours to count.
            self.publisher_changes += 1;
        }
        self.publisher = h.publisher_id;
        // Wrapping: a header is written by another process and may hold any value.
        self.expected = h.sequence.wrapping_add(1);
    }
}

/// Receives the frames and events an engine publishes under a name. Opening works before
/// the publisher exists and survives publisher restarts; frames arrive from the moment of
/// opening on (no history).
pub struct FrameSubscriber {
    // Fields drop in order: ports before their services, services before the node.
    frames: Subscriber<Ipc, cg_frame, cg_sample_header>,
    events: Subscriber<Ipc, cg_stream_event, cg_sample_header>,
    frame_service: FrameService,
    _event_service: EventService,
    _node: Node<Ipc>,
    frame_seq: SequenceTracker,
    event_seq: SequenceTracker,
}

fn create_error(what: &str, name: &str, e: SubscriberCreateError) -> Error {
    match e {
        SubscriberCreateError::ExceedsMaxSupportedSubscribers => Error::LimitReached(format!(
            "{name:?} already has {MAX_SUBSCRIBERS} subscribers (the most a service allows)"
        )),
        e => shm_error(&format!("creating the {what} subscriber of {name:?}"), e),
    }
}

impl FrameSubscriber {
    /// `buffer_frames` (1..=`CG_MAX_SUBSCRIBER_BUFFER`): frames kept for this subscriber
    /// between two reads; beyond it the oldest are overwritten (and counted as dropped).
    pub fn open(name: &str, buffer_frames: usize) -> Result<FrameSubscriber> {
        if buffer_frames == 0 || buffer_frames > CG_MAX_SUBSCRIBER_BUFFER {
            return Err(Error::InvalidArgument(format!(
                "buffer_frames must be 1..={CG_MAX_SUBSCRIBER_BUFFER}, got {buffer_frames}"
            )));
        }
        let node = create_node()?;
        let (frame_service, event_service) = open_services(&node, name)?;
        let frames = frame_service
            .subscriber_builder()
            .buffer_size(buffer_frames)
            .create()
            .map_err(|e| create_error("frame", name, e))?;
        let events = event_service
            .subscriber_builder()
            .buffer_size(EVENT_BUFFER)
            .create()
            .map_err(|e| create_error("event", name, e))?;
        Ok(FrameSubscriber {
            frames,
            events,
            frame_service,
            _event_service: event_service,
            _node: node,
            frame_seq: SequenceTracker::default(),
            event_seq: SequenceTracker::default(),
        })
    }

    /// Copies the oldest unread frame into `out` and returns true, or returns false when
    /// there is none. Never blocks.
    pub fn receive(&mut self, out: &mut cg_frame) -> Result<bool> {
        receive_into(&self.frames, &mut self.frame_seq, out)
    }

    /// Copies the oldest unread stream event into `out` and returns true, or false when
    /// there is none. Never blocks.
    pub fn receive_event(&mut self, out: &mut cg_stream_event) -> Result<bool> {
        receive_into(&self.events, &mut self.event_seq, out)
    }

    pub fn stats(&self) -> SubscriberStats {
        SubscriberStats {
            frames_received: self.frame_seq.received,
            frames_dropped: self.frame_seq.dropped,
            events_received: self.event_seq.received,
            events_dropped: self.event_seq.dropped,
            publisher_changes: self.frame_seq.publisher_changes,
            publishers: self.frame_service.dynamic_config().number_of_publishers() as u64,
        }
    }
}

fn receive_into<T: Debug + ZeroCopySend + Copy + 'static>(
    port: &Subscriber<Ipc, T, cg_sample_header>,
    seq: &mut SequenceTracker,
    out: &mut T,
) -> Result<bool> {
    match port.receive() {
        Ok(Some(sample)) => {
            seq.see(sample.user_header());
            *out = *sample.payload();
            Ok(true)
        }
        Ok(None) => Ok(false),
        Err(e) => Err(shm_error("receiving", e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_are_counted_per_publisher() {
        let mut t = SequenceTracker::default();
        let h = |publisher_id, sequence| cg_sample_header { publisher_id, sequence };
        t.see(&h(7, 100)); // late join: nothing before 100 is ours
        t.see(&h(7, 101));
        t.see(&h(7, 105)); // 102..=104 lost
        assert_eq!((t.received, t.dropped, t.publisher_changes), (3, 3, 0));
        t.see(&h(9, 0)); // publisher restarted
        t.see(&h(9, 1));
        assert_eq!((t.received, t.dropped, t.publisher_changes), (5, 3, 1));
        // Hostile headers (any process of the user can write one) never overflow.
        t.see(&h(9, u64::MAX));
        t.see(&h(9, u64::MAX));
        t.see(&h(9, 0));
        assert_eq!(t.dropped, u64::MAX);
    }
}
