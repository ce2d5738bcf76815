"""The calibration's forward model: residuals of each scan and their derivative in log c1.

Parameter ``theta = ln c1``; the material is homogeneous neo-Hookean with a fixed
Poisson ratio, so the bulk modulus scales with c1. Derivatives use the converged
tangent (direct sensitivity): ``K du/dtheta = -dR/dtheta``, one factorisation per scan.
With ``reference_state="unload"`` the stress-free geometry ``X = x_ref - u0`` depends on
theta too; its sensitivity solves the linearised unloading equation
``(K0 - D0) du0 = -R0_theta`` (``D0`` the residual's shape derivative), one more
factorisation.

Where a strongly sagging reference scan admits no stress-free mesh with straight
elements (slivers at the clamped rim pass through zero volume while gravity is removed:
the diagnosis in :mod:`fem.unload`), the same inverse problem is solved with curved
stress-free elements on the loaded mesh (``unload_method="spatial"``, Govindjee &
Mihalic 1998): the reference is then the loaded mesh carrying the compatible prestress
``F0`` (:mod:`fem.prestress`), postures are solved by :func:`fem.prestress.solve_prestressed`
and their derivatives by :func:`fem.prestress.solve_prestressed_sensitivity` with
``dF0/dtheta`` from :func:`fem.prestress.prestress_sensitivity`. ``reference_state=
"prestress"`` uses that formulation from the start; ``"unload"`` switches to it when the
straight-element Newton fails (``spatial_fallback``) and says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

import fem
from fem.discretize import Formulation
from fem.fields import gravity_vector, vertex_displacement_mm
from fem.prestress import (
    prestress_sensitivity,
    solve_prestressed_sensitivity,
)
from fem.sensitivity import state_sensitivity, stress_free_sensitivity, vertex_dofs
from fem.units import DEFAULT_DENSITY_KG_M3, STANDARD_GRAVITY_M_S2
from fem.unload import recover_stress_free

from .effects import EffectValues, effect_model, effect_support

__all__ = ["ForwardModel", "ReferenceRecoveryFailed", "ScanState"]

# Inverse Newton inside the loop: 10 load steps at most (a sagging scan on a coarse mesh
# can leave no valid stress-free state, where cut-backs would go on for many minutes).
_UNLOAD_NEWTON = fem.SolverOptions(max_steps=10)
# With springs in the support no other method takes over (the prestressed formulation has
# no springs; a diagnosis has no fixed-point fallback), so the inverse Newton gets more
# load steps. Measured on the quick null twin (seed 0, 14 mm, 165 degree bound) with the
# plate on 2557 Pa/mm springs: 10 steps stop at load factor 0.984 (53 s), 30 converge
# (74 s); on inclusions seed 1 at 1031 Pa/mm both stop at 0.63 (the smallest step).
_UNLOAD_NEWTON_SPRINGS = fem.SolverOptions(max_steps=30)
_RECOVERIES_KEPT = 32  # converged recoveries kept by (effects, theta) (a few MB each at most)
log = logging.getLogger(__name__)


class ReferenceRecoveryFailed(fem.ConvergenceError):
    """No stress-free reference was recovered at a c1 (the postures were never solved).

    Attributes
    ----------
    method : str or None
        The recovery that failed: ``"newton"`` (straight stress-free elements, the
        inverse Newton), ``"spatial"`` (curved ones) or ``"fixed-point"``; None where
        not said.
    """

    # (a default, so that a process pool's worker can pickle it: the attribute travels
    # in the exception's __dict__)
    def __init__(self, message: str, *, method: str | None = None) -> None:
        super().__init__(message)
        self.method = method


@dataclass
class ScanState:
    """Converged state of one posture at the current theta (reused as warm start).

    Attributes
    ----------
    state : numpy.ndarray, shape (n_dofs,)
        The solver's full unknown vector (:attr:`fem.Solution.state`: solver frame, SI;
        displacement from the stress-free nodes, or from the loaded reference mesh when
        the model is prestressed).
    positions_mm : numpy.ndarray, shape (n_nodes, 3)
        Deformed vertex positions, reference frame (the reference scan's LPS), mm.
    dpositions_mm : numpy.ndarray, shape (n_nodes, 3), or None
        ``d positions_mm / d theta``, mm per unit ``ln c1`` (reference frame), including
        the stress-free geometry's own derivative; None where no gradient was asked for.
    dstate : numpy.ndarray, shape (n_dofs,), or None
        ``d state / d theta`` (solver frame, SI per unit ``ln c1``); None without gradient.
    """

    state: np.ndarray
    positions_mm: np.ndarray  # deformed vertex positions, reference frame
    dpositions_mm: np.ndarray | None = None  # d positions / d theta
    dstate: np.ndarray | None = None  # d state / d theta


@dataclass
class ForwardModel:
    """Solves the postures of a calibration for a given ``theta = ln c1``.

    Parameters
    ----------
    mesh : TetMesh
        The reference scan's mesh (loaded geometry, reference frame, mm).
    gravity_ref : ndarray, shape (3,)
        Gravity of the reference scan (unit, reference frame).
    nu : float
        Poisson's ratio of the homogeneous material (dimensionless).
    density_kg_m3 : float
        Density of the homogeneous material, kg/m^3.
    reference_state : {"unload", "prestress", "shortcut"}
        ``unload``: stress-free mesh with straight elements (inverse Newton);
        ``prestress``: the loaded mesh with the compatible prestress of a stress-free
        state with curved elements (:mod:`fem.prestress`, ``inverse``); ``shortcut``:
        the loaded scan taken as stress-free.
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Finite element formulation (:func:`fem.discretize`).
    g_m_s2 : float
        Magnitude of gravity, m/s^2, for the reference recovery and every posture.
    unload_method : {"newton", "spatial", "fixed-point"}
        How the stress-free reference is recovered: the inverse Newton with straight
        elements, curved elements on the prestressed loaded mesh, or the fixed point.
        Set to ``"spatial"`` by ``reference_state="prestress"``, and changed by the
        fallbacks (logged); not used with ``"shortcut"``.
    spatial_fallback : bool
        ``unload``: when the inverse Newton fails, switch to the ``prestress``
        formulation for this and every later theta (logged; ``unload_method`` becomes
        ``"spatial"``). Not with springs in the support (effects).
    fixed_point_fallback : bool
        When the inverse Newton fails (and ``spatial_fallback`` does not apply), recover
        the reference by the (slow) fixed point instead of raising
        :class:`fem.ConvergenceError`.
    effects : EffectValues, optional
        Effects of the library (:mod:`calib.model.effects`) on a region-tagged mesh; they
        replace ``nu`` and ``density_kg_m3`` and set the support. None: homogeneous,
        clamped (the calibration's model). Change them with :meth:`set_effects`.
    rim_fold_said : bool
        Whether the warning on vertex tetrahedra inverted at the clamped rim has been said
        in full; later recoveries say theirs in one line (review AX: three paragraphs in
        one calibration). The calibration's check meshes take the calibration's.

    Attributes
    ----------
    solves : int
        FE solves so far: one per posture solve, plus the forward solves of every
        stress-free recovery (``ReferenceRecovery.iterations``).
    inverted_reference_elements : int
        Vertex tetrahedra with non-positive volume in the last recovered (or cached)
        stress-free mesh (:attr:`fem.unload.ReferenceRecovery.inverted_elements`); 0
        before any recovery.
    current_dX : numpy.ndarray, shape (n_nodes, 3), or None
        ``d stress-free vertex positions / d theta`` of the last :meth:`evaluate`, mm per
        unit ``ln c1`` (reference frame); zeros without a gradient, for ``"shortcut"`` and
        on the prestressed loaded mesh; None before any evaluation.
    """

    mesh: fem.TetMesh
    gravity_ref: np.ndarray
    nu: float = 0.499
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3
    reference_state: str = "unload"
    formulation: Formulation = "taylor-hood"
    g_m_s2: float = STANDARD_GRAVITY_M_S2
    unload_method: str = "newton"
    spatial_fallback: bool = False
    fixed_point_fallback: bool = True
    effects: EffectValues | None = None
    solves: int = 0
    inverted_reference_elements: int = 0
    _disc: fem.Discretization | None = None
    _X: np.ndarray | None = None
    _u0: np.ndarray | None = None
    _X_theta: float | None = None  # theta of a converged recovery held in _X
    current_dX: np.ndarray | None = None  # d stress-free nodes / d theta of the last evaluate
    _states: dict = field(default_factory=dict)
    # (effects, theta) -> (X, u0, inverted elements, prestress)
    _recovered: dict = field(default_factory=dict)
    _kept: set = field(default_factory=set)  # keys of _recovered never dropped (keep_recovery)
    _du0: tuple | None = None  # (theta, d u0 / d theta) of the last gradient
    _ps: object = None  # fem.prestress.Prestress of the last spatial recovery
    _dF0: tuple | None = None  # (theta, d F0 / d theta) of the last spatial gradient
    rim_fold_said: bool = False

    def __post_init__(self) -> None:
        if self.reference_state not in ("unload", "prestress", "shortcut"):
            raise ValueError(
                "reference state must be unload, prestress or shortcut, not "
                f"{self.reference_state!r}"
            )
        if self.reference_state == "prestress":
            self.unload_method = "spatial"
        self._disc = fem.discretize(self.mesh, self._support(), formulation=self.formulation)

    def _support(self):
        return fem.Clamped() if self.effects is None else effect_support(self.effects)

    def set_effects(self, effects: EffectValues | None) -> None:
        """Use other effect values (or None: homogeneous, clamped).

        Recovered references stay cached by effect values and theta (a diagnosis comes
        back to a candidate's fit); warm starts are kept unless the support changes. Where
        it changes, the next recovery starts from rest: the clamped rim's stress-free
        reference is not unique, and an inverse Newton started from the recovery of a
        plate on springs converged to another one (the quick null twin, seed 0: a stiff
        inclusion's print 0.068 mm mean against 0.073 from rest, its screen estimate 1.22
        against 0.86). Within one support the warm start does not change the recovery
        (from rest and from 0.67x to 1.5x c1 alike, to 1e-12 mm on that twin; tested).
        """
        old = self._support()
        self.effects = effects
        self._X_theta, self._du0, self._dF0 = None, None, None
        if self._support() != old:
            self._disc = fem.discretize(self.mesh, self._support(), formulation=self.formulation)
            self._states = {}
            self._u0 = None

    @property
    def discretization(self) -> fem.Discretization:
        """Discretization of the loaded reference mesh (its nodes as given)."""
        return self._disc

    @property
    def stress_free_nodes_mm(self) -> np.ndarray | None:
        """Stress-free vertex positions of the last recovery (mm), None before any."""
        return self._X

    @property
    def stress_free_theta(self) -> float | None:
        """``ln c1`` of :attr:`stress_free_nodes_mm` (with :attr:`effects`), None before any."""
        return self._X_theta

    @property
    def stress_free_state(self) -> np.ndarray | None:
        """Solver state of the reference posture on :attr:`stress_free_nodes_mm` (unload)."""
        return self._u0

    @property
    def prestress(self):
        """The :class:`fem.prestress.Prestress` of the last spatial recovery, or None."""
        return self._ps

    @property
    def prestressed(self) -> bool:
        """Whether postures are solved on the prestressed loaded mesh (``spatial``)."""
        return self.reference_state != "shortcut" and self.unload_method == "spatial"

    @property
    def state_nodes_mm(self) -> np.ndarray | None:
        """The nodes a posture's state displaces (positions are these plus displacement).

        The stress-free nodes, or the loaded mesh's when :attr:`prestressed`.
        """
        return self.mesh.nodes_mm if self.prestressed else self._X

    def model(self, theta: float, nodes_mm: np.ndarray | None = None) -> fem.Model:
        """The model at ``c1 = exp(theta)`` on the given nodes (homogeneous without effects)."""
        mesh = self.mesh if nodes_mm is None else self.mesh.with_nodes(nodes_mm)
        if self.effects is not None:
            return effect_model(mesh, float(np.exp(theta)), self.effects)
        mat = fem.NeoHookean(float(np.exp(theta)), nu=self.nu)
        return fem.Model.homogeneous(mesh, mat, density_kg_m3=self.density_kg_m3)

    def _load(self, g_dir: np.ndarray) -> tuple[np.ndarray, float]:
        if self.reference_state == "shortcut":
            from fem.unload import shortcut_gravity

            return shortcut_gravity(g_dir, self.gravity_ref, g_m_s2=self.g_m_s2)
        return np.asarray(g_dir, float), self.g_m_s2

    def _solve(self, theta, disc, g_dir, key, retry: bool = True):
        """One posture, warm-started from its last state; retried with small load steps.

        On ``disc`` (the stress-free mesh), or with the prestress of the last recovery
        on the loaded mesh when :attr:`prestressed`.
        """
        direction, mag = self._load(g_dir)
        model = self.model(theta, disc.mesh.nodes_mm)
        prev = self._states.get(key)
        out = fem.solve_posture(
            model,
            gravity=direction,
            g_m_s2=mag,
            disc=disc,
            prestress=self._ps if self.prestressed else None,
            x0=None if prev is None else prev.state,
            retry=retry,
        )
        if out.retried is not None:
            log.warning(
                "solve failed for %s at c1=%.1f Pa (%s); retried with small load steps",
                key,
                np.exp(theta),
                out.retried,
            )
        sol = out.solution
        self.solves += 1
        return model, sol, direction, mag

    def stress_free(self, theta: float) -> np.ndarray:
        """Stress-free vertex positions at theta (mm); the loaded scan for the shortcut.

        Raises
        ------
        ReferenceRecoveryFailed
            No stress-free reference at this theta (a :class:`fem.ConvergenceError`, told
            apart from a failed posture solve).
        """
        if self.reference_state == "shortcut":
            self._X = self.mesh.nodes_mm
            return self._X
        if theta == self._X_theta:  # recovered already (first estimate, final states)
            return self._X
        key = (self.effects, theta)
        if key in self._recovered:  # e.g. the calibrated c1 again after the profile
            self._recovered[key] = self._recovered.pop(key)  # the least recently used goes
            self._X, self._u0, self.inverted_reference_elements, self._ps = self._recovered[key]
            self._X_theta = theta
            return self._X
        try:
            rec = self._recover(theta)
        except fem.ConvergenceError as exc:
            raise ReferenceRecoveryFailed(str(exc), method=self.unload_method) from exc
        self._X, self._ps = rec.nodes_mm, rec.prestress
        # the warm start of the next recovery: the inverse's own unknown
        self._u0 = rec.prestress.inverse_state if rec.prestress is not None else rec.solution.state
        self._X_theta = theta
        self._recovered[key] = (self._X, self._u0, rec.inverted_elements, self._ps)
        for old in [k for k in self._recovered if k not in self._kept]:
            if len(self._recovered) <= _RECOVERIES_KEPT:
                break
            self._recovered.pop(old)
        if (
            rec.inverted_elements > 0
            and rec.inverted_elements != self.inverted_reference_elements
            and not self.prestressed
        ):
            # an inverted straight stress-free element keeps det F > 0 only with its loaded
            # quadratic element folded too (fem.unload's module notes): say so
            n = rec.inverted_elements
            what = f"{n} vertex tetrahedr{'on' if n == 1 else 'a'} inverted at the clamped rim"
            where = f"recovered reference at c1={np.exp(theta):.1f} Pa ({self.mesh.n_tets} tets)"
            if self.rim_fold_said:  # review AX: the same paragraph three times a run
                log.warning("%s: %s (as said above)", where, what)
            else:
                log.warning(
                    "%s: %s, and %s loaded quadratic element%s folded with %s (the model is "
                    "wrong there, locally: the surface next to the back plate; "
                    "--reference-state prestress has curved stress-free elements and none)",
                    where, what, "its" if n == 1 else "their", "" if n == 1 else "s",
                    "it" if n == 1 else "them",
                )  # fmt: skip
            self.rim_fold_said = True
        self.inverted_reference_elements = rec.inverted_elements
        return self._X

    def _recover(self, theta: float):
        """The stress-free reference at ``theta`` by the current method (its fallbacks)."""
        start = self.model(theta)
        kw = {"gravity": self.gravity_ref, "g_m_s2": self.g_m_s2, "formulation": self.formulation}
        rec = None
        if self.unload_method == "newton":
            try:
                # a bounded effort: past it another method takes over (and says so)
                rec = self._inverse_newton(start, theta, kw)
            except fem.ConvergenceError as exc:
                if self.spatial_fallback and self._disc.spring is None:
                    log.warning(
                        "inverse Newton failed at c1=%.1f Pa (%s); solving the reference with "
                        "curved stress-free elements (prestressed loaded mesh) from now on",
                        np.exp(theta),
                        exc,
                    )
                    self.use_spatial()
                elif self.fixed_point_fallback:
                    log.warning(
                        "inverse Newton failed at c1=%.1f Pa (%s); using the fixed point "
                        "from now on",
                        np.exp(theta),
                        exc,
                    )
                    self.unload_method = "fixed-point"
                else:
                    raise
        if rec is None and self.unload_method == "spatial":
            rec = recover_stress_free(start, method="spatial", x0_state=self._u0, **kw)
        if rec is None:
            # tight: the gradient assumes X + u0 = x_ref; 1e-3 mm already costs ~1 % of it
            rec = recover_stress_free(
                start, method="fixed-point", x0_nodes_mm=self._X, tol_mm=1e-5, max_iter=20, **kw
            )
        self.solves += rec.iterations
        if not rec.converged:  # a geometry off the scan would bias every residual: fail
            raise fem.ConvergenceError(
                f"stress-free reference missed its tolerance at c1 = {np.exp(theta):.1f} Pa: "
                f"the loaded geometry is {rec.max_error_mm:.3g} mm off the scan after "
                f"{rec.iterations} solves"
            )
        return rec

    def _inverse_newton(self, start: fem.Model, theta: float, kw: dict):
        """Inverse Newton from the last recovery's state; once more from rest if that fails.

        The last recovery may be of other effect values (a diagnosis' other candidate, a
        Poisson's ratio far from this one), a start outside this one's basin.
        """
        opts = _UNLOAD_NEWTON if self._disc.spring is None else _UNLOAD_NEWTON_SPRINGS
        try:
            return recover_stress_free(start, x0_state=self._u0, options=opts, **kw)
        except fem.ConvergenceError as exc:
            if self._u0 is None:
                raise
            log.warning(
                "inverse Newton from the last recovered state failed at c1=%.1f Pa (%s); "
                "once more from rest",
                np.exp(theta),
                exc,
            )
        return recover_stress_free(start, x0_state=None, options=opts, **kw)

    def keep_recovery(self, theta: float) -> None:
        """Never drop the recovery at ``theta`` (the calibrated c1) from the kept ones.

        After the fit, the interval's and the profile's recoveries at other c1 would push
        it out; solving it again from another start can fail where the fit's got through.
        """
        self._kept.add((self.effects, theta))

    def use_spatial(self) -> None:
        """Switch to the prestressed formulation: recoveries and warm starts start over."""
        self.unload_method = "spatial"
        self._u0, self._X_theta, self._recovered, self._du0 = None, None, {}, None
        self._kept = set()
        self._states = {}

    def evaluate(
        self, theta: float, gravities: dict, *, gradient: bool = True, retry: bool = True
    ) -> dict:
        """Solve every posture at ``theta``; positions and (optionally) their derivatives.

        Parameters
        ----------
        theta : float
            ``ln c1`` with c1 in Pa.
        gravities : dict of str to ndarray (3,)
            Gravity direction of each posture to solve, reference frame.
        gradient : bool
        retry : bool
            Retry a failed solve with small load steps (slow); off where a failure is
            merely recorded (likelihood-profile points).

        Returns
        -------
        dict of str to ScanState
        """
        X = self.stress_free(theta)
        if self.prestressed:
            return self._evaluate_prestressed(theta, gravities, gradient, retry)
        disc = self._disc.with_nodes(X)
        model_at = self._model_at(disc)
        dX, dX_state = np.zeros_like(X), None
        if gradient and self.reference_state == "unload":
            if self._du0 is None or self._du0[0] != theta:  # one factorisation per theta
                g0 = gravity_vector(self.gravity_ref, self.g_m_s2)
                self._du0 = (theta, stress_free_sensitivity(disc, model_at, theta, self._u0, g0))
            du0 = self._du0[1]
            dX = -vertex_displacement_mm(disc, du0)  # X = x_ref - u0
            dX_state = np.zeros(disc.n_dofs)
            v = vertex_dofs(disc)
            dX_state[v] = -du0[v]
        out = {}
        for name, g in gravities.items():
            _, sol, direction, mag = self._solve(theta, disc, g, name, retry)
            st = ScanState(sol.state, X + sol.displacement_mm)
            if gradient:
                g_vec = gravity_vector(direction, mag)
                du = state_sensitivity(disc, model_at, theta, sol.state, g_vec, dX_state=dX_state)
                st.dpositions_mm = dX + vertex_displacement_mm(disc, du)
                st.dstate = du
            out[name] = st
            self._states[name] = st
        self.current_dX = dX
        return out

    def _evaluate_prestressed(self, theta, gravities, gradient: bool, retry: bool) -> dict:
        """:meth:`evaluate` on the loaded mesh with the prestress of the last recovery."""
        disc, ps = self._disc, self._ps
        model_at = self._model_at(disc)
        if gradient and (self._dF0 is None or self._dF0[0] != theta):  # once per theta
            self._dF0 = (theta, prestress_sensitivity(model_at, theta, ps, disc=disc))
        out = {}
        for name, g in gravities.items():
            _, sol, direction, mag = self._solve(theta, disc, g, name, retry)
            st = ScanState(sol.state, self.mesh.nodes_mm + sol.displacement_mm)
            if gradient:
                kw = {"gravity": direction, "g_m_s2": mag, "disc": disc}
                du = solve_prestressed_sensitivity(model_at, theta, ps, self._dF0[1], sol, **kw)
                st.dpositions_mm = vertex_displacement_mm(disc, du)
                st.dstate = du
            out[name] = st
            self._states[name] = st
        self.current_dX = np.zeros_like(self.mesh.nodes_mm)  # the loaded mesh does not move
        return out

    def _model_at(self, disc: fem.Discretization):
        """``theta -> Model`` on the nodes of ``disc`` (for :mod:`fem.sensitivity`)."""
        return lambda t: self.model(t, disc.mesh.nodes_mm)
