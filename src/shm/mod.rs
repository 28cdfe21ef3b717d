//! Frames shared with other processes over iceoryx2 zero-copy shared memory.
//!
//! An engine created with a publish name `<name>` (`EngineConfig::publish_name`,
//! `cg_engine_config.publish_name`) offers two publish-subscribe services:
//!
//! * `comgrasp/<name>/frames`: every frame every stream of the engine generates, payload
//!   [`cg_frame`](crate::frame::cg_frame) exactly as `cg_poll_frame` returns it (stream id and
//!   frame index inside);
//! * `comgrasp/<name>/events`: one [`cg_stream_event`] when a stream starts, ends, is
//!   cancelled or fails.
//!
//! Why these settings (both services, [`records`]):
//! * **The producer never waits for a subscriber**: safe overflow is on, so a full subscriber
//!   buffer loses its *oldest* sample, on the subscriber's side only; a sample that cannot be
//!   loaned (a crashed subscriber still holding some) is skipped and counted, never waited for.
//! * **Drops are counted where they happen**: each sample carries a
//!   [`cg_sample_header`] with the publisher's id and a sequence number, so a subscriber
//!   counts exactly how many samples it lost.
//! * **No history**: a subscriber that joins late gets the frames from then on.
//! * **No signal handlers, no console noise** in the host's process: nodes are created with
//!   signal handling disabled and iceoryx2's log level is `Fatal` unless `IOX2_LOG_LEVEL` says
//!   otherwise.
//! * Resources of processes that died (a killed subscriber or publisher) are reclaimed
//!   whenever a publisher or subscriber is created and when a stream starts.
mod node;
pub mod publisher;
pub mod records;
pub mod subscriber;

pub use node::reclaim_dead_nodes;
pub use publisher::{cg_publisher_stats, FramePublisher, PublisherStats};
pub use records::*;
pub use subscriber::{cg_subscriber_stats, FrameSubscriber, SubscriberStats};
