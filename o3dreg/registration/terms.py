"""The distance terms of the elastic cost, eq. (3) of Berar et al. (2005): small value types
the user composes in :class:`~o3dreg.DistanceEstimation`.

Each names a term and holds its settings; its residuals, Jacobian rows and share of the normal
equations are in ``o3dreg.registration._terms``, which the level problem
(``o3dreg.registration._cost``) builds from it. The regulariser belongs to each level
(:attr:`~o3dreg.ElasticLevel.regularization`).
"""

from __future__ import annotations

from dataclasses import dataclass

from .._validation import check_positive

__all__ = ["BARYCENTRE_WEIGHTINGS", "Barycentre", "DistanceTerm", "PointToSurface"]

#: How the barycentre rows are weighted (:attr:`Barycentre.weighting`).
BARYCENTRE_WEIGHTINGS = ("count", "uniform")


@dataclass(frozen=True)
class DistanceTerm:
    """A distance term of the cost."""


@dataclass(frozen=True)
class PointToSurface(DistanceTerm):
    """Template -> target: the distance ``d(y_i, S)`` of every moved template vertex to the target
    surface (eq. 2; point-to-plane at the closest point)."""


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
        summed), so that the term is the target -> template distance itself up to a constant.
        ``'uniform'``: one unit per template vertex that has any target vertex (eq. 3 read
        literally); a part of the target the template does not reach yet then pulls as one
        vertex.
    """

    weight: float = 1.0
    correction: bool = False
    target_points_per_source_point: float = 10.0
    weighting: str = "count"

    def __post_init__(self) -> None:
        check_positive(self.weight, "weight", allow_zero=True)
        if not isinstance(self.correction, bool):
            raise TypeError(f"`correction` must be a bool, got {type(self.correction).__name__}")
        check_positive(self.target_points_per_source_point, "target_points_per_source_point")
        if self.weighting not in BARYCENTRE_WEIGHTINGS:
            raise ValueError(
                f"`weighting` must be one of {BARYCENTRE_WEIGHTINGS}, got {self.weighting!r}"
            )
