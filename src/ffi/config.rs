//! Versioned configuration structs (SDL3 / sherpa-onnx style): each starts with
//! `struct_size`, an `_init` function fills it and every default, fields are only ever
//! appended, and the library reads only the first `struct_size` bytes. So a host compiled
//! against an older header keeps working with a newer library (missing fields take their
//! defaults), and a newer host works with an older library (unknown trailing fields are
//! ignored).
use std::ffi::{c_char, CStr};
use std::mem::{size_of, MaybeUninit};
use std::path::PathBuf;

use super::panic::{boundary, Failure};
use super::status::cg_status;
use crate::config::{Anchor, Placement};
use crate::config::{DecoderBackend, InstructionSet, RuntimeOptions, Scheduling, StepBackend};
use crate::engine::{EngineConfig, StreamConfig};
use crate::frame::{cg_coordinate_system, CoordinateSystem};

/// Settings of a new engine. Initialize with `cg_engine_config_init(&cfg)` (a macro that
/// passes `sizeof cfg` to `cg_engine_config_init_sized`), then change fields.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct cg_engine_config {
    /// `sizeof(cg_engine_config)` of the header the host was compiled with (set by
    /// `cg_engine_config_init`). Smaller than the first version's size:
    /// `CG_ERR_INVALID_ARGUMENT`.
    pub struct_size: u32,
    /// Coordinate system of every frame (a `cg_coordinate_system` value; others give
    /// `CG_ERR_INVALID_ARGUMENT`). Default `CG_COORDS_NATIVE`.
    pub coordinate_system: cg_coordinate_system,
    /// Path of the model bundle directory, NUL-terminated UTF-8 (an empty string is
    /// `CG_ERR_INVALID_ARGUMENT`). Borrowed only during `cg_engine_create`. A path given here
    /// always wins. NULL selects, in order: the directory named by the `COMGRASP_BUNDLE`
    /// environment variable when it is set (set but empty or not a valid bundle:
    /// `CG_ERR_BUNDLE`, with no fallback); else the default bundle embedded in the library
    /// (cargo feature `embedded-default`, on by default), so NULL works from any working
    /// directory; else `CG_ERR_BUNDLE`. Default NULL.
    pub bundle_path: *const c_char,
    /// 1: fill `cg_frame.joint_positions` by forward kinematics; 0: leave them zero.
    /// Default 0.
    pub enable_fk: u32,
    /// Frames each stream buffers before its worker waits for the host to poll,
    /// 1..=65536. Default 256 (~8.5 s at 30 fps, ~1.6 KiB per frame).
    pub ring_capacity: u32,
    /// Most streams alive at once (started and not yet destroyed), 1..=1024; `cg_start`
    /// returns `CG_ERR_LIMIT` beyond it. Default 16.
    pub max_streams: u32,
    /// Reserved, must be 0.
    pub reserved: u32,
    /// Publish name, NUL-terminated: when not NULL, every frame of every stream (exactly as
    /// `cg_poll_frame` returns it) and a `cg_stream_event` when a stream starts, ends, is
    /// cancelled or fails are also published over iceoryx2 shared memory on
    /// `comgrasp/<name>/frames` and `comgrasp/<name>/events`, for `cg_subscriber_open(name)`
    /// in other processes. 1..=`CG_MAX_PUBLISH_NAME_BYTES` bytes of ASCII letters, digits,
    /// '_', '-', '.' (else `CG_ERR_INVALID_ARGUMENT`); the services cannot be opened:
    /// `CG_ERR_SHM`. Slow or dead subscribers never slow the engine. Borrowed only during
    /// `cg_engine_create`. Default NULL (no shared memory). Appended after the first version
    /// of this struct (32 bytes, which stays accepted).
    pub publish_name: *const c_char,
    /// Runtime options (the fields from here on were appended in library 0.3; a host with an
    /// older header gets them all automatic). Each is 0 for "automatic", the fastest choice
    /// for the bundle and machine. Step implementation: a `CG_BACKEND_*` value.
    pub step_backend: u32,
    /// Decoder implementation: a `CG_BACKEND_*` value.
    pub decoder_backend: u32,
    /// Threads of the native step: 0 automatic (2 when the machine has two cores and the
    /// model is big enough for it to pay), 1 or 2.
    pub step_threads: u32,
    /// Threads of the native decoder: 0 automatic, 1 or 2.
    pub decoder_threads: u32,
    /// Tokens a stream decodes at once after its first chunk: 0 automatic (4 when both
    /// models are native and the step is no bigger than the decoder, else 1), or 1 to
    /// `CG_MAX_DECODE_GROUP`. The frames are the same for every value.
    pub decode_group: u32,
    /// Run the next token steps while a chunk decodes: a `CG_OVERLAP_*` value. The frames
    /// are the same either way.
    pub overlap: u32,
    /// Cap on the native kernels' instruction set: a `CG_ISA_*` value. Process-wide (the
    /// kernels are shared code): an engine created with a cap lowers it for every engine
    /// of the process from then on.
    pub max_isa: u32,
    /// Reserved, must be 0.
    pub reserved2: u32,
    /// How streams are driven (appended in library 0.4): a `CG_SCHEDULING_*` value.
    /// Default `CG_SCHEDULING_AUTO` (the crowd scheduler).
    pub scheduling: u32,
    /// Threads of the crowd scheduler: 0 automatic (the machine's cores minus one, at
    /// least one, so the game keeps a core), or 1 to `CG_MAX_SCHEDULER_THREADS`.
    pub scheduler_threads: u32,
}

