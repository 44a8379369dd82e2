"""Robust kernels and correspondence rejection of one level, as small objects.

The counterparts of Open3D's ``RobustKernel`` (a per-residual weight ``w(r) = rho'(r) / r`` for
iteratively reweighted least squares) and ``CorrespondenceChecker`` (a 0/1 verdict on each
correspondence). :class:`~o3dreg.registration._cost.LevelProblem` multiplies a kernel's weights
by the product of its checkers' masks; each piece here is tested alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .distance import SurfaceDistanceQuery

#: Tuning constants of the robust losses (95% efficiency under Gaussian noise), in units of the
#: robust scale ``sigma``.
LOSS_CONSTANTS = {"linear": np.inf, "huber": 1.345, "cauchy": 2.3849, "tukey": 4.6851}


@dataclass(frozen=True)
class RobustKernel:
    """IRLS weights ``w(r) = rho'(r) / r`` of the loss ``loss`` with threshold ``threshold``.

    ``huber``: ``1`` if ``|r| <= c`` else ``c / |r|``; ``cauchy``: ``1 / (1 + (r / c)^2)``;
    ``tukey``: ``(1 - (r / c)^2)^2`` if ``|r| < c`` else ``0``; ``linear`` (no kernel): ``1``.
    """

    loss: str = "linear"
    threshold: float = np.inf

    def __post_init__(self) -> None:
        if self.loss not in LOSS_CONSTANTS:
            raise ValueError(f"`loss` must be one of {sorted(LOSS_CONSTANTS)}, got {self.loss!r}")

    @classmethod
    def scaled(cls, loss: str, sigma: float) -> RobustKernel:
        """The kernel of ``loss`` at its tuning constant times the robust scale ``sigma``."""
        return cls(loss, LOSS_CONSTANTS[loss] * sigma)

    def weight(self, r: np.ndarray) -> np.ndarray:
        """Weights of the residuals ``r`` (same shape)."""
        if self.loss == "linear" or r.size == 0:
            return np.ones(r.shape)
        z = np.abs(r) / self.threshold
        if self.loss == "huber":
            return 1.0 / np.maximum(z, 1.0)
        if self.loss == "cauchy":
            return 1.0 / (1.0 + z * z)
        return np.where(z < 1.0, (1.0 - z * z) ** 2, 0.0)


def robust_weights(r: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights of the residuals ``r`` for the threshold ``c`` (see :class:`RobustKernel`)."""
    return RobustKernel(loss, c).weight(r)


def robust_scale(r: np.ndarray, floor: float) -> float:
    """``max(1.4826 * median(|r|), floor)``: the MAD scale of residuals whose centre is zero."""
    if r.size == 0:
        return floor
    return max(1.4826 * float(np.median(np.abs(r))), floor)


class CorrespondenceChecker(Protocol):
    """A 0/1 verdict on each point-to-surface correspondence ``y_i -> closest_i`` (on ``face_i``,
    at distance ``distance_i``)."""

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray: ...


@dataclass(frozen=True)
class BoundaryChecker:
    """Rejects correspondences whose closest point lies on the target's open boundary with the
    point beyond it (the template covers more than the scan)."""

    target: SurfaceDistanceQuery

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        return ~self.target.beyond_boundary(points, faces, closest)


@dataclass(frozen=True)
class NormalChecker:
    """Rejects correspondences whose template normal and target triangle normal make an angle
    above ``max_angle`` degrees. ``normals`` are the template's, one per point, already turned
    to the target's orientation. ``face_normals`` holds the unit normal of every target
    triangle, or looks up those of the triangles it is given (e.g.
    :meth:`SurfaceDistanceQuery.face_normal`: a single check of a large target then computes
    only the normals it needs)."""

    normals: np.ndarray
    face_normals: np.ndarray | Callable[[np.ndarray], np.ndarray]
    max_angle: float

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        lookup = self.face_normals
        target = lookup(faces) if callable(lookup) else lookup[faces]
        cos = (self.normals * target).sum(axis=1)
        return cos >= float(np.cos(np.radians(self.max_angle)))


@dataclass(frozen=True)
class DistanceChecker:
    """Rejects correspondences farther than ``factor`` robust scales ``sigma``."""

    factor: float
    sigma: float

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        return distances <= self.factor * self.sigma


def support(
    checkers: list[CorrespondenceChecker],
    points: np.ndarray,
    distances: np.ndarray,
    faces: np.ndarray,
    closest: np.ndarray,
) -> np.ndarray:
    """The correspondences every checker accepts."""
    keep = np.ones(points.shape[0], dtype=bool)
    for checker in checkers:
        keep &= checker.check(points, distances, faces, closest)
    return keep
