"""Load-time checks of a bundle: what the engine checks, in Python, with precise errors.

``load_and_verify_bundle(dir)`` returns the manifest or raises ``BundleError`` naming the
first problem: unknown format/version, a missing, unlisted, resized or altered file (by
SHA-256), a manifest shape that disagrees with a graph's real inputs/outputs (read with
``onnx``), a layout that does not tile 0..335, component ids that break the
End = J, Pad = J + 1 rule, a native weight file (``native`` sections) whose dtype or shape
disagrees with its entry, and so on. The schema is in ``export.bundle``'s docstring.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..layout import COMPONENTS, CONTACT_CHANNELS, FRAME_DIM
from ..skeleton import NUM_JOINTS
from .bundle import FORMAT, MANIFEST, VERSION
from .text_encoder_export import sha256_file

REQUIRED = ("fps", "frames_per_token", "l_max", "frame_dim", "layout", "components", "normalization",
            "text_encoder", "transformer", "decoder", "skeleton", "objects", "sampling", "parity", "files",
            "provenance")


class BundleError(ValueError):
    """The bundle is not one this reader can use; the message says exactly why."""


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise BundleError(msg)


def load_and_verify_bundle(bundle_dir: str | Path, strict: bool = True) -> dict:
    """Verify everything the engine relies on; ``strict`` also rejects files the manifest
    does not list. Returns the parsed manifest."""
    root = Path(bundle_dir)
    try:
        m = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BundleError(f"{root}: no {MANIFEST}") from None
    except ValueError as e:
        raise BundleError(f"{root / MANIFEST}: not valid JSON ({e})") from None
    _check(isinstance(m, dict) and m.get("format") == FORMAT,
           f"{MANIFEST}: format is {m.get('format') if isinstance(m, dict) else m!r}, expected {FORMAT!r}")
    _check(m.get("version") == VERSION, f"{MANIFEST}: unsupported bundle version {m.get('version')!r} "
                                        f"(this reader knows version {VERSION})")
    missing = [k for k in REQUIRED if k not in m]
    _check(not missing, f"{MANIFEST}: missing keys {missing}")
    try:
        _verify_files(root, m["files"], strict)
        _verify_layout(m)
        _verify_text_encoder(root, m)
        _verify_transformer(root, m)
        _verify_decoder(root, m)
        _verify_rest(root, m)
        for key in ("text_encoder", "transformer", "decoder"):
            if m[key].get("native") is not None:
                _verify_native(root, m, m[key]["native"], f"{key}.native")
        if m["text_encoder"].get("native") is not None:
            _verify_text_native(m)
    except (KeyError, TypeError, IndexError, StopIteration) as e:  # a malformed entry, never a crash
        raise BundleError(f"{MANIFEST}: malformed or incomplete entry ({type(e).__name__}: {e})") from e
    return m


def _verify_files(root: Path, files: dict, strict: bool) -> None:
    for rel, info in files.items():
        _check(not Path(rel).is_absolute() and ".." not in Path(rel).parts, f"file path {rel!r} leaves the bundle")
        p = root / rel
        _check(p.is_file(), f"file listed in the manifest is missing: {rel}")
        size = p.stat().st_size
        _check(size == info["bytes"], f"file {rel}: {size} bytes, manifest says {info['bytes']}")
        digest = sha256_file(p)
        _check(digest == info["sha256"], f"file {rel}: SHA-256 {digest} does not match the manifest's {info['sha256']}")
    if strict:
        extra = sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                       if p.is_file() and p.relative_to(root).as_posix() not in files
                       and p.relative_to(root).as_posix() != MANIFEST)
        _check(not extra, f"files not listed in the manifest: {extra}")


def _listed(m: dict, rel: str, what: str) -> None:
    _check(rel in m["files"], f"{what} names {rel!r}, which is not in the manifest's files table")


def _verify_layout(m: dict) -> None:
    _check(m["frame_dim"] == FRAME_DIM, f"frame_dim {m['frame_dim']} != {FRAME_DIM}")
    pos = 0
    for f in m["layout"]:
        _check(f["start"] == pos and f["stop"] > f["start"], f"layout field {f['name']}: [{f['start']}, {f['stop']}) "
                                                             f"does not continue at {pos}")
        pos = f["stop"]
    _check(pos == FRAME_DIM, f"layout fields end at {pos}, not {FRAME_DIM}")
    comps = m["components"]
    _check([c["name"] for c in comps] == list(COMPONENTS),
           f"components are {[c['name'] for c in comps]}, expected {list(COMPONENTS)}")
    pos = 0
    for i, c in enumerate(comps):
        a, b = c["slice"]
        fields = [(f["start"], f["stop"]) for f in m["layout"] if f["component"] == c["name"]]
        _check(c["index"] == i and a == pos and b > a, f"component {c['name']}: slice {c['slice']} / index "
                                                       f"{c['index']} do not tile the frame at {pos}")
        _check(fields and fields[0][0] == a and fields[-1][1] == b,
               f"component {c['name']}: slice {c['slice']} disagrees with its layout fields {fields}")
        j = c["codebook_size"]
        _check(j >= 1 and (c["end_id"], c["pad_id"], c["vocab_size"]) == (j, j + 1, j + 2),
               f"component {c['name']}: codebook_size {j} needs end_id {j}, pad_id {j + 1}, vocab_size {j + 2}; "
               f"got {c['end_id']}, {c['pad_id']}, {c['vocab_size']}")
        pos = b
    _check(pos == FRAME_DIM, f"component slices end at {pos}, not {FRAME_DIM}")
    n = m["normalization"]
    mean, std = np.asarray(n["mean"], np.float64), np.asarray(n["std"], np.float64)
    _check(mean.shape == (FRAME_DIM,) and std.shape == (FRAME_DIM,),
           f"normalization mean/std have {mean.shape}/{std.shape} values, need {FRAME_DIM}")
    _check(bool(np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()),
           "normalization: mean/std must be finite with std > 0")
    c = list(CONTACT_CHANNELS)
    _check(bool((mean[c] == 0).all() and (std[c] == 1).all()),
           f"normalization: contact channels {c} need mean 0, std 1")


def graph_io(path: Path) -> tuple[list[dict], list[dict]]:
    """The graph's real inputs (initializers excluded) and outputs as [{name, dtype, shape}]."""
    import onnx
    from onnx.helper import tensor_dtype_to_np_dtype

    g = onnx.load(str(path), load_external_data=False).graph
    inits = {i.name for i in g.initializer}

    def one(v):
        t = v.type.tensor_type
        shape = [d.dim_value if d.HasField("dim_value") else d.dim_param for d in t.shape.dim]
        return {"name": v.name, "dtype": str(tensor_dtype_to_np_dtype(t.elem_type)), "shape": shape}

    return [one(v) for v in g.input if v.name not in inits], [one(v) for v in g.output]


