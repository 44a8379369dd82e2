"""Point-to-surface distances with libigl's AABB tree, built once per surface."""

from __future__ import annotations

from functools import cached_property
from typing import Any

import igl
import numpy as np
from scipy.spatial import cKDTree

from .._geometry import apply_transformation, barycentric, face_cross, into_frame, row_norms
from ..mesh.edges import SortedEdges

__all__ = ["FramedQuery", "SurfaceDistanceQuery"]

#: Below this many triangles, :meth:`SurfaceDistanceQuery.closest_few` builds the full tree
#: (a fraction of a second).
CLOSEST_FEW_MIN_FACES = 200_000

#: Unless it has at least this many triangles per query point: a handful of points (a fine
#: level's cover check on the template) are answered by the tree of the triangles near them,
#: built in a third of the whole surface's time.
CLOSEST_FEW_FACES_PER_POINT = 64

#: A point whose closest surface point lies on the open boundary is beyond it when its offset
#: along the surface exceeds this fraction of the mean edge. A tolerance pulls every template
#: vertex within it onto the rim, and through the lattice drags its neighbours along the
#: surface towards the data; a tenth of an edge only absorbs rounding (the cut targets of
#: docs/robustness.md measure both).
BEYOND_BOUNDARY_TOLERANCE = 0.1


