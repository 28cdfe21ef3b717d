//! Hostile bundles, beyond the single-defect cases of `bundle_corrupt.rs`: damaged graphs
//! whose digest was recomputed (so the ONNX reader itself must fail cleanly), a tokenizer of
//! the wrong kind, manifests with absurd numbers, symlink loops, FIFOs and devices where
//! files should be, unreadable directories and a 100 MB manifest.
//!
//! Every case must give an `Error::Bundle` naming the file at fault and the reason, never be
//! accepted, never panic, and finish within seconds: each load runs on its own thread under
//! a time limit, so a hang fails the test instead of stalling CI.
#![cfg(unix)]
mod bundle_support;

use std::ffi::CString;
use std::fs;
use std::os::unix::fs::{symlink, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use bundle_support::*;
use comgrasp::Bundle;
use comgrasp::Error;

/// Longest any single load may take here (the tiny bundle loads in well under a second).
const LIMIT: Duration = Duration::from_secs(30);

/// Loads `dir` on another thread; `Err(message)` if it panicked or did not finish in time.
fn load_within(dir: &Path, limit: Duration) -> Result<comgrasp::Result<()>, String> {
    let (tx, rx) = mpsc::channel();
    let d = dir.to_path_buf();
    let t0 = Instant::now();
    std::thread::spawn(move || {
        let r = std::panic::catch_unwind(|| Bundle::load(&d).map(|_| ()));
        let _ = tx.send(r);
    });
    match rx.recv_timeout(limit) {
        Ok(Ok(r)) => {
            println!("  ({} loaded or failed in {:?})", dir.display(), t0.elapsed());
            Ok(r)
        }
        Ok(Err(p)) => Err(format!(
            "Bundle::load panicked: {:?}",
            p.downcast_ref::<String>().map(String::as_str).or_else(|| p.downcast_ref::<&str>().copied())
        )),
        Err(_) => Err(format!("Bundle::load did not finish within {limit:?} (hang)")),
    }
}

/// Expects an `Error::Bundle` about `file` (see [`assert_bundle_error`]) from a load that
/// must finish within [`LIMIT`].
fn expect_bundle_error(dir: &Path, file: &str, needles: &[&str]) -> String {
    let loaded = load_within(dir, LIMIT).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    assert_bundle_error(loaded, dir, file, needles)
}

/// Writes `bytes` as `rel` and records its new size and SHA-256 in the manifest (also in
/// `text_encoder.sha256` when listed there), so only the file's content can be at fault.
fn replace_with_matching_hash(b: &TempBundle, rel: &str, bytes: &[u8]) {
    fs::write(b.path(rel), bytes).unwrap();
    let sha = comgrasp::bundle::verify::sha256_hex(bytes);
    b.edit_manifest(|m| {
        m["files"][rel]["sha256"] = sha.clone().into();
        m["files"][rel]["bytes"] = bytes.len().into();
        if m["text_encoder"]["sha256"].get(rel).is_some() {
            m["text_encoder"]["sha256"][rel] = sha.into();
        }
    });
}

fn mkfifo(p: &Path) {
    let c = CString::new(p.as_os_str().as_encoded_bytes()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0, "mkfifo {}", p.display());
}

fn is_root() -> bool {
    unsafe { libc::geteuid() == 0 }
}

/// A fresh empty scratch directory.
fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("bundle_hostile-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&d);
    fs::create_dir_all(&d).unwrap();
    d
}

// ---------------------------------------------------------------------------------------
// Damaged graphs that pass the digest check.

#[test]
fn truncated_graphs_with_matching_hash() {
    for rel in ["step.onnx", "decoder.onnx", "text_encoder.onnx"] {
        let full = fs::read(tiny_dir().join(rel)).unwrap();
        // From an empty file through a header-only stub to one byte short.
        for keep in [0, 1, 16, full.len() / 10, full.len() / 2, full.len() - 1] {
            let b = TempBundle::copy_of(&tiny_dir());
            replace_with_matching_hash(&b, rel, &full[..keep]);
            println!("{rel} truncated to {keep} of {} bytes:", full.len());
            let msg = expect_bundle_error(&b.dir, rel, &[]);
            assert!(msg.contains("tract cannot") || msg.contains("graph") || msg.contains("tract panicked"), "{msg}");
        }
    }
}

#[test]
fn bit_flipped_graphs() {
    // Digest unchanged: the SHA-256 check refuses every flip, wherever it is.
    for rel in ["step.onnx", "decoder.onnx", "text_encoder.onnx"] {
        let b = TempBundle::copy_of(&tiny_dir());
        let mut bytes = fs::read(b.path(rel)).unwrap();
        bytes[7] ^= 0x80;
        fs::write(b.path(rel), &bytes).unwrap();
        expect_bundle_error(&b.dir, rel, &["SHA-256", "corrupt or replaced"]);
    }
    // Digest recomputed (a deliberately forged bundle): flips in the protobuf structure
    // must be refused or give a graph that still matches every declared input and output;
    // a flip inside weight data is a different, valid model (only the original digest can
    // tell). Either way: no panic, no hang, no unbounded allocation.
    let rel = "decoder.onnx";
    let orig = fs::read(tiny_dir().join(rel)).unwrap();
    // The header region (ir_version, producer, opset, graph framing) densely, then the body
    // (nodes and initializers) sparsely; ~0.7 s per load in a debug test build.
    let mut positions: Vec<usize> = (0..48).step_by(6).collect();
    positions.extend((1..7).map(|i| i * orig.len() / 7));
    let (mut refused, mut accepted) = (0, 0);
    for (k, &at) in positions.iter().enumerate() {
        let bit = if k % 2 == 0 { 0x01u8 } else { 0x80 };
        let b = TempBundle::copy_of(&tiny_dir());
        let mut bytes = orig.clone();
        bytes[at] ^= bit;
        replace_with_matching_hash(&b, rel, &bytes);
        match load_within(&b.dir, LIMIT).unwrap_or_else(|e| panic!("flip {bit:#x} at {at}: {e}")) {
            Ok(()) => accepted += 1,
            Err(Error::Bundle { path, msg }) => {
                assert!(path.ends_with(rel), "flip at {at}: error names {}: {msg}", path.display());
                println!("flip {bit:#04x} at byte {at}: {msg}");
                refused += 1;
            }
            Err(e) => panic!("flip at {at}: not a bundle error: {e:?}"),
        }
    }
    println!(
        "{rel}: {} bit flips with recomputed digests: {refused} refused, {accepted} loaded (weight bytes)",
        positions.len()
    );
    assert!(refused > 0, "no structural flip was refused");
}

// ---------------------------------------------------------------------------------------
// A tokenizer of the wrong kind (digest recomputed each time).

#[test]
fn tokenizer_json_of_another_kind() {
    // Another model's config.json: JSON, but no tokenizer at all.
    let b = TempBundle::copy_of(&tiny_dir());
    let config = serde_json::json!({
        "architectures": ["BertModel"], "hidden_size": 32, "model_type": "bert", "vocab_size": 257
    });
    replace_with_matching_hash(&b, "tokenizer.json", config.to_string().as_bytes());
    expect_bundle_error(&b.dir, "tokenizer.json", &["not a valid tokenizers JSON"]);

    // The bundle's manifest in place of the tokenizer.
    let b = TempBundle::copy_of(&tiny_dir());
    let manifest = fs::read(b.path("manifest.json")).unwrap();
    replace_with_matching_hash(&b, "tokenizer.json", &manifest);
    expect_bundle_error(&b.dir, "tokenizer.json", &["not a valid tokenizers JSON"]);

    // A valid tokenizer of another type (WordLevel over the same vocabulary, same padding
    // and special tokens): it would load and tokenize, but not as the encoder was trained.
    let b = TempBundle::copy_of(&tiny_dir());
    let mut tok: serde_json::Value = serde_json::from_slice(&fs::read(b.path("tokenizer.json")).unwrap()).unwrap();
    let vocab = tok["model"]["vocab"].clone();
    tok["model"] = serde_json::json!({ "type": "WordLevel", "vocab": vocab, "unk_token": "[UNK]" });
    replace_with_matching_hash(&b, "tokenizer.json", tok.to_string().as_bytes());
    expect_bundle_error(&b.dir, "tokenizer.json", &["model type is WordLevel", "minilm", "WordPiece"]);

    // Another model's WordPiece tokenizer (the default bundle's, its padding and truncation
    // set to this bundle's 16 tokens): right kind, wrong vocabulary.
    let b = TempBundle::copy_of(&tiny_dir());
    let other = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default/tokenizer.json");
    let mut tok: serde_json::Value = serde_json::from_slice(&fs::read(other).unwrap()).unwrap();
    tok["padding"]["strategy"] = serde_json::json!({ "Fixed": 16 });
    tok["truncation"]["max_length"] = 16.into();
    replace_with_matching_hash(&b, "tokenizer.json", tok.to_string().as_bytes());
    expect_bundle_error(&b.dir, "tokenizer.json", &["special token", "[CLS]", "the manifest says 2"]);

    // Not JSON at all.
    let b = TempBundle::copy_of(&tiny_dir());
    replace_with_matching_hash(&b, "tokenizer.json", b"\x00\x01\x02 binary");
    expect_bundle_error(&b.dir, "tokenizer.json", &["not a valid tokenizers JSON"]);
}

// ---------------------------------------------------------------------------------------
// Manifests whose hashes, shapes, slices or numbers do not match.

#[test]
fn manifest_hash_and_size_disagreeing_with_intact_files() {
    let b = TempBundle::copy_of(&tiny_dir());
    // Both places that record the tokenizer's digest agree, on a wrong value.
    b.edit_manifest(|m| {
        m["files"]["tokenizer.json"]["sha256"] = "0".repeat(64).into();
        m["text_encoder"]["sha256"]["tokenizer.json"] = "0".repeat(64).into();
    });
    expect_bundle_error(&b.dir, "tokenizer.json", &["SHA-256", "0000000000", "corrupt or replaced"]);
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["files"]["step.onnx"]["sha256"] = "ABC".into());
    expect_bundle_error(&b.dir, "manifest.json", &["step.onnx", "not a lower-case hex SHA-256"]);
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["text_encoder"]["sha256"]["tokenizer.json"] = "1".repeat(64).into());
    expect_bundle_error(&b.dir, "manifest.json", &["text_encoder sha256 of tokenizer.json"]);
}

