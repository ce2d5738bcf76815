"""The digital twin (``calib.twin.synthesize``): determinism, sealed truth, atomic output."""

from __future__ import annotations

import json
import re
import tomllib

import numpy as np
import pytest
from calib_helpers import SMALL_PRESET, polyhedron_volume_mm3
from typer.testing import CliRunner

import calib.twin.synth
from calib.cli import app
from calib.model.effects import TruthEffects
from calib.twin import synthesize


def _files(folder):
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _pixels(folder):
    import pydicom

    return {
        p.relative_to(folder).as_posix(): pydicom.dcmread(p).PixelData
        for p in sorted(folder.rglob("*.dcm"))
    }


def _truth(out):
    doc = json.loads((out / "truth" / "truth.json").read_text())
    return doc


@pytest.fixture(scope="module")
def twin_a(tmp_path_factory):
    out = tmp_path_factory.mktemp("a") / "twin"
    record = synthesize(out, preset=SMALL_PRESET, seed=3)
    return out, record


def test_layout_and_record(twin_a):
    out, record = twin_a
    assert sorted(p.name for p in out.iterdir()) == ["scans", "truth"]
    assert sorted(p.name for p in (out / "scans").iterdir()) == [
        "left_lateral", "right_lateral", "session.toml"]  # fmt: skip
    assert sorted(p.name for p in (out / "truth").iterdir()) == [
        "left_lateral_surface.ply", "right_lateral_surface.ply", "truth.json"]  # fmt: skip
    truth = json.loads((out / "truth" / "truth.json").read_text())
    assert truth == json.loads(json.dumps(record))
    assert (truth["preset"], truth["seed"]) == ("custom", 3)
    # review BI: a custom preset's settings were not written, nor the commit
    settings = truth["preset_settings"]
    assert settings["spacing_mm"] == list(SMALL_PRESET.spacing_mm)
    assert [p["name"] for p in settings["postures"]] == [p.name for p in SMALL_PRESET.postures]
    assert "effects" not in settings and "source" in truth
    # The preset's default hides the dissertation's skin layer.
    assert truth["effects"]["active"] == ["skin"]
    assert truth["material"] == {"law": "neo-hookean", "c1_pa": 420.0, "c2_pa": 0.0, "nu": 0.499}
    for name, angle in (("left_lateral", 0.0), ("right_lateral", 180.0)):
        scan = truth["scans"][name]
        T = np.asarray(scan["T_scanner_from_phantom"])
        # A rigid pose: orthonormal rotation (round-off) and no reflection.
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        # Gravity in the phantom frame is the scanner's (0, 1, 0) pulled back by the pose...
        np.testing.assert_allclose(scan["gravity_phantom"], T[:3, :3].T @ [0, 1, 0], atol=1e-12)
        # ...and within the pose's tilt (1 deg, calib.postures) of the nominal posture.
        nominal = [np.cos(np.radians(angle)), 0.0, np.sin(np.radians(angle))]
        cos = np.clip(np.dot(scan["gravity_phantom"], nominal), -1, 1)
        assert np.degrees(np.arccos(cos)) <= 1.0 + 1e-9
        # Truth fiducials are the stress-free markers posed in the scanner (round-off).
        free = np.asarray(truth["stress_free"]["fiducials_phantom_mm"])
        np.testing.assert_allclose(scan["fiducials_lps_mm"], free @ T[:3, :3].T + T[:3, 3],
                                   atol=1e-9)  # fmt: skip


def test_same_seed_is_byte_identical(twin_a, tmp_path):
    out_a, _ = twin_a
    out_b = tmp_path / "twin"
    synthesize(out_b, preset=SMALL_PRESET, seed=3)
    files_a, files_b = _files(out_a / "scans"), _files(out_b / "scans")
    assert sorted(files_a) == sorted(files_b)
    assert len([f for f in files_a if f.endswith(".dcm")]) > 20
    different = [f for f in files_a if files_a[f] != files_b[f]]
    assert different == []
    assert _truth(out_a) == _truth(out_b)
    for ply in ("left_lateral_surface.ply", "right_lateral_surface.ply"):
        assert (out_a / "truth" / ply).read_bytes() == (out_b / "truth" / ply).read_bytes()


