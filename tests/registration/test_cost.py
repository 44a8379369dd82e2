"""The level cost of eq. (3): analytic Jacobian against finite differences, and zero at identity."""

import numpy as np
import pytest
from _helpers import level_problem

from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration import BoundaryChecker, CauchyLoss, DistanceChecker, NormalAngleChecker
from o3dreg.registration.elastic import lattice_box, vertex_normals
from o3dreg.registration.lattice import TrilinearLattice


@pytest.fixture(scope="module")
def meshes():
    source = synthetic_form("cube", 300)
    target = synthetic_form("sphere", 1500)
    return (
        (np.asarray(source.vertices), np.asarray(source.triangles)),
        (np.asarray(target.vertices), np.asarray(target.triangles)),
    )


def make_problem(
    source, target, symmetric_weight=1.0, regularization=0.3, energy="bending", resolution=4
):
    points = source[0] * 0.9
    origin, size = lattice_box([points, target[0]])
    lattice = TrilinearLattice.zeros(origin, size, (resolution,) * 3)
    return level_problem(
        points,
        target,
        lattice,
        symmetric_weight=symmetric_weight,
        regularization=regularization,
        energy=energy,
    )


@pytest.mark.parametrize("energy", ["bending", "membrane"])
def test_jacobian_matches_finite_differences(meshes, energy):
    problem = make_problem(*meshes, energy=energy)
    rng = np.random.default_rng(0)
    u = rng.normal(scale=0.5, size=problem.number_of_unknowns)
    ev = problem.evaluate(u)
    J = ev.jacobian.toarray()
    h = 1e-6
    cols = rng.choice(problem.number_of_unknowns, 25, replace=False)
    for j in cols:
        e = np.zeros_like(u)
        e[j] = h
        plus, minus = problem.evaluate(u + e), problem.evaluate(u - e)
        # The barycentre assignments are piecewise constant: a step of 1e-6 mm does not change
        # them (checked), so central differences see the same smooth residual as the Jacobian.
        assert plus.residuals.shape == minus.residuals.shape == ev.residuals.shape
        fd = (plus.residuals - minus.residuals) / (2 * h)
        # Point-to-surface distances are smooth off the surface and the medial axis: central
        # differences are accurate to O(h^2 * curvature) plus rounding ~1e-10 / h.
        np.testing.assert_allclose(J[:, j], fd, atol=2e-5)


def test_cost_terms_add_up(meshes):
    problem = make_problem(*meshes)
    ev = problem.evaluate(np.random.default_rng(1).normal(size=problem.number_of_unknowns))
    assert ev.cost == pytest.approx(float(ev.residuals @ ev.residuals))
    parts = ("point-to-surface", "barycentre", "regulariser")
    assert ev.cost == pytest.approx(sum(ev.cost_of(name) for name in parts))


def test_symmetric_cost_is_zero_for_identical_meshes(meshes):
    target = meshes[1]
    origin, size = lattice_box([target[0]])
    lattice = TrilinearLattice.zeros(origin, size, (4, 4, 4))
    problem = level_problem(target[0], target, lattice, regularization=1.0)
    ev = problem.evaluate(np.zeros(problem.number_of_unknowns))
    # Every target vertex is its own nearest template vertex: barycentres are the vertices.
    assert ev.cost_of("point-to-surface") < 1e-20
    assert ev.cost_of("barycentre") == 0.0
    assert ev.cost_of("regulariser") == 0.0


def test_bending_energy_is_free_for_affine_motion(meshes):
    # With every node free, an affine node field has zero second differences everywhere.
    lattice = make_problem(*meshes).lattice
    nodes = lattice.node_positions()
    all_free = level_problem(
        nodes, meshes[1], lattice, symmetric_weight=0.0, regularization=1.0, energy="bending"
    )
    a = np.array([[0.1, 0.2, 0.0], [0.0, -0.1, 0.3], [0.05, 0.0, 0.1]])
    ev = all_free.evaluate((nodes @ a.T + 2.0).ravel())
    assert ev.cost_of("regulariser") < 1e-20
    # ... while the membrane energy charges the same stretch.
    membrane = level_problem(
        nodes, meshes[1], lattice, symmetric_weight=0.0, regularization=1.0, energy="membrane"
    )
    assert membrane.evaluate((nodes @ a.T + 2.0).ravel()).cost_of("regulariser") > 1.0


@pytest.mark.parametrize(
    "robustness",
    [
        dict(checkers=(BoundaryChecker(),)),
        dict(
            loss=CauchyLoss(),
            checkers=(BoundaryChecker(), NormalAngleChecker(60.0), DistanceChecker(3.0)),
        ),
    ],
    ids=["plain", "robust"],
)
def test_normal_equations_are_those_of_the_jacobian(meshes, robustness):
    # The solver assembles J^T J and J^T r block by block, without J: it must be the same
    # system as the Jacobian that is checked against finite differences above.
    source, target = meshes
    points = source[0] * 0.9
    origin, size = lattice_box([points, target[0]])
    lattice = TrilinearLattice.zeros(origin, size, (4, 4, 4))
    normals = vertex_normals(points, source[1])
    problem = level_problem(points, target, lattice, **robustness, normals=normals)
    u = np.random.default_rng(2).normal(scale=0.5, size=problem.number_of_unknowns)
    ev = problem.evaluate(u)
    A, g = problem.normal_equations(ev)
    J = ev.jacobian
    scale = abs(J.T @ J).max()
    # Sums of the same products in another order: equal to rounding.
    np.testing.assert_allclose(A.toarray(), (J.T @ J).toarray(), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(g, J.T @ ev.residuals, rtol=0, atol=1e-12 * abs(g).max())