#[test]
fn slices_and_shapes_that_do_not_match() {
    // A component slice that disagrees with its layout fields.
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        let stop = m["components"][0]["slice"][1].as_u64().unwrap();
        m["components"][0]["slice"][1] = (stop - 1).into();
        m["components"][1]["slice"][0] = (stop - 1).into();
    });
    expect_bundle_error(&b.dir, "manifest.json", &["component global", "disagrees with its layout fields"]);

    // Decoder context consistent inside the manifest, but not what decoder.onnx takes.
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        let k1 = m["decoder"]["state_tokens"].as_u64().unwrap() - 1;
        m["decoder"]["state_tokens"] = k1.into();
        m["decoder"]["context_tokens"] = (k1 + 1).into();
        m["decoder"]["inputs"][0]["shape"][2] = k1.into();
        m["decoder"]["outputs"][1]["shape"][2] = k1.into();
        let books: Vec<serde_json::Value> = m["decoder"]["state_pad_ids"].as_array().unwrap().clone();
        m["decoder"]["initial_state"] =
            serde_json::json!([books.iter().map(|j| vec![j.clone(); k1 as usize]).collect::<Vec<_>>()]);
    });
    expect_bundle_error(&b.dir, "decoder.onnx", &["state", "in the graph"]);

    // A text encoder whose declared max_tokens disagrees with the graph and the tokenizer.
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        let te = &mut m["text_encoder"];
        te["max_tokens"] = 24.into();
        for list in ["inputs", "outputs"] {
            for io in te[list].as_array_mut().unwrap() {
                io["shape"][1] = 24.into();
            }
        }
    });
    expect_bundle_error(&b.dir, "tokenizer.json", &["padding must be Fixed(24)"]);

    // Too few skeleton joints and a short normalization vector.
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        m["skeleton"]["rest_joints"].as_array_mut().unwrap().pop();
    });
    expect_bundle_error(&b.dir, "manifest.json", &["skeleton: need 55"]);
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        m["normalization"]["mean"].as_array_mut().unwrap().pop();
    });
    expect_bundle_error(&b.dir, "manifest.json", &["normalization mean/std have 334/335"]);
}

