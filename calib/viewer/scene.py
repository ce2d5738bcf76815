"""What the browser view shows, read from a work folder and a surrogate (read only).

:func:`load_scene` gathers, in the **phantom frame** of posture angles (``x_phantom =
R_ref_from_phantom^T x_ref``, the frame of ``phantom-calib sweep`` and ``surrogate
predict --frame phantom``):

* the model's boundary surface (from the surrogate's mesh, else the work folder's
  ``calibration/reference_mesh.vtu``), its nipple vertex, the tumour and the reference
  scan's fiducials;
* the FE states ``calibrate`` saved (``calibration/<scan>_deformed.vtu``), each at its
  scan's gravity;
* each scan's measured surface (``scans/<scan>/surface_ref.ply``, already registered into
  the reference frame by ``ingest``) and its per-vertex error (``calibration/<scan>_error.ply``,
  ``error_mm``, signed, shown signed in the colours of the project's PNG maps, on the
  scan's own scale, review CD-10); after
  ``diagnose``, the same error of its refitted model (``diagnosis/refit/``, a work folder
  of saved states). The faces whose vertices are all scored
  (:attr:`calib.data.measurements.ScanMeasurement.scored`) come first, their number in
  ``n_scored_faces``: the others touch the back plate or a cut field of view, whose
  error is not measured (0 in the maps), and are shown grey, not as 0 mm;
* what is missing, as sentences naming the file and the command that makes it.

:class:`Predictor` evaluates the surrogate (:meth:`nn.Surrogate.predict`) for a gravity
vector (phantom frame, m/s^2) and a c1, and returns the displayed surface vertex positions.
Nothing here writes into the work folder or reads a twin's sealed truth.
"""

from __future__ import annotations

import json
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fem.units import STANDARD_GRAVITY_M_S2

__all__ = ["Frame", "Predictor", "Scene", "SurfaceModelMismatchError", "load_scene"]


class SurfaceModelMismatchError(ValueError):
    """A surrogate trained on another mesh than the work folder's reference mesh."""


@dataclass(frozen=True)
class Frame:
    """One predicted frame, phantom frame (mm).

    Attributes
    ----------
    surface_mm : ndarray, shape (n_vertices, 3), float32
        The displayed boundary vertices (the scene's ``vertex_nodes`` of the mesh).
    nipple_mm, tumour_mm : ndarray, shape (3,) or None
    extrapolating : bool
        The query lies outside the surrogate's trained c1 or load range.
    """

    surface_mm: np.ndarray
    nipple_mm: np.ndarray | None
    tumour_mm: np.ndarray | None
    extrapolating: bool


@dataclass
class Scene:
    """Everything the page shows (see the module docstring).

    Attributes
    ----------
    work : Path
    R_ref_from_phantom : ndarray, shape (3, 3) or None
    vertex_nodes : ndarray of int, shape (n_vertices,) or None
        Mesh nodes of the displayed boundary vertices.
    faces : ndarray of int, shape (n_faces, 3) or None
        Triangles, indices into ``vertex_nodes``.
    rest_mm : ndarray, shape (n_vertices, 3) or None
        Stress-free positions of the displayed vertices, phantom frame.
    missing : list of str
        What is absent and how to make it.
    info : dict
        The JSON document of ``/api/scene`` (model, scans, states, landmarks).
    states : dict of str to tuple
        Saved FE states: displayed vertices (n_vertices, 3), nipple (3,) and tumour (3,)
        or None, phantom frame, mm.
    overlays : dict of str to dict
        Per scan: ``vertices_mm`` (phantom frame), ``faces``, ``error_mm`` (signed, mm)
        and ``error_after_mm`` (diagnose's refit) where present.
    predictor : Predictor or None
    """

    work: Path
    R_ref_from_phantom: np.ndarray | None = None
    vertex_nodes: np.ndarray | None = None
    faces: np.ndarray | None = None
    rest_mm: np.ndarray | None = None
    missing: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    states: dict = field(default_factory=dict)
    overlays: dict = field(default_factory=dict)
    predictor: Predictor | None = None

    def to_phantom(self, points_ref_mm: np.ndarray) -> np.ndarray:
        """Reference-frame points (k, 3) in the phantom frame."""
        return np.asarray(points_ref_mm, float) @ self.R_ref_from_phantom


