"""``phantom-calib view``: the page in a real headless Chromium against the surrogate.

The browser tests need Debian's ``chromium``; without it they skip, except under CI (the
``CI`` environment variable set), where they fail: CI installs it.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import struct
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))
from sweep_helpers import BOX_C1_PA, make_box_work

from calib.cli import app
from calib.viewer import (
    PortInUseError,
    SurfaceModelMismatchError,
    load_scene,
    make_server,
)
from calib.viewer.headless import HeadlessBrowser, find_chromium

C1_AXIS = (400.0, 640.0)


def _need_chromium():
    if find_chromium() is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing under CI (apt-get install chromium)")
        pytest.skip("chromium is not installed (apt-get install chromium)")


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """A clamped block's work folder, a 24-scenario sweep (c1 axis) and our surrogate, ~3 s."""
    return _box_with_surrogate(tmp_path_factory.mktemp("viewer"))


def _box_with_surrogate(root: Path, R_ref_from_phantom=None):
    import nn
    from calib.workflows.sweep import SweepOptions, run_sweep

    work = make_box_work(root / "work", R_ref_from_phantom=R_ref_from_phantom)
    opts = SweepOptions(
        plan="sphere:12", c1_axis=f"{C1_AXIS[0]}:{C1_AXIS[1]}:2", holdout=0.25, backend="serial"
    )
    run_sweep(work, root / "sweep", opts)
    data = nn.load_sweep(root / "sweep")
    sur = nn.Surrogate.from_fit(nn.fit_reduced_kernel(data, device="cpu"), data)
    model = nn.save_surrogate(sur, root / "model.pt")
    return work, model


class _Serving:
    def __init__(self, scene):
        self.server = make_server(scene, port=0)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self.server

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def browser():
    _need_chromium()
    with HeadlessBrowser(width=1000, height=640) as b:
        yield b


@pytest.fixture
def never_served(monkeypatch):
    """A refusal that regressed would serve forever (the test hung); now it fails."""
    from calib.viewer.server import ViewerServer

    def served(self, *args, **kwargs):
        raise AssertionError("the view was served: it should have been refused first")

    monkeypatch.setattr(ViewerServer, "serve_forever", served)


def _expected_phantom_mm(model: Path, gravity, c1_pa: float) -> np.ndarray:
    """Boundary vertex positions from nn alone (not the viewer's code), phantom frame."""
    import nn
    from fem.mesh import boundary_faces

    sur = nn.load_surrogate(model)
    pred = sur.predict(np.asarray(gravity, float), c1_pa=c1_pa, frame="phantom")
    nodes = np.unique(boundary_faces(sur.mesh.tets))
    x_ref = sur.mesh.nodes_mm + pred.nodes_mm[0]
    return x_ref[nodes] @ sur.R_ref_from_phantom  # x_phantom = R^T x_ref, row vectors


