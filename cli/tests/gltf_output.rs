//! `comgrasp generate --glb/--preview` on the tiny bundle, checked from the outside:
//! the Khronos glTF validator accepts the glb with no error and no warning; the glb read
//! back (a small reader here) and evaluated at every frame reproduces the engine's own
//! forward kinematics from a separate `--coords gltf --fk` run; the PNG decodes (the `png`
//! crate checks CRCs, the zlib stream and its Adler-32) to six panels, none blank; bad output paths fail with a message instead of a panic.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use serde_json::Value;

const PROMPT: &str = "A woman drinks from the mug";
/// Three token steps (48 frames): short, and min = max makes the length independent of
/// the sampled End token.
const LENGTH: [&str; 4] = ["--min-len", "3", "--max-len", "3"];
const SEED: &str = "11";

fn comgrasp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_comgrasp")).args(args).output().expect("run comgrasp")
}

/// The repository root (this crate is its cli/ member).
fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("cli/ has a parent")
}

fn tiny() -> String {
    root().join("models/tiny").to_string_lossy().into_owned()
}

fn tmp(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("gltf-{}-{name}", std::process::id()))
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// The outputs every test reads, generated once per test binary.
struct Generated {
    glb_path: PathBuf,
    glb: Vec<u8>,
    png: Vec<u8>,
    summary: String,
    /// Frames of the reference run (`--coords gltf --fk --out`), as JSON objects.
    reference: Vec<Value>,
}

fn generated() -> &'static Generated {
    static G: OnceLock<Generated> = OnceLock::new();
    G.get_or_init(|| {
        let tiny = tiny();
        let (glb_path, png_path, json_path) = (tmp("motion.glb"), tmp("motion.png"), tmp("reference.json"));
        let (glb_s, png_s, json_s) =
            (glb_path.to_string_lossy(), png_path.to_string_lossy(), json_path.to_string_lossy());
        let mut args =
            vec!["generate", "--bundle", &tiny, "--text", PROMPT, "--seed", SEED, "--glb", &glb_s, "--preview", &png_s];
        args.extend(LENGTH);
        let o = comgrasp(&args);
        let summary = text(&o.stdout);
        assert!(o.status.success(), "generate --glb failed: {}\n{summary}", text(&o.stderr));
        // The reference: same prompt and seed, the engine's FK in glTF coordinates. A
        // separate run, so the glb run must itself have switched to glTF coordinates.
        let mut args = vec![
            "generate", "--bundle", &tiny, "--text", PROMPT, "--seed", SEED, "--coords", "gltf", "--fk", "--out",
            &json_s,
        ];
        args.extend(LENGTH);
        let o = comgrasp(&args);
        assert!(o.status.success(), "reference run failed: {}", text(&o.stderr));
        let reference: Value = serde_json::from_slice(&std::fs::read(&json_path).unwrap()).unwrap();
        Generated {
            glb: std::fs::read(&glb_path).unwrap(),
            png: std::fs::read(&png_path).unwrap(),
            glb_path,
            summary,
            reference: reference.as_array().unwrap().clone(),
        }
    })
}

#[test]
fn summary_names_what_was_written() {
    let g = generated();
    assert_eq!(g.summary.lines().count(), 1, "{}", g.summary);
    assert!(g.summary.starts_with("48 frames, "), "{}", g.summary);
    let want = format!("wrote glb {} ({} bytes)", g.glb_path.display(), g.glb.len());
    assert!(g.summary.contains(&want), "{want:?} not in {}", g.summary);
    assert!(g.summary.contains("; object mug (prompt says \"mug\"); "), "{}", g.summary);
    assert!(
        g.summary.contains("; wrote preview ") && g.summary.contains("(1536x320, frames 0,9,19,28,38,47)"),
        "{}",
        g.summary
    );
}

