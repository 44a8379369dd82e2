"""The target surface a registration prepares once: canonical order, debris removed, its levels
of detail and its nested subsamples."""

import numpy as np
import open3d as o3d
from _helpers import morton_code

from o3dreg.mesh.canonical import canonical_mesh, oriented_faces
from o3dreg.mesh.cleaning import mesh_components
from o3dreg.mesh.edges import SortedEdges
from o3dreg.registration._target import TargetSurface
from o3dreg.registration.distance import SurfaceDistanceQuery


def sphere(radius: float, resolution: int, centre=(0.0, 0.0, 0.0)):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices) + centre, np.asarray(mesh.triangles)


def test_the_target_is_canonical_and_loses_its_debris():
    big, debris = sphere(10.0, 30), sphere(0.5, 4, centre=(30.0, 0.0, 0.0))
    v = np.concatenate([debris[0], big[0]])
    f = np.concatenate([debris[1], big[1] + len(debris[0])])
    before = v.copy(), f.copy()
    kept = TargetSurface.from_mesh(v, f, min_component=0.05)
    # Exactly the big sphere, in the order canonical_mesh gives it alone.
    expected = canonical_mesh(*big)
    np.testing.assert_array_equal(kept.vertices, expected[0])
    np.testing.assert_array_equal(kept.faces, expected[1])
    everything = TargetSurface.from_mesh(v, f)
    assert everything.vertices.shape[0] == v.shape[0]
    np.testing.assert_array_equal(v, before[0])  # inputs are not modified
    np.testing.assert_array_equal(f, before[1])


def test_subsamples_are_nested_and_drawn_once():
    target = TargetSurface.from_mesh(*sphere(10.0, 60))
    large = target.subsample(2000)
    small = target.subsample(500)
    assert small.shape[0] < large.shape[0] < target.vertices.shape[0]
    # Every point of the smaller subsample is a point of the larger one (drawn from it).
    rows = {tuple(p) for p in large}
    assert all(tuple(p) in rows for p in small)
    assert target.subsample(500) is small


def test_levels_of_detail_only_where_coarser_than_the_target():
    target = TargetSurface.from_mesh(*sphere(10.0, 60))
    edge = target.query.mean_edge
    coarse, fine = 4.0 * edge, 1.0 * edge
    target.build_levels_of_detail([coarse, fine])
    simplified = target.at_detail(coarse)
    assert simplified is not target.query
    assert simplified.vertices.shape[0] < target.vertices.shape[0]
    # A voxel under twice the mean edge gets the full target.
    assert target.at_detail(fine) is target.query
    # The simplified surface stays within about a voxel of the full one.
    assert target.query.distance(simplified.vertices).max() < coarse