#[test]
fn absurd_numbers_are_errors_not_overflows_or_huge_allocations() {
    let cases: [(&str, fn(&mut serde_json::Value), &[&str]); 6] = [
        ("l_max = u64::MAX", |m| m["l_max"] = u64::MAX.into(), &["l_max + 2"]),
        (
            "codebook_size = u64::MAX",
            |m| m["components"][2]["codebook_size"] = u64::MAX.into(),
            &["codebook_size", "absurd"],
        ),
        (
            "n_heads * head_dim overflows",
            |m| {
                m["transformer"]["n_heads"] = (1u64 << 62).into();
                m["transformer"]["head_dims"][0] = 8.into();
            },
            &["width"],
        ),
        ("state_tokens = u64::MAX", |m| m["decoder"]["state_tokens"] = u64::MAX.into(), &["state_tokens"]),
        (
            "state_tokens = 2^40 (consistent context)",
            |m| {
                m["decoder"]["state_tokens"] = (1u64 << 40).into();
                m["decoder"]["context_tokens"] = ((1u64 << 40) + 1).into();
                m["decoder"]["inputs"][0]["shape"][2] = (1u64 << 40).into();
                m["decoder"]["outputs"][1]["shape"][2] = (1u64 << 40).into();
            },
            &["initial_state"],
        ),
        ("fps given as the string \"inf\"", |m| m["fps"] = serde_json::Value::String("inf".into()), &["schema"]),
    ];
    for (what, edit, needles) in cases {
        println!("{what}:");
        let b = TempBundle::copy_of(&tiny_dir());
        b.edit_manifest(edit);
        expect_bundle_error(&b.dir, "manifest.json", needles);
    }
}

