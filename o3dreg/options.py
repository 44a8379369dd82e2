"""Configuration value types of the elastic registration: levels, criteria, estimation method."""

from __future__ import annotations

from dataclasses import dataclass

from ._validation import check_positive, check_probability

ENERGIES = ("bending", "membrane")

__all__ = [
    "SOLVERS",
    "DistanceEstimation",
    "ElasticCriteria",
    "ElasticLevel",
    "default_levels",
]

#: Solvers a level may use (see :mod:`o3dreg._solvers`).
SOLVERS = ("lm", "trf", "lm-dense")


@dataclass(frozen=True)
class ElasticCriteria:
    """When to stop optimising one level.

    A level stops when one of these holds after an accepted step ``k``:

    * ``(F_{k-1} - F_k) / F_{k-1} < relative_cost`` (relative decrease of the total cost ``F``);
    * ``max |step of a node| / cell_size < relative_step`` (largest node move relative to the cell);
    * ``k == max_iteration`` (reported as not converged).

    Attributes
    ----------
    max_iteration : int
        Accepted Levenberg-Marquardt steps per level. Default 20.
    relative_cost : float
        Default 1e-3.
    relative_step : float
        Default 1e-3.
    """

    max_iteration: int = 20
    relative_cost: float = 1e-3
    relative_step: float = 1e-3

    def __post_init__(self) -> None:
        check_positive(self.max_iteration, "max_iteration", integer=True)
        check_positive(self.relative_cost, "relative_cost", allow_zero=True)
        check_positive(self.relative_step, "relative_step", allow_zero=True)

    def __repr__(self) -> str:
        return (
            f"ElasticCriteria(max_iteration={self.max_iteration}, "
            f"relative_cost={self.relative_cost:g}, relative_step={self.relative_step:g})"
        )


@dataclass(frozen=True)
class ElasticLevel:
    """One level of the multi-resolution hierarchy.

    Attributes
    ----------
    resolution : int
        Cells per axis of this level's cubic lattice (the paper's elementary cubes; ``2**k`` for an
        octree hierarchy).
    regularization : float
        Weight ``lambda`` of the regularisation ``P(p)`` of this level's node displacements ``u``:
        the cost adds ``lambda * N * mean_s |(D u)_s|^2`` over the finite-difference stencils ``s``
        touching a free node, ``N`` the number of template vertices. ``lambda = 1`` makes a mean
        (second) difference of 1 mm between neighbouring node displacements cost as much as a
        mean distance of 1 mm to the target.
    energy : {'bending', 'membrane'}
        ``'bending'`` (default): second differences, the discrete thin-plate energy; affine
        motions cost nothing, so coarse levels may scale and shear freely. ``'membrane'``: first
        differences, which also resists uniform stretching.
    adaptive_quantile : float or None
        ``None``: every cell holding template vertices is refined (a uniform grid). A value ``q``
        in ``[0, 1)``: only cells holding a vertex whose distance to the target exceeds the
        ``q``-quantile of the distances at the start of the level are refined (the octree-spline
        variant of Szeliski and Lavallee: subdivide where residuals remain large).
    points_per_node : float or None
        Data budget of the level: the level is optimised on a spatial subsample of about
        ``points_per_node`` template vertices per lattice node touching data (at least 1000),
        which determines a coarse lattice as well as all vertices do at a fraction of the cost.
        ``None`` uses every vertex. Default 20.
    simplify_target : bool
        Measure this level's template->target distances to a copy of the target simplified by
        vertex clustering with voxels of 1/16 of a cell, when that voxel is at least twice the
        target's mean edge (coarse levels only). The lattice cannot resolve finer detail, and
        the queries get several times cheaper. Default ``True``; the reported distances always
        use the full target.
    solver : {'lm', 'trf', 'lm-dense'}
        ``'lm'``: Levenberg-Marquardt on sparse normal equations (default, fastest);
        ``'trf'``: :func:`scipy.optimize.least_squares` trust-region reflective with a sparse
        Jacobian; ``'lm-dense'``: ``least_squares(method='lm')`` (MINPACK, dense Jacobian: small
        problems only).
    criteria : ElasticCriteria or None
        Stopping rule of this level; ``None`` uses the registration's ``criteria``.
    """

    resolution: int
    regularization: float = 1.0
    energy: str = "bending"
    adaptive_quantile: float | None = None
    points_per_node: float | None = 20.0
    simplify_target: bool = True
    solver: str = "lm"
    criteria: ElasticCriteria | None = None

    def __post_init__(self) -> None:
        check_positive(self.resolution, "resolution", integer=True)
        check_positive(self.regularization, "regularization", allow_zero=True)
        if self.energy not in ENERGIES:
            raise ValueError(f"`energy` must be one of {ENERGIES}, got {self.energy!r}")
        if self.adaptive_quantile is not None:
            q = check_probability(self.adaptive_quantile, "adaptive_quantile")
            if q >= 1.0:
                raise ValueError(f"`adaptive_quantile` must be in [0, 1), got {q!r}")
        if self.points_per_node is not None:
            check_positive(self.points_per_node, "points_per_node")
        if self.solver not in SOLVERS:
            raise ValueError(f"`solver` must be one of {SOLVERS}, got {self.solver!r}")
        if self.criteria is not None and not isinstance(self.criteria, ElasticCriteria):
            raise TypeError(
                f"`criteria` must be an ElasticCriteria or None, got {type(self.criteria).__name__}"
            )

    def __repr__(self) -> str:
        extra = ""
        if self.adaptive_quantile is not None:
            extra += f", adaptive_quantile={self.adaptive_quantile:g}"
        if self.energy != "bending":
            extra += f", energy={self.energy!r}"
        if self.solver != "lm":
            extra += f", solver={self.solver!r}"
        if self.criteria is not None:
            extra += f", criteria={self.criteria!r}"
        return f"ElasticLevel(resolution={self.resolution}, regularization={self.regularization:g}{extra})"


