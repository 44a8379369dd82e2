"""The target surface of an elastic registration, prepared once.

:class:`TargetSurface` holds everything a registration derives from the target and nothing
else: the mesh in canonical order with its debris removed, its exact distance query, its levels
of detail (one simplified copy per coarse lattice) and its nested even subsamples (the points of
the barycentre term). The coarse-to-fine driver asks it for what a level needs; nothing hands
``(vertices, faces)`` tuples and cache dictionaries around.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property

import igl
import numpy as np

from .._distinct import distinct_ranks
from .._edges import SortedEdges
from .._geometry import bounds, face_doubled_areas
from ..volume.cleaning import mesh_components
from .distance import FramedQuery, SurfaceDistanceQuery
from .result import SurfaceDistances
from .sampling import lexicographic_order, morton_order, spatial_subsample
from .verdict import Moments, moments

logger = logging.getLogger("o3dreg")

#: A coarse level measures distances to the target simplified with this many voxels per cell.
TARGET_VOXELS_PER_CELL = 16.0


class TargetSurface:
    """The target in canonical order, without small components, with its distance query,
    levels of detail and subsamples.

    Parameters
    ----------
    query : SurfaceDistanceQuery
        The distance query of the prepared target (its vertices and faces are the target's);
        :meth:`from_mesh` prepares one from a mesh.
    """

    def __init__(self, query: SurfaceDistanceQuery) -> None:
        self.query = query
        self.vertices, self.faces = query.vertices, query.faces
        self._details: dict[float, SurfaceDistanceQuery] = {}
        self._subsamples: dict[int, np.ndarray] = {}

    @classmethod
    def from_mesh(
        cls, vertices: np.ndarray, faces: np.ndarray, min_component: float | None = None
    ) -> TargetSurface:
        """The target of a validated mesh (``as_mesh_arrays``; not modified): in canonical order,
        without components smaller than ``min_component`` of the largest (``None``: all kept;
        see :attr:`~o3dreg.DistanceEstimation.min_target_component`)."""
        v, f = canonical_mesh(vertices, faces)
        # One sort of the edges answers the orientation, the components and the open edges (a
        # million triangles: 0.4 s each time).
        edges = SortedEdges(v.shape[0], f)
        if edges.inconsistent_edges():
            o = oriented_faces(v, f)
            f = _sorted_triangles(o[:, 0], o[:, 1], o[:, 2], v.shape[0])
            edges = SortedEdges(v.shape[0], f)
        if min_component is not None:
            kept_v, kept_f = drop_small_components(v, f, min_component, edges)
            if kept_f is not f:
                return cls(SurfaceDistanceQuery(kept_v, kept_f))
        return cls(SurfaceDistanceQuery(v, f, open_edges=edges.open_edges()))

    @property
    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def in_frame(self, frame: np.ndarray) -> TargetSurface:
        """This target in the coordinates of ``frame``, a rigid transformation from them to the
        target's: the same vertices (in the same order) and triangles moved there, answered by
        this target's distance query (one AABB tree), with its own levels of detail and
        subsamples (made there, so that they do not depend on how the target lies)."""
        return TargetSurface(FramedQuery(self.query, frame))

    def build_levels_of_detail(self, voxels: Iterable[float]) -> None:
        """Simplified copies of the target for the voxel sizes ``voxels``.

        A lattice with cells of size ``h`` cannot follow surface detail much finer than ``h``;
        far from convergence, the template points of a coarse level are also far from the
        surface, where an AABB query against a dense mesh visits many boxes. Vertex clustering
        with voxels of ``h / 16`` keeps the shape to within a voxel and makes those queries
        several times faster. Only made when the voxel is at least twice the target's mean edge
        length. Finest first, each copy clustered from the previous one: a million-vertex target
        is clustered once, the coarser copies cost a fraction of that.
        """
        edge = self.query.mean_edge
        v, f = self.vertices, self.faces
        for voxel in sorted({v for v in voxels if v >= 2.0 * edge}):
            v, f = cluster_vertices(v, f, voxel)
            if f.shape[0] == 0:
                break
            self._details[voxel] = SurfaceDistanceQuery(v, f)

    def at_detail(self, voxel: float) -> SurfaceDistanceQuery:
        """The simplified target for ``voxel`` (the full target when none was made for it)."""
        return self._details.get(voxel, self.query)

    def finest_detail(self) -> SurfaceDistanceQuery:
        """The least simplified copy of the target (the full target when none was made)."""
        return self._details[min(self._details)] if self._details else self.query

    def subsample(self, budget: int) -> np.ndarray:
        """An even subsample of about ``budget`` target vertices, nested across budgets.

        The largest budget asked first is drawn from the full target once; smaller ones are drawn
        from the smallest larger one, so a million-vertex target is sorted into cells once per
        registration, not once per level. Ask for the largest budget first.
        """
        if budget in self._subsamples:
            return self._subsamples[budget]
        larger = [b for b in self._subsamples if b > budget]
        source = self._subsamples[min(larger)] if larger else self.vertices
        chosen = source[spatial_subsample(source, budget)]
        self._subsamples[budget] = chosen[morton_order(chosen)]
        return self._subsamples[budget]

    @cached_property
    def moments(self) -> Moments:
        """Area and size (the trace of the covariance) of the target, for the verdict; computed
        once."""
        return moments(self.vertices, self.faces)

    def distances(
        self, moved: np.ndarray, faces: np.ndarray, forward: np.ndarray | None = None
    ) -> DistanceArrays:
        """Distances from the moved template vertices to the target surface (``forward`` when
        the caller has them already) and from the target vertices to the moved template
        surface."""
        if forward is None:
            forward = self.query.closest_few(moved)[0]
        backward = SurfaceDistanceQuery(moved, faces).distance(self.vertices)
        return DistanceArrays(forward, backward)


@dataclass(frozen=True)
class DistanceArrays:
    """Point-to-surface distances both ways, per vertex: what the result's
    :class:`~o3dreg.SurfaceDistances` summarise and the verdict's percentiles are taken of.

    Attributes
    ----------
    forward : (n,) ndarray
        From each moved template vertex to the target surface.
    backward : (m,) ndarray
        From each target vertex to the moved template surface.
    """

    forward: np.ndarray
    backward: np.ndarray

    def summary(self) -> SurfaceDistances:
        return SurfaceDistances.from_arrays(self.forward, self.backward)


def canonical_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with its vertices and triangles in a canonical order.

    Exact duplicate vertices are merged, vertices are sorted lexicographically ``(x, y, z)``,
    each triangle is rotated (orientation kept) to start at its smallest index, triangles are
    sorted and repeated ones (and those that merging made degenerate) removed. Everything computed
    from the result is then independent of the input's vertex and face numbering, and triangle
    soups (STL) get their connectivity back, so open boundaries are found.
    """
    order = lexicographic_order(vertices)
    sorted_v = vertices[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = np.any(sorted_v[1:] != sorted_v[:-1], axis=1)
    ids = np.cumsum(new) - 1
    remap = np.empty(order.size, dtype=np.int64)
    remap[order] = ids
    v = sorted_v[new]
    f0, f1, f2 = (remap[faces[:, k]] for k in range(3))
    keep = (f0 != f1) & (f1 != f2) & (f2 != f0)
    f0, f1, f2 = f0[keep], f1[keep], f2[keep]
    if f0.size == 0:
        return v, np.zeros((0, 3), dtype=np.int64)
    return _drop_unused(v, _sorted_triangles(f0, f1, f2, v.shape[0]))


def oriented_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The triangles with each connected piece oriented one way: its majority's, by area.

    Scans and meshes from other tools may hold patches wound the other way. The template's
    normals are compared with the target's (``max_normal_angle``), so such a patch rejected
    correct correspondences: half a mandible wound backwards left 45% of the template without
    data, 2.5 mm off on average with verdict ``ok``. libigl's ``bfs_orient`` orients each piece
    like its first triangle; a piece whose first triangle was the odd one out is turned back.
    """
    oriented, piece = igl.bfs_orient(np.ascontiguousarray(faces, dtype=np.int64))
    oriented = np.asarray(oriented, dtype=np.int64)
    piece = np.asarray(piece, dtype=np.int64).ravel()
    turned = ~np.all(oriented == faces, axis=1)
    area = face_doubled_areas(vertices, faces)
    turned_area = np.bincount(piece, weights=area * turned)
    back = (turned_area > 0.5 * np.bincount(piece, weights=area))[piece]
    oriented[back] = oriented[back, ::-1]
    return oriented


def cluster_vertices(
    vertices: np.ndarray, faces: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh simplified by vertex clustering on a grid of cubes of side ``voxel``.

    Open3D's ``simplify_vertex_clustering`` with the ``Average`` contraction, followed by its
    ``remove_degenerate_triangles`` and ``remove_unreferenced_vertices``: the grid starts half a
    voxel below the smallest coordinates; the vertices of a voxel become one, their mean; a
    triangle is kept when its corners fall in three voxels, once per orientation; vertices of no
    kept triangle go. Here in NumPy, 3-4 times faster than Open3D on a million vertices, in an
    order that does not depend on the input's (voxels by key, triangles as :func:`canonical_mesh`
    sorts them) and with each mean summed in input order (Open3D sums in the order of a hash
    set, which the platform's standard library decides).
    """
    lo = bounds(vertices)[0] - 0.5 * voxel
    keys = np.floor((vertices - lo) / voxel).astype(np.int64)
    dims = bounds(keys)[1] + 1
    if float(np.prod(dims, dtype=np.float64)) < 2.0**62:
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        cluster = distinct_ranks(flat)
    else:  # a voxel tiny for the extent: rows of keys
        _, cluster = np.unique(keys, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    count = np.bincount(cluster)
    v = np.stack([np.bincount(cluster, weights=vertices[:, k]) / count for k in range(3)], axis=1)
    f0, f1, f2 = (cluster[faces[:, k]] for k in range(3))
    keep = (f0 != f1) & (f1 != f2) & (f2 != f0)
    f0, f1, f2 = f0[keep], f1[keep], f2[keep]
    v, f = _drop_unused(v, _sorted_triangles(f0, f1, f2, v.shape[0]))
    return v, f.reshape(-1, 3)


def _sorted_triangles(f0: np.ndarray, f1: np.ndarray, f2: np.ndarray, n: int) -> np.ndarray:
    """Triangles ``(f0, f1, f2)`` (no two corners equal) each rotated, orientation kept, to start
    at its smallest index, sorted lexicographically, repeats removed: ``(k, 3)``."""
    second, third = f1 < f0, f2 < np.minimum(f0, f1)  # the smallest is f1, or f2
    r0 = np.where(third, f2, np.where(second, f1, f0))
    r1 = np.where(third, f0, np.where(second, f2, f1))
    r2 = np.where(third, f1, np.where(second, f0, f2))
    m = np.int64(n)
    if n < 2**21:
        # One int64 key per triangle (three indices of 21 bits): a plain sort, decoded, is the
        # lexicographic order at a fraction of the cost of lexsort on a million triangles, and
        # repeated triangles are repeated keys.
        key = np.sort((r0 * m + r1) * m + r2)
        unique = np.ones(key.size, dtype=bool)
        unique[1:] = key[1:] != key[:-1]
        key = key[unique]
        return np.stack([key // (m * m), (key // m) % m, key % m], axis=1)
    f = np.stack([r0, r1, r2], axis=1)
    f = f[np.lexsort((f[:, 2], f[:, 1], f[:, 0]))]
    repeated = np.zeros(f.shape[0], dtype=bool)
    repeated[1:] = np.all(f[1:] == f[:-1], axis=1)
    return f[~repeated]


def _drop_unused(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without the vertices no triangle uses (renumbered in order)."""
    used = np.zeros(v.shape[0], dtype=bool)
    used[f.ravel()] = True
    if used.all():
        return v, f
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def drop_small_components(
    vertices: np.ndarray, faces: np.ndarray, fraction: float, edges: SortedEdges | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its connected components smaller than ``fraction`` of the largest (the
    arrays themselves when none is; ``edges``: the faces' sorted edges, where known)."""
    components = mesh_components(vertices, faces, edges)
    big = components.vertex_counts >= fraction * components.vertex_counts[0]
    keep = big[components.labels]
    if keep.all():
        return vertices, faces
    kept = faces[keep]
    used = np.zeros(vertices.shape[0], dtype=bool)
    used[kept.ravel()] = True
    remap = np.cumsum(used) - 1
    logger.info(
        "ignoring %d small target component(s) (%d vertices)",
        int((~big).sum()),
        int((~used).sum()),
    )
    return vertices[used], remap[kept]