/// `cg_engine_config.step_backend` / `decoder_backend`: native when the bundle has native
/// weights, else the ONNX graph in tract.
pub const CG_BACKEND_AUTO: u32 = 0;
/// The Rust kernels (`CG_ERR_BUNDLE` at creation if the bundle has no native weights).
pub const CG_BACKEND_NATIVE: u32 = 1;
/// The bundle's ONNX graph in tract (the reference; slower).
pub const CG_BACKEND_TRACT: u32 = 2;
/// `cg_engine_config.overlap`: when it pays (both models native, two decoder threads, the
/// step no bigger than the decoder).
pub const CG_OVERLAP_AUTO: u32 = 0;
/// Never overlap.
pub const CG_OVERLAP_OFF: u32 = 1;
/// Overlap whenever both models are native and the decoder has two threads.
pub const CG_OVERLAP_ON: u32 = 2;
/// `cg_engine_config.max_isa`: the best instruction set the CPU has.
pub const CG_ISA_BEST: u32 = 0;
/// Plain code, no SIMD intrinsics.
pub const CG_ISA_PORTABLE: u32 = 1;
/// At most AVX2 + FMA.
pub const CG_ISA_AVX2: u32 = 2;
/// At most AVX-512F (the same as `CG_ISA_BEST` today).
pub const CG_ISA_AVX512: u32 = 3;
/// `cg_engine_config.scheduling`: the crowd scheduler.
pub const CG_SCHEDULING_AUTO: u32 = 0;
/// The crowd scheduler: a few threads drive every stream, their token steps batched (each
/// weight read once per batch); the frames are the same as on a thread per stream.
pub const CG_SCHEDULING_CROWD: u32 = 1;
/// One worker thread per stream (each step and decode may use two threads).
pub const CG_SCHEDULING_PER_STREAM: u32 = 2;
/// Most crowd scheduler threads (`cg_engine_config.scheduler_threads`).
pub const CG_MAX_SCHEDULER_THREADS: u32 = 64;
const _: () = assert!(CG_MAX_SCHEDULER_THREADS as usize == crate::config::MAX_SCHEDULER_THREADS);
/// Most tokens in one decode (`cg_engine_config.decode_group`).
pub const CG_MAX_DECODE_GROUP: u32 = 8;
// (a literal, so cbindgen writes it into the header)
const _: () = assert!(CG_MAX_DECODE_GROUP as usize == crate::config::MAX_DECODE_GROUP);

/// Set in `cg_stream_config.use_defaults`: ignore `seed`, use the bundle's default seed.
pub const CG_USE_DEFAULT_SEED: u32 = 1 << 0;
/// Set in `cg_stream_config.use_defaults`: ignore `temperature`.
pub const CG_USE_DEFAULT_TEMPERATURE: u32 = 1 << 1;
/// Set in `cg_stream_config.use_defaults`: ignore `top_k`.
pub const CG_USE_DEFAULT_TOP_K: u32 = 1 << 2;
/// Set in `cg_stream_config.use_defaults`: ignore `min_len`.
pub const CG_USE_DEFAULT_MIN_LEN: u32 = 1 << 3;
/// Set in `cg_stream_config.use_defaults`: ignore `max_len`.
pub const CG_USE_DEFAULT_MAX_LEN: u32 = 1 << 4;
/// Set in `cg_stream_config.use_defaults`: ignore `guidance` (version 3 of the struct; a
/// shorter struct always takes the default).
pub const CG_USE_DEFAULT_GUIDANCE: u32 = 1 << 5;
/// All `CG_USE_DEFAULT_*` bits: every field takes the bundle's default.
pub const CG_USE_DEFAULT_ALL: u32 = 0x3f;
/// Set in `cg_stream_config.flags`: frames are the model's raw output, without the
/// contact-consistency stage (the object may float or drift, a hand may hold empty air).
pub const CG_STREAM_RAW_OUTPUT: u32 = 1 << 0;
/// Set in `cg_stream_config.flags`: the resting object stays where the model put it instead
/// of where the model's hand first closes on it (placement from the grasp, which holds the
/// first frame back until that grasp, at most 128 frames ahead: docs/engine.md).
pub const CG_STREAM_NO_GRASP_PLACEMENT: u32 = 1 << 1;
/// Set in `cg_stream_config.flags`: the model's legs are left as they are, so its feet may
/// slide, instead of a foot it stands on staying planted (for a host that runs its own
/// foot IK on uneven ground: docs/engine.md).
pub const CG_STREAM_FREE_FEET: u32 = 1 << 2;
/// All `CG_STREAM_*` flags this library knows.
pub const CG_STREAM_FLAGS_ALL: u32 = CG_STREAM_RAW_OUTPUT | CG_STREAM_NO_GRASP_PLACEMENT | CG_STREAM_FREE_FEET;
/// Set in `cg_stream_config.anchor`: `character_position` / `character_rotation` place the
/// character in the host's world.
pub const CG_ANCHOR_CHARACTER: u32 = 1 << 0;
/// Set in `cg_stream_config.anchor`: the object starts at `object_position` /
/// `object_rotation`; the character reaches for it (it must be within the reach envelope:
/// 0.8 m horizontally from the character's ground point, 0.3-1.6 m above it).
pub const CG_ANCHOR_OBJECT: u32 = 1 << 1;
/// Set in `cg_stream_config.anchor` with `CG_ANCHOR_OBJECT` and without
/// `CG_ANCHOR_CHARACTER`: the character is placed at the model's own spot relative to the
/// object (the "interaction spot") instead of reaching from where it stands.
pub const CG_ANCHOR_PLACE_CHARACTER: u32 = 1 << 2;
/// All `CG_ANCHOR_*` bits.
pub const CG_ANCHOR_ALL: u32 = 0x7;

