"""Error maps of a calibrated model: figures (matplotlib) and a PLY with per-vertex error.

Every report draws a scan's error the same way (:func:`surface_error_figure`): the
measured surface, opaque and shaded, seen from the front and from the side in the
phantom frame (``R_ref_from_phantom``), coloured by the signed distance of each measured
point to the model surface along the model's outward normal (+: the scan lies outside
the model), on a diverging scale symmetric about zero whose top the caller may share
between scans. Functions return figures, callers decide where they go.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write

__all__ = [
    "draw_surface_views",
    "face_error_mm",
    "map_figure",
    "save_figure",
    "shared_error_scale_mm",
    "signed_colorbar",
    "signed_error_mapper",
    "surface_error_figure",
    "surface_in_phantom_frame",
    "write_error_ply",
]

#: Colour map of signed errors: blue (scan inside the model), white, red (outside); a
#: diverging map readable with red-green colour-vision deficiency.
SIGNED_CMAP = "RdBu_r"
#: What the sign of a surface error means (every signed map's colour bar says it).
SIGN_NOTE = "+: the scan lies outside the model"
#: The two views of a surface map: (title, elevation, azimuth), phantom frame.
VIEWS = (("front (from the apex)", 90.0, -90.0), ("side (lateral, from -y)", 0.0, -90.0))


def face_error_mm(
    error_mm: np.ndarray, faces: np.ndarray, scored: np.ndarray, *, signed: bool = False
) -> np.ndarray:
    """The error of each face: the mean over its scored vertices, (f,) mm.

    A face at the rim holds back-plate vertices, whose error is not measured (0 in the
    per-vertex arrays); averaging them in would pale the rim. Every face needs a scored
    vertex.

    Parameters
    ----------
    error_mm : ndarray, shape (n,)
        Signed distance of each vertex to the model (mm).
    faces : ndarray, shape (f, 3)
    scored : ndarray of bool, shape (n,)
        :attr:`calib.data.measurements.ScanMeasurement.scored`.
    signed : bool
        Average the signed distances; else their magnitudes (|error|).
    """
    w = np.asarray(scored, bool)[faces]
    e = np.asarray(error_mm, float)
    e = e if signed else np.abs(e)
    return (e[faces] * w).sum(axis=1) / w.sum(axis=1)


def surface_in_phantom_frame(scan, R_ref_from_phantom: np.ndarray):
    """A scan's surface ready to draw: phantom-frame vertices, scored faces, shading.

    Parameters
    ----------
    scan : ScanMeasurement
        Its ``vertices_mm`` in the reference frame, ``faces`` and ``scored``.
    R_ref_from_phantom : ndarray, shape (3, 3)

    Returns
    -------
    vertices_mm : ndarray, shape (n, 3)
        Phantom frame (``R_ref_from_phantom^T x_ref``).
    faces : ndarray, shape (f, 3)
        The faces holding a scored vertex (the back plate's left out).
    shade : ndarray, shape (f,)
        Two-sided Lambertian factor in [0.55, 1]: the shape stays readable under colour.
    """
    v = np.asarray(scan.vertices_mm, float) @ np.asarray(R_ref_from_phantom, float)
    faces = scan.faces[scan.scored[scan.faces].any(axis=1)]
    tri = v[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    return v, faces, 0.55 + 0.45 * np.abs(n @ light)


def signed_error_mapper(top_mm: float):
    """The colour scale of signed errors: ``[-top_mm, top_mm]`` on :data:`SIGNED_CMAP`."""
    from matplotlib import cm, colormaps, colors

    return cm.ScalarMappable(norm=colors.Normalize(-top_mm, top_mm), cmap=colormaps[SIGNED_CMAP])


def draw_surface_views(fig, grid: tuple[int, int, int], surface, face_values, mapper, title: str):
    """Draw a shaded surface in :data:`VIEWS` into two subplots of ``fig``.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    grid : (rows, columns, first)
        The subplot grid and the index of the first of two adjacent panels.
    surface : tuple
        :func:`surface_in_phantom_frame`'s result.
    face_values : ndarray, shape (f,)
        The value of each face, coloured by ``mapper``.
    mapper : matplotlib.cm.ScalarMappable
    title : str
        Above each panel, before the view's name.

    Returns
    -------
    list of Axes3D
    """
    from matplotlib.ticker import MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    v, faces, shade = surface
    lo, hi = v.min(axis=0), v.max(axis=0)
    hi = np.maximum(hi, lo + 1.0)  # a flat patch keeps a drawable box
    axes = []
    for k, (view, elev, azim) in enumerate(VIEWS):
        ax = fig.add_subplot(grid[0], grid[1], grid[2] + k, projection="3d")
        rgba = mapper.to_rgba(face_values)
        rgba[:, :3] *= shade[:, None]
        ax.add_collection3d(Poly3DCollection(v[faces], facecolors=rgba, edgecolors="none"))
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
        # the frame on every axis (review AX: four frames across the reports), the labels
        # clear of the tick labels (mplot3d's default pad puts a face-on axis' on them)
        for axis, name in ((ax.xaxis, "x"), (ax.yaxis, "y"), (ax.zaxis, "z")):
            axis.set_label_text(f"{name} (mm, phantom frame)")
            axis.labelpad = 10
        ax.set_title(f"{_panel_title(title, fig, grid[1])}\n{view}" if title else view, fontsize=10)
        ax.set_box_aspect(hi - lo)
        ax.view_init(elev=elev, azim=azim)
        hidden = ax.zaxis if elev == 90.0 else ax.yaxis  # the axis along the line of sight
        hidden.set_ticks([])  # review BY, F9: its tick lines combed into the next label
        hidden.label.set_visible(False)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            if axis is not hidden:  # review BY, F9: x labels ran together at 20 mm steps
                axis.set_major_locator(MaxNLocator(5))
        axes.append(ax)
    return axes


def map_figure(width_in: float, height_in: float):
    """An empty figure for surface maps: constrained layout with a margin at the sides.

    mplot3d's axis labels lie outside what the constrained layout measures: without the
    margin the left panel's y label is cut at the figure's edge.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    fig.get_layout_engine().set(rect=(0.03, 0.0, 0.95, 1.0))
    return fig


def signed_colorbar(
    fig,
    mapper,
    axes,
    *,
    saturated: bool,
    shrink: float = 0.7,
    label: str = f"distance of the scan to the model surface (mm)\n{SIGN_NOTE}",
):
    """The colour bar of a signed map, its sign said, extended where the scale saturates."""
    return fig.colorbar(
        mapper, ax=axes, shrink=shrink, label=label, extend="both" if saturated else "neither"
    )


def surface_error_figure(
    scan, error_mm: np.ndarray, R_ref_from_phantom: np.ndarray, title: str, *, vmax=None
):
    """The measured surface coloured by its signed distance to the model, two views.

    Parameters
    ----------
    scan : ScanMeasurement
        The measured scan (``vertices_mm`` in the reference frame, ``faces``, ``scored``).
    error_mm : ndarray, shape (n_vertices,)
        Signed distance of every measured vertex to the model surface
        (:attr:`calib.evaluation.ScanMetrics.vertex_error_mm`; + outside the model).
    R_ref_from_phantom : ndarray, shape (3, 3)
        The phantom frame the views are drawn in.
    title : str
    vmax : float, optional
        Top of the symmetric colour scale (mm); default the scan's 99th percentile of
        |error| (share it between scans to compare them: :func:`shared_error_scale_mm`).

    Returns
    -------
    matplotlib.figure.Figure
    """
    surface = surface_in_phantom_frame(scan, R_ref_from_phantom)
    e = face_error_mm(error_mm, surface[1], scan.scored, signed=True)
    top = vmax or max(float(np.percentile(np.abs(e), 99)) if e.size else 0.0, 1e-3)
    mapper = signed_error_mapper(top)
    fig = map_figure(10, 4.8)
    axes = draw_surface_views(fig, (1, 2, 1), surface, e, mapper, "")
    signed_colorbar(fig, mapper, axes, saturated=bool(np.any(np.abs(e) > top)))
    fig.suptitle(wrapped_title(title, fig))
    return fig


def _wrapped(title: str, width_in: float, size_pt: float) -> str:
    """``title`` in lines that fit ``width_in`` inches at ``size_pt`` (~0.6 em a character)."""
    import textwrap

    chars = max(20, int(width_in * 72.0 / (0.6 * size_pt)))
    return "\n".join(textwrap.fill(line, chars) for line in title.splitlines() or [""])


def _panel_title(title: str, fig, columns: int, size_pt: float = 10.0) -> str:
    """``title`` in lines that fit one of ``columns`` panels across ``fig`` at ``size_pt``.

    The diagnosis maps' change row (~95 characters a panel) ran into its neighbour's.
    """
    return _wrapped(title, fig.get_figwidth() / columns, size_pt)


def wrapped_title(title: str, fig) -> str:
    """``title`` in lines that fit the figure's width at a figure title's font size.

    The validation maps' titles (scan, role, posture, mean error, frame, scale: ~130
    characters) ran past both edges of a 10-inch figure, cut at its borders.
    """
    from matplotlib import rcParams
    from matplotlib.font_manager import FontProperties

    size_pt = FontProperties(size=rcParams["figure.titlesize"]).get_size_in_points()
    return _wrapped(title, fig.get_figwidth(), size_pt)


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


def save_figure(fig, path: Path, *, dpi: int = 110) -> Path:
    """Save a figure atomically (the format from the suffix)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return atomic_write(path, lambda p: fig.savefig(p, dpi=dpi, format=fmt))
