"""A CIRS-073-like breast phantom in its stress-free state (phantom frame, mm).

The back plate is the plane z = 0 and the breast lies at z > 0. The outer surface is
an irregular, asymmetric half-ellipsoid with a nipple; 19 near-spherical inclusions
sit inside, one of them tracked; three fiducial markers lie on the back plate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay

__all__ = ["Phantom", "PhantomSpec", "build_phantom", "sphere_surface"]


@dataclass(frozen=True)
class PhantomSpec:
    """Parameters of the phantom; every random choice comes from ``seed``.

    Attributes
    ----------
    semi_axes_mm : tuple of float
        Half-widths of the base ellipse (x, y) and the depth (z), mm.
    irregularity : float
        Relative amplitude of the smooth random shape perturbation.
    nipple_height_mm, nipple_radius_mm : float
        Height and base radius of the nipple bump.
    n_inclusions : int
    inclusion_diameter_range_mm : tuple of float
    skin_thickness_mm : float
        Thickness of the optional skin layer (0 for none).
    resolution_mm : float
        Target edge length of the surface triangulation.
    seed : int
    """

    semi_axes_mm: tuple[float, float, float] = (60.0, 40.0, 70.0)
    irregularity: float = 0.06
    nipple_height_mm: float = 5.0
    nipple_radius_mm: float = 6.0
    n_inclusions: int = 19
    inclusion_diameter_range_mm: tuple[float, float] = (3.0, 10.0)
    skin_thickness_mm: float = 0.0
    resolution_mm: float = 4.0
    seed: int = 0


@dataclass(frozen=True)
class Phantom:
    """The stress-free phantom.

    Attributes
    ----------
    vertices_mm : ndarray, shape (n, 3)
        Closed outer surface (dome and flat base), outward-oriented triangles.
    faces : ndarray, shape (m, 3)
    back_vertex : ndarray of bool, shape (n,)
        Vertices on the back plate (z = 0).
    inclusion_centres_mm : ndarray, shape (k, 3)
    inclusion_diameters_mm : ndarray, shape (k,)
    tracked_inclusion : int
        Index of the tracked tumour among the inclusions.
    fiducials_mm : ndarray, shape (3, 3)
        Marker centres on the back plate.
    nipple_mm : ndarray, shape (3,)
        The surface point farthest from the back plate.
    spec : PhantomSpec
    """

    vertices_mm: np.ndarray
    faces: np.ndarray
    back_vertex: np.ndarray
    inclusion_centres_mm: np.ndarray
    inclusion_diameters_mm: np.ndarray
    tracked_inclusion: int
    fiducials_mm: np.ndarray
    nipple_mm: np.ndarray
    spec: PhantomSpec = field(default_factory=PhantomSpec)

    @property
    def tumour_mm(self) -> np.ndarray:
        """Centre of the tracked inclusion, shape (3,)."""
        return self.inclusion_centres_mm[self.tracked_inclusion]


def _shape_field(spec: PhantomSpec):
    """Smooth random radial factor f(theta, phi) and the nipple direction."""
    rng = np.random.default_rng(spec.seed)
    coef = rng.normal(scale=spec.irregularity / 2.5, size=(3, 3, 2))
    tilt = rng.uniform(0.10, 0.22)  # apex leans sideways: an asymmetric, sagging shape
    phi_tilt = rng.uniform(0, 2 * np.pi)

    def factor(theta, phi):
        f = np.ones_like(theta)
        for m in range(3):
            for n in range(1, 4):
                a, b = coef[m, n - 1]
                ang = (m + 1) * phi
                f += (a * np.cos(ang) + b * np.sin(ang)) * np.sin(n * theta) ** 2
        return f

    return factor, tilt, phi_tilt


def _dome_point(spec: PhantomSpec, theta, phi, factor, tilt, phi_tilt):
    a, b, h = spec.semi_axes_mm
    f = factor(theta, phi)
    s, c = np.sin(theta), np.cos(theta)
    x = a * s * np.cos(phi) * f + tilt * a * c**2 * np.cos(phi_tilt)
    y = b * s * np.sin(phi) * f + tilt * b * c**2 * np.sin(phi_tilt)
    z = h * c * f
    return np.stack([x, y, z], axis=-1)


def _nipple(points, spec: PhantomSpec, apex):
    """Add a smooth nipple bump around the apex along the local outward direction."""
    r = np.linalg.norm(points[:, :2] - apex[:2], axis=1)
    bump = spec.nipple_height_mm * np.exp(-0.5 * (r / (0.5 * spec.nipple_radius_mm)) ** 2)
    out = points.copy()
    out[:, 2] += bump * (points[:, 2] > 0)
    return out


def _disk_points(radii: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concentric rings in the unit disk: ``counts[k]`` points at radius ``radii[k]``."""
    pts = [np.zeros((1, 2))]
    for k, (r, m) in enumerate(zip(radii, counts, strict=True)):
        ang = 2 * np.pi * (np.arange(m) + 0.5 * (k % 2)) / m
        pts.append(r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    return np.vstack(pts)


def _rings(spec: PhantomSpec, quarter_mm: float, rim_n: int):
    """Ring radii (unit disk) and point counts: uniform, plus finer rings at the nipple."""
    n = max(4, int(np.ceil(quarter_mm / spec.resolution_mm)))
    radii = list(np.arange(1, n + 1) / n)
    counts = [max(6, int(round(rim_n * np.sin(r * np.pi / 2)))) for r in radii]
    fine = min(spec.resolution_mm, spec.nipple_radius_mm / 2.5)
    arcs = np.arange(fine, 1.5 * spec.nipple_radius_mm, fine)
    arcs = arcs[arcs < 0.75 * quarter_mm / n]
    radii = list(arcs / quarter_mm) + radii
    counts = [max(6, int(round(2 * np.pi * a / fine))) for a in arcs] + counts
    return np.array(radii), np.array(counts)


def _dome_and_base(spec: PhantomSpec):
    """Dome and flat base on one unit-disk triangulation, sharing the rim vertices.

    The dome maps disk radius rho to the polar angle rho pi/2; the base maps the same
    disk onto the rim polygon radially (the rim is star-shaped about the z axis), so
    both triangulations are valid for any irregularity.
    """
    a, b, h = spec.semi_axes_mm
    factor, tilt, phi_tilt = _shape_field(spec)
    quarter = np.pi / 2 * np.hypot(np.hypot(a, b) / np.sqrt(2), h)
    rim_n = int(np.ceil(2 * np.pi * np.hypot(a, b) / np.sqrt(2) / spec.resolution_mm))
    uv = _disk_points(*_rings(spec, quarter, rim_n))
    rho, phi = np.linalg.norm(uv, axis=1), np.arctan2(uv[:, 1], uv[:, 0])
    dome = _dome_point(spec, rho * np.pi / 2, phi, factor, tilt, phi_tilt)
    on_rim = np.isclose(rho, 1.0)
    dome[on_rim, 2] = 0.0
    rim_xy = _dome_point(spec, np.full_like(phi, np.pi / 2), phi, factor, tilt, phi_tilt)[:, :2]
    base = np.column_stack([rho[:, None] * rim_xy, np.zeros(len(rho))])
    return dome, base, Delaunay(uv).simplices, on_rim


def _closed_surface(spec: PhantomSpec):
    dome, base, tri, on_rim = _dome_and_base(spec)
    apex = dome[np.argmax(dome[:, 2])]
    dome = _nipple(dome, spec, apex)
    inner = np.flatnonzero(~on_rim)
    base_index = np.arange(len(dome))  # rim vertices are shared with the dome
    base_index[inner] = len(dome) + np.arange(len(inner))
    verts = np.vstack([dome, base[inner]])
    faces = np.vstack([tri, base_index[tri][:, ::-1]])
    return _orient_outward(verts, faces)


def _orient_outward(verts, faces):
    """Consistent outward winding (trimesh's normal repair)."""
    import trimesh

    m = trimesh.Trimesh(verts, faces, process=False)
    trimesh.repair.fix_normals(m)
    if not m.is_watertight:
        raise RuntimeError("internal error: the phantom surface is not watertight")
    return np.asarray(m.vertices), np.asarray(m.faces)


def sphere_surface(centre_mm, radius_mm: float, *, subdivisions: int = 2):
    """Triangulated sphere (icosphere), outward oriented: ``(vertices (n, 3), faces (m, 3))``."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_mm)
    return np.asarray(s.vertices) + np.asarray(centre_mm), np.asarray(s.faces)


def _signed_distance(verts, faces, points):
    """Signed distance to the closed surface, positive inside (mm)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(verts, np.float32)),
        o3d.core.Tensor(np.asarray(faces, np.uint32)),
    )
    query = o3d.core.Tensor(np.asarray(points, np.float32))
    return -scene.compute_signed_distance(query).numpy().astype(float)


