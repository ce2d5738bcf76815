"""Synthetic geometry shared by the registration tests (phantom-like dome, marker layouts)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

#: Back-plate marker layout (mm), in the plate plane z = 0, centred near the origin; pairwise
#: distances 116, 124 and 130 mm (distinct, inside the 60-150 mm range of a real back plate).
MARKERS_MM = np.array([[-60.0, -40.0, 0.0], [70.0, -30.0, 0.0], [-10.0, 65.0, 0.0]])


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def random_rigid(rng: np.random.Generator, *, max_translation_mm: float = 100.0) -> np.ndarray:
    R = Rotation.random(random_state=rng).as_matrix()
    return rigid(R, rng.uniform(-max_translation_mm, max_translation_mm, 3))


def perturbation(rng: np.random.Generator, angle_deg: float, shift_mm: float) -> np.ndarray:
    """Rotation by exactly angle_deg about a random axis and a shift of exactly shift_mm."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
    return rigid(R, shift_mm * direction)


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(R_est @ R_true.T).magnitude()))


def make_dome(
    *,
    a_mm: float = 60.0,
    b_mm: float = 40.0,
    c_mm: float = 70.0,
    bump_mm: float = 6.0,
    bump_sigma_mm: float = 6.0,
    n_u: int = 40,
    n_v: int = 96,
    n_plate: int = 12,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closed half-ellipsoid dome (120 x 80 x 70 mm) with a nipple bump, on a flat back plate.

    Returns vertices (n, 3) mm, outward-wound faces (f, 3), a back-plate mask (n,) and the
    nipple apex (3,).
    """
    u = np.linspace(0.0, np.pi / 2, n_u + 1)[1:]
    v = np.linspace(0.0, 2 * np.pi, n_v, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    x, y, z = a_mm * np.sin(U) * np.cos(V), b_mm * np.sin(U) * np.sin(V), c_mm * np.cos(U)
    z = z + bump_mm * np.exp(-(x**2 + y**2) / (2 * bump_sigma_mm**2)) * np.cos(U)
    apex = np.array([[0.0, 0.0, c_mm + bump_mm]])
    rings = np.stack([x, y, z], axis=-1)  # (n_u, n_v, 3); the last ring is the rim at z = 0
    s = np.linspace(1.0, 0.0, n_plate + 1)[1:-1]
    plate = np.stack(
        [s[:, None] * rings[-1, :, 0], s[:, None] * rings[-1, :, 1], np.zeros((s.size, n_v))],
        axis=-1,
    )
    all_rings = np.concatenate([rings, plate], axis=0)  # (n_r, n_v, 3)
    n_r = all_rings.shape[0]
    centre = np.array([[0.0, 0.0, 0.0]])
    vertices = np.concatenate([apex, all_rings.reshape(-1, 3), centre])
    idx = 1 + np.arange(n_r * n_v).reshape(n_r, n_v)
    nxt = np.roll(idx, -1, axis=1)
    faces = [np.stack([np.zeros(n_v, int), idx[0], nxt[0]], axis=1)]
    for i in range(n_r - 1):
        faces.append(np.stack([idx[i], idx[i + 1], nxt[i + 1]], axis=1))
        faces.append(np.stack([idx[i], nxt[i + 1], nxt[i]], axis=1))
    last = len(vertices) - 1
    faces.append(np.stack([idx[-1], np.full(n_v, last), nxt[-1]], axis=1))
    faces = np.concatenate(faces)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if mesh.volume < 0:
        faces = faces[:, ::-1]
    back_plate = vertices[:, 2] < 1e-9
    return vertices, faces, back_plate, apex[0]


@pytest.fixture(scope="session")
def dome():
    return make_dome()
