"""Statistics of surface residuals: noise model, intervals, misfit and effect tests.

Pure numpy/scipy (no FE, no files). ``noise``: variogram and kernel fit
(:class:`NoiseModel`), covariances, whitening; ``intervals``: parameter intervals with
measured coverage; ``profile``: a noise level by height band; ``scores``: the misfit
test and effect screening; ``coverage``: cheap linear models on phantom-like geometry
for the studies in ``benchmarks/bench_coverage.py``.

Errors (all ``ValueError`` subclasses): :class:`ConsistencyError`, :class:`NoiseModelError`,
:class:`IntervalError`, :class:`ScreeningError`, :class:`SampleError`,
:class:`UnknownKernelError`.
"""

from .consistency import ConsistencyError
from .intervals import IntervalError, ParameterInterval, parameter_intervals, sandwich_covariance
from .kernels import KERNELS, UnknownKernelError, correlation
from .noise import NoiseFit, NoiseModel, NoiseModelError, Variogram, estimate_noise, whitener
from .profile import HeightProfile, height_profile
from .sample import SampleError, SurfaceSample
from .scores import EffectScreening, ModelFit, ScreeningError, misfit_test, screen_effects

__all__ = [
    "ConsistencyError",
    "KERNELS",
    "EffectScreening",
    "HeightProfile",
    "IntervalError",
    "ModelFit",
    "NoiseFit",
    "NoiseModel",
    "NoiseModelError",
    "ParameterInterval",
    "SampleError",
    "ScreeningError",
    "SurfaceSample",
    "UnknownKernelError",
    "Variogram",
    "correlation",
    "estimate_noise",
    "height_profile",
    "misfit_test",
    "parameter_intervals",
    "sandwich_covariance",
    "screen_effects",
    "whitener",
]
