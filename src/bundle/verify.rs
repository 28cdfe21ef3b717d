//! Load-time checks of a bundle, the Rust twin of `export/verify.py`: every problem is an
//! `Error::Bundle` naming the file and what is wrong, found before any stream starts.
//!
//! Order: parse the manifest (format and version first, so a newer bundle reports its
//! version rather than an unknown field); check it for internal consistency (layout,
//! component ids, shapes implied by the widths, skeleton, sampling, ...); check the files
//! (listed, present, size, SHA-256, nothing unlisted); then the graphs are loaded and their
//! real inputs/outputs compared with the manifest (`model::graph`), and the parity index is
//! checked against the `.npy` headers.
//!
//! Every check reads through a [`BundleSource`], so a directory and an in-memory bundle
//! (the embedded default) are verified alike; only the regular-file check and the walk
//! for unlisted files look at the disk itself (see `bundle::source`).
//!
//! Two decisions that differ from the Python verifier's `strict` mode:
//! * Files and directories whose name starts with '.' are ignored when looking for
//!   unlisted files (`.DS_Store`, editor swap files); every other unlisted file is an
//!   error, because it means the directory mixes two exports.
//! * `parity/` is optional: a shipped bundle may leave the test vectors out. When the
//!   `parity/` directory is absent, the manifest's `parity/...` entries are not required;
//!   when it is present, every listed parity file must be there and verify.
use std::collections::BTreeSet;
use std::io::Read;
use std::path::{Component as PathComponent, Path, PathBuf};

use sha2::{Digest, Sha256};

use super::manifest::*;
use super::npy;
use super::source::{BundleSource, FileStat};
use crate::error::{Error, Result};

/// The directory holding the optional parity vectors.
pub const PARITY_DIR: &str = "parity";

fn ensure(cond: bool, path: &Path, msg: impl FnOnce() -> String) -> Result<()> {
    if cond {
        Ok(())
    } else {
        Err(Error::bundle(path, msg()))
    }
}

/// Largest `manifest.json` accepted, in bytes. The shipped manifests are 36-60 KB (the
/// provenance section included); a file far larger is not a manifest, and refusing it
/// before reading bounds the loader's memory and time on a hostile bundle.
pub const MANIFEST_MAX_BYTES: u64 = 16 << 20;

/// Reads and parses `manifest.json`: format and version first, then the schema.
pub fn read_manifest(src: &BundleSource) -> Result<Manifest> {
    src.check_root()?;
    let path = src.path_of(MANIFEST_FILE);
    let bytes = match src.read_at_most(MANIFEST_FILE, MANIFEST_MAX_BYTES) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let what = if src.directory().is_some() { "the directory" } else { "the file set" };
            return Err(Error::bundle(&path, format!("missing: {what} is not a model bundle")));
        }
        Err(e) => return Err(Error::bundle(&path, format!("cannot read: {e}"))),
    };
    parse_manifest(&path, &bytes)
}

/// Parses the bytes of a `manifest.json` (`path` only names it in errors): UTF-8, JSON,
/// format and version first (so a newer bundle reports its version rather than an unknown
/// field), then the version 1 schema. No consistency checks ([`check_manifest`] does them).
/// Public for the fuzz target `manifest` (fuzz/).
#[doc(hidden)]
pub fn parse_manifest(path: &Path, bytes: &[u8]) -> Result<Manifest> {
    let text = std::str::from_utf8(bytes).map_err(|_| Error::bundle(path, "not UTF-8 text"))?;
    let value: serde_json::Value =
        serde_json::from_str(text).map_err(|e| Error::bundle(path, format!("not valid JSON ({e})")))?;
    let format = value.get("format").and_then(|v| v.as_str());
    ensure(format == Some(FORMAT), path, || {
        format!("format is {}, expected {FORMAT:?}", value.get("format").map_or("missing".into(), |v| v.to_string()))
    })?;
    let version = value.get("version").and_then(|v| v.as_u64());
    ensure(version == Some(VERSION), path, || {
        format!(
            "unsupported bundle version {} (this engine reads version {VERSION})",
            value.get("version").map_or("missing".into(), |v| v.to_string())
        )
    })?;
    // Parse again from the text, so schema errors carry a line and column.
    serde_json::from_str::<Manifest>(text)
        .map_err(|e| Error::bundle(path, format!("does not match the version {VERSION} schema: {e}")))
}

