"""``phantom-calib simulate``: one gravity solve on a user's mesh."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import numpy as np

import fem
from fem.discretize import Formulation
from fem.meshing import (
    find_back_plane,
    flat_tolerance_mm,
    tag_node_sets,
    warn_left_near_plane,
)
from fem.units import DEFAULT_DENSITY_KG_M3, STANDARD_GRAVITY_M_S2

from ..choices import BackSupport
from ..data.session import checked_density_kg_m3
from ..io import atomic_write, input_records, provenance, write_json_atomic

__all__ = [
    "CALIBRATED_OPTIONS",
    "SimulateOptions",
    "calibrated_model",
    "parse_back_plane",
    "parse_vector",
    "run_simulate",
    "say_calibrated_model",
]

log = logging.getLogger(__name__)


#: Plausible extent of a phantom or breast, mm: a mesh outside it is in other units.
BODY_EXTENT_MM = (10.0, 2000.0)
#: Below this extent (mm) a body is warned about: centimetres pass the range above.
SMALL_BODY_MM = 40.0
#: Output formats that keep the tetrahedra and the ``displacement_mm`` point data
#: (review AT: .stl, .ply, .off and .inp dropped them, .obj and .xdmf failed after the solve).
OUTPUT_SUFFIXES = (".vtu", ".vtk", ".msh")


def _extent_mm(mesh: fem.TetMesh) -> float:
    """The mesh's largest bounding-box side, mm (0 without nodes)."""
    return float(np.ptp(mesh.nodes_mm, axis=0).max()) if mesh.n_nodes else 0.0


@dataclass(frozen=True)
class SimulateOptions:
    """Options of the ``simulate`` command (see the README for their meaning).

    Every number is checked at construction (finite, in range), so a bad option fails
    before any file is read.

    Attributes
    ----------
    c1_pa : float
        Neo-Hookean ``c1`` of the homogeneous material, Pa (``--c1``; positive).
    nu : float
        Poisson's ratio, in (0, 0.5) (``--nu``; dimensionless).
    density_kg_m3 : float
        Density, kg/m^3 (``--density``; within the session's range).
    gravity : tuple of float, shape (3,)
        Gravity direction in the mesh file's frame (normalised by the solve; any length)
        (``--gravity``).
    g_m_s2 : float
        Gravity's magnitude, m/s^2 (``--g``; positive).
    bc : {"clamped", "sliding"}
        Support of the back face: :class:`fem.Clamped`, or :class:`fem.Sliding` with its
        rim held (``--bc``).
    back_plane : str
        ``"auto"`` (the mesh's own ``set:back``, else the detected flat face) or
        ``"z=MM"`` (the boundary nodes at that z, mm, in the mesh file's frame)
        (``--back-plane``).
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Finite element formulation (``--formulation``).
    """

    c1_pa: float
    nu: float = 0.499
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3
    gravity: tuple[float, float, float] = (0.0, 1.0, 0.0)
    g_m_s2: float = STANDARD_GRAVITY_M_S2
    bc: BackSupport = "clamped"
    back_plane: str = "auto"
    formulation: Formulation = "taylor-hood"

    def __post_init__(self) -> None:
        checks = (
            ("c1_pa (--c1)", self.c1_pa, self.c1_pa > 0, "a positive stress in Pa"),
            ("nu (--nu)", self.nu, 0 < self.nu < 0.5, "in (0, 0.5)"),
            (
                "g_m_s2 (--g)",
                self.g_m_s2,
                0 < self.g_m_s2 <= MAX_G_M_S2,  # review BU: 9810 (mm/s^2) failed in the solve
                f"a positive magnitude in m/s^2 up to {MAX_G_M_S2:g} (the direction is "
                "gravity, --gravity; 9810 would be mm/s^2)",
            ),
        )
        for name, value, ok, expected in checks:
            if not np.isfinite(value) or not ok:
                raise ValueError(f"{name} must be {expected}, got {value}")
        # the session's range
        checked_density_kg_m3(self.density_kg_m3, "density_kg_m3 (--density)")
        # found documenting its fields: the Python API's gravity was checked only in the solve,
        # after the mesh was read (the command line's parse_vector checks it first)
        try:
            vec = tuple(float(v) for v in self.gravity)
        except (TypeError, ValueError):
            vec = ()
        if not _nonzero_direction(vec):
            raise ValueError(
                f"gravity (--gravity) must be a non-zero direction X,Y,Z of finite length, got "
                f"{self.gravity!r}"
            )
        if self.bc not in get_args(BackSupport):
            raise ValueError(f"bc (--bc) must be 'clamped' or 'sliding', got {self.bc!r}")
        if self.formulation not in fem.FORMULATIONS:
            raise ValueError(
                f"formulation (--formulation) must be one of {sorted(fem.FORMULATIONS)}, "
                f"got {self.formulation!r}"
            )
        parse_back_plane(self.back_plane)


