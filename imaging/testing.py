"""Small built-in phantom geometry for tests and benchmarks (not the real phantom).

A half-ellipsoid dome on the back plate (plane z = 0, breast at z > 0) with spherical
inclusions and spherical fiducial markers beside the dome's footprint, all in the phantom
frame (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "TestPhantom",
    "dome_in_thick_slices",
    "dome_surface",
    "make_test_phantom",
    "sphere_surface",
]


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


def dome_in_thick_slices(
    semi_axes_mm: tuple[float, float, float] = (60.0, 40.0, 70.0),
    *,
    slice_mm: int = 5,
    tilt_deg: float = 4.0,
    noise: float = 0.02,
    seed: int = 0,
):
    """A half-ellipsoid on a plate tilted ``tilt_deg`` about x, scanned in thick slices.

    Voxelised on a 1 mm grid, averaged over ``slice_mm`` along z (partial volume) and
    smoothed; its surface (:func:`imaging.surface.extract_surface`) has a terraced back
    face. Seeded Gaussian noise of ``noise`` (body = 1).

    Returns
    -------
    vertices : (n, 3) ndarray
        Surface vertices, mm (the plate through the origin).
    faces : (m, 3) ndarray
    affine_lps_from_index : (4, 4) ndarray
        The volume's.
    plate_normal : (3,) ndarray
        The plate's true normal, into the body.
    fiducials_mm : (3, 3) ndarray
        Three points on the plate beside the footprint (the markers' centres).
    """
    from scipy import ndimage

    from imaging.surface import extract_surface
    from imaging.volume import Volume, affine_from_geometry

    a, b, c = semi_axes_mm
    pad, k, t = 12.0, int(slice_mm), np.radians(tilt_deg)
    xs, ys = np.arange(-a - pad, a + pad), np.arange(-b - pad - 10, b + pad + 10)
    zs = np.arange(-pad - 10, c + pad)
    zs = zs[: (len(zs) // k) * k]
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    Yr, Zr = np.cos(t) * Y + np.sin(t) * Z, -np.sin(t) * Y + np.cos(t) * Z
    inside = ((X / a) ** 2 + (Yr / b) ** 2 + (Zr / c) ** 2 <= 1) & (Zr >= 0)
    img = inside.astype(np.float32).reshape(len(xs), len(ys), -1, k).mean(-1)
    img += np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)
    smooth = ndimage.gaussian_filter(img, (0.5, 0.5, 0.5 / k))
    origin = np.array([xs[0], ys[0], zs[0] + (k - 1) / 2])
    A = affine_from_geometry(origin, np.array([1.0, 1.0, float(k)]), np.eye(3))
    s = extract_surface(Volume(smooth, A), mask=Volume(ndimage.binary_opening(smooth > 0.5), A))
    R = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    fid = np.array([[a + 8, 0, -2.5], [-a - 5, 10, -2.5], [0, -b - 8, -2.5]]) @ R.T
    return s.vertices_lps_mm, s.faces, A, R @ np.array([0.0, 0.0, 1.0]), fid