/// Internal consistency of the manifest (no file is read).
pub fn check_manifest(src: &BundleSource, m: &Manifest) -> Result<()> {
    let mp = src.path_of(MANIFEST_FILE);
    let p = mp.as_path();
    ensure(m.fps.is_finite() && m.fps > 0.0, p, || format!("fps must be finite and > 0, got {}", m.fps))?;
    ensure(m.frames_per_token >= 1, p, || "frames_per_token must be >= 1".into())?;
    ensure(m.l_max >= 1, p, || "l_max must be >= 1".into())?;
    ensure(m.frame_dim == FRAME_DIM, p, || format!("frame_dim {} != {FRAME_DIM}", m.frame_dim))?;
    check_layout(p, m)?;
    check_normalization(p, m)?;
    check_text_encoder(p, m)?;
    check_transformer(p, m)?;
    check_decoder(p, m)?;
    check_skeleton_objects_sampling(p, m)?;
    for (what, rel) in [
        ("text_encoder files.onnx", &m.text_encoder.files.onnx),
        ("text_encoder files.tokenizer", &m.text_encoder.files.tokenizer),
        ("transformer file", &m.transformer.file),
        ("decoder file", &m.decoder.file),
        ("parity index", &m.parity.index),
    ] {
        ensure(m.files.contains_key(rel.as_str()), p, || {
            format!("{what} names {rel:?}, which is not in the files table")
        })?;
    }
    for o in &m.objects {
        ensure(m.files.contains_key(&o.mesh), p, || {
            format!("object {} names mesh {:?}, which is not in the files table", o.name, o.mesh)
        })?;
    }
    for (name, sha) in &m.text_encoder.sha256 {
        let listed = m.files.get(name).map(|f| f.sha256.as_str());
        ensure(listed == Some(sha.as_str()), p, || {
            format!("text_encoder sha256 of {name} is {sha}, the files table says {listed:?}")
        })?;
    }
    Ok(())
}

fn check_layout(p: &Path, m: &Manifest) -> Result<()> {
    let mut pos = 0;
    for f in &m.layout {
        ensure(f.start == pos && f.stop > f.start, p, || {
            format!("layout field {}: [{}, {}) does not continue at {pos}", f.name, f.start, f.stop)
        })?;
        pos = f.stop;
    }
    ensure(pos == FRAME_DIM, p, || format!("layout fields end at {pos}, not {FRAME_DIM}"))?;
    let names: Vec<&str> = m.components.iter().map(|c| c.name.as_str()).collect();
    ensure(names == STREAMS, p, || format!("components are {names:?}, expected {STREAMS:?}"))?;
    let mut pos = 0;
    for (i, c) in m.components.iter().enumerate() {
        let [a, b] = c.slice;
        ensure(c.index == i && a == pos && b > a, p, || {
            format!("component {}: slice {:?} / index {} do not tile the frame at {pos}", c.name, c.slice, c.index)
        })?;
        let fields: Vec<(usize, usize)> =
            m.layout.iter().filter(|f| f.component == c.name).map(|f| (f.start, f.stop)).collect();
        ensure(fields.first().map(|f| f.0) == Some(a) && fields.last().map(|f| f.1) == Some(b), p, || {
            format!("component {}: slice {:?} disagrees with its layout fields {fields:?}", c.name, c.slice)
        })?;
        let j = c.codebook_size;
        // Token ids travel as i64 (and as u32-friendly indices); keep them far from overflow
        // (checked first, so j + 2 below cannot overflow).
        ensure(j < (1 << 31), p, || format!("component {}: codebook_size {j} is absurd", c.name))?;
        ensure(j >= 1 && (c.end_id, c.pad_id, c.vocab_size) == (j, j + 1, j + 2), p, || {
            format!(
                "component {}: codebook_size {j} needs end_id {j}, pad_id {}, vocab_size {}; got {}, {}, {}",
                c.name,
                j + 1,
                j + 2,
                c.end_id,
                c.pad_id,
                c.vocab_size
            )
        })?;
        pos = b;
    }
    ensure(pos == FRAME_DIM, p, || format!("component slices end at {pos}, not {FRAME_DIM}"))
}

