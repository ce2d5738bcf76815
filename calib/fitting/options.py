"""Options of a calibration (``phantom-calib calibrate``), checked before any work."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal, get_args

from fem.discretize import Formulation
from fem.meshing import check_max_dihedral_deg

from ..model.residuals import OBJECTIVES

__all__ = [
    "MESH_SIZE_RANGE_MM",
    "CalibrationOptions",
    "OptionsError",
    "check_mesh_check_ratio",
    "mesh_check_ratios",
    "parse_mesh_check",
]

Objective = Literal["surface", "nipple", "landmarks"]
ReferenceState = Literal["unload", "prestress", "shortcut"]


class OptionsError(ValueError):
    """An option of a calibration out of range or of the wrong kind.

    The message names the option (its command-line flag) and what was expected.
    """


#: Element edge lengths a model mesh may take, mm (calibrate's and diagnose's alike).
MESH_SIZE_RANGE_MM = (1.0, 50.0)


def check_mesh_check_ratio(ratio: float) -> None:
    """Raise :class:`OptionsError` unless ``ratio`` lies in [0.5, 0.9] or [1.1, 3].

    A finer check mesh or a coarser one (their sizes over the model mesh's).
    """
    if not (0.5 <= ratio <= 0.9 or 1.1 <= ratio <= 3.0):
        raise OptionsError(
            f"mesh_check_ratio (--mesh-check) must lie in [0.5, 0.9] or [1.1, 3], got {ratio}"
        )


def mesh_check_ratios(ratio: float | tuple[float, ...]) -> tuple[float, ...]:
    """The check meshes' size ratios as a tuple, checked (``()`` for no mesh check).

    One ratio (a two-mesh check with the assumed order) or two reciprocal ones, ``r > 1``
    and ``1/r`` (a three-mesh check with the observed order,
    :func:`calib.fitting.meshcheck.grid_convergence`).
    """
    ratios = tuple(float(q) for q in (ratio if isinstance(ratio, tuple | list) else (ratio,)))
    if ratios in ((), (0.0,)):
        return ()
    if len(ratios) > 2:
        raise OptionsError(f"a mesh check takes one or two ratios, got {len(ratios)}: {ratios}")
    for q in ratios:
        check_mesh_check_ratio(q)
    if len(ratios) == 2:
        hi, lo = max(ratios), min(ratios)
        if not (hi > 1.0 > lo and abs(hi * lo - 1.0) < 0.02):
            raise OptionsError(
                "two mesh check ratios must be reciprocal, a coarser r and a finer 1/r "
                f"(e.g. 1.4,0.714), got {ratios}"
            )
    return ratios


def parse_mesh_check(text: str) -> float | tuple[float, ...]:
    """``"1.4"`` -> 1.4, ``"1.4,0.714"`` -> (1.4, 0.714), ``"0"`` -> 0.0 (the CLI's form)."""
    try:
        values = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise OptionsError(
            f"--mesh-check takes a ratio or two (e.g. 1.4 or 1.4,0.714), got {text!r}"
        ) from None
    mesh_check_ratios(values)
    return values[0] if len(values) == 1 else values


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of a calibration (see ``phantom-calib calibrate --help``).

    Attributes
    ----------
    objective : {"surface", "nipple", "landmarks"}
        The residuals fitted (:mod:`calib.model.residuals`).
    reference_state : {"unload", "prestress", "shortcut"}
        ``unload``: the stress-free reference recovered by inverse elastostatics (straight
        elements; where the mesh admits none, curved ones, as ``prestress``).
        ``prestress``: the loaded reference mesh carrying the prestress of a stress-free
        state with curved elements (:mod:`fem.prestress`). ``shortcut``: the
        dissertation's (the loaded reference scan taken as stress-free, load ``g - g0``).
    mesh_size_mm : float
        Element edge length of the model mesh.
    mesh_retry_mm : tuple of float
        Sizes tried in turn when no stress-free reference exists on a mesh (each size is
        tried once, ``mesh_size_mm`` first).
    mesh_max_dihedral_deg : float or None
        TetGen's optimisation bound on the largest dihedral angle of the model mesh
        (:func:`fem.meshing.tetrahedralize`); None keeps the ``tetgen`` package's (177
        degrees). 165 removes most slivers, where the straight stress-free recovery
        fails first (docs/calibration-evidence.md, "Slivers and the stress-free recovery").
    formulation : str
        FE formulation (:data:`fem.FORMULATIONS`).
    nu : float
        Poisson's ratio of the model, in (0, 0.5).
    max_points : int
        Measured surface points per scan (a seeded subsample).
    c1_guess_pa : float
        Starting value of the first estimate.
    max_iterations : int
        Gauss-Newton iterations (with a line search) of the search for c1.
    profile_points : int
        Points of the likelihood profile over c1 (0 or 1: none).
    mesh_check_ratio : float or tuple of float
        Element-size ratio of the check mesh (0: no mesh check); two reciprocal ratios
        (``(1.4, 1/1.4)``): a coarser and a finer check mesh, the observed order.
    seed : int
        Seed of the surface subsample.

    Raises
    ------
    OptionsError
        An option of the wrong kind or out of range, as the options are made (a
        ``ValueError``; the message names the option).
    """

    objective: Objective = "surface"
    reference_state: ReferenceState = "unload"
    mesh_size_mm: float = 12.0
    mesh_retry_mm: tuple[float, ...] = (14.0, 16.0)  # when the reference cannot be unloaded
    mesh_max_dihedral_deg: float | None = None
    formulation: Formulation = "taylor-hood"
    nu: float = 0.499
    max_points: int = 3000
    c1_guess_pa: float = 500.0
    max_iterations: int = 30
    profile_points: int = 5
    mesh_check_ratio: float | tuple[float, ...] = 1.4
    seed: int = 0

    def __post_init__(self) -> None:
        # review AI: a wrong type or formulation failed only inside the fit, after ingest
        least_of = {"max_points": 10, "max_iterations": 1, "profile_points": 0, "seed": 0}
        for name, least in least_of.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise OptionsError(f"{name} must be an integer, got {value!r}")
            if value < least:
                raise OptionsError(f"{name} must be >= {least}, got {value}")
        if isinstance(self.mesh_retry_mm, list):
            object.__setattr__(self, "mesh_retry_mm", tuple(self.mesh_retry_mm))
        if not isinstance(self.mesh_retry_mm, tuple):
            raise OptionsError(
                f"mesh_retry_mm must be a tuple of sizes in mm, got {self.mesh_retry_mm!r}"
            )
        numbers_of = [
            ("mesh_size_mm", self.mesh_size_mm),
            ("nu", self.nu),
            ("c1_guess_pa", self.c1_guess_pa),
            *(("mesh_retry_mm", v) for v in self.mesh_retry_mm),
        ]
        for name, value in numbers_of:
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise OptionsError(f"{name} must be a number, got {value!r}")
        from fem import FORMULATIONS

        if self.formulation not in FORMULATIONS:
            raise OptionsError(
                f"formulation must be one of {', '.join(FORMULATIONS)}, got {self.formulation!r}"
            )
        if self.objective not in OBJECTIVES:
            raise OptionsError(
                f"objective (--objective) must be one of {', '.join(OBJECTIVES)}, got "
                f"{self.objective!r}"
            )
        if self.reference_state not in get_args(ReferenceState):
            raise OptionsError(
                "reference_state (--reference-state) must be unload, prestress or shortcut, "
                f"not {self.reference_state!r}"
            )
        lo, hi = MESH_SIZE_RANGE_MM
        for size in (self.mesh_size_mm, *self.mesh_retry_mm):
            if not lo <= size <= hi:
                raise OptionsError(
                    f"mesh_size_mm (--mesh-size) must lie in [{lo:g}, {hi:g}] mm, got {size}"
                )
        try:
            check_max_dihedral_deg(
                self.mesh_max_dihedral_deg, "mesh_max_dihedral_deg (--mesh-max-dihedral)"
            )
        except ValueError as exc:  # fem's words, as one of the options' errors
            raise OptionsError(str(exc)) from None
        if not 0.0 < self.nu < 0.5:
            raise OptionsError(f"nu (--nu), Poisson's ratio, must lie in (0, 0.5), got {self.nu}")
        if not (self.c1_guess_pa > 0 and math.isfinite(self.c1_guess_pa)):
            raise OptionsError(
                f"c1_guess_pa (--c1-guess) must be a positive c1 in Pa, got {self.c1_guess_pa}"
            )
        if isinstance(self.mesh_check_ratio, list):
            object.__setattr__(self, "mesh_check_ratio", tuple(self.mesh_check_ratio))
        mesh_check_ratios(self.mesh_check_ratio)
