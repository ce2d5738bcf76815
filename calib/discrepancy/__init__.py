"""The missing-effect diagnosis (``phantom-calib diagnose``): pure logic, no files.

Where the calibrated model and the scans disagree (:mod:`.localise`), which effect of the
library could explain it (:mod:`.fields`, :mod:`.screen`), its confirmation by a full FE
refit (:mod:`.refit`), the verdict (:mod:`.diagnose`) and, for what was not found, the
sizes the scans would show in the effects' own parameters (:mod:`.limits`). Writing is
:mod:`calib.workflows.diagnose`'s.
"""

from .diagnose import DEFAULT_EFFECTS, Candidate, Diagnosis, DiagnosisOptions, diagnose
from .problem import DiagnosisError, Problem, build_problem

__all__ = [
    "DEFAULT_EFFECTS",
    "Candidate",
    "Diagnosis",
    "DiagnosisError",
    "DiagnosisOptions",
    "Problem",
    "build_problem",
    "diagnose",
]
