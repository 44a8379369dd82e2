"""The public strategies (losses, correspondence checkers, distance terms) against one contract
each, and their translation to and from :class:`~o3dreg.DistanceEstimation`.

A new loss, checker or term is one class in its module plus one entry in a list here. The
residuals and Jacobians of the terms have their own contract in test_terms.py.
"""

import dataclasses

import numpy as np
import pytest

import o3dreg
from o3dreg import (
    Barycentre,
    BoundaryChecker,
    CauchyLoss,
    DistanceChecker,
    DistanceEstimation,
    HuberLoss,
    L2Loss,
    NormalAngleChecker,
    PointToSurface,
    TukeyLoss,
)
from o3dreg.registration.checkers import CheckerContext
from o3dreg.registration.distance import SurfaceDistanceQuery

LOSSES = [L2Loss(), HuberLoss(), CauchyLoss(), TukeyLoss(), CauchyLoss(scale=2.0)]
CHECKERS = [BoundaryChecker(), NormalAngleChecker(60.0), DistanceChecker(2.0)]
TERMS = [PointToSurface(), Barycentre(weight=0.5, correction=True)]


@pytest.mark.parametrize("loss", LOSSES, ids=repr)
class TestLossContract:
    r = np.concatenate([-np.linspace(0.0, 10.0, 201)[::-1], np.linspace(0.0, 10.0, 201)])

    def test_weights_lie_in_0_1_and_are_1_at_0(self, loss):
        w = loss.weight(self.r, 1.5)
        assert w.shape == self.r.shape
        assert np.all((w >= 0.0) & (w <= 1.0))
        assert loss.weight(np.zeros(1), 1.5)[0] == 1.0

    def test_weights_are_even_and_fall_with_the_residual(self, loss):
        w = loss.weight(self.r, 1.5)
        np.testing.assert_array_equal(w, w[::-1])
        half = w[self.r >= 0]
        assert np.all(np.diff(half) <= 0.0)

    def test_weights_scale_with_sigma(self, loss):
        # Residuals in other units, with the scale in the same units: the same weights.
        np.testing.assert_allclose(loss.weight(3.0 * self.r, 4.5), loss.weight(self.r, 1.5))

    def test_a_value_type(self, loss):
        assert "\n" not in repr(loss)
        with pytest.raises(dataclasses.FrozenInstanceError):
            loss.scale = 1.0  # type: ignore[misc]
        assert DistanceEstimation.compose(loss=loss).robust_loss == loss


@pytest.fixture(scope="module")
def square():
    # A unit square of two triangles (open boundary), normals +z.
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    return SurfaceDistanceQuery(v, np.array([[0, 1, 2], [0, 2, 3]]))


@pytest.mark.parametrize("checker", CHECKERS, ids=repr)
class TestCheckerContract:
    def test_a_mask_per_level_that_keeps_a_good_match(self, checker, square):
        pts = np.array([[0.5, 0.5, 0.01], [0.25, 0.75, -0.01]])
        normals = np.array([[0.0, 0.0, 1.0]] * 2)
        mask = checker.bind(CheckerContext(square, True, normals, sigma=1.0))
        assert mask is not None
        keep = mask.check(pts, *square.closest(pts))
        assert keep.dtype == bool and keep.shape == (2,)
        assert keep.all()

    def test_a_value_type(self, checker):
        assert "\n" not in repr(checker)
        assert hash(checker) == hash(dataclasses.replace(checker))
        assert DistanceEstimation.compose(checkers=[checker]).checkers == (checker,)


@pytest.mark.parametrize("term", TERMS, ids=repr)
def test_terms_are_value_types_the_estimation_holds(term):
    assert "\n" not in repr(term)
    terms = [PointToSurface()] if isinstance(term, PointToSurface) else [PointToSurface(), term]
    assert DistanceEstimation.compose(terms=terms).terms == tuple(terms)


def test_the_flags_and_the_strategies_are_one_estimation():
    assert DistanceEstimation.compose() == DistanceEstimation()
    assert DistanceEstimation().robust_loss == CauchyLoss()
    assert DistanceEstimation().checkers == (BoundaryChecker(), NormalAngleChecker(90.0))
    paper = DistanceEstimation.paper()
    assert paper == DistanceEstimation.compose(
        terms=[PointToSurface(), Barycentre(weighting="uniform", skip_covered=False)],
        loss=L2Loss(),
        checkers=[],
        min_target_component=None,
    )
    assert DistanceEstimation(symmetric=False).terms == (PointToSurface(),)


def test_compose_refuses_what_the_cost_cannot_hold():
    with pytest.raises(ValueError, match="`terms`"):
        DistanceEstimation.compose(terms=[Barycentre()])
    with pytest.raises(ValueError, match="`checkers`"):
        DistanceEstimation.compose(checkers=[DistanceChecker(2.0), DistanceChecker(3.0)])
    with pytest.raises(TypeError, match="`loss`"):
        DistanceEstimation.compose(loss="cauchy")

    # The settings keep a loss by name and checkers by parameters: a subclass would silently
    # become the library's class (its own weights and masks lost).
    class Harder(CauchyLoss):
        def _weights(self, z):
            return np.where(z < 1.0, 1.0, 0.0)

    class Closer(DistanceChecker):
        pass

    with pytest.raises(TypeError, match="`loss` must be one of the library's losses .* Harder"):
        DistanceEstimation.compose(loss=Harder())
    with pytest.raises(ValueError, match="the library's classes"):
        DistanceEstimation.compose(checkers=[Closer(2.0)])
    with pytest.raises(ValueError, match="`max_angle`"):
        NormalAngleChecker(200.0)
    with pytest.raises(ValueError, match="`scale`"):
        CauchyLoss(scale=-1.0)


def test_every_strategy_is_public():
    for value in (*LOSSES, *CHECKERS, *TERMS):
        assert type(value).__name__ in o3dreg.__all__
