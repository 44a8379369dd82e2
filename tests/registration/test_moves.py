"""The template's moves summed per region of space (``LocalMoves``): the bound the barycentre
term's searches rest on."""

from __future__ import annotations

import numpy as np
import pytest

from o3dreg.registration._moves import MAX_CELLS_PER_AXIS, LocalMoves


def _distances(targets: np.ndarray, sites: np.ndarray) -> np.ndarray:
    return np.sqrt(((targets[:, None, :] - sites[None, :, :]) ** 2).sum(axis=2))


@pytest.mark.parametrize("side", [0.5, 3.0, 40.0])
def test_no_template_point_comes_nearer_than_the_bound(side):
    # The claim of LocalMoves: since a mark, no template point came nearer to a target point
    # than min(its distance then, side) less the growth of that target point's sum. Checked on
    # every (target, template) pair along random walks of mixed step sizes, one point wandering
    # far outside the grid and back (clamped into the border cubes), from marks taken at
    # several times. Exact but for rounding in the sums (1e-9 of the mm-sized distances).
    rng = np.random.default_rng(11)
    targets = rng.uniform(-10.0, 10.0, (300, 3))
    y = rng.uniform(-10.0, 10.0, (80, 3))
    moves = LocalMoves(targets, y, side)
    marks, then = [], []
    for step in range(30):
        if step % 7 == 0:
            marks.append(moves.marks(slice(None)))
            then.append(_distances(targets, y))
        move = rng.normal(size=y.shape) * (2.0 if step % 5 == 0 else 0.2)
        move[0] = [25.0, 0.0, 0.0] if step < 15 else [-25.0, 0.0, 0.0]
        y = y + move
        moves.step(y, np.linalg.norm(move, axis=1))
        now = _distances(targets, y)
        for mark, before in zip(marks, then):
            bound = np.minimum(before, moves.side) - moves.since(mark)[:, None]
            assert np.all(now >= bound - 1e-9)


def test_the_bound_is_tight_where_nothing_moved():
    # Steps of the points on one side add nothing to the cubes two or more away from them: the
    # target points there see no growth at all.
    targets = np.array([[0.5, 0.5, 0.5], [9.5, 9.5, 9.5]])
    y = np.array([[0.2, 0.2, 0.2], [9.0, 9.0, 9.0]])
    moves = LocalMoves(targets, y, 1.0)
    mark = moves.marks(slice(None))
    moves.step(y + [[0.3, 0.0, 0.0], [0.0, 0.0, 0.0]], np.array([0.3, 0.0]))
    np.testing.assert_allclose(moves.since(mark), [0.3, 0.0])


def test_the_grid_is_bounded():
    # A side far below the extent is enlarged: at most MAX_CELLS_PER_AXIS cubes span the points.
    points = np.array([[0.0, 0.0, 0.0], [100.0, 50.0, 10.0]])
    moves = LocalMoves(points, points, 0.01)
    assert moves.side == pytest.approx(100.0 / MAX_CELLS_PER_AXIS)
    assert moves.shape == (MAX_CELLS_PER_AXIS + 1,) * 3
    assert LocalMoves(points, points, 30.0).side == 30.0
