"""Analytic object shapes: signed distance functions and triangle meshes.

Every SynthGrasp object is a union of primitives, each with a pose inside the object frame
(object z up, origin at the bounding-box centre). The SDF is negative inside, in metres.
Sphere, box, capped cylinder and torus SDFs are exact; the pyramid and the half-sphere
(bowl) use the max over their bounding planes, which is exact inside and a lower bound
outside near edges (never over-reports a distance, so a grasp search never ends inside).
A union of overlapping parts is exact outside and approximate deep inside; both are fine
for contact and penetration measures at the millimetre scale near the surface.

The spec is plain JSON (written beside each mesh as ``<mesh>.shape.json``) so metrics on
SynthGrasp use exact distances while real GRAB meshes fall back to a grid SDF.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Part:
    kind: str  # sphere | box | cylinder | torus | pyramid | half_sphere
    params: dict
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def local(self, p: np.ndarray) -> np.ndarray:
        """Object-frame points -> this part's frame."""
        r = Rotation.from_rotvec(self.rotvec).as_matrix()
        # einsum, not @: this numpy's BLAS path for (N,3)@(3,3) is ~100x slower at large N.
        return np.einsum("ni,ij->nj", p - np.asarray(self.pos), r)  # row form of R^T (p - t)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return _SDF[self.kind](self.local(p), **self.params)

    def mesh(self, max_edge: float) -> trimesh.Trimesh:
        m = _MESH[self.kind](**self.params)
        m = _subdivide(m, max_edge)
        tf = np.eye(4)
        tf[:3, :3] = Rotation.from_rotvec(self.rotvec).as_matrix()
        tf[:3, 3] = self.pos
        m.apply_transform(tf)
        return m


@dataclass(frozen=True)
class Shape:
    parts: tuple[Part, ...]
    meta: dict = field(default_factory=dict)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (m) of object-frame points (..., 3); negative inside."""
        p = np.asarray(p, dtype=np.float64)
        flat = p.reshape(-1, 3)
        d = np.min(np.stack([part.sdf(flat) for part in self.parts]), axis=0)
        return d.reshape(p.shape[:-1])

    def gradient(self, p: np.ndarray, h: float = 1e-4) -> np.ndarray:
        """Outward unit normal field by central differences."""
        p = np.asarray(p, dtype=np.float64)
        g = np.stack(
            [self.sdf(p + h * e) - self.sdf(p - h * e) for e in np.eye(3)], axis=-1
        )
        return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)

    def mesh(self, max_edge: float = 0.008) -> trimesh.Trimesh:
        m = trimesh.util.concatenate([part.mesh(max_edge) for part in self.parts])
        return m

    def to_json(self) -> str:
        return json.dumps(
            {
                "meta": self.meta,
                "parts": [
                    {"kind": p.kind, "params": p.params, "pos": list(p.pos), "rotvec": list(p.rotvec)}
                    for p in self.parts
                ],
            },
            indent=1,
        )

    @staticmethod
    def from_json(text: str) -> Shape:
        d = json.loads(text)
        parts = tuple(
            Part(p["kind"], dict(p["params"]), tuple(p["pos"]), tuple(p["rotvec"])) for p in d["parts"]
        )
        for p in parts:
            if p.kind not in _SDF:
                raise ValueError(f"unknown shape part kind {p.kind!r}")
        return Shape(parts, d.get("meta", {}))

    @staticmethod
    def load(path: str | Path) -> Shape:
        return Shape.from_json(Path(path).read_text())


# ---- exact / bounded SDFs (part frame, z is the axis) -------------------------------------


def _sd_sphere(p, r):
    return np.linalg.norm(p, axis=-1) - r


def _sd_box(p, hx, hy, hz):
    q = np.abs(p) - np.array([hx, hy, hz])
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def _sd_cylinder(p, r, half_h):
    d = np.stack([np.linalg.norm(p[:, :2], axis=-1) - r, np.abs(p[:, 2]) - half_h], -1)
    return np.minimum(d.max(-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)


def _sd_torus(p, major, minor):
    q = np.stack([np.linalg.norm(p[:, :2], axis=-1) - major, p[:, 2]], -1)
    return np.linalg.norm(q, axis=-1) - minor


def _sd_pyramid(p, base, height):
    # Square base of side `base` centred at z = -height/2, apex at z = +height/2.
    a = base / 2.0
    z = p[:, 2] + height / 2.0
    n = np.array([height, a]) / np.hypot(height, a)  # side-plane normal in (x|y, z)
    planes = [
        n[0] * (np.abs(p[:, 0]) - a) + n[1] * z,
        n[0] * (np.abs(p[:, 1]) - a) + n[1] * z,
        -z,
    ]
    return np.max(np.stack(planes), axis=0)


def _sd_half_sphere(p, r):
    # Lower half of a sphere (a bowl's outside), flat face at z = +r/2, centred on the bbox.
    c = p - np.array([0.0, 0.0, r / 2.0])
    return np.maximum(np.linalg.norm(c, axis=-1) - r, c[:, 2])


_SDF = {
    "sphere": _sd_sphere,
    "box": _sd_box,
    "cylinder": _sd_cylinder,
    "torus": _sd_torus,
    "pyramid": _sd_pyramid,
    "half_sphere": _sd_half_sphere,
}


# ---- meshes -------------------------------------------------------------------------------


def _subdivide(m: trimesh.Trimesh, max_edge: float) -> trimesh.Trimesh:
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=max_edge, max_iter=12)
    return trimesh.Trimesh(v, f, process=True)


def _pyramid_mesh(base, height):
    a, h = base / 2.0, height / 2.0
    v = np.array([[-a, -a, -h], [a, -a, -h], [a, a, -h], [-a, a, -h], [0, 0, h]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return trimesh.Trimesh(v, f, process=True)


def _half_sphere_mesh(r):
    n_lat, n_lon = 12, 32
    lat = np.linspace(0.0, np.pi / 2, n_lat + 1)[1:]  # from the pole down to the equator
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    verts = [[0.0, 0.0, -r]]
    for t in lat:
        for ph in lon:
            verts.append([r * np.sin(t) * np.cos(ph), r * np.sin(t) * np.sin(ph), -r * np.cos(t)])
    verts.append([0.0, 0.0, 0.0])  # centre of the flat top
    verts = np.array(verts)
    faces = []
    for j in range(n_lon):
        faces.append([0, 1 + (j + 1) % n_lon, 1 + j])
    for i in range(n_lat - 1):
        for j in range(n_lon):
            a = 1 + i * n_lon + j
            b = 1 + i * n_lon + (j + 1) % n_lon
            c = a + n_lon
            d = b + n_lon
            faces += [[a, b, d], [a, d, c]]
    top = len(verts) - 1
    ring = 1 + (n_lat - 1) * n_lon
    for j in range(n_lon):
        faces.append([top, ring + j, ring + (j + 1) % n_lon])
    verts[:, 2] += r / 2.0
    return trimesh.Trimesh(verts, np.array(faces), process=True)


_MESH = {
    "sphere": lambda r: trimesh.creation.icosphere(subdivisions=3, radius=r),
    "box": lambda hx, hy, hz: trimesh.creation.box(extents=(2 * hx, 2 * hy, 2 * hz)),
    "cylinder": lambda r, half_h: trimesh.creation.cylinder(radius=r, height=2 * half_h, sections=32),
    "torus": lambda major, minor: trimesh.creation.torus(major, minor, major_sections=32, minor_sections=16),
    "pyramid": _pyramid_mesh,
    "half_sphere": _half_sphere_mesh,
}
