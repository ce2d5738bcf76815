"""Material points: a point outside the mesh, taken at the nearest point inside."""

from __future__ import annotations

import numpy as np
import pytest
from femtest_meshes import box_mesh

from fem import Clamped, discretize
from fem.probe import MaterialPoint, nearest_inside_mm


@pytest.fixture(scope="module")
def box():
    return box_mesh((10.0, 20.0, 30.0), (3, 4, 5), jitter=0.2, seed=2)


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ([5.0, 7.0, 11.0], [5.0, 7.0, 11.0]),  # inside: unchanged
        ([12.5, 7.0, 11.0], [10.0, 7.0, 11.0]),  # 2.5 mm past the x = 10 face
        ([-1.0, -2.0, 11.0], [0.0, 0.0, 11.0]),  # past an edge: onto the edge
        ([5.0, 7.0, 33.0], [5.0, 7.0, 30.0]),
    ],
)
def test_a_point_outside_the_box_is_taken_at_the_nearest_point_inside(box, point, expected):
    # closed form: the nearest point of a box; its faces are flat whatever the jitter.
    # Tolerance: the millionth of the way to the element's centroid (< 3e-5 mm here).
    q = nearest_inside_mm(box, np.array(point))
    np.testing.assert_allclose(q, expected, atol=3e-5)


def test_locate_takes_an_outside_point_at_the_nearest_inside_or_raises(box):
    disc = discretize(box, Clamped("z0"), formulation="p1")
    with pytest.raises(ValueError, match="lies outside the mesh"):
        MaterialPoint.locate(disc, np.array([12.5, 7.0, 11.0]))
    mp = MaterialPoint.locate(disc, np.array([12.5, 7.0, 11.0]), outside="nearest")
    # the barycentric mix of its element's vertices: round-off and the 1e-6 nudge
    np.testing.assert_allclose(mp.place_mm(box.nodes_mm), [10.0, 7.0, 11.0], atol=3e-5)
    inside = MaterialPoint.locate(disc, np.array([5.0, 7.0, 11.0]), outside="nearest")
    np.testing.assert_allclose(inside.place_mm(box.nodes_mm), [5.0, 7.0, 11.0], atol=1e-12)


@pytest.mark.parametrize("formulation", ["taylor-hood", "p2", "mini", "p1"])
def test_edge_midpoint_displacement_agrees_with_interpolation_at_the_midpoints(box, formulation):
    # two code paths: the edge's own degree of freedom (or its ends' mean) against the
    # basis's value at the located midpoint; a state with random entries tests the edge
    # numbering on every edge, not only on a smooth field. Tolerance: round-off of the
    # barycentric location (1e-12 relative)
    from fem import displacement_at, edge_midpoint_displacement_mm

    disc = discretize(box, Clamped("z0"), formulation=formulation)
    state = np.random.default_rng(3).normal(size=disc.n_dofs)
    edges = np.unique(
        np.sort(
            box.tets[:, [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]].reshape(-1, 2), axis=1
        ),
        axis=0,
    )
    edges = edges[::-1]  # any order, either direction
    edges[::2] = edges[::2, ::-1]
    got = edge_midpoint_displacement_mm(disc, state, edges)
    midpoints = box.nodes_mm[edges].mean(axis=1)
    want = displacement_at(disc, state, midpoints)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.abs(want).max())
    with pytest.raises(ValueError, match="are not an edge of the mesh"):
        far = np.argmax(np.linalg.norm(box.nodes_mm - box.nodes_mm[0], axis=1))
        edge_midpoint_displacement_mm(disc, state, [[0, far]])
