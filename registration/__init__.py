"""Rigid registration of phantom scans: fiducial fit, gravity, ICP and surface distances.

Heavy dependencies (open3d) are imported inside the functions that need them.
"""

from registration.correspondence import (
    CONFIDENCE_DEFINITION,
    AmbiguousMatchWarning,
    ConstellationError,
    ConstellationMatch,
    match_constellation,
)
from registration.distances import (
    DistanceSummary,
    PointDistance,
    PointError,  # noqa: F401  (former name, kept importable)
    SurfaceDistances,
    SurfaceError,  # noqa: F401  (former name, kept importable)
    closest_point_distances,
    hausdorff_mm,
    landmark_errors,
    nipple_error,
    point_to_surface_distances,
    summarise,
    surface_errors,
)
from registration.errors import (
    AmbiguousCorrespondenceError,
    DegenerateMarkersError,
    MarkerCountError,
    PostureMismatchError,
    PostureMismatchWarning,
    RegistrationError,
)
from registration.gravity import (
    PostureCheck,
    angle_between_deg,
    check_posture,
    gravity_in_reference,
)
from registration.icp import IcpLevel, IcpResult, icp_refine, sample_triangles
from registration.rigid import RigidFit, apply_transform, check_marker_geometry, fit_rigid
from registration.session import (
    ScanRegistration,
    footprint_mismatch_mm,
    format_registration_table,
    register_scans,
)

__all__ = [
    "CONFIDENCE_DEFINITION",
    "AmbiguousCorrespondenceError",
    "AmbiguousMatchWarning",
    "ConstellationError",
    "ConstellationMatch",
    "DegenerateMarkersError",
    "DistanceSummary",
    "IcpLevel",
    "IcpResult",
    "MarkerCountError",
    "PointDistance",
    "PostureCheck",
    "PostureMismatchError",
    "PostureMismatchWarning",
    "RegistrationError",
    "RigidFit",
    "ScanRegistration",
    "SurfaceDistances",
    "angle_between_deg",
    "apply_transform",
    "check_marker_geometry",
    "check_posture",
    "closest_point_distances",
    "fit_rigid",
    "footprint_mismatch_mm",
    "format_registration_table",
    "gravity_in_reference",
    "hausdorff_mm",
    "icp_refine",
    "landmark_errors",
    "match_constellation",
    "nipple_error",
    "point_to_surface_distances",
    "register_scans",
    "sample_triangles",
    "summarise",
    "surface_errors",
]