// ---------------------------------------------------------------------------------------
// The file system: loops, FIFOs, devices, directories, permissions, size.

#[test]
fn bundle_directory_that_is_a_symlink_loop() {
    let d = scratch("dirloop");
    symlink(d.join("b"), d.join("a")).unwrap();
    symlink(d.join("a"), d.join("b")).unwrap();
    expect_bundle_error(&d.join("a"), "a", &["not a directory", "symbolic links"]);
    // A self-referencing link too.
    symlink(d.join("self"), d.join("self")).unwrap();
    expect_bundle_error(&d.join("self"), "self", &["symbolic links"]);
    fs::remove_dir_all(&d).unwrap();
}

#[test]
fn manifest_that_is_a_symlink_loop_a_device_or_a_directory() {
    let b = TempBundle::copy_of(&tiny_dir());
    let m = b.path("manifest.json");
    fs::remove_file(&m).unwrap();
    symlink(&m, &m).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "symbolic links"]);
    // An endless device: refused unread, not read forever.
    fs::remove_file(&m).unwrap();
    symlink("/dev/zero", &m).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "not a regular file"]);
    fs::remove_file(&m).unwrap();
    fs::create_dir(&m).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "directory"]);
}

#[test]
fn fifos_never_block_the_loader() {
    // A FIFO without a writer: a plain open() would wait forever.
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_file(b.path("manifest.json")).unwrap();
    mkfifo(&b.path("manifest.json"));
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "not a regular file (a FIFO"]);

    for rel in ["step.onnx", "tokenizer.json", "parity/index.json"] {
        let b = TempBundle::copy_of(&tiny_dir());
        fs::remove_file(b.path(rel)).unwrap();
        mkfifo(&b.path(rel));
        expect_bundle_error(&b.dir, rel, &["is not a regular file"]);
    }

    // The bundle path itself a FIFO, or a regular file.
    let d = scratch("fifo-root");
    mkfifo(&d.join("bundle"));
    expect_bundle_error(&d.join("bundle"), "bundle", &["not a directory"]);
    fs::write(d.join("file"), b"{}").unwrap();
    expect_bundle_error(&d.join("file"), "file", &["not a directory"]);
    fs::remove_dir_all(&d).unwrap();
}

