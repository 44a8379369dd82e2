"""The residual terms of one level's cost, eq. (3) of Berar et al. (2005) plus the regulariser.

Every term has the same contract (:class:`ResidualTerm`): from what an evaluation measured
(:class:`Geometry`), the weights of the current linearisation (:class:`Weights`) and what the
term has of its own there (:class:`TermState`), :meth:`linearise` gives its residuals and what
their Jacobian rows with respect to the level's unknowns ``u`` are made of (a
:class:`TermBlock`; the rows themselves are built on demand), and :meth:`normal_share` gives the
term's share ``(J^T J, J^T r)`` of the normal equations. The distance terms' shares go through
per-point 3x3 matrices on the level's fixed pattern (``_assembly``), never through ``J``. The
level cost is the sum of the terms (:class:`~o3dreg.registration._cost.LevelProblem`).

A distance term is a :class:`DistanceTermAtLevel`, made for one level by ``bind`` of its
public value type (:mod:`o3dreg.registration.terms`). Besides the contract it may use hooks,
whose defaults suit a term that reads only the shared point-to-surface geometry:
:meth:`~DistanceTermAtLevel.correspond` (correspondences of its own, measured at every
evaluation and held for the trial steps from it), :meth:`~DistanceTermAtLevel.start` and
:meth:`~DistanceTermAtLevel.own_weights` (a robust scale and weights of those correspondences),
and :attr:`~DistanceTermAtLevel.reassigns`. The barycentre term uses them all.
tests/registration/test_terms.py checks the contract for every term.

The moved points are ``y = base + W u`` with ``W`` the constant sparse trilinear weights of the
free nodes (see ``_cost``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .._geometry import row_norms
from ._assembly import NormalAssembly, symmetric_outer
from ._moves import LocalMoves
from ._robust import CorrespondenceMask, robust_scale
from ._threads import in_halves
from .checkers import CheckerContext, CorrespondenceChecker, bound_masks
from .distance import SurfaceDistanceQuery
from .lattice import TrilinearLattice

if TYPE_CHECKING:
    from .losses import RobustLoss


@dataclass
class Geometry:
    """What one evaluation measured at ``u``, before any weighting: the shared point-to-surface
    correspondences of the moved points, and what each distance term measured itself
    (``own``, in the order of the terms; ``None`` for a term without correspondences of its
    own)."""

    u: np.ndarray
    moved: np.ndarray
    distances: np.ndarray
    closest: np.ndarray
    gradients: np.ndarray
    faces: np.ndarray
    own: tuple[Any, ...] = ()


@dataclass
class Weights:
    """The weights of one linearisation (``None`` where unweighted).

    ``point``: per template point, robust weight times support; ``support``: the 0/1 masks of
    the correspondence checkers; ``own``: per distance term, the robust weights of its own
    correspondences (the barycentre term: per target point).
    """

    point: np.ndarray | None = None
    support: np.ndarray | None = None
    own: tuple[np.ndarray | None, ...] = ()


@dataclass(frozen=True)
class TermState:
    """What one distance term has of its own at an evaluation: its correspondences
    (``found``, from :meth:`DistanceTermAtLevel.correspond`), their robust weights, and the
    linearisation data held from the point a trial step starts at (``held``, its block's
    :attr:`TermBlock.held`; ``None``: made from ``found``)."""

    found: Any = None
    weights: np.ndarray | None = None
    held: Any = None


@dataclass
class TermBlock:
    """One term's residuals ``r`` at one ``u`` and what its Jacobian rows and normal-equation
    share are made of.

    ``jacobian`` is built on demand (Levenberg-Marquardt needs only the cost of a trial step,
    and only the normal equations at accepted points). A distance term's rows are
    ``W_i (x) v_i`` (point-to-surface, ``v_i`` a row vector) or ``s_i W_i (x) I_3``
    (barycentre); its share of ``J^T J`` is then ``sum_i (W_i^T W_i) (x) M_i`` with ``metric``
    the 6 entries of every ``M_i`` and ``isotropic`` a further ``c_i I``, its share of
    ``J^T r`` is ``sum_i W_i^T f_i`` with ``rhs`` the ``f_i`` (see ``_assembly``).
    """

    value: np.ndarray | Callable[[], np.ndarray] = field(repr=False)
    make_jacobian: Callable[[], sp.csr_matrix] = field(repr=False)
    #: ``|r|^2``, given where it is cheaper than from ``r`` (the regulariser: ``u^T (J^T J) u``).
    known_cost: float | None = None
    metric: np.ndarray | None = None
    isotropic: np.ndarray | None = None
    rhs: np.ndarray | None = None
    #: What a trial step from this point holds of the term (the barycentre term: its ``(b, s)``).
    held: Any = None
    #: ``J^T r`` of a term whose share does not go through per-point metrics (the regulariser).
    gradient: np.ndarray | None = None

    @cached_property
    def residuals(self) -> np.ndarray:
        """The residual vector ``r`` (built on demand where only its norm is needed)."""
        return self.value() if callable(self.value) else self.value

    @cached_property
    def cost(self) -> float:
        if self.known_cost is not None:
            return self.known_cost
        return float(self.residuals @ self.residuals)

    @cached_property
    def jacobian(self) -> sp.csr_matrix:
        return self.make_jacobian()


class ResidualTerm(Protocol):
    """The contract of a term of the level cost (see the module docstring)."""

    name: str

    def linearise(self, g: Geometry, w: Weights, state: TermState) -> TermBlock: ...

    def normal_share(self, block: TermBlock) -> tuple[sp.spmatrix, np.ndarray]: ...


@dataclass(frozen=True)
class RobustStart:
    """What a level knows when it estimates its robust scales, at ``u = 0``.

    Attributes
    ----------
    points : (n, 3) ndarray
        The level's template points moved by the coarser levels.
    keep : (n,) bool ndarray
        Their point-to-surface correspondences that the checkers not measured in scales accept.
    loss : RobustLoss
        The loss of every distance term.
    floor : float
        The smallest robust scale of the level.
    checkers : sequence of CorrespondenceChecker
        The checkers measured in robust scales (``needs_scale``), to bind with a term's own.
    context : CheckerContext
        The level's checker context (without a scale).
    """

    points: np.ndarray
    keep: np.ndarray
    loss: RobustLoss
    floor: float
    checkers: Sequence[CorrespondenceChecker]
    context: CheckerContext


class DistanceTermAtLevel:
    """A distance term of one level: the :class:`ResidualTerm` contract (:meth:`linearise`,
    :meth:`normal_share` through per-point metrics) and hooks whose defaults suit a term that
    reads only the shared point-to-surface geometry.

    Parameters
    ----------
    assembly : NormalAssembly
        The level's trilinear weights ``W`` and normal-equation pattern.
    """

    name = "distance term"
    #: Whether :meth:`correspond` re-assigns points at every evaluation: Levenberg-Marquardt's
    #: accepted steps are then a linearly converging fixed-point iteration, which the solver
    #: extrapolates (see ``_solvers._extrapolation``).
    reassigns = False

    def __init__(self, assembly: NormalAssembly) -> None:
        self.assembly = assembly

    @property
    def number_of_unknowns(self) -> int:
        return 3 * self.assembly.W.shape[1]

    def start(self, robust: RobustStart) -> None:
        """Estimate what the robust weights of :meth:`own_weights` need (called once, at the
        level start, when the level is robust)."""

    def correspond(self, y: np.ndarray, at_start: bool = False) -> Any:
        """The term's own correspondences at the moved points ``y`` (``at_start``: ``y`` is
        the level's start), or ``None`` when it has none."""
        return None

    def own_weights(self, g: Geometry, found: Any) -> np.ndarray | None:
        """Robust weights of the correspondences ``found`` at ``g`` (``None``: unweighted)."""
        return None

    @property
    def masks_own(self) -> bool:
        """Whether :meth:`own_mask` keeps some correspondences out, robust level or not."""
        return False

    def own_mask(self, found: Any) -> np.ndarray | None:
        """The 0/1 factor of each of the correspondences ``found`` that the term keeps, on top
        of the robust weights (``None``: all kept)."""
        return None

    def linearise(self, g: Geometry, w: Weights, state: TermState) -> TermBlock:
        raise NotImplementedError

    def normal_share(self, block: TermBlock) -> tuple[sp.spmatrix, np.ndarray]:
        """``(J^T J, J^T r)`` from the block's per-point metric and right-hand side."""
        assert block.rhs is not None
        n = block.rhs.shape[0]
        metric = block.metric if block.metric is not None else np.zeros((n, 6))
        A = self.assembly.matrix(metric, block.isotropic, with_gram=False)
        return A, self.assembly.vector(block.rhs)

    def point_rows(self, rows: np.ndarray) -> sp.csr_matrix:
        """The Jacobian of one residual per point with derivative ``rows[i]`` (a row vector)
        with respect to ``y_i``: row ``i`` is ``W_i (x) rows[i]``."""
        W = self.assembly.W
        n = rows.shape[0]
        return sp.csr_matrix(
            (
                (W.data[:, None] * rows[np.repeat(np.arange(n), np.diff(W.indptr))]).ravel(),
                (3 * W.indices[:, None] + np.arange(3)).ravel(),
                W.indptr * 3,
            ),
            shape=(n, self.number_of_unknowns),
        )

    def isotropic_rows(self, scale: np.ndarray) -> sp.csr_matrix:
        """The Jacobian of the residuals ``scale_i (y_i - c_i)`` (3 per point, ``c_i`` fixed):
        rows ``scale_i W_i (x) I_3``."""
        Wx = sp.kron(self.assembly.W, sp.identity(3), format="csr")  # (3n, 3m)
        return sp.diags(np.repeat(scale, 3), format="csr") @ Wx