#[test]
fn khronos_validator_reports_no_errors_or_warnings() {
    let g = generated();
    let validator = root().join(".tools/node/node_modules/gltf-validator/package.json");
    assert!(
        validator.is_file(),
        "the Khronos glTF validator is not installed ({} missing): run `bash scripts/setup_node.sh`",
        validator.display()
    );
    let o = Command::new("node")
        .arg(root().join("tests/gltf/validate.mjs"))
        .arg(&g.glb_path)
        .output()
        .expect("cannot run `node` (needed for the glTF validator; see scripts/setup_node.sh)");
    let stdout = text(&o.stdout);
    assert!(o.status.code().is_some_and(|c| c <= 1), "validate.mjs could not run: {}\n{stdout}", text(&o.stderr));
    let report: Value = serde_json::from_str(&stdout).expect("validate.mjs prints the report as JSON");
    let issues = &report["issues"];
    assert_eq!(
        (issues["numErrors"].as_u64(), issues["numWarnings"].as_u64()),
        (Some(0), Some(0)),
        "validator issues: {:#}",
        issues["messages"]
    );
    assert!(o.status.success());
    let info = &report["info"];
    assert_eq!((info["animationCount"].as_u64(), info["hasSkins"].as_bool()), (Some(1), Some(true)), "{info:#}");
}

// ---------------------------------------------------------------------------------------
// A minimal glb reader and glTF node evaluator.

