"""The nearest and second-nearest of a few thousand sites, for many points: a uniform grid
compiled with Numba.

The barycentre term assigns every target point to its nearest moved template point at each
accepted step; the template points move, so the search structure is rebuilt each time. A grid
is built in one counting sort; each point searches the cells around its own in growing shells
and stops once no unsearched cell can hold a point nearer than its second-nearest (an exact
bound: the distance from the point to the cells outside the searched block). It runs on every
core, without the GIL.
"""

from __future__ import annotations

import numba
import numpy as np

from ._compiled import JIT, split

__all__ = ["nearest_two"]

#: Cells at most per site (the grid's memory stays linear in the sites).
CELLS_PER_SITE = 8


@numba.njit(**JIT)
def _grid(sites, origin, size, dims):  # type: ignore[no-untyped-def]
    """Sites sorted by cell (a counting sort): ``first[c]:first[c + 1]`` index ``order``."""
    n = sites.shape[0]
    cell = np.empty(n, np.int64)
    for i in range(n):
        c = 0
        for a in range(3):
            k = int((sites[i, a] - origin[a]) / size)
            c = c * dims[a] + min(max(k, 0), dims[a] - 1)
        cell[i] = c
    first = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        first[cell[i] + 1] += 1
    for c in range(1, first.size):
        first[c] += first[c - 1]
    fill = first[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):  # in index order: each cell's sites stay sorted by index
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return first, order


@numba.njit(inline="always", **JIT)
def _outside(p, lo, hi):  # type: ignore[no-untyped-def]
    """Distance from ``p`` to the interval ``[lo, hi]`` (0 inside)."""
    return max(lo - p, 0.0, p - hi)


@numba.njit(inline="always", **JIT)
def _visit(sites, first, order, cell, p0, p1, p2, d1, i1, d2, i2):  # type: ignore[no-untyped-def]
    """The best two so far, updated with the sites of ``cell``."""
    for k in range(first[cell], first[cell + 1]):
        i = order[k]
        e0 = sites[i, 0] - p0
        e1 = sites[i, 1] - p1
        e2 = sites[i, 2] - p2
        d = e0 * e0 + e1 * e1 + e2 * e2
        # Lexicographic in (distance, index): exact ties go to the smaller index.
        if d < d1 or (d == d1 and i < i1):
            d2, i2 = d1, i1
            d1, i1 = d, i
        elif d < d2 or (d == d2 and i < i2):
            d2, i2 = d, i
    return d1, i1, d2, i2


@numba.njit(inline="always", **JIT)
def _axis(p, origin, size, dim):  # type: ignore[no-untyped-def]
    """The point's cell on one axis (clamped to the grid) and its distance to the grid's
    extent there."""
    k = int(np.floor((p - origin) / size))
    return min(max(k, 0), dim - 1), _outside(p, origin, origin + dim * size)


@numba.njit(inline="always", **JIT)
def _gap(p, origin, size, dim, c, r):  # type: ignore[no-untyped-def]
    """Distance from ``p`` to the grid's cells outside ``[c - r, c + r]`` on one axis."""
    gap = np.inf
    if c - r > 0:
        gap = max(p - (origin + (c - r) * size), 0.0)
    if c + r < dim - 1:
        gap = min(gap, max(origin + (c + r + 1) * size - p, 0.0))
    return gap


@numba.njit(**JIT)
def _search(sites, first, order, origin, size, dims, points, out_d, out_i, begin, end):  # type: ignore[no-untyped-def]
    n0, n1, n2 = dims[0], dims[1], dims[2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for j in range(begin, end):
        p0, p1, p2 = points[j, 0], points[j, 1], points[j, 2]
        c0, a0 = _axis(p0, o0, size, n0)
        c1, a1 = _axis(p1, o1, size, n1)
        c2, a2 = _axis(p2, o2, size, n2)
        d1 = d2 = np.inf
        i1 = i2 = -1
        r = 0
        while True:
            # The shell of cells at Chebyshev distance r from the point's cell.
            for x in range(max(c0 - r, 0), min(c0 + r, n0 - 1) + 1):
                for y in range(max(c1 - r, 0), min(c1 + r, n1 - 1) + 1):
                    row = (x * n1 + y) * n2
                    if abs(x - c0) == r or abs(y - c1) == r:
                        for z in range(max(c2 - r, 0), min(c2 + r, n2 - 1) + 1):
                            d1, i1, d2, i2 = _visit(
                                sites, first, order, row + z, p0, p1, p2, d1, i1, d2, i2
                            )
                    else:  # inside the shell's x-y extent: only its two z faces
                        if c2 - r >= 0:
                            d1, i1, d2, i2 = _visit(
                                sites, first, order, row + c2 - r, p0, p1, p2, d1, i1, d2, i2
                            )
                        if c2 + r < n2:
                            d1, i1, d2, i2 = _visit(
                                sites, first, order, row + c2 + r, p0, p1, p2, d1, i1, d2, i2
                            )
            # The nearest unsearched cell lies outside the block [c - r, c + r] on some axis:
            # its squared distance is at least the gap to that side plus the point's distance
            # to the grid's extent along the other two axes.
            g0 = _gap(p0, o0, size, n0, c0, r)
            g1 = _gap(p1, o1, size, n1, c1, r)
            g2 = _gap(p2, o2, size, n2, c2, r)
            bound = min(
                g0 * g0 + a1 * a1 + a2 * a2,
                g1 * g1 + a0 * a0 + a2 * a2,
                g2 * g2 + a0 * a0 + a1 * a1,
            )
            if d2 < bound or bound == np.inf:
                break
            r += 1
        out_d[j, 0], out_d[j, 1] = np.sqrt(d1), np.sqrt(d2)
        out_i[j, 0], out_i[j, 1] = i1, i2


def nearest_two(sites: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the nearest and second-nearest site of every point.

    Exact; ties in distance go to the smaller site index. With one site the second distance is
    ``inf`` and its index -1.

    Parameters
    ----------
    sites : (n, 3) ndarray
        At least one site.
    points : (k, 3) ndarray

    Returns
    -------
    distances : (k, 2) ndarray
    indices : (k, 2) int64 ndarray
    """
    s = np.ascontiguousarray(sites, dtype=np.float64)
    p = np.ascontiguousarray(points, dtype=np.float64)
    n = s.shape[0]
    lo, hi = s.min(axis=0), s.max(axis=0)
    extent = np.maximum(hi - lo, 0.0)
    # Cells about as wide as the spacing of sites on a surface filling half its box's area.
    box_area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    size = float(np.sqrt(box_area / n)) if box_area > 0 else float(extent.max())
    if not size > 0:
        size = 1.0
    dims = np.maximum(np.ceil(extent / size).astype(np.int64), 1)
    while int(np.prod(dims)) > CELLS_PER_SITE * n + 27:
        size *= 1.25
        dims = np.maximum(np.ceil(extent / size).astype(np.int64), 1)
    first, order = _grid(s, lo, size, dims)
    distances = np.empty((p.shape[0], 2))
    indices = np.empty((p.shape[0], 2), dtype=np.int64)
    split(_search, p.shape[0], s, first, order, lo, size, dims, p, distances, indices)
    return distances, indices
