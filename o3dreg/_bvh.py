"""Exact closest points on a triangle mesh: a bounding volume hierarchy of its triangles.

The registration asks the same target for the closest points of a few thousand moving template
points tens of times per level. The tree and its query are compiled (``o3dreg/_kernels.c``,
through :mod:`o3dreg._compiled`): the query runs on every core without the GIL and takes a hint
per point, a triangle whose distance bounds the search before it starts.

The tree: each range of triangles is split in halves at the median of their box centres along
their longest extent, down to leaves of at most :data:`LEAF_SIZE` triangles; each node holds the
bounding box of its triangles. A query descends the nearer child first and skips every node
whose box is not nearer than the best triangle found so far; the closest point on a triangle is
found in the Voronoi region of the point (vertex, edge or face; Ericson, *Real-Time Collision
Detection*, 5.1.5), flat triangles (a point, a segment, collinear corners) by their edges.
"""

from __future__ import annotations

import numpy as np

from ._compiled import library, split

__all__ = ["LEAF_SIZE", "TriangleTree"]

#: Triangles per leaf at most: a leaf's triangles are tested one after the other.
LEAF_SIZE = 4


class TriangleTree:
    """Bounding volume hierarchy of a triangle mesh's triangles, for exact closest points.

    Parameters
    ----------
    vertices : (n, 3) float64 ndarray
    faces : (m, 3) int64 ndarray
        A triangle mesh with at least one triangle; indices in range.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        m = f.shape[0]
        # The compiled code trusts its indices: checked here, once, in O(m).
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or m == 0:
            raise ValueError(
                f"a closest-point tree needs (n, 3) vertices and (m >= 1, 3) faces, got "
                f"{v.shape} and {f.shape}"
            )
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(
                f"face indices must lie in [0, {v.shape[0]}), got {f.min()}..{f.max()}"
            )
        if not np.isfinite(v).all():
            raise ValueError("a closest-point tree needs finite vertex coordinates")
        # Halving a range longer than a leaf leaves halves of at least (LEAF_SIZE + 1) // 2.
        smallest = (LEAF_SIZE + 1) // 2
        capacity = max(1, 2 * -(-m // smallest))
        order = np.empty(m, dtype=np.int64)
        corners = np.empty((m, 9))
        flat = np.empty(m, dtype=np.uint8)
        start, stop, left = (np.empty(capacity, dtype=np.int64) for _ in range(3))
        box = np.empty((capacity, 6))
        count = library.o3dreg_bvh_build(
            v, f, m, LEAF_SIZE, capacity, order, corners, flat, start, stop, left, box
        )
        if count < 0:
            raise MemoryError(f"no memory for the closest-point tree of {m} triangles")
        self._start, self._stop, self._left = start[:count], stop[:count], left[:count]
        self._box = box[:count]
        # Leaves' triangles side by side, in the tree's order (``face_of``; ``rank``: inverse).
        self._corners, self._flat, self._face_of = corners, flat, order
        self._rank = np.empty_like(order)
        self._rank[order] = np.arange(m)

    def __repr__(self) -> str:
        return f"TriangleTree(faces={self._corners.shape[0]}, nodes={self._left.shape[0]})"

    def closest(
        self, points: np.ndarray, hint: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Squared distances, closest triangles and closest points of ``points`` (``(k, 3)``).

        ``hint``: per point a triangle index (or -1) whose distance starts the search; the
        answer is the same with or without it, up to which of several equally close triangles
        is named (the smallest index of those the search reaches).
        """
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        k = pts.shape[0]
        if not np.isfinite(pts).all():
            raise ValueError("closest points are asked for finite points only")
        if hint is None:
            hints = np.full(k, -1, dtype=np.int64)
        else:
            hints = np.ascontiguousarray(hint, dtype=np.int64)
            if hints.shape != (k,) or (k and hints.max() >= self._rank.shape[0]):
                raise ValueError(f"hint must hold {k} triangle indices (or -1), got {hints.shape}")
        sqr = np.empty(k)
        face = np.empty(k, dtype=np.int64)
        closest = np.empty((k, 3))
        split(
            library.o3dreg_bvh_query, k, self._corners, self._flat, self._face_of, self._rank,
            self._start, self._stop, self._left, self._box, pts, hints, sqr, face, closest,
        )  # fmt: skip
        return sqr, face, closest
