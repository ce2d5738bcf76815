"""The ``phantom-calib`` command line (typer commands only; the work is in workflows)."""

from . import diagnose as _diagnose  # noqa: F401 - registers the diagnose command
from . import sweep as _sweep  # noqa: F401 - registers the sweep and surrogate commands
from . import view as _view  # noqa: F401 - registers the view command
from .app import app, fail, main

__all__ = ["app", "fail", "main"]
