"""Torch surrogates of the FE model (gravity direction to displacement).

Planned in a later issue; this package is importable so that the layout is fixed.
"""

__all__: list[str] = []
