"""The nearest and second-nearest of a few thousand sites, for many points, on a uniform grid.

The barycentre term assigns every target point to its nearest moved template point at each
accepted step; the template points move, so the search structure is rebuilt each time. The grid
is built in one counting sort; each point searches the cells around its own in growing shells
and stops once no unsearched cell can hold a site nearer than its second-nearest (an exact
bound: the distance from the point to the cells outside the searched block). Compiled
(``o3dreg/_kernels.c``, through :mod:`o3dreg._compiled`), on every core, without the GIL.
"""

from __future__ import annotations

import numpy as np

from ._compiled import library, split

__all__ = ["nearest_two"]

#: Cells at most per site (the grid's memory stays linear in the sites).
CELLS_PER_SITE = 8


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
    lo = np.ascontiguousarray(s.min(axis=0))
    extent = np.maximum(s.max(axis=0) - lo, 0.0)
    # Cells about as wide as the spacing of sites on a surface filling half its box's area.
    box_area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    size = float(np.sqrt(box_area / n)) if box_area > 0 else float(extent.max())
    if not size > 0:
        size = 1.0
    dims = np.maximum(np.ceil(extent / size).astype(np.int64), 1)
    while int(np.prod(dims)) > CELLS_PER_SITE * n + 27:
        size *= 1.25
        dims = np.maximum(np.ceil(extent / size).astype(np.int64), 1)
    first = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    if library.o3dreg_grid_build(s, n, lo, size, dims, first, order) < 0:
        raise MemoryError(f"no memory for the grid of {n} sites")
    distances = np.empty((p.shape[0], 2))
    indices = np.empty((p.shape[0], 2), dtype=np.int64)
    split(
        library.o3dreg_grid_nearest_two, p.shape[0], s, first, order, lo, size, dims, p,
        distances, indices,
    )  # fmt: skip
    return distances, indices
