"""The benchmark's pure helpers (comgrasp_train.bench): the engine's tokenization, the
derived TTFF / RTF, the bandwidth limit and the report tables. No timing is asserted."""

import json
from pathlib import Path

import numpy as np
import pytest

from comgrasp_train import bench

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "models" / "tiny"


def test_stats_nearest_rank_p90():
    s = bench.stats([5.0, 1.0, 3.0, 2.0, 4.0, 6.0, 7.0, 8.0, 9.0, 10.0])
    assert s["median"] == 5.5 and s["p90"] == 9.0 and s["min"] == 1.0 and s["n"] == 10
    assert bench.stats([]) is None


def test_tokens_hash_matches_the_rust_bench():
    # src/bin/comgrasp/bench.rs token_hash_is_sha256_of_le_int64
    assert bench.tokens_sha256(np.zeros((1, 4), np.int64)) == \
        "66687aadf862bd776c8fc18b8e9f8e20089714856ee233b3902a591d0d5f2925"


@pytest.mark.skipif(not (TINY / "tokenizer.json").is_file(), reason="no tiny bundle")
def test_engine_tokenize_pads_truncates_and_adds_special_tokens():
    from tokenizers import Tokenizer

    te = json.loads((TINY / "manifest.json").read_text())["text_encoder"]
    tok = Tokenizer.from_file(str(TINY / te["files"]["tokenizer"]))
    t = te["max_tokens"]
    specials = te["tokenizer"]["special_tokens"]
    f = bench.engine_tokenize(tok, "A woman drinks from the mug.", t)
    assert set(f) == {"input_ids", "attention_mask", "token_type_ids", "position_ids"}
    assert all(v.shape == (1, t) and v.dtype == np.int64 for v in f.values())
    ids, mask = f["input_ids"][0], f["attention_mask"][0]
    n = int(mask.sum())
    assert ids[0] == specials["cls"]["id"] and ids[n - 1] == specials["sep"]["id"]
    assert (ids[n:] == te["tokenizer"]["padding"]["pad_id"]).all() and (mask[n:] == 0).all()
    assert (f["position_ids"][0] == np.arange(t)).all()
    long = bench.engine_tokenize(tok, " ".join(["mug"] * (4 * t)), t)
    assert long["attention_mask"].all() and long["input_ids"][0, -1] == specials["sep"]["id"]
    with pytest.raises(ValueError):
        bench.engine_tokenize(tok, "   ", t)


def test_derived_stream_same_formula_for_every_runtime():
    d = bench.derived_stream(2.0, 3.0, 5.0, 1.0, 4.0, 16, 30.0)
    assert d["ttff_ms"] == 10.0 and d["ms_per_token"] == 5.0
    assert d["rtf"] == pytest.approx(16 * 1e3 / 5.0 / 30.0)
    assert bench.derived_stream(None, 3.0, 5.0, None, 4.0, 16, 30.0) == \
        {"ttff_ms": None, "ms_per_token": None, "rtf": None}


def _engine(path="tract", step=10.0, native_bytes=None):
    st = lambda m: {"median": m, "p90": m, "mean": m, "min": m, "max": m, "n": 3}  # noqa: E731
    return {
        "engine_path": {"step": path, "decoder": path}, "threads": {"tract": 1},
        "config": {"steps": 3}, "load_ms": 5.0,
        "model": {"step_graph_bytes": 10_000_000, "kv_cache_bytes": 1_000_000,
                  "weights": {"fp32_bytes": 39_000_000, "int8_bytes": 10_000_000,
                              "native_step_reported_bytes": native_bytes}},
        "bandwidth": {"gb_per_s_1t": 20.0, "gb_per_s_2t": 30.0},
        "text_ms": st(1.0), "step_ms": st(step), "decode_ms": st(4.0), "text_input_ids": [2, 5, 3, 0],
        "derived": {"ttff_ms": 15.0, "rtf": 40.0}, "stream": {"ttff_ms": st(16.0), "matches_step_loop": True},
        "tokens_sha256": "ab" * 32,
    }


def _python(torch=True):
    st = lambda m: {"median": m, "p90": m, "mean": m, "min": m, "max": m, "n": 3}  # noqa: E731
    p = {"threads": 1, "peak_rss_mib": 100.0,
         "onnxruntime": {"text_ms": st(2.0), "step_ms": st(5.0), "decode_ms": st(4.0), "text_input_ids": [2, 5, 3, 0],
                         "stream": {"ttff_ms": 12.0, "rtf": 50.0}, "tokens_sha256": "ab" * 32}}
    if torch:
        p["torch"] = {"source": "x", "text_ms": st(3.0), "kv": {"step_ms": st(20.0), "tokens_sha256": "cd" * 32},
                      "decode_ms": st(8.0), "stream": {"ttff_ms": 30.0, "rtf": 20.0}}
    else:
        p["torch"], p["torch_note"] = None, "no weights"
    return p


def test_limit_uses_the_bytes_of_the_path_that_ran():
    tract = bench.limit_row(_engine("tract"), 5.0)
    assert tract["basis"] == "fp32"
    assert tract["lim_fp32"] == pytest.approx(40e6 / 20e9 * 1e3)  # (39 MB + 1 MB KV) / 20 GB/s
    assert tract["engine_over"] == pytest.approx(10.0 / tract["lim_fp32"])
    assert tract["ort_over"] == pytest.approx(5.0 / tract["lim_fp32"])
    native = bench.limit_row(_engine("native", 1.0, native_bytes=9_000_000), 5.0)
    assert native["basis"] == "int8" and native["lim_int8"] == pytest.approx(10e6 / 20e9 * 1e3)
    assert native["engine_over"] == pytest.approx(1.0 / native["lim_int8"])


def test_table_rows_ratios_and_agreement():
    out = bench.markdown_table([("default", _engine("native", 1.0), _python()),
                                ("default", _engine("tract"), _python(torch=False))])
    rows = [line for line in out.splitlines() if line.startswith("| default |")]
    assert len(rows) == 10  # five tables, two rows each
    ort_native = rows[0].split(" | ")
    assert ort_native[1:3] == ["native", "1"]
    # text 1 / 2 ms -> 0.50; step 1 / 5 -> 0.20; RTF is the time ratio: ORT 50 / engine 40.
    assert ort_native[-5:] == ["0.50", "0.20", "1.00", "1.25", "1.25 |"]
    assert "PyTorch: n/a (no weights)" in out
    agree = [r for r in rows if "abababababab" in r]
    assert agree and all(r.split(" | ")[5] == "yes" and r.rstrip(" |").endswith("yes") for r in agree)
    assert "**NO**" in agree[0]  # torch KV drew other tokens
