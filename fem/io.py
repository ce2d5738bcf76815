"""Mesh input and output: anything meshio reads or writes, plus TetGen files.

Geometry is in millimetres at every public boundary, as in :class:`fem.TetMesh`.
Region tags and node sets travel with the mesh:

* VTU (ParaView) and other meshio formats: cell data ``"region"`` (integer tag)
  and one 0/1 mask per region name, ``"region:<name>"``; node sets as point
  data masks ``"set:<name>"``. Medit ``.mesh`` keeps the tags only (its regions read
  back as ``"region<tag>"``).
* Abaqus ``.inp``: one ``*ELSET`` per region name and one ``*NSET`` per node set.
* TetGen ``.node/.ele``: the region tag as the first element attribute (names
  are not stored, see :data:`fem.mesh.REGION_IDS`); ``.face`` with the boundary
  triangles. Node sets are not stored.

When reading, region tags come from the cell data ``"region"``,
``"gmsh:physical"``, ``"medit:ref"``, ``"tetgen:ref"`` or ``"CellEntityIds"``
(the first present), else from element sets that partition the mesh (Abaqus),
else every element is ``"bulk"``. Their names come from the ``"region:<name>"`` masks
(the toolkit's own files but ``.mesh``), Gmsh's physical names or the element sets; a tag without a
name is ``"region<tag>"``, or ``"bulk"`` where it is the file's only one (another tool's
numbers are not :data:`fem.mesh.REGION_IDS`). Every write is atomic: a temporary file in the
same folder is renamed over the target, so a failed write leaves nothing behind.

The TetGen readers and writers live in :mod:`fem.io_tetgen` and :func:`atomic_write`
in :mod:`fem.io_common`; both are re-exported here.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io_common import atomic_write
from .io_tetgen import read_tetgen, read_tetgen_face, write_tetgen
from .mesh import REGION_IDS, MeshError, TetMesh

__all__ = [
    "InputPoints",
    "atomic_write",
    "mesh_format_for",
    "read_mesh",
    "read_meshio",
    "read_tetgen",
    "read_tetgen_face",
    "write_mesh",
    "write_tetgen",
]

log = logging.getLogger(__name__)

_TAG_KEYS = ("region", "gmsh:physical", "medit:ref", "tetgen:ref", "CellEntityIds")
_VOLUME_CELLS = {"tetra", "tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge"}
_VOLUME_CELLS |= {"wedge15", "pyramid", "pyramid13", "polyhedron"}
_SET_PREFIX, _REGION_PREFIX = "set:", "region:"


@dataclass(frozen=True)
class InputPoints:
    """The point array of a mesh file and where the nodes of the mesh read from it came from.

    :func:`read_mesh` drops the points of the file that no tetrahedron uses (and the
    mid-side nodes of quadratic tetrahedra) and numbers the rest anew; this maps results
    on the read mesh back onto the file's own point numbering.

    Attributes
    ----------
    points_mm : ndarray, shape (n_points, 3)
        Every point of the file, in the file's order, mm.
    node_index : ndarray of int, shape (n_nodes,)
        The file's point number of each node of the read :class:`TetMesh`.
    midside : ndarray of int, shape (n_midside, 3)
        The mid-side points of quadratic tetrahedra the read mesh dropped, one row
        ``[point, a, b]`` each: the point is on the edge between the file's points ``a``
        and ``b`` (by its slot in meshio's order, checked by position: see
        ``_midside_points``); empty for linear input.
    """

    points_mm: np.ndarray
    node_index: np.ndarray
    midside: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))

    @property
    def n_points(self) -> int:
        """Number of points in the file."""
        return len(self.points_mm)

    def scatter(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Per-node values of the read mesh as per-point values of the file.

        Parameters
        ----------
        values : array_like, shape (n_nodes,) or (n_nodes, k)
            One row per node of the read mesh.
        fill : float
            The value of the points the read mesh dropped.

        Returns
        -------
        ndarray, shape (n_points,) or (n_points, k)
            Float rows in the file's point order; ``fill`` where no node came from.

        Raises
        ------
        ValueError
            ``values`` does not have one row per node.
        """
        v = np.asarray(values, dtype=float)
        if v.ndim == 0 or len(v) != len(self.node_index):
            raise ValueError(
                f"expected one row per mesh node ({len(self.node_index)}), got shape {v.shape}"
            )
        out = np.full((self.n_points, *v.shape[1:]), fill, dtype=float)
        out[self.node_index] = v
        return out


