"""Mesh I/O round trips (VTU, Abaqus .inp, TetGen .node/.ele/.face) and bad files."""

from __future__ import annotations

import numpy as np
import pytest
from femtest_meshes import box_mesh

from fem import MeshError, boundary_faces
from fem.io import read_mesh, read_tetgen, read_tetgen_face, write_mesh, write_tetgen


@pytest.fixture
def mesh():
    m = box_mesh((12.0, 8.0, 6.0), (4, 3, 3), jitter=0.3, seed=4)
    region = np.where(m.nodes_mm[m.tets].mean(1)[:, 0] > 6.0, 2, 1)
    m = m.with_regions(region, {"bulk": 1, "inclusion": 2})
    return m.with_node_sets(back=m.node_sets["z0"], nipple=np.array([5]))


def _same(a, b, *, node_sets=True, exact=True):
    if exact:
        assert np.array_equal(a.nodes_mm, b.nodes_mm)  # repr / float64 round trips exactly
    else:
        np.testing.assert_allclose(a.nodes_mm, b.nodes_mm, rtol=1e-15, atol=0)
    assert np.array_equal(a.tets, b.tets)
    assert np.array_equal(a.region, b.region)
    assert dict(a.region_names) == dict(b.region_names)
    if node_sets:
        assert set(a.node_sets) == set(b.node_sets)
        for k in a.node_sets:
            assert np.array_equal(np.sort(a.node_sets[k]), b.node_sets[k])


@pytest.mark.parametrize("suffix", [".vtu", ".inp", ".msh", ".vtk"])
def test_meshio_round_trip(mesh, tmp_path, suffix):
    path = write_mesh(mesh, tmp_path / f"phantom{suffix}")
    back = read_mesh(path)
    _same(mesh, back, node_sets=suffix in (".vtu", ".inp", ".vtk"), exact=suffix != ".msh")
    assert [p.name for p in tmp_path.iterdir()] == [f"phantom{suffix}"]  # no temp files left


def test_vtu_point_and_cell_data(mesh, tmp_path):
    import meshio

    u = np.random.default_rng(0).standard_normal((mesh.n_nodes, 3))
    vol = mesh.volumes_mm3()
    path = write_mesh(
        mesh, tmp_path / "r.vtu", point_data={"displacement_mm": u}, cell_data={"vol": vol}
    )
    m = meshio.read(path)
    assert np.array_equal(m.point_data["displacement_mm"], u)
    assert np.array_equal(m.cell_data["vol"][0], vol)
    assert np.array_equal(np.flatnonzero(m.point_data["set:back"]), np.sort(mesh.node_sets["back"]))
    with pytest.raises(ValueError, match="point data needs"):
        write_mesh(mesh, tmp_path / "bad.vtu", point_data={"u": u[:-1]})
    assert not (tmp_path / "bad.vtu").exists()


