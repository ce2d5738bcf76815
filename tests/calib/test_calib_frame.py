"""The phantom frame of posture angles, recovered from the scans' gravity."""

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
    ms = SimpleNamespace(reference=prone, scans={"prone": prone, "sup": _scan(-88.0)})
    with pytest.raises(ValueError, match="add a scan in a lateral posture"):
        fit(ms)
