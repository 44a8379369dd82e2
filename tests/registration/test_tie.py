"""A near tie of the rigid start, settled by the elastic registrations from both poses."""

from types import SimpleNamespace

import numpy as np
import pytest
from _helpers import warped_blob

import o3dreg
from o3dreg.app.synthetic import synthetic_form
from o3dreg.registration.rigid import AMBIGUOUS_START, RigidRegistrationResult
from o3dreg.registration.tie import (
    TIE_AGREEMENT,
    TIE_CLOSE_FIT,
    TIE_FIT_RATIO,
    local_turn,
    settle_tie,
    symmetric_fit,
)

AMBIGUOUS = RigidRegistrationResult(
    score=4.0,
    runner_up_score=4.2,
    runner_up_transformation=np.eye(4),
    candidates=14,
    warnings=(f"{AMBIGUOUS_START}: two distinct poses fit almost equally well", "scale: other"),
    ambiguous=True,
)


def _registration(fit, offset):
    """A stand-in for a registration: its symmetric distance ``fit`` (both directions alike)
    and 100 vertices moved by ``offset``."""
    distances = SimpleNamespace(source_to_target_mean=fit, target_to_source_mean=fit)
    return SimpleNamespace(distances=distances, vertices=np.zeros((100, 3)) + offset)


def test_symmetric_fit_is_the_mean_of_both_directions():
    distances = SimpleNamespace(source_to_target_mean=1.0, target_to_source_mean=3.0)
    assert symmetric_fit(SimpleNamespace(distances=distances)) == 2.0


@pytest.mark.parametrize(
    ("fits", "turns", "apart", "kept", "settled"),
    [
        ((1.0, 1.0), (3.0, 3.0), 0.0, 0, "winner"),  # both ended alike: the tie is moot
        ((1.0, 5.0), (50.0, 50.0), 0.5 * TIE_AGREEMENT, 0, "winner"),  # alike, however turned
        ((1.0, 0.99 * TIE_FIT_RATIO), (3.0, 3.0), 0.5, 0, None),  # not clearly closer
        ((1.0, 1.01 * TIE_FIT_RATIO), (3.0, 3.0), 0.5, 0, "winner"),
        ((1.01 * TIE_FIT_RATIO, 1.0), (3.0, 3.0), 0.5, 1, "runner-up"),
        ((1.0, 3.0), (50.0, 3.0), 0.5, 0, None),  # closer, but turning parts apart
        ((3.0, 1.0), (3.0, 50.0), 0.5, 0, None),
        ((1.01, 3.0), (3.0, 3.0), 0.5, 0, None),  # closer, but not close to the target
    ],
)
def test_which_registration_settles_the_tie(fits, turns, apart, kept, settled):
    diagonal = 1.0 / TIE_CLOSE_FIT  # a fit of 1 is as loose as a settling fit may be
    pair = (_registration(fits[0], 0.0), _registration(fits[1], [apart * diagonal, 0.0, 0.0]))
    index, start = settle_tie(AMBIGUOUS, pair, turns, diagonal)
    assert index == kept and start.tie_kept == settled
    assert start.tie_fits == fits
    assert start.ambiguous == (settled is None)
    # Only the ambiguity goes; the scores stay the rigid search's.
    assert (start.score, start.runner_up_score) == (4.0, 4.2)
    assert "scale: other" in start.warnings
    assert any(w.startswith(AMBIGUOUS_START) for w in start.warnings) == (settled is None)


def test_on_a_partial_target_only_the_vertices_both_support_must_agree():
    # Two registrations that place the 80 vertices with data alike and the 20 without 10% of
    # the diagonal apart: the tie is settled (the rest hangs where no data say). Where the two
    # support different vertices, every vertex counts and they stay apart.
    diagonal = 1.0 / TIE_CLOSE_FIT
    first, second = _registration(5.0, 0.0), _registration(5.0, 0.0)
    second.vertices[80:] += [0.1 * diagonal, 0.0, 0.0]
    first.supported = second.supported = np.arange(100) < 80
    index, start = settle_tie(AMBIGUOUS, (first, second), (3.0, 3.0), diagonal)
    assert (index, start.tie_kept) == (0, "winner")
    second.supported = np.arange(100) >= 20  # 60 shared of 80 each: too few to stand for them
    assert settle_tie(AMBIGUOUS, (first, second), (3.0, 3.0), diagonal)[1].ambiguous