fn check_normalization(p: &Path, m: &Manifest) -> Result<()> {
    let n = &m.normalization;
    ensure(n.mean.len() == FRAME_DIM && n.std.len() == FRAME_DIM, p, || {
        format!("normalization mean/std have {}/{} values, need {FRAME_DIM}", n.mean.len(), n.std.len())
    })?;
    ensure(n.mean.iter().all(|v| v.is_finite()) && n.std.iter().all(|v| v.is_finite() && *v > 0.0), p, || {
        "normalization: mean/std must be finite with std > 0".into()
    })?;
    ensure(CONTACT_CHANNELS.iter().all(|&c| n.mean[c] == 0.0 && n.std[c] == 1.0), p, || {
        format!("normalization: contact channels {CONTACT_CHANNELS:?} need mean 0, std 1")
    })
}

fn io(name: &str, dtype: Dtype, shape: &[usize]) -> IoSpec {
    IoSpec { name: name.into(), dtype, shape: shape.to_vec(), value: None }
}

/// Compares declared IO lists with the ones the other manifest fields imply.
fn same_io(p: &Path, what: &str, declared: &[IoSpec], implied: &[IoSpec]) -> Result<()> {
    let strip = |v: &[IoSpec]| v.iter().map(|s| (s.name.clone(), s.dtype, s.shape.clone())).collect::<Vec<_>>();
    let (d, i) = (strip(declared), strip(implied));
    if d == i {
        return Ok(());
    }
    let first = d.iter().zip(&i).position(|(a, b)| a != b).unwrap_or(d.len().min(i.len()));
    let show = |v: &Vec<(String, Dtype, Vec<usize>)>| {
        v.get(first).map_or("nothing".to_string(), |(n, t, s)| format!("{n} {t} {s:?}"))
    };
    Err(Error::bundle(
        p,
        format!(
        "{what} #{first}: the manifest declares {}, but the other manifest fields imply {} ({} declared, {} implied)",
        show(&d), show(&i), d.len(), i.len()),
    ))
}

fn check_text_encoder(p: &Path, m: &Manifest) -> Result<()> {
    let t = &m.text_encoder;
    let tt = t.max_tokens;
    ensure(tt >= 2, p, || format!("text_encoder max_tokens {tt} is too small"))?;
    ensure(t.dim >= 1, p, || "text_encoder dim must be >= 1".into())?;
    let known = ["input_ids", "attention_mask", "token_type_ids", "position_ids"];
    let mut seen = BTreeSet::new();
    for e in &t.inputs {
        ensure(known.contains(&e.name.as_str()) && seen.insert(e.name.as_str()), p, || {
            format!("text_encoder input {:?} is unknown or repeated (known: {known:?})", e.name)
        })?;
        ensure(e.dtype == Dtype::Int64 && e.shape == [1, tt], p, || {
            format!("text_encoder input {} is {} {:?}, needs int64 [1, max_tokens {tt}]", e.name, e.dtype, e.shape)
        })?;
    }
    ensure(seen.contains("input_ids") && seen.contains("attention_mask"), p, || {
        "text_encoder inputs must include input_ids and attention_mask".into()
    })?;
    let pooled = t.outputs.iter().find(|o| o.name == t.pool_output).ok_or_else(|| {
        Error::bundle(p, format!("text_encoder pool_output {:?} is not among its outputs", t.pool_output))
    })?;
    ensure(pooled.dtype == Dtype::Float32 && pooled.shape == [1, tt, t.dim], p, || {
        format!(
            "text_encoder {} is {} {:?}, needs float32 [1, {tt}, dim {}]",
            pooled.name, pooled.dtype, pooled.shape, t.dim
        )
    })?;
    for (what, v) in [("mean_eps", t.mean_eps), ("norm_eps", t.norm_eps)] {
        ensure(v.is_finite() && v > 0.0, p, || format!("text_encoder {what} must be finite and > 0, got {v}"))?;
    }
    if t.pooling == Pooling::Eos {
        let sel = t.eos_selection.ok_or_else(|| Error::bundle(p, "text_encoder pooling 'eos' needs eos_selection"))?;
        ensure(sel != EosSelection::FirstEos || t.eos_id.is_some(), p, || {
            "text_encoder eos_selection 'first_eos' needs eos_id".into()
        })?;
    }
    Ok(())
}

