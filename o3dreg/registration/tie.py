"""A near tie of the rigid start, settled by the elastic registrations from both poses.

The rigid search ranks poses by how closely the template fits the target rigidly. Where the
target differs from the template by more than a rigid motion (a bone stretched or shortened by a
third, a skull-like cap under a smooth warp), no pose fits closely and a wrong one can score
within :data:`~o3dreg.registration.rigid.AMBIGUITY_RATIO` of the right one: the start is then
reported ambiguous and the registration ``suspect``, however right. The levels remove what the
rigid fit cannot, so the registrations from the two poses tell them apart where the shape does:
the one from the right pose fits closely without turning the template's parts against each
other, the one from the wrong pose fits worse or has to turn its parts round to fit.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from .._geometry import polar_angles, proper_rotation, row_norms
from .result import RigidStart
from .rigid import AMBIGUOUS_START

__all__ = [
    "TIE_AGREEMENT",
    "TIE_CLOSE_FIT",
    "TIE_FIT_RATIO",
    "TIE_SHARED_SUPPORT",
    "TIE_TURN",
    "local_turn",
    "settle_tie",
    "symmetric_fit",
]

logger = logging.getLogger("o3dreg")

#: A registration settles the tie when it fits the target this many times closer than the other
#: pose's (symmetric distances), closely (:data:`TIE_CLOSE_FIT`), and without turning parts of
#: the template against each other (:data:`TIE_TURN`). Measured on 27 ambiguous starts (an
#: asymmetric blob, a long bone, a skull-like cap, a dumbbell: turned, stretched, bent,
#: twisted; a single-surface cap; rigid and similarity starts): the registrations kept by that
#: rule fit 1.7-36 times closer and are all right (within 1.4% of the diagonal); every wrong one
#: that fits closer and closely (twisted targets, 6% off) turns parts by 20-24 degrees, and
#: near-symmetric shapes (a dumbbell, its mirror image) fit alike from both poses (ratio 1.0).
TIE_FIT_RATIO = 1.5
#: The largest symmetric distance, as a fraction of the target's diagonal, of a registration
#: that settles a tie by its fit (the registrations kept: 0.015-0.063%). A coarse hierarchy on a
#: deformed sphere (levels of 2 and 4 cells) fits from two poses 85 degrees apart to 0.29% and
#: 0.46%, the closer one 4.8% off: neither fit says much of the pose. Noisy and partial
#: targets (whose distances hold the noise, or the template beyond the cut) are settled only
#: by registrations ending alike.
TIE_CLOSE_FIT = 0.001
#: Registrations from the two poses that end within this fraction of the target's diagonal of
#: each other (mean vertex distance) settle the tie too: the result does not depend on it (a
#: long bone shortened by a quarter or a third, a dumbbell stretched: 0.1-0.5%; distinct
#: results lie 3-60% apart). On a partial target the distance is taken over the vertices both
#: support (:data:`TIE_SHARED_SUPPORT`): the rest has no data, wherever it hangs (a mandible
#: cut to its front 30%: 0.15% over the 788 vertices both support, 1.3% over all).
TIE_AGREEMENT = 0.01
#: The vertices both registrations support stand for them when they hold at least this
#: fraction of each one's supported vertices (else every vertex counts).
TIE_SHARED_SUPPORT = 0.9
#: The largest local turn (degrees; :func:`local_turn`) of a registration that settles a tie by
#: its fit. The registrations kept turn parts of the template by 2.6-8.9 degrees against the
#: map's overall rotation (which a similarity start 11 degrees off adds to every vertex: the
#: turn against the start would read 12.5); on bent and twisted targets, and stretched ones
#: that both registrations miss, 12-51.
TIE_TURN = 10.0


def local_turn(deformation: Any, points: np.ndarray, moved: np.ndarray) -> float:
    """How far a map of space turns parts of a template against each other: the 90th
    percentile, over the template ``points`` (rigidly aligned; ``moved`` where the map sends
    them), of the angle (degrees) between the map's local rotation (the polar part of its
    Jacobian) and its overall rotation (the least-squares rotation of ``points`` onto
    ``moved``)."""
    overall = proper_rotation(points - points.mean(axis=0), moved - moved.mean(axis=0))
    local = np.einsum("ji,kjl->kil", overall, deformation.jacobian(points))
    return float(np.percentile(polar_angles(local), 90))


def symmetric_fit(result: Any) -> float:
    """The mean of the mean source -> target and target -> source surface distances of an
    :class:`~o3dreg.ElasticRegistrationResult` (the rigid score's measure, after the levels)."""
    distances = result.distances
    return 0.5 * (distances.source_to_target_mean + distances.target_to_source_mean)


def settle_tie(
    rigid: Any,
    registrations: tuple[Any, Any],
    turns: tuple[float, float],
    diagonal: float,
) -> tuple[int, RigidStart]:
    """Which of the registrations from an ambiguous rigid start's two poses to keep.

    Parameters
    ----------
    rigid : RigidRegistrationResult
        The ambiguous rigid start.
    registrations : (ElasticRegistrationResult, ElasticRegistrationResult)
        The registrations from its winner's and its runner-up's pose.
    turns : (float, float)
        How far each one's map turns parts of the template against each other
        (:func:`local_turn`).
    diagonal : float
        The target's bounding-box diagonal.

    Returns
    -------
    kept : int
        0 for the winner's registration, 1 for the runner-up's.
    start : RigidStart
        The rigid start to report: ``tie_kept`` set and the ambiguity warning dropped when the
        tie is settled (:data:`TIE_FIT_RATIO`, :data:`TIE_CLOSE_FIT`, :data:`TIE_TURN`,
        :data:`TIE_AGREEMENT`), else as the rigid step left it (ambiguous, the winner's
        registration kept).
    """
    fits = (symmetric_fit(registrations[0]), symmetric_fit(registrations[1]))
    apart = _apart(*registrations)
    start = dataclasses.replace(RigidStart.from_rigid(rigid), tie_fits=fits)
    kept = int(np.argmin(fits))
    if apart <= TIE_AGREEMENT * diagonal:
        kept = 0
    elif (
        not turns[kept] <= TIE_TURN
        or not fits[1 - kept] >= TIE_FIT_RATIO * fits[kept]
        or not fits[kept] <= TIE_CLOSE_FIT * diagonal
    ):
        logger.info(
            "rigid start: near tie not settled by the registrations from both poses "
            "(symmetric distances %.4g and %.4g, %.4g apart)",
            *fits,
            apart,
        )
        return 0, start
    names = ("winner", "runner-up")
    logger.info(
        "rigid start: near tie settled by the registrations from both poses: the %s's kept "
        "(symmetric distances %.4g and %.4g, %.4g apart)",
        names[kept],
        *fits,
        apart,
    )
    warnings = tuple(w for w in start.warnings if not w.startswith(AMBIGUOUS_START))
    return kept, dataclasses.replace(
        start, ambiguous=False, warnings=warnings, tie_kept=names[kept]
    )


def _apart(first: Any, second: Any) -> float:
    """Mean distance between two registrations' vertices, over those both support when they
    stand for both (:data:`TIE_SHARED_SUPPORT`), else over all."""
    shared = np.ones(first.vertices.shape[0], dtype=bool)
    a, b = getattr(first, "supported", None), getattr(second, "supported", None)
    if a is not None and b is not None:
        both = np.asarray(a) & np.asarray(b)
        count = int(both.sum())
        if count and count >= TIE_SHARED_SUPPORT * max(int(np.sum(a)), int(np.sum(b))):
            shared = both
    return float(row_norms(first.vertices[shared] - second.vertices[shared]).mean())
