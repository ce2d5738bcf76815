import itertools

import numpy as np
import pytest
from conftest import MARKERS_MM, random_rigid, rotation_error_deg

from registration import (
    AmbiguousCorrespondenceError,
    DegenerateMarkersError,
    MarkerCountError,
    RegistrationError,
    apply_transform,
    fit_rigid,
)


def _naive_arun(p, q):
    """Arun et al. without the reflection correction (what the correction must fix)."""
    H = (p - p.mean(0)).T @ (q - q.mean(0))
    U, _, Vt = np.linalg.svd(H)
    return Vt.T @ U.T


def test_random_transforms_recovered_from_three_noisy_markers():
    rng = np.random.default_rng(20240401)
    # "0.2 mm isotropic noise" read as a 3D RMS localisation error of 0.2 mm, i.e. sigma =
    # 0.2/sqrt(3) mm per axis.  The translation error at the marker centroid is then
    # N(0, sigma^2/3) per axis, whose 99th percentile norm is 3.37 * 0.067 = 0.22 mm < 0.3 mm;
    # with 0.2 mm *per axis* that percentile would be 0.39 mm and the 0.3 mm bound could not
    # hold for any estimator.  The rotation error for this ~120 mm triangle is ~0.1 deg RMS.
    sigma = 0.2 / np.sqrt(3.0)
    n_trials = 1000
    ok, dets = 0, []
    for _ in range(n_trials):
        T = random_rigid(rng)
        target = apply_transform(T, MARKERS_MM) + rng.normal(0.0, sigma, (3, 3))
        fit = fit_rigid(MARKERS_MM, target)
        dets.append(np.linalg.det(fit.rotation))
        rot = rotation_error_deg(fit.rotation, T[:3, :3])
        trans = np.linalg.norm(fit.translation_mm - T[:3, 3])
        ok += rot <= 0.3 and trans <= 0.3
    # Markers are centred on the origin of the source frame, so translation_mm is the
    # displacement at the markers (not a lever-arm artefact).
    assert ok / n_trials >= 0.99, f"only {ok / n_trials:.3f} of trials within bounds"
    # det of a rotation is +1 to round-off (1e-12 is ~1e4 double epsilons).
    np.testing.assert_allclose(dets, 1.0, atol=1e-12)


def _random_planar_layout(rng, n):
    """Random markers in the plane z = 0, redrawn until clearly non-degenerate."""
    while True:
        src = np.c_[rng.uniform(-70, 70, (n, 2)), np.zeros(n)]
        d = np.linalg.norm(src[:, None] - src[None], axis=-1)[np.triu_indices(n, 1)]
        s = np.linalg.svd(src - src.mean(0), compute_uv=False)
        if d.min() > 10.0 and s[1] / np.sqrt(n) > 10.0:
            return src


def test_coplanar_markers_never_give_a_reflection():
    rng = np.random.default_rng(7)
    # Exactly coplanar, noise-free: H has rank 2, the third singular vectors have arbitrary
    # sign and the naive SVD returns a reflection in a fair share of cases.
    naive_reflections = 0
    for n in (3, 4, 5):
        for _ in range(100):
            src = _random_planar_layout(rng, n)
            T = random_rigid(rng)
            tgt = apply_transform(T, src)
            naive_reflections += np.linalg.det(_naive_arun(src, tgt)) < 0
            fit = fit_rigid(src, tgt)
            # exact data: recovered to round-off (1e-9 relative to 100 mm coordinates)
            assert np.linalg.det(fit.rotation) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_allclose(fit.T_target_from_source, T, atol=1e-9)
            assert fit.fre_mm < 1e-9
    assert naive_reflections > 0, "test set does not exercise the reflection case"


def test_mirrored_target_still_gives_a_rotation():
    # Target is the mirror image of a non-coplanar set: the best *rotation* is returned.
    src = np.array([[0.0, 0, 0], [80, 0, 0], [0, 60, 0], [10, 20, 50]])
    tgt = src * np.array([1.0, 1.0, -1.0])
    fit = fit_rigid(src, tgt)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0, abs=1e-12)
    assert fit.fre_mm > 1.0  # a rotation cannot explain a mirror image


