"""What the scans measured, in the reference scan's LPS frame (the ref frame), mm."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .session import ScanEntry, Session

__all__ = ["Measurements", "ScanMeasurement", "load_measurements", "read_scan"]


@dataclass(frozen=True)
class ScanMeasurement:
    """One scan's measured geometry, reference frame (mm).

    Attributes
    ----------
    name, role : str
    gravity_ref : ndarray, shape (3,)
        Unit gravity direction in the reference frame (from the fiducial registration).
    vertices_mm, faces : ndarray
        The measured closed surface (``surface_ref.ply``).
    back_plate : ndarray of bool
        Vertices on the back plate.
    nipple_mm, tumour_mm : ndarray, shape (3,)
        Landmarks (``tumour_mm`` may be None).
    back_point_mm, back_normal : ndarray, shape (3,)
        The back plane (outward normal) mapped into the reference frame.
    T_ref_from_scan : ndarray, shape (4, 4)
    posture_plane : str or None
        The session's nominal posture plane (``posture.plane``), if given.
    posture_angle_deg : float or None
        The session's nominal posture angle (``posture.angle_deg``), if given.
    fov_edge : ndarray of bool or None
        Vertices where the field of view cuts the body (``surface_ref.ply``'s
        ``fov_edge``; None: it cuts nothing).
    back_voxel_depth_mm : float or None
        The slice thickness across the back plane (``ingest.json``
        ``back_plane.voxel_depth_mm``; None where not recorded).
    tre_nipple_mm : float or None
        The expected target registration error at the nipple (``ingest.json``
        ``tre_nipple_mm``, Fitzpatrick's; 0 for the reference scan; None where not
        recorded).
    """

    name: str
    role: str
    gravity_ref: np.ndarray
    vertices_mm: np.ndarray
    faces: np.ndarray
    back_plate: np.ndarray
    nipple_mm: np.ndarray
    tumour_mm: np.ndarray | None
    back_point_mm: np.ndarray
    back_normal: np.ndarray
    T_ref_from_scan: np.ndarray
    posture_plane: str | None = None
    posture_angle_deg: float | None = None
    fov_edge: np.ndarray | None = None
    back_voxel_depth_mm: float | None = None
    tre_nipple_mm: float | None = None

    @property
    def in_view(self) -> np.ndarray:
        """Vertices off a cut field of view's edge (all where nothing is cut), (n,) bool."""
        if self.fov_edge is None:
            return np.ones(len(self.vertices_mm), bool)
        return ~self.fov_edge

    @property
    def scored(self) -> np.ndarray:
        """Vertices measured on the phantom's surface, (n,) bool.

        Off the back plate and off the field of view's edge: what the fit and the errors use.
        """
        return ~self.back_plate & self.in_view

    @property
    def nominal_posture(self) -> dict | None:
        """``{"plane", "angle_deg"}`` as the session gives them (None: no posture given)."""
        if self.posture_plane is None and self.posture_angle_deg is None:
            return None
        return {"plane": self.posture_plane, "angle_deg": self.posture_angle_deg}

    def surface_points(self, *, max_points: int = 4000, seed: int = 0) -> np.ndarray:
        """Measured surface vertices (:attr:`scored`), a seeded subsample, (k, 3).

        Parameters
        ----------
        max_points : int
            At most this many points are returned (a uniform seeded subset).
        seed : int
            Seed of the subset.

        Returns
        -------
        (k, 3) float
            Points in the ref frame, mm, in vertex order.
        """
        pts = self.vertices_mm[self.scored]
        if len(pts) > max_points:
            rng = np.random.default_rng(seed)
            pts = pts[np.sort(rng.choice(len(pts), max_points, replace=False))]
        return pts


@dataclass(frozen=True)
class Measurements:
    """All scans of a session after ingest.

    Attributes
    ----------
    reference : ScanMeasurement
    scans : dict of str to ScanMeasurement
        Every scan, the reference too.
    density_kg_m3 : float or None
        The phantom's declared density (the session's ``phantom.density_kg_m3``), which
        :func:`calib.fitting.fit` takes; None where the scans came without a session.
    """

    reference: ScanMeasurement
    scans: dict[str, ScanMeasurement]
    density_kg_m3: float | None = None

    def __repr__(self) -> str:  # review BW, F4: thousands of characters of arrays
        scans = ", ".join(f"{n} ({s.role})" for n, s in self.scans.items())
        density = "" if self.density_kg_m3 is None else f"; {self.density_kg_m3:g} kg/m^3"
        return f"Measurements({scans}{density})"

    def with_role(self, role: str) -> list[ScanMeasurement]:
        """Scans of one role.

        Parameters
        ----------
        role : str
            ``"reference"``, ``"calibration"`` or ``"validation"``.

        Returns
        -------
        list of ScanMeasurement
            In the session's order.
        """
        return [s for s in self.scans.values() if s.role == role]