fn check_transformer(p: &Path, m: &Manifest) -> Result<()> {
    let tr = &m.transformer;
    let (l, h, s) = (tr.n_layers, tr.n_heads, tr.cache_slots);
    ensure(tr.batch == 1, p, || format!("transformer batch {} != 1", tr.batch))?;
    ensure(l >= 1 && h >= 1, p, || "transformer n_layers and n_heads must be >= 1".into())?;
    // Checked arithmetic throughout: the values come from a file (a hostile l_max of
    // usize::MAX must be an error, not an overflow panic).
    ensure(s == tr.block_size && Some(s) == m.l_max.checked_add(2), p, || {
        format!(
            "transformer cache_slots {s} / block_size {} must equal l_max + 2 = {}",
            tr.block_size,
            m.l_max.saturating_add(2)
        )
    })?;
    ensure(tr.d_text == m.text_encoder.dim, p, || {
        format!("transformer d_text {} != text_encoder dim {}", tr.d_text, m.text_encoder.dim)
    })?;
    ensure(tr.widths.len() == N_STREAMS && tr.head_dims.len() == N_STREAMS, p, || {
        format!("transformer widths/head_dims need {N_STREAMS} values")
    })?;
    let mut inputs = vec![
        io("tokens", Dtype::Int64, &[1, N_STREAMS]),
        io("pos", Dtype::Int64, &[1]),
        io("text_emb", Dtype::Float32, &[1, tr.d_text]),
    ];
    let mut outputs = Vec::new();
    let mut rows = Vec::new();
    for (i, c) in m.components.iter().enumerate() {
        let (w, d) = (tr.widths[i], tr.head_dims[i]);
        ensure(d >= 1 && h.checked_mul(d) == Some(w), p, || {
            format!("transformer stream {}: width {w} != n_heads {h} x head_dim {d}", c.name)
        })?;
        for kv in ["k", "v"] {
            inputs.push(io(&format!("cache_{kv}_{}", c.name), Dtype::Float32, &[l, 1, h, s, d]));
            rows.push(io(&format!("new_{kv}_{}", c.name), Dtype::Float32, &[l, 1, h, 1, d]));
        }
        outputs.push(io(&format!("logits_{}", c.name), Dtype::Float32, &[1, c.vocab_size]));
    }
    outputs.extend(rows);
    same_io(p, "transformer input", &tr.inputs, &inputs)?;
    same_io(p, "transformer output", &tr.outputs, &outputs)
}

