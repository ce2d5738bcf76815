"""Readers and writers: round trips, determinism and bad-input errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
from scipy.spatial.transform import Rotation

from imaging import (
    DicomSeriesError,
    Volume,
    VolumeReadError,
    affine_from_geometry,
    read_volume,
    write_dicom_series,
    write_nifti,
    write_volume,
)

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "breast-mri-lesion"


@pytest.fixture(scope="module")
def small_volume() -> Volume:
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    A = affine_from_geometry([1.0, -2.0, 3.0], [0.8, 0.9, 1.5], R)
    arr = np.random.default_rng(0).uniform(0, 1000, (24, 20, 8)).astype(np.float32)
    return Volume(arr, A, "small")


def test_index_lps_round_trip(small_volume):
    ijk = np.array([[0, 0, 0], [1.5, 2.25, 3.0], [23, 19, 7]])
    p = small_volume.index_to_lps(ijk)
    np.testing.assert_allclose(p[0], [1.0, -2.0, 3.0])
    np.testing.assert_allclose(small_volume.lps_to_index(p), ijk, atol=1e-12)
    np.testing.assert_allclose(small_volume.spacing_mm, [0.8, 0.9, 1.5])
    # both ways take any (..., 3) (review BJ: lps_to_index took (3,) and (N, 3) only);
    # the tolerance: round-off of a 3x3 inverse on indices of order 10
    grid = np.stack(np.meshgrid([0.0, 2.5], [1.0, 4.0, 7.5], [3.0], indexing="ij"), -1)
    back = small_volume.lps_to_index(small_volume.index_to_lps(grid))
    assert back.shape == grid.shape == (2, 3, 1, 3)
    np.testing.assert_allclose(back, grid, atol=1e-12)
    np.testing.assert_allclose(small_volume.lps_to_index(p[1]), ijk[1], atol=1e-12)


def test_dicom_round_trip_and_determinism(small_volume, tmp_path):
    files = write_dicom_series(small_volume, tmp_path / "a", seed=7)
    again = write_dicom_series(small_volume, tmp_path / "b", seed=7)
    other = write_dicom_series(small_volume, tmp_path / "c", seed=8)
    assert [f.read_bytes() for f in files] == [f.read_bytes() for f in again]
    assert files[0].read_bytes() != other[0].read_bytes()
    v = read_volume(tmp_path / "a")
    # uint16 quantisation: step = range / 65000 ~ 0.015, so error <= half a step.
    assert np.abs(v.array - small_volume.array).max() <= 0.5 * 1000 / 65000 + 1e-3
    # Positions are written with 6 decimals, cosines with 8: round-off <= 1e-5 mm.
    np.testing.assert_allclose(
        v.affine_lps_from_index, small_volume.affine_lps_from_index, atol=1e-5
    )
    ds = pydicom.dcmread(files[0])
    assert ds.Modality == "MR" and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.4"


def test_dicom_monochrome1(small_volume, tmp_path):
    write_dicom_series(small_volume, tmp_path / "m1", photometric="MONOCHROME1")
    v = read_volume(tmp_path / "m1")
    assert np.abs(v.array - small_volume.array).max() <= 0.5 * 1000 / 65000 + 1e-3


def test_dicom_agrees_with_simpleitk(small_volume, tmp_path):
    import SimpleITK as sitk

    write_dicom_series(small_volume, tmp_path / "s")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    ref = Volume.from_sitk(reader.Execute())
    ours = read_volume(tmp_path / "s")
    np.testing.assert_allclose(ours.array, ref.array, atol=1e-3)
    np.testing.assert_allclose(ours.affine_lps_from_index, ref.affine_lps_from_index, atol=1e-6)


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".nrrd", ".mha"])
def test_file_round_trip(small_volume, tmp_path, suffix):
    path = write_volume(small_volume, tmp_path / f"v{suffix}")
    v = read_volume(path)
    np.testing.assert_array_equal(v.array, small_volume.array)
    # NIfTI stores the affine in float32: relative round-off ~1e-7 of ~50 mm.
    np.testing.assert_allclose(
        v.affine_lps_from_index, small_volume.affine_lps_from_index, atol=1e-4
    )
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_nifti_is_ras_on_disk(tmp_path):
    import nibabel as nib

    v = Volume(
        np.zeros((2, 2, 2), np.float32),
        affine_from_geometry([10.0, 20.0, 30.0], [1, 1, 1], np.eye(3)),
    )
    img = nib.load(write_nifti(v, tmp_path / "x.nii.gz"))
    # LPS (10, 20, 30) is RAS (-10, -20, 30); the LPS +i axis is RAS -x.
    np.testing.assert_allclose(img.affine[:3, 3], [-10.0, -20.0, 30.0], atol=1e-5)
    np.testing.assert_allclose(img.affine[:3, 0], [-1.0, 0.0, 0.0])


@pytest.mark.skipif(not DATA.is_dir(), reason="shared data absent")
def test_real_nrrd_geometry():
    v = read_volume(DATA / "breast1_image.nrrd")
    assert v.shape == (45, 120, 21)
    # Values from the NRRD header (space LPS, origin and space directions).
    np.testing.assert_allclose(v.spacing_mm, [0.664062, 0.664062, 2.1], atol=1e-6)
    np.testing.assert_allclose(v.origin_lps_mm, [-116.54304, -48.144654, 9.45], atol=1e-5)


# ---- bad input ----------------------------------------------------------------------


@pytest.fixture
def series(small_volume, tmp_path) -> Path:
    write_dicom_series(small_volume, tmp_path / "series", seed=1)
    return tmp_path / "series"


def test_truncated_file(series):
    f = series / "IM00004.dcm"
    f.write_bytes(f.read_bytes()[:-300])
    with pytest.raises(DicomSeriesError, match="IM00004.dcm.*pixel data"):
        read_volume(series)


@pytest.mark.parametrize("name", ["IM00001.dcm", "IM00004.dcm"])
def test_a_slice_cut_before_its_pixel_data_is_an_error(series, name):
    # read with force, a file cut before (7FE0,0010) is a dataset without pixel data: it
    # was skipped as a report, and a first or last slice went missing without a word
    f = series / name
    data = f.read_bytes()
    f.write_bytes(data[: data.rfind(b"\xe0\x7f\x10\x00")])
    with pytest.raises(DicomSeriesError, match=f"{name}: an MR image slice without pixel data"):
        read_volume(series)


def test_corrupt_file(series):
    (series / "IM00002.dcm").write_bytes(b"not a dicom file at all" * 10)
    with pytest.raises(DicomSeriesError, match="IM00002.dcm.*not a readable DICOM"):
        read_volume(series)


def test_mixed_series(series, small_volume, tmp_path):
    other = write_dicom_series(small_volume, tmp_path / "other", seed=2, series_number=5)
    shutil.copy(other[0], series / "extra.dcm")
    with pytest.raises(DicomSeriesError, match=r"holds 2 DICOM series(.|\n)*8 files(.|\n)*1 files"):
        read_volume(series)


def test_missing_slice(series):
    (series / "IM00005.dcm").unlink()
    with pytest.raises(DicomSeriesError, match="1 missing slice.*IM00004.dcm and IM00006.dcm"):
        read_volume(series)


def test_non_mr_modality(small_volume, tmp_path):
    write_dicom_series(small_volume, tmp_path / "ct", modality="CT")
    with pytest.raises(DicomSeriesError, match="IM00001.dcm: Modality is 'CT', expected 'MR'"):
        read_volume(tmp_path / "ct")


def test_inconsistent_orientation(series):
    f = series / "IM00003.dcm"
    ds = pydicom.dcmread(f)
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.save_as(f)
    with pytest.raises(DicomSeriesError, match="IM00003.dcm: ImageOrientationPatient"):
        read_volume(series)


def test_empty_folder_and_missing_path(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DicomSeriesError, match="empty: folder holds no DICOM files"):
        read_volume(tmp_path / "empty")
    with pytest.raises(VolumeReadError, match="nope.nii.gz: no such file"):
        read_volume(tmp_path / "nope.nii.gz")


def test_corrupt_nifti(small_volume, tmp_path):
    p = write_nifti(small_volume, tmp_path / "v.nii.gz")
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(VolumeReadError, match="v.nii.gz: cannot read NIfTI"):
        read_volume(p)


def _renifti(path, **change):
    """The NIfTI at ``path`` saved again with header fields changed (sform/qform codes, units)."""
    import nibabel as nib

    img = nib.load(path)
    img = nib.Nifti1Image(np.asanyarray(img.dataobj), None, img.header)
    for key, value in change.items():
        if key == "units":
            img.header.set_xyzt_units(value)
        else:
            img.header[key] = value
    out = path.with_name(f"changed_{len(list(path.parent.iterdir()))}.nii.gz")
    nib.save(img, out)
    return out


def test_a_nifti_without_scanner_placement_or_in_other_units_is_refused(small_volume, tmp_path):
    # without sform and qform nibabel places voxels by their sizes alone (gravity would land
    # in an arbitrary frame); metres would scale every length by 1000
    p = write_nifti(small_volume, tmp_path / "v.nii.gz")
    np.testing.assert_allclose(
        read_volume(p).affine_lps_from_index, small_volume.affine_lps_from_index, atol=1e-4
    )
    with pytest.raises(VolumeReadError, match=r"changed_\d.nii.gz: .*neither an sform nor a qform"):
        read_volume(_renifti(p, sform_code=0, qform_code=0))
    with pytest.raises(VolumeReadError, match="spatial unit is 'meter'"):
        read_volume(_renifti(p, units="meter"))
    # only one of the two, or units left unknown (as converters write them): read as before
    for change in ({"sform_code": 0}, {"qform_code": 0}, {"units": "unknown"}):
        v = read_volume(_renifti(p, **change))
        np.testing.assert_allclose(
            v.affine_lps_from_index, small_volume.affine_lps_from_index, atol=1e-4
        )


def test_a_nifti_s_scanner_form_is_read_and_another_space_said(small_volume, tmp_path, caplog):
    # review AE: an sform of code 2-4 (aligned, Talairach, MNI) was read as the scanner's
    # frame, where scanner.gravity is given, even beside a qform of code 1
    import logging

    import nibabel as nib

    p = write_nifti(small_volume, tmp_path / "v.nii.gz")
    img = nib.load(p)
    moved = img.header.get_sform()
    moved[:3, 3] += [40.0, 0.0, 0.0]  # an aligned space 40 mm off the scanner's
    other = nib.Nifti1Image(np.asanyarray(img.dataobj), None, img.header)
    other.header.set_sform(moved, code=2)
    nib.save(other, tmp_path / "aligned.nii.gz")
    with caplog.at_level(logging.WARNING, logger="imaging.io"):
        v = read_volume(tmp_path / "aligned.nii.gz")  # the qform, code 1: the scanner's
    np.testing.assert_allclose(
        v.affine_lps_from_index, small_volume.affine_lps_from_index, atol=1e-4
    )
    assert "the qform is used" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="imaging.io"):
        read_volume(_renifti(tmp_path / "aligned.nii.gz", qform_code=0))
    assert "space code 2, not the scanner's (1)" in caplog.text


def test_writer_refuses_to_overwrite(series, small_volume):
    with pytest.raises(FileExistsError):
        write_dicom_series(small_volume, series)