struct Glb {
    json: Value,
    bin: Vec<u8>,
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn read_glb(b: &[u8]) -> Glb {
    assert_eq!(&b[..4], b"glTF");
    assert_eq!(u32_at(b, 4), 2, "glb version");
    assert_eq!(u32_at(b, 8) as usize, b.len(), "glb length field");
    let json_len = u32_at(b, 12) as usize;
    assert_eq!(&b[16..20], b"JSON");
    let json = serde_json::from_slice(&b[20..20 + json_len]).expect("JSON chunk parses");
    let at = 20 + json_len;
    let bin_len = u32_at(b, at) as usize;
    assert_eq!(&b[at + 4..at + 8], b"BIN\0");
    assert_eq!(at + 8 + bin_len, b.len(), "exactly two chunks");
    Glb { json, bin: b[at + 8..].to_vec() }
}

impl Glb {
    /// The FLOAT data of an accessor, tightly packed.
    fn floats(&self, accessor: usize) -> Vec<f32> {
        let a = &self.json["accessors"][accessor];
        assert_eq!(a["componentType"], 5126, "accessor {accessor} is FLOAT");
        let width = match a["type"].as_str().unwrap() {
            "SCALAR" => 1,
            "VEC3" => 3,
            "VEC4" => 4,
            "MAT4" => 16,
            t => panic!("unexpected accessor type {t}"),
        };
        let view = &self.json["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
        assert!(view.get("byteStride").is_none_or(|s| s.as_u64() == Some(4 * width as u64)));
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize + a["byteOffset"].as_u64().unwrap_or(0) as usize;
        let n = a["count"].as_u64().unwrap() as usize * width;
        (0..n).map(|i| f32::from_le_bytes(self.bin[start + 4 * i..start + 4 * i + 4].try_into().unwrap())).collect()
    }

    fn node(&self, i: usize) -> &Value {
        &self.json["nodes"][i]
    }
}

type Mat3 = [[f64; 3]; 3];

fn quat_to_matrix(q: [f64; 4]) -> Mat3 {
    let [x, y, z, w] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn mat_vec(a: &Mat3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| a[i][k] * v[k]).sum())
}

fn vec3(v: &Value) -> [f64; 3] {
    std::array::from_fn(|k| v[k].as_f64().unwrap())
}

fn vec4(v: &Value) -> [f64; 4] {
    std::array::from_fn(|k| v[k].as_f64().unwrap())
}

/// Every node's local TRS at keyframe `k` of animation 0: the channel's k-th output where a
/// channel targets it, else the node's own translation / rotation.
fn local_pose(glb: &Glb, k: usize) -> Vec<([f64; 3], [f64; 4])> {
    let nodes = glb.json["nodes"].as_array().unwrap();
    let mut pose: Vec<([f64; 3], [f64; 4])> = nodes
        .iter()
        .map(|n| {
            assert!(n.get("matrix").is_none() && n.get("scale").is_none(), "TRS only: {n}");
            let t = n.get("translation").map_or([0.0; 3], vec3);
            let r = n.get("rotation").map_or([0.0, 0.0, 0.0, 1.0], vec4);
            (t, r)
        })
        .collect();
    let anim = &glb.json["animations"][0];
    for ch in anim["channels"].as_array().unwrap() {
        let s = &anim["samplers"][ch["sampler"].as_u64().unwrap() as usize];
        assert_eq!(s["interpolation"], "LINEAR");
        let out = glb.floats(s["output"].as_u64().unwrap() as usize);
        let node = ch["target"]["node"].as_u64().unwrap() as usize;
        match ch["target"]["path"].as_str().unwrap() {
            "translation" => pose[node].0 = std::array::from_fn(|c| out[3 * k + c] as f64),
            "rotation" => pose[node].1 = std::array::from_fn(|c| out[4 * k + c] as f64),
            p => panic!("unexpected channel path {p}"),
        }
    }
    pose
}

/// World (rotation, position) of every node: world = parent world · T(t) · R(q).
fn world(glb: &Glb, pose: &[([f64; 3], [f64; 4])]) -> Vec<(Mat3, [f64; 3])> {
    let nodes = glb.json["nodes"].as_array().unwrap();
    let mut parent = vec![None; nodes.len()];
    for (i, n) in nodes.iter().enumerate() {
        for c in n.get("children").and_then(Value::as_array).into_iter().flatten() {
            let c = c.as_u64().unwrap() as usize;
            assert!(parent[c].replace(i).is_none(), "node {c} has two parents");
        }
    }
    fn eval(
        i: usize,
        parent: &[Option<usize>],
        pose: &[([f64; 3], [f64; 4])],
        memo: &mut Vec<Option<(Mat3, [f64; 3])>>,
    ) -> (Mat3, [f64; 3]) {
        if let Some(w) = memo[i] {
            return w;
        }
        let (t, q) = pose[i];
        let r = quat_to_matrix(q);
        let w = match parent[i] {
            None => (r, t),
            Some(p) => {
                let (pr, pt) = eval(p, parent, pose, memo);
                let o = mat_vec(&pr, t);
                (mat_mul(&pr, &r), [pt[0] + o[0], pt[1] + o[1], pt[2] + o[2]])
            }
        };
        memo[i] = Some(w);
        w
    }
    let mut memo = vec![None; nodes.len()];
    (0..nodes.len()).map(|i| eval(i, &parent, pose, &mut memo)).collect()
}

#[test]
fn glb_skeleton_and_object_reproduce_the_engine_frames() {
    let g = generated();
    let glb = read_glb(&g.glb);
    let frames = &g.reference;
    let t = frames.len();
    assert_eq!(t, 48);

    // Joint nodes 0..55 carry the bundle's joint names; the skin binds exactly them.
    let manifest: Value =
        serde_json::from_slice(&std::fs::read(root().join("models/tiny/manifest.json")).unwrap()).unwrap();
    let names = manifest["skeleton"]["joint_names"].as_array().unwrap();
    assert_eq!(names.len(), 55);
    for (j, name) in names.iter().enumerate() {
        assert_eq!(&glb.node(j)["name"], name, "node {j}");
    }
    let skin = &glb.json["skins"][0];
    assert_eq!(skin["joints"], Value::from((0..55).collect::<Vec<u64>>()));
    let scene_nodes = glb.json["scenes"][0]["nodes"].as_array().unwrap();
    assert!(scene_nodes.contains(&Value::from(0)), "the pelvis is a scene root (no parent adds a translation)");

    // The bind pose (rest TRS) times the inverse bind matrices is the identity.
    let rest: Vec<([f64; 3], [f64; 4])> = (0..glb.json["nodes"].as_array().unwrap().len())
        .map(|i| {
            let n = glb.node(i);
            (n.get("translation").map_or([0.0; 3], vec3), n.get("rotation").map_or([0.0, 0.0, 0.0, 1.0], vec4))
        })
        .collect();
    let bind = world(&glb, &rest);
    let ibm = glb.floats(skin["inverseBindMatrices"].as_u64().unwrap() as usize);
    for j in 0..55 {
        let m = &ibm[16 * j..16 * j + 16]; // column-major
        let (r, p) = bind[j];
        for i in 0..3 {
            for c in 0..3 {
                let prod: f64 = (0..3).map(|k| r[i][k] * m[4 * c + k] as f64).sum();
                assert!((prod - f64::from(u8::from(i == c))).abs() < 1e-6, "joint {j}: bind rotation · IBM");
            }
            let tr: f64 = (0..3).map(|k| r[i][k] * m[12 + k] as f64).sum::<f64>() + p[i];
            assert!(tr.abs() < 1e-5, "joint {j}: bind translation · IBM = {tr}");
        }
    }

    // Sampler input = the frame times.
    let anim = &glb.json["animations"][0];
    let input = glb.floats(anim["samplers"][0]["input"].as_u64().unwrap() as usize);
    assert_eq!(input.len(), t);
    for (k, f) in frames.iter().enumerate() {
        assert_eq!(input[k], f["time_s"].as_f64().unwrap() as f32, "time of frame {k}");
    }

    // Every frame: glTF node evaluation = the engine's FK, and the object node = the frame's object pose.
    let object_node = glb.json["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .position(|n| n["name"] == "mug")
        .expect("an object node named mug");
    let mut worst = 0.0f64;
    for (k, f) in frames.iter().enumerate() {
        let w = world(&glb, &local_pose(&glb, k));
        let fk = f["joint_positions"].as_array().unwrap();
        for j in 0..55 {
            let want = vec3(&fk[j]);
            for c in 0..3 {
                let d = (w[j].1[c] - want[c]).abs();
                worst = worst.max(d);
                assert!(d <= 1e-4, "frame {k} joint {j} ({}): glb {:?} vs engine {want:?}", names[j], w[j].1);
            }
        }
        let (r, p) = w[object_node];
        let (want_p, want_r) = (vec3(&f["object_translation"]), quat_to_matrix(vec4(&f["object_rotation"])));
        for i in 0..3 {
            assert!((p[i] - want_p[i]).abs() <= 1e-6, "frame {k}: object position {p:?} vs {want_p:?}");
            for c in 0..3 {
                assert!((r[i][c] - want_r[i][c]).abs() <= 1e-5, "frame {k}: object rotation");
            }
        }
    }
    eprintln!("largest glb-vs-engine joint difference: {worst:.2e} m");

    // The table top the mug starts on: a static, level quad in the scene at the height of
    // the first frame's mug bottom (glTF: y up), under the mug.
    let table = glb.json["nodes"].as_array().unwrap().iter().position(|n| n["name"] == "table");
    let table = table.expect("a table node (the tiny bundle's mug starts above the ground)");
    assert!(scene_nodes.contains(&Value::from(table)));
    let mesh = &glb.json["meshes"][glb.node(table)["mesh"].as_u64().unwrap() as usize];
    let top = glb.floats(mesh["primitives"][0]["attributes"]["POSITION"].as_u64().unwrap() as usize);
    assert_eq!(top.len(), 12);
    let heights: Vec<f32> = top.chunks(3).map(|p| p[1]).collect();
    assert!(heights.iter().all(|h| (h - heights[0]).abs() < 1e-6), "level: {heights:?}");
    let mug = vec3(&frames[0]["object_centre"]);
    let half =
        manifest["objects"].as_array().unwrap().iter().find(|o| o["name"] == "mug").unwrap()["half_extents"].clone();
    // The object's own (native) axis k is S e_k in glTF (S: (x, y, z) -> (x, z, -y)).
    let s: Mat3 = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]];
    let r = mat_mul(&quat_to_matrix(vec4(&frames[0]["object_rotation"])), &s);
    let bottom = mug[1] - (0..3).map(|k| r[1][k].abs() * half[k].as_f64().unwrap()).sum::<f64>();
    assert!((heights[0] as f64 - bottom).abs() < 1e-4, "table at {} vs the mug's bottom {bottom}", heights[0]);
    let (xs, zs): (Vec<f64>, Vec<f64>) = top.chunks(3).map(|p| (p[0] as f64, p[2] as f64)).unzip();
    let inside = |v: f64, vs: &[f64]| {
        vs.iter().cloned().fold(f64::INFINITY, f64::min) <= v
            && v <= vs.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
    };
    assert!(inside(mug[0], &xs) && inside(mug[2], &zs), "the mug starts over the table");
}

