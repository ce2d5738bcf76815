"""The one place where units are converted.

Public boundaries of the toolkit use millimetres for lengths, pascals for stresses,
kg/m^3 for densities and m/s^2 for accelerations. The solver works in SI internally.
The two physical constants the toolkit assumes where a caller gives none are here too.
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_DENSITY_KG_M3",
    "MM_PER_M",
    "M_PER_MM",
    "STANDARD_GRAVITY_M_S2",
    "m_to_mm",
    "mm_to_m",
]

M_PER_MM = 1.0e-3
MM_PER_M = 1.0e3
STANDARD_GRAVITY_M_S2 = 9.81
#: The density of a body whose density is not given (water's; ``session.toml``'s default
#: ``phantom.density_kg_m3``).
DEFAULT_DENSITY_KG_M3 = 1000.0


def mm_to_m(value):
    """Convert a length (scalar or array) from millimetres to metres."""
    return value * M_PER_MM


def m_to_mm(value):
    """Convert a length (scalar or array) from metres to millimetres."""
    return value * MM_PER_M