/// Sampling settings of one stream. Initialize with `cg_stream_config_init` (which sets
/// `use_defaults = CG_USE_DEFAULT_ALL`); to override a field, set it AND clear its bit:
/// `cfg.seed = 42; cfg.use_defaults &= ~CG_USE_DEFAULT_SEED;`. Passing NULL instead of a
/// config to `cg_start` means "all defaults".
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct cg_stream_config {
    /// `sizeof(cg_stream_config)` of the host's header (set by `cg_stream_config_init`).
    pub struct_size: u32,
    /// Bitmask of `CG_USE_DEFAULT_*`: a set bit means "ignore this field, use the default".
    pub use_defaults: u32,
    /// Seed of the sampler's SplitMix64 generator; same seed + text + bundle = same motion.
    pub seed: u64,
    /// Softmax temperature, finite and >= 0; 0 = greedy (arg max).
    pub temperature: f64,
    /// Sample among the k most likely tokens only; 0 = no top-k filtering.
    pub top_k: u32,
    /// End is not allowed before this many token steps (16 frames each).
    pub min_len: u32,
    /// End is forced at this many token steps; 1..=the bundle's L_max.
    pub max_len: u32,
    /// Bitmask of `CG_STREAM_*` flags; 0 = the defaults (the contact-consistency stage on).
    /// Unknown bits are `CG_ERR_INVALID_ARGUMENT`. (Named `reserved`, must-be-0, before.)
    pub flags: u32,
    /// Scene anchoring (version 2 of this struct): bitmask of `CG_ANCHOR_*`; 0 = the
    /// model's own placement. Positions and rotations below are in the engine's coordinate
    /// system (its basis and units, as frames are); rotations unit quaternions (x, y, z, w).
    pub anchor: u32,
    /// Reserved, must be 0.
    pub reserved: u32,
    /// With `CG_ANCHOR_CHARACTER`: the character's ground point (under the pelvis at the
    /// first frame).
    pub character_position: [f32; 3],
    /// With `CG_ANCHOR_CHARACTER`: its heading; only the turn about the up axis counts, and
    /// the identity faces the native +y axis (glTF -z, Unity -z, Unreal -y).
    pub character_rotation: [f32; 4],
    /// With `CG_ANCHOR_OBJECT`: where the object starts (its origin, as
    /// `cg_frame.object_translation`).
    pub object_position: [f32; 3],
    /// With `CG_ANCHOR_OBJECT`: the object's start rotation.
    pub object_rotation: [f32; 4],
    /// Non-zero: continue the stream with this id (of the same engine, ended: its `CG_END`
    /// was seen, among its 64 most recent): start where it left off (the character's place,
    /// heading and last pose, blended from over 15 frames; its object, resting or held).
    /// Excludes `anchor`.
    pub continue_from: u64,
    /// Classifier-free guidance scale (version 3), finite and >= 0: how far each token's
    /// logits are pushed from the null condition's towards the prompt's; 1 = the prompt
    /// alone. For bundles trained with text dropout; costs a second token step per step.
    pub guidance: f64,
}

/// Size of the first published version of each struct: the smallest `struct_size`
/// accepted. Frozen: fields appended later take their defaults when a host's struct is
/// shorter (`cg_engine_config` v1 ended at `reserved`, before `publish_name`).
const ENGINE_CONFIG_V1_SIZE: usize = std::mem::offset_of!(cg_engine_config, publish_name);
const STREAM_CONFIG_V1_SIZE: usize = std::mem::offset_of!(cg_stream_config, anchor);

impl Default for cg_engine_config {
    fn default() -> Self {
        let d = EngineConfig::default();
        cg_engine_config {
            struct_size: size_of::<cg_engine_config>() as u32,
            coordinate_system: d.coordinate_system,
            bundle_path: std::ptr::null(),
            enable_fk: d.enable_fk as u32,
            ring_capacity: d.ring_capacity as u32,
            max_streams: d.max_streams as u32,
            reserved: 0,
            publish_name: std::ptr::null(),
            step_backend: CG_BACKEND_AUTO,
            decoder_backend: CG_BACKEND_AUTO,
            step_threads: 0,
            decoder_threads: 0,
            decode_group: 0,
            overlap: CG_OVERLAP_AUTO,
            max_isa: CG_ISA_BEST,
            reserved2: 0,
            scheduling: CG_SCHEDULING_AUTO,
            scheduler_threads: 0,
        }
    }
}

impl Default for cg_stream_config {
    fn default() -> Self {
        cg_stream_config {
            struct_size: size_of::<cg_stream_config>() as u32,
            use_defaults: CG_USE_DEFAULT_ALL,
            seed: 0,
            temperature: 1.0,
            top_k: 0,
            min_len: 0,
            max_len: 0,
            flags: 0,
            anchor: 0,
            reserved: 0,
            character_position: [0.0; 3],
            character_rotation: [0.0, 0.0, 0.0, 1.0],
            object_position: [0.0; 3],
            object_rotation: [0.0, 0.0, 0.0, 1.0],
            continue_from: 0,
            guidance: 1.0,
        }
    }
}