// ---------------------------------------------------------------------------------------
// PNG: decoded by the `png` crate (chunk CRCs, zlib stream and Adler-32 checked there).

#[test]
fn preview_png_is_well_formed_and_not_blank() {
    let bytes = &generated().png;
    let mut reader = png::Decoder::new(std::io::Cursor::new(&bytes[..])).read_info().expect("a valid PNG header");
    let mut rgb = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut rgb).expect("valid image data");
    let (w, h) = (info.width as usize, info.height as usize);
    assert_eq!((w, h), (6 * 256, 320), "six 256×320 panels");
    assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Rgb, png::BitDepth::Eight), "8-bit RGB");
    assert_eq!(info.buffer_size(), 3 * w * h);
    reader.finish().expect("a complete file (IEND)");

    // Not blank: plenty of pixels differ from the background (top-left pixel), in several colours.
    let pixels: Vec<[u8; 3]> = rgb[..3 * w * h].chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    let background = pixels[0];
    let drawn = pixels.iter().filter(|&&p| p != background).count();
    let mut colours = pixels.clone();
    colours.sort_unstable();
    colours.dedup();
    assert!(drawn > 2000 && colours.len() >= 5, "{drawn} drawn pixels, {} colours", colours.len());
    // Every panel has something drawn in it.
    for panel in 0..6 {
        let n = (0..h)
            .flat_map(|y| (panel * 256..panel * 256 + 256).map(move |x| (x, y)))
            .filter(|&(x, y)| pixels[y * w + x] != background)
            .count();
        assert!(n > 300, "panel {panel}: {n} drawn pixels");
    }
}

