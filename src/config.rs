//! Typed configuration, plain data: the engine's ([`EngineConfig`]), a stream's
//! ([`StreamConfig`]) and how an engine runs its models ([`RuntimeOptions`]: backends, thread
//! counts, decode grouping, overlap and the instruction-set cap; C: the fields after
//! `publish_name` in `cg_engine_config`), with their limits. The bottom floor: it imports
//! only the error type and the coordinate systems of [`crate::frame`].
//!
//! Every option defaults to "automatic", the choice that is fastest on the bundle and
//! machine (each consumer documents its rule). The library itself never reads the
//! environment for these: only the `comgrasp` CLI and the benchmark call
//! [`RuntimeOptions::from_env`], so two engines in one process can run differently and a
//! test sets options instead of process-wide variables.
use std::path::PathBuf;

use crate::error::{Error, Result};
use crate::frame::CoordinateSystem;

/// Which implementation runs the Transformer step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum StepBackend {
    /// Native when the bundle has `transformer.native`, tract otherwise.
    #[default]
    Auto,
    /// The Rust kernels (`model::native`); an error at load if the bundle has no native weights.
    Native,
    /// The ONNX graph in tract.
    Tract,
}

impl StepBackend {
    /// `"native"` / `"tract"` / `"auto"`.
    pub fn name(self) -> &'static str {
        match self {
            StepBackend::Auto => "auto",
            StepBackend::Native => "native",
            StepBackend::Tract => "tract",
        }
    }
}

/// Which implementation runs the VQ decoder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecoderBackend {
    /// `decoder.onnx` in tract.
    Tract,
    /// The incremental Rust decoder on the `decoder.native` weights.
    Native,
}

impl DecoderBackend {
    /// `"tract"` or `"native"`.
    pub fn name(self) -> &'static str {
        match self {
            DecoderBackend::Tract => "tract",
            DecoderBackend::Native => "native",
        }
    }
}

/// The widest SIMD instruction set the native kernels may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum InstructionSet {
    /// Plain Rust (auto-vectorized for the build target).
    Portable,
    /// AVX2 + FMA.
    Avx2,
    /// AVX-512F.
    Avx512,
}

impl InstructionSet {
    /// `"portable"`, `"avx2"` or `"avx512"`.
    pub fn name(self) -> &'static str {
        match self {
            InstructionSet::Portable => "portable",
            InstructionSet::Avx2 => "avx2",
            InstructionSet::Avx512 => "avx512",
        }
    }
}

/// How an engine drives its streams' generations.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Scheduling {
    /// The crowd scheduler.
    #[default]
    Auto,
    /// The crowd scheduler (`crate::crowd`): a few threads for all streams, their token
    /// steps batched (each weight read once per batch).
    Crowd,
    /// One worker thread per stream (each step and decode on up to two threads of its own).
    PerStream,
}

impl Scheduling {
    /// `"crowd"`, `"per-stream"` or `"auto"`.
    pub fn name(self) -> &'static str {
        match self {
            Scheduling::Auto => "auto",
            Scheduling::Crowd => "crowd",
            Scheduling::PerStream => "per-stream",
        }
    }
}

/// Most crowd scheduler threads (`RuntimeOptions::scheduler_threads`). (C: `CG_MAX_SCHEDULER_THREADS`.)
/// cbindgen:ignore
pub const MAX_SCHEDULER_THREADS: usize = 64;

/// Most tokens one grouped decode takes (`RuntimeOptions::decode_group`).
pub const MAX_DECODE_GROUP: usize = 8;

