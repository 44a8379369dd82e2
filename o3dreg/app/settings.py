"""How a template is registered onto a patient, as one value: shared by every entry point.

``o3dreg register``, ``o3dreg build-model``, :func:`~o3dreg.register_batch` and
:func:`o3dreg.app.model_folder.build_model_folder` all take a :class:`RegistrationSettings`, so a
model is built with exactly the settings a single registration was tried with.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..registration.elastic import registration_elastic
from ..registration.landmark_start import registration_landmarks
from ..registration.options import DistanceEstimation, ElasticCriteria, ElasticLevel

__all__ = ["STARTS", "RegistrationSettings"]

#: How the rigid part is found when no ``init`` is given.
STARTS = ("rigid", "similarity", "identity")


@dataclass(frozen=True)
class RegistrationSettings:
    """Everything that says how a template is registered onto a patient.

    Attributes
    ----------
    levels : tuple of ElasticLevel or None
        The lattice hierarchy, coarse to fine. ``None``: :func:`~o3dreg.default_levels`.
    estimation_method : DistanceEstimation or None
        Single or symmetric distance and the robust settings. ``None``: ``DistanceEstimation()``.
    criteria : ElasticCriteria or None
        Stopping rule of every level. ``None``: ``ElasticCriteria()``.
    padding : float
        Lattice margin (fraction of the data's extent). Default 0.1.
    parts : {'joint', 'connected'}
        One deformation for the whole template, or one per connected piece.
    start : {'rigid', 'similarity', 'identity'}
        The pre-alignment when no ``init`` (for instance from landmarks) is given: the rigid
        search of :func:`~o3dreg.registration_rigid` (default), the same with a uniform scale,
        or none (the meshes are already aligned). With landmarks, ``'similarity'`` fits a scale
        to them and ``'rigid'`` does not.
    """

    levels: tuple[ElasticLevel, ...] | None = None
    estimation_method: DistanceEstimation | None = None
    criteria: ElasticCriteria | None = None
    padding: float = 0.1
    parts: str = "joint"
    start: str = "rigid"

    def __post_init__(self) -> None:
        if self.levels is not None:
            levels = (self.levels,) if isinstance(self.levels, ElasticLevel) else tuple(self.levels)
            for k, level in enumerate(levels):
                if not isinstance(level, ElasticLevel):
                    raise TypeError(
                        f"`levels[{k}]` must be an ElasticLevel, got {type(level).__name__}"
                    )
            object.__setattr__(self, "levels", levels)
        if self.estimation_method is not None and not isinstance(
            self.estimation_method, DistanceEstimation
        ):
            raise TypeError(
                "`estimation_method` must be a DistanceEstimation, "
                f"got {type(self.estimation_method).__name__}"
            )
        if self.criteria is not None and not isinstance(self.criteria, ElasticCriteria):
            raise TypeError(
                f"`criteria` must be an ElasticCriteria, got {type(self.criteria).__name__}"
            )
        if self.parts not in ("joint", "connected"):
            raise ValueError(f"`parts` must be 'joint' or 'connected', got {self.parts!r}")
        if self.start not in STARTS:
            raise ValueError(f"`start` must be one of {STARTS}, got {self.start!r}")

    @classmethod
    def from_options(cls, **options: Any) -> RegistrationSettings:
        """Settings from :func:`~o3dreg.registration_elastic`'s keyword names (``levels``,
        ``estimation_method``, ``criteria``, ``padding``, ``parts``) and ``start``."""
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(options) - fields
        if unknown:
            raise TypeError(
                f"unexpected registration option(s) {sorted(unknown)}; allowed: {sorted(fields)}"
            )
        return cls(**options)

    def elastic_options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~o3dreg.registration_elastic` (``init`` aside)."""
        return {
            "levels": None if self.levels is None else list(self.levels),
            "estimation_method": self.estimation_method,
            "criteria": self.criteria,
            "padding": self.padding,
            "parts": self.parts,
        }

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready description (for reports)."""
        description = {
            "levels": None
            if self.levels is None
            else [dataclasses.asdict(level) for level in self.levels],
            "estimation_method": None
            if self.estimation_method is None
            else dataclasses.asdict(self.estimation_method),
            "criteria": None if self.criteria is None else dataclasses.asdict(self.criteria),
            "padding": self.padding,
            "parts": self.parts,
            "start": self.start,
        }
        return _plain(description)

    def landmark_start(
        self, template_landmarks: Any, patient_landmarks: Any, *, labels: Any = None
    ) -> np.ndarray:
        """The ``init`` from corresponding landmarks (rigid, or a similarity when ``start`` is
        ``'similarity'``): :func:`~o3dreg.registration_landmarks`, with the pairs of ``labels``
        only when given."""
        return registration_landmarks(
            template_landmarks,
            patient_landmarks,
            with_scaling=self.start == "similarity",
            labels=labels,
        ).transformation

    def register(
        self,
        source: Any,
        target: Any,
        *,
        init: Any = None,
        callback: Callable[[Any], Any] | None = None,
    ) -> Any:
        """Register ``source`` onto ``target`` with these settings.

        Parameters
        ----------
        source, target : open3d.geometry.TriangleMesh or (vertices, faces)
            Not modified.
        init : (4, 4) array_like, optional
            A start (for instance :meth:`landmark_start`); replaces ``start``.
        callback : callable, optional
            Called with each level's report.

        Returns
        -------
        ElasticRegistrationResult
            With its verdict (``status``, ``warnings``); a similarity start's scores
            (``rigid_start``) and ambiguity warning are carried into it.
        """
        if init is None and self.start == "identity":
            init = np.eye(4)
        # A similarity start is the elastic step's own start with a scale: found on the target
        # as that step prepares it (validated once, islands dropped, one AABB tree), its scores
        # and warnings carried into the result as the rigid start's are.
        return registration_elastic(
            source,
            target,
            init=init,
            callback=callback,
            with_scaling=init is None and self.start == "similarity",
            **self.elastic_options(),
        )

    def __repr__(self) -> str:
        levels = "default" if self.levels is None else [lev.resolution for lev in self.levels]
        return (
            f"RegistrationSettings(levels={levels}, estimation_method="
            f"{self.estimation_method or 'default'}, start={self.start!r}, parts={self.parts!r})"
        )


def resolve_settings(settings: Any, options: dict[str, Any]) -> RegistrationSettings:
    """One :class:`RegistrationSettings` from a ``settings`` argument or loose keywords."""
    if settings is not None:
        if options:
            raise TypeError(
                f"pass registration options in `settings` or as keywords, not both "
                f"(got `settings` and {sorted(options)})"
            )
        if not isinstance(settings, RegistrationSettings):
            raise TypeError(
                f"`settings` must be a RegistrationSettings, got {type(settings).__name__}"
            )
        return settings
    return RegistrationSettings.from_options(**options)


def _plain(value: Any) -> Any:
    """``value`` with arrays as lists and what JSON has no form for (a term of one's own in
    ``more_terms``, say) as its repr."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)
