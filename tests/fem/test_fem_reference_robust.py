"""The reference state on a real scan mesh, where the straight-element inverse fails.

Fixture ``data/quick_none_12mm_reference.npz``: the calibration's 12 mm model mesh of the
reference scan of the quick twin with ``--effect none`` (23.7 mm sag; 4729 tets, node
sets ``back``, ``surface``, ``nipple``; the scan's gravity). On it the inverse Newton on
straight stress-free elements (``recover_stress_free(method="newton")``) stalls at load
factor ~0.66-0.8 (see fem/unload.py's docstring); the spatial inverse does not need
straight stress-free elements; MULF reaches g0 but its passes fail there. Regenerate
it with::

    phantom-calib synth OUT --preset quick --seed 0 --effect none
    phantom-calib ingest OUT/scans --out OUT-work
    python tests/fem/test_fem_reference_robust.py --regenerate OUT/scans OUT-work

The solves on it take a minute or more each: ``slow``. The meshing checks are fast.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import fem
from fem.discretize import plane_fit
from fem.meshing import remesh_surface, tag_node_sets, tetrahedralize
from fem.prestress import compute_prestress, node_displacement_mm, round_trip_mm, solve_prestressed
from fem.unload import recover_stress_free

FIXTURE = Path(__file__).with_name("data") / "quick_none_12mm_reference.npz"


def load_fixture() -> tuple[fem.TetMesh, np.ndarray]:
    d = np.load(FIXTURE)
    sets = {k: d[k] for k in ("back", "surface", "nipple")}
    mesh = fem.TetMesh(d["nodes_mm"], d["tets"], np.ones(len(d["tets"]), int), {"bulk": 1}, sets)
    return mesh, d["gravity"]


def _model(mesh, c1_pa=420.0):
    return fem.Model.homogeneous(mesh, fem.NeoHookean(c1_pa, nu=0.499), density_kg_m3=1000.0)


def _plane(mesh):
    """Point and outward unit normal of the back plane of the fixture."""
    back = mesh.node_set("back")
    n, d, _ = plane_fit(mesh.nodes_mm[back])
    if mesh.nodes_mm.mean(axis=0) @ n > d:
        n = -n
    return mesh.nodes_mm[back].mean(axis=0), n


def _remeshed(mesh, size_mm: float | None, max_dihedral_deg: float | None = None):
    """The fixture's boundary surface meshed again (coarser: no volume bound; finer)."""
    faces = fem.boundary_faces(mesh.tets)
    used, inv = np.unique(faces, return_inverse=True)
    v, f = mesh.nodes_mm[used], inv.reshape(-1, 3)
    vol = None if size_mm is None else size_mm**3 / (6.0 * np.sqrt(2.0))
    p0, n = _plane(mesh)
    out = tetrahedralize(
        v, f, max_volume_mm3=vol, size_mm=size_mm or 12.0, max_dihedral_deg=max_dihedral_deg
    )
    bnodes = np.unique(fem.boundary_faces(out.tets))
    back = bnodes[np.abs((out.nodes_mm[bnodes] - p0) @ n) < 1e-6]
    return tag_node_sets(out, back, n)


# -- slow: the solves on the scan mesh ---------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("c1_pa", [420.0, 840.0])
def test_spatial_recovery_on_the_hard_scan_mesh(c1_pa):
    """Succeeds at the scan's own c1 and at twice it (less sag to undo) in 10 load steps."""
    mesh, g = load_fixture()
    model = _model(mesh, c1_pa)
    rec = recover_stress_free(model, gravity=g, method="spatial",
                              options=fem.SolverOptions(max_steps=10))  # fmt: skip
    assert rec.converged and rec.prestress is not None
    # issue 17's bar: the recovered state reloaded from scratch within 0.01 mm
    assert round_trip_mm(model, rec.prestress) <= 0.01


@pytest.mark.slow
def test_spatial_recovery_at_a_softer_c1_fails_loudly():
    """At 0.75 x the scan's c1 the spatial inverse does not reach g0: said, bounded.

    A softer body sags more, so its stress-free shape lies farther from the scan. At
    315 Pa the load stepping stops at load factor 0.922 with 10 load steps (the budget)
    and at 0.928 with 200, where its cut-backs reach the smallest step; at 210 Pa at 0.609
    and 0.619 (this call with ``max_steps`` 10 and 200). The calibration takes such a c1
    as a failed evaluation, or, at its first estimate, stops with remedies
    (``calib.fitting.optimise``); here the error must say how far it got.
    """
    mesh, g = load_fixture()
    model, opts = _model(mesh, 315.0), fem.SolverOptions(max_steps=10)
    with pytest.raises(fem.ConvergenceError, match=r"\(spatial inverse\): stopped at") as info:
        recover_stress_free(model, gravity=g, method="spatial", options=opts)
    assert 0.0 < info.value.load_factor < 1.0 and info.value.iterations > 0


