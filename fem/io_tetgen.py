"""TetGen ``.node``, ``.ele`` and ``.face`` readers and writers (re-exported by :mod:`fem.io`).

Coordinates are in millimetres. The region tag is the first element attribute
(names are not stored, see :data:`fem.mesh.REGION_IDS`); ``.face`` holds the
boundary triangles. Node sets are not stored. Every write is atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .io_common import _region_name_for, atomic_write
from .mesh import REGION_IDS, MeshError, TetMesh, boundary_faces

__all__ = ["read_tetgen", "read_tetgen_face", "write_tetgen"]


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