fn check_decoder(p: &Path, m: &Manifest) -> Result<()> {
    let d = &m.decoder;
    ensure(d.batch == 1, p, || format!("decoder batch {} != 1", d.batch))?;
    ensure(d.context_tokens >= 1 && d.state_tokens.checked_add(1) == Some(d.context_tokens), p, || {
        format!("decoder state_tokens {} != context_tokens {} - 1", d.state_tokens, d.context_tokens)
    })?;
    ensure(d.frames_per_token == m.frames_per_token, p, || {
        format!("decoder frames_per_token {} != manifest frames_per_token {}", d.frames_per_token, m.frames_per_token)
    })?;
    let k1 = d.state_tokens;
    same_io(
        p,
        "decoder input",
        &d.inputs,
        &[io("state", Dtype::Int64, &[1, N_STREAMS, k1]), io("tokens", Dtype::Int64, &[1, N_STREAMS])],
    )?;
    same_io(
        p,
        "decoder output",
        &d.outputs,
        &[
            io("frames", Dtype::Float32, &[1, m.frames_per_token, FRAME_DIM]),
            io("next_state", Dtype::Int64, &[1, N_STREAMS, k1]),
        ],
    )?;
    let books: Vec<i64> = m.components.iter().map(|c| c.codebook_size as i64).collect();
    ensure(d.state_pad_ids == books, p, || {
        format!("decoder state_pad_ids {:?} != codebook sizes {books:?}", d.state_pad_ids)
    })?;
    // Compared in place: building the expected array would allocate whatever state_tokens
    // a hostile manifest declares.
    let state_ok = d.initial_state.len() == 1
        && d.initial_state[0].len() == books.len()
        && d.initial_state[0].iter().zip(&books).all(|(row, &j)| row.len() == k1 && row.iter().all(|&v| v == j));
    ensure(state_ok, p, || "decoder initial_state is not the state_pad_ids repeated state_tokens times".into())?;
    ensure(d.contact_channels == CONTACT_CHANNELS, p, || {
        format!("decoder contact_channels {:?} != {CONTACT_CHANNELS:?}", d.contact_channels)
    })?;
    ensure(d.output_is_normalized && d.contact_is_probability, p, || {
        "decoder must output normalized features with contact probabilities".into()
    })?;
    ensure(d.contact_threshold > 0.0 && d.contact_threshold < 1.0, p, || {
        format!("decoder contact_threshold {} must be in (0, 1)", d.contact_threshold)
    })
}

fn check_skeleton_objects_sampling(p: &Path, m: &Manifest) -> Result<()> {
    let sk = &m.skeleton;
    let par = &sk.parents;
    ensure(
        sk.joint_names.len() == NUM_JOINTS && par.len() == NUM_JOINTS && sk.rest_joints.len() == NUM_JOINTS,
        p,
        || {
            format!(
                "skeleton: need {NUM_JOINTS} joint names, parents and rest joints; got {}, {}, {}",
                sk.joint_names.len(),
                par.len(),
                sk.rest_joints.len()
            )
        },
    )?;
    ensure(par[0] == -1 && (1..NUM_JOINTS).all(|j| par[j] >= 0 && (par[j] as usize) < j), p, || {
        "skeleton: parents must put the root first (-1) and every parent before its children".into()
    })?;
    ensure(sk.rest_joints.iter().flatten().all(|v| v.is_finite()), p, || "skeleton rest_joints must be finite".into())?;
    // The contact stage rests, carries and lands the prompt's object by its box.
    ensure(!m.objects.is_empty(), p, || "objects: the catalogue needs at least one object".into())?;
    let mut names = BTreeSet::new();
    for o in &m.objects {
        ensure(!o.name.is_empty() && names.insert(o.name.as_str()), p, || {
            format!("object name {:?} is empty or repeated", o.name)
        })?;
        ensure(o.name.len() <= OBJECT_NAME_MAX && !o.name.contains('\0'), p, || {
            format!("object name {:?}: at most {OBJECT_NAME_MAX} bytes, no NUL", o.name)
        })?;
        ensure(o.centre.iter().chain(&o.half_extents).all(|v| v.is_finite()), p, || {
            format!("object {}: centre/half_extents must be finite", o.name)
        })?;
    }
    let s = &m.sampling;
    ensure(
        s.min_len <= s.max_len && s.max_len <= m.l_max && s.temperature.is_finite() && s.temperature >= 0.0,
        p,
        || {
            format!(
                "sampling defaults need 0 <= min_len {} <= max_len {} <= l_max {}, temperature {} finite >= 0",
                s.min_len, s.max_len, m.l_max, s.temperature
            )
        },
    )?;
    ensure(s.rng == "splitmix64", p, || format!("sampling rng {:?} is not \"splitmix64\"", s.rng))
}

/// A relative '/'-separated path that stays inside the bundle.
fn safe_rel(rel: &str) -> bool {
    !rel.is_empty()
        && !rel.contains('\\')
        && !rel.contains(':')
        && Path::new(rel).components().all(|c| matches!(c, PathComponent::Normal(_)))
}

