"""Order-independent spatial subsampling of point sets."""

from __future__ import annotations

import numpy as np

__all__ = ["morton_order", "spatial_subsample"]


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
    n = points.shape[0]
    if count >= n:
        return np.arange(n)
    lo = points.min(axis=0)
    extent = float(np.ptp(points, axis=0).max()) or 1.0
    # Points on a surface occupy cells in proportion to (extent / cell)^2: start there, then
    # adjust the cell size a few times towards the requested count.
    cell = extent / np.sqrt(count)
    for attempt in range(8):
        keys = np.floor((points - lo) / cell).astype(np.int64)
        dims = keys.max(axis=0) + 1
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        # Occupied cells, counted on the sorted keys alone (the full sort below is 5x dearer).
        sorted_flat = np.sort(flat)
        occupied = 1 + int(np.count_nonzero(sorted_flat[1:] != sorted_flat[:-1]))
        ratio = occupied / count
        if 0.7 <= ratio <= 1.4 or attempt == 7:
            break
        cell *= np.sqrt(ratio)
    offset = ((points - (lo + (keys + 0.5) * cell)) ** 2).sum(axis=1)
    # Sort by cell, then by distance to the cell centre, then by coordinates (a total order on
    # distinct points, so the choice does not depend on their numbering).
    # The coordinates only break exact ties of the offset, which are rare: sort on two keys and
    # fall back to all five only when a cell's nearest point is tied.
    order = np.lexsort((offset, flat))
    sorted_flat = flat[order]
    first = np.ones(n, dtype=bool)
    first[1:] = sorted_flat[1:] != sorted_flat[:-1]
    sorted_offset = offset[order]
    tied = ~first[1:] & first[:-1] & (sorted_offset[1:] == sorted_offset[:-1])
    if tied.any():
        order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], offset, flat))
    return np.sort(order[first])


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Indices sorting ``points`` along a Morton (Z-order) curve of ``2**bits`` cells per axis.

    Nearby points end up near each other in memory, which makes a batch of nearest-neighbour
    queries issued in this order faster (the tree nodes they visit stay in cache). Ties are
    broken by coordinates, so the order depends on the positions only.
    """
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    lo = points.min(axis=0)
    extent = float(np.ptp(points, axis=0).max()) or 1.0
    cells = np.minimum(((points - lo) / extent * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    code = np.zeros(points.shape[0], dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.lexsort((points[:, 2], points[:, 1], points[:, 0], code))
