"""Sparse direct solvers: agreement of PARDISO and SuperLU, bitwise reproducibility."""

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from fem import linalg

#: What `make test` sets to one thread per worker
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _convection_diffusion(m: int) -> sp.csr_matrix:
    """Unsymmetric 3-D 7-point operator on an m^3 grid (diagonally dominant, well posed)."""
    T = sp.diags([-1.0, 2.1, -1.2], [-1, 0, 1], shape=(m, m))
    eye = sp.eye(m)
    return (
        sp.kron(sp.kron(T, eye), eye)
        + sp.kron(sp.kron(eye, T), eye)
        + sp.kron(sp.kron(eye, eye), T)
    ).tocsr()


def test_superlu_solves_to_rounding():
    A = _convection_diffusion(12)
    x_true = np.random.default_rng(0).standard_normal(A.shape[0])
    x = linalg.solve_sparse(A, A @ x_true, method="superlu")
    # Condition number of this operator is O(10^2): 1e-10 leaves six digits of margin.
    np.testing.assert_allclose(x, x_true, rtol=0, atol=1e-10)


@pytest.mark.skipif("pardiso" not in linalg.available_solvers(), reason="MKL PARDISO absent")
def test_pardiso_is_bitwise_reproducible():
    # The digital twin promises byte-identical output for a seed; MKL's defaults broke that
    # in CI: under CPU contention MKL changes its thread count and the last bits move
    # (2 of 10 repeated solves of this 27k-unknown system differed with a busy process
    # beside it on 2 cores). A fresh solver per repeat redoes the ordering, and a busy
    # process provokes the contention.
    A = _convection_diffusion(30)
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    answers = []
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        for _ in range(10):
            linalg._PardisoCache.clear()
            answers.append(linalg.solve_sparse(A, b, method="pardiso"))
    finally:
        busy.kill()
        busy.wait()
    assert all(np.array_equal(answers[0], x) for x in answers[1:])
    # review CC-04: whether the busy process provokes MKL's change of thread count
    # depends on the scheduler, so the settings that make the bits reproducible are
    # checked on the solver itself too: the sequential METIS ordering and conditional
    # numerical reproducibility at the current thread count (MKL's iparm[1], iparm[33])
    # (review CE-8: on the solver the solves used, the cached one, not a fresh one)
    solver = linalg._PardisoCache.solvers[11][0]
    assert solver.iparm[1] == 2
    assert solver.iparm[33] == max(int(solver.libmkl.MKL_Get_Max_Threads()), 1)
    np.testing.assert_allclose(A @ answers[0], b, rtol=0, atol=1e-10)
    # the symmetric indefinite path (forward Newton) agrees with the unsymmetric one
    S = (A + A.T).tocsr()
    x_sym = linalg.solve_sparse(S, b, method="pardiso", symmetric=True)
    x_uns = linalg.solve_sparse(S, b, method="pardiso")
    # both are backward stable on this well-conditioned operator: 1e-10 leaves margin
    np.testing.assert_allclose(x_sym, x_uns, rtol=0, atol=1e-10)
    # one factorisation solved twice gives the same bits (a state PARDISO kept between
    # solve phases would show), and the fresh solver's answer to backward-stable accuracy
    factor = linalg.factorize(A, method="pardiso")
    first = factor(b)
    assert np.array_equal(first, factor(b))
    np.testing.assert_allclose(first, answers[0], rtol=0, atol=1e-10)


@pytest.mark.parametrize("method", linalg.available_solvers())
def test_factor_survives_a_later_factorization_and_preconditions_gmres(method):
    """A factor stays valid after the shared PARDISO instance factorised another matrix,
    and as a GMRES preconditioner of a nearby matrix it reaches the asked tolerance."""
    A = _convection_diffusion(10)
    B = A + sp.diags(np.full(A.shape[0], 0.05))  # a 'later tangent': 2 % off A's diagonal
    x_true = np.random.default_rng(2).standard_normal(A.shape[0])
    fa = linalg.factorize(A, method=method)
    linalg.factorize(B, method=method)(B @ x_true)  # overwrites the shared instance
    # condition O(10^2): 1e-10 leaves digits of margin, as in the SuperLU test above
    np.testing.assert_allclose(fa(A @ x_true), x_true, rtol=0, atol=1e-10)
    scale = np.linspace(1.0, 3.0, A.shape[0])
    x = linalg.solve_preconditioned(B, B @ x_true, fa, scale=scale, rtol=1e-9)
    assert x is not None
    b = B @ x_true
    assert np.linalg.norm(scale * (B @ x - b)) <= 1e-9 * np.linalg.norm(scale * b)
    # one Krylov step cannot reach 1e-9 with a 2 % perturbation: reported, not hidden
    assert (
        linalg.solve_preconditioned(B, B @ x_true, fa, scale=scale, rtol=1e-9, max_iterations=1)
        is None
    )


def test_pardiso_survives_a_change_of_mkl_thread_count():
    # A cached PARDISO solver set up for one MKL thread count segfaulted in its next
    # factorisation after threadpoolctl changed the count (found by the sweep's pool
    # workers). Run in a subprocess: a crash must fail the test, not kill the suite.
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import numpy as np
        from threadpoolctl import threadpool_limits
        import fem
        from fem.geometry import PhantomSpec, build_phantom
        from fem.linalg import available_solvers
        from fem.meshing import mesh_phantom
        assert "pardiso" in available_solvers()
        mesh = mesh_phantom(build_phantom(PhantomSpec(resolution_mm=16.0, n_inclusions=0)),
                            size_mm=16.0)
        model = fem.Model.homogeneous(mesh, fem.NeoHookean(420.0, nu=0.49))
        disc = fem.discretize(mesh, model.support)
        from threadpoolctl import threadpool_info
        u, counts = [], []
        for k in range(3):  # the thread count alternates between solves
            with threadpool_limits(limits=1 if k % 2 else 2):
                counts.append([p["num_threads"] for p in threadpool_info()
                               if p["internal_api"] == "mkl"])
                u.append(fem.solve(model, gravity=[0, 1, 0], disc=disc).displacement_mm)
        assert counts[0] != counts[1], counts  # the count did change (review BV, F5)
        assert np.allclose(u[0], u[1], atol=1e-9) and np.allclose(u[0], u[2], atol=1e-9)
        print("ok")
        """
    )
    # without the thread variables `make test` sets (review BV, F5: MKL stayed at 1 thread)
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False,
        env=env,
    )  # fmt: skip
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr
