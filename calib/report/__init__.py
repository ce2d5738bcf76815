"""Reports of results: error maps, tables, the validation report."""

from .maps import save_figure, surface_error_figure, write_error_ply
from .tables import format_calibration

__all__ = ["format_calibration", "save_figure", "surface_error_figure", "write_error_ply"]
