//! `comgrasp generate`: one prompt → all frames → a JSON or NPZ file, an animated glTF
//! binary and/or a PNG strip of key frames, plus a one-line summary with the numbers a
//! user asks first (how much motion, how fast it started) and what was written.
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use comgrasp::bvh;
use comgrasp::frame::{CG_BODY_JOINTS, CG_HAND_JOINTS, CG_NUM_JOINTS};
use comgrasp::{Anchor, CoordinateSystem, Engine, EngineConfig, Error, Frame, Placement, PollResult, StreamConfig};
use serde::Serialize;

use crate::npz;
use crate::png::Image;
use crate::scene::Scene;
use crate::{gltf, preview, Failure};

/// `comgrasp generate`: generates one motion and writes every frame to a file, an animated
/// glTF and/or a PNG strip of key frames (without any of them only the summary is printed).
#[derive(clap::Args)]
pub struct Args {
    /// Model bundle directory (e.g. models/tiny); default: the COMGRASP_BUNDLE environment
    /// variable, else the bundle built into the library.
    #[arg(long, value_name = "DIR")]
    bundle: Option<PathBuf>,
    /// What to do, e.g. "A woman drinks from the mug".
    #[arg(long, value_name = "PROMPT")]
    text: String,
    /// FILE.json (an array of frame objects) or FILE.npz (numpy arrays).
    #[arg(long, value_name = "FILE")]
    out: Option<String>,
    /// FILE.glb: animated glTF 2.0 binary (a skinned stand-in body on the SMPL-X skeleton, the
    /// object the prompt names, one animation); implies --coords gltf.
    #[arg(long, value_name = "FILE")]
    glb: Option<String>,
    /// FILE.png: a strip of 6 key frames (skeleton, object, contact).
    #[arg(long, value_name = "FILE")]
    preview: Option<String>,
    /// FILE.bvh: the body and fingers as BVH (y up, centimetres, ZXY Euler channels), and
    /// the object's track in FILE's stem + .object.bvh; implies --coords gltf.
    #[arg(long, value_name = "FILE")]
    bvh: Option<String>,
    /// Sampler seed (default: the bundle's).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Softmax temperature, >= 0; 0 = greedy (default: the bundle's).
    #[arg(long, value_name = "T", allow_negative_numbers = true)]
    temperature: Option<f64>,
    /// Sample among the K most likely tokens; 0 = all (default: the bundle's).
    #[arg(long, value_name = "K")]
    top_k: Option<u32>,
    /// No end before N token steps of 16 frames (default: the bundle's).
    #[arg(long, value_name = "N")]
    min_len: Option<u32>,
    /// End at N token steps at the latest (default: the bundle's).
    #[arg(long, value_name = "N")]
    max_len: Option<u32>,
    /// Classifier-free guidance scale, >= 0; 1 = the prompt alone (default: the bundle's).
    /// For a model trained with `train-gpt --text-dropout`; costs a second step per step.
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    guidance: Option<f64>,
    /// Coordinate system of the frames: native (z up, metres), gltf (y up), unity (y up,
    /// left-handed) or unreal (z up, left-handed, centimetres); default native, and gltf with
    /// --glb (another system conflicts with --glb).
    #[arg(long, value_name = "SYSTEM", ignore_case = true)]
    coords: Option<Coords>,
    /// Also compute the 55 world joint positions (joint_positions).
    #[arg(long)]
    fk: bool,
    /// The model's raw output: no contact-consistency stage (the object may float or drift,
    /// a hand may close on empty air).
    #[arg(long)]
    raw: bool,
    /// Keep the resting object where the model's first frame puts it, instead of placing it
    /// where the model's hand first closes on it (which holds frames back until that grasp).
    #[arg(long)]
    no_grasp_placement: bool,
    /// Leave the model's legs as they are (its feet may slide), instead of keeping a foot it
    /// stands on planted.
    #[arg(long)]
    free_feet: bool,
    /// Scene anchoring: the character's ground point and heading in the frames' coordinate
    /// system, X,Y,Z[,YAW] (YAW: degrees about the system's up axis; 0 faces native +y).
    #[arg(long, value_name = "X,Y,Z[,YAW]", value_parser = placement, allow_hyphen_values = true)]
    character: Option<[f32; 4]>,
    /// Scene anchoring: where the object starts, X,Y,Z[,YAW] (its origin; YAW about the up
    /// axis); the character reaches for it (within 0.8 m and 0.3-1.6 m above its ground).
    #[arg(long, value_name = "X,Y,Z[,YAW]", value_parser = placement, allow_hyphen_values = true)]
    object: Option<[f32; 4]>,
    /// With --object and without --character: place the character at the model's own spot
    /// relative to the object.
    #[arg(long, requires = "object", conflicts_with = "character")]
    place_character: bool,
    /// Another prompt that continues where the previous one left off (repeatable: --then
    /// "Drink from it" --then "Put it back down"); the frames form one timeline.
    #[arg(long, value_name = "TEXT")]
    then: Vec<String>,
}

