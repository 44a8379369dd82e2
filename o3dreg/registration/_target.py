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

import numpy as np

from .._geometry import bounds, vertex_areas
from ..mesh.canonical import canonical_mesh, cluster_vertices, oriented_faces, sorted_triangles
from ..mesh.cleaning import Components, drop_small_components, mesh_components
from ..mesh.edges import SortedEdges
from ..mesh.noise import noise_level
from ..mesh.sampling import spatial_subsample_weights, voxel_ranks
from .distance import FramedQuery, SurfaceDistanceQuery
from .result import SurfaceDistances
from .verdict import Moments, moments, reached_faces

logger = logging.getLogger("o3dreg")

#: A coarse level measures distances to the target simplified with this many voxels per cell.
TARGET_VOXELS_PER_CELL = 16.0

#: Subsample points per cell over which the area each stands for is averaged.
AREA_POINTS = 10.0


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
        # Per budget, the subsample's points and the target area each stands for (summed per
        # cell), and those areas as :meth:`subsample_areas` gives them.
        self._subsamples: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._relative_areas: dict[int, np.ndarray] = {}

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
            f = sorted_triangles(o[:, 0], o[:, 1], o[:, 2], v.shape[0])
            edges = SortedEdges(v.shape[0], f)
        if min_component is not None:
            kept_v, kept_f = drop_small_components(v, f, min_component, edges)
            if kept_f is not f:
                # The Morton order depends on the bounds, which the debris widened: the kept
                # surface in its own order, as it would be prepared without them.
                return cls(SurfaceDistanceQuery(*canonical_mesh(kept_v, kept_f)))
        return cls(SurfaceDistanceQuery(v, f, open_edges=edges.open_edges()))

    @property
    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def without_islands(self, points: np.ndarray) -> TargetSurface:
        """This target without the components that no point of ``points`` (the template,
        rigidly aligned) has its closest point on, where they are islands by the verdict's
        rule (:func:`~o3dreg.registration.verdict.reached_faces`): debris or a neighbouring
        bone the template does not model, which the levels are not to pull it towards (a
        mandible with a copy of 30% of its size beside its condyle: the condyle pulled 14% of
        the diagonal off). Itself where nothing is left out."""
        if len(self.components) < 2:
            return self
        kept = reached_faces(
            points,
            *self.mesh,
            lambda: noise_level(*self.mesh),
            components=self.components,
            query=self.query,
        )
        if kept is None:
            return self
        used = np.unique(self.faces[kept])
        index = np.full(self.vertices.shape[0], -1, dtype=np.int64)
        index[used] = np.arange(used.size)
        logger.info(
            "registration_elastic: %d target triangles of components the template does not "
            "reach left out of the levels",
            int(np.count_nonzero(~kept)),
        )
        return TargetSurface(SurfaceDistanceQuery(self.vertices[used], index[self.faces[kept]]))

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
        registration, not once per level. Ask for the largest budget first. A subsample keeps the
        target's canonical order, along a Morton curve: a batch of nearest-neighbour queries from
        its points visits the tree cache-friendly.
        """
        if budget not in self._subsamples:
            larger = [b for b in self._subsamples if b > budget]
            if larger:
                source, areas = self._subsamples[min(larger)]
            else:
                source, areas = self.vertices, vertex_areas(self.vertices, self.faces)
            keep, summed = spatial_subsample_weights(source, budget, areas)
            self._subsamples[budget] = source.take(keep, axis=0), summed
        return self._subsamples[budget][0]

    def subsample_areas(self, budget: int) -> np.ndarray:
        """The target area each point of :meth:`subsample` ``(budget)`` stands for, relative to
        their mean: 1 where the target is sampled as evenly as the budget allows.

        A subsample point stands for the vertex areas of its grid cell (summed); those sums are
        averaged over the points of coarser cells holding about :data:`AREA_POINTS` of them: the
        sample's density varies where the target's does (a part sampled finer than the budget
        allows elsewhere), not from one fine cell to the next, whose sums vary by the 1-3
        vertices a cell happens to hold.
        """
        if budget in self._relative_areas:
            return self._relative_areas[budget]
        points = self.subsample(budget)
        areas = self._subsamples[budget][1]
        total = float(areas.sum())
        if points.shape[0] < 2 or total <= 0:
            relative = np.ones(points.shape[0])
        else:
            # Cells of about AREA_POINTS points on a flat surface.
            cell = float(np.sqrt(total * AREA_POINTS / points.shape[0]))
            group = voxel_ranks(points, cell, bounds(points)[0])
            per_point = np.bincount(group, areas) / np.bincount(group)
            relative = per_point[group] / (total / points.shape[0])
        self._relative_areas[budget] = relative
        return relative

    @cached_property
    def components(self) -> Components:
        """Connected components of the target (found once: an edge sort)."""
        return mesh_components(self.vertices, self.faces)

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