def test_page_follows_the_gravity_and_c1_controls(box, browser, tmp_path):
    work, model = box
    with _Serving(load_scene(work, model)) as server:
        browser.goto(server.url)
        assert browser.evaluate("window.viewer.error") is None
        # review CD-12: the first frame said it was drawn "after the control moved"
        status = browser.evaluate("document.getElementById('status').textContent")
        assert status.startswith("surrogate ours prediction drawn; trained c1 "), status
        # review CD-9: the frame's axes are drawn as the camera turns them; its default
        # puts -z up on the screen (the plate above the breast), as the key says
        z_end = browser.evaluate("document.querySelectorAll('#axes line')[2].getAttribute('y2')")
        assert float(z_end) > 34.0  # +z points down (SVG y grows downwards)
        assert "screen up: −z" in browser.evaluate("document.getElementById('axesbox').innerText")
        n = browser.evaluate("window.viewer.nVertices()")
        # this block's phantom frame is turned against its back face (frame mistakes show,
        # tests/nn/sweep_helpers.py): no plate is drawn, and the page says why
        assert browser.evaluate("window.viewer.plate") is None
        assert "no back plate drawn" in browser.evaluate("document.body.innerText")
        checked = []
        # (transverse angle, tilt, c1 slider position 0..1000) moved as a user would:
        # set the input's value and fire its "input" event
        for a, s, c1pos in [(90.0, 0.0, None), (20.0, 35.0, None), (200.0, -50.0, 800)]:
            js = f"document.getElementById('angle_a').value = {a};"
            js += f"document.getElementById('angle_s').value = {s};"
            if c1pos is not None:
                js += f"document.getElementById('c1').value = {c1pos};"
                js += "document.getElementById('c1').dispatchEvent(new Event('input'));"
            js += "document.getElementById('angle_a').dispatchEvent(new Event('input'));"
            browser.evaluate(js + "window.viewer.settled()")
            last = browser.evaluate("window.viewer.lastFrame")
            # review AX: "control -> frame 332.7 ms" read as a developer's metric
            status = browser.evaluate("document.getElementById('status').textContent")
            assert status.startswith("surrogate prediction drawn ") and status.endswith(
                " ms after the control moved"
            ), status
            g, c1 = np.array(last["gravity"]), last["c1"]
            # the page's gravity is the posture-angle convention of the README's sweeps
            rad_a, rad_s = np.radians(a), np.radians(s)
            g_ref = 9.81 * np.array(
                [np.cos(rad_a) * np.cos(rad_s), np.sin(rad_s), np.sin(rad_a) * np.cos(rad_s)]
            )
            np.testing.assert_allclose(g, g_ref, atol=1e-9)
            if c1pos is None:
                assert c1 == pytest.approx(500.0, rel=1e-12)  # the calibrated c1, exactly
            else:  # log scale over the trained range
                assert c1 == pytest.approx(C1_AXIS[0] * (C1_AXIS[1] / C1_AXIS[0]) ** 0.8)
            expect = _expected_phantom_mm(model, g, c1)
            assert len(expect) == n
            idx = [
                0,
                n // 2,
                n - 1,
                int(np.argmax(np.linalg.norm(expect - expect.mean(0), axis=1))),
            ]
            got = np.array([browser.evaluate(f"window.viewer.readVertex({i})") for i in idx])
            # 1e-3 mm is the bound; what we expect is the float32 rounding of the
            # GPU buffer, 2^-24 |x| <= 6e-6 mm at |x| <= 100 mm, plus the surrogate's float32
            # POD expansion (~1e-6 mm, nn.modules)
            np.testing.assert_allclose(got, expect[idx], atol=1e-3, rtol=0)
            checked.append(got)
        # the controls moved the surface (not a frozen picture): mm-scale differences
        assert np.abs(checked[1] - checked[0]).max() > 0.1
        assert np.abs(checked[2] - checked[1]).max() > 0.1
        shot = browser.screenshot(tmp_path / "view.png")
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size > 5000


def test_the_page_draws_the_back_plate_in_the_plane_of_the_clamped_nodes(tmp_path, browser):
    # review AX: no plate, no scale. A block whose phantom frame has z along its back face's
    # inward normal (as calibrate's frame has, calib.fitting.result.phantom_frame; turned
    # about z only): the plate is a 10 mm grid in the back nodes' plane (review BC: not the
    # body's lowest z, which on make demo's mesh lay 0.46 mm past the plate), wider than
    # the body
    from sweep_helpers import rotation_xyz

    import nn

    work, model = _box_with_surrogate(tmp_path, rotation_xyz((0.0, 0.0, 40.0)))
    scene = load_scene(work, model)
    mesh = nn.load_surrogate(model).mesh
    back_z = (mesh.nodes_mm[mesh.back_nodes] @ scene.R_ref_from_phantom)[:, 2]
    assert np.ptp(back_z) < 1e-9 and scene.info["plate_z_mm"] == pytest.approx(back_z[0])
    rest = scene.rest_mm
    with _Serving(scene) as server:
        browser.goto(server.url)
        assert browser.evaluate("window.viewer.error") is None
        plate = browser.evaluate("window.viewer.plate")
    assert plate["spacing_mm"] == 10
    assert plate["z_mm"] == pytest.approx(scene.info["plate_z_mm"], abs=1e-9)
    for k, key in enumerate(("x_mm", "y_mm")):
        assert plate[key][0] < rest[:, k].min() and plate[key][1] > rest[:, k].max()


