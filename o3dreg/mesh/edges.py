"""The edges of a triangle mesh, sorted once for the two questions asked of them: which triangles
share an edge (connected components) and which edges belong to one triangle only (open edges).

Each (triangle, edge slot) entry gets one int64 key per undirected edge; a stable sort of the
keys puts the entries of one edge next to each other. On a million-triangle target the sort is
most of either answer's cost, so the target's preparation sorts once and asks both.
"""

from __future__ import annotations

import numpy as np

from .distinct import sort_keys


class SortedEdges:
    """The edge entries of ``faces`` sorted by undirected edge.

    Slot ``k`` of a triangle is its edge joining corners ``k + 1`` and ``k + 2`` (opposite corner
    ``k``); entry ``e`` is slot ``e % 3`` of triangle ``e // 3``.

    Parameters
    ----------
    n_vertices : int
        Number of vertices the faces index.
    faces : (m, 3) int ndarray
        Triangles without a repeated corner (the caller has checked them).
    """

    def __init__(self, n_vertices: int, faces: np.ndarray) -> None:
        self.faces = faces
        self.n_vertices = int(n_vertices)
        n = np.int64(n_vertices)
        # One edge slot at a time: a million-triangle mesh needs no (m, 3) temporaries of
        # strided arithmetic beyond the key itself.
        key = np.empty(faces.shape, dtype=np.int64)
        forward = np.empty(faces.shape, dtype=bool)
        for k in range(3):
            a, b = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
            key[:, k] = np.minimum(a, b) * n + np.maximum(a, b)
            forward[:, k] = a < b
        self._forward = forward.ravel()
        # Stable: ties keep the entries' order, so the result does not depend on the sort's
        # internals.
        self.order, ordered = sort_keys(key)
        #: ``same[i]``: sorted entries ``i`` and ``i + 1`` are the same edge.
        self.same = ordered[1:] == ordered[:-1]

    def triangle_links(self) -> tuple[np.ndarray, np.ndarray]:
        """Pairs of triangles sharing an edge: consecutive entries of one edge (a chain where
        three or more triangles share it), as two index arrays."""
        triangle = self.order // 3
        return triangle[:-1][self.same], triangle[1:][self.same]

    def open_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Per triangle, which slot is an open edge (an edge of no other triangle), ``(m, 3)``
        bool; per vertex, whether it lies on an open edge, ``(n,)`` bool."""
        m = self.faces.shape[0]
        entries = self.order[self._runs_of(1)]
        open_edge = np.zeros(3 * m, dtype=bool)
        open_edge[entries] = True
        triangle, slot = entries // 3, entries % 3
        on_boundary = np.zeros(self.n_vertices, dtype=bool)
        on_boundary[self.faces[triangle, (slot + 1) % 3]] = True
        on_boundary[self.faces[triangle, (slot + 2) % 3]] = True
        return open_edge.reshape(m, 3), on_boundary

    def inconsistent_edges(self) -> int:
        """Edges of exactly two triangles that run along it the same way: where the triangles'
        orientations disagree (0 on a consistently oriented mesh)."""
        pairs = self._runs_of(2)  # the first entry of each edge of exactly two triangles
        first = self.order[pairs]
        second = self.order[np.flatnonzero(pairs) + 1]
        return int(np.count_nonzero(self._forward[first] == self._forward[second]))

    def _runs_of(self, length: int) -> np.ndarray:
        """Per sorted entry, whether it starts a run of exactly ``length`` (1 or 2) entries of
        one edge."""
        same = self.same
        if self.order.size == 0:
            return np.zeros(0, dtype=bool)
        starts = np.ones(same.size + 1, dtype=bool)  # not the continuation of a run
        starts[1:] &= ~same
        if length == 1:
            starts[:-1] &= ~same  # and not continued
            return starts
        starts[:-1] &= same  # continued once...
        starts[:-2] &= ~same[1:]  # ...and not twice
        starts[-1] = False
        return starts
