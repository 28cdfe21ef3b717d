//! What travels through shared memory, and the service names. The payload and header types
//! are `#[repr(C)]` and carry a versioned iceoryx2 type name, so a process built against an
//! incompatible layout cannot connect (iceoryx2 also checks size and alignment).
use iceoryx2::prelude::ZeroCopySend;

use crate::error::{Error, Result};
use crate::frame::cg_frame;

/// `cg_stream_event.kind`: the stream started (its first frame follows).
pub const CG_STREAM_EVENT_STARTED: u32 = 1;
/// `cg_stream_event.kind`: the stream ended; `frame_count` frames were generated.
pub const CG_STREAM_EVENT_ENDED: u32 = 2;
/// `cg_stream_event.kind`: the stream was cancelled after `frame_count` frames.
pub const CG_STREAM_EVENT_CANCELLED: u32 = 3;
/// `cg_stream_event.kind`: the stream's worker failed after `frame_count` frames.
pub const CG_STREAM_EVENT_FAILED: u32 = 4;

/// Bytes of `cg_stream_event.text`, the terminating NUL included.
pub const CG_EVENT_TEXT_BYTES: usize = 256;

/// A stream's lifecycle record, published on `comgrasp/<name>/events`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct cg_stream_event {
    /// The stream's id (the `stream_id` of its frames).
    pub stream_id: u64,
    /// Frames the stream had generated when the event was sent (0 for STARTED; the total
    /// for ENDED).
    pub frame_count: u64,
    /// A `CG_STREAM_EVENT_*` value.
    pub kind: u32,
    /// Frames per second of the engine's model (`time_s = frame_index / fps`).
    pub fps: f32,
    /// The prompt, UTF-8, NUL-terminated, cut at a character boundary to at most 255 bytes.
    pub text: [u8; CG_EVENT_TEXT_BYTES],
}

impl Default for cg_stream_event {
    fn default() -> Self {
        cg_stream_event { stream_id: 0, frame_count: 0, kind: 0, fps: 0.0, text: [0; CG_EVENT_TEXT_BYTES] }
    }
}

impl cg_stream_event {
    /// The prompt as a string (up to the first NUL).
    pub fn text_str(&self) -> &str {
        let end = self.text.iter().position(|&b| b == 0).unwrap_or(CG_EVENT_TEXT_BYTES);
        // Written only by `set_text`, which cuts at a character boundary; a foreign writer
        // could put anything there, hence the lossless fallback to the valid prefix.
        match std::str::from_utf8(&self.text[..end]) {
            Ok(s) => s,
            Err(e) => std::str::from_utf8(&self.text[..e.valid_up_to()]).unwrap_or(""),
        }
    }

    /// Stores `text`, cut at a character boundary so it stays valid UTF-8.
    pub fn set_text(&mut self, text: &str) {
        let mut n = text.len().min(CG_EVENT_TEXT_BYTES - 1);
        while !text.is_char_boundary(n) {
            n -= 1;
        }
        self.text = [0; CG_EVENT_TEXT_BYTES];
        self.text[..n].copy_from_slice(&text.as_bytes()[..n]);
    }
}

/// The iceoryx2 user header of every sample: which publisher sent it and its place in that
/// publisher's sequence (0, 1, 2, ... per service), so a subscriber can count what it lost.
/// cbindgen:ignore
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct cg_sample_header {
    /// Unique per publisher (process id and a per-process counter).
    pub publisher_id: u64,
    /// Per publisher and service, starting at 0.
    pub sequence: u64,
}

// SAFETY (all three): plain `#[repr(C)]` data without pointers or references, valid in any
// process that maps it; the type names carry the layout version.
unsafe impl ZeroCopySend for cg_frame {
    unsafe fn type_name() -> &'static str {
        "comgrasp::cg_frame/1"
    }
}
unsafe impl ZeroCopySend for cg_stream_event {
    unsafe fn type_name() -> &'static str {
        "comgrasp::cg_stream_event/1"
    }
}
unsafe impl ZeroCopySend for cg_sample_header {
    unsafe fn type_name() -> &'static str {
        "comgrasp::cg_sample_header/1"
    }
}

/// Longest accepted publish name, in bytes.
pub const CG_MAX_PUBLISH_NAME_BYTES: usize = 64;

/// Most subscribers per service at once; one more gets `CG_ERR_LIMIT`.
/// cbindgen:ignore
pub const MAX_SUBSCRIBERS: usize = 8;
/// Most publishers per service at once (engines sharing a name, or a restarted publisher
/// whose predecessor's resources are not reclaimed yet).
/// cbindgen:ignore
pub const MAX_PUBLISHERS: usize = 4;
/// Largest subscriber buffer, in frames (~8.5 s at 30 fps). The shared memory a publisher
/// maps grows with `MAX_SUBSCRIBERS * MAX_SUBSCRIBER_BUFFER` frames (~3.3 MiB).
pub const CG_MAX_SUBSCRIBER_BUFFER: usize = 256;
/// Event buffer of every subscriber (events are rare: a few per stream).
/// cbindgen:ignore
pub const EVENT_BUFFER: usize = 64;

/// The two service names of a publish name, after checking it: 1..=64 bytes of ASCII
/// letters, digits, `_`, `-` and `.` (a name is also a file name in /dev/shm; no `/`).
pub fn service_names(name: &str) -> Result<(String, String)> {
    let ok = !name.is_empty()
        && name.len() <= CG_MAX_PUBLISH_NAME_BYTES
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.')
        && name != "."
        && name != "..";
    if !ok {
        return Err(Error::InvalidArgument(format!(
            "publish name {name:?} must be 1..={CG_MAX_PUBLISH_NAME_BYTES} bytes of ASCII letters, digits, '_', '-' and '.'"
        )));
    }
    Ok((format!("comgrasp/{name}/frames"), format!("comgrasp/{name}/events")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_checked() {
        assert_eq!(service_names("game-1.a_b").unwrap().0, "comgrasp/game-1.a_b/frames");
        assert_eq!(service_names("x").unwrap().1, "comgrasp/x/events");
        for bad in ["", "a/b", "a b", "..", "é", &"n".repeat(65)] {
            assert!(matches!(service_names(bad), Err(Error::InvalidArgument(_))), "{bad:?} accepted");
        }
        assert!(service_names(&"n".repeat(64)).is_ok());
    }

    #[test]
    fn event_text_is_cut_at_a_character_boundary() {
        let mut e = cg_stream_event::default();
        e.set_text("A woman drinks from the mug");
        assert_eq!(e.text_str(), "A woman drinks from the mug");
        let long = "é".repeat(200); // 400 bytes, 2 per character
        e.set_text(&long);
        assert_eq!(e.text_str().len(), 254);
        assert!(long.starts_with(e.text_str()));
        assert_eq!(e.text[255], 0);
        e.text[0] = 0xff; // not UTF-8: the valid prefix (empty) comes back, no panic
        assert_eq!(e.text_str(), "");
    }
}
