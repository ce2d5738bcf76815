"""The :class:`Volume` type: a 3-D image array with its index-to-LPS affine.

Conventions
-----------
``array[i, j, k]`` is indexed in the order (i, j, k) where, for a DICOM series, ``i`` runs
along a row (the column index), ``j`` down a column (the row index) and ``k`` over slices.
This is also SimpleITK's (x, y, z) index order and nibabel's array order. The 4 x 4
``affine_lps_from_index`` maps homogeneous indices ``(i, j, k, 1)`` (voxel centres) to
patient LPS coordinates in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Volume", "affine_from_geometry"]


def affine_from_geometry(
    origin_lps_mm: np.ndarray, spacing_mm: np.ndarray, direction: np.ndarray
) -> np.ndarray:
    """Build an index-to-LPS affine.

    Parameters
    ----------
    origin_lps_mm : (3,) array
        LPS position (mm) of the centre of voxel (0, 0, 0).
    spacing_mm : (3,) array
        Voxel spacing (mm) along i, j, k.
    direction : (3, 3) array
        Unit direction cosines of the i, j, k axes in LPS, as columns.

    Returns
    -------
    (4, 4) ndarray
        ``affine_lps_from_index``.
    """
    A = np.eye(4)
    A[:3, :3] = np.asarray(direction, float) @ np.diag(np.asarray(spacing_mm, float))
    A[:3, 3] = np.asarray(origin_lps_mm, float)
    return A


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar 3-D image in patient LPS millimetres.

    Parameters
    ----------
    array : (ni, nj, nk) ndarray
        Voxel values in (i, j, k) index order (see the module docstring).
    affine_lps_from_index : (4, 4) ndarray
        Maps homogeneous voxel indices to LPS mm (voxel centres).
    source : str
        Where the volume came from (file or folder path, or a description); used in messages.
    """

    array: np.ndarray
    affine_lps_from_index: np.ndarray
    source: str = field(default="<memory>")

    def __post_init__(self) -> None:
        arr = np.asarray(self.array)
        A = np.asarray(self.affine_lps_from_index, dtype=float)
        if arr.ndim != 3:
            raise ValueError(f"{self.source}: volume array must be 3-D, got shape {arr.shape}")
        if A.shape != (4, 4) or not np.all(np.isfinite(A)):
            raise ValueError(f"{self.source}: affine must be a finite 4 x 4 matrix")
        if abs(np.linalg.det(A[:3, :3])) < 1e-12:
            raise ValueError(f"{self.source}: affine is singular")
        object.__setattr__(self, "array", arr)
        object.__setattr__(self, "affine_lps_from_index", A)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (ni, nj, nk)."""
        return tuple(int(n) for n in self.array.shape)  # type: ignore[return-value]

    @property
    def spacing_mm(self) -> np.ndarray:
        """Voxel spacing (3,) in mm along i, j, k."""
        return np.linalg.norm(self.affine_lps_from_index[:3, :3], axis=0)

    @property
    def direction(self) -> np.ndarray:
        """Direction cosines (3, 3) of the i, j, k axes in LPS (columns)."""
        return self.affine_lps_from_index[:3, :3] / self.spacing_mm

    @property
    def origin_lps_mm(self) -> np.ndarray:
        """LPS position (3,) in mm of voxel (0, 0, 0)."""
        return self.affine_lps_from_index[:3, 3].copy()

    @property
    def voxel_volume_mm3(self) -> float:
        """Volume of one voxel in mm^3."""
        return float(abs(np.linalg.det(self.affine_lps_from_index[:3, :3])))

    def index_to_lps(self, ijk: np.ndarray) -> np.ndarray:
        """Map (n, 3) (possibly fractional) indices to (n, 3) LPS points in mm.

        Parameters
        ----------
        ijk : (N, 3) float
            Voxel indices in (i, j, k) array order, possibly fractional; integers are voxel
            centres. Any shape ``(..., 3)`` is accepted.

        Returns
        -------
        (N, 3) float
            The same points in the patient LPS frame, mm (shape like ``ijk``):
            ``affine_lps_from_index`` applied.
        """
        ijk = np.asarray(ijk, dtype=float)
        A = self.affine_lps_from_index
        return ijk @ A[:3, :3].T + A[:3, 3]

    def lps_to_index(self, points_lps_mm: np.ndarray) -> np.ndarray:
        """Map (n, 3) LPS points in mm to (n, 3) fractional indices.

        The inverse of :meth:`index_to_lps`.

        Parameters
        ----------
        points_lps_mm : (N, 3) float
            Points in the patient LPS frame, mm. Any shape ``(..., 3)`` is accepted, as
            by :meth:`index_to_lps`.

        Returns
        -------
        (N, 3) float
            Fractional voxel indices in (i, j, k) array order (shape like
            ``points_lps_mm``); integers are voxel centres. Points outside the grid give
            indices outside ``[0, shape)``; nothing is clipped.
        """
        p = np.asarray(points_lps_mm, dtype=float)
        A = self.affine_lps_from_index
        # review BJ: solve() on the transposed points took (3,) and (N, 3) only
        return (p - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T

    def with_array(self, array: np.ndarray, *, source: str | None = None) -> Volume:
        """Return a volume on the same grid with another array of the same shape."""
        array = np.asarray(array)
        if array.shape != self.array.shape:
            raise ValueError(f"shape {array.shape} differs from the grid {self.array.shape}")
        return Volume(array, self.affine_lps_from_index.copy(), source or self.source)

    def to_sitk(self):  # SimpleITK is imported lazily
        """Return a ``SimpleITK.Image`` with the same geometry (array copied).

        Returns
        -------
        SimpleITK.Image
            The voxel values with ITK's LPS origin (mm), spacing (mm) and direction
            cosines taken from ``affine_lps_from_index``; ITK's index ``(i, j, k)`` is this
            array's (its numpy view is ``(k, j, i)``).
        """
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(self.array, (2, 1, 0))))
        img.SetSpacing([float(s) for s in self.spacing_mm])
        img.SetOrigin([float(o) for o in self.origin_lps_mm])
        img.SetDirection([float(d) for d in self.direction.ravel()])
        return img

    @classmethod
    def from_sitk(cls, image, *, source: str = "<sitk>") -> Volume:
        """Build a volume from a 3-D scalar ``SimpleITK.Image`` (LPS, as ITK uses).

        Parameters
        ----------
        image : SimpleITK.Image
            3-D, one component per voxel; its origin, spacing (mm) and direction are in
            LPS, as ITK keeps them.
        source : str
            Where the image came from, for messages.

        Returns
        -------
        Volume
            The array in (i, j, k) index order (ITK's numpy view transposed) with
            ``affine_lps_from_index`` built from the image's geometry.

        Raises
        ------
        ValueError
            ``image`` is not 3-D or not scalar.
        """
        if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
            raise ValueError(f"{source}: expected a 3-D scalar image")
        import SimpleITK as sitk

        arr = np.transpose(sitk.GetArrayFromImage(image), (2, 1, 0))
        direction = np.array(image.GetDirection(), float).reshape(3, 3)
        A = affine_from_geometry(
            np.array(image.GetOrigin()), np.array(image.GetSpacing()), direction
        )
        return cls(arr, A, source)
