"""Readers facing files from other writers: no DICOM preamble, stray files, enhanced DICOM,
rounded slice positions, NRRD and MetaImage headers without geometry or in metres."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from scipy.spatial.transform import Rotation

from imaging import (
    DicomSeriesError,
    Volume,
    VolumeReadError,
    affine_from_geometry,
    read_volume,
    write_dicom_series,
)

ENHANCED_MR = "1.2.840.10008.5.1.4.1.1.4.1"


def _volume(R: np.ndarray, spacing=(0.8, 0.9, 1.37), shape=(12, 10, 9)) -> Volume:
    A = affine_from_geometry([12.345, -67.891, 23.456], list(spacing), R)
    arr = np.random.default_rng(3).integers(0, 4000, shape).astype(np.uint16)
    return Volume(arr, A, "robust")


@pytest.fixture(scope="module")
def oblique() -> Volume:
    return _volume(Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix())


@pytest.fixture
def series(oblique, tmp_path) -> Path:
    write_dicom_series(oblique, tmp_path / "series", seed=4)
    return tmp_path / "series"


def _rewrite(folder: Path, change) -> None:
    """Rewrite every slice of ``folder`` after ``change(k, dataset)``; k counts from 0."""
    for k, f in enumerate(sorted(folder.glob("IM*.dcm"))):
        ds = pydicom.dcmread(f)
        change(k, ds)
        ds.save_as(f, enforce_file_format=True)


# ---- 0. compressed pixel data ----------------------------------------------------------


@pytest.mark.parametrize(
    "syntax", ["JPEGLosslessProcess14_1", "JPEGLSLossless", "JPEG2000Lossless", "RLELossless"]
)
def test_losslessly_compressed_series_read_to_the_same_volume(oblique, series, syntax):
    # a scanner or another renderer may write compressed slices; pydicom alone decodes
    # RLE, Pillow JPEG 2000, python-gdcm JPEG Lossless and JPEG-LS (without it those two
    # are 'cannot decode pixel data', checked by hand). Lossless: the same stored values,
    # so the same volume to the last bit (the uncompressed series reads exactly so)
    import gdcm  # a dependency (pyproject): without it the JPEG family is not decoded

    expected = read_volume(series)
    for f in sorted(series.glob("IM*.dcm")):
        reader = gdcm.ImageReader()
        reader.SetFileName(str(f))
        assert reader.Read()
        change = gdcm.ImageChangeTransferSyntax()
        change.SetTransferSyntax(gdcm.TransferSyntax(getattr(gdcm.TransferSyntax, syntax)))
        change.SetInput(reader.GetImage())
        assert change.Change()
        writer = gdcm.ImageWriter()
        writer.SetFileName(str(f))
        writer.SetFile(reader.GetFile())
        writer.SetImage(change.GetOutput())
        assert writer.Write()
    want = gdcm.TransferSyntax(getattr(gdcm.TransferSyntax, syntax)).GetString()
    for f in series.glob("IM*.dcm"):  # every slice in the syntax asked for (review P)
        assert pydicom.dcmread(f).file_meta.TransferSyntaxUID == want
    v = read_volume(series)
    np.testing.assert_array_equal(v.array, expected.array)
    np.testing.assert_array_equal(v.affine_lps_from_index, expected.affine_lps_from_index)


def test_pixel_data_no_decoder_reads_is_named(series):
    # a compressed syntax without a decoder: the file and pydicom's reason, not a crash
    from pydicom.encaps import encapsulate

    def change(k, ds):
        ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.4.100"  # MPEG2: no decoder
        ds.PixelData = encapsulate([ds.PixelData])

    _rewrite(series, change)
    with pytest.raises(DicomSeriesError, match=r"IM\w*\.dcm: cannot decode pixel data"):
        read_volume(series)


# ---- 1. files without the preamble and "DICM" prefix ----------------------------------


@pytest.mark.parametrize("implicit_vr", [True, False])
def test_dicom_without_preamble_reads(oblique, series, implicit_vr):
    expected = read_volume(series)
    for f in sorted(series.glob("*.dcm")):
        ds = Dataset()
        ds.update(pydicom.dcmread(f))  # no file meta, no preamble: Dataset.save_as's default
        ds.save_as(f, implicit_vr=implicit_vr, little_endian=True)
    assert b"DICM" not in next(series.glob("*.dcm")).read_bytes()[:132]
    v = read_volume(series)
    np.testing.assert_array_equal(v.array, oblique.array.astype(np.float32))
    np.testing.assert_allclose(v.affine_lps_from_index, oblique.affine_lps_from_index, atol=1e-5)
    np.testing.assert_allclose(v.affine_lps_from_index, expected.affine_lps_from_index)


def test_dicom_without_preamble_still_needs_image_data(series):
    ds = Dataset()
    ds.update(pydicom.dcmread(series / "IM00003.dcm"))
    del ds.ImagePositionPatient, ds.SOPClassUID
    ds.save_as(series / "IM00003.dcm", implicit_vr=True, little_endian=True)
    # no DICM prefix, no SOP class, no position: a file named .dcm that is not a DICOM image
    with pytest.raises(DicomSeriesError, match=r"IM00003.dcm: not a readable DICOM file"):
        read_volume(series)


# ---- 2. stray files in the series folder ----------------------------------------------


def test_stray_files_are_skipped_with_a_warning(oblique, series, caplog):
    rng = np.random.default_rng(0)
    (series / "info.yaml").write_text("scanner: 3T\nslices: 9\n")
    (series / "thumb.png").write_bytes(b"\x89PNG\r\n\x1a\n" + rng.bytes(2000))
    (series / "README").write_text("Phantom scan, left lateral.\n")
    report = pydicom.dcmread(series / "IM00001.dcm")
    del report.PixelData
    report.SOPClassUID = "1.2.840.10008.5.1.4.1.1.88.11"  # Basic Text SR: no pixel data
    report.save_as(series / "report.dcm", enforce_file_format=True)
    with caplog.at_level(logging.WARNING, logger="imaging.dicom"):
        v = read_volume(series)
    np.testing.assert_array_equal(v.array, oblique.array.astype(np.float32))
    skipped = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    for name in ("info.yaml", "thumb.png", "README", "report.dcm"):
        assert f"{name}: skipped" in skipped


def test_a_folder_of_stray_files_only_holds_no_dicom(tmp_path, caplog):
    folder = tmp_path / "scan"
    folder.mkdir()
    (folder / "thumb.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(500))
    with (
        caplog.at_level(logging.WARNING, logger="imaging.dicom"),
        pytest.raises(DicomSeriesError, match=r"scan: folder holds no DICOM files$"),
    ):
        read_volume(folder)
    assert "thumb.png: skipped" in caplog.text


def test_a_series_of_images_without_geometry_says_so(series):
    # review AE: SimpleITK/GDCM's defaults write secondary captures without
    # ImagePositionPatient; every slice was skipped and the error said "no DICOM files"
    for f in sorted(series.glob("*.dcm")):
        ds = pydicom.dcmread(f)
        del ds.ImagePositionPatient
        ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.7"  # Secondary Capture Image Storage
        ds.save_as(f, enforce_file_format=True)
    n = len(list(series.glob("*.dcm")))
    said = (
        rf"{n} DICOM images, none with ImagePositionPatient \(SOP class 1.2.840.10008.5.1.4.1.1.7"
    )
    with pytest.raises(DicomSeriesError, match=said):
        read_volume(series)


def test_a_folder_holding_a_volume_file_names_it(oblique, tmp_path, caplog):
    # review BG: a scan path at the folder of a NIfTI said "folder holds no DICOM files"
    from imaging import write_nifti

    write_nifti(oblique, tmp_path / "scan" / "left.nii.gz")
    with (
        caplog.at_level(logging.WARNING, logger="imaging.dicom"),
        pytest.raises(
            DicomSeriesError,
            match=r"scan: folder holds no DICOM files but the volume file\(s\) left\.nii\.gz: "
            r"point `path` at the file$",
        ),
    ):
        read_volume(tmp_path / "scan")


def test_a_parent_folder_names_its_subfolders(oblique, tmp_path):
    write_dicom_series(oblique, tmp_path / "exam" / "DICOM")
    (tmp_path / "exam" / "notes.txt").write_text("exam notes\n")
    with pytest.raises(
        DicomSeriesError,
        match=r"exam: folder holds no DICOM files; it has subfolders DICOM/: point `path` at "
        r"the series folder",
    ):
        read_volume(tmp_path / "exam")


# ---- 3. enhanced multi-frame DICOM, a single DICOM file -------------------------------


@pytest.mark.parametrize("sop_class", [ENHANCED_MR, "1.2.840.10008.5.1.4.1.1.4"])
def test_enhanced_multi_frame_is_refused(series, sop_class):
    frames = sorted(series.glob("*.dcm"))
    ds = pydicom.dcmread(frames[0])
    ds.PixelData = b"".join(pydicom.dcmread(f).PixelData for f in frames)
    ds.NumberOfFrames = len(frames)
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = sop_class
    # an enhanced image keeps its geometry in functional group sequences, not at the top
    del ds.ImagePositionPatient, ds.ImageOrientationPatient, ds.PixelSpacing
    for f in frames:
        f.unlink()
    ds.save_as(series / "enhanced.dcm", enforce_file_format=True)
    with pytest.raises(
        DicomSeriesError,
        match=r"enhanced.dcm: enhanced multi-frame DICOM .*9 frame\(s\).* is not supported; "
        r"export the series as classic single-frame MR slices .* or as a NIfTI file",
    ):
        read_volume(series)


def test_a_single_dicom_file_asks_for_the_series_folder(series):
    with pytest.raises(VolumeReadError, match=r"IM00001.dcm: .*point `path` at the series folder"):
        read_volume(series / "IM00001.dcm")


# ---- 4. ImagePositionPatient rounded to 0.1 mm ----------------------------------------


def _round_positions(k: int, ds) -> None:
    ds.ImagePositionPatient = [f"{float(x):.1f}" for x in ds.ImagePositionPatient]


@pytest.mark.parametrize(
    "R",
    [np.eye(3), Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()],
    ids=["axial", "oblique"],
)
def test_positions_rounded_to_a_tenth_of_a_mm_read(R, tmp_path):
    truth = _volume(R, spacing=(0.8, 0.9, 1.37), shape=(12, 10, 16))
    write_dicom_series(truth, tmp_path / "s")
    _rewrite(tmp_path / "s", _round_positions)
    v = read_volume(tmp_path / "s")
    np.testing.assert_array_equal(v.array, truth.array.astype(np.float32))
    corners = np.array([[i, j, k] for i in (0, 11) for j in (0, 9) for k in (0, 15)], float)
    err = np.abs(v.index_to_lps(corners) - truth.index_to_lps(corners))
    assert err.max() < 0.05, err.max()


def test_rounded_positions_with_a_missing_slice_are_refused(series):
    _rewrite(series, _round_positions)
    (series / "IM00005.dcm").unlink()
    with pytest.raises(DicomSeriesError, match="1 missing slice.*IM00004.dcm and IM00006.dcm"):
        read_volume(series)


def _step(k: int) -> float:
    return 0.23 * max(k - 4, 0)  # spacing 1.37 mm, then 1.6 mm from the fifth slice on


def _growing(k: int) -> float:
    return 0.05 * max(k - 3, 0) * (max(k - 3, 0) + 1) / 2  # spacing grows 0.05 mm a slice


def _one_off(k: int) -> float:
    return 0.05 * (k == 4)  # one slice 0.05 mm out of line: only rounding could explain that


@pytest.mark.parametrize(
    ("shift_mm", "fmt"),
    [(_step, ".1f"), (_growing, ".1f"), (_one_off, ".6f")],
    ids=["step-rounded", "growing-rounded", "one-off-exact"],
)
def test_variable_spacing_is_refused(oblique, series, shift_mm, fmt):
    normal = oblique.direction[:, 2]

    def stretch(k, ds):
        shifted = np.array(ds.ImagePositionPatient, float) + shift_mm(k) * normal
        ds.ImagePositionPatient = [format(x, fmt) for x in shifted]

    _rewrite(series, stretch)
    with pytest.raises(DicomSeriesError, match="IM0000.*non-uniform slice spacing"):
        read_volume(series)


# ---- 5. NRRD and MetaImage headers ------------------------------------------------------

_DATA = np.arange(24, dtype=np.uint8)
_NRRD = (
    "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 3 4\nendian: little\nencoding: raw\n"
    "kinds: domain domain domain\n"
)
_NRRD_SPACE = (
    "space: left-posterior-superior\nspace directions: (0.5,0,0) (0,0.6,0) (0,0,0.7)\n"
    "space origin: (1,2,3)\n"
)


def _nrrd(path: Path, extra: str) -> Path:
    path.write_bytes((_NRRD + extra + "\n").encode() + _DATA.tobytes())
    return path


def test_nrrd_with_geometry_in_mm_reads(tmp_path):
    for name, extra in [
        ("plain.nrrd", _NRRD_SPACE),
        ("mm.nrrd", _NRRD_SPACE + 'space units: "mm" "mm" "mm"\n'),
        ("unknown.nrrd", _NRRD_SPACE + 'space units: "" "" ""\n# a comment\nnote:=m\n'),
    ]:
        v = read_volume(_nrrd(tmp_path / name, extra))
        np.testing.assert_allclose(v.spacing_mm, [0.5, 0.6, 0.7])
        np.testing.assert_allclose(v.origin_lps_mm, [1, 2, 3])
        assert v.array[1, 2, 3] == _DATA.reshape(4, 3, 2)[3, 2, 1]
    (tmp_path / "d.raw").write_bytes(_DATA.tobytes())
    header = _NRRD.replace("NRRD0004", "NRRD0005") + _NRRD_SPACE + "data file: d.raw\n"
    (tmp_path / "d.nhdr").write_text(header)
    np.testing.assert_allclose(read_volume(tmp_path / "d.nhdr").origin_lps_mm, [1, 2, 3])


@pytest.mark.parametrize(
    "extra",
    [
        "",
        "spacings: 0.5 0.6 0.7\n",
        "space dimension: 3\n",
    ],
    ids=["bare", "spacings", "unnamed-space-without-directions"],
)
def test_nrrd_without_scanner_orientation_is_refused(tmp_path, extra):
    with pytest.raises(
        VolumeReadError,
        match=r"v.nrrd: the NRRD header has no `space[a-z ]*`.* field, so its orientation in the "
        r"scanner is unknown",
    ):
        read_volume(_nrrd(tmp_path / "v.nrrd", extra))


def test_an_nrrd_space_without_patient_axes_is_read_as_lps_and_said(tmp_path, caplog):
    # review T: `scanner-xyz` or `3D-right-handed` was read as LPS without a word; the
    # session's gravity is in the files' axes, so a session mixing them is wrong silently
    for space in ("scanner-xyz", "3D-right-handed"):
        extra = _NRRD_SPACE.replace("left-posterior-superior", space)
        caplog.clear()
        with caplog.at_level("WARNING", logger="imaging.io"):
            v = read_volume(_nrrd(tmp_path / f"{space}.nrrd", extra))
        np.testing.assert_allclose(v.origin_lps_mm, [1, 2, 3])  # as written
        assert f"the NRRD space is '{space}', which names no patient axes" in caplog.text
    # review BM: `space dimension: 3` is NRRD's space without names (refused before)
    extra = _NRRD_SPACE.replace("space: left-posterior-superior", "space dimension: 3")
    assert extra != _NRRD_SPACE
    caplog.clear()
    with caplog.at_level("WARNING", logger="imaging.io"):
        v = read_volume(_nrrd(tmp_path / "unnamed.nrrd", extra))
    np.testing.assert_allclose(v.origin_lps_mm, [1, 2, 3])
    np.testing.assert_allclose(v.spacing_mm, [0.5, 0.6, 0.7])
    assert "the NRRD space is 'space dimension: 3', which names no patient axes" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="imaging.io"):
        read_volume(_nrrd(tmp_path / "lps.nrrd", _NRRD_SPACE))
    assert "names no patient axes" not in caplog.text


def test_nrrd_in_metres_is_refused(tmp_path):
    path = _nrrd(tmp_path / "m.nrrd", _NRRD_SPACE + 'space units: "m" "m" "m"\n')
    with pytest.raises(
        VolumeReadError,
        match=r'm.nrrd: the NRRD space units are "m" "m" "m"; phantom-calib reads millimetres',
    ):
        read_volume(path)


_MHA = "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
_MHA_TAIL = "ElementSpacing = 0.5 0.6 0.7\nDimSize = 2 3 4\nElementType = MET_UCHAR\n"


def test_metaimage_without_placement_is_refused(tmp_path):
    bare = tmp_path / "bare.mha"
    bare.write_bytes((_MHA + _MHA_TAIL + "ElementDataFile = LOCAL\n").encode() + _DATA.tobytes())
    with pytest.raises(
        VolumeReadError,
        match=r"bare.mha: the MetaImage header has neither `TransformMatrix` nor `Offset`",
    ):
        read_volume(bare)
    placed = tmp_path / "placed.mha"
    geometry = "TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = 1 2 3\n"
    placed.write_bytes(
        (_MHA + geometry + _MHA_TAIL + "ElementDataFile = LOCAL\n").encode() + _DATA.tobytes()
    )
    np.testing.assert_allclose(read_volume(placed).origin_lps_mm, [1, 2, 3])
    (tmp_path / "d.raw").write_bytes(_DATA.tobytes())
    (tmp_path / "d.mhd").write_text(_MHA + _MHA_TAIL + "ElementDataFile = d.raw\n")
    with pytest.raises(VolumeReadError, match="d.mhd: the MetaImage header has neither"):
        read_volume(tmp_path / "d.mhd")


@pytest.mark.parametrize(("shear", "warned"), [(0.0, False), (0.0005, False), (0.2, True)])
def test_a_sheared_affine_is_read_and_said(tmp_path, caplog, shear, warned):
    # review BM: read without a word; the segmentation takes the axes as square
    import nibabel as nib

    A = np.diag([0.8, 0.9, 1.5, 1.0])
    A[0, 2] = shear * 1.5  # the k axis leans along x (RAS), as a kept gantry tilt does
    img = nib.Nifti1Image(np.zeros((4, 5, 6), np.float32), A)
    img.set_sform(A, code=1)
    img.header.set_xyzt_units("mm")
    nib.save(img, tmp_path / "s.nii.gz")
    with caplog.at_level(logging.WARNING, logger="imaging.io"):
        v = read_volume(tmp_path / "s.nii.gz")
    np.testing.assert_allclose(v.affine_lps_from_index[2, 2], 1.5)  # placed as written
    assert ("s.nii.gz: the voxel axes are sheared" in caplog.text) is warned, caplog.text


@pytest.mark.parametrize(
    ("spacing", "refused"), [("0.0005 0.0006 0.0007", True), ("0.1 0.1 2", False)]
)
def test_a_metaimage_in_metres_is_refused(tmp_path, spacing, refused):
    # review BM: a MetaImage stores no unit; one in metres failed later, in the marker
    # detection, without a word of units. 0.1 mm voxels (the finest MR) still read
    path = tmp_path / "m.mha"
    tail = _MHA_TAIL.replace("0.5 0.6 0.7", spacing)
    geometry = "TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = 0.001 0.002 0.003\n"
    path.write_bytes(
        (_MHA + geometry + tail + "ElementDataFile = LOCAL\n").encode() + _DATA.tobytes()
    )
    if not refused:
        np.testing.assert_allclose(read_volume(path).spacing_mm, [0.1, 0.1, 2.0])
        return
    with pytest.raises(
        VolumeReadError, match=r"m.mha: voxel edges of 0.0005, 0.0006, 0.0007 mm.*metres\?"
    ):
        read_volume(path)


@pytest.mark.parametrize(
    ("matrix", "field", "warned"),
    [
        ("1 0 0 0 1 0 0 0 1", "RAI", False),  # the identity in LPS, as ITK writes it
        ("0 1 0 1 0 0 0 0 -1", "ARS", False),  # axes permuted, z flipped: still agreed
        ("1 0 0 0 1 0 0 0 1", "LPI", True),  # a writer that meant RAS: x and y flipped
    ],
)
def test_metaimage_orientation_that_disagrees_is_said(tmp_path, caplog, matrix, field, warned):
    # review AE: ITK ignores AnatomicalOrientation, so a RAS-space file from another
    # writer was read with x and y flipped without a word
    path = tmp_path / "o.mha"
    geometry = f"TransformMatrix = {matrix}\nOffset = 1 2 3\nAnatomicalOrientation = {field}\n"
    path.write_bytes(
        (_MHA + geometry + _MHA_TAIL + "ElementDataFile = LOCAL\n").encode() + _DATA.tobytes()
    )
    with caplog.at_level(logging.WARNING, logger="imaging.io"):
        read_volume(path)
    assert (f"AnatomicalOrientation {field}, but" in caplog.text) is warned, caplog.text