def _nonzero_direction(vec: tuple) -> bool:
    """Whether ``vec`` is three finite numbers, not all zero, whose length is finite too."""
    # its length finite too: 0,0,1e300 passed, and a normalised load came out zero
    with np.errstate(over="ignore"):
        finite = len(vec) == 3 and np.all(np.isfinite(vec)) and np.isfinite(np.linalg.norm(vec))
    return bool(finite and np.any(vec))


#: The largest gravity magnitude ``--g`` takes, m/s^2 (a centrifuge's 100 g).
MAX_G_M_S2 = 1000.0
#: Tetrahedra above which a solve is warned of as large (memory and time).
LARGE_MESH_TETS = 200_000


def parse_vector(text: str) -> tuple[float, float, float]:
    """Parse ``"X,Y,Z"`` into a non-zero 3-vector."""
    try:
        vec = tuple(float(p) for p in text.split(","))
    except ValueError:
        vec = ()
    if not _nonzero_direction(vec):  # review BU: the option unnamed
        raise ValueError(
            f"--gravity: expected a non-zero vector 'X,Y,Z' of finite length, got {text!r}"
        )
    return vec  # type: ignore[return-value]


def parse_back_plane(text: str) -> float | None:
    """``auto`` gives None; ``z=MM`` gives the plane's z in mm."""
    if text == "auto":
        return None
    if text.startswith("z="):
        try:
            return float(text[2:])
        except ValueError:
            pass
    raise ValueError(f"back_plane (--back-plane) must be 'auto' or 'z=MM', got {text!r}")


def _back_nodes(mesh: fem.TetMesh, z_mm: float | None):
    own = mesh.node_sets.get("back")
    if z_mm is None and own is not None and len(own):
        # the mesh's own back set (`set:back`, as calibrate writes it): review AT, the
        # detected plane clamped 3 nodes the calibration had left free
        return (*_own_back(mesh, np.asarray(own)), "set:back")
    if z_mm is None:
        nodes, normal, _ = find_back_plane(mesh)
        return nodes, normal, "detected"
    bnodes = np.unique(fem.boundary_faces(mesh.tets))
    # within the flat-face tolerance (review BU: within 1e-6 of the extent, a face off by
    # 0.01 mm on half its nodes was held on the other half, without a word)
    tol = flat_tolerance_mm(mesh)
    nodes = bnodes[np.abs(mesh.nodes_mm[bnodes, 2] - z_mm) < tol]
    if len(nodes) < 3:
        raise fem.MeshError(
            f"no back face found at z={z_mm} mm (found {len(nodes)} boundary nodes within "
            f"{tol:.3g} mm of it)"
        )
    normal = np.array([0.0, 0.0, -1.0 if mesh.nodes_mm[:, 2].mean() > z_mm else 1.0])
    warn_left_near_plane(mesh, nodes, normal, float(normal[2] * z_mm), tol, f"z={z_mm:g}")
    return nodes, normal, f"z={z_mm:g}"


