"""Synthetic scans with known truth shared by the imaging tests (helpers)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from imaging import render_mr_volume, scan_grid_covering
from imaging.testing import make_test_phantom


@dataclass
class PosedScan:
    volume: object
    phantom: object
    T: np.ndarray  # T_scanner_from_phantom

    def to_scanner(self, p):
        return np.asarray(p, float) @ self.T[:3, :3].T + self.T[:3, 3]


def make_scan(
    *,
    spacing=(1.0, 1.0, 1.3),
    angles=(15.0, -20.0, 30.0),
    iop_angles=(10.0, 5.0, -8.0),
    bias=0.2,
    snr=25.0,
    seed=1,
    min_shape=(0, 0, 0),
    semi_axes=(45.0, 35.0, 30.0),
    n_inclusions=5,
    skin=0.0,
    fiducials_mm=None,
    intensities=None,
) -> PosedScan:
    """A posed, rendered test phantom; ``fiducials_mm`` (phantom frame) replaces its markers."""
    ph = make_test_phantom(semi_axes_mm=semi_axes, n_inclusions=n_inclusions, seed=seed)
    if fiducials_mm is not None:
        from dataclasses import replace

        ph = replace(ph, fiducial_centres_mm=np.asarray(fiducials_mm, float))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    T[:3, 3] = [10.0, -20.0, 30.0]
    scan = PosedScan(None, ph, T)
    pts = scan.to_scanner(np.r_[ph.body[0], ph.fiducial_centres_mm])
    D = Rotation.from_euler("zyx", iop_angles, degrees=True).as_matrix()
    grid = scan_grid_covering(pts, spacing_mm=spacing, direction=D, min_shape=min_shape)
    scan.volume = render_mr_volume(
        ph.body,
        T_scanner_from_phantom=T,
        grid=grid,
        inclusions=ph.inclusions,
        fiducial_centres_mm=ph.fiducial_centres_mm,
        fiducial_radius_mm=ph.fiducial_radius_mm,
        bias_amplitude=bias,
        snr=snr,
        seed=seed,
        skin_thickness_mm=skin,
        intensities=intensities,
    )
    return scan


def true_surface_distance(scan: PosedScan, points_lps_mm: np.ndarray) -> np.ndarray:
    """Unsigned distances (mm) of points to the true posed body surface."""
    import open3d as o3d

    v, f = scan.phantom.body
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(scan.to_scanner(v).astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(f.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    q = o3d.core.Tensor(np.asarray(points_lps_mm, np.float32))
    return scene.compute_distance(q).numpy()
