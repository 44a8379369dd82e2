"""Ordinary and generalised Procrustes: recovery, invariance, no reflections, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from o3dreg import generalized_procrustes, procrustes_transform


def _shape(n: int = 60, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3)) * [30.0, 20.0, 10.0]


def _similarity(seed: int, scale: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = scale * Rotation.random(random_state=seed).as_matrix()
    t[:3, 3] = rng.normal(size=3) * 50
    return t


def _apply(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ t[:3, :3].T + t[:3, 3]


@pytest.mark.parametrize("scaling", [False, True])
def test_procrustes_transform_recovers_known_motion(scaling):
    x = _shape()
    truth = _similarity(3, scale=1.7 if scaling else 1.0)
    y = _apply(truth, x)
    t = procrustes_transform(x, y, scaling=scaling)
    np.testing.assert_allclose(t, truth, atol=1e-9)


def test_procrustes_transform_never_reflects():
    x = _shape()
    mirrored = x * [-1.0, 1.0, 1.0]
    t = procrustes_transform(x, mirrored)
    assert np.linalg.det(t[:3, :3]) > 0
    np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)


def test_gpa_recovers_rotations_of_one_shape():
    x = _shape()
    truths = [_similarity(s) for s in range(5)]
    shapes = np.stack([_apply(t, x) for t in truths])
    before = shapes.copy()
    result = generalized_procrustes(shapes)
    np.testing.assert_array_equal(shapes, before)  # input untouched
    assert result.success
    # Every aligned copy coincides with the mean (they are one shape in 5 poses).
    np.testing.assert_allclose(result.residuals, 0.0, atol=1e-9)
    # transformations[i] undoes pose i up to one common motion G: T_i P_i = G for all i.
    common = [t @ p for t, p in zip(result.transformations, truths)]
    for g in common[1:]:
        np.testing.assert_allclose(g, common[0], atol=1e-9)
    for t in result.transformations:
        assert np.linalg.det(t[:3, :3]) > 0


@pytest.mark.parametrize("scaling", [False, True])
def test_gpa_invariant_to_random_similarities(scaling):
    rng = np.random.default_rng(1)
    base = _shape()
    shapes = np.stack([base + rng.normal(size=base.shape) for _ in range(6)])
    ref = generalized_procrustes(shapes, scaling=scaling)
    moved = np.stack(
        [
            _apply(_similarity(10 + i, scale=(0.5 + i / 4) if scaling else 1.0), s)
            for i, s in enumerate(shapes)
        ]
    )
    again = generalized_procrustes(moved, scaling=scaling)
    # The aligned configurations agree up to one global rigid motion (similarity: and one global
    # scale, since the mean's size is the inputs' mean size): compare all pairwise distances
    # within the mean (1e-6 relative: iterative convergence at tolerance 1e-10).
    d1 = np.linalg.norm(ref.mean[:, None] - ref.mean[None], axis=2)
    d2 = np.linalg.norm(again.mean[:, None] - again.mean[None], axis=2)
    r1, r2 = ref.residuals, again.residuals
    if scaling:
        d1, d2 = d1 / np.linalg.norm(d1), d2 / np.linalg.norm(d2)
        r1, r2 = r1 / np.linalg.norm(ref.mean), r2 / np.linalg.norm(again.mean)
    np.testing.assert_allclose(d2, d1, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(r2, r1, rtol=1e-6)


def test_gpa_rigid_keeps_size_and_similarity_normalises_it():
    x = _shape()
    shapes = np.stack([x, 2.0 * x])
    rigid = generalized_procrustes(shapes)
    assert rigid.residuals.max() > 1.0  # sizes kept: the two cannot coincide
    similar = generalized_procrustes(shapes, scaling=True)
    np.testing.assert_allclose(similar.residuals, 0.0, atol=1e-9)


def test_gpa_no_reflection_even_for_mirror_images():
    x = _shape()
    result = generalized_procrustes([x, x * [1.0, -1.0, 1.0], x])
    assert np.all(np.linalg.det(result.transformations[:, :3, :3]) > 0)
    assert result.residuals[1] > 1.0


def test_gpa_reports_non_convergence():
    rng = np.random.default_rng(0)
    shapes = [rng.normal(size=(30, 3)) for _ in range(4)]
    result = generalized_procrustes(shapes, max_iteration=1, tolerance=0.0)
    assert not result.success and "did not converge" in result.message


def test_procrustes_bad_input():
    x = _shape()
    with pytest.raises(ValueError, match="at least 2 shapes"):
        generalized_procrustes([x])
    with pytest.raises(ValueError, match="same number of points"):
        generalized_procrustes([x, x[:-1]])
    with pytest.raises(TypeError, match="sequence"):
        generalized_procrustes("shapes")
    with pytest.raises(ValueError, match="same shape"):
        procrustes_transform(x, x[:-1])
    with pytest.raises(TypeError, match="scaling"):
        procrustes_transform(x, x, scaling="yes")
    # A NumPy bool is a bool.
    np.testing.assert_allclose(procrustes_transform(x, x, scaling=np.True_), np.eye(4), atol=1e-12)


def test_gpa_refuses_a_shape_with_all_its_points_at_one_place():
    # With scaling, such a shape (first, as the mean's start) would shrink every shape to a point
    # and report success.
    x = _shape()
    point = np.repeat(x.mean(axis=0, keepdims=True), x.shape[0], axis=0)
    for scaling in (False, True):
        with pytest.raises(ValueError, match=r"got shape\(s\) \[0\] with all their points at one"):
            generalized_procrustes([point, x, x + 1.0], scaling=scaling)
