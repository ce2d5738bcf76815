"""The validation report: tables (Markdown, HTML) and figures of a :class:`Validation`.

Figures (matplotlib, returned to the caller):

- :func:`error_surface_figure`: the measured surface shaded by its signed distance to
  the model (red: the scan outside the model), seen from the front and from the side of
  the phantom, on a colour scale shared by every scan (mm);
- :func:`error_by_displacement_figure`: the dissertation's kind of histogram (its Figs.
  3.18-3.21): the share of surface points per error bin, split by how far the surface
  moved from the reference posture;
- :func:`outline_figure`: the measured body outline (the segmentation mask's boundary)
  and the model's outline in three orthogonal slices of the scan through the tumour.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..validation import BAND_POINTS, ScanValidation, Validation
from .maps import shared_error_scale_mm, surface_error_figure
from .tables import POSTURE_NOTE

__all__ = [
    "error_by_displacement_figure",
    "error_surface_figure",
    "outline_figure",
    "validation_error_scale_mm",
    "validation_html",
    "validation_markdown",
]


def validation_error_scale_mm(v: Validation, scans: dict) -> float:
    """The colour-scale top (mm) that validate's error maps share.

    :func:`calib.report.maps.shared_error_scale_mm` over every scan validated, the
    calibration scans included (review AK: the validation scans' alone left a calibration
    scan's map saturated over 12 %).

    Parameters
    ----------
    v : Validation
    scans : dict of str to ScanMeasurement
        The work folder's measured scans (their ``scored`` vertices).
    """
    return shared_error_scale_mm(
        np.asarray(sv.metrics.vertex_error_mm)[scans[sv.name].scored] for sv in v.scans.values()
    )


def displacement_bins_mm(displacement_mm: np.ndarray) -> tuple[float, ...]:
    """Edges ``(0, s, 2 s, 3 s, inf)`` of the displacement bins of one scan (mm).

    ``s`` is a quarter of the 99th percentile of the finite displacements, rounded to
    1, 2 or 5 times a power of ten: one scale fits a 2 mm tilt and a 35 mm turn alike.

    Parameters
    ----------
    displacement_mm : ndarray, shape (n,)
        How far the surface moved near each measured vertex (mm); NaN where unknown.

    Returns
    -------
    tuple of float
        Increasing edges; ``(0, inf)`` when nothing moved or nothing is known.
    """
    d = np.asarray(displacement_mm, float)
    d = d[np.isfinite(d)]
    top = float(np.percentile(d, 99)) if d.size else 0.0
    if not top > 0.0:
        return (0.0, np.inf)
    raw = top / 4.0
    power = 10.0 ** np.floor(np.log10(raw))
    m = raw / power
    step = power * (1.0 if m < 1.5 else 2.0 if m < 3.5 else 5.0 if m < 7.5 else 10.0)
    return (0.0, step, 2 * step, 3 * step, np.inf)


def error_surface_figure(
    sv: ScanValidation, scan, R_ref_from_phantom: np.ndarray, *, vmax: float | None = None
):
    """The measured surface coloured by its signed error (mm), front and side, phantom frame.

    Parameters
    ----------
    sv : ScanValidation
    scan : ScanMeasurement
        The measured scan (its surface, reference frame).
    R_ref_from_phantom : ndarray, shape (3, 3)
    vmax : float, optional
        Top of the symmetric colour scale (mm); share it between scans to compare them.
    """
    mean = sv.surface["fiducial"]["mean"].value
    # "(fiducial frame)" read as the axes' frame (review AX): the registration named
    return surface_error_figure(
        scan,
        sv.metrics.vertex_error_mm,
        R_ref_from_phantom,
        f"{sv.name} ({sv.role}, posture {sv.posture_label}): surface error, mean |e| "
        f"{mean:.2f} mm (fiducial registration"
        + ("; colour scale shared by the scans)" if vmax is not None else ")"),
        vmax=vmax,
    )


def error_by_displacement_figure(scans: list[ScanValidation]):
    """Share of surface points per |error| bin, by displacement-magnitude bin, one row a scan."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 2.8 * max(len(scans), 1) + 0.6), layout="constrained")
    axes = fig.subplots(max(len(scans), 1), 1, squeeze=False)[:, 0]

    # the measured points: off the back plate (0 there, not compared)
    offs = [sv.metrics.vertex_error_mm != 0.0 for sv in scans]
    errs = [np.abs(sv.metrics.vertex_error_mm[off]) for sv, off in zip(scans, offs, strict=True)]
    # one error axis for every scan (review AX: 0-1.75 mm in one panel, 0-0.8 in the next)
    top = max([float(np.percentile(e, 99.5)) for e in errs if e.size] + [0.1])
    bins = np.linspace(0.0, top, 21)
    for ax, sv, off, err in zip(axes, scans, offs, errs, strict=False):
        if not err.size:  # review BA: every error 0 (nothing scored) divided by zero
            ax.set_title(f"{sv.name} ({sv.role}): no measured point off the back plate")
            continue
        disp = sv.displacement_mm[off]
        edges = displacement_bins_mm(disp)
        stacks, labels, colours = [], [], []
        for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            sel = (disp >= a) & (disp < b)
            if sel.any():
                stacks.append(err[sel])
                colours.append(_bin_colour(i, len(edges) - 1))
                labels.append(
                    f"moved {a:g}–{b:g} mm ({100 * sel.mean():.0f} %)"
                    if np.isfinite(b)
                    else f"moved > {a:g} mm ({100 * sel.mean():.0f} %)"
                    if a > 0
                    else "all points"
                )
        if not stacks:  # no displacement saved: one histogram
            stacks, labels, colours = [err], ["all points"], ["0.5"]
        weights = [np.full(len(s), 100.0 / len(err)) for s in stacks]
        # review BY, F8: points beyond the shared axis were dropped without a mark (the
        # right lateral's 2.13 mm beyond 1.45): the last bin holds them, and says so
        stacks = [np.minimum(s, top) for s in stacks]
        beyond = float(np.mean(err > top)) * 100.0
        ax.hist(stacks, bins=bins, weights=weights, stacked=True, label=labels, color=colours)
        ax.set_xlim(0.0, top)
        ax.set_xlabel(
            "|distance| of the measured surface to the model (mm, either side)"
            + (f"; the last bin holds the {beyond:.1f} % beyond {top:.2f} mm" if beyond else "")
        )
        ax.set_ylabel("surface points (%)")
        ax.set_title(
            f"{sv.name} ({sv.role}, {sv.posture_label}): mean "
            f"{err.mean():.2f} mm, p95 {np.percentile(err, 95):.2f} mm"
        )
        # review AX: "moved" said from where (the model surface, from the reference scan)
        ax.legend(
            fontsize=8, title="model surface moved\nfrom the reference scan", title_fontsize=8
        )
    return fig


def _bin_colour(i: int, n: int):
    from matplotlib import colormaps

    return colormaps["viridis"](0.15 + 0.7 * i / max(n - 1, 1))


def _slice_segments(vertices_index: np.ndarray, faces: np.ndarray, axis: int, at: float):
    """Segments (k, 2, 3) where a triangle surface crosses the index plane ``axis = at``."""
    d = vertices_index[:, axis] - at
    tri_d = d[faces]
    crosses = (tri_d.min(axis=1) < 0) & (tri_d.max(axis=1) > 0)
    segs = []
    for f, td in zip(faces[crosses], tri_d[crosses], strict=True):
        pts = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            if (td[i] < 0) != (td[j] < 0):
                t = td[i] / (td[i] - td[j])
                pts.append(vertices_index[f[i]] + t * (vertices_index[f[j]] - vertices_index[f[i]]))
        if len(pts) == 2:
            segs.append(pts)
    return np.asarray(segs).reshape(-1, 2, 3)


def outline_figure(
    sv: ScanValidation,
    mask,
    model_lps_mm: np.ndarray,
    model_faces: np.ndarray,
    centre_lps_mm: np.ndarray,
    *,
    centre: str = "the tumour",
    model_tumour_lps_mm: np.ndarray | None = None,
):
    """Measured (mask boundary) and model outlines in three slices of the scan.

    Parameters
    ----------
    sv : ScanValidation
    mask : imaging.Volume
        The scan's body mask (``WORK/scans/<name>/mask.nii.gz``).
    model_lps_mm : ndarray, shape (n, 3)
        The deformed model's vertices in the scan's LPS frame.
    model_faces : ndarray, shape (f, 3)
        The model's boundary triangles.
    centre_lps_mm : ndarray, shape (3,)
        Where the three slices cross (the measured tumour, else the nipple).
    centre : str
        What that point is, for the title and the legend: marked in every slice.
    model_tumour_lps_mm : ndarray, shape (3,), optional
        The simulated tumour centre (scan LPS), marked in every slice where given.
    """
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    A = np.asarray(mask.affine_lps_from_index, float)
    inv = np.linalg.inv(A)
    to_index = lambda p: np.asarray(p, float) @ inv[:3, :3].T + inv[:3, 3]  # noqa: E731
    vi = to_index(model_lps_mm)
    c = to_index(np.asarray(centre_lps_mm, float)[None])[0]
    mt = None
    if model_tumour_lps_mm is not None:
        mt = to_index(np.asarray(model_tumour_lps_mm, float)[None])[0]
    arr = np.asarray(mask.array) > 0
    sp = np.asarray(mask.spacing_mm, float)
    fig = Figure(figsize=(12, 5.0), layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, axis in zip(axes, (2, 1, 0), strict=True):
        k = int(np.clip(round(c[axis]), 0, arr.shape[axis] - 1))
        sl = np.take(arr, k, axis=axis).astype(float)
        rest = [a for a in range(3) if a != axis]
        extent = (
            -0.5 * sp[rest[0]],
            (sl.shape[0] - 0.5) * sp[rest[0]],
            -0.5 * sp[rest[1]],
            (sl.shape[1] - 0.5) * sp[rest[1]],
        )
        ax.imshow(sl.T, origin="lower", cmap="gray", extent=extent, alpha=0.35)
        ax.contour(
            np.arange(sl.shape[0]) * sp[rest[0]],
            np.arange(sl.shape[1]) * sp[rest[1]],
            sl.T,
            levels=[0.5],
            colors=["#1f77b4"],
            linewidths=1.2,
        )
        segs = _slice_segments(vi, model_faces, axis, float(k))
        if len(segs):
            xy = segs[:, :, rest] * sp[rest]
            ax.add_collection(LineCollection(xy, colors="#d62728", linewidths=1.2))
        # review AX: the title named the tumour and no slice showed it; the centre lies in
        # every slice, the simulated tumour projected onto it
        ax.plot(*(c[rest] * sp[rest]), "+", color="#1f77b4", ms=11, mew=1.6)
        if mt is not None:
            ax.plot(*(mt[rest] * sp[rest]), "x", color="#d62728", ms=8, mew=1.6)
        # equal scales by the data limits: the boxes keep the layout's sizes, so the labels
        # stay clear of the legend below (an adjusted box moved the first panel's)
        ax.set_aspect("equal", adjustable="datalim")
        # review BY, F12: the slice by its index only
        ax.set_title(
            f"slice {'ijk'[axis]} = {k} of the scan ({k * sp[axis]:.1f} mm along {'ijk'[axis]})"
        )
        # voxel index times spacing along the volume's axes, not patient directions
        ax.set_xlabel(f"along {'ijk'[rest[0]]} (mm)")
        ax.set_ylabel(f"along {'ijk'[rest[1]]} (mm)")
    from matplotlib.patches import Patch

    axes[0].plot([], [], color="#1f77b4", label="measured (segmentation)")
    axes[0].plot(
        [],
        [],
        color="#d62728",
        label="model at the calibrated c1\n(its face on the back plate not drawn)",
    )
    axes[0].plot([], [], "+", color="#1f77b4", ms=9, mew=1.6, label=f"{centre} (measured)")
    if mt is not None:
        axes[0].plot([], [], "x", color="#d62728", ms=7, mew=1.6, label="simulated tumour "
                     "(projected on each slice)")  # fmt: skip
    # below the panels: inside the first one it hid part of the outlines it explains
    handles = axes[0].get_legend_handles_labels()[0]
    # review BY, F12: the light and dark grey were in no legend
    handles.insert(0, Patch(facecolor="white", edgecolor="0.6", label="segmented body (light)"))
    fig.legend(handles=handles, loc="outside lower center", ncols=5, fontsize=8)
    fig.suptitle(f"{sv.name}: measured and simulated outlines through {centre} (scan frame)")
    return fig


def _icp_fit(icp: dict) -> str:
    """The ICP's fitness (share of points within its last gate), and whether it settled.

    Review BP, P8: with errors beyond the 1 mm final gate (a larger, softer or misfitting
    body) the ICP frame's figures rest on few points, and nothing said so.
    """
    fitness = icp.get("fitness")
    if fitness is None:
        return "–"
    return f"{fitness:.2f}" + ("" if icp.get("settled", True) else " (not settled)")


def _row(sv: ScanValidation) -> list[str]:
    fid, icp = sv.surface["fiducial"], sv.surface["icp"]
    t = sv.tumour or {}
    reg = sv.registration

    def num(x):
        return "–" if x is None else f"{x:.2f}"

    ref = sv.reference or {}
    dis = []
    if ref.get("surface_mean_mm") is not None:
        dis.append(f"surface {ref['surface_mean_mm']:.2f} ± {ref['surface_sd_mm']:.2f}")
    if ref.get("nipple_mm") is not None:
        dis.append(f"nipple {ref['nipple_mm']:.2f}")
    if ref.get("tumour_mm") is not None:  # review AG: 3.647, where the command says 3.65
        dis.append(f"tumour {ref['tumour_mm']:.2f}")
    return [
        sv.name,
        sv.role,
        sv.posture_label,
        f"{fid['mean'].text()} ± {fid['sd'].value:.2f}",
        fid["median"].text(),
        fid["p95"].text(),
        fid["max"].text(),
        f"{icp['mean'].text()} ± {icp['sd'].value:.2f}",
        _icp_fit(sv.metrics.icp),
        sv.nipple["fiducial"].text(),
        sv.nipple["icp"].text(),
        sv.nipple_landmark.text(),
        t["fiducial"].text() if "fiducial" in t else "–",
        t["icp"].text() if "icp" in t else "–",
        num(reg.get("fre_mm")),
        num(reg.get("tre_nipple_mm")),
        num(reg.get("tre_tumour_mm")),
        "; ".join(dis) or "–",
    ]


HEADER = [
    "scan",
    "role",
    "posture",
    "surface mean ± sd (fiducial)",
    "median (fiducial)",
    "p95 (fiducial)",
    "max (fiducial)",
    "surface mean ± sd (ICP)",
    "ICP fitness",
    "nipple (fiducial)",
    "nipple (ICP)",
    "nipple tip (fiducial)",
    "tumour (fiducial)",
    "tumour (ICP)",
    "FRE",
    "TRE nipple",
    "TRE tumour",
    "dissertation's own phantom (published; its fit 420 Pa)",
]


def _intro(v: Validation) -> tuple[list[str], str, list[str]]:
    """The page's warnings, its c1 line and its definitions, one item each.

    Review BY, F14: they were one paragraph of ~1,100 characters a reader could not parse.
    """
    ci = v.c1_ci95_pa
    band = (
        f"95 % interval {ci[0]:.1f}–{ci[1]:.1f} Pa; each figure's band in brackets is "
        "its range over that interval"
        if ci
        else "no c1 interval: figures without bands"
    )
    warnings = [f"WARNING (calibration): {said}." for said in v.caveats]
    warnings += [f"WARNING: {said}." for said in v.notes]
    warnings += [
        f"Not validated: {n}, no FE solution at calibration ({why})." for n, why in v.failed.items()
    ]
    terms = [
        "All distances in mm.",
        "Bands: first order in ln c1; in the fiducial frame measured on "
        f"{BAND_POINTS} points across the interval, in the ICP frame at its ends and the "
        "estimate."
        if ci
        else "Bands: none (no c1 interval).",
        f"Posture: {POSTURE_NOTE}.",
        "Error maps: red where the scan lies outside the model, blue inside.",
        "Fiducial frame: the scan mapped by its fiducial registration only; median, p95 "
        "and max are of this frame.",
        "ICP: after a rigid ICP of the measured onto the simulated surface (which "
        "minimises the surface error: biased low; the nipple and tumour errors may rise "
        "or fall).",
        "Nipple: the dissertation's distance from the simulated nipple to the nearest "
        "measured vertex (blind to a slide along the surface); nipple tip: to the "
        "measured nipple tip.",
        "FRE/TRE: the scan's fiducial registration error and expected target registration "
        "error (a model error below the TRE cannot be told from registration error).",
        "The dissertation's column: its published figures for the original CIRS "
        "phantom's scans at the nearest posture, a baseline to compare with, not figures "
        "of this phantom.",
    ]
    return warnings, f"c1 = {v.c1_pa:.1f} Pa ({band}).", terms


def validation_markdown(v: Validation, figures: dict[str, list[str]] | None = None) -> str:
    """The report as Markdown: the table, then each scan's figures (relative paths)."""
    rows = [_row(s) for s in v.scans.values()]
    lines = [
        "# Validation",
        "",
        *_intro_markdown(v),
        "",
        "| " + " | ".join(HEADER) + " |",
        "|" + "---|" * len(HEADER),
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    for name, files in (figures or {}).items():
        lines += ["", f"## {name}", ""] + [f"![{Path(f).stem}]({f})" for f in files]
    return "\n".join(lines) + "\n"


def _intro_markdown(v: Validation) -> list[str]:
    warnings, c1, terms = _intro(v)
    return [*(f"**{w}**" for w in warnings), *([""] if warnings else []), c1, "",
            *(f"- {t}" for t in terms)]  # fmt: skip


def _intro_html(v: Validation) -> str:
    esc = html.escape
    warnings, c1, terms = _intro(v)
    return (
        "".join(f"<p><strong>{esc(w)}</strong></p>" for w in warnings)
        + f"<p>{esc(c1)}</p><ul>"
        + "".join(f"<li>{esc(t)}</li>" for t in terms)
        + "</ul>"
    )


def validation_html(v: Validation, figures: dict[str, list[str]] | None = None) -> str:
    """The report as a self-standing HTML page (figures by relative path)."""
    esc = html.escape
    head = "".join(f"<th>{esc(h)}</th>" for h in HEADER)
    body = "".join(
        "<tr>" + "".join(f"<td>{esc(c)}</td>" for c in _row(s)) + "</tr>" for s in v.scans.values()
    )
    figs = "".join(
        f"<h2>{esc(name)}</h2>"
        + "".join(
            f'<p><img src="{esc(f)}" alt="{esc(Path(f).stem)}" style="max-width:100%"></p>'
            for f in files
        )
        for name, files in (figures or {}).items()
    )
    style = (
        "body{font-family:sans-serif;margin:2em;max-width:80em}"
        "table{border-collapse:collapse;font-size:90%}"
        "td,th{border:1px solid #bbb;padding:.3em .5em;text-align:right}"
        "td:first-child,td:nth-child(2),td:last-child{text-align:left}"
    )
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>Validation</title>"
        f"<style>{style}</style></head><body><h1>Validation</h1>{_intro_html(v)}"
        f"<table><tr>{head}</tr>{body}</table>{figs}</body></html>\n"
    )
