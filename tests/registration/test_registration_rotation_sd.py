"""The rotation uncertainty fiducials leave, and a warning where it is large.

Three markers nearly on one 100 mm line passed the collinearity check (an absolute 1 mm
offset) and tilted the registered gravity by 5-16 degrees with 0.3 mm of localisation
error, silently (audit G, item 2). ``RigidFit.rotation_sd_deg`` is the rotation part of
Fitzpatrick's TRE: with isotropic per-axis noise ``s`` on the target markers only (3D
FLE ``s sqrt 3``) the rotation about the weakest axis has sd ``s / (f sqrt N)`` rad, ``f``
the markers' RMS distance from it (least squares of N tangential displacements). 4000
seeded fits: the sd's relative sampling error is 1.1 %, so the bar is 6 %.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration import fit_rigid, register_scans

LINE = np.array([[-50.0, 0.0, 0.0], [10.0, 3.0, 0.0], [50.0, -2.0, 1.5]])  # offsets ~2 mm


def test_the_rotation_sd_matches_simulated_fits():
    rng = np.random.default_rng(3)
    s = 0.3
    angles = []
    for _ in range(4000):
        fit = fit_rigid(LINE, LINE + rng.normal(0.0, s, LINE.shape))
        angles.append(Rotation.from_matrix(fit.rotation).as_rotvec())
    angles = np.asarray(angles)
    axis = np.linalg.svd(LINE - LINE.mean(0))[2][0]  # the line: the weakest axis
    measured = np.degrees(np.std(angles @ axis))
    predicted = fit.rotation_sd_deg(fle_mm=s * np.sqrt(3.0))
    assert predicted > 4.0  # degrees: a real hazard
    assert measured == pytest.approx(predicted, rel=0.06)


def test_nearly_collinear_fiducials_are_warned_about(caplog):
    rng = np.random.default_rng(0)
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    scan = (LINE + rng.normal(0.0, 0.3, LINE.shape)) @ R.T
    with caplog.at_level(logging.WARNING, logger="registration.session"):
        regs = register_scans({"ref": LINE, "turned": scan}, reference="ref")
    assert regs["turned"].rotation_sd_deg > 1.0  # ROTATION_SD_WARN_DEG
    assert "scan 'turned': the fiducials leave the registration's rotation" in caplog.text
    assert regs["turned"].to_json()["rotation_sd_deg"] == regs["turned"].rotation_sd_deg


def test_well_spread_fiducials_stay_silent(caplog):
    square = np.array([[0, 0, 0], [60, 5, 0], [55, 70, 3], [-5, 65, 40]], float)
    rng = np.random.default_rng(1)
    with caplog.at_level(logging.WARNING, logger="registration.session"):
        regs = register_scans(
            {"ref": square, "s": square + rng.normal(0.0, 0.2, square.shape)}, reference="ref"
        )
    # about FLE / (sqrt(N) x the markers' rms radius) = 0.2 / (2 x 47.5 mm) = 0.12 degrees
    # (measured 0.105): 0.5 is four times that and half the warning's 1 degree
    assert regs["s"].rotation_sd_deg < 0.5 and "weakest axis" not in caplog.text
