"""scripts/quality_report.py: the bars table it writes and the held-out wordings it runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
quality_report = pytest.importorskip("quality_report")


def _row(text: str, label: str) -> list[str]:
    line = next(x for x in text.splitlines() if x.startswith(f"| {label}"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_bars_read_an_earlier_table_and_the_engines_frames(tmp_path):
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"VQ reconstruction": {
        "mpjpe_mm": {"mean": 44.0, "ci95": 1.0}, "h_mpjpe_mm": {"mean": 12.0, "ci95": 1.0},
        "contact_accuracy": {"mean": 0.99, "ci95": 0.01}}}))
    out = tmp_path / "out"
    out.mkdir()
    for name, ok in (("engine.json", 0.95), ("engine_held_out.json", 0.7), ("engine_raw.json", 0.1)):
        (out / name).write_text(json.dumps({"n": 48, "rates": {"intent_ok": ok, "intent_grasp": 0.96}}))
    text = quality_report.bars(out, earlier)
    # No table of its own: PyTorch's rows come from the earlier one, and say so.
    assert _row(text, "VQ reconstruction MPJPE")[1:] == ["44.000 ± 1.000", "<= 15.0", "no"]
    assert f"(from {earlier})" in _row(text, "VQ reconstruction MPJPE")[0]
    assert _row(text, "VQ reconstruction H-MPJPE")[3] == "yes"
    assert _row(text, "generation intent_ok, template prompts")[1] == "not measured"
    # The engine's frames carry the generation bars: met, missed, and no target for raw.
    assert _row(text, "engine frames, template prompts: intent_ok")[1:] == ["0.950", ">= 0.9", "yes"]
    assert _row(text, "engine frames, held-out wordings: intent_ok")[1:] == ["0.700", ">= 0.8", "no"]
    assert _row(text, "engine frames, held-out wordings: intent_grasp")[1:] == ["0.960", ">= 0.95", "yes"]
    assert _row(text, "engine frames, raw (no contact stage): intent_ok")[2:] == ["–", "–"]
    # A table of its own wins over the earlier one.
    (out / "table.json").write_text(json.dumps({"VQ reconstruction": {"mpjpe_mm": {"mean": 14.0, "ci95": 0.5}}}))
    text = quality_report.bars(out, earlier)
    assert _row(text, "VQ reconstruction MPJPE")[:2] == ["VQ reconstruction MPJPE (mm)", "14.000 ± 0.500"]


def test_held_out_wordings_keep_the_meaning_and_change_the_words():
    from comgrasp_train.grab.paraphrase import HELD_OUT_VERBS

    for k, (text, meaning) in enumerate(quality_report.prompts(12)):
        held = quality_report.held_out_wording(k, meaning)
        assert held != text and held == quality_report.held_out_wording(k, meaning)
        intent, _, mode = meaning.split()
        # The intent's held-out verb, and the hands the meaning names.
        verbs = {f.split("{obj}")[0] for v in HELD_OUT_VERBS[intent] for f in v if f}
        assert any(v in held.lower() for v in verbs), (held, verbs)
        for side in ("left", "right"):
            assert (side in held.lower()) == (side in mode), (held, mode)