@pytest.mark.parametrize("first_index", [0, 1])
def test_tetgen_round_trip_and_face_reader(mesh, tmp_path, first_index):
    files = write_tetgen(mesh, tmp_path / "ph", first_index=first_index)
    assert sorted(p.name for p in files) == ["ph.ele", "ph.face", "ph.node"]
    back = read_tetgen(tmp_path / "ph.node")
    _same(mesh, back, node_sets=False)
    _same(mesh, read_mesh(tmp_path / "ph.ele"), node_sets=False)
    faces, markers = read_tetgen_face(tmp_path / "ph.face")
    assert np.array_equal(faces, boundary_faces(mesh.tets))  # zero-based whatever the file's base
    assert np.all(markers == 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ph.ele", "ph.face", "ph.node"]


def test_tetgen_face_reader_handwritten(tmp_path):
    """A TetGen-style file with comments, 1-based, no markers; base from the .node file."""
    (tmp_path / "t.node").write_text("# nodes\n4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n")
    (tmp_path / "t.face").write_text("4 0  # no markers\n1 2 3 4\n2 1 4 3\n3 1 2 4\n4 1 3 2\n")
    faces, markers = read_tetgen_face(tmp_path / "t.face")
    assert faces.tolist() == [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]
    assert markers.tolist() == [0, 0, 0, 0]
    # 0-based node file with faces numbered from 1: the node file decides
    (tmp_path / "z.node").write_text("4 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n")
    (tmp_path / "z.face").write_text("1 1\n1 1 2 3 7\n")
    faces, markers = read_tetgen_face(tmp_path / "z.face")
    assert faces.tolist() == [[1, 2, 3]] and markers.tolist() == [7]


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.vtu"):
        read_mesh(tmp_path / "nothere.vtu")
    bad = tmp_path / "garbage.vtu"
    bad.write_text("this is not xml")
    with pytest.raises(MeshError, match="garbage.vtu"):
        read_mesh(bad)
    (tmp_path / "b.node").write_text("4 3 0 0\n1 0 0 0\n2 1 0 0\n")  # truncated
    (tmp_path / "b.ele").write_text("1 4 0\n1 1 2 3 4\n")
    with pytest.raises(MeshError, match=r"b\.node.*expected 4 records"):
        read_mesh(tmp_path / "b.node")
    (tmp_path / "e.node").write_text("0 3 0 0\n")
    with pytest.raises(MeshError, match=r"e\.node: expected 3-D nodes, got 0"):
        read_tetgen(tmp_path / "e")
    with pytest.raises(FileNotFoundError, match=r"c\.ele"):
        (tmp_path / "c.node").write_text("1 3 0 0\n1 0 0 0\n")
        read_tetgen(tmp_path / "c")


def test_failed_write_leaves_nothing(mesh, tmp_path):
    target = tmp_path / "out.vtu"
    write_mesh(mesh, target)
    before = target.read_bytes()
    with pytest.raises(ValueError, match=r"out.vtu: cell data needs \d+ rows, got 3"):
        write_mesh(mesh, target, cell_data={"x": np.zeros(3)})  # wrong length
    assert target.read_bytes() == before
    with pytest.raises(ValueError, match="unknown mesh file suffix"):
        write_mesh(mesh, tmp_path / "out.xyz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.vtu"]


def test_read_orients_and_reads_gmsh_tags(tmp_path):
    import meshio

    mesh = box_mesh((4.0, 4.0, 4.0), (2, 2, 2))
    tets = mesh.tets.copy()
    tets[::2] = tets[::2][:, [1, 0, 2, 3]]  # half of them negatively oriented
    tri = boundary_faces(mesh.tets)[:4]
    m = meshio.Mesh(
        mesh.nodes_mm,
        [("triangle", tri), ("tetra", tets)],
        cell_data={"gmsh:physical": [np.full(4, 9), np.full(len(tets), 7)]},
        field_data={"gland": np.array([7, 3]), "skin_surface": np.array([9, 2])},
    )
    m.cell_data["gmsh:geometrical"] = [np.ones(4, int), np.ones(len(tets), int)]
    path = tmp_path / "g.msh"
    meshio.write(path, m, file_format="gmsh22", binary=False)
    back = read_mesh(path)
    assert np.all(back.volumes_mm3() > 0)
    assert dict(back.region_names) == {"gland": 7} and np.all(back.region == 7)
    assert read_mesh(path, orient=False).volumes_mm3().min() < 0


@pytest.mark.parametrize(
    ("tags", "names"),
    [
        ((2, 3), {"region2": 2, "region3": 3}),  # were read as "inclusion" and "skin"
        ((3, 3), {"bulk": 3}),  # MMG's or CGAL's one domain, numbered 3: the bulk
    ],
)
def test_another_tool_s_bare_region_numbers_are_not_the_toolkit_s_names(tmp_path, tags, names):
    # review BU, F11: a VTU's CellEntityIds 2 and 3 without names were told to the user as
    # "its 2 regions (inclusion, skin)"
    import meshio

    mesh = box_mesh((4.0, 4.0, 4.0), (2, 2, 2))
    half = len(mesh.tets) // 2
    ids = np.r_[np.full(half, tags[0]), np.full(len(mesh.tets) - half, tags[1])]
    path = tmp_path / "ids.vtu"
    meshio.write(
        path, meshio.Mesh(mesh.nodes_mm, [("tetra", mesh.tets)], cell_data={"CellEntityIds": [ids]})
    )
    back = read_mesh(path)
    assert dict(back.region_names) == names and np.array_equal(back.region, ids)