def reference_canonical_mesh(vertices, faces):
    """canonical_mesh as its docstring states it, with NumPy's lexsort and unique: the
    vertices by Morton code of their cell of a 1024^3 grid over the bounds' largest extent,
    then by x, y, z."""
    lo = vertices.min(axis=0)
    extent = (vertices.max(axis=0) - lo).max()
    cells = np.minimum(((vertices - lo) / extent * 1024).astype(np.int64), 1023)
    order = np.lexsort((vertices[:, 2], vertices[:, 1], vertices[:, 0], morton_code(cells)))
    # Equal points are neighbours in that order: the first of each run is kept.
    sorted_v = vertices[order]
    new = np.r_[True, np.any(sorted_v[1:] != sorted_v[:-1], axis=1)]
    v = sorted_v[new]
    remap = np.empty(len(vertices), dtype=np.int64)
    remap[order] = np.cumsum(new) - 1
    f = remap[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    shift = np.argmin(f, axis=1)
    f = np.stack([f[np.arange(len(f)), (shift + k) % 3] for k in range(3)], axis=1)
    f = np.unique(f, axis=0)
    used = np.unique(f)
    keep = np.full(len(v), -1)
    keep[used] = np.arange(used.size)
    return v[used], keep[f]


def test_canonical_mesh_is_the_morton_order_without_repeats():
    # Duplicate vertices (a soup), repeated and rotated triangles (orientation kept), triangles
    # that merging makes degenerate, ties in the Morton code, unreferenced vertices: the same
    # mesh as the definition computed with lexsort and unique.
    rng = np.random.default_rng(4)
    v, f = sphere(10.0, 12)
    v = np.round(v, 1)  # ties in x (and merged poles)
    soup = v[f.ravel()]
    faces = np.arange(soup.shape[0]).reshape(-1, 3)
    faces = np.concatenate([faces, faces[:40], faces[:30][:, [1, 2, 0]], faces[:20][:, [2, 0, 1]]])
    soup = np.concatenate([soup, rng.normal(size=(5, 3))])  # unreferenced
    perm = rng.permutation(faces.shape[0])
    cv, cf = canonical_mesh(soup, faces[perm])
    rv, rf = reference_canonical_mesh(soup, faces[perm])
    np.testing.assert_array_equal(cv, rv)
    np.testing.assert_array_equal(cf, rf)
    # A reversed triangle is another triangle (the orientation is kept).
    flipped = np.concatenate([faces, faces[:1, ::-1]])
    assert canonical_mesh(soup, flipped)[1].shape[0] == cf.shape[0] + 1


def test_vertex_clustering_is_open3ds():
    # The levels of detail: the same simplified mesh as Open3D's simplify_vertex_clustering
    # (Average) followed by remove_degenerate_triangles and remove_unreferenced_vertices, in
    # canonical order. The means are summed in another order: equal to rounding.
    from o3dreg.io.mesh import to_open3d
    from o3dreg.mesh.canonical import cluster_vertices

    v, f = canonical_mesh(*sphere(10.0, 60))
    v = v + np.array([3.0, -7.0, 1.0])  # off the origin: the grid starts at the data
    for voxel in (0.8, 2.5):
        mesh = to_open3d(v, f).simplify_vertex_clustering(
            voxel, o3d.geometry.SimplificationContraction.Average
        )
        mesh.remove_degenerate_triangles()
        mesh.remove_unreferenced_vertices()
        ov, of = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        cv, cf = cluster_vertices(v, f, voxel)
        assert cv.shape == ov.shape and cf.shape == of.shape
        # Match Open3D's vertices to ours (each the mean of the same voxel's vertices).
        tree = o3d.geometry.KDTreeFlann(to_open3d(cv, cf))
        match = np.array([tree.search_knn_vector_3d(p, 1)[1][0] for p in ov])
        np.testing.assert_allclose(cv[match], ov, rtol=0, atol=1e-12 * np.abs(v).max())
        assert np.unique(match).size == match.size

        def rotated(faces):
            shift = np.argmin(faces, axis=1)
            rows = np.arange(len(faces))[:, None]
            return {tuple(t) for t in faces[rows, (shift[:, None] + np.arange(3)) % 3]}

        assert rotated(match[of]) == rotated(cf)  # the same triangles, orientation kept
        # Canonical: the triangles sorted, every vertex used.
        np.testing.assert_array_equal(cf, cf[np.lexsort(cf.T[::-1])])
        assert np.unique(cf).size == cv.shape[0]


def _open_edges_by_counting(n_vertices, faces):
    """Open edges by counting each undirected edge in a dictionary (the definition)."""
    count: dict[tuple[int, int], int] = {}
    for tri in faces.tolist():
        for k in range(3):
            a, b = tri[(k + 1) % 3], tri[(k + 2) % 3]
            edge = (min(a, b), max(a, b))
            count[edge] = count.get(edge, 0) + 1

    def key(t, k):
        a, b = t[(k + 1) % 3], t[(k + 2) % 3]
        return (min(a, b), max(a, b))

    open_edge = np.array([[count[key(t, k)] == 1 for k in range(3)] for t in faces.tolist()])
    on_boundary = np.zeros(n_vertices, dtype=bool)
    for (a, b), c in count.items():
        if c == 1:
            on_boundary[[a, b]] = True
    return open_edge, on_boundary


def test_one_edge_sort_answers_components_and_open_edges():
    # An open sphere (5% of its triangles removed), a separate triangle and a fin on one of the
    # sphere's edges (an edge of three triangles: not open).
    rng = np.random.default_rng(0)
    v, f = sphere(10.0, 12)
    f = f[rng.random(len(f)) > 0.05]
    n = len(v)
    v = np.concatenate([v, v[:3] + 50.0, [[0.0, 0.0, 30.0]]])
    f = np.concatenate([f, [[n, n + 1, n + 2]], [[f[0, 0], f[0, 1], n + 3]]]).astype(np.int64)
    edges = SortedEdges(len(v), f)
    open_edge, on_boundary = edges.open_edges()
    expected = _open_edges_by_counting(len(v), f)
    np.testing.assert_array_equal(open_edge, expected[0])
    np.testing.assert_array_equal(on_boundary, expected[1])
    # The components from the shared sort are those of a fresh one.
    shared, fresh = mesh_components(v, f, edges), mesh_components(v, f)
    np.testing.assert_array_equal(shared.labels, fresh.labels)
    assert shared.vertex_counts.tolist()[-1] == 3  # the lone triangle
    # The prepared target's open edges (given by from_mesh) are the lazily computed ones.
    target = TargetSurface.from_mesh(v, f, min_component=0.0)
    lazy = SurfaceDistanceQuery(target.vertices, target.faces).open_edges
    for given, computed in zip(target.query.open_edges, lazy):
        np.testing.assert_array_equal(given, computed)


def test_patches_wound_the_other_way_are_turned_to_their_piece_majority():
    # Two spheres; on the first a third of the triangles (one cap) wound backwards, the second
    # wound backwards entirely (a whole piece is left as it is: its majority is itself).
    v1, f1 = sphere(10.0, 20)
    v2, f2 = sphere(5.0, 10, centre=(40.0, 0.0, 0.0))
    cap = v1[f1].mean(axis=1)[:, 2] > 4.0
    assert 0.1 < cap.mean() < 0.5
    mixed = f1.copy()
    mixed[cap] = mixed[cap][:, ::-1]
    v = np.concatenate([v1, v2])
    f = np.concatenate([mixed, f2[:, ::-1] + len(v1)]).astype(np.int64)
    assert SortedEdges(len(v), f).inconsistent_edges() > 0
    assert SortedEdges(len(v1), f1.astype(np.int64)).inconsistent_edges() == 0
    oriented = oriented_faces(v, f)
    assert SortedEdges(len(v), oriented).inconsistent_edges() == 0
    expected = np.concatenate([f1, f2[:, ::-1] + len(v1)])
    np.testing.assert_array_equal(oriented, expected)  # the cap turned back, nothing else
    # The prepared target: consistent, and the same surface as from the well-wound input.
    target = TargetSurface.from_mesh(v, f)
    reference = TargetSurface.from_mesh(v, expected)
    np.testing.assert_array_equal(target.faces, reference.faces)
    np.testing.assert_array_equal(target.vertices, reference.vertices)


def grid_patch(x0: float, x1: float, spacing: float):
    """A flat rectangle ``[x0, x1] x [0, 100]`` (z = 0) triangulated on a square grid."""
    xs = np.arange(x0, x1 + spacing / 2, spacing)
    ys = np.arange(0.0, 100.0 + spacing / 2, spacing)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    k = np.arange(x.size).reshape(x.shape)[:-1, :-1].ravel()
    ny = ys.size
    f = np.concatenate([np.stack([k, k + ny, k + ny + 1], 1), np.stack([k, k + ny + 1, k + 1], 1)])
    return v, f


def test_subsample_points_stand_for_the_area_around_them():
    # Two halves of equal area, one sampled 16 times as densely: the budget is more than the
    # sparse half has vertices, so the subsample takes all of those and fills up with the dense
    # half. Counted per point, the sparse half would weigh a quarter of the sample; by the
    # areas its points stand for, half (to the cells straddling the seam, a few percent).
    dense, sparse = grid_patch(0.0, 50.0, 0.5), grid_patch(50.0 + 1e-6, 100.0, 2.0)
    v = np.concatenate([dense[0], sparse[0]])
    f = np.concatenate([dense[1], sparse[1] + len(dense[0])])
    target = TargetSurface.from_mesh(v, f)
    points = target.subsample(10000)
    areas = target.subsample_areas(10000)
    assert areas.shape == (points.shape[0],)
    right = points[:, 0] > 50.0
    assert right.sum() < 0.25 * points.shape[0]
    assert abs(areas[right].sum() / areas.sum() - 0.5) < 0.05
    np.testing.assert_allclose(areas.mean(), 1.0, rtol=1e-12)


def test_an_evenly_sampled_target_gives_its_subsample_even_areas():
    target = TargetSurface.from_mesh(*sphere(10.0, 60))
    for budget in (2000, 500):
        areas = target.subsample_areas(budget)
        # Cells of ~10 points: their sums vary with how a cell cuts the sphere, by tens of
        # percent, not by the factor of a density change.
        low, high = np.percentile(areas, [5, 95])
        assert 0.6 < low and high < 1.6
