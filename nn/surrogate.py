"""Surrogate files (TorchScript) and queries with input checks.

A surrogate file is a TorchScript archive (``torch.jit.save``) of a module of
:mod:`nn.modules` with one extra file, ``surrogate.json``: ``format``
(``phantom-calib.surrogate``), ``format_version`` 1, ``kind`` (``ours`` or
``dissertation``), ``model`` (the sweep's calibrated model block), ``mesh_sha256``,
``trained`` (c1 range in Pa and load ``rho g / c1`` range in 1/m of the training
scenarios), ``store`` (path and plan of the sweep) and ``report`` (training record and
errors). It loads anywhere with ``torch.jit.load`` alone; :func:`load_surrogate` adds
the checks of :meth:`Surrogate.predict`.
"""

from __future__ import annotations

import contextlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from .data import MODEL_KEYS, SweepData

__all__ = [
    "ExtrapolationWarning",
    "FarExtrapolationWarning",
    "MeshMismatchError",
    "Prediction",
    "Surrogate",
    "SurrogateFileError",
    "direction_limit_deg",
    "outside_hull_deg",
    "evaluate",
    "load_surrogate",
    "quiet_jit",
    "save_surrogate",
]

FORMAT, FORMAT_VERSION = "phantom-calib.surrogate", 1
_EXTRA = "surrogate.json"
_REL_TOL = 1e-3  # range checks: 0.1 % slack (rounded user input, e.g. 6.9367,0,6.9367)
#: A query direction farther than this from every training direction, or than
#: :data:`DIRECTION_SPACING_FACTOR` times the training directions' median spacing where
#: that is wider (:func:`direction_limit_deg`), is an extrapolation: one great circle
#: (``--plan dissertation:transverse``) answers a direction 90 degrees off it without a
#: word otherwise. 5 degrees: the plans' own rounding and a few degrees of posture error
#: stay inside (the reduced model's kernel varies smoothly over ~1 degree).
DIRECTION_SLACK_DEG = 5.0
#: The direction limit in units of the training directions' median spacing. Review BP
#: (P6): at twice the spacing the dissertation plan (two circles, 15 degrees apart on
#: each) answered a direction 29 degrees off both circles without a word, 0.17-0.19 mm
#: off FE on the surface's mean (2.3 % of the displacement; max 0.25-0.46 mm) where its
#: validation directions read 7e-6 mm (``python benchmarks/bench_surrogate_trust.py``).
#: One spacing keeps every direction of a full quasi-uniform sphere plan inside (a
#: Fibonacci lattice's farthest hole lies 0.75-0.82 spacings from its nearest direction)
#: and every direction of a circle in its plane (half a spacing), and warns beyond 15
#: degrees off the dissertation plan's circles. A plan with held-out directions also
#: keeps its validated reach (:func:`direction_limit_deg`): a held-out lattice point lies
#: about one spacing from the training directions, half of them beyond it (review BR).
DIRECTION_SPACING_FACTOR = 1.0
#: A query direction farther than this (degrees) outside the hull of the training
#: directions around it (:func:`outside_hull_deg`) is an extrapolation, however near the
#: nearest lies. Review BP (P6), measured on the quick twin's dissertation plan (``python
#: benchmarks/bench_surrogate_trust.py``): a transverse posture tilted out of its circle
#: errs by about 0.011 mm on the surface's mean per degree (0.023 mm at 2 degrees, 0.11
#: mm at 10, where the nearest training direction lies 7.8-12.5 degrees off and the
#: spacing check said nothing), against 7e-6 mm on the plan's own validation
#: directions; between the circles near their shared axis, and in a sphere plan's holes,
#: a query is surrounded by training directions and this check is silent. One degree
#: keeps a registered scan's gravity (a few tenths of a degree off its nominal plane)
#: inside; a query exactly 1 degree out is inside, beyond it warns.
HULL_SLACK_DEG = 1.0
#: Training directions that span a plane or a line only (one great circle, one direction)
#: leave the linear term no response out of their span (least squares' minimum norm): a
#: query farther out of the span than this is an extrapolation, whatever its nearest
#: training direction. Reviews AD and AF, one great circle (``dissertation:transverse``)
#: on the tests' block: against FE, 0.58 mm off at 5 degrees out of the plane for 3.3 mm
#: of displacement, 3.2 mm at 29 degrees, where the direction check's 30 degrees said
#: nothing; against the two-circle surrogate at its calibrated c1, 0.11 mm at a node at 1
#: degree on 6.8 mm (1.6 % of the displacement per degree). A quarter of a degree keeps a
#: typed direction's rounding inside (6.9367,0,6.9367: 0.006 degrees) and warns of a
#: registered scan's gravity half a degree off the plane.
SPAN_SLACK_DEG = 0.25


