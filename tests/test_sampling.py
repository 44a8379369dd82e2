"""Spatial subsampling: even, sized as asked, independent of the vertex order."""

import numpy as np

from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration.sampling import spatial_subsample


def test_count_and_order_independence():
    pts = np.asarray(synthetic_form("sphere", 5000).vertices)
    idx = spatial_subsample(pts, 1000)
    # The cell size is tuned until the count is within [0.7, 1.4] of the request.
    assert 700 <= idx.size <= 1400
    perm = np.random.default_rng(0).permutation(pts.shape[0])
    idx_perm = spatial_subsample(pts[perm], 1000)
    np.testing.assert_array_equal(np.sort(pts[perm][idx_perm], axis=0), np.sort(pts[idx], axis=0))


def test_all_points_when_the_budget_allows():
    pts = np.random.default_rng(1).normal(size=(50, 3))
    np.testing.assert_array_equal(spatial_subsample(pts, 50), np.arange(50))


def test_even_coverage():
    # Every point of the sphere has a chosen point within about two cells.
    pts = np.asarray(synthetic_form("sphere", 5000).vertices)
    chosen = pts[spatial_subsample(pts, 500)]
    from scipy.spatial import cKDTree

    gap = cKDTree(chosen).query(pts)[0].max()
    cell = 80.0 / np.sqrt(500)  # sphere of diameter 80
    assert gap < 2.5 * cell


def test_ties_at_the_cell_centre_do_not_depend_on_the_order():
    # Cells of size 1 (extent 10, budget 100) holding 4 points each, mirrored about the cell
    # centre: equally near it, so the coordinates must break the tie (the full sort's fallback).
    q = np.concatenate([np.arange(10) + 0.25, np.arange(10) + 0.75])
    x, y = np.meshgrid(q, q, indexing="ij")
    grid = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.5)], axis=1)
    pts = np.concatenate([grid, [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]])
    idx = spatial_subsample(pts, 100)
    assert idx.size == 101  # 100 cells of the grid, one of the far anchor
    for seed in range(3):
        perm = np.random.default_rng(seed).permutation(pts.shape[0])
        idx_perm = spatial_subsample(pts[perm], 100)
        np.testing.assert_array_equal(
            np.sort(pts[perm][idx_perm], axis=0), np.sort(pts[idx], axis=0)
        )
