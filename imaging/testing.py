"""Small built-in phantom geometry for tests and benchmarks (not the real phantom).

A half-ellipsoid dome on the back plate (plane z = 0, breast at z > 0) with spherical
inclusions and spherical fiducial markers beside the dome's footprint, all in the phantom
frame (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TestPhantom", "dome_surface", "make_test_phantom", "sphere_surface"]


def sphere_surface(
    centre_mm: np.ndarray, radius_mm: float, *, subdivisions: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere (vertices (n, 3) mm, faces (m, 3)) of a sphere."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(ico.vertices) * radius_mm + np.asarray(centre_mm, float), np.asarray(
        ico.faces
    )


def dome_surface(
    semi_axes_mm: tuple[float, float, float] = (45.0, 35.0, 30.0), *, subdivisions: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Build a closed half-ellipsoid dome: its z >= 0 half plus the flat base at z = 0.

    Built from an icosphere whose lower half is projected onto z = 0 (a one-to-one map onto
    the base ellipse), so the surface is closed and watertight.
    """
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(ico.vertices) * np.asarray(semi_axes_mm, float)
    v[:, 2] = np.maximum(v[:, 2], 0.0)
    return v, np.asarray(ico.faces)


@dataclass(frozen=True, eq=False)
class TestPhantom:
    """Test phantom geometry in the phantom frame (mm)."""

    __test__ = False  # not a pytest class

    body: tuple[np.ndarray, np.ndarray]
    inclusions: list[tuple[np.ndarray, np.ndarray]]
    inclusion_centres_mm: np.ndarray
    inclusion_diameters_mm: np.ndarray
    fiducial_centres_mm: np.ndarray
    fiducial_radius_mm: float
    nipple_mm: np.ndarray
    semi_axes_mm: tuple[float, float, float]


def make_test_phantom(
    *,
    semi_axes_mm: tuple[float, float, float] = (45.0, 35.0, 30.0),
    n_inclusions: int = 5,
    diameter_range_mm: tuple[float, float] = (4.0, 10.0),
    fiducial_radius_mm: float = 2.5,
    seed: int = 0,
) -> TestPhantom:
    """Dome phantom with non-overlapping spherical inclusions and three markers.

    Inclusions are placed at random (seeded) at least 3 mm inside the dome and 3 mm apart;
    the markers sit on the back plate (centres at z = -radius, just behind the plate)
    outside the dome's footprint, in a scalene triangle.
    """
    rng = np.random.default_rng(seed)
    a = np.asarray(semi_axes_mm, float)
    centres: list[np.ndarray] = []
    diameters: list[float] = []
    for _ in range(10000):
        if len(centres) == n_inclusions:
            break
        d = float(rng.uniform(*diameter_range_mm))
        c = rng.uniform(-1, 1, 3) * a
        c[2] = abs(c[2])
        r = d / 2.0 + 3.0
        if c[2] < r or np.sum((c / (a - r)) ** 2) > 1.0:
            continue
        if any(
            np.linalg.norm(c - q) < r + e / 2.0 for q, e in zip(centres, diameters, strict=True)
        ):
            continue
        centres.append(c)
        diameters.append(d)
    if len(centres) < n_inclusions:
        raise ValueError(f"could not place {n_inclusions} inclusions in the dome")
    r_m = float(fiducial_radius_mm)
    angles = np.radians([100.0, 215.0, 330.0])
    fid = np.stack(
        [np.cos(angles) * (a[0] + 8.0), np.sin(angles) * (a[1] + 8.0), -r_m * np.ones(3)], 1
    )
    return TestPhantom(
        body=dome_surface(semi_axes_mm),
        inclusions=[sphere_surface(c, d / 2.0) for c, d in zip(centres, diameters, strict=True)],
        inclusion_centres_mm=np.array(centres).reshape(-1, 3),
        inclusion_diameters_mm=np.array(diameters),
        fiducial_centres_mm=fid,
        fiducial_radius_mm=r_m,
        nipple_mm=np.array([0.0, 0.0, a[2]]),
        semi_axes_mm=tuple(a),
    )
