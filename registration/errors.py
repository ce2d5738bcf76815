"""Exception and warning classes of the registration package."""

from __future__ import annotations

__all__ = [
    "AmbiguousCorrespondenceError",
    "DegenerateMarkersError",
    "MarkerCountError",
    "PostureMismatchError",
    "PostureMismatchWarning",
    "RegistrationError",
]


class RegistrationError(ValueError):
    """Base class for bad input or an impossible registration."""


class MarkerCountError(RegistrationError):
    """Marker sets of the wrong size or shape (fewer than 3, count mismatch)."""


class DegenerateMarkersError(RegistrationError):
    """Marker set that cannot define a rigid transform (coincident or collinear markers)."""


class AmbiguousCorrespondenceError(RegistrationError):
    """Unknown marker correspondence that two or more orderings explain about equally well."""


class PostureMismatchError(RegistrationError):
    """Registered gravity directions contradict the nominal posture angles."""


class PostureMismatchWarning(UserWarning):
    """Registered gravity directions disagree mildly with the nominal posture angles."""