def test_permuted_marker_order_recovered():
    rng = np.random.default_rng(3)
    for perm in itertools.permutations(range(3)):
        T = random_rigid(rng)
        tgt = apply_transform(T, MARKERS_MM) + rng.normal(0, 0.1, (3, 3))
        shuffled = np.empty_like(tgt)
        shuffled[list(perm)] = tgt  # source i is now at row perm[i]
        fit = fit_rigid(MARKERS_MM, shuffled, correspondence="auto")
        assert fit.permutation == perm
        given = fit_rigid(MARKERS_MM, tgt)
        # the same marker pairs give the same fit up to round-off
        np.testing.assert_allclose(fit.T_target_from_source, given.T_target_from_source, atol=1e-9)
        # wrong orderings of a scalene 116/124/130 mm triangle leave residuals of several mm
        assert fit.second_best_fre_mm > 3.0


def test_auto_correspondence_on_four_markers():
    rng = np.random.default_rng(11)
    src = np.array([[-60.0, -40, 0], [70, -30, 0], [-10, 65, 0], [40, 50, 5]])
    T = random_rigid(rng)
    perm = (2, 0, 3, 1)
    tgt = np.empty_like(src)
    tgt[list(perm)] = apply_transform(T, src)
    fit = fit_rigid(src, tgt, correspondence="auto")
    assert fit.permutation == perm
    np.testing.assert_allclose(fit.T_target_from_source, T, atol=1e-9)  # exact data


def test_symmetric_layout_is_ambiguous():
    isosceles = np.array([[-50.0, 0, 0], [50, 0, 0], [0, 90, 0]])
    with pytest.raises(AmbiguousCorrespondenceError, match="ambiguous"):
        fit_rigid(isosceles, isosceles + 5.0, correspondence="auto")


def test_the_plate_normal_tells_a_flip_from_the_true_ordering():
    # a layout with a mirror line (an isosceles triangle or trapezoid) on the plate: a
    # 180-degree turn about that line fits as well as the truth, and flips the body
    # through the plate; the plate's normal rules it out (refused as ambiguous before).
    # A rectangle's turn in the plate keeps the normal: still ambiguous. The normal, not
    # a body point: markers on posts put a body point on either side of their plane
    rng = np.random.default_rng(7)
    up = np.array([0.0, 0.0, 1.0])  # the plate z = 0, the body above
    for layout in (
        np.array([[-50.0, 0, 0], [50, 0, 0], [0, 90, 0]]),  # isosceles
        np.array([[-60.0, -40, 0], [60, -40, 0], [30, 40, 0], [-30, 40, 0]]),  # trapezoid
    ):
        for _ in range(5):
            T = random_rigid(rng)
            perm = tuple(rng.permutation(len(layout)))
            tgt = np.empty_like(layout)
            tgt[list(perm)] = apply_transform(T, layout)
            with pytest.raises(AmbiguousCorrespondenceError):
                fit_rigid(layout, tgt, correspondence="auto")
            normals = (up, T[:3, :3] @ up)
            fit = fit_rigid(layout, tgt, correspondence="auto", plate_normals=normals)
            np.testing.assert_allclose(fit.T_target_from_source, T, atol=1e-9)
    rectangle = np.array([[-60.0, -40, 0], [60, -40, 0], [60, 40, 0], [-60, 40, 0]])
    with pytest.raises(AmbiguousCorrespondenceError):
        fit_rigid(rectangle, rectangle, correspondence="auto", plate_normals=(up, up))
    # a tie-break that cannot score (an empty footprint) decides nothing (NaN compared
    # false both ways, and the first ordering was taken)
    with pytest.raises(AmbiguousCorrespondenceError, match=r"mismatch is \[nan"):
        fit_rigid(rectangle, rectangle, correspondence="auto", tie_break=lambda T: np.nan)
    # a scalene layout whose best fit flips the body: markers and planes disagree
    scalene = np.array([[-60.0, -40, 0], [70, -30, 0], [-10, 65, 0]])
    with pytest.raises(RegistrationError, match="flips the body through the plate, and the"):
        fit_rigid(scalene, scalene, correspondence="auto", plate_normals=(up, -up))


@pytest.mark.parametrize(
    ("source", "target", "error", "match"),
    [
        (MARKERS_MM[:2], MARKERS_MM[:2], MarkerCountError, "at least 3"),
        (MARKERS_MM, np.r_[MARKERS_MM, [[0.0, 0, 0]]], MarkerCountError, "mismatch"),
        (
            np.array([[0.0, 0, 0], [50, 0, 0], [120, 0, 0]]),
            MARKERS_MM,
            DegenerateMarkersError,
            "collinear",
        ),
        (
            MARKERS_MM,
            np.array([[0.0, 0, 0], [50, 0, 0], [50, 0, 0.1]]),
            DegenerateMarkersError,
            "coincident",
        ),
        (MARKERS_MM, np.zeros((3, 2)), MarkerCountError, "shape"),
        (np.r_[MARKERS_MM[:2], [[np.nan, 0, 0]]], MARKERS_MM, RegistrationError, "NaN"),
    ],
)
def test_bad_marker_sets_give_clear_errors(source, target, error, match):
    with pytest.raises(error, match=match):
        fit_rigid(source, target, name="scan 'x'")
    assert issubclass(error, ValueError)


