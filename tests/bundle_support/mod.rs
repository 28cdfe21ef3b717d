//! Helpers shared by the bundle_* and parity_* integration tests: the committed tiny
//! bundle, its parity index, `.npy` loading and throw-away bundle copies.
#![allow(dead_code)]
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use comgrasp::bundle::npy;

/// models/tiny, the bundle committed for tests.
pub fn tiny_dir() -> PathBuf {
    // Another bundle's parity vectors replay through the same tests with
    // COMGRASP_PARITY_BUNDLE=<dir> (e.g. a freshly exported one before it is shipped).
    match std::env::var_os("COMGRASP_PARITY_BUNDLE") {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("tiny"),
    }
}

/// parity/index.json of a bundle.
pub fn parity_index(dir: &Path) -> serde_json::Value {
    let text = fs::read_to_string(dir.join("parity/index.json")).expect("read parity/index.json");
    serde_json::from_str(&text).expect("parse parity/index.json")
}

/// Tolerance recorded for `rel` in the parity index.
pub fn tolerance(index: &serde_json::Value, rel: &str) -> f64 {
    index["files"]
        .as_array()
        .expect("files")
        .iter()
        .find(|e| e["path"] == rel)
        .and_then(|e| e["tolerance"].as_f64())
        .unwrap_or_else(|| panic!("{rel} not in parity/index.json"))
}

pub fn load_f32(dir: &Path, rel: &str) -> (Vec<usize>, Vec<f32>) {
    let p = dir.join(rel);
    let a = npy::read(&p).unwrap_or_else(|e| panic!("{e}"));
    let v = a.to_f32(&p).unwrap_or_else(|e| panic!("{e}"));
    (a.shape, v)
}

pub fn load_i64(dir: &Path, rel: &str) -> (Vec<usize>, Vec<i64>) {
    let p = dir.join(rel);
    let a = npy::read(&p).unwrap_or_else(|e| panic!("{e}"));
    let v = a.to_i64(&p).unwrap_or_else(|e| panic!("{e}"));
    (a.shape, v)
}

pub fn load_f64(dir: &Path, rel: &str) -> Vec<f64> {
    let p = dir.join(rel);
    let a = npy::read(&p).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a.dtype, npy::NpyDtype::F64, "{rel}");
    a.to_f64()
}

/// Integer parity vectors as u64 (token ids and raw SplitMix64 outputs).
pub fn load_u64(dir: &Path, rel: &str) -> Vec<u64> {
    let p = dir.join(rel);
    let a = npy::read(&p).unwrap_or_else(|e| panic!("{e}"));
    match a.dtype {
        npy::NpyDtype::U64 => a.to_u64(&p).unwrap_or_else(|e| panic!("{e}")),
        _ => load_i64(dir, rel).1.into_iter().map(|v| v as u64).collect(),
    }
}

pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter().zip(b).map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs()).fold(0.0, f64::max)
}

/// A copy of a bundle in a fresh temporary directory, removed on drop.
pub struct TempBundle {
    pub dir: PathBuf,
}

static COUNTER: AtomicUsize = AtomicUsize::new(0);

impl TempBundle {
    pub fn copy_of(src: &Path) -> TempBundle {
        let n = COUNTER.fetch_add(1, Ordering::SeqCst);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        let dir = std::env::temp_dir().join(format!("comgrasp-bundle-test-{}-{n}-{nanos}", std::process::id()));
        copy_dir(src, &dir);
        TempBundle { dir }
    }

    pub fn path(&self, rel: &str) -> PathBuf {
        self.dir.join(rel)
    }

    /// Rewrites manifest.json through `edit`.
    pub fn edit_manifest(&self, edit: impl FnOnce(&mut serde_json::Value)) {
        let p = self.path("manifest.json");
        let mut v: serde_json::Value = serde_json::from_str(&fs::read_to_string(&p).unwrap()).unwrap();
        edit(&mut v);
        fs::write(&p, serde_json::to_string_pretty(&v).unwrap()).unwrap();
    }
}

impl Drop for TempBundle {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.dir);
    }
}

fn copy_dir(src: &Path, dst: &Path) {
    fs::create_dir_all(dst).unwrap();
    for e in fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            fs::copy(e.path(), to).unwrap();
        }
    }
}

/// Checks that a load of `dir` failed with an `Error::Bundle` whose path ends with `file`
/// and whose message contains every string of `needles`. Returns the message for further
/// checks.
pub fn assert_bundle_error(loaded: comgrasp::Result<()>, dir: &Path, file: &str, needles: &[&str]) -> String {
    match loaded {
        Ok(()) => panic!("loading {} succeeded, expected an error about {file}", dir.display()),
        Err(comgrasp::Error::Bundle { path, msg }) => {
            let full = format!("{}: {msg}", path.display());
            assert!(path.ends_with(file), "error path {} does not name {file}: {full}", path.display());
            for n in needles {
                assert!(full.contains(n), "error {full:?} does not mention {n:?}");
            }
            println!("{full}");
            full
        }
        Err(e) => panic!("expected Error::Bundle about {file}, got {e:?}"),
    }
}
