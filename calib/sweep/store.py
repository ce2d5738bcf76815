"""The sweep store: one Zarr (v3) folder per sweep, written scenario by scenario.

Why Zarr and not HDF5: a sweep is written one scenario at a time by a process that can
be killed at any moment. Zarr keeps every chunk in its own file and zarr-python's
local store writes each file atomically (a temporary file, then a rename), so with one
chunk per scenario a scenario is committed by its own files and a kill -9 can only lose
the scenarios being written; an HDF5 file is one file whose internal structures a kill
during a write can corrupt as a whole. Zarr also reads lazily in parallel (dask,
xarray) and needs no file locks. (Zarr format 3, zarr-python >= 3.0.)

Format ``phantom-calib.sweep``, version 1 (the folder ``SWEEP`` is the Zarr root group)
---------------------------------------------------------------------------------------

Root attributes (``SWEEP/zarr.json``):

``format`` = ``"phantom-calib.sweep"``, ``format_version`` = 1; ``status``
(``"running"`` or ``"complete"``); ``mesh_sha256`` (SHA-256 of ``mesh/nodes_mm`` as
little-endian float64 bytes followed by ``mesh/tets`` as little-endian int64);
``n_nodes``, ``n_dofs``, ``n_scenarios``; ``model`` (the calibrated model:
``c1_pa`` (the c1 every scenario is solved at), ``nu``, ``density_kg_m3``, ``g_m_s2``,
``formulation``, ``support``, ``reference_state``, ``law``, ``R_ref_from_phantom``
(3x3, phantom frame columns in the reference-scan frame), ``nipple_node``,
``tumour_stress_free_mm``); ``plan`` (``spec``, ``c1_axis``, ``holdout``, ``seed``,
``chunk_size``, ``max_angle_deg``, counts); ``codes`` (``role``: ``["train",
"validation"]``, ``plane``: ``["transverse", "sagittal", "sphere"]``, ``status``:
``["pending", "solved", "failed"]``); ``convergence_columns``; ``frames``;
``provenance`` (versions, input hashes of ``calibration.json`` and the reference
mesh, options); ``summary`` (counts and times of the last run).

Arrays (S scenarios, N mesh vertices, D solver unknowns; all lengths in mm, all vectors
in the reference-scan frame unless the name says ``phantom``):

=============================  =================  ========  ============================
path                           shape              dtype     content
=============================  =================  ========  ============================
``mesh/nodes_mm``              (N, 3)             float64   reference mesh (loaded if prestress)
``mesh/tets``                  (T, 4)             int64     its tetrahedra
``mesh/surface_nodes``         (n_s,)             int64     node set ``surface`` (boundary
                                                            without the back plate)
``mesh/back_nodes``            (n_b,)             int64     node set ``back`` (support)
``mesh/boundary_faces``        (F, 3)             int64     boundary triangles (for PLY)
``scenarios/gravity_phantom``  (S, 3)             float64   unit gravity, phantom frame
``scenarios/gravity_ref``      (S, 3)             float64   unit gravity, reference frame
``scenarios/c1_pa``            (S,)               float64   c1 of the scenario
``scenarios/g_m_s2_solved``    (S,)               float64   gravity solved at model c1:
                                                            ``g_m_s2 * c1_model / c1``
``scenarios/load_per_m``       (S, 3)             float64   ``rho g gravity_ref / c1``
                                                            (1/m): what the solution
                                                            depends on
``scenarios/role``             (S,)               int8      code into ``codes.role``
``scenarios/plane``            (S,)               int8      code into ``codes.plane``
``scenarios/angle_deg``        (S,)               float64   posture angle (NaN: sphere)
``scenarios/chunk``            (S,)               int64     continuation chunk
``scenarios/parent``           (S,)               int64     warm-start scenario, -1 cold
``scenarios/order``            (S,)               int64     the scenario at tour
                                                            position k (a permutation)
``results/status``             (S,)               int8      0 pending, 1 solved, 2 failed
``results/displacement_mm``    (S, N, 3)          float64   vertex displacements
``results/tumour_mm``          (S, 3)             float64   tumour-centre material point
                                                            displacement (NaN: none)
``results/nipple_mm``          (S, 3)             float64   nipple vertex displacement
``results/convergence``        (S, 9)             float64   ``convergence_columns``:
                                                            newton_iterations,
                                                            load_steps, cutbacks,
                                                            factorizations, wall_s,
                                                            warm_start (0/1), attempts,
                                                            final_residual, cpu_s
                                                            (the worker's CPU time)
``results/state``              (S, D)             float64   full solver vector (solver
                                                            frame, SI; internal, for
                                                            exact warm starts)
=============================  =================  ========  ============================

Every ``results/*`` array has one chunk per scenario (chunk shape ``(1, ...)``, files
``results/<name>/c/<i>/...``). A scenario is committed when its ``results/status``
chunk says 1 (solved) or 2 (failed): that chunk is written after the others, so a
reader trusts the ``results`` of scenario ``i`` only when ``status[i] == 1``; a
missing chunk of a solved scenario (which Zarr would read as the NaN fill value) means
a truncated store. Re-running the sweep solves the pending scenarios only.
A running sweep holds ``SWEEP/.lock`` (``HOST:PID``; one of another host is never taken over).
"""

