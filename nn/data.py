"""Read a sweep store (format ``phantom-calib.sweep`` v1) into arrays, checking it.

The format is documented in the README ("Sweep store") and in ``calib.sweep.store``;
this module reads it without importing ``calib`` (``nn`` sits below it). Only solved
scenarios (``results/status == 1``) are returned.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["StoreFormatError", "SweepData", "load_sweep", "training_scenarios"]

log = logging.getLogger(__name__)
FORMAT, FORMAT_VERSION = "phantom-calib.sweep", 1
_ARRAYS = (
    "mesh/nodes_mm",
    "mesh/tets",
    "mesh/surface_nodes",
    "mesh/back_nodes",
    "mesh/boundary_faces",
    "scenarios/gravity_phantom",
    "scenarios/gravity_ref",
    "scenarios/c1_pa",
    "scenarios/load_per_m",
    "scenarios/role",
    "scenarios/plane",
    "scenarios/angle_deg",
    "results/status",
    "results/displacement_mm",
    "results/tumour_mm",
    "results/nipple_mm",
)


#: The root attributes the reader needs besides ``format``, ``format_version`` and ``model``
#: (a store without ``codes`` is read with the codes phantom-calib writes).
ROOT_KEYS = ("mesh_sha256", "n_scenarios")
#: What the surrogates read of the store's ``model`` block.
MODEL_KEYS = ("c1_pa", "density_kg_m3", "g_m_s2", "R_ref_from_phantom", "nipple_node")
_SCENARIO_KEYS = ("gravity_ref", "gravity_phantom", "c1_pa", "load_per_m", "role", "plane")


class StoreFormatError(ValueError):
    """A sweep store that cannot be used: missing, truncated, or inconsistent (the file)."""


@dataclass(frozen=True)
class SweepData:
    """The solved scenarios of a sweep store.

    Attributes
    ----------
    path : Path
    nodes_mm : ndarray, shape (N, 3)
        The reference mesh, reference-scan frame, mm: stress-free, or the loaded mesh of
        a prestressed reference (``model["prestress"]`` set; review BF).
    tets : ndarray, shape (T, 4)
    surface_nodes, back_nodes : ndarray of int
    boundary_faces : ndarray, shape (F, 3)
    index : ndarray of int, shape (S,)
        Scenario numbers in the store.
    gravity_ref, gravity_phantom : ndarray, shape (S, 3)
        Unit gravity directions.
    c1_pa : ndarray, shape (S,)
    load_per_m : ndarray, shape (S, 3)
        ``rho g gravity_ref / c1`` (1/m).
    role : ndarray of str, shape (S,)
        ``train`` or ``validation``.
    plane : ndarray of str, shape (S,)
    angle_deg : ndarray, shape (S,)
    displacement_mm : ndarray, shape (S, N, 3)
    tumour_mm, nipple_mm : ndarray, shape (S, 3)
    model : dict
        The store's ``model`` attribute (c1, nu, density, g, R_ref_from_phantom, ...).
    mesh_sha256 : str
    attrs : dict
        All root attributes.
    failed_load_per_m : ndarray, shape (F, 3)
        The loads of the scenarios the sweep could not solve (status failed), which no
        subset drops.
    """

    path: Path
    nodes_mm: np.ndarray
    tets: np.ndarray
    surface_nodes: np.ndarray
    back_nodes: np.ndarray
    boundary_faces: np.ndarray
    index: np.ndarray
    gravity_ref: np.ndarray
    gravity_phantom: np.ndarray
    c1_pa: np.ndarray
    load_per_m: np.ndarray
    role: np.ndarray
    plane: np.ndarray
    angle_deg: np.ndarray
    displacement_mm: np.ndarray
    tumour_mm: np.ndarray
    nipple_mm: np.ndarray
    model: dict
    mesh_sha256: str
    attrs: dict = field(repr=False, default_factory=dict)
    failed_load_per_m: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))

    def __repr__(self) -> str:  # review BW, F4: 39,000 characters of arrays
        roles = ", ".join(f"{int(np.sum(self.role == r))} {r}" for r in np.unique(self.role))
        return (
            f"SweepData({len(self)} scenarios: {roles or 'none'}; {len(self.nodes_mm)} nodes, "
            f"{len(self.tets)} tetrahedra; {str(self.path)!r})"
        )

    def __len__(self) -> int:
        return len(self.index)

    @property
    def has_tumour(self) -> bool:
        """True when the model has a tumour centre (its displacements are finite)."""
        return bool(np.all(np.isfinite(self.tumour_mm)))

    def subset(self, mask: np.ndarray) -> SweepData:
        """The scenarios selected by a boolean mask or an index array."""
        from dataclasses import replace

        sel = np.asarray(mask)
        per = (
            "index",
            "gravity_ref",
            "gravity_phantom",
            "c1_pa",
            "load_per_m",
            "role",
            "plane",
            "angle_deg",
            "displacement_mm",
            "tumour_mm",
            "nipple_mm",
        )
        return replace(self, **{k: getattr(self, k)[sel] for k in per})


def _mesh_sha256(nodes: np.ndarray, tets: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(nodes, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(tets, dtype="<i8").tobytes())
    return h.hexdigest()


def _read_attrs(path: Path) -> dict:
    meta = path / "zarr.json"
    if not path.is_dir():
        raise StoreFormatError(f"{path}: no such sweep store folder")
    if not meta.is_file():
        raise StoreFormatError(
            f"{meta} not found: {path} is not a sweep store (or a truncated one)"
        )
    try:
        attrs = json.loads(meta.read_text()).get("attributes", {})
    except (OSError, ValueError) as exc:
        raise StoreFormatError(f"{meta}: not valid JSON ({exc})") from exc
    if attrs.get("format") != FORMAT:
        raise StoreFormatError(f"{meta}: not a {FORMAT} store (format {attrs.get('format')!r})")
    version = attrs.get("format_version")
    if version != FORMAT_VERSION or isinstance(version, bool):  # True == 1
        # review BF: say what to do (and "1" as text read as "format version 1")
        newer = (
            isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION
        )
        raise StoreFormatError(
            f"{meta}: format version {version!r}; this reader knows {FORMAT_VERSION}"
            + (
                " (written by a newer phantom-calib: upgrade it to read this store)"
                if newer
                else ""
            )
        )
    return attrs


def _open_arrays(path: Path) -> dict:
    import zarr

    out = {}
    for name in _ARRAYS:
        meta = path / name / "zarr.json"
        if not meta.is_file():
            raise StoreFormatError(f"{meta} not found (truncated store)")
        try:
            out[name] = zarr.open_array(path / name, mode="r")
        except Exception as exc:  # zarr raises many kinds on bad metadata
            raise StoreFormatError(f"{meta}: cannot open ({type(exc).__name__}: {exc})") from exc
    return out


def training_scenarios(data: SweepData) -> SweepData:
    """The ``role == "train"`` scenarios, refused where too few or where loads repeat.

    Two scenarios of one load ``rho g gravity / c1`` (a store swept with a c1 axis of
    equal values, or merged from two sweeps) are the same FE solution: a leave-one-out
    error sees each point's copy (0 at every kernel width: review AD's duplicated store
    picked a width whose validation error was 11 times the right one), and a held-out
    split by scenario trains on its test points.

    Raises
    ------
    ValueError
        Fewer than 2 training scenarios, or two of one load (to 1e-12 relative).
    """
    train = data.subset(data.role == "train")
    if len(train) < 2:
        raise ValueError(f"{data.path}: {len(train)} training scenario(s); need at least 2")
    from scipy.spatial import cKDTree

    q = train.load_per_m / np.linalg.norm(train.load_per_m, axis=1).max()
    # within 1e-12 of each other (review BT: rounding to 12 decimals let two loads 2.5e-16
    # apart on either side of a rounding boundary through)
    pairs = cKDTree(q).query_pairs(1e-12, output_type="ndarray")
    if len(pairs):
        k = int(train.index[pairs[:, 1].min()])
        raise ValueError(
            f"{data.path}: {len(np.unique(pairs[:, 1]))} training scenario(s) repeat another's "
            f"load rho g gravity / c1 (scenario {k} among them): sweep without repeats"
        )
    return train


def load_sweep(path: str | Path, *, allow_pending: bool = True) -> SweepData:
    """Read the solved scenarios of a sweep store.

    Parameters
    ----------
    path : path
        The store folder (``SWEEP``).
    allow_pending : bool
        Accept a store with pending scenarios (a running or interrupted sweep), logging
        how many; else raise.

    Returns
    -------
    SweepData

    Raises
    ------
    StoreFormatError
        Not a sweep store, another format version, a missing array or chunk of a solved
        scenario (truncated; a tumour chunk too where the model has a tumour), an
        unreadable chunk, a ``model`` block without :data:`MODEL_KEYS`, mesh arrays that
        do not match ``mesh_sha256``, result shapes of another mesh, node sets past the
        mesh, non-finite scenario arrays (``angle_deg`` aside), c1 <= 0, role or plane
        codes outside ``codes``, or no solved scenario.
    """
    path = Path(path)
    attrs = _read_attrs(path)
    absent = [k for k in ROOT_KEYS if k not in attrs]
    if absent:  # review BF: a missing n_scenarios read as "results of another mesh?"
        raise StoreFormatError(
            f"{path / 'zarr.json'}: the store's root attributes lack {', '.join(absent)} "
            "(written by `phantom-calib sweep`)"
        )
    model = attrs.get("model")
    lacking = [k for k in MODEL_KEYS if not isinstance(model, dict) or model.get(k) is None]
    if lacking:
        raise StoreFormatError(
            f"{path / 'zarr.json'}: the store's `model` block lacks {', '.join(lacking)} "
            "(written by `phantom-calib sweep`)"
        )
    arr = _open_arrays(path)

    def read(name: str, index=slice(None), chunk: str = "") -> np.ndarray:
        # review AD: a corrupt chunk gave the codec's words only ("Zstd decompression
        # error"), naming no file
        try:
            return np.asarray(arr[name][index])
        except Exception as exc:  # zarr and its codecs raise many kinds
            raise StoreFormatError(
                f"{path / name}{chunk}: unreadable ({type(exc).__name__}: {exc}); the store "
                "is damaged: sweep again into a fresh --out"
            ) from exc

    nodes = read("mesh/nodes_mm")
    tets = read("mesh/tets")
    if _mesh_sha256(nodes, tets) != attrs.get("mesh_sha256"):
        raise StoreFormatError(
            f"{path / 'mesh'}: mesh arrays do not match the store's "
            "mesh_sha256 (a store mixed from another mesh?)"
        )
    nipple_node = model["nipple_node"]
    if not (
        isinstance(nipple_node, int)
        and not isinstance(nipple_node, bool)
        and 0 <= nipple_node < len(nodes)
    ):  # review BF: an index past the mesh became an IndexError traceback in training
        raise StoreFormatError(
            f"{path / 'zarr.json'}: model.nipple_node {nipple_node!r} must be an integer "
            f"node index below the store's {len(nodes)} nodes"
        )
    node_sets = {k: read(f"mesh/{k}") for k in ("surface_nodes", "back_nodes", "boundary_faces")}
    for k, v in node_sets.items():
        if v.size and (v.min() < 0 or v.max() >= len(nodes)):
            raise StoreFormatError(
                f"{path / 'mesh' / k}: node indices {int(v.min())}..{int(v.max())} outside "
                f"the store's {len(nodes)} nodes"
            )
    S = int(attrs.get("n_scenarios", -1))
    disp = arr["results/displacement_mm"]
    if disp.shape != (S, len(nodes), 3):
        raise StoreFormatError(
            f"{path / 'results/displacement_mm/zarr.json'}: shape {disp.shape}, expected "
            f"({S}, {len(nodes)}, 3) for this store's mesh (results of another mesh?)"
        )
    for name in _ARRAYS[5:]:
        if arr[name].shape[0] != S:
            raise StoreFormatError(
                f"{path / name / 'zarr.json'}: {arr[name].shape[0]} scenarios, the store has {S}"
            )
    status = read("results/status")
    if np.any((status < 0) | (status > 2)):  # review BF: counted as neither, unsaid
        raise StoreFormatError(
            f"{path / 'results/status'}: codes outside 0..2 (pending, solved, failed)"
        )
    solved = np.flatnonzero(status == 1)
    pending = int(np.sum(status == 0))
    failed = int(np.sum(status == 2))
    if pending and not allow_pending:
        raise StoreFormatError(
            f"{path}: {pending} of {S} scenarios pending (sweep not complete: run the same "
            "`phantom-calib sweep` again to finish it)"
        )
    if pending or failed:
        log.warning(
            "%s: %d of %d scenarios pending, %d failed (attribute `failures`); using the %d solved",
            *(path, pending, S, failed, len(solved)),
        )
    if not solved.size:
        raise StoreFormatError(f"{path / 'results/status'}: no solved scenario")
    u = np.stack([read("results/displacement_mm", i, f"/c/{i}/0/0") for i in solved])
    bad = [int(i) for i, ui in zip(solved, u, strict=True) if not np.all(np.isfinite(ui))]
    if bad:
        raise StoreFormatError(
            f"{path}/results/displacement_mm/c/{bad[0]}/0/0: missing or not "
            f"finite for {len(bad)} solved scenario(s) (truncated store)"
        )
    nipple = read("results/nipple_mm")[solved]
    lost = solved[~np.all(np.isfinite(nipple), axis=1)]
    if lost.size:  # review BF: the README says the chunk file is named
        raise StoreFormatError(
            f"{path}/results/nipple_mm/c/{int(lost[0])}/0: missing or not finite for "
            f"{lost.size} solved scenario(s) (truncated store)"
        )
    tumour = read("results/tumour_mm")[solved]
    if model.get("tumour_stress_free_mm") is not None:
        # review AD: one lost chunk turned a model with a tumour into one without
        lost = solved[~np.all(np.isfinite(tumour), axis=1)]
        if lost.size:
            raise StoreFormatError(
                f"{path}/results/tumour_mm/c/{int(lost[0])}/0: missing or not finite for "
                f"{lost.size} solved scenario(s) of a model with a tumour (truncated store)"
            )
    codes = attrs.get("codes", {})
    roles = np.asarray(codes.get("role", ["train", "validation"]))
    planes = np.asarray(codes.get("plane", ["transverse", "sagittal", "sphere"]))
    sc = {k: read(f"scenarios/{k}")[solved] for k in _SCENARIO_KEYS}
    for k, v in sc.items():  # all finite (not angle_deg: NaN on a sphere plan)
        if not np.all(np.isfinite(v)):
            i = int(solved[np.flatnonzero(~np.isfinite(v).reshape(len(v), -1).all(axis=1))[0]])
            raise StoreFormatError(f"{path}/scenarios/{k}: not finite at scenario {i}")
    if np.any(sc["c1_pa"] <= 0):
        raise StoreFormatError(f"{path}/scenarios/c1_pa: a c1 <= 0 Pa")
    for k, names in (("role", roles), ("plane", planes)):
        code = sc[k]
        if np.any((code < 0) | (code >= len(names)) | (code != np.round(code))):
            raise StoreFormatError(
                f"{path}/scenarios/{k}: codes outside 0..{len(names) - 1} (`codes.{k}`: "
                f"{names.tolist()})"
            )
    return SweepData(
        path=path,
        nodes_mm=nodes,
        tets=tets,
        surface_nodes=node_sets["surface_nodes"],
        back_nodes=node_sets["back_nodes"],
        boundary_faces=node_sets["boundary_faces"],
        index=solved,
        gravity_ref=sc["gravity_ref"],
        gravity_phantom=sc["gravity_phantom"],
        c1_pa=sc["c1_pa"],
        load_per_m=sc["load_per_m"],
        role=roles[sc["role"].astype(int)],
        plane=planes[sc["plane"].astype(int)],
        angle_deg=read("scenarios/angle_deg")[solved],
        displacement_mm=u,
        tumour_mm=tumour,
        nipple_mm=nipple,
        model=dict(model),
        mesh_sha256=attrs["mesh_sha256"],
        attrs=attrs,
        failed_load_per_m=read("scenarios/load_per_m")[status == 2].reshape(-1, 3),
    )