def _place_inclusions(spec: PhantomSpec, verts, faces, rng):
    lo, hi = spec.inclusion_diameter_range_mm
    diam = np.sort(rng.uniform(lo, hi, spec.n_inclusions))[::-1]
    centres: list[np.ndarray] = []
    box_lo, box_hi = verts.min(axis=0), verts.max(axis=0)
    margin = 3.0 + spec.skin_thickness_mm
    for d in diam:
        for _ in range(200):
            cand = rng.uniform(box_lo, box_hi, size=(64, 3))
            sd = _signed_distance(verts, faces, cand)
            ok = (sd > d / 2 + margin) & (cand[:, 2] > d / 2 + margin)
            for c, dc in zip(centres, diam, strict=False):
                ok &= np.linalg.norm(cand - c, axis=1) > (d + dc) / 2 + 2.0
            if ok.any():
                centres.append(cand[np.flatnonzero(ok)[0]])
                break
        else:
            raise ValueError(f"could not place {spec.n_inclusions} inclusions in the phantom")
    return np.array(centres).reshape(-1, 3), diam


def _fiducials(spec: PhantomSpec, rng) -> np.ndarray:
    """Three markers on the back plate outside the footprint, distinct pair distances."""
    a, b, _ = spec.semi_axes_mm
    while True:
        ang = np.sort(rng.uniform(0, 2 * np.pi, 3))
        ang[1:] = ang[0] + np.cumsum(rng.uniform(1.6, 2.6, 2))
        rad = rng.uniform(1.2, 1.4, 3)
        pts = np.column_stack([a * rad * np.cos(ang), b * rad * np.sin(ang), np.zeros(3)])
        d = np.sort([np.linalg.norm(pts[i] - pts[j]) for i, j in ((0, 1), (0, 2), (1, 2))])
        if np.diff(d).min() > 8.0:
            return pts


def build_phantom(spec: PhantomSpec | None = None) -> Phantom:
    """Build the stress-free phantom from its specification (deterministic in ``seed``).

    Parameters
    ----------
    spec : PhantomSpec, optional
        Defaults to the CIRS-073-like default.

    Returns
    -------
    Phantom
    """
    spec = spec or PhantomSpec()
    verts, faces = _closed_surface(spec)
    rng = np.random.default_rng([spec.seed, 1])
    centres, diam = (
        _place_inclusions(spec, verts, faces, rng)
        if spec.n_inclusions
        else (
            np.zeros((0, 3)),
            np.zeros(0),
        )
    )
    tracked = int(np.argmin(np.abs(diam - 8.0))) if len(diam) else -1
    return Phantom(
        vertices_mm=verts,
        faces=faces,
        back_vertex=np.abs(verts[:, 2]) < 1e-9,
        inclusion_centres_mm=centres,
        inclusion_diameters_mm=diam,
        tracked_inclusion=tracked,
        fiducials_mm=_fiducials(spec, rng),
        nipple_mm=verts[np.argmax(verts[:, 2])],
        spec=spec,
    )
