"""The registration options, defined once: ``o3dreg register`` and ``o3dreg build-model`` both
add this group and turn it into one :class:`~o3dreg.app.settings.RegistrationSettings`.

Every option defaults to ``None`` (not given), so an unset option keeps the library's default
(:class:`~o3dreg.DistanceEstimation`, :class:`~o3dreg.ElasticLevel`, ...): the command line
never carries a second copy of a default.
"""

from __future__ import annotations

import argparse
import itertools
import warnings
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..app.settings import RegistrationSettings
from ..io.landmark_files import read_landmarks
from ..registration.distance import SurfaceDistanceQuery
from ..registration.options import (
    DistanceEstimation,
    ElasticCriteria,
    ElasticLevel,
    default_levels,
    paper_levels,
)
from ..shape.landmark_transfer import LANDMARK_REACH
from ._common import float_list, int_list

#: DistanceEstimation fields set by the options below (option dest -> field).
_ESTIMATION = {
    "symmetric_weight": "symmetric_weight",
    "loss": "loss",
    "max_normal_angle": "max_normal_angle",
    "max_distance_factor": "max_distance_factor",
    "min_target_component": "min_target_component",
}


def add_registration_options(parser: argparse.ArgumentParser) -> None:
    """The options saying how a template is registered onto a patient."""
    reg = parser.add_argument_group("registration (the same for register and build-model)")
    reg.add_argument(
        "--levels",
        type=int_list,
        default=None,
        help="cells per axis of each level, coarse to fine (default 2,4,8,16; 2,4,8,16,32 for an "
        "elongated template)",
    )
    reg.add_argument(
        "--regularization",
        type=float_list,
        default=None,
        help="bending-energy weight, one value or one per level (default 0.1)",
    )
    reg.add_argument("--no-symmetric", action="store_true", help="single distance (paper eq. 2)")
    reg.add_argument(
        "--symmetric-weight", type=float, default=None, help="weight of the barycentre term"
    )
    reg.add_argument(
        "--barycentre-correction",
        action="store_true",
        help="compare barycentres with the template's own Voronoi centroids (dense targets)",
    )
    reg.add_argument(
        "--max-iteration", type=int, default=None, help="LM steps per level (default 20)"
    )
    start = reg.add_mutually_exclusive_group()
    start.add_argument(
        "--no-rigid",
        action="store_true",
        help="no pre-alignment: the meshes are already aligned",
    )
    start.add_argument(
        "--with-scaling",
        action="store_true",
        help="similarity pre-alignment (a uniform scale too; from landmarks as well)",
    )
    reg.add_argument(
        "--parts",
        choices=["joint", "connected"],
        default=None,
        help="'connected': one deformation per connected piece of the template",
    )
    robust = parser.add_argument_group(
        "robustness (the defaults handle partial scans, debris and outliers)"
    )
    robust.add_argument(
        "--paper",
        action="store_true",
        help="the paper's method: eq. (3) on every level of the default hierarchy with plain "
        "least squares (linear loss, no boundary or normal rejection, every target "
        "component; the options below still apply on top)",
    )
    robust.add_argument(
        "--loss",
        choices=["linear", "huber", "cauchy", "tukey"],
        default=None,
        help="robust loss of both distance terms (default cauchy; linear: least squares)",
    )
    robust.add_argument(
        "--max-normal-angle",
        type=float,
        default=None,
        metavar="DEG",
        help="drop matches whose normals differ by more than DEG degrees (default 90; 180: off)",
    )
    robust.add_argument(
        "--max-distance-factor",
        type=float,
        default=None,
        metavar="K",
        help="drop matches farther than K robust scales",
    )
    robust.add_argument(
        "--min-target-component",
        type=float,
        default=None,
        metavar="F",
        help="ignore target islands smaller than F times its largest component "
        "(default 0.01; 0: keep all)",
    )
    robust.add_argument(
        "--keep-boundary",
        action="store_true",
        help="do not drop matches beyond the target's open boundary",
    )


def build_levels(args: argparse.Namespace, template: Any = None) -> list[ElasticLevel] | None:
    """The hierarchy from ``--levels``, ``--regularization`` and ``--paper`` (``None``: the
    default; ``--regularization`` alone reweights the default levels of ``template``)."""
    # --paper is the published method: eq. (3) on every default level (paper_levels).
    hierarchy = paper_levels() if args.paper else default_levels(template)
    if args.levels is None and args.regularization is None:
        return hierarchy if args.paper else None
    resolutions = args.levels or [lev.resolution for lev in hierarchy]
    if any(b < a for a, b in itertools.pairwise(resolutions)):
        raise ValueError(
            "--levels must go from coarse to fine (cells per axis not decreasing), got "
            + ",".join(map(str, resolutions))
        )
    weights = args.regularization or [hierarchy[0].regularization]
    if len(weights) == 1:
        weights = weights * len(resolutions)
    if len(weights) != len(resolutions):
        raise ValueError(
            f"--regularization must give 1 or {len(resolutions)} values, got {len(weights)}"
        )
    # The hierarchy (default, or --paper's) keeps its barycentre-term schedule; levels given on
    # the command line use the term at full weight (eq. 3 at every level, as published).
    if args.levels is None:
        return [replace(lev, regularization=w) for lev, w in zip(hierarchy, weights)]
    return [ElasticLevel(r, w) for r, w in zip(resolutions, weights)]


