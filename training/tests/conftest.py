"""Shared fixtures: small GRAB-format datasets written by the tests themselves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comgrasp_train.grab.format import write_grab_npz
from comgrasp_train.objects.catalogue import write_object_meshes
from comgrasp_train.representation import object_centre_local


def random_sequence_arrays(rng: np.random.Generator, T: int, n_obj_vertices: int) -> dict:
    """Plausible random GRAB arrays: smooth random joint rotations, a drifting object."""
    t = np.linspace(0, 1, T)[:, None]
    fullpose = (rng.normal(0, 0.3, (1, 165)) + rng.normal(0, 0.3, (1, 165)) * np.sin(2 * np.pi * t)).astype(np.float32)
    transl = (np.array([0.1, -0.2, 0.9]) + 0.05 * t * rng.normal(size=(1, 3))).astype(np.float32)
    obj_t = (np.array([0.0, 0.5, 0.8]) + 0.1 * t * rng.normal(size=(1, 3))).astype(np.float32)
    obj_aa = (rng.normal(0, 1, (1, 3)) * t).astype(np.float32)
    contact = np.zeros((T, n_obj_vertices), np.int8)
    contact[T // 4: T // 2, :5] = 22  # right palm touches
    contact[T // 3: 2 * T // 3, 5:9] = 27  # left index touches
    return dict(fullpose=fullpose, transl=transl, object_transl=obj_t, object_global_orient=obj_aa,
                table_transl=np.tile([[0.0, 0.5, 0.75]], (T, 1)).astype(np.float32),
                table_global_orient=np.zeros((T, 3), np.float32),
                contact_body=np.zeros((T, 16), np.int8), contact_object=contact)


@pytest.fixture
def one_thread():
    """Tiny models: extra torch threads only add contention on a shared machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def grab_root(tmp_path_factory) -> Path:
    """A GRAB-layout root with meshes for 'mug' and 'cubesmall' and six good sequences."""
    root = tmp_path_factory.mktemp("grab")
    meshes = write_object_meshes(root, ["mug", "cubesmall"])
    rng = np.random.default_rng(0)
    import trimesh

    nv = {n: len(trimesh.load(p, process=False).vertices) for n, p in meshes.items()}
    specs = [("s1", "male", "mug", "drink"), ("s1", "male", "cubesmall", "lift"),
             ("s3", "female", "mug", "pass"), ("s9", "male", "cubesmall", "offhand"),
             ("s10", "male", "mug", "inspect"), ("s10", "male", "cubesmall", "lift")]
    for i, (sid, gender, obj, intent) in enumerate(specs):
        arrays = random_sequence_arrays(rng, 48 + 8 * i, nv[obj])
        write_grab_npz(root / "grab" / sid / f"{obj}_{intent}_{i}.npz", gender=gender, sbj_id=sid,
                       obj_name=obj, motion_intent=intent,
                       vtemp=f"tools/subject_meshes/{gender}/{sid}.ply",
                       object_mesh=f"tools/object_meshes/contact_meshes/{obj}.ply", **arrays)
    object_centre_local.cache_clear()
    return root