class Predictor:
    """The surrogate evaluated for the page (one query at a time, under a lock).

    Parameters
    ----------
    surrogate : nn.Surrogate
    vertex_nodes : ndarray of int
        Mesh nodes to return.
    """

    def __init__(self, surrogate, vertex_nodes: np.ndarray):
        self.surrogate = surrogate
        self.vertex_nodes = np.asarray(vertex_nodes)
        self.R = surrogate.R_ref_from_phantom
        model = surrogate.meta["model"]
        self.rest_ref_mm = surrogate.mesh.nodes_mm
        t = model.get("tumour_stress_free_mm")
        self.tumour_rest_ref_mm = None if t is None else np.asarray(t, float)
        self._lock = threading.Lock()

    def predict(self, gravity_phantom_m_s2, c1_pa: float) -> Frame:
        """Deformed boundary vertices for one gravity vector and c1.

        Parameters
        ----------
        gravity_phantom_m_s2 : array_like, shape (3,)
            Gravity acceleration, phantom frame, m/s^2.
        c1_pa : float

        Returns
        -------
        Frame
        """
        import nn

        with self._lock, warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", nn.ExtrapolationWarning)
            pred = self.surrogate.predict(
                np.asarray(gravity_phantom_m_s2, float), c1_pa=float(c1_pa), frame="phantom"
            )
        u = self.surrogate.boundary_displacement_mm(pred)
        x_ref = self.rest_ref_mm[self.vertex_nodes] + u[self.vertex_nodes]
        nipple = None
        if pred.nipple_mm is not None:
            node = int(self.surrogate.meta["model"]["nipple_node"])
            nipple = (self.rest_ref_mm[node] + pred.nipple_mm[0]) @ self.R
        tumour = None
        if pred.tumour_mm is not None and self.tumour_rest_ref_mm is not None:
            tumour = (self.tumour_rest_ref_mm + pred.tumour_mm[0]) @ self.R
        extrapolating = any(issubclass(w.category, nn.ExtrapolationWarning) for w in caught)
        return Frame((x_ref @ self.R).astype(np.float32), nipple, tumour, extrapolating)


def _boundary(tets: np.ndarray, faces: np.ndarray | None = None):
    """Boundary vertices (mesh nodes) and triangles indexing them."""
    if faces is None:
        from fem.mesh import boundary_faces

        faces = boundary_faces(np.asarray(tets))
    faces = np.asarray(faces, dtype=np.int64)
    nodes, inverse = np.unique(faces, return_inverse=True)
    return nodes, inverse.reshape(faces.shape)


def _error_ply(path: Path, n_vertices: int, missing: list) -> np.ndarray | None:
    """The ``error_mm`` vertex scalar of an error PLY (``calib.report.write_error_ply``).

    None where the file is absent; where it cannot be read, has no ``error_mm`` or not
    ``n_vertices`` values (the scan's measured surface's), None with a line in
    ``missing`` naming it (review CD-2, CD-5: a corrupt file was a traceback, a
    mismatched one dropped without a word).
    """
    from ..data.work import read_meshio

    if not path.is_file():
        return None
    try:
        m = read_meshio(path, "error map")
    except ValueError as exc:
        missing.append(f"{exc}: its scan is shown without it")
        return None
    e = m.point_data.get("error_mm")
    if e is None or np.size(e) != n_vertices:
        has = "no `error_mm`" if e is None else f"{np.size(e)} values of `error_mm`"
        missing.append(
            f"{path} has {has}, where its scan's measured surface has {n_vertices} "
            "vertices (written for another calibration?): its scan is shown without it"
        )
        return None
    return np.asarray(e, float).reshape(-1)


def _command_hint(work: Path) -> dict:
    return {
        "calibrate": f"phantom-calib calibrate SCANS --out {work}  # SCANS: the folder of "
        "session.toml",
        "surrogate": (
            f"phantom-calib sweep {work} --out SWEEP && "
            f"phantom-calib surrogate train SWEEP --out MODEL.pt && "
            f"phantom-calib view {work} --model MODEL.pt"
        ),
        "diagnose": f"phantom-calib diagnose {work}",
    }