def estimation_method(args: argparse.Namespace) -> DistanceEstimation:
    """The library's defaults (or ``--paper``'s plain least squares), with the given options
    (``--paper``'s levels: :func:`build_levels`)."""
    changes = _estimation_changes(args)
    return DistanceEstimation.paper(**changes) if args.paper else DistanceEstimation(**changes)


def _estimation_changes(args: argparse.Namespace) -> dict[str, Any]:
    changes: dict[str, Any] = {
        field: getattr(args, dest)
        for dest, field in _ESTIMATION.items()
        if getattr(args, dest) is not None
    }
    if args.no_symmetric:
        # The barycentre term's options say how a term is weighed that --no-symmetric removes.
        for flag, given in (
            ("--symmetric-weight", args.symmetric_weight is not None),
            ("--barycentre-correction", args.barycentre_correction),
        ):
            if given:
                raise ValueError(f"{flag} sets the barycentre term, which --no-symmetric drops")
        changes["symmetric"] = False
    if args.barycentre_correction:
        changes["barycentre_correction"] = True
    if args.keep_boundary:
        changes["reject_boundary"] = False
    if "min_target_component" in changes:
        changes["min_target_component"] = changes["min_target_component"] or None  # 0: keep all
    return changes


def settings_from_args(args: argparse.Namespace, template: Any = None) -> RegistrationSettings:
    """One :class:`RegistrationSettings` from the options of :func:`add_registration_options`.

    Options not given leave the library's defaults in place (``estimation_method=None`` when
    no distance option and no ``--paper`` is given); ``template``: the mesh the default levels
    are chosen for where ``--regularization`` reweights them
    (:func:`~o3dreg.default_levels`).
    """
    given = args.paper or bool(_estimation_changes(args))
    estimation = estimation_method(args) if given else None
    criteria = None
    if args.max_iteration is not None:
        criteria = ElasticCriteria(max_iteration=args.max_iteration)
    levels = build_levels(args, template)
    start = "identity" if args.no_rigid else "similarity" if args.with_scaling else "rigid"
    return RegistrationSettings(
        levels=None if levels is None else tuple(levels),
        estimation_method=estimation,
        criteria=criteria,
        parts=args.parts or "joint",
        start=start,
    )


# -- the landmark start (register --landmarks, build-model --landmarks) ---------------------------
def read_quietly(path: str) -> tuple[tuple[str, ...], np.ndarray]:
    """``read_landmarks(path)`` without its warnings: they were given when the file was first
    read (by the registration's landmark start)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_landmarks(path)


def far_landmarks(
    landmarks: tuple[Sequence[str], np.ndarray], mesh: Any, used: Sequence[str]
) -> tuple[dict[str, float], float]:
    """The ``(labels, points)`` among ``used`` farther from ``mesh`` than
    :data:`~o3dreg.shape.landmark_transfer.LANDMARK_REACH` of its size (anatomy the mesh does
    not show), with their distances, and that limit."""
    labels, points = landmarks
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    limit = LANDMARK_REACH * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    # A handful of points: no tree of the whole mesh (the registration builds its own).
    distance = SurfaceDistanceQuery(vertices, faces).closest_few(np.asarray(points))[0]
    far = {label: float(d) for label, d in zip(labels, distance) if label in used and d > limit}
    return far, limit


def far_landmark_warnings(
    sides: Sequence[tuple[str, dict[str, float], float]], used: Sequence[str]
) -> list[str]:
    """One sentence per side (``(name, far landmarks, limit)`` of :func:`far_landmarks`) with
    landmarks off its surface; it names the ``--labels`` that leave them out when 3 pairs
    remain."""
    off = {label for _, far, _ in sides for label in far}
    near = [label for label in used if label not in off]
    hint = f" (--labels {','.join(near)})" if len(near) >= 3 else ""
    return [
        f"{side} landmarks far from the {side} surface (more than {limit:.3g}, "
        f"{LANDMARK_REACH:.0%} of its size): "
        f"{', '.join(f'{label} ({d:.3g})' for label, d in far.items())}; they steer the start "
        f"all the same: leave out landmarks of anatomy the meshes do not show{hint}"
        for side, far, limit in sides
        if far
    ]
