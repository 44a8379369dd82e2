"""A near tie of the rigid start, settled by the elastic registrations from both poses.

The rigid search ranks poses by how closely the template fits the target rigidly. Where the
target differs from the template by more than a rigid motion (a bone stretched or shortened by a
third, a skull-like cap under a smooth warp), no pose fits closely and a wrong one can score
within :data:`~o3dreg.registration.rigid.AMBIGUITY_RATIO` of the right one: the start is then
reported ambiguous and the registration ``suspect``, however right. The levels remove what the
rigid fit cannot, so the registrations from the two poses tell them apart where the shape does:
the one from the right pose fits closely while turning space little, the one from the wrong
pose fits worse or has to turn the template round locally to fit.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from .._geometry import row_norms
from .result import RigidStart
from .rigid import AMBIGUOUS_START

__all__ = ["TIE_AGREEMENT", "TIE_CLOSE_FIT", "TIE_FIT_RATIO", "settle_tie", "symmetric_fit"]

logger = logging.getLogger("o3dreg")

#: A registration settles the tie when it fits the target this many times closer than the other
#: pose's (symmetric distances) and its map turns space by at most
#: :data:`~o3dreg.registration.elastic.GIVEN_START_TURN` at 90% of the template's vertices.
#: Measured on 25 ambiguous starts (an asymmetric blob, a long bone, a skull-like cap, a
#: dumbbell: turned, stretched, bent, twisted; a single-surface cap): the registrations kept
#: by that rule fit 1.7-36 times closer and are all right (within 1.4% of the diagonal); every
#: wrong one that fits closer (bent or twisted targets, a blob stretched by half: 4.7-49% off)
#: turns space by 12-56 degrees there, and near-symmetric shapes (a dumbbell, its mirror
#: image) fit alike from both poses (ratio 1.0).
TIE_FIT_RATIO = 1.5
#: ... and when it fits the target closely: a symmetric distance of at most this fraction of the
#: target's diagonal (the registrations kept above: 0.015-0.063%). A coarse hierarchy on a
#: deformed sphere (levels of 2 and 4 cells) fits from two poses 85 degrees apart to 0.29% and
#: 0.46%, the closer one 4.8% off: neither fit says much of the pose. Noisy and partial
#: targets (whose distances hold the noise, or the template beyond the cut) are settled only
#: by registrations ending alike.
TIE_CLOSE_FIT = 0.001
#: Registrations from the two poses that end within this fraction of the target's diagonal of
#: each other (mean vertex distance) settle the tie too: the result does not depend on it (a
#: long bone shortened by a quarter or a third, a dumbbell stretched: 0.1-0.5%; distinct
#: results lie 3-60% apart).
TIE_AGREEMENT = 0.01


def symmetric_fit(result: Any) -> float:
    """The mean of the mean source -> target and target -> source surface distances of an
    :class:`~o3dreg.ElasticRegistrationResult` (the rigid score's measure, after the levels)."""
    distances = result.distances
    return 0.5 * (distances.source_to_target_mean + distances.target_to_source_mean)


def settle_tie(
    rigid: Any,
    registrations: tuple[Any, Any],
    turned: tuple[bool, bool],
    diagonal: float,
) -> tuple[int, RigidStart]:
    """Which of the registrations from an ambiguous rigid start's two poses to keep.

    Parameters
    ----------
    rigid : RigidRegistrationResult
        The ambiguous rigid start.
    registrations : (ElasticRegistrationResult, ElasticRegistrationResult)
        The registrations from its winner's and its runner-up's pose.
    turned : (bool, bool)
        Whether each one's map turns space by more than
        :data:`~o3dreg.registration.elastic.GIVEN_START_TURN` at a tenth of the template's
        vertices.
    diagonal : float
        The target's bounding-box diagonal.

    Returns
    -------
    kept : int
        0 for the winner's registration, 1 for the runner-up's.
    start : RigidStart
        The rigid start to report: ``tie_kept`` set and the ambiguity warning dropped when the
        tie is settled (:data:`TIE_FIT_RATIO`, :data:`TIE_CLOSE_FIT`, :data:`TIE_AGREEMENT`),
        else as the rigid step
        left it (ambiguous, the winner's registration kept).
    """
    fits = (symmetric_fit(registrations[0]), symmetric_fit(registrations[1]))
    apart = float(row_norms(registrations[0].vertices - registrations[1].vertices).mean())
    start = dataclasses.replace(RigidStart.from_rigid(rigid), tie_fits=fits)
    kept = int(np.argmin(fits))
    if apart <= TIE_AGREEMENT * diagonal:
        kept = 0
    elif (
        turned[kept]
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
