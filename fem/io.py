"""Mesh input and output: anything meshio reads or writes, plus TetGen files.

Geometry is in millimetres at every public boundary, as in :class:`fem.TetMesh`.
Region tags and node sets travel with the mesh:

* VTU (ParaView) and other meshio formats: cell data ``"region"`` (integer tag)
  and one 0/1 mask per region name, ``"region:<name>"``; node sets as point
  data masks ``"set:<name>"``.
* Abaqus ``.inp``: one ``*ELSET`` per region name and one ``*NSET`` per node set.
* TetGen ``.node/.ele``: the region tag as the first element attribute (names
  are not stored, see :data:`fem.mesh.REGION_IDS`); ``.face`` with the boundary
  triangles. Node sets are not stored.

When reading, region tags come from the cell data ``"region"``,
``"gmsh:physical"``, ``"medit:ref"``, ``"tetgen:ref"`` or ``"CellEntityIds"``
(the first present), else from element sets that partition the mesh (Abaqus),
else every element is ``"bulk"``. Every write is atomic: a temporary file in the
same folder is renamed over the target, so a failed write leaves nothing behind.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from .mesh import REGION_IDS, MeshError, TetMesh, boundary_faces

__all__ = [
    "atomic_write",
    "read_mesh",
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


def atomic_write(path: str | os.PathLike, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file next to ``path``, then rename it to ``path``.

    The temporary file keeps the suffix (format-sniffing writers work); on any error it
    is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
    )
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _region_name_for(tag: int) -> str:
    known = {v: k for k, v in REGION_IDS.items()}
    return known.get(int(tag), f"region{int(tag)}")


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
    for tag in np.unique(tags):
        if int(tag) not in names.values():
            names[_region_name_for(tag)] = int(tag)
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


def _node_sets(m, keep: np.ndarray) -> dict[str, np.ndarray]:
    """Node sets from ``set:<name>`` point data masks and meshio point sets (new numbering)."""
    new_index = np.full(len(m.points), -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    sets = {}
    for key, values in m.point_data.items():
        if key.startswith(_SET_PREFIX):
            sets[key[len(_SET_PREFIX) :]] = np.flatnonzero(np.asarray(values) > 0)
    for name, ids in m.point_sets.items():
        sets[name] = np.asarray(ids, dtype=np.int64)
    out = {}
    for name, ids in sets.items():
        ids = new_index[ids]
        out[name] = np.unique(ids[ids >= 0])
    return out


def _to_tetmesh(m, path: Path, *, orient: bool) -> TetMesh:
    types = [c.type for c in m.cells]
    tet_blocks = [i for i, t in enumerate(types) if t in ("tetra", "tetra10")]
    other_volumes = sorted({t for t in types if t in _VOLUME_CELLS} - {"tetra", "tetra10"})
    if not tet_blocks or other_volumes:
        found = ", ".join(sorted(set(types))) or "no cells"
        raise MeshError(f"{path}: expected a tetrahedral mesh, found cell types: {found}")
    if any(types[i] == "tetra10" for i in tet_blocks):
        log.warning("%s: quadratic tetrahedra read as linear ones (mid-side nodes dropped)", path)
    tets = np.vstack([np.asarray(m.cells[i].data)[:, :4] for i in tet_blocks]).astype(np.int64)
    tagged = _tags_from_cell_data(m, tet_blocks) or _tags_from_cell_sets(m, tet_blocks, len(tets))
    region, names = tagged or (np.full(len(tets), REGION_IDS["bulk"]), {"bulk": REGION_IDS["bulk"]})
    keep = np.unique(tets)
    if keep.size < len(m.points):
        log.info(
            "%s: %d nodes not used by any tetrahedron dropped", path, len(m.points) - keep.size
        )
    remap = np.full(len(m.points), -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    points = np.asarray(m.points, dtype=float)
    if points.shape[1] != 3:
        raise MeshError(f"{path}: expected 3-D points, got {points.shape[1]} coordinates")
    mesh = TetMesh(points[keep], remap[tets], region, names, _node_sets(m, keep))
    return mesh.oriented() if orient else mesh


def read_mesh(path: str | os.PathLike, *, orient: bool = True) -> TetMesh:
    """Read a tetrahedral mesh (coordinates in mm) from any format meshio reads.

    Parameters
    ----------
    path : str or path-like
        Mesh file: ``.vtu``, ``.inp``, ``.msh``, ``.mesh``, ``.node``/``.ele``, ...
    orient : bool
        Flip negatively oriented elements (:meth:`TetMesh.oriented`); degenerate
        elements raise :class:`fem.MeshError` either way.

    Returns
    -------
    TetMesh
        Linear tets (quadratic ones lose their mid-side nodes; unused nodes are
        dropped), region tags and node sets as described in the module docstring.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    MeshError
        The file cannot be parsed, or it holds no tetrahedra or other volume cells.
    """
    path = Path(path)
    if path.suffix.lower() in (".node", ".ele"):
        return read_tetgen(path, orient=orient)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    import meshio

    try:
        m = meshio.read(path)
    # meshio raises many kinds for bad files, and calls sys.exit when no reader succeeds
    except (Exception, SystemExit) as exc:  # noqa: BLE001
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    return _to_tetmesh(m, path, orient=orient)


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

    fmt = file_format or _format_for(path)
    m = _meshio_mesh(mesh, path, fmt, point_data, cell_data)
    atomic_write(path, lambda tmp: meshio.write(tmp, m, file_format=fmt))
    return path


def _format_for(path: Path) -> str:
    import meshio

    suffixes = "".join(path.suffixes[-2:]).lower()
    if path.suffix.lower() == ".msh":
        return "gmsh22"  # meshio's gmsh 4.1 writer drops the region tags
    for ext in (suffixes, path.suffix.lower()):
        if ext in meshio.extension_to_filetypes:
            return meshio.extension_to_filetypes[ext][0]
    raise ValueError(f"{path}: unknown mesh file suffix {path.suffix!r}")


def _data_lines(path: Path) -> list[list[str]]:
    """Whitespace-split lines of a TetGen file without comments and blank lines."""
    if not path.is_file():
        raise FileNotFoundError(f"TetGen file not found: {path}")
    rows = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            rows.append(line.split())
    if not rows:
        raise MeshError(f"{path}: empty TetGen file")
    return rows


def _table(path: Path, rows: list[list[str]], n: int, min_cols: int) -> np.ndarray:
    body = rows[1 : n + 1]
    if len(body) != n or any(len(r) < min_cols for r in body):
        raise MeshError(f"{path}: expected {n} records of at least {min_cols} numbers")
    try:
        return np.array([[float(v) for v in r] for r in body])
    except ValueError as exc:
        raise MeshError(f"{path}: non-numeric entry ({exc})") from exc


def _basename(path: str | os.PathLike) -> Path:
    """TetGen basename: the path without a ``.node``, ``.ele`` or ``.face`` suffix."""
    p = Path(path)
    return p.with_suffix("") if p.suffix.lower() in (".node", ".ele", ".face") else p


def _read_node(path: Path) -> tuple[np.ndarray, int]:
    rows = _data_lines(path)
    try:
        n, dim = int(rows[0][0]), int(rows[0][1])
    except (IndexError, ValueError) as exc:
        raise MeshError(f"{path}: bad .node header {' '.join(rows[0])!r}") from exc
    if dim != 3 or n < 1:
        raise MeshError(f"{path}: expected 3-D nodes, got {n} nodes of dimension {dim}")
    table = _table(path, rows, n, 4)
    first = int(table[0, 0])
    if not np.array_equal(table[:, 0], np.arange(first, first + n)):
        raise MeshError(f"{path}: nodes are not numbered consecutively")
    return table[:, 1:4], first


def read_tetgen(path: str | os.PathLike, *, orient: bool = True) -> TetMesh:
    """Read TetGen ``.node`` and ``.ele`` files (either path, or the basename).

    Parameters
    ----------
    path : str or path-like
        ``mesh.node``, ``mesh.ele`` or ``mesh``; both files must exist.
    orient : bool
        Flip negatively oriented elements.

    Returns
    -------
    TetMesh
        Coordinates as stored (mm); the first element attribute, when present,
        is the region tag (else ``bulk``).
    """
    base = _basename(path)
    nodes, first = _read_node(base.with_name(base.name + ".node"))
    ele = base.with_name(base.name + ".ele")
    rows = _data_lines(ele)
    try:
        n, per, n_attr = (int(v) for v in (rows[0] + ["0"])[:3])
    except ValueError as exc:
        raise MeshError(f"{ele}: bad .ele header {' '.join(rows[0])!r}") from exc
    if per != 4:
        raise MeshError(f"{ele}: expected 4-node tetrahedra, got {per} nodes per element")
    table = _table(ele, rows, n, 5 + n_attr).astype(np.int64)
    tets = table[:, 1:5] - first
    if n_attr:
        region = table[:, 5]
        names = {_region_name_for(t): int(t) for t in np.unique(region)}
    else:
        region, names = np.full(n, REGION_IDS["bulk"]), {"bulk": REGION_IDS["bulk"]}
    mesh = TetMesh(nodes, tets, region, names)
    return mesh.oriented() if orient else mesh


def read_tetgen_face(
    path: str | os.PathLike, *, node_path: str | os.PathLike | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a TetGen ``.face`` file (boundary triangles and their markers).

    Parameters
    ----------
    path : str or path-like
        The ``.face`` file.
    node_path : str or path-like, optional
        The matching ``.node`` file, whose first index (0 or 1) sets the numbering;
        defaults to the ``.node`` file of the same basename. When it does not exist
        the face file's own first index is taken as the base.

    Returns
    -------
    faces : ndarray of int, shape (k, 3)
        Zero-based node indices.
    markers : ndarray of int, shape (k,)
        Boundary markers (zeros when the file has none).
    """
    path = Path(path)
    rows = _data_lines(path)
    try:
        n, has_marker = (int(v) for v in (rows[0] + ["0"])[:2])
    except ValueError as exc:
        raise MeshError(f"{path}: bad .face header {' '.join(rows[0])!r}") from exc
    table = _table(path, rows, n, 4 + (has_marker > 0)).astype(np.int64)
    node_file = Path(node_path) if node_path is not None else path.with_suffix(".node")
    first = _read_node(node_file)[1] if node_file.is_file() else int(table[0, 0]) if n else 0
    faces = table[:, 1:4] - first
    markers = table[:, 4] if has_marker else np.zeros(n, dtype=np.int64)
    if faces.size and faces.min() < 0:
        raise MeshError(f"{path}: node index below the first index {first} of {node_file.name}")
    return faces, markers