def _turn(degrees, axis=(0.0, 0.0, 1.0)):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis)).as_matrix()


class _Map:
    """A map of space given by its Jacobian at each point (what local_turn reads)."""

    def __init__(self, jacobians):
        self.jacobians = jacobians

    def jacobian(self, points):
        return self.jacobians


def test_a_map_turning_everything_alike_turns_no_part():
    # The whole template turned by 40 degrees (a start that far off, corrected by the levels):
    # every local rotation is the overall one, so no part turns against another.
    points = np.random.default_rng(0).normal(size=(200, 3))
    rotation = _turn(40.0, (1.0, 2.0, 3.0) / np.sqrt(14.0))
    turn = local_turn(_Map(np.repeat(rotation[None], 200, axis=0)), points, points @ rotation.T)
    assert turn == pytest.approx(0.0, abs=1e-5)


def test_two_halves_turned_apart_turn_by_their_angle():
    # Two ends of a bar twisted by +30 and -30 degrees about its axis (z): the overall rotation
    # is none, each part turns 30 degrees against it.
    # A grid symmetric in x, y and z: the least-squares overall rotation is exactly none.
    grid = np.arange(-2.0, 3.0)
    x, y, z = np.meshgrid(grid, grid, np.r_[-5.0:0.0, 1.0:6.0], indexing="ij")
    points = np.column_stack([x.ravel(), y.ravel(), 4.0 * z.ravel()])
    up = points[:, 2] > 0
    rotations = np.where(up[:, None, None], _turn(30.0), _turn(-30.0))
    moved = np.einsum("kij,kj->ki", rotations, points)
    assert local_turn(_Map(rotations), points, moved) == pytest.approx(30.0, abs=1e-6)


def test_a_stretched_target_is_told_apart_by_the_levels():
    # The blob 1.4 times longer along z: no rigid pose removes the stretch, and a wrong pose
    # scores within 1.2 of the right one (measured 5.48 against 4.99). From the right pose the
    # levels fit the target 2.6 times closer than from the wrong one, without turning it round:
    # a right registration, 'ok'.
    template, (vt, ft), truth = warped_blob()
    centre = vt.mean(axis=0)
    stretch = np.array([1.0, 1.0, 1.4])
    target = ((vt - centre) * stretch + centre, ft)
    truth = (truth - centre) * stretch + centre
    assert o3dreg.registration_rigid(template, target).ambiguous
    result = o3dreg.registration_elastic(template, target)
    diagonal = np.linalg.norm(np.ptp(target[0], axis=0))
    error = np.linalg.norm(result.vertices - truth, axis=1).mean()
    assert error < 0.01 * diagonal  # right (measured 0.26%)
    start = result.rigid_start
    assert start.tie_kept == "winner" and not start.ambiguous
    assert start.tie_fits[1] > TIE_FIT_RATIO * start.tie_fits[0]
    assert result.status == "ok", result.warnings


def test_a_symmetric_shape_stays_ambiguous():
    # A cube: the registrations from two of its 24 rotations fit it equally well and end apart
    # (each vertex on another corner): the tie is the shape's, and the warning stays.
    from scipy.spatial.transform import Rotation

    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("zx", [45.0, 30.0], degrees=True).as_matrix()
    target = synthetic_form("cube", 3000)
    target.transform(turn)
    result = o3dreg.registration_elastic(
        synthetic_form("cube", 600), target, levels=[o3dreg.ElasticLevel(2)]
    )
    start = result.rigid_start
    assert start.ambiguous and start.tie_kept is None and start.tie_fits is not None
    assert max(start.tie_fits) < TIE_FIT_RATIO * min(start.tie_fits)
    assert result.status == "suspect"
    assert any(w.startswith(AMBIGUOUS_START) for w in result.warnings)
