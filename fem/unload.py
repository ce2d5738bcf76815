"""Stress-free reference recovery ("unloading") and the dissertation's shortcut.

A scan shows the phantom deformed by gravity ``g0``. The stress-free geometry ``X``
is the one that deforms into the measured geometry ``x_m`` under ``g0``. Reversing
gravity is not the inverse in nonlinear elasticity; here ``X`` is found by the
backward-displacement fixed point ``X <- X - a (X + u(X) - x_m)`` with Aitken's
adaptive relaxation ``a``, each forward solve warm-started from the last.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .discretize import Formulation, discretize
from .model import Model
from .solver import Solution, SolverOptions, solve

__all__ = ["ReferenceRecovery", "recover_stress_free", "shortcut_gravity"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReferenceRecovery:
    """Result of :func:`recover_stress_free`.

    Attributes
    ----------
    nodes_mm : ndarray, shape (n_nodes, 3)
        The recovered stress-free node positions, model frame, mm.
    converged : bool
    iterations : int
        Forward solves used.
    max_error_mm : float
        Largest distance between the loaded recovered geometry and the measured one.
    history_mm : tuple of float
        ``max_error_mm`` after each iteration.
    solution : Solution
        The forward solve from the recovered geometry under ``g0``.
    """

    nodes_mm: np.ndarray
    converged: bool
    iterations: int
    max_error_mm: float
    history_mm: tuple[float, ...]
    solution: Solution


def _aitken(alpha: float, r_old: np.ndarray | None, r_new: np.ndarray) -> float:
    if r_old is None:
        return alpha
    d = r_new - r_old
    denom = float(np.sum(d * d))
    if denom == 0.0:
        return alpha
    return float(np.clip(-alpha * np.sum(r_old * d) / denom, 0.1, 1.5))


def recover_stress_free(
    model: Model,
    *,
    gravity: np.ndarray,
    g_m_s2: float = 9.81,
    formulation: Formulation = "taylor-hood",
    tol_mm: float = 0.01,
    max_iter: int = 60,
    options: SolverOptions | None = None,
    x0_nodes_mm: np.ndarray | None = None,
    x0_state: np.ndarray | None = None,
) -> ReferenceRecovery:
    """Find the stress-free geometry whose deformation under ``gravity`` is the mesh.

    Parameters
    ----------
    model : Model
        ``model.mesh`` holds the measured (loaded) geometry, mm.
    gravity : array_like, shape (3,)
        Direction of the gravity ``g0`` the measured geometry is under, model frame.
    g_m_s2 : float
        Its magnitude.
    formulation : str
    tol_mm : float
        Stop when every node of the loaded recovered geometry is within this distance
        of the measured one.
    max_iter : int
        Most forward solves.
    options : SolverOptions, optional
    x0_nodes_mm : ndarray, shape (n_nodes, 3), optional
        Initial guess of the stress-free geometry (e.g. from a nearby material).
    x0_state : ndarray, optional
        Warm start of the first forward solve (``Solution.state``).

    Returns
    -------
    ReferenceRecovery
    """
    x_m = model.mesh.nodes_mm
    disc0 = discretize(model.mesh, model.support, formulation=formulation)
    X = x_m.copy() if x0_nodes_mm is None else np.asarray(x0_nodes_mm, float).copy()
    alpha, r_old, state, history = 1.0, None, x0_state, []
    for it in range(1, max_iter + 1):
        disc = disc0.with_nodes(X)
        sol = solve(
            model.with_mesh(disc.mesh),
            gravity=gravity,
            g_m_s2=g_m_s2,
            disc=disc,
            options=options,
            x0=state,
        )
        state = sol.state
        r = X + sol.displacement_mm - x_m
        err = float(np.linalg.norm(r, axis=1).max())
        history.append(err)
        log.info("reference recovery iteration %d: max error %.4g mm", it, err)
        if err <= tol_mm:
            return ReferenceRecovery(X, True, it, err, tuple(history), sol)
        alpha = _aitken(alpha, r_old, r)
        X, r_old = X - alpha * r, r
    return ReferenceRecovery(X, False, max_iter, err, tuple(history), sol)


def shortcut_gravity(g_target, g_reference, *, g_m_s2: float = 9.81) -> tuple[np.ndarray, float]:
    """The dissertation's shortcut load: the loaded scan taken as stress-free, load ``g - g0``.

    Parameters
    ----------
    g_target, g_reference : array_like, shape (3,)
        Gravity directions of the target posture and of the reference scan.

    Returns
    -------
    direction : ndarray, shape (3,)
    magnitude_m_s2 : float
        Pass both to :func:`fem.solve` (``gravity=direction, g_m_s2=magnitude``).
    """
    g = np.asarray(g_target, float) / np.linalg.norm(g_target)
    g0 = np.asarray(g_reference, float) / np.linalg.norm(g_reference)
    d = (g - g0) * g_m_s2
    n = float(np.linalg.norm(d))
    return (d / n if n > 0 else g), n