/// `X,Y,Z[,YAW]` for --character / --object.
fn placement(v: &str) -> Result<[f32; 4], String> {
    let n: Vec<f32> =
        v.split(',').map(|x| x.trim().parse::<f32>().map_err(|e| format!("{x:?}: {e}"))).collect::<Result<_, _>>()?;
    match n[..] {
        [x, y, z] => Ok([x, y, z, 0.0]),
        [x, y, z, yaw] => Ok([x, y, z, yaw]),
        _ => Err(format!("expected X,Y,Z or X,Y,Z,YAW, got {} numbers", n.len())),
    }
}

/// `--coords` values.
#[derive(Clone, Copy, clap::ValueEnum)]
enum Coords {
    Native,
    Gltf,
    Unity,
    Unreal,
}

impl From<Coords> for CoordinateSystem {
    fn from(c: Coords) -> CoordinateSystem {
        match c {
            Coords::Native => CoordinateSystem::CG_COORDS_NATIVE,
            Coords::Gltf => CoordinateSystem::CG_COORDS_GLTF,
            Coords::Unity => CoordinateSystem::CG_COORDS_UNITY,
            Coords::Unreal => CoordinateSystem::CG_COORDS_UNREAL,
        }
    }
}

/// The parsed command line.
struct Options {
    /// Prompts that continue the first (`--then`).
    then: Vec<String>,
    /// `None`: the engine's default (COMGRASP_BUNDLE or the embedded bundle).
    bundle: Option<PathBuf>,
    text: String,
    out: Option<(PathBuf, Format)>,
    glb: Option<PathBuf>,
    preview: Option<PathBuf>,
    bvh: Option<PathBuf>,
    stream: StreamConfig,
    coords: CoordinateSystem,
    fk: bool,
}

#[derive(Clone, Copy)]
enum Format {
    Json,
    Npz,
}