def _verify_graph(root: Path, m: dict, rel: str, section: dict, what: str) -> None:
    _listed(m, rel, what)
    ins, outs = graph_io(root / rel)
    for kind, declared, real in (("inputs", section["inputs"], ins), ("outputs", section["outputs"], outs)):
        d = [(e["name"], e["dtype"], list(e["shape"])) for e in declared]
        r = [(e["name"], e["dtype"], e["shape"]) for e in real]
        _check(d == r, f"{rel}: the manifest's {what} {kind} {d} do not match the graph's {r}")


def _shape(section: dict, name: str) -> list:
    return next(e["shape"] for e in section["inputs"] + section["outputs"] if e["name"] == name)


def _verify_text_encoder(root: Path, m: dict) -> None:
    t = m["text_encoder"]
    onnx_rel, tok_rel = t["files"]["onnx"], t["files"]["tokenizer"]
    _verify_graph(root, m, onnx_rel, t, "text_encoder")
    _listed(m, tok_rel, "text_encoder")
    for e in t["inputs"]:
        _check(e["shape"] == [1, t["max_tokens"]],
               f"text_encoder input {e['name']} shape {e['shape']} != [1, max_tokens {t['max_tokens']}]")
    pooled = _shape(t, t["pool_output"])
    _check(pooled[:2] == [1, t["max_tokens"]] and pooled[2] == t["dim"],
           f"text_encoder {t['pool_output']} shape {pooled} != [1, {t['max_tokens']}, dim {t['dim']}]")
    from tokenizers import Tokenizer

    enc = Tokenizer.from_file(str(root / tok_rel)).encode("a test prompt", add_special_tokens=True)
    _check(len(enc.ids) == t["max_tokens"],
           f"{tok_rel} pads to {len(enc.ids)} tokens, manifest max_tokens {t['max_tokens']}")