#: The 7 mm remesh's round trip lands on another equilibrium at the clamped rim.
OTHER_EQUILIBRIUM = pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason="the curved stress-free mesh loaded from rest (the whole load cut back, then 3 "
    "load steps) settles 0.035-0.094 mm off the scan at 18 of its 27,422 nodes, all within "
    "0.75 mm of the clamped back, where the recovered state is an equilibrium too "
    "(warm-started: 1e-14 mm); from a tenth of g0 it comes back to 3e-7 mm. The rim's "
    "curved elements (det F0 from 0.25 to 4222) admit more than one equilibrium; README, "
    "Status",
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "size_mm",
    [pytest.param(None, id="coarse"), pytest.param(7.0, id="fine", marks=OTHER_EQUILIBRIUM)],
)
def test_spatial_recovery_on_a_coarse_and_a_fine_mesh(size_mm):
    """The same scan surface meshed coarser (no volume bound) and finer (7 mm elements)."""
    mesh, g = load_fixture()
    mesh = _remeshed(mesh, size_mm)
    model = _model(mesh)
    ps = compute_prestress(model, gravity=g, method="inverse",
                           options=fem.SolverOptions(max_steps=10))  # fmt: skip
    assert round_trip_mm(model, ps) <= 0.01


@pytest.fixture(scope="module")
def recovered_fixture():
    """The fixture at 420 Pa, its gravity and its spatial inverse (recovered once)."""
    mesh, g = load_fixture()
    model = _model(mesh)
    opts = fem.SolverOptions(max_steps=10)
    return model, g, compute_prestress(model, gravity=g, method="inverse", options=opts)


@pytest.mark.slow
@pytest.mark.parametrize("axis, angle_deg", [((1, 0, 0), 25.0), ((0, 0, 1), 90.0)])
def test_a_posture_reaches_one_state_along_any_load_path(recovered_fixture, axis, angle_deg):
    """From the recovered state the whole load change and steps of 1/50 agree.

    The curved stress-free mesh loaded from rest can settle on another equilibrium at
    the rim (the fine case above); a posture is solved on the prestressed loaded mesh,
    starting from the recovered equilibrium instead. Two load paths to the same gravity
    must reach the same state: Newton's tolerance (1e-8 of the load) leaves them 1e-11 to
    3e-9 mm apart (measured here and at -90 degrees, and at 25 degrees on the 7 mm remesh),
    so 1e-6 mm is a bar a branch change cannot pass.
    """
    from scipy.spatial.transform import Rotation

    model, g, ps = recovered_fixture
    g_new = Rotation.from_rotvec(np.radians(angle_deg) * np.asarray(axis, float)).apply(g)
    disc0 = fem.discretize(model.mesh, model.support)
    states = [
        node_displacement_mm(disc0, solve_prestressed(model, ps, gravity=g_new, options=o).state)
        for o in (None, fem.SolverOptions(initial_step=0.02))
    ]
    assert np.linalg.norm(states[0] - states[1], axis=1).max() <= 1e-6


@pytest.mark.slow
def test_mulf_on_the_hard_scan_mesh_fails_loudly():
    """MULF's passes do not settle on this mesh (the rim elements): a bounded, reported failure.

    Gee et al.'s load steps reach g0, but the first passes at full load cannot be solved
    (det F0 at the rim elements' quadrature points spans 0.06-8e3 with 10 load steps);
    the error names the load factor and the iterations. Documented in fem/prestress.py.
    """
    mesh, g = load_fixture()
    model = _model(mesh)
    with pytest.raises(fem.ConvergenceError, match="MULF prestress not converged") as info:
        compute_prestress(model, gravity=g, method="mulf", options=fem.SolverOptions(max_steps=10),
                          max_passes=5)  # fmt: skip
    assert info.value.load_factor == 1.0 and info.value.iterations > 0


# -- fast: the support's node set after a repaired or remeshed surface ------------------