@dataclass(frozen=True)
class DistanceEstimation:
    """What the elastic registration minimises: eq. (2) or the symmetric eq. (3) of the paper.

    Attributes
    ----------
    symmetric : bool
        ``True`` (default): template->target point-to-surface distances plus the barycentre term
        for target->template (eq. 3). ``False``: the paper's "single distance" (eq. 2).
    symmetric_weight : float
        Weight of the barycentre term relative to the point-to-surface term. Default 1 (the
        paper's unweighted sum).
    target_points_per_source_point : float
        At most this many target vertices per template vertex enter the barycentre term (an even
        spatial subsample of the target when it is denser). Default 10: every barycentre still
        averages about ten target vertices, and a million-vertex target costs no more per
        iteration than a 30k-vertex one.
    """

    symmetric: bool = True
    symmetric_weight: float = 1.0
    target_points_per_source_point: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.symmetric, bool):
            raise TypeError(f"`symmetric` must be a bool, got {type(self.symmetric).__name__}")
        check_positive(self.symmetric_weight, "symmetric_weight", allow_zero=True)
        check_positive(self.target_points_per_source_point, "target_points_per_source_point")

    def __repr__(self) -> str:
        return (
            f"DistanceEstimation(symmetric={self.symmetric}, "
            f"symmetric_weight={self.symmetric_weight:g})"
        )


def default_levels() -> list[ElasticLevel]:
    """The default hierarchy: 2, 4, 8 and 16 cells per axis, bending energy with weight 0.1.

    Chosen on the bunny under known warps of 2-10% of its diagonal and on the paper's cone ->
    sphere case (docs/registration.md records the sweep): 1.0 is too stiff for large warps, 0.01
    leaves the Jacobian determinant lower for no gain in accuracy.
    """
    return [
        ElasticLevel(resolution=2, regularization=0.1),
        ElasticLevel(resolution=4, regularization=0.1),
        ElasticLevel(resolution=8, regularization=0.1),
        ElasticLevel(resolution=16, regularization=0.1),
    ]
