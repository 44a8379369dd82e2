"""Configuration value types of the elastic registration: levels, criteria, estimation method."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import open3d as o3d

from .._validation import as_mesh_arrays, as_points, check_bool, check_positive, check_probability
from .checkers import BoundaryChecker, CorrespondenceChecker, DistanceChecker, NormalAngleChecker
from .losses import LOSS_TYPES, RobustLoss, loss_named
from .terms import BARYCENTRE_WEIGHTINGS, Barycentre, DistanceTerm, PointToSurface

ENERGIES = ("bending", "membrane")


#: Robust losses of :class:`DistanceEstimation`.
LOSSES = ("linear", "huber", "cauchy", "tukey")

__all__ = [
    "SOLVERS",
    "DistanceEstimation",
    "ElasticCriteria",
    "ElasticLevel",
    "default_levels",
    "paper_levels",
]

#: Solvers a level may use (see :mod:`o3dreg.registration._solvers`).
SOLVERS = ("lm", "trf", "lm-dense")

#: Most cells per axis of one level. Setting a level up holds about 150 bytes per lattice node
#: (node indices of every finite-difference stencil, the displacements): ~0.3 GB for 128 cells
#: (129^3 nodes), 2.6 GB for 256, 150 GB for 1000. Finer lattices than this are also far finer
#: than any template's sampling (a 4k-vertex template has about one vertex per cell at 16).
MAX_RESOLUTION = 128

#: Most levels in one hierarchy: each is a full optimisation and keeps its lattice in the
#: deformation (24 bytes per node: 0.8 GB for 16 levels of 128 cells).
MAX_LEVELS = 16


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
        Accepted Levenberg-Marquardt steps per level (solver ``'lm'``). Default 20. SciPy's
        solvers count function evaluations instead (``max_nfev`` of ``least_squares``):
        ``'trf'`` at most ``3 * max_iteration``, ``'lm-dense'`` (MINPACK) at most
        ``(n + 1) * max_iteration`` for ``n`` unknowns, and stop on their own tolerances.
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
        octree hierarchy), at most :data:`MAX_RESOLUTION` (128: memory).
    regularization : float
        Weight ``lambda`` of the regularisation ``P(p)`` of this level's node displacements ``u``:
        the cost adds ``lambda * N * mean_s |(D u)_s|^2`` over the finite-difference stencils ``s``
        touching a free node, ``N`` the number of template vertices. ``lambda = 1`` makes a mean
        (second) difference of 1 mm between neighbouring node displacements cost as much as a
        mean distance of 1 mm to the target. Default 0.1 (see :func:`default_levels`).
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
        the queries get several times cheaper. Default ``True``. The level's own figures
        (:class:`~o3dreg.LevelReport` ``mean_distance``, costs) are then measured on that copy;
        the result's ``distances`` always use the full target.
    min_jacobian_determinant : float or None
        Folding guard of the ``'lm'`` solver: a step after which the smallest Jacobian
        determinant ``det(dT/dx)`` of the whole map (coarser levels included), sampled at the
        level's template points and at 8 interior points (local coordinates 1/4 and 3/4) of
        every cell holding one, falls
        below this value (and below its value before the step) is rejected like a step that
        increases the cost (the damping grows, so the next step is shorter and smoother).
        ``None`` disables the guard. Default 0.05. The SciPy solvers ignore it.
    solver : {'lm', 'trf', 'lm-dense'}
        ``'lm'``: Levenberg-Marquardt on sparse normal equations (default, fastest);
        ``'trf'``: :func:`scipy.optimize.least_squares` trust-region reflective with a sparse
        Jacobian; ``'lm-dense'``: ``least_squares(method='lm')`` (MINPACK, dense Jacobian: small
        problems only).
    criteria : ElasticCriteria or None
        Stopping rule of this level; ``None`` uses the registration's ``criteria``.
    symmetric_scale : float
        Multiplies :attr:`DistanceEstimation.symmetric_weight` at this level; ``0`` makes the
        level minimise the single distance (eq. 2). Default 1 (eq. 3 as published); the
        default hierarchy lowers it at its fine levels (see :func:`default_levels`).
    barycentre_reach : float or None
        ``None`` (default): every target point pulls its nearest template point (eq. 3). A
        value ``c``: only the target points farther from their nearest template point than
        ``c`` times that point's ring radius (its distance to its 6th-nearest neighbour among
        the level's template points, measured where the level starts) pull it: the parts of
        the target the template does not reach yet (a condyle's tip, a protrusion). Where the
        template covers the target, no target point is that far and the term has no rows, so
        covered vertices are not slid towards the centroids of their Voronoi cells. A target
        point farther than one lattice cell does not pull (that far is the coarser levels' to
        reach, so debris the island filter kept does not pull), and the robust scale is
        measured on all target points, so the loss discounts the farthest. Only the target
        points farther than 0.8 of the threshold at the level start are followed through the
        level. The default hierarchy sets 1 on its finest level.
    """

    resolution: int
    regularization: float = 0.1
    energy: str = "bending"
    adaptive_quantile: float | None = None
    points_per_node: float | None = 20.0
    simplify_target: bool = True
    solver: str = "lm"
    criteria: ElasticCriteria | None = None
    min_jacobian_determinant: float | None = 0.05
    symmetric_scale: float = 1.0
    barycentre_reach: float | None = None

    def __post_init__(self) -> None:
        check_positive(self.resolution, "resolution", integer=True)
        check_positive(self.symmetric_scale, "symmetric_scale", allow_zero=True)
        object.__setattr__(
            self, "simplify_target", check_bool(self.simplify_target, "simplify_target")
        )
        if self.barycentre_reach is not None:
            check_positive(self.barycentre_reach, "barycentre_reach")
        if self.resolution > MAX_RESOLUTION:
            raise ValueError(
                f"`resolution` must be at most {MAX_RESOLUTION} cells per axis (memory: about "
                f"150 bytes per lattice node, {self.resolution + 1}^3 nodes requested), "
                f"got {self.resolution}"
            )
        if self.min_jacobian_determinant is not None:
            d = check_positive(
                self.min_jacobian_determinant, "min_jacobian_determinant", allow_zero=True
            )
            if d >= 1.0:
                raise ValueError(f"`min_jacobian_determinant` must be in [0, 1), got {d!r}")
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
        if self.symmetric_scale != 1.0:
            extra += f", symmetric_scale={self.symmetric_scale:g}"
        if self.barycentre_reach is not None:
            extra += f", barycentre_reach={self.barycentre_reach:g}"
        return f"ElasticLevel(resolution={self.resolution}, regularization={self.regularization:g}{extra})"