def test_a_record_file_given_as_the_work_folder_is_named(tmp_path):
    # review AT: "no such work folder" for WORK/calibration.json, which exists
    record = tmp_path / "calibration.json"
    record.write_text("{}")
    with pytest.raises(FileNotFoundError, match="is a file: pass the work folder"):
        load_scene(record)


def test_page_without_calibration_says_what_is_missing(tmp_path, browser):
    empty = tmp_path / "work"
    empty.mkdir()
    scene = load_scene(empty)
    assert scene.rest_mm is None and scene.predictor is None
    with _Serving(scene) as server:
        browser.goto(server.url)
        assert browser.evaluate("window.viewer.error") is None
        text = browser.evaluate("document.body.innerText")
        assert "calibration.json is missing" in text
        assert "phantom-calib calibrate" in text
        assert "phantom-calib surrogate train" in text
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(server.url + "api/predict?g=0,0,9.81&c1=500")
        assert err.value.code == 404
        err.value.close()


def test_surrogate_without_work_scans_still_views(box):
    work, model = box
    scene = load_scene(work, model)
    assert any("could not be read back" in m and "no `scans`" in m for m in scene.missing)
    with _Serving(scene) as server:
        with urllib.request.urlopen(server.url + "api/predict?g=0,0,9.81&c1=500") as r:
            body = np.frombuffer(r.read(), "<f4")
            assert r.headers["X-Extrapolating"] == "0"
        n = len(scene.rest_mm)
        expect = _expected_phantom_mm(model, [0, 0, 9.81], 500.0)
        # float32 transport: 2^-24 relative of <= 100 mm coordinates
        np.testing.assert_allclose(body[: 3 * n].reshape(n, 3), expect, atol=1e-4, rtol=0)
        # the nipple is a displayed vertex; the tumour follows the surrogate's tumour
        nv = scene.info["landmarks"]["nipple_vertex"]
        np.testing.assert_allclose(body[3 * n : 3 * n + 3], expect[nv], atol=1e-4, rtol=0)
        assert np.all(np.isfinite(body[3 * n + 3 :]))
        # outside the trained c1 range: drawn, and flagged
        with urllib.request.urlopen(server.url + "api/predict?g=0,0,9.81&c1=2000") as r:
            assert r.headers["X-Extrapolating"] == "1"
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(server.url + "api/predict?g=0,9.81&c1=500")
        assert err.value.code == 400 and "X,Y,Z" in json.loads(err.value.read())["error"]
        err.value.close()


