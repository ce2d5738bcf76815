"""Mesh convergence of the nipple displacement under lateral gravity (issue 2).

The phantom (no inclusions, fixed seed) is rebuilt and meshed at sizes h, h/sqrt 2,
h/2, so geometry and field refine together. The observed order of convergence comes
from three levels (Richardson); the locking-free Taylor-Hood element is then compared
with displacement-only P2 on a refined mesh.

Measured (c1 = 420 Pa, nu = 0.499, lateral 1 g): 23.62, 23.90, 24.05 mm on the 16, 11.3,
8 mm meshes (1.5k to 10k tets), observed order 1.6, extrapolated 24.28 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

import fem
from fem.geometry import PhantomSpec, build_phantom
from fem.meshing import mesh_phantom

SIZES_MM = (16.0, 16.0 / np.sqrt(2.0), 8.0)


def _nipple_mm(size_mm: float, formulation: str, nu: float = 0.499) -> float:
    spec = PhantomSpec(resolution_mm=size_mm, n_inclusions=0, seed=1)
    mesh = mesh_phantom(build_phantom(spec), size_mm=size_mm)
    model = fem.Model.homogeneous(mesh, fem.NeoHookean(420.0, nu=nu), density_kg_m3=1000.0)
    sol = fem.solve(model, gravity=[1.0, 0.0, 0.0], formulation=formulation)
    assert sol.converged
    return float(np.linalg.norm(sol.displacement_mm[mesh.node_set("nipple")[0]]))


@pytest.fixture(scope="module")
def taylor_hood():
    return [_nipple_mm(h, "taylor-hood") for h in SIZES_MM]


@pytest.mark.slow
def test_observed_order_of_convergence(taylor_hood):
    f1, f2, f3 = taylor_hood
    # monotone approach: successive changes shrink
    assert abs(f3 - f2) < abs(f2 - f1)
    p = np.log(abs(f2 - f1) / abs(f3 - f2)) / np.log(np.sqrt(2.0))
    # Expected order: at most 2, from the straight-sided (piecewise linear) geometry, which
    # the quadratic field cannot beat; the singular stress where the free surface meets the
    # clamped rim lowers point values towards ~1.2 (measured here 1.6; the calibration's
    # three-mesh checks of the quick twins observed 1.15 and 1.70,
    # docs/calibration-evidence.md). The bracket is that range with 0.1 below and 0.2
    # above for three unstructured meshes' scatter (review CC-07: the former [1, 4] let
    # through orders no argument gives). It pins these three coarse meshes' behaviour:
    # finer meshes of the default phantom are in no asymptotic range (README, Benchmarks:
    # orders 0.02-0.30 on 9, 7 and 5.5 mm), so this is no claim about the limit.
    assert 1.1 <= p <= 2.2, p
    f_inf = f3 + (f3 - f2) / (np.sqrt(2.0) ** p - 1.0)
    # the finest mesh's Richardson error estimate (f3 - f2) / (sqrt 2^p - 1), relative:
    # measured 0.95 % (24.05 against 24.28 mm); the bar twice that
    assert abs(f3 / f_inf - 1.0) < 0.02


@pytest.mark.slow
def test_taylor_hood_agrees_with_p2_on_a_refined_mesh():
    # Displacement-only P2 is a valid reference only away from incompressibility: at
    # nu = 0.499 it locks (measured: 23.51 mm against Taylor-Hood's 24.05 mm on the 8 mm
    # mesh, -2.3 %). At nu = 0.45 neither locks, and Taylor-Hood on the middle mesh must
    # agree with P2 on the finest mesh to 1 % (issue 2; their difference on the same
    # 11.3 mm mesh was 0.67 %).
    th = _nipple_mm(SIZES_MM[1], "taylor-hood", nu=0.45)
    p2 = _nipple_mm(SIZES_MM[2], "p2", nu=0.45)
    assert abs(th / p2 - 1.0) < 0.01, (th, p2)
