"""How far the template points have moved near each target point: a bound, per region of
space, on the moves that can change a target point's nearest template point."""

from __future__ import annotations

import numpy as np

from .._geometry import bounds

#: Cells per axis of the grid the moves are summed on, at most (a grid of at most 33^3 cells:
#: summing and spreading the moves of one step costs a fraction of a millisecond).
MAX_CELLS_PER_AXIS = 32


class LocalMoves:
    """The template's moves summed per region of space, step after step.

    Space is cut into cubes of side ``side``; each step adds to every cube the largest move of a
    template point that ended the step in that cube or in one of its 26 neighbours. For a target
    point ``t`` in cube ``c``, every point outside the 27 cubes around ``c`` is at least
    ``side`` away from ``t``; a point inside them now was there since a time it was at distance
    ``r`` from ``t``, or stepped in from at least ``side`` away, and each of its steps since
    ended inside and was added to cube ``c``. So since any time, no template point came nearer
    to ``t`` than ``min(r, side)`` (``r`` its distance then) less the growth of cube ``c``'s sum
    (:meth:`since`).

    Parameters
    ----------
    target_points : (m, 3) ndarray
        The fixed points whose neighbourhoods are watched.
    template_points : (n, 3) ndarray
        The template points' positions now (with ``target_points``, the extent of the grid).
    side : float
        The cubes' side (enlarged so that at most :data:`MAX_CELLS_PER_AXIS` span the points).
    """

    def __init__(self, target_points: np.ndarray, template_points: np.ndarray, side: float) -> None:
        lo_t, hi_t = bounds(target_points)
        lo_y, hi_y = bounds(template_points)
        self.origin = np.minimum(lo_t, lo_y)
        extent = float((np.maximum(hi_t, hi_y) - self.origin).max())
        self.side = max(float(side), extent / MAX_CELLS_PER_AXIS) or 1.0
        n = int(np.floor(extent / self.side)) + 1
        self.shape = (n, n, n)
        self._target_cells = self.cells(target_points)
        self._total = np.zeros(int(np.prod(self.shape)))

    def cells(self, points: np.ndarray) -> np.ndarray:
        """The flat cube index of each point; points beyond the grid go to its nearest cube
        (the distance from a point inside the grid to a cube it is clamped into is no larger
        than to the point itself: the bound stays a bound)."""
        keys = np.floor((points - self.origin) / self.side).astype(np.int64)
        np.clip(keys, 0, self.shape[0] - 1, out=keys)
        n = self.shape[0]
        return (keys[:, 0] * n + keys[:, 1]) * n + keys[:, 2]

    def step(self, moved: np.ndarray, length: np.ndarray) -> None:
        """Record a step of the template points to ``moved``, of ``length`` each."""
        largest = np.zeros(self._total.size)
        np.maximum.at(largest, self.cells(moved), length)
        self._total += _spread(largest.reshape(self.shape)).ravel()

    def marks(self, which: np.ndarray | slice) -> np.ndarray:
        """The sums of the cubes of the target points ``which`` now (to pass to :meth:`since`
        later)."""
        return self._total.take(self._target_cells[which])

    def since(self, marks: np.ndarray) -> np.ndarray:
        """How much nearer than at ``marks`` (:meth:`marks` of every target point) any template
        point may have come to each target point, beyond those already within ``side``."""
        return self._total.take(self._target_cells) - marks


def _spread(grid: np.ndarray) -> np.ndarray:
    """The largest value of each cube and its 26 neighbours (a 3 x 3 x 3 maximum, one axis at a
    time)."""
    out = grid
    for axis in range(3):
        a = np.moveaxis(out, axis, 0)
        b = a.copy()
        np.maximum(b[1:], a[:-1], out=b[1:])
        np.maximum(b[:-1], a[1:], out=b[:-1])
        out = np.moveaxis(b, 0, axis)
    return out