def test_port_in_use_names_the_port_and_a_free_one(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(PortInUseError, match=rf"port {port} on 127\.0\.0\.1 is in use") as e:
            make_server(load_scene(tmp_path), port=port)
        free = int(str(e.value).rsplit("--port ", 1)[1])
        assert free != port
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", free))  # the suggestion binds
        res = CliRunner().invoke(app, ["view", str(tmp_path), "--port", str(port)])
        assert res.exit_code == 2
        assert f"port {port}" in res.output and "try --port" in res.output


def test_bad_model_file_is_a_one_line_error(tmp_path, never_served):
    bad = tmp_path / "model.pt"
    bad.write_text("not a model")
    res = CliRunner().invoke(app, ["view", str(tmp_path), "--model", str(bad), "--port", "0"])
    assert res.exit_code == 2 and "not a TorchScript surrogate" in res.output


TILT_DEG = 50.0


def _work_with_scans(root: Path, model: Path) -> tuple[Path, dict]:
    """The block's work folder with two scans written as ``calibrate`` and ``ingest`` do.

    ``tilt_50`` (calibration role) has a measured surface (the surrogate's boundary at its
    posture, shifted 0.4 mm in z), a saved FE state, a known signed error map and a
    ``diagnose`` refit (``diagnosis/refit/``, a work folder) whose saved state *is* the
    measured surface; ``left_lateral`` is the reference scan. Returns the folder and the
    planted values.
    """
    import imaging
    import nn
    from calib.io import RunOutputs
    from calib.report.maps import write_error_ply
    from fem.io import read_mesh, write_mesh
    from fem.mesh import boundary_faces

    work = make_box_work(root / "work")  # the sweep's mesh (deterministic)
    doc = json.loads((work / "calibration.json").read_text())
    doc.pop("run_id")  # the new run's
    mesh = read_mesh(work / "calibration" / "reference_mesh.vtu", orient=False)
    sur = nn.load_surrogate(model)
    R = sur.R_ref_from_phantom
    a = np.radians(TILT_DEG)
    g_ph = {"left_lateral": np.array([1.0, 0, 0]), "tilt_50": np.array([np.cos(a), 0, np.sin(a)])}
    faces = boundary_faces(mesh.tets)
    nodes, inv = np.unique(faces, return_inverse=True)
    faces = inv.reshape(faces.shape)
    u = sur.predict(g_ph["tilt_50"] * 9.81, c1_pa=500.0).nodes_mm[0]
    measured = mesh.nodes_mm[nodes] + u[nodes] + [0.0, 0.0, 0.4]
    error = np.linspace(-2.0, 1.5, len(nodes))  # known signed values
    back = np.isclose(mesh.nodes_mm[nodes][:, 2], 0.0)
    fid = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 40.0, 0.0]])
    for name, g in g_ph.items():
        folder = work / "scans" / name
        folder.mkdir(parents=True)
        ingest = {
            "T_ref_from_scan": np.eye(4).tolist(),
            "back_plane": {"point_lps_mm": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, -1.0]},
            "gravity_ref": (R @ g).tolist(),
            "nipple_lps_mm": measured[
                np.flatnonzero(nodes == doc["model"]["nipple_node"])[0]
            ].tolist(),
            "tumour_lps_mm": [20.0, 20.0, 14.0],
            "fiducials_lps_mm": fid.tolist(),
        }
        (folder / "ingest.json").write_text(json.dumps(ingest))
        surf = imaging.SurfaceMesh(measured, faces, back, {})
        imaging.write_ply(folder / "surface_ref.ply", surf)
    doc["scans"] = {"tilt_50": {"role": "calibration", "model": {"tumour_mm": [20, 20, 14.5]}}}
    with RunOutputs(work, folder="calibration", record="calibration.json") as run:
        write_mesh(mesh, run.path("reference_mesh.vtu"))
        write_mesh(
            mesh.with_nodes(mesh.nodes_mm + u),
            run.path("tilt_50_deformed.vtu"),
            point_data={"displacement_mm": u},
        )
        write_error_ply(run.path("tilt_50_error.ply"), measured, faces, error)
        run_id = run.commit(doc)["run_id"]
    refit = work / "diagnosis" / "refit"  # as calib.workflows.diagnose.write_refit writes it
    shutil.copytree(work / "scans", refit / "scans")
    with RunOutputs(refit, folder="calibration", record="calibration.json") as run:
        write_mesh(mesh, run.path("reference_mesh.vtu"))
        u_after = u + [0.0, 0.0, 0.4]  # the refit's state is the measured surface
        write_mesh(
            mesh.with_nodes(mesh.nodes_mm + u_after),
            run.path("tilt_50_deformed.vtu"),
            point_data={"displacement_mm": u_after},
        )
        run.commit(doc | {"diagnosis": {"calibration_run_id": run_id}})
    planted = {
        "R": R, "g_ph": g_ph, "measured": measured, "error": error, "back": back, "faces": faces,
        "state": (mesh.nodes_mm + u)[nodes], "fiducials": fid,
    }  # fmt: skip
    return work, planted