from __future__ import annotations

import json
import os
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from .continuation import Continuation
from .model import SweepModel
from .plans import PLANES, ROLES, Plan, canonical_c1_axis

__all__ = [
    "CONVERGENCE_COLUMNS",
    "FORMAT",
    "FORMAT_VERSION",
    "StoreError",
    "StoreLockedError",
    "StoreMismatchError",
    "SweepStore",
]

FORMAT, FORMAT_VERSION = "phantom-calib.sweep", 1
CONVERGENCE_COLUMNS = (
    "newton_iterations",
    "load_steps",
    "cutbacks",
    "factorizations",
    "wall_s",
    "warm_start",
    "attempts",
    "final_residual",
    "cpu_s",
)
STATUS = ("pending", "solved", "failed")
PENDING, SOLVED, FAILED = 0, 1, 2
FRAMES = {
    "reference": "the reference scan's LPS frame, mm (the model's frame)",
    "phantom": "posture-angle frame: transverse angle a -> (cos a, 0, sin a), "
    "sagittal -> (0, cos a, sin a); gravity_ref = R_ref_from_phantom @ gravity_phantom",
}


def _model_differences(have: dict, want: dict, prefix: str = "model.") -> str:
    """The keys of two ``model`` blocks that differ, with both values where short.

    Review BT: a store of another model was refused without saying what differed.
    Nested blocks (``prestress``, ``effects``) are compared key by key; arrays are named
    only.
    """
    want = json.loads(json.dumps(want))  # JSON numbers and lists, as the store holds them
    said = []
    for k in sorted(set(have) | set(want)):
        x, y = have.get(k), want.get(k)
        if x == y:
            continue
        if isinstance(x, dict) and isinstance(y, dict):
            said.append(_model_differences(x, y, f"{prefix}{k}."))
        elif isinstance(x, list) or isinstance(y, list):
            said.append(f"{prefix}{k} differs")
        else:
            said.append(f"{prefix}{k}: {x!r} in the store, {y!r} now")
    return "; ".join(t for t in said if t)


class StoreError(RuntimeError):
    """A sweep store that cannot be read or written (the file and the reason)."""


class StoreMismatchError(StoreError):
    """An existing store holds another model, mesh or plan than the one asked for."""