class PointToSurfaceTerm(DistanceTermAtLevel):
    """(a) ``sqrt(w_i) d(y_i, S)`` for every template point: the distance to the target surface.

    Its derivative is ``sqrt(w_i)`` times the unit vector from the closest point (point-to-plane
    on the surface), so row ``i`` of ``J`` is ``W_i (x) v_i`` with ``v_i = sqrt(w_i) grad_i``;
    its share of ``J^T J`` has ``M_i = v_i v_i^T``, of ``J^T r`` ``f_i = r_i v_i``. It reads
    the point-to-surface geometry every evaluation measures (the weights, checkers and the
    verdict need it too).
    """

    name = "point-to-surface"

    def linearise(self, g: Geometry, w: Weights, state: TermState) -> TermBlock:
        dist, rows = g.distances, g.gradients
        r = dist
        if w.point is not None:
            sw = np.sqrt(w.point)
            r = sw * dist
            rows = rows * sw[:, None]
        return TermBlock(
            r,
            lambda: self.point_rows(rows),
            metric=symmetric_outer(rows),
            rhs=r[:, None] * rows,
        )


class PullTerm(DistanceTermAtLevel):
    """``s_i (y_i - c_i)`` for every point (3 residuals each): each moved point pulled towards
    a point ``c_i`` of its own with the weight ``s_i^2``.

    ``pulls(g, w, state) -> (c, s)`` gives them at an evaluation; they are held over the trial
    steps from it (as ICP holds its pairs while it solves for the motion), so the rows are
    ``s_i W_i (x) I_3`` and the share of ``J^T J`` is ``s_i^2 I`` per point. A point with
    ``s_i = 0`` has zero rows. The barycentre term is one (its ``c_i`` the barycentres); so is
    a term pulling given template points to given target points.

    Parameters
    ----------
    assembly : NormalAssembly
        The level's trilinear weights ``W`` and normal-equation pattern.
    pulls : callable, optional
        ``pulls(g, w, state) -> (c, s)``, ``(n, 3)`` and ``(n,)``; a subclass may override
        :meth:`pulls` instead.
    name : str
        The term's name.
    """

    name = "pull"

    def __init__(
        self,
        assembly: NormalAssembly,
        pulls: Callable[[Geometry, Weights, TermState], tuple[np.ndarray, np.ndarray]]
        | None = None,
        name: str | None = None,
    ) -> None:
        super().__init__(assembly)
        self._pulls = pulls
        if name is not None:
            self.name = name

    def pulls(self, g: Geometry, w: Weights, state: TermState) -> tuple[np.ndarray, np.ndarray]:
        """The points ``c`` and row scales ``s`` at ``g`` under ``w``."""
        if self._pulls is None:
            raise NotImplementedError("a PullTerm needs `pulls`")
        return self._pulls(g, w, state)

    def linearise(self, g: Geometry, w: Weights, state: TermState) -> TermBlock:
        """The block at ``g``; with ``state.held``, the ``(c, s)`` of the point a trial step
        starts at."""
        c, s = state.held if state.held is not None else self.pulls(g, w, state)
        r = s[:, None] * (g.moved - c)
        return TermBlock(
            r.ravel(),
            lambda: self.isotropic_rows(s),
            isotropic=s * s,
            rhs=s[:, None] * r,
            held=(c, s),
        )


