"""Stress-free reference recovery ("unloading") and the dissertation's shortcut.

A scan shows the phantom deformed by gravity ``g0``. The stress-free geometry ``X``
is the one that deforms into the measured geometry ``x_m`` under ``g0``. Reversing
gravity is not the inverse in nonlinear elasticity. Three methods find ``X``:

- ``"newton"`` (default): inverse elastostatics in displacement form on straight-sided
  stress-free elements. The unknown is the displacement ``u`` with ``X = x_m - u`` at the
  vertices; Newton's method on ``R(u; x_m - u) = 0`` uses the consistent Jacobian
  ``K - D`` (``D`` the residual's derivative in the reference geometry,
  :mod:`fem.shape_derivative`), with line search and load stepping; the loaded geometry
  matches ``x_m`` at the vertices by construction (its P2 edge nodes are free). The
  springs of an elastic or sliding support carry ``-k u`` per unit stress-free area, as
  in the forward solve.
- ``"fixed-point"``: the backward-displacement iteration ``X <- X - a (X + u(X) - x_m)``
  with Aitken's adaptive relaxation ``a``, each forward solve warm-started from the last.
  The same discrete equations as ``newton``; they agree to their tolerance.
- ``"spatial"``: inverse elastostatics in spatial form (Govindjee & Mihalic 1996, 1998;
  :mod:`fem.prestress`, ``method="inverse"``): the loaded mesh is the computational
  domain and the stress-free elements are curved (isoparametric P2), so only
  ``det(I - grad_x U) > 0`` at quadrature points is required. Another discrete problem:
  its answers differ from ``newton``'s by the discretisation error (0.7 % of a 31 mm
  posture change on the 16 mm twin mesh, below), and its postures are solved with
  :func:`fem.prestress.solve_prestressed` (``ReferenceRecovery.prestress``), not on
  ``nodes_mm``.

Diagnosis of ``newton``'s failures (issue 17; the calibration's model meshes of the
quick twin's reference scan, ``calib.model.reference.reference_mesh``, c1 = 420 Pa,
nu = 0.499, clamped back; ``benchmarks/bench_reference.py`` for the table):

- *Which elements.* Thin elements of the loaded mesh on the clamped back at the rim.
  TetGen's radius-edge bound does not remove slivers: every twin mesh of 8-16 mm has
  17-122 elements with a dihedral angle below 5 degrees, 3-19 of them touching the
  back. The stress-free vertex tetrahedra that invert are such slivers (loaded min.
  dihedral 1.1 degrees on the 12 mm mesh, median 2.9-3.5 degrees on 14 and 16 mm), all
  touching the back. The rim itself is not degenerate: the wedge between back and
  surface is >= 63 degrees everywhere (median 97-136).
- *At which load factor.* On the 12 mm ``--effect none`` mesh (4729 tets, 23.7 mm sag)
  the worst sliver's stress-free/loaded volume ratio is 0.60, 0.19 and -0.28 at load
  factors 0.2, 0.4 and 0.6: its straight tetrahedron passes through zero volume, where
  the affine reference map is singular (shape gradients ~ 1/volume) and beyond which the
  P2 loaded element must fold to keep ``det F > 0``. Newton's steps then shrink (0.25 to
  0.006) and it stops at load factor 0.66 after 82 iterations (the calibration's 10
  load steps; 310 s on a loaded 2-core machine), 0.79 after 177 (60 steps), a second,
  non-sliver element inverting at 0.77. Where the first load step is large enough to
  jump the singular configuration, it converges with inverted vertex tetrahedra (14 and
  16 mm: 2 and 4).
- *Not the tangent.* The Jacobi-scaled 1-norm condition of ``K - D`` stays
  8.2e5, 8.1e5, 8.0e5, 7.9e5 at load factors 0, 0.2, 0.4, 0.6: no limit point, so
  arc-length continuation would not help; the obstacle is the singular reference map.
- *Why not monotone in the mesh size.* Whether a sliver sits on the clamped rim and how
  the load steps meet it is the mesher's draw, not resolution.
- *Why there.* The inverse displacement is steep at the clamped rim: on the 12 mm mesh
  a node 0.6 mm above the back moves 1.4 mm while its element's other nodes are clamped
  (the loaded surface leaves the back at 130-136 degrees on the sagging side, an
  overhang the unloading must rotate back). A straight element that thin cannot follow.
  (Also seen: the ingested back set reaches 0.4-1.1 mm beyond the truth's clamped
  footprint, and the back plane lies 0.16-0.20 mm below the truth's: segmentation, not
  the cause, but it clamps the first sub-millimetre of that overhang.)
- *The remedy.* Keep the loaded mesh (valid by construction) as the domain and let the
  stress-free elements curve: ``"spatial"`` converges on the same 12 mm mesh in 30
  iterations and 3 load steps (118 s), round trip 4e-7 mm (the curved stress-free mesh
  loaded by ``g0`` from zero). The same rim shear shows there as extreme local volume
  ratios: ``det F0`` lies in [0.73, 1.48] at 98 % of the quadrature points but reaches
  0.2 and 489 in 46 small elements at the back (centroids 0.5 mm above it, median): a
  curved element may nearly collapse at a quadrature point, a straight one may not.

References
----------
Govindjee, S. & Mihalic, P. A. (1996). Computational methods for inverse finite
elastostatics. *CMAME* 136, 47-57.
Govindjee, S. & Mihalic, P. A. (1998). Computational methods for inverse deformations in
quasi-incompressible finite elasticity. *IJNME* 43, 821-838.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .assemble import assemble, external_force, scatter
from .discretize import Formulation, discretize, spring_shape_derivative
from .model import Model
from .prestress import (
    Prestress,
    compute_prestress,
    isoparametric_discretization,
    stress_free_node_positions_mm,
)
from .shape_derivative import geometry_matrices
from .solver import (
    ConvergenceError,
    Solution,
    SolverOptions,
    _newton,
    _Stats,
    gravity_vector,
    merit,
    merit_weights,
    newton_step,
    solve,
    vertex_displacement_mm,
)
from .units import STANDARD_GRAVITY_M_S2

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
    inverted_elements : int
        Elements whose recovered vertex tetrahedron has non-positive volume (see the
        module docstring). With ``spatial`` the stress-free elements are curved and these
        straight vertex tetrahedra are for information only.
    method : str
        The method that produced it.
    prestress : Prestress or None
        ``spatial``: the compatible prestress of the loaded mesh
        (:func:`fem.prestress.compute_prestress` with ``method="inverse"``). Its
        stress-free mesh is curved: solve postures with
        :func:`fem.prestress.solve_prestressed` on the loaded mesh, not with
        :func:`fem.solve` on ``nodes_mm``.
    """

    nodes_mm: np.ndarray
    converged: bool
    iterations: int
    max_error_mm: float
    history_mm: tuple[float, ...]
    solution: Solution
    inverted_elements: int = 0
    method: str = "newton"
    prestress: Prestress | None = None


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
    g_m_s2: float = STANDARD_GRAVITY_M_S2,
    formulation: Formulation = "taylor-hood",
    tol_mm: float = 0.01,
    max_iter: int = 60,
    options: SolverOptions | None = None,
    x0_nodes_mm: np.ndarray | None = None,
    x0_state: np.ndarray | None = None,
    method: Literal["newton", "fixed-point", "spatial"] = "newton",
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
    method : {"newton", "fixed-point", "spatial"}
        See the module docstring. With ``newton`` and ``spatial`` a warm start is
        ``x0_state`` alone (``ReferenceRecovery.solution.state`` of the same method).

    Returns
    -------
    ReferenceRecovery

    Raises
    ------
    ConvergenceError
        ``newton`` or ``spatial`` could not apply the full load within
        ``options.max_steps`` load steps; the message and the exception's
        ``load_factor`` attribute say how far it got.
    """
    if method == "spatial":
        return _spatial(model, gravity, g_m_s2, formulation, options, x0_state)
    if method == "newton":
        return _inverse_newton(model, gravity, g_m_s2, formulation, options, x0_state, tol_mm)
    if method != "fixed-point":
        raise ValueError(
            f"unknown recovery method {method!r}; choose newton, fixed-point or spatial"
        )
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
            return _recovery(model, X, True, it, err, tuple(history), sol)
        alpha = _aitken(alpha, r_old, r)
        X, r_old = X - alpha * r, r
    return _recovery(model, X, False, max_iter, err, tuple(history), sol)


def _recovery(model: Model, X: np.ndarray, *args) -> ReferenceRecovery:
    inverted = int((model.mesh.with_nodes(X).volumes_mm3() <= 0).sum())
    if inverted:  # reported in the result; callers decide how loudly (calib warns once)
        log.info("recovered reference: %d inverted elements (mesh too coarse near the "
                 "clamped rim?)", inverted)  # fmt: skip
    return ReferenceRecovery(X, *args, inverted_elements=inverted)


def shortcut_gravity(
    gravity_scan, gravity_ref, *, g_m_s2: float = STANDARD_GRAVITY_M_S2
) -> tuple[np.ndarray, float]:
    """The dissertation's shortcut load: the loaded scan taken as stress-free, load ``g - g0``.

    Parameters
    ----------
    gravity_scan, gravity_ref : array_like, shape (3,)
        Gravity directions of the scan's posture and of the reference scan, in the ref
        frame (the model's); any non-zero length (normalised here).
    g_m_s2 : float
        Gravitational acceleration magnitude, m/s^2, of both postures.

    Returns
    -------
    direction : ndarray, shape (3,)
        Unit direction of ``g_m_s2 * (g - g0)`` in the ref frame (``g``, the scan's
        direction, when the two postures coincide).
    magnitude_m_s2 : float
        Its magnitude, m/s^2 (0 when the postures coincide). Pass both to
        :func:`fem.solve` (``gravity=direction, g_m_s2=magnitude``).
    """
    g = np.asarray(gravity_scan, float) / np.linalg.norm(gravity_scan)
    g0 = np.asarray(gravity_ref, float) / np.linalg.norm(gravity_ref)
    d = (g - g0) * g_m_s2
    n = float(np.linalg.norm(d))
    return (d / n if n > 0 else g), n


class _Inverse:
    """``R(u; x_m - u) = 0`` at load factor ``lam``.

    It has the interface of the forward solver's problems, so the same Newton
    iteration and line search serve both.
    """

    def __init__(self, model: Model, disc0, g_vec, opts: SolverOptions):
        self.model, self.disc0, self.g, self.opts = model, disc0, g_vec, opts
        self.x_m = disc0.mesh.nodes_mm
        self.free = disc0.free
        self.stats = _Stats()
        self.f_scale = max(np.linalg.norm(external_force(disc0, model, g_vec)), 1e-300)
        self.v_scale = float(disc0.weights.sum())
        self.u_free = disc0.free < 3 * disc0.n_scalar_u
        self.factor = None

    def disc(self, u):
        X = self.x_m - vertex_displacement_mm(self.disc0, u)
        return self.disc0.with_nodes(X)

    def residual(self, u, lam, tangent: bool):
        d = self.disc(u)
        mdl = self.model.with_mesh(d.mesh)
        st = assemble(d, mdl, u, tangent=tangent)
        if st.min_J <= 0:
            return None, None
        r = scatter(d, st.vectors) - lam * external_force(d, mdl, self.g)
        if d.spring is not None:
            # springs of an elastic or sliding support carry -k u, u the inverse's own
            # unknown, per unit area of the stress-free face X = x_m - u (``with_nodes``
            # assembles them there, as for a forward solve)
            r += d.spring @ u
        M = None
        if tangent:
            M = d.pattern.matrix(st.matrices - geometry_matrices(d, mdl, u, lam * self.g))
            if d.spring is not None:
                f = self.free
                M = M + (d.spring - spring_shape_derivative(d, u))[f][:, f]
        return r[self.free], M

    def merit(self, r) -> float:
        return merit(r, self.u_free, self.f_scale, self.v_scale, self.disc0.mixed)

    @property
    def scale(self) -> np.ndarray:
        """Row weights of the free residual whose norm is :meth:`merit`."""
        return merit_weights(self.u_free, self.f_scale, self.v_scale)

    def linear_solve(self, M, r, m: float):
        """Newton step; the inverse problem's tangent is not symmetric."""
        return newton_step(self, M, r, m, symmetric=False)


def _inverse_newton(model, gravity, g_m_s2, formulation, options, x0_state, tol_mm):
    opts = options or SolverOptions()
    disc0 = discretize(model.mesh, model.support, formulation=formulation)
    prob = _Inverse(model, disc0, gravity_vector(gravity, g_m_s2), opts)
    u, lam, dlam, steps = np.zeros(disc0.n_dofs), 0.0, opts.initial_step, 0
    if x0_state is not None:
        warm = _newton(prob, np.asarray(x0_state, float).copy(), 1.0)
        if warm is not None:
            u, lam, steps = warm, 1.0, 1
    attempts = 0
    while lam < 1.0 and dlam >= opts.min_step and attempts < opts.max_steps:
        attempts += 1
        trial = min(1.0, lam + dlam)
        new = _newton(prob, u, trial)
        if new is None:
            dlam *= 0.25
            continue
        u, lam, steps = new, trial, steps + 1
        dlam = min(2.0 * dlam, 1.0 - lam) if lam < 1.0 else dlam
    converged = lam >= 1.0
    if not converged:
        err = ConvergenceError(
            f"stress-free reference not recovered: inverse Newton stopped at load factor "
            f"{lam:.3g} after {prob.stats.newton} iterations in {attempts} load steps "
            f"(limit {opts.max_steps}); method='spatial' does not need straight stress-free "
            "elements"
        )
        err.load_factor, err.iterations = lam, prob.stats.newton
        raise err
    X = prob.x_m - vertex_displacement_mm(disc0, u)
    sol = solve(model.with_mesh(model.mesh.with_nodes(X)), gravity=gravity, g_m_s2=g_m_s2,
                disc=disc0.with_nodes(X), options=opts, x0=u)  # fmt: skip
    err = float(np.linalg.norm(X + sol.displacement_mm - prob.x_m, axis=1).max())
    if err > tol_mm:
        log.warning("reference recovery: loaded geometry off by %.3g mm (tol %.3g)", err, tol_mm)
    return _recovery(model, X, err <= tol_mm, prob.stats.newton, err, (err,), sol)


def _spatial(model, gravity, g_m_s2, formulation, options, x0_state) -> ReferenceRecovery:
    """The spatial (isoparametric) inverse of :mod:`fem.prestress`, as a recovery."""
    opts = options or SolverOptions()
    disc0 = discretize(model.mesh, model.support, formulation=formulation)
    ps = compute_prestress(model, gravity=gravity, g_m_s2=g_m_s2, method="inverse",
                           disc=disc0, options=opts, x0_state=x0_state)  # fmt: skip
    X_dofs = stress_free_node_positions_mm(disc0, ps)
    iso = isoparametric_discretization(disc0, X_dofs)
    # the curved stress-free mesh under g0, warm-started at the recovered state: a
    # converged check of the recovered state in the forward solver's own assembly
    sol = solve(model.with_mesh(iso.mesh), gravity=gravity, g_m_s2=g_m_s2, disc=iso,
                options=opts, x0=ps.inverse_state)  # fmt: skip
    rec = _recovery(model, ps.stress_free_nodes_mm, True, ps.newton_iterations,
                    ps.residual_displacement_mm, (ps.residual_displacement_mm,), sol)  # fmt: skip
    return replace(rec, method="spatial", prestress=ps)