def test_max_fre_rejects_a_spurious_marker():
    tgt = MARKERS_MM.copy()
    # one marker 8 mm off along an edge: changes two pairwise distances by ~8 mm, which no
    # rigid motion can absorb (an out-of-plane shift would be mostly absorbed by a tilt)
    edge = tgt[2] - tgt[0]
    tgt[2] += 8.0 * edge / np.linalg.norm(edge)
    with pytest.raises(RegistrationError, match="exceeds"):
        fit_rigid(MARKERS_MM, tgt, max_fre_mm=2.0)


def test_weights_ignore_a_zero_weight_outlier():
    rng = np.random.default_rng(5)
    src = np.array([[-60.0, -40, 0], [70, -30, 0], [-10, 65, 0], [40, 50, 5]])
    T = random_rigid(rng)
    tgt = apply_transform(T, src)
    tgt[3] += 10.0
    fit = fit_rigid(src, tgt, weights=[1.0, 1.0, 1.0, 0.0])
    np.testing.assert_allclose(fit.T_target_from_source, T, atol=1e-9)  # exact on 3 markers
    assert fit.residuals_mm[3] == pytest.approx(np.sqrt(3) * 10.0, rel=1e-9)
    # equal weights are the unweighted fit (two code paths agree to round-off)
    a = fit_rigid(src, tgt, weights=np.full(4, 2.5))
    b = fit_rigid(src, tgt)
    np.testing.assert_allclose(a.T_target_from_source, b.T_target_from_source, atol=1e-12)


def test_fitzpatrick_tre_and_fle_estimate_match_monte_carlo():
    rng = np.random.default_rng(99)
    fle = 0.5  # 3D RMS, mm
    sigma = fle / np.sqrt(3.0)
    targets = np.array([[0.0, 0.0, 80.0], [30.0, -20.0, 40.0], [150.0, 0.0, 0.0]])
    n = 3000
    err2 = np.zeros(len(targets))
    fre2 = 0.0
    fit0 = None
    for _ in range(n):
        T = random_rigid(rng)
        fit = fit_rigid(MARKERS_MM, apply_transform(T, MARKERS_MM) + rng.normal(0, sigma, (3, 3)))
        err = apply_transform(fit.T_target_from_source, targets) - apply_transform(T, targets)
        err2 += np.sum(err**2, axis=1)
        fre2 += fit.fre_mm**2
        fit0 = fit
    tre_mc = np.sqrt(err2 / n)
    tre_formula = fit0.tre_mm(targets, fle_mm=fle)
    # Monte Carlo RMS of ~3 dof: relative SE ~ 0.82/sqrt(3000)/2 = 0.75 %; the first-order
    # formula is exact to O(FLE/distance) ~ 0.5 %; 5 % is > 5 SE.
    np.testing.assert_allclose(tre_mc, tre_formula, rtol=0.05)
    # E[FRE^2] = (1 - 2/N) FLE^2 (Fitzpatrick 1998), so the FLE estimate is unbiased in the
    # mean square; relative SE of mean FRE^2 with 3 dof is ~ 0.82/sqrt(3000) = 1.5 %.
    assert np.sqrt(fre2 / n / (1 - 2 / 3)) == pytest.approx(fle, rel=0.05)
    assert fit0.fle_estimate_mm == pytest.approx(fit0.fre_mm * np.sqrt(3.0), rel=1e-12)
    assert isinstance(fit0.tre_mm(targets[0]), float)


def test_result_is_frozen():
    fit = fit_rigid(MARKERS_MM, MARKERS_MM + 1.0)
    with pytest.raises(ValueError, match="read-only"):
        fit.T_target_from_source[0, 0] = 2.0
    with pytest.raises(AttributeError):
        fit.fre_mm = 0.0