/// Copies the caller's struct (only its declared `struct_size` bytes) over our defaults.
/// The result is returned as raw storage: the caller reads fields whose every bit pattern
/// is valid directly, and validates enum fields from their raw integer first.
///
/// SAFETY: `src` is non-NULL and points to at least `struct_size` readable bytes (the
/// caller's promise when it sets `struct_size`).
pub(crate) unsafe fn read_versioned<T: Copy + Default>(
    src: *const T,
    min_size: usize,
    name: &str,
) -> Result<MaybeUninit<T>, Failure> {
    let declared = unsafe { std::ptr::read_unaligned(src as *const u32) } as usize;
    if declared < min_size {
        return Err(Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("{name}.struct_size is {declared}, at least {min_size} expected; call {name}_init first"),
        ));
    }
    let mut out = MaybeUninit::new(T::default());
    let n = declared.min(size_of::<T>());
    unsafe { std::ptr::copy_nonoverlapping(src as *const u8, out.as_mut_ptr() as *mut u8, n) };
    Ok(out)
}

fn coordinate_system_from_raw(raw: u32) -> Option<CoordinateSystem> {
    Some(match raw {
        0 => cg_coordinate_system::CG_COORDS_NATIVE,
        1 => cg_coordinate_system::CG_COORDS_GLTF,
        2 => cg_coordinate_system::CG_COORDS_UNITY,
        3 => cg_coordinate_system::CG_COORDS_UNREAL,
        _ => return None,
    })
}

/// Converts and validates a C engine config.
///
/// SAFETY: `cfg` is non-NULL and valid for `cfg.struct_size` bytes; `bundle_path`, if not
/// NULL, is a NUL-terminated string.
pub(crate) unsafe fn engine_config_from_c(cfg: *const cg_engine_config) -> Result<EngineConfig, Failure> {
    let raw = unsafe { read_versioned(cfg, ENGINE_CONFIG_V1_SIZE, "cg_engine_config")? };
    let p = raw.as_ptr();
    // The enum field is read as its raw integer: a C caller may have stored any value, and
    // materializing an invalid enum in Rust would be undefined behaviour.
    let coords_raw = unsafe { std::ptr::addr_of!((*p).coordinate_system).cast::<u32>().read() };
    let coordinate_system = coordinate_system_from_raw(coords_raw).ok_or_else(|| {
        Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("cg_engine_config.coordinate_system {coords_raw} is not a cg_coordinate_system value"),
        )
    })?;
    // SAFETY: the remaining fields are integers and a raw pointer: any bit pattern is valid.
    let (bundle_path, enable_fk, ring_capacity, max_streams, reserved, publish_name) = unsafe {
        (
            std::ptr::addr_of!((*p).bundle_path).read(),
            std::ptr::addr_of!((*p).enable_fk).read(),
            std::ptr::addr_of!((*p).ring_capacity).read(),
            std::ptr::addr_of!((*p).max_streams).read(),
            std::ptr::addr_of!((*p).reserved).read(),
            std::ptr::addr_of!((*p).publish_name).read(),
        )
    };
    let invalid = |msg: String| Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, msg);
    if enable_fk > 1 {
        return Err(invalid(format!("cg_engine_config.enable_fk must be 0 or 1, got {enable_fk}")));
    }
    if reserved != 0 {
        return Err(invalid("cg_engine_config.reserved must be 0".into()));
    }
    let bundle_path = unsafe { optional_str(bundle_path, "cg_engine_config.bundle_path")? }.map(PathBuf::from);
    let publish_name = unsafe { optional_str(publish_name, "cg_engine_config.publish_name")? }.map(String::from);
    // SAFETY: plain integers, read one by one (the struct as a whole may hold an invalid
    // enum value, so it is never materialized).
    let runtime = runtime_from_c(unsafe {
        [
            std::ptr::addr_of!((*p).step_backend).read(),
            std::ptr::addr_of!((*p).decoder_backend).read(),
            std::ptr::addr_of!((*p).step_threads).read(),
            std::ptr::addr_of!((*p).decoder_threads).read(),
            std::ptr::addr_of!((*p).decode_group).read(),
            std::ptr::addr_of!((*p).overlap).read(),
            std::ptr::addr_of!((*p).max_isa).read(),
            std::ptr::addr_of!((*p).reserved2).read(),
        ]
    })?;
    // Appended in 0.4 (a shorter host struct left our defaults in the copy). SAFETY: plain integers.
    let (scheduling, scheduler_threads) =
        unsafe { (std::ptr::addr_of!((*p).scheduling).read(), std::ptr::addr_of!((*p).scheduler_threads).read()) };
    let invalid_field = |field: &str, v: u32, want: &str| {
        Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("cg_engine_config.{field} is {v}, expected {want}"),
        )
    };
    let runtime = RuntimeOptions {
        scheduling: match scheduling {
            CG_SCHEDULING_AUTO => Scheduling::Auto,
            CG_SCHEDULING_CROWD => Scheduling::Crowd,
            CG_SCHEDULING_PER_STREAM => Scheduling::PerStream,
            v => return Err(invalid_field("scheduling", v, "a CG_SCHEDULING_* value (0 to 2)")),
        },
        scheduler_threads: match scheduler_threads {
            0 => None,
            n if n <= CG_MAX_SCHEDULER_THREADS => Some(n as usize),
            n => return Err(invalid_field("scheduler_threads", n, "0 (automatic) to CG_MAX_SCHEDULER_THREADS")),
        },
        ..runtime
    };
    Ok(EngineConfig {
        bundle_path,
        coordinate_system,
        enable_fk: enable_fk == 1,
        ring_capacity: ring_capacity as usize,
        max_streams: max_streams as usize,
        default_stream: StreamConfig::default(),
        publish_name,
        runtime,
    })
}

