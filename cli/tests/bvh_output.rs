//! `comgrasp generate --bvh` on the tiny bundle, read back by a real BVH parser (the `bvh`
//! package from PyPI, in the project's venv: scripts/setup_python.sh installs it with the
//! training test extras) whose forward kinematics must reproduce the engine's own
//! `joint_positions` (`--fk`, the same run) within 1 mm at every joint and frame, and the
//! object track the frames' object pose (cli/tests/bvh_check.py). Also: the options that
//! conflict with a y-up file are refused.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn comgrasp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_comgrasp")).args(args).output().expect("run comgrasp")
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("cli/ has a parent")
}

fn tmp(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("bvh-{}-{name}", std::process::id()))
}

#[test]
fn bvh_read_back_by_a_parser_matches_the_engines_joints() {
    let (bvh, npz) = (tmp("m.bvh"), tmp("m.npz"));
    let tiny = root().join("models/tiny");
    let o = comgrasp(&[
        "generate",
        "--bundle",
        tiny.to_str().unwrap(),
        "--text",
        "Someone lifts the mug with both hands",
        "--seed",
        "4",
        "--min-len",
        "4",
        "--max-len",
        "4",
        "--fk",
        "--bvh",
        bvh.to_str().unwrap(),
        "--out",
        npz.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary = String::from_utf8_lossy(&o.stdout);
    let track = tmp("m.object.bvh");
    assert!(summary.contains(&format!("wrote bvh {} and {}", bvh.display(), track.display())), "{summary}");
    let text = std::fs::read_to_string(&bvh).unwrap();
    assert!(text.starts_with("HIERARCHY\nROOT pelvis\n"));
    assert!(text.contains("Frames: 64\nFrame Time: 0.03333333\n"), "4 steps of 16 frames at 30 fps");
    assert_eq!(text.matches("CHANNELS 3 Zrotation Xrotation Yrotation").count(), 54, "every joint but the root");

    let python = root().join(".venv/bin/python");
    assert!(python.exists(), "{} is missing: run scripts/setup_python.sh", python.display());
    let check = Command::new(&python)
        .arg(root().join("cli/tests/bvh_check.py"))
        .args([&bvh, &track, &npz, &tiny])
        .output()
        .expect("run bvh_check.py");
    let out = String::from_utf8_lossy(&check.stdout);
    assert!(check.status.success(), "{out}{}", String::from_utf8_lossy(&check.stderr));
    assert!(out.starts_with("55 joints x 64 frames"), "{out}");
}

#[test]
fn bvh_is_y_up_and_named_bvh() {
    let tiny = root().join("models/tiny");
    let base = ["generate", "--bundle", tiny.to_str().unwrap(), "--text", "A mug", "--max-len", "1"];
    let path = tmp("x.bvh");
    let o = comgrasp(&[&base[..], &["--bvh", path.to_str().unwrap(), "--coords", "unreal"]].concat());
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--bvh is y up"), "{}", String::from_utf8_lossy(&o.stderr));
    let wrong = tmp("x.txt");
    let o = comgrasp(&[&base[..], &["--bvh", wrong.to_str().unwrap()]].concat());
    assert_eq!(o.status.code(), Some(2));
    assert!(!wrong.exists());
}
