//! The `comgrasp` command-line tool, run as a user would: `generate` on the tiny bundle to
//! JSON and NPZ (both files parsed back and checked against each other), and bad command
//! lines (a clear message and a non-zero exit code, never a panic).
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use comgrasp::bundle::npy::{self, NpyDtype};

const PROMPT: &str = "The man lifts a small cube.";

fn comgrasp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_comgrasp")).args(args).output().expect("run comgrasp")
}

fn tiny() -> String {
    // The repository root is this crate's (cli/) parent.
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/tiny").to_string_lossy().into_owned()
}

fn tmp(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("cli-{}-{name}", std::process::id()))
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Runs `generate` with `extra` arguments, asserts success, returns the summary's frame count.
fn generate(out: &Path, extra: &[&str]) -> usize {
    let tiny = tiny();
    let mut args = vec!["generate", "--bundle", &tiny, "--text", PROMPT, "--seed", "5", "--out"];
    let out_s = out.to_string_lossy();
    args.push(&out_s);
    args.extend_from_slice(extra);
    let o = comgrasp(&args);
    let (stdout, stderr) = (text(&o.stdout), text(&o.stderr));
    assert!(o.status.success(), "exit {:?}\n{stdout}\n{stderr}", o.status);
    // "N frames, S s of motion at F fps; first frame X ms after start, ..."
    assert_eq!(stdout.lines().count(), 1, "one summary line: {stdout}");
    assert!(stdout.contains(" s of motion at 30 fps; first frame ") && stdout.contains(" total "), "{stdout}");
    // "... generation G ms (Rx real time), ...": R is the seconds of motion over G.
    let number_before = |text: &str, marker: &str| -> f64 {
        let head = &text[..text.find(marker).unwrap_or_else(|| panic!("no {marker:?} in {text}"))];
        head.rsplit([' ', '(']).next().unwrap().parse().unwrap()
    };
    let (motion_s, generation_ms) = (number_before(&stdout, " s of motion"), number_before(&stdout, " ms ("));
    let rtf = number_before(&stdout, "x real time)");
    let want = motion_s * 1e3 / generation_ms;
    // G is printed to 0.1 ms: a short run's factor is only known to within 0.05 / G of itself.
    let tol = 0.5 + want * (0.051 / generation_ms + 0.005);
    assert!(rtf > 0.0 && (rtf - want).abs() <= tol, "real-time factor {rtf} vs {want}: {stdout}");
    stdout.split_whitespace().next().unwrap().parse().unwrap()
}

#[test]
fn generate_writes_json_and_npz_that_agree() {
    let (json_path, npz_path) = (tmp("motion.json"), tmp("motion.npz"));
    let n_json = generate(&json_path, &[]);
    let n_npz = generate(&npz_path, &["--fk"]);
    assert!(n_json > 0 && n_json.is_multiple_of(16), "{n_json} frames");
    assert_eq!(n_json, n_npz, "same seed and prompt, same length");
    let t = n_json;

    // JSON: an array of frame objects with named fields.
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json_path).unwrap()).unwrap();
    let frames = json.as_array().expect("a JSON array");
    assert_eq!(frames.len(), t);
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f["frame_index"].as_u64(), Some(i as u64));
        assert_eq!(f["is_last"].as_bool(), Some(i + 1 == t), "is_last on frame {i}");
        assert_eq!(f["body_rotations"].as_array().unwrap().len(), 21);
        assert_eq!(f["left_hand_rotations"].as_array().unwrap().len(), 15);
        assert_eq!(f["contact"].as_array().unwrap().len(), 2);
        assert!(f.get("joint_positions").is_none(), "no joint_positions without --fk");
        let q: Vec<f64> = f["root_rotation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-3, "unit quaternion, got norm {norm}");
    }

    // NPZ: a zip of .npy arrays with (T, ...) shapes.
    let arrays = read_npz(&std::fs::read(&npz_path).unwrap());
    let shape_of = |name: &str| -> &npy::Npy {
        &arrays.iter().find(|(n, _)| n == &format!("{name}.npy")).unwrap_or_else(|| panic!("no {name}.npy")).1
    };
    for (name, rest) in [
        ("root_translation", &[3][..]),
        ("root_rotation", &[4]),
        ("body_rotations", &[21, 4]),
        ("left_hand_rotations", &[15, 4]),
        ("right_hand_rotations", &[15, 4]),
        ("object_translation", &[3]),
        ("object_rotation", &[4]),
        ("object_centre", &[3]),
        ("contact_probability", &[2]),
        ("contact", &[2]),
        ("joint_positions", &[55, 3]),
    ] {
        let a = shape_of(name);
        let mut want = vec![t];
        want.extend_from_slice(rest);
        assert_eq!(a.shape, want, "{name}");
        let dtype = if name == "contact" { NpyDtype::U8 } else { NpyDtype::F32 };
        assert_eq!(a.dtype, dtype, "{name}");
    }
    let fps = shape_of("fps");
    assert!(fps.shape.is_empty() && fps.to_f64() == [30.0], "fps: {:?} {:?}", fps.shape, fps.to_f64());

    // Same seed, prompt and coordinates: the NPZ holds the JSON's numbers (f32 round-trips
    // exactly through JSON's shortest representation).
    let p = Path::new("root_translation.npy");
    let root = shape_of("root_translation").to_f32(p).unwrap();
    for (i, f) in frames.iter().enumerate() {
        let j: Vec<f32> =
            f["root_translation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
        assert_eq!(j, root[3 * i..3 * i + 3], "root_translation of frame {i}");
    }
    let _ = std::fs::remove_file(json_path);
    let _ = std::fs::remove_file(npz_path);
}

