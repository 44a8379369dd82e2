"""A start from landmarks: the rigid (or similarity) transformation of corresponding points.

Where a shape is nearly symmetric (a head, a sphere-like bone) or a scan shows only part of it,
no search over poses can be trusted; a few landmarks placed on the template and on the patient
(eye corners, nose tip, a bony prominence) fix the pose. The transformation is the least-squares
fit of the pairs (Kabsch; Umeyama with a scale) and becomes the ``init`` of the elastic step.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._geometry import apply_transformation, fit_pose
from .._validation import as_points, check_bool
from ..io.landmark_files import read_landmarks, select_labels

__all__ = ["LandmarkRegistrationResult", "registration_landmarks"]

logger = logging.getLogger("o3dreg")

#: Landmarks are degenerate (collinear, or all in one point) when the second singular value of
#: the centred points is below this fraction of the first: a rotation about their line is then
#: undetermined.
COLLINEAR_TOLERANCE = 1e-3

#: A landmark farther than this fraction of the landmarks' spread (RMS distance from their
#: centroid) from its pair after the best fit is reported: placement errors of a few mm on
#: landmarks 50-100 mm apart stay far below it; a left-right swap on a mandible was 80%.
MISFIT_FRACTION = 0.2


@dataclass(frozen=True, eq=False)
class LandmarkRegistrationResult:
    """The outcome of :func:`registration_landmarks`.

    Attributes
    ----------
    transformation : (4, 4) ndarray
        Maps source (template) landmarks onto target (patient) landmarks; rigid, or a
        similarity with ``with_scaling``.
    labels : tuple of str
        The pairs used, in order.
    residuals : (l,) ndarray
        Distance of each mapped source landmark from its target landmark, in the target's
        units: a large one points at a misplaced (or mislabelled) landmark.
    scale : float
        The uniform scale of ``transformation`` (1 when rigid).
    warnings : tuple of str
        What the fit says of the landmarks (also logged): a set no motion fits (labels
        swapped, coordinate systems mixed), else each landmark far from its pair under the fit
        of the others.
    """

    transformation: np.ndarray
    labels: tuple[str, ...]
    residuals: np.ndarray = field(repr=False)
    scale: float = 1.0
    #: What the fit says of the landmarks (also logged): a set that no motion fits (residual
    #: RMS above :data:`MISFIT_FRACTION` of the landmarks' spread: labels swapped, coordinate
    #: systems mixed), else each landmark that far from its pair under the fit of the others.
    warnings: tuple[str, ...] = ()

    @property
    def rms(self) -> float:
        """Root mean square of :attr:`residuals`."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    def __repr__(self) -> str:
        return (
            f"LandmarkRegistrationResult(pairs={len(self.labels)}, scale={self.scale:.4g}, "
            f"rms={self.rms:.4g}, max={float(self.residuals.max()):.4g})"
        )


def _fit_findings(
    labels: tuple[str, ...],
    ps: np.ndarray,
    pt: np.ndarray,
    residuals: np.ndarray,
    with_scaling: bool,
) -> tuple[str, ...]:
    """What a landmark fit shows (:attr:`LandmarkRegistrationResult.warnings`): a set that no
    motion fits, else each landmark far from its pair under the fit of the others."""
    spread = float(np.sqrt(((pt - pt.mean(axis=0)) ** 2).sum(axis=1).mean()))
    rms = float(np.sqrt(np.mean(residuals**2)))
    if rms > MISFIT_FRACTION * spread:
        # No motion fits the set: swapped labels spread their misfit over every landmark.
        return (
            f"the landmarks fit no {'similarity' if with_scaling else 'rigid motion'}: residual "
            f"rms {rms:.3g} is {100 * rms / spread:.0f}% of their spread {spread:.3g}; labels "
            "swapped (left and right?) or the two files in other coordinate systems (LPS, RAS)?",
        )
    # A misplaced landmark pulls the fit towards itself (its residual in the fit of all is a
    # fraction of its error, and it spreads to the others): each is measured against the fit of
    # the others, the worst named and set aside, while 3 remain to fit.
    found: list[str] = []
    kept = np.arange(ps.shape[0])
    while kept.size >= 4:
        left_out = np.empty(kept.size)
        for j, i in enumerate(kept):
            others = kept[kept != i]
            fit = fit_pose(ps[others], pt[others], with_scaling)
            left_out[j] = np.linalg.norm(apply_transformation(fit, ps[i]) - pt[i])
        worst = int(np.argmax(left_out))
        if left_out[worst] <= MISFIT_FRACTION * spread:
            break
        found.append(
            f"landmark {labels[kept[worst]]!r} lies {left_out[worst]:.3g} from its pair under the "
            f"fit of the others ({100 * left_out[worst] / spread:.0f}% of the landmarks' spread "
            f"{spread:.3g}): misplaced or mislabelled"
        )
        kept = np.delete(kept, worst)
    return tuple(found)


