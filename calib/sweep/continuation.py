"""Continuation order of a sweep: which solved scenario warm-starts which.

Scenarios are points ``b = g_hat * c1_cal / c1`` of the load space (the gravity
direction scaled by the relative load ``rho g / c1`` of the solve, see
:mod:`calib.sweep.plans`): two scenarios close in ``b`` have close solutions, so one
warm-starts the other's Newton iterations (a few iterations instead of load stepping
from zero).

The order is fixed by the plan alone, never by the workers:

1. a greedy nearest-neighbour tour through all scenarios, from scenario 0 (ties to the
   lower index);
2. the tour is cut into ``ceil(S / chunk_size)`` contiguous chunks of near-equal size;
3. in each chunk, a scenario's *parent* is the nearest scenario before it in the chunk,
   when it lies within ``max_angle_deg`` (relative to the larger load); the first
   scenario of a chunk, or one far from the others, starts cold (load stepping).

Each solve starts from its parent's stored solver state, so the numbers of a sweep do not
depend on the backend, the worker count or on interruptions: a solve's input is the
same bits whichever worker runs it, whenever (Newton's iterates, PARDISO's solves with
fixed ordering and conditional numerical reproducibility, see :mod:`fem.linalg`, are
deterministic functions of their input). Chunks can run in parallel; inside a chunk a
scenario waits for its parent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Continuation", "plan_continuation"]


@dataclass(frozen=True)
class Continuation:
    """Warm-start structure of a sweep.

    Attributes
    ----------
    order : ndarray of int, shape (S,)
        Scenario indices in tour order.
    chunk : ndarray of int, shape (S,)
        Chunk of each scenario (by scenario index).
    parent : ndarray of int, shape (S,)
        Scenario whose solution warm-starts each scenario, -1 for a cold start.
    """

    order: np.ndarray
    chunk: np.ndarray
    parent: np.ndarray

    @property
    def n_chunks(self) -> int:
        """Number of chunks."""
        return int(self.chunk.max()) + 1 if self.chunk.size else 0


def _greedy_tour(points: np.ndarray) -> np.ndarray:
    n = len(points)
    order = np.empty(n, dtype=np.int64)
    visited = np.zeros(n, dtype=bool)
    current = 0
    for k in range(n):
        order[k] = current
        visited[current] = True
        if k == n - 1:
            break
        d = np.linalg.norm(points - points[current], axis=1)
        d[visited] = np.inf
        current = int(np.argmin(d))  # first minimum: ties go to the lower index
    return order


def plan_continuation(
    loads: np.ndarray, *, chunk_size: int = 12, max_angle_deg: float = 45.0
) -> Continuation:
    """Order, chunks and warm-start parents of a sweep's scenarios.

    Parameters
    ----------
    loads : ndarray, shape (S, 3)
        Load-space points ``g_hat * c1_cal / c1`` (any fixed frame).
    chunk_size : int
        Scenarios per chunk (the last chunks may hold one less).
    max_angle_deg : float
        A parent must lie within ``2 sin(max_angle / 2)`` times the larger load of the
        two (the chord of that angle for equal loads); farther, a cold start is cheaper
        than Newton from a distant state.

    Returns
    -------
    Continuation
    """
    loads = np.asarray(loads, float)
    if loads.ndim != 2 or loads.shape[1] != 3:
        raise ValueError(f"loads must have shape (S, 3), got {loads.shape}")
    if chunk_size < 1:
        raise ValueError(f"chunk size must be >= 1, got {chunk_size}")
    n = len(loads)
    order = _greedy_tour(loads) if n else np.zeros(0, dtype=np.int64)
    n_chunks = -(-n // chunk_size)
    pieces = np.array_split(order, n_chunks) if n else []
    chunk = np.empty(n, dtype=np.int64)
    parent = np.full(n, -1, dtype=np.int64)
    chord = 2.0 * np.sin(np.radians(max_angle_deg) / 2.0)
    norms = np.linalg.norm(loads, axis=1)
    for c, piece in enumerate(pieces):
        chunk[piece] = c
        for k in range(1, len(piece)):
            i, earlier = piece[k], piece[:k]
            d = np.linalg.norm(loads[earlier] - loads[i], axis=1)
            j = int(np.argmin(d))
            if d[j] <= chord * max(norms[i], norms[earlier[j]]):
                parent[i] = earlier[j]
    return Continuation(order=order, chunk=chunk, parent=parent)
