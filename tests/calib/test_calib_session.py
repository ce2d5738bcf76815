"""session.toml loading and validation, ``scaffold_session`` and ``phantom-calib init``."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from calib_helpers import VALID_TOML, make_scan_folder
from typer.testing import CliRunner

from calib.cli import app
from calib.data.session import SessionError, load_session, scaffold_session


def test_valid_session_loads(tmp_path):
    folder = make_scan_folder(tmp_path / "scans")
    s = load_session(folder)
    assert s.folder == folder.resolve()
    # gravity [0, 2, 0] is normalised to a unit vector (exact in floating point).
    np.testing.assert_array_equal(s.gravity_scanner, [0.0, 1.0, 0.0])
    assert s.density_kg_m3 == 1050.0
    assert s.expected_fiducials == 4
    np.testing.assert_array_equal(s.tumour_hint_lps_mm, [12.0, -30.5, 40.2])
    assert [e.name for e in s.scans] == ["left", "right", "tilt"]
    assert s.reference.name == "left"
    assert [e.name for e in s.by_role("calibration")] == ["right"]
    assert [e.name for e in s.by_role("validation")] == ["tilt"]
    assert s.scans[1].path == (folder / "right.nii.gz").resolve()
    assert s.scans[1].path.is_absolute()
    assert (s.scans[0].posture_plane, s.scans[0].posture_angle_deg) == ("transverse", 0.0)
    assert s.scans[1].posture_angle_deg == 180  # an integer angle is accepted
    assert (s.scans[2].posture_plane, s.scans[2].posture_angle_deg) == (None, None)


def test_defaults_and_oblique_gravity_normalised(tmp_path):
    toml = VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", "gravity = [3.0, 0.0, -4.0]")
    toml = toml.replace("density_kg_m3 = 1050.0\n", "").replace("fiducials = 4\n", "")
    toml = toml.replace("[landmarks]\ntumour = [12.0, -30.5, 40.2]\n", "")
    s = load_session(make_scan_folder(tmp_path, toml))
    # |(3, 0, -4)| = 5: closed form, to round-off.
    np.testing.assert_allclose(s.gravity_scanner, [0.6, 0.0, -0.8], rtol=0, atol=1e-15)
    assert (s.density_kg_m3, s.expected_fiducials, s.tumour_hint_lps_mm) == (1000.0, 3, None)


def test_default_gravity_when_scanner_table_absent(tmp_path):
    toml = VALID_TOML.replace("[scanner]\ngravity = [0.0, 2.0, 0.0]\n", "")
    s = load_session(make_scan_folder(tmp_path, toml))
    np.testing.assert_array_equal(s.gravity_scanner, [0.0, 1.0, 0.0])


def test_missing_session_toml(tmp_path):
    folder = make_scan_folder(tmp_path / "scans", toml=None)
    with pytest.raises(SessionError, match="no session.toml") as err:
        load_session(folder)
    assert str(folder.resolve()) in str(err.value)


def _scan_block(name: str, path: str, role: str) -> str:
    return f'[[scans]]\nname = "{name}"\npath = "{path}"\nrole = "{role}"\n'


_HEAD = VALID_TOML.split("[[scans]]")[0]

# (id, session.toml text, regex the message must match)
BAD_SESSIONS = [
    ("toml-syntax", VALID_TOML.replace('name = "left"', 'name = "left'), r"not valid TOML"),
    ("no-scans", _HEAD, r"no \[\[scans\]\]"),
    (
        "unknown-role",
        VALID_TOML.replace('role = "validation"', 'role = "validate"'),
        r"#3: role must be one of .*'validate'",
    ),
    (
        "zero-references",
        VALID_TOML.replace('role = "reference"', 'role = "calibration"'),
        r"exactly one scan must have role 'reference', found none",
    ),
    (
        "two-references",
        VALID_TOML.replace('role = "validation"', 'role = "reference"'),
        r"exactly one .*reference.*found left \(#1\), tilt \(#3\)$",  # review BG: entries
    ),
    (
        "duplicate-names",
        VALID_TOML.replace('name = "tilt"', 'name = "left"'),
        r"duplicate scan name\(s\) left in \[\[scans\]\] #1, #3 \(",
    ),
    (  # review AC: one folder of the work folder on a case-insensitive file system
        "names-differing-in-case",
        VALID_TOML.replace('name = "tilt"', 'name = "Left"'),
        r"duplicate scan name\(s\) Left, left in \[\[scans\]\] #1, #3 \(names are compared "
        "without case",
    ),
    (  # review BG: 720 was accepted and matched no posture
        "posture-angle-out-of-range",
        VALID_TOML.replace("angle_deg = 180", "angle_deg = 540"),
        r"#2: posture.angle_deg must lie in \[-360, 360\] degrees, got 540",
    ),
    (
        "missing-scan-path",
        VALID_TOML.replace('path = "tilt"', 'path = "no_such_series"'),
        r"#3 \(tilt\): scan path .*no_such_series does not exist",
    ),
    (
        "gravity-two-numbers",
        VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", "gravity = [0.0, 1.0]"),
        r"scanner.gravity must be a list of 3 numbers",
    ),
    (
        "gravity-not-a-list",
        VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", 'gravity = "down"'),
        r"scanner.gravity must be a list of 3 numbers, got 'down'",
    ),
    (
        "gravity-zero",
        VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", "gravity = [0.0, 0.0, 0.0]"),
        r"scanner.gravity must be non-zero",
    ),
    (
        "gravity-overflows",  # review AC: normalised to zeros
        VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", "gravity = [1e308, 1e308, 0.0]"),
        r"scanner.gravity must be non-zero and of finite length",
    ),
    (
        "gravity-nan",
        VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", "gravity = [0.0, nan, 0.0]"),
        r"scanner.gravity must be a list of 3 numbers",
    ),
    (
        # review AY: an integer beyond a float's range was a bare TypeError (np.isfinite)
        "tumour-huge-integer",
        VALID_TOML.replace("tumour = [12.0, -30.5, 40.2]", "tumour = [12, -30, " + "9" * 400 + "]"),
        r"landmarks.tumour must be a list of 3 numbers",
    ),
    (
        "tumour-malformed",
        VALID_TOML.replace("tumour = [12.0, -30.5, 40.2]", "tumour = [[12.0, -30.5, 40.2]]"),
        r"landmarks.tumour must be a list of 3 numbers",
    ),
    (
        "density-negative",
        VALID_TOML.replace("density_kg_m3 = 1050.0", "density_kg_m3 = -1.0"),
        r"phantom.density_kg_m3 must lie in \[500, 3000\] kg/m\^3 .*, got -1.0",
    ),
    (
        "density-in-g-per-cm3",  # review AI: c1 scales with the density (1.0: c1 / 1000)
        VALID_TOML.replace("density_kg_m3 = 1050.0", "density_kg_m3 = 1.05"),
        r"phantom.density_kg_m3 must lie in \[500, 3000\] kg/m\^3 \(a tissue phantom's; 1.0 "
        r"would be g/cm\^3\), got 1.05",
    ),
    (
        "density-string",
        VALID_TOML.replace("density_kg_m3 = 1050.0", 'density_kg_m3 = "1000"'),
        r"phantom.density_kg_m3 must lie in .*, got '1000'",
    ),
    (
        "fiducials-two",
        VALID_TOML.replace("fiducials = 4", "fiducials = 2"),
        r"phantom.fiducials must be an integer from 3 to 7 .*, got 2",
    ),
    (
        "fiducials-float",
        VALID_TOML.replace("fiducials = 4", "fiducials = 3.5"),
        r"phantom.fiducials must be an integer from 3 to 7 .*, got 3.5",
    ),
    (
        # review AW: 8 markers were refused by the registration after every scan had been
        # segmented (registration.rigid.MAX_AUTO_MARKERS: every ordering is fitted)
        "fiducials-eight",
        VALID_TOML.replace("fiducials = 4", "fiducials = 8"),
        r"phantom.fiducials must be an integer from 3 to 7 \(the markers are matched .*got 8",
    ),
    (
        "scanner-not-a-table",
        VALID_TOML.replace("[scanner]\ngravity = [0.0, 2.0, 0.0]\n", 'scanner = "1.5T"\n'),
        r"\[scanner\] must be a table",
    ),
    (
        "unknown-scan-key",
        VALID_TOML.replace('role = "validation"', 'role = "validation"\nangle = 25'),
        r"#3: unknown key\(s\) angle; expected name, path, role, posture",
    ),
    (
        "empty-name",
        VALID_TOML.replace('name = "tilt"', 'name = ""'),
        r"#3: 'name' must be a non-empty string, got ''",
    ),
    (
        "missing-role",
        VALID_TOML.replace('role = "validation"\n', ""),
        r"#3: 'role' is missing \(a non-empty string\)",  # review BG: said "must be"
    ),
    (
        # review BG: a file that is not a volume was refused only when ingest read it,
        # after the scans before it, without naming session.toml or the entry
        "path-not-a-volume",
        VALID_TOML.replace('path = "right.nii.gz"', 'path = "session.toml"'),
        r"#2 \(right\): path 'session.toml' is not a volume file: expected a DICOM series "
        r"folder or a \.nii, \.nii\.gz, \.nrrd, \.nhdr, \.mha, \.mhd file",
    ),
    (
        "path-a-dicom-file",
        VALID_TOML.replace('path = "left"', 'path = "left/IM00001.dcm"'),
        r"#1 \(left\): path 'left/IM00001.dcm' is a single DICOM file: point path at its "
        "series folder",
    ),
    (
        "posture-angle-string",
        VALID_TOML.replace("angle_deg = 180", 'angle_deg = "180"'),
        r"#2: posture.angle_deg must be a number, got '180'",
    ),
    (
        "name-climbs-out",
        VALID_TOML.replace('name = "tilt"', 'name = "../../evil"'),
        r"#3: name '../../evil' must start with a letter or digit",
    ),
    (
        "name-with-a-slash",
        VALID_TOML.replace('name = "tilt"', 'name = "tilt/25"'),
        r"#3: name 'tilt/25' must start .* only letters, digits",
    ),
    (
        # review AW: ingest stages WORK/scans/<name>/ and then writes the run marker
        # WORK/scans/RUN over it (on a case-insensitive file system for "run" too)
        "name-of-the-run-marker",
        VALID_TOML.replace('name = "tilt"', 'name = "Run"'),
        r"#3: name 'Run' is taken by the run marker in WORK/scans/",
    ),
    (
        "name-with-a-space",
        VALID_TOML.replace('name = "tilt"', 'name = "tilt 25"'),
        r"#3: name 'tilt 25' must",
    ),
    (
        "posture-plane-coronal",
        VALID_TOML.replace(
            'plane = "transverse", angle_deg = 180', 'plane = "coronal", angle_deg = 180'
        ),
        r"#2: posture.plane must be one of transverse, sagittal, got 'coronal'",
    ),
    (
        # review CG-9: the posture's key checks had no test
        "posture-angle-typo",
        VALID_TOML.replace("angle_deg = 180", "angle = 180"),
        r"#2: unknown posture key\(s\) angle; expected plane, angle_deg",
    ),
    (
        "fiducials-true",
        VALID_TOML.replace("fiducials = 4", "fiducials = true"),
        r"phantom.fiducials must be an integer from 3 to 7 .*, got True",
    ),
    (
        "scans-entry-not-a-table",
        'scans = ["left", "right"]\n' + VALID_TOML[: VALID_TOML.index("[[scans]]")],
        r"\[\[scans\]\] #1 must be a table",
    ),
    (
        "posture-not-a-table",
        VALID_TOML.replace('posture = { plane = "transverse", angle_deg = 180 }', "posture = 180"),
        r"#2: posture must be an inline table",
    ),
]


@pytest.mark.parametrize(
    ("toml", "pattern"), [b[1:] for b in BAD_SESSIONS], ids=[b[0] for b in BAD_SESSIONS]
)
def test_bad_session_names_file_and_problem(tmp_path, toml, pattern):
    folder = make_scan_folder(tmp_path / "scans", toml)
    with pytest.raises(SessionError) as err:
        load_session(folder)
    message = str(err.value)
    assert str(folder.resolve() / "session.toml") in message
    assert re.search(pattern, message), message
    assert "\n" not in message.split(": not valid TOML")[0]  # one line up to the parser's text


def test_a_byte_order_mark_is_read_and_other_encodings_are_refused(tmp_path):
    folder = make_scan_folder(tmp_path / "scans", VALID_TOML)
    toml = folder / "session.toml"
    toml.write_bytes(b"\xef\xbb\xbf" + VALID_TOML.encode())  # as Windows editors save UTF-8
    assert [s.name for s in load_session(folder).scans] == ["left", "right", "tilt"]
    toml.write_bytes(
        VALID_TOML.replace('name = "tilt"', 'name = "tilt"  # r\u00e9p\u00e9t\u00e9').encode(
            "latin-1"
        )
    )
    with pytest.raises(SessionError, match=r"session.toml: not UTF-8 text \(byte \d+\)"):
        load_session(folder)


def test_session_error_is_a_value_error():
    assert issubclass(SessionError, ValueError)


def test_gravity_with_a_string_component(tmp_path):
    toml = VALID_TOML.replace("gravity = [0.0, 2.0, 0.0]", 'gravity = ["a", 1.0, 0.0]')
    folder = make_scan_folder(tmp_path / "scans", toml)
    with pytest.raises(SessionError, match=r"session.toml: scanner.gravity must be a list"):
        load_session(folder)


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_non_finite_density(tmp_path, value):
    toml = VALID_TOML.replace("density_kg_m3 = 1050.0", f"density_kg_m3 = {value}")
    # review CG-12: the file, the key, the range and the value (it matched the key only)
    with pytest.raises(SessionError, match=rf"session\.toml: phantom\.density_kg_m3 must lie in "
                       rf"\[500, 3000\] kg/m\^3 .*got {value}$"):  # fmt: skip
        load_session(make_scan_folder(tmp_path / "scans", toml))


@pytest.mark.parametrize(
    ("old", "new", "said"),
    [
        ("fiducials = 4", "fiducial = 4",
         r"unknown key\(s\) fiducial in \[phantom\]; expected density_kg_m3, fiducials"),
        ("[landmarks]", "[landmark]",
         r"unknown table\(s\) landmark; expected landmarks, phantom, scanner, scans, source"),
    ],
    ids=["phantom-key", "top-level-table"],
)  # fmt: skip
def test_unknown_key_outside_scans(tmp_path, old, new, said):
    toml = VALID_TOML.replace(old, new)
    with pytest.raises(SessionError, match=rf"session\.toml: {said}"):  # review CG-12
        load_session(make_scan_folder(tmp_path / "scans", toml))


def test_the_source_table_says_whether_the_scans_were_simulated(tmp_path):
    # review BY, F13: reports set a twin's figures beside the dissertation's MRI ones
    # without a word that its scans were simulated; [source] says so (optional)
    assert load_session(make_scan_folder(tmp_path / "plain")).source == {}
    toml = '[source]\nsimulated = true\ngenerator = "another FE code, v2"\n' + VALID_TOML
    s = load_session(make_scan_folder(tmp_path / "simulated", toml))
    assert s.source == {"simulated": True, "generator": "another FE code, v2"}
    for bad, pattern in [
        ('simulated = "yes"', r"source\.simulated must be true or false.*got 'yes'"),
        ("simulated = 1", r"source\.simulated must be true or false.*got 1"),
        ('generator = ""', r"source\.generator must be one line of text of 1 to 200"),
        (f'generator = "{"x" * 201}"', r"source\.generator must be one line"),
        ('generator = "a\\nb"', r"source\.generator must be one line"),
        ("simulate = true", r"unknown key\(s\) simulate in \[source\]"),
    ]:
        folder = make_scan_folder(tmp_path / f"bad{len(bad)}", f"[source]\n{bad}\n" + VALID_TOML)
        with pytest.raises(SessionError, match=pattern):
            load_session(folder)


def test_the_twin_s_session_says_its_scans_were_simulated_and_hides_its_effect():
    from calib.twin.synth import PRESETS, _session_toml

    text = _session_toml(PRESETS["quick"], "quick", np.array([1.0, 2.0, 3.0]))
    source = tomllib.loads(text)["source"]
    assert source["simulated"] is True and source["generator"].endswith("synth, preset quick")
    assert "skin" not in text and "effect" not in text  # the diagnosis is tested blind


# --- scaffold_session and `phantom-calib init` ------------------------------------------------


def _bare_folder(tmp_path):
    folder = make_scan_folder(tmp_path / "scans", toml=None)
    (folder / "empty_dir").mkdir()  # no files: not a series
    (folder / "notes.txt").write_text("not a volume")
    (folder / "extra.mha").write_bytes(b"placeholder")
    return folder


def test_scaffold_finds_series_and_volumes_and_loads(tmp_path):
    folder = _bare_folder(tmp_path)
    path = scaffold_session(folder)
    assert path == folder / "session.toml"
    s = load_session(folder)
    names = {e.name: e for e in s.scans}
    assert set(names) == {"extra", "left", "right", "tilt"}
    assert names["right"].path == (folder / "right.nii.gz").resolve()
    assert names["left"].path == (folder / "left").resolve()
    assert len(s.by_role("reference")) == 1
    assert len(s.by_role("calibration")) == 3
    np.testing.assert_array_equal(s.gravity_scanner, [0.0, 1.0, 0.0])
    assert not list(folder.glob(".session*"))  # no temporary file left behind


def test_scaffold_refuses_to_overwrite(tmp_path):
    folder = _bare_folder(tmp_path)
    (folder / "session.toml").write_text("# mine\n")
    with pytest.raises(SessionError, match=r"session.toml exists"):
        scaffold_session(folder)
    assert (folder / "session.toml").read_text() == "# mine\n"
    scaffold_session(folder, overwrite=True)
    assert len(load_session(folder).scans) == 4


def test_scaffold_empty_folder(tmp_path):
    with pytest.raises(SessionError, match="no DICOM series folders or volume files"):
        scaffold_session(tmp_path)
    assert not (tmp_path / "session.toml").exists()


def test_scaffold_refuses_a_work_folder(tmp_path):
    # review AC: pointed at WORK, init listed its calibration/, scans/, validation/ as series
    for name in ("calibration", "validation"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "RUN").write_text("{}")
    (tmp_path / "scans" / "left").mkdir(parents=True)
    (tmp_path / "scans" / "left" / "ingest.json").write_text("{}")
    with pytest.raises(SessionError, match="is a work folder"):
        scaffold_session(tmp_path)
    assert not (tmp_path / "session.toml").exists()
    with pytest.raises(SessionError, match="this is a work folder: pass the scan folder"):
        load_session(tmp_path)
    # review AX: the work folder's scans/ (its per-scan results became series) and a
    # twin's OUT (its scans/ and its sealed truth/ became two series) were accepted
    with pytest.raises(SessionError, match=r"is a work folder's scans/ \(ingest's results\)"):
        scaffold_session(tmp_path / "scans")
    with pytest.raises(SessionError, match="this is a work folder's scans/"):
        load_session(tmp_path / "scans")
    assert not (tmp_path / "scans" / "session.toml").exists()
    twin = _bare_folder(tmp_path / "T")
    scaffold_session(twin)
    (tmp_path / "T" / "truth").mkdir()
    (tmp_path / "T" / "truth" / "truth.json").write_text("{}")
    with pytest.raises(SessionError, match=r"T/scans holds a session.toml: pass that folder"):
        scaffold_session(tmp_path / "T")
    with pytest.raises(SessionError, match=r"no session.toml \(did you mean .*T/scans\?"):
        load_session(tmp_path / "T")


def test_cli_init(tmp_path):
    folder = _bare_folder(tmp_path)
    runner = CliRunner()
    result = runner.invoke(app, ["init", str(folder)])
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output
    assert len(load_session(folder).scans) == 4
    # what to edit is said in the file (review AX: no posture, nor what the roles mean)
    text = (folder / "session.toml").read_text()
    assert text.startswith("# written by `phantom-calib init`") and "# posture = {" in text
    again = runner.invoke(app, ["init", str(folder)])
    assert again.exit_code == 2
    assert "error:" in again.stderr and "session.toml exists" in again.stderr
    assert runner.invoke(app, ["init", str(folder), "--overwrite"]).exit_code == 0


def test_cli_init_missing_folder(tmp_path):
    result = CliRunner().invoke(app, ["init", str(tmp_path / "nowhere")])
    assert result.exit_code == 2
    assert "nowhere" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_scaffold_names_are_valid_scan_names(tmp_path):
    (tmp_path / "left lateral (1).nii.gz").write_bytes(b"placeholder")
    (tmp_path / "_25deg.mha").write_bytes(b"placeholder")
    scaffold_session(tmp_path)
    assert [s.name for s in load_session(tmp_path).scans] == ["25deg", "left_lateral__1_"]


def test_scaffold_result_loads_when_stems_collide(tmp_path):
    (tmp_path / "a.nii.gz").write_bytes(b"placeholder")
    (tmp_path / "a.mha").write_bytes(b"placeholder")
    (tmp_path / "RUN.nrrd").write_bytes(b"placeholder")  # the run marker's name is taken
    scaffold_session(tmp_path)
    assert sorted(s.name for s in load_session(tmp_path).scans) == ["RUN_2", "a", "a_2"]


def test_calibrate_without_a_calibration_scan_stops_before_ingest(tmp_path):
    from calib.fitting import CalibrationOptions
    from calib.workflows.calibrate import run_calibration

    toml = VALID_TOML.replace('role = "calibration"', 'role = "validation"')
    folder = make_scan_folder(tmp_path / "scans", toml)
    work = tmp_path / "work"
    with pytest.raises(SessionError, match=r"session.toml: no scan has role 'calibration'"):
        run_calibration(folder, work, CalibrationOptions())
    assert not (work / "scans").exists()  # nothing ingested


@pytest.mark.parametrize("command", ["ingest", "calibrate"])
def test_an_output_folder_holding_the_scans_is_refused_before_it_deletes_them(tmp_path, command):
    # review AC: `ingest T/scans --out T` ran, then committed T/scans (its results' folder)
    # over the scan data: session.toml and every series deleted, exit 0
    scans = make_scan_folder(tmp_path / "T" / "scans")
    before = sorted(p.relative_to(scans) for p in scans.rglob("*"))
    for out, says in ((tmp_path / "T", "holds the scan data"), (scans, "is the scan data")):
        result = CliRunner().invoke(app, [command, str(scans), "--out", str(out)])
        assert result.exit_code == 2, result.output
        assert says in result.stderr and "choose an output folder outside it" in result.stderr
        assert sorted(p.relative_to(scans) for p in scans.rglob("*")) == before
    # a scan's series inside --out, the session elsewhere: refused as well
    series = tmp_path / "W" / "left"
    series.mkdir(parents=True)
    (series / "IM00001.dcm").write_bytes(b"placeholder")
    toml = (scans / "session.toml").read_text().replace('path = "left"', f'path = "{series}"')
    assert toml != (scans / "session.toml").read_text()
    (scans / "session.toml").write_text(toml)
    result = CliRunner().invoke(app, [command, str(scans), "--out", str(tmp_path / "W")])
    assert result.exit_code == 2 and f"holds the scan data {series}" in result.stderr


def test_scaffold_skips_hidden_folders_and_two_scans_of_one_series_are_said(tmp_path, caplog):
    # review AC: a hidden folder (sorted first) became the reference; two scans reading
    # one series (no deformation between them) were accepted without a word
    folder = make_scan_folder(tmp_path / "scans", toml=None)
    (folder / ".cache").mkdir()
    (folder / ".cache" / "x.bin").write_bytes(b"placeholder")
    session = load_session(scaffold_session(folder).parent)
    assert ".cache" not in [s.name for s in session.scans]
    toml = VALID_TOML.replace('path = "tilt"', 'path = "left"')
    assert toml != VALID_TOML
    (folder / "session.toml").write_text(toml)
    with caplog.at_level("WARNING", logger="calib.data.session"):
        load_session(folder)
    assert "read the same data" in caplog.text and "'left', 'tilt'" in caplog.text


def test_a_marker_count_unlike_the_session_s_names_its_key(tmp_path, monkeypatch):
    # review AX: "found 3 fiducial markers, expected 4" did not say where 4 came from
    from types import SimpleNamespace

    import imaging
    from calib.data import ingest

    def found_three(volume, expected_fiducials):
        raise imaging.FiducialError(
            f"s.nii: found 3 fiducial markers, expected {expected_fiducials}"
        )

    monkeypatch.setattr(imaging, "read_volume", lambda path: None)
    monkeypatch.setattr(imaging, "process_scan", found_three)
    session = SimpleNamespace(folder=tmp_path, expected_fiducials=4)
    says = r"expected 4 \(the count expected is .*session.toml's \[phantom\] fiducials = 4"
    with pytest.raises(imaging.FiducialError, match=says):
        ingest._process(SimpleNamespace(path=tmp_path / "s.nii"), session, print)


def test_the_session_s_volume_suffixes_are_the_readers():
    # session.toml's paths are checked against the formats imaging reads (kept apart so
    # that reading a session does not import imaging)
    from calib.data.session import VOLUME_SUFFIXES
    from imaging.dicom import VOLUME_FILE_SUFFIXES

    assert VOLUME_SUFFIXES == VOLUME_FILE_SUFFIXES


def test_the_ingest_fingerprint_survives_moving_the_scan_folder():
    # review BG: a scan folder moved or copied elsewhere was "session.toml changed";
    # review BH: a scan outside the session's folder keeps its absolute path, so moving
    # the session alone does not change it either
    from calib.data.session import ScanEntry, Session

    def session(folder: str, outside: str = "/data/right.nii.gz") -> Session:
        scans = (
            ScanEntry("left", Path(folder) / "left", "reference", "transverse", 0.0),
            ScanEntry("right", Path(outside), "calibration", "transverse", 180.0),
        )
        return Session(Path(folder), np.array([0.0, 1.0, 0.0]), 1000.0, 3, None, scans)

    here, there = session("/scans/a"), session("/elsewhere/b/scans")
    assert here.ingest_fingerprint() == there.ingest_fingerprint()
    assert here.ingest_fingerprint(paths="absolute") != there.ingest_fingerprint(paths="absolute")
    # the scan outside enters as it is: another one is another session
    assert session("/scans/a", "/data/other.nii.gz").ingest_fingerprint() != (
        here.ingest_fingerprint()
    )