def test_different_seed_differs(twin_a, tmp_path):
    out_a, rec_a = twin_a
    out_c = tmp_path / "twin"
    # Also exercises the effects override: `none` gives a homogeneous neo-Hookean truth.
    # (Seed 5: another seed than twin_a's 3. Review CG-20: the comment here said seeds 4
    # and 9 fail to mesh, from the first commit's mesher; test_twin_truth_mesh_builds
    # now checks that they build, on the quick preset.)
    rec_c = synthesize(out_c, preset=SMALL_PRESET, seed=5, effects=TruthEffects())
    assert rec_c["effects"]["active"] == []
    for name in ("left_lateral", "right_lateral"):
        T_a = np.asarray(rec_a["scans"][name]["T_scanner_from_phantom"])
        T_c = np.asarray(rec_c["scans"][name]["T_scanner_from_phantom"])
        # Shifts are drawn uniformly in +-30 mm: two seeds agreeing to 1 mm would be a bug.
        assert np.abs(T_a[:3, 3] - T_c[:3, 3]).max() > 1.0
        assert not np.allclose(T_a[:3, :3], T_c[:3, :3])
    pix_a, pix_c = _pixels(out_a / "scans"), _pixels(out_c / "scans")
    common = set(pix_a) & set(pix_c)
    assert common and all(pix_a[f] != pix_c[f] for f in common)