def direction_limit_deg(spacing_deg: float, validated_deg: float | None = None) -> float:
    """How far (degrees) a query direction may lie from every training direction.

    Parameters
    ----------
    spacing_deg : float
        The training directions' median spacing (``trained.direction_spacing_deg``).
    validated_deg : float, optional
        How far the surrogate's validation directions lie from the training ones, at
        most, up to two spacings (``trained.validated_direction_deg``; None where the
        training directions span a plane or a line): its validation error was measured
        that far out.

    Returns
    -------
    float
        ``max(DIRECTION_SLACK_DEG, DIRECTION_SPACING_FACTOR * spacing_deg,
        validated_deg)``; a query farther from every training direction (0.1 % slack) is
        an :class:`ExtrapolationWarning`.
    """
    limit = max(DIRECTION_SLACK_DEG, DIRECTION_SPACING_FACTOR * float(spacing_deg))
    return max(limit, float(validated_deg)) if validated_deg is not None else limit


class ExtrapolationWarning(UserWarning):
    """A query outside the c1 or load range the surrogate was trained on."""


class FarExtrapolationWarning(ExtrapolationWarning):
    """A query whose answer is not to be trusted at all.

    A load beyond :data:`FAR_LOAD_FACTOR` times the trained range (the exponential
    kernel grows without bound: ten times the trained load read 7e17 mm, review AM), or
    nearer a scenario the sweep could not solve than any trained one.
    ``phantom-calib surrogate predict`` refuses these without ``--extrapolate``.
    """


#: Loads beyond this factor past the trained range (either side) are far: on review AM's
#: store 1.5 times the load erred by 6 % against FE, twice by a factor of 2.5
FAR_LOAD_FACTOR = 1.5


class SurrogateFileError(ValueError):
    """A file that is not a readable phantom-calib surrogate."""


class MeshMismatchError(ValueError):
    """A surrogate and a sweep store (or another input) of different meshes."""


@dataclass(frozen=True)
class SurrogateMesh:
    """The mesh a surrogate predicts on (the sweep's reference mesh, reference frame, mm).

    The stress-free mesh, or the loaded reference scan's mesh for a prestressed reference
    (:attr:`Surrogate.prestressed`).
    """

    nodes_mm: np.ndarray
    tets: np.ndarray
    boundary_faces: np.ndarray
    surface_nodes: np.ndarray
    back_nodes: np.ndarray


@dataclass(frozen=True, eq=False)
class Prediction:
    """Displacements (mm, reference frame) predicted for a batch of B queries.

    Its arrays are read-only (review BW, F3), and two predictions are equal only if they
    are the same object (``==`` on the arrays raised).

    Attributes
    ----------
    nodes_mm : ndarray, shape (B, N, 3) or None
        Every vertex (ours); None for the surface-only baseline.
    surface_mm : ndarray, shape (B, n_surface, 3)
    tumour_mm : ndarray, shape (B, 3) or None
    nipple_mm : ndarray, shape (B, 3) or None
    """

    nodes_mm: np.ndarray | None
    surface_mm: np.ndarray
    tumour_mm: np.ndarray | None
    nipple_mm: np.ndarray | None

    def __post_init__(self) -> None:  # read-only views: the caller's arrays stay as given
        for name in ("nodes_mm", "surface_mm", "tumour_mm", "nipple_mm"):
            array = getattr(self, name)
            if array is not None:
                view = np.asarray(array).view()
                view.setflags(write=False)
                object.__setattr__(self, name, view)

    def __repr__(self) -> str:  # review BW, F4: 17,000 characters of arrays in a notebook
        b, n_surface = self.surface_mm.shape[:2]
        nodes = "surface only" if self.nodes_mm is None else f"{self.nodes_mm.shape[1]} nodes"
        largest = float(np.linalg.norm(self.surface_mm, axis=-1).max(initial=0.0))
        tumour = "" if self.tumour_mm is None else ", tumour"
        return (
            f"Prediction({b} queries, {nodes}, {n_surface} surface vertices{tumour}; "
            f"largest surface displacement {largest:.3g} mm)"
        )


def _chord_deg(chord: np.ndarray) -> np.ndarray:
    """The angle (degrees) between unit vectors a chord ``|a - b|`` apart."""
    return np.degrees(2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0)))


def _span(directions: np.ndarray) -> np.ndarray | None:
    """An orthonormal basis (rows) of the directions' span where it is a plane or a line.

    ``None`` where they span all three dimensions. The rank is read from the singular
    values relative to the largest (1e-6: the plans' directions are exact to round-off).
    """
    _, sv, vt = np.linalg.svd(directions, full_matrices=False)
    rank = int(np.sum(sv > 1e-6 * sv[0]))
    return vt[:rank] if rank < 3 else None


def outside_hull_deg(u: np.ndarray, directions: np.ndarray, spacing_deg: float) -> np.ndarray:
    """How far (degrees) each query lies outside the hull of the directions around it.

    Every training direction within the nearest one's angle plus two spacings (the
    query's neighbourhood: a direction far across the sphere surrounds nothing; with one
    spacing a query near a Fibonacci lattice's direction missed part of the ring around
    it) and in the query's hemisphere is projected gnomonically onto the plane tangent to
    the sphere at the query (great circles map to straight lines, so a circle's
    directions stay on one line). The query, the plane's origin, lies inside their convex
    hull where no gap between their bearings reaches 180 degrees (distance 0); otherwise
    its distance to the hull is the least distance to a segment between two of them,
    turned back into an angle. The hull holds the nearest direction, so a query within
    ``d`` degrees of one lies at most ``d`` outside.

    Parameters
    ----------
    u : array_like, shape (B, 3) or (3,)
        Query directions (normalised here; non-zero).
    directions : ndarray, shape (M, 3)
        Unit training directions, M >= 1.
    spacing_deg : float
        Their median spacing (``trained.direction_spacing_deg``).

    Returns
    -------
    ndarray, shape (B,)
        Degrees; 90 where no training direction lies in the query's hemisphere.
    """
    from scipy.spatial import cKDTree

    d = np.asarray(directions, float)
    u = np.atleast_2d(np.asarray(u, float))
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    tree = cKDTree(d)
    return _outside_hull_deg(u, d, tree, _chord_deg(tree.query(u)[0]), spacing_deg)


