//! The native (incremental) decoder against decoder.onnx in tract, on the bundle
//! `COMGRASP_PARITY_BUNDLE` names (default models/tiny), which must carry `decoder.native`:
//! the same frames (<= 1e-4, the parity tolerance) over long random token sequences from
//! the start of a sequence (where the pad embeddings and the layers' zero padding matter)
//! and after `reset`; and clean load errors for native weights that are corrupt or do not
//! match the manifest. Run with `--nocapture` to see the measured differences.
mod bundle_support;

use std::path::Path;
use std::sync::Arc;

use bundle_support::*;
use comgrasp::bundle::N_STREAMS;
use comgrasp::model::{DecoderBackend, DecoderModel};
use comgrasp::Bundle;

const TOLERANCE: f64 = 1e-4;

fn bundle() -> Arc<Bundle> {
    let dir = tiny_dir();
    let b = Bundle::load(&dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    assert!(
        b.manifest.decoder.native.is_some(),
        "{} has no decoder.native weights: re-export it (bundle.py writes them)",
        dir.display()
    );
    b
}

fn both(b: &Bundle) -> (DecoderModel, DecoderModel) {
    let native = DecoderModel::load_backend(b.origin(), &b.manifest, Some(DecoderBackend::Native)).unwrap();
    let tract = DecoderModel::load_backend(b.origin(), &b.manifest, Some(DecoderBackend::Tract)).unwrap();
    assert_eq!((native.backend(), tract.backend()), (DecoderBackend::Native, DecoderBackend::Tract));
    (native, tract)
}

/// Deterministic random codes (xorshift), `n` tokens per component.
fn random_tokens(books: [usize; N_STREAMS], n: usize, seed: u64) -> Vec<[i64; N_STREAMS]> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    (0..n).map(|_| std::array::from_fn(|i| (next() % books[i] as u64) as i64)).collect()
}

#[test]
fn the_bundle_decoder_is_native_when_the_bundle_has_native_weights() {
    let b = bundle();
    // Default options: automatic, which is native whenever the bundle has native weights
    // (the library reads no environment variable for it).
    assert_eq!(b.decoder.backend(), DecoderBackend::Native);
}

#[test]
fn native_frames_match_tract_over_long_sequences_and_after_reset() {
    let b = bundle();
    let (native, tract) = both(&b);
    let books = b.manifest.codebook_sizes();
    let k = b.manifest.decoder.context_tokens;
    let (mut ns, mut ts) = (native.new_state(), tract.new_state());
    let (mut a, mut c) = (vec![0f32; native.chunk_len()], vec![0f32; tract.chunk_len()]);
    let mut first_run = Vec::new();
    for (round, seed) in [(0, 7u64), (1, 8), (2, 7)] {
        if round > 0 {
            ns.reset().unwrap();
            ts.reset().unwrap();
            assert_eq!(ns.decoded(), 0);
        }
        let tokens = random_tokens(books, 120, seed);
        let (mut worst_start, mut worst) = (0f64, 0f64);
        let mut frames = Vec::new();
        for (i, t) in tokens.iter().enumerate() {
            native.decode(&mut ns, *t, &mut a).unwrap();
            tract.decode(&mut ts, *t, &mut c).unwrap();
            let d = max_abs_diff(&a, &c);
            assert!(d <= TOLERANCE, "round {round} token {i}: native vs tract max|diff| {d:e}");
            if i < k {
                worst_start = worst_start.max(d)
            } else {
                worst = worst.max(d)
            }
            frames.extend_from_slice(&a);
        }
        assert_eq!(ns.decoded(), tokens.len());
        println!(
            "round {round}: {} tokens, max|native - tract| first K={k}: {worst_start:.3e}, after: {worst:.3e}",
            tokens.len()
        );
        // Same tokens after reset: the very same frames (the state is fully reset).
        if round == 0 {
            first_run = frames;
        } else if round == 2 {
            assert!(frames == first_run, "reset did not reproduce the first run bit for bit");
        }
    }
    // A fresh state mid-way equals a reset one.
    let t0 = random_tokens(books, 3, 99);
    let mut fresh = native.new_state();
    ns.reset().unwrap();
    let mut f = vec![0f32; native.chunk_len()];
    for t in &t0 {
        native.decode(&mut fresh, *t, &mut a).unwrap();
        native.decode(&mut ns, *t, &mut f).unwrap();
        assert!(a == f);
    }
    // States are not interchangeable between backends or models.
    assert!(matches!(tract.decode(&mut fresh, t0[0], &mut a), Err(comgrasp::Error::WrongState(_))));
    assert!(matches!(b.decoder.decode(&mut fresh, t0[0], &mut a), Err(comgrasp::Error::WrongState(_))));
    // Input checks are the same on both paths.
    assert!(matches!(
        native.decode(&mut ns, [books[0] as i64, 0, 0, 0], &mut a),
        Err(comgrasp::Error::InvalidArgument(_))
    ));
    assert!(matches!(native.decode(&mut ns, [0; 4], &mut a[1..]), Err(comgrasp::Error::InvalidArgument(_))));
}