/// The runtime fields of a C engine config (`step_backend` .. `reserved2`, in order), validated.
fn runtime_from_c(fields: [u32; 8]) -> Result<RuntimeOptions, Failure> {
    let [step_backend, decoder_backend, step_threads, decoder_threads, decode_group, overlap, max_isa, reserved2] =
        fields;
    let invalid = |field: &str, v: u32, want: &str| {
        Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("cg_engine_config.{field} is {v}, expected {want}"),
        )
    };
    let backend = |field: &str, v: u32| match v {
        CG_BACKEND_AUTO => Ok(None),
        CG_BACKEND_NATIVE => Ok(Some(DecoderBackend::Native)),
        CG_BACKEND_TRACT => Ok(Some(DecoderBackend::Tract)),
        _ => Err(invalid(field, v, "a CG_BACKEND_* value (0 to 2)")),
    };
    let threads = |field: &str, v: u32| match v {
        0 => Ok(None),
        1 | 2 => Ok(Some(v as usize)),
        _ => Err(invalid(field, v, "0 (automatic), 1 or 2")),
    };
    if reserved2 != 0 {
        return Err(invalid("reserved2", reserved2, "0"));
    }
    Ok(RuntimeOptions {
        step_backend: match backend("step_backend", step_backend)? {
            None => StepBackend::Auto,
            Some(DecoderBackend::Native) => StepBackend::Native,
            Some(DecoderBackend::Tract) => StepBackend::Tract,
        },
        decoder_backend: backend("decoder_backend", decoder_backend)?,
        step_threads: threads("step_threads", step_threads)?,
        decoder_threads: threads("decoder_threads", decoder_threads)?,
        decode_group: match decode_group {
            0 => None,
            g if g <= CG_MAX_DECODE_GROUP => Some(g as usize),
            g => return Err(invalid("decode_group", g, "0 (automatic) to CG_MAX_DECODE_GROUP")),
        },
        overlap: match overlap {
            CG_OVERLAP_AUTO => None,
            CG_OVERLAP_OFF => Some(false),
            CG_OVERLAP_ON => Some(true),
            v => return Err(invalid("overlap", v, "a CG_OVERLAP_* value (0 to 2)")),
        },
        max_isa: match max_isa {
            CG_ISA_BEST => None,
            CG_ISA_PORTABLE => Some(InstructionSet::Portable),
            CG_ISA_AVX2 => Some(InstructionSet::Avx2),
            CG_ISA_AVX512 => Some(InstructionSet::Avx512),
            v => return Err(invalid("max_isa", v, "a CG_ISA_* value (0 to 3)")),
        },
        ..RuntimeOptions::default()
    })
}

/// A NULL-or-string config field: NULL is `None`; otherwise it must be non-empty UTF-8.
///
/// SAFETY: `p` is NULL or a NUL-terminated string valid for the call.
pub(crate) unsafe fn optional_str<'a>(p: *const c_char, field: &str) -> Result<Option<&'a str>, Failure> {
    if p.is_null() {
        return Ok(None);
    }
    let s = unsafe { CStr::from_ptr(p) }
        .to_str()
        .map_err(|_| Failure::new(cg_status::CG_ERR_INVALID_UTF8, format_args!("{field} is not valid UTF-8")))?;
    if s.is_empty() {
        return Err(Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, format_args!("{field} is empty")));
    }
    Ok(Some(s))
}

/// Converts a C stream config (NULL = all defaults).
///
/// SAFETY: `cfg` is NULL or valid for `cfg.struct_size` bytes.
pub(crate) unsafe fn stream_config_from_c(cfg: *const cg_stream_config) -> Result<StreamConfig, Failure> {
    if cfg.is_null() {
        return Ok(StreamConfig::default());
    }
    let raw = unsafe { read_versioned(cfg, STREAM_CONFIG_V1_SIZE, "cg_stream_config")? };
    // SAFETY: every field is an integer or a float: any bit pattern is valid.
    let c = unsafe { raw.assume_init() };
    if c.flags & !CG_STREAM_FLAGS_ALL != 0 {
        return Err(Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("cg_stream_config.flags: unknown bits {:#x}", c.flags & !CG_STREAM_FLAGS_ALL),
        ));
    }
    let set = |bit: u32| c.use_defaults & bit == 0;
    // a host whose struct ends before `guidance` never set it, whatever its bits say
    let has_guidance = c.struct_size as usize >= std::mem::offset_of!(cg_stream_config, guidance) + size_of::<f64>();
    Ok(StreamConfig {
        seed: set(CG_USE_DEFAULT_SEED).then_some(c.seed),
        temperature: set(CG_USE_DEFAULT_TEMPERATURE).then_some(c.temperature),
        top_k: set(CG_USE_DEFAULT_TOP_K).then_some(c.top_k),
        min_len: set(CG_USE_DEFAULT_MIN_LEN).then_some(c.min_len),
        max_len: set(CG_USE_DEFAULT_MAX_LEN).then_some(c.max_len),
        guidance: (has_guidance && set(CG_USE_DEFAULT_GUIDANCE)).then_some(c.guidance),
        raw_output: (c.flags & CG_STREAM_RAW_OUTPUT != 0).then_some(true),
        grasp_placement: (c.flags & CG_STREAM_NO_GRASP_PLACEMENT != 0).then_some(false),
        foot_lock: (c.flags & CG_STREAM_FREE_FEET != 0).then_some(false),
        anchor: anchor_from_c(&c)?,
        continue_from: (c.continue_from != 0).then_some(c.continue_from),
    })
}

