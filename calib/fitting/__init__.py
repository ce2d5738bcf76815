"""Fitting c1: options, objective, optimiser, uncertainty, mesh check, likelihood profile.

:func:`fit` is pure: measurements in, a frozen :class:`Calibration` out, no files.
"""

from .options import CalibrationOptions, OptionsError
from .pipeline import fit
from .result import SCHEMA_VERSION, Calibration

__all__ = ["SCHEMA_VERSION", "Calibration", "CalibrationOptions", "OptionsError", "fit"]