class StoreLockedError(StoreError):
    """Another live process is writing the store."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class SweepStore:
    """Writer of a sweep store (see the module docstring for the format).

    Use :meth:`create` for a new store and :meth:`open` to resume one; one process
    writes at a time (:meth:`lock`).
    """

    def __init__(self, path: Path, group):
        self.path = Path(path)
        self.group = group
        self._results = {
            k: group[f"results/{k}"]
            for k in ("status", "displacement_mm", "tumour_mm", "nipple_mm", "convergence", "state")
        }
        self._locked = False

    # -- creation and opening -------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        model: SweepModel,
        plan: Plan,
        continuation: Continuation,
        *,
        n_dofs: int,
        chunk_size: int,
        max_angle_deg: float,
        provenance: dict,
    ) -> SweepStore:
        """Write a new, empty store (its mesh, scenarios and metadata) at ``path``.

        Parameters
        ----------
        path : path
            Folder to create; it must not exist or be empty.
        model : SweepModel
        plan : Plan
        continuation : Continuation
        n_dofs : int
            Length of the solver vector.
        chunk_size : int
        max_angle_deg : float
            Parameters of the continuation (recorded; a resume must use the same).
        provenance : dict

        Returns
        -------
        SweepStore
        """
        import zarr

        from fem import boundary_faces

        path = Path(path)
        if path.exists() and any(path.iterdir()):
            raise StoreError(f"{path}: exists and is not an empty folder")
        g = zarr.open_group(path, mode="w")
        S, N = len(plan), len(model.nodes_mm)

        def const(name: str, data) -> None:
            data = np.ascontiguousarray(data)
            g.create_array(name, data=data, chunks=data.shape or None, overwrite=True)

        const("mesh/nodes_mm", model.nodes_mm.astype(np.float64))
        const("mesh/tets", model.tets.astype(np.int64))
        const("mesh/surface_nodes", model.surface_nodes.astype(np.int64))
        const("mesh/back_nodes", model.back_nodes.astype(np.int64))
        const("mesh/boundary_faces", boundary_faces(model.tet_mesh().tets).astype(np.int64))
        R = np.asarray(model.R_ref_from_phantom)
        g_ref = plan.gravity_phantom @ R.T
        ratio = model.c1_pa / plan.c1_pa
        const("scenarios/gravity_phantom", plan.gravity_phantom)
        const("scenarios/gravity_ref", g_ref)
        const("scenarios/c1_pa", plan.c1_pa.astype(np.float64))
        const("scenarios/g_m_s2_solved", model.g_m_s2 * ratio)
        const(
            "scenarios/load_per_m",
            g_ref * (model.density_kg_m3 * model.g_m_s2 / plan.c1_pa)[:, None],
        )
        const("scenarios/role", plan.role.astype(np.int8))
        const("scenarios/plane", plan.plane.astype(np.int8))
        const("scenarios/angle_deg", plan.angle_deg.astype(np.float64))
        const("scenarios/chunk", continuation.chunk)
        const("scenarios/parent", continuation.parent)
        const("scenarios/order", continuation.order)
        specs = {
            "status": ((S,), (1,), "i1", PENDING),
            "displacement_mm": ((S, N, 3), (1, N, 3), "f8", np.nan),
            "tumour_mm": ((S, 3), (1, 3), "f8", np.nan),
            "nipple_mm": ((S, 3), (1, 3), "f8", np.nan),
            "convergence": (
                (S, len(CONVERGENCE_COLUMNS)),
                (1, len(CONVERGENCE_COLUMNS)),
                "f8",
                np.nan,
            ),
            "state": ((S, n_dofs), (1, n_dofs), "f8", np.nan),
        }
        for name, (shape, chunks, dtype, fill) in specs.items():
            g.create_array(
                f"results/{name}", shape=shape, chunks=chunks, dtype=dtype, fill_value=fill
            )
        plan_doc = plan.describe() | {
            "chunk_size": int(chunk_size),
            "max_angle_deg": float(max_angle_deg),
        }
        # attributes last: a store without them was interrupted while being created
        g.attrs.update(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "status": "running",
                "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "mesh_sha256": model.mesh_sha256,
                "model_key": model.key,
                "n_nodes": int(N),
                "n_dofs": int(n_dofs),
                "n_scenarios": int(S),
                "model": model.physics(),
                "plan": plan_doc,
                "codes": {"role": list(ROLES), "plane": list(PLANES), "status": list(STATUS)},
                "convergence_columns": list(CONVERGENCE_COLUMNS),
                "frames": FRAMES,
                "provenance": provenance,
            }
        )
        return cls(path, g)

    @classmethod
    def open(cls, path: str | os.PathLike) -> SweepStore:
        """Open an existing store for writing (resume), checking its format.

        Raises
        ------
        StoreError
            Not a sweep store, another format version, or an incomplete one.
        """
        import zarr

        path = Path(path)
        meta = path / "zarr.json"
        if not meta.is_file():
            raise StoreError(f"{meta} not found: {path} is not a sweep store")
        try:
            g = zarr.open_group(path, mode="r+")
            attrs = dict(g.attrs)
        except Exception as exc:  # zarr raises many kinds on bad metadata
            what = f"{type(exc).__name__}: {exc}"
            raise StoreError(f"{meta}: cannot open the store ({what})") from exc
        if attrs.get("format") != FORMAT:
            raise StoreError(
                f"{meta}: not a {FORMAT} store (an interrupted creation, or another kind of "
                "Zarr group); remove it or choose another --out"
            )
        if attrs.get("format_version") != FORMAT_VERSION:
            raise StoreError(
                f"{meta}: format version {attrs.get('format_version')}, this "
                f"phantom-calib reads {FORMAT_VERSION}"
            )
        try:
            return cls(path, g)
        except KeyError as exc:
            raise StoreError(f"{path}: array {exc} missing (truncated store)") from exc

    @property
    def attrs(self) -> dict:
        """The root attributes."""
        return dict(self.group.attrs)

    def check_matches(
        self, model: SweepModel, plan: Plan, *, chunk_size: int, max_angle_deg: float
    ) -> None:
        """Raise :class:`StoreMismatchError` unless the store is this model's and plan's."""
        a = self.attrs
        meta = self.path / "zarr.json"
        if a.get("mesh_sha256") != model.mesh_sha256:
            raise StoreMismatchError(
                f"{meta}: the store holds a sweep of another mesh (mesh_sha256 differs); "
                "choose another --out, or --overwrite"
            )
        for name in ("back_nodes", "surface_nodes"):  # not in the key (review BT)
            have = np.sort(np.asarray(self.group[f"mesh/{name}"][:]))
            now = np.sort(np.asarray(getattr(model, name)))
            if not np.array_equal(have, now):
                raise StoreMismatchError(
                    f"{meta}: the store was swept with another node set mesh/{name} "
                    f"({len(have)} nodes, {len(now)} now): the support or the surface of the "
                    "model differs; choose another --out, or --overwrite"
                )
        if a.get("model_key") != model.key:
            differ = _model_differences(a.get("model") or {}, model.physics())
            raise StoreMismatchError(
                f"{meta}: the store holds another calibrated model "
                f"({differ or 'c1, nu, density, support ...'}); choose another --out, "
                "or --overwrite"
            )
        want = plan.describe() | {
            "chunk_size": int(chunk_size),
            "max_angle_deg": float(max_angle_deg),
        }
        have = dict(a.get("plan", {}))
        if have.get("c1_axis"):  # a store made before the axis was written one way
            have["c1_axis"] = canonical_c1_axis(have["c1_axis"])
        # the seed draws a sphere plan's held-out directions only: elsewhere it is no part
        # of the plan (review AD: a dissertation store was refused a resume at another seed)
        unused = {"seed"} if not want.get("holdout") else set()
        diff = sorted(k for k in want if k not in unused and have.get(k) != want[k])
        if diff:
            detail = ", ".join(f"{k}: {have.get(k)!r} != {want[k]!r}" for k in diff)
            raise StoreMismatchError(
                f"{meta}: the store holds another plan ({detail}); "
                "choose another --out, or --overwrite"
            )

    # -- locking --------------------------------------------------------------------------
    def lock(self) -> None:
        """Take ``SWEEP/.lock`` (a dead holder's lock is taken over).

        The lock holds ``HOST:PID``. A holder on another host (a store on a shared file
        system) cannot be seen to have died from here: its lock is refused, naming it
        (review BT: a bare pid read as dead there, and a second host's run took the lock
        of a store being written). A lock of a bare pid (older versions) is this host's.
        """
        import socket

        lock = self.path / ".lock"
        here = socket.gethostname()
        for _ in range(2):
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    host, _, pid_text = lock.read_text().strip().rpartition(":")
                    pid = int(pid_text or 0)
                except (OSError, ValueError):
                    host, pid = "", 0
                if pid and host and host != here:
                    raise StoreLockedError(
                        f"{lock}: process {pid} on host {host} holds this store's lock (a sweep "
                        "running there, or one that died: remove the file if none runs)"
                    ) from None
                if pid and pid != os.getpid() and _pid_alive(pid):
                    raise StoreLockedError(f"{lock}: process {pid} is writing this store") from None
                lock.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as f:
                f.write(f"{here}:{os.getpid()}")
            self._locked = True
            return
        raise StoreLockedError(f"{lock}: cannot take the lock")

    def unlock(self) -> None:
        """Release ``SWEEP/.lock``."""
        if self._locked:
            (self.path / ".lock").unlink(missing_ok=True)
            self._locked = False

    def clean_partial(self) -> int:
        """Remove temporary chunk files of writes interrupted by a kill; return the count."""
        n = 0
        for p in self.path.rglob("*.partial"):
            p.unlink(missing_ok=True)
            n += 1
        return n

    def requeue_lost(self) -> list[int]:
        """Set solved scenarios with a result chunk file missing back to pending.

        A solved scenario's displacement, state and nipple chunks (and its tumour chunk
        where the model has a tumour) are files under ``results/<name>/c/<i>/``; one lost
        by a partial copy left the store "complete" and a re-run solved nothing (review
        AM). Returns the scenarios set back.
        """
        names = ["displacement_mm", "state", "nipple_mm"]
        if (self.attrs.get("model") or {}).get("tumour_stress_free_mm") is not None:
            names.append("tumour_mm")
        solved = np.flatnonzero(self.status() == SOLVED)
        lost = [
            int(i)
            for i in solved
            if not all(
                any(p.is_file() for p in (self.path / "results" / n / "c" / str(i)).rglob("*"))
                for n in names
            )
        ]
        for i in lost:
            self._results["status"][i] = PENDING
        return lost

    # -- scenarios ------------------------------------------------------------------------
    def _read(self, name: str, index=slice(None)) -> np.ndarray:
        # review AD: a missing array gave a KeyError traceback, a corrupt chunk the
        # codec's words only ("Zstd decompression error"), naming no file
        try:
            return np.asarray(self.group[name][index])
        except Exception as exc:  # zarr and its codecs raise many kinds
            raise StoreError(
                f"{self.path / name}: unreadable ({type(exc).__name__}: {exc}); the store is "
                "damaged: sweep again with --overwrite or into a fresh --out"
            ) from exc

    def status(self) -> np.ndarray:
        """Status code of every scenario, (S,) int8 (0 pending, 1 solved, 2 failed)."""
        return self._read("results/status")

    def scenario_array(self, name: str) -> np.ndarray:
        """A ``scenarios/<name>`` array."""
        return self._read(f"scenarios/{name}")

    def state(self, i: int) -> np.ndarray:
        """Solver vector of solved scenario ``i`` (for a warm start)."""
        x = self._read("results/state", i)
        if not np.all(np.isfinite(x)):
            raise StoreError(
                f"{self.path}/results/state/c/{i}/0: missing or not finite (truncated store)"
            )
        return x

    def commit(self, i: int, result) -> None:
        """Write scenario ``i``'s result, its status chunk last.

        Parameters
        ----------
        i : int
        result : calib.sweep.engine.ScenarioResult
        """
        r = self._results
        if result.ok:
            r["displacement_mm"][i] = result.displacement_mm
            r["state"][i] = result.state
            r["tumour_mm"][i] = result.tumour_mm
            r["nipple_mm"][i] = result.nipple_mm
        cols = self.group.attrs.get("convergence_columns", CONVERGENCE_COLUMNS)
        r["convergence"][i] = np.array([result.stats.get(c, np.nan) for c in cols], dtype=float)
        failures = dict(self.group.attrs.get("failures", {}))
        if not result.ok:
            failures[str(i)] = result.message
            self.group.attrs["failures"] = failures
        elif str(i) in failures:  # review AD: a retried scenario's failure stayed listed
            del failures[str(i)]
            self.group.attrs["failures"] = failures
        r["status"][i] = SOLVED if result.ok else FAILED

    def mark_running(self) -> None:
        """Set the root ``status`` to ``running`` before scenarios are solved.

        A run killed before its end leaves it so; :meth:`set_status_attrs` sets
        ``complete`` when none is pending.
        """
        self.group.attrs["status"] = "running"

    def record_resume(self, record: dict) -> None:
        """Append a later run's provenance record to the root ``resumes`` attribute.

        ``provenance`` stays the creating run's; each run that solves scenarios of an
        existing store adds its own record here (review BI: a resume with other code,
        versions or thread counts left no trace).
        """
        resumes = list(self.attrs.get("resumes", []))
        self.group.attrs["resumes"] = [*resumes, json.loads(json.dumps(record))]

    def set_status_attrs(self, status: str, summary: dict) -> None:
        """Set the root ``status`` and ``summary`` attributes."""
        self.group.attrs.update({"status": status, "summary": json.loads(json.dumps(summary))})
