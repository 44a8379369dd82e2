"""The cost of one level, eq. (3) of Berar et al. (2005), with its analytic Jacobian: the sum of
the distance terms a :class:`~o3dreg.DistanceEstimation` holds (bound to the level, ``_terms``)
and the level's regulariser, weighted by the loss and the checkers.

Unknowns ``u`` are the displacements of the level's free lattice nodes, node-major
(``[u_0x, u_0y, u_0z, u_1x, ...]``). The template points ``x`` (rigidly aligned) are fixed, so the
moved points ``y = x + prev(x) + W u`` are linear in ``u`` with the constant sparse matrix ``W`` of
trilinear weights (8 nodes per point). Every evaluation measures the point-to-surface
correspondences of the moved points once (AABB tree): the point-to-surface term, the weights,
the checkers and the level's report read them. A term with correspondences of its own (the
barycentre term: the nearest template point of every target point) measures them too, and
trial steps hold them (:meth:`LevelProblem.evaluate`).

Robustness enters as per-row weights, recomputed at every accepted point and held fixed in
the Jacobian (iteratively reweighted least squares inside Levenberg-Marquardt): the
point-to-surface rows become ``sqrt(w_i) d_i`` with Jacobian ``sqrt(w_i) grad_i (x) W_i``, where
``w_i`` is the robust-loss weight of ``d_i`` (see :class:`~o3dreg.DistanceEstimation`) times the
0/1 masks of the checkers (closest point beyond the target's open boundary, incompatible
normals, distance beyond ``max_distance_factor`` scales). A term's own correspondences get
weights of their own (:meth:`~o3dreg.registration._terms.DistanceTermAtLevel.own_weights`,
in a scale of their own); the masks ``m_i`` of the template points are offered to every term
(the barycentre term gives a template point with no data of its own no row, so data near a cut
cannot pull the unsupported part of the template into the covered part).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from .._geometry import det3
from ..mesh.distinct import distinct
from ._assembly import NormalAssembly
from ._robust import CorrespondenceMask, robust_scale, support
from ._terms import (
    DistanceTermAtLevel,
    Geometry,
    RegulariserTerm,
    ResidualTerm,
    RobustStart,
    TermBlock,
    TermState,
    Weights,
)
from .checkers import CheckerContext, CorrespondenceChecker, bound_masks
from .distance import SurfaceDistanceQuery
from .lattice import TrilinearLattice
from .losses import L2Loss, RobustLoss
from .terms import DistanceTerm, TargetSamples, TermContext, WholeTarget

__all__ = ["SCALE_FLOOR", "Evaluation", "LevelProblem", "bound_masks"]

#: Smallest robust scale ``sigma``, as a fraction of the level's cell size. A level that starts
#: nearly converged (the finest ones on a clean target) has a tiny median residual; a scale
#: taken from it alone would discount the tail of genuine misfit the level is there to remove.
#: A smaller floor costs accuracy on clean targets, a larger one robustness to cuts and debris
#: (benchmarks/bench_robust.py measures both sides).
SCALE_FLOOR = 0.05


@dataclass
class Evaluation:
    """Residuals, Jacobian blocks and cost terms at one ``u``."""

    u: np.ndarray
    cost: float
    distances: np.ndarray
    moved: np.ndarray
    weights: np.ndarray | None = None
    support: np.ndarray | None = None
    #: Per distance term, the robust weights of its own correspondences.
    own_weights: tuple[np.ndarray | None, ...] = ()
    geometry: Geometry | None = None
    terms: tuple[TermBlock, ...] = ()
    #: The names of the terms, in the order of :attr:`terms`.
    names: tuple[str, ...] = ()
    #: Whether the terms' own correspondences are those of an earlier point (a trial step).
    held: bool = False

    def cost_of(self, name: str) -> float:
        """The cost of the terms called ``name`` (0 when there is none)."""
        return sum((b.cost for b, n in zip(self.terms, self.names) if n == name), 0.0)

    @property
    def residuals(self) -> np.ndarray:
        """All residuals, the terms' in order (built on demand: the solver needs the cost)."""
        return np.concatenate([b.residuals for b in self.terms])

    @property
    def jacobian(self) -> sp.csr_matrix:
        """The full sparse Jacobian: the terms' blocks (built on demand) stacked."""
        return sp.vstack([b.jacobian for b in self.terms], format="csr")