@pytest.fixture(scope="module")
def scans_work(box, tmp_path_factory):
    return _work_with_scans(tmp_path_factory.mktemp("viewer-scans"), box[1])


def test_scene_reads_scans_states_and_maps_into_the_phantom_frame(scans_work, box):
    work, p = scans_work
    scene = load_scene(work, box[1])
    R = p["R"]
    # the frame: x_phantom = R^T x_ref (row vectors: x @ R); float32 storage, 2^-24 |x|
    ov = scene.overlays["tilt_50"]
    np.testing.assert_allclose(ov["vertices_mm"], p["measured"] @ R, atol=1e-5, rtol=0)
    np.testing.assert_array_equal(ov["error_mm"], p["error"].astype(np.float32))  # <f4 on disk
    # the faces whose error is measured first (the back plate's are drawn grey, not 0 mm)
    whole = ~p["back"][p["faces"]].any(axis=1)
    n = ov["n_scored_faces"]
    assert n == whole.sum() and 0 < n < len(whole)
    assert not p["back"][ov["faces"][:n]].any() and p["back"][ov["faces"][n:]].any(axis=1).all()
    assert {tuple(f) for f in ov["faces"]} == {tuple(f) for f in p["faces"]}
    # after diagnose: its refitted state is the measured surface, so the error measured
    # as calibrate measures it is 0 (float32 storage of <= 100 mm coordinates: 1e-5 mm)
    np.testing.assert_allclose(ov["error_after_mm"], 0.0, atol=1e-5)
    pos, nipple, tumour = scene.states["tilt_50"]
    np.testing.assert_allclose(pos, p["state"] @ R, atol=1e-5, rtol=0)
    np.testing.assert_allclose(tumour, np.array([20, 20, 14.5]) @ R, atol=1e-12)
    scans = {s["name"]: s for s in scene.info["scans"]}
    assert scans["left_lateral"]["role"] == "reference"
    np.testing.assert_allclose(
        scans["tilt_50"]["gravity_phantom_m_s2"], 9.81 * p["g_ph"]["tilt_50"], atol=1e-12
    )
    assert scans["tilt_50"]["maps"] == ["error_mm", "error_after_mm"]
    np.testing.assert_allclose(scene.info["landmarks"]["fiducials_mm"], p["fiducials"] @ R)
    assert not any("diagnos" in m for m in scene.missing)


def test_a_diagnosis_of_an_earlier_calibration_is_not_shown(scans_work, box, tmp_path):
    # calibrate does not remove WORK/diagnosis/: its refit's maps were shown beside the new
    # calibration's error map, on one scale, as if they were its "after"
    work = tmp_path / "work"
    shutil.copytree(scans_work[0], work)
    refit = work / "diagnosis" / "refit" / "calibration.json"
    doc = json.loads(refit.read_text())
    doc["diagnosis"]["calibration_run_id"] = "20260101T000000.000000Z-1"
    refit.write_text(json.dumps(doc))
    scene = load_scene(work, box[1])
    assert "error_after_mm" not in scene.overlays["tilt_50"]
    assert any("is of an earlier calibration (run 20260101T000000" in m for m in scene.missing)


def test_an_unknown_scan_is_refused_before_a_port_is_opened(scans_work, never_served):
    # it was a note on the page, and --screenshot saved the default view and exited 0
    res = CliRunner().invoke(app, ["view", str(scans_work[0]), "--scan", "tilt_25", "--port", "0"])
    assert res.exit_code == 2
    assert "--scan 'tilt_25': no such scan" in res.output and "tilt_50" in res.output


