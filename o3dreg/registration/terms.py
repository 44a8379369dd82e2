"""The distance terms of the elastic cost, eq. (3) of Berar et al. (2005): small value types
the user composes in :class:`~o3dreg.DistanceEstimation`, as Open3D's ``TransformationEstimation``
and ``RobustKernel``.

Each holds its settings; at every level, :meth:`DistanceTerm.bind` makes its residuals for that
level (a ``DistanceTermAtLevel`` of ``o3dreg.registration._terms``: residuals, Jacobian rows,
share of the normal equations) from what the level offers (:class:`TermContext`). The level
problem (``o3dreg.registration._cost``) sums the bound terms and the level's regulariser
(:attr:`~o3dreg.ElasticLevel.regularization`).

A new term is one class here (a subclass of :class:`DistanceTerm` whose ``bind`` returns a
``PullTerm`` of ``_terms`` when the term pulls points towards points, or its own level class
there) plus one entry in the contract tests (tests/registration/test_terms.py);
:meth:`DistanceEstimation.compose <o3dreg.DistanceEstimation.compose>` takes it as it is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .._validation import check_bool, check_positive
from ._assembly import NormalAssembly
from ._terms import BarycentreTerm, DistanceTermAtLevel, PointToSurfaceTerm, uncovered_candidates
from .distance import SurfaceDistanceQuery

__all__ = [
    "BARYCENTRE_WEIGHTINGS",
    "Barycentre",
    "DistanceTerm",
    "PointToSurface",
    "TargetSamples",
    "TermContext",
    "WholeTarget",
]

#: How the barycentre rows are weighted (:attr:`Barycentre.weighting`).
BARYCENTRE_WEIGHTINGS = ("count", "uniform")


class TargetSamples(Protocol):
    """Even subsamples of a level's target, for the terms that measure from the target."""

    def points(self, per_point: float) -> np.ndarray:
        """About ``per_point`` target vertices per template point of the level, ``(k, 3)``."""
        ...

    def areas(self, per_point: float) -> np.ndarray | None:
        """The target area each of :meth:`points` ``(per_point)`` stands for, relative to
        their mean, ``(k,)`` (``None``: not known; every point counts alike)."""
        ...


@dataclass(frozen=True)
class WholeTarget:
    """:class:`TargetSamples` that are every vertex of the target, without areas."""

    vertices: np.ndarray

    def points(self, per_point: float) -> np.ndarray:
        return self.vertices

    def areas(self, per_point: float) -> np.ndarray | None:
        return None


@dataclass(frozen=True)
class TermContext:
    """What a level offers its distance terms.

    Attributes
    ----------
    assembly : NormalAssembly
        The level's trilinear weights ``W`` (the moved points are ``y = points + W u``, ``u`` the
        displacements of the free lattice nodes) and its normal-equation pattern.
    points : (n, 3) ndarray
        The template points the level is posed on, moved by the coarser levels (``y`` at
        ``u = 0``).
    indices : (n,) int ndarray
        Their numbers among the template's vertices. A coarse level is posed on an even
        subsample of the template (:attr:`~o3dreg.ElasticLevel.points_per_node`): a term tied
        to given vertices (landmarks) has rows only at the levels whose subsample holds them
        (``points_per_node=None`` poses a level on every vertex).
    target : SurfaceDistanceQuery
        The surface the level measures distances to (the target or its level of detail).
    target_samples : TargetSamples
        Even subsamples of the target's vertices, about ``per_point`` of them per point of
        ``points`` (:meth:`~TargetSamples.points`), and the target area each stands for
        (:meth:`~TargetSamples.areas`).
    symmetric_scale : float
        The level's :attr:`~o3dreg.ElasticLevel.symmetric_scale`.
    voronoi_offsets : callable or None
        ``voronoi_offsets()``: the offset from each point to the centroid of its own Voronoi
        cell on the template surface moved by the coarser levels (``None``: not offered).
    barycentre_reach : float or None
        The level's :attr:`~o3dreg.ElasticLevel.barycentre_reach`.
    nearest_known : callable or None
        ``nearest_known(sample)``: the nearest of ``points`` of every point of a target sample
        and its distance, where the previous level's search state has them (else ``None``).
    cell_size : float
        The level's smallest lattice cell edge.
    template_mesh : callable or None
        ``template_mesh()``: every template vertex moved by the coarser levels, and the
        template's faces (``None``: not offered).
    """

    assembly: NormalAssembly
    points: np.ndarray
    indices: np.ndarray
    target: SurfaceDistanceQuery
    target_samples: TargetSamples
    symmetric_scale: float = 1.0
    voronoi_offsets: Callable[[], np.ndarray] | None = None
    barycentre_reach: float | None = None
    nearest_known: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None] | None = None
    cell_size: float = np.inf
    template_mesh: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None


@dataclass(frozen=True)
class DistanceTerm:
    """A distance term of the cost; :meth:`bind` makes its residuals for one level."""

    def bind(self, context: TermContext) -> DistanceTermAtLevel | None:
        """The term at a level (``None``: it has no rows there)."""
        raise NotImplementedError