pub fn run(args: Args) -> Result<(), Failure> {
    let opts = options(args).map_err(|m| Failure::Usage(format!("generate: {m}")))?;
    let t0 = Instant::now();

    let engine = Engine::new(EngineConfig {
        bundle_path: opts.bundle.clone(),
        coordinate_system: opts.coords,
        // The preview draws the skeleton from the engine's own joint positions.
        enable_fk: opts.fk || opts.preview.is_some(),
        // The CLI is where the COMGRASP_* runtime variables are read (the library never does).
        runtime: comgrasp::config::RuntimeOptions::from_env().map_err(engine_failure)?,
        ..EngineConfig::default()
    })
    .map_err(engine_failure)?;
    let bundle = engine.bundle().cloned().ok_or_else(|| Failure::Run("the engine has no model bundle".into()))?;
    let fps = bundle.manifest.fps;
    // Skeleton and object mesh before generating, so a broken mesh does not cost a run.
    let scene = if opts.glb.is_some() || opts.preview.is_some() {
        Some(Scene::load(&bundle, opts.coords, &opts.text).map_err(Failure::Run)?)
    } else {
        None
    };
    let load = t0.elapsed();

    let t_start = Instant::now();
    let mut frames: Vec<Frame> = Vec::new();
    let mut first_frame = None;
    let mut object = None;
    let mut previous = None;
    // The prompt, then each --then prompt continuing where the one before left off; one
    // timeline (frame_index and time_s run on, is_last only on the very last frame).
    for text in std::iter::once(&opts.text).chain(&opts.then) {
        let cfg = StreamConfig { continue_from: previous, ..opts.stream.clone() };
        let mut stream = engine.start(text, cfg).map_err(engine_failure)?;
        let offset = frames.len() as u64;
        if let Some(last) = frames.last_mut() {
            last.is_last = 0;
        }
        let mut f = Frame::default();
        loop {
            match stream.wait(&mut f, Duration::from_millis(100)) {
                PollResult::Frame => {
                    first_frame.get_or_insert_with(|| t_start.elapsed());
                    f.frame_index += offset;
                    f.time_s = f.frame_index as f64 / fps;
                    frames.push(f);
                }
                PollResult::Pending => {}
                PollResult::End => break,
                PollResult::Cancelled => return Err(Failure::Run("the stream was cancelled".into())),
                PollResult::Error => {
                    let msg = stream.error().map_or_else(|| "the stream failed".into(), |e| e.to_string());
                    return Err(Failure::Run(msg));
                }
            }
        }
        object.get_or_insert_with(|| {
            stream.object().map(|o| match &o.alias {
                Some(alias) => format!("object {} (prompt says {alias:?})", o.name),
                None => format!("object {} (the prompt names no catalogue object; using the first)", o.name),
            })
        });
        previous = Some(stream.id());
    }
    let generation = t_start.elapsed();
    let object = object.flatten();
    drop(engine);

    if let Some((path, format)) = &opts.out {
        write(path, *format, &frames, fps, opts.fk)
            .map_err(|e| Failure::Run(format!("cannot write {}: {e}", path.display())))?;
    }
    let mut wrote = Vec::new();
    if let (Some(path), Some(scene)) = (&opts.glb, &scene) {
        let bytes = gltf::glb(scene, &frames, &opts.text, fps).map_err(|e| Failure::Run(format!("glb: {e}")))?;
        write_file(path, &bytes)?;
        wrote.push(format!("glb {} ({} bytes)", path.display(), bytes.len()));
    }
    if let Some(path) = &opts.bvh {
        let r = &bundle.manifest.skeleton.rest_joints;
        let rest: [[f32; 3]; CG_NUM_JOINTS] = std::array::from_fn(|j| r[j]);
        let text = |t: comgrasp::Result<String>| t.map_err(|e| Failure::Run(format!("bvh: {e}")));
        write_file(path, text(bvh::body(&rest, &frames, opts.coords, fps))?.as_bytes())?;
        let stem = path.file_stem().map_or_else(Default::default, |s| s.to_string_lossy().into_owned());
        let track = path.with_file_name(format!("{stem}.object.bvh"));
        write_file(&track, text(bvh::object(&frames, opts.coords, fps))?.as_bytes())?;
        wrote.push(format!("bvh {} and {}", path.display(), track.display()));
    }
    if let (Some(path), Some(scene)) = (&opts.preview, &scene) {
        let p = preview::render(scene, &frames).map_err(|e| Failure::Run(format!("preview: {e}")))?;
        let png = p.image.encode().map_err(|e| Failure::Run(format!("cannot encode {}: {e}", path.display())))?;
        write_file(path, &png)?;
        let Image { width, height, .. } = p.image;
        let keys: Vec<String> = p.key_frames.iter().map(usize::to_string).collect();
        wrote.push(format!("preview {} ({width}x{height}, frames {})", path.display(), keys.join(",")));
    }
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let motion_s = frames.len() as f64 / fps;
    let mut line = format!(
        "{} frames, {motion_s:.2} s of motion at {fps} fps; first frame {} after start, generation {:.1} ms \
         ({:.0}x real time), bundle load {:.1} ms, total {:.1} ms",
        frames.len(),
        first_frame.map_or("none".into(), |d| format!("{:.1} ms", ms(d))),
        ms(generation),
        motion_s / generation.as_secs_f64(),
        ms(load),
        ms(t0.elapsed()),
    );
    if let Some(object) = object {
        line += &format!("; {object}");
    }
    if let Some((path, _)) = &opts.out {
        line += &format!("; wrote {}", path.display());
    }
    for w in wrote {
        line += &format!("; wrote {w}");
    }
    // A closed stdout (e.g. `| head -0`) is not worth a panic or an error.
    let _ = writeln!(std::io::stdout(), "{line}");
    Ok(())
}

/// Engine errors caused by the arguments (a bad sampling value, an over-long prompt) are
/// usage errors; the rest (bundle, inference, I/O) are run failures.
fn engine_failure(e: Error) -> Failure {
    match e {
        Error::InvalidArgument(_) => Failure::Usage(format!("generate: {e}")),
        e => Failure::Run(e.to_string()),
    }
}

/// Writes a whole output file; a failure names the file.
fn write_file(path: &Path, bytes: &[u8]) -> Result<(), Failure> {
    std::fs::write(path, bytes).map_err(|e| Failure::Run(format!("cannot write {}: {e}", path.display())))
}

