//! Version and layout queries, so a binding can refuse to run against a stale library
//! (the usual Unity failure: an old DLL left in `Assets/Plugins`).
use std::ffi::c_char;

use super::panic::boundary_value;
use crate::frame::cg_frame;

/// Version of the C ABI. Bumped on any incompatible change (a struct layout, a function
/// signature, a status value's meaning). Compare with `cg_abi_version()` at startup.
pub const CG_ABI_VERSION: u32 = 1;

/// Longest accepted prompt, in UTF-8 bytes (excluding the terminating NUL).
pub const CG_MAX_TEXT_BYTES: u32 = 4096;
// A literal above so cbindgen can emit it; kept equal to the engine's limit here.
const _: () = assert!(CG_MAX_TEXT_BYTES as usize == crate::engine::MAX_TEXT_BYTES);
// The frame layout is ABI: any change must bump CG_ABI_VERSION (and this number).
const _: () = assert!(std::mem::size_of::<cg_frame>() == 1608);

/// The library's `CG_ABI_VERSION`. A host compiled against a header with a different value
/// must not use this library. Any thread.
#[no_mangle]
pub extern "C" fn cg_abi_version() -> u32 {
    boundary_value("cg_abi_version", || CG_ABI_VERSION)
}

/// The library's version ("MAJOR.MINOR.PATCH"), a static NUL-terminated string that lives
/// for the whole program; do not free it. Any thread.
#[no_mangle]
pub extern "C" fn cg_version_string() -> *const c_char {
    boundary_value("cg_version_string", || concat!(env!("CARGO_PKG_VERSION"), "\0").as_ptr() as *const c_char)
}

/// `sizeof(cg_frame)` as the library sees it; a binding compares it with its own
/// struct size (C# `Marshal.SizeOf<CgFrame>()`) to detect a layout mismatch. Any thread.
#[no_mangle]
pub extern "C" fn cg_frame_size() -> usize {
    boundary_value("cg_frame_size", std::mem::size_of::<cg_frame>)
}