/// Lower-case hex SHA-256 of a file, streamed.
pub fn sha256_file(path: &Path) -> Result<String> {
    let (mut f, _) = super::source::open_regular(path).map_err(|e| Error::bundle(path, format!("cannot open: {e}")))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf).map_err(|e| Error::bundle(path, format!("cannot read: {e}")))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(hex(&h.finalize()))
}

/// Lower-case hex SHA-256 of bytes in memory.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// Whether `parity/` exists (see the module doc).
pub fn has_parity(src: &BundleSource) -> bool {
    src.has_dir(PARITY_DIR)
}

/// Every listed file is present with its size and SHA-256; nothing unlisted is present.
pub fn check_files(src: &BundleSource, m: &Manifest) -> Result<()> {
    let mp = src.path_of(MANIFEST_FILE);
    let parity = has_parity(src);
    for (rel, entry) in &m.files {
        ensure(safe_rel(rel) && rel != MANIFEST_FILE, &mp, || {
            format!("files table entry {rel:?} is not a path inside the bundle")
        })?;
        let hex_ok =
            entry.sha256.len() == 64 && entry.sha256.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b));
        ensure(hex_ok, &mp, || format!("files table entry {rel}: {:?} is not a lower-case hex SHA-256", entry.sha256))?;
        if (!parity && rel.starts_with("parity/")) || src.omits(rel) {
            continue;
        }
        let path = src.path_of(rel);
        let len = match src.stat(rel) {
            Ok(FileStat::File { len }) => len,
            Ok(FileStat::Missing) => {
                return Err(Error::bundle(&path, format!("listed in the manifest but missing (file {rel})")))
            }
            Ok(FileStat::NotAFile) => return Err(Error::bundle(&path, format!("file {rel} is not a regular file"))),
            Err(e) => return Err(Error::bundle(&path, format!("cannot read: {e}"))),
        };
        ensure(len == entry.bytes, &path, || format!("file {rel} has {len} bytes, the manifest says {}", entry.bytes))?;
        let got = src.sha256(rel)?;
        ensure(got == entry.sha256, &path, || {
            format!(
                "file {rel}: SHA-256 {got} does not match the manifest's {} (corrupt or replaced file)",
                entry.sha256
            )
        })?;
    }
    let extra: Vec<String> =
        src.list()?.into_iter().filter(|r| r != MANIFEST_FILE && !m.files.contains_key(r)).collect();
    ensure(extra.is_empty(), &src.root(), || {
        let shown: Vec<&String> = extra.iter().take(8).collect();
        format!(
            "{} file(s) not listed in the manifest: {shown:?}{}",
            extra.len(),
            if extra.len() > 8 { " ..." } else { "" }
        )
    })
}

/// The tokenizer model type each text encoder kind is exported with.
fn tokenizer_type_for(kind: &str) -> Option<&'static str> {
    match kind {
        "minilm" => Some("WordPiece"),
        "clip" => Some("BPE"),
        _ => None,
    }
}

/// The id `tokenizer.json` gives `token`: an added (special) token first, else the model's
/// vocabulary (a `{token: id}` map, or Unigram's `[[token, score], ...]` list).
fn token_id(tok: &serde_json::Value, token: &str) -> Option<u64> {
    let added = tok.get("added_tokens").and_then(|v| v.as_array()).and_then(|a| {
        a.iter().find(|e| e.get("content").and_then(|c| c.as_str()) == Some(token)).and_then(|e| e.get("id")?.as_u64())
    });
    added.or_else(|| match tok.get("model")?.get("vocab")? {
        serde_json::Value::Object(map) => map.get(token)?.as_u64(),
        serde_json::Value::Array(list) => {
            list.iter().position(|e| e.get(0).and_then(|t| t.as_str()) == Some(token)).map(|i| i as u64)
        }
        _ => None,
    })
}

