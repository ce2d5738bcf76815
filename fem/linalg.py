"""Sparse direct solves: MKL PARDISO where available, SuperLU everywhere."""

from __future__ import annotations

import ctypes
import glob
import logging
import os
import sys
from collections.abc import Callable
from functools import cache
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["available_solvers", "factorize", "solve_preconditioned", "solve_sparse"]

log = logging.getLogger(__name__)
LinearSolver = Literal["auto", "pardiso", "superlu"]


class _PardisoCache:
    """One PARDISO instance per matrix type, reusing its symbolic analysis per pattern.

    Each entry is ``[solver, pattern key, owner, threads]``: ``owner`` is the token of the
    factorization the instance holds now, so a factor handed out earlier can tell
    whether it was overwritten (and then factorises its matrix again); ``threads`` is
    MKL's thread count the instance was set up for.
    """

    solvers: dict = {}  # mtype -> [solver, pattern key, owner token, MKL threads]
    libmkl = None

    @classmethod
    def clear(cls) -> None:
        cls.solvers = {}


def _pardiso_factor(A: sp.csr_matrix, symmetric: bool) -> Callable[[np.ndarray], np.ndarray]:
    mtype = -2 if symmetric else 11
    A = sp.triu(A, format="csr") if symmetric else A.tocsr()
    A.sort_indices()
    key = (A.shape[0], A.nnz, hash(A.indptr.tobytes()), hash(A.indices.tobytes()))
    threads = _mkl_threads()
    entry = _PardisoCache.solvers.get(mtype)
    if entry is None or entry[3] != threads:
        # A solver set up for another MKL thread count (its reproducibility setting,
        # iparm[33], is tied to it) crashes in its next factorisation: make a new one.
        entry = _PardisoCache.solvers[mtype] = [_reproducible_pardiso(mtype), None, None, threads]
    solver, token = entry[0], object()

    def factor() -> None:
        if entry[1] != key:
            solver._check_A(A)
            solver.set_phase(11)
            solver._call_pardiso(A, np.zeros(A.shape[0]))
            entry[1] = key
        solver.set_phase(22)
        solver._call_pardiso(A, np.zeros(A.shape[0]))
        entry[2] = token

    def solve(b: np.ndarray) -> np.ndarray:
        if entry[2] is not token:  # another matrix was factorised since: redo ours
            factor()
        solver.set_phase(33)
        x = solver._call_pardiso(A, np.asarray(b, dtype=np.float64))
        return np.asarray(x).reshape(np.shape(b))

    factor()
    return solve


def _mkl_threads() -> int:
    """MKL's current maximum thread count (threadpoolctl and MKL_NUM_THREADS change it)."""
    if _PardisoCache.libmkl is None:  # the library pypardiso loads (a CDLL is shared)
        _PardisoCache.libmkl = _pardiso().PyPardisoSolver().libmkl
    return max(int(_PardisoCache.libmkl.MKL_Get_Max_Threads()), 1)


def _reproducible_pardiso(mtype: int = 11):
    """A PARDISO solver whose results are bitwise reproducible.

    ``mtype`` 11 is real unsymmetric, -2 real symmetric indefinite (upper triangle given).
    MKL's defaults use the parallel (OpenMP) nested dissection, whose ordering and hence
    the last bits of the solution vary from run to run. We take MKL's own defaults
    (``pardisoinit``), switch to the sequential METIS ordering (``iparm[1] = 2``) and turn
    on conditional numerical reproducibility for the current thread count
    (``iparm[33]``), so that the same input gives the same bits on the same machine.
    For the symmetric indefinite saddle-point systems of the mixed formulations,
    symmetric scaling and weighted matching (``iparm[10] = iparm[12] = 1``) are needed:
    without them the factorisation is silently wrong.
    """
    solver = _pardiso().PyPardisoSolver(mtype=mtype)
    init = solver.libmkl.pardisoinit
    init.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32), ctypes.c_void_p]
    init.restype = None
    init(solver.pt.ctypes.data, ctypes.byref(ctypes.c_int32(mtype)), solver.iparm.ctypes.data)
    solver.iparm[1] = 2
    solver.iparm[10] = solver.iparm[12] = 1
    solver.iparm[33] = max(int(solver.libmkl.MKL_Get_Max_Threads()), 1)
    return solver


def _point_pypardiso_at_mkl() -> None:
    """Tell pypardiso where MKL's runtime lies, when it sits in this environment's ``lib``.

    Without ``PYPARDISO_MKL_RT`` every new solver walks ``sys.prefix`` recursively for
    the library (about 0.7 s per solver in a virtual environment with many packages).
    A user's own setting is kept.
    """
    if os.environ.get("PYPARDISO_MKL_RT"):
        return
    found = sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len)
    if found:
        os.environ["PYPARDISO_MKL_RT"] = found[0]


