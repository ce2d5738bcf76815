"""The FE model of the phantom: reference mesh, forward model, residuals, effect library."""

from .effects import EFFECTS, EffectError, TruthEffects, parse_effects, truth_model
from .forward import ForwardModel, ScanState
from .reference import reference_mesh
from .residuals import OBJECTIVES, Residuals, SimulatedSurface, scan_residuals

__all__ = [
    "EFFECTS",
    "OBJECTIVES",
    "EffectError",
    "ForwardModel",
    "Residuals",
    "ScanState",
    "SimulatedSurface",
    "TruthEffects",
    "parse_effects",
    "reference_mesh",
    "scan_residuals",
    "truth_model",
]
