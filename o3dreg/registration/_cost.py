"""The cost of one level, eq. (3) of Berar et al. (2005), with its analytic Jacobian: the sum of
the residual terms of ``_terms`` weighted by the kernels and checkers of ``_robust``.

Unknowns ``u`` are the displacements of the level's free lattice nodes, node-major
(``[u_0x, u_0y, u_0z, u_1x, ...]``). The template points ``x`` (rigidly aligned) are fixed, so the
moved points ``y = x + prev(x) + W u`` are linear in ``u`` with the constant sparse matrix ``W`` of
trilinear weights (8 nodes per point). Residual blocks:

(a) ``d(y_i, S)`` for every template vertex: point-to-surface distance to the target (AABB tree);
    its derivative is the unit vector from the closest point (point-to-plane on the surface);
(b) ``sqrt(w_s) (y_i - b_i)`` for every template vertex that is the nearest template vertex of at
    least one target vertex, ``b_i`` the barycentre of those target vertices (re-assigned at every
    evaluation, held fixed in the Jacobian as an ICP step does);
(c) ``sqrt(lambda N / E) (D u)`` over the ``E`` finite-difference stencils of the lattice that
    touch a free node: second differences (thin-plate bending energy, free for affine motion) or
    first differences (membrane energy). Fixed nodes keep a zero increment.

Robustness enters as per-row weights, recomputed at every evaluation and held fixed in
the Jacobian (iteratively reweighted least squares inside Levenberg-Marquardt): block (a) becomes
``sqrt(w_i) d_i`` with Jacobian ``sqrt(w_i) grad_i (x) W_i``, where ``w_i`` is the robust-loss
weight of ``d_i`` (see :class:`~o3dreg.DistanceEstimation`) times 0/1 masks (closest point beyond
the target's open boundary, incompatible normals, distance beyond ``max_distance_factor``
scales). Block (b) averages the target vertices with their own robust weights ``v_j`` (of the
distance to their nearest template vertex) and scales row ``i`` by
``sqrt(w_s * mean_j v_j) * m_i`` with ``m_i`` the 0/1 support mask of template vertex ``i``: a
template vertex with no data of its own gets no barycentre row, so data near a cut cannot pull
the unsupported part of the template into the covered part.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .._geometry import det3
from ..mesh.distinct import distinct
from ._assembly import NormalAssembly
from ._robust import CorrespondenceMask, robust_scale, support
from ._terms import (
    BarycentreTerm,
    Geometry,
    PointToSurfaceTerm,
    RegulariserTerm,
    ResidualTerm,
    TermBlock,
    Weights,
)
from .checkers import CheckerContext, CorrespondenceChecker
from .distance import SurfaceDistanceQuery
from .lattice import TrilinearLattice
from .losses import L2Loss, RobustLoss

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
    cost_distance: float
    cost_symmetric: float
    cost_regularization: float
    distances: np.ndarray
    moved: np.ndarray
    weights: np.ndarray | None = None
    support: np.ndarray | None = None
    target_weights: np.ndarray | None = None
    geometry: Geometry | None = None
    terms: tuple[TermBlock, ...] = ()

    #: Whether the barycentre term's assignment is that of an earlier point (a trial step).
    held_assignment: bool = False

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

    The cost is the sum of :attr:`terms` (point-to-surface, barycentre when the symmetric
    weight is positive, regulariser), in that order in the residual vector.

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
    target_points : (k, 3) ndarray or None
        Target vertices for the symmetric term; ``None`` disables it.
    symmetric_weight, regularization : float
        The barycentre term's weight at this level; the regulariser's ``lambda``.
    energy : {'bending', 'membrane'}
        The regulariser's finite differences (see :class:`~o3dreg.ElasticLevel`).
    loss : RobustLoss, optional
        The robust loss of both distance terms (default plain least squares).
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
    barycentre_offsets : (n, 3) ndarray or None
        The barycentre correction's offsets (see :class:`~o3dreg.Barycentre`).
    barycentre_counted : bool
        Weigh each barycentre row by the target points it stands for (see
        :class:`~o3dreg.Barycentre`'s ``weighting``).
    pool : Executor or None
        One worker thread for the barycentre term's k-d tree queries, which then run while the
        point-to-surface query of the same points runs (``None``: one after the other).
    """

    def __init__(
        self,
        points: np.ndarray,
        previous: np.ndarray,
        lattice: TrilinearLattice,
        active: np.ndarray,
        target: SurfaceDistanceQuery,
        target_points: np.ndarray | None,
        symmetric_weight: float,
        regularization: float,
        energy: str = "bending",
        *,
        loss: RobustLoss | None = None,
        checkers: Sequence[CorrespondenceChecker] = (),
        target_has_boundary: bool = True,
        min_jacobian_determinant: float | None = None,
        normals: np.ndarray | None = None,
        prior: Any = None,
        barycentre_offsets: np.ndarray | None = None,
        barycentre_counted: bool = False,
        pool: Executor | None = None,
    ) -> None:
        self.lattice = lattice
        self.pool = pool
        self.loss = loss or L2Loss()
        self.min_jacobian_determinant = min_jacobian_determinant
        self.base = points + previous
        self._points = points
        self.target = target
        self.target_points = target_points if symmetric_weight > 0 else None
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
        self.surface = PointToSurfaceTerm(self.assembly, target)
        self.barycentre = (
            None
            if self.target_points is None
            else BarycentreTerm(
                self.assembly,
                self.target_points,
                symmetric_weight,
                barycentre_offsets,
                barycentre_counted,
            )
        )
        self.terms: list[ResidualTerm] = [self.surface]
        if self.barycentre is not None:
            self.terms.append(self.barycentre)
        self.terms.append(self.regulariser)
        context = CheckerContext(target, target_has_boundary, normals)
        # The masks of the checkers, in the order they are combined; those measured in robust
        # scales are bound once the scales are known.
        self.checkers: list[CorrespondenceMask] = bound_masks(
            [c for c in checkers if not c.needs_scale], context
        )
        scaled = [c for c in checkers if c.needs_scale]
        self._robust = not isinstance(self.loss, L2Loss) or bool(scaled)
        self.sigma = self.sigma_symmetric = 1.0
        # The closest points (and barycentre assignment) at the level start, shared by the scales
        # and the first evaluation.
        self._start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._start_assignment: tuple[np.ndarray, np.ndarray] | None = None
        if self._robust:
            self._estimate_scales(lattice)
        self.checkers += bound_masks(scaled, replace(context, sigma=self.sigma))
        # The scaled checkers also judge the barycentre term's target -> template distances.
        self.target_checkers = bound_masks(scaled, replace(context, sigma=self.sigma_symmetric))
        self._fold = None
        if min_jacobian_determinant is not None and self.number_of_unknowns:
            self._fold = self._fold_samples(prior, active)

    def _estimate_scales(self, lattice: TrilinearLattice) -> None:
        """The robust scales ``sigma`` of both distance terms from the data at the level start
        (``u = 0``), over the correspondences the other checkers accept (the distance checker
        itself is measured in these scales)."""
        floor = SCALE_FLOOR * float(lattice.cell_size.min())
        self._prefetch(self.base)
        self._start = dist, face, closest = self.target.closest(self.base)
        keep = support(self.checkers, self.base, dist, face, closest)
        self.sigma = self.loss.scale or robust_scale(dist[keep], floor)
        if self.barycentre is not None:
            # The first evaluation's assignment; the scale is measured to the supported points
            # only, whose nearest is the same wherever the nearest of all is supported.
            self._start_assignment = e, nearest = self.barycentre.measure(self.base)
            lost = ~keep[nearest] if keep.any() else np.zeros(e.shape, dtype=bool)
            if lost.any():
                e = e.copy()
                e[lost], _ = cKDTree(self.base[keep]).query(self.barycentre.target_points[lost])
            self.sigma_symmetric = self.loss.scale or robust_scale(e, floor)

    # -- folding ----------------------------------------------------------------------------------
    def _fold_samples(
        self, prior: Any, active: np.ndarray
    ) -> tuple[np.ndarray, list[sp.csr_matrix]]:
        """Samples (8 per cell, at local coordinates 1/4 and 3/4) of every cell holding an active
        point of the level; the Jacobian of the coarser levels there and the derivative
        operators of the increment (``d u / d x_a = D_a U``)."""
        lat = self.lattice
        f = self.free_nodes
        pts = lat.cell_samples(lat.occupied_cells(self._points[active]))
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
        """Whether the cost re-assigns target points to template points (the barycentre term):
        Levenberg-Marquardt's accepted steps are then a linearly converging fixed-point
        iteration (see ``_solvers._extrapolation``)."""
        return self.barycentre is not None

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
        weights and 0/1 masks are those of ``weights_of``, and so is the barycentre term's
        assignment of target points to template points. Levenberg-Marquardt compares a trial
        with the current point under one linearisation (one weighted least-squares problem, as
        in iteratively reweighted least squares and in ICP, whose assignments are fixed while
        the transformation is solved for): measured under its own weights, a step that brings
        more template points into support would count their distances as a cost increase and
        be rejected although it moved towards the data, and a changing assignment makes the
        quadratic model's predictions meaningless. :meth:`reweighted` then gives the accepted
        point its own weights and assignment.

        With ``reassign`` (and ``weights_of``), the barycentre term's assignment is that of ``u``
        itself while the weights and masks stay those of ``weights_of``: a point reached by
        extrapolating several steps (see ``_solvers``) is compared with the current one under
        the same weights (a jump cannot look better by pushing points into rejection), each
        with the assignment a Levenberg-Marquardt step from it would start from.
        """
        y = self.moved(u)
        at_start = not u.any()
        found = self._start if at_start else None
        if not (at_start and self._start_assignment is not None):
            # Needed now, or by :meth:`reweighted` if a trial step is accepted.
            self._prefetch(y)
        dist, closest, grad, face = self.surface.measure(y, found)
        if weights_of is None:
            e = nearest = None
            if self.barycentre is not None:
                if at_start and self._start_assignment is not None:
                    e, nearest = self._start_assignment
                else:
                    e, nearest = self.barycentre.measure(y)
            geometry = Geometry(u, y, dist, closest, grad, face, e, nearest)
            return self._assemble(geometry, self._weights(geometry))
        assert weights_of.geometry is not None
        held = weights_of.geometry
        e, nearest = held.target_distances, held.nearest
        if reassign and self.barycentre is not None:
            e, nearest = self.barycentre.measure(y)
        geometry = Geometry(u, y, dist, closest, grad, face, e, nearest)
        weights = Weights(weights_of.weights, weights_of.support, weights_of.target_weights)
        targets = None
        if self.barycentre is not None and not reassign:
            targets = weights_of.terms[1].targets
        return self._assemble(geometry, weights, targets)

    def _prefetch(self, y: np.ndarray) -> None:
        """Start the barycentre term's assignment at ``y`` on the worker thread, if any."""
        if self.barycentre is not None and self.pool is not None:
            self.barycentre.prefetch(y, self.pool)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        """``ev`` with the weights, masks and barycentre assignment of its own point (no new
        point-to-surface query)."""
        g = ev.geometry
        assert g is not None
        if ev.held_assignment and self.barycentre is not None:
            e, nearest = self.barycentre.measure(g.moved)
            g = Geometry(g.u, g.moved, g.distances, g.closest, g.gradients, g.faces, e, nearest)
        return self._assemble(g, self._weights(g))

    def _weights(self, g: Geometry) -> Weights:
        """Per-point weights (robust kernel times the checkers' support), support masks and
        per-target-point weights of the barycentre term at the geometry ``g``."""
        if not (self.checkers or self._robust):
            return Weights()
        mask = support(self.checkers, g.moved, g.distances, g.faces, g.closest)
        w = self.loss.weight(g.distances, self.sigma) * mask
        v = None
        if self._robust and g.target_distances is not None:
            e = g.target_distances
            v = self.loss.weight(e, self.sigma_symmetric)
            for checker in self.target_checkers:
                v = v * checker.check(g.moved, e, g.faces, g.closest)
        return Weights(w, mask, v)

    def _assemble(
        self,
        g: Geometry,
        w: Weights,
        targets: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Evaluation:
        surface = self.surface.linearise(g, w)
        regulariser = self.regulariser.linearise(g, w)
        blocks: tuple[TermBlock, ...] = (surface, regulariser)
        cost_sym = 0.0
        barycentre = None
        if self.barycentre is not None:
            barycentre = self.barycentre.linearise(g, w, targets)
            blocks = (surface, barycentre, regulariser)
            cost_sym = barycentre.cost
        cost_d = surface.cost
        cost_r = regulariser.cost
        return Evaluation(
            u=g.u,
            cost=cost_d + cost_sym + cost_r,
            cost_distance=cost_d,
            cost_symmetric=cost_sym,
            cost_regularization=cost_r,
            distances=g.distances,
            moved=g.moved,
            weights=w.point,
            support=w.support,
            target_weights=w.target,
            geometry=g,
            terms=blocks,
            held_assignment=targets is not None,
        )

    def normal_equations(self, ev: Evaluation) -> tuple[sp.bsr_matrix, np.ndarray]:
        """``J^T J`` and ``J^T r``, the sum of the terms' shares, assembled on the level's fixed
        pattern (``_assembly``): the data terms' per-point metrics and right-hand sides are
        summed first, then scattered once."""
        n = ev.moved.shape[0]
        metric = np.zeros((n, 6))
        isotropic = None
        rhs = np.zeros((n, 3))
        for block in ev.terms[:-1]:  # the data terms
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


def bound_masks(
    checkers: Sequence[CorrespondenceChecker], context: CheckerContext
) -> list[CorrespondenceMask]:
    """The masks of ``checkers`` at a level (those that reject something there)."""
    masks = (checker.bind(context) for checker in checkers)
    return [mask for mask in masks if mask is not None]
