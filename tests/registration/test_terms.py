"""The residual terms of a level (the distance terms, the regulariser) against one contract, and
the robust kernels and correspondence checkers alone.

Contract of every term: its analytic Jacobian rows equal central finite differences of its
residuals, and its share of the normal equations equals ``J^T J`` and ``J^T r`` of that Jacobian,
with plain and with robust weights. A new distance term is one class and one entry in
``CONTRACT``; the two terms defined here (``ClosestPoint``, ``LandmarkPairs``) are such terms,
and run through a whole registration as the library's own do.
"""

from dataclasses import dataclass

import numpy as np
import pytest
import scipy.sparse as sp
from _helpers import level_problem

from o3dreg import DistanceEstimation, ElasticLevel, registration_elastic
from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration import (
    Barycentre,
    BoundaryChecker,
    CauchyLoss,
    DistanceChecker,
    DistanceTerm,
    NormalAngleChecker,
    PointToSurface,
)
from o3dreg.registration._assembly import NormalAssembly, symmetric_outer
from o3dreg.registration._robust import BoundaryMask, DistanceMask, NormalMask, support
from o3dreg.registration._terms import PullTerm
from o3dreg.registration.distance import SurfaceDistanceQuery
from o3dreg.registration.elastic import lattice_box, vertex_normals
from o3dreg.registration.lattice import TrilinearLattice
from o3dreg.registration.losses import loss_named
from o3dreg.registration.terms import TermContext


@dataclass(frozen=True)
class ClosestPoint(DistanceTerm):
    """Point-to-point ICP: every template point pulled to its closest point on the target, with
    the point-to-surface term's robust weights and masks."""

    def bind(self, context: TermContext) -> PullTerm:
        def pulls(g, w, state):
            scale = np.ones(g.moved.shape[0]) if w.point is None else np.sqrt(w.point)
            return g.closest, scale

        return PullTerm(context.assembly, pulls, name="closest point")


@dataclass(frozen=True, eq=False)
class LandmarkPairs(DistanceTerm):
    """Template vertices ``vertices`` pulled to the target points ``points`` with ``weight``
    (a level that does not use a landmark's vertex has no row for it)."""

    vertices: np.ndarray
    points: np.ndarray
    weight: float = 1.0

    def bind(self, context: TermContext) -> PullTerm | None:
        rows = np.flatnonzero(np.isin(context.indices, self.vertices))
        if rows.size == 0:
            return None
        goals = context.points.copy()
        order = np.argsort(self.vertices)
        at = order[np.searchsorted(self.vertices, context.indices[rows], sorter=order)]
        goals[rows] = self.points[at]
        scale = np.zeros(context.points.shape[0])
        scale[rows] = np.sqrt(self.weight)
        return PullTerm(context.assembly, lambda g, w, state: (goals, scale), name="landmarks")


#: Every distance term, once or more with other settings; ``None`` stands for the regulariser.
CONTRACT = [
    PointToSurface(),
    Barycentre(weighting="uniform"),
    Barycentre(weight=0.5, weighting="count"),
    ClosestPoint(),
    LandmarkPairs(np.array([3, 40, 200]), np.array([[0.0, 0, 38], [38.0, 0, 0], [0, -38.0, 5]])),
    None,
]
ROBUSTNESS = {
    "plain": dict(checkers=(BoundaryChecker(),)),
    "robust": dict(
        loss=CauchyLoss(),
        checkers=(BoundaryChecker(), NormalAngleChecker(60.0), DistanceChecker(3.0)),
    ),
}


@pytest.fixture(scope="module")
def level():
    source = synthetic_form("cube", 300)
    target = synthetic_form("sphere", 1500)
    vs, fs = np.asarray(source.vertices), np.asarray(source.triangles)
    target = (np.asarray(target.vertices), np.asarray(target.triangles))
    points = vs * 0.9
    origin, size = lattice_box([points, target[0]])
    lattice = TrilinearLattice.zeros(origin, size, (4, 4, 4))
    return points, target, lattice, vertex_normals(points, fs)