/// How an engine runs its models. `Default` is automatic everywhere.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RuntimeOptions {
    /// Step implementation. Default `Auto` (native when the bundle has native weights).
    pub step_backend: StepBackend,
    /// Decoder implementation; `None`: native when the bundle has native weights.
    pub decoder_backend: Option<DecoderBackend>,
    /// Threads of the native step, 1 or 2; `None`: 2 on a machine with two or more cores
    /// when the step is big enough for the hand-overs to pay.
    pub step_threads: Option<usize>,
    /// Threads of the native decoder, 1 or 2; `None`: as for the step.
    pub decoder_threads: Option<usize>,
    /// Tokens per decode after a stream's first chunk, 1 ..= [`MAX_DECODE_GROUP`]; `None`:
    /// 4 when both models are native and the step is no bigger than the decoder, else 1.
    pub decode_group: Option<usize>,
    /// Run the next token steps while a chunk decodes; `None`: when both models are native,
    /// the decoder has two threads and the step is no bigger than the decoder. `Some(true)`
    /// overlaps whenever both are native and the decoder has two threads.
    pub overlap: Option<bool>,
    /// Cap on the native kernels' instruction set; `None`: the best the CPU has. The kernels
    /// are shared code, so the cap is process-wide: an engine created with a cap lowers it
    /// for the whole process from then on (it never rises again). Results differ only in
    /// the last bits between instruction sets.
    pub max_isa: Option<InstructionSet>,
    /// How streams are driven; `Auto`: the crowd scheduler.
    pub scheduling: Scheduling,
    /// Threads of the crowd scheduler, 1 ..= [`MAX_SCHEDULER_THREADS`]; `None`: the
    /// machine's cores minus one (at least one), so a game keeps a core.
    pub scheduler_threads: Option<usize>,
}

/// The environment variables [`RuntimeOptions::from_env`] reads, one per field.
pub const RUNTIME_ENV: [&str; 9] = [
    "COMGRASP_STEP",
    "COMGRASP_DECODER",
    "COMGRASP_STEP_THREADS",
    "COMGRASP_DECODER_THREADS",
    "COMGRASP_DECODE_GROUP",
    "COMGRASP_OVERLAP",
    "COMGRASP_NATIVE_ISA",
    "COMGRASP_SCHEDULING",
    "COMGRASP_SCHEDULER_THREADS",
];

impl RuntimeOptions {
    /// Checks the numeric fields' ranges.
    pub fn validate(&self) -> Result<()> {
        for (name, threads) in [("step_threads", self.step_threads), ("decoder_threads", self.decoder_threads)] {
            if let Some(n) = threads {
                if !(1..=2).contains(&n) {
                    return Err(Error::InvalidArgument(format!(
                        "runtime {name} must be 1 or 2 (or automatic), got {n}"
                    )));
                }
            }
        }
        if let Some(n) = self.scheduler_threads {
            if !(1..=MAX_SCHEDULER_THREADS).contains(&n) {
                return Err(Error::InvalidArgument(format!(
                    "runtime scheduler_threads must be 1 to {MAX_SCHEDULER_THREADS} (or automatic), got {n}"
                )));
            }
        }
        if let Some(g) = self.decode_group {
            if !(1..=MAX_DECODE_GROUP).contains(&g) {
                return Err(Error::InvalidArgument(format!(
                    "runtime decode_group must be 1 to {MAX_DECODE_GROUP} (or automatic), got {g}"
                )));
            }
        }
        Ok(())
    }

    /// The options the `COMGRASP_*` variables of [`RUNTIME_ENV`] set (unset or empty:
    /// automatic). For the CLI and the benchmark only: the library never calls it.
    pub fn from_env() -> Result<RuntimeOptions> {
        RuntimeOptions::from_vars(|name| match std::env::var(name) {
            Ok(v) => Ok(Some(v)),
            Err(std::env::VarError::NotPresent) => Ok(None),
            Err(e) => Err(Error::InvalidArgument(format!("{name}: {e}"))),
        })
    }