def _outside_hull_deg(u, d, tree, nearest, spacing_deg) -> np.ndarray:
    """:func:`outside_hull_deg` of unit queries with their nearest angles (degrees)."""
    reach = np.minimum(nearest + 2.0 * spacing_deg, 90.0)
    out = np.zeros(len(u))
    k = min(len(d), 32)
    for start in range(0, len(u), 256):  # bounded memory: (256, k, k, 2) segments, or m x m
        rows = np.arange(start, min(start + 256, len(u)))
        chord, idx = tree.query(u[rows], k=k)
        chord, idx = chord.reshape(len(rows), k), idx.reshape(len(rows), k)
        full = _chord_deg(chord[:, -1]) <= reach[rows] + 1e-9  # maybe more within reach
        if k < len(d) and np.any(full):  # every direction within reach: no tie decides
            chord_all, idx_all = tree.query(u[rows[full]], k=len(d))
            chord_all, idx_all = chord_all.reshape(-1, len(d)), idx_all.reshape(-1, len(d))
            within = _chord_deg(chord_all) <= reach[rows[full], None] + 1e-9
            m = int(within.sum(axis=1).max())  # nearest first: those within reach lead
            out[rows[full]] = _hull_gap_deg(
                u[rows[full]], d, idx_all[:, :m], chord_all[:, :m], reach[rows[full]]
            )
            rows, chord, idx = rows[~full], chord[~full], idx[~full]
        out[rows] = _hull_gap_deg(u[rows], d, idx, chord, reach[rows])
    return out


def _hull_gap_deg(u, d, idx, chord, reach) -> np.ndarray:
    """:func:`outside_hull_deg` for queries ``u`` (B, 3) and their neighbours (B, k)."""
    nb = d[idx]  # (B, k, 3), nearest first
    cos = np.einsum("bkj,bj->bk", nb, u)
    use = (_chord_deg(chord) <= reach[:, None] + 1e-9) & (cos > 1e-3)  # one hemisphere
    # a basis of the tangent plane: u x (1, 0, 0), or u x (0, 1, 0) near the x axis
    x, y, z = u.T
    near_x = np.abs(x) >= 0.9
    e1 = np.where(near_x[:, None], np.c_[-z, np.zeros_like(x), x], np.c_[np.zeros_like(x), z, -y])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    ex, ey, ez = e1.T
    e2 = np.c_[y * ez - z * ey, z * ex - x * ez, x * ey - y * ex]  # u x e1
    p = nb / np.where(use, cos, 1.0)[..., None]  # on the tangent plane at u
    xy = np.stack([np.einsum("bkj,bj->bk", p, e1), np.einsum("bkj,bj->bk", p, e2)], axis=-1)
    xy = np.where(use[..., None], xy, xy[:, :1])  # an unused neighbour repeats the nearest
    bearing = np.sort(np.arctan2(xy[..., 1], xy[..., 0]), axis=1)
    gaps = np.diff(np.concatenate([bearing, bearing[:, :1] + 2 * np.pi], axis=1), axis=1)
    out = np.zeros(len(u))
    outside = np.flatnonzero(gaps.max(axis=1) >= np.pi - 1e-12)
    if len(outside):  # every segment a-b (a point where a = b) of the queries outside
        a, b = xy[outside, :, None, :], xy[outside, None, :, :]
        ab = b - a
        den = np.einsum("bijc,bijc->bij", ab, ab)
        t = np.einsum("bijc,bijc->bij", a, ab) / np.where(den > 0, den, 1.0)
        t = np.clip(-t, 0.0, 1.0)
        gap = np.linalg.norm(a + t[..., None] * ab, axis=-1).min(axis=(1, 2))
        out[outside] = np.degrees(np.arctan(gap))
    return np.where(use[:, 0], out, 90.0)


def _unit_directions(gravity_ref: np.ndarray) -> np.ndarray:
    """The distinct unit directions (rounded to 1e-9) of non-zero gravities, shape (n, 3)."""
    g = np.asarray(gravity_ref, float).reshape(-1, 3)
    g = g[np.linalg.norm(g, axis=1) > 0]
    return np.unique(np.round(g / np.linalg.norm(g, axis=1, keepdims=True), 9), axis=0)