def problem_of(level, terms, weights):
    points, target, lattice, normals = level
    return level_problem(
        points, target, lattice, terms=terms, **ROBUSTNESS[weights], normals=normals
    )


@pytest.mark.parametrize("weights", list(ROBUSTNESS))
@pytest.mark.parametrize("term", CONTRACT, ids=lambda t: "regulariser" if t is None else repr(t))
class TestTermContract:
    def setup_term(self, level, term, weights):
        # The term alone (the regulariser beside the point-to-surface term): the level cost's
        # last term is the regulariser, the first the one tested.
        problem = problem_of(level, [PointToSurface() if term is None else term], weights)
        index = -1 if term is None else 0
        rng = np.random.default_rng(CONTRACT.index(term))
        u = rng.normal(scale=0.5, size=problem.number_of_unknowns)
        ev = problem.evaluate(u)
        if weights == "robust":
            # The robust case must actually weight: some rows down-weighted or rejected.
            assert ev.weights is not None and ev.weights.min() < 0.99
        return problem, index, u, ev, rng

    def test_jacobian_matches_central_differences(self, level, term, weights):
        problem, index, u, ev, rng = self.setup_term(level, term, weights)
        J = ev.terms[index].jacobian.toarray()
        assert abs(J).max() > 0  # the term has rows here
        h = 1e-6
        for j in rng.choice(problem.number_of_unknowns, 20, replace=False):
            e = np.zeros_like(u)
            e[j] = h
            # Weights, masks and a term's own correspondences held at those of ``u`` (one IRLS
            # linearisation, as a trial step of Levenberg-Marquardt).
            plus = problem.evaluate(u + e, weights_of=ev).terms[index].residuals
            minus = problem.evaluate(u - e, weights_of=ev).terms[index].residuals
            # Distances are smooth off the surface and the medial axis: central differences
            # are accurate to O(h^2 * curvature) plus rounding ~1e-10 / h.
            np.testing.assert_allclose(J[:, j], (plus - minus) / (2 * h), atol=2e-5)

    def test_normal_share_is_that_of_the_jacobian(self, level, term, weights):
        problem, index, _, ev, _ = self.setup_term(level, term, weights)
        block = ev.terms[index]
        A, g = problem.terms[index].normal_share(block)
        J, r = block.jacobian, block.residuals
        JtJ = (J.T @ J).toarray()
        # The same products summed in another order: equal to rounding.
        scale = max(abs(JtJ).max(), 1e-300)
        np.testing.assert_allclose(A.toarray(), JtJ, rtol=0, atol=1e-12 * scale)
        Jtr = J.T @ r
        np.testing.assert_allclose(g, Jtr, rtol=0, atol=1e-12 * max(abs(Jtr).max(), 1e-300))


@pytest.mark.parametrize("weights", list(ROBUSTNESS))
def test_the_level_is_the_sum_of_its_terms(level, weights):
    terms = [t for t in CONTRACT if t is not None]
    problem = problem_of(level, terms, weights)
    ev = problem.evaluate(np.random.default_rng(3).normal(size=problem.number_of_unknowns))
    assert [t.name for t in problem.terms] == [
        "point-to-surface",
        "barycentre",
        "barycentre",
        "closest point",
        "landmarks",
        "regulariser",
    ]
    np.testing.assert_array_equal(ev.residuals, np.concatenate([b.residuals for b in ev.terms]))
    assert ev.cost == sum(b.cost for b in ev.terms)
    A, g = problem.normal_equations(ev)
    shares = [t.normal_share(b) for t, b in zip(problem.terms, ev.terms)]
    scale = abs(A).max()
    np.testing.assert_allclose(
        A.toarray(), sum(a.toarray() for a, _ in shares), rtol=0, atol=1e-13 * scale
    )
    np.testing.assert_allclose(g, sum(b for _, b in shares), rtol=0, atol=1e-13 * abs(g).max())