def _own_back(mesh: fem.TetMesh, own: np.ndarray):
    """The mesh's ``set:back``, checked: a flat face of the boundary (review AT).

    A set of a few nodes at the nipple (any tool may export a point array of that name)
    failed the solve with "the support leaves the body free".
    """
    from fem.discretize import plane_fit

    inside = ~np.isin(own, np.unique(fem.boundary_faces(mesh.tets)))
    extent = _extent_mm(mesh)
    why = normal = None
    if len(own) < 3:
        why = f"{len(own)} nodes"
    elif inside.any():
        why = f"{int(inside.sum())} of its {len(own)} nodes are inside the body"
    else:
        normal, _, rms = plane_fit(mesh.nodes_mm[own])
        span = float(np.ptp(mesh.nodes_mm[own], axis=0).max())
        if rms > 1e-3 * extent:
            why = f"its {len(own)} nodes lie {rms:.3g} mm (rms) off one plane"
        elif span < 0.25 * extent:
            why = f"its {len(own)} nodes span {span:.3g} mm of a {extent:.3g} mm body"
    if why is not None:
        raise fem.MeshError(
            f"the mesh's `set:back` point data is no back face to clamp ({why}); remove it "
            "or give --back-plane z=MM"
        )
    if normal @ (mesh.nodes_mm.mean(axis=0) - mesh.nodes_mm[own].mean(axis=0)) > 0:
        normal = -normal  # outward: away from the body
    log.info("clamping the mesh's own back face (`set:back`, %d nodes)", len(own))
    return own, normal


#: What ``simulate``'s options set that calibrate's model records (``calibration.json``
#: ``model``): the option's name on the command line, its attribute and the model's key.
CALIBRATED_OPTIONS = (
    ("--density", "density_kg_m3", "density_kg_m3"),
    ("--nu", "nu", "nu"),
    ("--formulation", "formulation", "formulation"),
    ("--g", "g_m_s2", "g_m_s2"),
    ("--bc", "bc", "support"),
)


def calibrated_model(mesh_path: Path) -> tuple[Path, dict] | None:
    """Calibrate's record of a mesh that is a calibration's ``reference_mesh.vtu``, or None.

    Review BP, P1: ``simulate`` of calibrate's own mesh solved the defaults (1000 kg/m^3)
    whatever the calibration had (an independent generator's 1200 kg/m^3 phantom: 17 %
    less displacement than the calibrated model's, without a word). The mesh file carries
    no physics; its ``calibration.json`` does (its ``model.reference_mesh`` names it).

    Parameters
    ----------
    mesh_path : Path
        The mesh ``simulate`` reads.

    Returns
    -------
    (Path, dict) or None
        ``calibration.json``'s path and the whole record, where the mesh is the one its
        ``model.reference_mesh`` names, or the loaded reference mesh of its prestress
        (``model.prestress.mesh``: then the record's ``model.prestress`` gains
        ``"solved": true``); None otherwise (any other mesh, or a record that cannot be
        read: ``simulate`` needs none).
    """
    import json

    path = Path(mesh_path).resolve()
    record_path = path.parent.parent / "calibration.json"
    if not record_path.is_file():
        return None
    try:
        record = json.loads(record_path.read_text())
        model = record["model"]
        named = (record_path.parent / model["reference_mesh"]).resolve()
        loaded = (model.get("prestress") or {}).get("mesh")
        loaded = None if loaded is None else (record_path.parent / loaded).resolve()
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if path == loaded:  # review BQ, Q11: the other mesh a user may try
        model["prestress"] = dict(model["prestress"], solved=True)
        return record_path, record
    return (record_path, record) if named == path else None


