import json
import warnings

import numpy as np
import pytest
from conftest import MARKERS_MM, random_rigid, rigid
from scipy.spatial.transform import Rotation

from registration import (
    MarkerCountError,
    PostureMismatchError,
    PostureMismatchWarning,
    RegistrationError,
    angle_between_deg,
    apply_transform,
    check_posture,
    format_registration_table,
    gravity_in_reference,
    register_scans,
)

G_SCANNER = np.array([0.0, 1.0, 0.0])
SIGMA = 0.2 / np.sqrt(3.0)  # 0.2 mm 3D RMS marker localisation noise, per axis


def _scan_set(rng, T_scan_from_ref_by_scan):
    """Noisy markers per scan given each scan's true pose relative to the reference scan."""
    return {
        name: apply_transform(T, MARKERS_MM) + rng.normal(0.0, SIGMA, (3, 3))
        for name, T in T_scan_from_ref_by_scan.items()
    }


def test_gravity_in_reference_closed_form():
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    g = gravity_in_reference(rigid(R, [5.0, 6, 7]), 2.0 * G_SCANNER)
    np.testing.assert_allclose(g, [-0.5, np.sqrt(3) / 2, 0.0], atol=1e-15)  # round-off
    assert angle_between_deg([1, 0, 0], [0, 3, 0]) == pytest.approx(90.0, abs=1e-12)
    # atan2 form stays accurate for tiny angles where acos(dot) would lose all digits
    assert angle_between_deg([1, 0, 0], [1, 1e-9, 0]) == pytest.approx(np.degrees(1e-9), rel=1e-6)
    with pytest.raises(RegistrationError, match="zero vector"):
        gravity_in_reference(np.eye(4), [0.0, 0, 0])


def test_gravity_recovered_per_scan_on_random_poses():
    rng = np.random.default_rng(2024)
    worst = 0.0
    for _ in range(50):
        poses = {"ref": np.eye(4)} | {f"s{i}": random_rigid(rng) for i in range(4)}
        regs = register_scans(_scan_set(rng, poses), reference="ref")
        for name, T in poses.items():
            truth = np.linalg.inv(T)[:3, :3] @ G_SCANNER  # R_ref_from_scan @ g_scanner
            worst = max(worst, angle_between_deg(regs[name].gravity_ref, truth))
            assert np.linalg.norm(regs[name].gravity_ref) == pytest.approx(1.0, abs=1e-12)
    # Noise on both marker sets: rotation error ~0.1 deg RMS per axis (see the rigid test),
    # so 0.5 deg is > 4 sigma for each of the 200 scans.
    assert worst < 0.5, f"worst gravity error {worst:.3f} deg"


def _transverse_poses(rng, angles_deg):
    """Phantom rolled about the scanner's S axis (LPS z) by each nominal angle, plus shifts."""
    poses = {}
    for name, a in angles_deg.items():
        R = Rotation.from_euler("z", a, degrees=True).as_matrix()
        poses[name] = rigid(R, rng.uniform(-30, 30, 3))
    return poses


def test_posture_cross_check_passes_warns_and_fails():
    rng = np.random.default_rng(8)
    angles = {"ref": 0.0, "left": 25.0, "right": -30.0, "prone": 45.0}
    markers = _scan_set(rng, _transverse_poses(rng, angles))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consistent postures: no warning at all
        regs = register_scans(markers, reference="ref", nominal_angles_deg=angles)
    assert set(regs) == set(angles)
    # measured 25 deg against nominal 30: 5 deg off (> 2 deg warning, < 10 deg error)
    off5 = angles | {"left": 30.0}
    with pytest.warns(PostureMismatchWarning, match="left"):
        register_scans(markers, reference="ref", nominal_angles_deg=off5)
    off15 = angles | {"left": 40.0}
    with pytest.raises(PostureMismatchError, match="left"):
        register_scans(markers, reference="ref", nominal_angles_deg=off15)
    # thresholds are configurable
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        register_scans(markers, reference="ref", nominal_angles_deg=off5, posture_warn_deg=6.0)
    with pytest.raises(PostureMismatchError):
        register_scans(markers, reference="ref", nominal_angles_deg=off5, posture_error_deg=4.0)


def test_check_posture_wraps_angles():
    g = {
        "a": np.array([np.sin(np.radians(170)), np.cos(np.radians(170)), 0.0]),
        "b": np.array([np.sin(np.radians(-170)), np.cos(np.radians(-170)), 0.0]),
    }
    (check,) = check_posture(g, {"a": 170.0, "b": -170.0})
    # 170 and -170 deg are 20 deg apart, not 340; exact geometry, so round-off tolerance
    assert check.nominal_deg == pytest.approx(20.0, abs=1e-9)
    assert check.discrepancy_deg == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(RegistrationError, match="unknown scans"):
        check_posture(g, {"c": 0.0})