// ---------------------------------------------------------------------------------------

#[test]
fn bad_output_paths_fail_cleanly() {
    let tiny = tiny();
    let t = tiny.as_str();
    // A directory where the file should go: only writing can find out (after generating).
    let dir_glb = tmp("is-a-dir.glb");
    let dir_png = tmp("is-a-dir.png");
    for d in [&dir_glb, &dir_png] {
        std::fs::create_dir_all(d).unwrap();
    }
    let (dir_glb, dir_png) = (dir_glb.to_string_lossy().into_owned(), dir_png.to_string_lossy().into_owned());
    let plain = tmp("plain-file");
    std::fs::write(&plain, b"x").unwrap();
    let under_file = plain.join("m.glb").to_string_lossy().into_owned();
    let gen = ["generate", "--bundle", t, "--text", PROMPT, "--min-len", "1", "--max-len", "1"];
    let cases: Vec<(Vec<&str>, i32, String)> = vec![
        ([&gen[..], &["--glb", &dir_glb]].concat(), 1, format!("cannot write {dir_glb}")),
        ([&gen[..], &["--preview", &dir_png]].concat(), 1, format!("cannot write {dir_png}")),
        ([&gen[..], &["--glb", &under_file]].concat(), 2, "is not a directory".into()),
        (
            [&gen[..], &["--glb", "/nonexistent/dir/m.glb"]].concat(),
            2,
            "--glb \"/nonexistent/dir/m.glb\": directory /nonexistent/dir does not exist".into(),
        ),
        ([&gen[..], &["--glb", "m.gltf"]].concat(), 2, "must end in .glb".into()),
        ([&gen[..], &["--preview", "m.jpg"]].concat(), 2, "must end in .png".into()),
        ([&gen[..], &["--glb", "m.glb", "--coords", "unity"]].concat(), 2, "conflicts with --coords unity".into()),
        ([&gen[..], &["--glb"]].concat(), 2, "a value is required for '--glb <FILE>'".into()),
    ];
    for (args, code, needle) in &cases {
        let o = comgrasp(args);
        let stderr = text(&o.stderr);
        assert_eq!(o.status.code(), Some(*code), "{args:?}: {stderr}");
        assert!(stderr.contains(needle.as_str()), "{args:?}: expected {needle:?} in {stderr:?}");
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(o.stdout.is_empty(), "{args:?} printed a summary");
    }
}

#[test]
fn a_prompt_without_a_catalogue_object_uses_the_first_and_says_so() {
    let tiny = tiny();
    let glb = tmp("wave.glb");
    let glb_s = glb.to_string_lossy();
    let o = comgrasp(&[
        "generate",
        "--bundle",
        &tiny,
        "--text",
        "A man waves",
        "--min-len",
        "1",
        "--max-len",
        "1",
        "--glb",
        &glb_s,
    ]);
    let stdout = text(&o.stdout);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(stdout.contains("object mug (the prompt names no catalogue object; using the first)"), "{stdout}");
    let g = read_glb(&std::fs::read(&glb).unwrap());
    assert_eq!(g.node(56)["name"], "mug");
}
