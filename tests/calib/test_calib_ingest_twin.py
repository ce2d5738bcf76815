"""The digital twin read back through ``run_ingest``, checked against its sealed truth.

One ``quick`` twin (4 postures, about a minute on 2 cores) is built and ingested once per
module. Tolerances are the accuracy bars of issues 3 (imaging), 4 (registration) and 5 (twin).
"""

from __future__ import annotations

import json
import logging

import nibabel as nib
import numpy as np
import pytest
from calib_helpers import polyhedron_volume_mm3

import imaging
import registration
from calib.data.ingest import load_ingest
from calib.twin import synthesize
from calib.workflows.ingest import run_ingest


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    base = tmp_path_factory.mktemp("twin")
    out, work = base / "twin", base / "work"
    record = synthesize(out, preset="quick", seed=0)
    said = []  # the registration's log lines (review AX: each was printed twice)
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda rec: said.append(rec.getMessage())
    logger = logging.getLogger("registration")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        result = run_ingest(out / "scans", work)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    truth = json.loads((out / "truth" / "truth.json").read_text())
    assert truth == json.loads(json.dumps(record))  # the returned record is what was sealed
    ingested = {name: load_ingest(work, name) for name in truth["scans"]}
    return {"out": out, "work": work, "truth": truth, "ingest": ingested, "result": result,
            "registration_log": said}  # fmt: skip


def test_each_scan_s_registration_is_said_once(twin):
    # ingest registers twice (without, then with landmarks, for the inclusion tracking);
    # `-v ingest` printed every "registered" line twice (review AX)
    said = [s for s in twin["registration_log"] if s.startswith("registered ")]
    assert sorted(s.split(":")[0] for s in said) == sorted(
        f"registered {name}" for name in twin["truth"]["scans"]
    )


def _reference(truth) -> str:
    (ref,) = [n for n, s in truth["scans"].items() if s["role"] == "reference"]
    return ref


def _T(matrix) -> np.ndarray:
    T = np.asarray(matrix, float)
    assert T.shape == (4, 4)
    return T


def _apply(T, points) -> np.ndarray:
    return np.asarray(points, float) @ T[:3, :3].T + T[:3, 3]


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def test_every_scan_reads_back(twin):
    truth, work = twin["truth"], twin["work"]
    assert set(twin["ingest"]) == set(truth["scans"]) and len(truth["scans"]) == 4
    for name, doc in twin["ingest"].items():
        folder = work / "scans" / name
        for f in ("surface.ply", "surface_ref.ply", "mask.nii.gz", "ingest.json"):
            assert (folder / f).is_file(), f"{name}: {f} missing"
        assert doc["role"] == truth["scans"][name]["role"]
        assert len(doc["fiducials_lps_mm"]) == 3
        surface = imaging.read_ply(folder / "surface.ply")
        assert len(surface.faces) > 1000
        # review CG-4: the mask (validate reads it) was only checked to exist. It is binary
        # and holds the body the surface bounds: their volumes agree to half a voxel over
        # the surface's area (the surface is the mask's boundary, smoothed; measured 0.6 %
        # on the quick twin's right lateral scan against a 5 % bound)
        mask = nib.load(folder / "mask.nii.gz")
        inside = np.asarray(mask.dataobj)
        assert set(np.unique(inside)) == {0, 1}
        voxel = np.asarray(mask.header.get_zooms()[:3], float)
        tri = surface.vertices_lps_mm[surface.faces]
        enclosed = polyhedron_volume_mm3(surface.vertices_lps_mm, surface.faces)
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        slack = area.sum() * 0.5 * voxel.max()
        assert abs(inside.sum() * voxel.prod() - enclosed) <= slack, name
        assert (work / "scans" / name / "surface_ref.ply").stat().st_size > 0
    assert _reference(truth) == twin["result"].session.reference.name
    assert not list(work.rglob(".*"))  # no temporary files left behind
    # the slice thickness across the plate reaches the model (its back face's tolerance):
    # the quick twin's 1.5 mm voxels: the longest voxel edge along the plate's normal lies
    # between 1.5 / sqrt(3) (a normal along the voxel's diagonal) and 1.5
    from calib.data.measurements import load_measurements
    from calib.data.session import load_session

    meas = load_measurements(work, load_session(twin["out"] / "scans"))
    for name, doc in twin["ingest"].items():
        depth = doc["back_plane"]["voxel_depth_mm"]
        assert 1.5 / np.sqrt(3.0) <= depth <= 1.5 + 1e-9, (name, depth)
        assert meas.scans[name].back_voxel_depth_mm == depth


