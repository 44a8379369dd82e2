"""The compiled kernels: exact closest points on triangles, the nearest two sites of points.

Both are checked against independent answers: libigl's point-mesh distances (the design card's
reference) and brute force over all pairs in NumPy, on analytic cases and random meshes with
degenerate triangles, far points and exact ties.
"""

import igl
import numpy as np
import pytest

from o3dreg import _compiled
from o3dreg._bvh import TriangleTree
from o3dreg._geometry import face_cross
from o3dreg._nearest import nearest_two
from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration.distance import SurfaceDistanceQuery
from o3dreg.registration.lattice import TrilinearLattice


def random_soup(rng, triangles=400, degenerate=40):
    """Random triangles in a box, ``degenerate`` of them flat: collapsed to a point, to a
    segment (a repeated corner), or with three collinear corners."""
    vertices = rng.uniform(-10, 10, size=(3 * triangles, 3))
    faces = np.arange(3 * triangles).reshape(-1, 3)
    for k in range(degenerate):
        a, b, c = faces[k]
        kind = k % 3
        if kind == 0:
            vertices[b] = vertices[c] = vertices[a]
        elif kind == 1:
            vertices[c] = vertices[b]
        else:
            vertices[c] = vertices[a] + 2.5 * (vertices[b] - vertices[a])
    return vertices, faces


def point_on_triangle_distance(p, a, b, c):
    """Distance from ``p`` to triangle ``abc`` by brute force: the plane's foot when inside,
    else the nearest of the three edges (a slow, independent formula)."""

    def segment(p, a, b):
        u = b - a
        uu = u @ u
        t = 0.0 if uu == 0 else np.clip((p - a) @ u / uu, 0, 1)
        return np.linalg.norm(p - (a + t * u))

    n = np.cross(b - a, c - a)
    best = min(segment(p, a, b), segment(p, b, c), segment(p, c, a))
    if n @ n > 0:
        foot = p - ((p - a) @ n) / (n @ n) * n
        # Inside when the foot is on the same side of every edge.
        signs = [np.cross(y - x, foot - x) @ n for x, y in ((a, b), (b, c), (c, a))]
        if min(signs) >= 0:
            best = min(best, np.linalg.norm(p - foot))
    return best


def test_the_closest_points_of_a_square_are_known():
    # The unit square in z = 0 as two triangles: a point above it is its height away; one
    # beyond an edge or a corner is that far from the edge or the corner.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    pts = np.array([[0.25, 0.75, 2.0], [0.5, 0.5, -3.0], [2.0, 0.5, 0.0], [2.0, 3.0, 1.0]])
    sqr, face, closest = TriangleTree(v, f).closest(pts)
    np.testing.assert_allclose(sqr, [4.0, 9.0, 1.0, 1.0 + 4.0 + 1.0], rtol=1e-15)
    np.testing.assert_allclose(closest, [[0.25, 0.75, 0], [0.5, 0.5, 0], [1, 0.5, 0], [1, 1, 0]])
    assert face[0] == 1
    # (0.5, 0.5) lies on the shared diagonal: the smaller triangle index is named.
    assert face[1] == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_tree_finds_libigls_distances_on_random_triangles(seed):
    # Random overlapping triangles and points near and far: the squared distances equal
    # libigl's up to rounding (1e-12 of the box's squared size), and the closest point lies at
    # that distance.
    rng = np.random.default_rng(seed)
    v, f = random_soup(rng, degenerate=0)
    pts = np.vstack([rng.uniform(-12, 12, size=(600, 3)), rng.uniform(-200, 200, size=(60, 3))])
    sqr, _, closest = TriangleTree(v, f).closest(pts)
    ref, _, _ = igl.point_mesh_squared_distance(pts, v, f)
    scale = 400.0 * 1e-12
    np.testing.assert_allclose(sqr, ref, rtol=1e-12, atol=scale)
    np.testing.assert_allclose(((pts - closest) ** 2).sum(axis=1), sqr, rtol=1e-12, atol=scale)


@pytest.mark.parametrize("seed", [0, 1])
def test_flat_triangles_are_as_near_as_their_edges(seed):
    # A tenth of the triangles flat (a point, a repeated corner, three collinear corners):
    # against brute force over every triangle. (libigl answers a collinear triangle by the
    # edges its Voronoi regions pick, not always the nearest: 5.65 against 5.19 on one.)
    rng = np.random.default_rng(seed)
    v, f = random_soup(rng, triangles=300, degenerate=30)
    pts = np.vstack([rng.uniform(-12, 12, size=(40, 3)), rng.uniform(-60, 60, size=(8, 3))])
    sqr, face, _ = TriangleTree(v, f).closest(pts)
    # rel 1e-9: the brute force projects onto the plane and then the edges, the tree works in
    # Voronoi regions; the two round differently where a point is nearly above an edge.
    for i, p in enumerate(pts):
        brute = min(point_on_triangle_distance(p, *v[t]) for t in f)
        assert sqr[i] == pytest.approx(brute**2, rel=1e-9)
        assert point_on_triangle_distance(p, *v[f[face[i]]]) ** 2 == pytest.approx(sqr[i], rel=1e-9)


