//! Validated handles (SDL3's `SDL_ObjectValid` idea, with generations against address reuse).
//!
//! A `cg_engine*` or `cg_stream*` is **not** a pointer to memory: its value encodes
//! `(generation, slot index, type tag)` and is resolved through a global registry on every
//! call. It is never dereferenced, so a destroyed, double-destroyed, forged, foreign or
//! wrong-type handle is detected and reported as `CG_ERR_INVALID_HANDLE` instead of causing
//! undefined behaviour. Layout of the value (low bits first): 4-bit tag (odd, so no aligned
//! real pointer ever matches), slot index, generation (never 0). A slot's generation grows
//! on every destroy, so an old handle never names the new object in a reused slot; a slot
//! whose generation would wrap is retired instead of reused.
//!
//! Lookups take a read lock (shared, uncontended in practice) and clone an `Arc`; neither
//! allocates. Creating and destroying take the write lock briefly; the object itself is
//! dropped outside the lock.
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use parking_lot::{Mutex, RwLock};

use crate::engine::Engine;
use crate::stream::{Stream, StreamCanceller};

/// Opaque handle to an engine (a loaded model bundle and its settings). Create with
/// `cg_engine_create`, destroy with `cg_engine_destroy`. Never dereference it.
pub struct cg_engine {
    _private: [u8; 0],
}

/// Opaque handle to a stream (one generation). Create with `cg_start`, destroy with
/// `cg_stream_destroy`. Never dereference it.
pub struct cg_stream {
    _private: [u8; 0],
}

/// Opaque handle to a shared-memory subscriber. Create with `cg_subscriber_open`, destroy
/// with `cg_subscriber_close`. Never dereference it.
pub struct cg_subscriber {
    _private: [u8; 0],
}

const TAG_BITS: u32 = 4;
const TAG_MASK: usize = (1 << TAG_BITS) - 1;
#[cfg(target_pointer_width = "64")]
const INDEX_BITS: u32 = 28;
#[cfg(target_pointer_width = "64")]
const GEN_BITS: u32 = 32;
#[cfg(not(target_pointer_width = "64"))]
const INDEX_BITS: u32 = 12;
#[cfg(not(target_pointer_width = "64"))]
const GEN_BITS: u32 = 16;
const INDEX_MASK: usize = (1 << INDEX_BITS) - 1;
const GEN_MAX: u64 = (1u64 << GEN_BITS) - 1;

/// Tag of engine handles.
pub(crate) const TAG_ENGINE: usize = 0x5;
/// Tag of stream handles.
pub(crate) const TAG_STREAM: usize = 0x9;
/// Tag of subscriber handles.
pub(crate) const TAG_SUBSCRIBER: usize = 0xD;
/// Tag of `cg_retargeter` handles.
pub(crate) const TAG_RETARGETER: usize = 0xB;

struct Slot<T> {
    generation: u64,
    value: Option<Arc<T>>,
}

struct Slots<T> {
    slots: Vec<Slot<T>>,
    free: Vec<usize>,
}

/// A registry of live objects of one type.
pub(crate) struct Registry<T> {
    tag: usize,
    inner: RwLock<Slots<T>>,
}

impl<T> Registry<T> {
    pub(crate) const fn new(tag: usize) -> Self {
        Registry { tag, inner: parking_lot::const_rwlock(Slots { slots: Vec::new(), free: Vec::new() }) }
    }

    fn encode(&self, index: usize, generation: u64) -> usize {
        ((generation as usize) << (TAG_BITS + INDEX_BITS)) | (index << TAG_BITS) | self.tag
    }

    fn decode(&self, handle: usize) -> Option<(usize, u64)> {
        if handle & TAG_MASK != self.tag {
            return None;
        }
        let index = (handle >> TAG_BITS) & INDEX_MASK;
        let generation = (handle >> (TAG_BITS + INDEX_BITS)) as u64;
        Some((index, generation))
    }

