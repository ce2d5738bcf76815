"""The validation report's displacement bins follow the scan, not one phantom's sag.

The bins were 0/5/10/20 mm, sized for the twin's ~24 mm sag: a 25 degree tilt that moved
the surface 2.5 mm had all its points in one bin. The edges are exact (a 1-2-5 ladder on
a quarter of the 99th percentile), so the checks are equalities.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.report.validation import displacement_bins_mm


@pytest.mark.parametrize(
    ("top_mm", "step_mm"),
    [(2.53, 0.5), (7.34, 2.0), (22.0, 5.0), (34.89, 10.0), (0.04, 0.01), (400.0, 100.0)],
)
def test_a_quarter_of_the_top_rounded_on_a_1_2_5_ladder(top_mm, step_mm):
    d = np.linspace(0.0, top_mm, 100_001)
    d = d * top_mm / np.percentile(d, 99)  # its 99th percentile is top_mm
    edges = displacement_bins_mm(d)
    assert edges[:4] == pytest.approx((0.0, step_mm, 2 * step_mm, 3 * step_mm), rel=1e-12)
    assert edges[4] == np.inf
    shares = np.histogram(d, bins=np.array(edges[:4] + (d.max() + 1,)))[0] / d.size
    assert (shares > 0).all()  # every bin holds points: no single-bin histogram


def test_nothing_known_or_nothing_moved_is_one_bin():
    assert displacement_bins_mm(np.full(10, np.nan)) == (0.0, np.inf)
    assert displacement_bins_mm(np.zeros(10)) == (0.0, np.inf)
    assert displacement_bins_mm(np.array([])) == (0.0, np.inf)
    assert displacement_bins_mm(np.array([np.nan, 3.0, 4.0]))[1] == pytest.approx(1.0)


def test_a_rim_face_is_coloured_by_its_scored_vertices_only():
    # back-plate vertices carry 0 (unmeasured) in the per-vertex error arrays: averaged
    # in, a rim face with two of them showed a third of its error
    from calib.report.maps import face_error_mm

    faces = np.array([[0, 1, 2], [1, 2, 3]])
    error = np.array([3.0, 0.0, 0.0, -1.0])
    scored = np.array([True, False, False, True])
    assert face_error_mm(error, faces, scored) == pytest.approx([3.0, 1.0], rel=1e-15)
    everything = np.ones(4, bool)
    assert face_error_mm(error, faces, everything) == pytest.approx([1.0, 1.0 / 3.0])


def _square_scan():
    """A flat 2 x 2 grid of vertices, two faces, every vertex scored (reference frame)."""
    v = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 0.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    from types import SimpleNamespace

    return SimpleNamespace(vertices_mm=v, faces=faces, scored=np.ones(4, bool))


def test_the_error_maps_show_the_sign_of_the_error():
    # review AX: every map showed |error|, so a model too stiff (the scan outside) and too
    # soft looked alike. The figure colours a face where the scan lies outside the model
    # (+) red and one inside blue.
    from matplotlib.colors import to_rgba_array
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from calib.report.maps import SIGN_NOTE, face_error_mm, surface_error_figure

    scan = _square_scan()
    error = np.array([1.0, 1.0, 1.0, -1.0])  # face 0 outside (+1), face 1 mostly inside
    faces_e = face_error_mm(error, scan.faces, scan.scored, signed=True)
    assert faces_e == pytest.approx([1.0, 1.0 / 3.0], rel=1e-15)
    assert face_error_mm(-error, scan.faces, scan.scored, signed=True) == pytest.approx(-faces_e)
    fig = surface_error_figure(scan, error, np.eye(3), "t", vmax=1.0)
    flipped = surface_error_figure(scan, -error, np.eye(3), "t", vmax=1.0)
    for f, sign in ((fig, 1.0), (flipped, -1.0)):
        coll = [c for c in f.axes[0].collections if isinstance(c, Poly3DCollection)]
        (rgba,) = (to_rgba_array(c.get_facecolor()) for c in coll)
        red_minus_blue = rgba[:, 0] - rgba[:, 2]
        assert (np.sign(red_minus_blue) == sign).all()  # + (1 and 1/3 mm): red; -: blue
        assert not np.allclose(rgba[0], rgba[1])  # 1 mm and 1/3 mm apart on the scale
    assert SIGN_NOTE in fig.axes[-1].get_ylabel()  # the colour bar says what + means


def test_a_map_s_long_title_stays_inside_its_figure():
    # the validation maps' titles (~130 characters) ran past both edges of the figure:
    # "ht_lateral (calibration, ... colour scale shared by the scan" in make demo's PNG
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from calib.report.maps import surface_error_figure

    title = ("right_lateral (calibration, posture 180°): surface error, mean |e| 0.30 mm "
             "(fiducial registration; colour scale shared by the scans)")  # fmt: skip
    fig = surface_error_figure(_square_scan(), np.zeros(4), np.eye(3), title, vmax=1.0)
    FigureCanvasAgg(fig).draw()
    box = fig._suptitle.get_window_extent()
    assert 0 <= box.x0 and box.x1 <= fig.bbox.x1
    assert fig._suptitle.get_text().replace("\n", " ") == title  # every word kept


def test_the_panels_titles_of_the_diagnosis_maps_do_not_run_into_each_other():
    # the change row's titles (~95 characters each, fontsize 10 on a 5-inch panel) ran
    # into each other in diagnose's residual maps
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from calib.report.diagnosis import residual_maps_figure

    scan = _square_scan()
    fig = residual_maps_figure("s", "diagnosis", scan, np.zeros(4), np.ones(4), np.eye(3), vmax=1.0)
    FigureCanvasAgg(fig).draw()
    row = [ax for ax in fig.axes if "change" in ax.get_title()]
    assert len(row) == 2
    left, right = (ax.title.get_window_extent() for ax in row)
    assert left.x1 <= right.x0, (left, right)
    assert 0 <= left.x0 and right.x1 <= fig.bbox.x1


def test_maps_of_a_scan_with_nothing_scored_are_drawn_not_raised():
    # review BA: with no scored face the scale's percentile of an empty array raised
    # (the notebook's plot_error_map without vmax, diagnose's change row), and the
    # error-by-displacement panel of a scan whose errors are all 0 divided by zero
    from types import SimpleNamespace

    from calib.report.diagnosis import residual_maps_figure
    from calib.report.maps import surface_error_figure
    from calib.report.validation import error_by_displacement_figure

    scan = _square_scan()
    scan.scored = np.zeros(4, bool)
    zero = np.zeros(4)
    surface_error_figure(scan, zero, np.eye(3), "t")
    residual_maps_figure("s", "calibration", scan, zero, zero, np.eye(3), vmax=1.0)
    sv = SimpleNamespace(name="s", role="validation", posture_label="25°",
                         metrics=SimpleNamespace(vertex_error_mm=zero),
                         displacement_mm=np.full(4, np.nan))  # fmt: skip
    fig = error_by_displacement_figure([sv])
    assert fig.axes[0].get_title() == "s (validation): no measured point off the back plate"


def test_errors_beyond_the_shared_axis_are_in_its_last_bin_and_said():
    # review BY, F8: the axis stops at the 99.5th percentile and np.histogram dropped the
    # points beyond it: a panel's bars summed to less than 100 % without a mark
    from types import SimpleNamespace

    from calib.report.validation import error_by_displacement_figure

    err = np.r_[np.linspace(0.01, 1.0, 999), 5.0]  # one point far out
    sv = SimpleNamespace(name="s", role="validation", posture_label="25°",
                         metrics=SimpleNamespace(vertex_error_mm=err),
                         displacement_mm=np.full(err.size, 3.0))  # fmt: skip
    ax = error_by_displacement_figure([sv]).axes[0]
    heights = sum(p.get_height() for p in ax.patches)
    assert heights == pytest.approx(100.0, rel=1e-12)  # every point counted
    top = np.percentile(err, 99.5)  # the shared axis's end
    said = f"the last bin holds the {100 * np.mean(err > top):.1f} % beyond {top:.2f} mm"
    assert ax.get_xlabel().endswith(said) and said == "the last bin holds the 0.5 % beyond 1.00 mm"


def test_the_axis_along_each_view_s_line_of_sight_has_no_ticks():
    # review BY, F9: the hidden axis kept its tick lines, a comb running into the next
    # axis's labels; the visible axes keep at most six ticks (labels ran together)
    from calib.report.maps import surface_error_figure

    scan = _square_scan()
    scan.vertices_mm = scan.vertices_mm * 10.0 + np.array([0.0, 0.0, 1.0]) * np.arange(4)[:, None]
    fig = surface_error_figure(scan, np.zeros(4), np.eye(3), "t")
    front, side = fig.axes[:2]
    assert len(front.zaxis.get_ticklocs()) == 0 and len(side.yaxis.get_ticklocs()) == 0
    for axis in (front.xaxis, front.yaxis, side.xaxis, side.zaxis):
        assert 0 < len(axis.get_ticklocs()) <= 6