/// The entries of a stored (uncompressed) zip, via its central directory, CRCs checked.
fn read_npz(zip: &[u8]) -> Vec<(String, npy::Npy)> {
    let u16_at = |i: usize| u16::from_le_bytes([zip[i], zip[i + 1]]) as usize;
    let u32_at = |i: usize| u32::from_le_bytes(zip[i..i + 4].try_into().unwrap()) as usize;
    let end = zip.len() - 22;
    assert_eq!(u32_at(end), 0x0605_4b50, "end of central directory record (no comment)");
    let (count, mut at) = (u16_at(end + 10), u32_at(end + 16));
    let mut out = Vec::new();
    for _ in 0..count {
        assert_eq!(u32_at(at), 0x0201_4b50, "central directory header");
        assert_eq!(u16_at(at + 10), 0, "stored, not compressed");
        let (crc, size, name_len, extra, comment) =
            (u32_at(at + 16) as u32, u32_at(at + 20), u16_at(at + 28), u16_at(at + 30), u16_at(at + 32));
        let name = String::from_utf8(zip[at + 46..at + 46 + name_len].to_vec()).unwrap();
        let local = u32_at(at + 42);
        assert_eq!(u32_at(local), 0x0403_4b50, "local header of {name}");
        let data_at = local + 30 + u16_at(local + 26) + u16_at(local + 28);
        let data = zip[data_at..data_at + size].to_vec();
        assert_eq!(crc32(&data), crc, "CRC of {name}");
        let arr = npy::parse(Path::new(&name), data).unwrap_or_else(|e| panic!("{e}"));
        out.push((name, arr));
        at += 46 + name_len + extra + comment;
    }
    out
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

#[test]
fn bad_command_lines_fail_cleanly() {
    let tiny = tiny();
    let t = tiny.as_str();
    // (arguments, exit code, text the message must contain)
    let cases: &[(&[&str], i32, &str)] = &[
        // clap's messages (exit code 2, usage on stderr)
        (&[], 2, "Usage: comgrasp <COMMAND>"),
        (&["dance"], 2, "unrecognized subcommand 'dance'"),
        (&["generate"], 2, "--text <PROMPT>"),
        (&["generate", "--bundle", t], 2, "the following required arguments were not provided"),
        (&["generate", "--bundle", t, "--text"], 2, "a value is required for '--text <PROMPT>'"),
        (&["generate", "--bundle", t, "--text", "hi", "--seed", "many"], 2, "invalid value 'many' for '--seed <N>'"),
        (&["generate", "--bundle", t, "--text", "hi", "--coords", "blender"], 2, "possible values: native, gltf"),
        (&["generate", "--bundle", t, "--text", "hi", "--wobble"], 2, "unexpected argument '--wobble'"),
        (&["bench", "--stream-runs", "0"], 2, "--stream-runs"),
        (&["publish", "--text", "hi"], 2, "--name <NAME>"),
        // the command's own checks and the engine's (also exit code 2)
        (&["generate", "--bundle", t, "--text", "hi", "--out", "m.csv"], 2, "must end in .json or .npz"),
        (&["generate", "--bundle", t, "--text", "hi", "--out", "/nonexistent/m.json"], 2, "does not exist"),
        (&["generate", "--bundle", t, "--text", "hi", "--temperature", "-1"], 2, "temperature"),
        (&["generate", "--bundle", t, "--text", "hi", "--max-len", "100000"], 2, "max_len"),
        (&["generate", "--bundle", t, "--text", "  "], 2, "empty or only whitespace"),
        (&["generate", "--bundle", "/nonexistent/bundle", "--text", "hi"], 1, "/nonexistent/bundle"),
    ];
    for (args, code, needle) in cases {
        let o = comgrasp(args);
        let stderr = text(&o.stderr);
        assert_eq!(o.status.code(), Some(*code), "{args:?}: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: expected {needle:?} in {stderr:?}");
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(o.stdout.is_empty(), "{args:?} printed to stdout");
    }
}

#[test]
fn help_and_version() {
    let o = comgrasp(&["generate", "--help"]);
    assert!(o.status.success());
    let help = text(&o.stdout);
    for opt in [
        "--bundle",
        "--text",
        "--out",
        "--seed",
        "--temperature",
        "--top-k",
        "--min-len",
        "--max-len",
        "--coords",
        "--fk",
    ] {
        assert!(help.contains(opt), "help lacks {opt}");
    }
    let o = comgrasp(&["--version"]);
    assert!(o.status.success());
    let version = text(&o.stdout);
    assert_eq!(
        version.trim(),
        format!("comgrasp {} (C ABI {})", env!("CARGO_PKG_VERSION"), comgrasp::ffi::CG_ABI_VERSION)
    );
    for command in ["bench", "publish", "subscribe", "shm-bench"] {
        let o = comgrasp(&[command, "--help"]);
        assert!(o.status.success() && text(&o.stdout).contains("Usage: comgrasp"), "{command} --help");
    }
}

#[cfg(unix)]
#[test]
fn non_utf8_argument_is_an_error_not_a_panic() {
    use std::os::unix::ffi::OsStrExt;
    let bad = std::ffi::OsStr::from_bytes(b"caf\xe9");
    let o = Command::new(env!("CARGO_BIN_EXE_comgrasp")).args(["generate", "--text"]).arg(bad).output().unwrap();
    let stderr = text(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("invalid UTF-8") && !stderr.contains("panicked"), "{stderr}");
}

#[test]
fn the_crowd_bench_runs_its_streams_at_the_guidance_it_is_given() {
    let tiny = tiny();
    let crowd = |guidance: &str| {
        comgrasp(&[
            "bench",
            "--bundle",
            &tiny,
            "--streams",
            "2",
            "--rounds",
            "1",
            "--probes",
            "1",
            "--steps",
            "2",
            "--crowd-only",
            "--json",
            &format!("--guidance={guidance}"),
        ])
    };
    for g in [1.0, 2.0] {
        let o = crowd(&g.to_string());
        assert!(o.status.success(), "{}", text(&o.stderr));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("one JSON object");
        assert_eq!(v["guidance"].as_f64(), Some(g), "{v}");
        let row = &v["rows"][0];
        assert_eq!(row["streams"].as_u64(), Some(2), "{v}");
        assert!(row["crowd"]["total_rtf"].as_f64().unwrap() > 0.0, "{v}");
    }
    // The scale reaches every stream, so a bad one is the engine's clear error.
    let o = crowd("-1");
    let stderr = text(&o.stderr);
    assert!(!o.status.success() && stderr.contains("guidance") && !stderr.contains("panicked"), "{stderr}");
}