def test_view_options_are_checked_before_the_page(tmp_path, monkeypatch, never_served):
    # review AG: --scan on a folder without calibrated scans exited 0; a --screenshot path
    # was checked only after chromium had run; a bad $CHROMIUM did not name it
    from calib.viewer.headless import BrowserError, HeadlessBrowser

    res = CliRunner().invoke(app, ["view", str(tmp_path), "--scan", "foo", "--port", "0"])
    assert res.exit_code == 2 and "--scan 'foo': no such scan" in res.output
    assert "it has no calibrated scans" in res.output
    for shot, says in (("shot.jpg", "a .png file"), ("nowhere/shot.png", "an existing folder")):
        args = ["view", str(tmp_path), "--port", "0", "--screenshot", str(tmp_path / shot)]
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and says in res.output, res.output
    # review AX: a folder with nothing to draw (no calibration, no surrogate) saved an
    # empty page and exited 0
    args = ["view", str(tmp_path), "--port", "0", "--screenshot", str(tmp_path / "s.png")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--screenshot: nothing to draw in" in res.output
    assert "this folder has no calibration" in res.output and not (tmp_path / "s.png").exists()
    monkeypatch.setenv("CHROMIUM", str(tmp_path / "no-chromium"))
    with pytest.raises(BrowserError, match=r"cannot start .*no-chromium \(\$CHROMIUM\)"):
        HeadlessBrowser().__enter__()


def test_page_at_a_scan_posture_shows_its_error_map(scans_work, box, browser, tmp_path):
    work, p = scans_work
    with _Serving(load_scene(work, box[1])) as server:
        browser.goto(server.url + "?scan=tilt_50")
        assert browser.evaluate("window.viewer.error") is None
        last = browser.evaluate("window.viewer.lastFrame")
        # the scan's own gravity, not the slider's rounding of it
        np.testing.assert_allclose(last["gravity"], 9.81 * p["g_ph"]["tilt_50"], atol=1e-12)
        expect = _expected_phantom_mm(box[1], last["gravity"], 500.0)
        got = np.array(browser.evaluate("window.viewer.readVertex(5)"))
        np.testing.assert_allclose(got, expect[5], atol=1e-3, rtol=0)  # as in the first test
        assert browser.evaluate("document.getElementById('overlay').value") == "error_mm"
        label = browser.evaluate("document.getElementById('bar').innerText")
        # the colour scale: 99th percentile of |error| over the vertices of the scored
        # faces (off the back plate; the planted errors there are not 0, and counted, gave
        # another scale)
        scored = np.unique(p["faces"][~p["back"][p["faces"]].any(axis=1)])
        e = np.sort(np.abs(p["error"].astype(np.float32)[scored]))
        p99 = e[int(0.99 * (len(e) - 1))]
        e_all = np.sort(np.abs(p["error"].astype(np.float32)))
        assert f"{e_all[int(0.99 * (len(e_all) - 1))]:.2f}" != f"{p99:.2f}"
        assert f"+{p99:.2f} mm: the scan" in label and f"−{p99:.2f} mm: inside" in label
        browser.evaluate(
            "document.getElementById('overlay').value = 'error_after_mm';"
            "document.getElementById('overlay').dispatchEvent(new Event('change'))"
        )
        label = browser.evaluate("document.getElementById('bar').innerText")
        assert f"{p99:.2f} mm" in label and "after diagnose's refit" in label  # one scale
        browser.screenshot(tmp_path / "scan.png")


def test_a_scan_without_the_map_asked_for_shows_its_surface_not_zeros(scans_work, box, browser):
    # review AG: the reference (no FE state, so no error map) in map mode was painted as
    # 0 mm everywhere under the previous scan's colour bar
    work, _ = scans_work
    with _Serving(load_scene(work, box[1])) as server:
        browser.goto(server.url + "?scan=left_lateral&overlay=error_mm")
        assert browser.evaluate("window.viewer.error") is None
        assert browser.evaluate("document.getElementById('bar').style.display") == "none"
        warn = browser.evaluate("document.getElementById('warn').textContent")
        assert "no error map for this scan" in warn and "its measured surface shown" in warn


def test_page_without_surrogate_shows_the_saved_fe_states(scans_work, browser):
    work, p = scans_work
    scene = load_scene(work)
    assert any("no surrogate" in m and "surrogate train" in m for m in scene.missing)
    with _Serving(scene) as server:
        browser.goto(server.url + "?scan=tilt_50")
        assert browser.evaluate("document.getElementById('angle_a').disabled")
        n = browser.evaluate("window.viewer.nVertices()")
        got = np.array([browser.evaluate(f"window.viewer.readVertex({i})") for i in range(n)])
        # the FE state calibrate saved (float32 of <= 100 mm coordinates)
        np.testing.assert_allclose(got, p["state"] @ p["R"], atol=1e-4, rtol=0)
        # review AG: the free view is the stress-free shape, and no longer says "prone"
        browser.goto(server.url)
        text = browser.evaluate("document.getElementById('gvec').textContent")
        assert "stress-free shape (no gravity)" in text
        # review AX: the disabled slider's 90° read as the shape's posture
        assert browser.evaluate("document.getElementById('a_val').textContent") == "–"
        browser.goto(server.url + "?scan=left_lateral")  # the reference: no saved state
        status = browser.evaluate("document.getElementById('status').textContent")
        assert "left_lateral: no saved FE state" in status


def test_surrogate_of_another_mesh_is_refused(box, tmp_path, never_served):
    other = make_box_work(tmp_path / "other", shift_mm=1.0)  # same block, moved 1 mm
    with pytest.raises(SurfaceModelMismatchError, match="reference_mesh.vtu"):
        load_scene(other, box[1])
    res = CliRunner().invoke(app, ["view", str(other), "--model", str(box[1]), "--port", "0"])
    assert res.exit_code == 2 and "train it from a sweep of this work folder" in res.output


def test_a_surrogate_of_an_earlier_calibration_is_said(box, tmp_path):
    # review AG: only the mesh was compared; the c1 slider started at the surrogate's c1
    stiffer = make_box_work(tmp_path / "stiffer", c1_pa=2 * BOX_C1_PA)  # the same mesh
    scene = load_scene(stiffer, box[1])
    assert any("was swept from a calibration at c1" in m for m in scene.missing)
    assert scene.info["model"]["c1_pa"] == pytest.approx(2 * BOX_C1_PA, rel=1e-12)
    assert not any("was swept from" in m for m in load_scene(box[0], box[1]).missing)


def test_the_view_never_writes_into_work(scans_work, box):
    work, _ = scans_work

    def snapshot():
        return {(str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in work.rglob("*")}

    before = snapshot()
    scene = load_scene(work, box[1])
    with _Serving(scene) as server:
        for path in ("", "api/scene", "api/surface", "api/overlay/tilt_50", "api/state/tilt_50"):
            with urllib.request.urlopen(server.url + path) as r:
                assert r.status == 200
    assert snapshot() == before


def test_an_unknown_scan_is_refused_before_its_taken_port(scans_work, never_served):
    # review CD-8: with --port 0 the order was not tested; on a taken port the --scan
    # error comes first, not the port's
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = str(taken.getsockname()[1])
        res = CliRunner().invoke(app, ["view", str(scans_work[0]), "--scan", "x", "--port", port])
    assert res.exit_code == 2 and "--scan 'x': no such scan" in res.output, res.output
    assert "in use" not in res.output


def test_a_port_browsers_refuse_is_refused_first(tmp_path, never_served):
    # review CD-3: --port 22 served, and the browser (and --screenshot, after 30 s) could
    # not load the page
    res = CliRunner().invoke(app, ["view", str(tmp_path), "--port", "22"])
    assert res.exit_code == 2
    assert res.output.startswith("error: --port 22: browsers refuse to load pages"), res.output


def test_corrupt_or_mismatched_files_in_work_are_named_not_a_traceback(
    scans_work, box, tmp_path, never_served
):
    from calib.data.work import read_work

    # review CD-2: a truncated error map was a traceback, a truncated FE state ended the
    # command through meshio's sys.exit (exit 1, "Couldn't read file"); review CD-5: a
    # missing or mismatched map was dropped without a word; review CD-4: --scan hid why
    # the folder had no scans
    def copy(name):
        work = tmp_path / name
        shutil.copytree(scans_work[0], work)
        return work, work / "calibration"

    work, cal = copy("truncated_map")
    data = (cal / "tilt_50_error.ply").read_bytes()
    (cal / "tilt_50_error.ply").write_bytes(data[: len(data) // 2])
    scene = load_scene(work, box[1])
    assert "error_mm" not in scene.overlays["tilt_50"]
    assert any("tilt_50_error.ply: not a readable error map" in m for m in scene.missing)

    work, cal = copy("no_map")
    (cal / "tilt_50_error.ply").unlink()
    scene = load_scene(work, box[1])
    assert any("tilt_50_error.ply is missing: tilt_50 is shown without" in m for m in scene.missing)

    work, cal = copy("other_map")
    from calib.report.maps import write_error_ply

    vertices = scans_work[1]["measured"][:3]
    write_error_ply(cal / "tilt_50_error.ply", vertices, np.array([[0, 1, 2]]), np.zeros(3))
    scene = load_scene(work, box[1])
    assert any("has 3 values of `error_mm`" in m for m in scene.missing), scene.missing

    # review CD-6: one unreadable FE state hid every scan; now only its state is left out
    work, cal = copy("truncated_state")
    data = (cal / "tilt_50_deformed.vtu").read_bytes()
    (cal / "tilt_50_deformed.vtu").write_bytes(data[: len(data) // 3])
    scene = load_scene(work)
    assert {s["name"] for s in scene.info["scans"]} == {"left_lateral", "tilt_50"}
    assert "tilt_50" not in scene.states and "error_mm" in scene.overlays["tilt_50"]
    said = [m for m in scene.missing if "tilt_50_deformed.vtu: not a readable mesh" in m]
    assert said and said[0].endswith("its scan is shown without its FE state"), scene.missing
    with pytest.raises(ValueError, match="tilt_50_deformed.vtu: not a readable mesh"):
        read_work(work)  # without the view's list, the folder is refused as before

    work, _ = copy("broken_record")
    (work / "calibration.json").write_text("{")
    res = CliRunner().invoke(app, ["view", str(work), "--scan", "tilt_50"])
    assert res.exit_code == 2 and "it has no calibrated scans (" in res.output, res.output
    assert "calibration.json" in res.output.split("it has no calibrated scans", 1)[1]


def test_a_screenshot_is_saved_and_a_failed_page_is_not(scans_work, box, tmp_path):
    # review CD-1: a page that failed (no WebGL2) was saved and the command exited 0;
    # review CD-3: a screenshot took port 8050, and failed where a view held it
    _need_chromium()
    work, _ = scans_work
    shot = tmp_path / "ok.png"
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:
        try:
            held.bind(("127.0.0.1", 8050))
            held.listen()
        except OSError:
            pass  # taken already: the screenshot must not need it either way
        args = ["view", str(work), "--model", str(box[1]), "--scan", "tilt_50"]
        res = CliRunner().invoke(app, [*args, "--screenshot", str(shot)])
    assert res.exit_code == 0, res.output
    assert f"wrote {shot}" in res.output and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # review CE-1: the page is the size asked for (the window's 1300 x 900 gave 1300 x 757)
    assert struct.unpack(">II", shot.read_bytes()[16:24]) == (1300, 900)
    no_webgl = tmp_path / "chromium-no-webgl"
    no_webgl.write_text(
        f'#!/bin/sh\nexec "{find_chromium()}" "$@" --disable-webgl --disable-3d-apis\n'
    )
    no_webgl.chmod(0o755)
    failed = tmp_path / "failed.png"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CHROMIUM", str(no_webgl))
        res = CliRunner().invoke(app, [*args, "--screenshot", str(failed)])
    assert res.exit_code == 2, res.output
    assert "the page failed, nothing saved" in res.output and "WebGL2" in res.output
    assert not failed.exists()