    /// Registers `value`; `None` when every slot is in use or retired.
    pub(crate) fn insert(&self, value: Arc<T>) -> Option<usize> {
        let mut inner = self.inner.write();
        let index = match inner.free.pop() {
            Some(i) => i,
            None => {
                let i = inner.slots.len();
                if i > INDEX_MASK {
                    return None;
                }
                inner.slots.push(Slot { generation: 1, value: None });
                i
            }
        };
        let slot = &mut inner.slots[index];
        slot.value = Some(value);
        Some(self.encode(index, slot.generation))
    }

    /// The live object behind `handle`, if it is one of ours.
    pub(crate) fn get(&self, handle: usize) -> Option<Arc<T>> {
        let (index, generation) = self.decode(handle)?;
        let inner = self.inner.read();
        let slot = inner.slots.get(index)?;
        if slot.generation != generation {
            return None;
        }
        slot.value.clone()
    }

    /// Unregisters `handle` and returns its object; `None` if it was not live (so a second
    /// destroy fails cleanly).
    pub(crate) fn remove(&self, handle: usize) -> Option<Arc<T>> {
        let (index, generation) = self.decode(handle)?;
        let mut inner = self.inner.write();
        let slot = inner.slots.get_mut(index)?;
        if slot.generation != generation {
            return None;
        }
        let value = slot.value.take()?;
        if slot.generation < GEN_MAX {
            slot.generation += 1;
            inner.free.push(index);
        } // else: retire the slot rather than let its generation wrap.
        Some(value)
    }
}

/// The registry's view of an engine.
pub(crate) struct EngineEntry {
    pub(crate) engine: Engine,
    pub(crate) poisoned: AtomicBool,
}

/// The registry's view of a stream. The canceller lives outside the mutex so `cg_cancel`
/// works while another thread is inside `cg_stream_wait`.
pub(crate) struct StreamEntry {
    pub(crate) id: u64,
    /// Immutable after `cg_start`: read by `cg_stream_get_info` from any thread.
    pub(crate) object: Option<crate::stream::StreamObject>,
    pub(crate) canceller: StreamCanceller,
    pub(crate) stream: Mutex<Stream>,
    pub(crate) poisoned: AtomicBool,
}

/// The registry's view of a shared-memory subscriber (one thread at a time: `try_lock`).
pub(crate) struct SubscriberEntry {
    pub(crate) subscriber: Mutex<crate::shm::FrameSubscriber>,
    pub(crate) poisoned: AtomicBool,
}

pub(crate) static ENGINES: Registry<EngineEntry> = Registry::new(TAG_ENGINE);
pub(crate) static SUBSCRIBERS: Registry<SubscriberEntry> = Registry::new(TAG_SUBSCRIBER);
pub(crate) static STREAMS: Registry<StreamEntry> = Registry::new(TAG_STREAM);

/// Registers an engine built in Rust (e.g. [`Engine::with_source_factory`] in tests) and
/// returns its C handle, to be destroyed with `cg_engine_destroy`. Not part of the C ABI.
#[doc(hidden)]
pub fn engine_into_handle(engine: Engine) -> Option<*mut cg_engine> {
    let entry = Arc::new(EngineEntry { engine, poisoned: AtomicBool::new(false) });
    ENGINES.insert(entry).map(|h| h as *mut cg_engine)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stale_double_and_foreign_handles_are_rejected() {
        let reg: Registry<u32> = Registry::new(TAG_STREAM);
        let a = reg.insert(Arc::new(1)).unwrap();
        assert_eq!(*reg.get(a).unwrap(), 1);
        assert!(reg.remove(a).is_some());
        assert!(reg.remove(a).is_none(), "double remove");
        assert!(reg.get(a).is_none(), "use after remove");
        let b = reg.insert(Arc::new(2)).unwrap();
        assert_ne!(a, b, "slot reuse must change the handle");
        assert!(reg.get(a).is_none());
        assert_eq!(*reg.get(b).unwrap(), 2);
        // A real (aligned) pointer and a handle of the other type are not ours.
        let boxed = Box::new(0u64);
        assert!(reg.get(&*boxed as *const u64 as usize).is_none());
        let other: Registry<u32> = Registry::new(TAG_ENGINE);
        let e = other.insert(Arc::new(3)).unwrap();
        assert!(reg.get(e).is_none());
        assert!(reg.get(0).is_none());
        assert!(reg.get(usize::MAX).is_none());
    }
}
