"""Accuracy of the full scan pipeline against known synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from imaging_synth import make_scan, true_surface_distance

from imaging import FiducialError, SegmentationError, Volume, process_scan
from imaging.surface import SurfaceMesh


def _check_accuracy(scan, res, report=None):
    ph = scan.phantom
    d = true_surface_distance(scan, res.surface.vertices_lps_mm)
    # Issue 3 accuracy bars: mean <= 0.3 mm (a third of a voxel), p95 <= 1 mm.
    assert d.mean() <= 0.3, d.mean()
    assert np.percentile(d, 95) <= 1.0, np.percentile(d, 95)
    true_fid = scan.to_scanner(ph.fiducial_centres_mm)
    err = np.linalg.norm(res.fiducials_lps_mm[:, None] - true_fid[None], axis=2).min(1)
    assert len(res.fiducials_lps_mm) == 3
    assert err.max() <= 0.2, err  # issue 3: fiducial centroids within 0.2 mm
    true_c = scan.to_scanner(ph.inclusion_centres_mm)
    assert len(res.inclusions.diameters_mm) == len(true_c)  # all found, nothing spurious
    dist = np.linalg.norm(res.inclusions.centres_lps_mm[:, None] - true_c[None], axis=2)
    match = dist.argmin(1)
    assert len(set(match)) == len(true_c)
    assert dist.min(1).max() <= 0.5  # issue 3: centres within 0.5 mm
    ddiam = np.abs(res.inclusions.diameters_mm - ph.inclusion_diameters_mm[match])
    assert ddiam.max() <= 1.0  # issue 3: diameters within 1 mm
    nip = np.linalg.norm(res.nipple_lps_mm - scan.to_scanner(ph.nipple_mm))
    assert nip <= 1.0  # issue 3: nipple within 1 mm
    if report is not None:
        report.update(
            mean=d.mean(),
            p95=np.percentile(d, 95),
            fid=err.max(),
            inc=dist.min(1).max(),
            diam=ddiam.max(),
            nipple=nip,
        )


def test_oblique_anisotropic_biased_noisy_scan(oblique_scan, oblique_result):
    res = oblique_result
    _check_accuracy(oblique_scan, res)
    q = res.surface.quality
    assert q["watertight"] and q["winding_consistent"]
    # The surface encloses the true dome volume (pi a b c * 2/3) to within 1 %
    # (partial-volume level set: error ~ mean distance * area / volume).
    a, b, c = oblique_scan.phantom.semi_axes_mm
    assert q["volume_ml"] == pytest.approx(2.0 / 3.0 * np.pi * a * b * c / 1000.0, rel=0.01)


def test_tumour_selection(oblique_scan, oblique_result):
    ph = oblique_scan.phantom
    true_c = oblique_scan.to_scanner(ph.inclusion_centres_mm)
    largest = true_c[np.argmax(ph.inclusion_diameters_mm)]
    assert np.linalg.norm(oblique_result.tumour_lps_mm - largest) <= 0.5
    smallest = true_c[np.argmin(ph.inclusion_diameters_mm)]
    res = process_scan(oblique_scan.volume, tumour_hint_lps_mm=smallest + 3.0)
    assert np.linalg.norm(res.tumour_lps_mm - smallest) <= 0.5


def test_back_plate_flags(oblique_scan, oblique_result):
    s = oblique_result.surface
    z_ph = (s.vertices_lps_mm - oblique_scan.T[:3, 3]) @ oblique_scan.T[:3, :3]
    z = z_ph[:, 2]
    # Flagged vertices lie on the flat back face (z = 0) within the 1.5 mm tolerance plus
    # the level-set error; vertices well above it are never flagged.
    assert np.all(np.abs(z[s.back_plate]) <= 2.0)
    assert not np.any(s.back_plate[z > 3.0])
    # the face's own vertices: all flagged here (the largest flagged |z| 1.43 mm); 95 %
    # leaves room for a voxel-staircase vertex of another pose
    assert s.back_plate[np.abs(z) < 0.3].mean() > 0.95


def test_json_summary(oblique_result):
    import json

    d = json.loads(json.dumps(oblique_result.to_json_dict()))
    assert np.asarray(d["fiducials_lps_mm"]).shape == (3, 3)
    assert len(d["inclusions"]) == len(oblique_result.inclusions.diameters_mm)


def test_wrong_marker_count(oblique_scan):
    with pytest.raises(FiducialError, match=r"<synthetic>.*found 3 fiducial markers, expected 4"):
        process_scan(oblique_scan.volume, expected_fiducials=4)


def _with_blob(scan, gain: float, at_mm=(0.0, 0.0, 12.0)) -> tuple[Volume, np.ndarray]:
    """The scan with a 2.5 mm ball of ``gain`` times the body level at ``at_mm`` (phantom
    frame; the default inside the body), and the ball's voxels (bool, the volume's shape)."""
    vol = scan.volume
    A = vol.affine_lps_from_index
    idx = np.indices(vol.array.shape).reshape(3, -1).T
    pts = idx @ A[:3, :3].T + A[:3, 3]
    near = np.linalg.norm(pts - scan.to_scanner([0.0, 0.0, 12.0]), axis=1) < 8.0
    level = np.median(np.asarray(vol.array).reshape(-1)[near])  # the body's, near the ball
    ball = np.linalg.norm(pts - scan.to_scanner(at_mm), axis=1) < 2.5
    arr = np.array(vol.array, np.float32).reshape(-1)
    arr[ball] = level * gain
    shape = vol.array.shape
    return Volume(arr.reshape(shape), A, "blob.nii.gz"), ball.reshape(shape)


def test_a_bright_blob_inside_the_body_is_no_marker(oblique_scan):
    # Review AE: every blob over the marker threshold (2 times the body) was a marker
    # candidate and was cut from the body mask, inside the body too: inclusions at 2.5
    # times the body stopped ingest (22 markers for 3), at 2.3 times dented the surface.
    # A blob that tissue encloses is an inclusion: the markers stay, the body keeps it.
    base = process_scan(oblique_scan.volume)
    for gain in (2.2, 3.0, 6.0):
        vol, ball = _with_blob(oblique_scan, gain)
        res = process_scan(vol)
        assert res.quality["fiducials_dropped"] == 0
        # the same markers: the bias field refitted with the ball moves them by ~1e-4 mm
        np.testing.assert_allclose(res.fiducials_lps_mm, base.fiducials_lps_mm, atol=0.05)
        assert np.asarray(res.mask.array, bool)[ball].all()


def test_a_marker_sunk_into_the_body_is_still_found():
    # reviews AF, AH: a marker more than half inside the body had a ring median of
    # 0.94-0.97 of the body level, read as an enclosed inclusion, and ingest stopped with 2
    # markers for 3. Standing out of the body (background within 2 voxels), it is a marker:
    # found, and cut from the body mask as markers are
    from imaging.detect import detect_fiducials
    from imaging.segment import segment_body

    plate = [[-9.20335342, 42.34673338, -2.5], [-43.41505835, -24.66378676, -2.5]]
    fid = [*plate, [0.0, 0.0, 28.5]]  # the body's top at 30 mm: r 2.5 mm, 1 mm out of it
    scan = make_scan(fiducials_mm=fid, n_inclusions=0, seed=1)
    seg = segment_body(scan.volume)
    found = detect_fiducials(seg).centres_lps_mm
    truth = np.array([scan.to_scanner(p) for p in fid])
    # review CC-10: the comment said half a voxel (1.5 mm), the bar was 0.75 mm. The
    # plate's markers, whole: issue 3's 0.2 mm (measured 0.004, 0.019); the sunk one,
    # most of it inside the body (1 mm of its 5 stands out): found at its centre, within half the
    # smallest voxel edge (1.0 x 1.0 x 1.3 mm voxels: 0.5 mm; measured 0.185)
    err = np.linalg.norm(found[:, None] - truth[None], axis=2).min(axis=0)
    assert err[:2].max() <= 0.2 and err[2] <= 0.5, err
    i, j, k = np.round(seg.mask.lps_to_index(truth[2][None])[0]).astype(int)
    assert not np.asarray(seg.mask.array)[i, j, k]  # its centre is no body


def test_a_faint_surplus_blob_is_left_out_and_a_bright_one_is_an_error(oblique_scan):
    # At SNR 8 the quick twin's tilt_25 scan had two inclusions lifted over the marker
    # threshold (peaks 2.01, 2.02 against the markers' 3.45-3.70) and ingest stopped.
    # A blob in the background 10 mm under the plate (where markers lie, not enclosed by
    # tissue) is a candidate: this scan's markers peak at 3.43-3.53 (normalised,
    # smoothed); a ball at 2.2x the body peaks near 2.2: 1.2 above the body against 2.43,
    # a ratio of about 2 >= 1.5, so it is left out and said. At 3.0x (peak near 3.0, a
    # ratio of about 1.2) no choice is clear: an error.
    base = process_scan(oblique_scan.volume)
    res = process_scan(_with_blob(oblique_scan, 2.2, at_mm=(0.0, 0.0, -10.0))[0])
    assert res.quality["fiducials_dropped"] == 1 and base.quality["fiducials_dropped"] == 0
    np.testing.assert_allclose(res.fiducials_lps_mm, base.fiducials_lps_mm, atol=0.05)
    with pytest.raises(FiducialError, match=r"blob.nii.gz: found 4 fiducial markers, expected 3"):
        process_scan(_with_blob(oblique_scan, 3.0, at_mm=(0.0, 0.0, -10.0))[0])


def test_missed_markers_are_explained(oblique_scan):
    # Markers dimmed under both thresholds (2 times the body; 1.3 apart from it) or a
    # bright blob that is no marker: the error says what was seen, not only "found 0".
    # Markers peak at 3.43-3.53 times the body level on this scan; clipped at 1.2 times
    # the body's median they stay under both.
    import re

    vol = oblique_scan.volume
    arr = np.array(vol.array, np.float32)
    body = float(np.median(arr[arr > 0.5 * arr.max() / 3.5]))
    dim = Volume(np.minimum(arr, 1.2 * body), vol.affine_lps_from_index, "dim.nii.gz")
    with pytest.raises(FiducialError) as exc:
        process_scan(dim)
    text = str(exc.value)
    assert "dim.nii.gz: found 0 fiducial markers, expected 3" in text
    peak = float(re.search(r"body level\) reaches ([0-9.]+)", text)[1])
    assert 1.0 < peak < 2.0, text  # the dimmed markers (and the body) lie under it
    assert "apart from the body, 0 compact blobs over 1.3 times" in text
    # one marker too many asked for: the three found and why nothing else counted
    said = r"found 3 fiducial markers, expected 4: .*; away from those, the brightest point"
    with pytest.raises(FiducialError, match=said) as exc:
        process_scan(vol, expected_fiducials=4)
    # the inclusions (1.6 times the body), not the markers' rims just under the threshold
    text = str(exc.value)
    assert 1.3 < float(re.search(r"body level\) reaches ([0-9.]+)", text)[1]) < 1.9
    assert "apart from the body, 3 compact blobs" in text  # the same three, lower


def test_dim_markers_apart_from_the_body_are_found_and_said(oblique_scan, caplog):
    # review T: markers under twice the body level (thick slices, another contrast) could
    # not be ingested at all; clipped at 1.8 times the body they are found apart from it,
    # within the 0.2 mm bar of issue 3, with a warning
    vol = oblique_scan.volume
    arr = np.array(vol.array, np.float32)
    body = float(np.median(arr[arr > 0.5 * arr.max() / 3.5]))
    dim = Volume(np.minimum(arr, 1.8 * body), vol.affine_lps_from_index, "dim.nii.gz")
    with caplog.at_level("WARNING"):
        res = process_scan(dim)
    assert res.quality["fiducial_threshold"] == 1.3
    assert "0 of 3 fiducial markers over 2 times the body level" in caplog.text
    true_fid = oblique_scan.to_scanner(oblique_scan.phantom.fiducial_centres_mm)
    err = np.linalg.norm(res.fiducials_lps_mm[:, None] - true_fid[None], axis=2).min(1)
    assert err.max() <= 0.2, err
    # the detection's candidate count is the search's that found them (was the 2.0 one's)
    from imaging.detect import detect_fiducials
    from imaging.segment import segment_body

    det = detect_fiducials(segment_body(dim))
    assert det.quality["n_candidates"] == det.quality["n_found"] == 3


def test_a_marker_beyond_the_crop_margin_is_found_and_a_vial_stays_out():
    # The crop keeps 30 mm around the body; a marker on a frame farther out was cut off
    # ("found 2 fiducial markers"). Now marker-sized bright blobs grow the crop; a larger
    # bright object in the field of view (a 16 mm reference vial) does not.
    from imaging.testing import make_test_phantom

    fid = np.array(make_test_phantom(semi_axes_mm=(45.0, 35.0, 30.0), seed=1).fiducial_centres_mm)
    far = fid.copy()
    far[0, :2] *= 1.0 + 40.0 / np.linalg.norm(far[0, :2])  # 40 mm farther out
    scan = make_scan(fiducials_mm=far)
    res = process_scan(scan.volume)
    err = np.linalg.norm(res.fiducials_lps_mm[:, None] - scan.to_scanner(far)[None], axis=2)
    assert err.min(1).max() <= 0.2  # issue 3's fiducial bar


def test_only_marker_sized_blobs_grow_the_crop():
    # 1 mm voxels, a crop of [20, 40) on each axis: a 2.5 mm ball beyond it grows the
    # crop to hold it with 8 mm around; a 16 mm vial beyond it does not, nor does a
    # marker inside
    from imaging.segment import _with_far_markers

    idx = np.indices((100, 100, 100)).reshape(3, -1).T
    crop = (slice(20, 40),) * 3

    def ball(centre, r):
        return (np.linalg.norm(idx - centre, axis=1) < r).reshape(100, 100, 100)

    pad = np.full(3, 8)
    vial = ball([80, 80, 80], 8.0)
    assert _with_far_markers(crop, vial | ball([30, 30, 30], 2.5), 1.0, pad, "t") == crop
    grown = _with_far_markers(crop, vial | ball([60, 30, 30], 2.5), 1.0, pad, "t")
    # the ball's last voxels (60 + 2, 30 + 2) and 8 around: stops 71 and 41
    assert grown == (slice(20, 71), slice(20, 41), slice(20, 41))


@pytest.mark.parametrize("skin", [1.6, 0.7])
def test_a_visible_skin_layer_keeps_the_accuracy_bars(skin):
    # A 1.5 mm skin rendered at 1.6 (0.7) times the body: before, the inner tail of a
    # bright skin's blur passed the edge margin in fragments and 84 of them were taken
    # for inclusions (20 at 1.3 times); the surface already met the bars (mean 0.22 mm).
    # Now a candidate whose brightest voxel lies on the margin is a surface layer.
    from imaging.synthetic import MRIntensities

    scan = make_scan(skin=1.5, intensities=MRIntensities(skin=1000.0 * skin))
    res = process_scan(scan.volume)
    _check_accuracy(scan, res)  # issue 3's bars, the 5 inclusions and nothing spurious
    if skin > 1.0:
        assert res.inclusions.quality["n_surface_layer"] > 0  # the fragments were there
    # in the scan's record (review BM: counted, not written)
    assert res.quality["inclusions_surface_layer"] == res.inclusions.quality["n_surface_layer"]


def test_a_field_of_view_that_cuts_the_body_is_said(oblique_scan, oblique_result, caplog, tmp_path):
    # the surface where the volume's edge cuts the body is the edge, not the phantom's:
    # a silent wrong answer before. The whole scan: no body voxel on the edge.
    assert oblique_result.quality["fov_cut_height_mm"] == 0.0
    vol = oblique_scan.volume
    mask = oblique_result.mask.array.astype(bool)
    keep = int(np.argwhere(mask.any(axis=(1, 2))).mean())  # through the body's middle
    cut = Volume(np.array(vol.array)[:keep], vol.affine_lps_from_index, "cut.nii.gz")
    with caplog.at_level("WARNING", logger="imaging.pipeline"):
        res = process_scan(cut, expected_fiducials=None)
    assert res.quality["fov_cut_height_mm"] > 10.0
    assert "cut.nii.gz: the field of view cuts the body" in caplog.text
    # its vertices there are flagged (and left out of the fit and the errors, see
    # tests/calib/test_calib_fov_edge.py): on the cut face, within a voxel of index
    # keep - 1 along the cut axis, and above the plate; the whole scan flags none
    assert oblique_result.surface.fov_edge is None
    assert oblique_result.quality["fov_edge_vertices"] == 0
    edge = res.surface.fov_edge
    assert edge.sum() == res.quality["fov_edge_vertices"] > 50
    assert f"its {int(edge.sum())} vertices there are flagged fov_edge" in caplog.text
    ijk = res.mask.lps_to_index(res.surface.vertices_lps_mm)
    assert (ijk[edge, 0] > keep - 2.0).all()
    # every vertex on the cut face carries a flag: fov_edge, or back_plate within its
    # 1.5 mm of the plate (the two meet: a review found 110 cut-face vertices in between)
    on_cut = ijk[:, 0] > keep - 1.5
    assert (edge | res.surface.back_plate)[on_cut].all()
    assert not (edge & res.surface.back_plate).any()
    # cut through the body's middle, the scan misses the nipple: the one found is on the cut
    assert "the nipple found lies on the field of view's cut" in caplog.text
    # and they survive the PLY round trip of WORK/scans/<name>/surface_ref.ply
    from imaging.surface import read_ply, write_ply

    back = read_ply(write_ply(tmp_path / "s.ply", res.surface))
    assert (back.fov_edge == edge).all() and (back.back_plate == res.surface.back_plate).all()
    assert read_ply(write_ply(tmp_path / "w.ply", oblique_result.surface)).fov_edge is None


@pytest.mark.parametrize("offset", [0.3, -0.5])
def test_a_background_offset_keeps_the_accuracy_bars(oblique_scan, oblique_result, offset, caplog):
    # the thresholds are fractions of the body level above zero: a DC offset of +0.3 (-0.5)
    # times the body level grew (shrank) the segmented body by 5 % (7 %) and moved the
    # nipple 0.45 (3.6) mm. Now the background's median is subtracted where it is more
    # than 3 robust sds from zero; a magnitude image's noise floor (1.75 sds) is left.
    assert oblique_result.quality["seg_background_offset"] == 0.0
    vol = oblique_scan.volume
    image = np.asarray(vol.array, np.float32) + 1000.0 * offset
    shifted = Volume(image, vol.affine_lps_from_index, "offset.nii.gz")
    with caplog.at_level("WARNING", logger="imaging.segment"):
        res = process_scan(shifted)
    assert "offset.nii.gz: the background lies at" in caplog.text
    # the offset found: the shift plus the noise floor's median (Rayleigh, SNR 25 of a
    # body at 1000: 1.18 x 40 = 47) within 2 % of the body level
    assert res.quality["seg_background_offset"] == pytest.approx(1000.0 * offset + 47, abs=20)
    _check_accuracy(oblique_scan, res)
    # as the scan without the offset: measured 0.995 of its volume (without the mend 1.033,
    # 0.947), surface mean 0.041 mm (0.035; without 0.28, 0.41 mm): bars well inside those
    # the noise under the offset: the rendered sigma is 1/25 of the body level (it read
    # 0.47 of that, the floor's median taken off with the offset); the bias field's +-20 %
    # and the level's share of the floor's median: 15 %
    assert res.quality["seg_noise_sigma_rel"] == pytest.approx(0.04, rel=0.15)
    ratio = res.quality["seg_volume_ml"] / oblique_result.quality["seg_volume_ml"]
    assert ratio == pytest.approx(1.0, abs=0.01)
    d0 = true_surface_distance(oblique_scan, oblique_result.surface.vertices_lps_mm).mean()
    assert true_surface_distance(oblique_scan, res.surface.vertices_lps_mm).mean() <= d0 + 0.02


def test_inclusion_threshold_rises_with_the_noise():
    # With a fixed contrast threshold of 0.15 this scan at SNR 8 gave 105 inclusions (5
    # true) and at SNR 5 114; on the quick twin at SNR 8, 1,384, whose tracking across
    # postures asked for 20 GiB. The threshold is now at least 4.5 noise sd of the
    # smoothed image (0.35 at SNR 8), and at SNR 25 it stays 0.15 (sd 0.025).
    from imaging.detect import detect_inclusions
    from imaging.segment import segment_body

    for snr, most in ((25.0, 5), (8.0, 5), (5.0, 15)):
        scan = make_scan(snr=snr)
        found = detect_inclusions(segment_body(scan.volume))
        true = scan.to_scanner(scan.phantom.inclusion_centres_mm)
        gap = np.linalg.norm(true[:, None] - found.centres_lps_mm[None], axis=2).min(1)
        # every inclusion still found: a detection within 1.5 mm (under the smallest
        # inclusion's 2 mm radius: not a neighbour's); measured 0.08, 0.17, 0.48 mm
        assert np.all(gap < 1.5), (snr, gap)
        assert len(found.diameters_mm) <= most, (snr, found.quality)
        if snr == 25.0:
            assert found.quality["threshold"] == 0.15


def test_an_inclusion_past_the_upper_diameter_is_said_not_dropped_silently(caplog):
    # the detection accepts 2-15 mm: a larger tumour (another phantom, another size) was
    # left out without a word and the largest remaining blob became the tumour (audit I:
    # a 2x dome with 8/16/24 mm inclusions gave the 8 mm one). Here the upper bound is
    # set to 6 mm on the test phantom's 4-10 mm inclusions: those above it are named,
    # at their true centres (within the 1.5 mm the detection test allows)
    from imaging.detect import detect_inclusions
    from imaging.segment import segment_body

    scan = make_scan()
    truth_d = scan.phantom.inclusion_diameters_mm
    truth_c = scan.to_scanner(scan.phantom.inclusion_centres_mm)
    with caplog.at_level("WARNING", logger="imaging.detect"):
        found = detect_inclusions(segment_body(scan.volume), diameter_range_mm=(2.0, 6.0))
    big = truth_d > 6.5  # clear of the bound (volume-equivalent diameters differ a little)
    assert big.any() and found.quality["n_too_large"] >= big.sum()
    assert "larger than the 6 mm the detection accepts were left out" in caplog.text
    import re

    listed = caplog.text.split("centres LPS ")[1].split(":")[0]
    named = np.array(re.findall(r"\(([-\d.]+), ([-\d.]+), ([-\d.]+)\)", listed), float)
    for c in truth_c[big]:
        assert np.linalg.norm(named - c, axis=1).min() < 1.5


def test_empty_segmentation():
    v = Volume(np.full((30, 30, 20), 7.0, np.float32), np.eye(4), "empty.nii.gz")
    with pytest.raises(SegmentationError, match="empty.nii.gz.*constant"):
        process_scan(v)


def test_a_body_in_few_thick_slices_keeps_a_flat_bias_field_and_its_volume():
    # review T: a 30 mm dome in 5 mm slices leaves the eroded body 2 slices along them;
    # the cubic bias field, undetermined along that axis, swung 0.31-2.06 over the body of
    # an unbiased image and halved its volume (46.7 ml of 99), then the markers drowned
    from imaging.segment import segment_body
    from imaging.synthetic import render_mr_volume, scan_grid_covering
    from imaging.testing import make_test_phantom

    ph = make_test_phantom(seed=0)
    pts = np.vstack([ph.body[0], ph.fiducial_centres_mm])
    grid = scan_grid_covering(pts, spacing_mm=(0.8, 0.8, 5.0), margin_mm=12.0)
    vol = render_mr_volume(
        ph.body,
        T_scanner_from_phantom=np.eye(4),
        grid=grid,
        inclusions=ph.inclusions,
        fiducial_centres_mm=ph.fiducial_centres_mm,
        fiducial_radius_mm=ph.fiducial_radius_mm,
        bias_amplitude=0.0,
        seed=0,
    )
    q = segment_body(vol).quality
    # no bias rendered: the fitted field is flat to the noise's few per cent (SNR 30)
    assert 0.9 <= q["bias_min"] and q["bias_max"] <= 1.1, q
    true_ml = 2.0 / 3.0 * np.pi * 45.0 * 35.0 * 30.0 / 1000.0
    # partial volume of half a 5 mm slice at the dome's base, where its cross-section is
    # largest: pi 45 35 2.5 mm^3 = 12.4 ml, 12.5 % of its 99 ml (the top's half slice
    # cuts a small cap; review CC-11: the comment had said 8 % there, under the bar and
    # under the measured +9.7 %)
    bar = np.pi * 45.0 * 35.0 * 2.5 / 1000.0 / true_ml
    assert abs(q["volume_ml"] / true_ml - 1.0) <= bar, (q["volume_ml"], true_ml)


def test_a_bias_field_that_swings_beyond_the_range_is_said_or_refused(caplog):
    # a body whose intensity rises k-fold across it: 6-fold, over BIAS_RANGE_WARN (4), is
    # said and the body kept whole; 30-fold, over BIAS_RANGE_MAX (8), is refused. Review BM:
    # the spread was measured on the uncorrected Otsu body, which loses the dim end first
    # (30-fold was said as 5.09), and the body was cut flat at that crop's face: both now
    # come from the corrected body. Tolerances: the ramp's k to 15 % (a cubic fitted to an
    # exponential ramp, and the body's boundary voxels), the volume to 3 % (its surface
    # voxels: 1 mm voxels on a 15-24 mm ellipsoid)
    import re

    from imaging.segment import BIAS_RANGE_MAX, BIAS_RANGE_WARN, segment_body

    def ramp(k):
        i, j, m = np.indices((60, 60, 40), float)
        body = ((i - 30) / 24) ** 2 + ((j - 30) / 24) ** 2 + ((m - 20) / 15) ** 2 <= 1.0
        arr = np.where(body, 1000.0 * np.exp(np.log(k) * (i - 6) / 48), 0.0)
        arr += np.random.default_rng(0).normal(0.0, 5.0, arr.shape) ** 2  # a positive floor
        return Volume(arr.astype(np.float32), np.eye(4), "ramp.nii.gz"), body.sum() / 1000.0

    vol, true_ml = ramp(6.0)
    with caplog.at_level("WARNING", logger="imaging.segment"):
        q = segment_body(vol).quality
    pattern = r"ramp.nii.gz: the intensity-bias field fitted inside the body spans a ratio of "
    said = re.search(pattern + r"([0-9.]+)", caplog.text)
    assert said and BIAS_RANGE_WARN < float(said.group(1)) <= BIAS_RANGE_MAX, caplog.text
    assert float(said.group(1)) == pytest.approx(6.0, rel=0.15)
    assert float(said.group(1)) == pytest.approx(q["bias_max"] / q["bias_min"], rel=0.01)
    assert q["volume_ml"] == pytest.approx(true_ml, rel=0.03)
    with pytest.raises(SegmentationError, match=r"ramp.nii.gz.*bias field.*spans a ratio of") as e:
        segment_body(ramp(30.0)[0])
    span = float(re.search(r"spans a ratio of ([0-9.]+)", str(e.value)).group(1))
    assert BIAS_RANGE_MAX < span and span == pytest.approx(30.0, rel=0.15)


def test_surface_is_a_surface_mesh(oblique_result):
    assert isinstance(oblique_result.surface, SurfaceMesh)
    assert oblique_result.surface.back_plate.shape == (len(oblique_result.surface.vertices_lps_mm),)


@pytest.mark.slow
def test_full_size_scan_accuracy():
    """256 x 256 x 200 at 0.8 x 0.8 x 1.0 mm, dissertation-like phantom size."""
    scan = make_scan(
        spacing=(0.8, 0.8, 1.0),
        min_shape=(256, 256, 200),
        semi_axes=(70.0, 55.0, 50.0),
        n_inclusions=19,
        seed=3,
    )
    res = process_scan(scan.volume)
    _check_accuracy(scan, res)


def test_a_noise_floor_is_not_an_offset_but_a_level_off_zero_is():
    # closed forms of the background's median: Rayleigh 1.18 sigma; a sum of squares over
    # 8 coils (chi, 16 dof) 3.9 sigma = 157 at sigma 40: 5.6 robust sds, which the sd rule
    # alone took for an offset (the body shrank 1.8 %); Gaussian noise around +300 / -500
    from imaging.segment import background_offset

    rng = np.random.default_rng(0)
    body = np.zeros((40, 40, 40), bool)
    body[12:28, 12:28, 12:28] = True

    def image(bg):
        out = bg.reshape(body.shape).copy()
        out[body] = 1000.0
        return out

    n = body.size
    rayleigh = np.hypot(*rng.normal(0.0, 40.0, (2, n)))
    coils8 = np.sqrt((rng.normal(0.0, 40.0, (16, n)) ** 2).sum(axis=0))
    assert background_offset(image(rayleigh), body) == 0.0
    assert background_offset(image(coils8), body) == 0.0
    # the median of 40-sd noise over ~60 000 voxels: within 1
    assert background_offset(image(300.0 + rng.normal(0.0, 40.0, n)), body) == pytest.approx(
        300.0, abs=1.0
    )
    assert background_offset(image(-500.0 + rng.normal(0.0, 40.0, n)), body) == pytest.approx(
        -500.0, abs=1.0
    )