def test_fiducials(twin):
    # Issue 3: fiducial centroids within 0.2 mm. The marker order of a scan is not the
    # truth's (correspondence is solved later, by registration): match by nearest.
    errors = {}
    for name, doc in twin["ingest"].items():
        found = np.asarray(doc["fiducials_lps_mm"])
        true = np.asarray(twin["truth"]["scans"][name]["fiducials_lps_mm"])
        d = np.linalg.norm(found[:, None] - true[None], axis=2)
        assert sorted(d.argmin(axis=1)) == [0, 1, 2], f"{name}: two markers match one truth"
        errors[name] = float(d.min(axis=1).max())
    assert max(errors.values()) <= 0.2, errors


def _nipple_errors(twin) -> dict:
    return {
        name: float(np.linalg.norm(np.subtract(doc["nipple_lps_mm"], truth_scan["nipple_lps_mm"])))
        for name, doc in twin["ingest"].items()
        for truth_scan in [twin["truth"]["scans"][name]]
    }


def test_nipple(twin):
    # Issue 3: nipple within 1 mm (in each scan's own LPS frame). The truth is the material
    # tip of the nipple bump; the bump tips over under a lateral load, so the apex relative
    # to the back plane missed it by 1.55-1.83 mm; the protrusion tip is 0.26-0.66 mm off
    # (quick twin, seed 0).
    errors = _nipple_errors(twin)
    assert max(errors.values()) <= 1.0, errors


def test_tracked_inclusion_is_detected(twin):
    # Issue 3: inclusion centres within 0.5 mm; all 19 inclusions found. The true
    # tumour must be among the detected inclusions (nearest one), whichever is tracked.
    n_true = len(twin["truth"]["stress_free"]["inclusion_diameters_mm"])
    errors = {}
    for name, doc in twin["ingest"].items():
        assert len(doc["inclusions"]) == n_true, f"{name}: {len(doc['inclusions'])} found"
        centres = np.array([inc["centre_lps_mm"] for inc in doc["inclusions"]])
        true = np.asarray(twin["truth"]["scans"][name]["tumour_lps_mm"])
        errors[name] = float(np.linalg.norm(centres - true, axis=1).min())
    assert max(errors.values()) <= 0.5, errors


def test_segmented_inclusions_hold_the_rendered_volume(twin):
    # The model's inclusions are spheres of ingest's volume-equivalent diameters, so their
    # volume is what a stiff inclusion's print scales with. The renderer draws icospheres
    # (0.966 of the nominal spheres' volume). Measured on the quick twin (8 scan sets x 4
    # scans, bench_diagnose --model-error's cases): the segmented total 0.977-1.008 of the
    # rendered one (0.977: a scan with one blob too many). Bar: 3 %.
    import trimesh

    from calib.twin.synth import RENDERED_SPHERE_SUBDIVISIONS
    from fem.geometry import sphere_surface

    unit = trimesh.Trimesh(
        *sphere_surface(np.zeros(3), 1.0, subdivisions=RENDERED_SPHERE_SUBDIVISIONS)
    ).volume
    true_d = np.asarray(twin["truth"]["stress_free"]["inclusion_diameters_mm"])
    rendered_mm3 = unit * ((true_d / 2.0) ** 3).sum()
    ratios = {}
    for name, doc in twin["ingest"].items():
        d = np.array([inc["diameter_mm"] for inc in doc["inclusions"]])
        assert len(d) == len(true_d), f"{name}: {len(d)} found"
        ratios[name] = float(np.pi / 6.0 * (d**3).sum() / rendered_mm3)
    assert all(abs(r - 1.0) <= 0.03 for r in ratios.values()), ratios


def test_tumour(twin):
    # Issue 3: tracked tumour centre within 0.5 mm.
    errors = {
        name: float(np.linalg.norm(np.subtract(doc["tumour_lps_mm"], t["tumour_lps_mm"])))
        for name, doc in twin["ingest"].items()
        for t in [twin["truth"]["scans"][name]]
    }
    assert max(errors.values()) <= 0.5, errors


def test_tracked_tumour_is_the_same_inclusion_in_every_scan(twin):
    # The tracked inclusion of each scan, mapped back to the phantom frame by the true pose,
    # must be nearest to the same stress-free inclusion. Displacements near the tracked
    # inclusions (< 10 mm) are below the inclusion spacing (~15 mm) — measured: identity
    # margins of 8 mm or more; the check compares indices, not distances.
    truth = twin["truth"]
    centres = np.asarray(truth["stress_free"]["inclusion_centres_phantom_mm"])
    index = {}
    for name, doc in twin["ingest"].items():
        T_phantom_from_scan = np.linalg.inv(_T(truth["scans"][name]["T_scanner_from_phantom"]))
        p = _apply(T_phantom_from_scan, doc["tumour_lps_mm"])
        index[name] = int(np.linalg.norm(centres - p, axis=1).argmin())
    assert len(set(index.values())) == 1, index


