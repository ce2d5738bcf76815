"""A calibrated work folder as one object for Jupyter: tables, figures, numbers.

>>> work = calib.load_work("demo-out/work")      # doctest: +SKIP
>>> work                                          # c1, interval, scans   # doctest: +SKIP
>>> work.validation_table()                       # the 25°/50° table   # doctest: +SKIP
>>> work.plot_error_map("tilt_25")                # a matplotlib Figure  # doctest: +SKIP

Everything is computed from what ``calibrate`` saved (no FE solve).
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .data.session import is_finite_number
from .data.work import WorkFolder, read_work
from .fitting.result import calibration_caveats
from .validation import Validation, validate_work

__all__ = ["Work"]


def _png(fig) -> bytes:
    from io import BytesIO

    buf = BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    return buf.getvalue()


def show_figures_in_jupyter() -> None:
    """Let a running IPython kernel show a bare matplotlib ``Figure`` as a PNG.

    The figures here are built without pyplot (no global state, no GUI backend), and a
    kernel shows such a figure as its text (``<Figure size ... with 1 Axes>``) until
    ``%matplotlib inline`` has run (review AG: notebooks 01 and 02 showed no figure).
    Registers a PNG formatter for ``Figure`` (IPython's ``for_type``) where the shell has
    none (review AH: one that ``%matplotlib inline`` or a retina setting registered is
    left as it is); outside IPython, nothing.
    """
    import sys

    if "IPython" not in sys.modules:
        return
    from IPython import get_ipython

    shell = get_ipython()
    if shell is None:
        return
    from matplotlib.figure import Figure

    png = shell.display_formatter.formatters["image/png"]
    try:
        png.lookup_by_type(Figure)
    except KeyError:
        png.for_type(Figure, _png)


@dataclass(frozen=True, eq=False)
class Work:
    """A calibrated ``WORK/`` folder (:func:`calib.load_work`; equal only to itself).

    Read-only: its record (at every depth), its states and their arrays refuse changes
    (review BW, F3: a changed ``record`` changed what it reported). The scans' and the
    mesh's arrays stay writable, as open3d and TetGen take them (review BZ, F1).

    Attributes
    ----------
    folder : WorkFolder
        The files read back (record, measurements, model mesh, saved states).
    """

    folder: WorkFolder
    _validation: Validation | None = field(default=None, repr=False)

    def keep_validation(self, validation: Validation, calibration_run_id: str | None) -> bool:
        """Keep a validation computed elsewhere of this folder (``calib.validate(work)``).

        Parameters
        ----------
        validation : Validation
            What :func:`calib.validation.validate_work` returned for this folder.
        calibration_run_id : str or None
            The run id of the calibration it validated (``validation.json``'s
            ``calibration_run_id``).

        Returns
        -------
        bool
            Whether it was kept: only a validation of the calibration this object holds
            (another one, written since it was loaded, is not its states').
        """
        if calibration_run_id is None or calibration_run_id != self.record.get("run_id"):
            return False
        object.__setattr__(self, "_validation", validation)
        return True

    @classmethod
    def load(cls, path: str | Path) -> Work:
        """Read a work folder that ``phantom-calib calibrate`` wrote (``calib.load_work``).

        Parameters
        ----------
        path : str or Path
            The work folder.

        Returns
        -------
        Work

        Raises
        ------
        FileNotFoundError
            No ``calibration.json``, or a file it names is missing.
        calib.io.StaleOutputError
            The folder's parts come from different runs (see
            :func:`calib.data.work.read_work`).
        """
        show_figures_in_jupyter()
        return cls(read_work(path))

    @property
    def record(self) -> dict:
        """``calibration.json``, read-only (``copy.deepcopy`` gives an editable copy)."""
        return self.folder.record

    @property
    def c1_pa(self) -> float:
        """The calibrated c1 (Pa)."""
        return self.folder.c1_pa

    @property
    def c1_ci95_pa(self) -> tuple[float, float] | None:
        """Its 95 % interval (Pa), or None."""
        ci = self.record.get("c1_ci95_pa")
        return None if ci is None else (float(ci[0]), float(ci[1]))

    @property
    def scans(self) -> dict[str, str]:
        """Scan name -> role."""
        return {n: s.role for n, s in self.folder.measurements.scans.items()}

    @property
    def validation(self) -> Validation:
        """Validation figures of every scan (computed once, or kept by ``calib.validate``)."""
        if self._validation is None:
            object.__setattr__(self, "_validation", validate_work(self.folder))
        return self._validation

    def validation_table(self) -> str:
        """The validation table as Markdown (Jupyter: ``display(Markdown(...))``).

        Returns
        -------
        str
            One row per scan: surface, nipple and tumour errors (mm) with their 95 % bands
            and the dissertation's figures beside them, as ``validate`` prints them.
        """
        from .report.validation import validation_markdown

        return validation_markdown(self.validation)

    def error_scale_mm(self) -> float:
        """The colour-scale top (mm) that validate's error maps share.

        Returns
        -------
        float
            mm; pass it as :meth:`plot_error_map`'s ``vmax`` to compare scans on one scale.
        """
        from .report.validation import validation_error_scale_mm

        return validation_error_scale_mm(self.validation, self.folder.measurements.scans)

    def plot_error_map(self, scan: str, *, vmax: float | None = None):
        """The measured surface of ``scan`` coloured by its signed error (matplotlib Figure).

        Red where the scan lies outside the model, blue inside (the reports' maps).

        Parameters
        ----------
        scan : str
            A calibration or validation scan (not the reference: the model's geometry).
        vmax : float, optional
            The colour scale's top, mm (default: the scan's own; :meth:`error_scale_mm`
            gives validate's shared one).

        Returns
        -------
        matplotlib.figure.Figure
            Made without pyplot (display it, or ``fig.savefig``).

        Raises
        ------
        calib.evaluation.EvaluationError
            ``scan`` has no error map (an unknown name, or the reference scan).
        ValueError
            ``vmax`` is not a positive number.
        """
        from .report.validation import error_surface_figure

        if vmax is not None and not (is_finite_number(vmax) and vmax > 0):
            raise ValueError(f"vmax must be a positive number of mm (or None), got {vmax!r}")
        sv = self._scan(scan)
        R = np.asarray(self.record["model"]["R_ref_from_phantom"], float)
        return error_surface_figure(sv, self.folder.measurements.scans[scan], R, vmax=vmax)

    def plot_error_by_displacement(self, scans: str | list[str] | None = None):
        """Error histograms by displacement magnitude (matplotlib Figure).

        Parameters
        ----------
        scans : str or list of str, optional
            A name or names of validated scans; default every one.

        Returns
        -------
        matplotlib.figure.Figure
            Made without pyplot.

        Raises
        ------
        calib.evaluation.EvaluationError
            A name that is not a validated scan.
        TypeError
            ``scans`` is neither a name nor a list of names.
        """
        from .evaluation import scan_names
        from .report.validation import error_by_displacement_figure

        names = scan_names(scans, self.validation.scans)
        return error_by_displacement_figure([self._scan(n) for n in names])

    def plot_profile(self):
        """The objective over c1: the optimiser's evaluations and the likelihood profile.

        Returns
        -------
        matplotlib.figure.Figure
            Made without pyplot; c1 (Pa) against the objective (mm^2), with the fitted c1
            and its 95 % interval.
        """
        from matplotlib.figure import Figure

        # review CB: a diagnosis refit's history holds its parameter vectors (`x`, ln c1
        # first, then its effects') and sums of squares: a KeyError 'c1_pa' here
        def drawn(row) -> bool:
            return "c1_pa" in row and "objective" in row

        rows = [r for r in self.record.get("profile") or [] if not r.get("failed") and drawn(r)]
        every = [h for h in self.record.get("history") or [] if not h.get("failed")]
        hist = [h for h in every if drawn(h)]
        fig = Figure(figsize=(6, 4), layout="constrained")
        ax = fig.subplots()
        if every and not hist:
            ax.set_title(
                "a joint fit: its evaluations are over c1 and its effects, not drawn here",
                fontsize=9,
            )
        if hist:
            ax.plot(
                [h["c1_pa"] for h in hist],
                [h["objective"] for h in hist],
                "o",
                color="0.6",
                label="optimiser evaluations",
            )
        if rows:
            rows = sorted(rows, key=lambda r: r["c1_pa"])
            ax.plot(
                [r["c1_pa"] for r in rows],
                [r["objective"] for r in rows],
                "-o",
                label="likelihood profile",
            )
        ax.axvline(self.c1_pa, color="k", lw=1, label=f"c1 = {self.c1_pa:.1f} Pa")
        if self.c1_ci95_pa:
            ax.axvspan(*self.c1_ci95_pa, color="C0", alpha=0.15, label="95 % interval")
        ax.set_xlabel("c1 (Pa)")
        ax.set_ylabel("objective J = mean(r²)/2 (mm²)")
        ax.legend(fontsize=8)
        return fig

    def _scan(self, name: str):
        """The validation of scan ``name``; ``EvaluationError`` for another name.

        Review BW, F2: a ``KeyError`` where ``plot_error_by_displacement`` and the README
        give ``EvaluationError`` for the same mistake; the reference scan is said to be it.
        """
        from .evaluation import EvaluationError

        if name not in self.validation.scans:
            role = self.scans.get(name)
            why = (
                "it is the reference scan: the model's stress-free geometry, no error map"
                if role == "reference"
                else "unknown scan"
            )
            raise EvaluationError(
                f"no error map of scan {name!r} ({why}); scans with one: "
                f"{sorted(self.validation.scans)}"
            )
        return self.validation.scans[name]

    def __repr__(self) -> str:
        ci = self.c1_ci95_pa
        interval = f" (95 % {ci[0]:.1f}–{ci[1]:.1f})" if ci else ""
        scans = ", ".join(f"{n} ({r})" for n, r in self.scans.items())
        warn = "".join(f"; WARNING: {said}" for said in calibration_caveats(self.record))
        named = ((self.record.get("model") or {}).get("effects") or {}).get("named")
        effects = f" with {', '.join(named)} (diagnose's refit)" if named else ""
        return (
            f"Work({str(self.folder.path)!r}: c1 = {self.c1_pa:.1f} Pa{interval}{effects}; "
            f"{scans}{warn})"
        )

    def _repr_html_(self) -> str:
        rows = []
        for name, s in self.record["scans"].items():
            if s.get("failed"):
                rows.append((name, s["role"], "no FE solution", "", "", ""))
                continue
            fid = s["surface_error_mm"]["fiducial"]
            tum = (s.get("tumour_error_mm") or {}).get("fiducial")
            rows.append(
                (
                    name,
                    s["role"],
                    f"{fid['mean']:.2f} ± {fid['sd']:.2f}",
                    f"{fid['max']:.2f}",
                    f"{s['nipple_error_mm']['fiducial']:.2f}",
                    "–" if tum is None else f"{tum:.2f}",
                )
            )
        head = ("scan", "role", "surface mean ± sd", "max", "nipple", "tumour")
        cells = "".join(
            "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows
        )
        th = "".join(f"<th>{h}</th>" for h in head)
        return f"<p>{html.escape(repr(self))}</p><table><tr>{th}</tr>{cells}</table>" + (
            "<p>errors in mm, fiducial frame</p>"
        )