def say_calibrated_model(mesh_path: Path, opts: SimulateOptions, found) -> dict | None:
    """Warn where a solve of calibrate's mesh is not the calibrated model; the record's part.

    Each option of :data:`CALIBRATED_OPTIONS` that differs from the calibration's model
    (``--c1``, required, is the user's choice: not compared) and a reference the solve
    cannot reproduce (curved stress-free elements, a prestressed reference or its loaded
    mesh, a diagnosis refit's effects: ``simulate`` solves one neo-Hookean body of straight
    elements from zero stress) are named in one warning, with the options that give the
    calibrated model.

    Parameters
    ----------
    mesh_path : Path
        The mesh solved (named in the warning).
    opts : SimulateOptions
        The solve's options.
    found : (Path, dict) or None
        :func:`calibrated_model` of ``mesh_path``.

    Returns
    -------
    dict or None
        ``RESULT.json``'s ``calibration``: its ``path``, ``differences`` (option to
        ``[calibrated, used]``) and ``reference`` (null, or why the solve differs from the
        calibrated model whatever the options); None for another mesh.
    """
    if found is None:
        return None
    record_path, record = found
    model = record.get("model") or {}
    diffs = {}
    effects = model.get("effects") or {}
    for flag, attr, key in CALIBRATED_OPTIONS:
        want, used = model.get(key), getattr(opts, attr)
        if want is None or (effects and attr == "bc"):  # a refit's support: said below
            continue
        try:
            same = (
                want == used
                if isinstance(used, str)
                else bool(np.isclose(float(want), float(used), rtol=1e-9))
            )
        except (TypeError, ValueError):  # a hand-edited record's value: not the same
            same = False
        if not same:
            diffs[flag] = [want, used]
    method = (record.get("reference_recovery") or {}).get("method")
    reference = None
    if (model.get("prestress") or {}).get("solved"):
        reference = (
            "this is the loaded reference mesh of the calibration's prestress (the reference "
            "scan's shape, stressed by its own gravity: model.prestress.state): simulate "
            "solves it from zero stress; the calibrated model's stress-free mesh is "
            f"{model.get('reference_mesh')}"
        )
    elif effects:  # review BQ, Q2: a diagnosis refit (its springs have no --bc)
        named = ", ".join(effects.get("named") or []) or "none named"
        reference = (
            f"the calibration is a diagnosis refit with its effects ({named}; "
            "model.effects: skin, inclusions, c2, springs at the plate), which simulate, "
            "one neo-Hookean body, does not solve: phantom-calib sweep solves them"
        )
    elif method != "spatial" and model.get("prestress"):
        reference = (
            "the calibrated reference is prestressed (the loaded reference scan's mesh with "
            "its stress): simulate solves this mesh from zero stress"
        )
    elif method == "spatial":
        reference = (
            "the calibrated stress-free reference has curved elements (its recovery's "
            "`spatial` method): simulate solves straight ones on its vertices"
        )
    if diffs or reference:
        said = [f"{flag} {used} (calibrated: {want})" for flag, (want, used) in diffs.items()]
        fix = " ".join(f"{flag} {want}" for flag, (want, _) in diffs.items())
        log.warning(
            "%s is the model mesh of %s; this solve is not the calibrated model's: %s%s",
            mesh_path,
            record_path,
            "; ".join(said + ([reference] if reference else [])),
            f" (for the calibrated model: {fix})" if fix else "",
        )
    return {
        "path": str(record_path),
        "differences": diffs,
        "reference": reference,
    }


def _model(mesh: fem.TetMesh, opts: SimulateOptions) -> fem.Model:
    material = fem.NeoHookean(opts.c1_pa, nu=opts.nu)
    supports = {"clamped": fem.Clamped(), "sliding": fem.Sliding()}
    return fem.Model.homogeneous(
        mesh, material, density_kg_m3=opts.density_kg_m3, support=supports[opts.bc]
    )