/// --character / --object as an [`Anchor`]: YAW turns about the coordinate system's up axis.
fn anchor(
    character: Option<[f32; 4]>,
    object: Option<[f32; 4]>,
    place_character: bool,
    coords: CoordinateSystem,
) -> Option<Anchor> {
    if character.is_none() && object.is_none() {
        return None;
    }
    let (s, _) = coords.basis();
    // The up axis in the frames' basis (native +z mapped), then the quaternion about it.
    let up = comgrasp::skeleton::mat_vec(&s, &[0.0, 0.0, 1.0]);
    let place = |v: [f32; 4]| {
        let h = (v[3] as f64).to_radians() / 2.0;
        let q = [up[0] * h.sin(), up[1] * h.sin(), up[2] * h.sin(), h.cos()].map(|x| x as f32);
        Placement { position: [v[0], v[1], v[2]], rotation: q }
    };
    Some(Anchor { character: character.map(place), object: object.map(place), place_character })
}

/// The checks clap cannot make: output names and directories, --glb against --coords.
fn options(a: Args) -> Result<Options, String> {
    let stream = StreamConfig {
        seed: a.seed,
        temperature: a.temperature,
        top_k: a.top_k,
        min_len: a.min_len,
        max_len: a.max_len,
        guidance: a.guidance,
        raw_output: a.raw.then_some(true),
        grasp_placement: a.no_grasp_placement.then_some(false),
        foot_lock: a.free_feet.then_some(false),
        anchor: None,
        continue_from: None,
    };
    let (character, object, place_character, then) = (a.character, a.object, a.place_character, a.then);
    let (bundle, text, out, glb, preview, fk, bvh) = (a.bundle, a.text, a.out, a.glb, a.preview, a.fk, a.bvh);
    let coords = a.coords.map(CoordinateSystem::from);
    // Decide formats and check directories before generating, so a typo does not cost a
    // whole run.
    let out = match out {
        None => None,
        Some(p) => {
            let (path, ext) = output_path("--out", &p, &["json", "npz"])?;
            Some((path, if ext == "json" { Format::Json } else { Format::Npz }))
        }
    };
    let glb = glb.map(|p| output_path("--glb", &p, &["glb"]).map(|(path, _)| path)).transpose()?;
    let preview = preview.map(|p| output_path("--preview", &p, &["png"]).map(|(path, _)| path)).transpose()?;
    let bvh = bvh.map(|p| output_path("--bvh", &p, &["bvh"]).map(|(path, _)| path)).transpose()?;
    // A glb and a BVH are y up by definition: their frames must be in glTF's basis, whatever
    // else is written. An explicit other system is a contradiction, not something to override.
    let y_up = [("--glb", glb.is_some()), ("--bvh", bvh.is_some())].into_iter().find(|(_, on)| *on).map(|(f, _)| f);
    let coords = match (coords, y_up) {
        (Some(c), Some(flag)) if c != CoordinateSystem::CG_COORDS_GLTF => {
            return Err(format!(
                "{flag} is y up (the glTF basis), which conflicts with --coords {}; drop --coords or use --coords gltf",
                coords_name(c)
            ))
        }
        (_, Some(_)) => CoordinateSystem::CG_COORDS_GLTF,
        (c, None) => c.unwrap_or(CoordinateSystem::CG_COORDS_NATIVE),
    };
    let stream = StreamConfig { anchor: anchor(character, object, place_character, coords), ..stream };
    Ok(Options { bundle, text, then, out, glb, preview, bvh, stream, coords, fk })
}

fn coords_name(c: CoordinateSystem) -> &'static str {
    match c {
        CoordinateSystem::CG_COORDS_NATIVE => "native",
        CoordinateSystem::CG_COORDS_GLTF => "gltf",
        CoordinateSystem::CG_COORDS_UNITY => "unity",
        CoordinateSystem::CG_COORDS_UNREAL => "unreal",
    }
}

/// An output file name: its extension (lower-cased) must be one of `exts` and its
/// directory must exist.
fn output_path(option: &str, p: &str, exts: &[&str]) -> Result<(PathBuf, String), String> {
    let path = PathBuf::from(p);
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).unwrap_or_default();
    if !exts.contains(&ext.as_str()) {
        let names: Vec<String> = exts.iter().map(|e| format!(".{e}")).collect();
        return Err(format!("{option} {p:?}: the file name must end in {}", names.join(" or ")));
    }
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(if dir.exists() {
            format!("{option} {p:?}: {} is not a directory", dir.display())
        } else {
            format!("{option} {p:?}: directory {} does not exist", dir.display())
        });
    }
    Ok((path, ext))
}

