"""Tumour and inclusion tracking across postures (ingest), checked against twin truth.

The default twin is small (2 lateral postures, 14 mm phantom, 2 mm voxels) but soft
(c1 = 300 Pa): the inclusions move up to 61 mm between the two scans, 2-5 times their
spacing. With seed 1 the former proximity tracking picked an inclusion 32 mm from the
true tumour there, silently. The truth of every inclusion's deformed centre is captured
while the twin is built (the truth file records only the tumour's).
"""

from __future__ import annotations

import json
import tomllib
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tomli_w
from calib_helpers import SMALL_PRESET, make_scan_folder

import calib.twin.synth as synth
from calib.data.ingest import (
    TUMOUR_MIN_CONFIDENCE,
    TumourChoice,
    TumourNotFoundWarning,
    _track_inclusions,
)
from calib.data.session import load_session
from calib.model.effects import TruthEffects
from calib.twin import PRESETS, synthesize
from calib.workflows.ingest import run_ingest
from registration import AmbiguousMatchWarning

SOFT_SMALL = replace(SMALL_PRESET, c1_pa=300.0, effects=TruthEffects())


def _apply(T, p):
    T = np.asarray(T, float)
    return np.asarray(p, float) @ T[:3, :3].T + T[:3, 3]


def build_twin(out: Path, preset, seed: int) -> dict:
    """Synthesize a twin and return its truth with every inclusion's deformed centre.

    The centres (scan LPS mm, per scan) are the mean vertex of each deformed inclusion
    sphere that the twin renders (an icosphere: its mean vertex is the centre to O(r^2)
    of the field's curvature), captured by wrapping ``calib.twin.synth._deform``.
    """
    captured = []
    real = synth._deform

    def deform(*args, **kwargs):
        truth = real(*args, **kwargs)
        captured.append(np.array([v.mean(0) for v, _ in truth.inclusions]))
        return truth

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(synth, "_deform", deform)
        record = synthesize(out, preset=preset, seed=seed)
    record = json.loads(json.dumps(record))
    for scan, centres in zip(record["scans"].values(), captured, strict=True):
        scan["inclusions_lps_mm"] = _apply(scan["T_scanner_from_phantom"], centres)
    return record


def tracking_errors(truth: dict, work: Path) -> dict:
    """Per scan: tumour error (mm), wrong identities, lowest confidence, motion (mm)."""
    docs = {n: json.loads((work / "scans" / n / "ingest.json").read_text()) for n in truth["scans"]}
    (ref,) = [n for n, s in truth["scans"].items() if s["role"] == "reference"]

    def true_index(name):  # each detection's true inclusion: the nearest true centre
        found = np.array([inc["centre_lps_mm"] for inc in docs[name]["inclusions"]])
        d = np.linalg.norm(found[:, None] - truth["scans"][name]["inclusions_lps_mm"][None], axis=2)
        # detections are within 0.5 mm of their inclusion (issue 3); one 2 mm or more from
        # every true inclusion is spurious (-1; e.g. a 2 mm blob in one quick twin)
        return np.where(d.min(1) < 2.0, d.argmin(1), -1)

    ref_true = true_index(ref)
    T_ref = np.asarray(truth["scans"][ref]["T_scanner_from_phantom"])
    ref_phantom = _apply(np.linalg.inv(T_ref), truth["scans"][ref]["inclusions_lps_mm"])
    out = {}
    for name, doc in docs.items():
        t = truth["scans"][name]
        tumour = doc["tumour_lps_mm"]
        err = np.inf if tumour is None else np.linalg.norm(np.subtract(tumour, t["tumour_lps_mm"]))
        ids = [inc["reference_index"] for inc in doc["inclusions"]]
        wrong = [] if name == ref else _wrong_identities(ids, true_index(name), ref_true)
        T = np.asarray(t["T_scanner_from_phantom"])
        moved = _apply(np.linalg.inv(T), t["inclusions_lps_mm"]) - ref_phantom
        out[name] = {
            "tumour_error_mm": float(err),
            "wrong": wrong,
            "min_confidence": min(inc["match_confidence"] for inc in doc["inclusions"]),
            "tumour_confidence": doc["tracking"]["tumour_confidence"],
            "max_motion_mm": float(np.linalg.norm(moved, axis=1).max()),
            "tumour_motion_mm": float(np.linalg.norm(
                np.subtract(t["tumour_phantom_mm"], truth["scans"][ref]["tumour_phantom_mm"]))),
        }  # fmt: skip
    return out