@cache
def _pardiso():
    _point_pypardiso_at_mkl()
    try:
        import pypardiso
    except Exception as exc:  # any import failure means "not available"
        # once per process (cached), where the user sees it: a solve may be 10-20x slower
        log.warning("MKL PARDISO (pypardiso) is not available (%s): using SuperLU, much "
                    "slower on large meshes (a 4,588-tet simulate: 39 s instead of 2 s). "
                    "On x86_64: pip install pypardiso", exc)  # fmt: skip
        return None
    return pypardiso


def available_solvers() -> list[str]:
    """Names of the sparse direct solvers usable on this machine."""
    return (["pardiso"] if _pardiso() is not None else []) + ["superlu"]


def solve_sparse(
    A: sp.csr_matrix, b: np.ndarray, *, method: LinearSolver = "auto", symmetric: bool = False
) -> np.ndarray:
    """Solve ``A x = b`` for a square sparse matrix.

    Parameters
    ----------
    A : scipy.sparse.csr_matrix, shape (n, n)
    b : ndarray, shape (n,)
    method : {"auto", "pardiso", "superlu"}
        ``auto`` takes PARDISO (pypardiso, MKL) when installed, else SuperLU.
    symmetric : bool
        ``A`` is symmetric (to round-off): PARDISO then factorises its upper triangle as
        symmetric indefinite, about a quarter faster. SuperLU ignores it.

    Returns
    -------
    ndarray, shape (n,)
    """
    return factorize(A, method=method, symmetric=symmetric)(b)


def factorize(
    A: sp.csr_matrix, *, method: LinearSolver = "auto", symmetric: bool = False
) -> Callable[[np.ndarray], np.ndarray]:
    """Factorize once, solve many: returns ``solve(b) -> x`` for the matrix ``A``.

    Parameters
    ----------
    A : scipy.sparse matrix, shape (n, n)
    method : {"auto", "pardiso", "superlu"}
    symmetric : bool
        As in :func:`solve_sparse`.

    Notes
    -----
    PARDISO factors share one solver instance per matrix type (so that the symbolic
    analysis of a sparsity pattern is done once per process); a factor whose instance
    has since factorised another matrix factorises its own again before solving.
    """
    method = _resolve(method)
    if method == "superlu":
        # Symmetric diagonal scaling: the mixed (u-p) blocks differ by many orders of
        # magnitude, which costs SuperLU's unscaled pivoting several digits.
        d = 1.0 / np.sqrt(np.maximum(abs(A).max(axis=1).toarray().ravel(), 1e-300))
        D = sp.diags(d)
        lu = spla.splu((D @ A @ D).tocsc(), permc_spec="COLAMD")
        return lambda b: d * lu.solve(d * np.asarray(b, dtype=float))
    return _pardiso_factor(A, symmetric)


def _resolve(method: str) -> str:
    if method == "auto":
        return "pardiso" if _pardiso() is not None else "superlu"
    if method == "pardiso" and _pardiso() is None:
        raise RuntimeError("linear solver 'pardiso' requested but pypardiso/MKL is missing")
    if method not in ("pardiso", "superlu"):
        raise ValueError(f"unknown linear solver {method!r}; choose auto, pardiso or superlu")
    return method


def solve_preconditioned(
    A: sp.csr_matrix,
    b: np.ndarray,
    factor: Callable[[np.ndarray], np.ndarray],
    *,
    scale: np.ndarray,
    rtol: float,
    max_iterations: int = 8,
) -> np.ndarray | None:
    """Solve ``A x = b`` by GMRES, preconditioned by the factor of a nearby matrix.

    Used for Newton steps late in an iteration, where the tangent changed little since
    it was last factorised: a few back-substitutions replace a factorization.

    Parameters
    ----------
    A : scipy.sparse matrix, shape (n, n)
    b : ndarray, shape (n,)
    factor : callable
        ``factor(y)`` approximately solves ``A x = y`` (e.g. :func:`factorize` of an
        earlier tangent).
    scale : ndarray, shape (n,)
        Row weights ``D``: convergence is measured as ``|D (A x - b)| <= rtol |D b|``
        (the solver's scaled residual norm, so force and volume rows count alike).
    rtol : float
        Relative tolerance on that scaled residual.
    max_iterations : int
        Krylov iterations (back-substitutions) before giving up.

    Returns
    -------
    ndarray, shape (n,), or None
        ``None`` when the tolerance was not reached: factorise ``A`` instead.
    """
    n = A.shape[0]
    op = spla.LinearOperator((n, n), matvec=lambda y: scale * (A @ factor(y / scale)))
    y, _ = spla.gmres(op, scale * b, rtol=rtol, atol=0.0, restart=max_iterations, maxiter=1)
    x = factor(y / scale)
    achieved = np.linalg.norm(scale * (A @ x - b)) / max(np.linalg.norm(scale * b), 1e-300)
    return x if achieved <= rtol else None
