"""One call from a scan volume to everything later stages need: :func:`process_scan`."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from imaging.detect import InclusionDetection, detect_fiducials, detect_inclusions
from imaging.landmarks import BackPlane, estimate_back_plane, find_nipple, select_tumour
from imaging.segment import segment_body
from imaging.surface import BACK_PLATE_TOL_MM, SurfaceMesh, extract_surface, mark_back_plate
from imaging.volume import Volume

__all__ = ["ScanResult", "process_scan"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ScanResult:
    """Everything extracted from one scan, in the scan's LPS frame (mm).

    Attributes
    ----------
    surface : SurfaceMesh
        Closed body surface with ``back_plate`` vertex flags.
    mask : Volume
        uint8 body mask on the scan grid.
    fiducials_lps_mm : (k, 3) ndarray
        Fiducial marker centroids (sorted lexicographically by L, P, S).
    nipple_lps_mm : (3,) ndarray
    tumour_lps_mm : (3,) ndarray or None
        Tracked inclusion centre (None when no inclusion was found).
    inclusions : InclusionDetection
        All inclusions: centres (n, 3) and volume-equivalent diameters (n,) in mm.
    back_plane : BackPlane
    voxel_size_mm : (3,) ndarray
        Spacing along i, j, k.
    quality : dict
        Segmentation, surface and landmark quality figures and stage timings (``time_*_s``).
    """

    surface: SurfaceMesh
    mask: Volume
    fiducials_lps_mm: np.ndarray
    nipple_lps_mm: np.ndarray
    tumour_lps_mm: np.ndarray | None
    inclusions: InclusionDetection
    back_plane: BackPlane
    voxel_size_mm: np.ndarray
    quality: dict = field(default_factory=dict)

    def to_json_dict(self) -> dict:
        """JSON-ready summary (lists and floats) for ``ingest.json``."""
        t = None if self.tumour_lps_mm is None else self.tumour_lps_mm.tolist()
        return {
            "fiducials_lps_mm": self.fiducials_lps_mm.tolist(),
            "nipple_lps_mm": self.nipple_lps_mm.tolist(),
            "tumour_lps_mm": t,
            "inclusions": [
                {"centre_lps_mm": c.tolist(), "diameter_mm": float(d)}
                for c, d in zip(
                    self.inclusions.centres_lps_mm, self.inclusions.diameters_mm, strict=True
                )
            ],
            "voxel_size_mm": self.voxel_size_mm.tolist(),
            "back_plane": {
                "point_lps_mm": self.back_plane.point_lps_mm.tolist(),
                "normal": self.back_plane.normal.tolist(),
                "method": self.back_plane.method,
                "beyond_face": self.back_plane.beyond_face,
                "fiducials_off_face_deg": self.back_plane.fiducials_off_face_deg,
                "voxel_depth_mm": self.back_plane.voxel_depth_mm,
            },
            "quality": {
                k: (v if v is None or isinstance(v, (bool, int, str)) else _finite_or_none(v))
                for k, v in self.quality.items()
            },
        }


#: Body voxels on the volume's edge up to this height above the back plane (mm, plus one
#: voxel) are the back face resting on a field of view that starts at the plate.
FOV_CUT_TOL_MM = 2.0


def _finite_or_none(v) -> float | None:
    """A quality figure for JSON: None where it is not finite (strict JSON has no NaN)."""
    v = float(v)
    return v if np.isfinite(v) else None


def fov_cut_height_mm(mask: Volume, plane: BackPlane) -> float:
    """Largest height above ``plane`` of a body voxel on the volume's edge (mm; 0: none).

    A field of view that cuts the body leaves body voxels on the volume's edge; the
    extracted surface there is the volume's edge. The back face resting on the plate may
    lie on the edge (heights near 0).

    Parameters
    ----------
    mask : Volume
        The body mask (:class:`imaging.segment.BodySegmentation`'s ``mask``).
    plane : BackPlane

    Returns
    -------
    float
    """
    a = np.asarray(mask.array).astype(bool)
    edge = np.ones(a.shape, bool)
    edge[1:-1, 1:-1, 1:-1] = False  # the voxels on the volume's six faces
    idx = np.argwhere(a & edge)
    if not len(idx):
        return 0.0
    h = (mask.index_to_lps(idx.astype(float)) - plane.point_lps_mm) @ plane.normal
    return float(max(0.0, h.max()))


def mark_fov_edge(
    vertices_lps_mm: np.ndarray, *, mask: Volume, plane: BackPlane, min_height_mm: float
) -> np.ndarray:
    """Flag the surface vertices where the field of view cuts the body, (n,) bool.

    A vertex within one voxel of one of the volume's six faces and more than
    ``min_height_mm`` above ``plane`` (the back-plate flag's tolerance, so that the two
    flags meet) lies on the cut: the surface there is the volume's edge, not the
    phantom's. Lower vertices on an edge are the back plate's.

    Parameters
    ----------
    vertices_lps_mm : ndarray, shape (n, 3)
    mask : Volume
        The volume's grid (the body mask).
    plane : BackPlane
    min_height_mm : float

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    v = np.asarray(vertices_lps_mm, float)
    ijk = mask.lps_to_index(v)
    top = np.asarray(mask.array.shape, float) - 1.0
    on_edge = ((ijk < 1.0) | (ijk > top - 1.0)).any(axis=1)
    return on_edge & ((v - plane.point_lps_mm) @ plane.normal > min_height_mm)


def process_scan(
    volume: Volume,
    *,
    expected_fiducials: int | None = 3,
    tumour_hint_lps_mm: np.ndarray | None = None,
    target_faces: int = 20000,
    smooth_iterations: int = 10,
    back_plate_tol_mm: float = BACK_PLATE_TOL_MM,
    marker_ratio: float = 2.0,
    inclusion_min_contrast: float = 0.15,
    seed: int = 0,
) -> ScanResult:
    """Segment a scan and extract its surface, fiducials, inclusions, nipple and tumour.

    Parameters
    ----------
    volume : Volume
        The MR scan (see :func:`imaging.io.read_volume`).
    expected_fiducials : int or None
        Expected marker count (``None``: accept any).
    tumour_hint_lps_mm : (3,) array, optional
        The tracked tumour is the inclusion nearest to this point (else the largest).
    target_faces : int
        Surface decimation target.
    smooth_iterations : int
        Taubin smoothing iterations.
    back_plate_tol_mm : float
        Vertices within this height of the back face are flagged ``back_plate``.
    marker_ratio, inclusion_min_contrast : float
        Detector thresholds relative to the body level (see :mod:`imaging.detect`).
    seed : int
        Seeds the bias-fit subsample and the RANSAC plane fallback.

    Raises
    ------
    ImagingError
        Empty segmentation, wrong marker count, ... (messages name the volume's source).
    """
    times = {}
    t0 = time.perf_counter()
    seg = segment_body(volume, marker_ratio=marker_ratio, seed=seed)
    times["time_segment_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fid = detect_fiducials(seg, expected=expected_fiducials, marker_ratio=marker_ratio)
    inc = detect_inclusions(seg, min_contrast=inclusion_min_contrast)
    times["time_detect_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    surf = extract_surface(
        seg.smoothed, mask=seg.mask, smooth_iterations=smooth_iterations, target_faces=target_faces
    )
    times["time_surface_s"] = time.perf_counter() - t0
    plane = estimate_back_plane(
        surf.vertices_lps_mm,
        fiducials_lps_mm=fid.centres_lps_mm,
        seed=seed,
        voxel_mm=volume.affine_lps_from_index[:3, :3],
    )
    flags = mark_back_plate(
        surf.vertices_lps_mm,
        plane_point_lps_mm=plane.point_lps_mm,
        plane_normal=plane.normal,
        tol_mm=back_plate_tol_mm,
    )
    nipple = find_nipple(surf.vertices_lps_mm, plane)
    cut = fov_cut_height_mm(seg.mask, plane)
    edge = None
    if cut > FOV_CUT_TOL_MM + float(volume.spacing_mm.max()):
        edge = mark_fov_edge(
            surf.vertices_lps_mm,
            mask=seg.mask,
            plane=plane,
            min_height_mm=back_plate_tol_mm,
        )
        log.warning(
            "%s: the field of view cuts the body: body voxels on the volume's edge lie up to "
            "%.0f mm above the back plate, where the surface is the volume's edge, not the "
            "phantom's: its %d vertices there are flagged fov_edge and left out of the fit "
            "and the errors",
            volume.source,
            cut,
            int(edge.sum()),
        )
        at = int(np.argmin(np.linalg.norm(surf.vertices_lps_mm - nipple.position_lps_mm, axis=1)))
        if edge[at]:
            log.warning(
                "%s: the nipple found lies on the field of view's cut: the scan misses the "
                "nipple, and its nipple figures and the nipple objective mean nothing",
                volume.source,
            )
    tumour = None
    if len(inc.diameters_mm):
        k = select_tumour(inc.centres_lps_mm, inc.diameters_mm, hint_lps_mm=tumour_hint_lps_mm)
        tumour = inc.centres_lps_mm[k]
    quality = {**{f"seg_{k}": v for k, v in seg.quality.items()}}
    quality.update({f"surface_{k}": v for k, v in surf.quality.items()})
    quality.update(
        n_fiducials=len(fid.centres_lps_mm),
        fiducials_dropped=int(fid.quality["n_dropped"]),
        fiducial_threshold=float(fid.quality["threshold"]),
        n_inclusions=len(inc.diameters_mm),
        inclusion_threshold=float(inc.quality["threshold"]),
        inclusions_too_large=int(inc.quality["n_too_large"]),
        inclusions_surface_layer=int(inc.quality["n_surface_layer"]),
        back_plate_fraction=float(flags.mean()),
        nipple_height_mm=nipple.height_mm,
        nipple_refined=bool(nipple.quality["refined"]),
        nipple_method=str(nipple.quality["method"]),
        fov_cut_height_mm=cut,
        fov_edge_vertices=0 if edge is None else int(edge.sum()),
        **times,
    )
    surface = SurfaceMesh(surf.vertices_lps_mm, surf.faces, flags, surf.quality, fov_edge=edge)
    return ScanResult(
        surface=surface,
        mask=seg.mask,
        fiducials_lps_mm=fid.centres_lps_mm,
        nipple_lps_mm=nipple.position_lps_mm,
        tumour_lps_mm=tumour,
        inclusions=inc,
        back_plane=plane,
        voxel_size_mm=volume.spacing_mm,
        quality=quality,
    )
