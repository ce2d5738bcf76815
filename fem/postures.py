"""Posture angles, gravity directions and scanner poses of the phantom experiment.

A posture angle ``theta`` (degrees) names the gravity direction in the phantom frame
``(cos theta, 0, sin theta)``: 0 deg is left lateral (gravity along +x), 180 deg right
lateral, and 25 or 50 deg tilt the phantom from left lateral towards prone (+z, the
breast hanging from the back plate). The plane of these angles is the phantom's x-z
plane, called "transverse" in ``session.toml``.

The sagittal plane is the phantom's y-z plane (``y = z x x``): a sagittal angle ``a``
names ``(0, cos a, sin a)``, so both planes meet at 90 deg (+z, prone) and 270 deg
(-z, supine). :func:`fibonacci_sphere` gives quasi-uniform directions over the whole
sphere for gravity sweeps (Gonzalez 2010, "Measurement of areas on a sphere using
Fibonacci and latitude-longitude lattices", Math. Geosci. 42:49-64).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

__all__ = [
    "PLANES",
    "fibonacci_sphere",
    "gravity_for_angle",
    "random_scanner_pose",
    "rotation_between",
]

#: Posture planes of :func:`gravity_for_angle`: the phantom-frame axes spanning each.
PLANES = {"transverse": (0, 2), "sagittal": (1, 2)}


def gravity_for_angle(
    angle_deg: float, *, plane: Literal["transverse", "sagittal"] = "transverse"
) -> np.ndarray:
    """Unit gravity vector in the phantom frame for a posture angle (see module doc).

    Parameters
    ----------
    angle_deg : float
        Posture angle in degrees.
    plane : {"transverse", "sagittal"}
        ``(cos a, 0, sin a)`` in the transverse (x-z) plane, ``(0, cos a, sin a)`` in the
        sagittal (y-z) plane.

    Returns
    -------
    ndarray, shape (3,)
    """
    if plane not in PLANES:
        raise ValueError(f"unknown posture plane {plane!r}; choose {sorted(PLANES)}")
    t = np.radians(angle_deg)
    g = np.zeros(3)
    i, k = PLANES[plane]
    g[i], g[k] = np.cos(t), np.sin(t)
    return g


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` quasi-uniform unit vectors on the sphere (a Fibonacci lattice), (n, 3).

    Point ``i`` has ``z = 1 - (2 i + 1) / n`` (equal-area bands) and longitude
    ``i`` times the golden angle ``pi (3 - sqrt 5)``; deterministic, no seed needed.

    Parameters
    ----------
    n : int
        Number of directions, >= 1.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    if n < 1:
        raise ValueError(f"a Fibonacci sphere needs at least one point, got {n}")
    i = np.arange(n, dtype=float)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return _axis_angle(perp, np.pi)
    return _axis_angle(v, np.arctan2(np.linalg.norm(v), c))


def random_scanner_pose(
    angle_deg: float,
    gravity_scanner: np.ndarray,
    rng: np.random.Generator,
    *,
    roll_deg: float = 5.0,
    tilt_deg: float = 1.0,
    shift_mm: float = 30.0,
    centre_mm: np.ndarray | None = None,
) -> np.ndarray:
    """A realistic ``T_scanner_from_phantom`` for a posture.

    The nominal posture brings the phantom's gravity direction onto the scanner's;
    straps and a head coil add a roll about gravity (up to ``roll_deg``), a small tilt
    (up to ``tilt_deg``, which changes the true gravity in the phantom frame) and a
    shift of up to ``shift_mm`` of ``centre_mm`` from the scanner's isocentre.
    """
    g_s = np.asarray(gravity_scanner, float) / np.linalg.norm(gravity_scanner)
    R = rotation_between(gravity_for_angle(angle_deg), g_s)
    R = _axis_angle(g_s, np.radians(rng.uniform(-roll_deg, roll_deg))) @ R
    tilt_axis = np.cross(g_s, rng.normal(size=3))
    R = _axis_angle(tilt_axis, np.radians(rng.uniform(-tilt_deg, tilt_deg))) @ R
    centre = np.zeros(3) if centre_mm is None else np.asarray(centre_mm, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre + rng.uniform(-shift_mm, shift_mm, 3)
    return T
