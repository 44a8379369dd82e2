"""The level solver's contract: non-convergence and broken problems are reported, never raised."""

import numpy as np
import pytest

from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration import Barycentre, BoundaryChecker, CauchyLoss, PointToSurface, _solvers
from o3dreg.registration._cost import LevelProblem
from o3dreg.registration.distance import SurfaceDistanceQuery
from o3dreg.registration.elastic import lattice_box
from o3dreg.registration.lattice import TrilinearLattice
from o3dreg.registration.options import ElasticCriteria

#: Point-to-surface and the barycentre term with one unit per row, on every target vertex.
UNIFORM_BARYCENTRE = (PointToSurface(), Barycentre(weighting="uniform"))


def small_problem(
    source: str = "cube", scale: float = 0.9, resolution: int = 4, vertices: int = 300
) -> LevelProblem:
    source_mesh, target = synthetic_form(source, vertices), synthetic_form("sphere", 1500)
    points = np.asarray(source_mesh.vertices) * scale
    tv, tf = np.asarray(target.vertices), np.asarray(target.triangles)
    origin, size = lattice_box([points, tv])
    return LevelProblem(
        points,
        np.zeros_like(points),
        TrilinearLattice.zeros(origin, size, (resolution,) * 3),
        np.ones(points.shape[0], dtype=bool),
        SurfaceDistanceQuery(tv, tf),
        UNIFORM_BARYCENTRE,
        0.1,
        checkers=(BoundaryChecker(),),
        min_jacobian_determinant=0.05,
    )


def test_a_non_finite_step_stops_with_a_message(monkeypatch):
    # A linear solver that returns NaN whatever the damping (as a singular or overflowing system
    # would): retrying with a larger damping would never end.
    problem = small_problem()
    monkeypatch.setattr(
        _solvers.DampedSystem, "solve_damped", lambda self, d, b: np.full(b.shape, np.nan)
    )
    info = _solvers.solve(problem, ElasticCriteria(), "lm")
    assert not info.success
    assert "non-finite" in info.message
    assert info.iterations == 0
    np.testing.assert_array_equal(info.evaluation.u, 0.0)


def test_a_non_finite_cost_stops_with_a_message(monkeypatch):
    # Every trial evaluates to a NaN cost (e.g. a distance query that broke down): no step is
    # taken and the level says why, instead of claiming convergence.
    problem = small_problem()
    original = problem.evaluate

    def broken(u, *args, **kwargs):
        ev = original(u, *args, **kwargs)
        if np.any(u != 0):
            ev.cost = float("nan")
        return ev

    monkeypatch.setattr(problem, "evaluate", broken)
    info = _solvers.solve(problem, ElasticCriteria(), "lm")
    assert not info.success
    assert "non-finite" in info.message


@pytest.mark.parametrize("resolution", [2, 4])
def test_a_healthy_level_still_converges(resolution):
    # The target shrunk by 10%: an exact solution exists (a scaling, free under the bending
    # energy) at which both distance terms vanish, so the level converges in a few steps. (The
    # cube onto the sphere above needs 15-20+ steps: its barycentre term slides the vertices
    # towards their Voronoi centroids, Lloyd's slow relaxation, and its exact symmetric ties
    # make the count depend on how nearest-neighbour searches break ties.)
    problem = small_problem("sphere", 0.9, resolution, vertices=1500)
    info = _solvers.solve(problem, ElasticCriteria(), "lm")
    assert info.success
    assert info.evaluation.cost < info.initial_cost


def test_the_extrapolation_is_the_rest_of_a_geometric_series():
    d = np.array([3.0, -1.0, 2.0, 0.5])
    for r in (0.5, 0.8):
        # Steps d, r d, r^2 d, ... sum to d / (1 - r): after the second, r^2 d / (1 - r) remain.
        jump = _solvers._extrapolation(r * d, d)
        np.testing.assert_allclose(jump, r * r * d / (1.0 - r), rtol=1e-12)
    assert _solvers._extrapolation(d, None) is None  # no earlier step
    assert _solvers._extrapolation(0.99 * d, d) is None  # ratio near 1: a guess too far
    assert _solvers._extrapolation(0.1 * d, d) is None  # already converging fast
    turned = np.array([1.0, 3.0, 0.0, 0.0])  # orthogonal to d: not one series
    assert abs(turned @ d) < 1e-12
    assert _solvers._extrapolation(0.5 * turned, d) is None
    assert _solvers._extrapolation(np.zeros(4), d) is None


def lloyd_problem() -> LevelProblem:
    # The cone onto the sphere on a 2-cell lattice (the paper's pair): the barycentre term
    # spreads the cone's vertices over the sphere towards their Voronoi centroids, a linearly
    # converging fixed-point iteration where the extrapolation is offered.
    source, target = synthetic_form("cone", 500), synthetic_form("sphere", 3000)
    points = np.asarray(source.vertices)
    tv, tf = np.asarray(target.vertices), np.asarray(target.triangles)
    origin, size = lattice_box([points, tv])
    return LevelProblem(
        points,
        np.zeros_like(points),
        TrilinearLattice.zeros(origin, size, (2, 2, 2)),
        np.ones(points.shape[0], dtype=bool),
        SurfaceDistanceQuery(tv, tf),
        UNIFORM_BARYCENTRE,
        0.1,
        loss=CauchyLoss(),
        checkers=(BoundaryChecker(),),
        min_jacobian_determinant=0.05,
    )