def _as_landmarks(value: Any, name: str) -> tuple[tuple[str, ...] | None, np.ndarray]:
    """Labels (or ``None``) and points from a file, a ``(labels, points)`` pair or points."""
    if isinstance(value, (str, os.PathLike)):
        labels, points = read_landmarks(value, name=name)
        return tuple(labels), as_points(points, f"{name} landmarks {os.fspath(value)!r}")
    if (
        isinstance(value, tuple)
        and len(value) == 2
        and not isinstance(value[0], np.ndarray)
        and all(isinstance(v, str) for v in value[0])
    ):
        labels = tuple(value[0])
        points = as_points(value[1], name)
        if len(labels) != points.shape[0]:
            raise ValueError(f"`{name}` has {len(labels)} labels for {points.shape[0]} points")
        return labels, points
    return None, as_points(value, name)


def _choose(
    labels: tuple[str, ...], points: np.ndarray, chosen: Any, name: str, value: Any
) -> tuple[tuple[str, ...], np.ndarray]:
    """The landmarks of ``chosen`` (the ``labels`` argument) of one side, in its order (a label
    the side holds twice is refused where it is chosen)."""
    path = f" {os.fspath(value)!r}" if isinstance(value, (str, os.PathLike)) else ""
    kept = select_labels(labels, chosen, f"`{name}`{path}")
    return tuple(labels[k] for k in kept), points[kept]


