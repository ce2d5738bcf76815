"""The phantom frame of posture angles, recovered from the scans' gravity."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.fitting import fit
from calib.fitting.result import phantom_frame
from fem.postures import gravity_for_angle

# a hidden frame: R_ref_from_phantom, an arbitrary rotation of the reference scan's frame
R_TRUE = Rotation.from_euler("xyz", [20.0, -35.0, 70.0], degrees=True).as_matrix()


def _scan(angle_deg, plane="transverse", *, nominal=True, name="s"):
    """A scan at a posture angle of the hidden frame (its plate normal is the frame's -z)."""
    return SimpleNamespace(
        name=name,
        gravity_ref=R_TRUE @ gravity_for_angle(angle_deg, plane=plane),
        back_normal=-R_TRUE[:, 2],
        posture_plane=plane,
        posture_angle_deg=angle_deg if nominal else None,
    )


LATERAL = [(a, "transverse") for a in (0.0, 25.0, 180.0, -60.0, 155.0)]


@pytest.mark.parametrize(
    ("angle_deg", "plane"), [*LATERAL, (40.0, "sagittal"), (200.0, "sagittal")]
)
def test_the_frame_is_recovered_from_the_reference_at_any_lateral_angle(angle_deg, plane):
    # closed form: the gravity's part in the plate's plane is cos(a) times the frame's x
    # (sagittal: y); before, a reference at 180 degrees flipped x and y (every angle off
    # by 180 degrees). Tolerance: round-off of a few unit-vector products.
    R = phantom_frame(_scan(angle_deg, plane))
    np.testing.assert_allclose(R, R_TRUE, atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_without_a_nominal_angle_the_reference_is_at_zero():
    # sessions without posture angles: the reference's gravity is the frame's x, as before
    np.testing.assert_allclose(phantom_frame(_scan(0.0, nominal=False)), R_TRUE, atol=1e-12)
    flipped = phantom_frame(_scan(180.0, nominal=False))
    np.testing.assert_allclose(flipped[:, 0], -R_TRUE[:, 0], atol=1e-12)


def test_a_prone_reference_takes_its_axes_from_a_lateral_scan():
    prone = _scan(90.0, name="prone")
    with pytest.raises(ValueError, match="'prone'.*within 10 degrees of the back plate"):
        phantom_frame(prone)
    # 85 degrees: its in-plane part (sin 5 degrees) is the registration's gravity error
    others = [_scan(85.0, name="tilt_85"), _scan(230.0, name="tilt_230")]
    np.testing.assert_allclose(phantom_frame(prone, others), R_TRUE, atol=1e-12)


def test_the_fit_refuses_undefined_axes_before_any_fe_work():
    # it raised in calibration.json's writer, after the whole fit
    prone = _scan(90.0, name="prone")
    ms = SimpleNamespace(
        reference=prone, scans={"prone": prone, "sup": _scan(-88.0)}, density_kg_m3=1000.0
    )
    with pytest.raises(ValueError, match="add a scan in a lateral posture"):
        fit(ms)


def test_ingest_checks_postures_in_two_planes_by_their_directions():
    # a session of transverse 0 / 180 and sagittal 30 / 60 degree scans: before, the
    # registration compared |a_i - a_j| and stopped ingest (sagittal 30 is 90 degrees from
    # transverse 0, not 30). Exact markers: the check's own 2 / 10 degree bars are far off.
    from calib.data.ingest import _register
    from calib.data.session import ScanEntry, Session
    from fem.postures import rotation_between

    g_scanner = np.array([0.0, 1.0, 0.0])
    postures = {"left": (0.0, "transverse"), "right": (180.0, "transverse"),
                "s30": (30.0, "sagittal"), "s60": (60.0, "sagittal")}  # fmt: skip
    markers_ref = np.array([[0.0, 0, 0], [80, 0, 0], [0, 60, 0], [30, 20, 5]])
    up = np.array([0.0, 0.0, 1.0])  # the plate's normal into the body, reference frame
    scans = {}
    for name, (a, plane) in postures.items():
        g_ref = R_TRUE @ gravity_for_angle(a, plane=plane)  # gravity, reference frame
        g_ref0 = R_TRUE @ gravity_for_angle(0.0)
        # the reference is scanned with its gravity along the scanner's; each scan's
        # rotation into the reference frame takes the scanner gravity to its own
        R_ref_from_scan = rotation_between(g_scanner, rotation_between(g_ref0, g_scanner) @ g_ref)
        scans[name] = SimpleNamespace(fiducials_lps_mm=markers_ref @ R_ref_from_scan,
                                      nipple_lps_mm=None, tumour_lps_mm=None,
                                      back_plane=SimpleNamespace(normal=up @ R_ref_from_scan),
                                      surface=SimpleNamespace(back_plate=None))  # fmt: skip
    entries = tuple(
        ScanEntry(n, Path(n), "reference" if n == "left" else "calibration", plane, a)
        for n, (a, plane) in postures.items()
    )
    session = Session(Path("."), g_scanner, 1000.0, 4, None, entries)
    regs = _register(session, scans, landmarks=False)
    assert set(regs) == set(postures)
    g = {n: r.gravity_ref for n, r in regs.items()}
    # round-off of the rotations: 1e-9
    assert np.degrees(np.arccos(g["left"] @ g["s30"])) == pytest.approx(90.0, abs=1e-9)
    assert np.degrees(np.arccos(g["s30"] @ g["s60"])) == pytest.approx(30.0, abs=1e-9)


@pytest.mark.parametrize(
    ("angle_deg", "plane", "nominal", "figures"),
    [
        (30.0, "sagittal", True, None),  # was reported as 90 degrees (transverse only)
        (60.0, "sagittal", False, None),  # no posture given: the plane from the gravity
        (29.99, "transverse", True, None),  # was given the dissertation's 25 (within 5)
        (25.4, "transverse", True, 25.0),
        (50.3, "transverse", False, 50.0),  # no posture given: the measured angle
        (25.0, "sagittal", True, None),  # the dissertation's tilts are transverse
    ],
)
def test_validation_reports_the_angle_in_the_scans_plane(angle_deg, plane, nominal, figures):
    from calib.validation import _posture, _reference_figures

    work = SimpleNamespace(record={"model": {"R_ref_from_phantom": R_TRUE.tolist()}})
    scan = _scan(angle_deg, plane, nominal=nominal)
    scan = SimpleNamespace(**vars(scan), role="validation")
    if not nominal:
        scan.posture_plane = None
    if nominal and angle_deg == 29.99:
        scan.posture_angle_deg = 30.0  # the session's nominal, registered 0.01 off
    measured, plane_of = _posture(work, scan)
    assert plane_of == plane
    assert measured == pytest.approx(angle_deg, abs=1e-9)  # exact geometry: round-off
    ref = _reference_figures(scan, measured, plane_of, tumour=True)
    assert (ref and ref["posture_angle_deg"]) == figures


# ---- PatientPosition: DICOM's patient coordinates turn with it ---------------------------


def test_patient_positions_that_differ_are_said(tmp_path, caplog):
    import pydicom

    from calib.data.ingest import _check_patient_positions
    from calib.data.session import ScanEntry, Session
    from imaging import Volume, affine_from_geometry, write_dicom_series
    from imaging.dicom import patient_position

    A = affine_from_geometry([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], np.eye(3))
    oblique = Volume(np.ones((4, 4, 3), np.uint16), A, "tiny")

    def _rewrite(folder, change):
        for f in sorted(folder.glob("IM*.dcm")):
            ds = pydicom.dcmread(f)
            change(0, ds)
            ds.save_as(f, enforce_file_format=True)

    folders = {}
    for name, position in (("left", "HFS"), ("right", "HFS"), ("tilt", None)):
        folders[name] = tmp_path / name
        write_dicom_series(oblique, folders[name], seed=4)
        if position is not None:
            _rewrite(folders[name], lambda k, ds, p=position: setattr(ds, "PatientPosition", p))
    assert patient_position(folders["left"]) == "HFS"
    assert patient_position(folders["tilt"]) is None  # the house writer does not say
    entries = tuple(ScanEntry(n, f, "calibration") for n, f in folders.items())
    session = Session(tmp_path, np.array([0.0, 1.0, 0.0]), 1000.0, 3, None, entries)
    with caplog.at_level("WARNING", logger="calib.data.ingest"):
        _check_patient_positions(session)  # the same position, or none written: silent
    assert caplog.text == ""
    _rewrite(folders["right"], lambda k, ds: setattr(ds, "PatientPosition", "HFP"))
    with caplog.at_level("WARNING", logger="calib.data.ingest"):
        _check_patient_positions(session)
    assert "different patient positions (left: HFS, right: HFP, tilt: none)" in caplog.text
