"""The cost of one level, eq. (3) of Berar et al. (2005), with its analytic Jacobian.

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

Robustness (issue 6) enters as per-row weights, recomputed at every evaluation and held fixed in
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

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .distance import SurfaceDistanceQuery
from .lattice import TrilinearLattice

#: Tuning constants of the robust losses (95% efficiency under Gaussian noise), in units of the
#: robust scale ``sigma``.
LOSS_CONSTANTS = {"linear": np.inf, "huber": 1.345, "cauchy": 2.3849, "tukey": 4.6851}


#: Smallest robust scale ``sigma``, as a fraction of the level's cell size. A level that starts
#: nearly converged (the finest ones on a clean target) has a tiny median residual; a scale
#: taken from it alone would discount the tail of genuine misfit the level is there to remove.
#: Measured on the bunny (3k -> 36k, rigid step; benchmarks/bench_robust.py and
#: bench_registration.py): with 0.01 the clean error was 19% above plain least squares at a 5%
#: warp (0.261 against 0.220 mm), with 0.03 12-18% at a 10% warp; 0.05 leaves 0.5% and 10%, and
#: still keeps a 40% cut within 1.42x (0.1: 3.5x) and 5% debris without the island filter within
#: 1.12x.
SCALE_FLOOR = 0.05


def robust_weights(r: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights ``w(r) = rho'(r) / r`` of the residuals ``r`` for the threshold ``c``.

    ``huber``: ``1`` if ``|r| <= c`` else ``c / |r|``; ``cauchy``: ``1 / (1 + (r / c)^2)``;
    ``tukey``: ``(1 - (r / c)^2)^2`` if ``|r| < c`` else ``0``; ``linear``: ``1``.
    """
    if loss == "linear" or r.size == 0:
        return np.ones(r.shape)
    z = np.abs(r) / c
    if loss == "huber":
        return 1.0 / np.maximum(z, 1.0)
    if loss == "cauchy":
        return 1.0 / (1.0 + z * z)
    return np.where(z < 1.0, (1.0 - z * z) ** 2, 0.0)


def robust_scale(r: np.ndarray, floor: float) -> float:
    """``max(1.4826 * median(|r|), floor)``: the MAD scale of residuals whose centre is zero."""
    if r.size == 0:
        return floor
    return max(1.4826 * float(np.median(np.abs(r))), floor)


@dataclass(frozen=True)
class Robustness:
    """Per-level robustness settings of :class:`LevelProblem` (see DistanceEstimation)."""

    loss: str = "linear"
    loss_scale: float | None = None
    max_distance_factor: float | None = None
    reject_boundary: bool = True
    max_normal_angle: float | None = None
    min_jacobian_determinant: float | None = None


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


@dataclass
class _Geometry:
    """What one evaluation measured at ``u``, before any weighting."""

    u: np.ndarray
    moved: np.ndarray
    distances: np.ndarray
    closest: np.ndarray
    gradients: np.ndarray
    faces: np.ndarray
    target_distances: np.ndarray | None
    nearest: np.ndarray | None


@dataclass
class Evaluation:
    """Residuals, Jacobian blocks and cost terms at one ``u``."""

    u: np.ndarray
    residuals: np.ndarray
    blocks: list[sp.csr_matrix]
    cost: float
    cost_distance: float
    cost_symmetric: float
    cost_regularization: float
    distances: np.ndarray
    moved: np.ndarray
    symmetric_scale: np.ndarray | None = None
    weights: np.ndarray | None = None
    support: np.ndarray | None = None
    target_weights: np.ndarray | None = None
    geometry: _Geometry | None = None

    @property
    def jacobian(self) -> sp.csr_matrix:
        """The full sparse Jacobian (the residual blocks stacked)."""
        return sp.vstack(self.blocks, format="csr")