def _components(mesh: fem.TetMesh) -> np.ndarray:
    """Connected-component label of every element (elements sharing a node are joined)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = mesh.n_tets
    rows = np.repeat(np.arange(n), 4)
    incidence = sp.csr_matrix((np.ones(4 * n), (rows, mesh.tets.ravel())), shape=(n, mesh.n_nodes))
    _, labels = connected_components(incidence @ incidence.T, directed=False)
    return labels


def check_orientation(
    mesh: fem.TetMesh, path: Path, node_index: np.ndarray | None = None
) -> np.ndarray:
    """Elements inverted against the rest (before any flipping), or none.

    One convention throughout (every element positive, or every one negative, as some
    writers order them) is flipped to positive silently. A few inverted among positive
    ones are either a tangled mesh, whose elements overlap (review AT: a node moved
    through its neighbours was flipped and solved without a word), or a recovered
    stress-free mesh with elements inverted at a clamped rim, which ``calibrate`` reports
    (its ``reference_mesh.vtu``, as ``make demo`` simulates it); :func:`say_inverted`
    tells which, once the back face is known. Non-finite coordinates are refused first.

    Returns
    -------
    ndarray of int
        The elements inverted against the rest (empty where there is one orientation).

    Raises
    ------
    fem.MeshError
        A point with a non-finite coordinate (named by ``node_index``, the file's point
        number of each node, where given).
    """
    bad = np.flatnonzero(~np.isfinite(mesh.nodes_mm).all(axis=1))
    if len(bad):
        # the file's own point number (review BU: the node's, with unused points before it
        # the wrong one)
        k = int(bad[0] if node_index is None else node_index[bad[0]])
        raise fem.MeshError(
            f"{path}: {len(bad)} points have non-finite coordinates, e.g. point {k} (0-based, "
            f"in the file's order) {mesh.nodes_mm[bad[0]].tolist()}"
        )
    return mesh.against_the_rest()


def say_inverted(
    mesh: fem.TetMesh, path: Path, few: np.ndarray, back: np.ndarray, *, recovered: bool
) -> None:
    """Warn of the elements :func:`check_orientation` found, flipped for the solve.

    Every one touching the clamped back face of a stress-free mesh calibrate recovered
    (``recovered``: :func:`calibrated_model` found its record): as such a mesh holds them;
    any other, or any in another mesh: a tangled mesh, whose answer is wrong (review BU,
    F12: a user's mesh tangled at its back face was told it looked like calibrate's).
    """
    if not len(few):
        return
    at_back = np.isin(mesh.tets[few], back).any(axis=1)
    if at_back.all() and recovered:
        log.warning(
            "%s: %d of %d elements, all at the back face, are inverted against the rest "
            "and are flipped (a stress-free mesh calibrate recovered holds such at the "
            "clamped rim, and reports them)",
            path,
            len(few),
            mesh.n_tets,
        )
        return
    if at_back.all():
        log.warning(
            "%s: %d of %d elements, all at the back face, are inverted against the rest and "
            "are flipped: a tangled mesh, whose elements overlap, gives a wrong answer near "
            "them (and where --bc sliding lets them move); untangle it (a copy of "
            "calibrate's reference_mesh.vtu, away from its work folder, holds such at the "
            "clamped rim: simulate it in place to have it checked)",
            path,
            len(few),
            mesh.n_tets,
        )
        return
    inner = few[~at_back]
    log.warning(
        "%s: %d of %d elements are inverted against the rest, %d of them away from the "
        "back face (e.g. tetrahedron %d, 0-based among the file's tetrahedra), and are "
        "flipped: a tangled mesh, whose elements overlap, gives a wrong answer; untangle it",
        path,
        len(few),
        mesh.n_tets,
        len(inner),
        inner[0],
    )


def check_mesh(mesh: fem.TetMesh, path: Path) -> None:
    """Refuse a mesh that cannot be a phantom in mm: wrong units, or several bodies."""
    extent = _extent_mm(mesh)
    lo, hi = BODY_EXTENT_MM
    if not lo <= extent <= hi:
        unit = "metres (scale it by 1000)" if extent < lo else "micrometres (scale it by 1e-3)"
        raise fem.MeshError(
            f"{path}: the mesh spans {extent:.4g} mm; lengths must be in "
            f"millimetres (a body of {lo:g}-{hi:g} mm). Is it in {unit}?"
        )
    if extent < SMALL_BODY_MM:
        log.warning(
            "%s: the mesh spans %.3g mm, small for a breast or a phantom: if it is in "
            "centimetres, scale it by 10 (lengths are read in millimetres)",
            path,
            extent,
        )
    _check_repeats(mesh, path, extent)
    labels = _components(mesh)
    counts = np.bincount(labels)
    if len(counts) > 1:
        raise fem.MeshError(
            f"{path}: the mesh has {len(counts)} disconnected parts "
            f"({sorted(counts.tolist(), reverse=True)} elements); a floating "
            "part has no support: remove it"
        )


def _check_repeats(mesh: fem.TetMesh, path: Path, extent_mm: float) -> None:
    """Refuse repeated tetrahedra and coincident nodes (review BU).

    A tetrahedron twice (Gmsh's MSH 2 writes an element once per physical group it is in)
    was solved with twice its stiffness and weight, and its faces counted as interior; two
    parts meshed apart and not merged share coordinates but no nodes, so the body was
    solved cut along the seam (a half-way crack: 25 % more displacement, no word).
    """
    from scipy.spatial import cKDTree

    _, first, count = np.unique(
        np.sort(mesh.tets, axis=1), axis=0, return_index=True, return_counts=True
    )
    if np.any(count > 1):
        k = int(first[np.argmax(count)])
        raise fem.MeshError(
            f"{path}: {int(np.sum(count - 1))} duplicate tetrahedra, each repeating another's "
            f"four nodes (e.g. element {k} of the file's tetrahedra): one copy of each is a "
            "body (Gmsh's MSH 2 writes an element once per physical group it is in; export "
            "one group, or MSH 4)"
        )
    pairs = cKDTree(mesh.nodes_mm).query_pairs(1e-6 * extent_mm, output_type="ndarray")
    if len(pairs):
        at = ", ".join(f"{v:.4g}" for v in mesh.nodes_mm[pairs[0, 0]])
        raise fem.MeshError(
            f"{path}: {len(pairs)} pairs of nodes share their coordinates (e.g. at ({at}) "
            "mm): parts meshed apart and not merged, which the solve would take as cut "
            "along the seam; merge duplicate nodes (Gmsh: Coherence; meshio or pyvista: "
            "clean) and give the merged mesh"
        )


def _say_a_flat_top(mesh: fem.TetMesh, path: Path, back_normal: np.ndarray) -> None:
    """Warn where the apex is one of several surface nodes at the top height (review BU).

    A flat-topped body (a box, a slab) has no apex: its "nipple" is one node of the tie,
    and ``nipple_displacement_mm`` that one node's (a box's corner moved 1.66 mm where its
    top moved 1.42-1.97 mm).
    """
    surface = mesh.node_set("surface")
    height = -(mesh.nodes_mm[surface] @ back_normal)
    extent = _extent_mm(mesh)
    tie = int(np.sum(height >= height.max() - 1e-6 * extent))
    if tie > 1:
        log.warning(
            "%s: %d surface nodes share the top height (a flat top): the nipple is one of "
            "them and its displacement that node's; give a `set:nipple` point-data mask of "
            "the node to follow",
            path,
            tie,
        )


def check_output(out_path: Path) -> None:
    """Fail before any work when ``out_path`` cannot be written as a mesh."""
    from fem.io import mesh_format_for

    from ..io import check_out_file

    if out_path.suffix.lower() not in OUTPUT_SUFFIXES:
        raise ValueError(
            f"out (--out) {out_path}: use {', '.join(OUTPUT_SUFFIXES)} (formats that keep the "
            "tetrahedra and the displacement_mm point data)"
        )
    mesh_format_for(out_path)  # the writer knows it
    check_out_file(out_path)
    check_out_file(out_path.with_suffix(".json"))  # RESULT.json, written beside it


def _midside_displacement_mm(disc, state: np.ndarray, points) -> np.ndarray:
    """The displacement of the input's quadratic mid-side points, (n_midside, 3) mm.

    Review BU, F14: they were NaN, 85 % of a quadratic file's points, though the default
    taylor-hood solve holds the displacement at every edge's midpoint. Each takes its
    edge's midpoint value (:func:`fem.edge_midpoint_displacement_mm`): exact for straight
    edges; a curved edge is solved straight, and its point takes the straight edge's
    midpoint value (``read_mesh`` warns).
    """
    if not len(points.midside):
        return np.zeros((0, 3))
    node_of = np.full(points.n_points, -1, dtype=np.int64)
    node_of[points.node_index] = np.arange(len(points.node_index))
    return fem.edge_midpoint_displacement_mm(disc, state, node_of[points.midside[:, 1:]])


def _in_file_numbering(mesh: fem.TetMesh, points, u_mm: np.ndarray, midside_u_mm: np.ndarray):
    """The deformed mesh and its displacement on every point of the input file.

    Quadratic mid-side points take ``midside_u_mm`` (rows of ``points.midside``); points
    the solve did not use (in no tetrahedron) keep their input position and get a NaN
    displacement.
    """
    k = points.node_index
    u = points.scatter(u_mm)
    x = points.points_mm.copy()
    x[k] += u_mm
    if len(midside_u_mm):
        mid = points.midside[:, 0]
        u[mid] = midside_u_mm
        x[mid] += midside_u_mm
    sets = {name: k[ids] for name, ids in mesh.node_sets.items()}
    out = fem.TetMesh(x, k[mesh.tets], mesh.region, mesh.region_names, sets)
    return out, u


def _mesh_files(mesh_path: str | Path) -> dict[str, Path]:
    """The files a mesh is read from: ``mesh``, and a TetGen mesh's other file.

    Review BK: a TetGen mesh is a ``.node`` and an ``.ele`` file, and only the one named
    was hashed (``mesh_companion`` is the other).
    """
    path = Path(mesh_path)
    other = {".node": ".ele", ".ele": ".node"}.get(path.suffix.lower())
    if other is None:
        return {"mesh": path}
    return {"mesh": path, "mesh_companion": path.with_name(path.stem + other)}


def run_simulate(mesh_path: str | Path, out_path: str | Path, opts: SimulateOptions) -> dict:
    """Solve the gravity load on a mesh file and write ``out_path`` and its ``.json``.

    The result is written in the input file's point numbering: point ``i`` of
    ``out_path`` is point ``i`` of ``mesh_path``. Points the solve does not use (in no
    tetrahedron) keep their input position with a NaN ``displacement_mm``;
    ``RESULT.json`` counts them (``unsolved_points``). The mid-side points of quadratic
    tetrahedra take the displacement at their edge's midpoint.

    Returns
    -------
    dict
        The summary written to ``RESULT.json``.
    """
    from fem.io import read_mesh, write_mesh

    # review BW, F1: a str out_path solved the whole posture, then failed writing
    mesh_path, out_path = Path(mesh_path), Path(out_path)

    check_output(out_path)
    written = {out_path.resolve(), out_path.with_suffix(".json").resolve()}
    if mesh_path.resolve() in written:  # review AC: the input was overwritten
        raise ValueError(f"out (--out) {out_path}: it (or its .json) is the input mesh {mesh_path}")
    t0 = time.perf_counter()
    try:
        mesh, points = read_mesh(mesh_path, orient=False, return_input_points=True)
        read = input_records(_mesh_files(mesh_path))  # review BI: hashed as read
        inverted = check_orientation(mesh, mesh_path, points.node_index)
        mesh = mesh.oriented()
        if mesh.n_tets == 0:
            raise fem.MeshError("the mesh has no tetrahedra")
        check_mesh(mesh, mesh_path)
        back, normal, back_source = _back_nodes(mesh, parse_back_plane(opts.back_plane))
        found = calibrated_model(mesh_path)
        say_inverted(mesh, mesh_path, inverted, back, recovered=found is not None)
        own_nipple = mesh.node_sets.get("nipple")
        mesh = tag_node_sets(mesh, back, normal)
        nipple_source = "apex"
        on_surface = own_nipple is not None and np.isin(own_nipple, mesh.node_set("surface"))
        if own_nipple is not None and not (len(own_nipple) == 1 and on_surface.all()):
            log.warning(
                "%s: its `set:nipple` point data (%d nodes) is not one surface node: the "
                "nipple is the apex, the surface node farthest from the back face",
                mesh_path,
                len(own_nipple),
            )
        elif own_nipple is not None:
            # review BP, P4: calibrate's `set:nipple` is the node nearest the measured
            # nipple, which need not be the apex; it was overwritten by the apex
            mesh = mesh.with_node_sets(nipple=np.asarray(own_nipple, dtype=np.int64))
            nipple_source = "set:nipple"
        if nipple_source == "apex":
            _say_a_flat_top(mesh, mesh_path, normal)
    except fem.MeshError as exc:  # every mesh problem names the mesh file
        if str(mesh_path) in str(exc):
            raise
        raise fem.MeshError(f"{mesh_path}: {exc}") from exc
    if len(mesh.region_names) > 1:  # review AU: a refit's skin solved as bulk, silently
        log.warning(
            "%s: its %d regions (%s) are solved as one neo-Hookean material at --c1: "
            "simulate is homogeneous (a diagnosis refit's effects: phantom-calib sweep)",
            mesh_path,
            len(mesh.region_names),
            ", ".join(sorted(mesh.region_names)[:4])
            + (", ..." if len(mesh.region_names) > 4 else ""),
        )
    calibration = say_calibrated_model(mesh_path, opts, found)
    model = _model(mesh, opts)
    if opts.formulation == "p1" and opts.nu > 0.45:  # review BU: 54 % of the answer, unsaid
        log.warning(
            "%s: linear tetrahedra (p1) lock at nu %g: the body comes out too stiff (about "
            "half the displacement of the default taylor-hood on a model mesh); use "
            "taylor-hood, mini or p2",
            mesh_path,
            opts.nu,
        )
    if mesh.n_tets > LARGE_MESH_TETS:  # review BU: no word before a long, large solve
        log.warning(
            "%s: %d tetrahedra: the direct solve's memory grows faster than the mesh (18,000 "
            "tetrahedra took 1.8 GB and 23 s with taylor-hood on one core): expect many GB "
            "and minutes; --formulation mini is lighter, or coarsen the mesh",
            mesh_path,
            mesh.n_tets,
        )
    try:
        disc = fem.discretize(model.mesh, model.support, formulation=opts.formulation)
        sol = fem.solve(model, gravity=np.array(opts.gravity), g_m_s2=opts.g_m_s2, disc=disc)
    except fem.ConvergenceError as exc:  # review BU: the error named no mesh
        raise fem.ConvergenceError(f"{mesh_path}: {exc}", element=exc.element) from exc
    except MemoryError as exc:  # review BU: a traceback (exit 1), not the documented exit 2
        raise RuntimeError(
            f"{mesh_path}: out of memory in the solve of its {mesh.n_tets} tetrahedra "
            f"({opts.formulation}): coarsen the mesh or use --formulation mini"
        ) from exc
    nipple = int(mesh.node_set("nipple")[0])
    midside_u = _midside_displacement_mm(disc, sol.state, points)
    unsolved = points.n_points - mesh.n_nodes - len(midside_u)
    if unsolved:
        log.warning(
            "%s: %d of its %d points are in no tetrahedron (or are mid-side points not on "
            "their edge, as said above) and were not solved: their displacement_mm in %s "
            "is NaN",
            mesh_path,
            unsolved,
            points.n_points,
            out_path,
        )
    extent = _extent_mm(mesh)
    if sol.max_displacement_mm > 0.5 * extent:
        log.warning(
            "%s: the body moved %.0f mm, more than half its size (%.0f mm): check c1 "
            "(Pa), the density (kg/m^3) and g (m/s^2)",
            mesh_path,
            sol.max_displacement_mm,
            extent,
        )
    deformed, u = _in_file_numbering(mesh, points, sol.displacement_mm, midside_u)
    summary = {
        # over every point written (review BV, F7: the vertices' was below RESULT.vtu's)
        "max_displacement_mm": float(np.nanmax(np.linalg.norm(u, axis=1))),
        "nipple_displacement_mm": float(np.linalg.norm(sol.displacement_mm[nipple])),
        "nipple_node": int(points.node_index[nipple]),  # the input file's numbering
        "nipple_source": nipple_source,
        # the clamped (or sliding) face; review BU: which plane it is, too
        "back": {
            "source": back_source,
            "nodes": len(back),
            "normal": [float(v) + 0.0 for v in np.round(normal, 6)],
            "offset_mm": float(np.mean(mesh.nodes_mm[back] @ normal)),
        },
        "inverted_elements_flipped": len(inverted),
        "points": points.n_points,
        "unsolved_points": unsolved,
        "converged": sol.converged,
        "newton_iterations": sol.newton_iterations,
        "load_steps": sol.load_steps,
        "dofs": sol.dofs,
        "wall_s": time.perf_counter() - t0,
        "formulation": sol.formulation,
        "calibration": calibration,
        "provenance": provenance(inputs=read, parameters=opts.__dict__),
    }
    json_path = out_path.with_suffix(".json")
    atomic_write(out_path, lambda p: write_mesh(deformed, p, point_data={"displacement_mm": u}))
    write_json_atomic(json_path, summary)
    return summary
