"""The robust scale and the correspondence masks of one level.

The public checkers (:mod:`o3dreg.registration.checkers`) bind to these masks at each level;
:class:`~o3dreg.registration._cost.LevelProblem` multiplies a loss's weights by the product of
the masks. Each piece is tested alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .distance import SurfaceDistanceQuery


def robust_scale(r: np.ndarray, floor: float) -> float:
    """``max(1.4826 * median(|r|), floor)``: the MAD scale of residuals whose centre is zero."""
    if r.size == 0:
        return floor
    return max(1.4826 * float(np.median(np.abs(r))), floor)


class CorrespondenceMask(Protocol):
    """A 0/1 verdict on each point-to-surface correspondence ``y_i -> closest_i`` (on ``face_i``,
    at distance ``distance_i``)."""

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray: ...


@dataclass(frozen=True)
class BoundaryMask:
    """Rejects correspondences whose closest point lies on the target's open boundary with the
    point beyond it (the template covers more than the scan)."""

    target: SurfaceDistanceQuery

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        return ~self.target.beyond_boundary(points, faces, closest)


@dataclass(frozen=True)
class NormalMask:
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
        target = lookup(faces) if callable(lookup) else lookup.take(faces, axis=0)
        cos = (self.normals * target).sum(axis=1)
        return cos >= float(np.cos(np.radians(self.max_angle)))


@dataclass(frozen=True)
class DistanceMask:
    """Rejects correspondences farther than ``factor`` robust scales ``sigma``."""

    factor: float
    sigma: float

    def check(
        self, points: np.ndarray, distances: np.ndarray, faces: np.ndarray, closest: np.ndarray
    ) -> np.ndarray:
        return distances <= self.factor * self.sigma


def support(
    masks: list[CorrespondenceMask],
    points: np.ndarray,
    distances: np.ndarray,
    faces: np.ndarray,
    closest: np.ndarray,
) -> np.ndarray:
    """The correspondences every mask accepts."""
    keep = np.ones(points.shape[0], dtype=bool)
    for mask in masks:
        keep &= mask.check(points, distances, faces, closest)
    return keep
