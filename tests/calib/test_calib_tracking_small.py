"""Tracking with one or two inclusions says that it cannot weigh a missed tumour.

With fewer than two matches beside the nipple no deformation field can be fitted, so a
match is rated by size and the initial maps alone: a single-inclusion phantom whose tumour
is missed in a scan tracked any other blob as the tumour with confidence ~1 and no word
(audit G, item 1: a 9.8 mm blob 45 mm away, confidence 0.999999). The match now carries
``field_checked`` (False there) and ingest warns about a tumour matched that way. Three
matched inclusions admit the field for the assignment and for each rival that drops one.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from calib.data.ingest import TumourChoice, _track_inclusions
from registration import AmbiguousMatchWarning, match_constellation

NIPPLE = np.array([0.0, 0.0, 60.0])


def _scan(centres, diameters, nipple=NIPPLE):
    return SimpleNamespace(
        inclusions=SimpleNamespace(
            centres_lps_mm=np.asarray(centres, float).reshape(-1, 3),
            diameters_mm=np.asarray(diameters, float),
        ),
        nipple_lps_mm=np.asarray(nipple, float),
        back_plane=SimpleNamespace(point_lps_mm=np.zeros(3), normal=np.array([0.0, 0.0, 1.0])),
        voxel_size_mm=np.full(3, 1.5),
    )


def _track(X, dX, Y, dY):
    scans = {"ref": _scan(X, dX), "s": _scan(Y, dY)}
    regs = {n: SimpleNamespace(T_ref_from_scan=np.eye(4)) for n in scans}
    session = SimpleNamespace(reference=SimpleNamespace(name="ref"), tumour_hint_lps_mm=None)
    return _track_inclusions(session, scans, regs, TumourChoice(0, "test"))["s"]


def test_one_inclusion_matched_to_another_blob_is_warned_about():
    with pytest.warns(AmbiguousMatchWarning, match="too few to fit a deformation field"):
        tr = _track([[0, 0, 30]], [10.0], [[45, 0, 20]], [9.8])
    assert tr.tumour_index == 0 and not tr.field_checked
    assert tr.to_json()["field_checked"] is False


def test_three_inclusions_are_checked_by_the_field_and_stay_silent():
    X = [[0, 0, 30], [30, 0, 30], [-20, 25, 25]]
    Y = np.asarray(X, float) + [1.0, 0.0, -0.5]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr = _track(X, [8.0, 6.0, 5.0], Y, [8.0, 6.0, 5.0])
    assert tr.tumour_index == 0 and tr.field_checked and tr.tumour_confidence > 0.95


@pytest.mark.parametrize(("n", "checked"), [(1, False), (2, False), (3, True), (5, True)])
def test_field_checked_counts_the_matches(n, checked):
    rng = np.random.default_rng(n)
    X = rng.uniform(-30.0, 30.0, (n, 3))
    sizes = np.linspace(5.0, 10.0, n)
    m = match_constellation(
        X, sizes, X + 0.2, sizes, anchors_reference_mm=NIPPLE[None], anchors_mm=NIPPLE[None]
    )
    assert (m.reference_index >= 0).all() and m.field_checked is checked