def test_session_outputs_json_and_table():
    rng = np.random.default_rng(4)
    poses = {"ref": np.eye(4), "a": random_rigid(rng), "b": random_rigid(rng)}
    markers = _scan_set(rng, poses)
    markers["b"] = markers["b"][[2, 0, 1]]  # detection order is arbitrary
    nipple_ref = np.array([0.0, 0.0, 76.0])
    landmarks = {
        s: {"nipple": apply_transform(T, nipple_ref)} for s, T in poses.items() if s != "b"
    }
    landmarks["a"]["tumour"] = apply_transform(poses["a"], [10.0, -5.0, 40.0])
    regs = register_scans(markers, reference="ref", landmarks_by_scan=landmarks)
    ref, a, b = regs["ref"], regs["a"], regs["b"]
    np.testing.assert_array_equal(ref.T_ref_from_scan, np.eye(4))
    assert ref.fre_mm == 0.0 and ref.tre_nipple_mm == 0.0
    assert b.permutation == (2, 0, 1)
    # the registered nipple lands on the reference nipple within the noise (4 sigma of a TRE
    # of ~0.2 mm); the tumour is closer to the markers, so its expected TRE is smaller
    mapped = apply_transform(a.T_ref_from_scan, landmarks["a"]["nipple"])
    assert np.linalg.norm(mapped - nipple_ref) < 1.0
    assert 0.0 < a.tre_tumour_mm < a.tre_nipple_mm
    assert b.tre_nipple_mm is None and b.tre_tumour_mm is None
    doc = json.loads(json.dumps(b.to_json()))
    for key in ("T_ref_from_scan", "fre_mm", "tre_nipple_mm", "tre_tumour_mm", "gravity_ref"):
        assert key in doc
    assert np.asarray(doc["T_ref_from_scan"]).shape == (4, 4)
    assert doc["tre_nipple_mm"] is None
    table = format_registration_table(regs)
    lines = table.splitlines()
    assert len(lines) == 2 + len(regs)
    assert lines[2].startswith("ref") and "reference" in lines[2]
    assert f"{a.fre_mm:.3f}" in table
    # review AI: the role column was blank for every scan but the reference
    named = format_registration_table(regs, roles={"a": "validation"}).splitlines()
    assert "validation" in next(line for line in named[2:] if line.startswith("a "))
    assert "reference" in named[2]


def test_session_errors():
    rng = np.random.default_rng(1)
    markers = _scan_set(rng, {"ref": np.eye(4), "a": random_rigid(rng)})
    with pytest.raises(RegistrationError, match="reference scan 'nope'"):
        register_scans(markers, reference="nope")
    with pytest.raises(MarkerCountError, match="scan 'a'"):
        register_scans(markers | {"a": markers["a"][:2]}, reference="ref")
    with pytest.raises(RegistrationError, match="gravity_scanner"):
        register_scans(markers, reference="ref", gravity_scanner={"ref": G_SCANNER})
    per_scan = register_scans(
        markers, reference="ref", gravity_scanner={"ref": G_SCANNER, "a": -G_SCANNER}
    )
    assert angle_between_deg(
        per_scan["a"].gravity_ref, -register_scans(markers, reference="ref")["a"].gravity_ref
    ) == pytest.approx(0.0, abs=1e-9)


def test_postures_in_two_planes_are_checked_by_their_nominal_directions():
    # transverse 0 deg (1, 0, 0) and sagittal 50 deg (0, cos 50, sin 50) are 90 deg apart,
    # not 50: the angle between the nominal directions is what the registration must show
    t = np.radians(50.0)
    nominal = {"left": np.array([1.0, 0.0, 0.0]), "tilt": np.array([0.0, np.cos(t), np.sin(t)])}
    rotate = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()  # any common frame
    g = {k: rotate @ v for k, v in nominal.items()}
    (check,) = check_posture(g, nominal_gravity=nominal)
    # exact geometry: round-off tolerance
    assert check.nominal_deg == pytest.approx(90.0, abs=1e-9)
    assert check.status == "ok"
    with pytest.raises(PostureMismatchError, match="nominal 50.00 deg"):
        check_posture(g, {"left": 0.0, "tilt": 50.0})  # read as one plane
    u = np.radians(10.0)  # the left scan at transverse 10 deg: 82.4 deg from the tilt
    g["left"] = rotate @ np.array([np.cos(u), 0.0, np.sin(u)])
    with pytest.raises(PostureMismatchError, match="tilt.*nominal 90.00 deg"):
        check_posture(g, nominal_gravity=nominal, error_deg=5.0)
    with pytest.raises(RegistrationError, match="either nominal_angles_deg or nominal_gravity"):
        check_posture(g, {"left": 0.0}, nominal_gravity=nominal)
