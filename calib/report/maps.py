"""Error maps of a calibrated model: figures (matplotlib) and a PLY with per-vertex error.

Figures use a perceptual colour map (cividis) for the error magnitude, whose
colour bar is in millimetres; functions return figures, callers decide where they go.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write

__all__ = ["error_map_figure", "face_error_mm", "save_figure", "write_error_ply"]

#: Colour map of error magnitudes (perceptually uniform, colour-vision-deficiency safe).
ERROR_CMAP = "cividis"


def face_error_mm(error_mm: np.ndarray, faces: np.ndarray, scored: np.ndarray) -> np.ndarray:
    """|error| of each face: the mean over its scored vertices, (f,) mm.

    A face at the rim holds back-plate vertices, whose error is not measured (0 in the
    per-vertex arrays); averaging them in would pale the rim. Every face needs a scored
    vertex.

    Parameters
    ----------
    error_mm : ndarray, shape (n,)
    faces : ndarray, shape (f, 3)
    scored : ndarray of bool, shape (n,)
        :attr:`calib.data.measurements.ScanMeasurement.scored`.
    """
    w = np.asarray(scored, bool)[faces]
    return (np.abs(np.asarray(error_mm, float))[faces] * w).sum(axis=1) / w.sum(axis=1)


def write_error_ply(path: Path, vertices_mm: np.ndarray, faces: np.ndarray, error_mm) -> Path:
    """Binary PLY of a surface with a per-vertex ``error_mm`` property (MeshLab, ParaView)."""
    import imaging

    surface = imaging.SurfaceMesh(np.asarray(vertices_mm, float), np.asarray(faces), None)
    return imaging.write_ply(path, surface, vertex_scalars={"error_mm": error_mm})


def shared_error_scale_mm(errors_mm) -> float:
    """The top of one colour scale for several scans' error maps (mm).

    The largest per-scan 99th percentile of |error|: no scan's map saturates over more
    than 1 % of its points, and the maps can be compared.

    Parameters
    ----------
    errors_mm : iterable of ndarray
        Each scan's errors on its scored points (mm).

    Returns
    -------
    float
        The top of the shared scale, mm (1e-3 at least).
    """
    tops = [float(np.percentile(np.abs(np.asarray(e, float)), 99)) for e in errors_mm if len(e)]
    return max([*tops, 1e-3])


def error_map_figure(points_mm: np.ndarray, error_mm: np.ndarray, title: str, *, vmax=None):
    """Two orthogonal views of the measured surface points coloured by |error| (mm).

    Parameters
    ----------
    points_mm : ndarray, shape (n, 3)
        Measured surface points (reference frame).
    error_mm : ndarray, shape (n,)
        Their distance to the simulated surface.
    title : str
    vmax : float, optional
        Top of the colour scale (mm); default the 99th percentile (shared scales let
        maps be compared).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    e = np.abs(np.asarray(error_mm, float))
    fig = Figure(figsize=(10, 4.5), layout="constrained")
    axes = fig.subplots(1, 2)
    top = vmax if vmax is not None else max(float(np.percentile(e, 99)), 1e-3)
    for ax, (i, j), lab in zip(axes, ((0, 1), (0, 2)), (("x", "y"), ("x", "z")), strict=True):
        order = np.argsort(points_mm[:, 3 - i - j])  # nearer points drawn last
        sc = ax.scatter(points_mm[order, i], points_mm[order, j], c=e[order], s=4,
                        cmap=ERROR_CMAP, vmin=0.0, vmax=top)  # fmt: skip
        ax.set_aspect("equal")
        ax.set_xlabel(f"{lab[0]} (mm, reference LPS)")
        ax.set_ylabel(f"{lab[1]} (mm)")
    fig.colorbar(sc, ax=axes, label="distance to the simulated surface (mm)")
    fig.suptitle(title)
    return fig


def save_figure(fig, path: Path, *, dpi: int = 110) -> Path:
    """Save a figure atomically (the format from the suffix)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return atomic_write(path, lambda p: fig.savefig(p, dpi=dpi, format=fmt))