class SurfaceDistanceQuery:
    """Closest points on a triangle mesh, for many queries against one surface.

    The AABB tree is built once, on the first :meth:`closest` (the expensive part), and reused by
    every later call, as the registration queries the same target surface at each iteration. A
    surface queried only a few times (a large target seen through its levels of detail) answers
    :meth:`closest_few` without it.

    Parameters
    ----------
    vertices : (n, 3) ndarray
    faces : (m, 3) int ndarray
        A valid triangle mesh (see :func:`o3dreg._validation.as_mesh_arrays`).
    open_edges : tuple of ndarray, optional
        :attr:`open_edges` of this mesh, where the caller has them (computed from
        :class:`~o3dreg.mesh.edges.SortedEdges` of the same faces).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        open_edges: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if open_edges is not None:
            self.__dict__["open_edges"] = open_edges  # the cached property, known already

    @cached_property
    def _tree(self) -> Any:
        tree = igl.AABB()
        tree.init(self.vertices, self.faces)
        return tree

    @property
    def has_tree(self) -> bool:
        """Whether the AABB tree is built (by the first :meth:`closest`)."""
        return "_tree" in self.__dict__

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit normal of every triangle, ``(m, 3)`` (computed on first use)."""
        return self._normals(self.faces)

    def face_normal(self, face: np.ndarray) -> np.ndarray:
        """Unit normals of the triangles ``face`` (indices), ``(k, 3)``: the rows of
        :attr:`face_normals`, computed all at once for a surface queried often (its tree is
        built, which costs far more), else only those asked for."""
        if "face_normals" in self.__dict__ or self.has_tree:
            return self.face_normals.take(face, axis=0)  # rows gathered faster than by [face]
        return self._normals(self.faces[face])

    def _normals(self, faces: np.ndarray) -> np.ndarray:
        normals = face_cross(self.vertices, faces)
        length = row_norms(normals)[:, None]
        return normals / np.where(length > 0, length, 1.0)

    def __repr__(self) -> str:
        return (
            f"SurfaceDistanceQuery(vertices={self.vertices.shape[0]}, faces={self.faces.shape[0]})"
        )

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface point of each query point (libigl's ``AABB.squared_distance``).

        Returns
        -------
        distances : (k,) ndarray
            Euclidean point-to-surface distances (not squared).
        face_index : (k,) int ndarray
            Triangle holding each closest point.
        closest : (k, 3) ndarray
            The closest points.
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        sqr, face, closest = self._tree.squared_distance(self.vertices, self.faces, pts)
        return np.sqrt(sqr), np.asarray(face, dtype=np.int64).ravel(), closest

    def closest_few(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`closest` for a few points on a large surface whose tree is not built yet.

        Building the AABB tree of a million-vertex surface costs seconds and hundreds of MB; a
        k-d tree of its vertices costs a tenth of that and bounds where the closest triangles
        are. The nearest vertex of a point ``x``, at distance ``r``, bounds its distance to the
        surface: ``d <= r``. Every point of a triangle lies within ``L / sqrt(3)`` of one of its
        corners (``L`` its longest edge; equality at an equilateral triangle's centre), so the
        closest triangle has a corner ``w`` with ``|x - w| <= r + reach(w)``, ``reach(w)`` the
        longest edge of the triangles around ``w`` over ``sqrt(3)``. The AABB tree of the
        triangles with such a corner gives the same distances and closest points as the full
        tree (the minimum over a set holding the closest triangle, computed the same way); where
        several triangles are exactly as close (a closest point on a shared edge or corner) it may
        name another of them. Surfaces whose tree is built, small surfaces queried at more than
        one point per :data:`CLOSEST_FEW_FACES_PER_POINT` triangles, and queries that would
        gather a quarter of the triangles use the full tree.
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        m = self.faces.shape[0]
        few = pts.shape[0] * CLOSEST_FEW_FACES_PER_POINT <= m
        if self.has_tree or pts.shape[0] == 0 or (m < CLOSEST_FEW_MIN_FACES and not few):
            return self.closest(pts)
        _, reach = self.edge_measures
        used = np.flatnonzero(reach > 0)  # the corners of triangles: the others bound nothing
        sites = self.vertices[used]
        tree = cKDTree(sites, balanced_tree=False, compact_nodes=False)
        r, _ = tree.query(pts)
        # A relative margin far above rounding in |x - w| and the bounds.
        margin = 1.0 + 1e-9
        balls = tree.query_ball_point(pts, (r + reach.max()) * margin, return_sorted=False)
        counts = np.array([len(b) for b in balls])
        near = used[np.concatenate([np.asarray(b, dtype=np.int64) for b in balls])]
        owner = np.repeat(np.arange(pts.shape[0]), counts)
        gap = row_norms(self.vertices[near] - pts[owner])
        near = near[gap <= (r[owner] + reach[near]) * margin]
        corner = np.zeros(self.vertices.shape[0], dtype=bool)
        corner[near] = True
        f = self.faces
        candidates = np.flatnonzero(corner[f[:, 0]] | corner[f[:, 1]] | corner[f[:, 2]])
        if 4 * candidates.size > f.shape[0]:
            return self.closest(pts)
        dist, face, closest = SurfaceDistanceQuery(self.vertices, f[candidates]).closest(pts)
        return dist, candidates[face], closest

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Point-to-surface distances, ``(k,)``."""
        return self.closest(points)[0]

    def gradient(
        self,
        points: np.ndarray,
        return_faces: bool = False,
        found: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> Any:
        """Distances, closest points and the gradient of the unsigned distance at each point.

        The gradient of ``d(x) = |x - c(x)|`` is the unit vector ``(x - c) / d``; on the surface,
        where it is undefined, the triangle's normal is used (the point-to-plane limit). With
        ``return_faces``, the closest triangle of each point is returned fourth. ``found``:
        :meth:`closest` of these points, when the caller has it.
        """
        dist, face, closest = found if found is not None else self.closest(points)
        diff = np.ascontiguousarray(points) - closest
        on_surface = dist <= 1e-12 * max(1.0, self._largest_coordinate)
        safe = np.where(on_surface, 1.0, dist)
        grad = diff / safe[:, None]
        grad[on_surface] = self.face_normal(face[on_surface])
        if return_faces:
            return dist, closest, grad, face
        return dist, closest, grad

    @cached_property
    def _largest_coordinate(self) -> float:
        """``max |x|`` over the vertices: the scale of "on the surface" in :meth:`gradient`."""
        return float(np.abs(self.vertices).max()) if self.vertices.size else 0.0

    # -- open boundaries (partial targets) ------------------------------------------------------
    @cached_property
    def open_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Per face, which edge is open (``(m, 3)`` bool, edge ``k`` opposite corner ``k``); per
        vertex whether it lies on an open edge. Computed once, lazily (or given to the
        constructor by a caller that sorted the edges already)."""
        return SortedEdges(self.vertices.shape[0], self.faces).open_edges()

    @cached_property
    def mean_edge(self) -> float:
        """Mean length of the triangles' edges (each interior edge counted twice)."""
        lengths = self._edge_lengths
        return float(np.concatenate(lengths).mean()) if self.faces.size else 0.0

    @cached_property
    def _edge_lengths(self) -> list[np.ndarray]:
        """Length of every triangle's edge ``k`` (opposite corner ``k``), for ``k = 0, 1, 2``."""
        v, f = self.vertices, self.faces
        # One edge slot and one coordinate at a time: a million-triangle mesh needs no (m, 3)
        # temporaries of strided arithmetic.
        cols = [np.ascontiguousarray(v[:, i]) for i in range(3)]
        lengths = []
        for k in range(3):
            a, b = f[:, (k + 1) % 3], f[:, (k + 2) % 3]
            d = [col[a] - col[b] for col in cols]
            lengths.append(np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
        return lengths

    @cached_property
    def edge_measures(self) -> tuple[float, np.ndarray]:
        """The mean edge length, and per vertex its reach: the longest edge of the triangles
        around it over ``sqrt(3)`` (0 for a vertex of no triangle; see :meth:`closest_few`)."""
        v, f = self.vertices, self.faces
        reach = np.zeros(v.shape[0])
        if not f.size:
            return 0.0, reach
        lengths = self._edge_lengths
        longest = np.maximum(np.maximum(lengths[0], lengths[1]), lengths[2]) / np.sqrt(3.0)
        for k in range(3):
            np.maximum.at(reach, f[:, k], longest)
        return self.mean_edge, reach

    @property
    def has_boundary(self) -> bool:
        """Whether the surface has open edges (edges of exactly one triangle)."""
        return bool(self.open_edges[1].any())

    def beyond_boundary(
        self, points: np.ndarray, face: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        """Which points lie beyond the surface's open boundary.

        A point is beyond the boundary when its closest surface point lies on an open edge or an
        open-boundary vertex (barycentric coordinate ``<= 1e-9`` opposite an open edge) and its
        offset ``p - c`` has a component tangent to that triangle longer than a tenth of the mean
        edge length of the surface (:data:`BEYOND_BOUNDARY_TOLERANCE`):
        ``|(p - c) - ((p - c) . n) n| > e / 10``. Points beyond a cut (where the surface has no
        data) are thus not pulled onto its rim, which would drag the template along the surface
        towards the data.

        Returns
        -------
        (k,) bool ndarray
        """
        on_boundary = self.open_edges[1]
        beyond = np.zeros(points.shape[0], dtype=bool)
        if points.shape[0] == 0 or not on_boundary.any():
            return beyond
        # Only a closest point on a triangle touching the boundary can be on it.
        near = np.flatnonzero(self._touches_boundary[face])
        if near.size:
            beyond[near] = self._beyond(points[near], face[near], closest[near])
        return beyond

    def closest_with_data(
        self, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`closest`, and whether each point has data: its closest point is not beyond
        the open boundary (:meth:`beyond_boundary`; every point of a closed surface has)."""
        dist, face, closest = self.closest(points)
        return dist, face, closest, ~self.beyond_boundary(points, face, closest)

    @cached_property
    def _touches_boundary(self) -> np.ndarray:
        """Per triangle: whether an edge or a corner of it lies on the open boundary."""
        open_edge, on_boundary = self.open_edges
        return np.asarray(open_edge.any(axis=1) | on_boundary[self.faces].any(axis=1))

    def _beyond(self, points: np.ndarray, face: np.ndarray, closest: np.ndarray) -> np.ndarray:
        open_edge, on_boundary = self.open_edges
        diff = points - closest
        n = self.face_normal(face)
        tangent = diff - (diff * n).sum(axis=1, keepdims=True) * n
        beyond = row_norms(tangent) > BEYOND_BOUNDARY_TOLERANCE * self.mean_edge
        # Only a point off its triangle's plane sideways can be beyond: where its closest point
        # lies is asked of those alone (most points sit straight above their triangle).
        off = np.flatnonzero(beyond)
        corners = self.faces[face[off]]
        bary = barycentric(self.vertices[corners], closest[off])
        tiny = bary <= 1e-9
        hit = (tiny & open_edge[face[off]]).any(axis=1)
        # At a corner (two coordinates ~0) the closest point is that vertex.
        vertex_hit = tiny.sum(axis=1) >= 2
        if vertex_hit.any():
            corner = np.argmax(bary[vertex_hit], axis=1)
            hit[vertex_hit] |= on_boundary[corners[vertex_hit, corner]]
        beyond[off] = hit
        return beyond


class FramedQuery(SurfaceDistanceQuery):
    """The distance query of a surface, asked in other coordinates.

    ``frame`` is the rigid transformation from these coordinates to the surface's. The surface's
    own query answers (its AABB tree, built once, is shared: distances do not depend on the
    coordinates), and so do its open edges and edge lengths, which a rigid motion leaves as they
    are; closest points come back in these coordinates, and so do the triangle normals, computed
    from the vertices moved here.

    Parameters
    ----------
    query : SurfaceDistanceQuery
        The surface in its own coordinates.
    frame : (4, 4) ndarray
        A rigid transformation (rotation and translation) from these coordinates to the
        surface's.
    """

    def __init__(self, query: SurfaceDistanceQuery, frame: np.ndarray) -> None:
        self._surface = query
        self._frame = np.asarray(frame, dtype=np.float64)
        super().__init__(into_frame(self._frame, query.vertices), query.faces)

    @property
    def has_tree(self) -> bool:
        return self._surface.has_tree

    @property  # type: ignore[override]
    def open_edges(self) -> tuple[np.ndarray, np.ndarray]:
        return self._surface.open_edges

    @property  # type: ignore[override]
    def edge_measures(self) -> tuple[float, np.ndarray]:
        return self._surface.edge_measures

    @property  # type: ignore[override]
    def mean_edge(self) -> float:
        return self._surface.mean_edge

    def _there(self, points: np.ndarray) -> np.ndarray:
        return apply_transformation(self._frame, np.asarray(points, dtype=np.float64))

    def _here(self, found: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Any:
        dist, face, closest = found
        return dist, face, into_frame(self._frame, closest)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._here(self._surface.closest(self._there(points)))  # type: ignore[no-any-return]

    def closest_few(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._here(self._surface.closest_few(self._there(points)))  # type: ignore[no-any-return]
