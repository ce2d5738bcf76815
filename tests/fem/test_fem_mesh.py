"""Phantom geometry, meshing, surface repair and back-plane detection."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fem import MeshError, boundary_faces, mesh_quality
from fem.geometry import PhantomSpec, build_phantom, sphere_surface
from fem.meshing import find_back_plane, mesh_phantom, tetrahedralize


@pytest.fixture(scope="module")
def phantom():
    return build_phantom()  # the default CIRS-073-like phantom, 19 inclusions


@pytest.fixture(scope="module")
def coarse_mesh():
    return mesh_phantom(build_phantom(PhantomSpec(resolution_mm=12, n_inclusions=0)), size_mm=12)


def test_phantom_surface_is_watertight_and_outward(phantom):
    import trimesh

    m = trimesh.Trimesh(phantom.vertices_mm, phantom.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward normals give a positive enclosed volume
    lo, hi = phantom.vertices_mm.min(0), phantom.vertices_mm.max(0)
    # about 120 x 80 mm at the base and 70 mm deep (+ nipple, +- irregularity 6 %, tilt)
    assert 100 < hi[0] - lo[0] < 150 and 65 < hi[1] - lo[1] < 100
    assert 60 < hi[2] < 90 and lo[2] == 0.0


def test_phantom_is_deterministic_in_its_seed(phantom):
    again = build_phantom()
    other = build_phantom(PhantomSpec(seed=1))
    for name in ("vertices_mm", "faces", "inclusion_centres_mm", "fiducials_mm"):
        assert np.array_equal(getattr(phantom, name), getattr(again, name))
    n = min(len(phantom.vertices_mm), len(other.vertices_mm))
    assert not np.allclose(phantom.vertices_mm[:n], other.vertices_mm[:n])
    assert not np.allclose(phantom.inclusion_centres_mm, other.inclusion_centres_mm)


def test_inclusions_inside_and_apart(phantom):
    import open3d as o3d

    c, d = phantom.inclusion_centres_mm, phantom.inclusion_diameters_mm
    assert len(c) == 19 and 0 <= phantom.tracked_inclusion < 19
    assert d.min() >= 3.0 and d.max() <= 10.0
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(phantom.vertices_mm.astype(np.float32)),
        o3d.core.Tensor(phantom.faces.astype(np.uint32)),
    )
    sd = scene.compute_signed_distance(o3d.core.Tensor(c.astype(np.float32))).numpy()
    assert np.all(-sd > d / 2)  # open3d: negative inside; each sphere wholly inside
    for i, j in itertools.combinations(range(len(c)), 2):
        assert np.linalg.norm(c[i] - c[j]) > (d[i] + d[j]) / 2


def test_fiducials_non_collinear_distinct_distances(phantom):
    f = phantom.fiducials_mm
    assert np.allclose(f[:, 2], 0.0)  # on the back plate
    area = np.linalg.norm(np.cross(f[1] - f[0], f[2] - f[0])) / 2
    assert area > 100.0  # mm^2: clearly non-collinear
    dist = np.sort([np.linalg.norm(f[i] - f[j]) for i, j in ((0, 1), (0, 2), (1, 2))])
    assert np.diff(dist).min() > 1.0  # distinct to well above MRI voxel size (~1 mm)


def test_mesh_phantom_quality_and_node_sets(coarse_mesh):
    mesh = coarse_mesh
    assert np.all(mesh.volumes_mm3() > 0)
    q = mesh_quality(mesh)
    assert q.n_inverted == 0 and q.min_volume_mm3 > 0
    back = mesh.node_set("back")
    assert len(back) >= 3 and np.allclose(mesh.nodes_mm[back, 2], 0.0)
    assert np.all(mesh.nodes_mm[mesh.node_set("surface"), 2] > 0)
    nipple = mesh.node_set("nipple")
    assert len(nipple) == 1 and mesh.nodes_mm[nipple[0], 2] == mesh.nodes_mm[:, 2].max()
    # the tets fill the surface's volume: TetGen keeps the boundary, splitting facets
    # in their planes to its own tolerance (measured 2.4e-7 relative)
    import trimesh

    ph = build_phantom(PhantomSpec(resolution_mm=12, n_inclusions=0))
    vol = trimesh.Trimesh(ph.vertices_mm, ph.faces, process=False).volume
    assert mesh.volumes_mm3().sum() == pytest.approx(vol, rel=1e-6)


def test_a_mesh_pickles_with_its_tags_and_sets_read_only(coarse_mesh):
    # a process pool, Dask or a saved notebook session carries meshes (calibrations hold
    # them): the read-only mapping views did not pickle
    import pickle
    from types import MappingProxyType

    mesh = coarse_mesh.with_node_sets(extra=np.array([0, 2]))
    again = pickle.loads(pickle.dumps(mesh))
    assert np.array_equal(again.nodes_mm, mesh.nodes_mm)
    assert np.array_equal(again.tets, mesh.tets) and np.array_equal(again.region, mesh.region)
    assert dict(again.region_names) == dict(mesh.region_names)
    assert sorted(again.node_sets) == sorted(mesh.node_sets)
    assert all(np.array_equal(again.node_sets[k], v) for k, v in mesh.node_sets.items())
    assert isinstance(again.node_sets, MappingProxyType)
    assert isinstance(again.region_names, MappingProxyType)


_PUSHED_SPHERE = """
import sys, numpy as np
from fem.geometry import sphere_surface
from fem.meshing import tetrahedralize
v, f = sphere_surface([0.0, 0.0, 0.0], 20.0, subdivisions=3)
v = v.copy()
top = np.argsort(-v[:, 2])[:4]  # a few vertices at the north pole ...
v[top, 2] = -24.0  # ... pushed through the south side: a self-intersecting surface
mesh = tetrahedralize(v, f, size_mm=4.0)
print(mesh.volumes_mm3().sum(), (mesh.volumes_mm3() <= 0).sum())
"""


def test_tetrahedralize_repairs_self_intersecting_surface(tmp_path):
    """Run in a child process: a crash in TetGen must not take the test session down."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    # run in tmp_path: TetGen drops _skipped.node/.face debug files in the working folder
    proc = subprocess.run(
        [sys.executable, "-c", _PUSHED_SPHERE],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"meshing crashed (rc {proc.returncode}): {proc.stderr[-300:]}"
    volume, n_inverted = proc.stdout.split()[-2:]
    ball = 4 / 3 * np.pi * 20.0**3
    # The pushed cap turns into a thin cone through the ball; the remeshed solid (inside =
    # majority of ray-parity votes) loses that cone, ~ pi r^2 h / 3 with r ~ 6 mm (ring of
    # moved vertices) and h ~ 44 mm, i.e. ~1.7e3 mm^3 or 5 % of the ball: allow 10 %,
    # and require that something was lost (the spike is not kept as solid).
    assert 0.90 * ball < float(volume) < ball
    assert int(n_inverted) == 0


def test_find_back_plane_of_dome_and_none_on_sphere():
    v, f = sphere_surface([0.0, 0.0, 0.0], 20.0, subdivisions=3)
    sphere = tetrahedralize(v, f)
    with pytest.raises(MeshError, match="no flat back face"):
        find_back_plane(sphere)
    keep = v[:, 2] > -1e-9
    v_dome = v.copy()
    v_dome[~keep, 2] = 0.0  # squash the lower half onto z = 0: a dome on a flat base
    dome = tetrahedralize(v_dome, f)
    nodes, normal, offset = find_back_plane(dome)
    np.testing.assert_allclose(normal, [0.0, 0.0, -1.0], atol=1e-9)  # planar to round-off
    assert offset == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(dome.nodes_mm[nodes, 2], 0.0)
    # every node of the flat base, and no other (review AA: it was "90 % of them")
    np.testing.assert_array_equal(
        np.sort(nodes), np.flatnonzero(np.abs(dome.nodes_mm[:, 2]) < 1e-9)
    )


def test_find_back_plane_takes_a_bowed_base_whole():
    # review BU: the group of the seed triangle's plane, never refitted, took a patch of a
    # base bowed within the tolerance (0.1 mm over 80 mm: 71 of 114 nodes clamped, the
    # rest free, 5.6 times the displacement); a sagitta of 0.06 mm over this 40 mm base
    # (the tolerance: 2e-3 of the 40 mm extent, 0.08 mm) took 213 of its 407 nodes
    v, f = sphere_surface([0.0, 0.0, 0.0], 20.0, subdivisions=3)
    base = v[:, 2] <= 1e-9
    v[base, 2] = -0.06 * (1.0 - (v[base, 0] ** 2 + v[base, 1] ** 2) / 400.0)
    dome = tetrahedralize(v, f)
    nodes, normal, _ = find_back_plane(dome)
    boundary = np.unique(boundary_faces(dome.tets))
    np.testing.assert_array_equal(np.sort(nodes), boundary[dome.nodes_mm[boundary, 2] <= 1e-9])
    assert normal[2] < -0.9999


def test_find_back_plane_refuses_two_faces_of_one_area():
    # review BU: a box's base or its top was clamped by the order of its elements, and
    # RESULT.json did not say which
    from femtest_meshes import box_mesh

    box = box_mesh((80.0, 60.0, 40.0), (4, 3, 2))
    with pytest.raises(MeshError, match=r"two flat faces of nearly the same area.*--back-plane"):
        find_back_plane(box)
    x = box.nodes_mm.copy()
    bump = np.sin(np.pi * x[:, 0] / 80.0) * np.sin(np.pi * x[:, 1] / 60.0)
    x[:, 2] += 8.0 * bump * x[:, 2] / 40.0  # a domed top: the base is the one flat face
    nodes, normal, _ = find_back_plane(box.with_nodes(x))
    np.testing.assert_allclose(normal, [0.0, 0.0, -1.0], atol=1e-9)
    np.testing.assert_array_equal(nodes, np.flatnonzero(x[:, 2] == 0.0))


@pytest.mark.parametrize("n", [9, 13])
def test_skin_band_volume_by_element_fractions(n):
    """Sum of (skin fraction x element volume) against the exact band volume of a box.

    Box 40 x 40 x 20 mm on its z = 0 back face: the points within t of the other five
    faces fill V - (40 - 2t)^2 (20 - t). Fractions sampled at 64 sub-tet centroids
    (a midpoint rule on a cut element, error O(1/4) of the cut elements' share) and
    rounded to 1/20 measured 0.1-0.3 % here on 5 and 3.3 mm elements; 1 % bound.
    """
    from femtest_meshes import box_mesh

    from fem.meshing import _skin_regions, skin_fraction

    t = 3.0
    mesh = box_mesh((40.0, 40.0, 20.0), (n, n, (n + 1) // 2), jitter=0.2, seed=1)
    tagged = _skin_regions(mesh, t, mesh.node_set("z0"))
    vol = tagged.volumes_mm3()
    frac_of_tag = {tag: skin_fraction(name) or 0.0 for name, tag in tagged.region_names.items()}
    band = sum(frac_of_tag[tag] * vol[tagged.region == tag].sum() for tag in frac_of_tag)
    exact = 40.0 * 40.0 * 20.0 - (40.0 - 2 * t) ** 2 * (20.0 - t)
    assert band == pytest.approx(exact, rel=0.01)
    assert {n for n in tagged.region_names if n.startswith("skin:")}  # partial elements exist


def test_tetgen_debug_files_are_not_left_in_the_working_directory(tmp_path, monkeypatch):
    # TetGen writes _skipped.face/_skipped.node into the cwd when it skips input faces;
    # a fake TetGen that does so must leave the folder as it found it: a file of that
    # name that was there before is not deleted (TetGen itself overwrites it)
    import sys
    import types

    from fem import meshing

    class FakeTetGen:
        def __init__(self, v, f):
            self.v = v

        def add_region(self, *a):
            pass

        def tetrahedralize(self, **kw):
            for name in ("_skipped.face", "_skipped.node"):
                (tmp_path / name).write_text("0\n")
            tets = np.array([[0, 1, 2, 3]])
            return self.v[:4], tets, np.zeros((1, 1)), None

    monkeypatch.setitem(sys.modules, "tetgen", types.SimpleNamespace(TetGen=FakeTetGen))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "_skipped.node").write_text("mine\n")
    v = np.eye(4, 3)
    meshing._tetgen(v, np.array([[0, 1, 2]]), None, 1.5, 10.0, ())
    assert not (tmp_path / "_skipped.face").exists()
    assert (tmp_path / "_skipped.node").exists()
