"""Homogeneous uniaxial stretch: nominal stress vs stretch in closed form.

For F = diag(s, t, t) the uncoupled Mooney-Rivlin energy with U = kappa/2 (J - 1)^2 is
w(s, t) = c1 (J^-2/3 a - 3) + c2 (J^-4/3 b - 3) + kappa/2 (J - 1)^2 with J = s t^2,
a = s^2 + 2 t^2, b = 2 s^2 t^2 + t^4. The nominal stress is P11 = dw/ds and free lateral
faces need dw/dt = 2 P22 = 0. Derivatives written out by hand below, independent of
fem.kinematics. The state is homogeneous, so any tet mesh (here an irregular one)
must reproduce it to round-off: reaction force = P11 x reference area.
"""

from __future__ import annotations

import numpy as np
import pytest
from femtest_meshes import box_mesh
from scipy.optimize import brentq

from fem import Constrained, Model, MooneyRivlin, NeoHookean, SolverOptions, discretize, solve
from fem.assemble import assemble, scatter

M_PER_MM = 1e-3


def _dw(s, t, c1, c2, kappa):
    """(dw/ds, dw/dt) of the uniaxial energy (module docstring)."""
    J, a, b = s * t**2, s**2 + 2 * t**2, 2 * s**2 * t**2 + t**4
    dJ_dl, dJ_dt = t**2, 2 * s * t
    w_l = (
        c1 * (-2 / 3 * J ** (-5 / 3) * dJ_dl * a + J ** (-2 / 3) * 2 * s)
        + c2 * (-4 / 3 * J ** (-7 / 3) * dJ_dl * b + J ** (-4 / 3) * 4 * s * t**2)
        + kappa * (J - 1) * dJ_dl
    )
    w_t = (
        c1 * (-2 / 3 * J ** (-5 / 3) * dJ_dt * a + J ** (-2 / 3) * 4 * t)
        + c2 * (-4 / 3 * J ** (-7 / 3) * dJ_dt * b + J ** (-4 / 3) * (4 * s**2 * t + 4 * t**3))
        + kappa * (J - 1) * dJ_dt
    )
    return w_l, w_t


def uniaxial_closed_form(s, c1, c2, kappa):
    """Lateral stretch t and nominal stress P11 (Pa) at axial stretch s."""
    t = brentq(lambda t: _dw(s, t, c1, c2, kappa)[1], 0.2, 2.0, xtol=1e-15, rtol=1e-15)
    return t, _dw(s, t, c1, c2, kappa)[0]


MATERIALS = {
    "neo-hookean": NeoHookean(400.0, nu=0.45),
    "mooney-rivlin": MooneyRivlin.from_poisson(300.0, 150.0, 0.45),
}


@pytest.mark.parametrize("stretch", [1.3, 0.8], ids=["tension", "compression"])
@pytest.mark.parametrize("formulation", ["p1", "taylor-hood"])
@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_uniaxial_stretch_matches_closed_form(name, formulation, stretch):
    material = MATERIALS[name]
    size_mm = np.array([30.0, 20.0, 10.0])
    mesh = box_mesh(size_mm, (4, 3, 3), jitter=0.3, seed=1)  # irregular tets, same box
    sup = tuple(Constrained(s, (i,)) for s, i in (("x0", 0), ("y0", 1), ("z0", 2), ("x1", 0)))
    model = Model.homogeneous(mesh, material, support=sup)
    disc = discretize(mesh, sup, formulation=formulation)
    sol = solve(
        model,
        prescribed={("x1", 0): (stretch - 1) * size_mm[0]},
        disc=disc,
        options=SolverOptions(rtol=1e-12),
    )
    t, P11 = uniaxial_closed_form(
        stretch, material.c1_pa, material.c2_pa, material.volumetric.kappa_pa
    )
    # Newton stops at a relative residual 1e-12; the state is exact up to that and
    # round-off (condition ~ kappa/mu ~ 10): 1e-9 relative leaves a wide margin.
    expected = mesh.nodes_mm * (np.array([stretch, t, t]) - 1)
    np.testing.assert_allclose(sol.displacement_mm, expected, rtol=0, atol=1e-9 * size_mm.max())
    # reaction on the stretched face: sum of the internal forces of its dofs
    r = scatter(disc, assemble(disc, model, sol.state, tangent=False).vectors)
    on_face = np.isclose(disc.basis().doflocs[0], size_mm[0] * M_PER_MM)
    reaction_n = r[3 * np.flatnonzero(on_face)].sum()
    area_m2 = size_mm[1] * size_mm[2] * M_PER_MM**2
    assert reaction_n == pytest.approx(P11 * area_m2, rel=1e-9)
    assert (P11 > 0) == (stretch > 1)  # the test can tell tension from compression


def test_closed_form_small_strain_limit():
    """Sanity of the hand derivation: at small strain P11 = E eps with E = 2 mu (1 + nu)."""
    m = MATERIALS["mooney-rivlin"]
    mu, kappa = m.shear_modulus_pa, m.volumetric.kappa_pa
    E = 9 * kappa * mu / (3 * kappa + mu)
    eps = 1e-6
    t, P11 = uniaxial_closed_form(1 + eps, m.c1_pa, m.c2_pa, kappa)
    # first-order expansion: relative error O(eps) = 1e-6, 1e-5 allows for brentq's tolerance
    assert P11 == pytest.approx(E * eps, rel=1e-5)
    nu = (3 * kappa - 2 * mu) / (2 * (3 * kappa + mu))
    assert (1 - t) / eps == pytest.approx(nu, rel=1e-5)
