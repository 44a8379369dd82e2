"""Solvers for one level, behind one interface (:class:`LevelSolver`): ``solve(problem, criteria)``.

* ``'lm'``: Levenberg-Marquardt on the sparse normal equations ``(J^T J + mu D) delta = -J^T r``
  with Marquardt's diagonal scaling ``D = diag(J^T J)`` and Nielsen's damping update. The system
  is symmetric positive definite and sparse (27-node stencil); it is solved by SciPy's conjugate
  gradients, preconditioned by each node's 3x3 diagonal block (SuperLU as a fallback), the coarsest level's by a dense Cholesky
  factorisation (:class:`DampedSystem`).
* ``'trf'``: :func:`scipy.optimize.least_squares` ``method='trf'`` with the sparse Jacobian.
* ``'lm-dense'``: :func:`scipy.optimize.least_squares` ``method='lm'`` (MINPACK, dense Jacobian).

Non-convergence is reported (``success=False`` and a message), never raised.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import least_squares

from ._cost import Evaluation, LevelProblem
from .options import ElasticCriteria


@dataclass
class SolveInfo:
    evaluation: Evaluation
    initial_cost: float
    iterations: int
    evaluations: int
    success: bool
    message: str


def solve(problem: LevelProblem, criteria: ElasticCriteria, method: str = "lm") -> SolveInfo:
    """Minimise the level cost from ``u = 0``."""
    if problem.number_of_unknowns == 0:
        ev = problem.evaluate(np.zeros(0))
        return SolveInfo(ev, ev.cost, 0, 1, True, "no free node at this level")
    return solver_named(method).solve(problem, criteria)


#: Largest system solved by a dense Cholesky factorisation (the coarsest level: 81 unknowns at 2
#: cells per axis). Larger ones go to conjugate gradients: a dense factorisation of a few hundred
#: unknowns is cheap on an idle machine, but multithreaded BLAS on a loaded one is far slower
#: than conjugate gradients.
DENSE_UNKNOWNS = 100

#: Conjugate gradients stop at ``|r| <= CG_RTOL |b|``, after at most ``CG_MAXITER`` iterations.
#: A Levenberg-Marquardt step needs no more: the next linearisation corrects it, so a tighter
#: tolerance costs CG iterations without changing the steps that are accepted.
CG_RTOL = 1e-4
CG_MAXITER = 1000


class DampedSystem:
    """``(A + diag(d)) x = b`` for one symmetric positive (semi)definite ``A`` and several
    dampings ``d`` (the retries of one Levenberg-Marquardt iteration).

    Tiny systems are factorised densely (Cholesky; ``A`` is made dense once). Others are solved
    by :func:`scipy.sparse.linalg.cg`, preconditioned by the inverse of each node's 3x3 diagonal
    block of ``A + diag(d)``: the damping ``mu diag(A)`` keeps the system well conditioned, so
    CG needs a few dozen products, far cheaper than a sparse LU, which is the fallback if CG
    does not converge. The block preconditioner takes each node's point-to-plane coupling of
    x, y, z whole (a plain Jacobi preconditioner sees only its diagonal).
    """

    def __init__(self, A: sp.spmatrix) -> None:
        self.size = A.shape[0]
        self.dense = A.toarray() if self.size <= DENSE_UNKNOWNS else None
        self.A: sp.bsr_matrix | None = None
        if self.dense is None:
            if self.size % 3:
                raise ValueError(f"the normal equations hold 3 unknowns per node, got {self.size}")
            # Every diagonal block stored (the assembly's matrices have them all; explicit
            # zeros are added otherwise): the damping is written into the blocks in place.
            nodes = self.size // 3
            bsr = A if sp.issparse(A) and A.format == "bsr" else sp.bsr_matrix(A)
            if bsr.blocksize != (3, 3):
                bsr = sp.bsr_matrix(A, blocksize=(3, 3))
            bsr.sort_indices()
            diagonal = self._diagonal_blocks(bsr)
            if diagonal.size != nodes:
                coo = bsr.tocoo()
                every = np.arange(self.size)
                csr = sp.csr_matrix(
                    (
                        np.concatenate([coo.data, np.zeros(self.size)]),
                        (np.concatenate([coo.row, every]), np.concatenate([coo.col, every])),
                    ),
                    shape=A.shape,
                )
                bsr = csr.tobsr(blocksize=(3, 3))
                bsr.sort_indices()
                diagonal = self._diagonal_blocks(bsr)
            self.A = bsr
            self._diagonal = diagonal

    @staticmethod
    def _diagonal_blocks(bsr: sp.bsr_matrix) -> np.ndarray:
        """Positions of the diagonal blocks among ``bsr``'s stored blocks."""
        rows = np.repeat(np.arange(bsr.shape[0] // 3), np.diff(bsr.indptr))
        return np.flatnonzero(bsr.indices == rows)

    def solve_damped(self, damping: np.ndarray, b: np.ndarray) -> np.ndarray:
        if self.dense is not None:
            M = self.dense.copy()
            M[np.diag_indices_from(M)] += damping
            try:
                factor = scipy.linalg.cho_factor(M, check_finite=False)
                return np.asarray(scipy.linalg.cho_solve(factor, b, check_finite=False))
            except (np.linalg.LinAlgError, ValueError):
                return np.asarray(scipy.linalg.solve(M, b, assume_a="sym"))
        assert self.A is not None
        d = np.asarray(damping, dtype=np.float64)
        if d.shape != (self.size,) or np.shape(b) != (self.size,):
            raise ValueError(
                f"expected a damping and a right-hand side of {self.size} values, got "
                f"{d.shape} and {np.shape(b)}"
            )
        blocks = self.A.data.copy()
        diagonal = blocks[self._diagonal]  # (nodes, 3, 3)
        diagonal[:, [0, 1, 2], [0, 1, 2]] += d.reshape(-1, 3)
        blocks[self._diagonal] = diagonal
        M = sp.bsr_matrix((blocks, self.A.indices, self.A.indptr), shape=self.A.shape)
        nodes = self.size // 3
        try:
            inverse = np.linalg.inv(diagonal)
        except np.linalg.LinAlgError:
            inverse = None
        x, info = (None, -1)
        if inverse is not None:
            preconditioner = sp.bsr_matrix(
                (inverse, np.arange(nodes), np.arange(nodes + 1)), shape=self.A.shape
            )
            x, info = spla.cg(M, b, rtol=CG_RTOL, atol=0.0, M=preconditioner, maxiter=CG_MAXITER)
        if info != 0:
            x = spla.spsolve(M.tocsc(), b)
        return np.asarray(x)


#: Damping beyond which no step is tried: the step is then ~1e-12 of a gradient step.
_MU_MAX = 1e12

#: Extrapolation of linearly converging steps (see :func:`_extrapolation`): the smallest cosine
#: between two successive accepted steps, and the range of their length ratio, for which the
#: sum of the geometric series they start is tried.
EXTRAPOLATION_MIN_COSINE = 0.9
EXTRAPOLATION_RATIO = (0.3, 0.95)

#: Jumps refused (no lower cost) after which a level offers no more.
MAX_REFUSED_JUMPS = 3


def _cell(problem: LevelProblem) -> float:
    return float(problem.lattice.cell_size.min())


def _folds_further(new: float, current: float, threshold: float | None) -> bool:
    """The folding guard's rule: a point whose smallest ``det(dT/dx)`` is below the threshold
    and below the current point's is refused."""
    return threshold is not None and new < threshold and new < current


def _extrapolation(step: np.ndarray, previous: np.ndarray | None) -> np.ndarray | None:
    """Where the steps ``previous, step`` lead if they go on as a geometric series, or ``None``.

    Where the barycentre term works (the coarse levels of the symmetric distance), each
    accepted step re-assigns target points to template points and the next one moves the
    template points towards the new barycentres: a fixed-point iteration (Lloyd's), which
    converges linearly. Its successive steps are then nearly parallel and shrink by a steady
    factor ``r``, so the rest of the series, ``step * r / (1 - r)``, is a good guess of the remaining way (the
    one-vector form of Aitken's / Anderson's acceleration). Only offered when the two steps
    are within :data:`EXTRAPOLATION_MIN_COSINE` of parallel and ``r`` within
    :data:`EXTRAPOLATION_RATIO` (a ratio near 1 would jump far on a guess); the solver keeps the
    jump only if it lowers the cost.
    """
    if previous is None:
        return None
    norm, norm_previous = float(np.linalg.norm(step)), float(np.linalg.norm(previous))
    if norm == 0.0 or norm_previous == 0.0:
        return None
    cosine = float(step @ previous) / (norm * norm_previous)
    ratio = norm / norm_previous
    low, high = EXTRAPOLATION_RATIO
    if cosine < EXTRAPOLATION_MIN_COSINE or not low < ratio < high:
        return None
    return step * (ratio / (1.0 - ratio))


class LevelSolver(Protocol):
    """What minimises one level's cost from ``u = 0``: the solvers are interchangeable."""

    def solve(self, problem: LevelProblem, criteria: ElasticCriteria) -> SolveInfo: ...


class LevenbergMarquardt:
    """``'lm'``: Levenberg-Marquardt on the sparse normal equations (see the module docstring),
    with the folding guard and the extrapolation of linearly converging steps."""

    def solve(self, problem: LevelProblem, criteria: ElasticCriteria) -> SolveInfo:
        return _LevenbergMarquardtRun(problem, criteria).run()


@dataclass(frozen=True)
class ScipyLeastSquares:
    """``'trf'`` and ``'lm-dense'``: :func:`scipy.optimize.least_squares` on the same residuals
    and Jacobian (no folding guard)."""

    method: str = "trf"

    def solve(self, problem: LevelProblem, criteria: ElasticCriteria) -> SolveInfo:
        return _scipy(problem, criteria, self.method)


def solver_named(method: str) -> LevelSolver:
    """The solver of :attr:`~o3dreg.ElasticLevel.solver` ``method``."""
    return LevenbergMarquardt() if method == "lm" else ScipyLeastSquares(method)


class _LevenbergMarquardtRun:
    """The state of one Levenberg-Marquardt minimisation: the point ``u`` with its evaluation,
    the damping ``mu`` (and its growth ``nu``), the folding guard's determinant and the counts
    the report gives."""

    def __init__(self, problem: LevelProblem, criteria: ElasticCriteria) -> None:
        self.problem, self.criteria = problem, criteria
        self.u = np.zeros(problem.number_of_unknowns)
        self.ev = problem.evaluate(self.u)
        self.initial = self.ev.cost
        self.evaluations = 1
        self.iterations = 0
        self.mu, self.nu = 1e-3, 2.0
        self.cell = _cell(problem)
        self.threshold = problem.min_jacobian_determinant
        self.guard = self.threshold is not None and problem.guards_folding
        self.det = problem.min_determinant(self.u) if self.guard else 1.0
        self.folds_rejected = 0
        self.previous_step: np.ndarray | None = None
        self.extrapolate = problem.reassigns
        self.refused = 0
        self.message = f"reached max_iteration={criteria.max_iteration}"
        self.success = False

    def run(self) -> SolveInfo:
        while self.iterations < self.criteria.max_iteration:
            A, g = self.problem.normal_equations(self.ev)
            diag = A.diagonal()
            if not (np.all(np.isfinite(g)) and np.all(np.isfinite(diag))):
                self._stop("non-finite gradient or normal equations: stopped", False)
                break
            diag = np.maximum(diag, 1e-12 * max(float(diag.max()), 1e-300))
            found = self._damped_step(A, g, diag)
            if found is None or self._accept(*found):
                break
        if self.folds_rejected:
            self.message += f" ({self.folds_rejected} folding step(s) rejected)"
        return SolveInfo(
            self.ev, self.initial, self.iterations, self.evaluations, self.success, self.message
        )

    def _stop(self, message: str, success: bool) -> None:
        self.message, self.success = message, success

    def _damped_step(
        self, A: sp.spmatrix, g: np.ndarray, diag: np.ndarray
    ) -> tuple[Evaluation, np.ndarray, float] | None:
        """The first damped step that lowers the cost (the damping grows after each refusal):
        its evaluation, the step and the determinant there; ``None`` (the stopping message set)
        when none does."""
        problem, criteria, ev = self.problem, self.criteria, self.ev
        non_finite = folded = 0
        system = DampedSystem(A)
        while True:
            delta = system.solve_damped(self.mu * diag, -g)
            if not np.all(np.isfinite(delta)):
                # A stronger damping makes the system better conditioned; past mu_max the
                # problem itself is broken: stop and say so (never loop, never raise).
                non_finite += 1
                if self._damp_more():
                    break
                continue
            predicted = -(g @ delta) - 0.5 * delta @ (A @ delta)
            if 2.0 * predicted < criteria.relative_cost * ev.cost:
                # Even the model promises less than the tolerance: stop without evaluating.
                break
            # The trial is measured under the current weights and masks (see
            # LevelProblem.evaluate): the same weighted least-squares cost as ``ev``.
            trial = problem.evaluate(self.u + delta, weights_of=ev)
            self.evaluations += 1
            actual = 0.5 * (ev.cost - trial.cost)
            rho = actual / predicted if predicted > 0 and np.isfinite(trial.cost) else -1.0
            if not np.isfinite(trial.cost):
                non_finite += 1
            trial_det = self.det
            if self.guard and rho > 0:
                # Folding guard: a step that brings det(dT/dx) below the threshold (and below
                # its current value) is rejected like a step that increases the cost.
                trial_det = problem.min_determinant(self.u + delta)
                if _folds_further(trial_det, self.det, self.threshold):
                    rho = -1.0
                    folded += 1
                    self.folds_rejected += 1
            if rho > 0:
                self.mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                self.nu = 2.0
                return trial, delta, trial_det
            if self._damp_more():
                break
        if non_finite:
            self._stop(f"non-finite step or cost ({non_finite} tries): stopped", False)
        elif folded:
            # Steps that lowered the cost were there; the guard refused them, and the damping
            # they raised left none that does not fold further.
            self._stop(
                "the folding guard refused every step that lowered the cost (each would bring "
                "det(dT/dx) below min_jacobian_determinant)",
                True,
            )
        elif self.mu > _MU_MAX:
            self._stop("no step decreases the cost (mu > 1e12)", True)
        else:
            self._stop("predicted relative decrease < relative_cost", True)
        return None

    def _damp_more(self) -> bool:
        """Grow the damping (Nielsen); whether it passed ``mu_max``."""
        self.mu *= self.nu
        self.nu *= 2.0
        return self.mu > _MU_MAX

    def _accept(self, trial: Evaluation, delta: np.ndarray, trial_det: float) -> bool:
        """Move to the accepted trial (and maybe jump further); whether the level has converged."""
        self.iterations += 1
        decrease = (self.ev.cost - trial.cost) / max(self.ev.cost, 1e-300)
        step = float(np.sqrt((delta.reshape(-1, 3) ** 2).sum(axis=1)).max()) / self.cell
        self.u = self.u + delta
        # Iteratively reweighted: the accepted point gets its own weights and masks.
        self.ev = self.problem.reweighted(trial)
        self.det = trial_det
        if decrease < self.criteria.relative_cost:
            self._stop(f"relative cost decrease {decrease:.2e} < relative_cost", True)
            return True
        if step < self.criteria.relative_step:
            self._stop(f"relative step {step:.2e} < relative_step", True)
            return True
        jump = _extrapolation(delta, self.previous_step) if self.extrapolate else None
        self.previous_step = delta
        if jump is not None:
            self._try_jump(jump)
        return False

    def _try_jump(self, jump: np.ndarray) -> None:
        """Jump along the series of the last steps when that lowers the cost.

        The jump is measured with its own barycentre assignment under the current weights and
        masks, against the current point's cost under the same (``ev``): kept only if lower,
        and (with the folding guard) only if it does not bring det(dT/dx) below the threshold.
        """
        problem = self.problem
        far = problem.evaluate(self.u + jump, weights_of=self.ev, reassign=True)
        self.evaluations += 1
        far_det = problem.min_determinant(self.u + jump) if self.guard else self.det
        unfolded = not self.guard or not _folds_further(far_det, self.det, self.threshold)
        if np.isfinite(far.cost) and far.cost < self.ev.cost and unfolded:
            self.u = self.u + jump
            self.ev = problem.reweighted(far)
            self.det = far_det
            self.previous_step = None  # the series restarts from the new point
        else:
            # The steps only looked like one series; where that keeps happening each refusal is
            # an evaluation lost: after MAX_REFUSED_JUMPS, no more on this level.
            self.refused += 1
            self.extrapolate = self.refused < MAX_REFUSED_JUMPS


def _scipy(problem: LevelProblem, criteria: ElasticCriteria, method: str) -> SolveInfo:
    cache: dict[bytes, Evaluation] = {}

    def evaluate(u: np.ndarray) -> Evaluation:
        key = u.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = problem.evaluate(u.copy())
        return cache[key]

    u0 = np.zeros(problem.number_of_unknowns)
    initial = evaluate(u0).cost
    dense = method == "lm-dense"
    m = evaluate(u0).residuals.size
    if dense and m < u0.size:
        raise ValueError(
            f"solver 'lm-dense' needs at least as many residuals as unknowns, got {m} < {u0.size}"
        )

    def jac(u: np.ndarray):
        J = evaluate(u).jacobian
        return J.toarray() if dense else J

    max_nfev = criteria.max_iteration * (u0.size + 1) if dense else criteria.max_iteration * 3
    res = least_squares(
        lambda u: evaluate(u).residuals,
        u0,
        jac=jac,
        method="lm" if dense else "trf",
        ftol=max(criteria.relative_cost, 1e-15),
        xtol=max(criteria.relative_step * 1e-3, 1e-15),
        gtol=1e-12,
        max_nfev=max_nfev,
        x_scale=1.0 if dense else "jac",
        tr_solver=None if dense else "lsmr",
    )
    ev = problem.evaluate(res.x)
    return SolveInfo(
        ev,
        initial,
        int(res.njev or res.nfev),
        int(res.nfev),
        bool(res.success),
        str(res.message),
    )