#[test]
fn listed_files_that_are_loops_or_devices() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("decoder.onnx");
    fs::remove_file(&p).unwrap();
    symlink(&p, &p).unwrap();
    expect_bundle_error(&b.dir, "decoder.onnx", &["cannot read", "symbolic links"]);
    fs::remove_file(&p).unwrap();
    symlink("/dev/urandom", &p).unwrap();
    expect_bundle_error(&b.dir, "decoder.onnx", &["not a regular file"]);
    // A subdirectory that loops back to the bundle: a listed mesh under it cannot be read.
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_dir_all(b.path("objects")).unwrap();
    symlink(b.path("objects"), b.path("objects")).unwrap();
    expect_bundle_error(&b.dir, "objects/cubesmall.obj", &["cannot read", "symbolic links"]);
}

#[test]
fn unreadable_bundle() {
    if is_root() {
        // Root ignores permission bits (CAP_DAC_OVERRIDE), so mode 000 denies nothing here;
        // the same "cannot open / cannot read" paths are exercised by the FIFO, device and
        // directory cases above, which root cannot read as files either.
        println!("SKIPPED the mode-000 part of unreadable_bundle: running as root, permission bits do not deny reads");
        return;
    }
    let b = TempBundle::copy_of(&tiny_dir());
    fs::set_permissions(b.path("manifest.json"), fs::Permissions::from_mode(0o000)).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "ermission denied"]);
    fs::set_permissions(b.path("manifest.json"), fs::Permissions::from_mode(0o644)).unwrap();

    fs::set_permissions(b.path("objects"), fs::Permissions::from_mode(0o000)).unwrap();
    let r = load_within(&b.dir, LIMIT);
    fs::set_permissions(b.path("objects"), fs::Permissions::from_mode(0o755)).unwrap();
    match r.unwrap() {
        Err(Error::Bundle { path, msg }) => {
            assert!(msg.contains("ermission denied"), "{}: {msg}", path.display());
            println!("{}: {msg}", path.display());
        }
        other => panic!("unreadable objects/: {other:?}"),
    }

    fs::set_permissions(&b.dir, fs::Permissions::from_mode(0o000)).unwrap();
    let r = load_within(&b.dir, LIMIT);
    fs::set_permissions(&b.dir, fs::Permissions::from_mode(0o755)).unwrap();
    match r.unwrap() {
        Err(Error::Bundle { msg, .. }) => assert!(msg.contains("ermission denied"), "{msg}"),
        other => panic!("unreadable bundle directory: {other:?}"),
    }
}

#[test]
fn huge_manifest_is_refused_quickly() {
    let b = TempBundle::copy_of(&tiny_dir());
    // 100 MB of whitespace followed by the real manifest (valid JSON, were it read).
    let real = fs::read(b.path("manifest.json")).unwrap();
    let mut big = vec![b' '; 100 << 20];
    big.extend_from_slice(&real);
    fs::write(b.path("manifest.json"), &big).unwrap();
    drop(big);
    let t0 = Instant::now();
    expect_bundle_error(&b.dir, "manifest.json", &["cannot read", "limit"]);
    assert!(t0.elapsed() < Duration::from_secs(5), "took {:?}", t0.elapsed());
    // A sparse 4 GiB file: refused from its size, nothing read.
    let f = fs::OpenOptions::new().write(true).truncate(true).open(b.path("manifest.json")).unwrap();
    f.set_len(4 << 30).unwrap();
    drop(f);
    let t0 = Instant::now();
    expect_bundle_error(&b.dir, "manifest.json", &["4294967296 bytes", "limit"]);
    assert!(t0.elapsed() < Duration::from_secs(2), "took {:?}", t0.elapsed());
}
