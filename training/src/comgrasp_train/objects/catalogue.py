"""The SynthGrasp object catalogue: GRAB's 15 primitives plus everyday composites.

Names follow GRAB's object names (``cubesmall``, ``mug``, ``waterbottle``...) so text
templates and a model trained on SynthGrasp use the same vocabulary as GRAB. Sizes are
our own choices in metres. ``uses`` lists the object-specific ``use`` actions the
generator can perform with the object (GRAB's fine-grained intents ``drink``/``pour``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .shapes import Part, Shape


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    aliases: tuple[str, ...]  # how text may name it; the first is the default noun
    shape: Shape
    two_handed: bool = False  # big enough that the generator may grasp it with both hands
    uses: tuple[str, ...] = ()
    # Preferred grasp: "side" (palm on the side, fingers wrap), "top" (palm above).
    grasp: str = "side"
    # Where the side grasp holds it (object-frame z of the palm centre), e.g. a mug's handle.
    handle: tuple[float, float, float] | None = None

    @property
    def half_height(self) -> float:
        m = self.shape.meta
        return float(m["half_extents"][2])

    @property
    def half_extents(self) -> np.ndarray:
        return np.asarray(self.shape.meta["half_extents"], dtype=np.float64)


def _shape(parts: list[Part], half_extents) -> Shape:
    return Shape(tuple(parts), {"half_extents": [float(x) for x in half_extents]})


def _primitives() -> list[ObjectSpec]:
    out = []
    sizes = {"small": 0, "medium": 1, "large": 2}
    for size, k in sizes.items():
        a = (0.05, 0.075, 0.10)[k]
        out.append(ObjectSpec(f"cube{size}", (f"{size} cube", "cube", "block"),
                              _shape([Part("box", {"hx": a / 2, "hy": a / 2, "hz": a / 2})], [a / 2] * 3),
                              two_handed=size == "large", grasp="top" if size == "small" else "side"))
        r = (0.025, 0.0375, 0.05)[k]
        out.append(ObjectSpec(f"sphere{size}", (f"{size} sphere", "sphere", "ball"),
                              _shape([Part("sphere", {"r": r})], [r] * 3),
                              two_handed=size == "large", grasp="top" if size == "small" else "side"))
        r, hh = (0.02, 0.03, 0.04)[k], (0.05, 0.065, 0.08)[k]
        out.append(ObjectSpec(f"cylinder{size}", (f"{size} cylinder", "cylinder"),
                              _shape([Part("cylinder", {"r": r, "half_h": hh})], [r, r, hh]),
                              two_handed=size == "large"))
        b, h = (0.05, 0.075, 0.10)[k], (0.05, 0.07, 0.09)[k]
        out.append(ObjectSpec(f"pyramid{size}", (f"{size} pyramid", "pyramid"),
                              _shape([Part("pyramid", {"base": b, "height": h})], [b / 2, b / 2, h / 2]),
                              grasp="top"))
        R, rr = (0.04, 0.055, 0.07)[k], (0.01, 0.0125, 0.015)[k]
        out.append(ObjectSpec(f"torus{size}", (f"{size} torus", "torus", "ring"),
                              _shape([Part("torus", {"major": R, "minor": rr})], [R + rr, R + rr, rr]),
                              grasp="top"))
    return out


def _composites() -> list[ObjectSpec]:
    mug = ObjectSpec(
        "mug", ("mug", "coffee mug", "cup of coffee"),
        _shape([Part("cylinder", {"r": 0.04, "half_h": 0.05}),
                # Handle: a torus standing in the x-z plane on the +x side.
                Part("torus", {"major": 0.028, "minor": 0.007}, (0.058, 0.0, 0.0), (np.pi / 2, 0.0, 0.0))],
               [0.093, 0.04, 0.05]),
        uses=("drink",), handle=(0.086, 0.0, 0.0),
    )
    bottle = ObjectSpec(
        "waterbottle", ("water bottle", "bottle"),
        _shape([Part("cylinder", {"r": 0.033, "half_h": 0.06}, (0.0, 0.0, -0.025)),
                Part("cylinder", {"r": 0.015, "half_h": 0.025}, (0.0, 0.0, 0.06))],
               [0.033, 0.033, 0.085]),
        uses=("drink", "pour"),
    )
    bowl = ObjectSpec(
        "bowl", ("bowl",),
        _shape([Part("half_sphere", {"r": 0.08})], [0.08, 0.08, 0.04]),
        two_handed=True, uses=("pour",),
    )
    cup = ObjectSpec(
        "cup", ("cup", "glass"),
        _shape([Part("cylinder", {"r": 0.035, "half_h": 0.045})], [0.035, 0.035, 0.045]),
        uses=("drink", "pour"),
    )
    apple = ObjectSpec(
        "apple", ("apple",),
        _shape([Part("sphere", {"r": 0.04})], [0.04, 0.04, 0.04]),
        grasp="side",
    )
    return [mug, bottle, bowl, cup, apple]


CATALOGUE: dict[str, ObjectSpec] = {o.name: o for o in _primitives() + _composites()}

TABLE_SIZE = (1.2, 0.8, 0.04)  # x, y, thickness; table frame origin at the top-surface centre


def table_shape() -> Shape:
    sx, sy, th = TABLE_SIZE
    return _shape([Part("box", {"hx": sx / 2, "hy": sy / 2, "hz": th / 2}, (0.0, 0.0, -th / 2))],
                  [sx / 2, sy / 2, th / 2])


def write_object_meshes(root: Path, names: list[str] | None = None, max_edge: float = 0.008) -> dict[str, Path]:
    """Write ``tools/object_meshes/contact_meshes/<name>.ply`` (+ ``.shape.json``) under a
    GRAB-layout root; returns name -> mesh path. The table is written as ``table.ply``."""
    out_dir = Path(root) / "tools" / "object_meshes" / "contact_meshes"
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    items = [(n, CATALOGUE[n].shape) for n in (names or list(CATALOGUE))]
    items.append(("table", table_shape()))
    for name, shape in items:
        path = out_dir / f"{name}.ply"
        mesh = shape.mesh(max_edge if name != "table" else 0.1)
        mesh.export(path)
        (out_dir / f"{name}.shape.json").write_text(shape.to_json())
        paths[name] = path
    return paths