def test_a_term_of_ones_own_registers_end_to_end():
    # Three landmarks of a sphere pulled 25 degrees along the surface of a larger sphere: the
    # point-to-surface term alone moves them outwards only (the spheres match everywhere), the
    # landmark term slides them to their targets, and the rest of the surface follows smoothly.
    template = synthetic_form("sphere", 800)
    target = synthetic_form("sphere", 3000)
    v = np.asarray(template.vertices)
    target.scale(1.1, center=(0.0, 0.0, 0.0))
    turn = np.radians(25.0)
    rotation = np.array(
        [[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]
    )
    vertices = np.argsort(np.abs(v[:, 2]))[[0, 40, 80]]  # near the equator
    goals = 1.1 * v[vertices] @ rotation.T
    levels = [ElasticLevel(r, points_per_node=None, symmetric_scale=0.0) for r in (2, 4, 8)]
    landmarks = LandmarkPairs(vertices, goals, weight=50.0)
    estimation = DistanceEstimation.compose(terms=[PointToSurface(), landmarks], checkers=[])
    assert estimation.terms == (PointToSurface(), landmarks)
    plain = registration_elastic(template, target, init=np.eye(4), levels=levels)
    pulled = registration_elastic(
        template, target, init=np.eye(4), levels=levels, estimation_method=estimation
    )
    miss_plain = np.linalg.norm(plain.vertices[vertices] - goals, axis=1)
    miss_pulled = np.linalg.norm(pulled.vertices[vertices] - goals, axis=1)
    assert miss_plain.min() > 15.0  # 25 degrees on a radius of 44 mm: about 19 mm
    assert miss_pulled.max() < 0.5
    # Still on the target: the landmark term slides the surface, it does not tear it off.
    assert pulled.distances.source_to_target_mean < 0.1


def test_the_estimation_holds_the_terms_it_is_given():
    closest = ClosestPoint()
    composed = DistanceEstimation.compose(terms=[PointToSurface(), Barycentre(0.5), closest])
    assert composed.terms == (PointToSurface(), Barycentre(0.5), closest)
    assert composed.more_terms == (closest,)
    assert composed == DistanceEstimation(symmetric_weight=0.5, more_terms=(closest,))
    assert "more_terms=(ClosestPoint(),)" in repr(composed)
    assert "more_terms" not in repr(DistanceEstimation())
    with pytest.raises(TypeError, match="`terms`"):
        DistanceEstimation.compose(terms=[PointToSurface(), "closest point"])
    with pytest.raises(TypeError, match="`terms`"):
        DistanceEstimation.compose(terms=[PointToSurface(), DistanceTerm()])  # no bind
    with pytest.raises(ValueError, match="`terms`"):
        DistanceEstimation.compose(terms=[closest])  # no point-to-surface term
    with pytest.raises(ValueError, match="`more_terms`"):
        DistanceEstimation(more_terms=(Barycentre(),))
    with pytest.raises(TypeError, match="`more_terms`"):
        DistanceEstimation(more_terms=closest)


def test_a_term_says_what_the_level_does_not_offer(level):
    # A level posed without the template's Voronoi offsets cannot correct the barycentres.
    with pytest.raises(ValueError, match="`correction=True`"):
        problem_of(level, [Barycentre(correction=True)], "plain")
    # A term with no rows at a level (weight times the level's symmetric_scale is 0) is left out.
    points, target, lattice, _ = level
    off = level_problem(
        points, target, lattice, terms=[PointToSurface(), Barycentre()], symmetric_scale=0.0
    )
    assert [t.name for t in off.terms] == ["point-to-surface", "regulariser"]
    assert not off.reassigns


@pytest.mark.parametrize("loss", ["linear", "huber", "cauchy", "tukey"])
def test_kernel_weight_is_the_derivative_of_its_loss_over_r(loss):
    # w(r) = rho'(r) / r: integrate w(r) r numerically and compare with the closed-form rho.
    c = 1.5
    rho = {
        "linear": lambda r: r**2 / 2,
        "huber": lambda r: np.where(abs(r) <= c, r**2 / 2, c * abs(r) - c**2 / 2),
        "cauchy": lambda r: c**2 / 2 * np.log1p((r / c) ** 2),
        "tukey": lambda r: np.where(abs(r) < c, c**2 / 6 * (1 - (1 - (r / c) ** 2) ** 3), c**2 / 6),
    }[loss]
    r = np.linspace(0.0, 4.0, 40001)
    integrand = loss_named(loss).weight(r, c / loss_named(loss).constant) * r
    integral = np.concatenate([[0.0], np.cumsum((integrand[1:] + integrand[:-1]) / 2 * np.diff(r))])
    # Trapezoid rule with step 1e-4 on a piecewise-smooth integrand: error ~1e-8.
    np.testing.assert_allclose(integral, rho(r), atol=1e-7)


def test_no_kernel_and_scaled_kernel():
    r = np.array([0.0, 1.0, 100.0])
    np.testing.assert_array_equal(loss_named("linear").weight(r, 1.0), 1.0)
    # The Cauchy loss at the scale sigma: its constant 2.3849 (95% efficiency) times sigma.
    k = CauchyLoss()
    assert k.threshold(2.0) == pytest.approx(2.3849 * 2.0)
    assert k.weight(np.array([k.threshold(2.0)]), 2.0)[0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="`loss`"):
        loss_named("l1")


def test_checkers_alone():
    # A unit square of two triangles (open boundary), normals +z.
    square = SurfaceDistanceQuery(
        np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), np.array([[0, 1, 2], [0, 2, 3]])
    )
    pts = np.array([[0.5, 0.5, 0.2], [2.0, 0.5, 0.0], [0.5, 0.5, -3.0]])
    dist, face, closest = square.closest(pts)
    boundary = BoundaryMask(square).check(pts, dist, face, closest)
    np.testing.assert_array_equal(boundary, [True, False, True])
    normals = np.array([[0.0, 0, 1], [0, 0, 1], [0, np.sin(1.0), np.cos(1.0)]])  # 1 rad = 57.3 deg
    for angle, expected in ((60.0, [True, True, True]), (50.0, [True, True, False])):
        checker = NormalMask(normals, square.face_normals, angle)
        np.testing.assert_array_equal(checker.check(pts, dist, face, closest), expected)
    distance = DistanceMask(factor=2.0, sigma=1.0).check(pts, dist, face, closest)
    np.testing.assert_array_equal(distance, [True, True, False])
    both = support([BoundaryMask(square), DistanceMask(2.0, 1.0)], pts, dist, face, closest)
    np.testing.assert_array_equal(both, [True, False, False])
    assert support([], pts, dist, face, closest).all()


