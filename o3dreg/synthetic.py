"""Known smooth deformations of space, for tests, examples and benchmarks.

A :class:`SmoothWarp` is a ground truth: applied to a mesh, it says where every point went, so a
registration's correspondence error can be measured exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._validation import as_points, check_positive

__all__ = ["SmoothWarp"]


@dataclass(frozen=True, eq=False)
class SmoothWarp:
    """``phi(x) = x + sum_j a_j exp(-|x - c_j|^2 / (2 s^2))``: a sum of Gaussian bumps.

    Attributes
    ----------
    centres : (k, 3) ndarray
    amplitudes : (k, 3) ndarray
        Displacement of each bump at its centre, in the input's units.
    width : float
        Gaussian standard deviation ``s``.

    Notes
    -----
    The map is one-to-one when ``max |a_j| / s`` stays well below ``exp(1/2) ~ 1.65`` (the
    Jacobian of one bump is ``I - a (x - c)^T / s^2 g``, whose determinant is at least
    ``1 - |a| / (s sqrt(e))``); :meth:`random` keeps it below 0.5.
    """

    centres: np.ndarray
    amplitudes: np.ndarray
    width: float
    _unused: Any = field(default=None, repr=False)

    @classmethod
    def random(
        cls,
        points: Any,
        *,
        magnitude: float = 0.05,
        number_of_bumps: int = 8,
        width: float = 0.3,
        seed: int = 0,
    ) -> SmoothWarp:
        """A random warp scaled to the extent of ``points``.

        Parameters
        ----------
        points : (n, 3) array_like
            Defines the scale: bump centres are drawn among these points.
        magnitude : float
            Bump amplitude as a fraction of the bounding-box diagonal (0.02 small, 0.05 medium,
            0.1 large).
        number_of_bumps : int
        width : float
            Gaussian width as a fraction of the diagonal.
        seed : int
            Seed of ``numpy.random.default_rng``; the same seed gives the same warp.
        """
        pts = as_points(points, "points")
        check_positive(magnitude, "magnitude")
        check_positive(number_of_bumps, "number_of_bumps", integer=True)
        check_positive(width, "width")
        rng = np.random.default_rng(seed)
        diagonal = float(np.linalg.norm(np.ptp(pts, axis=0)))
        centres = pts[rng.choice(pts.shape[0], number_of_bumps, replace=False)]
        directions = rng.normal(size=(number_of_bumps, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        amplitudes = directions * magnitude * diagonal
        return cls(centres, amplitudes, width * diagonal)

    def __call__(self, points: Any) -> np.ndarray:
        pts = as_points(points, "points", allow_empty=True)
        d2 = ((pts[:, None, :] - self.centres[None, :, :]) ** 2).sum(axis=2)
        g = np.exp(-d2 / (2.0 * self.width**2))
        return pts + g @ self.amplitudes