    /// [`from_env`](Self::from_env) over any lookup (tests pass a map).
    pub fn from_vars(get: impl Fn(&str) -> Result<Option<String>>) -> Result<RuntimeOptions> {
        let [step, decoder, step_threads, decoder_threads, group, overlap, isa, scheduling, sched_threads] =
            RUNTIME_ENV;
        let var = |name: &str| -> Result<Option<String>> {
            Ok(get(name)?.map(|v| v.trim().to_ascii_lowercase()).filter(|v| !v.is_empty()))
        };
        let bad = |name: &str, v: &str, want: &str| Error::InvalidArgument(format!("{name}={v:?}: expected {want}"));
        let options = RuntimeOptions {
            step_backend: match var(step)?.as_deref() {
                None | Some("auto") => StepBackend::Auto,
                Some("native") => StepBackend::Native,
                Some("tract") => StepBackend::Tract,
                Some(v) => return Err(bad(step, v, "native, tract or auto")),
            },
            decoder_backend: match var(decoder)?.as_deref() {
                None | Some("auto") => None,
                Some("native") => Some(DecoderBackend::Native),
                Some("tract") => Some(DecoderBackend::Tract),
                Some(v) => return Err(bad(decoder, v, "native, tract or auto")),
            },
            step_threads: threads(step_threads, var(step_threads)?)?,
            decoder_threads: threads(decoder_threads, var(decoder_threads)?)?,
            decode_group: match var(group)? {
                None => None,
                Some(v) => match v.parse::<usize>() {
                    Ok(g) if (1..=MAX_DECODE_GROUP).contains(&g) => Some(g),
                    _ => return Err(bad(group, &v, &format!("1 to {MAX_DECODE_GROUP}"))),
                },
            },
            overlap: match var(overlap)?.as_deref() {
                None => None,
                Some("0") => Some(false),
                Some("1") => Some(true),
                Some(v) => return Err(bad(overlap, v, "0 or 1")),
            },
            max_isa: match var(isa)?.as_deref() {
                None => None,
                Some("portable") => Some(InstructionSet::Portable),
                Some("avx2") => Some(InstructionSet::Avx2),
                Some("avx512") => Some(InstructionSet::Avx512),
                Some(v) => return Err(bad(isa, v, "portable, avx2 or avx512")),
            },
            scheduling: match var(scheduling)?.as_deref() {
                None | Some("auto") => Scheduling::Auto,
                Some("crowd") => Scheduling::Crowd,
                Some("per-stream") => Scheduling::PerStream,
                Some(v) => return Err(bad(scheduling, v, "crowd, per-stream or auto")),
            },
            scheduler_threads: match var(sched_threads)? {
                None => None,
                Some(v) => match v.parse::<usize>() {
                    Ok(n) if (1..=MAX_SCHEDULER_THREADS).contains(&n) => Some(n),
                    _ => return Err(bad(sched_threads, &v, &format!("1 to {MAX_SCHEDULER_THREADS}"))),
                },
            },
        };
        options.validate()?;
        Ok(options)
    }
}

fn threads(name: &str, v: Option<String>) -> Result<Option<usize>> {
    match v.as_deref() {
        None => Ok(None),
        Some("1") => Ok(Some(1)),
        Some("2") => Ok(Some(2)),
        Some(v) => Err(Error::InvalidArgument(format!("{name}={v:?}: expected 1 or 2"))),
    }
}

/// Whether a native computation should use two threads: the option when set, else two
/// when the machine has two or more cores and the work `pays` for the hand-overs.
pub(crate) fn two_threads(option: Option<usize>, pays: bool) -> bool {
    match option {
        Some(n) => n == 2,
        None => pays && std::thread::available_parallelism().map_or(1, |n| n.get()) >= 2,
    }
}

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
    /// How the models run (backends, threads, decode grouping, overlap, instruction set);
    /// automatic by default. The library never reads these from the environment.
    pub runtime: RuntimeOptions,
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
            runtime: RuntimeOptions::default(),
        }
    }
}

impl EngineConfig {
    /// Checks the ranges of every field but the publish name.
    pub fn validate(&self) -> Result<()> {
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
        // The publish name's syntax is checked where shared memory lives (`Engine::new`).
        self.runtime.validate()?;
        self.default_stream.validate()
    }
}