@dataclass(frozen=True)
class PointToSurface(DistanceTerm):
    """Template -> target: the distance ``d(y_i, S)`` of every moved template vertex to the target
    surface (eq. 2; point-to-plane at the closest point)."""

    def bind(self, context: TermContext) -> DistanceTermAtLevel:
        return PointToSurfaceTerm(context.assembly)


@dataclass(frozen=True)
class Barycentre(DistanceTerm):
    """Target -> template: every template vertex pulled to the barycentre ``b_i`` of the target
    vertices whose nearest template vertex it is (the second half of eq. 3).

    Attributes
    ----------
    weight : float
        Weight relative to the point-to-surface term. Default 1 (the paper's unweighted sum).
        Each level multiplies it by its :attr:`~o3dreg.ElasticLevel.symmetric_scale`.
    correction : bool
        Pull ``y_i + o_i`` rather than ``y_i`` to ``b_i``, ``o_i`` the offset from template
        vertex ``i`` to the centroid of its own Voronoi cell on the template surface. The
        paper's term (``False``, default) slides the vertices of an unevenly sampled template
        along the surface towards an even spacing (Lloyd's relaxation); the correction removes
        that drift when the target is much denser than the template, and weakens the term's
        spreading when it is not.
    target_points_per_source_point : float
        At most this many target vertices per template vertex enter the term (an even spatial
        subsample of a denser target), so that a million-vertex target costs no more per
        iteration than one of tens of thousands. Default 10.
    weighting : {'count', 'uniform'}
        Weight of template vertex ``i``'s row. ``'count'`` (default): the number of target
        vertices whose nearest template vertex it is, relative to the mean (robust weights
        summed; each target vertex counted with the target area it stands for, where the level
        offers it), so that the term is the target -> template distance itself up to a
        constant.
        ``'uniform'``: one unit per template vertex that has any target vertex (eq. 3 read
        literally); a part of the target the template does not reach yet then pulls as one
        vertex.
    skip_covered : bool
        ``True`` (default): a target vertex nearer to the moved template's surface than to its
        nearest template vertex by more than a fifth of the level's cell, and at most half as
        far from the surface as from that vertex (measured once, at the level start), does not
        pull at that level. It lies over a template triangle far larger
        than the template's spacing elsewhere (a quadric decimation leaves such slivers on a
        straight shaft); as its nearest vertex stands for the whole triangle, it would pull that
        vertex along the surface with the weight of all the target the triangle covers (a long
        bone's template then slid 70 mm). On an evenly sampled template no target vertex is
        that far from its nearest vertex and nothing is left out. ``False``: the paper's term.
    """

    weight: float = 1.0
    correction: bool = False
    target_points_per_source_point: float = 10.0
    weighting: str = "count"
    skip_covered: bool = True

    def __post_init__(self) -> None:
        check_positive(self.weight, "weight", allow_zero=True)
        object.__setattr__(self, "correction", check_bool(self.correction, "correction"))
        object.__setattr__(self, "skip_covered", check_bool(self.skip_covered, "skip_covered"))
        check_positive(self.target_points_per_source_point, "target_points_per_source_point")
        if self.weighting not in BARYCENTRE_WEIGHTINGS:
            raise ValueError(
                f"`weighting` must be one of {BARYCENTRE_WEIGHTINGS}, got {self.weighting!r}"
            )

    def bind(self, context: TermContext) -> DistanceTermAtLevel | None:
        weight = self.weight * context.symmetric_scale
        if weight <= 0:
            return None
        offsets = None
        if self.correction:
            if context.voronoi_offsets is None:
                raise ValueError(
                    "`correction=True` needs the Voronoi offsets the level did not offer "
                    "(TermContext.voronoi_offsets)"
                )
            offsets = context.voronoi_offsets()
        per_point = self.target_points_per_source_point
        sample = context.target_samples.points(per_point)
        counted = self.weighting == "count"
        # Counted rows weigh the target area each point stands for (see `weighting`).
        areas = context.target_samples.areas(per_point) if counted else None
        # Target points over the template's large triangles are left out (see skip_covered).
        template_mesh = context.template_mesh if self.skip_covered else None
        if context.barycentre_reach is None:
            return BarycentreTerm(
                context.assembly,
                sample,
                weight,
                offsets,
                counted=counted,
                template_mesh=template_mesh,
                cell_size=context.cell_size,
                areas=areas,
            )
        # Only the target points the template does not reach pull; those nowhere near the
        # threshold at the start are left out of every search.
        known = None if context.nearest_known is None else context.nearest_known(sample)
        beyond, candidates, distances = uncovered_candidates(
            context.points, sample, context.barycentre_reach, known
        )
        if candidates.size == 0:
            return None
        return BarycentreTerm(
            context.assembly,
            sample.take(candidates, axis=0),
            weight,
            offsets,
            counted=counted,
            beyond=beyond,
            stands_for=sample.shape[0],
            # Farther than a cell is the coarser levels' to reach: left to them, debris the
            # island filter kept does not pull.
            within=context.cell_size,
            scale_distances=distances,
            template_mesh=template_mesh,
            cell_size=context.cell_size,
            areas=None if areas is None else areas.take(candidates),
        )