fn anchor_from_c(c: &cg_stream_config) -> Result<Option<Anchor>, Failure> {
    let invalid = |m: String| Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, m);
    if c.anchor & !CG_ANCHOR_ALL != 0 || c.reserved != 0 {
        return Err(invalid(format!(
            "cg_stream_config: unknown anchor bits {:#x} or non-zero reserved",
            c.anchor & !CG_ANCHOR_ALL
        )));
    }
    if c.anchor == 0 {
        return Ok(None);
    }
    let set = |bit: u32| c.anchor & bit != 0;
    Ok(Some(Anchor {
        character: set(CG_ANCHOR_CHARACTER)
            .then_some(Placement { position: c.character_position, rotation: c.character_rotation }),
        object: set(CG_ANCHOR_OBJECT).then_some(Placement { position: c.object_position, rotation: c.object_rotation }),
        place_character: set(CG_ANCHOR_PLACE_CHARACTER),
    }))
}

/// Fills the first `size` bytes of `*cfg` with the defaults and sets `struct_size` to
/// `size` (capped at this library's `sizeof(cg_engine_config)`). `size` is the HOST's
/// `sizeof(cg_engine_config)`: the header's `cg_engine_config_init(cfg)` macro passes it, so
/// a library never writes past a host's struct, whichever of the two is newer. Call it
/// before changing fields, so fields added in later versions get their defaults. Errors:
/// `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_ARGUMENT` (`size` below the first version's 32
/// bytes). Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_config_init_sized(cfg: *mut cg_engine_config, size: usize) -> cg_status {
    boundary("cg_engine_config_init_sized", || unsafe { engine_config_init(cfg, size) })
}

/// The first version's entry point, for binaries built against the first header (whose
/// struct ends before `publish_name`): fills the first version's 32 bytes. Code compiled
/// with the current header reaches `cg_engine_config_init_sized` through the
/// `cg_engine_config_init(cfg)` macro instead. Errors: `CG_ERR_NULL_POINTER`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_engine_config_init(cfg: *mut cg_engine_config) -> cg_status {
    boundary("cg_engine_config_init", || unsafe { engine_config_init(cfg, ENGINE_CONFIG_V1_SIZE) })
}

/// SAFETY: `cfg` is NULL or valid for `size` writable bytes.
unsafe fn engine_config_init(cfg: *mut cg_engine_config, size: usize) -> Result<cg_status, Failure> {
    let defaults = |n: usize| cg_engine_config { struct_size: n as u32, ..cg_engine_config::default() };
    unsafe { init_sized(cfg, size, ENGINE_CONFIG_V1_SIZE, "cg_engine_config_init", defaults) }
}

/// Writes the first `min(size, sizeof T)` bytes of `defaults(n)` to `*cfg`: a library never
/// writes past a host's struct, whichever of the two is newer.
///
/// SAFETY: `cfg` is NULL or valid for `size` writable bytes.
unsafe fn init_sized<T>(
    cfg: *mut T,
    size: usize,
    v1: usize,
    name: &str,
    defaults: impl Fn(usize) -> T,
) -> Result<cg_status, Failure> {
    if cfg.is_null() {
        return Err(Failure::new(cg_status::CG_ERR_NULL_POINTER, format_args!("{name}: cfg is NULL")));
    }
    if size < v1 {
        return Err(Failure::new(
            cg_status::CG_ERR_INVALID_ARGUMENT,
            format_args!("{name}: size {size} is below the first version's {v1} bytes"),
        ));
    }
    let n = size.min(size_of::<T>());
    let value = defaults(n);
    unsafe { std::ptr::copy_nonoverlapping(&value as *const T as *const u8, cfg as *mut u8, n) };
    Ok(cg_status::CG_OK)
}

/// The first version's entry point, for binaries built against a header whose struct ends
/// at `flags` (40 bytes): fills those bytes with the defaults (`use_defaults =
/// CG_USE_DEFAULT_ALL`). Code compiled with the current header reaches
/// `cg_stream_config_init_sized` through the `cg_stream_config_init(cfg)` macro instead.
/// Errors: `CG_ERR_NULL_POINTER`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_stream_config_init(cfg: *mut cg_stream_config) -> cg_status {
    boundary("cg_stream_config_init", || unsafe { stream_config_init(cfg, STREAM_CONFIG_V1_SIZE) })
}

/// Fills the first `size` bytes of `*cfg` with the defaults and sets `struct_size` to
/// `size` (capped at this library's `sizeof(cg_stream_config)`). `size` is the HOST's
/// `sizeof(cg_stream_config)`: the header's `cg_stream_config_init(cfg)` macro passes it.
/// Errors: `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_ARGUMENT` (`size` below the first
/// version's 40 bytes). Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_stream_config_init_sized(cfg: *mut cg_stream_config, size: usize) -> cg_status {
    boundary("cg_stream_config_init_sized", || unsafe { stream_config_init(cfg, size) })
}

