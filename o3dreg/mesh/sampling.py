"""Order-independent spatial subsampling of point sets."""

from __future__ import annotations

import numpy as np

from .._geometry import bounds
from .distinct import distinct_ranks, sort_keys

__all__ = ["morton_order", "spatial_subsample", "spatial_subsample_weights", "voxel_ranks"]


def spatial_subsample(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of about ``count`` points spread evenly over ``points``.

    One point per occupied cell of a regular grid (the one nearest the cell centre), with the cell
    size chosen so that about ``count`` cells are occupied. The choice depends on the positions
    only, not on the order of the points, so results do not change when a mesh's vertices are
    renumbered.

    Returns
    -------
    (k,) int ndarray
        Sorted indices, ``k <= len(points)``; all indices when ``count >= len(points)``.
    """
    return _subsample(points, count, None)[0]


def spatial_subsample_weights(
    points: np.ndarray, count: int, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points of :func:`spatial_subsample`, each with the summed ``weights`` of the points of
    its cell (what it stands for: with vertex areas, the area around it).

    Returns
    -------
    indices : (k,) int ndarray
        As :func:`spatial_subsample`.
    summed : (k,) float ndarray
        Per chosen point, the sum of ``weights`` over its cell; ``weights`` itself when every
        point is kept. The sums add up to ``weights.sum()`` (to rounding).
    """
    indices, summed = _subsample(points, count, weights)
    assert summed is not None
    return indices, summed


def _subsample(
    points: np.ndarray, count: int, weights: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`spatial_subsample`, and with ``weights`` the sums of
    :func:`spatial_subsample_weights`."""
    n = points.shape[0]
    if count >= n:
        return np.arange(n), None if weights is None else np.asarray(weights, dtype=np.float64)
    lo, hi = bounds(points)
    extent = float((hi - lo).max()) or 1.0
    # Points on a surface occupy cells in proportion to (extent / cell)^2: start there, then
    # adjust the cell size a few times towards the requested count.
    cell = extent / np.sqrt(count)
    for attempt in range(8):
        keys = np.floor((points - lo) / cell).astype(np.int64)
        # The largest key of each axis is that of the largest coordinate (floor and division are
        # monotone): no reduction over the keys.
        dims = np.floor((hi - lo) / cell).astype(np.int64) + 1
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        # The cells by one sort of their keys: counted here, and their points grouped below.
        order, sorted_flat = sort_keys(flat)
        first = np.ones(n, dtype=bool)
        first[1:] = sorted_flat[1:] != sorted_flat[:-1]
        ratio = np.count_nonzero(first) / count
        if 0.7 <= ratio <= 1.4 or attempt == 7:
            break
        cell *= np.sqrt(ratio)
    d = points - (lo + (keys + 0.5) * cell)
    offset = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    # Per cell, the point nearest its centre: a minimum over each run of equal keys.
    starts = np.flatnonzero(first)
    sorted_offset = offset[order]
    nearest = np.minimum.reduceat(sorted_offset, starts)
    best = sorted_offset == np.repeat(nearest, np.diff(np.append(starts, n)))
    if np.count_nonzero(best) > starts.size:
        # Two points of a cell equally near its centre (rare): the coordinates decide, a total
        # order on distinct points, so the choice does not depend on their numbering.
        order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], offset, flat))
        chosen = order[first]
    else:
        chosen = order[best]
    # Both choices list one point per cell, in the cells' order.
    by_index = np.argsort(chosen)
    if weights is None:
        return chosen[by_index], None
    summed = np.add.reduceat(np.asarray(weights, dtype=np.float64)[order], starts)
    return chosen[by_index], summed[by_index]


def voxel_ranks(points: np.ndarray, voxel: float, origin: np.ndarray) -> np.ndarray:
    """The voxel of every point on a grid of cubes of side ``voxel`` whose first corner is
    ``origin`` (at or below every point): ranks ``0 .. k-1`` of the ``k`` occupied voxels, in the
    order of their keys (x slowest), so that points share a rank exactly when they share a voxel.
    """
    keys = np.floor((points - origin) / voxel).astype(np.int64)
    dims = bounds(keys)[1] + 1
    if float(np.prod(dims, dtype=np.float64)) < 2.0**62:
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        return distinct_ranks(flat)
    # A voxel tiny for the extent: rows of keys (the same order).
    _, ranks = np.unique(keys, axis=0, return_inverse=True)
    return np.asarray(ranks).ravel()


def _spread_bits(bits: int) -> np.ndarray:
    """For every ``v < 2**bits``, ``v`` with bit ``b`` moved to bit ``3 b`` (a Morton code's
    share of one axis)."""
    values = np.arange(1 << bits, dtype=np.int64)
    out = np.zeros_like(values)
    for bit in range(bits):
        out |= ((values >> bit) & 1) << (3 * bit)
    return out


_SPREAD_10 = _spread_bits(10)


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Indices sorting ``points`` along a Morton (Z-order) curve of ``2**bits`` cells per axis.

    Nearby points end up near each other in memory, which makes a batch of nearest-neighbour
    queries issued in this order faster (the tree nodes they visit stay in cache). Ties are
    broken by coordinates, so the order depends on the positions only.
    """
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if not 1 <= bits <= 21:
        raise ValueError(f"`bits` must be in [1, 21] (a 63-bit code), got {bits}")
    lo, hi = bounds(points)
    extent = float((hi - lo).max()) or 1.0
    cells = np.minimum(((points - lo) / extent * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    spread = _SPREAD_10 if bits == 10 else _spread_bits(bits)
    code = spread[cells[:, 0]] | (spread[cells[:, 1]] << 1) | (spread[cells[:, 2]] << 2)
    return _break_ties(sort_keys(code)[0], code, (points[:, 2], points[:, 1], points[:, 0]))


def _break_ties(order: np.ndarray, primary: np.ndarray, keys: tuple[np.ndarray, ...]) -> np.ndarray:
    """``order`` (an argsort of ``primary``) as ``np.lexsort((*keys, primary))`` orders: each run
    of equal ``primary`` values (and only those) sorted by ``keys`` (the last most significant),
    then by index. Taken in their positions' order, the runs come in ``primary`` order, so
    sorting their points by ``(primary, keys, index)`` and putting them back fills every run's
    positions with its own points."""
    sorted_primary = primary[order]
    same = sorted_primary[1:] == sorted_primary[:-1]
    if same.any():
        tied = np.zeros(order.size, dtype=bool)
        tied[1:] = same
        tied[:-1] |= same
        at = np.flatnonzero(tied)
        run = order[at]
        order[at] = run[np.lexsort((run, *(k[run] for k in keys), primary[run]))]
    return order
