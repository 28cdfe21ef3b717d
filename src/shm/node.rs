//! The iceoryx2 node every publisher and subscriber of this library uses, and the two
//! services, opened or created with identical settings on both sides (iceoryx2 refuses to
//! open a service whose settings disagree).
use std::fmt::Debug;
use std::sync::Once;

use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;

use super::records::*;
use crate::error::{Error, Result};
use crate::frame::cg_frame;

/// Thread-safe flavour: a publisher is shared by all stream workers of an engine, and C
/// hosts may move a subscriber between threads.
pub(crate) type Ipc = ipc_threadsafe::Service;
pub(crate) type FrameService = PortFactory<Ipc, cg_frame, cg_sample_header>;
pub(crate) type EventService = PortFactory<Ipc, cg_stream_event, cg_sample_header>;

pub(crate) fn shm_error(what: &str, e: impl Debug) -> Error {
    Error::SharedMemory(format!("{what}: {e:?}"))
}

/// A node that installs no signal handler (the host owns its signals) and a quiet logger.
/// Dead nodes (processes killed without cleaning up) are reclaimed first, so a restarted
/// publisher or subscriber finds their slots and memory free again.
pub(crate) fn create_node() -> Result<Node<Ipc>> {
    static QUIET: Once = Once::new();
    QUIET.call_once(|| set_log_level_from_env_or(LogLevel::Fatal));
    let node = NodeBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| shm_error("creating the iceoryx2 node", e))?;
    node.try_cleanup_dead_nodes();
    Ok(node)
}

/// What processes that died without cleaning up (killed publishers or subscribers) left in
/// shared memory, reclaimed now: `(nodes cleaned, nodes that could not be)`. Publishers and
/// subscribers do this by themselves when they are created and when a stream starts; this
/// is for tools (`comgrasp shm-clean`) and tests.
pub fn reclaim_dead_nodes() -> Result<(u64, u64)> {
    let node = create_node()?;
    let state = node.try_cleanup_dead_nodes();
    Ok((state.cleanups, state.failed_cleanups))
}

fn service_name(name: &str) -> Result<ServiceName> {
    name.try_into().map_err(|e| shm_error(&format!("service name {name:?}"), e))
}

/// Opens or creates `comgrasp/<name>/frames` and `comgrasp/<name>/events`.
pub(crate) fn open_services(node: &Node<Ipc>, publish_name: &str) -> Result<(FrameService, EventService)> {
    let (frames_name, events_name) = service_names(publish_name)?;
    Ok((open_service(node, &frames_name, CG_MAX_SUBSCRIBER_BUFFER)?, open_service(node, &events_name, EVENT_BUFFER)?))
}

fn open_service<T: Debug + ZeroCopySend>(
    node: &Node<Ipc>,
    name: &str,
    max_buffer: usize,
) -> Result<PortFactory<Ipc, T, cg_sample_header>> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<T>()
        .user_header::<cg_sample_header>()
        .enable_safe_overflow(true)
        .history_size(0)
        .subscriber_max_buffer_size(max_buffer)
        // Samples are copied out and released at once.
        .subscriber_max_borrowed_samples(1)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_publishers(MAX_PUBLISHERS)
        .open_or_create()
        .map_err(|e| shm_error(&format!("opening service {name}"), e))
}