/// SAFETY: `cfg` is NULL or valid for `size` writable bytes.
unsafe fn stream_config_init(cfg: *mut cg_stream_config, size: usize) -> Result<cg_status, Failure> {
    let defaults = |n: usize| cg_stream_config { struct_size: n as u32, ..cg_stream_config::default() };
    unsafe { init_sized(cfg, size, STREAM_CONFIG_V1_SIZE, "cg_stream_config_init", defaults) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn old_and_new_struct_sizes() {
        let mut c =
            cg_stream_config { use_defaults: CG_USE_DEFAULT_ALL & !CG_USE_DEFAULT_SEED, seed: 7, ..Default::default() };
        let s = unsafe { stream_config_from_c(&c) }.unwrap();
        assert_eq!(s, StreamConfig { seed: Some(7), ..Default::default() });
        c.flags = CG_STREAM_RAW_OUTPUT;
        let s = unsafe { stream_config_from_c(&c) }.unwrap();
        assert_eq!(s, StreamConfig { seed: Some(7), raw_output: Some(true), ..Default::default() });
        c.flags = CG_STREAM_NO_GRASP_PLACEMENT;
        let s = unsafe { stream_config_from_c(&c) }.unwrap();
        assert_eq!(s, StreamConfig { seed: Some(7), grasp_placement: Some(false), ..Default::default() });
        c.flags = CG_STREAM_FREE_FEET;
        let s = unsafe { stream_config_from_c(&c) }.unwrap();
        assert_eq!(s, StreamConfig { seed: Some(7), foot_lock: Some(false), ..Default::default() });
        c.flags = 1 << 5;
        let e = unsafe { stream_config_from_c(&c) }.unwrap_err();
        assert_eq!(e.0, cg_status::CG_ERR_INVALID_ARGUMENT);
        c.flags = 0;
        // Version 2: scene anchoring; a v1 host (40 bytes) never has it, whatever follows.
        c.anchor = CG_ANCHOR_OBJECT | CG_ANCHOR_PLACE_CHARACTER;
        c.object_position = [1.0, 2.0, 0.8];
        let s = unsafe { stream_config_from_c(&c) }.unwrap();
        let a = s.anchor.unwrap();
        assert!(a.place_character && a.character.is_none());
        assert_eq!(a.object.unwrap().position, [1.0, 2.0, 0.8]);
        c.struct_size = STREAM_CONFIG_V1_SIZE as u32;
        assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap().anchor, None);
        // Version 3: guidance, taken only when its bit is clear and the struct reaches it.
        c.struct_size = size_of::<cg_stream_config>() as u32;
        c.guidance = 2.5;
        assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap().guidance, None);
        c.use_defaults &= !CG_USE_DEFAULT_GUIDANCE;
        assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap().guidance, Some(2.5));
        c.struct_size = std::mem::offset_of!(cg_stream_config, guidance) as u32;
        assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap().guidance, None);
        c.struct_size = size_of::<cg_stream_config>() as u32;
        for (anchor, reserved) in [(1 << 3, 0), (CG_ANCHOR_OBJECT, 1)] {
            (c.anchor, c.reserved) = (anchor, reserved);
            assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap_err().0, cg_status::CG_ERR_INVALID_ARGUMENT);
        }
        (c.anchor, c.reserved) = (0, 0);
        c.struct_size = 8;
        assert_eq!(unsafe { stream_config_from_c(&c) }.unwrap_err().0, cg_status::CG_ERR_INVALID_ARGUMENT);
        // The sized init writes no byte past the host's struct; the v1 entry point 40 bytes.
        let mut buf = [0xAAu8; 200];
        let p = buf.as_mut_ptr() as *mut cg_stream_config;
        assert_eq!(unsafe { cg_stream_config_init_sized(p, STREAM_CONFIG_V1_SIZE) }, cg_status::CG_OK);
        assert!(buf[STREAM_CONFIG_V1_SIZE..].iter().all(|&b| b == 0xAA));
        assert_eq!(u32::from_ne_bytes(buf[..4].try_into().unwrap()) as usize, STREAM_CONFIG_V1_SIZE);
        assert_eq!(unsafe { cg_stream_config_init(p) }, cg_status::CG_OK);
        assert!(buf[STREAM_CONFIG_V1_SIZE..].iter().all(|&b| b == 0xAA));
        assert_eq!(unsafe { cg_stream_config_init_sized(p, 200) }, cg_status::CG_OK);
        assert!(buf[size_of::<cg_stream_config>()..].iter().all(|&b| b == 0xAA));
        let full = unsafe { p.read_unaligned() };
        assert_eq!(full, cg_stream_config::default());
        assert_eq!(unsafe { cg_stream_config_init_sized(p, 39) }, cg_status::CG_ERR_INVALID_ARGUMENT);

        let e = cg_engine_config::default();
        assert!(unsafe { engine_config_from_c(&e) }.is_ok());
        // What a C caller can write: the enum field as a plain integer, here out of range.
        #[repr(C)]
        struct FromC {
            struct_size: u32,
            coordinate_system: u32,
            rest: [u64; 9],
        }
        assert_eq!(size_of::<FromC>(), size_of::<cg_engine_config>());
        let bad = FromC { struct_size: size_of::<FromC>() as u32, coordinate_system: 99, rest: [0; 9] };
        let r = unsafe { engine_config_from_c(&bad as *const FromC as *const cg_engine_config) };
        assert_eq!(r.unwrap_err().0, cg_status::CG_ERR_INVALID_ARGUMENT);

        // A host compiled against the v1 header (32 bytes, no publish_name): the bytes after
        // its struct are never read, and publish_name takes its default.
        #[repr(C)]
        struct V1 {
            struct_size: u32,
            coordinate_system: u32,
            rest: [u64; 3],
            trailing_garbage: usize,
        }
        let v1 = V1 { struct_size: 32, coordinate_system: 0, rest: [0; 3], trailing_garbage: 0xdead_beef };
        let c = unsafe { engine_config_from_c(&v1 as *const V1 as *const cg_engine_config) }.unwrap();
        assert_eq!(c.publish_name, None);
        let mut named = cg_engine_config { publish_name: c"game".as_ptr(), ..Default::default() };
        assert_eq!(unsafe { engine_config_from_c(&named) }.unwrap().publish_name.as_deref(), Some("game"));
        // Init never writes past the host's struct: a v1-sized host keeps its next bytes.
        let mut host = V1 { struct_size: 0, coordinate_system: 9, rest: [7; 3], trailing_garbage: 0x1234 };
        let p = &mut host as *mut V1 as *mut cg_engine_config;
        assert_eq!(unsafe { cg_engine_config_init(p) }, cg_status::CG_OK);
        assert_eq!((host.struct_size, host.coordinate_system, host.trailing_garbage), (32, 0, 0x1234));
        assert_eq!(unsafe { cg_engine_config_init_sized(p, 31) }, cg_status::CG_ERR_INVALID_ARGUMENT);
        let mut full = cg_engine_config { max_streams: 0, ..Default::default() };
        assert_eq!(unsafe { cg_engine_config_init_sized(&mut full, 4096) }, cg_status::CG_OK, "bigger host: capped");
        assert_eq!((full.struct_size as usize, full.max_streams), (size_of::<cg_engine_config>(), 16));
        named.publish_name = c"".as_ptr();
        assert_eq!(unsafe { engine_config_from_c(&named) }.unwrap_err().0, cg_status::CG_ERR_INVALID_ARGUMENT);
    }

    #[test]
    fn runtime_fields() {
        // A host compiled against the 0.2 header (40 bytes, up to publish_name): whatever
        // follows its struct is never read, and every runtime option is automatic.
        #[repr(C)]
        struct V2 {
            head: cg_engine_config_v2_head,
            trailing_garbage: [u32; 8],
        }
        #[repr(C)]
        struct cg_engine_config_v2_head {
            struct_size: u32,
            coordinate_system: u32,
            bundle_path: *const c_char,
            small: [u32; 4],
            publish_name: *const c_char,
        }
        assert_eq!(size_of::<cg_engine_config_v2_head>(), std::mem::offset_of!(cg_engine_config, step_backend));
        let head = cg_engine_config_v2_head {
            struct_size: size_of::<cg_engine_config_v2_head>() as u32,
            coordinate_system: 0,
            bundle_path: std::ptr::null(),
            small: [0, 256, 16, 0],
            publish_name: std::ptr::null(),
        };
        let v2 = V2 { head, trailing_garbage: [7; 8] };
        let c = unsafe { engine_config_from_c(&v2 as *const V2 as *const cg_engine_config) }.unwrap();
        assert_eq!(c.runtime, RuntimeOptions::default());
        // A 0.3 host (up to reserved2): garbage after its struct is not read either.
        let v3 = cg_engine_config {
            struct_size: std::mem::offset_of!(cg_engine_config, scheduling) as u32,
            scheduling: 99,
            scheduler_threads: 1000,
            ..Default::default()
        };
        let c = unsafe { engine_config_from_c(&v3) }.unwrap();
        assert_eq!((c.runtime.scheduling, c.runtime.scheduler_threads), (Scheduling::Auto, None));

        let set = cg_engine_config {
            step_backend: CG_BACKEND_TRACT,
            decoder_backend: CG_BACKEND_NATIVE,
            step_threads: 1,
            decoder_threads: 2,
            decode_group: CG_MAX_DECODE_GROUP,
            overlap: CG_OVERLAP_OFF,
            max_isa: CG_ISA_AVX2,
            scheduling: CG_SCHEDULING_PER_STREAM,
            scheduler_threads: 5,
            ..Default::default()
        };
        assert_eq!(
            unsafe { engine_config_from_c(&set) }.unwrap().runtime,
            RuntimeOptions {
                step_backend: StepBackend::Tract,
                decoder_backend: Some(DecoderBackend::Native),
                step_threads: Some(1),
                decoder_threads: Some(2),
                decode_group: Some(8),
                overlap: Some(false),
                max_isa: Some(InstructionSet::Avx2),
                scheduling: Scheduling::PerStream,
                scheduler_threads: Some(5),
            }
        );
        let d = cg_engine_config::default();
        for (bad, field) in [
            (cg_engine_config { step_backend: 3, ..d }, "step_backend"),
            (cg_engine_config { decoder_backend: 9, ..d }, "decoder_backend"),
            (cg_engine_config { step_threads: 3, ..d }, "step_threads"),
            (cg_engine_config { decoder_threads: u32::MAX, ..d }, "decoder_threads"),
            (cg_engine_config { decode_group: CG_MAX_DECODE_GROUP + 1, ..d }, "decode_group"),
            (cg_engine_config { overlap: 3, ..d }, "overlap"),
            (cg_engine_config { max_isa: 4, ..d }, "max_isa"),
            (cg_engine_config { reserved2: 1, ..d }, "reserved2"),
            (cg_engine_config { scheduling: 3, ..d }, "scheduling"),
            (cg_engine_config { scheduler_threads: CG_MAX_SCHEDULER_THREADS + 1, ..d }, "scheduler_threads"),
        ] {
            let f = unsafe { engine_config_from_c(&bad) }.unwrap_err();
            assert_eq!(f.0, cg_status::CG_ERR_INVALID_ARGUMENT, "{field}");
            let msg = unsafe { CStr::from_ptr(crate::ffi::cg_last_error()) }.to_string_lossy().into_owned();
            assert!(msg.contains(&format!("cg_engine_config.{field} ")), "{field}: {msg}");
        }
    }
}