/// `tokenizer.json` belongs to this text encoder, not merely to some tokenizer: its model
/// type is the one the encoder kind is exported with (MiniLM: WordPiece, CLIP: BPE), its
/// padding id is the manifest's `text_encoder.pad_id`, and every special token the manifest
/// records (`text_encoder.tokenizer.special_tokens`) has the recorded id. A tokenizer of
/// another kind or another model would otherwise load and silently feed the graph wrong ids.
/// Run after `TextEncoder::load`, which already rejected a file that is no tokenizer at all.
pub fn check_tokenizer(src: &BundleSource, m: &Manifest) -> Result<()> {
    let t = &m.text_encoder;
    let rel = &t.files.tokenizer;
    let path = src.path_of(rel);
    let tok: serde_json::Value = serde_json::from_slice(&src.read_file(rel)?)
        .map_err(|e| Error::bundle(&path, format!("not valid JSON ({e})")))?;
    let model_type = tok.get("model").and_then(|v| v.get("type")).and_then(|v| v.as_str()).unwrap_or("(none)");
    if let Some(want) = tokenizer_type_for(&t.kind) {
        ensure(model_type == want, &path, || {
            format!(
                "tokenizer model type is {model_type}, a {} text encoder needs {want} (a tokenizer of another kind)",
                t.kind
            )
        })?;
    }
    let pad = tok.get("padding").and_then(|p| p.get("pad_id")).and_then(|v| v.as_i64());
    ensure(pad == Some(t.pad_id), &path, || {
        format!("padding pad_id is {pad:?}, the manifest's text_encoder.pad_id is {}", t.pad_id)
    })?;
    if let Some(special) = t.tokenizer.get("special_tokens").and_then(|v| v.as_object()) {
        for (role, spec) in special {
            let (Some(token), Some(id)) =
                (spec.get("token").and_then(|v| v.as_str()), spec.get("id").and_then(|v| v.as_u64()))
            else {
                continue;
            };
            let got = token_id(&tok, token);
            ensure(got == Some(id), &path, || {
                format!(
                    "special token {token:?} ({role}) has id {got:?} in the tokenizer, the manifest says {id} \
                         (the tokenizer of another model?)"
                )
            })?;
        }
    }
    Ok(())
}

/// parity/index.json agrees with the manifest and with the `.npy` headers (when parity/
/// is present).
pub fn check_parity_index(src: &BundleSource, m: &Manifest) -> Result<()> {
    if !has_parity(src) {
        return Ok(());
    }
    let path: PathBuf = src.path_of(&m.parity.index);
    let index: serde_json::Value = serde_json::from_slice(&src.read_file(&m.parity.index)?)
        .map_err(|e| Error::bundle(&path, format!("not valid JSON ({e})")))?;
    ensure(
        index.get("format").and_then(|v| v.as_str()) == Some("comgrasp-parity")
            && index.get("version").and_then(|v| v.as_u64()) == Some(1),
        &path,
        || "not a version 1 comgrasp-parity index".into(),
    )?;
    let files = index.get("files").and_then(|v| v.as_array()).ok_or_else(|| Error::bundle(&path, "no files list"))?;
    for e in files {
        let rel = e
            .get("path")
            .and_then(|v| v.as_str())
            .ok_or_else(|| Error::bundle(&path, format!("entry without a path: {e}")))?;
        ensure(m.files.contains_key(rel), &path, || {
            format!("lists {rel:?}, which is not in the manifest's files table")
        })?;
        let dtype = e.get("dtype").and_then(|v| v.as_str()).unwrap_or("?");
        let shape = e.get("shape").cloned().unwrap_or(serde_json::Value::Null);
        let npy_path = src.path_of(rel);
        let h = npy::parse_header(&npy_path, &src.read_file(rel)?)?;
        let same_shape = shape.as_array().is_some_and(|a| {
            a.len() == h.shape.len() && a.iter().zip(&h.shape).all(|(x, &y)| x.as_u64() == Some(y as u64))
        });
        ensure(h.dtype.numpy_name() == dtype && same_shape, &npy_path, || {
            format!("the file is {} {:?} but parity/index.json says {dtype} {shape}", h.dtype.numpy_name(), h.shape)
        })?;
    }
    Ok(())
}