class LevelProblem:
    """Residuals and Jacobian of one lattice level for a fixed set of template points.

    The cost is the sum of :attr:`terms`: the distance terms bound to the level, in the order
    given, then the regulariser; the residual vector follows that order.

    Parameters
    ----------
    points : (n, 3) ndarray
        Template vertices after the rigid transformation.
    previous : (n, 3) ndarray
        Displacement of ``points`` by the coarser levels (held fixed).
    lattice : TrilinearLattice
        The level's lattice (its displacements are ignored: the increment starts at zero).
    active : (n,) bool ndarray
        Points whose cells are refined; the nodes of those cells are the unknowns.
    target : SurfaceDistanceQuery
        The target surface.
    terms : sequence of DistanceTerm
        The distance terms, each bound to the level with what it offers (``TermContext`` of
        :mod:`o3dreg.registration.terms`); a term whose ``bind`` gives ``None`` has no rows
        here.
    regularization : float
        The regulariser's ``lambda``.
    energy : {'bending', 'membrane'}
        The regulariser's finite differences (see :class:`~o3dreg.ElasticLevel`).
    target_samples : TargetSamples, optional
        Target vertices for the terms that measure from the target, and the area each stands
        for (default :class:`~o3dreg.registration.terms.WholeTarget`: every vertex of
        ``target``, every point counting alike).
    indices : (n,) int ndarray, optional
        The numbers of ``points`` among the template's vertices (default ``0 .. n-1``).
    symmetric_scale : float
        The level's :attr:`~o3dreg.ElasticLevel.symmetric_scale`.
    barycentre_reach : float or None
        The level's :attr:`~o3dreg.ElasticLevel.barycentre_reach`.
    voronoi_offsets : callable, optional
        The barycentre correction's offsets (see :class:`~o3dreg.Barycentre`).
    loss : RobustLoss, optional
        The robust loss of every distance term (default plain least squares).
    checkers : sequence of CorrespondenceChecker
        Bound to masks for this level: before the robust scales are estimated, or after them
        for those measured in scales (``needs_scale``).
    target_has_boundary : bool
        Whether the whole target has open edges (``target`` may be a simplified copy).
    min_jacobian_determinant : float or None
        The folding guard's threshold (``None``: no guard).
    normals : (n, 3) ndarray or None
        Template normals turned to the target's orientation, for the normal-angle checker.
    prior : LatticeDeformation or None
        The coarser levels' map, whose Jacobian the folding guard adds to this level's.
    start : tuple of ndarray, optional
        :meth:`SurfaceDistanceQuery.closest` of ``points + previous`` on ``target``, where the
        caller has it (the previous level ended there); queried otherwise.
    nearest_known : callable, optional
        ``nearest_known(sample)``: the nearest of ``points + previous`` of every point of a
        target sample and its distance, where the previous level's search state has them
        (``None`` otherwise).
    template_mesh : callable, optional
        ``template_mesh()``: every template vertex moved by the coarser levels, and the
        template's faces, for the terms that measure the template's surface.
    """

    def __init__(
        self,
        points: np.ndarray,
        previous: np.ndarray,
        lattice: TrilinearLattice,
        active: np.ndarray,
        target: SurfaceDistanceQuery,
        terms: Sequence[DistanceTerm],
        regularization: float,
        energy: str = "bending",
        *,
        target_samples: TargetSamples | None = None,
        indices: np.ndarray | None = None,
        symmetric_scale: float = 1.0,
        barycentre_reach: float | None = None,
        voronoi_offsets: Callable[[], np.ndarray] | None = None,
        loss: RobustLoss | None = None,
        checkers: Sequence[CorrespondenceChecker] = (),
        target_has_boundary: bool = True,
        min_jacobian_determinant: float | None = None,
        normals: np.ndarray | None = None,
        prior: Any = None,
        start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        nearest_known: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None] | None = None,
        template_mesh: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        self.lattice = lattice
        self.loss = loss or L2Loss()
        self.min_jacobian_determinant = min_jacobian_determinant
        self.base = points + previous
        self._points = points
        self.target = target
        n = points.shape[0]
        nodes, weights = lattice.weights(points)
        free_nodes = distinct(nodes[active], lattice.number_of_nodes)
        lookup = np.full(lattice.number_of_nodes, -1, dtype=np.int64)
        lookup[free_nodes] = np.arange(free_nodes.size)
        self.free_nodes = free_nodes
        self._lookup = lookup
        local = lookup[nodes]
        self.number_of_unknowns = 3 * free_nodes.size
        self.regulariser = RegulariserTerm(
            lattice, lookup, free_nodes.size, regularization, n, energy
        )
        self.assembly = NormalAssembly(
            local,
            np.where(local >= 0, weights, 0.0),
            free_nodes.size,
            self.regulariser.node_gram,
            cells=nodes[:, 0],
        )
        offered = TermContext(
            self.assembly,
            self.base,
            np.arange(n) if indices is None else indices,
            target,
            target_samples or WholeTarget(target.vertices),
            symmetric_scale,
            voronoi_offsets,
            barycentre_reach,
            nearest_known,
            float(lattice.cell_size.min()),
            template_mesh,
        )
        bound = (term.bind(offered) for term in terms)
        self.distance_terms: list[DistanceTermAtLevel] = [t for t in bound if t is not None]
        self.terms: list[ResidualTerm] = [*self.distance_terms, self.regulariser]
        context = CheckerContext(target, target_has_boundary, normals)
        # The masks of the checkers, in the order they are combined; those measured in robust
        # scales are bound once the scales are known.
        self.checkers: list[CorrespondenceMask] = bound_masks(
            [c for c in checkers if not c.needs_scale], context
        )
        scaled = [c for c in checkers if c.needs_scale]
        self._robust = not isinstance(self.loss, L2Loss) or bool(scaled)
        self._own_masked = any(t.masks_own for t in self.distance_terms)
        self.sigma = 1.0
        # The closest points at the level start, shared by the scales and the first evaluation.
        self._start = start
        if self._robust:
            self._estimate_scales(lattice, scaled, context)
        self.checkers += bound_masks(scaled, replace(context, sigma=self.sigma))
        self._fold = None
        if min_jacobian_determinant is not None and self.number_of_unknowns:
            self._fold = self._fold_samples(prior, active)

    def _estimate_scales(
        self,
        lattice: TrilinearLattice,
        scaled: list[CorrespondenceChecker],
        context: CheckerContext,
    ) -> None:
        """The robust scale ``sigma`` of the point-to-surface distances from the data at the
        level start (``u = 0``), over the correspondences the other checkers accept (the
        distance checker itself is measured in this scale); then each distance term's own."""
        floor = SCALE_FLOOR * float(lattice.cell_size.min())
        if self._start is None:
            self._start = self.target.closest(self.base)
        dist, face, closest = self._start
        keep = support(self.checkers, self.base, dist, face, closest)
        self.sigma = self.loss.scale or robust_scale(dist[keep], floor)
        start = RobustStart(self.base, keep, self.loss, floor, scaled, context)
        for term in self.distance_terms:
            term.start(start)

    # -- folding ----------------------------------------------------------------------------------
    def _fold_samples(
        self, prior: Any, active: np.ndarray
    ) -> tuple[np.ndarray, list[sp.csr_matrix]]:
        """Samples of the map where the level moves the template: the active points themselves
        and 8 samples (local coordinates 1/4 and 3/4) of every cell holding one; the Jacobian of
        the coarser levels there and the derivative operators of the increment
        (``d u / d x_a = D_a U``)."""
        lat = self.lattice
        f = self.free_nodes
        moved = self._points[active]
        # det(dT/dx) is a cubic inside a cell: positive at the 8 samples, it can still be
        # negative at a template point between them (a fold the verdict then measures).
        pts = np.vstack([lat.cell_samples(lat.occupied_cells(moved)), moved])
        base = np.broadcast_to(np.eye(3), (pts.shape[0], 3, 3)).copy()
        if prior is not None:
            base = prior.jacobian(pts)
        nodes, _, grads = lat.basis(pts)
        local_nodes = self._lookup[nodes]
        keep = local_nodes >= 0
        rows = np.broadcast_to(np.arange(pts.shape[0])[:, None], nodes.shape)[keep]
        ops = [
            sp.csr_matrix(
                (grads[:, :, a][keep], (rows, local_nodes[keep])), shape=(pts.shape[0], f.size)
            )
            for a in range(3)
        ]
        return base, ops

    @property
    def reassigns(self) -> bool:
        """Whether a term re-assigns correspondences at every evaluation (the barycentre term):
        Levenberg-Marquardt's accepted steps are then a linearly converging fixed-point
        iteration (see ``_solvers._extrapolation``)."""
        return any(term.reassigns for term in self.distance_terms)

    @property
    def guards_folding(self) -> bool:
        """Whether :meth:`min_determinant` samples the map (the folding guard is on)."""
        return self._fold is not None

    def min_determinant(self, u: np.ndarray) -> float:
        """Smallest ``det(dT/dx)`` over the fold samples with this level's increment ``u``."""
        if self._fold is None:
            return 1.0
        base, ops = self._fold
        U = u.reshape(-1, 3)
        jac = base.copy()
        for a, D in enumerate(ops):
            jac[:, :, a] += D @ U
        return float(det3(jac).min()) if jac.shape[0] else 1.0

    def moved(self, u: np.ndarray) -> np.ndarray:
        """Template points moved by the coarser levels and the increment ``u``."""
        return self.base + self.assembly.W @ u.reshape(-1, 3)

    def scatter(self, u: np.ndarray) -> TrilinearLattice:
        """The level's lattice with the free nodes displaced by ``u``."""
        d = np.zeros((self.lattice.number_of_nodes, 3))
        d[self.free_nodes] = u.reshape(-1, 3)
        return self.lattice.with_displacements(d)

    def evaluate(
        self, u: np.ndarray, weights_of: Evaluation | None = None, *, reassign: bool = False
    ) -> Evaluation:
        """Residuals (and Jacobian blocks, built on demand) at ``u``.

        With ``weights_of``, the evaluation of a trial step from that earlier point: its robust
        weights and 0/1 masks are those of ``weights_of``, and so are the terms' own
        correspondences (the barycentre term's assignment of target points to template points).
        Levenberg-Marquardt compares a trial with the current point under one linearisation
        (one weighted least-squares problem, as in iteratively reweighted least squares and in
        ICP, whose assignments are fixed while the transformation is solved for): measured under
        its own weights, a step that brings more template points into support would count their
        distances as a cost increase and be rejected although it moved towards the data, and a
        changing assignment makes the quadratic model's predictions meaningless.
        :meth:`reweighted` then gives the accepted point its own weights and correspondences.

        With ``reassign`` (and ``weights_of``), the terms' own correspondences are those of ``u``
        itself while the weights and masks stay those of ``weights_of``: a point reached by
        extrapolating several steps (see ``_solvers``) is compared with the current one under
        the same weights (a jump cannot look better by pushing points into rejection), each
        with the assignment a Levenberg-Marquardt step from it would start from.
        """
        y = self.moved(u)
        at_start = not u.any()
        found = self._start if at_start else None
        dist, closest, grad, face = self.target.gradient(y, return_faces=True, found=found)
        if weights_of is None:
            own = tuple(term.correspond(y, at_start) for term in self.distance_terms)
            geometry = Geometry(u, y, dist, closest, grad, face, own)
            return self._assemble(geometry, self._weights(geometry))
        assert weights_of.geometry is not None
        own = weights_of.geometry.own
        if reassign:
            own = tuple(term.correspond(y) for term in self.distance_terms)
        geometry = Geometry(u, y, dist, closest, grad, face, own)
        weights = Weights(weights_of.weights, weights_of.support, weights_of.own_weights)
        held = None
        if not reassign:
            held = tuple(block.held for block in weights_of.terms[: len(self.distance_terms)])
        return self._assemble(geometry, weights, held)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        """``ev`` with the weights, masks and own correspondences of its own point (no new
        point-to-surface query)."""
        g = ev.geometry
        assert g is not None
        if ev.held:
            g = replace(g, own=tuple(term.correspond(g.moved) for term in self.distance_terms))
        return self._assemble(g, self._weights(g))

    def _weights(self, g: Geometry) -> Weights:
        """Per-point weights (robust kernel times the checkers' support), support masks and
        each distance term's weights of its own correspondences at the geometry ``g``."""
        own: tuple[np.ndarray | None, ...] = (None,) * len(self.distance_terms)
        if self._robust:
            own = tuple(t.own_weights(g, f) for t, f in zip(self.distance_terms, g.own))
        if self._own_masked:
            own = tuple(
                _times(v, t.own_mask(f)) for v, t, f in zip(own, self.distance_terms, g.own)
            )
        if not (self.checkers or self._robust):
            return Weights(own=own)
        mask = support(self.checkers, g.moved, g.distances, g.faces, g.closest)
        w = self.loss.weight(g.distances, self.sigma) * mask
        return Weights(w, mask, own)

    def _assemble(self, g: Geometry, w: Weights, held: tuple[Any, ...] | None = None) -> Evaluation:
        """The terms' blocks at ``g`` under ``w`` (``held``: per distance term, what the trial
        step holds of the point it starts at)."""
        blocks = []
        for k, term in enumerate(self.distance_terms):
            state = TermState(g.own[k], w.own[k], None if held is None else held[k])
            blocks.append(term.linearise(g, w, state))
        blocks.append(self.regulariser.linearise(g, w))
        cost = 0.0
        for block in blocks:
            cost += block.cost
        return Evaluation(
            u=g.u,
            cost=cost,
            distances=g.distances,
            moved=g.moved,
            weights=w.point,
            support=w.support,
            own_weights=w.own,
            geometry=g,
            terms=tuple(blocks),
            names=tuple(term.name for term in self.terms),
            held=held is not None,
        )

    def normal_equations(self, ev: Evaluation) -> tuple[sp.bsr_matrix, np.ndarray]:
        """``J^T J`` and ``J^T r``, the sum of the terms' shares, assembled on the level's fixed
        pattern (``_assembly``): the distance terms' per-point metrics and right-hand sides are
        summed first, then scattered once."""
        n = ev.moved.shape[0]
        metric = np.zeros((n, 6))
        isotropic = None
        rhs = np.zeros((n, 3))
        for block in ev.terms[: len(self.distance_terms)]:
            assert block.rhs is not None
            if block.metric is not None:
                metric += block.metric
            if block.isotropic is not None:
                isotropic = block.isotropic if isotropic is None else isotropic + block.isotropic
            rhs += block.rhs
        A = self.assembly.matrix(metric, isotropic)
        regulariser = ev.terms[-1].gradient
        assert regulariser is not None
        g = self.assembly.vector(rhs) + regulariser
        return A, g


def _times(weights: np.ndarray | None, mask: np.ndarray | None) -> np.ndarray | None:
    """``weights * mask``, either ``None`` standing for all ones."""
    if mask is None:
        return weights
    return mask if weights is None else weights * mask