def test_scans_do_not_reveal_the_truth(twin_a):
    import pydicom

    out, record = twin_a
    scans = out / "scans"
    assert not list(scans.rglob("*.json")) and not list(scans.rglob("*.ply"))
    assert {p.suffix for p in scans.rglob("*") if p.is_file()} == {".toml", ".dcm"}
    text = (scans / "session.toml").read_text()
    doc = tomllib.loads(text)
    assert set(doc) == {"source", "scanner", "phantom", "landmarks", "scans"}
    # that they were simulated, and by what, but not with which effects (review BY, F13)
    assert doc["source"]["simulated"] is True and set(doc["source"]) == {"simulated", "generator"}
    # the tracked tumour is named by a rough point (as an experimenter would), not the truth
    truth = json.loads((out / "truth" / "truth.json").read_text())
    ref_truth = truth["scans"]["left_lateral"]["tumour_lps_mm"]
    assert np.linalg.norm(np.subtract(doc["landmarks"]["tumour"], ref_truth)) > 0.3
    assert doc["phantom"] == {"density_kg_m3": 1000.0, "fiducials": 3}
    assert doc["scanner"] == {"gravity": [0.0, 1.0, 0.0]}
    for scan in doc["scans"]:
        assert set(scan) == {"name", "path", "role", "posture"}
        assert set(scan["posture"]) == {"plane", "angle_deg"}
    # Words of the truth record; digits are not searched in DICOM values (UIDs, positions).
    secret = re.compile(r"c1|c2|effect|skin|T_scanner|truth|seed|mooney|hooke", re.IGNORECASE)
    assert not secret.search(text) and "420" not in text, text  # 420 Pa: the true c1
    for name, scan in record["scans"].items():
        T = np.asarray(scan["T_scanner_from_phantom"])
        files = sorted((scans / name).glob("*.dcm"))
        for path in (files[0], files[len(files) // 2], files[-1]):
            ds = pydicom.dcmread(path)
            assert "ImageComments" not in ds and "StudyDescription" not in ds
            assert ds.SeriesDescription == name
            strings = [str(el.value) for el in ds.iterall() if el.keyword != "PixelData"]
            assert not any(secret.search(s) for s in strings), [
                s for s in strings if secret.search(s)
            ]
            # The grid is axis-aligned: its orientation carries nothing of the random pose.
            iop = np.asarray(ds.ImageOrientationPatient, float)
            np.testing.assert_array_equal(iop, [1, 0, 0, 0, 1, 0])
            assert not np.allclose(np.abs(T[:3, :2].T.ravel()), np.abs(iop), atol=1e-3)


@pytest.mark.parametrize("seed", [4, 7, 9])
def test_twin_truth_mesh_builds(seed):
    # The first stage of calib.twin.synth._build for the quick preset and its default skin layer.
    from fem.geometry import PhantomSpec, build_phantom
    from fem.meshing import mesh_phantom

    p = calib.twin.synth.PRESETS["quick"]
    phantom = build_phantom(PhantomSpec(resolution_mm=p.phantom_resolution_mm, seed=seed))
    mesh = mesh_phantom(phantom, size_mm=p.truth_mesh_mm,
                        skin_thickness_mm=p.effects.skin_thickness_mm)  # fmt: skip
    assert len(mesh.node_set("back")) >= 3


def test_an_inclusions_twin_meshes_the_spheres_the_renderer_draws():
    # Stiffer inclusions are meshed as conforming spheres (the icospheres of
    # fem.meshing.mesh_phantom): the inclusion region is their union, its volume theirs
    # to round-off, each element inside one sphere. Tagging elements by centroid made
    # 3875 mm3 of 10 mm elements reaching past the spheres (3451 mm3) on this seed.
    import fem
    from fem.geometry import PhantomSpec, build_phantom, sphere_surface
    from fem.meshing import inclusion_spheres

    p = calib.twin.synth.PRESETS["quick"]
    phantom = build_phantom(PhantomSpec(resolution_mm=p.phantom_resolution_mm, seed=0))
    mesh = calib.twin.synth._truth_mesh(phantom, p, TruthEffects(inclusion_ratio=5.0))
    inside = mesh.region == fem.mesh.REGION_IDS["inclusion"]
    centres, diameters = phantom.inclusion_centres_mm, phantom.inclusion_diameters_mm
    polyhedra = sum(
        polyhedron_volume_mm3(*sphere_surface(c, r, subdivisions=k))
        for c, r, k in inclusion_spheres(phantom)
    )
    assert mesh.volumes_mm3()[inside].sum() == pytest.approx(polyhedra, rel=1e-9)
    node_d = np.linalg.norm(mesh.nodes_mm[mesh.tets[inside]][:, :, None] - centres, axis=3)
    assert np.all(np.any(np.all(node_d <= diameters / 2 * (1 + 1e-9), axis=1), axis=1))
    # inclusions of the bulk's material: the lighter mesh (elements tagged by centroid)
    plain = calib.twin.synth._truth_mesh(phantom, p, TruthEffects())
    assert plain.n_tets < mesh.n_tets / 2


class _Interrupt(RuntimeError):
    pass


def _interrupt_second_render(monkeypatch):
    real, calls = calib.twin.synth._render, []

    def render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise _Interrupt("interrupted on the second posture")
        return real(*args, **kwargs)

    monkeypatch.setattr(calib.twin.synth, "_render", render)
    return calls


def test_interrupted_run_leaves_nothing(tmp_path, monkeypatch):
    calls = _interrupt_second_render(monkeypatch)
    with pytest.raises(_Interrupt):
        synthesize(tmp_path / "twin", preset=SMALL_PRESET, seed=3)
    assert len(calls) == 2  # the first posture was written before the interruption
    assert list(tmp_path.iterdir()) == []  # no OUT, no hidden partial folder


def test_interrupted_overwrite_keeps_the_old_folder(tmp_path, monkeypatch):
    out = tmp_path / "twin"
    (out / "scans").mkdir(parents=True)
    (out / "scans" / "session.toml").write_text("# previous run\n")
    _interrupt_second_render(monkeypatch)
    with pytest.raises(_Interrupt):
        synthesize(out, preset=SMALL_PRESET, seed=3, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["twin"]
    assert (out / "scans" / "session.toml").read_text() == "# previous run\n"


def test_existing_out_without_overwrite(tmp_path):
    out = tmp_path / "twin"
    out.mkdir()
    with pytest.raises(FileExistsError, match="exists"):
        synthesize(out, preset=SMALL_PRESET)
    assert list(out.iterdir()) == []


def test_unknown_preset(tmp_path):
    with pytest.raises(ValueError, match=r"unknown preset 'fast'.*dissertation.*quick"):
        synthesize(tmp_path / "twin", preset="fast")
    assert list(tmp_path.iterdir()) == []


def test_a_custom_preset_is_recorded_as_json_or_refused_before_any_work(tmp_path):
    # review BK: preset_settings were written after every solve, and a NaN or a value JSON
    # cannot hold failed there; numpy numbers are recorded as numbers
    from dataclasses import replace

    from calib.twin.synth import _preset_settings

    p = replace(SMALL_PRESET, c1_pa=np.float64(420.0), spacing_mm=np.array([2.0, 2.0, 2.0]))
    settings = _preset_settings(p)
    assert settings["c1_pa"] == 420.0 and settings["spacing_mm"] == [2.0, 2.0, 2.0]
    with pytest.raises(ValueError, match="a TwinPreset field truth.json cannot record"):
        synthesize(tmp_path / "twin", preset=replace(SMALL_PRESET, snr=float("nan")))
    with pytest.raises(ValueError, match="Path is not a JSON value"):
        synthesize(tmp_path / "twin", preset=replace(SMALL_PRESET, snr=tmp_path))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (["--effect", "wrinkles"], r"unknown effect 'wrinkles'"),
        (["--effect", "poisson=0.6"], r"effect 'poisson': value 0.6 outside the range"),
        (["--effect", "none", "--effect", "skin"], r"'none' cannot be combined"),
    ],
    ids=["unknown-effect", "out-of-range", "none-combined"],
)
def test_cli_synth_bad_options(tmp_path, args, pattern):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "twin"), *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert re.search(pattern, lines[0]), lines[0]
    assert "Traceback" not in result.output
    assert list(tmp_path.iterdir()) == []