def _tags_from_cell_data(m, tet_blocks: list[int]) -> tuple[np.ndarray, dict] | None:
    for key in _TAG_KEYS:
        if key in m.cell_data:
            tags = np.concatenate([np.asarray(m.cell_data[key][i]) for i in tet_blocks])
            tags = tags.astype(np.int64).reshape(len(tags), -1)[:, 0]
            return tags, _names_for_tags(m, key, tags, tet_blocks)
    return None


def _names_for_tags(m, key: str, tags: np.ndarray, tet_blocks: list[int]) -> dict:
    names = {}
    for k in m.cell_data:
        if k.startswith(_REGION_PREFIX):
            mask = np.concatenate([np.asarray(m.cell_data[k][i]) for i in tet_blocks]) > 0
            if mask.any():
                names[k[len(_REGION_PREFIX) :]] = int(tags[mask][0])
    if key == "gmsh:physical":  # field_data: name -> [tag, dimension]
        for name, (tag, dim) in ((n, np.asarray(v)[:2]) for n, v in m.field_data.items()):
            if dim == 3:
                names[name] = int(tag)
    bare = [int(t) for t in np.unique(tags) if int(t) not in names.values()]
    if len(bare) == 1 and not names:  # one material: the bulk, whatever its number
        return {"bulk": bare[0]}
    # review BU, F11: another tool's numbers are not the toolkit's (MMG numbers a body 3,
    # which was read as "skin"); the toolkit's own files name their regions
    names.update({f"region{t}": t for t in bare})
    return names


def _tags_from_cell_sets(m, tet_blocks: list[int], n_tets: int):
    """Regions from element sets (Abaqus ``*ELSET``) when they partition the elements."""
    region = np.zeros(n_tets, dtype=np.int64)
    names: dict[str, int] = {}
    offsets = np.cumsum([0] + [len(m.cells[i].data) for i in tet_blocks])
    for name, per_block in m.cell_sets.items():
        idx = [np.asarray(per_block[b]) + o for b, o in zip(tet_blocks, offsets, strict=False)]
        idx = np.concatenate(idx).astype(np.int64) if idx else np.zeros(0, np.int64)
        if idx.size == 0:
            continue
        tag = REGION_IDS.get(name, max([*REGION_IDS.values(), *names.values()]) + 1)
        names[name] = tag
        if np.any(region[idx] != 0):
            return None
        region[idx] = tag
    if not names or np.any(region == 0):
        return None
    return region, names


#: Node sets read from a file's own labels under any case, and from labelled surfaces.
_KNOWN_SETS = ("back", "nipple")