def _wrong_identities(ids, true_k, ref_true) -> list[int]:
    """Detections whose identity contradicts the truth.

    Matched: right when the reference detection is the same true inclusion. Unmatched:
    right for a spurious detection or an inclusion the reference scan did not detect.
    """
    seen = set(ref_true[ref_true >= 0].tolist())
    return [
        k
        for k, (i, tk) in enumerate(zip(ids, true_k, strict=True))
        if (i is None and tk in seen) or (i is not None and (tk < 0 or ref_true[i] != tk))
    ]


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    base = tmp_path_factory.mktemp("tracking")
    truth = build_twin(base / "twin", SOFT_SMALL, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ambiguity warning on this twin
        result = run_ingest(base / "twin" / "scans", base / "work")
    return {"base": base, "truth": truth, "work": base / "work", "result": result}


def test_every_inclusion_keeps_its_identity_under_large_motion(twin):
    # Issue 18 bar: tracked tumour within 0.5 mm (the imaging bar of issue 3) in every
    # posture, every inclusion's identity right, each with confidence >= 0.95 (measured:
    # 1 - 1e-8). The motion is what defeats proximity: >= 40 mm here (61 mm measured).
    errors = tracking_errors(twin["truth"], twin["work"])
    assert max(e["max_motion_mm"] for e in errors.values()) >= 40.0, errors
    assert max(e["tumour_motion_mm"] for e in errors.values()) >= 30.0, errors
    for name, e in errors.items():
        assert e["tumour_error_mm"] <= 0.5, (name, e)
        assert e["wrong"] == [], (name, e)
        assert e["min_confidence"] >= TUMOUR_MIN_CONFIDENCE, (name, e)


def test_ingest_json_reports_identity_and_confidence(twin):
    truth, work = twin["truth"], twin["work"]
    keys = {"fiducials_lps_mm", "nipple_lps_mm", "tumour_lps_mm", "inclusions",
            "voxel_size_mm", "back_plane", "quality", "T_ref_from_scan", "fre_mm",
            "tre_nipple_mm", "tre_tumour_mm", "gravity_ref", "residuals_mm", "frames"}  # fmt: skip
    for name, scan in truth["scans"].items():
        doc = json.loads((work / "scans" / name / "ingest.json").read_text())
        assert keys <= set(doc), keys - set(doc)  # the former contract is unchanged
        tr = doc["tracking"]
        assert set(tr) >= {"tumour_index", "tumour_reference_index", "tumour_confidence",
                           "selection", "method", "match_confidence_definition"}  # fmt: skip
        incs = doc["inclusions"]
        assert all({"centre_lps_mm", "diameter_mm", "reference_index", "match_confidence"}
                   <= set(inc) for inc in incs)  # fmt: skip
        # the tracked tumour is the inclusion whose identity is the reference's tumour
        k = tr["tumour_index"]
        assert incs[k]["reference_index"] == tr["tumour_reference_index"]
        assert doc["tumour_lps_mm"] == incs[k]["centre_lps_mm"]
        assert "nearest to the [landmarks] tumour hint" in tr["selection"]
        if scan["role"] == "reference":
            assert [inc["reference_index"] for inc in incs] == list(range(len(incs)))
            assert {inc["match_confidence"] for inc in incs} == {1.0}
        assert 0.0 <= min(inc["match_confidence"] for inc in incs) <= 1.0


def test_summary_table_says_which_inclusion_and_why(twin):
    result = twin["result"]
    text = result.summary_table
    k = result.tumour_choice.reference_index
    assert (
        f"tracked tumour: reference inclusion {k}, nearest to the [landmarks] tumour hint" in text
    )
    for name in twin["truth"]["scans"]:
        assert any(line.startswith(name) and "1.000" in line for line in text.splitlines())


def test_without_a_hint_the_largest_is_tracked_and_said(twin, tmp_path):
    # The same scans with no [landmarks] table: the largest reference inclusion is tracked,
    # the reason says so, and the same true inclusion is tracked in the other scan.
    scans = twin["base"] / "twin" / "scans"
    doc = tomllib.loads((scans / "session.toml").read_text())
    doc.pop("landmarks")
    for s in doc["scans"]:
        s["path"] = str(scans / s["path"])
    (tmp_path / "session.toml").write_text(tomli_w.dumps(doc))
    result = run_ingest(tmp_path, tmp_path / "work")
    ref = load_session(tmp_path).reference.name
    diameters = result.scans[ref].inclusions.diameters_mm
    assert result.tumour_choice.reference_index == int(np.argmax(diameters))
    assert result.tumour_choice.reason.startswith(
        f"the largest inclusion ({diameters.max():.1f} mm; no [landmarks] tumour hint"
    )
    assert "the largest inclusion" in result.summary_table
    truth = twin["truth"]
    identity = set()
    for name, res in result.scans.items():
        tr = result.tracking[name]
        assert tr.reference_index[tr.tumour_index] == result.tumour_choice.reference_index
        # the tracked inclusion is one and the same true inclusion in every scan
        d = np.linalg.norm(truth["scans"][name]["inclusions_lps_mm"] - res.tumour_lps_mm, axis=1)
        assert d.min() <= 0.5
        identity.add(int(d.argmin()))
    assert len(identity) == 1, identity


# ------------------------------------------------------------------------------------
# ambiguous and missing matches, on stand-in scans (no twin needed)


def _scan(centres, diameters, nipple):
    return SimpleNamespace(
        inclusions=SimpleNamespace(
            centres_lps_mm=np.asarray(centres, float), diameters_mm=np.asarray(diameters, float)
        ),
        nipple_lps_mm=np.asarray(nipple, float),
        back_plane=SimpleNamespace(point_lps_mm=np.zeros(3), normal=np.array([0.0, 0.0, 1.0])),
        voxel_size_mm=np.full(3, 1.5),
    )


def _stand_in(pair_turned: bool, drop_tumour: bool = False):
    """A 16-inclusion constellation sheared by 30 mm; the tumour (0) has an equal twin (1)."""
    rng = np.random.default_rng(18)
    X = [[0.0, 0.0, 30.0], [8.0, 0.0, 30.0]]
    while len(X) < 16:
        p = rng.uniform([-50, -35, 8], [50, 35, 60])
        if np.linalg.norm(np.asarray(X) - p, axis=1).min() > 14:
            X.append(p)
    X = np.asarray(X)
    d = np.concatenate([[6.0, 6.0], np.linspace(3.0, 10.0, 14)])

    def shear(p):  # 30 mm at the nipple height (70 mm), growing with height
        p = np.atleast_2d(p)
        return p + np.outer(p[:, 2] / 70.0, [30.0, 5.0, -3.0])

    Y = shear(X)
    if pair_turned:  # the equal pair across the direction the shear carries it to
        mid, v = Y[:2].mean(0), Y[1] - Y[0]
        w = np.cross(v, [0.0, 0.0, 1.0])
        w *= np.linalg.norm(v) / 2 / np.linalg.norm(w)
        Y[0], Y[1] = mid + w, mid - w
    order = np.random.default_rng(1).permutation(16)
    Y, dY = Y[order], d[order]
    if drop_tumour:
        keep = order != 0
        Y, dY = Y[keep], dY[keep]
    nipple = np.array([0.0, 0.0, 70.0])
    scans = {"ref": _scan(X, d, nipple), "right": _scan(Y, dY, shear(nipple)[0])}
    regs = {n: SimpleNamespace(T_ref_from_scan=np.eye(4)) for n in scans}
    session = SimpleNamespace(reference=SimpleNamespace(name="ref"), tumour_hint_lps_mm=None)
    return session, scans, regs, order


def test_clear_constellation_is_tracked_silently():
    session, scans, regs, order = _stand_in(pair_turned=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tracking = _track_inclusions(session, scans, regs, TumourChoice(0, "test"))
    tr = tracking["right"]
    assert list(tr.reference_index) == order.tolist()
    assert tr.tumour_index == int(np.flatnonzero(order == 0)[0])
    assert tr.tumour_confidence >= TUMOUR_MIN_CONFIDENCE


def test_ambiguous_tumour_match_warns_with_scan_and_candidates():
    # The tumour and its equal neighbour turned across their expected separation: either
    # identity explains the scan about equally, so the pick is flagged, never silent.
    session, scans, regs, order = _stand_in(pair_turned=True)
    with pytest.warns(AmbiguousMatchWarning) as record:
        tracking = _track_inclusions(session, scans, regs, TumourChoice(0, "test"))
    (w,) = [r for r in record if issubclass(r.category, AmbiguousMatchWarning)]
    text = str(w.message)
    tr = tracking["right"]
    assert tr.tumour_confidence < TUMOUR_MIN_CONFIDENCE
    assert text.startswith("scan 'right': ambiguous match of the tracked tumour")
    j0, j1 = (int(np.flatnonzero(order == k)[0]) for k in (0, 1))
    assert f"inclusion {j0} " in text and f"inclusion {j1} " in text  # both candidates
    assert f"confidence {tr.tumour_confidence:.2f}" in text


def test_missing_tumour_warns_and_leaves_it_unset():
    session, scans, regs, _ = _stand_in(pair_turned=False, drop_tumour=True)
    with pytest.warns(TumourNotFoundWarning, match=r"scan 'right': the tracked tumour .* matches "
                      r"no inclusion .*its tumour_lps_mm is left unset"):  # fmt: skip
        tracking = _track_inclusions(session, scans, regs, TumourChoice(0, "test"))
    assert tracking["right"].tumour_index is None


def test_scan_without_inclusions_warns():
    session, scans, regs, _ = _stand_in(pair_turned=False)
    scans["right"] = _scan(np.zeros((0, 3)), np.zeros(0), scans["right"].nipple_lps_mm)
    with pytest.warns(TumourNotFoundWarning, match=r"scan 'right': no inclusion found"):
        tracking = _track_inclusions(session, scans, regs, TumourChoice(0, "test"))
    assert tracking["right"].tumour_index is None and tracking["right"].reference_index == ()


def test_cli_shows_the_warning(tmp_path):
    # The command line shows an ingest warning on stderr (Python's default display, which
    # the progress bar keeps visible): run in a fresh interpreter, with run_ingest
    # replaced by one that warns as the tracking does.
    import subprocess
    import sys

    folder = make_scan_folder(tmp_path / "scans")
    argv = ["phantom-calib", "ingest", str(folder), "--out", str(tmp_path / "w")]
    code = (
        "import sys, warnings, types\n"
        "import calib.workflows.ingest as wf\n"
        "from registration import AmbiguousMatchWarning\n"
        "def fake(scans, out, progress=None):\n"
        "    warnings.warn(\"scan 'right': ambiguous match of the tracked tumour\", "
        "AmbiguousMatchWarning, stacklevel=2)\n"
        "    return types.SimpleNamespace(summary_table='table')\n"
        "wf.run_ingest = fake\n"
        "from calib.cli import main\n"
        f"sys.argv = {argv!r}\n"
        "main()\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "AmbiguousMatchWarning: scan 'right': ambiguous match" in run.stderr, run.stderr


# ------------------------------------------------------------------------------------
# slow: the quick preset, several seeds


def _assert_tracked_with_large_motion(tmp_path, preset, seed) -> None:
    """Ingest a twin without a warning; >= 40 mm motion, every tumour tracked to the bars."""
    truth = build_twin(tmp_path / "twin", preset, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run_ingest(tmp_path / "twin" / "scans", tmp_path / "work")
    errors = tracking_errors(truth, tmp_path / "work")
    assert max(e["max_motion_mm"] for e in errors.values()) >= 40.0, errors
    for name, e in errors.items():
        assert e["tumour_error_mm"] <= 0.5 and e["wrong"] == [], (name, e)
        assert e["min_confidence"] >= TUMOUR_MIN_CONFIDENCE, (name, e)


SOFT_QUICK = replace(PRESETS["quick"], c1_pa=300.0, effects=TruthEffects())


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_quick_soft_twin_every_posture(tmp_path, seed):
    # Quick preset (4 postures, 10 mm, 1.5 mm voxels), c1 = 300 Pa: inclusion motion up
    # to 61 mm between the laterals. Bars as in the default test.
    _assert_tracked_with_large_motion(tmp_path, SOFT_QUICK, seed)


SLIDING_SMALL = replace(SMALL_PRESET, c1_pa=950.0, effects=TruthEffects(sliding=True))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_sliding_twin(tmp_path, seed):
    # The back plate slides (the independent generator did). c1 = 950 Pa is about
    # the softest the FE solves on this small twin (900 Pa fails for seed 1): inclusion
    # motion 40.8 and 41.7 mm; the former tracker was 30.6 and 52.6 mm off on these seeds.
    _assert_tracked_with_large_motion(tmp_path, SLIDING_SMALL, seed)


def test_the_size_sd_grows_with_voxels_past_those_it_was_measured_on():
    # closed form: 0.3 mm up to 2 mm voxels (measured on the twin at 1.5-2 mm: the twin's
    # matching is unchanged), in proportion to the largest voxel edge beyond (thick slices)
    from calib.data.ingest import size_sd_mm

    assert size_sd_mm([1.5, 1.5, 1.5]) == size_sd_mm([0.8] * 3, [2.0] * 3) == 0.3
    assert size_sd_mm([1.0, 1.0, 3.0]) == pytest.approx(0.45)
    assert size_sd_mm([0.8] * 3, [1.0, 1.0, 4.0]) == pytest.approx(0.6)


def test_a_tumour_hint_far_from_every_inclusion_is_warned_about():
    # a tumour ingest did not segment (too large, dark): the nearest inclusion is tracked
    # as the tumour all the same, no longer silently (radius + 5 mm: TUMOUR_HINT_SLACK_MM)
    from calib.data.ingest import TumourHintWarning, _choose_tumour

    res = _scan([[0.0, 0.0, 20.0], [30.0, 0.0, 20.0]], [8.0, 6.0], [0.0, 0.0, 60.0])

    def session(hint):
        return SimpleNamespace(reference=SimpleNamespace(name="ref"), tumour_hint_lps_mm=hint)

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        near = _choose_tumour(session(np.array([0.0, 8.9, 20.0])), res)  # 4 + 5 mm: within
    assert near.reference_index == 0
    said = r"'ref': .* nearest the \[landmarks\] tumour hint is 9.1 mm from it \(8.0 mm wide\)"
    with pytest.warns(TumourHintWarning, match=said):
        far = _choose_tumour(session(np.array([0.0, 9.1, 20.0])), res)
    assert far.reference_index == 0 and "9.1 mm away" in far.reason
    # review BG: with no inclusion in the reference scan the hint was dropped unsaid
    none = _scan(np.zeros((0, 3)), np.zeros(0), [0.0, 0.0, 60.0])
    with pytest.warns(TumourHintWarning, match=r"'ref': no inclusion found .* hint is not used"):
        lone = _choose_tumour(session(np.array([0.0, 9.1, 20.0])), none)
    assert lone.reference_index is None
    with warnings.catch_warnings():  # no hint, nothing to say
        warnings.simplefilter("error")
        assert _choose_tumour(session(None), none).reference_index is None
