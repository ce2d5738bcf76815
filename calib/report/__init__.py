"""Reports of results: error maps, tables, the validation report."""

from .maps import error_map_figure, save_figure, write_error_ply
from .tables import format_calibration

__all__ = ["error_map_figure", "format_calibration", "save_figure", "write_error_ply"]
