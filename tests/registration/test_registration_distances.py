import numpy as np
import pytest
import trimesh
from conftest import perturbation

from registration import (
    RegistrationError,
    apply_transform,
    closest_point_distances,
    hausdorff_mm,
    landmark_errors,
    nipple_error,
    point_to_surface_distances,
    summarise,
    surface_errors,
)

R_IN, R_OUT = 50.0, 53.0


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=R_IN)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    # largest gap between the polyhedron and the true sphere: r minus the smallest distance
    # of a face plane from the centre (~0.01 mm here)
    n = mesh.face_normals
    sag = R_IN - np.min(np.einsum("ij,ij->i", n, v[f[:, 0]]))
    return v, f, sag


def _directions(n, seed):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_concentric_spheres_point_to_surface(sphere):
    v, f, sag = sphere
    u = _directions(2000, 0)
    outside = point_to_surface_distances(R_OUT * u, v, f)
    inside = point_to_surface_distances((2 * R_IN - R_OUT) * u, v, f)
    # true answer +-3 mm; the polyhedron lies within `sag` inside the sphere, plus float32
    # ray-casting round-off (~1e-5 mm at 50 mm)
    tol = sag + 1e-4
    np.testing.assert_allclose(outside, R_OUT - R_IN, atol=tol)
    np.testing.assert_allclose(inside, -(R_OUT - R_IN), atol=tol)
    unsigned = point_to_surface_distances((2 * R_IN - R_OUT) * u, v, f, signed=False)
    np.testing.assert_allclose(unsigned, -inside, rtol=0, atol=1e-12)


def test_concentric_spheres_point_to_point_and_hausdorff(sphere):
    v, _, _ = sphere
    outer = v * (R_OUT / R_IN)  # the same directions on the outer sphere
    d, idx = closest_point_distances(outer, v, return_index=True)
    # the closest point on a concentric sphere lies along the same ray: exactly 3 mm
    np.testing.assert_allclose(d, R_OUT - R_IN, atol=1e-9)
    np.testing.assert_array_equal(idx, np.arange(len(v)))
    assert hausdorff_mm(outer, v) == pytest.approx(R_OUT - R_IN, abs=1e-9)
    # one stray point 20 mm outside raises the symmetric Hausdorff distance to 20 mm
    stray = np.r_[v, [[0.0, 0.0, R_IN + 20.0]]]
    assert hausdorff_mm(stray, v) == pytest.approx(20.0, abs=1e-9)
    assert hausdorff_mm(v, stray) == pytest.approx(20.0, abs=1e-9)


def test_offset_planes():
    g = np.linspace(-50, 50, 21)  # 21 x 21 grid, 5 mm spacing, in the plane z = 0
    X, Y = np.meshgrid(g, g)
    verts = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    i = np.arange(20)
    a = (i[:, None] * 21 + i[None, :]).ravel()
    faces = np.r_[np.c_[a, a + 1, a + 22], np.c_[a, a + 22, a + 21]]  # +z normals
    rng = np.random.default_rng(1)
    q = np.c_[rng.uniform(-45, 45, (500, 2)), np.full(500, 4.5)]
    # exact planar geometry: float32 round-off only
    np.testing.assert_allclose(point_to_surface_distances(q, verts, faces), 4.5, atol=1e-5)
    below = q * [1, 1, -1]
    np.testing.assert_allclose(point_to_surface_distances(below, verts, faces), -4.5, atol=1e-5)
    np.testing.assert_allclose(
        point_to_surface_distances(below, verts, faces[:, ::-1]), 4.5, atol=1e-5
    )  # the sign follows the winding
    # review BK: float faces gave an IndexError, not the documented RegistrationError
    with pytest.raises(RegistrationError, match="integer vertex indices, got float64"):
        point_to_surface_distances(q, verts, faces + 0.5)
    upper = verts + [0.0, 0.0, 4.5]
    np.testing.assert_allclose(closest_point_distances(upper, verts), 4.5, atol=1e-12)


def test_summarise_closed_form():
    d = np.arange(1.0, 101.0)
    s = summarise(d, frame="icp")
    assert s.frame == "icp" and s.n == 100
    assert s.mean_mm == pytest.approx(50.5, abs=1e-12)
    assert s.median_mm == pytest.approx(50.5, abs=1e-12)
    assert s.sd_mm == pytest.approx(np.sqrt(100 * 101 / 12), abs=1e-9)  # var of 1..n, ddof 1
    assert s.p95_mm == pytest.approx(95.05, abs=1e-9)  # linear interpolation at rank 94.05
    assert s.max_mm == 100.0
    assert s.rms_mm == pytest.approx(np.sqrt(101 * 201 / 6), abs=1e-9)  # sqrt(mean k^2)
    assert set(s.to_json()) >= {"frame", "mean_mm", "sd_mm", "median_mm", "p95_mm", "max_mm"}
    with pytest.raises(RegistrationError, match="frame"):
        summarise(d, frame="scanner")