/// A classifier-free guidance scale (DESIGN §4), validated: finite and >= 0, rounded to
/// the f32 the logits are combined in (as the reference rounds it).
pub fn guidance_scale(g: f64) -> Result<f32> {
    if (0.0..=f32::MAX as f64).contains(&g) {
        Ok(g as f32)
    } else {
        Err(Error::InvalidArgument(format!("guidance must be finite and >= 0, got {g}")))
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
    /// Classifier-free guidance scale, finite and >= 0: how far the logits are pushed from
    /// the null condition's towards the prompt's (1 = the prompt alone; unset = the
    /// bundle's default). Costs a second token step per step.
    pub guidance: Option<f64>,
    /// `Some(true)`: frames are the model's raw output, without the contact-consistency
    /// stage (`crate::contact`). Unset = false: the stage is on.
    pub raw_output: Option<bool>,
    /// `Some(false)`: the contact stage keeps the resting object where the model's first
    /// frame put it. Unset = true: it is placed where the model's hand first closes on it
    /// (`crate::contact::GraspOnset`), the frames held back until then (at most
    /// `contact::PLACE_LOOKAHEAD`). Moot without the stage, with an anchored object or a
    /// continued stream.
    pub grasp_placement: Option<bool>,
    /// `Some(false)`: the contact stage leaves the model's legs as they are, so its feet may
    /// slide. Unset = true: a foot the model stands on stays planted (`crate::feet`). Moot
    /// without the stage.
    pub foot_lock: Option<bool>,
    /// Where the host's scene puts the character and the object (`crate::anchor`); unset:
    /// the model's own placement.
    pub anchor: Option<Anchor>,
    /// Start from where this earlier, ended stream of the same engine left off: its
    /// character's place, heading and last pose (blended from), its object and whether a
    /// hand holds it. Excludes `anchor`.
    pub continue_from: Option<u64>,
}

/// A position and a rotation in the host's world, in the engine's coordinate system (its
/// basis and units, as frames are): position (x, y, z), rotation a unit quaternion
/// (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    pub position: [f32; 3],
    pub rotation: [f32; 4],
}

/// Scene anchoring of one stream (docs/engine.md, "Scene anchoring").
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Anchor {
    /// The character's ground point (under the pelvis at the first frame) and heading
    /// (only the rotation about the up axis counts; identity faces the native +y axis).
    pub character: Option<Placement>,
    /// The object's start pose (its origin, as `object_translation`): the generated object
    /// starts there and the reach correction brings the hand to it.
    pub object: Option<Placement>,
    /// With `object` and without `character`: place the character at the model's own spot
    /// relative to the object (the "interaction spot") instead of reaching for it.
    pub place_character: bool,
}

/// |q| may differ from 1 by this much in a host's quaternion.
pub const UNIT_QUATERNION_TOLERANCE: f32 = 1e-3;

impl Placement {
    fn validate(&self, what: &str) -> Result<()> {
        if !self.position.iter().chain(&self.rotation).all(|v| v.is_finite()) {
            return Err(Error::InvalidArgument(format!("anchor: {what} has a non-finite value: {self:?}")));
        }
        let n = self.rotation.iter().map(|v| v * v).sum::<f32>().sqrt();
        if (n - 1.0).abs() > UNIT_QUATERNION_TOLERANCE {
            return Err(Error::InvalidArgument(format!(
                "anchor: {what} rotation is not a unit quaternion (|q| = {n}): {:?}",
                self.rotation
            )));
        }
        Ok(())
    }
}

