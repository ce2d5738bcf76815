"""Torch surrogates of the calibrated FE model: gravity (and c1) to displacements.

Reads sweep stores (:func:`load_sweep`, format in the README and ``calib.sweep.store``)
and never imports ``calib``. Two surrogates: ours (:func:`fit_reduced_kernel`, a POD
basis and a kernel over the load ``rho g / c1``) and the dissertation's two MLPs
(:func:`fit_dissertation_mlps`), both exported as TorchScript (:func:`save_surrogate`)
and queried with input checks (:meth:`Surrogate.predict`)::

    import nn
    data = nn.load_sweep("sweep")
    sur = nn.Surrogate.from_fit(nn.fit_reduced_kernel(data), data)
    nn.save_surrogate(sur, "model.pt")
    pred = nn.load_surrogate("model.pt").predict([0.0, 0.0, 9.81])   # prone, phantom frame

torch loads on first use of a name that needs it, so ``import nn`` stays light.
"""

from __future__ import annotations

import importlib

__all__ = [
    "ExtrapolationWarning",
    "FarExtrapolationWarning",
    "MeshMismatchError",
    "Prediction",
    "StoreFormatError",
    "Surrogate",
    "SurrogateFileError",
    "SweepData",
    "evaluate",
    "fit_dissertation_mlps",
    "fit_reduced_kernel",
    "load_surrogate",
    "load_sweep",
    "save_surrogate",
    "select_device",
]

_LAZY = {
    "StoreFormatError": "nn.data",
    "SweepData": "nn.data",
    "load_sweep": "nn.data",
    "fit_reduced_kernel": "nn.reduced",
    "fit_dissertation_mlps": "nn.baseline",
    "select_device": "nn.device",
    "ExtrapolationWarning": "nn.surrogate",
    "FarExtrapolationWarning": "nn.surrogate",
    "MeshMismatchError": "nn.surrogate",
    "Prediction": "nn.surrogate",
    "Surrogate": "nn.surrogate",
    "SurrogateFileError": "nn.surrogate",
    "evaluate": "nn.surrogate",
    "load_surrogate": "nn.surrogate",
    "save_surrogate": "nn.surrogate",
}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'nn' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
