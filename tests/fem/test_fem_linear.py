"""Linear limit of the nonlinear solver, and two code paths for the same answer."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from femtest_meshes import box_mesh

from fem import Clamped, Model, NeoHookean, SolverOptions, discretize, solve
from fem.assemble import assemble
from fem.geometry import PhantomSpec, build_phantom
from fem.linalg import available_solvers, solve_sparse
from fem.meshing import mesh_phantom

M_PER_MM = 1e-3


@pytest.fixture(scope="module")
def small_phantom_mesh():
    return mesh_phantom(build_phantom(PhantomSpec(resolution_mm=12, n_inclusions=0)), size_mm=12)


def _full_matrix(disc, matrices):
    edofs = disc.element_dofs()
    n = edofs.shape[1]
    rows, cols = np.repeat(edofs, n, axis=1).ravel(), np.tile(edofs, (1, n)).ravel()
    return sp.csr_matrix((matrices.ravel(), (rows, cols)), shape=(disc.n_dofs,) * 2)


def _gravity_solutions(model, disc, g_m_s2):
    """Displacements (mm) under gravity g along x, y, z and along (1, -2, 3)/|.|."""
    axes = [solve(model, gravity=e, g_m_s2=g_m_s2, disc=disc).displacement_mm for e in np.eye(3)]
    d = np.array([1.0, -2.0, 3.0]) / np.sqrt(14.0)
    combined = solve(model, gravity=d, g_m_s2=g_m_s2, disc=disc).displacement_mm
    superposed = sum(di * ui for di, ui in zip(d, axes, strict=True))
    return combined, superposed


@pytest.mark.parametrize("formulation", ["p1", "taylor-hood"])
def test_linear_limit_superposition_of_gravity(small_phantom_mesh, formulation):
    model = Model.homogeneous(small_phantom_mesh, NeoHookean(420.0, nu=0.499))
    disc = discretize(small_phantom_mesh, model.support, formulation=formulation)
    combined, superposed = _gravity_solutions(model, disc, 9.81e-4)
    rel = np.linalg.norm(combined - superposed) / np.linalg.norm(combined)
    # at 1e-4 g the strains are ~1e-5 (1 g sags ~20 mm of 70), so the quadratic
    # terms are ~1e-5 relative; Newton's rtol 1e-8 adds less. Issue's bound: 1e-4.
    assert rel < 1e-4, f"superposition error {rel:.2e}"


def test_superposition_fails_at_one_g(small_phantom_mesh):
    """The same check at 1 g sees the nonlinearity (so the test above can fail)."""
    model = Model.homogeneous(small_phantom_mesh, NeoHookean(420.0, nu=0.499))
    disc = discretize(small_phantom_mesh, model.support, formulation="p1")
    combined, superposed = _gravity_solutions(model, disc, 9.81)
    assert np.linalg.norm(combined - superposed) / np.linalg.norm(combined) > 1e-3


def test_p1_tangent_at_rest_equals_scikit_fem_linear_elasticity():
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet
    from skfem.models.elasticity import linear_elasticity

    mesh = box_mesh((12.0, 8.0, 6.0), (4, 3, 3), jitter=0.3, seed=5)
    material = NeoHookean(420.0, nu=0.45)
    model = Model.homogeneous(mesh, material, support=Clamped("z0"))
    disc = discretize(mesh, model.support, formulation="p1")
    K = _full_matrix(disc, assemble(disc, model, np.zeros(disc.n_dofs)).matrices)
    # linearised at F = I: shear modulus 2 c1, Lame lambda = kappa - 2/3 mu
    mu = 2.0 * material.c1_pa
    lam = material.volumetric.kappa_pa - 2.0 / 3.0 * mu
    m = MeshTet(np.ascontiguousarray(mesh.nodes_mm.T * M_PER_MM), np.ascontiguousarray(mesh.tets.T))
    basis = Basis(m, ElementVector(ElementTetP1()))
    # skfem's vector P1 numbers dof (node, component) as 3 node + component, as fem does
    assert np.array_equal(basis.nodal_dofs, 3 * np.arange(mesh.n_nodes) + np.arange(3)[:, None])
    K_ref = linear_elasticity(Lambda=lam, Mu=mu).assemble(basis)
    # two exact integrations of the same constant-gradient integrand: round-off only
    assert abs(K - K_ref).max() <= 1e-12 * abs(K_ref).max()


_NEEDS_PARDISO = pytest.mark.skipif(
    "pardiso" not in available_solvers(), reason="pypardiso (MKL) not installed"
)


@_NEEDS_PARDISO
@pytest.mark.parametrize("formulation", ["p1", "taylor-hood"])
def test_pardiso_and_superlu_agree(formulation):
    mesh = box_mesh((10.0, 10.0, 40.0), (3, 3, 9), jitter=0.2, seed=2)
    model = Model.homogeneous(mesh, NeoHookean(420.0, nu=0.49), support=Clamped("z1"))
    disc = discretize(mesh, model.support, formulation=formulation)
    sol = solve(model, gravity=[1.0, 0.0, -1.0], disc=disc)
    K = disc.pattern.matrix(assemble(disc, model, sol.state).matrices)  # a deformed state
    # a right-hand side of the solver's own scales (m and Pa): K times the solution
    x_true = sol.state[disc.free]
    b = K @ x_true
    x_p = solve_sparse(K, b, method="pardiso")
    x_s = solve_sparse(K, b, method="superlu")
    # both are backward stable direct solvers, differing by ~cond(K) eps; 1e-10 is the
    # brief's "same answers" (measured: see the report, ~1e-12 or below)
    for x in (x_p, x_s):
        assert np.linalg.norm(x - x_true) / np.linalg.norm(x_true) < 1e-10
    assert np.linalg.norm(x_p - x_s) / np.linalg.norm(x_s) < 1e-10


@_NEEDS_PARDISO
def test_pardiso_and_superlu_solves_agree_to_newton_tolerance():
    """At the level of solve(), both linear solvers give the same displacement."""
    mesh = box_mesh((10.0, 10.0, 40.0), (3, 3, 9), jitter=0.2, seed=2)
    model = Model.homogeneous(mesh, NeoHookean(420.0, nu=0.49), support=Clamped("z1"))
    disc = discretize(mesh, model.support, formulation="taylor-hood")
    u = [
        solve(model, gravity=[1.0, 0.0, -1.0], disc=disc, options=SolverOptions(linear_solver=m))
        for m in ("pardiso", "superlu")
    ]
    # Newton stops at relative residual 1e-8 (SolverOptions.rtol); with quadratic
    # convergence the last step is far smaller, 1e-8 relative in u is a safe bound
    diff = np.linalg.norm(u[0].displacement_mm - u[1].displacement_mm)
    assert diff / np.linalg.norm(u[1].displacement_mm) < 1e-8


@pytest.mark.parametrize("linear_solver", available_solvers())
def test_reusing_an_earlier_factorization_gives_the_newton_answer(linear_solver):
    """Late Newton steps by GMRES on a stale factor: same converged state, fewer factors."""
    mesh = box_mesh((10.0, 10.0, 40.0), (3, 3, 9), jitter=0.2, seed=2)
    model = Model.homogeneous(mesh, NeoHookean(420.0, nu=0.49), support=Clamped("z1"))
    disc = discretize(mesh, model.support, formulation="taylor-hood")
    runs = {
        reuse: solve(
            model,
            gravity=[1.0, 0.0, -1.0],
            disc=disc,
            options=SolverOptions(linear_solver=linear_solver, reuse_factor_below=reuse),
        )
        for reuse in (0.0, 1.0)
    }
    fresh, reused = runs[0.0], runs[1.0]
    assert fresh.factorizations == fresh.newton_iterations  # 0 disables reuse
    assert reused.factorizations < reused.newton_iterations  # the path was taken
    # both stop at the relative residual 1e-8 (quadratic rate): 1e-8 relative in u
    diff = np.linalg.norm(reused.displacement_mm - fresh.displacement_mm)
    assert diff / np.linalg.norm(fresh.displacement_mm) < 1e-8