def _verify_transformer(root: Path, m: dict) -> None:
    tr, comps = m["transformer"], m["components"]
    _verify_graph(root, m, tr["file"], tr, "transformer")
    L, H, S = tr["n_layers"], tr["n_heads"], tr["cache_slots"]
    _check(S == tr["block_size"] == m["l_max"] + 2, f"transformer cache_slots {S} / block_size {tr['block_size']} "
                                                    f"must equal l_max + 2 = {m['l_max'] + 2}")
    _check(tr["d_text"] == m["text_encoder"]["dim"], f"transformer d_text {tr['d_text']} != text_encoder dim "
                                                     f"{m['text_encoder']['dim']}")
    expect = {"tokens": [1, len(comps)], "pos": [1], "text_emb": [1, tr["d_text"]]}
    for c, w, d in zip(comps, tr["widths"], tr["head_dims"]):
        _check(w == H * d, f"transformer stream {c['name']}: width {w} != n_heads {H} x head_dim {d}")
        s = c["name"]
        expect[f"logits_{s}"] = [1, c["vocab_size"]]
        for kv in "kv":
            expect[f"cache_{kv}_{s}"] = [L, 1, H, S, d]
            expect[f"new_{kv}_{s}"] = [L, 1, H, 1, d]
    for name, shape in expect.items():
        got = _shape(tr, name)
        _check(got == shape, f"{tr['file']}: {name} has shape {got}, but the manifest's components/transformer "
                             f"fields imply {shape}")


def _verify_decoder(root: Path, m: dict) -> None:
    dec, comps = m["decoder"], m["components"]
    _verify_graph(root, m, dec["file"], dec, "decoder")
    k1, p = dec["state_tokens"], len(comps)
    _check(k1 == dec["context_tokens"] - 1 >= 0, f"decoder state_tokens {k1} != context_tokens - 1")
    _check(dec["frames_per_token"] == m["frames_per_token"], "decoder frames_per_token != manifest frames_per_token")
    for name, shape in (("state", [1, p, k1]), ("next_state", [1, p, k1]), ("tokens", [1, p]),
                        ("frames", [1, m["frames_per_token"], m["frame_dim"]])):
        got = _shape(dec, name)
        _check(got == shape, f"{dec['file']}: {name} has shape {got}, the manifest implies {shape}")
    books = [c["codebook_size"] for c in comps]
    _check(dec["state_pad_ids"] == books, f"decoder state_pad_ids {dec['state_pad_ids']} != codebook sizes {books}")
    _check(dec["initial_state"] == [[[j] * k1 for j in books]],
           "decoder initial_state is not the state_pad_ids repeated state_tokens times")
    _check(dec["contact_channels"] == list(CONTACT_CHANNELS), f"decoder contact_channels {dec['contact_channels']} "
                                                              f"!= {list(CONTACT_CHANNELS)}")


def _verify_rest(root: Path, m: dict) -> None:
    sk = m["skeleton"]
    par = sk["parents"]
    _check(len(sk["joint_names"]) == len(par) == NUM_JOINTS and par[0] == -1
           and all(0 <= par[j] < j for j in range(1, len(par))),
           f"skeleton: need {NUM_JOINTS} joint names and parents, root first, parents before children")
    _check(np.asarray(sk["rest_joints"], np.float64).shape == (NUM_JOINTS, 3), "skeleton rest_joints must be (55, 3)")
    for o in m["objects"]:
        _listed(m, o["mesh"], f"object {o['name']}")
        _check(len(o["centre"]) == 3, f"object {o['name']}: centre must have 3 values")
    s = m["sampling"]
    _check(0 <= s["min_len"] <= s["max_len"] <= m["l_max"] and s["top_k"] >= 0 and s["temperature"] >= 0,
           f"sampling defaults {s} need 0 <= min_len <= max_len <= l_max {m['l_max']}, top_k >= 0, temperature >= 0")
    index_rel = m["parity"]["index"]
    _listed(m, index_rel, "parity")
    index = json.loads((root / index_rel).read_text(encoding="utf-8"))
    for e in index["files"]:
        _listed(m, e["path"], "parity/index.json")
        a = np.load(root / e["path"], mmap_mode="r")
        _check(str(a.dtype) == e["dtype"] and list(a.shape) == e["shape"],
               f"{e['path']}: {a.dtype} {list(a.shape)} but parity/index.json says {e['dtype']} {e['shape']}")


