//! The default bundle embedded in the library (feature `embedded-default`): an engine with
//! no bundle path loads it from any working directory, through the Rust API and the C ABI;
//! its files are the ones in `models/default`; an in-memory bundle gets the same checks and
//! precise errors as a directory.
//!
//! Nothing here depends on the numbers of the particular model in `models/default` (it is
//! replaced by the trained bundle): only on it being a valid bundle with a mug mesh.
//! `COMGRASP_BUNDLE` is process-global and must be unset for the `None` path to mean the
//! embedded bundle; the tests that set it live in their own binary (`bundle_env.rs`).
#![cfg(feature = "embedded-default")]

use std::ffi::CStr;
use std::path::{Path, PathBuf};
use std::ptr::null_mut;
use std::sync::Once;
use std::time::{Duration, Instant};

use comgrasp::bundle::source::StaticFiles;
use comgrasp::bundle::{embedded, select, verify, BundleSource};
use comgrasp::config::{DecoderBackend, RuntimeOptions, StepBackend};
use comgrasp::engine::StreamConfig;
use comgrasp::ffi::*;
use comgrasp::model::text::{TextBackend, TextEncoder};
use comgrasp::Bundle;
use comgrasp::{Engine, EngineConfig, Error, Frame, PollResult};

fn default_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default")
}

/// Makes sure `COMGRASP_BUNDLE` from the developer's shell does not redirect these tests.
fn no_env_override() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| std::env::remove_var(select::BUNDLE_ENV));
}

fn embedded_files() -> StaticFiles {
    embedded::files().expect("built with feature embedded-default")
}