def _self_intersecting(mesh):
    """The fixture's surface with one spike pushed through the opposite side."""
    faces = fem.boundary_faces(mesh.tets)
    used, inv = np.unique(faces, return_inverse=True)
    v, f = mesh.nodes_mm[used].copy(), inv.reshape(-1, 3)
    top = int(np.argmax(v @ -_plane(mesh)[1]))  # the vertex farthest from the back plane
    c = v.mean(axis=0)
    v[top] = c + 2.5 * (c - v[top])  # through the body and out of the back
    return v, f


def test_a_remeshed_surface_keeps_its_back_plane(caplog):
    """TetGen rejects the surface; the remeshed one keeps the plane flat (keep_planes).

    Without it, smoothing moves the back off the plane and the node set found there is
    empty: ``tag_node_sets`` says so (no numpy warning, no support without faces).
    """
    mesh, _ = load_fixture()
    v, f = _self_intersecting(mesh)
    p0, n = _plane(mesh)
    for keep, expect_ok in (([(p0, n, 2.0)], True), ((), False)):
        caplog.clear()  # each pass says it remeshed (the text accumulates: review AA)
        with caplog.at_level("WARNING", logger="fem.meshing"):
            out = tetrahedralize(v, f, max_volume_mm3=12.0**3 / 8.5, size_mm=12.0,
                                 keep_planes=keep)  # fmt: skip
        assert "after it was remeshed" in caplog.text
        bnodes = np.unique(fem.boundary_faces(out.tets))
        back = bnodes[np.abs((out.nodes_mm[bnodes] - p0) @ n) < 1e-6]
        if expect_ok:
            tagged = tag_node_sets(out, back, n)
            fem.discretize(tagged, fem.Clamped())  # the support finds its faces
        else:
            with pytest.raises(fem.MeshError, match="back node set has"):
                tag_node_sets(out, back, n)


def test_remesh_surface_is_watertight():
    mesh, _ = load_fixture()
    v, f = _self_intersecting(mesh)
    rv, rf = remesh_surface(v, f, size_mm=12.0)
    import trimesh

    assert trimesh.Trimesh(rv, rf).is_watertight


def test_a_lower_dihedral_bound_leaves_fewer_slivers():
    """TetGen's optimisation bound on the largest dihedral angle removes slivers.

    The fixture's surface meshed at 12 mm: the ``tetgen`` package's bound (177 degrees)
    leaves tens of slivers (an angle below 5 or above 175 degrees; the inverse Newton's
    failures start at such elements on the clamped rim, fem/unload.py); 165 degrees
    leaves under half as many (``bench_reference.py --max-dihedral`` measures 2.4-13 times
    fewer on the quick twins' reference meshes, so a half is a loose bar). Both meshes
    fill the same closed surface: TetGen splits its facets in their own planes, so the
    volumes agree to round-off (1e-9 relative).
    """
    mesh, _ = load_fixture()
    loose, tight = (_remeshed(mesh, 12.0, bound) for bound in (None, 165.0))
    q_loose, q_tight = fem.mesh_quality(loose), fem.mesh_quality(tight)
    assert q_loose.n_slivers >= 10
    assert q_tight.n_slivers < 0.5 * q_loose.n_slivers
    assert q_tight.max_dihedral_deg < q_loose.max_dihedral_deg
    assert tight.volumes_mm3().sum() == pytest.approx(loose.volumes_mm3().sum(), rel=1e-9)
    with pytest.raises(ValueError, match="max_dihedral_deg must lie in"):
        _remeshed(mesh, 12.0, 200.0)


def _regenerate(scans: str, work: str) -> None:
    try:
        from calib.data.measurements import load_measurements
        from calib.data.session import load_session
        from calib.model.reference import reference_mesh
    except ImportError:
        from calib.measurements import load_measurements
        from calib.refmodel import reference_mesh
        from calib.session import load_session
    ref = load_measurements(work, load_session(scans)).reference
    mesh = reference_mesh(ref, size_mm=12.0)
    FIXTURE.parent.mkdir(exist_ok=True)
    np.savez_compressed(FIXTURE, nodes_mm=mesh.nodes_mm, tets=mesh.tets.astype(np.int32),
                        back=mesh.node_set("back"), surface=mesh.node_set("surface"),
                        nipple=mesh.node_set("nipple"),
                        gravity=np.asarray(ref.gravity_ref, float))  # fmt: skip
    print(f"wrote {FIXTURE} ({FIXTURE.stat().st_size} bytes, {mesh.n_tets} tets)")


if __name__ == "__main__":
    if len(sys.argv) != 4 or sys.argv[1] != "--regenerate":
        sys.exit("usage: python tests/fem/test_fem_reference_robust.py --regenerate SCANS WORK")
    _regenerate(sys.argv[2], sys.argv[3])
