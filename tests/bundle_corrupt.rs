//! Corrupt bundles give a precise `Error::Bundle` at load time, never a panic: each test
//! copies models/tiny to a temporary directory, breaks one thing and checks the error
//! names the file at fault and the reason.
mod bundle_support;

use std::fs;
use std::path::Path;

use bundle_support::*;
use comgrasp::Bundle;

/// Loads `dir`, expecting an `Error::Bundle` about `file` (see [`assert_bundle_error`]).
fn expect_bundle_error(dir: &Path, file: &str, needles: &[&str]) -> String {
    assert_bundle_error(Bundle::load(dir).map(drop), dir, file, needles)
}

#[test]
fn intact_copy_loads() {
    let b = TempBundle::copy_of(&tiny_dir());
    Bundle::load(&b.dir).unwrap();
}

#[test]
fn flipped_byte_in_step_graph() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("step.onnx");
    let mut bytes = fs::read(&p).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x01;
    fs::write(&p, bytes).unwrap();
    expect_bundle_error(&b.dir, "step.onnx", &["SHA-256", "step.onnx"]);
}

#[test]
fn resized_file() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("objects/mug.obj");
    let mut bytes = fs::read(&p).unwrap();
    bytes.push(b'\n');
    fs::write(&p, bytes).unwrap();
    expect_bundle_error(&b.dir, "objects/mug.obj", &["bytes", "manifest"]);
}

#[test]
fn deleted_file() {
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_file(b.path("decoder.onnx")).unwrap();
    expect_bundle_error(&b.dir, "decoder.onnx", &["missing"]);
}

#[test]
fn missing_manifest() {
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_file(b.path("manifest.json")).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["missing"]);
    let nowhere = b.path("no-such-dir");
    expect_bundle_error(&nowhere, "no-such-dir", &["not a directory"]);
}

#[test]
fn unlisted_file() {
    let b = TempBundle::copy_of(&tiny_dir());
    fs::write(b.path("objects/extra.obj"), b"v 0 0 0\n").unwrap();
    // Dot-files (OS junk) are ignored.
    fs::write(b.path(".DS_Store"), b"junk").unwrap();
    expect_bundle_error(&b.dir, "", &["not listed", "objects/extra.obj"]);
}

#[test]
fn parity_directory_is_optional() {
    let b = TempBundle::copy_of(&tiny_dir());
    fs::remove_dir_all(b.path("parity")).unwrap();
    Bundle::load(&b.dir).unwrap();
}

#[test]
fn wrong_version() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["version"] = 2.into());
    expect_bundle_error(&b.dir, "manifest.json", &["unsupported bundle version 2"]);
}

#[test]
fn wrong_format() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["format"] = "something-else".into());
    expect_bundle_error(&b.dir, "manifest.json", &["format", "something-else"]);
}

#[test]
fn truncated_manifest_json() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("manifest.json");
    let text = fs::read(&p).unwrap();
    fs::write(&p, &text[..text.len() / 2]).unwrap();
    expect_bundle_error(&b.dir, "manifest.json", &["not valid JSON", "EOF"]);
}

#[test]
fn unknown_and_missing_fields() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["transformer"]["kv_dtype"] = "int8".into());
    expect_bundle_error(&b.dir, "manifest.json", &["unknown field `kv_dtype`"]);
    b.edit_manifest(|m| {
        m["transformer"].as_object_mut().unwrap().remove("kv_dtype");
        m.as_object_mut().unwrap().remove("fps");
    });
    expect_bundle_error(&b.dir, "manifest.json", &["missing field `fps`"]);
}

#[test]
fn codebook_size_breaking_the_id_rule() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["components"][1]["codebook_size"] = 33.into());
    expect_bundle_error(&b.dir, "manifest.json", &["component body", "codebook_size 33"]);
}

#[test]
fn codebook_size_disagreeing_with_the_graphs() {
    // Consistent ids and declared shapes for J = 40, but step.onnx was exported for J = 32.
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        let c = &mut m["components"][1];
        c["codebook_size"] = 40.into();
        c["end_id"] = 40.into();
        c["pad_id"] = 41.into();
        c["vocab_size"] = 42.into();
        m["transformer"]["outputs"][1]["shape"] = serde_json::json!([1, 42]);
        m["decoder"]["state_pad_ids"][1] = 40.into();
        let k1 = m["decoder"]["state_tokens"].as_u64().unwrap() as usize;
        m["decoder"]["initial_state"][0][1] = serde_json::json!(vec![40; k1]);
    });
    expect_bundle_error(&b.dir, "step.onnx", &["logits_body is float32 [1, 34] in the graph", "[1, 42]"]);
}