/// A copy of the embedded files plus the reference graphs the library leaves out (read
/// from models/default: a plain in-memory bundle must be complete), passed through `edit`,
/// leaked so it is `'static` like `include_bytes!` data (a few MiB per call, once per test).
fn leaked_copy(edit: impl FnOnce(&mut Vec<(&'static str, Vec<u8>)>)) -> StaticFiles {
    let mut owned: Vec<(&'static str, Vec<u8>)> = embedded_files().iter().map(|(n, b)| (*n, b.to_vec())).collect();
    for name in embedded::omitted() {
        owned.push((name, std::fs::read(default_dir().join(name)).unwrap()));
    }
    edit(&mut owned);
    let files: Vec<(&'static str, &'static [u8])> =
        owned.into_iter().map(|(n, b)| (n, &*Box::leak(b.into_boxed_slice()))).collect();
    Box::leak(files.into_boxed_slice())
}

fn expect_bundle_error(source: BundleSource, file: &str, needles: &[&str]) {
    match Bundle::load_source(source) {
        Ok(_) => panic!("loading succeeded, expected an error about {file}"),
        Err(Error::Bundle { path, msg }) => {
            let full = format!("{}: {msg}", path.display());
            assert_eq!(path, Path::new(file), "error names the wrong file: {full}");
            for n in needles {
                assert!(full.contains(n), "error {full:?} does not mention {n:?}");
            }
        }
        Err(e) => panic!("expected Error::Bundle about {file}, got {e:?}"),
    }
}

#[test]
fn none_path_streams_from_any_directory() {
    no_env_override();
    // Nothing relative to the crate can be found from here.
    let elsewhere = std::env::temp_dir().join(format!("comgrasp-embedded-cwd-{}", std::process::id()));
    std::fs::create_dir_all(&elsewhere).unwrap();
    std::env::set_current_dir(&elsewhere).unwrap();

    let engine = Engine::new(EngineConfig::default()).unwrap_or_else(|e| panic!("{e}"));
    let bundle = engine.bundle().expect("a bundle");
    assert!(bundle.origin().is_embedded() && bundle.origin().directory().is_none());
    assert_eq!(bundle.origin().to_string(), "<embedded>");

    let opts = StreamConfig { min_len: Some(1), max_len: Some(2), seed: Some(7), ..Default::default() };
    let mut s = engine.start("pick up the mug", opts).unwrap();
    let mut f = Frame::default();
    let mut frames = 0u64;
    let mut saw_last = false;
    loop {
        match s.wait(&mut f, Duration::from_secs(60)) {
            PollResult::Frame => {
                assert_eq!(f.frame_index, frames);
                assert!(!saw_last, "frame after is_last");
                saw_last = f.is_last != 0;
                frames += 1;
            }
            PollResult::End => break,
            other => panic!("{other:?}: {:?}", s.error()),
        }
    }
    let per_token = bundle.manifest.frames_per_token as u64;
    assert!(frames >= 1 && frames <= 2 * per_token, "{frames} frames for max_len 2");
    assert!(saw_last, "the last frame is marked");
    let _ = std::fs::remove_dir(&elsewhere);
}

#[test]
fn file_bytes_equal_the_files_on_disk_for_both_sources() {
    no_env_override();
    let mesh = "objects/mug.obj";
    let on_disk = std::fs::read(default_dir().join(mesh)).unwrap();
    let embedded = Bundle::load_source(BundleSource::embedded().unwrap()).unwrap();
    let dir = Bundle::load(&default_dir()).unwrap();
    assert_eq!(dir.origin().directory(), Some(default_dir().as_path()));
    assert_eq!(embedded.file_bytes(mesh).unwrap(), on_disk);
    assert_eq!(dir.file_bytes(mesh).unwrap(), on_disk);
    // Names outside the manifest are refused for both, named in the source's terms.
    match embedded.file_bytes("build.rs") {
        Err(Error::Bundle { path, msg }) => {
            assert_eq!(path, Path::new("<embedded>/build.rs"));
            assert!(msg.contains("not a file the manifest lists"), "{msg}");
        }
        other => panic!("{other:?}"),
    }
    assert!(dir.file_bytes("../Cargo.toml").is_err());
}

#[test]
fn embedded_set_is_the_listed_files_without_parity_and_reference_graphs() {
    let files = embedded_files();
    assert_eq!(files[0].0, "manifest.json");
    let bundle = Bundle::load(&default_dir()).unwrap();
    // The three default models run natively: their ONNX graphs stay on disk only, so the
    // library holds each weight once.
    let m = &bundle.manifest;
    assert!(m.transformer.native.is_some() && m.decoder.native.is_some() && m.text_encoder.native.is_some());
    assert_eq!(
        embedded::omitted(),
        [m.transformer.file.as_str(), m.decoder.file.as_str(), m.text_encoder.files.onnx.as_str()]
    );
    let mut names: Vec<&str> = files[1..].iter().map(|(n, _)| *n).collect();
    names.sort_unstable();
    let listed: Vec<&str> = m
        .files
        .keys()
        .map(String::as_str)
        .filter(|n| !n.starts_with("parity/") && !embedded::omitted().contains(n))
        .collect();
    assert_eq!(names, listed);
    for (name, bytes) in files {
        assert_eq!(*bytes, &std::fs::read(default_dir().join(name)).unwrap()[..], "{name}");
    }
}

#[test]
fn tract_backend_on_the_embedded_default_says_where_the_graphs_are() {
    no_env_override();
    let embedded = BundleSource::embedded().unwrap();
    let tract = RuntimeOptions { step_backend: StepBackend::Tract, ..Default::default() };
    match Bundle::load_with(embedded.clone(), &tract) {
        Err(Error::Bundle { path, msg }) => {
            assert_eq!(path, Path::new("<embedded>/step.onnx"));
            assert!(msg.contains("native weights") && msg.contains("models/default"), "{msg}");
        }
        other => panic!("expected a bundle error, got {:?}", other.map(drop)),
    }
    let tract = RuntimeOptions { decoder_backend: Some(DecoderBackend::Tract), ..Default::default() };
    match Bundle::load_with(embedded, &tract) {
        Err(Error::Bundle { path, .. }) => assert_eq!(path, Path::new("<embedded>/decoder.onnx")),
        other => panic!("expected a bundle error, got {:?}", other.map(drop)),
    }
    let embedded = BundleSource::embedded().unwrap();
    let m = verify::read_manifest(&embedded).unwrap();
    match TextEncoder::load_with(&embedded, &m, TextBackend::Tract) {
        Err(Error::Bundle { path, msg }) => {
            assert_eq!(path, Path::new("<embedded>/text_encoder.onnx"));
            assert!(msg.contains("native text encoder") && msg.contains("models/default"), "{msg}");
        }
        other => panic!("expected a bundle error, got {:?}", other.map(drop)),
    }
    // The same options on the directory run both graphs in tract.
    let dir = Bundle::load_with(BundleSource::dir(default_dir()), &tract).unwrap();
    assert_eq!(dir.decoder.backend(), DecoderBackend::Tract);
}

#[test]
fn c_abi_create_with_null_bundle_path() {
    no_env_override();
    let mut cfg = cg_engine_config::default();
    let mut e: *mut cg_engine = null_mut();
    unsafe {
        assert_eq!(cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()), cg_status::CG_OK);
        assert!(cfg.bundle_path.is_null());
        let st = cg_engine_create(&cfg, &mut e);
        assert_eq!(st, cg_status::CG_OK, "{}", CStr::from_ptr(cg_last_error()).to_string_lossy());
        assert!(!e.is_null());
        let mut s = null_mut();
        assert_eq!(cg_start(e, c"grasp the mug".as_ptr(), std::ptr::null(), &mut s), cg_status::CG_OK);
        let mut f = Frame::default();
        let t0 = Instant::now();
        let end = loop {
            match cg_stream_wait(s, 1_000, &mut f) {
                cg_status::CG_OK | cg_status::CG_PENDING => assert!(t0.elapsed() < Duration::from_secs(120)),
                other => break other,
            }
        };
        assert_eq!(end, cg_status::CG_END);
        assert_eq!(cg_stream_destroy(s), cg_status::CG_OK);
        assert_eq!(cg_engine_destroy(e), cg_status::CG_OK);
    }
}

#[test]
fn corrupt_in_memory_copy_names_the_file() {
    // An intact copy passes the same checks (not the embedded once-per-process shortcut).
    Bundle::load_source(BundleSource::memory(leaked_copy(|_| {}))).unwrap();

    let flipped = leaked_copy(|files| {
        let (_, bytes) = files.iter_mut().find(|(n, _)| *n == "step.onnx").unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x01;
    });
    expect_bundle_error(BundleSource::memory(flipped), "<memory>/step.onnx", &["SHA-256", "corrupt"]);

    let missing = leaked_copy(|files| files.retain(|(n, _)| *n != "decoder.onnx"));
    expect_bundle_error(
        BundleSource::memory(missing),
        "<memory>/decoder.onnx",
        &["listed in the manifest but missing"],
    );

    let extra = leaked_copy(|files| files.push(("objects/extra.obj", b"v 0 0 0\n".to_vec())));
    expect_bundle_error(BundleSource::memory(extra), "<memory>", &["not listed", "objects/extra.obj"]);

    let no_manifest = leaked_copy(|files| files.retain(|(n, _)| *n != "manifest.json"));
    expect_bundle_error(
        BundleSource::memory(no_manifest),
        "<memory>/manifest.json",
        &["missing", "not a model bundle"],
    );
}

/// Cost of the embedded bundle's SHA-256 check (done once per process) and of a second
/// engine's load, which skips it; printed for the record (`--nocapture`), not asserted.
#[test]
fn embedded_hash_cost() {
    let files = embedded_files();
    let bytes: usize = files.iter().map(|(_, b)| b.len()).sum();
    let t = Instant::now();
    for (_, b) in files {
        std::hint::black_box(verify::sha256_hex(b));
    }
    let hash = t.elapsed();
    let t = Instant::now();
    Bundle::load_source(BundleSource::embedded().unwrap()).unwrap();
    let first = t.elapsed();
    let t = Instant::now();
    Bundle::load_source(BundleSource::embedded().unwrap()).unwrap();
    let again = t.elapsed();
    let t = Instant::now();
    Bundle::load(&default_dir()).unwrap();
    let dir = t.elapsed();
    eprintln!(
        "embedded bundle: {bytes} bytes in {} files; SHA-256 of all {:.2} ms ({:.0} MB/s); \
               load {:.1} ms (this test's first), again {:.1} ms; the same from its directory {:.1} ms",
        files.len(),
        hash.as_secs_f64() * 1e3,
        bytes as f64 / hash.as_secs_f64() / 1e6,
        first.as_secs_f64() * 1e3,
        again.as_secs_f64() * 1e3,
        dir.as_secs_f64() * 1e3
    );
}
