"""Correspondence checkers: which template -> target correspondences count, as Open3D's
``CorrespondenceChecker``. Small value types the user composes.

A checker gives a 0/1 verdict on each correspondence ``y_i -> closest_i``; a rejected one gets
weight 0 (and its template vertex no barycentre row), so the vertex follows its neighbours'
regularised motion. At each level a checker is bound to what it needs (the level's target, the
template normals, the robust scale) as a mask of ``o3dreg.registration._robust``.

A new checker is one class here (a subclass of :class:`CorrespondenceChecker` with ``bind``)
plus one entry in the contract tests (tests/registration/test_strategies.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .._validation import check_positive
from ._robust import BoundaryMask, CorrespondenceMask, DistanceMask, NormalMask
from .distance import SurfaceDistanceQuery

__all__ = [
    "BoundaryChecker",
    "CheckerContext",
    "CorrespondenceChecker",
    "DistanceChecker",
    "NormalAngleChecker",
]


@dataclass(frozen=True)
class CheckerContext:
    """What a level offers its checkers.

    Attributes
    ----------
    target : SurfaceDistanceQuery
        The surface the level measures distances to (the target or its level of detail).
    target_has_boundary : bool
        Whether the whole target has open edges (a simplified copy of a closed surface can have
        spurious ones).
    normals : (n, 3) ndarray or None
        Unit template vertex normals at the level start, turned to the target's orientation.
    sigma : float or None
        The robust scale of the residuals checked (``None`` before it is estimated).
    """

    target: SurfaceDistanceQuery
    target_has_boundary: bool = True
    normals: np.ndarray | None = None
    sigma: float | None = None


@dataclass(frozen=True)
class CorrespondenceChecker:
    """A rule that rejects correspondences; :meth:`bind` makes its mask for one level."""

    #: Whether the mask depends on the robust scale (bound once the scale is estimated, and
    #: also applied to the barycentre term's target -> template distances).
    needs_scale: ClassVar[bool] = False

    def bind(self, context: CheckerContext) -> CorrespondenceMask | None:
        """The mask of this rule at a level (``None``: it rejects nothing there)."""
        raise NotImplementedError


@dataclass(frozen=True)
class BoundaryChecker(CorrespondenceChecker):
    """Reject a template vertex whose closest target point lies on an open boundary edge or
    vertex of the target and which lies beyond it (its offset has a tangential part longer than
    a tenth of the target's mean edge): the target has no data there (a cut, a hole, a partial
    scan). No effect on closed targets."""

    def bind(self, context: CheckerContext) -> CorrespondenceMask | None:
        if not (context.target_has_boundary and context.target.has_boundary):
            return None
        return BoundaryMask(context.target)


@dataclass(frozen=True)
class NormalAngleChecker(CorrespondenceChecker):
    """Reject a correspondence when the template vertex normal and the normal of the target
    triangle holding its closest point make an angle above ``max_angle`` degrees, in
    ``(0, 180]``: surfaces facing away from each other (the inner side of a thin shell,
    debris)."""

    max_angle: float = 90.0

    def __post_init__(self) -> None:
        a = check_positive(self.max_angle, "max_angle")
        if a > 180.0:
            raise ValueError(f"`max_angle` must be in (0, 180] degrees, got {a!r}")

    def bind(self, context: CheckerContext) -> CorrespondenceMask | None:
        if context.normals is None:
            return None
        # Normals of the triangles found only: a target may have millions of triangles.
        return NormalMask(context.normals, context.target.face_normal, self.max_angle)


@dataclass(frozen=True)
class DistanceChecker(CorrespondenceChecker):
    """Reject a correspondence whose residual exceeds ``factor`` robust scales ``sigma``:
    farther than the data justify."""

    factor: float
    needs_scale: ClassVar[bool] = True

    def __post_init__(self) -> None:
        check_positive(self.factor, "factor")

    def bind(self, context: CheckerContext) -> CorrespondenceMask | None:
        if context.sigma is None:
            return None
        return DistanceMask(self.factor, context.sigma)


def bound_masks(
    checkers: Sequence[CorrespondenceChecker], context: CheckerContext
) -> list[CorrespondenceMask]:
    """The masks of ``checkers`` at a level (those that reject something there)."""
    masks = (checker.bind(context) for checker in checkers)
    return [mask for mask in masks if mask is not None]