def test_a_hint_changes_nothing_but_the_start():
    # Any triangle (a good one, a bad one, none) may start the search: the same distances and
    # closest points come back.
    rng = np.random.default_rng(3)
    form = synthetic_form("open_ring", 3000)
    v, f = np.asarray(form.vertices), np.asarray(form.triangles)
    tree = TriangleTree(v, f)
    pts = v[rng.choice(len(v), 500)] + rng.normal(scale=2.0, size=(500, 3))
    sqr, face, closest = tree.closest(pts)
    for hint in (face, rng.integers(0, len(f), 500), np.full(500, -1)):
        s2, _, c2 = tree.closest(pts, hint)
        np.testing.assert_array_equal(s2, sqr)
        np.testing.assert_array_equal(c2, closest)


def test_the_answers_do_not_depend_on_the_threads(monkeypatch):
    # Every query is answered by the same code whichever thread takes its range.
    rng = np.random.default_rng(4)
    v, f = random_soup(rng, 2000, 0)
    pts = rng.uniform(-12, 12, size=(5000, 3))
    lattice = TrilinearLattice.zeros((-12, -12, -12), (24, 24, 24), (4, 4, 4))
    lattice = lattice.with_displacements(rng.normal(size=lattice.displacements.shape))
    # A half sphere around the points: about half of them lie beyond its open boundary.
    sphere = synthetic_form("sphere", 3000)
    sv, sf = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    query = SurfaceDistanceQuery(sv, sf[sv[sf].mean(axis=1)[:, 2] < 0.0])
    around = pts * (np.abs(sv).max() / 8.0)

    def answers():
        _, face, closest = query.closest(around)
        return (
            *TriangleTree(v, f).closest(pts),
            *nearest_two(v, pts),
            lattice.displacement(pts),
            lattice.displacement_gradient(pts),
            face_cross(v, f),
            query.beyond_boundary(around, face, closest),
        )

    monkeypatch.setattr(_compiled, "MIN_PER_THREAD", 10**9)
    monkeypatch.setattr(_compiled, "MIN_PER_THREAD_CHEAP", 10**9)
    one = answers()
    monkeypatch.setattr(_compiled, "MIN_PER_THREAD", 1)
    monkeypatch.setattr(_compiled, "MIN_PER_THREAD_CHEAP", 1)
    monkeypatch.setattr(_compiled, "_threads", lambda: 7)
    many = answers()
    assert 0 < one[-1].sum() < pts.shape[0]  # both answers of the boundary test occur
    for a, b in zip(one, many):
        np.testing.assert_array_equal(a, b)


def brute_nearest_two(sites, points):
    d = ((points[:, None, :] - sites[None, :, :]) ** 2).sum(axis=2)
    # Lexicographic (distance, index): a stable sort of the distances.
    order = np.argsort(d, axis=1, kind="stable")[:, :2]
    return np.sqrt(np.take_along_axis(d, order, axis=1)), order


@pytest.mark.parametrize(
    "case", ["cloud", "surface", "flat", "clustered", "far", "duplicates", "few"]
)
def test_the_nearest_two_sites_are_those_of_brute_force(case):
    rng = np.random.default_rng(5)
    form = np.asarray(synthetic_form("cone", 1500).vertices)
    sites = {
        "cloud": rng.uniform(-1, 1, size=(800, 3)),
        "surface": form,
        "flat": np.column_stack([rng.uniform(-1, 1, size=(600, 2)), np.zeros(600)]),
        "clustered": np.vstack([rng.normal(size=(400, 3)) * 1e-3, rng.normal(size=(20, 3)) * 50]),
        "far": form,
        "duplicates": np.round(rng.uniform(-1, 1, size=(900, 3)), 1),
        "few": rng.uniform(-1, 1, size=(3, 3)),
    }[case]
    lo, hi = sites.min(axis=0), sites.max(axis=0)
    span = hi - lo + 1.0
    points = rng.uniform(lo - 0.2 * span, hi + 0.2 * span, size=(1500, 3))
    if case == "far":
        points = points + np.array([40.0, -3.0, 7.0]) * span
    if case == "duplicates":
        points = np.vstack([points, sites[:100]])  # exact ties between repeated sites
    d, i = nearest_two(sites, points)
    bd, bi = brute_nearest_two(sites, points)
    # The same squared distances summed in the same order: equal to the last bit.
    np.testing.assert_array_equal(d, bd)
    np.testing.assert_array_equal(i, bi)