def test_gravity_in_reference_frame(twin):
    # Issue 4: gravity recovered per scan within 0.5 deg. The true gravity in the reference
    # frame is R_ref (rotation of the reference's T_scanner_from_phantom) @ g_phantom.
    truth = twin["truth"]
    R_ref = _T(truth["scans"][_reference(truth)]["T_scanner_from_phantom"])[:3, :3]
    errors = {}
    for name, doc in twin["ingest"].items():
        g_true = R_ref @ np.asarray(truth["scans"][name]["gravity_phantom"])
        assert np.linalg.norm(doc["gravity_ref"]) == pytest.approx(1.0, abs=1e-9)
        errors[name] = _angle_deg(doc["gravity_ref"], g_true)
    assert max(errors.values()) <= 0.5, errors


def test_the_nipple_sags_with_gravity_and_a_flipped_gravity_is_said(twin, caplog):
    # review AE: a scanner.gravity of the wrong sign (an image written prone, read with
    # the supine default) turned every posture's load around and no check saw it. On the
    # twin the nipple moves along the change of gravity (review AE: cosines +1.00, +0.87,
    # +0.82; the 25 degree scan's 2.5 mm move is under the 5 mm that counts); with
    # gravity turned round every cosine changes sign, and that is said.
    from dataclasses import replace

    from calib.data.ingest import check_gravity_sign

    res = twin["result"]
    with caplog.at_level("WARNING", logger="calib.data.ingest"):
        cos = check_gravity_sign(res.session, res.scans, res.registrations)
    assert set(cos) == {"right_lateral", "tilt_50"} and min(cos.values()) > 0.5, cos
    assert "against the change of gravity" not in caplog.text
    up = {n: replace(r, gravity_ref=-r.gravity_ref) for n, r in res.registrations.items()}
    with caplog.at_level("WARNING", logger="calib.data.ingest"):
        flipped = check_gravity_sign(res.session, res.scans, up)
    assert flipped == pytest.approx({n: -c for n, c in cos.items()}, abs=1e-12)
    assert "in every posture the nipple moved against the change of gravity" in caplog.text


def test_registration_maps_fiducials_and_pose(twin):
    # Issue 4: translation within 0.3 mm, rotation within 0.3 deg. The truth fiducials
    # are listed in the same (phantom) order for every scan.
    truth = twin["truth"]
    ref = truth["scans"][_reference(truth)]
    T_ref = _T(ref["T_scanner_from_phantom"])
    for name, doc in twin["ingest"].items():
        t = truth["scans"][name]
        T = _T(doc["T_ref_from_scan"])
        mapped = _apply(T, t["fiducials_lps_mm"])
        err = np.linalg.norm(mapped - np.asarray(ref["fiducials_lps_mm"]), axis=1).max()
        assert err <= 0.3, f"{name}: fiducials mapped to {err:.3f} mm"
        T_true = T_ref @ np.linalg.inv(_T(t["T_scanner_from_phantom"]))
        R_err = T[:3, :3] @ T_true[:3, :3].T
        angle = np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1.0, 1.0)))
        assert angle <= 0.3, f"{name}: rotation off by {angle:.3f} deg"
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-9)  # never a reflection


def test_surface_accuracy(twin):
    # Issue 3: mean distance to the true surface <= 0.3 mm, 95th percentile <= 1 mm.
    out, work = twin["out"], twin["work"]
    stats = {}
    for name, t in twin["truth"]["scans"].items():
        ours = imaging.read_ply(work / "scans" / name / "surface.ply")
        true = imaging.read_ply(out / "truth" / t["surface"])
        d = registration.point_to_surface_distances(
            ours.vertices_lps_mm, true.vertices_lps_mm, true.faces, signed=False
        )
        s = registration.summarise(d)
        stats[name] = (round(s.mean_mm, 3), round(s.p95_mm, 3))
    assert all(mean <= 0.3 and p95 <= 1.0 for mean, p95 in stats.values()), stats


def test_true_deformation_is_physical(twin):
    # Issue 5: nipple displacement from the stress-free state under a lateral 1 g of 10-30 mm
    # (the dissertation's phantom moved by more than 10 mm over 40 % of its surface).
    truth = twin["truth"]
    free = np.asarray(truth["stress_free"]["nipple_phantom_mm"])
    lateral = {n: s for n, s in truth["scans"].items() if s["nominal_angle_deg"] in (0, 180)}
    assert set(lateral) == {"left_lateral", "right_lateral"}
    moved = {n: float(np.linalg.norm(np.subtract(s["nipple_phantom_mm"], free)))
             for n, s in lateral.items()}  # fmt: skip
    assert all(10.0 <= m <= 30.0 for m in moved.values()), moved
    # Left and right lateral gravity are opposite: the nipple moves to opposite sides (x).
    dx = {n: s["nipple_phantom_mm"][0] - free[0] for n, s in lateral.items()}
    assert dx["left_lateral"] > 5.0 and dx["right_lateral"] < -5.0, dx


