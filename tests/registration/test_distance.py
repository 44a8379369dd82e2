"""Closest points on a surface: the AABB tree built on first use, and the few queries of a large
surface answered without it."""

import numpy as np
import pytest

from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration import distance
from o3dreg.registration._target import TargetSurface
from o3dreg.registration.distance import SurfaceDistanceQuery


@pytest.fixture
def sphere():
    mesh = synthetic_form("sphere", 20000)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def assert_same_closest(few, full, query, pts):
    np.testing.assert_array_equal(few[0], full[0])  # the distances, bit for bit
    same = few[1] == full[1]
    np.testing.assert_array_equal(few[2][same], full[2][same])
    # Where two triangles are exactly as close (a closest point on a shared edge or corner, or
    # two points of a symmetric mesh; here a point radially above a vertex of the convex sphere),
    # either may be named, with its own closest point.
    for i in np.flatnonzero(~same):
        named = SurfaceDistanceQuery(query.vertices, query.faces[few[1][i : i + 1]])
        assert named.closest(few[2][i : i + 1])[0][0] <= 1e-9  # on the named triangle
        # ... and at the same distance from the point (to rounding of the subtraction).
        assert np.linalg.norm(pts[i] - few[2][i]) == pytest.approx(full[0][i], rel=1e-12)


def test_the_tree_is_built_on_first_use(sphere):
    query = SurfaceDistanceQuery(*sphere)
    assert not query.has_tree
    assert query.mean_edge > 0 and query.face_normal(np.array([0])).shape == (1, 3)
    assert not query.has_tree
    query.closest(np.zeros((1, 3)))
    assert query.has_tree
    assert not TargetSurface.from_mesh(*sphere).query.has_tree


def test_few_queries_without_the_tree_find_the_same_points(sphere, monkeypatch):
    v, f = sphere
    monkeypatch.setattr(distance, "CLOSEST_FEW_MIN_FACES", 0)
    rng = np.random.default_rng(0)
    # Near the surface (a registered template), on vertices (closest triangles tied), inside.
    pts = np.concatenate(
        [
            v[rng.choice(len(v), 300)] * (1.0 + rng.normal(scale=0.01, size=(300, 1))),
            v[:50],
            0.9 * v[rng.choice(len(v), 50)],
        ]
    )
    few_query = SurfaceDistanceQuery(v, f)
    few = few_query.closest_few(pts)
    assert not few_query.has_tree  # answered by a tree of the triangles near the points
    full_query = SurfaceDistanceQuery(v, f)
    full = full_query.closest(pts)
    assert_same_closest(few, full, few_query, pts)
    # A point far off (the nearest vertex bounds well): still a few triangles.
    far = np.array([[500.0, 0.0, 0.0]])
    np.testing.assert_array_equal(few_query.closest_few(far)[0], full_query.closest(far)[0])
    assert not few_query.has_tree
    # The centre, as far from every vertex: most triangles would be gathered, the full tree
    # answers.
    centre = np.zeros((1, 3))
    np.testing.assert_array_equal(few_query.closest_few(centre)[0], full_query.closest(centre)[0])
    assert few_query.has_tree


def test_a_handful_of_points_on_a_small_surface_skips_its_tree(sphere):
    # Below CLOSEST_FEW_MIN_FACES triangles, a query of at most one point per
    # CLOSEST_FEW_FACES_PER_POINT of them (a fine level's few target points on the template) is
    # answered by the tree of the triangles near the points; more points build the whole tree.
    v, f = sphere
    assert f.shape[0] < distance.CLOSEST_FEW_MIN_FACES
    rng = np.random.default_rng(4)
    # 20 points off one cap of the sphere (few, and near few triangles).
    cap = v[np.argsort(v[:, 2])[-400:]]
    pts = 1.05 * cap[rng.choice(len(cap), 20)]
    query = SurfaceDistanceQuery(v, f)
    few = query.closest_few(pts)
    assert not query.has_tree
    full = SurfaceDistanceQuery(v, f).closest(pts)
    assert_same_closest(few, full, query, pts)
    # One point more than a CLOSEST_FEW_FACES_PER_POINT-th of the triangles: the whole tree.
    many = f.shape[0] // distance.CLOSEST_FEW_FACES_PER_POINT + 1
    query.closest_few(np.repeat(pts, -(-many // len(pts)), axis=0)[:many])
    assert query.has_tree


def test_vertices_of_no_triangle_bound_nothing(sphere, monkeypatch):
    # An unreferenced vertex next to a query point is not on the surface: its distance must not
    # be taken as a bound on the distance to the surface.
    v, f = sphere
    monkeypatch.setattr(distance, "CLOSEST_FEW_MIN_FACES", 0)
    point = np.array([[0.0, 0.0, 0.0]])  # the centre, 20 mm from the surface
    stray = np.concatenate([v, point + 0.01])
    few = SurfaceDistanceQuery(stray, f).closest_few(point)
    full = SurfaceDistanceQuery(v, f).closest(point)
    np.testing.assert_array_equal(few[0], full[0])
    assert few[0][0] > 10.0
