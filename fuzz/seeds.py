#!/usr/bin/env python3
"""Writes the committed seed corpora under fuzz/corpus/<target>/ (deterministic; rerun after
a manifest schema change). Seeds are small hand-made inputs that reach each target's
interesting paths at once; libFuzzer mutates from there. Usage: python3 fuzz/seeds.py"""
import json
import shutil
import struct
from pathlib import Path

FUZZ = Path(__file__).resolve().parent
ROOT = FUZZ.parent
TINY = ROOT / "models" / "tiny"


def write(target: str, name: str, data: bytes) -> None:
    d = FUZZ / "corpus" / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)


def reset(target: str) -> None:
    shutil.rmtree(FUZZ / "corpus" / target, ignore_errors=True)


# --- prompt_text: byte 0 = mode (bit 0: cg_start_utf8, bit 1: wait for the first frame).
reset("prompt_text")
prompts = {
    "mug": (2, "A woman drinks from the mug".encode()),
    "cube_utf8": (3, "The man lifts a small cube.".encode()),
    "unicode": (2, "Eine Frau trinkt aus dem Becher \u00e9\u00e8 \u4e2d\u6587 \U0001f964".encode()),
    "combining": (2, "a\u0301\u0302\u0303 \u200b\u200d\ufeff cup".encode()),
    "blank": (0, b" \t\n\u3000".replace(b"\\u3000", "\u3000".encode())),
    "nul_counted": (1, b"lift\x00the cube"),
    "bad_utf8": (1, b"lift \xff\xfe the \xc3"),
    "long_words": (2, ("pneumonoultramicroscopicsilicovolcanoconiosis " * 40).encode()),
    "at_limit": (3, b"a " * 2048),
    "over_limit": (1, b"b" * 4097),
    "special_tokens": (2, b"[CLS] [SEP] [PAD] [UNK] [MASK] ##ing"),
    "punct": (2, b"!!!???...,,,;;;:::---___((()))"),
}
for name, (mode, text) in prompts.items():
    write("prompt_text", name, bytes([mode]) + text)