#[test]
fn native_decoder_replays_the_pytorch_parity_vectors() {
    let b = bundle();
    let (native, _) = both(&b);
    let dir = tiny_dir();
    let index = parity_index(&dir);
    let dec = &index["decode"][0]["files"];
    let rel = |k: &str| dec[k].as_str().unwrap().to_string();
    let (_, flat) = load_i64(&dir, &rel("tokens"));
    let tokens: Vec<[i64; N_STREAMS]> = flat.chunks_exact(N_STREAMS).map(|r| [r[0], r[1], r[2], r[3]]).collect();
    let (_, stream) = load_f32(&dir, &rel("frames_stream"));
    let (_, offline) = load_f32(&dir, &rel("frames_offline"));
    let mut st = native.new_state();
    let mut chunk = vec![0f32; native.chunk_len()];
    let mut all = Vec::new();
    for t in &tokens {
        native.decode(&mut st, *t, &mut chunk).unwrap();
        all.extend_from_slice(&chunk);
    }
    let (ds, d_off) = (max_abs_diff(&all, &stream), max_abs_diff(&all, &offline));
    println!("native decoder: {} chunks, max|diff| vs PyTorch stream {ds:.3e}, offline {d_off:.3e}", tokens.len());
    assert!(ds <= tolerance(&index, &rel("frames_stream")) && d_off <= tolerance(&index, &rel("frames_offline")));
}

// ----------------------------------------------------------------------------- load errors

fn native_dir(b: &TempBundle) -> String {
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(b.path("manifest.json")).unwrap()).unwrap();
    m["decoder"]["native"]["dir"].as_str().unwrap().to_string()
}

/// Rewrites the files table entry of `rel` after the file changed.
fn rehash(b: &TempBundle, rel: &str) {
    let p = b.path(rel);
    let sha = comgrasp::bundle::verify::sha256_file(&p).unwrap();
    let len = std::fs::metadata(&p).unwrap().len();
    b.edit_manifest(|m| {
        m["files"][rel] = serde_json::json!({"sha256": sha, "bytes": len});
    });
}

fn load_err(b: &TempBundle) -> String {
    match Bundle::load(&b.dir) {
        Ok(_) => panic!("loading {} succeeded", b.dir.display()),
        Err(comgrasp::Error::Bundle { path, msg }) => {
            let s = format!("{}: {msg}", path.display());
            println!("{s}");
            s
        }
        Err(e) => panic!("expected Error::Bundle, got {e:?}"),
    }
}

/// A float32 tensor of the first component's attention or first conv, for edits.
fn some_tensor(b: &TempBundle, dtype: &str) -> (String, Vec<usize>) {
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(b.path("manifest.json")).unwrap()).unwrap();
    let t = m["decoder"]["native"]["tensors"].as_object().unwrap();
    t.iter()
        .filter(|(n, v)| n.contains(".decoder.") && v["dtype"] == dtype && v["shape"].as_array().unwrap().len() >= 2)
        .map(|(n, v)| {
            (n.clone(), v["shape"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as usize).collect())
        })
        .next()
        .unwrap_or_else(|| panic!("no {dtype} decoder tensor"))
}

fn write_npy_f32(p: &Path, shape: &[usize], data: &[f32]) {
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(p, comgrasp::bundle::npy::encode("<f4", shape, &bytes)).unwrap();
}

#[test]
fn missing_native_tensor_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let (name, _) = some_tensor(&b, "float32");
    b.edit_manifest(|m| {
        m["decoder"]["native"]["tensors"].as_object_mut().unwrap().remove(&name);
    });
    let e = load_err(&b);
    assert!(e.contains(&name) && e.contains("lack"), "{e}");
}