#: How far from one plane of constant phantom z the back nodes may lie for the page to
#: draw the plate there (mm): calibrate's reference mesh puts them on the fitted back
#: plane, whose normal is the frame's z (``calib.fitting.result.phantom_frame``).
PLATE_FLATNESS_MM = 1e-3


def load_scene(work: str | Path, model: str | Path | None = None) -> Scene:
    """Read what the page shows from a work folder and an optional surrogate.

    Parameters
    ----------
    work : path
        A work folder (``calibrate`` output); a folder without a calibration still loads:
        ``Scene.missing`` says what is absent.
    model : path, optional
        A surrogate (``phantom-calib surrogate train``).

    Returns
    -------
    Scene

    Raises
    ------
    nn.SurrogateFileError
        ``model`` is not a readable surrogate.
    SurfaceModelMismatchError
        The surrogate's mesh is not the work folder's reference mesh.
    FileNotFoundError
        ``work`` is not a folder.
    """
    work = Path(work)
    from ..data.work import not_a_folder

    if why := not_a_folder(work):
        raise FileNotFoundError(f"{work}: {why}")
    hint = _command_hint(work)
    scene = Scene(work)
    info: dict = {
        "work": str(work),
        "model": None,
        "scans": [],
        "states": [],
        "landmarks": {},
        "g_m_s2": STANDARD_GRAVITY_M_S2,
        "c1_pa": None,
    }
    sur = None
    if model is not None:
        import nn

        sur = nn.load_surrogate(model)
    folder = None
    if not (work / "calibration.json").is_file():
        scene.missing.append(
            f"{work / 'calibration.json'} is missing: this folder has no calibration. "
            f"Run: {hint['calibrate']}"
        )
    else:
        from ..data.work import read_work
        from ..io import StaleOutputError

        unreadable: list[str] = []
        try:
            folder = read_work(work, unreadable_states=unreadable)
            for why in unreadable:  # review CD-6: one bad state hid every scan
                scene.missing.append(f"{why}: its scan is shown without its FE state")
        except KeyError as exc:
            scene.missing.append(
                f"{work / 'calibration.json'} has no {exc} entry: no scans, FE states or "
                "error maps to show"
            )
        except (OSError, ValueError, StaleOutputError) as exc:
            scene.missing.append(f"the calibration could not be read back: {exc}")
    if folder is None and sur is None:
        scene.missing.append(
            f"no surrogate (--model) either: nothing to draw. Make one: {hint['surrogate']}"
        )
        scene.info = info
        return scene

    record_model = sur.meta["model"] if sur is not None else folder.record["model"]
    R = np.asarray(record_model["R_ref_from_phantom"], float)
    scene.R_ref_from_phantom = R
    if sur is not None:
        nodes_ref = sur.mesh.nodes_mm
        vnodes, faces = _boundary(sur.mesh.tets, sur.mesh.boundary_faces)
        # a sweep solves on the stress-free mesh, or on the loaded one of a prestressed
        # reference (calib.sweep.model): the surrogate's mesh is that one
        prestress = (folder.record.get("model") or {}).get("prestress") if folder else None
        mesh_path = work / (prestress["mesh"] if prestress else "calibration/reference_mesh.vtu")
        wn = None
        if folder is not None and not prestress:
            wn = folder.mesh.nodes_mm
        elif mesh_path.is_file():
            from fem.io import read_mesh

            wn = read_mesh(mesh_path, orient=False).nodes_mm
        if wn is not None:
            if wn.shape != nodes_ref.shape or not np.allclose(wn, nodes_ref, atol=1e-6):
                raise SurfaceModelMismatchError(
                    f"{model}: the surrogate's mesh ({len(nodes_ref)} nodes) is not "
                    f"{mesh_path} ({len(wn)} nodes); train it from a sweep of this work folder"
                )
    else:
        nodes_ref = folder.mesh.nodes_mm
        vnodes, faces = _boundary(folder.mesh.tets)
    scene.vertex_nodes, scene.faces = vnodes, faces
    scene.rest_mm = (nodes_ref[vnodes] @ R).astype(np.float32)
    # the back plate's plane, z of the phantom frame: the clamped back nodes' (review BC:
    # the body's lowest z lay 0.46 mm past it on make demo's mesh, a lip over the plate)
    back = sur.mesh.back_nodes if sur is not None else folder.mesh.node_sets.get("back")
    back_z = (nodes_ref[back] @ R)[:, 2] if back is not None and len(back) else np.zeros(0)
    info["plate_z_mm"] = None
    if back_z.size and np.ptp(back_z) <= PLATE_FLATNESS_MM:
        info["plate_z_mm"] = float(np.mean(back_z))
    else:
        scene.missing.append(
            "no back plate drawn: the mesh's back nodes do not lie in one plane normal to "
            "the phantom frame's z"
        )
    nipple_node = int(record_model["nipple_node"])
    hit = np.flatnonzero(vnodes == nipple_node)
    t = record_model.get("tumour_stress_free_mm")
    info["landmarks"] = {
        "nipple_vertex": int(hit[0]) if hit.size else None,
        "tumour_rest_mm": None if t is None else (np.asarray(t, float) @ R).tolist(),
        "fiducials_mm": [],
    }
    g = float(record_model.get("g_m_s2", STANDARD_GRAVITY_M_S2))
    if sur is not None:
        lo, hi = sur.meta["trained"]["c1_pa"]
        c1_now = float(record_model["c1_pa"])
        try:  # calibration.json's, also where its scans cannot be shown
            c1_now = float(json.loads((work / "calibration.json").read_text())["c1_pa"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        if not np.isclose(c1_now, float(record_model["c1_pa"]), rtol=1e-9, atol=0.0):
            # review AG: a surrogate of an earlier calibration on the same mesh passed, its
            # c1 slider at that calibration's c1
            scene.missing.append(
                f"{model} was swept from a calibration at c1 {float(record_model['c1_pa']):.1f} "
                f"Pa; {work / 'calibration.json'} now says {c1_now:.1f} Pa (calibrate ran "
                "since): the c1 slider starts at the calibration's; sweep and train again"
            )
        info["model"] = {
            "path": str(model),
            "kind": sur.kind,
            "c1_pa": c1_now,
            "c1_range_pa": [float(lo), float(hi)],
            "load_range_per_m": sur.meta["trained"]["load_per_m"],
            "g_m_s2": g,
        }
        scene.predictor = Predictor(sur, vnodes)
    else:
        scene.missing.append(
            "no surrogate (--model): the page shows the FE states calibrate saved. "
            f"To turn gravity freely, make one: {hint['surrogate']}"
        )
    info["g_m_s2"] = g
    info["c1_pa"] = float(folder.c1_pa) if folder is not None else float(record_model["c1_pa"])
    if folder is not None:
        _add_work(scene, folder, info, vnodes, hint)
    scene.info = info
    return scene


def _add_work(scene: Scene, folder, info: dict, vnodes: np.ndarray, hint: dict) -> None:
    """FE states, measured surfaces, error maps and fiducials of a read-back work folder."""
    from ..data.work import ingest_record

    work = folder.path
    R = scene.R_ref_from_phantom
    g = info["g_m_s2"]
    ref_name = folder.record["model"]["reference_scan"]
    refit_maps = _refit_maps(work, scene.missing)
    for name, scan in folder.measurements.scans.items():
        g_ph = (np.asarray(scan.gravity_ref, float) @ R) * g
        entry = {"name": name, "role": scan.role, "gravity_phantom_m_s2": g_ph.tolist()}
        faces = np.asarray(scan.faces, np.int64)
        whole = scan.scored[faces].all(axis=1)
        overlay = {
            "vertices_mm": scene.to_phantom(scan.vertices_mm).astype(np.float32),
            "faces": np.concatenate([faces[whole], faces[~whole]]),
            "n_scored_faces": int(whole.sum()),
        }
        err_path = work / "calibration" / f"{name}_error.ply"
        err = _error_ply(err_path, len(scan.vertices_mm), scene.missing)
        if err is not None:
            overlay["error_mm"] = err.astype(np.float32)
        elif name in folder.states and not err_path.exists():  # review CD-5: unsaid
            scene.missing.append(f"{err_path} is missing: {name} is shown without its map")
        after = refit_maps.get(name)
        if after is not None and len(after) == len(scan.vertices_mm):
            overlay["error_after_mm"] = after.astype(np.float32)
        entry["maps"] = [k for k in ("error_mm", "error_after_mm") if k in overlay]
        entry["nipple_mm"] = scene.to_phantom(scan.nipple_mm[None])[0].tolist()
        if scan.tumour_mm is not None:
            entry["tumour_mm"] = scene.to_phantom(scan.tumour_mm[None])[0].tolist()
        scene.overlays[name] = overlay
        info["scans"].append(entry)
        if name in folder.states:
            st = folder.states[name]
            nip = scene.to_phantom(st.positions_mm[folder.nipple_node][None])[0]
            tum = None if st.tumour_mm is None else scene.to_phantom(st.tumour_mm[None])[0]
            pos = scene.to_phantom(st.positions_mm[vnodes]).astype(np.float32)
            scene.states[name] = (pos, nip, tum)
            info["states"].append(name)
    try:
        ing = ingest_record(folder, ref_name)
        fid = np.asarray(ing["fiducials_lps_mm"], float)
        T = np.asarray(ing["T_ref_from_scan"], float)
        fid_ref = fid @ T[:3, :3].T + T[:3, 3]
        info["landmarks"]["fiducials_mm"] = scene.to_phantom(fid_ref).tolist()
    except (OSError, KeyError, ValueError):
        scene.missing.append(f"no fiducials in {work / 'scans' / ref_name / 'ingest.json'}")
    if not any("error_mm" in o for o in scene.overlays.values()):
        scene.missing.append(f"no error maps ({work / 'calibration'}/<scan>_error.ply)")
    if made := (folder.record or {}).get("diagnosis"):  # review AT: it advised a refused run
        source = made.get("source_work") or "its source work folder"
        if not Path(source).is_absolute() and work.parent.name == "diagnosis":
            source = work.parent.parent  # older refits recorded it as given (review AU)
        scene.missing.append(
            f"a diagnosis' refitted model: its error maps show in the view of the calibration "
            f"it came from ({source})"
        )
    elif not (work / "diagnosis").is_dir():
        scene.missing.append(f"no error maps of diagnose's refit: run {hint['diagnose']}")


def _refit_maps(work: Path, missing: list) -> dict:
    """Signed vertex errors of diagnose's final model (``diagnosis/refit/``), per scan.

    ``diagnose`` saves the refitted model as a work folder (states, no error PLYs); its
    errors are measured here as ``calibrate`` measures them
    (:func:`calib.evaluation.scan_metrics` of the saved state). A refit made from
    another calibration than the folder's current one (``calibrate`` ran since) is left
    out and said.
    """
    refit = work / "diagnosis" / "refit"
    if not (refit / "calibration.json").is_file():
        return {}
    try:
        made_from = json.loads((refit / "calibration.json").read_text())["diagnosis"]
        current = json.loads((work / "calibration.json").read_text()).get("run_id")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        missing.append(f"diagnose's refitted model could not be read back: {exc}")
        return {}
    if made_from.get("calibration_run_id") != current:
        missing.append(
            f"{work / 'diagnosis'} is of an earlier calibration (run "
            f"{made_from.get('calibration_run_id')}; now {current}): run diagnose again"
        )
        return {}
    from ..data.work import read_work
    from ..evaluation import scan_metrics
    from ..io import StaleOutputError
    from ..model.residuals import SimulatedSurface

    try:
        rw = read_work(refit)
    except (OSError, ValueError, KeyError, StaleOutputError) as exc:
        missing.append(f"diagnose's refitted model could not be read back: {exc}")
        return {}
    faces = SimulatedSurface.of(rw.mesh).faces
    out = {}
    for name, st in rw.states.items():
        scan = rw.measurements.scans[name]
        m = scan_metrics(scan, st.positions_mm, faces, rw.nipple_node, st.tumour_mm)
        out[name] = np.asarray(m.vertex_error_mm, float)
    return out
