"""Consistent tangent vs central finite differences (assembly and constitutive level)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from femtest_meshes import box_mesh

from fem import Constrained, FebioNeoHookean, Model, MooneyRivlin, NeoHookean, discretize
from fem.assemble import assemble, scatter
from fem.kinematics import invariants, piola, piola_and_tangent

MATERIALS = {
    "neo-hookean": NeoHookean(500.0, nu=0.45),
    "neo-hookean-log": NeoHookean(500.0, nu=0.3, kind="log"),
    "mooney-rivlin": MooneyRivlin.from_poisson(300.0, 200.0, 0.45),
    "febio-neo-hookean": FebioNeoHookean(3000.0, 0.3),
}
# Central differences: truncation O(h^2) ~ 1e-12 and cancellation ~ 1e-16 / h ~ 1e-10
# relative for h = 1e-6 of the state's scale, so a correct tangent gives ~1e-9 and
# the bound 1e-6 separates it clearly from a wrong one (errors O(1)).
FD_REL_STEP = 1e-6
TANGENT_RTOL = 1e-6


def _state(disc, noise_m, p_scale_pa, rng):
    """A random affine displacement (gradient ~ 0.15) plus dof noise, and random pressures."""
    x = np.zeros(disc.n_dofs)
    nu = 3 * disc.n_scalar_u
    X = disc.basis().doflocs.T  # (n_scalar_u, 3), m
    X = np.where(np.isfinite(X), X, 0.0)  # MINI's bubble dofs have no location: noise only
    x[:nu] = (X @ rng.uniform(-0.15, 0.15, (3, 3)).T).ravel()
    x[:nu] += rng.uniform(-noise_m, noise_m, nu)
    x[nu:] = rng.uniform(-p_scale_pa, p_scale_pa, disc.n_p)
    return x


def _full_tangent(disc, matrices):
    edofs = disc.element_dofs()
    n = edofs.shape[1]
    rows, cols = np.repeat(edofs, n, axis=1).ravel(), np.tile(edofs, (1, n)).ravel()
    return sp.csr_matrix((matrices.ravel(), (rows, cols)), shape=(disc.n_dofs,) * 2)


@pytest.mark.parametrize("name", sorted(MATERIALS))
@pytest.mark.parametrize("formulation", ["p1", "p2", "mini", "taylor-hood"])
def test_assembled_tangent_matches_finite_differences(formulation, name):
    rng = np.random.default_rng(7)
    mesh = box_mesh((10.0, 10.0, 10.0), (3, 3, 3), jitter=0.25, seed=3)
    sup = Constrained("z0")
    model = Model.homogeneous(mesh, MATERIALS[name], support=sup)
    disc = discretize(mesh, sup, formulation=formulation)
    # strains ~ 15 % plus 0.1 mm noise on 5 mm elements: a non-trivial state
    x = _state(disc, 0.1e-3, 300.0, rng)
    st = assemble(disc, model, x, tangent=True)
    assert st.min_J > 0.5
    K = _full_tangent(disc, st.matrices)

    def residual(y):
        return scatter(disc, assemble(disc, model, y, tangent=False).vectors)

    for _ in range(3):
        v = _state(disc, 0.1e-3, 300.0, rng)
        h = FD_REL_STEP
        fd = (residual(x + h * v) - residual(x - h * v)) / (2 * h)
        Kv = K @ v
        err = np.linalg.norm(Kv - fd) / np.linalg.norm(Kv)
        assert err < TANGENT_RTOL, f"tangent error {err:.2e}"
    # the reduced CSR assembly (the solver's path) equals the full matrix on free dofs
    free = disc.free
    K_red = disc.pattern.matrix(st.matrices)
    diff = abs(K_red - K[free][:, free]).max()
    assert diff <= 1e-12 * abs(K).max()  # same sums in another order: round-off only


def _energy(material, F):
    """Strain energy written out independently of fem.kinematics (Pa)."""
    C = F.T @ F
    I1, I2, J = np.trace(C), 0.5 * (np.trace(C) ** 2 - np.trace(C @ C)), np.linalg.det(F)
    if isinstance(material, FebioNeoHookean):
        mu, lam = material.shear_modulus_pa, material.volumetric.kappa_pa
        return mu / 2 * (I1 - 3) - mu * np.log(J) + lam / 2 * np.log(J) ** 2
    vol = material.volumetric
    G = J - 1 if vol.kind == "quadratic" else np.log(J)
    return (
        material.c1_pa * (J ** (-2 / 3) * I1 - 3)
        + material.c2_pa * (J ** (-4 / 3) * I2 - 3)
        + vol.kappa_pa / 2 * G**2
    )


def _first_and_second(material, F):
    I1, I2, J, _, _ = invariants(F)
    first, second = material.partials(I1, I2, J)
    G, G1, G2 = material.volumetric.g(J)
    k = material.volumetric.kappa_pa
    W1, W2, WJ = first
    W11, W12, W1J, W22, W2J, WJJ = second
    return (W1, W2, WJ + k * G * G1), (W11, W12, W1J, W22, W2J, WJJ + k * (G1**2 + G * G2))


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_piola_and_tangent_match_finite_differences_of_energy(name):
    material = MATERIALS[name]
    rng = np.random.default_rng(11)
    F = np.eye(3) + rng.uniform(-0.25, 0.25, (3, 3))  # a general, non-symmetric F
    assert np.linalg.det(F) > 0.3
    first, second = _first_and_second(material, F[None])
    P = piola(F[None], first)[0]
    P2, A = piola_and_tangent(F[None], first, second)
    np.testing.assert_allclose(P2[0], P, rtol=1e-13, atol=0)  # same formula, two paths
    h = 1e-6  # F is O(1): same error budget as above
    P_fd, A_fd = np.zeros((3, 3)), np.zeros((3, 3, 3, 3))
    for k in range(3):
        for m in range(3):
            dF = np.zeros((3, 3))
            dF[k, m] = h
            P_fd[k, m] = (_energy(material, F + dF) - _energy(material, F - dF)) / (2 * h)
            plus = piola(F[None] + dF, _first_and_second(material, F[None] + dF)[0])[0]
            minus = piola(F[None] - dF, _first_and_second(material, F[None] - dF)[0])[0]
            A_fd[:, :, k, m] = (plus - minus) / (2 * h)
    assert np.linalg.norm(P - P_fd) / np.linalg.norm(P) < TANGENT_RTOL
    assert np.linalg.norm(A[0] - A_fd) / np.linalg.norm(A_fd) < TANGENT_RTOL
    # major symmetry of a hyperelastic tangent, A_iJkL = A_kLiJ (round-off)
    np.testing.assert_allclose(A[0], A[0].transpose(2, 3, 0, 1), atol=1e-12 * abs(A).max())


@pytest.mark.parametrize("name", ["neo-hookean", "neo-hookean-log", "febio-neo-hookean"])
def test_structured_stiffness_equals_full_tangent_contraction(name):
    """The W(I1, J) fast path and the general fourth-order contraction: same matrices."""
    from fem.assemble import _energy_terms, deformation_gradient
    from fem.stiffness import stiffness_uu, stiffness_uu_general, stiffness_uu_i1j

    rng = np.random.default_rng(5)
    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2), jitter=0.25, seed=3)
    disc = discretize(mesh, Constrained("z0"), formulation="taylor-hood")
    x = _state(disc, 0.1e-3, 300.0, rng)
    F = deformation_gradient(disc, x)
    p = rng.uniform(-300.0, 300.0, F.shape[:2])
    first, second, *_ = _energy_terms(MATERIALS[name], F, p)
    fast = stiffness_uu_i1j(disc.grad_u, disc.weights, F, first, second)
    full = stiffness_uu_general(disc.grad_u, disc.weights, F, first, second)
    # the same sums in another order: round-off of the largest entries only
    np.testing.assert_allclose(fast, full, rtol=0, atol=1e-12 * abs(full).max())
    assert np.array_equal(stiffness_uu(disc.grad_u, disc.weights, F, first, second), fast)