#[test]
fn declared_shape_disagreeing_with_the_fields() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["transformer"]["outputs"][1]["shape"] = serde_json::json!([1, 35]));
    expect_bundle_error(&b.dir, "manifest.json", &["transformer output #1", "logits_body", "[1, 34]"]);
}

#[test]
fn layout_that_does_not_tile() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["layout"][3]["start"] = 16.into());
    expect_bundle_error(&b.dir, "manifest.json", &["layout field object_transl"]);
}

#[test]
fn bad_normalization_and_skeleton() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| m["normalization"]["std"][7] = 0.0.into());
    expect_bundle_error(&b.dir, "manifest.json", &["std > 0"]);
    b.edit_manifest(|m| {
        m["normalization"]["std"][7] = 0.2.into();
        m["skeleton"]["parents"][3] = 5.into();
    });
    expect_bundle_error(&b.dir, "manifest.json", &["skeleton", "parents"]);
}

#[test]
fn path_escaping_the_bundle() {
    let b = TempBundle::copy_of(&tiny_dir());
    b.edit_manifest(|m| {
        let e = m["files"]["objects/mug.obj"].clone();
        m["files"].as_object_mut().unwrap().insert("../outside.obj".into(), e);
    });
    expect_bundle_error(&b.dir, "manifest.json", &["../outside.obj", "not a path inside the bundle"]);
}

#[test]
fn garbage_graph_with_matching_hash() {
    // A file that passes the hash check (the manifest was updated) but is not ONNX.
    let b = TempBundle::copy_of(&tiny_dir());
    let garbage = b"this is not an onnx graph".to_vec();
    fs::write(b.path("decoder.onnx"), &garbage).unwrap();
    let sha = comgrasp::bundle::verify::sha256_file(&b.path("decoder.onnx")).unwrap();
    b.edit_manifest(|m| {
        m["files"]["decoder.onnx"]["sha256"] = sha.into();
        m["files"]["decoder.onnx"]["bytes"] = garbage.len().into();
    });
    expect_bundle_error(&b.dir, "decoder.onnx", &["tract cannot read"]);
}

#[test]
fn graph_swapped_for_another() {
    // decoder.onnx replaced by step.onnx with a consistent files table: the graph's inputs
    // disagree with the decoder section.
    let b = TempBundle::copy_of(&tiny_dir());
    fs::copy(b.path("step.onnx"), b.path("decoder.onnx")).unwrap();
    b.edit_manifest(|m| {
        m["files"]["decoder.onnx"] = m["files"]["step.onnx"].clone();
    });
    expect_bundle_error(&b.dir, "decoder.onnx", &["graph inputs are", "state"]);
}

#[test]
fn tokenizer_without_fixed_padding() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("tokenizer.json");
    let mut tok: serde_json::Value = serde_json::from_str(&fs::read_to_string(&p).unwrap()).unwrap();
    tok["padding"] = serde_json::Value::Null;
    fs::write(&p, serde_json::to_string(&tok).unwrap()).unwrap();
    let sha = comgrasp::bundle::verify::sha256_file(&p).unwrap();
    let len = fs::metadata(&p).unwrap().len();
    b.edit_manifest(|m| {
        m["files"]["tokenizer.json"]["sha256"] = sha.clone().into();
        m["files"]["tokenizer.json"]["bytes"] = len.into();
        m["text_encoder"]["sha256"]["tokenizer.json"] = sha.into();
    });
    expect_bundle_error(&b.dir, "tokenizer.json", &["padding must be Fixed(16)"]);
}

#[test]
fn parity_index_disagreeing_with_npy() {
    let b = TempBundle::copy_of(&tiny_dir());
    let p = b.path("parity/index.json");
    let mut idx: serde_json::Value = serde_json::from_str(&fs::read_to_string(&p).unwrap()).unwrap();
    idx["files"][0]["shape"] = serde_json::json!([1, 17]);
    fs::write(&p, serde_json::to_string(&idx).unwrap()).unwrap();
    let sha = comgrasp::bundle::verify::sha256_file(&p).unwrap();
    let len = fs::metadata(&p).unwrap().len();
    b.edit_manifest(|m| {
        m["files"]["parity/index.json"]["sha256"] = sha.into();
        m["files"]["parity/index.json"]["bytes"] = len.into();
    });
    expect_bundle_error(&b.dir, "case0_input_ids.npy", &["parity/index.json says int64 [1,17]"]);
}
