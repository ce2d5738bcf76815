"""Sparse direct solves: MKL PARDISO where available, SuperLU everywhere."""

from __future__ import annotations

import ctypes
import logging
from functools import cache
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["available_solvers", "factorize", "solve_sparse"]

log = logging.getLogger(__name__)
LinearSolver = Literal["auto", "pardiso", "superlu"]


class _PardisoCache:
    """One PARDISO instance per matrix type, reusing its symbolic analysis per pattern."""

    solvers: dict = {}  # mtype -> [solver, pattern key]

    @classmethod
    def clear(cls) -> None:
        cls.solvers = {}


def _pardiso_solve(A: sp.csr_matrix, b: np.ndarray, symmetric: bool) -> np.ndarray:
    mtype = -2 if symmetric else 11
    A = sp.triu(A, format="csr") if symmetric else A.tocsr()
    A.sort_indices()
    key = (A.shape[0], A.nnz, hash(A.indptr.tobytes()), hash(A.indices.tobytes()))
    if mtype not in _PardisoCache.solvers:
        _PardisoCache.solvers[mtype] = [_reproducible_pardiso(mtype), None]
    entry = _PardisoCache.solvers[mtype]
    solver = entry[0]
    if entry[1] != key:
        solver._check_A(A)
        solver.set_phase(11)
        solver._call_pardiso(A, b)
        entry[1] = key
    solver.set_phase(23)
    x = solver._call_pardiso(A, np.asarray(b, dtype=np.float64))
    return np.asarray(x).reshape(b.shape)


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


@cache
def _pardiso():
    try:
        import pypardiso
    except Exception as exc:  # noqa: BLE001 - any import failure means "not available"
        log.info("MKL PARDISO unavailable (%s); using SuperLU", exc)
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
    if method == "auto":
        method = "pardiso" if _pardiso() is not None else "superlu"
    if method == "pardiso":
        if _pardiso() is None:
            raise RuntimeError("linear solver 'pardiso' requested but pypardiso/MKL is missing")
        return _pardiso_solve(A, b, symmetric)
    if method == "superlu":
        return factorize(A, method="superlu")(b)
    raise ValueError(f"unknown linear solver {method!r}; choose auto, pardiso or superlu")


def factorize(A: sp.csr_matrix, *, method: LinearSolver = "auto"):
    """Factorize once, solve many: returns ``solve(b) -> x`` for the matrix ``A``.

    Parameters
    ----------
    A : scipy.sparse matrix, shape (n, n)
    method : {"auto", "pardiso", "superlu"}
    """
    if method == "auto":
        method = "pardiso" if _pardiso() is not None else "superlu"
    if method == "superlu":
        # Symmetric diagonal scaling: the mixed (u-p) blocks differ by many orders of
        # magnitude, which costs SuperLU's unscaled pivoting several digits.
        d = 1.0 / np.sqrt(np.maximum(abs(A).max(axis=1).toarray().ravel(), 1e-300))
        D = sp.diags(d)
        lu = spla.splu((D @ A @ D).tocsc(), permc_spec="COLAMD")
        return lambda b: d * lu.solve(d * np.asarray(b, dtype=float))
    if method != "pardiso" or _pardiso() is None:
        raise ValueError(f"linear solver {method!r} is not available")
    A = A.tocsr()
    A.sort_indices()
    solver = _reproducible_pardiso()
    solver.factorize(A)
    return lambda b: np.asarray(solver.solve(A, np.asarray(b, dtype=np.float64))).reshape(b.shape)
