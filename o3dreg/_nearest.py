"""The nearest and second-nearest of a few thousand sites, for many points, on a uniform grid.

The barycentre term assigns every target point to its nearest moved template point at each
accepted step; the template points move, so the search structure is rebuilt each time. The grid
is built in one counting sort; each point searches the cells around its own in growing shells
and stops once no unsearched cell can hold a site nearer than its second-nearest (an exact
bound: the distance from the point to the cells outside the searched block). Compiled
(``o3dreg/_kernels.c``, through :mod:`o3dreg._compiled`), on every core, without the GIL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._compiled import library, split
from ._geometry import bounds

__all__ = ["Assignment", "SiteGrid", "nearest_two"]

#: Cells at most per site (the grid's memory stays linear in the sites).
CELLS_PER_SITE = 8


class SiteGrid:
    """A uniform grid of sites (``(n, 3)``, at least one), sorted into cells in one counting
    sort."""

    def __init__(self, sites: np.ndarray) -> None:
        s = np.ascontiguousarray(sites, dtype=np.float64)
        n = s.shape[0]
        # The compiled search turns coordinates into cell numbers: they must be finite.
        if s.ndim != 2 or s.shape[1] != 3 or n == 0 or not np.isfinite(s).all():
            raise ValueError(f"sites must be (n >= 1, 3) finite coordinates, got {s.shape}")
        lo, hi = bounds(s)
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
        first = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
        order = np.empty(n, dtype=np.int64)
        if library.o3dreg_grid_build(s, n, lo, size, dims, first, order) < 0:
            raise MemoryError(f"no memory for the grid of {n} sites")
        self.sites = s
        self._grid = (first, order, lo, size, dims)

    def nearest_two(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`nearest_two` of ``points`` among these sites."""
        p = _finite_points(points)
        distances = np.empty((p.shape[0], 2))
        indices = np.empty((p.shape[0], 2), dtype=np.int64)
        split(
            library.o3dreg_grid_nearest_two, p.shape[0], self.sites, *self._grid, p, distances,
            indices,
        )  # fmt: skip
        return distances, indices

    def reassign(
        self, points: np.ndarray, path: np.ndarray, moved: float, state: Assignment, every: bool
    ) -> np.ndarray:
        """Update the nearest site of each point where it may have changed (every point's with
        ``every``), and return each point's distance to it.

        The sites have moved along paths of length ``path`` (per site) and ``moved`` (the sum of
        the largest moves) since the first assignment. A point is searched again unless its
        nearest site is still provably nearest: ``own + (moved - mark) < gap``, ``own`` its
        nearest site's path since its last search (see ``BarycentreTerm.measure``).
        """
        p = _finite_points(points)
        k = p.shape[0]
        if any(a.shape != (k,) for a in (state.nearest, state.gap, state.mark, state.path_mark)):
            raise ValueError(f"the assignment must hold one entry per point ({k})")
        if k and not 0 <= state.nearest.min() <= state.nearest.max() < self.sites.shape[0]:
            raise ValueError("the assignment names sites that do not exist")
        if np.shape(path) != (self.sites.shape[0],):
            raise ValueError(f"path must hold one length per site ({self.sites.shape[0]})")
        distance = np.empty(k)
        split(
            library.o3dreg_grid_reassign, p.shape[0], self.sites, *self._grid, p,
            np.ascontiguousarray(path, dtype=np.float64), float(moved), int(every),
            state.nearest, state.gap, state.mark, state.path_mark, distance,
        )  # fmt: skip
        return distance


def _finite_points(points: np.ndarray) -> np.ndarray:
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(p).all():
        raise ValueError("the nearest sites are asked for finite points only")
    return p


@dataclass
class Assignment:
    """Each point's nearest site and what proves it still nearest (updated in place by
    :meth:`SiteGrid.reassign`): the gap between its second and first distances at its last
    search, the sites' summed largest moves then (``mark``), its nearest site's path then."""

    nearest: np.ndarray
    gap: np.ndarray
    mark: np.ndarray
    path_mark: np.ndarray

    @classmethod
    def empty(cls, k: int) -> Assignment:
        return cls(np.zeros(k, dtype=np.int64), np.zeros(k), np.zeros(k), np.zeros(k))


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
    return SiteGrid(sites).nearest_two(points)
