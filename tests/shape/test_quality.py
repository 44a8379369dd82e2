"""Model quality: compactness, generalisation, specificity, tables and plots."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers import population

from o3dreg import build_shape_model, compactness, generalization, specificity


@pytest.fixture(scope="module")
def data():
    (_tv, tf), _, truths, _, _ = population(8, seed=3)
    return tf, truths


def test_compactness_is_cumulative_variance(data):
    tf, truths = data
    model = build_shape_model(truths, tf)
    curve = compactness(model)
    np.testing.assert_allclose(curve.values, model.cumulative_variance_ratio)
    assert "cumulative %" in curve.table()
    # A deterministic measure: no spread column of zeros that would read as "not measured".
    assert "sd" not in curve.table().splitlines()[1]
    assert all(len(line.split()) == 2 for line in curve.table().splitlines()[2:])


def test_generalization_of_a_three_mode_population(data):
    tf, truths = data
    curve = generalization(truths, tf)
    assert list(curve.modes) == list(range(7))
    # Exact 3-mode data: a left-out shape is reconstructed by 3 modes up to the second-order
    # pose effects of Procrustes (< 5 % of the mean-only error).
    assert curve.values[3] < 0.05 * curve.values[0]
    assert np.all(np.diff(curve.values) < 1e-9)


def test_generalization_with_a_repeated_shape(data):
    # Leaving out the third shape leaves two copies of one: that model is the mean alone.
    tf, truths = data
    curve = generalization([truths[0], truths[0], truths[1]], tf)
    assert list(curve.modes) == [0, 1]
    assert np.all(np.isfinite(curve.values)) and curve.values[1] <= curve.values[0]


def test_specificity_is_seeded_and_small_for_exact_model(data, tmp_path):
    tf, truths = data
    model = build_shape_model(truths, tf)
    a = specificity(model, truths, number_of_samples=20, seed=4, max_modes=3)
    b = specificity(model, truths, number_of_samples=20, seed=4, max_modes=3)
    np.testing.assert_array_equal(a.values, b.values)
    assert a.values.shape == (3,) and np.all(a.values > 0)
    path = a.plot(tmp_path / "spec.png")
    assert open(path, "rb").read(8) == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(OSError, match="exists"):
        a.plot(tmp_path / "spec.png")
    assert a.as_dict()["name"] == "specificity"


def test_quality_bad_input(data):
    tf, truths = data
    with pytest.raises(ValueError, match="at least 3"):
        generalization(truths[:2], tf)
    with pytest.raises(TypeError, match="ShapeModel"):
        compactness(truths)
    model = build_shape_model(truths, tf)
    with pytest.raises(ValueError, match="points"):
        specificity(model, truths[:, :-1])
    with pytest.raises(ValueError, match="`seed` must be a finite integer >= 0"):
        specificity(model, truths, seed=-3)
    # The generalisation curve starts at the mean alone (0 modes).
    assert "modes 0.." in repr(generalization(truths, tf, max_modes=2))