def _egg_patch(rng, n: int):
    """A flat egg-shaped face 80 x 55 mm, 6 mm off the origin, triangulated from n points."""
    from scipy.spatial import Delaunay

    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False) + rng.uniform(0.0, np.pi / 100)
    rim = np.c_[6.0 + 40.0 * np.cos(t), 27.5 * np.sin(t) * (1.0 + 0.15 * np.cos(t))]
    inner = rng.uniform(-1.0, 1.0, (4 * n, 2)) * [40.0, 32.0] + [6.0, 0.0]
    u = (inner[:, 0] - 6.0) / 40.0
    inside = inner[:, 1] ** 2 < (27.5 * (1.0 + 0.15 * u)) ** 2 * (1.0 - u**2) * 0.95
    xy = np.vstack([rim, inner[inside][:n]])
    return np.c_[xy, np.zeros(len(xy))], Delaunay(xy).simplices


def test_two_samplings_of_one_face_lie_apart_as_points_not_as_patches():
    # the same face triangulated from two random samplings (about 2 mm apart, as a
    # decimated scan surface): their vertices lie 0.9 mm from each other's nearest vertex
    # on average, a floor the tie-break's bar (1 mm and twice) had to clear on top of a
    # true misfit (the small equilateral twin: true ordering 1.13 mm, next 2.51); vertex
    # to triangle, only the outlines differ: chords of one curve through 200 points at
    # other phases, each rim vertex off the other's chords by at most the sagitta c^2 /
    # (8 rho) = 0.008 mm (chords c of 1.1 mm at the egg's tightest radius of curvature,
    # rho = 27.5^2 / 40 = 18.9 mm), on the 200 rim vertices of about 900 (the inner ones
    # lie on the plane): a mean under 0.002 mm. A 3 mm shift, a true misfit, adds 0.2 mm
    # to the floor as points and is far above it as patches (the rim's vertices on the
    # far side lie up to 3 mm out).
    from registration import footprint_mismatch_mm

    rng = np.random.default_rng(5)
    a, b = _egg_patch(rng, 700), _egg_patch(rng, 700)
    as_points = footprint_mismatch_mm(a[0], b[0])
    as_patches = footprint_mismatch_mm(a, b)
    assert 0.5 < as_points < 1.5, as_points
    assert as_patches < 0.005, as_patches
    shifted = (a[0] + [3.0, 0.0, 0.0], a[1])
    assert footprint_mismatch_mm(shifted[0], b[0]) < as_points + 0.5
    assert footprint_mismatch_mm(shifted, b) > 0.15
    assert footprint_mismatch_mm(shifted, b) > 20.0 * as_patches


def test_the_footprint_tells_the_turns_of_a_square_layout_apart():
    # four markers at the corners of a square plate: its 90-degree turns in the plate fit
    # alike, and keep the body's side; the body's back face on the plate does not move
    # between postures, and a turn moves it unless it shares the layout's symmetry
    from registration import register_scans
    from registration.errors import AmbiguousCorrespondenceError as Ambiguous

    square = np.array([[-50.0, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]])
    t = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    r = np.linspace(0.0, 1.0, 8)[:, None]
    # an egg-shaped back face 80 x 55 mm, 6 mm off the square's centre
    egg = np.c_[
        (6.0 + r * 40.0 * np.cos(t)).ravel(),
        (r * 27.5 * np.sin(t) * (1.0 + 0.15 * np.cos(t))).ravel(),
        np.zeros(t.size * r.size),
    ]
    disc = np.c_[(r * 35.0 * np.cos(t)).ravel(), (r * 35.0 * np.sin(t)).ravel(), 0 * egg[:, 2]]
    up = np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(11)
    for _ in range(4):
        T = random_rigid(rng)
        perm = rng.permutation(4)
        scan = {"ref": square, "other": apply_transform(T, square)[perm]}
        sides = {"ref": up, "other": T[:3, :3] @ up}
        with pytest.raises(Ambiguous):
            register_scans(scan, reference="ref", plate_normals_by_scan=sides)
        feet = {"ref": egg, "other": apply_transform(T, egg)}
        reg = register_scans(
            scan, reference="ref", plate_normals_by_scan=sides, footprints_by_scan=feet
        )
        np.testing.assert_allclose(reg["other"].T_ref_from_scan, np.linalg.inv(T), atol=1e-9)
        # a round back face on the square's centre turns into itself: still ambiguous,
        # the message says by how little the footprint tells the orderings apart
        feet = {"ref": disc, "other": apply_transform(T, disc)}
        with pytest.raises(Ambiguous, match=r"the other data tell them apart by 0\.00"):
            register_scans(
                scan, reference="ref", plate_normals_by_scan=sides, footprints_by_scan=feet
            )