def test_the_normal_checker_looks_up_only_the_normals_it_needs():
    # The final support check of a registration runs once on the full target: on a target
    # whose tree is not built (a large one, answered by closest_few), it asks the query for
    # the normals of the triangles found (face_normal) instead of computing the normal of every
    # triangle (face_normals), with the same verdicts. A query whose tree is built (queried
    # tens of times by the levels) computes them all once.
    from o3dreg.app.synthetic import synthetic_form
    from o3dreg.registration.checkers import CheckerContext
    from o3dreg.registration.elastic import vertex_normals

    sphere = synthetic_form("sphere", 2000)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    rng = np.random.default_rng(0)
    pts = v[:300] + rng.normal(scale=2.0, size=(300, 3))
    normals = vertex_normals(v, f)[:300] + rng.normal(scale=0.8, size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lazy_query, other = SurfaceDistanceQuery(v, f), SurfaceDistanceQuery(v, f)
    found = other.closest(pts)
    lazy = NormalMask(normals, lazy_query.face_normal, 45.0).check(pts, *found)
    assert "face_normals" not in lazy_query.__dict__
    full = NormalMask(normals, SurfaceDistanceQuery(v, f).face_normals, 45.0)
    np.testing.assert_array_equal(lazy, full.check(pts, *found))
    assert 0 < lazy.sum() < lazy.size  # both verdicts occur
    moved = v[:, :] * 1.01
    context = CheckerContext(lazy_query, normals=vertex_normals(moved, f))
    bound = NormalAngleChecker(45.0).bind(context)
    assert bound is not None
    bound.check(moved, *other.closest(moved))
    assert "face_normals" not in lazy_query.__dict__
    np.testing.assert_array_equal(other.face_normal(found[1]), full.face_normals[found[1]])
    assert "face_normals" in other.__dict__


def test_normal_assembly_is_the_sum_over_points():
    # Random trilinear-like weights on 8 of 30 nodes per point (some fixed: -1), random symmetric
    # 3x3 metrics and vectors: the fixed-pattern assembly must equal the dense sum
    # sum_i (W_i^T W_i) (x) M_i + G (x) I_3 and W^T f, whatever the cells' order.
    rng = np.random.default_rng(4)
    n, m = 200, 30
    cells = rng.integers(0, 12, n)
    cell_nodes = np.stack([rng.choice(m, 8, replace=False) for _ in range(12)])
    cell_nodes[3, :2] = -1  # a cell with fixed corners
    nodes = cell_nodes[cells]
    weights = np.where(nodes >= 0, rng.random((n, 8)), 0.0)
    gram = sp.random(m, m, density=0.2, random_state=5)
    gram = (gram + gram.T).tocsr()
    assembly = NormalAssembly(nodes, weights, m, gram, cells=cells)
    v = rng.normal(size=(n, 3))
    iso = rng.random(n)
    f = rng.normal(size=(n, 3))
    W = np.zeros((n, m))
    for i in range(n):
        for k in range(8):
            if nodes[i, k] >= 0:
                W[i, nodes[i, k]] += weights[i, k]
    expected = sum(
        np.kron(np.outer(W[i], W[i]), np.outer(v[i], v[i]) + iso[i] * np.eye(3)) for i in range(n)
    ) + np.kron(gram.toarray(), np.eye(3))
    A = assembly.matrix(symmetric_outer(v), iso)
    # The same products summed in another order: equal to rounding.
    np.testing.assert_allclose(A.toarray(), expected, rtol=0, atol=1e-12 * abs(expected).max())
    np.testing.assert_allclose(assembly.vector(f), (W.T @ f).ravel(), rtol=0, atol=1e-12)
    # The pair sums are the product with S[pair(a, b), i] = W_ia W_ib built by hand, point by
    # point.
    keys = np.repeat(np.arange(m), np.diff(assembly.indptr)) * m + assembly.indices
    pair, point = [], []
    for i in range(n):
        free = nodes[i][nodes[i] >= 0]
        a, b = np.repeat(free, free.size), np.tile(free, free.size)
        pair.append(np.searchsorted(keys, a * m + b))
        point.append(np.full(a.size, i))
    pair, point = np.concatenate(pair), np.concatenate(point)
    S = sp.csc_matrix((W[point, keys[pair] // m] * W[point, keys[pair] % m], (pair, point)))
    S.resize(keys.size, n)
    metric = symmetric_outer(v)
    # The same products summed in another order: equal to rounding.
    scale = 1e-12 * abs(metric).max()
    np.testing.assert_allclose(assembly.pair_sums(metric), S @ metric, rtol=0, atol=scale)
    np.testing.assert_allclose(
        assembly.pair_sums(iso), S @ iso, rtol=0, atol=1e-12 * abs(iso).max()
    )
    # One value (row) per point: anything else is refused.
    with pytest.raises(ValueError, match="points"):
        assembly.pair_sums(np.zeros(n + 1))


def brute_force_nearest(points: np.ndarray, sites: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest site of every point by comparing all distances; exact ties to the smaller index
    (``argmin`` returns the first minimum)."""
    d = np.sqrt(((points[:, None, :] - sites[None, :, :]) ** 2).sum(axis=2))
    nearest = d.argmin(axis=1)
    return d[np.arange(points.shape[0]), nearest], nearest


@pytest.mark.parametrize("cell_size", [np.inf, 30.0, 4.0, 0.5])
def test_the_barycentre_assignment_is_exact_along_any_path(cell_size):
    # The term re-searches only the target points whose nearest template point may have changed
    # since their last search (and within a radius that held last time): along a path of small
    # steps, large jumps, moves back and a far excursion (which empties that radius for most
    # points), every assignment must be the brute-force one. A radius reset for every point
    # after one of them missed it once let the others keep stale assignments (up to 2 mm off).
    # With a lattice cell, the moves are also summed near each target point (LocalMoves): cubes
    # larger than the sites' spread, about their spacing, and far smaller.
    from o3dreg.registration._terms import BarycentreTerm

    rng = np.random.default_rng(3)
    sites = rng.normal(size=(60, 3)) * 10.0
    sites[1] = sites[0] * [1, 1, -1]  # mirror pairs: exact ties on the plane z = 0
    targets = rng.normal(size=(2000, 3)) * 12.0
    targets[:50, 2] = 0.0
    sites[0, 2] = 3.0
    sites[1, 2] = -3.0
    term = BarycentreTerm(None, targets, 1.0, cell_size=cell_size)  # type: ignore[arg-type]
    y = sites.copy()
    path = []
    for step in range(12):
        move = rng.normal(size=3) * (0.05 if step % 3 else 2.0) + 0.3 * np.sin(y / 7.0 + step)
        y = y + move
        path.append(y.copy())
    path.append(sites + 40.0)  # a far excursion: most points miss the radius
    path.append(sites.copy())  # and back
    path.append(sites + 0.01)
    for y in path:
        distance, nearest = term.measure(y)
        expected_distance, expected = brute_force_nearest(targets, y)
        np.testing.assert_array_equal(nearest, expected)
        np.testing.assert_allclose(distance, expected_distance, rtol=1e-12)


def test_a_move_of_one_part_searches_the_target_points_near_it_only(monkeypatch):
    # Steps of the left fifth of a flat template leave the rest where it was: with the moves
    # summed near each target point (a lattice cell given), the target points far from the left
    # keep their assignment unsearched; with the largest move anywhere (no cell) they are
    # searched again too. The assignments are the brute-force ones either way.
    from o3dreg.registration import _terms

    searched: list[int] = []
    search = _terms._nearest_two

    def counted(tree, points, k, bound):
        searched.append(points.shape[0])
        return search(tree, points, k, bound)

    monkeypatch.setattr(_terms, "_nearest_two", counted)
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(*[np.arange(0.0, 100.0, 4.0)] * 2, indexing="ij"), -1)
    sites = np.column_stack([grid.reshape(-1, 2), np.zeros(grid[..., 0].size)])
    targets = np.column_stack([rng.uniform(0, 96, (20000, 2)), rng.normal(0, 0.5, 20000)])
    moves = [rng.normal(0, 0.3, sites.shape) * (sites[:, :1] < 20.0) for _ in range(4)]
    total = {}
    for cell in (np.inf, 20.0):
        term = _terms.BarycentreTerm(None, targets, 1.0, cell_size=cell)  # type: ignore[arg-type]
        y = sites.copy()
        term.measure(y)
        searched.clear()
        for move in moves:
            y = y + move
            distance, nearest = term.measure(y)
            expected_distance, expected = brute_force_nearest(targets, y)
            np.testing.assert_array_equal(nearest, expected)
            np.testing.assert_allclose(distance, expected_distance, rtol=1e-12)
        total[cell] = sum(searched)
    # The moved fifth and the cubes around it: well under half of what the global bound sends.
    assert total[20.0] < 0.5 * total[np.inf]


@pytest.mark.parametrize("robust", [False, True])
def test_counted_barycentre_rows_are_the_target_to_template_distance(robust):
    # With rows weighted by the target points they stand for, the block's squared norm is the
    # target->template sum (N / M) sum_j v_j |t_j - y_nn(j)|^2 less the scatter of the target
    # points about their barycentres (which does not depend on y): the identity
    # sum_j v_j |t_j - y|^2 = V |b - y|^2 + sum_j v_j |t_j - b|^2 for b the v-weighted mean.
    # Exact to rounding (sums of ~1e4 squares of mm-sized numbers).
    from o3dreg.registration._terms import BarycentreTerm

    rng = np.random.default_rng(7)
    y = rng.normal(size=(40, 3)) * 10.0
    targets = rng.normal(size=(900, 3)) * 12.0
    counted = BarycentreTerm(None, targets, 1.0, counted=True)  # type: ignore[arg-type]
    uniform = BarycentreTerm(None, targets, 1.0)  # type: ignore[arg-type]
    _, nearest = counted.measure(y)
    v = rng.uniform(0.2, 1.0, targets.shape[0]) if robust else None
    bary, scale = counted.targets(y.shape[0], nearest, v)
    block = ((scale[:, None] * (y - bary)) ** 2).sum()
    vv = np.ones(targets.shape[0]) if v is None else v
    direct = (vv * ((targets - y[nearest]) ** 2).sum(axis=1)).sum()
    scatter = (vv * ((targets - bary[nearest]) ** 2).sum(axis=1)).sum()
    ratio = y.shape[0] / targets.shape[0]
    np.testing.assert_allclose(block, ratio * (direct - scatter), rtol=1e-10)
    # The same barycentres; uniform rows weigh each template point by its mean target weight.
    ubary, uscale = uniform.targets(y.shape[0], nearest, v)
    np.testing.assert_allclose(ubary, bary)
    counts = np.bincount(nearest, minlength=y.shape[0])
    assigned = counts > 0
    np.testing.assert_allclose(
        uscale[assigned] ** 2,
        np.bincount(nearest, vv, minlength=y.shape[0])[assigned] / counts[assigned],
    )


def test_uncovered_candidates_are_the_target_points_beyond_the_template():
    # A square grid of spacing h: an inner node has 4 neighbours at h and 4 at h*sqrt(2), so its
    # 6th-nearest (its ring radius) is at h*sqrt(2); a corner's is at h*sqrt(5).
    from o3dreg.registration._terms import CANDIDATE_SHARE, uncovered_candidates

    h, reach = 0.1, 1.2
    g = np.arange(11) * h
    x, y = np.meshgrid(g, g)
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    # The square sampled 4 times finer: no point is farther than h/sqrt(2) (a cell centre) from
    # a node, below CANDIDATE_SHARE * reach * h*sqrt(2) = 0.085; a strip 0.3-0.5 beyond x = 1
    # is farther than any node's threshold.
    f = np.arange(41) * h / 4
    fx, fy = np.meshgrid(f, f)
    covered = np.column_stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)])
    sx, sy = np.meshgrid(1.0 + np.linspace(0.3, 0.5, 5), f)
    strip = np.column_stack([sx.ravel(), sy.ravel(), np.zeros(sx.size)])
    assert CANDIDATE_SHARE * reach * h * np.sqrt(2) > h / np.sqrt(2)
    target = np.vstack([covered, strip])
    beyond, candidates, distances = uncovered_candidates(points, target, reach)
    np.testing.assert_array_equal(candidates, covered.shape[0] + np.arange(strip.shape[0]))
    inner = (points[:, :2] > 0.5 * h).all(axis=1) & (points[:, :2] < 1 - 0.5 * h).all(axis=1)
    np.testing.assert_allclose(beyond[inner], reach * h * np.sqrt(2), rtol=1e-12)
    corner = np.flatnonzero((points[:, :2] == 0).all(axis=1))
    np.testing.assert_allclose(beyond[corner], reach * h * np.sqrt(5), rtol=1e-12)
    # Given the nearest points and distances, the same answer without a search.
    from scipy.spatial import cKDTree

    known = cKDTree(points).query(target)
    np.testing.assert_allclose(distances, known[0], rtol=1e-12)
    again = uncovered_candidates(points, target, reach, known)
    np.testing.assert_array_equal(again[1], candidates)


def test_barycentre_reach_is_validated_and_shown():
    with pytest.raises(ValueError, match="barycentre_reach"):
        ElasticLevel(16, barycentre_reach=0.0)
    with pytest.raises(ValueError, match="barycentre_reach"):
        ElasticLevel(16, barycentre_reach=-1.0)
    assert "barycentre_reach=1" in repr(ElasticLevel(16, barycentre_reach=1.0))
    assert "barycentre_reach" not in repr(ElasticLevel(16))
