"""Sliding semilandmarks: stay on the surfaces, reduce the criterion, compare models."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers import FAST, population

from o3dreg import build_shape_model, generalized_procrustes, register_batch, slide_semilandmarks
from o3dreg._geometry import face_cross, turned_triangles
from o3dreg.registration.distance import SurfaceDistanceQuery


@pytest.fixture(scope="module")
def registered(tmp_path_factory):
    (tv, tf), targets, _truths, _, poses = population(6, seed=5, template_resolution=8)
    batch = register_batch(
        (tv, tf), targets, tmp_path_factory.mktemp("reg"), levels=FAST, init=np.stack(poses)
    )
    return tf, targets, batch.shapes()[1]


def test_procrustes_sliding_stays_on_surface_and_reduces_distance(registered):
    tf, targets, shapes = registered
    before = shapes.copy()
    result = slide_semilandmarks(shapes, targets, criterion="procrustes", max_iteration=4)
    np.testing.assert_array_equal(shapes, before)
    for (v, f), s in zip(targets, result.shapes):
        assert SurfaceDistanceQuery(v, f).distance(s).max() < 1e-6
    assert result.procrustes_distances[-1] < result.procrustes_distances[0]
    # The comparison the issue asks for: less total variance after sliding (the tangential,
    # arbitrary part of the correspondences is removed).
    with_sliding = build_shape_model(result.shapes, tf)
    without = build_shape_model(shapes, tf)
    assert with_sliding.total_variance < without.total_variance


def test_bending_sliding_and_fixed_points(registered):
    _, targets, shapes = registered
    fixed = np.array([0, 1, 2])
    result = slide_semilandmarks(shapes, targets, criterion="bending", max_iteration=2, fixed=fixed)
    assert result.shapes.shape == shapes.shape and result.iterations <= 2
    # Fixed points are only re-projected onto their surface (they were already on it).
    start = np.stack(
        [SurfaceDistanceQuery(v, f).closest(s)[2] for (v, f), s in zip(targets, shapes)]
    )
    np.testing.assert_allclose(result.shapes[:, fixed], start[:, fixed], atol=1e-9)
    assert "SlidingResult(bending" in repr(result)


def test_sliding_bad_input(registered):
    _, targets, shapes = registered
    with pytest.raises(ValueError, match="criterion"):
        slide_semilandmarks(shapes, targets, criterion="energy")
    with pytest.raises(ValueError, match="one per shape"):
        slide_semilandmarks(shapes, targets[:-1])
    with pytest.raises(ValueError, match="fixed"):
        slide_semilandmarks(shapes, targets, fixed=[10**6])
    # A boolean mask read as indices would fix points 0 and 1 instead of the marked ones.
    mask = np.zeros(shapes.shape[1], dtype=bool)
    mask[[5, 10]] = True
    with pytest.raises(TypeError, match="`fixed` must be integer indices"):
        slide_semilandmarks(shapes, targets, fixed=mask)
    with pytest.raises(TypeError, match="`fixed` must be integer indices"):
        slide_semilandmarks(shapes, targets, fixed=[2.7])


def test_bending_sliding_with_every_point_fixed_moves_nothing(registered):
    _, targets, shapes = registered
    every = np.arange(shapes.shape[1])
    result = slide_semilandmarks(shapes, targets, criterion="bending", max_iteration=2, fixed=every)
    start = np.stack(
        [SurfaceDistanceQuery(v, f).closest(s)[2] for (v, f), s in zip(targets, shapes)]
    )
    np.testing.assert_allclose(result.shapes, start, atol=1e-9)


def test_a_slide_never_turns_a_semilandmark_triangle_over():
    # A 3 x 3 grid on a plane, its centre pushed 1.5 spacings to the right (past its right
    # neighbours, which move 0.1): unguarded, its triangles turn over (a patient far from the
    # mean folded 2-6% of a mandible's triangles in 5 iterations). Guarded, the centre's move
    # and its right neighbours' are halved until none turns; the vertices of no turned triangle
    # (0, 2, 6: on the left, and corners whose only triangles stay) move in full.
    from o3dreg.shape.sliding import _projected

    corners = np.array([[-10.0, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]])
    query = SurfaceDistanceQuery(corners, np.array([[0, 1, 2], [0, 2, 3]]))
    grid = np.array([[x, y, 0.0] for y in (-1, 0, 1) for x in (-1, 0, 1)])
    faces = []
    for r in range(2):
        for c in range(2):
            a = 3 * r + c
            faces += [[a, a + 1, a + 4], [a, a + 4, a + 3]]
    faces = np.array(faces)
    step = np.tile([0.1, 0.0, 0.0], (9, 1))
    step[4] = [1.5, 0.0, 0.0]
    assert turned_triangles(grid, grid + step, faces).any()  # the unguarded move folds
    moved = _projected(query, grid, step, grid, faces)
    assert not turned_triangles(grid, moved, faces).any()
    np.testing.assert_allclose(moved[[0, 2, 6]], grid[[0, 2, 6]] + step[[0, 2, 6]])
    assert 0.1 < moved[4, 0] < 1.1  # held back, not dropped


def test_guarded_sliding_keeps_the_meshes_unfolded(registered):
    tf, targets, shapes = registered
    result = slide_semilandmarks(shapes, targets, max_iteration=4, faces=tf)
    for given, slid in zip(shapes, result.shapes):
        assert ((face_cross(slid, tf) * face_cross(given, tf)).sum(axis=1) > 0).all()
    # The first distance is that of the shapes given, the last that of the slid ones.
    before = generalized_procrustes(shapes).residuals.mean()
    assert result.procrustes_distances[0] == pytest.approx(before)
    assert len(result.procrustes_distances) == result.iterations + 1


def test_the_default_criterion_is_bending_energy(registered):
    # As in geomorph's gpagen and Morpho's slider3d; the Procrustes criterion bunches points
    # when iterated (docs/shape-model.md, benchmarks/bench_sliding.py).
    _, targets, shapes = registered
    assert slide_semilandmarks(shapes, targets, max_iteration=1).criterion == "bending"


@pytest.mark.parametrize("planar", [False, True])
def test_the_bending_matrix_gives_affine_maps_no_energy(planar):
    # Be is the upper-left block of L^-1 for the kernel U(r) = r: Be P = 0 (an affine map bends
    # nothing), Be symmetric and negative semidefinite. Points in a plane make L singular: the
    # pseudo-inverse takes over and the same holds.
    from o3dreg.shape.sliding import _bending_matrix

    points = np.random.default_rng(3).normal(size=(60, 3)) * 20
    if planar:
        points[:, 2] = 0.0
    be = _bending_matrix(points)
    affine = np.hstack([np.ones((60, 1)), points])
    scale = np.abs(be).max()
    np.testing.assert_allclose(be @ affine, 0.0, atol=1e-9 * scale * 20)
    np.testing.assert_allclose(be, be.T, atol=1e-12 * scale)
    assert np.linalg.eigvalsh(be).max() < 1e-9 * scale


def test_four_semilandmarks_do_not_slide():
    # An affine map carries any 4 points anywhere: no slide of them bends, so none is made.
    # (L^-1 is rounding noise there, which the ridge would blow up to moves of twice the radius.)
    rng = np.random.default_rng(4)
    _, targets, truths, _, _ = population(3, seed=4, template_resolution=8)
    picks = [0, 30, 60, 90]
    shapes = [t[picks] + rng.normal(size=(4, 3)) * 0.05 for t in truths]
    result = slide_semilandmarks(shapes, targets)
    for (v, f), given, slid in zip(targets, shapes, result.shapes):
        # Only the projection onto the surface, whose distance is the noise added (~0.05).
        np.testing.assert_allclose(slid, SurfaceDistanceQuery(v, f).closest(given)[2], atol=1e-9)
    assert result.success and result.iterations == 1


@pytest.mark.parametrize(("scale", "offset"), [(1.0, 1e6), (1.0, 1e3), (1e-6, 0.0), (1e4, 0.0)])
def test_the_bending_step_does_not_depend_on_the_origin_or_the_unit(scale, offset):
    # On a sphere every rotation slides all points along their tangent planes at no energy: the
    # step's ridge amplifies any error along those directions ~1e9 times. A patient whose origin
    # is 1e6 away, or a model in micrometres or metres, must get the same slide, scaled.
    from o3dreg.shape.sliding import _bending_matrix, _bending_step, _tangent_bases

    rng = np.random.default_rng(5)
    mean = rng.normal(size=(200, 3))
    mean *= 10.0 / np.linalg.norm(mean, axis=1, keepdims=True)
    shape = mean + rng.normal(size=mean.shape) * 0.3
    t1, t2 = _tangent_bases(mean / 10.0)
    free = np.ones(200, dtype=bool)
    reference = _bending_step(shape, t1, t2, _bending_matrix(mean), free)
    step = _bending_step(shape * scale + offset, t1, t2, _bending_matrix(mean * scale), free)
    # 1e-6 of the radius: far below any slide that matters, far above rounding.
    np.testing.assert_allclose(step / scale, reference, atol=1e-5)


def test_bending_on_too_many_points_is_refused_before_any_work(monkeypatch):
    # The dense solve takes about 90 n^2 bytes: past BENDING_MAX_POINTS the call is refused
    # with its size and the cures, before any sliding.
    from o3dreg.shape import sliding

    monkeypatch.setattr(sliding, "BENDING_MAX_POINTS", 10)
    shapes = np.zeros((2, 11, 3))
    surface = (np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(
        ValueError, match=r"`criterion`: .* all 11 points .* at most 10: .*'procrustes'"
    ):
        slide_semilandmarks(shapes + np.arange(11)[None, :, None], [surface, surface])
    with pytest.raises(ValueError, match=r"`slide`: .* do without sliding"):
        sliding.check_bending_size(11, name="slide")
    sliding.check_bending_size(11, criterion="procrustes")  # no dense solve: any size