def test_surface_errors_in_both_frames(dome):
    vertices, faces, back_plate, _ = dome
    rng = np.random.default_rng(3)
    T_off = perturbation(rng, 2.0, 2.0)  # a fiducial registration 2 deg / 2 mm off
    measured = apply_transform(T_off, vertices[~back_plate])
    errs = surface_errors(measured, vertices, faces, fixed_mask=~back_plate)
    fid, icp = errs["fiducial"], errs["icp"]
    assert (fid.frame, icp.frame) == ("fiducial", "icp")
    assert fid.summary.frame == "fiducial" and icp.summary.frame == "icp"
    assert fid.method == "point_to_surface"
    np.testing.assert_array_equal(fid.T_applied, np.eye(4))
    # a 2 deg / 2 mm misplacement shows up as mm-scale errors in the fiducial frame ...
    assert fid.summary.mean_mm > 0.3
    # ... and is absorbed by ICP (measured points are mesh vertices: float32 floor)
    assert icp.summary.max_mm < 1e-3
    np.testing.assert_allclose(icp.T_applied @ T_off, np.eye(4), atol=1e-6)
    # Hausdorff over the same (non-back-plate) vertex sets: at least the largest error in the
    # fiducial frame, round-off after ICP
    assert fid.hausdorff_mm >= fid.summary.max_mm - 1e-4
    assert icp.hausdorff_mm < 1e-3
    # point-to-point path agrees on the ICP side (same vertices)
    ptp = surface_errors(measured, vertices, frames=("icp",))
    assert ptp["icp"].method == "point_to_point" and ptp["icp"].summary.max_mm < 1e-3
    with pytest.raises(RegistrationError, match="no T_fixed_from_moving"):
        nipple_error(vertices[0], vertices, frames=("icp",))
    # review BJ: two points for the nipple gave numpy's reshape error
    with pytest.raises(RegistrationError, match=r"one point \(3,\), got shape \(2, 3\)"):
        nipple_error(vertices[:2], vertices)


def test_nipple_and_landmark_errors(dome):
    vertices, _, _, nipple = dome
    shift = np.eye(4)
    shift[:3, 3] = [0.0, 0.0, 3.0]
    predicted = nipple - [0.0, 0.0, 3.0]  # the prediction sinks 3 mm into the apex
    err = nipple_error(predicted, vertices, T_fixed_from_moving=shift)
    # the apex is a vertex and the surface is horizontal there: exactly 3 mm, then 0 after
    # the ICP shift (round-off)
    assert err["fiducial"].error_mm == pytest.approx(3.0, abs=1e-9)
    assert err["icp"].error_mm == pytest.approx(0.0, abs=1e-9)
    assert err["icp"].frame == "icp" and err["icp"].method == "closest_point"
    tumour_pred = np.array([1.0, 2.0, 30.0])
    tumour_meas = np.array([4.0, 6.0, 30.0])
    lm = landmark_errors(
        {"nipple": predicted, "tumour": tumour_pred},
        {"nipple": nipple, "tumour": tumour_meas},
        frames=("fiducial", "icp"),
        T_fixed_from_moving=shift,
    )
    assert lm["fiducial"]["tumour"].error_mm == pytest.approx(5.0, abs=1e-12)  # 3-4-5
    assert lm["icp"]["tumour"].error_mm == pytest.approx(np.sqrt(34.0), abs=1e-12)
    assert lm["icp"]["nipple"].error_mm == pytest.approx(0.0, abs=1e-12)
    assert lm["fiducial"]["nipple"].frame == "fiducial"
    # the former name still reads, said deprecated; both at once are refused
    with pytest.warns(DeprecationWarning, match="T_icp is now T_fixed_from_moving"):
        old = nipple_error(predicted, vertices, T_icp=shift)
    assert old["icp"].error_mm == err["icp"].error_mm
    with pytest.raises(RegistrationError, match="not also T_icp"):
        nipple_error(predicted, vertices, T_fixed_from_moving=shift, T_icp=shift)