def write_tetgen(
    mesh: TetMesh, basename: str | os.PathLike, *, first_index: int = 1, faces: bool = True
) -> tuple[Path, ...]:
    """Write TetGen ``.node``, ``.ele`` (region tag as attribute) and ``.face`` files.

    Parameters
    ----------
    mesh : TetMesh
    basename : str or path-like
        Path without suffix (a ``.node``/``.ele`` suffix is stripped).
    first_index : {0, 1}
        Number of the first node, element and face (TetGen's default is 1).
    faces : bool
        Also write the boundary triangles (marker 1, outward oriented) as ``.face``.

    Returns
    -------
    tuple of Path
        The files written, each atomically.
    """
    if first_index not in (0, 1):
        raise ValueError(f"first_index must be 0 or 1, got {first_index}")
    base = _basename(basename)
    b = first_index
    ids = np.arange(mesh.n_nodes) + b
    node_lines = [f"{mesh.n_nodes} 3 0 0"]
    node_lines += [
        f"{i} {x!r} {y!r} {z!r}" for i, (x, y, z) in zip(ids, mesh.nodes_mm.tolist(), strict=True)
    ]
    ele_lines = [f"{mesh.n_tets} 4 1"]
    ele_lines += [
        f"{k + b} {t[0]} {t[1]} {t[2]} {t[3]} {r}"
        for k, (t, r) in enumerate(zip((mesh.tets + b).tolist(), mesh.region.tolist(), strict=True))
    ]
    out = {".node": node_lines, ".ele": ele_lines}
    if faces:
        bf = boundary_faces(mesh.tets) + b
        out[".face"] = [f"{len(bf)} 1"] + [
            f"{k + b} {f[0]} {f[1]} {f[2]} 1" for k, f in enumerate(bf.tolist())
        ]
    written = []
    for suffix, lines in out.items():
        target = base.with_name(base.name + suffix)
        text = "# written by phantom-calib fem.io\n" + "\n".join(lines) + "\n"
        atomic_write(target, lambda tmp, text=text: tmp.write_text(text))
        written.append(target)
    return tuple(written)
