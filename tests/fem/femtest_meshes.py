"""Small synthetic meshes for the fem tests (no test functions here)."""

from __future__ import annotations

import numpy as np

from fem import TetMesh


def box_mesh(size_mm=(1.0, 1.0, 1.0), n=(2, 2, 2), *, jitter=0.0, seed=0) -> TetMesh:
    """Tet mesh of the box [0, a] x [0, b] x [0, c] (mm) from scikit-fem's tensor split.

    ``n`` is the number of points per axis. ``jitter`` (fraction of the grid spacing)
    moves every node randomly but keeps the box: a node on a face keeps its normal
    coordinate, so the mesh is irregular yet fills the same box. Node sets ``x0``,
    ``x1``, ``y0``, ``y1``, ``z0``, ``z1`` hold the nodes of each face.
    """
    from skfem import MeshTet

    axes = [np.linspace(0.0, s, k) for s, k in zip(size_mm, n, strict=True)]
    m = MeshTet.init_tensor(*axes)
    p = m.p.T.copy()
    size = np.asarray(size_mm, dtype=float)
    on_lo, on_hi = np.isclose(p, 0.0), np.isclose(p, size)
    if jitter:
        h = size / (np.asarray(n) - 1)
        rng = np.random.default_rng(seed)
        move = rng.uniform(-jitter, jitter, p.shape) * h
        move[on_lo | on_hi] = 0.0
        p += move
    sets = {}
    for i, ax in enumerate("xyz"):
        sets[f"{ax}0"] = np.flatnonzero(on_lo[:, i])
        sets[f"{ax}1"] = np.flatnonzero(on_hi[:, i])
    mesh = TetMesh(p, m.t.T, np.ones(m.t.shape[1], dtype=int), {"bulk": 1}, sets)
    return mesh.oriented()
