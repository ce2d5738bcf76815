"""Hanging bar under its own weight against the incompressible 1D closed form.

../shared/data/README.md (peer reference values): for W = c1 (I1 - 3), incompressible,
each section carries the nominal stress rho g (L - X), so the local stretch solves
2 c1 (lambda - lambda^-2) = rho g (L - X) and the tip displacement is the integral of
(lambda - 1) dX; it holds for a slender bar away from the clamped end.
"""

from __future__ import annotations

import pytest
from femtest_meshes import box_mesh
from scipy.integrate import quad
from scipy.optimize import brentq

from fem import Clamped, Model, NeoHookean, solve

L_MM, WIDTH_MM = 100.0, 5.0  # slender: aspect ratio 20
RHO, G = 1000.0, 9.81
C1 = 700.0  # Pa: stretch 1.30 at the clamp, 13.7 mm tip sag


def _stretch(X_mm):
    s = RHO * G * (L_MM - X_mm) * 1e-3
    return brentq(lambda lam: 2 * C1 * (lam - lam**-2) - s, 1.0, 10.0, xtol=1e-14)


def tip_closed_form_mm():
    return quad(lambda X: _stretch(X) - 1.0, 0.0, L_MM, epsabs=1e-12, limit=200)[0]


def _tip_fe_mm(n, formulation, nu):
    mesh = box_mesh((WIDTH_MM, WIDTH_MM, L_MM), n)
    model = Model.homogeneous(mesh, NeoHookean(C1, nu=nu), density_kg_m3=RHO, support=Clamped("z1"))
    sol = solve(model, gravity=[0.0, 0.0, -1.0], g_m_s2=G, formulation=formulation)
    assert sol.converged
    return -sol.displacement_mm[mesh.node_sets["z0"], 2].mean()  # mean over the free end


def test_closed_form_stretch_range():
    """The case is in the intended regime: 10-30 % stretch at the clamp."""
    assert 1.1 < _stretch(0.0) < 1.31
    assert _stretch(L_MM) == pytest.approx(1.0)


@pytest.mark.parametrize("n", [(3, 3, 41), (4, 4, 61)], ids=["960tets", "3240tets"])
def test_hanging_bar_taylor_hood_matches_closed_form(n):
    tip_fe = _tip_fe_mm(n, "taylor-hood", 0.499)
    tip = tip_closed_form_mm()
    # 2 %: the bound. What remains (measured -1.25 % and -1.15 % on these meshes,
    # -1.6 % at 480 tets) is the clamped end, which stops the lateral contraction over
    # about one width where the stretch is largest, plus nu = 0.499 instead of 0.5.
    assert abs(tip_fe - tip) / tip < 0.02, f"tip {tip_fe:.3f} mm vs {tip:.3f} mm"


def test_hanging_bar_p1_locks_at_nu_04999():
    """P1 displacement tets lock: the locking-free element is needed (issue: 15 % trial)."""
    tip = tip_closed_form_mm()
    p1 = _tip_fe_mm((3, 3, 41), "p1", 0.4999)
    th = _tip_fe_mm((3, 3, 41), "taylor-hood", 0.4999)
    assert abs(th - tip) / tip < 0.02  # same bound as above
    assert p1 < 0.9 * th  # P1 sags at least 10 % less on this mesh
