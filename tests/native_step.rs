//! The native step (src/model/native/step.rs) against the tract step graph on the same
//! inputs: logits within 1e-4, identical greedy tokens, on models/tiny (or
//! COMGRASP_PARITY_BUNDLE) and models/default; one and two threads (COMGRASP_STEP_THREADS)
//! give bit-identical logits; and corrupt or mismatched native weight files are clean load
//! errors.
mod bundle_support;

use std::fs;
use std::path::Path;

use bundle_support::*;
use comgrasp::bundle::{BundleSource, N_STREAMS};
use comgrasp::config::RuntimeOptions;
use comgrasp::model::{StepBackend, StepModel};
use comgrasp::Bundle;

const TOL: f64 = 1e-4;

fn default_dir() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default")
}

/// Teacher-forced on the parity tokens, then free-running greedy from each path's own
/// tokens: logits agree within TOL at every step and the greedy tokens are identical.
fn compare_paths(dir: &Path, max_steps: usize) {
    let b = Bundle::load(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    let src = BundleSource::dir(dir);
    let native = StepModel::load_with(&src, &b.manifest, StepBackend::Native).unwrap();
    let tract = StepModel::load_with(&src, &b.manifest, StepBackend::Tract).unwrap();
    assert_eq!((native.backend(), tract.backend()), (StepBackend::Native, StepBackend::Tract));
    let m = &b.manifest;
    let (pad, end) = (m.pad_ids(), m.end_ids());
    let index = parity_index(dir);
    let steps = max_steps.min(native.cache_slots());
    let (mut sn, mut st) = (native.new_state(), tract.new_state());
    let mut worst = 0f64;
    for (ci, case) in index["step"].as_array().unwrap().iter().enumerate() {
        let emb = load_f32(dir, case["files"]["text_emb"].as_str().unwrap()).1;
        let forced = load_i64(dir, case["files"]["tokens"].as_str().unwrap()).1;
        let forced: Vec<[i64; N_STREAMS]> = forced.chunks_exact(N_STREAMS).map(|c| [c[0], c[1], c[2], c[3]]).collect();
        for teacher in [true, false] {
            sn.reset().unwrap();
            st.reset().unwrap();
            let (mut tn, mut tt) = (pad, pad);
            let mut greedy_n = Vec::new();
            for k in 0..steps {
                if teacher && k > forced.len() {
                    break;
                }
                let ln = native.step(&mut sn, tn, k, &emb).unwrap();
                let lt = tract.step(&mut st, tt, k, &emb).unwrap();
                for s in 0..N_STREAMS {
                    let d = max_abs_diff(ln[s], lt[s]);
                    assert!(
                        d <= TOL,
                        "{} case {ci} step {k} stream {s}: native vs tract logits differ by {d:e}",
                        dir.display()
                    );
                    worst = worst.max(d);
                }
                let arg = |l: &[f32], s: usize| -> i64 {
                    let mut best = (0usize, f32::NEG_INFINITY);
                    for (i, &x) in l.iter().enumerate() {
                        if i as i64 != pad[s] && x > best.1 {
                            best = (i, x);
                        }
                    }
                    best.0 as i64
                };
                let gn: [i64; N_STREAMS] = std::array::from_fn(|s| arg(ln[s], s));
                let gt: [i64; N_STREAMS] = std::array::from_fn(|s| arg(lt[s], s));
                assert_eq!(gn, gt, "{} case {ci} step {k}: greedy tokens differ", dir.display());
                if teacher {
                    if k < forced.len() {
                        (tn, tt) = (forced[k], forced[k]);
                    }
                } else {
                    greedy_n.push(gn);
                    // End ids are real tokens the model can be fed; the pad id is excluded above.
                    let _ = end;
                    (tn, tt) = (gn, gt);
                }
            }
            println!(
                "{} case {ci} ({}): {} steps agree",
                dir.display(),
                if teacher { "teacher-forced" } else { "greedy" },
                if teacher { forced.len() + 1 } else { greedy_n.len() }
            );
        }
    }
    println!("{}: worst native vs tract logits difference {worst:.3e}", dir.display());
}

#[test]
fn native_matches_tract_on_tiny() {
    compare_paths(&tiny_dir(), usize::MAX);
}

#[test]
fn native_matches_tract_on_default() {
    compare_paths(&default_dir(), usize::MAX);
}

/// Names of this process's threads (Linux; empty elsewhere).
fn thread_names() -> Vec<String> {
    let Ok(dir) = fs::read_dir("/proc/self/task") else { return Vec::new() };
    dir.filter_map(|e| fs::read_to_string(e.ok()?.path().join("comm")).ok()).map(|s| s.trim().to_string()).collect()
}

/// The logits of every step of a generation (the parity case's text embedding, tokens
/// derived from the step number) with `threads` step threads, as bits.
fn logits_bits(dir: &Path, threads: &str) -> Vec<u32> {
    let b = Bundle::load(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    let options = RuntimeOptions {
        step_backend: StepBackend::Native,
        step_threads: Some(threads.parse().unwrap()),
        ..Default::default()
    };
    let step = StepModel::load(&BundleSource::dir(dir), &b.manifest, &options).unwrap();
    if threads == "2" && cfg!(target_os = "linux") {
        assert!(thread_names().iter().any(|n| n == "comgrasp-step"), "no step helper thread with 2 threads");
    }
    let emb = b.text.embed("pick up the mug").unwrap();
    let vocab = b.manifest.vocab_sizes();
    let mut st = step.new_state();
    let mut tokens = b.manifest.pad_ids();
    let mut out = Vec::new();
    for k in 0..step.cache_slots() {
        let logits = step.step(&mut st, tokens, k, &emb).unwrap();
        out.extend(logits.iter().flat_map(|l| l.iter().map(|v| v.to_bits())));
        tokens = std::array::from_fn(|s| ((k * 7 + s) % (vocab[s] - 2)) as i64);
    }
    out
}

#[test]
fn one_and_two_threads_give_bit_identical_logits() {
    for dir in [tiny_dir(), default_dir()] {
        let one = logits_bits(&dir, "1");
        assert!(one.iter().all(|&b| f32::from_bits(b).is_finite()));
        assert!(one == logits_bits(&dir, "2"), "{}: 2 threads' logits differ from 1 thread's", dir.display());
    }
}

#[test]
fn auto_picks_native_and_forcing_native_without_weights_fails() {
    let b = Bundle::load(&tiny_dir()).unwrap();
    let src = BundleSource::dir(tiny_dir());
    assert_eq!(StepModel::load_with(&src, &b.manifest, StepBackend::Auto).unwrap().backend(), StepBackend::Native);
    let mut m = b.manifest.clone();
    m.transformer.native = None;
    assert_eq!(StepModel::load_with(&src, &m, StepBackend::Auto).unwrap().backend(), StepBackend::Tract);
    match StepModel::load_with(&src, &m, StepBackend::Native) {
        Err(comgrasp::Error::Bundle { msg, .. }) => assert!(msg.contains("no transformer.native"), "{msg}"),
        other => panic!("expected a bundle error, got {other:?}"),
    }
}

// ---------------------------------------------------------------------------------------
// Corrupt native weights: every case is an Error::Bundle at load naming the file.

const TENSOR: &str = "streams.1.blocks.0.attn.qkv.weight";

fn rel(name: &str) -> String {
    format!("native/step/{name}.npy")
}

fn f32_npy(shape: &[usize], values: &[f32]) -> Vec<u8> {
    comgrasp::bundle::npy::encode("<f4", shape, &values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>())
}

/// Writes `bytes` as `rel` and lists it in the files table with its real digest.
fn put(b: &TempBundle, rel: &str, bytes: &[u8]) {
    fs::write(b.path(rel), bytes).unwrap();
    let sha = comgrasp::bundle::verify::sha256_hex(bytes);
    b.edit_manifest(|m| m["files"][rel] = serde_json::json!({"sha256": sha, "bytes": bytes.len()}));
}

fn expect(b: &TempBundle, file: &str, needles: &[&str]) {
    let loaded = Bundle::load(&b.dir).map(drop);
    assert_bundle_error(loaded, &b.dir, file, needles);
}

fn declared_shape(b: &TempBundle, name: &str) -> Vec<usize> {
    let m: serde_json::Value = serde_json::from_str(&fs::read_to_string(b.path("manifest.json")).unwrap()).unwrap();
    serde_json::from_value(m["transformer"]["native"]["tensors"][name]["shape"].clone()).unwrap()
}

#[test]
fn native_tensor_with_a_wrong_shape() {
    // Declared and stored consistently, but not what the manifest's widths imply.
    let b = TempBundle::copy_of(&tiny_dir());
    let shape = declared_shape(&b, TENSOR);
    let bad = [shape[0] - 1, shape[1]];
    put(&b, &rel(TENSOR), &f32_npy(&bad, &vec![0.0; bad[0] * bad[1]]));
    b.edit_manifest(|m| m["transformer"]["native"]["tensors"][TENSOR]["shape"] = serde_json::json!(bad));
    expect(&b, &rel(TENSOR), &[TENSOR, "expected"]);

    // The file disagrees with the manifest's declaration.
    let b = TempBundle::copy_of(&tiny_dir());
    put(&b, &rel(TENSOR), &f32_npy(&bad, &vec![0.0; bad[0] * bad[1]]));
    expect(&b, &rel(TENSOR), &["the manifest declares"]);
}

#[test]
fn native_tensor_with_a_wrong_dtype() {
    let b = TempBundle::copy_of(&tiny_dir());
    let shape = declared_shape(&b, TENSOR);
    let n = shape[0] * shape[1];
    put(&b, &rel(TENSOR), &comgrasp::bundle::npy::encode("<f8", &shape, &vec![0u8; 8 * n]));
    expect(&b, &rel(TENSOR), &["float64", "float32"]);

    // Declared int8 without its scale file.
    let b = TempBundle::copy_of(&tiny_dir());
    put(&b, &rel(TENSOR), &comgrasp::bundle::npy::encode("|i1", &shape, &vec![0u8; n]));
    b.edit_manifest(|m| m["transformer"]["native"]["tensors"][TENSOR]["dtype"] = "int8".into());
    expect(&b, &format!("native/step/{TENSOR}.scale.npy"), &["cannot read"]);
}

#[test]
fn native_tensor_missing_or_extra() {
    // Listed in the native section but not there (and not in the files table).
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_file(b.path(&rel(TENSOR))).unwrap();
    b.edit_manifest(|m| {
        m["files"].as_object_mut().unwrap().remove(&rel(TENSOR));
    });
    expect(&b, &rel(TENSOR), &["cannot read"]);

    // Not listed in the native section at all.
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_file(b.path(&rel(TENSOR))).unwrap();
    b.edit_manifest(|m| {
        m["files"].as_object_mut().unwrap().remove(&rel(TENSOR));
        m["transformer"]["native"]["tensors"].as_object_mut().unwrap().remove(TENSOR);
    });
    expect(&b, "native/step", &["lack tensor", TENSOR]);

    // A tensor the step does not use.
    let b = TempBundle::copy_of(&tiny_dir());
    put(&b, &rel("streams.0.extra"), &f32_npy(&[2], &[1.0, 2.0]));
    b.edit_manifest(|m| {
        m["transformer"]["native"]["tensors"]["streams.0.extra"] = serde_json::json!({"dtype": "float32", "shape": [2]})
    });
    expect(&b, "native/step", &["streams.0.extra", "does not use"]);
}

#[test]
fn native_tensor_with_a_nan() {
    let b = TempBundle::copy_of(&tiny_dir());
    let shape = declared_shape(&b, TENSOR);
    let mut v = vec![0.5f32; shape[0] * shape[1]];
    v[17] = f32::NAN;
    put(&b, &rel(TENSOR), &f32_npy(&shape, &v));
    expect(&b, &rel(TENSOR), &["value 17 is not finite"]);
}

#[test]
fn native_tensor_truncated_with_matching_hash() {
    let b = TempBundle::copy_of(&tiny_dir());
    let full = fs::read(b.path(&rel(TENSOR))).unwrap();
    put(&b, &rel(TENSOR), &full[..full.len() - 3]);
    expect(&b, &rel(TENSOR), &[]);
}