@dataclass(frozen=True)
class DistanceEstimation:
    """What the elastic registration minimises: eq. (2) or the symmetric eq. (3) of the paper.

    The defaults are made for real scans, which are partial (a skull without its vault, a face
    scan under a full-head template), carry debris and meet the template in a rough pose: a
    robust loss (``'cauchy'``), no correspondence beyond the target's open boundary or between
    surfaces facing away from each other (``max_normal_angle=90``), and no target islands smaller than
    1% of its largest component. On clean, complete targets they cost little (docs/robustness.md
    gives the figures). :meth:`paper` is the one switch back to the paper's plain least squares
    (the setting that reproduces its Table 1).

    Attributes
    ----------
    symmetric : bool
        ``True`` (default): template->target point-to-surface distances plus the barycentre term
        for target->template (eq. 3). ``False``: the paper's "single distance" (eq. 2).
    symmetric_weight : float
        Weight of the barycentre term relative to the point-to-surface term. Default 1 (the
        paper's unweighted sum).
    barycentre_correction : bool
        Pull ``y_i + o_i`` rather than ``y_i`` to the barycentre ``b_i``, where ``o_i`` is the
        offset from template vertex ``i`` to the centroid of its own Voronoi cell on the
        template surface (computed at the start of every level). The paper's term (``False``,
        default) slides the vertices of an unevenly sampled template along the surface towards
        an even spacing (Lloyd's relaxation), which costs correspondence accuracy; the correction
        removes most of that drift when the target is much denser than the template. It
        assumes that density ratio: on targets as coarse as the template it moves vertices that
        are already in place, and it weakens the spreading of the paper's cone -> sphere case
        (figures in docs/registration.md).
    barycentre_skip_covered : bool
        ``True`` (default): target vertices that lie on the template's surface far from every
        template vertex (over a triangle much larger than the template's spacing elsewhere, such
        as the long slivers a quadric decimation leaves on a straight shaft) do not pull, as
        they are on the template already; measured once per level (see
        :attr:`~o3dreg.Barycentre.skip_covered`). On an evenly sampled template nothing is left
        out. ``False``: every target vertex pulls its nearest template vertex (the paper's term;
        :meth:`paper`).
    barycentre_weighting : {'count', 'uniform'}
        Weight of template vertex ``i``'s barycentre row. ``'count'`` (default): the number of
        target vertices whose nearest template vertex it is, relative to the mean (``n_i N /
        M``, robust weights summed), so that the term is the target->template distance itself:
        ``sum_i n_i |y_i - b_i|^2 = sum_j |t_j - y_nn(j)|^2`` minus a constant; each target
        vertex counts with the target area it stands for (relative to the mean), so that a part
        sampled more finely than the rest weighs its area, not its vertex count. A part of the
        target that the template does not reach yet (a longer condyle, a taller ramus) is
        assigned to the few template vertices on its edge, and pulls them with the weight of
        all its points. ``'uniform'``: one unit per template vertex that has any target vertex
        (eq. 3 read literally); such a part then pulls as one vertex, and a template smaller
        than the patient stops short of it (docs/shape-model.md: 8 CT mandibles, 56 template ->
        patient pairs).
    target_points_per_source_point : float
        At most this many target vertices per template vertex enter the barycentre term (an even
        spatial subsample of the target when it is denser). Default 10: every barycentre still
        averages about ten target vertices, and a million-vertex target costs no more per
        iteration than a 30k-vertex one.
    loss : {'linear', 'huber', 'cauchy', 'tukey'}
        Robust loss of both distance terms, applied as iteratively reweighted least squares: at
        every cost evaluation each residual ``r`` (a point-to-surface distance ``d_i``, or the
        distance ``e_j`` of a target vertex to its nearest template vertex) gets the weight
        ``w(r)`` and enters as ``sqrt(w) r`` (Jacobian ``sqrt(w) J``, weights held fixed in it).
        With ``z = |r| / (k sigma)``: ``'huber'`` (``k = 1.345``) ``w = min(1, 1 / z)``;
        ``'cauchy'`` (``k = 2.3849``) ``w = 1 / (1 + z^2)``; ``'tukey'`` (``k = 4.6851``)
        ``w = (1 - z^2)^2`` for ``z < 1``, else 0; ``'linear'``: ``w = 1`` (plain least squares,
        the paper's cost). Default ``'cauchy'``: it keeps a weight for every residual (no hard
        cut), so a correspondence that starts far off can still come in, while debris and the
        data beyond a cut weigh little. A target vertex's weight ``v_j`` enters its barycentre
        ``b_i = sum v_j t_j / sum v_j`` and the row scale ``sqrt(w_s mean_j v_j)``.
    loss_scale : float or None
        ``sigma`` above, in the input's units. ``None`` (default): estimated at the start of
        every level from the data, ``sigma = max(1.4826 median |r|, 0.05 h)`` (the MAD of
        residuals centred at zero; ``h`` the level's cell size), separately for ``d_i`` (over the
        correspondences not rejected by the masks below) and for ``e_j``.
    max_distance_factor : float or None
        Drop (weight 0) every correspondence whose residual exceeds ``max_distance_factor *
        sigma``: farther than the data justify. ``None`` (default) keeps them.
    reject_boundary : bool
        Drop the template->target correspondence of a template vertex whose closest target point
        lies on an open boundary edge or vertex of the target and which lies beyond it (its
        offset has a tangential part longer than a tenth of the target's mean edge): the target
        has no data there (a cut, a hole, a partial scan), so the vertex follows its neighbours'
        regularised motion instead of being dragged onto the rim. Such a vertex also gets no
        barycentre row. No effect on closed targets. Default ``True``.
    max_normal_angle : float or None
        Drop a correspondence when the angle between the template vertex normal (at the start
        of the level, after the coarser levels' deformation) and the normal of the target
        triangle holding its closest point exceeds this many degrees, in ``(0, 180]``. Each
        mesh must be consistently oriented; a target oriented the other way round as a whole
        (inside out, as some marching-cubes and scanner outputs are) is detected from the
        correspondences after the rigid step and compared reversed. Default 90: only surfaces
        facing away from each other (the inner side of a thin shell, debris) are kept apart; a
        smaller angle may also drop correct matches where the shapes differ much, whose
        normals start far apart. ``None`` (or 180) disables it.
    min_target_component : float or None
        Ignore the connected components of the target with fewer vertices than this fraction
        of its largest component (islands, debris, loose fragments a marching-cubes surface
        keeps). Unless ``None``, the components that no template vertex has its closest point
        on after the rigid start are left out of the levels too, where their area is at most
        half that of the others (the verdict's island rule): a neighbouring bone or debris the
        template does not model is not pulled towards. Default 0.01; ``None`` uses every
        component. The reported distances and the verdict still measure the whole target.
    more_terms : tuple of DistanceTerm
        Distance terms added to those the fields above describe (a term of your own: any
        :class:`~o3dreg.DistanceTerm` with ``bind``). Default none; :meth:`compose` puts there
        the terms it is given besides :class:`~o3dreg.PointToSurface` and
        :class:`~o3dreg.Barycentre`.
    """

    symmetric: bool = True
    symmetric_weight: float = 1.0
    barycentre_correction: bool = False
    barycentre_weighting: str = "count"
    target_points_per_source_point: float = 10.0
    loss: str = "cauchy"
    loss_scale: float | None = None
    max_distance_factor: float | None = None
    reject_boundary: bool = True
    max_normal_angle: float | None = 90.0
    min_target_component: float | None = 0.01
    # Only in a batch's resume key when set: keys made before the field existed stay valid.
    more_terms: tuple[DistanceTerm, ...] = field(default=(), metadata={"keyed_when_set": True})
    barycentre_skip_covered: bool = field(default=True, metadata={"keyed_when_set": True})

    def __post_init__(self) -> None:
        object.__setattr__(self, "symmetric", check_bool(self.symmetric, "symmetric"))
        check_positive(self.symmetric_weight, "symmetric_weight", allow_zero=True)
        object.__setattr__(
            self,
            "barycentre_correction",
            check_bool(self.barycentre_correction, "barycentre_correction"),
        )
        object.__setattr__(
            self,
            "barycentre_skip_covered",
            check_bool(self.barycentre_skip_covered, "barycentre_skip_covered"),
        )
        if self.barycentre_weighting not in BARYCENTRE_WEIGHTINGS:
            raise ValueError(
                f"`barycentre_weighting` must be one of {BARYCENTRE_WEIGHTINGS}, "
                f"got {self.barycentre_weighting!r}"
            )
        check_positive(self.target_points_per_source_point, "target_points_per_source_point")
        if self.min_target_component is not None:
            f = check_probability(self.min_target_component, "min_target_component")
            if f <= 0.0:
                raise ValueError(f"`min_target_component` must be in (0, 1], got {f!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"`loss` must be one of {LOSSES}, got {self.loss!r}")
        if self.loss_scale is not None:
            check_positive(self.loss_scale, "loss_scale")
        if self.max_distance_factor is not None:
            check_positive(self.max_distance_factor, "max_distance_factor")
        object.__setattr__(
            self, "reject_boundary", check_bool(self.reject_boundary, "reject_boundary")
        )
        if self.max_normal_angle is not None:
            a = check_positive(self.max_normal_angle, "max_normal_angle")
            if a > 180.0:
                raise ValueError(f"`max_normal_angle` must be in (0, 180] degrees, got {a!r}")
        more = _as_terms(self.more_terms, "more_terms")
        described = [t for t in more if type(t) in (PointToSurface, Barycentre)]
        if described:
            raise ValueError(
                "`more_terms` must not hold PointToSurface() or Barycentre(...) (the fields "
                f"`symmetric`, `symmetric_weight`, `barycentre_*` describe them), got {described!r}"
            )
        object.__setattr__(self, "more_terms", more)

    @classmethod
    def paper(cls, **changes: Any) -> DistanceEstimation:
        """The paper's plain least squares: no robust loss, no rejection, every target component,
        one unit of weight per barycentre row (``barycentre_weighting='uniform'``), every target
        vertex pulling (``barycentre_skip_covered=False``).

        Eq. (3) of Berar et al. (2005) (``symmetric=False``: eq. 2) exactly as published on the
        levels of :func:`paper_levels` (the default levels limit the barycentre term on the
        finest one); the setting of ``examples/paper_tables.py``, which reproduces Table 1, and
        of the command line's ``--paper``. ``changes`` override single fields, e.g.
        ``DistanceEstimation.paper(symmetric=False)``.
        """
        fields: dict[str, Any] = {
            "loss": "linear",
            "reject_boundary": False,
            "max_normal_angle": None,
            "min_target_component": None,
            "barycentre_weighting": "uniform",
            "barycentre_skip_covered": False,
        }
        fields.update(changes)
        return cls(**fields)

    # -- the strategies these settings stand for (translated once per registration) -------------
    @property
    def robust_loss(self) -> RobustLoss:
        """The loss of both distance terms (``loss`` and ``loss_scale``), e.g. ``CauchyLoss()``."""
        return loss_named(self.loss, self.loss_scale)

    @property
    def checkers(self) -> tuple[CorrespondenceChecker, ...]:
        """The correspondence checkers (``reject_boundary``, ``max_normal_angle``,
        ``max_distance_factor``)."""
        found: list[CorrespondenceChecker] = []
        if self.reject_boundary:
            found.append(BoundaryChecker())
        if self.max_normal_angle is not None:
            found.append(NormalAngleChecker(self.max_normal_angle))
        if self.max_distance_factor is not None:
            found.append(DistanceChecker(self.max_distance_factor))
        return tuple(found)

    @property
    def terms(self) -> tuple[DistanceTerm, ...]:
        """The distance terms: :class:`~o3dreg.PointToSurface`, :class:`~o3dreg.Barycentre`
        when ``symmetric``, then ``more_terms``."""
        if not self.symmetric:
            return (PointToSurface(), *self.more_terms)
        barycentre = Barycentre(
            self.symmetric_weight,
            self.barycentre_correction,
            self.target_points_per_source_point,
            self.barycentre_weighting,
            self.barycentre_skip_covered,
        )
        return (PointToSurface(), barycentre, *self.more_terms)

    @classmethod
    def compose(
        cls,
        *,
        terms: Any = None,
        loss: RobustLoss | None = None,
        checkers: Any = None,
        min_target_component: float | None = 0.01,
    ) -> DistanceEstimation:
        """The estimation of the given strategy objects (Open3D's way of composing them).

        Parameters
        ----------
        terms : sequence of DistanceTerm
            One :class:`~o3dreg.PointToSurface`, at most one :class:`~o3dreg.Barycentre`, and
            any other :class:`~o3dreg.DistanceTerm` with ``bind`` (kept in ``more_terms``, in
            the order given). Default the first two (eq. 3).
        loss : RobustLoss, optional
            Default ``CauchyLoss()``.
        checkers : sequence of CorrespondenceChecker
            At most one of each kind. Default boundary and normal angle (90 degrees).
        min_target_component : float or None
            As the attribute. Default 0.01.

        Examples
        --------
        >>> from o3dreg import Barycentre, DistanceEstimation, PointToSurface, TukeyLoss
        >>> DistanceEstimation.compose(
        ...     terms=[PointToSurface(), Barycentre(weight=0.5)], loss=TukeyLoss(), checkers=[]
        ... ).terms[1].weight
        0.5
        """
        terms = (PointToSurface(), Barycentre()) if terms is None else _as_terms(terms, "terms")
        if checkers is None:
            checkers = (BoundaryChecker(), NormalAngleChecker())
        checkers = tuple(checkers)
        kinds = [type(t) for t in terms]
        if kinds.count(PointToSurface) != 1 or kinds.count(Barycentre) > 1:
            raise ValueError(
                "`terms` must hold one PointToSurface(), at most one Barycentre(...) and any "
                f"other DistanceTerm, got {terms!r}"
            )
        if loss is None:
            loss = loss_named("cauchy")
        # The settings hold a loss by its name and the checkers by their parameters: a class of
        # one's own (a subclass included) would be replaced by the library's, so it is refused.
        known_losses = tuple(LOSS_TYPES.values())
        if type(loss) not in known_losses:
            raise TypeError(
                "`loss` must be one of the library's losses "
                f"({', '.join(t.__name__ for t in known_losses)}), got {type(loss).__name__}"
            )
        by_kind = {type(c): c for c in checkers}
        if len(by_kind) != len(checkers) or not all(
            type(c) in (BoundaryChecker, NormalAngleChecker, DistanceChecker) for c in checkers
        ):
            raise ValueError(
                "`checkers` must hold at most one each of BoundaryChecker, NormalAngleChecker "
                f"and DistanceChecker (the library's classes), got {checkers!r}"
            )
        angle = by_kind.get(NormalAngleChecker)
        distance = by_kind.get(DistanceChecker)
        given = [t for t in terms if isinstance(t, Barycentre) and type(t) is Barycentre]
        barycentre = given[0] if given else Barycentre()
        return cls(
            symmetric=bool(given),
            symmetric_weight=barycentre.weight,
            barycentre_correction=barycentre.correction,
            target_points_per_source_point=barycentre.target_points_per_source_point,
            barycentre_weighting=barycentre.weighting,
            barycentre_skip_covered=barycentre.skip_covered,
            loss=loss.name,
            loss_scale=loss.scale,
            max_distance_factor=None if distance is None else distance.factor,  # type: ignore[attr-defined]
            reject_boundary=BoundaryChecker in by_kind,
            max_normal_angle=None if angle is None else angle.max_angle,  # type: ignore[attr-defined]
            min_target_component=min_target_component,
            more_terms=tuple(t for t in terms if type(t) not in (PointToSurface, Barycentre)),
        )

    def __repr__(self) -> str:
        extra = f", loss={self.loss!r}"
        if self.loss_scale is not None:
            extra += f", loss_scale={self.loss_scale:g}"
        if self.max_distance_factor is not None:
            extra += f", max_distance_factor={self.max_distance_factor:g}"
        extra += f", reject_boundary={self.reject_boundary}"
        angle = self.max_normal_angle
        extra += f", max_normal_angle={'None' if angle is None else format(angle, 'g')}"
        part = self.min_target_component
        extra += f", min_target_component={'None' if part is None else format(part, 'g')}"
        if not self.barycentre_skip_covered:
            extra += ", barycentre_skip_covered=False"
        if self.more_terms:
            extra += f", more_terms={self.more_terms!r}"
        return (
            f"DistanceEstimation(symmetric={self.symmetric}, "
            f"symmetric_weight={self.symmetric_weight:g}{extra})"
        )


def _as_terms(terms: Any, name: str) -> tuple[DistanceTerm, ...]:
    """``terms`` as a tuple of distance terms that can be bound to a level; a clear error naming
    the parameter ``name`` for anything else."""
    if isinstance(terms, (str, bytes)) or not hasattr(terms, "__iter__"):
        raise TypeError(f"`{name}` must be a sequence of DistanceTerm, got {type(terms).__name__}")
    found = tuple(terms)
    for term in found:
        if not isinstance(term, DistanceTerm):
            raise TypeError(f"`{name}` must hold DistanceTerm instances, got {type(term).__name__}")
        if type(term).bind is DistanceTerm.bind:
            raise TypeError(f"`{name}`: {type(term).__name__} does not implement DistanceTerm.bind")
    return found


#: ``symmetric_scale`` of the default levels 2, 4, 8, 16 (see :func:`default_levels`).
DEFAULT_SYMMETRIC_SCALES = (1.0, 1.0, 0.3, 0.3)
#: ``barycentre_reach`` of the default levels: on the finest, only the target the template does
#: not reach pulls.
DEFAULT_BARYCENTRE_REACH = (None, None, None, 1.0)


#: An elongated template gets a fifth, 32-cell level when its second principal extent spans fewer
#: than this many cells of the 16-cell level (the lattice is a cube on the longest extent, so a
#: long bone's cross-section gets few cells: a 450 mm femur's 80 mm condyles 2.4 of them). The
#: bunny's 3k template spans 9.6, the development mandibles' 12.4-13.2, the paper's forms 13.
ELONGATED_CELLS_ACROSS = 4.0


def cells_across(template: Any, resolution: int, padding: float = 0.1) -> float:
    """How many cells of a ``resolution``-cell lattice the template's second principal extent
    spans: the lattice is a cube on the largest extent, grown by ``padding`` of it on each side
    (as :func:`~o3dreg.registration_elastic` lays it, up to the target's own extent).

    ``template`` is a triangle mesh (any kind ``registration_elastic`` takes, a ``(vertices,
    faces)`` pair included) or its ``(n, 3)`` vertices.
    """
    vertices = _template_vertices(template)
    if vertices.shape[0] < 2:
        return float("inf")
    centred = vertices - vertices.mean(axis=0)
    axes = np.linalg.eigh(centred.T @ centred)[1]
    extents = np.sort(np.ptp(centred @ axes, axis=0))[::-1]
    if extents[0] <= 0.0:
        return float("inf")
    return float(resolution * extents[1] / ((1.0 + 2.0 * padding) * extents[0]))


def _template_vertices(template: Any) -> np.ndarray:
    """The vertices of a template given as a mesh, a ``(vertices, faces)`` pair or points."""
    if isinstance(template, (tuple, list)):
        # Two 2-D arrays are a (vertices, faces) pair; points are rows of three numbers.
        if len(template) == 2 and all(np.ndim(part) == 2 for part in template):
            return as_mesh_arrays(template, "template")[0]
    elif not isinstance(template, (np.ndarray, o3d.geometry.PointCloud)):
        return as_mesh_arrays(template, "template")[0]
    return as_points(template, "template")


def default_levels(template: Any = None) -> list[ElasticLevel]:
    """The default hierarchy: 2, 4, 8 and 16 cells per axis, the barycentre term on coarse levels,
    and for an elongated ``template`` a fifth level of 32 cells.

    Bending energy with weight 0.1 on every level; the barycentre term at full weight on the two
    coarse levels, 0.3 at 8 cells, and 0.3 at 16 cells limited to the target the template does
    not reach (``barycentre_reach=1``).

    The regularisation: 1.0 is too stiff for large warps, 0.01 leaves the Jacobian determinant
    lower for no gain in accuracy (the sweep on the bunny under known warps and on the paper's
    cone -> sphere case is in docs/registration.md).

    The barycentre term spreads the template over the whole target, a large-scale effect the
    coarse levels settle; on a fine lattice it also slides each template vertex towards the
    centroid of its Voronoi cell of target points (Lloyd's relaxation), which costs
    correspondence accuracy and, as its assignments change at every evaluation, twice the
    evaluations. This schedule keeps the spreading (the cone -> sphere of Table 1) and most of
    the single distance's accuracy on warps of one surface; on the finest level only the target
    points farther from the template than a ring of its vertices pull (a condyle the coarse
    levels left short), so a target the template covers gets no barycentre rows there (figures
    in docs/registration.md).
    :func:`paper_levels` is eq. (3) at every level, the published method.

    The lattice is a cube on the template's longest extent, so across a long bone (a femur, an
    ulna) the 16-cell level has only a few cells. Given the ``template`` (a mesh or its
    ``(n, 3)`` vertices; :func:`~o3dreg.registration_elastic` passes its source), a template
    whose second principal extent spans fewer than :data:`ELONGATED_CELLS_ACROSS` cells of the
    16-cell level (:func:`cells_across`) gets a fifth level of 32 cells, set like the 16-cell
    one (figures in docs/registration.md). Without a template: the four levels.

    Parameters
    ----------
    template : triangle mesh, (vertices, faces) or (n, 3) array_like, optional
        The template the levels are for (only its extents matter): any mesh
        :func:`~o3dreg.registration_elastic` takes as its source, or its vertices.

    Returns
    -------
    list of ElasticLevel

    Examples
    --------
    >>> [lev.resolution for lev in default_levels()]
    [2, 4, 8, 16]
    >>> shaft = [[x, y, z] for x in (0.0, 400.0) for y in (0.0, 40.0) for z in (0.0, 40.0)]
    >>> [lev.resolution for lev in default_levels(shaft)]
    [2, 4, 8, 16, 32]
    """
    levels = [
        ElasticLevel(resolution=r, symmetric_scale=s, barycentre_reach=reach)
        for r, s, reach in zip((2, 4, 8, 16), DEFAULT_SYMMETRIC_SCALES, DEFAULT_BARYCENTRE_REACH)
    ]
    if template is not None and cells_across(template, 16) < ELONGATED_CELLS_ACROSS:
        levels.append(replace(levels[-1], resolution=32))
    return levels


def paper_levels() -> list[ElasticLevel]:
    """The default hierarchy with eq. (3) of Berar et al. (2005) at every level, as published.

    The levels of :func:`default_levels` with the barycentre term at full weight on every level
    (``symmetric_scale=1``) and every target point pulling (``barycentre_reach=None``). With
    :meth:`DistanceEstimation.paper` it is the setting of ``examples/paper_tables.py``, which
    reproduces Tables 1-2 of the paper.

    Examples
    --------
    >>> [(lev.resolution, lev.symmetric_scale, lev.barycentre_reach) for lev in paper_levels()]
    [(2, 1.0, None), (4, 1.0, None), (8, 1.0, None), (16, 1.0, None)]
    """
    return [replace(lev, symmetric_scale=1.0, barycentre_reach=None) for lev in default_levels()]