class LevelProblem:
    """Residuals and Jacobian of one lattice level for a fixed set of template points.

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
        robustness: Robustness | None = None,
        normals: np.ndarray | None = None,
        prior: Any = None,
        barycentre_offsets: np.ndarray | None = None,
    ) -> None:
        self.lattice = lattice
        self.barycentre_offsets = barycentre_offsets
        self.robust = robustness or Robustness()
        self.base = points + previous
        self._points = points
        self.target = target
        self.target_points = target_points if symmetric_weight > 0 else None
        self.sqrt_ws = float(np.sqrt(symmetric_weight))
        n = points.shape[0]
        nodes, weights = lattice.weights(points)
        free_nodes = np.unique(nodes[active].ravel())
        lookup = np.full(lattice.number_of_nodes, -1, dtype=np.int64)
        lookup[free_nodes] = np.arange(free_nodes.size)
        self.free_nodes = free_nodes
        local = lookup[nodes]
        keep = local >= 0
        rows = np.broadcast_to(np.arange(n)[:, None], local.shape)[keep]
        # W restricted to free nodes, (n, m).
        self.W = sp.csr_matrix((weights[keep], (rows, local[keep])), shape=(n, free_nodes.size))
        self.number_of_unknowns = 3 * free_nodes.size
        self._G = self._stencil_matrix(lookup, energy)
        edges = max(self._G.shape[0], 1)
        self.sqrt_reg = float(np.sqrt(regularization * n / edges))
        self._Jreg = sp.kron(self._G, sp.identity(3), format="csr") * self.sqrt_reg
        self._Wx = sp.kron(self.W, sp.identity(3), format="csr")  # (3n, 3m) for vector residuals
        self._reg_gram = (self._Jreg.T @ self._Jreg).tocsr()
        self.normals = normals
        rb = self.robust
        self._reject_boundary = rb.reject_boundary and target.has_boundary
        self._cos_max = (
            None
            if rb.max_normal_angle is None or normals is None
            else float(np.cos(np.radians(rb.max_normal_angle)))
        )
        self._c = LOSS_CONSTANTS[rb.loss]
        self._robust = rb.loss != "linear" or rb.max_distance_factor is not None
        self.sigma = self.sigma_symmetric = 1.0
        if self._robust:
            # Scales from the data at the level start (u = 0), over the correspondences the
            # other masks accept (the distance mask itself is measured in these scales).
            floor = SCALE_FLOOR * float(lattice.cell_size.min())
            dist, face, closest = target.closest(self.base)
            keep = self._masks(self.base, dist, face, closest, distance=False)
            self.sigma = rb.loss_scale or robust_scale(dist[keep], floor)
            if self.target_points is not None:
                e, _ = cKDTree(self.base[keep] if keep.any() else self.base).query(
                    self.target_points, workers=-1
                )
                self.sigma_symmetric = rb.loss_scale or robust_scale(e, floor)
        self._fold = None
        if rb.min_jacobian_determinant is not None and self.number_of_unknowns:
            self._fold = self._fold_samples(prior, active)

    def _masks(
        self,
        y: np.ndarray,
        dist: np.ndarray,
        face: np.ndarray,
        closest: np.ndarray,
        distance: bool = True,
    ) -> np.ndarray:
        """0/1 support of each point: not beyond the open boundary, compatible normal, and
        (with ``distance``) within ``max_distance_factor`` robust scales."""
        keep = np.ones(y.shape[0], dtype=bool)
        if self._reject_boundary:
            keep &= ~self.target.beyond_boundary(y, face, closest)
        if self._cos_max is not None and self.normals is not None:
            cos = (self.normals * self.target.face_normals[face]).sum(axis=1)
            keep &= cos >= self._cos_max
        if distance and self.robust.max_distance_factor is not None:
            keep &= dist <= self.robust.max_distance_factor * self.sigma
        return keep

    # -- folding ----------------------------------------------------------------------------------
    def _fold_samples(
        self, prior: Any, active: np.ndarray
    ) -> tuple[np.ndarray, list[sp.csr_matrix]]:
        """Samples (8 per cell, at local coordinates 1/4 and 3/4) of every cell holding an active
        point of the level; the Jacobian of the coarser levels there and the derivative
        operators of the increment (``d u / d x_a = D_a U``)."""
        lat = self.lattice
        f = self.free_nodes
        cells, _, _ = lat.locate(self._points[active])
        flat = np.unique(lat.node_index(cells))
        nz1, ny1 = lat.node_shape[2], lat.node_shape[1]
        cells = np.stack([flat // (ny1 * nz1), (flat // nz1) % ny1, flat % nz1], axis=1)
        pts = lat.cell_samples(cells)
        base = np.broadcast_to(np.eye(3), (pts.shape[0], 3, 3)).copy()
        if prior is not None:
            base = prior.jacobian(pts)
        lookup = np.full(lat.number_of_nodes, -1, dtype=np.int64)
        lookup[f] = np.arange(f.size)
        nodes, _, grads = lat.basis(pts)
        local_nodes = lookup[nodes]
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
        return float(np.linalg.det(jac).min()) if jac.shape[0] else 1.0

    def _stencil_matrix(self, lookup: np.ndarray, energy: str) -> sp.csr_matrix:
        """Finite-difference operator over the lattice, one row per stencil touching a free node.

        ``'membrane'``: first differences along x, y, z (``int |grad u|^2``).
        ``'bending'``: second differences along each axis and mixed differences weighted
        ``sqrt(2)`` (the thin-plate energy ``int |Hess u|^2``), whose null space is the affine
        maps: a level may add any affine motion without cost.
        """
        lat = self.lattice
        node_shape = np.asarray(lat.node_shape)
        stencils = _STENCILS[energy]
        all_ijk = np.stack(
            np.meshgrid(*[np.arange(s) for s in lat.node_shape], indexing="ij"), axis=-1
        ).reshape(-1, 3)
        rows, cols, vals = [], [], []
        count = 0
        for offsets, coefs in stencils:
            span = offsets.max(axis=0)
            anchors = all_ijk[np.all(all_ijk + span < node_shape, axis=1)]
            local = lookup[lat.node_index(anchors[:, None, :] + offsets[None, :, :])]
            keep = np.any(local >= 0, axis=1)
            local = local[keep]
            e = count + np.arange(local.shape[0])
            for j, c in enumerate(coefs):
                free = local[:, j] >= 0
                rows.append(e[free])
                cols.append(local[free, j])
                vals.append(np.full(int(free.sum()), c))
            count += local.shape[0]
        return sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(count, self.free_nodes.size),
        )

    def moved(self, u: np.ndarray) -> np.ndarray:
        """Template points moved by the coarser levels and the increment ``u``."""
        return self.base + self.W @ u.reshape(-1, 3)

    def scatter(self, u: np.ndarray) -> TrilinearLattice:
        """The level's lattice with the free nodes displaced by ``u``."""
        d = np.zeros((self.lattice.number_of_nodes, 3))
        d[self.free_nodes] = u.reshape(-1, 3)
        return self.lattice.with_displacements(d)

    def evaluate(self, u: np.ndarray, weights_of: Evaluation | None = None) -> Evaluation:
        """Residuals and Jacobian blocks at ``u``.

        The robust weights and 0/1 masks are those of ``u`` itself, or, with ``weights_of``,
        those of that earlier evaluation: Levenberg-Marquardt compares a trial step with the
        current point under the current weights (one weighted least-squares problem per
        linearisation, as in iteratively reweighted least squares). Measured under their own
        weights, a step that brings more template points into support would count their
        distances as a cost increase and be rejected, although it moved towards the data.
        """
        y = self.moved(u)
        dist, closest, grad, face = self.target.gradient(y, return_faces=True)
        e = nearest = None
        if self.target_points is not None:
            e, nearest = self._assign(y)
        geometry = _Geometry(u, y, dist, closest, grad, face, e, nearest)
        if weights_of is None:
            weights = self._weights(geometry)
        else:
            weights = (weights_of.weights, weights_of.support, weights_of.target_weights)
        return self._assemble(geometry, *weights)

    def reweighted(self, ev: Evaluation) -> Evaluation:
        """``ev`` with the weights and masks of its own point (no new distance query)."""
        assert ev.geometry is not None
        return self._assemble(ev.geometry, *self._weights(ev.geometry))

    def _weights(
        self, g: _Geometry
    ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """Per-point weights (robust weight times support), support masks and per-target-point
        weights of the barycentre term at the geometry ``g``; ``None`` where unweighted."""
        if not (self._reject_boundary or self._cos_max is not None or self._robust):
            return None, None, None
        support = self._masks(g.moved, g.distances, g.faces, g.closest)
        w = robust_weights(g.distances, self.robust.loss, self._c * self.sigma) * support
        v = None
        if self._robust and g.target_distances is not None:
            e = g.target_distances
            v = robust_weights(e, self.robust.loss, self._c * self.sigma_symmetric)
            if self.robust.max_distance_factor is not None:
                v = v * (e <= self.robust.max_distance_factor * self.sigma_symmetric)
        return w, support, v

    def _assemble(
        self,
        g: _Geometry,
        weights: np.ndarray | None,
        support: np.ndarray | None,
        target_weights: np.ndarray | None,
    ) -> Evaluation:
        y, dist, grad = g.moved, g.distances, g.gradients
        n = y.shape[0]
        ra = dist
        if weights is not None:
            sw = np.sqrt(weights)
            ra = sw * dist
            grad = grad * sw[:, None]
        # (a) point-to-surface distances: row i has grad_i (x) W_i.
        Ja = sp.csr_matrix(
            (
                (
                    self.W.data[:, None] * grad[np.repeat(np.arange(n), np.diff(self.W.indptr))]
                ).ravel(),
                (3 * self.W.indices[:, None] + np.arange(3)).ravel(),
                self.W.indptr * 3,
            ),
            shape=(n, self.number_of_unknowns),
        )
        blocks = [Ja]
        residuals = [ra]
        cost_sym = 0.0
        scale = None
        if self.target_points is not None:
            # (b) barycentre of the target vertices whose nearest template vertex is i.
            assert g.nearest is not None
            nearest = g.nearest
            counts = np.bincount(nearest, minlength=n)
            if target_weights is not None:
                v = target_weights
                vsum = np.bincount(nearest, v, minlength=n)
                sums = np.stack(
                    [
                        np.bincount(nearest, v * self.target_points[:, c], minlength=n)
                        for c in range(3)
                    ],
                    axis=1,
                )
                bary = sums / np.where(vsum > 0, vsum, 1.0)[:, None]
                assigned = vsum / np.maximum(counts, 1)
            else:
                sums = np.stack(
                    [np.bincount(nearest, self.target_points[:, c], minlength=n) for c in range(3)],
                    axis=1,
                )
                bary = sums / np.maximum(counts, 1)[:, None]
                assigned = (counts > 0).astype(np.float64)
            if support is not None:
                # A template vertex without data of its own is not pulled by the barycentres.
                assigned = assigned * support
            # Every template vertex has a row (zero when nothing is assigned to it), so the
            # residual vector keeps its length from one evaluation to the next.
            scale = self.sqrt_ws * np.sqrt(assigned)
            if self.barycentre_offsets is not None:
                # Compare like with like: the template's own sampling puts the centroid of its
                # Voronoi cell at y_i + offset_i, not at y_i (see elastic._barycentre_offsets).
                bary = bary - self.barycentre_offsets
            rb = (scale[:, None] * (y - bary)).ravel()
            blocks.append(sp.diags(np.repeat(scale, 3), format="csr") @ self._Wx)
            residuals.append(rb)
            cost_sym = float(rb @ rb)
        rc = self._Jreg @ g.u
        blocks.append(self._Jreg)
        residuals.append(rc)
        r = np.concatenate(residuals)
        cost_d = float(ra @ ra)
        cost_r = float(rc @ rc)
        return Evaluation(
            u=g.u,
            residuals=r,
            blocks=blocks,
            cost=cost_d + cost_sym + cost_r,
            cost_distance=cost_d,
            cost_symmetric=cost_sym,
            cost_regularization=cost_r,
            distances=dist,
            moved=y,
            symmetric_scale=scale,
            weights=weights,
            support=support,
            target_weights=target_weights,
            geometry=g,
        )

    def _assign(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest moved template vertex of every target point (exact), and its distance.

        The points move little between evaluations, so the query is bounded by a radius that
        held for nearly all of them last time (a bounded k-d tree search prunes more: measured
        40% faster); the few points without a neighbour inside it are searched again unbounded.
        """
        assert self.target_points is not None
        tree = cKDTree(y, leafsize=32)
        bound = getattr(self, "_nn_bound", np.inf)
        e, nearest = tree.query(self.target_points, workers=-1, distance_upper_bound=bound)
        missed = ~np.isfinite(e)
        if missed.any():
            e[missed], nearest[missed] = tree.query(self.target_points[missed], workers=-1)
        self._nn_bound = 2.0 * float(np.percentile(e, 99)) if e.size else np.inf
        return e, nearest

    def normal_equations(self, ev: Evaluation) -> tuple[sp.csr_matrix, np.ndarray]:
        """``J^T J`` and ``J^T r`` assembled block by block.

        The regularisation block is constant within a level (cached); the barycentre block is
        ``(W^T S^2 W) (x) I_3`` with ``S`` the per-vertex weights, computed on the small
        ``(m, m)`` node matrix rather than on the ``3n x 3m`` Jacobian.
        """
        n = ev.distances.size
        Ja = ev.blocks[0]
        ra = ev.residuals[:n]
        A = Ja.T @ Ja + self._reg_gram
        g = Ja.T @ ra
        if ev.symmetric_scale is not None:
            s2 = ev.symmetric_scale**2
            A = A + sp.kron(self.W.T @ sp.diags(s2) @ self.W, sp.identity(3), format="csr")
            rb = ev.residuals[n : 4 * n]
            g = g + self._Wx.T @ (np.repeat(ev.symmetric_scale, 3) * rb)
        rc = ev.residuals[ev.residuals.size - self._Jreg.shape[0] :]
        g = g + self._Jreg.T @ rc
        return A.tocsr(), g