#[test]
fn declared_shape_disagreeing_with_the_architecture_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(b.path("manifest.json")).unwrap()).unwrap();
    let name = m["decoder"]["native"]["tensors"]
        .as_object()
        .unwrap()
        .keys()
        .find(|n| n.ends_with(".qkv.bias"))
        .expect("an attention qkv bias")
        .clone();
    let mut shape: Vec<usize> = m["decoder"]["native"]["tensors"][&name]["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as usize)
        .collect();
    shape[0] += 1;
    // the file agrees with the new declaration, the architecture does not
    let dir = native_dir(&b);
    let rel = format!("{dir}/{name}.npy");
    write_npy_f32(&b.path(&rel), &shape, &vec![0.5; shape.iter().product()]);
    rehash(&b, &rel);
    b.edit_manifest(|m| m["decoder"]["native"]["tensors"][&name]["shape"] = serde_json::json!(shape));
    let e = load_err(&b);
    assert!(e.contains(&name), "{e}");
}

#[test]
fn file_disagreeing_with_its_declaration_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let (name, shape) = some_tensor(&b, "float32");
    let dir = native_dir(&b);
    let rel = format!("{dir}/{name}.npy");
    let mut wrong = shape.clone();
    wrong.reverse();
    wrong.push(1);
    write_npy_f32(&b.path(&rel), &wrong, &vec![0.5; shape.iter().product()]);
    rehash(&b, &rel);
    let e = load_err(&b);
    assert!(e.contains(&name) && e.contains("declares"), "{e}");
}

#[test]
fn non_finite_weight_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let (name, shape) = some_tensor(&b, "float32");
    let dir = native_dir(&b);
    let rel = format!("{dir}/{name}.npy");
    let mut v = vec![0.25f32; shape.iter().product()];
    v[3] = f32::NAN;
    write_npy_f32(&b.path(&rel), &shape, &v);
    rehash(&b, &rel);
    let e = load_err(&b);
    assert!(e.contains("not finite"), "{e}");
}

#[test]
fn unknown_decoder_layer_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let dir = native_dir(&b);
    let name = "parts.body.decoder.layers.99.conv.bias";
    let rel = format!("{dir}/{name}.npy");
    write_npy_f32(&b.path(&rel), &[4], &[0.0; 4]);
    rehash(&b, &rel);
    b.edit_manifest(|m| {
        m["decoder"]["native"]["tensors"][name] = serde_json::json!({"dtype": "float32", "shape": [4]})
    });
    let e = load_err(&b);
    assert!(e.contains(name) && e.contains("architecture"), "{e}");
}

#[test]
fn attention_window_disagreeing_with_context_tokens_is_a_bundle_error() {
    // A wider attention window makes the receptive field longer than the manifest's K.
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let dir = native_dir(&b);
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(b.path("manifest.json")).unwrap()).unwrap();
    let names: Vec<String> = m["decoder"]["native"]["tensors"]
        .as_object()
        .unwrap()
        .keys()
        .filter(|n| n.ends_with(".rel_bias"))
        .cloned()
        .collect();
    assert!(!names.is_empty(), "the decoder has no attention");
    for name in &names {
        let shape: Vec<usize> = m["decoder"]["native"]["tensors"][name]["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as usize)
            .collect();
        let wider = [shape[0], shape[1] + 2];
        let rel = format!("{dir}/{name}.npy");
        write_npy_f32(&b.path(&rel), &wider, &vec![0.0; wider[0] * wider[1]]);
        rehash(&b, &rel);
        b.edit_manifest(|m| m["decoder"]["native"]["tensors"][name]["shape"] = serde_json::json!(wider));
    }
    let e = load_err(&b);
    assert!(e.contains("context_tokens"), "{e}");
}

#[test]
fn forcing_native_without_native_weights_is_a_bundle_error() {
    let b = TempBundle::copy_of(bundle().origin().directory().unwrap());
    let dir = native_dir(&b);
    b.edit_manifest(|m| {
        m["decoder"].as_object_mut().unwrap().remove("native");
    });
    // the decoder's native files would now be unlisted extras: remove them and their entries
    std::fs::remove_dir_all(b.path(&dir)).unwrap();
    let prefix = format!("{dir}/");
    b.edit_manifest(|m| m["files"].as_object_mut().unwrap().retain(|k, _| !k.starts_with(&prefix)));
    let bundle = Bundle::load(&b.dir).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(bundle.decoder.backend(), DecoderBackend::Tract);
    match DecoderModel::load_backend(bundle.origin(), &bundle.manifest, Some(DecoderBackend::Native)) {
        Err(comgrasp::Error::Bundle { msg, .. }) => assert!(msg.contains("decoder.native"), "{msg}"),
        other => panic!("expected a bundle error, got {other:?}"),
    }
}