def _node_sets(m, keep: np.ndarray) -> dict[str, np.ndarray]:
    """Node sets from ``set:<name>`` point data masks and meshio point sets (new numbering)."""
    new_index = np.full(len(m.points), -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    sets = {}
    for key, values in m.point_data.items():
        if key.startswith(_SET_PREFIX):
            sets[key[len(_SET_PREFIX) :]] = np.flatnonzero(np.asarray(values) > 0)
    for name, ids in m.point_sets.items():
        # Abaqus names are case-insensitive and usually upper case (NSET=BACK): review BU
        sets[name.lower() if name.lower() in _KNOWN_SETS else name] = np.asarray(ids, np.int64)
    # a labelled surface (a Gmsh physical surface "back"): its triangles' nodes, by cell set
    # (MSH 4) or by physical tag (MSH 2: the names in field_data only)
    labels = dict(m.cell_sets)
    tags = m.cell_data.get("gmsh:physical")
    for name, (tag, *_dim) in (m.field_data or {}).items() if tags is not None else ():
        labels.setdefault(name, [np.flatnonzero(np.asarray(t) == tag) for t in tags])
    for name, blocks in labels.items():
        if name.lower() in _KNOWN_SETS and name.lower() not in sets:
            nodes = [
                np.asarray(c.data)[np.asarray(idx, dtype=np.int64)].ravel()
                for c, idx in zip(m.cells, blocks, strict=False)
                if c.type in ("triangle", "triangle6", "vertex") and idx is not None
            ]
            if any(len(n) for n in nodes):
                sets[name.lower()] = np.unique(np.concatenate(nodes))
    out = {}
    for name, ids in sets.items():
        ids = new_index[ids]
        out[name] = np.unique(ids[ids >= 0])
    return out


def _to_tetmesh(m, path: Path, *, orient: bool) -> tuple[TetMesh, InputPoints]:
    types = [c.type for c in m.cells]
    tet_blocks = [i for i, t in enumerate(types) if t in ("tetra", "tetra10")]
    other_volumes = sorted({t for t in types if t in _VOLUME_CELLS} - {"tetra", "tetra10"})
    if not tet_blocks or other_volumes:
        found = ", ".join(sorted(set(types))) or "no cells"
        raise MeshError(f"{path}: expected a tetrahedral mesh, found cell types: {found}")
    if any(types[i] == "tetra10" for i in tet_blocks):
        log.warning(
            "%s: quadratic tetrahedra read as linear ones (straight edges; their mid-side "
            "points are not nodes of the mesh read)",
            path,
        )
    tets = np.vstack([np.asarray(m.cells[i].data)[:, :4] for i in tet_blocks]).astype(np.int64)
    if tets.size and (tets.min() < 0 or tets.max() >= len(m.points)):  # was an IndexError
        raise MeshError(
            f"{path}: tetrahedra index points {tets.min()}..{tets.max()}, but the file has "
            f"{len(m.points)} points"
        )
    tagged = _tags_from_cell_data(m, tet_blocks) or _tags_from_cell_sets(m, tet_blocks, len(tets))
    region, names = tagged or (np.full(len(tets), REGION_IDS["bulk"]), {"bulk": REGION_IDS["bulk"]})
    keep, remap = _used_points(path, len(m.points), tets)
    points = np.asarray(m.points, dtype=float)
    if points.shape[1] != 3:
        raise MeshError(f"{path}: expected 3-D points, got {points.shape[1]} coordinates")
    mesh = TetMesh(points[keep], remap[tets], region, names, _node_sets(m, keep))
    tet10 = [np.asarray(m.cells[i].data) for i in tet_blocks if types[i] == "tetra10"]
    if tet10:
        inputs = InputPoints(points, keep, _midside_points(path, points, np.vstack(tet10), keep))
    else:
        inputs = InputPoints(points, keep)
    return (mesh.oriented() if orient else mesh), inputs


def _used_points(path, n_points: int, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points some tetrahedron uses, and each point's new number (-1: dropped).

    The file's unused points are dropped, said at info level; ``keep`` is
    :attr:`InputPoints.node_index`.
    """
    keep = np.unique(tets)
    if keep.size < n_points:
        log.info("%s: %d nodes not used by any tetrahedron dropped", path, n_points - keep.size)
    remap = np.full(n_points, -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    return keep, remap


#: The six edges of a tetrahedron in meshio's (VTK's) order of a quadratic one's mid-side
#: points, which meshio gives for every format it reads (it reorders Gmsh's)
_TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
#: A mid-side point this far from its edge's midpoint (a fraction of the edge's length) is
#: not taken to be on that edge: the file's order is not meshio's, or the element is folded.
#: An adjacent edge's midpoint lies half an edge away in a regular tetrahedron.
MIDSIDE_OFF_EDGE = 0.3


def _midside_points(path, points: np.ndarray, cells: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``[point, a, b]`` of each mid-side point of quadratic tetrahedra (rows of 10 points).

    Each of a cell's last six points is on the edge of :data:`_TET_EDGES` in its slot
    (review BV, F1: matching by the nearest midpoint swapped the points of curved slivers,
    whose opposite edges' midpoints nearly meet). Left out, with a warning: a point farther
    than :data:`MIDSIDE_OFF_EDGE` of its edge's length from the edge's midpoint, one that
    cells place on different edges, and one that is also a corner of a tetrahedron (review
    BV, F2: it was moved twice). Points off their straight edge's midpoint (curved
    elements, solved straight) are counted in a warning.
    """
    corners = cells[:, :4]
    a, b = corners[:, _TET_EDGES[:, 0]], corners[:, _TET_EDGES[:, 1]]  # (C, 6)
    length = np.linalg.norm(points[b] - points[a], axis=-1)
    off = np.linalg.norm(points[cells[:, 4:10]] - 0.5 * (points[a] + points[b]), axis=-1)
    rel = off / np.where(length > 0, length, np.inf)
    flat = np.stack([cells[:, 4:10], np.minimum(a, b), np.maximum(a, b)], axis=-1).reshape(-1, 3)
    rel = rel.ravel()
    point_ids, n_edges = np.unique(np.unique(flat, axis=0)[:, 0], return_counts=True)
    refused = np.union1d(flat[rel > MIDSIDE_OFF_EDGE, 0], point_ids[n_edges > 1])
    refused = np.union1d(refused, np.intersect1d(flat[:, 0], keep))
    good = ~np.isin(flat[:, 0], refused)
    _, first = np.unique(flat[good, 0], return_index=True)  # a point shared by cells: once
    out = flat[good][first].astype(np.int64)
    curved = np.unique(flat[good & (rel > 1e-6), 0])
    if len(curved):
        log.warning(
            "%s: %d mid-side points lie off their straight edge's midpoint (up to %.2g of the "
            "edge's length): the elements are solved with straight edges",
            path,
            len(curved),
            float(rel[good].max()),
        )
    if len(refused):
        log.warning(
            "%s: %d mid-side points are not on their edge in meshio's order of a quadratic "
            "tetrahedron's points (more than %g of the edge's length from its midpoint, on "
            "different edges in different cells, or a corner of another tetrahedron): they "
            "are not solved",
            path,
            len(refused),
            MIDSIDE_OFF_EDGE,
        )
    return out


def read_mesh(
    path: str | os.PathLike, *, orient: bool = True, return_input_points: bool = False
) -> TetMesh | tuple[TetMesh, InputPoints]:
    """Read a tetrahedral mesh (coordinates in mm) from any format meshio reads.

    Parameters
    ----------
    path : str or path-like
        Mesh file: ``.vtu``, ``.inp``, ``.msh``, ``.mesh``, ``.node``/``.ele``, ...
    orient : bool
        Flip negatively oriented elements (:meth:`TetMesh.oriented`); degenerate
        elements raise :class:`fem.MeshError` either way.
    return_input_points : bool
        Also return the file's points and the file point number of each mesh node
        (:class:`InputPoints`), to write results in the file's own numbering.

    Returns
    -------
    TetMesh
        Linear tets (quadratic ones lose their mid-side nodes; unused nodes are
        dropped and the rest numbered anew), region tags and node sets as described
        in the module docstring.
    InputPoints
        Only with ``return_input_points``.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    MeshError
        The file cannot be parsed, or it holds no tetrahedra or other volume cells.
    """
    path = Path(path)
    if path.suffix.lower() in (".node", ".ele"):
        mesh = read_tetgen(path, orient=orient)
        points = mesh.nodes_mm.copy()
        keep, remap = _used_points(path, mesh.n_nodes, mesh.tets)
        if keep.size < mesh.n_nodes:  # review BU: they failed after the solve, unnamed
            mesh = TetMesh(points[keep], remap[mesh.tets], mesh.region, mesh.region_names)
        return (mesh, InputPoints(points, keep)) if return_input_points else mesh
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: the file is empty")

    def read(p: Path):
        import meshio

        m = _read_hybrid_abaqus(p) if p.suffix.lower() == ".inp" else None
        return meshio.read(p) if m is None else m

    mesh, points = _to_tetmesh(read_meshio(path, read=read), path, orient=orient)
    return (mesh, points) if return_input_points else mesh


def read_meshio(path: str | Path, *, read: Callable | None = None, error: Callable | None = None):
    """A file read by meshio, every failure one exception that names the file.

    meshio raises many kinds for bad files and calls ``sys.exit`` when no reader takes
    one; what it prints is kept for the message.

    Parameters
    ----------
    path : str or Path
    read : callable, optional
        ``read(path)`` in place of ``meshio.read``.
    error : callable, optional
        ``error(why)`` gives the exception to raise (default a :class:`MeshError`
        "``path``: cannot read mesh (why)").

    Returns
    -------
    meshio.Mesh
    """
    import contextlib
    import io

    import meshio

    path, said = Path(path), io.StringIO()
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            return (read or meshio.read)(path)
    except (Exception, SystemExit) as exc:
        why = " ".join(said.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        raise (error or (lambda w: MeshError(f"{path}: cannot read mesh ({w})")))(why) from exc


def _read_hybrid_abaqus(path: Path):
    """An Abaqus file of hybrid tetrahedra (``C3D4H``, ``C3D10H``) read as plain ones.

    Hybrid elements are what an Abaqus model of nearly incompressible tissue uses; meshio
    reads their type as ``tetra4`` and then fails on it (review BU: "cannot read mesh
    (KeyError: 'tetra4')"). The nodes are the same: the solve picks its own formulation
    (``--formulation``). None where the file has none (read as it is).
    """
    import re
    import tempfile

    import meshio

    text = path.read_text(errors="replace")
    plain, n = re.subn(r"(?i)(type\s*=\s*c3d(?:4|10))h\b", r"\1", text)
    if not n:
        return None
    log.info("%s: hybrid tetrahedra (C3D4H/C3D10H) read as C3D4/C3D10", path)
    with tempfile.TemporaryDirectory() as tmp:
        plain_path = Path(tmp) / path.name
        plain_path.write_text(plain)
        return meshio.read(plain_path)


def _meshio_mesh(mesh: TetMesh, path: Path, fmt: str, point_data, cell_data):
    import meshio

    pdata = {k: np.asarray(v) for k, v in (point_data or {}).items()}
    cdata = {k: [np.asarray(v)] for k, v in (cell_data or {}).items()}
    for arr, n, what in [(v, mesh.n_nodes, "point") for v in pdata.values()] + [
        (v[0], mesh.n_tets, "cell") for v in cdata.values()
    ]:
        if len(arr) != n:
            raise ValueError(f"{path}: {what} data needs {n} rows, got {len(arr)}")
    point_sets, cell_sets, field_data = {}, {}, {}
    if fmt.startswith("gmsh"):  # gmsh keeps tags only as physical/geometrical entities
        cdata["gmsh:physical"] = cdata["gmsh:geometrical"] = [mesh.region.astype(np.int32)]
        field_data = {n: np.array([t, 3]) for n, t in mesh.region_names.items()}
    if fmt == "abaqus":
        point_sets = {k: np.asarray(v) for k, v in mesh.node_sets.items()}
        cell_sets = {n: [np.flatnonzero(mesh.region == t)] for n, t in mesh.region_names.items()}
    else:
        cdata["region"] = [mesh.region.astype(np.int32)]
        for name, tag in mesh.region_names.items():
            cdata[_REGION_PREFIX + name] = [(mesh.region == tag).astype(np.uint8)]
        for name, ids in mesh.node_sets.items():
            mask = np.zeros(mesh.n_nodes, dtype=np.uint8)
            mask[ids] = 1
            pdata[_SET_PREFIX + name] = mask
    return meshio.Mesh(
        mesh.nodes_mm,
        [("tetra", mesh.tets)],
        point_data=pdata,
        cell_data=cdata,
        point_sets=point_sets,
        cell_sets=cell_sets,
        field_data=field_data,
    )


def write_mesh(
    mesh: TetMesh,
    path: str | os.PathLike,
    *,
    point_data: Mapping[str, np.ndarray] | None = None,
    cell_data: Mapping[str, np.ndarray] | None = None,
    file_format: str | None = None,
) -> Path:
    """Write a mesh (mm) with its regions, node sets and extra data, atomically.

    Parameters
    ----------
    mesh : TetMesh
    path : str or path-like
        Target file; the format follows the suffix (``.vtu``, ``.inp``, ``.msh``,
        ...) unless ``file_format`` is given. ``.node``/``.ele`` write TetGen files.
    point_data : mapping of str to ndarray, optional
        Per-node arrays, shape (n_nodes,) or (n_nodes, k), e.g. ``displacement_mm``.
    cell_data : mapping of str to ndarray, optional
        Per-element arrays, shape (n_tets,) or (n_tets, k).
    file_format : str, optional
        A meshio format name, overriding the suffix.

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    if file_format is None and path.suffix.lower() in (".node", ".ele"):
        write_tetgen(mesh, path.with_suffix(""))
        return path
    import meshio

    fmt = file_format or mesh_format_for(path)
    m = _meshio_mesh(mesh, path, fmt, point_data, cell_data)
    atomic_write(path, lambda tmp: meshio.write(tmp, m, file_format=fmt))
    return path


def mesh_format_for(path: str | Path) -> str:
    """The meshio format :func:`write_mesh` writes ``path`` in (by its suffix).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    str
        A meshio file format (``.msh`` is ``gmsh22``, whose writer keeps the region tags).

    Raises
    ------
    ValueError
        A suffix meshio does not know.
    """
    import meshio

    path = Path(path)

    suffixes = "".join(path.suffixes[-2:]).lower()
    if path.suffix.lower() == ".msh":
        return "gmsh22"  # meshio's gmsh 4.1 writer drops the region tags
    for ext in (suffixes, path.suffix.lower()):
        if ext in meshio.extension_to_filetypes:
            return meshio.extension_to_filetypes[ext][0]
    raise ValueError(f"{path}: unknown mesh file suffix {path.suffix!r}")
