"""The words of the options that take one of a fixed set.

Each is the Python API's ``Literal`` type and the command line's choice (typer lists the
words in ``--help`` and refuses any other before a file is read): one definition each, in
a module that imports nothing, so that ``phantom-calib --help`` loads none of the modules
that use them (review BH). The calibration's own (``Objective``, ``ReferenceState``) are
:mod:`calib.fitting.options`'s, the elements' ``fem.discretize.Formulation`` and the
training device's ``nn.device.Device``.
"""

from __future__ import annotations

from typing import Literal

__all__ = [
    "BackSupport",
    "MeshErrorTreatment",
    "NoiseProfile",
    "PredictFrame",
    "PresetName",
    "SurrogateKind",
]

#: ``simulate --bc``: how the back plate holds the body: ``clamped`` (every back node
#: fixed) or ``sliding`` (frictionless: the normal displacement fixed, and the rim held in
#: the plane, :class:`fem.Sliding`).
BackSupport = Literal["clamped", "sliding"]
#: ``synth --preset``: the keys of :data:`calib.twin.PRESETS`.
PresetName = Literal["quick", "dissertation"]
#: ``diagnose --noise-profile``: one noise level at every height, or by height above the
#: back plate.
NoiseProfile = Literal["flat", "plate"]
#: ``diagnose --mesh-error``: whether the tests also condition on one direction of the
#: model mesh's own discretisation error.
MeshErrorTreatment = Literal["ignored", "absorbed"]
#: ``surrogate train --kind``: the reduced basis with a kernel, or the dissertation's MLPs.
SurrogateKind = Literal["ours", "dissertation"]
#: ``surrogate predict --frame``: the gravity vector in the phantom (posture-angle) frame
#: or in the model's (calibration.json's ``gravity_ref``).
PredictFrame = Literal["phantom", "ref"]
