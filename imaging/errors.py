"""Exception classes of the imaging package.

Every error derives from :class:`ImagingError` (a :class:`ValueError`) and its message names
the file (or input) and the reason.
"""

from __future__ import annotations

__all__ = [
    "DicomSeriesError",
    "FiducialError",
    "ImagingError",
    "SegmentationError",
    "SurfaceError",
    "VolumeReadError",
]


class ImagingError(ValueError):
    """Base class for bad imaging input or a failed imaging stage."""


class VolumeReadError(ImagingError):
    """A volume file that is missing, truncated, corrupt or of an unsupported format."""


class DicomSeriesError(VolumeReadError):
    """A DICOM series folder that violates the expected structure.

    For example several series, a missing slice, mixed orientation, a non-MR modality.
    """


class SegmentationError(ImagingError):
    """A segmentation that found nothing usable (empty body, no object at a seed point)."""


class FiducialError(SegmentationError):
    """A fiducial marker count different from the expected count."""


class SurfaceError(ImagingError):
    """A surface that cannot be extracted, repaired or read."""