def _pair(
    source: Any, target: Any, chosen: Any = None
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    ls, ps = _as_landmarks(source, "source")
    lt, pt = _as_landmarks(target, "target")
    if chosen is not None:
        if ls is None or lt is None:
            bare = " and ".join(n for n, lab in (("`source`", ls), ("`target`", lt)) if lab is None)
            raise ValueError(f"`labels` chooses labelled landmarks, but {bare} holds bare points")
        ls, ps = _choose(ls, ps, chosen, "source", source)
        lt, pt = _choose(lt, pt, chosen, "target", target)
    if ls is None or lt is None:
        if ps.shape != pt.shape:
            raise ValueError(
                f"`source` and `target` must hold as many landmarks (paired by order), "
                f"got {ps.shape[0]} and {pt.shape[0]}"
            )
        labels = ls or lt or tuple(f"L{k + 1}" for k in range(ps.shape[0]))
        return tuple(labels), ps, pt
    for name, labels in (("source", ls), ("target", lt)):
        repeated = sorted({lab for lab in labels if labels.count(lab) > 1})
        if repeated:
            raise ValueError(f"`{name}` repeats landmark labels {repeated}")
    missing_t = [lab for lab in ls if lab not in lt]
    missing_s = [lab for lab in lt if lab not in ls]
    if missing_t or missing_s:
        raise ValueError(
            "`source` and `target` landmark labels must match: "
            + "; ".join(
                part
                for part in (
                    f"{missing_t} only in `source`" if missing_t else "",
                    f"{missing_s} only in `target`" if missing_s else "",
                )
                if part
            )
        )
    index = {lab: k for k, lab in enumerate(lt)}
    return ls, ps, pt[[index[lab] for lab in ls]]


def registration_landmarks(
    source: Any, target: Any, *, with_scaling: bool = False, labels: Any = None
) -> LandmarkRegistrationResult:
    """The rigid or similarity transformation best mapping source landmarks onto target ones.

    Parameters
    ----------
    source, target : path, (labels, points) or (l, 3) array_like
        The template's and the patient's landmarks: a landmark file (CSV ``label,x,y,z`` or a
        3D Slicer ``.mrk.json``, read by :func:`~o3dreg.read_landmarks`), a pair of a label
        sequence and an ``(l, 3)`` array, or bare points. Labelled landmarks are paired by label
        (the order may differ; every label must be on both sides); bare points by order. At
        least 3 pairs, not all on one line. Files are read in LPS, as o3dreg's meshes are
        (:func:`~o3dreg.read_landmarks` converts RAS files that say so). In the input's units;
        not modified.
    with_scaling : bool, optional
        Also estimate a uniform scale (a similarity: e.g. a template of another size, or
        landmarks in other units). Default ``False``.
    labels : sequence of str, optional
        The pairs to use, by label (labelled landmarks only): each must be on both sides, and
        the others are left out (e.g. landmarks of anatomy a mesh does not show). Default:
        every landmark.

    Returns
    -------
    LandmarkRegistrationResult
        ``transformation`` is the ``init`` for :func:`~o3dreg.registration_elastic`;
        ``residuals`` the distance left at each pair.

    Raises
    ------
    ValueError
        Fewer than 3 pairs, labels that do not match, repeated labels, a label of ``labels``
        missing on a side (naming that side's labels), or landmarks on one line (or in one
        point): the rotation about that line is undetermined.

    References
    ----------
    .. [1] S. Umeyama, "Least-squares estimation of transformation parameters between two
       point patterns", IEEE TPAMI 13(4), 1991. :doi:`10.1109/34.88573`

    Examples
    --------
    >>> import numpy as np
    >>> from o3dreg import registration_landmarks
    >>> template = np.array([[0.0, 0, 0], [10, 0, 0], [0, 20, 0], [0, 0, 5]])
    >>> patient = 2.0 * template + (1.0, 2.0, 3.0)
    >>> result = registration_landmarks(template, patient, with_scaling=True)
    >>> round(result.scale, 6), bool(result.rms < 1e-9)
    (2.0, True)
    """
    with_scaling = check_bool(with_scaling, "with_scaling")
    paired, ps, pt = _pair(source, target, labels)
    if ps.shape[0] < 3:
        raise ValueError(
            f"`source` and `target` must hold at least 3 landmark pairs, got {ps.shape[0]}"
            + ("" if labels is None else f" (`labels` chooses {', '.join(paired)})")
        )
    for name, pts in (("source", ps), ("target", pt)):
        with np.errstate(over="ignore", invalid="ignore"):
            centred = pts - pts.mean(axis=0)
            finite = np.isfinite((centred * centred).sum())
        if not finite:
            # LAPACK's SVD of inf/NaN spins without end (and ignores SIGTERM): refuse first.
            raise ValueError(
                f"`{name}` landmark coordinates must be finite numbers of a plausible size, got "
                f"values up to {float(np.abs(pts).max()):.3g}: their squares overflow"
            )
        singular = np.linalg.svd(centred, compute_uv=False)
        if singular[0] <= 0.0 or singular[1] < COLLINEAR_TOLERANCE * singular[0]:
            raise ValueError(
                f"`{name}` landmarks are degenerate (all on one line or in one point): the "
                "rotation about that line is undetermined; add a landmark off the line"
            )
    t = fit_pose(ps, pt, with_scaling)
    residuals = np.linalg.norm(apply_transformation(t, ps) - pt, axis=1)
    scale = float(np.cbrt(np.linalg.det(t[:3, :3])))
    warnings = _fit_findings(paired, ps, pt, residuals, with_scaling)
    for line in warnings:
        logger.warning("registration_landmarks: %s", line)
    return LandmarkRegistrationResult(t, tuple(paired), residuals, scale, warnings)
