"""The level solver's contract: non-convergence and broken problems are reported, never raised."""

import numpy as np
import pytest

from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration import _solvers
from o3dreg.registration._cost import LevelProblem, Robustness
from o3dreg.registration.distance import SurfaceDistanceQuery
from o3dreg.registration.elastic import lattice_box
from o3dreg.registration.lattice import TrilinearLattice
from o3dreg.registration.options import ElasticCriteria


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
        tv,
        1.0,
        0.1,
        robustness=Robustness(min_jacobian_determinant=0.05),
    )


def test_a_non_finite_step_stops_with_a_message(monkeypatch):
    # A linear solver that returns NaN whatever the damping (as a singular or overflowing system
    # would): the solver used to retry with a larger damping forever.
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
