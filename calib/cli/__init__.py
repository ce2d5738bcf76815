"""The ``phantom-calib`` command line (typer commands only; the work is in workflows)."""

from .app import app, fail, main

__all__ = ["app", "fail", "main"]
