"""``phantom-calib simulate`` writes its result in the input file's point numbering.

The reader drops points no tetrahedron uses and the mid-side nodes of quadratic
tetrahedra (simulate solves those at their edges' midpoints), and numbers the rest anew;
RESULT.vtu used to hold that reduced list, so a node-by-node comparison with another FE
code was off by an index shift (audit item 3).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.cli import app

CORNERS = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [10.0, 10.0, 30.0]])
ORPHAN = [50.0, 50.0, 50.0]
#: meshio's tetra10 edge order: (0,1), (1,2), (0,2), (0,3), (1,3), (2,3)
EDGES = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]


def _write(path: Path, points, cells) -> Path:
    import meshio

    meshio.write(path, meshio.Mesh(np.asarray(points, float), cells))
    return path


def _simulate(mesh: Path, out: Path) -> dict:
    args = ["simulate", str(mesh), "--c1", "420", "--gravity", "1,0,0", "--out", str(out)]
    res = CliRunner().invoke(app, [*args, "--back-plane", "z=0"])
    assert res.exit_code == 0, res.output
    return json.loads(out.with_suffix(".json").read_text())


@pytest.fixture(scope="module")
def four(tmp_path_factory):
    """The solve of the bare 4-node, 1-tet mesh."""
    import meshio

    d = tmp_path_factory.mktemp("four")
    summary = _simulate(_write(d / "four.vtu", CORNERS, [("tetra", [[0, 1, 2, 3]])]), d / "R.vtu")
    return meshio.read(d / "R.vtu"), summary


def test_an_orphan_point_keeps_its_place(four, tmp_path, caplog):
    import meshio

    m4, s4 = four
    u4 = m4.point_data["displacement_mm"]
    assert np.abs(u4[3]).max() > 0.1  # the apex moves: a real solve to compare with
    points = np.vstack([ORPHAN, CORNERS])  # the orphan first: every other index shifts
    mesh = _write(tmp_path / "five.vtu", points, [("tetra", [[1, 2, 3, 4]])])
    with caplog.at_level(logging.WARNING, logger="calib.workflows.simulate"):
        s5 = _simulate(mesh, tmp_path / "R.vtu")
    m5 = meshio.read(tmp_path / "R.vtu")
    u5 = m5.point_data["displacement_mm"]
    assert m5.points.shape == (5, 3) and u5.shape == (5, 3)
    assert np.all(np.isnan(u5[0])) and np.array_equal(m5.points[0], ORPHAN)
    np.testing.assert_allclose(u5[1:], u4, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m5.points[1:], m4.points, rtol=0, atol=1e-12)
    assert np.array_equal(m5.cells_dict["tetra"], m4.cells_dict["tetra"] + 1)
    assert s5["nipple_node"] == s4["nipple_node"] + 1 == 4  # the apex, in the file's numbering
    assert (s5["points"], s5["unsolved_points"]) == (5, 1)
    assert (s4["points"], s4["unsolved_points"]) == (4, 0)
    assert s5["max_displacement_mm"] == pytest.approx(s4["max_displacement_mm"], rel=1e-12)
    assert any("1 of its 5 points" in r.getMessage() for r in caplog.records)


def test_mid_side_nodes_of_quadratic_tets_are_solved_at_their_edges(four, tmp_path):
    # review BU, F14: they were NaN (documented), though taylor-hood solves every edge's
    # midpoint; tests/calib/test_simulate_user_meshes.py checks the values on a larger mesh
    import meshio

    m4, _ = four
    mids = np.array([(CORNERS[a] + CORNERS[b]) / 2 for a, b in EDGES])
    mesh = _write(tmp_path / "quad.vtu", np.vstack([CORNERS, mids]), [("tetra10", [range(10)])])
    s = _simulate(mesh, tmp_path / "R.vtu")
    m = meshio.read(tmp_path / "R.vtu")
    u = m.point_data["displacement_mm"]
    assert u.shape == (10, 3) and (s["points"], s["unsolved_points"]) == (10, 0)
    np.testing.assert_allclose(u[:4], m4.point_data["displacement_mm"], rtol=0, atol=1e-12)
    on_back = [i for i, (a, b) in enumerate(EDGES) if a < 3 and b < 3]  # the clamped face's
    assert np.all(u[4:][on_back] == 0.0) and np.abs(u[4:]).max() > 0.01  # the others move
    np.testing.assert_allclose(m.points[4:], mids + u[4:], rtol=0, atol=1e-12)
