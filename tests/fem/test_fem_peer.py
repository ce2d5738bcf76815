"""Peer verification problems from the FEBio test suite (te01, mi04).

Setups and gold values from ../shared/data/README.md ("Peer reference values"):
FEBio verification suite (febiosoftware/TestSuite), problems te01 and mi04. The
figures are copied here so that the tests do not need that folder.
"""

from __future__ import annotations

import numpy as np
import pytest
from femtest_meshes import box_mesh
from scipy.optimize import brentq

from fem import (
    Constrained,
    FebioNeoHookean,
    Model,
    MooneyRivlin,
    SolverOptions,
    TetMesh,
    Volumetric,
    solve,
)

# FEBio te01 gold: free displacements (u2x, u3y, u4z) and the solution norm.
TE01_GOLD = np.array([0.214464, 0.214464, -0.322457])
TE01_GOLD_NORM = 0.44268188785
# FEBio mi04 gold: lateral stretch and the norm sqrt(8) (1 - t) of the free displacements.
MI04_T = 0.72593501
MI04_GOLD_NORM = 0.775172839024
# The issue asks for rtol 1e-5; the gold values are given to 6 significant digits.
PEER_RTOL = 1e-5
M_PER_MM = 1e-3  # the meshes are in mm, FEBio's unit problems in m


def _symmetry(*sets):
    return tuple(Constrained(name, (axis,)) for name, axis in sets)


def test_febio_te01_single_tet_uncoupled_mooney_rivlin():
    nodes_mm = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 1e3  # unit tet, 1 m
    sets = {"sx": [0, 2, 3], "sy": [0, 1, 3], "sz": [0, 1, 2]}  # nodes on x=0, y=0, z=0
    mesh = TetMesh(nodes_mm, [[0, 1, 2, 3]], [1], {"bulk": 1}, sets)
    material = MooneyRivlin(1.0, 0.0, Volumetric(1000.0, "log"))
    model = Model(
        mesh, {"bulk": material}, {"bulk": 1.0}, _symmetry(("sx", 0), ("sy", 1), ("sz", 2))
    )
    sol = solve(model, point_forces_n={3: [0.0, 0.0, -0.5]}, formulation="p1")
    u_m = sol.displacement_mm * M_PER_MM
    free = np.array([u_m[1, 0], u_m[2, 1], u_m[3, 2]])
    assert sol.converged
    np.testing.assert_allclose(free, TE01_GOLD, rtol=PEER_RTOL)
    np.testing.assert_allclose(np.linalg.norm(free), TE01_GOLD_NORM, rtol=PEER_RTOL)
    # the symmetry supports: every other component is exactly zero
    mask = np.ones((4, 3), dtype=bool)
    mask[[1, 2, 3], [0, 1, 2]] = False
    assert np.all(u_m[mask] == 0.0)


def test_mi04_lateral_stretch_closed_form():
    """The gold t solves mu (t^2 - 1) + lambda ln(2 t^2) = 0 (README); check our reading."""
    E, nu = 1.0, 0.45
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    t = brentq(lambda t: mu * (t**2 - 1) + lam * np.log(2 * t**2), 0.1, 1.0, xtol=1e-15)
    # the gold value is printed to 8 decimals: agreement to half a unit in the last one
    assert abs(t - MI04_T) < 5e-9
    # FEBio's gold norm is its own Newton-converged value, 3e-8 relative from the exact
    # root's; 1e-7 still tells the two readings of the problem apart
    assert np.sqrt(8) * (1 - t) == pytest.approx(MI04_GOLD_NORM, rel=1e-7)


@pytest.mark.parametrize("formulation", ["p1", "p2", "taylor-hood", "mini"])
@pytest.mark.parametrize("n", [2, 3], ids=["6tets", "48tets"])
def test_febio_mi04_uniaxial_stretch_coupled_neo_hookean(formulation, n):
    mesh = box_mesh((1e3, 1e3, 1e3), (n, n, n))  # unit cube of 1 m, tensor tet split
    sup = _symmetry(("x0", 0), ("y0", 1), ("z0", 2), ("x1", 0))
    model = Model(mesh, {"bulk": FebioNeoHookean(1.0, 0.45)}, {"bulk": 1.0}, sup)
    sol = solve(
        model,
        prescribed={("x1", 0): 1e3},  # stretch 2
        formulation=formulation,
        options=SolverOptions(rtol=1e-11),
    )
    u_m = sol.displacement_mm * M_PER_MM
    x_m = mesh.nodes_mm * M_PER_MM
    # homogeneous state: lateral displacement (t - 1) y and (t - 1) z at every node
    t_y = 1 + u_m[mesh.node_sets["y1"], 1]
    t_z = 1 + u_m[mesh.node_sets["z1"], 2]
    np.testing.assert_allclose(t_y, MI04_T, rtol=PEER_RTOL)
    np.testing.assert_allclose(t_z, MI04_T, rtol=PEER_RTOL)
    # and exactly homogeneous everywhere inside: to Newton's tolerance (rtol 1e-11) and the
    # gold value's rounding (8 decimals: 5e-9 of the 1 m cube); review CC-13: 1e-6 m was
    # 200 times that
    expected = x_m * (np.array([2.0, MI04_T, MI04_T]) - 1)
    np.testing.assert_allclose(u_m, expected, atol=1e-8)
    if n == 2:  # the 8 corner nodes of FEBio's hex8: the gold norm of the free displacements
        free = np.concatenate([u_m[mesh.node_sets["y1"], 1], u_m[mesh.node_sets["z1"], 2]])
        np.testing.assert_allclose(np.linalg.norm(free), MI04_GOLD_NORM, rtol=PEER_RTOL)