def _check_ingest_shapes(doc: dict, path: Path) -> None:
    """The arrays of ``ingest.json`` this reader uses, of the right shape and finite.

    Review AT: a ``nipple_lps_mm`` of null reached the user as an IndexError traceback.
    """
    plane = doc.get("back_plane")
    wanted = [
        ("T_ref_from_scan", doc.get("T_ref_from_scan"), (4, 4)),
        ("gravity_ref", doc.get("gravity_ref"), (3,)),
        ("nipple_lps_mm", doc.get("nipple_lps_mm"), (3,)),
        ("back_plane.normal", (plane or {}).get("normal"), (3,)),
        ("back_plane.point_lps_mm", (plane or {}).get("point_lps_mm"), (3,)),
    ]
    if doc.get("tumour_lps_mm") is not None:
        wanted.append(("tumour_lps_mm", doc["tumour_lps_mm"], (3,)))
    for key, value, shape in wanted:
        try:
            a = np.asarray(value, float)
        except (TypeError, ValueError):
            a = np.empty(0)
        if value is None or a.shape != shape or not np.all(np.isfinite(a)):
            raise ValueError(
                f"{path}: `{key}` must be {' x '.join(map(str, shape))} finite numbers, "
                f"got {value!r}; run `phantom-calib ingest` again"
            )


def read_scan(work: Path, entry: ScanEntry) -> ScanMeasurement:
    """One scan's measurements from ``WORK/scans/<name>/`` (role from ``entry``)."""
    import imaging
    from registration import apply_transform

    from .ingest import load_ingest

    name = entry.name
    folder = work / "scans" / name
    doc = load_ingest(work, name)
    _check_ingest_shapes(doc, folder / "ingest.json")
    surf = imaging.read_ply(folder / "surface_ref.ply")
    T = np.asarray(doc["T_ref_from_scan"], float)
    tumour = doc.get("tumour_lps_mm")
    plane = doc["back_plane"]
    normal = T[:3, :3] @ np.asarray(plane["normal"], float)
    back_point = apply_transform(T, plane["point_lps_mm"])
    centroid = surf.vertices_lps_mm.mean(axis=0)
    if normal @ (centroid - back_point) > 0:  # make it point away from the body
        normal = -normal
    normal = normal / np.linalg.norm(normal)
    if surf.back_plate is not None:
        flags = np.asarray(surf.back_plate, bool)
    else:  # a surface written without flags: the vertices on the back plane are the plate
        from imaging.surface import BACK_PLATE_TOL_MM

        flags = np.abs((surf.vertices_lps_mm - back_point) @ normal) < BACK_PLATE_TOL_MM
    return ScanMeasurement(
        name=name,
        role=entry.role,  # the current session's role, never a stale ingest record
        gravity_ref=np.asarray(doc["gravity_ref"], float),
        vertices_mm=surf.vertices_lps_mm,
        faces=surf.faces,
        back_plate=flags,
        nipple_mm=apply_transform(T, doc["nipple_lps_mm"]),
        tumour_mm=None if tumour is None else apply_transform(T, tumour),
        back_point_mm=back_point,
        back_normal=normal,
        T_ref_from_scan=T,
        posture_plane=entry.posture_plane,
        posture_angle_deg=entry.posture_angle_deg,
        fov_edge=surf.fov_edge,
        back_voxel_depth_mm=plane.get("voxel_depth_mm"),
        tre_nipple_mm=doc.get("tre_nipple_mm"),
    )


def load_measurements(work: str | Path, session: Session) -> Measurements:
    """Read every scan's ``ingest.json`` and ``surface_ref.ply`` from a work folder.

    Parameters
    ----------
    work : str or Path
        The work folder ``ingest`` wrote (its ``scans/<name>/``).
    session : Session
        The session those results were ingested from (:func:`load_session`).

    Returns
    -------
    Measurements
        Every scan's measured geometry in the ref frame (the reference scan's LPS), mm.

    Raises
    ------
    calib.data.ingest.StaleIngestError
        The ingest results are missing, or not those of the session's current scans
        (the recorded fingerprints differ): run ``phantom-calib ingest`` again.
    ValueError
        A scan's ``ingest.json`` lacks an array it needs or holds one of the wrong shape
        or non-finite.
    imaging.SurfaceError
        A scan's ``surface_ref.ply`` cannot be read.
    """
    from .ingest import StaleIngestError, stale_reasons

    work = Path(work)
    reasons = stale_reasons(work, session)
    if reasons:
        raise StaleIngestError(
            f"{work}: the ingest results do not match {session.folder}: "
            f"{'; '.join(reasons)}. Run `phantom-calib ingest` again"
        )
    scans = {s.name: read_scan(work, s) for s in session.scans}
    return Measurements(scans[session.reference.name], scans, session.density_kg_m3)
