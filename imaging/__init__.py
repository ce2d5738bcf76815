"""MRI volumes to phantom surfaces, fiducials, nipple and tumour; MR-like synthetic scans.

Everything is in patient LPS millimetres. Heavy dependencies (SimpleITK, pydicom, nibabel,
open3d, scikit-image, trimesh) are imported inside the functions that need them.
"""

from imaging.detect import (
    FiducialDetection,
    InclusionDetection,
    InclusionMask,
    detect_fiducials,
    detect_inclusions,
    segment_inclusion_at,
)
from imaging.dicom import read_dicom_series, write_dicom_series
from imaging.errors import (
    DicomSeriesError,
    FiducialError,
    ImagingError,
    SegmentationError,
    SurfaceError,
    VolumeReadError,
)
from imaging.io import read_volume, write_nifti, write_volume
from imaging.landmarks import BackPlane, Nipple, estimate_back_plane, find_nipple, select_tumour
from imaging.pipeline import ScanResult, process_scan
from imaging.segment import BodySegmentation, segment_body
from imaging.surface import SurfaceMesh, extract_surface, mark_back_plate, read_ply, write_ply
from imaging.synthetic import MRIntensities, ScanGrid, render_mr_volume, scan_grid_covering
from imaging.volume import Volume, affine_from_geometry

__all__ = [
    "BackPlane",
    "BodySegmentation",
    "DicomSeriesError",
    "FiducialDetection",
    "FiducialError",
    "ImagingError",
    "InclusionDetection",
    "InclusionMask",
    "MRIntensities",
    "Nipple",
    "ScanGrid",
    "ScanResult",
    "SegmentationError",
    "SurfaceError",
    "SurfaceMesh",
    "Volume",
    "VolumeReadError",
    "affine_from_geometry",
    "detect_fiducials",
    "detect_inclusions",
    "estimate_back_plane",
    "extract_surface",
    "find_nipple",
    "mark_back_plate",
    "process_scan",
    "read_dicom_series",
    "read_ply",
    "read_volume",
    "render_mr_volume",
    "scan_grid_covering",
    "segment_body",
    "segment_inclusion_at",
    "select_tumour",
    "write_dicom_series",
    "write_nifti",
    "write_ply",
    "write_volume",
]
