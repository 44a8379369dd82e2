"""Spatial subsampling: even, sized as asked, independent of the vertex order."""

import numpy as np
import pytest
from _helpers import morton_code

from o3dreg.app.synthetic import synthetic_form
from o3dreg.mesh import distinct as _distinct
from o3dreg.mesh.sampling import morton_order, spatial_subsample


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


def test_occupied_cells_counted_on_a_bitmap_or_by_sorting_agree(monkeypatch):
    # Small grids count occupied cells on a bitmap, large ones by sorting the keys: the same
    # count, so the same cell size and the same subsample.
    pts = np.asarray(synthetic_form("sphere", 5000).vertices)
    bitmap = spatial_subsample(pts, 700)
    monkeypatch.setattr(_distinct, "_BITMAP_PER_VALUE", 0)
    monkeypatch.setattr(_distinct, "_BITMAP_FLOOR", 0)
    np.testing.assert_array_equal(spatial_subsample(pts, 700), bitmap)


def test_each_cell_keeps_its_point_nearest_the_centre():
    pts = np.random.default_rng(2).uniform(0.0, 10.0, size=(4000, 3))
    idx = spatial_subsample(pts, 300)
    chosen = pts[idx]
    # Recover the grid from the chosen points' cells: no other point of a chosen point's cell
    # is nearer that cell's centre. Cell size found as spatial_subsample does (same search).
    lo, extent = pts.min(axis=0), np.ptp(pts, axis=0).max()
    cell = extent / np.sqrt(300)
    for _ in range(8):
        keys = np.floor((pts - lo) / cell).astype(np.int64)
        occupied = np.unique(keys, axis=0).shape[0]
        if 0.7 <= occupied / 300 <= 1.4:
            break
        cell *= np.sqrt(occupied / 300)
    assert np.unique(keys, axis=0).shape[0] == idx.size  # one point per occupied cell
    offset = np.linalg.norm(pts - (lo + (keys + 0.5) * cell), axis=1)
    for i in idx[:50]:
        same = np.all(keys == keys[i], axis=1)
        assert offset[i] == offset[same].min()
    assert chosen.shape == (idx.size, 3)


def test_morton_order_follows_the_curve_and_breaks_ties_by_coordinates():
    rng = np.random.default_rng(3)
    # Few bits, so many points share a code; exact duplicates too.
    pts = np.round(rng.uniform(0.0, 1.0, size=(3000, 3)), 2)
    pts = np.concatenate([pts, pts[:100]])
    order = morton_order(pts, bits=3)
    lo, extent = pts.min(axis=0), np.ptp(pts, axis=0).max()
    cells = np.minimum(((pts - lo) / extent * 8).astype(np.int64), 7)
    code = morton_code(cells)
    # Z-order: codes never decrease; among equal codes, (x, y, z) never decreases.
    key = np.column_stack([code, pts])[order]
    np.testing.assert_array_equal(np.lexsort(key.T[::-1]), np.arange(key.shape[0]))
    # The order depends on the positions only.
    for seed in range(3):
        perm = np.random.default_rng(seed).permutation(pts.shape[0])
        np.testing.assert_array_equal(pts[perm][morton_order(pts[perm], bits=3)], pts[order])
    # The default 10 bits: the code of every point as the bit-by-bit definition.
    cells10 = np.minimum(((pts - lo) / extent * 1024).astype(np.int64), 1023)
    code10 = morton_code(cells10)[morton_order(pts)]
    assert np.all(np.diff(code10) >= 0)


def test_weighted_subsample_sums_each_cells_weights():
    from o3dreg.mesh.sampling import spatial_subsample_weights

    rng = np.random.default_rng(5)
    pts = rng.uniform(0.0, 10.0, size=(3000, 3))
    weights = rng.uniform(0.5, 2.0, size=3000)
    idx, summed = spatial_subsample_weights(pts, 300, weights)
    # The same points as the unweighted subsample, and every weight counted once.
    np.testing.assert_array_equal(idx, spatial_subsample(pts, 300))
    np.testing.assert_allclose(summed.sum(), weights.sum(), rtol=1e-12)
    # Unit weights count the points of each cell: the cells partition the points.
    _, counts = spatial_subsample_weights(pts, 300, np.ones(3000))
    assert counts.min() >= 1 and counts.sum() == 3000
    # Renumbering the points moves the weights with them.
    perm = rng.permutation(3000)
    idx_p, summed_p = spatial_subsample_weights(pts[perm], 300, weights[perm])
    by_point = {tuple(p): w for p, w in zip(pts[idx], summed)}
    for p, w in zip(pts[perm][idx_p], summed_p):
        assert by_point[tuple(p)] == pytest.approx(w, rel=1e-12)


def test_weighted_subsample_keeps_the_weights_when_every_point_is_kept():
    from o3dreg.mesh.sampling import spatial_subsample_weights

    pts = np.random.default_rng(1).normal(size=(50, 3))
    weights = np.arange(50.0)
    idx, summed = spatial_subsample_weights(pts, 50, weights)
    np.testing.assert_array_equal(idx, np.arange(50))
    np.testing.assert_array_equal(summed, weights)