fn write(path: &Path, format: Format, frames: &[Frame], fps: f64, fk: bool) -> std::io::Result<()> {
    let mut w = BufWriter::new(File::create(path)?);
    match format {
        Format::Json => write_json(&mut w, frames, fk)?,
        Format::Npz => npz::write(&mut w, &npz_arrays(frames, fps, fk))?,
    }
    w.into_inner().map_err(|e| e.into_error())?.sync_all()
}

/// One frame as JSON: the C frame's fields by name (reserved padding left out,
/// `joint_positions` only with `--fk`). Borrowed, so serializing copies nothing.
#[derive(Serialize)]
struct JsonFrame<'a> {
    frame_index: u64,
    time_s: f64,
    root_translation: &'a [f32; 3],
    root_rotation: &'a [f32; 4],
    body_rotations: &'a [[f32; 4]],
    left_hand_rotations: &'a [[f32; 4]],
    right_hand_rotations: &'a [[f32; 4]],
    object_translation: &'a [f32; 3],
    object_rotation: &'a [f32; 4],
    object_centre: &'a [f32; 3],
    left_wrist_to_object: &'a [f32; 3],
    right_wrist_to_object: &'a [f32; 3],
    contact_probability: &'a [f32; 2],
    contact: &'a [u8; 2],
    is_last: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    joint_positions: Option<&'a [[f32; 3]]>,
}

/// A JSON array with one frame object per line: valid JSON that still diffs and greps well.
fn write_json(w: &mut impl Write, frames: &[Frame], fk: bool) -> std::io::Result<()> {
    w.write_all(b"[")?;
    for (i, f) in frames.iter().enumerate() {
        w.write_all(if i == 0 { b"\n" } else { b",\n" })?;
        let jf = JsonFrame {
            frame_index: f.frame_index,
            time_s: f.time_s,
            root_translation: &f.root_translation,
            root_rotation: &f.root_rotation,
            body_rotations: &f.body_rotations,
            left_hand_rotations: &f.left_hand_rotations,
            right_hand_rotations: &f.right_hand_rotations,
            object_translation: &f.object_translation,
            object_rotation: &f.object_rotation,
            object_centre: &f.object_centre,
            left_wrist_to_object: &f.left_wrist_to_object,
            right_wrist_to_object: &f.right_wrist_to_object,
            contact_probability: &f.contact_probability,
            contact: &f.contact,
            is_last: f.is_last != 0,
            joint_positions: fk.then_some(&f.joint_positions[..]),
        };
        serde_json::to_writer(&mut *w, &jf)?;
    }
    w.write_all(b"\n]\n")
}

/// The frames as (T, ...) arrays, one per frame field, plus the scalar `fps`.
fn npz_arrays(frames: &[Frame], fps: f64, fk: bool) -> Vec<npz::Array> {
    let t = frames.len();
    let f32s = |name: &str, shape: &[usize], get: &dyn Fn(&Frame) -> &[f32]| {
        let mut full = vec![t];
        full.extend_from_slice(shape);
        npz::Array::f32(name, &full, frames.iter().flat_map(|f| get(f).iter().copied()))
    };
    let mut arrays = vec![
        f32s("root_translation", &[3], &|f| &f.root_translation),
        f32s("root_rotation", &[4], &|f| &f.root_rotation),
        f32s("body_rotations", &[CG_BODY_JOINTS, 4], &|f| f.body_rotations.as_flattened()),
        f32s("left_hand_rotations", &[CG_HAND_JOINTS, 4], &|f| f.left_hand_rotations.as_flattened()),
        f32s("right_hand_rotations", &[CG_HAND_JOINTS, 4], &|f| f.right_hand_rotations.as_flattened()),
        f32s("object_translation", &[3], &|f| &f.object_translation),
        f32s("object_rotation", &[4], &|f| &f.object_rotation),
        f32s("object_centre", &[3], &|f| &f.object_centre),
        f32s("left_wrist_to_object", &[3], &|f| &f.left_wrist_to_object),
        f32s("right_wrist_to_object", &[3], &|f| &f.right_wrist_to_object),
        f32s("contact_probability", &[2], &|f| &f.contact_probability),
        npz::Array::u8("contact", &[t, 2], frames.iter().flat_map(|f| f.contact)),
        npz::Array::scalar_f64("fps", fps),
    ];
    if fk {
        arrays.push(f32s("joint_positions", &[CG_NUM_JOINTS, 3], &|f| f.joint_positions.as_flattened()));
    }
    arrays
}
