"""Volume readers and writers: DICOM series folders, NIfTI, NRRD and MHA.

All readers return a :class:`~imaging.volume.Volume` in LPS millimetres; NIfTI's RAS world
frame is converted to LPS. Writers are atomic (a temporary file in the same folder, then
:func:`os.replace`).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from imaging.dicom import DICOM_SUFFIXES
from imaging.errors import VolumeReadError
from imaging.files import atomic_write
from imaging.volume import Volume

__all__ = ["read_volume", "write_nifti", "write_volume"]

log = logging.getLogger(__name__)

_RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
_ITK_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd")
#: The most of a file read to find its NRRD or MetaImage text header.
_HEADER_BYTES = 1 << 20
#: NRRD ``space units`` read as millimetres; "" is NRRD's unknown unit, read as mm as NIfTI's.
_MM_UNITS = {"", "mm", "millimeter", "millimeters", "millimetre", "millimetres"}
#: NRRD ``space`` values that name patient axes (with or without time); the others
#: (``scanner-xyz``, ``3D-right-handed``, ...) are read as LPS, with a warning.
_ANATOMICAL_SPACES = {
    f"{name}{time}"
    for name in ("right-anterior-superior", "left-anterior-superior", "left-posterior-superior")
    for time in ("", "-time")
} | {"ras", "las", "lps", "rast", "last", "lpst"}


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix.lower()


def read_volume(path: str | os.PathLike) -> Volume:
    """Read a scan volume, dispatching on the path.

    Parameters
    ----------
    path : path-like
        A folder holding one DICOM series (not one of its files), or a ``.nii``/``.nii.gz``,
        ``.nrrd``/``.nhdr`` or ``.mha``/``.mhd`` file.

    Returns
    -------
    Volume
        Array in (i, j, k) order and its index-to-LPS affine (mm).

    Raises
    ------
    VolumeReadError
        Missing, truncated, corrupt or unsupported input, or one whose placement in the
        scanner is unknown or not in millimetres; the message names the file.
    """
    p = Path(path)
    if p.is_dir():
        from imaging.dicom import read_dicom_series

        return _check_geometry(read_dicom_series(p))
    if not p.is_file():
        raise VolumeReadError(f"{p}: no such file or folder")
    suffix = _suffix(p)
    if suffix in (".nii", ".nii.gz"):
        return _check_geometry(_read_nifti(p))
    if suffix in _ITK_SUFFIXES:
        return _check_geometry(_read_itk(p))
    if suffix in DICOM_SUFFIXES:
        raise VolumeReadError(
            f"{p}: a single DICOM file; a DICOM scan is read as a whole series: point `path` "
            f"at the series folder that holds all its slices ({p.parent})"
        )
    raise VolumeReadError(
        f"{p}: unsupported volume format {suffix!r} (expected a DICOM folder, .nii, .nii.gz, "
        ".nrrd, .nhdr, .mha or .mhd)"
    )


#: Voxel edges under this (mm) are taken for lengths in metres: MR voxels are 0.1 mm and
#: more, and a 1 mm voxel written in metres is 0.001 (review BM: a MetaImage stores no
#: unit, and such a volume failed later, in the marker detection, without a word of units)
MIN_VOXEL_MM = 0.01


#: Direction cosines of two voxel axes whose dot product exceeds this are sheared: about
#: 0.06 degrees off a right angle (oblique scans' direction matrices are orthonormal to
#: round-off; a written float32 affine to about 1e-7)
SHEAR_TOLERANCE = 1e-3


def _check_geometry(volume: Volume) -> Volume:
    """``volume``, unless its voxel edges are too small to be millimetres; shear is said.

    Review BM: a sheared affine (a gantry tilt kept in the affine, or an oblique resample
    written as an sform) was read without a word, while the segmentation's smoothing and
    erosion and the inclusions' depths take the voxel axes as orthogonal (the surface,
    mapped through the whole affine, is right).
    """
    sp = volume.spacing_mm
    d = volume.direction
    cos = np.abs(d.T @ d - np.eye(3)).max()
    if cos > SHEAR_TOLERANCE:
        log.warning(
            "%s: the voxel axes are sheared (%.2f degrees off square at most): the surface "
            "is placed through the whole affine, but the segmentation's smoothing and "
            "erosion and the inclusions' depths take the axes as square; resample the scan "
            "onto a square grid for full accuracy",
            volume.source,
            float(np.degrees(np.arcsin(min(cos, 1.0)))),
        )
    if float(sp.min()) < MIN_VOXEL_MM:
        raise VolumeReadError(
            f"{volume.source}: voxel edges of {', '.join(f'{v:.3g}' for v in sp)} mm, under "
            f"{MIN_VOXEL_MM:g} mm: lengths in metres? phantom-calib reads millimetres (a "
            "MetaImage stores no unit); write the scan with its spacing and origin in mm"
        )
    return volume


def _read_nifti(path: Path) -> Volume:
    import nibabel as nib

    try:
        img = nib.load(str(path))
        arr = np.asanyarray(img.dataobj)
    except Exception as exc:  # nibabel raises many types for broken files
        raise VolumeReadError(f"{path}: cannot read NIfTI file ({exc})") from exc
    if arr.ndim == 4 and arr.shape[3] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise VolumeReadError(f"{path}: expected a 3-D volume, got shape {arr.shape}")
    affine = _RAS_FROM_LPS @ _nifti_scanner_affine(path, img.header)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise VolumeReadError(f"{path}: NIfTI affine is missing or singular")
    return Volume(np.array(arr), affine, str(path))


#: NIfTI's xform code of scanner coordinates (NIFTI_XFORM_SCANNER_ANAT); 2-4 are aligned,
#: Talairach and MNI spaces.
_NIFTI_SCANNER = 1


def _nifti_scanner_affine(path: Path, header) -> np.ndarray:
    """A NIfTI's voxel-to-RAS affine in the scanner's frame, checked.

    Refused: no sform nor qform (both codes 0: nibabel places the voxels by their sizes
    alone, and the session's gravity would land in an arbitrary frame); spatial units
    other than mm (``unknown`` is read as mm, as scanners' converters write it). The form
    whose code says scanner coordinates (1) is used, the sform where both do, as nibabel
    does (an sform and a qform that disagree are logged); where neither does (codes 2-4:
    an aligned, Talairach or MNI space) the sform, with a warning: ``scanner.gravity`` is
    read in the scanner's frame (review AE).
    """
    s_code, q_code = int(header["sform_code"]), int(header["qform_code"])
    if s_code == 0 and q_code == 0:
        raise VolumeReadError(
            f"{path}: the NIfTI header has neither an sform nor a qform (both codes 0), so "
            "its orientation in the scanner is unknown; write it with its scanner geometry"
        )
    unit = header.get_xyzt_units()[0]
    if unit not in ("mm", "unknown"):
        raise VolumeReadError(
            f"{path}: the NIfTI spatial unit is {unit!r}; phantom-calib reads millimetres "
            "(xyzt_units mm)"
        )
    if s_code > 0 and q_code > 0:
        gap = np.abs(header.get_sform() - header.get_qform()).max()
        if gap > 1e-3:
            log.warning(
                "%s: NIfTI sform and qform differ by up to %.3g; the %s is used",
                path,
                gap,
                "qform" if q_code == _NIFTI_SCANNER != s_code else "sform",
            )
    if q_code == _NIFTI_SCANNER != s_code:
        return np.asarray(header.get_qform(), float)
    if s_code != _NIFTI_SCANNER:
        log.warning(
            "%s: the NIfTI's placement is in space code %d, not the scanner's (1): "
            "scanner.gravity is read in it as if it were",
            path,
            s_code or q_code,
        )
    return np.asarray(header.get_sform() if s_code else header.get_qform(), float)


def _read_itk(path: Path) -> Volume:
    import SimpleITK as sitk

    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unknown reason"
        raise VolumeReadError(f"{path}: cannot read image ({msg})") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise VolumeReadError(f"{path}: expected a 3-D scalar volume")
    if _suffix(path) in (".nrrd", ".nhdr"):
        _check_nrrd_geometry(path)
    else:
        header = _metaimage_header(path)
        _check_metaimage_geometry(path, header)
        direction = np.array(img.GetDirection(), float).reshape(3, 3)
        _check_metaimage_orientation(path, header, direction)
    return Volume.from_sitk(img, source=str(path))


def _metaimage_header(path: Path) -> dict[str, str]:
    """A MetaImage header's fields (names lower case) up to ``ElementDataFile``, its last."""
    fields = {}
    for line in _header_lines(path):
        name, sep, value = line.partition("=")
        if not sep:
            continue
        fields[name.strip().lower()] = value.strip()
        if name.strip().lower() == "elementdatafile":
            break
    return fields


def _check_metaimage_orientation(path: Path, header: dict, direction: np.ndarray) -> None:
    """Warn where a MetaImage's ``AnatomicalOrientation`` disagrees with its matrix.

    ITK reads a MetaImage's ``TransformMatrix`` and ``Offset`` as LPS and ignores
    ``AnatomicalOrientation`` (review AE: ``RAI`` and ``LPI`` headers read alike); the
    field names, per axis, the side its coordinate grows from (``RAI``: the identity in
    LPS). A file whose field disagrees may come from a writer that meant another space
    (RAS: x and y flipped).
    """
    given = header.get("anatomicalorientation", "").upper()
    if len(given) != 3 or given == "???":
        return
    # the side each image axis grows from: the opposite of where its LPS direction points
    sides = ("RL", "AP", "IS")  # LPS +x points to L (grows from R), +y to P, +z to S
    axes = np.argmax(np.abs(direction), axis=0)  # each column's dominant LPS axis
    read = "".join(sides[a][0 if direction[a, k] > 0 else 1] for k, a in enumerate(axes.tolist()))
    if read != given:
        log.warning(
            "%s: AnatomicalOrientation %s, but its TransformMatrix read as LPS (as ITK reads "
            "it, ignoring that field) says %s: check the coordinates (a writer that meant "
            "RAS flips x and y)",
            path,
            given,
            read,
        )


def _header_lines(path: Path) -> list[str]:
    """The text lines at the start of a file (its NRRD or MetaImage header and what follows)."""
    with open(path, "rb") as fh:
        head = fh.read(_HEADER_BYTES)
    return head.decode("latin-1").replace("\r\n", "\n").split("\n")


def _check_nrrd_geometry(path: Path) -> None:
    """Refuse an NRRD whose placement in the scanner is unknown or not in millimetres.

    SimpleITK reads an NRRD without ``space`` and ``space directions`` as the identity at
    origin 0, and ignores ``space units`` (metres would be read as mm, a 1000-fold error),
    so both are checked on the text header (which ends at the first empty line).
    """
    fields: dict[str, str] = {}
    for line in _header_lines(path)[1:]:
        if not line.strip():
            break
        name, sep, value = line.partition(":")
        if line.startswith("#") or not sep or value.startswith("="):  # comment, key:=value
            continue
        fields[name.strip()] = value.strip()
    # review BM: `space dimension: 3` is NRRD's form of a space that names no axes (what
    # some exporters write); it places the volume as a non-anatomical `space` does
    if "space" not in fields and fields.get("space dimension") == "3":
        fields["space"] = "space dimension: 3"
    missing = [f"`{name}`" for name in ("space", "space directions") if name not in fields]
    if missing:
        raise VolumeReadError(
            f"{path}: the NRRD header has no {' or '.join(missing)} field, so its orientation "
            "in the scanner is unknown; write it with its scanner geometry (`space` or "
            "`space dimension: 3`, `space directions`, `space origin`)"
        )
    if fields["space"].lower() not in _ANATOMICAL_SPACES:
        log.warning(
            "%s: the NRRD space is %r, which names no patient axes: its axes are read as "
            "LPS (as DICOM's); session.toml's gravity is in them, so every scan of the "
            "session should be written in the same space",
            path,
            fields["space"],
        )
    if "space units" in fields:
        raw = fields["space units"]
        units = re.findall(r'"([^"]*)"', raw) if '"' in raw else raw.split()
        if any(u.strip().lower() not in _MM_UNITS for u in units):
            raise VolumeReadError(
                f"{path}: the NRRD space units are {raw}; phantom-calib reads millimetres "
                '(space units "mm", or none)'
            )


def _check_metaimage_geometry(path: Path, header: dict) -> None:
    """Refuse a MetaImage header that says nothing of where the volume lies in the scanner.

    Without ``TransformMatrix`` and ``Offset`` (or their aliases) SimpleITK places the voxels
    at the identity at origin 0. MetaImage stores no spatial unit, so units are not checked.
    """
    keys = set(header)
    oriented = bool(keys & {"transformmatrix", "rotation", "orientation"})
    placed = bool(keys & {"offset", "position", "origin"})
    if not (oriented or placed):
        raise VolumeReadError(
            f"{path}: the MetaImage header has neither `TransformMatrix` nor `Offset` (nor "
            "`Rotation`/`Orientation`, `Position`/`Origin`), so its placement in the scanner "
            "is unknown; write it with its scanner geometry"
        )


def write_nifti(volume: Volume, path: str | os.PathLike) -> Path:
    """Write a volume as NIfTI-1 (``.nii`` or ``.nii.gz``), atomically.

    The LPS affine is converted to RAS and stored as both sform and qform (code 1,
    scanner). Returns the path written.
    """
    import nibabel as nib

    target = Path(path)
    if _suffix(target) not in (".nii", ".nii.gz"):
        raise ValueError(f"{target}: NIfTI path must end in .nii or .nii.gz")
    affine_ras = _RAS_FROM_LPS @ volume.affine_lps_from_index
    arr = volume.array
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    img = nib.Nifti1Image(arr, affine_ras)
    img.set_sform(affine_ras, code=1)
    img.set_qform(affine_ras, code=1)
    img.header.set_xyzt_units("mm")
    return atomic_write(target, lambda tmp: nib.save(img, tmp), suffix=_suffix(target))


def write_volume(volume: Volume, path: str | os.PathLike) -> Path:
    """Write a volume as NIfTI, NRRD or MHA (chosen by the suffix), atomically."""
    target = Path(path)
    if _suffix(target) in (".nii", ".nii.gz"):
        return write_nifti(volume, target)
    if _suffix(target) not in (".nrrd", ".mha"):
        raise ValueError(f"{target}: unsupported output suffix (use .nii[.gz], .nrrd or .mha)")
    import SimpleITK as sitk

    arr = volume.array.astype(np.uint8) if volume.array.dtype == bool else volume.array
    image = volume.with_array(arr).to_sitk()
    return atomic_write(target, lambda tmp: sitk.WriteImage(image, str(tmp), useCompression=True),
                        suffix=_suffix(target))  # fmt: skip
