"""Robust losses of the distance terms: small value types the user composes, as Open3D's
``RobustKernel``.

A loss turns each residual ``r`` into the weight ``w(r) = rho'(r) / r`` of iteratively
reweighted least squares: at every cost evaluation a residual enters as ``sqrt(w) r`` (Jacobian
``sqrt(w) J``, the weights held fixed in it). With ``z = |r| / (k sigma)``, ``k`` the loss's
tuning constant (95% efficiency under Gaussian noise) and ``sigma`` its scale.

A new loss is one class here (a subclass of :class:`RobustLoss` with its ``name``, ``constant``
and ``_weights``) plus one entry in the contract tests (tests/registration/test_strategies.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .._validation import check_positive

__all__ = ["CauchyLoss", "HuberLoss", "L2Loss", "RobustLoss", "TukeyLoss", "loss_named"]


@dataclass(frozen=True)
class RobustLoss:
    """The weights of a robust loss at the scale ``sigma``.

    Attributes
    ----------
    scale : float or None
        ``sigma``, in the input's units. ``None`` (default): estimated at the start of every
        level from the data, ``sigma = max(1.4826 median |r|, 0.05 h)`` (the MAD of residuals
        centred at zero; ``h`` the level's cell size).
    """

    #: The loss's name in :attr:`~o3dreg.DistanceEstimation.loss`.
    name: ClassVar[str] = ""
    #: Tuning constant ``k``, in units of ``sigma``.
    constant: ClassVar[float] = np.inf

    scale: float | None = None

    def __post_init__(self) -> None:
        if self.scale is not None:
            check_positive(self.scale, "scale")

    def threshold(self, sigma: float) -> float:
        """``k sigma``: the residual at which the weight starts to fall (``z = 1``)."""
        return self.constant * sigma

    def weight(self, r: np.ndarray, sigma: float) -> np.ndarray:
        """The weights ``w(r)`` of the residuals ``r`` (same shape) at the scale ``sigma``."""
        if r.size == 0:
            return np.ones(r.shape)
        return self._weights(np.abs(r) / self.threshold(sigma))

    def _weights(self, z: np.ndarray) -> np.ndarray:
        return np.ones(z.shape)

    def __repr__(self) -> str:
        scale = "" if self.scale is None else f"scale={self.scale:g}"
        return f"{type(self).__name__}({scale})"


@dataclass(frozen=True, repr=False)
class L2Loss(RobustLoss):
    """Plain least squares, ``w = 1``: the paper's cost.

    ``scale`` (``sigma``): as :class:`RobustLoss`'s.
    """

    name: ClassVar[str] = "linear"

    def weight(self, r: np.ndarray, sigma: float) -> np.ndarray:
        return np.ones(r.shape)


@dataclass(frozen=True, repr=False)
class HuberLoss(RobustLoss):
    """``w = min(1, 1 / z)``, ``k = 1.345``: quadratic near zero, linear in the tail.

    ``scale`` (``sigma``): as :class:`RobustLoss`'s.
    """

    name: ClassVar[str] = "huber"
    constant: ClassVar[float] = 1.345

    def _weights(self, z: np.ndarray) -> np.ndarray:
        return 1.0 / np.maximum(z, 1.0)


@dataclass(frozen=True, repr=False)
class CauchyLoss(RobustLoss):
    """``w = 1 / (1 + z^2)``, ``k = 2.3849``: every residual keeps a weight (no hard cut), so a
    correspondence that starts far off can still come in, while debris weighs little.

    ``scale`` (``sigma``): as :class:`RobustLoss`'s.
    """

    name: ClassVar[str] = "cauchy"
    constant: ClassVar[float] = 2.3849

    def _weights(self, z: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + z * z)


@dataclass(frozen=True, repr=False)
class TukeyLoss(RobustLoss):
    """``w = (1 - z^2)^2`` for ``z < 1``, else 0, ``k = 4.6851``: residuals beyond ``k sigma``
    are dropped.

    ``scale`` (``sigma``): as :class:`RobustLoss`'s.
    """

    name: ClassVar[str] = "tukey"
    constant: ClassVar[float] = 4.6851

    def _weights(self, z: np.ndarray) -> np.ndarray:
        return np.where(z < 1.0, (1.0 - z * z) ** 2, 0.0)


#: The losses by :attr:`RobustLoss.name`.
LOSS_TYPES: dict[str, type[RobustLoss]] = {
    cls.name: cls for cls in (L2Loss, HuberLoss, CauchyLoss, TukeyLoss)
}


def loss_named(name: str, scale: float | None = None) -> RobustLoss:
    """The loss called ``name`` (``'linear'``, ``'huber'``, ``'cauchy'``, ``'tukey'``)."""
    if name not in LOSS_TYPES:
        raise ValueError(f"`loss` must be one of {tuple(LOSS_TYPES)}, got {name!r}")
    return LOSS_TYPES[name](scale)