def test_one_site_has_no_second():
    d, i = nearest_two(np.zeros((1, 3)), np.array([[3.0, 4.0, 0.0]]))
    np.testing.assert_array_equal(d, [[5.0, np.inf]])
    np.testing.assert_array_equal(i, [[0, -1]])


def test_the_kept_assignment_is_the_nearest_site_after_every_move():
    # SiteGrid.reassign searches only the points whose nearest site may have changed (the
    # barycentre term's bound): after each of 12 random moves of the sites, small and large,
    # every point's site is its nearest by brute force (ties to the smaller index), and its
    # distance is that site's.
    from o3dreg._nearest import Assignment, SiteGrid

    rng = np.random.default_rng(6)
    sites = np.asarray(synthetic_form("sphere", 800).vertices)
    points = sites[rng.choice(len(sites), 3000)] + rng.normal(scale=3.0, size=(3000, 3))
    state = Assignment.empty(len(points))
    path, moved, last = np.zeros(len(sites)), 0.0, None
    for step in range(12):
        if last is not None:
            sites = sites + rng.normal(scale=[0.05, 0.5, 4.0][step % 3], size=sites.shape)
            move = np.sqrt(((sites - last) ** 2).sum(axis=1))
            path, moved = path + move, moved + move.max()
        distance = SiteGrid(sites).reassign(points, path, moved, state, every=last is None)
        last = sites.copy()
        _, best = brute_nearest_two(sites, points)
        np.testing.assert_array_equal(state.nearest, best[:, 0])
        np.testing.assert_array_equal(
            distance, np.sqrt(((points - sites[best[:, 0]]) ** 2).sum(axis=1))
        )


def test_the_tree_refuses_what_its_compiled_code_would_read_out_of_bounds():
    v = np.eye(3)
    with pytest.raises(ValueError, match="face indices"):
        TriangleTree(v, np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="m >= 1"):
        TriangleTree(v, np.zeros((0, 3), dtype=np.int64))
    tree = TriangleTree(v, np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="hint"):
        tree.closest(np.zeros((2, 3)), np.array([0, 1]))
    sqr, face, _ = tree.closest(np.zeros((2, 3)), np.array([0, -1]))
    np.testing.assert_allclose(sqr, [1 / 3, 1 / 3])
    np.testing.assert_array_equal(face, [0, 0])


def test_a_forked_child_splits_queries_on_threads_of_its_own(monkeypatch):
    # A process forked after the parent split a query (a ProcessPoolExecutor of `build-model
    # --jobs` after a first registration) inherits no threads: its queries must not wait for
    # the parent's. Before: the child's first split query hung.
    import multiprocessing

    monkeypatch.setattr(_compiled, "MIN_PER_THREAD", 1)
    monkeypatch.setattr(_compiled, "_threads", lambda: 2)
    v, f = random_soup(np.random.default_rng(7), 200, 0)
    pts = np.random.default_rng(8).uniform(-12, 12, size=(500, 3))
    tree = TriangleTree(v, f)
    here = tree.closest(pts)[0]  # the parent's pool exists now
    context = multiprocessing.get_context("fork")
    receive, send = context.Pipe(duplex=False)
    child = context.Process(target=lambda: send.send(tree.closest(pts)[0]))
    child.start()
    answered = receive.poll(30)
    if not answered:
        child.kill()
    child.join()
    assert answered, "the forked child's query did not finish in 30 s"
    np.testing.assert_array_equal(receive.recv(), here)


def test_the_grid_refuses_what_its_compiled_code_cannot_place():
    from o3dreg._nearest import Assignment, SiteGrid

    with pytest.raises(ValueError, match="finite"):
        nearest_two(np.array([[0.0, np.nan, 0.0]]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        nearest_two(np.zeros((2, 3)), np.array([[np.inf, 0.0, 0.0]]))
    grid = SiteGrid(np.eye(3))
    with pytest.raises(ValueError, match="sites that do not exist"):
        grid.reassign(
            np.zeros((2, 3)),
            np.zeros(3),
            0.0,
            Assignment(np.array([0, 3]), *np.zeros((3, 2))),
            False,
        )
    with pytest.raises(ValueError, match="one entry per point"):
        grid.reassign(np.zeros((2, 3)), np.zeros(3), 0.0, Assignment.empty(3), True)
    with pytest.raises(ValueError, match="finite"):
        TriangleTree(np.eye(3), np.array([[0, 1, 2]])).closest(np.full((1, 3), np.nan))