def _directions(gravity_ref: np.ndarray) -> tuple[list, float]:
    """The distinct unit directions of the training gravities and their median spacing.

    The spacing is the median angle (degrees) from each direction to its nearest other;
    0 for a single direction.
    """
    from scipy.spatial import cKDTree

    d = _unit_directions(gravity_ref)
    if len(d) < 2:
        return d.tolist(), 0.0
    spacing = _chord_deg(cKDTree(d).query(d, k=2)[0][:, 1])
    return d.tolist(), float(np.median(spacing))


def _fit_meta(fit, data: SweepData) -> dict:
    train = data.subset(data.role == "train")
    q = np.linalg.norm(train.load_per_m, axis=1)
    directions, spacing = _directions(train.gravity_ref)
    valid = data.subset(data.role == "validation")
    # review BS: only where the training directions span three dimensions (a plane's
    # validation directions off it, dissertation:transverse's sagittal circle, are the
    # span check's), and up to two spacings (a sparse hold-out widens it no further)
    validated = None
    if _span(np.asarray(directions, float)) is None:
        validated = _validated_deg(valid.gravity_ref, directions)
        validated = None if validated is None else min(validated, 2.0 * spacing)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": fit.report["kind"],
        "model": data.model,
        "mesh_sha256": data.mesh_sha256,
        "trained": {
            "c1_pa": [float(train.c1_pa.min()), float(train.c1_pa.max())],
            "load_per_m": [float(q.min()), float(q.max())],
            "directions_ref": directions,
            "direction_spacing_deg": spacing,
            "validated_direction_deg": validated,
            "loads_per_m": train.load_per_m.tolist(),
            "failed_loads_per_m": data.failed_load_per_m.tolist(),
        },
        "store": {
            "path": str(data.path),
            "plan": data.attrs.get("plan", {}),
            # review BI: a store written again at the same path was still "the" store;
            # review BT: its root created_utc (the README's), not its provenance record's
            "created_utc": data.attrs.get("created_utc")
            or (data.attrs.get("provenance") or {}).get("created_utc"),
            "training_sha256": _training_digest(train),
        },
        "report": fit.report,
    }


def _validated_deg(gravity_ref: np.ndarray, directions: list) -> float | None:
    """The farthest (degrees) a validation direction lies from every training direction.

    None without validation directions (or without training ones).
    """
    from scipy.spatial import cKDTree

    u = _unit_directions(gravity_ref)
    if not len(u) or not len(directions):
        return None
    return float(_chord_deg(cKDTree(np.asarray(directions, float)).query(u)[0]).max())


def _training_digest(train: SweepData) -> str:
    """SHA-256 of the training scenarios as read: numbers, loads, c1, displacements, tumour.

    Little-endian float64 (int64 for the numbers) bytes in that order: two surrogates
    trained on the same solutions carry the same digest whatever store they came from.
    """
    import hashlib

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(train.index, dtype="<i8").tobytes())
    for a in (train.load_per_m, train.c1_pa, train.displacement_mm, train.tumour_mm):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