def test_a_jump_that_does_not_lower_the_cost_is_discarded(monkeypatch):
    with monkeypatch.context() as never:
        never.setattr(_solvers, "EXTRAPOLATION_MIN_COSINE", 2.0)  # no jump offered
        plain = _solvers.solve(lloyd_problem(), ElasticCriteria(), "lm")
    problem = lloyd_problem()
    original = problem.evaluate
    offered = []

    def no_better(u, *args, reassign=False, **kwargs):
        ev = original(u, *args, reassign=reassign, **kwargs)
        if reassign:
            offered.append(u)
            ev.cost = float(kwargs.get("weights_of", args[0] if args else None).cost)
        return ev

    monkeypatch.setattr(problem, "evaluate", no_better)
    info = _solvers.solve(problem, ElasticCriteria(), "lm")
    assert offered  # the case does offer jumps
    # Every jump costing as much as the current point was refused: the iterates are the plain
    # solver's, bit for bit; only the refused evaluations were counted on top.
    np.testing.assert_array_equal(info.evaluation.u, plain.evaluation.u)
    assert info.iterations == plain.iterations
    assert info.evaluations == plain.evaluations + len(offered)


def test_kept_jumps_shorten_a_lloyd_level(monkeypatch):
    with_jumps = _solvers.solve(lloyd_problem(), ElasticCriteria(), "lm")
    monkeypatch.setattr(_solvers, "EXTRAPOLATION_MIN_COSINE", 2.0)  # never offered
    plain = _solvers.solve(lloyd_problem(), ElasticCriteria(), "lm")
    assert with_jumps.success and plain.success
    # The jumps skip steps of the same fixed-point iteration: measured 14 iterations (15
    # evaluations) -> 9 (14, the jumps' included), ending 1.5% lower. Asserted: fewer
    # iterations and evaluations, and no higher a cost.
    assert with_jumps.iterations < plain.iterations
    assert with_jumps.evaluations < plain.evaluations
    assert with_jumps.evaluation.cost <= plain.evaluation.cost


def block_system(seed=0, nodes=60):
    """A symmetric positive semidefinite 3x3-block matrix on a chain of nodes (each coupled with
    its neighbours within 3), with rank-1 blocks on the diagonal: point-to-plane normal
    equations' shape, whose x, y, z are coupled at every node."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(4 * nodes):
        g = rng.normal(size=3)
        a = int(rng.integers(0, nodes))
        b = min(nodes - 1, a + int(rng.integers(0, 4)))
        r = np.zeros(3 * nodes)
        r[3 * a : 3 * a + 3] += g
        r[3 * b : 3 * b + 3] += 0.5 * g
        rows.append(r)
    J = np.array(rows)
    return J.T @ J


def test_the_damped_system_is_solved_to_the_conjugate_gradients_tolerance():
    import scipy.sparse as sp

    A = block_system()
    n = A.shape[0]
    assert n > _solvers.DENSE_UNKNOWNS  # the conjugate-gradients path
    rng = np.random.default_rng(1)
    b = rng.normal(size=n)
    damping = 1e-3 * np.maximum(np.diag(A), 1e-12)
    x = _solvers.DampedSystem(sp.bsr_matrix(A, blocksize=(3, 3))).solve_damped(damping, b)
    M = A + np.diag(damping)
    residual = np.linalg.norm(M @ x - b)
    assert residual <= _solvers.CG_RTOL * np.linalg.norm(b) * (1 + 1e-9)
    # From a CSR matrix too (the system takes any sparse format).
    y = _solvers.DampedSystem(sp.csr_matrix(A)).solve_damped(damping, b)
    np.testing.assert_array_equal(x, y)


def test_the_damped_system_falls_back_to_a_direct_solve(monkeypatch):
    import scipy.sparse as sp

    A = block_system(seed=2)
    n = A.shape[0]
    b = np.random.default_rng(3).normal(size=n)
    damping = 1e-3 * np.maximum(np.diag(A), 1e-12)
    exact = np.linalg.solve(A + np.diag(damping), b)
    # Conjugate gradients stopped after one iteration: the sparse LU answers.
    monkeypatch.setattr(_solvers, "CG_MAXITER", 1)
    x = _solvers.DampedSystem(sp.bsr_matrix(A, blocksize=(3, 3))).solve_damped(damping, b)
    np.testing.assert_allclose(x, exact, rtol=1e-8, atol=1e-10 * np.abs(exact).max())
    # An indefinite system (never met by Levenberg-Marquardt, whose damping is positive):
    # whichever path answers, the answer meets the conjugate gradients' tolerance.
    monkeypatch.setattr(_solvers, "CG_MAXITER", 1000)
    indefinite = A - 0.5 * np.abs(A).max() * np.eye(n)
    x = _solvers.DampedSystem(sp.bsr_matrix(indefinite, blocksize=(3, 3))).solve_damped(
        np.zeros(n), b
    )
    residual = np.linalg.norm(indefinite @ x - b)
    assert residual <= _solvers.CG_RTOL * np.linalg.norm(b) * (1 + 1e-9)


def test_a_node_without_a_diagonal_block_is_solved_too():
    # A node no row touches (no stored diagonal block): the damping alone holds it, and the
    # solution meets the conjugate gradients' tolerance on the damped system.
    import scipy.sparse as sp

    rng = np.random.default_rng(4)
    J = rng.normal(size=(400, 150))
    J[:, 30:33] = 0.0
    A = J.T @ J
    damping = 1e-3 * np.maximum(np.diag(A), 1.0)
    b = rng.normal(size=150)
    x = _solvers.DampedSystem(sp.csr_matrix(A)).solve_damped(damping, b)
    residual = np.linalg.norm((A + np.diag(damping)) @ x - b)
    assert residual <= _solvers.CG_RTOL * np.linalg.norm(b) * (1 + 1e-9)
    np.testing.assert_allclose(x[30:33], b[30:33] / damping[30:33])
