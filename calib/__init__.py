"""Calibrate a breast phantom's hyperelastic material from multi-posture MRI.

The Python API for notebooks and scripts (the ``phantom-calib`` command line calls the
same functions)::

    import calib
    calib.synthesize("twin", preset="quick", seed=0)       # a digital twin scan set
    calib.ingest("twin/scans", "work")                    # surfaces, landmarks, frames
    result = calib.calibrate("twin/scans", "work")         # fit c1, write WORK/
    work = calib.load_work("work")                        # everything in WORK/, with plots
    calib.diagnose("work")                                # the missing-effect diagnosis
    calib.simulate("work/calibration/reference_mesh.vtu", "deformed.vtu",
                   c1_pa=work.c1_pa, gravity=(0, 1, 0))    # one posture, any mesh
    calib.gravity_sweep("work", "sweep.zarr", plan="sphere:48")   # ``phantom-calib sweep``
    calib.train_surrogate("sweep.zarr", "model.pt")       # then calib.load_surrogate

and, without files: ``calib.fit(measurements, options) -> Calibration`` and
``calib.evaluate(calibration) -> {scan: ScanEvaluation}`` and
``calib.check_postures(calibration, evaluations)`` (does every scan alone ask for the
same c1?). Subpackages, one job each (lowest first): ``stats``, ``data``, ``model``,
``fitting``, ``discrepancy``, ``sweep``, ``report``, ``twin``, ``viewer``, ``workflows``,
``cli``. Heavy dependencies load on first use, so ``import calib`` stays fast.
"""

from __future__ import annotations

import importlib
import importlib.util

__all__ = [
    "Calibration",
    "CalibrationOptions",
    "DiagnosisOptions",
    "SimulateOptions",
    "SweepOptions",
    "calibrate",
    "check_postures",
    "diagnose",
    "evaluate",
    "fit",
    "gravity_sweep",
    "ingest",
    "load_measurements",
    "load_session",
    "load_surrogate",
    "load_work",
    "simulate",
    "synthesize",
    "train_surrogate",
    "validate",
]

# public name -> (module, attribute); imported on first access (PEP 562)
_LAZY = {
    "Calibration": ("calib.fitting", "Calibration"),
    "CalibrationOptions": ("calib.fitting", "CalibrationOptions"),
    "DiagnosisOptions": ("calib.discrepancy", "DiagnosisOptions"),
    "SimulateOptions": ("calib.workflows.simulate", "SimulateOptions"),
    "SweepOptions": ("calib.workflows.sweep", "SweepOptions"),
    "fit": ("calib.fitting", "fit"),
    "evaluate": ("calib.evaluation", "evaluate"),
    "check_postures": ("calib.evaluation", "check_postures"),
    "load_measurements": ("calib.data", "load_measurements"),
    "load_session": ("calib.data", "load_session"),
    "synthesize": ("calib.twin", "synthesize"),
    "ingest": ("calib.api", "ingest"),
    "calibrate": ("calib.api", "calibrate"),
    "validate": ("calib.api", "validate"),
    "load_work": ("calib.api", "load_work"),
    "diagnose": ("calib.api", "diagnose"),
    "simulate": ("calib.api", "simulate"),
    "gravity_sweep": ("calib.api", "gravity_sweep"),
    "train_surrogate": ("calib.api", "train_surrogate"),
    "load_surrogate": ("calib.api", "load_surrogate"),
}


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    # a subpackage or module, imported on first access (``calib.sweep.progress_lines``
    # raised AttributeError after ``import calib`` alone); private names are not looked up
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'calib' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