class BarycentreTerm(PullTerm):
    """(b) ``s_i (y_i - b_i)`` for every template point: the target-to-template half of eq. (3).

    ``b_i`` is the barycentre of the target points whose nearest moved template point is ``i``
    (assigned at every accepted point of Levenberg-Marquardt and held fixed for its trial steps
    and in the Jacobian, as an ICP step does), averaged with the target points' robust weights
    ``v_j``; ``s_i = sqrt(w_s * mean_j v_j) * m_i`` with ``m_i`` the support mask of point
    ``i`` (``counted``: ``sqrt(w_s * (N / M) * sum_j v_j) * m_i``, ``N`` template and ``M``
    target points, so that the rows weigh what the target points they stand for weigh: the
    block is then the target->template distance ``(N / M) sum_j v_j |t_j - y_i|^2`` up to a
    constant; with ``areas`` ``a_j``, the target area each point stands for relative to the
    mean, ``a_j v_j`` replaces ``v_j`` in the sums and barycentres, so that the block is that
    distance integrated over the target's area, whatever its sampling): a template point with
    no data of its own gets no row, so data near a cut cannot pull the unsupported part of the
    template into the covered part. Every template point keeps a
    (possibly zero) row, so the residual vector keeps its length. With ``offsets``,
    ``b_i - offset_i`` replaces ``b_i`` (the template's own Voronoi centroid bias, see
    ``elastic._barycentre_offsets``). Its share of ``J^T J`` is ``s_i^2 I`` per point.

    Its correspondences (:meth:`correspond`) are the nearest template point of every target
    point and that distance ``e_j``; their robust weights ``v_j`` use a scale of their own and
    the checkers measured in scales. With ``beyond``, a target point pulls only if ``e_j``
    exceeds ``beyond`` at its template point and not ``within`` (:meth:`own_mask`; see
    :attr:`~o3dreg.ElasticLevel.barycentre_reach`); ``target_points`` may then be the
    candidates of a larger sample of ``stands_for`` points, which the rows are counted
    against, and ``scale_distances`` that sample's distances, which the robust scale is
    measured on.
    """

    name = "barycentre"
    reassigns = True

    def __init__(
        self,
        assembly: NormalAssembly,
        target_points: np.ndarray,
        weight: float,
        offsets: np.ndarray | None = None,
        counted: bool = False,
        beyond: np.ndarray | None = None,
        stands_for: int | None = None,
        within: float = np.inf,
        scale_distances: np.ndarray | None = None,
        template_mesh: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
        cell_size: float = np.inf,
        areas: np.ndarray | None = None,
    ) -> None:
        super().__init__(assembly)
        self.target_points = target_points
        # The target area each target point stands for, relative to the mean over the sample
        # (None: every point alike).
        self.areas = areas
        # A column per axis: gathered and summed per axis, faster than strided rows.
        self._columns = [np.ascontiguousarray(target_points[:, c]) for c in range(3)]
        # The number of target points the rows are counted against: the whole sample when
        # ``target_points`` are the candidates of ``beyond`` only.
        self.stands_for = target_points.shape[0] if stands_for is None else stands_for
        self.sqrt_ws = float(np.sqrt(weight))
        self.offsets = offsets
        self.counted = counted
        # Per template point, the distance a target point must exceed to pull it (None: any),
        # and the distance it must not exceed.
        self.beyond = beyond
        self.within = within
        # The distances the robust scale is measured on, where not those of ``target_points``.
        self.scale_distances = scale_distances
        # The moved template surface at the level start, to find the target points it covers
        # far from every template point (:meth:`_find_covered`), and the level's cell.
        self.template_mesh = template_mesh
        self.cell_size = cell_size
        self.covered: np.ndarray | None = None
        # The robust scale of the distances e_j, the loss and the masks measured in it (set by
        # :meth:`start`), and the level start's assignment when the scale measured it.
        self.sigma = 1.0
        self.loss: RobustLoss | None = None
        self.masks: list[CorrespondenceMask] = []
        self._start: tuple[np.ndarray, np.ndarray] | None = None
        self._nn_bound = np.inf
        # Search state of :meth:`measure`: the positions, nearest template point, gap between
        # the nearest and second-nearest distance at each target point's last search.
        self._last: np.ndarray | None = None
        self._moved = 0.0
        self._mark = np.zeros(0)
        self._path = np.zeros(0)
        self._path_mark = np.zeros(0)
        self._gap = np.zeros(0)
        self._nearest = np.zeros(0, dtype=np.int64)
        # The same bound with the moves summed near each target point (:class:`LocalMoves`):
        # the gap to the second-nearest capped at the cubes' side, and the marks of the sums.
        self._local: LocalMoves | None = None
        self._local_gap = np.zeros(0)
        self._local_mark = np.zeros(0)

    def start(self, robust: RobustStart) -> None:
        """The scale of the distances ``e_j`` over the target points, measured to the template
        points whose point-to-surface correspondence is kept."""
        base, keep = robust.points, robust.keep
        # The first evaluation's assignment; the scale is measured to the supported points
        # only, whose nearest is the same wherever the nearest of all is supported.
        self._start = e, nearest = self.measure(base)
        lost = ~keep[nearest] if keep.any() else np.zeros(e.shape, dtype=bool)
        if lost.any():
            e = e.copy()
            e[lost], _ = cKDTree(base[keep]).query(self.target_points[lost])
        self.loss = robust.loss
        if self.covered is not None and self.covered.any() and not self.covered.all():
            e = e[~self.covered]
        if self.scale_distances is not None:
            # Measured on all the sample (mostly covered): a target point far beyond every
            # other, debris rather than a part left short, is discounted by the loss.
            e = self.scale_distances
        self.sigma = robust.loss.scale or robust_scale(e, robust.floor)
        # The checkers measured in scales also judge the distances e_j, in their own scale.
        self.masks = bound_masks(robust.checkers, replace(robust.context, sigma=self.sigma))

    @property
    def masks_own(self) -> bool:
        return self.beyond is not None or self.template_mesh is not None

    def own_mask(self, found: Any) -> np.ndarray | None:
        """0 for the target points the template surface covers far from every template point
        (:meth:`_find_covered`); with ``beyond``, also for those no farther from their nearest
        template point than ``beyond`` there (the parts of the target the template reaches) or
        farther than ``within``; 1 elsewhere."""
        e, nearest = found
        keep = None
        if self.beyond is not None:
            keep = (e > self.beyond.take(nearest)) & (e <= self.within)
        if self.covered is not None and self.covered.any():
            keep = ~self.covered if keep is None else keep & ~self.covered
        return None if keep is None else keep.astype(np.float64)

    def correspond(self, y: np.ndarray, at_start: bool = False) -> tuple[np.ndarray, np.ndarray]:
        if at_start and self._start is not None:
            return self._start
        return self.measure(y)

    def own_weights(self, g: Geometry, found: Any) -> np.ndarray | None:
        assert self.loss is not None
        e = found[0]
        v = self.loss.weight(e, self.sigma)
        for mask in self.masks:
            v = v * mask.check(g.moved, e, g.faces, g.closest)
        return v

    def measure(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest moved template point of every target point (exact), and its distance.

        Only the target points whose nearest template point may have changed are searched
        again. A search returns the nearest and second-nearest distances ``e1 <= e2``; while
        the nearest template point has moved along a path of length ``d`` since and no template
        point by more than ``D``, the nearest is still nearer than any other if
        ``e1 + d < e2 - D`` (triangle inequality), so only points with ``d + D >= e2 - e1`` are
        searched (exact ties included), ``d`` the nearest point's summed moves between
        searches and ``D`` the sum of the template's largest moves (the nearest point's own
        path, tighter than ``D``, leaves fewer points to search for the same assignments). Given
        the level's cell, ``D`` is also summed near each target point
        (:class:`~o3dreg.registration._moves.LocalMoves`: the moves that ended in one of the 27
        cubes around it, with ``e2`` capped at the cubes' side), and a point is searched only
        when both bounds ask for it: a step of one part of the template leaves the rest
        unsearched. The k-d tree search is bounded by a radius that held for nearly all points last
        time (a bounded search prunes more); the few points without a neighbour inside it are
        searched again unbounded.
        """
        search = self._plan(y)
        if search is not None:
            tree = cKDTree(y, leafsize=32, balanced_tree=False, compact_nodes=False)
            k = min(2, y.shape[0])
            # take: rows gathered several times faster than by fancy indexing.
            points = self.target_points.take(search, axis=0)
            bound = self._nn_bound
            if not np.isfinite(bound) and points.shape[0] > 4 * FIRST_BOUND_SAMPLE:
                # A first search knows no distances yet: those of a strided share of its points.
                share = points[:: points.shape[0] // FIRST_BOUND_SAMPLE]
                bound = _search_radius(tree.query(share)[0])
            self._keep(search, _nearest_two(tree, points, k, bound))
        found = self._assignment(y)
        if self.covered is None and self.template_mesh is not None:
            self.covered = self._find_covered(found[0])
        return found

    def _find_covered(self, e: np.ndarray) -> np.ndarray:
        """The target points the template surface covers far from every template point: nearer
        to the surface than to their nearest template point by more than
        :data:`COVERED_SHARE` of a cell and at most :data:`COVERED_RATIO` times as far from it,
        measured once, at the level start (``e``: those distances there).

        The term stands for the target -> template distance by the distance to the nearest
        template point. On a template with triangles far larger than its spacing elsewhere (the
        long slivers a quadric decimation leaves on a straight shaft) a target point over such a
        triangle is on the template's surface, yet far from every vertex; left in, it would
        pull the few vertices around the triangle along the surface with the weight of all the
        target it covers. Only the points farther than the margin from their nearest template
        point are measured: a nearer one cannot be nearer to the surface by more than that.
        """
        margin = COVERED_SHARE * self.cell_size
        covered = np.zeros(e.shape[0], dtype=bool)
        far = np.flatnonzero(e > margin)
        if far.size and self.template_mesh is not None:
            surface = SurfaceDistanceQuery(*self.template_mesh())
            ef = e.take(far)
            # Few points as a rule (a template's large triangles): the tree of the triangles
            # near them, not of the whole template.
            d = surface.closest_few(self.target_points.take(far, axis=0))[0]
            covered[far[(ef - d > margin) & (d < COVERED_RATIO * ef)]] = True
        return covered

    def _plan(self, y: np.ndarray) -> np.ndarray | None:
        """Move the search state to ``y``; the target points to search again (indices), or
        ``None`` when none needs it."""
        t = self.target_points
        if self._last is None or self._last.shape != y.shape:
            search = np.arange(t.shape[0])
            self._moved = 0.0
            self._path = np.zeros(y.shape[0])
            self._mark = np.zeros(t.shape[0])
            self._path_mark = np.zeros(t.shape[0])
            self._gap = np.zeros(t.shape[0])
            self._nearest = np.zeros(t.shape[0], dtype=np.int64)
            self._local = None
            if np.isfinite(self.cell_size) and t.shape[0] > 0:
                self._local = LocalMoves(t, y, LOCAL_MOVES_SHARE * self.cell_size)
                self._local_gap = np.zeros(t.shape[0])
                self._local_mark = np.zeros(t.shape[0])
        else:
            step = row_norms(y - self._last)
            self._moved += float(step.max())
            self._path += step
            # The nearest point has come at most its own path nearer or farther, any other at
            # most the largest path nearer (anywhere, or near this target point).
            own = self._path.take(self._nearest) - self._path_mark
            may_change = own + (self._moved - self._mark) >= self._gap
            if self._local is not None:
                self._local.step(y, step)
                may_change &= own + self._local.since(self._local_mark) >= self._local_gap
            search = np.flatnonzero(may_change)
        self._last = y.copy()
        return search if search.size else None

    def _keep(self, search: np.ndarray, found: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """Keep what a search (:func:`_nearest_two`) ``found`` for the target points
        ``search``."""
        e, nearest, bound = found
        first = nearest[:, 0]
        second = np.full(e.shape[0], np.inf)
        if e.shape[1] == 2:
            # Exact ties (symmetric shapes) go to the smaller index, whatever the tree's
            # order; a second neighbour beyond the search radius is at least that far.
            tied = np.flatnonzero(e[:, 1] == e[:, 0])
            if tied.size:
                first = first.copy()
                first[tied] = nearest[tied].min(axis=1)
            second = np.minimum(e[:, 1], bound)
        # Every point searched (a level's first search, large moves): slices, not scatters.
        at: Any = slice(None) if search.size == self._nearest.size else search
        self._nearest[at] = first
        self._gap[at] = second - e[:, 0]
        self._mark[at] = self._moved
        self._path_mark[at] = self._path.take(first)
        if self._local is not None:
            self._local_gap[at] = np.minimum(second, self._local.side) - e[:, 0]
            self._local_mark[at] = self._local.marks(at)

    def _assignment(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest template point of every target point at ``y`` (as kept) and its
        distance; the next search's radius."""
        nearest = self._nearest.copy()
        # row_norms(target_points - y[nearest]), the same numbers, a column at a time.
        d = [
            col - np.ascontiguousarray(y[:, c]).take(nearest) for c, col in enumerate(self._columns)
        ]
        distance = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        self._nn_bound = _search_radius(distance[:: max(1, distance.size // NN_BOUND_SAMPLE)])
        return distance, nearest

    def targets(
        self,
        number_of_points: int,
        nearest: np.ndarray,
        v: np.ndarray | None = None,
        support: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The barycentres ``b_i`` (offsets applied) and row scales ``s_i`` of the assignment
        ``nearest`` (of every target point) with the target points' robust weights ``v`` (times
        their ``areas``) and the template points' ``support``."""
        n = number_of_points
        if self.areas is not None:
            v = self.areas if v is None else v * self.areas
        counts = np.bincount(nearest, minlength=n)
        if v is not None:
            vsum = np.bincount(nearest, v, minlength=n)
            sums = np.stack(
                [np.bincount(nearest, v * col, minlength=n) for col in self._columns], axis=1
            )
            bary = sums / np.where(vsum > 0, vsum, 1.0)[:, None]
            if self.counted:
                assigned = vsum / (self.stands_for / n)
            else:
                assigned = vsum / np.maximum(counts, 1)
        else:
            sums = np.stack(
                [np.bincount(nearest, col, minlength=n) for col in self._columns], axis=1
            )
            bary = sums / np.maximum(counts, 1)[:, None]
            if self.counted:
                assigned = counts / (self.stands_for / n)
            else:
                assigned = (counts > 0).astype(np.float64)
        if support is not None:
            assigned = assigned * support
        scale = self.sqrt_ws * np.sqrt(assigned)
        if self.offsets is not None:
            bary = bary - self.offsets
        return bary, scale

    def pulls(self, g: Geometry, w: Weights, state: TermState) -> tuple[np.ndarray, np.ndarray]:
        """The barycentres and row scales of the assignment ``state.found``."""
        return self.targets(g.moved.shape[0], state.found[1], state.weights, w.support)


#: A target point is covered by the template surface far from every template point (and left
#: out of the barycentre term) when it is nearer to that surface than to its nearest template
#: point by more than COVERED_SHARE of the level's cell (on an evenly sampled template the two
#: differ by less than half its spacing, a fraction of any cell the template's detail fits) and
#: at most COVERED_RATIO times as far from the surface as from that point. A point the template
#: has not reached (the paper's cone spreading over a sphere leaves parts of it 5-10 mm away)
#: is about as far from both, and keeps pulling.
COVERED_SHARE = 0.2
COVERED_RATIO = 0.5


#: The neighbour whose distance is a template point's ring radius: on a triangulated surface a
#: vertex has about 6 neighbours around it.
RING_NEIGHBOURS = 6


#: A target point is a candidate of the reach-limited barycentre term when, at the level start,
#: it is farther than this share of the threshold from its nearest template point; the others
#: are left out of the level's searches (a fine level moves a template point by a fraction of
#: its ring, and on a covered target they are nearly all of them).
CANDIDATE_SHARE = 0.8


def uncovered_candidates(
    points: np.ndarray,
    target_points: np.ndarray,
    reach: float,
    known: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The threshold of every template point (``reach`` times its ring radius: its distance to
    its :data:`RING_NEIGHBOURS`-th nearest other point, or the farthest for fewer points, 0 for
    one; no point of a surface the points sample evenly is farther than that from its nearest
    point), the indices of the target points farther than :data:`CANDIDATE_SHARE` of it from
    their nearest template point, and every target point's distance to that point (``known``:
    those distances and nearest points, where the caller has them)."""
    tree = cKDTree(points)
    k = min(RING_NEIGHBOURS + 1, points.shape[0])
    ring = tree.query(points, k=k)[0][:, -1] if k >= 2 else np.zeros(points.shape[0])
    beyond = reach * ring
    e, nearest = known if known is not None else tree.query(target_points, workers=-1)
    return beyond, np.flatnonzero(e > CANDIDATE_SHARE * beyond.take(nearest)), e


#: The side of the cubes :class:`~o3dreg.registration._moves.LocalMoves` sums the template's
#: moves on, in cells of the level's lattice (at least a 32nd of the extent). Coarser cubes sum
#: the moves of more of the template, finer ones cap more gaps at their side: on the bunny's
#: medium and large warps an eighth of a cell searched 11% fewer target points than half a cell.
LOCAL_MOVES_SHARE = 0.125


#: Distances the barycentre term's search radius is estimated from (a strided share of all).
NN_BOUND_SAMPLE = 4096

#: Target points a level's first search estimates its radius from (it knows no distances yet).
FIRST_BOUND_SAMPLE = 256


def _search_radius(distances: np.ndarray) -> float:
    """The radius a search of the barycentre term is bounded by, from an even share of the
    distances to the nearest template point: twice their 99th percentile (``inf`` for none).
    It only decides which points are searched twice (the answer is exact either way)."""
    return 2.0 * float(np.percentile(distances, 99)) if distances.size else np.inf


def _nearest_two(
    tree: Any,
    points: np.ndarray,
    k: int,
    bound: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``k`` nearest sites (two, or one for a tree of one site) of ``points`` in ``tree``,
    searched within ``bound`` first and the points without a neighbour inside it again
    unbounded; the radius each point was searched within.

    A large batch is searched in two halves at once
    (:func:`~o3dreg.registration._threads.in_halves`).
    """
    e, nearest = in_halves(lambda p: tree.query(p, k=k, distance_upper_bound=bound), points)
    e, nearest = e.reshape(-1, k), nearest.reshape(-1, k)
    radius = np.full(e.shape[0], bound)
    missed = ~np.isfinite(e[:, 0])
    if missed.any():
        e2, n2 = tree.query(points[missed], k=k)
        e[missed], nearest[missed] = e2.reshape(-1, k), n2.reshape(-1, k)
        radius[missed] = np.inf
    return e, nearest, radius


def _stencils() -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    eye = np.eye(3, dtype=np.int64)
    membrane = [(np.array([np.zeros(3, np.int64), e]), np.array([-1.0, 1.0])) for e in eye]
    bending = [
        (np.array([np.zeros(3, np.int64), e, 2 * e]), np.array([1.0, -2.0, 1.0])) for e in eye
    ]
    for a, b in ((0, 1), (1, 2), (0, 2)):
        offsets = np.array([np.zeros(3, np.int64), eye[a], eye[b], eye[a] + eye[b]])
        bending.append((offsets, np.sqrt(2.0) * np.array([1.0, -1.0, -1.0, 1.0])))
    return {"membrane": membrane, "bending": bending}


_STENCILS = _stencils()


class RegulariserTerm:
    """(c) ``sqrt(lambda N / E) (D u)``: the regulariser ``P(p)`` over the ``E`` finite-difference
    stencils of the lattice that touch a free node (``N`` template points).

    ``'bending'``: second differences along each axis and mixed differences weighted ``sqrt(2)``
    (the thin-plate energy ``int |Hess u|^2``), whose null space is the affine maps: a level may
    add any affine motion without cost. ``'membrane'``: first differences (``int |grad u|^2``).
    Fixed nodes keep a zero increment. Linear in ``u``: ``J`` and ``J^T J`` are constant;
    :attr:`node_gram` is ``J^T J`` per node pair (``J^T J = node_gram (x) I_3``).
    """

    name = "regulariser"

    def __init__(
        self,
        lattice: TrilinearLattice,
        lookup: np.ndarray,
        number_of_free_nodes: int,
        regularization: float,
        number_of_points: int,
        energy: str = "bending",
    ) -> None:
        G = _stencil_matrix(lattice, lookup, number_of_free_nodes, energy)
        edges = max(G.shape[0], 1)
        self.sqrt_reg = float(np.sqrt(regularization * number_of_points / edges))
        self.G = (G * self.sqrt_reg).tocsr()
        self.node_gram = (self.G.T @ self.G).tocsr()

    def residuals(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(self.G @ u.reshape(-1, 3)).ravel()

    def linearise(self, g: Geometry, w: Weights, state: TermState | None = None) -> TermBlock:
        U = g.u.reshape(-1, 3)
        gradient = np.asarray(self.node_gram @ U)
        # |D u|^2 = u^T (D^T D) u: the product with the small node Gram matrix, which the
        # normal equations need anyway, instead of the long residual vector.
        cost = max(float((U * gradient).sum()), 0.0)
        return TermBlock(
            lambda: self.residuals(g.u),
            lambda: sp.kron(self.G, sp.identity(3), format="csr"),
            known_cost=cost,
            gradient=gradient.ravel(),
        )

    def normal_share(self, block: TermBlock) -> tuple[sp.spmatrix, np.ndarray]:
        J = block.jacobian
        return (J.T @ J).tocsr(), J.T @ block.residuals


def _stencil_matrix(
    lattice: TrilinearLattice, lookup: np.ndarray, number_of_free_nodes: int, energy: str
) -> sp.csr_matrix:
    """Finite-difference operator over the lattice, one row per stencil touching a free node
    (``lookup``: free-node index of every lattice node, -1 where fixed), stencil by stencil,
    anchors in node order."""
    node_shape = np.asarray(lattice.node_shape)
    rows, cols, vals = [], [], []
    count = 0
    for offsets, coefs in _STENCILS[energy]:
        # The anchors whose stencil fits in the lattice, in node order; node numbers are linear
        # in the node coordinates, so a stencil's nodes are its anchor's number plus offsets.
        span = offsets.max(axis=0)
        axes = [np.arange(int(n - s)) for n, s in zip(node_shape, span)]
        grid = np.meshgrid(*axes, indexing="ij")
        anchors = lattice.node_index(np.stack([g.ravel() for g in grid], axis=1))
        local = lookup[anchors[:, None] + lattice.node_index(offsets)[None, :]]
        free = local >= 0
        keep = free[:, 0].copy()
        for j in range(1, free.shape[1]):
            keep |= free[:, j]
        local, free = local[keep], free[keep]
        e = count + np.arange(local.shape[0])
        for j, c in enumerate(coefs):
            rows.append(e[free[:, j]])
            cols.append(local[free[:, j], j])
            vals.append(np.full(rows[-1].size, c))
        count += local.shape[0]
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(count, number_of_free_nodes),
    )