class Surrogate:
    """A loaded surrogate: a TorchScript module and its metadata.

    Parameters
    ----------
    module : torch.jit.ScriptModule or torch.nn.Module
    meta : dict
        The ``surrogate.json`` document.
    path : Path, optional
    """

    def __init__(self, module, meta: dict, path: Path | None = None):
        self.module, self.meta, self.path = module, meta, path
        b = {k: v.detach().cpu().numpy() for k, v in module.named_buffers()}
        self.mesh = SurrogateMesh(
            b["mesh_nodes_mm"],
            b["mesh_tets"],
            b["mesh_boundary_faces"],
            b["surface_nodes"],
            b["back_nodes"],
        )
        self.R_ref_from_phantom = np.asarray(meta["model"]["R_ref_from_phantom"], float)

    def __repr__(self) -> str:  # review BW, F4: the default <object at 0x...>
        trained = self.meta.get("trained") or {}
        lo, hi = trained.get("c1_pa", [float("nan")] * 2)
        valid = ((self.report.get("errors") or {}).get("validation") or {}).get("surface_mean_mm")
        where = "" if self.path is None else f", {Path(self.path).name}"
        said = "" if valid is None else f", validation surface mean {valid:.2g} mm"
        return (
            f"Surrogate({self.kind!r}, {len(trained.get('directions_ref', []))} training "
            f"directions, c1 {lo:.1f}–{hi:.1f} Pa{said}{where})"
        )

    @classmethod
    def from_fit(cls, fit, data: SweepData) -> Surrogate:
        """A surrogate from a fit (:mod:`nn.reduced`, :mod:`nn.baseline`) and its data."""
        from .modules import ReducedKernelModule

        module = fit.module()
        if not hasattr(module, "mesh_nodes_mm"):
            module = ReducedKernelModule(fit, data)
        meta = _fit_meta(fit, data)
        sur = cls(module, meta)
        # the baseline holds 20 % of its training scenarios out of its fit: its `train`
        # errors are those of the other 80 % (review AD: they held the test ones too)
        test = np.isin(data.index, fit.report.get("test_scenarios", []))
        meta["report"]["errors"] = {
            "train": evaluate(sur, data.subset((data.role == "train") & ~test)),
            "validation": evaluate(sur, data.subset(data.role == "validation")),
        }
        if test.any():  # the baseline's 80 / 20 hold-out
            meta["report"]["errors"]["test"] = evaluate(sur, data.subset(test))
        return sur

    @property
    def kind(self) -> str:
        """``ours`` or ``dissertation``."""
        return self.meta["kind"]

    @property
    def report(self) -> dict:
        """The training report (with errors on the training and validation scenarios)."""
        return self.meta["report"]

    @property
    def prestressed(self) -> bool:
        """True when the sweep's reference is the prestressed loaded mesh.

        The store's ``model.prestress`` (or ``reference_state`` ``prestress``): the
        displacements are then relative to the loaded reference scan's mesh
        (``mesh.nodes_mm``), and the true answer at zero gravity is the stress-free
        shape, away from that mesh, which the sweep never solved.
        """
        model = self.meta["model"]
        return bool(model.get("prestress")) or model.get("reference_state") == "prestress"

    @property
    def surface_only(self) -> bool:
        """True for the dissertation baseline, which predicts surface nodes only."""
        return self.kind == "dissertation"

    @property
    def boundary_known(self) -> bool:
        """True when every boundary vertex's displacement follows from a prediction.

        A surface-only model of a non-clamped support does not know its back plate's.
        """
        return not self.surface_only or self.meta["model"].get("support") == "clamped"

    @property
    def mesh_sha256(self) -> str:
        """Identity of the mesh the surrogate was trained on."""
        return self.meta["mesh_sha256"]

    def _checked(self, gravity, c1_pa, frame: str):
        g = np.asarray(gravity, dtype=float)
        if g.ndim == 1:
            g = g[None, :]
        if g.ndim != 2 or g.shape[1] != 3:
            raise ValueError(f"gravity must have shape (3,) or (B, 3), got {np.shape(gravity)}")
        with np.errstate(over="ignore"):  # 0,0,1e300 predicted NaN displacements
            length = np.linalg.norm(g, axis=1)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(length))):
            raise ValueError("gravity holds NaN or infinite values, or a vector of infinite length")
        if frame == "phantom":
            g = g @ self.R_ref_from_phantom.T
        elif frame != "ref":
            raise ValueError(f"frame must be 'phantom' or 'ref', got {frame!r}")
        c1_model = float(self.meta["model"]["c1_pa"])
        if c1_pa is None:
            c1 = np.full(len(g), c1_model)
        else:
            given = np.asarray(c1_pa, float)
            if given.ndim > 1 or given.size not in (1, len(g)):  # review AU: numpy's words
                raise ValueError(
                    f"c1_pa must be one value or one per gravity ({len(g)}), got shape "
                    f"{given.shape}"
                )
            c1 = np.broadcast_to(given, (len(g),)).copy()
        if not np.all(np.isfinite(c1)) or np.any(c1 <= 0):
            raise ValueError(f"c1 must be finite and positive, got {c1_pa!r}")
        self._warn_range(g, c1)
        return g, c1

    def _warn_direction(self, g: np.ndarray) -> None:
        """Warn when a loaded query's direction lies away from every training direction.

        Surrogates saved before the directions were recorded are not checked.
        """
        trained = self.meta["trained"]
        dirs = trained.get("directions_ref")
        if dirs is None or not len(g) or not len(dirs):
            return
        u = g / np.linalg.norm(g, axis=1, keepdims=True)
        d, span, tree = self._trained_directions()
        if span is not None:
            out = np.linalg.norm(u - (u @ span.T) @ span, axis=1)
            off = np.degrees(np.arcsin(np.clip(out, 0.0, 1.0)))
            if np.any(off > SPAN_SLACK_DEG):
                k = int(np.argmax(off))
                warnings.warn(
                    f"gravity direction {np.round(u[k], 3).tolist()} (reference frame) lies "
                    f"{off[k]:.1f} degrees out of the {'plane' if len(span) == 2 else 'line'} "
                    f"of the training directions (limit {SPAN_SLACK_DEG:g}): the surrogate "
                    "extrapolates (nothing out of that span was trained)",
                    ExtrapolationWarning,
                    stacklevel=4,
                )
                return
        # review BR: the distance first (a far query is told how far), then the hull of
        # the directions around the queries within the distance limit
        spacing = float(trained["direction_spacing_deg"])
        angle = _chord_deg(tree.query(u)[0])
        limit = direction_limit_deg(spacing, trained.get("validated_direction_deg"))
        if np.any(angle > limit * (1 + _REL_TOL)):  # a gap of one missing direction: inside
            k = int(np.argmax(angle))
            warnings.warn(
                f"gravity direction {np.round(u[k], 3).tolist()} (reference frame) lies "
                f"{angle[k]:.1f} degrees from the nearest training direction (limit "
                f"{limit:.1f}): the surrogate extrapolates",
                ExtrapolationWarning,
                stacklevel=4,
            )
            return
        # a query within HULL_SLACK_DEG of a training direction lies at most that far out
        near = np.flatnonzero(angle > HULL_SLACK_DEG)
        if not len(near):
            return
        outside = _outside_hull_deg(u[near], d, tree, angle[near], spacing)
        if np.any(outside > HULL_SLACK_DEG):
            k = int(near[np.argmax(outside)])
            warnings.warn(
                f"gravity direction {np.round(u[k], 3).tolist()} (reference frame) lies "
                f"{outside.max():.1f} degrees outside the training directions around it "
                f"(limit {HULL_SLACK_DEG:g}): the surrogate extrapolates (a sphere:N plan "
                "trains on directions all round)",
                ExtrapolationWarning,
                stacklevel=4,
            )

    def _trained_directions(self):
        """The training directions (M, 3), their span (:func:`_span`) and a k-d tree.

        Worked out once per surrogate from ``trained.directions_ref``: every query's
        direction checks read them.
        """
        from scipy.spatial import cKDTree

        cached = getattr(self, "_directions_cache", None)
        if cached is None:
            d = np.asarray(self.meta["trained"]["directions_ref"], float)
            cached = self._directions_cache = (d, _span(d), cKDTree(d))
        return cached

    def _warn_failed(self, load_per_m: np.ndarray) -> None:
        """Warn when a load lies nearer a scenario the sweep could not solve than any trained.

        Review AM: where the FE model had no solution (a soft c1 in a steep posture), the
        surrogate answered inside every trained range with an inverted mesh. Surrogates
        saved before the loads were recorded are not checked.
        """
        trained = self.meta["trained"]
        failed = np.asarray(trained.get("failed_loads_per_m") or np.zeros((0, 3)), float)
        if not len(failed) or not len(load_per_m) or "loads_per_m" not in trained:
            return
        loads = np.asarray(trained["loads_per_m"], float)
        d_train = np.linalg.norm(load_per_m[:, None] - loads[None], axis=2).min(axis=1)
        d_failed = np.linalg.norm(load_per_m[:, None] - failed[None], axis=2)
        near = d_failed.min(axis=1) < d_train
        if np.any(near):
            k = int(np.argmax(near))
            f = failed[int(np.argmin(d_failed[k]))]
            warnings.warn(
                f"load rho g / c1 = {np.round(load_per_m[k], 3).tolist()} 1/m (reference "
                "frame) lies nearer a scenario the sweep could not solve "
                f"({np.round(f, 3).tolist()} 1/m, the store's `failures`) than any trained "
                "one: the FE model may have no solution here, and the surrogate extrapolates",
                FarExtrapolationWarning,
                stacklevel=4,
            )

    def _trained_magnitude_c1(self, g: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """The c1 that gives each query's load ``rho g / c1`` at the sweep's magnitude.

        The dissertation baseline's input is the gravity's direction (and c1): its
        magnitude is the sweep's ``g_m_s2``. The solution depends on the load ``rho g / c1``
        only (:mod:`calib.sweep.plans`), so a query at another magnitude is the trained
        one at ``c1 * g_m_s2 / |g|``; it was answered at the sweep's magnitude (half the
        gravity gave twice its load's displacement, review BP P2). Zero gravity keeps its c1
        (the module answers zero displacement there).
        """
        norm = np.linalg.norm(g, axis=1)
        g_trained = float(self.meta["model"]["g_m_s2"])
        scale = np.divide(g_trained, norm, out=np.ones_like(norm), where=norm > 0)
        return c1 * scale

    def _warn_range(self, g: np.ndarray, c1: np.ndarray) -> None:
        lo, hi = self.meta["trained"]["c1_pa"]
        loaded = np.linalg.norm(g, axis=1) > 0  # no load: zero displacement at any c1
        # review BQ, Q3: the dissertation baseline is fed the c1 of the query's load at the
        # sweep's magnitude; that is the c1 its training range bounds
        fed = self._trained_magnitude_c1(g, c1) if self.surface_only else c1
        out = loaded & ((fed < lo * (1 - _REL_TOL)) | (fed > hi * (1 + _REL_TOL)))
        rho = float(self.meta["model"]["density_kg_m3"])
        q = rho * np.linalg.norm(g, axis=1) / c1
        qlo, qhi = self.meta["trained"]["load_per_m"]
        # one warning of the c1 or the load below: far from the trained range, it says so
        far = np.any((q > qhi * FAR_LOAD_FACTOR) | ((q > 0) & (q < qlo / FAR_LOAD_FACTOR)))
        beyond = (
            f" (its load rho g / c1 lies beyond {FAR_LOAD_FACTOR:g} times the trained range: "
            "not to be trusted, the kernel grows without bound)"
            if far
            else ""
        )
        if self.surface_only and lo == hi:
            # review BP P2: without a c1 axis the baseline's input is the direction alone,
            # so it answers the one trained load whatever the query's c1 or magnitude
            far = np.any(loaded & (np.abs(q / qlo - 1.0) > _REL_TOL)) if qlo > 0 else far
            if far:
                beyond = (
                    " (the dissertation baseline trained without a c1 axis knows one load, "
                    "rho g / c1 at the sweep's c1 and magnitude: it answers that load's "
                    "displacement whatever the query's)"
                )
        category = FarExtrapolationWarning if far else ExtrapolationWarning
        if np.any(out):
            k = int(np.flatnonzero(out)[0])
            at = (
                f" (the c1 of its load at the sweep's {self.meta['model']['g_m_s2']:g} m/s^2: "
                f"{fed[k]:.6g} Pa)"
                if fed[k] != c1[k]
                else ""
            )
            warnings.warn(
                f"c1 = {c1[k]:.6g} Pa{at} lies outside the trained range "
                f"[{lo:.6g}, {hi:.6g}] Pa: the surrogate extrapolates{beyond}",
                category,
                stacklevel=3,
            )
        if self.prestressed and np.any(q == 0):
            warnings.warn(
                "zero gravity on a prestressed reference is the loaded reference shape's "
                f"own state, not in the trained range [{qlo:.6g}, {qhi:.6g}] 1/m: the "
                "surrogate answers zero displacement (the loaded reference shape), not "
                "the stress-free shape",
                ExtrapolationWarning,
                stacklevel=3,
            )
        self._warn_direction(g[loaded])
        self._warn_failed(rho * g[loaded] / c1[loaded, None])
        below = q < qlo * (1 - _REL_TOL)
        outq = (q > 0) & (below | (q > qhi * (1 + _REL_TOL)))
        if np.any(outq) and not np.any(out):
            pre = (
                "; on a prestressed reference it interpolates towards zero displacement "
                "(the loaded reference shape) at zero load, not the stress-free shape"
                if self.prestressed and np.any(below & outq)
                else ""
            )
            k = int(np.flatnonzero(outq)[0])
            glo, ghi = (b * c1[k] / rho for b in (qlo, qhi))  # in m/s^2 at this c1
            # review AX: a unit vector given (as simulate's direction) read as 1 m/s^2
            warnings.warn(
                f"gravity magnitude {np.linalg.norm(g[k]):.4g} m/s^2 at c1 = {c1[k]:.6g} Pa "
                f"lies outside the trained [{glo:.4g}, {ghi:.4g}] m/s^2 (the gravity vector's "
                f"length is its magnitude; load rho g / c1 = {q[k]:.6g} 1/m against "
                f"[{qlo:.6g}, {qhi:.6g}]): the surrogate extrapolates{pre}{beyond}",
                category,
                stacklevel=3,
            )

    def predict(
        self, gravity_m_s2, *, c1_pa=None, frame: Literal["phantom", "ref"] = "phantom"
    ) -> Prediction:
        """Predict displacements for gravity acceleration vectors.

        Parameters
        ----------
        gravity_m_s2 : array_like, shape (3,) or (B, 3)
            Gravity acceleration in m/s^2 (the length is the magnitude; a zero vector is
            no load and gives zero displacement: the stress-free shape, or, for a
            :attr:`prestressed` reference, the loaded reference shape, with a warning),
            in ``frame``.
        c1_pa : float or array_like, optional
            c1 of each query (default: the calibrated c1 of the sweep).
        frame : {"phantom", "ref"}
            Posture-angle frame (gravity ``(cos a, 0, sin a) * 9.81`` for a transverse
            angle a) or the model's reference-scan frame.

        Returns
        -------
        Prediction
            Batch axis first (B = 1 for a single vector).

        Raises
        ------
        ValueError
            NaN or infinite input, a non-positive c1, a bad shape or frame.

        Warns
        -----
        ExtrapolationWarning
            c1, or the load ``rho g / c1``, outside the range of the training scenarios;
            a direction farther from every training direction than
            :func:`direction_limit_deg`, or beyond :data:`HULL_SLACK_DEG` outside the
            training directions around it (:func:`outside_hull_deg`), or out of the span
            of training directions that span a plane or a line; on a
            :attr:`prestressed` reference also zero gravity, whose true answer (the
            stress-free shape) the sweep never solved.
        """
        import torch

        g, c1 = self._checked(gravity_m_s2, c1_pa, frame)
        c1_in = self._trained_magnitude_c1(g, c1) if self.surface_only else c1
        with torch.inference_mode():
            out = self.module(torch.as_tensor(g), torch.as_tensor(c1_in))
        out = {k: v.numpy().astype(np.float64) for k, v in out.items()}
        nodes = out.get("nodes_mm")
        surface = nodes[:, self.mesh.surface_nodes] if nodes is not None else out["surface_mm"]
        nipple_node = int(self.meta["model"]["nipple_node"])
        nipple = None
        if nodes is not None:
            nipple = nodes[:, nipple_node]
        else:
            hit = np.flatnonzero(self.mesh.surface_nodes == nipple_node)
            nipple = surface[:, hit[0]] if hit.size else None
        return Prediction(nodes, surface, out.get("tumour_mm"), nipple)

    def boundary_displacement_mm(self, pred: Prediction, k: int = 0) -> np.ndarray:
        """Displacement of every vertex (N, 3) of query ``k`` of a prediction.

        For the surface-only baseline the interior vertices are NaN and the clamped back
        plate is at rest.

        Parameters
        ----------
        pred : Prediction
            From :meth:`predict`.
        k : int
            Index of the query in ``pred``'s batch.

        Returns
        -------
        (N, 3) float
            Displacement of every mesh vertex, reference frame, mm (NaN where unknown).

        Raises
        ------
        ValueError
            A surface-only prediction of a model whose back plate is not clamped.
        """
        if pred.nodes_mm is not None:
            return pred.nodes_mm[k].copy()  # as the surface-only branch: the caller's to change
        if not self.boundary_known:
            raise ValueError(
                "the dissertation baseline predicts surface nodes only; the back "
                "plate of a non-clamped model is unknown"
            )
        u = np.full_like(self.mesh.nodes_mm, np.nan)
        u[self.mesh.back_nodes] = 0.0
        u[self.mesh.surface_nodes] = pred.surface_mm[k]
        return u


@contextlib.contextmanager
def quiet_jit():
    """Silence torch's deprecation of TorchScript (torch >= 2.9 points to torch.export).

    TorchScript is the export format asked for (one file, loadable from C++ and Python
    without this package); it still works through Python 3.13.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", r"`torch\.jit\.\w+` is deprecated", DeprecationWarning)
        yield


def save_surrogate(sur: Surrogate, path: str | Path) -> Path:
    """Script the module and save it with ``surrogate.json`` (TorchScript archive)."""
    import torch

    text = json.dumps(sur.meta, allow_nan=False)
    with quiet_jit():
        scripted = torch.jit.script(sur.module)
        torch.jit.save(scripted, str(path), _extra_files={_EXTRA: text})
    return Path(path)


def load_surrogate(path: str | Path) -> Surrogate:
    """Load a surrogate file written by :func:`save_surrogate`.

    Raises
    ------
    SurrogateFileError
        Missing file, not a TorchScript archive, or no phantom-calib metadata.
    """
    import torch

    path = Path(path)
    if path.is_dir():  # review AM: a sweep store was "not found"
        raise SurrogateFileError(f"{path}: a folder, not a surrogate file (.pt)")
    if not path.is_file():
        raise SurrogateFileError(f"{path}: surrogate file not found")
    extra = {_EXTRA: ""}
    try:
        with quiet_jit():
            module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    except Exception as exc:  # torch raises RuntimeError and others
        # torch's first sentence; the rest is advice on checkpoints (review AM)
        said = str(exc).split(". ")[0].strip()
        raise SurrogateFileError(f"{path}: not a TorchScript surrogate ({said})") from exc
    try:
        meta = json.loads(extra[_EXTRA])
    except ValueError:
        meta = {}
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise SurrogateFileError(
            f"{path}: no {FORMAT} v{FORMAT_VERSION} metadata ({_EXTRA}) in the archive"
        )
    # review AD: metadata without these gave a KeyError traceback in predict
    lacking = [k for k in ("kind", "model", "trained", "report", "mesh_sha256") if k not in meta]
    lacking += [f"model.{k}" for k in MODEL_KEYS if k not in (meta.get("model") or {})]
    lacking += [
        f"trained.{k}" for k in ("c1_pa", "load_per_m") if k not in (meta.get("trained") or {})
    ]
    if lacking:
        raise SurrogateFileError(f"{path}: its metadata ({_EXTRA}) lacks {', '.join(lacking)}")
    return Surrogate(module.eval(), meta, path)


def evaluate(sur: Surrogate, data: SweepData) -> dict:
    """Errors of a surrogate against the FE solutions of a sweep's scenarios.

    Surface: Euclidean error at every surface vertex (node set ``surface``) of every
    scenario; tumour: Euclidean error of the tumour-centre displacement.

    Parameters
    ----------
    sur : Surrogate
    data : SweepData
        Scenarios to compare (e.g. ``data.subset(data.role == "validation")``).

    Returns
    -------
    dict
        ``n``, ``surface_mean_mm``, ``surface_p95_mm``, ``surface_max_mm``,
        ``tumour_mean_mm``, ``tumour_max_mm`` (None without a tumour).

    Raises
    ------
    MeshMismatchError
        The store is of another mesh than the surrogate's.
    """
    if data.mesh_sha256 != sur.mesh_sha256:
        raise MeshMismatchError(
            f"{data.path / 'zarr.json'}: a sweep of another mesh than the "
            f"surrogate's (mesh_sha256 differs)"
        )
    if not len(data):
        return {"n": 0}
    g = data.gravity_ref * float(data.model["g_m_s2"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExtrapolationWarning)
        pred = sur.predict(g, c1_pa=data.c1_pa, frame="ref")
    e = np.linalg.norm(pred.surface_mm - data.displacement_mm[:, data.surface_nodes], axis=2)
    out = {
        "n": len(data),
        "surface_mean_mm": float(e.mean()),
        "surface_p95_mm": float(np.percentile(e, 95)),
        "surface_max_mm": float(e.max()),
        "tumour_mean_mm": None,
        "tumour_max_mm": None,
    }
    if pred.tumour_mm is not None and data.has_tumour:
        et = np.linalg.norm(pred.tumour_mm - data.tumour_mm, axis=1)
        out |= {"tumour_mean_mm": float(et.mean()), "tumour_max_mm": float(et.max())}
    return out


def surface_errors(sur: Surrogate, data: SweepData) -> np.ndarray:
    """Per-scenario, per-surface-vertex Euclidean errors (S, n_surface), mm (for maps)."""
    g = data.gravity_ref * float(data.model["g_m_s2"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExtrapolationWarning)
        pred = sur.predict(g, c1_pa=data.c1_pa, frame="ref")
    return np.linalg.norm(pred.surface_mm - data.displacement_mm[:, data.surface_nodes], axis=2)