# --- manifest: the tiny bundle's manifest (pretty and minified) and broken variants.
reset("manifest")
text = (TINY / "manifest.json").read_text()
m = json.loads(text)
write("manifest", "tiny_pretty.json", text.encode())
write("manifest", "tiny_min.json", json.dumps(m, separators=(",", ":")).encode())
write("manifest", "truncated.json", text.encode()[: len(text) // 2])


def variant(name: str, edit) -> None:
    v = json.loads(text)
    edit(v)
    write("manifest", name, json.dumps(v, separators=(",", ":")).encode())


variant("version2.json", lambda v: v.__setitem__("version", 2))
variant("huge_l_max.json", lambda v: v.__setitem__("l_max", 2**64 - 1))
variant("huge_state_tokens.json", lambda v: (v["decoder"].__setitem__("state_tokens", 2**40),
                                             v["decoder"].__setitem__("context_tokens", 2**40 + 1)))
variant("huge_codebook.json", lambda v: v["components"][1].__setitem__("codebook_size", 2**64 - 1))
variant("huge_heads.json", lambda v: v["transformer"].__setitem__("n_heads", 2**63))
variant("unknown_field.json", lambda v: v["transformer"].__setitem__("kv_dtype", "int8"))
variant("escaping_path.json", lambda v: v["files"].__setitem__("../x", v["files"]["step.onnx"]))
variant("no_files.json", lambda v: v.__setitem__("files", {}))


# --- npy: small parity vectors and broken headers.
reset("npy")
for rel in ["parity/text/case0_input_ids.npy", "parity/text/case0_attention_mask.npy", "parity/rng/u64.npy"]:
    p = TINY / rel
    if p.exists() and p.stat().st_size < 4096:
        write("npy", p.name, p.read_bytes())


def npy(descr: str, shape: str, data: bytes, major: int = 1) -> bytes:
    header = ("{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)).encode()
    header += b" " * ((-(len(header) + 11)) % 16) + b"\n"
    size = struct.pack("<H", len(header)) if major == 1 else struct.pack("<I", len(header))
    return b"\x93NUMPY" + bytes([major, 0]) + size + header + data


write("npy", "f4_2x3.npy", npy("<f4", "(2, 3)", struct.pack("<6f", *range(6))))
write("npy", "v2_i8.npy", npy("<i8", "(2,)", struct.pack("<2q", -1, 7), major=2))
write("npy", "overflow_shape.npy", npy("<f8", "(4294967296, 4294967296, 0)", b""))
write("npy", "zero_dim.npy", npy("|u1", "()", b"\x05"))
write("npy", "fortran.npy", npy("<f4", "(1,)", b"\0\0\0\0").replace(b"False", b"True "))


# --- abi_sequence: op code, then operands (see fuzz_targets/abi_sequence.rs).
reset("abi_sequence")
CFG = bytes([5, 0xff]) + bytes(8) + bytes([4, 64, 0, 0, 1, 1])  # stream config operands (unused with NULL cfg)


def start(engine_idx: int, chunks_sel: int, mult: int, frames: int, mode: int) -> bytes:
    # op 3, engine pick (sel 3 = from the list, index), chunks sel (+ multiplier), frames,
    # fail sel (1 = no failure), mode (2 = scripted text, NULL cfg), config operands.
    ops = bytes([3, 3, engine_idx, chunks_sel])
    if chunks_sel % 4 != 0:
        ops += bytes([mult])
    return ops + bytes([frames, 1, mode]) + CFG


seq_basic = (bytes([0, 3, 1])                 # test engine: ring 4, max_streams 2
             + start(0, 1, 1, 3, 2)           # stream: 2 chunks of 4 frames
             + bytes([8, 3, 0])               # drain it to END
             + bytes([13, 3, 0, 1])           # stream count
             + bytes([10, 3, 0])              # destroy it
             + bytes([5, 2, 3, 0])            # poll the destroyed handle
             + bytes([2, 3, 0]))              # destroy the engine
write("abi_sequence", "basic", seq_basic)
seq_cancel = (bytes([0, 1, 3])
              + start(0, 0, 0, 15, 2)          # an endless stream
              + bytes([6, 3, 3, 0])            # wait 1 ms
              + bytes([11, 3, 0, 2])           # cancel racing a wait
              + bytes([5, 2, 3, 0])            # poll: CANCELLED
              + bytes([10, 3, 0, 10, 3, 0])    # destroy twice
              + bytes([2, 3, 0, 2, 3, 0]))     # engine destroy twice
write("abi_sequence", "cancel_race", seq_cancel)
seq_limit = (bytes([0, 0, 0])                  # max_streams 1
             + start(0, 1, 0, 0, 2) + start(0, 1, 0, 0, 2)   # the second hits CG_ERR_LIMIT
             + bytes([2, 3, 0])                # engine destroyed with a live stream
             + bytes([7, 4, 3, 0])             # the stream after its engine is gone
             + bytes([12, 3, 0, 1]))
write("abi_sequence", "limit_and_orphan", seq_limit)
seq_bad = (bytes([1, 4, 2, 0, 1]) + bytes(8) + bytes([1, 1])   # cg_engine_create, bad configs
           + bytes([5, 1]) + struct.pack("<Q", 0x0000_0001_0000_0019)  # forged stream handle
           + bytes([9, 0, 10, 0, 2, 0])       # NULL cancel / destroy / engine destroy
           + bytes([14, 0xfd, 0xff, 0xff, 0xff, 7, 1])            # status string, message
           + bytes([15]))
write("abi_sequence", "bad_inputs", seq_bad)
seq_fail = (bytes([0, 7, 3]) + start(0, 3, 1, 4, 2)[:-len(CFG) - 2] + bytes([0, 1, 2]) + CFG
            + bytes([8, 3, 0, 5, 2, 3, 0]))
write("abi_sequence", "failing_stream", seq_fail)
print("seeds written under", FUZZ / "corpus")


# --- a libFuzzer dictionary for the manifest target: every key of the schema, as JSON.
keys = set()


def walk(v) -> None:
    if isinstance(v, dict):
        for k, x in v.items():
            keys.add(k)
            walk(x)
    elif isinstance(v, list):
        for x in v:
            walk(x)


walk(m)
tokens = sorted('"%s"' % k for k in keys if k.isascii() and "/" not in k and len(k) < 40)
tokens += ['"comgrasp-bundle"', '"splitmix64"', '"int64"', '"float32"', '"mean"', '"eos"', '"first_eos"',
           '"argmax_id"', "18446744073709551615", "-1", "1e309", "null", "true", "[]", "{}"]
lines = ["# Generated by fuzz/seeds.py: the manifest schema's keys and special values."]
for i, t in enumerate(tokens):
    lines.append('kw%d="%s"' % (i, t.replace("\\", "\\\\").replace('"', '\\"')))
(FUZZ / "manifest.dict").write_text("\n".join(lines) + "\n")