def _npy_header(path: Path) -> tuple[str, list]:
    a = np.load(path, mmap_mode="r")
    return str(a.dtype), list(a.shape)


def _verify_native(root: Path, m: dict, section: dict, what: str) -> None:
    """Every tensor of a native section: its files listed, their npy dtype/shape as the
    entry says (int8: (shape) int8 + (rows,) float32 scale; int4: (rows, ceil(cols/2))
    uint8 + scale)."""
    base = section["dir"].rstrip("/")
    for name, spec in section["tensors"].items():
        dtype, shape = spec["dtype"], [int(d) for d in spec["shape"]]
        rel = f"{base}/{name}.npy"
        _listed(m, rel, what)
        if dtype == "float32":
            want = ("float32", shape)
        elif dtype == "int8":
            want = ("int8", shape)
        elif dtype == "int4":
            _check(len(shape) == 2, f"{what} {name}: int4 tensors are 2-D, shape {shape}")
            want = ("uint8", [shape[0], (shape[1] + 1) // 2])
        else:
            raise BundleError(f"{what} {name}: unknown dtype {dtype!r} (float32 | int8 | int4)")
        got = _npy_header(root / rel)
        _check(got == (want[0], want[1]), f"{rel}: {got[0]} {got[1]}, but {what} implies {want[0]} {want[1]}")
        if dtype in ("int8", "int4"):
            srel = f"{base}/{name}.scale.npy"
            _listed(m, srel, what)
            got = _npy_header(root / srel)
            _check(got == ("float32", shape[:1]), f"{srel}: {got[0]} {got[1]}, expected float32 {shape[:1]}")


def _verify_text_native(m: dict) -> None:
    """text_encoder.native: a whole BERT (every BertTokenStates parameter, nothing else),
    exact GELU, heads dividing the width, the position table cut to max_tokens."""
    from .native_weights import bert_native_names

    t = m["text_encoder"]
    n = t["native"]
    names = set(n["tensors"])
    layers = sorted({int(k.split(".")[1]) for k in names if k.startswith("layers.")})
    _check(layers == list(range(len(layers))) and names == set(bert_native_names(len(layers))),
           f"text_encoder.native: tensors are not those of a BERT of {len(layers)} layers")
    _check(n["activation"] == "gelu", f"text_encoder.native: activation {n['activation']!r}, only 'gelu' (erf)")
    hidden = t["hidden"]
    _check(isinstance(n["heads"], int) and n["heads"] > 0 and hidden % n["heads"] == 0,
           f"text_encoder.native: heads {n['heads']} does not divide hidden {hidden}")
    _check(float(n["layer_norm_eps"]) > 0, "text_encoder.native: layer_norm_eps must be > 0")
    tensors = n["tensors"]
    _check(tensors["embeddings.position_embeddings.weight"]["shape"] == [t["max_tokens"], hidden],
           f"text_encoder.native: position table {tensors['embeddings.position_embeddings.weight']['shape']} "
           f"!= [max_tokens {t['max_tokens']}, hidden {hidden}]")
    word = tensors["embeddings.word_embeddings.weight"]["shape"]
    _check(len(word) == 2 and word[1] == hidden, f"text_encoder.native: word table {word} is not [vocab, {hidden}]")
    int4 = sorted(k for k, v in tensors.items() if v["dtype"] == "int4")
    _check(int4 in ([], ["embeddings.word_embeddings.weight"]),
           f"text_encoder.native: only the word table may be int4, got {int4}")


def main(argv: list[str] | None = None) -> int:
    """``python -m comgrasp_train.export.verify BUNDLE...``: exit 1 naming the first problem."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(description="verify model bundles as the engine loads them")
    ap.add_argument("bundles", nargs="+")
    ap.add_argument("--lenient", action="store_true", help="allow files the manifest does not list")
    a = ap.parse_args(argv)
    for b in a.bundles:
        try:
            load_and_verify_bundle(b, strict=not a.lenient)
        except BundleError as e:
            print(f"{b}: {e}", file=sys.stderr)
            return 1
        print(f"{b}: ok")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