impl Anchor {
    /// What can be checked without the bundle and the coordinate system (the generator
    /// checks the object's reach).
    pub fn validate(&self) -> Result<()> {
        if let Some(c) = &self.character {
            c.validate("character")?;
        }
        if let Some(o) = &self.object {
            o.validate("object")?;
        }
        if self.place_character && (self.object.is_none() || self.character.is_some()) {
            return Err(Error::InvalidArgument(
                "anchor: place_character needs the object's pose and no character placement".into(),
            ));
        }
        Ok(())
    }
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
            guidance: self.guidance.or(fallback.guidance),
            raw_output: self.raw_output.or(fallback.raw_output),
            grasp_placement: self.grasp_placement.or(fallback.grasp_placement),
            foot_lock: self.foot_lock.or(fallback.foot_lock),
            anchor: self.anchor.or(fallback.anchor),
            continue_from: self.continue_from.or(fallback.continue_from),
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
        if let Some(g) = self.guidance {
            guidance_scale(g)?;
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
        if let Some(a) = &self.anchor {
            a.validate()?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn parse(pairs: &[(&str, &str)]) -> Result<RuntimeOptions> {
        let map: HashMap<String, String> = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        RuntimeOptions::from_vars(|name| Ok(map.get(name).cloned()))
    }

    #[test]
    fn variables_map_to_fields() {
        assert_eq!(parse(&[]).unwrap(), RuntimeOptions::default());
        assert_eq!(parse(&[("COMGRASP_STEP", ""), ("COMGRASP_OVERLAP", " ")]).unwrap(), RuntimeOptions::default());
        let o = parse(&[
            ("COMGRASP_STEP", "Tract"),
            ("COMGRASP_DECODER", "native"),
            ("COMGRASP_STEP_THREADS", "1"),
            ("COMGRASP_DECODER_THREADS", "2"),
            ("COMGRASP_DECODE_GROUP", "8"),
            ("COMGRASP_OVERLAP", "0"),
            ("COMGRASP_NATIVE_ISA", "avx2"),
            ("COMGRASP_SCHEDULING", "per-stream"),
            ("COMGRASP_SCHEDULER_THREADS", "3"),
        ])
        .unwrap();
        assert_eq!(
            o,
            RuntimeOptions {
                step_backend: StepBackend::Tract,
                decoder_backend: Some(DecoderBackend::Native),
                step_threads: Some(1),
                decoder_threads: Some(2),
                decode_group: Some(8),
                overlap: Some(false),
                max_isa: Some(InstructionSet::Avx2),
                scheduling: Scheduling::PerStream,
                scheduler_threads: Some(3),
            }
        );
    }

    #[test]
    fn bad_values_name_the_variable() {
        for (k, v) in [
            ("COMGRASP_STEP", "gpu"),
            ("COMGRASP_DECODER", "onnx"),
            ("COMGRASP_STEP_THREADS", "3"),
            ("COMGRASP_DECODER_THREADS", "0"),
            ("COMGRASP_DECODE_GROUP", "9"),
            ("COMGRASP_DECODE_GROUP", "x"),
            ("COMGRASP_OVERLAP", "yes"),
            ("COMGRASP_NATIVE_ISA", "sse2"),
            ("COMGRASP_SCHEDULING", "threads"),
            ("COMGRASP_SCHEDULER_THREADS", "0"),
            ("COMGRASP_SCHEDULER_THREADS", "65"),
        ] {
            let e = parse(&[(k, v)]).unwrap_err().to_string();
            assert!(e.contains(k) && e.contains(v), "{k}={v}: {e}");
        }
    }

    #[test]
    fn validate_checks_ranges() {
        let ok = RuntimeOptions { step_threads: Some(2), decode_group: Some(1), ..Default::default() };
        assert!(ok.validate().is_ok());
        for bad in [
            RuntimeOptions { step_threads: Some(0), ..Default::default() },
            RuntimeOptions { decoder_threads: Some(3), ..Default::default() },
            RuntimeOptions { decode_group: Some(0), ..Default::default() },
            RuntimeOptions { decode_group: Some(MAX_DECODE_GROUP + 1), ..Default::default() },
            RuntimeOptions { scheduler_threads: Some(0), ..Default::default() },
            RuntimeOptions { scheduler_threads: Some(MAX_SCHEDULER_THREADS + 1), ..Default::default() },
        ] {
            assert!(matches!(bad.validate(), Err(Error::InvalidArgument(_))), "{bad:?}");
        }
        assert!(two_threads(Some(2), false) && !two_threads(Some(1), true) && !two_threads(None, false));
    }
}