@pytest.mark.parametrize("slope", [1.04, 1.2])
def test_a_strong_coil_bias_keeps_the_body_whole_and_its_markers(twin, slope, caplog):
    # review BM: the segmentation's crop and bias fit came from the uncorrected Otsu body.
    # Under a smooth bias exp(slope j) across the field of view (the body spans 5.8 and
    # 7.4 of it: warned, not refused, by the contract's 4-8) the far marker fell out of the
    # crop (1.04: "found 2 fiducial markers, expected 3"), the body was cut flat at the
    # crop's face (at 1.3: 304 voxels, 0.9 % of its volume, scored as surface) and the
    # warning said the spread of the part it kept (4.07 of 7.0). Tolerances: the volume to
    # 0.2 % and the markers to 0.2 mm (a bias corrected to a cubic's accuracy moves the
    # 50 %-level boundary by a fraction of a voxel, 1.5 mm here)
    import re

    ref = _reference(twin["truth"])
    volume = imaging.read_volume(twin["out"] / "scans" / ref)
    plain = imaging.process_scan(volume, expected_fiducials=3)
    a = np.asarray(volume.array, np.float32)
    ramp = np.exp(slope * np.linspace(-1.0, 1.0, a.shape[1]))[None, :, None]
    with caplog.at_level("WARNING", logger="imaging.segment"):
        biased = imaging.process_scan(volume.with_array(a * ramp), expected_fiducials=3)
    q = biased.quality
    assert q["seg_volume_ml"] == pytest.approx(plain.quality["seg_volume_ml"], rel=0.002)
    said = re.search(r"spans a ratio of ([0-9.]+)", caplog.text)
    assert said, caplog.text
    # the warning prints the ratio to 3 significant digits (%.3g): on a ratio of 4-8 a
    # rounding of at most 0.005, 0.13 %, against rel 0.01 (review CG-19: the bar had no
    # source; it tells the printed ratio from another quantity, not the rounding)
    assert float(said.group(1)) == pytest.approx(q["seg_bias_max"] / q["seg_bias_min"], rel=0.01)
    assert 4.0 < float(said.group(1)) <= 8.0
    np.testing.assert_allclose(biased.fiducials_lps_mm, plain.fiducials_lps_mm, atol=0.2)
    # made again from the corrected body; the unbiased scan once
    assert (plain.quality["seg_crop_passes"], q["seg_crop_passes"]) == (1, 2)


def test_a_body_still_cut_after_the_last_segmentation_is_refused(twin, monkeypatch):
    # review BM: with one segmentation allowed, the biased scan above is cut at its crop
    import imaging.segment

    monkeypatch.setattr(imaging.segment, "CROP_PASSES", 1)
    volume = imaging.read_volume(twin["out"] / "scans" / _reference(twin["truth"]))
    a = np.asarray(volume.array, np.float32)
    ramp = np.exp(1.2 * np.linspace(-1.0, 1.0, a.shape[1]))[None, :, None]
    with pytest.raises(imaging.SegmentationError, match=r"still reaches .*crop \(axis 1 low\)"):
        imaging.segment.segment_body(volume.with_array(a * ramp))


def test_an_inclusion_near_the_surface_in_thick_slices_is_not_taken_for_a_layer(twin):
    # review BM: a candidate whose extreme lay within the edge margin plus the longest
    # voxel edge was dropped as a surface layer's tail: in 6 mm slices (the reference scan
    # averaged in fours) a 4.7 mm inclusion 7.5 mm deep was. Now only one whose contrast
    # rises towards the surface is. Every inclusion of 4 mm or more is found within 3 mm of
    # its place in the 1.5 mm scan (smaller ones fade under the threshold in 6 mm slices)
    from imaging.detect import detect_inclusions
    from imaging.segment import segment_body

    volume = imaging.read_volume(twin["out"] / "scans" / _reference(twin["truth"]))
    a = np.asarray(volume.array, np.float32)
    nk = a.shape[2] // 4 * 4
    A = volume.affine_lps_from_index.copy()
    A[:3, 3] += 1.5 * A[:3, 2]  # the centre of the first four slices
    A[:3, 2] *= 4.0
    thick = imaging.Volume(
        a[:, :, :nk].reshape(*a.shape[:2], nk // 4, 4).mean(3), A, "thick.nii.gz"
    )
    fine = detect_inclusions(segment_body(volume))
    coarse = detect_inclusions(segment_body(thick))
    big = fine.centres_lps_mm[fine.diameters_mm >= 4.0]
    assert len(big) >= 10
    d = np.linalg.norm(big[:, None] - coarse.centres_lps_mm[None], axis=2).min(axis=1)
    assert d.max() <= 3.0, d
