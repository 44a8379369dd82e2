"""Rigid (or similarity) pre-alignment: the paper's initial rototranslation.

Several starting poses are refined by Open3D's ICP and ranked by the symmetric surface distance
on the whole target: the input pose (as given, and with centroids matched), the four moment
frames (area-weighted centroids and principal axes, one per proper choice of axis signs) and,
where two principal values are close (a head, a sphere-like bone: the axes in their plane are
then arbitrary), a deterministic sampling of rotations. The winner and the best distinct other
pose are both reported; a near tie is an ambiguity and comes with a warning. The source's mirror
image is searched from its moment frames beside them: where it fits clearly better, the target
may be the other side (left and right swapped), and a warning says so.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterator
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import contextmanager
from functools import cached_property
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .._geometry import (
    apply_transformation,
    face_doubled_areas,
    fit_pose,
    rotation_angle,
    row_norms,
)
from .._text import ratio_text
from .._validation import as_mesh_arrays, as_transformation, check_bool, check_positive
from ..mesh.canonical import cluster_vertices
from ..mesh.edges import SortedEdges
from ..mesh.noise import noise_level
from ..mesh.sampling import spatial_subsample
from .distance import SurfaceDistanceQuery

__all__ = [
    "RigidRegistrationResult",
    "SizeMismatch",
    "moment_alignments",
    "registration_rigid",
    "rigid_candidates",
    "surface_moments",
]

logger = logging.getLogger("o3dreg")
reg = o3d.pipelines.registration

#: Two principal values closer than this (relative to the larger) leave the principal axes in
#: their plane undetermined: a 20% difference is within the variation between patients of a
#: near-round bone (the demo's head: 6% to 28%), so the moment frames alone cannot be trusted.
CLOSE_PRINCIPAL_VALUES = 0.2
#: Rotations sampled (super-Fibonacci, deterministic) when principal values are close; the
#: :data:`SAMPLED_KEPT` best before ICP (by a cheap nearest-point score) are refined.
SAMPLED_ROTATIONS = 72
SAMPLED_KEPT = 8
#: Sizes (RMS radius about the centroid) differing by more than this factor are taken for
#: different units (10 for cm vs mm, 25.4 for inches, 1000 for m), not anatomy: adult bones of
#: one kind vary far less than 3 times in linear size.
MAX_SIZE_RATIO = 3.0
#: A target with fewer triangles cannot determine a pose, let alone a deformation (one
#: triangle's moments say nothing of a bone's): refused before any work.
MIN_TARGET_TRIANGLES = 4
#: A target whose open edges are longer than this times the square root of its area is
#: taken as partial: the bunny with its holes 1.4, cut by 10-50% of its height 3.3-5.6, its
#: front half 3.8; a bone surface from CT is closed (0). A partial target's moments are not the
#: template's, so its moment frames say little of the pose: rotations are sampled for it as for
#: close principal values (bunny parts, half to a third of it, turned at random: 40 of 60 right
#: poses against 38, one wrong pose without the ambiguity warning against two). A scale found on
#: it is warned about.
PARTIAL_BOUNDARY = 2.5
#: A distinct pose whose score is within this factor of the winner's is an ambiguity: the
#: demo's flipped poses score 1.7-2.5 times the right one.
AMBIGUITY_RATIO = 1.2
#: The opening words of the ambiguity warning.
AMBIGUOUS_START = "the rigid start is ambiguous"
#: The template's mirror image is searched from its four moment frames beside the template; a
#: mirror image that scores this many times better than the template's winning pose is warned
#: about (left and right swapped?). A chiral shape fits its own mirror image far worse: the
#: asymmetric blob under a 3% warp, 1.7 times worse; mirrored, the mirror image 1.7 times better.
#: A bilaterally symmetric bone fits both alike (CT mandibles: 0.93-1.01), as a nearly
#: symmetric shape is its own mirror image; fit_shape_model uses the same factor.
MIRROR_RATIO = 1.25
#: The mirror image is refined (as the winner is) only where its search scored this many times
#: better than the template's: refining moves a warped target's scores by up to a fifth (the
#: blob under an 8% warp, mirrored: 1.18 times at the search, 1.42 refined), while a bilaterally
#: symmetric bone's two searches stay within 4% of each other (CT mandibles: 0.96-1.04).
MIRROR_SEARCH_RATIO = 1.1
#: The opening words of the names of the mirror image's starts.
MIRROR_IMAGE = "mirror image"
#: A near tie is broken by the input pose when one of the two poses is within the first of these
#: rotations of it and the other beyond the second: scans of one protocol come in a common
#: orientation (the demo's patients within 10 degrees, the test populations within 40), while the
#: poses a near-symmetric shape confuses are a half-turn apart. The nearer pose is kept.
INPUT_POSE_NEAR = 45.0
INPUT_POSE_FAR = 90.0
#: The input pose is also refined where it lies, as the winner is (all points, the refinement's
#: correspondence distance), beside the search from it, and wins if it scores best: a scan given
#: near its pose is in that pose's basin, which the search's coarse ICP at four times the
#: distance can leave on a noisy, partial target (the bunny under a 5% warp without its top
#: 30-40% and with noise of 0.5-2% of its diagonal per axis, 32 targets: 10 winners 30-80
#: degrees off, one of them without the ambiguity warning; with the input pose refined in place,
#: every winner within 13 degrees).
INPUT_POSE_REFINED = "input pose, refined in place"
#: Points of the coarse target and of the source subsample the search from many starts works
#: on (ICP and scores): the search only ranks poses, which the refinement then polishes on the
#: full surfaces, so a few hundred source points pick the same winners as many more.
SEARCH_POINTS = 1000
SEARCH_SOURCE_POINTS = 500
#: The search from many starts pairs points up to 4 times ``max_correspondence_distance`` apart
#: (a wide basin); with the default point-to-plane estimation it weighs each pair by Tukey's
#: biweight of width this many times ``max_correspondence_distance`` (pairs beyond it count
#: nothing), so that the template's parts without data on a partial target, paired with its rim
#: or another part, do not drag the pose. The bunny's parts under noise of up to 1% of the
#: diagonal, turned at random (``bench_robust.py --turned-parts``): 1 wrong pose in 128 against
#: 6 unweighted, whose wrong winners scored 25-41% above the right pose refined (no start had
#: reached its basin); under 2% noise half of them are lost either way. Whole targets keep their
#: poses; a partial one's search takes about 25% longer. A width of 1 lost the bottom 30% of the
#: bunny (its far starts' pairs all weighed nothing).
SEARCH_KERNEL_WIDTH = 2.0
#: The runner-up is refined (as the winner is) only when its score from the search is below this
#: factor times the winner's refined score: the refinement changes a pose's score by a few
#: percent, far less than a pose twice as far would need to come within AMBIGUITY_RATIO of the
#: winner.
RUNNER_UP_REFINED = 2.0
#: ICP runs in bursts of this many iterations (even: see :meth:`_CandidateSearch.icp`) and stops
#: when a burst moves the source by less than a fraction of the target's diagonal (RMS): at the
#: search from many starts, SEARCH_STILL (its poses are only starts for the refinement, which
#: moves them by far more); at the refinement, REFINE_STILL (below what the correspondences'
#: alternation near convergence moves the pose by at every iteration, and far below what a
#: decimated template can fix the pose to).
ICP_BURST = 4
SEARCH_STILL = 1e-4
REFINE_STILL = 1e-5
#: A target of more vertices is aligned to in a copy simplified by vertex clustering to about
#: DETAIL_VERTICES (tens of times a template's density): the trees and moments of a
#: million-vertex target cost seconds, and its detail below the template's spacing moves no
#: pose.
LARGE_TARGET = 200_000
DETAIL_VERTICES = 100_000
#: Threads that run the candidate search's ICP starts (and the runner-up's refinement beside the
#: winner's) side by side. Open3D's ICP releases the GIL and each run is independent and on one
#: thread, so the poses and scores are those of running them one after the other (tested); the
#: scores stay in the calling thread (libigl's queries hold the GIL, which also holds back the
#: ICP threads between their bursts).
SEARCH_THREADS = 4
#: Two poses are distinct when the source vertices they place differ by more than this fraction
#: of the target's bounding-box diagonal (RMS): about what ICP's basin of attraction spans.
DISTINCT_POSE = 0.05
#: On a noisy target, two poses are distinct only when the source vertices they place differ by
#: more than DISTINCT_POSE plus this many times the target's noise (``noise_level``, RMS): every
#: target point lies off the surface by about that much, so poses closer than that fit it alike.
#: Measured on the bunny under isotropic noise of 2-4% of its diagonal per axis: ICP from
#: different starts ends at poses 1-10 degrees apart, up to 0.9 noise levels beyond
#: DISTINCT_POSE, scoring within 1-7% of each other; the half-turn that noise of 5% makes score
#: within 3-11% of the right pose lies 5-7 noise levels beyond (and stays distinct). On a clean
#: surface the noise is a fraction of a percent of the diagonal and changes nothing.
DISTINCT_NOISE = 2.0
#: Noise lifts every pose's score (the symmetric distance) by about half the noise level (0.45-0.75
#: of it measured on the bunny under noise of 0.2-5% of its diagonal): a target's noise is taken
#: to be at most this many times the winner's score, so a pose farther than that noise would blur
#: is distinct without measuring it (the half-turns of a clean target: no cost).
NOISE_PER_SCORE = 4.0
#: A near tie on a target whose noise exceeds this fraction of its diagonal is not broken by the
#: input pose: noise of that size blurs poses a half-turn apart into a tie (the bunny with
#: isotropic noise of 4-5% of its diagonal per axis, a 1000-vertex template: wrong poses score
#: within 15% of the right one, or below it), so the tie says nothing of a symmetry and the
#: input pose nothing of the answer. Up to 3% per axis the right pose wins clearly (runner-ups
#: score 1.3 times it or more). Measured only where it matters: a tie the input pose would break.
NOISY_TIE = 0.02
#: ...and whose winning score is at least this fraction of the measured noise: a faceted shape
#: (a box) reads as noisy at its corners (:func:`~o3dreg.mesh.noise.noise_level`), while it fits
#: itself exactly; a noisy target's best fit stays about half its noise away (NOISE_PER_SCORE).
NOISY_TIE_SCORE = 0.25


def surface_moments(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Area, centroid and covariance of a triangulated surface (exact integrals).

    Uses ``int_T x x^T dA = A / 12 (sum_i v_i v_i^T + s s^T)`` with ``s = v_0 + v_1 + v_2``, so
    the result does not depend on how densely the surface is sampled.

    Returns
    -------
    area : float
    centroid : (3,) ndarray
    covariance : (3, 3) ndarray
        ``1/A int (x - c)(x - c)^T dA``.
    """
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    areas = 0.5 * face_doubled_areas(vertices, faces)
    area = float(areas.sum())
    if area <= 0:
        raise ValueError("the surface has zero area")
    s = a + b + c
    centroid = areas @ s / (3.0 * area)
    second = np.zeros((3, 3))
    for p in (a, b, c, s):  # (3, m) @ (m, 3) products: twice as fast as a three-operand einsum
        second += (p * areas[:, None]).T @ p
    second /= 12.0 * area
    return area, centroid, second - np.outer(centroid, centroid)


def moment_alignments(
    source: tuple[np.ndarray, np.ndarray],
    target: tuple[np.ndarray, np.ndarray],
    *,
    with_scaling: bool = False,
) -> list[np.ndarray]:
    """The four candidate transformations matching centroids and principal axes.

    Returns
    -------
    list of (4, 4) ndarray
        ``T`` with ``T @ [x, 1]`` mapping the source's principal frame onto the target's, one
        per proper (determinant +1) choice of axis signs.
    """
    return _moment_frames(surface_moments(*source), surface_moments(*target), with_scaling)


def _moment_frames(
    source: tuple[float, np.ndarray, np.ndarray],
    target: tuple[float, np.ndarray, np.ndarray],
    with_scaling: bool,
) -> list[np.ndarray]:
    """:func:`moment_alignments` from the two surfaces' :func:`surface_moments`."""
    _, cs, covs = source
    _, ct, covt = target
    ls, es = np.linalg.eigh(covs)
    lt, et = np.linalg.eigh(covt)
    es, et = es[:, ::-1], et[:, ::-1]
    scale = float(np.sqrt(lt.sum() / ls.sum())) if with_scaling else 1.0
    out = []
    for signs in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]):
        rot = et @ np.diag(signs) @ es.T
        if np.linalg.det(rot) < 0:
            rot = et @ np.diag(signs) @ np.diag([1, 1, -1]) @ es.T
        t = np.eye(4)
        t[:3, :3] = scale * rot
        t[:3, 3] = ct - scale * rot @ cs
        out.append(t)
    return out


def _sampled_rotations(count: int) -> np.ndarray:
    """``count`` rotations spread evenly over SO(3), deterministic (super-Fibonacci spirals,
    Alexa 2022, :doi:`10.1109/CVPR52688.2022.00801`)."""
    phi, psi = np.sqrt(2.0), 1.533751168755204288118041
    s = np.arange(count) + 0.5
    r, big = np.sqrt(s / count), np.sqrt(1.0 - s / count)
    alpha, beta = 2.0 * np.pi * s / phi, 2.0 * np.pi * s / psi
    x, y, z, w = r * np.sin(alpha), r * np.cos(alpha), big * np.sin(beta), big * np.cos(beta)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _has_close_principal_values(covariance: np.ndarray) -> bool:
    values = np.clip(np.linalg.eigvalsh(covariance), 0.0, None)
    gaps = np.diff(values) / np.maximum(values[1:], 1e-300)
    return bool(np.any(gaps < CLOSE_PRINCIPAL_VALUES))


def rigid_candidates(
    source: tuple[np.ndarray, np.ndarray],
    target: tuple[np.ndarray, np.ndarray],
    *,
    with_scaling: bool = False,
) -> list[tuple[str, np.ndarray]]:
    """The starting poses :func:`registration_rigid` refines and ranks.

    Parameters
    ----------
    source, target : tuple of (n, 3) ndarray and (m, 3) int ndarray
        Valid triangle meshes (vertices, faces).
    with_scaling : bool, optional
        Scale the source to the target's size (RMS radius about the centroid) in every pose but
        the input pose.

    Returns
    -------
    list of (str, (4, 4) ndarray)
        A name and a transformation for each: ``'input pose'`` (the identity),
        ``'centroids matched'``, ``'moment frame 1'`` to ``'moment frame 4'`` and, when two
        principal values of either surface are within :data:`CLOSE_PRINCIPAL_VALUES` of each
        other or the target is partial (:data:`PARTIAL_BOUNDARY`), ``'sampled rotation k'``
        (:data:`SAMPLED_ROTATIONS` rotations about the centroids, in a fixed order).
    """
    partial = open_boundary_ratio(*target) > PARTIAL_BOUNDARY
    return _candidates(surface_moments(*source), surface_moments(*target), with_scaling, partial)


def _candidates(
    source: tuple[float, np.ndarray, np.ndarray],
    target: tuple[float, np.ndarray, np.ndarray],
    with_scaling: bool,
    partial: bool = False,
) -> list[tuple[str, np.ndarray]]:
    """:func:`rigid_candidates` from the two surfaces' :func:`surface_moments` (``partial``:
    whether the target is)."""
    _, cs, covs = source
    _, ct, covt = target
    scale = _size_ratio(covs, covt) if with_scaling else 1.0
    out: list[tuple[str, np.ndarray]] = [("input pose", np.eye(4))]
    matched = np.eye(4)
    matched[:3, :3] *= scale
    matched[:3, 3] = ct - scale * cs
    out.append(("centroids matched", matched))
    moments = _moment_frames(source, target, with_scaling)
    out += [(f"moment frame {k + 1}", t) for k, t in enumerate(moments)]
    if partial or _has_close_principal_values(covs) or _has_close_principal_values(covt):
        for k, rot in enumerate(_sampled_rotations(SAMPLED_ROTATIONS)):
            t = np.eye(4)
            t[:3, :3] = scale * rot
            t[:3, 3] = ct - scale * rot @ cs
            out.append((f"sampled rotation {k + 1}", t))
    return out


def _mirror_starts(
    source: tuple[float, np.ndarray, np.ndarray], candidates: list[tuple[str, np.ndarray]]
) -> list[tuple[str, np.ndarray]]:
    """The moment frames of ``candidates`` applied to the source's mirror image (its reflection
    through its centroid across the plane of its two largest principal axes): the four
    improper choices of axis signs."""
    _, cs, covs = source
    axis = np.linalg.eigh(covs)[1][:, 0]
    mirror = np.eye(4)
    mirror[:3, :3] -= 2.0 * np.outer(axis, axis)
    mirror[:3, 3] = 2.0 * axis * (axis @ cs)
    return [
        (f"{MIRROR_IMAGE}, {name}", t @ mirror)
        for name, t in candidates
        if name.startswith("moment frame")
    ]


def _size_ratio(cov_source: np.ndarray, cov_target: np.ndarray) -> float:
    """Target size over source size (RMS radius about the centroid)."""
    return float(np.sqrt(max(np.trace(cov_target), 1e-300) / max(np.trace(cov_source), 1e-300)))


class RigidRegistrationResult(reg.RegistrationResult):  # type: ignore[misc]
    """Open3D's ``RegistrationResult``, plus how the starting pose was chosen.

    Attributes
    ----------
    transformation : (4, 4) ndarray
        Maps the source onto the target (``init`` included).
    fitness, inlier_rmse : float
        As Open3D's ICP computes them at ``max_correspondence_distance``.
    correspondence_set : open3d.utility.Vector2iVector
    score : float
        The winner's symmetric surface distance: the mean of the mean source->target
        point-to-surface distance and the mean target->source one (target points to the moved
        source surface), on the whole target, in the input's units.
    runner_up_score : float or None
        The same for the best pose distinct from the winner (its source vertices more than
        :data:`DISTINCT_POSE` of the target's diagonal away, RMS, and on a noisy target more
        than :data:`DISTINCT_NOISE` times its noise beyond), after the same refinement when
        it came within :data:`RUNNER_UP_REFINED` of the winner (otherwise its score from the
        search, the pose too far behind to come near the winner); lower than ``score`` when the
        input pose broke a near tie in its favour. ``None`` when there was none (a given
        ``init``, or every start reached one pose).
    runner_up_transformation : (4, 4) ndarray or None
    candidates : int
        Starting poses tried.
    warnings : tuple of str
        Plain sentences: an ambiguity (:attr:`ambiguous`), a scale found on a partial target,
        an ``init`` from which ICP found no correspondence.
    ambiguous : bool
        Whether a distinct pose scored within :data:`AMBIGUITY_RATIO` of the winner, untold
        apart by the input pose (then a warning says so).
    mirror_score : float or None
        The same score for the source's mirror image, searched from its moment frames and
        refined where its search scored :data:`MIRROR_SEARCH_RATIO` times better than the
        template's (else ``None``); a warning says so when it stays that much better (:attr:`mirrored`).

    Parameters
    ----------
    icp : open3d.pipelines.registration.RegistrationResult, optional
        The winning ICP result, whose transformation, fitness, RMSE and correspondences are
        copied; the other arguments set the attributes of the same names.
    """

    def __init__(
        self,
        icp: Any = None,
        *,
        score: float = float("nan"),
        runner_up_score: float | None = None,
        runner_up_transformation: np.ndarray | None = None,
        candidates: int = 0,
        warnings: tuple[str, ...] = (),
        ambiguous: bool = False,
    ) -> None:
        super().__init__()
        if icp is not None:
            self.transformation = icp.transformation
            self.fitness = icp.fitness
            self.inlier_rmse = icp.inlier_rmse
            self.correspondence_set = icp.correspondence_set
        self.score = float(score)
        self.runner_up_score = None if runner_up_score is None else float(runner_up_score)
        self.runner_up_transformation = runner_up_transformation
        self.candidates = int(candidates)
        self.warnings = tuple(warnings)
        self._ambiguous = bool(ambiguous)
        self.mirror_score: float | None = None

    @property
    def ambiguous(self) -> bool:
        """Whether a distinct pose scored within :data:`AMBIGUITY_RATIO` of the winner and the
        input pose did not tell them apart (:data:`INPUT_POSE_NEAR`, :data:`INPUT_POSE_FAR`)."""
        return self._ambiguous

    @property
    def mirrored(self) -> bool:
        """Whether the source's mirror image fits the target :data:`MIRROR_RATIO` times better
        than the source: the target may be the other side (left and right swapped)."""
        return self.mirror_score is not None and self.score > MIRROR_RATIO * self.mirror_score

    def __repr__(self) -> str:
        runner = "none" if self.runner_up_score is None else f"{self.runner_up_score:.4g}"
        return (
            f"RigidRegistrationResult(fitness={self.fitness:.4g}, "
            f"inlier_rmse={self.inlier_rmse:.4g}, score={self.score:.4g}, runner_up={runner}, "
            f"candidates={self.candidates}, ambiguous={self.ambiguous})"
        )


def registration_rigid(
    source: Any,
    target: Any,
    *,
    init: Any = None,
    max_correspondence_distance: float | None = None,
    with_scaling: bool = False,
    estimation_method: Any = None,
    criteria: Any = None,
) -> RigidRegistrationResult:
    """Rigid or similarity alignment of ``source`` onto ``target``.

    Without ``init``, every pose of :func:`rigid_candidates` is refined by ICP (at four times
    ``max_correspondence_distance``, a subsample of the source against a coarse copy of the
    target; with the default estimation, each pair weighed by Tukey's biweight,
    :data:`SEARCH_KERNEL_WIDTH`) and scored by the symmetric surface distance on the whole
    target; the best pose is refined at ``max_correspondence_distance`` with all points and
    scored again, and so is the best distinct other pose unless it scored more than
    :data:`RUNNER_UP_REFINED` times the winner. The input pose is also refined where it lies,
    on all points, and wins if it scores best (:data:`INPUT_POSE_REFINED`). The lower score
    wins. Each ICP runs on one thread (the
    starts side by side, see :data:`SEARCH_THREADS`), so the same input gives a bit-identical
    pose.
    A target of more than :data:`LARGE_TARGET` vertices is aligned to in a copy simplified by
    vertex clustering to about :data:`DETAIL_VERTICES` vertices (``fitness``, ``inlier_rmse``
    and the scores are measured on it).

    Parameters
    ----------
    source : open3d.geometry.TriangleMesh or (vertices, faces)
        The template: the surface that moves. Not modified.
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface the source is matched to. Not modified.
    init : (4, 4) array_like, optional
        Initial transformation. When given, the candidate search (and the size check) is
        skipped and ICP starts from it.
    max_correspondence_distance : float, optional
        ICP's inlier distance, in the input's units. Default: 5% of the target's bounding-box
        diagonal (after a first pass at 4 times that).
    with_scaling : bool, optional
        Estimate a uniform scale too (similarity). Uses point-to-point ICP, as Open3D's
        point-to-plane estimation has no scale.
    estimation_method : open3d.pipelines.registration.TransformationEstimation, optional
        Default: ``TransformationEstimationPointToPlane()`` (or ``PointToPoint(with_scaling=True)``
        when ``with_scaling``).
    criteria : open3d.pipelines.registration.ICPConvergenceCriteria, optional
        Default: 50 iterations, relative fitness and RMSE 1e-6. ICP also stops when
        :data:`ICP_BURST` iterations move the source by less than :data:`REFINE_STILL` of the
        target's diagonal (RMS): near convergence, the correspondences can alternate between
        two sets and keep the RMSE test from ever stopping it.

    Returns
    -------
    RigidRegistrationResult
        An ``open3d.pipelines.registration.RegistrationResult``: ``transformation`` maps
        ``source`` onto ``target`` (``init`` included), ``fitness`` and ``inlier_rmse`` as
        Open3D computes them at ``max_correspondence_distance``; plus the winner's and the
        runner-up's scores and ``warnings`` (a near tie between distinct poses: the shape is
        nearly symmetric and the pose may be wrong; start from landmarks then).

    Raises
    ------
    ValueError
        Without ``init`` and ``with_scaling``, when the two surfaces' sizes differ by more than
        :data:`MAX_SIZE_RATIO` (different units): convert one of them, or pass
        ``with_scaling=True`` for a similarity start.

    Examples
    --------
    >>> import open3d as o3d, numpy as np
    >>> from o3dreg import registration_rigid
    >>> mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 4.0)
    >>> moved = o3d.geometry.TriangleMesh(mesh).translate((0.2, -0.1, 0.3))
    >>> result = registration_rigid(mesh, moved)
    >>> bool(np.allclose(result.transformation[:3, 3], (0.2, -0.1, 0.3), atol=1e-6))
    True
    """
    vs, fs = as_mesh_arrays(source, "source", drop_degenerate=True)
    vt, ft = as_mesh_arrays(target, "target", drop_degenerate=True)
    return _registration_rigid(
        vs,
        fs,
        vt,
        ft,
        None,
        init=init,
        max_correspondence_distance=max_correspondence_distance,
        with_scaling=with_scaling,
        estimation_method=estimation_method,
        criteria=criteria,
    )


def mirror_warnings(result: RigidRegistrationResult) -> tuple[str, ...]:
    """The warning for a ``result`` whose source's mirror image fits better
    (:attr:`RigidRegistrationResult.mirrored`); empty otherwise."""
    if not result.mirrored:
        return ()
    score, mirror = result.score, float(result.mirror_score or 0.0)
    return (
        f"the template's mirror image fits the target {ratio_text(score, mirror)} times "
        f"better than the template (symmetric distances {mirror:.3g} and {score:.3g}): the "
        "target may be the other side (left and right swapped); register the other side's "
        "template, or mirror the target",
    )


def default_start(
    vs: np.ndarray,
    fs: np.ndarray,
    target: SurfaceDistanceQuery,
    *,
    with_scaling: bool = False,
    mirror: bool = True,
) -> RigidRegistrationResult:
    """``registration_rigid((vs, fs), (target.vertices, target.faces),
    with_scaling=with_scaling)`` with its other defaults, for a target already validated and
    given with its distance query (``registration_elastic``'s): the AABB tree of a large target
    is not built a second time. ``mirror=False`` leaves out the mirror check (a caller that
    checks reflections its own way: ``fit_shape_model``)."""
    vs, fs = as_mesh_arrays((vs, fs), "source", drop_degenerate=True)
    return _registration_rigid(
        vs, fs, target.vertices, target.faces, target, with_scaling=with_scaling, mirror=mirror
    )


def check_given_start(
    vs: np.ndarray,
    fs: np.ndarray,
    target: SurfaceDistanceQuery,
    init: np.ndarray,
    moved: np.ndarray,
) -> RigidRegistrationResult | None:
    """The rigid search, run to check a registration from a given ``init``.

    Given ``init`` 60-135 degrees off, the levels wrap the template onto the target's wrong
    parts, to surface distances as small as a right registration's and without a fold (an
    asymmetric blob, a long bone, a skull-like cap: 10-45% of the diagonal from the truth, every
    other finding quiet). The pose the registration took (the least-squares fit of the source
    ``vs`` onto its registered vertices ``moved``) is then far from the pose the search finds
    and scores far worse (2.4-12 times the search's pose, 9-62% of the diagonal from it),
    while right ones from starts 0-60 degrees off end within 2% of the diagonal of it.

    Returns
    -------
    RigidRegistrationResult or None
        The search's winner, its ``warnings`` replaced by one sentence when it is distinct from
        the registration's pose (as the search tells distinct poses) and scores better than it
        by more than :data:`AMBIGUITY_RATIO`, else empty. A search that is itself ambiguous
        (two distinct poses in a near tie: a near-symmetric shape) warns of nothing: ``init``
        settles such a tie (a quadric template of a long bone onto its own surface: the
        search's two best poses, half a turn apart, both score better than the exact pose).
        ``None`` when the search cannot run: sizes apart by more than
        :data:`MAX_SIZE_RATIO`, or a source too small to pose.
    """
    scale = float(np.cbrt(abs(np.linalg.det(init[:3, :3]))))
    scaling = abs(scale - 1.0) > 1e-9
    try:
        winner = default_start(vs, fs, target, with_scaling=scaling)
    except ValueError:  # SizeMismatch or a source too small: the verdict's size rule speaks
        return None
    taken = fit_pose(vs, moved, scaling)
    diagonal = float(np.linalg.norm(np.ptp(target.vertices, axis=0)))
    search = _CandidateSearch(
        vs, fs, target.vertices, target.faces, 0.05 * diagonal, diagonal, target
    )
    found = np.asarray(winner.transformation)
    # The registration's pose is scored as the search scores its own poses, refined by ICP, as
    # long as the refinement stays in its basin: a decimated template's exact pose scores up to
    # twice its refined one (a long bone onto its own surface: 0.21 against 0.12), while ICP
    # from a wrapped template's pose leaves for another basin.
    taken_score = search.score(taken)
    method = (
        reg.TransformationEstimationPointToPoint(with_scaling=True)
        if scaling
        else reg.TransformationEstimationPointToPlane()
    )
    refined = np.asarray(
        search.refine(taken, method, reg.ICPConvergenceCriteria(1e-6, 1e-6, 50)).transformation
    )
    if not search.distinct(refined, taken):
        taken_score = min(taken_score, search.score(refined))
    # What the search says of the pose is `init`'s to settle; a mirror image is not.
    winner.warnings = mirror_warnings(winner)
    # The search's own near tie (a symmetric shape) is `init`'s to settle.
    tied = winner.ambiguous or search.tie(winner.score, taken_score)
    if tied or not search.distinct(found, taken, winner.score):
        return winner
    turn = rotation_angle(found @ np.linalg.inv(taken))
    winner.warnings += (
        f"the registration from the given `init` ended in a pose {turn:.0f} degrees from the "
        "one the rigid search finds, which fits the target "
        f"{ratio_text(taken_score, winner.score)} times better (symmetric distance "
        f"{winner.score:.3g} against {taken_score:.3g}): the levels may have wrapped the "
        "template onto the wrong parts; check `init`, or leave it out for the rigid search",
    )
    return winner


def _registration_rigid(
    vs: np.ndarray,
    fs: np.ndarray,
    vt: np.ndarray,
    ft: np.ndarray,
    target_query: SurfaceDistanceQuery | None,
    *,
    init: Any = None,
    max_correspondence_distance: float | None = None,
    with_scaling: bool = False,
    estimation_method: Any = None,
    criteria: Any = None,
    mirror: bool = True,
) -> RigidRegistrationResult:
    """:func:`registration_rigid` on validated arrays; ``target_query``: the target's distance
    query when one exists (built here otherwise); ``mirror``: whether the source's mirror image
    is searched too (:data:`MIRROR_RATIO`)."""
    if vt.shape[0] > LARGE_TARGET:
        vt, ft = _simplified(vt, ft, DETAIL_VERTICES)
        target_query = None
    with_scaling = check_bool(with_scaling, "with_scaling")
    given = init is not None
    if given:
        candidates = [("init", as_transformation(init, "init", similarity=True))]
    else:
        _check_target(ft)
        if fs.shape[0] < MIN_TARGET_TRIANGLES:
            # A triangle's moments say nothing of a shape's pose (its size check would blame
            # the units).
            raise ValueError(
                f"`source` must be a surface of at least {MIN_TARGET_TRIANGLES} non-degenerate "
                f"triangles for its pose to be searched, got {fs.shape[0]}: give `init`"
            )
        # Each surface's moments once: they serve the size check and every start.
        moments_s, moments_t = surface_moments(vs, fs), surface_moments(vt, ft)
        if not with_scaling:
            _check_sizes(moments_s[2], moments_t[2])
        known = target_query.open_edges[0] if target_query is not None else None
        cut = open_boundary_ratio(vt, ft, known)
        candidates = _candidates(moments_s, moments_t, with_scaling, cut > PARTIAL_BOUNDARY)
        if mirror:
            candidates += _mirror_starts(moments_s, candidates)
    diagonal = float(np.linalg.norm(np.ptp(vt, axis=0)))
    if max_correspondence_distance is None:
        max_correspondence_distance = 0.05 * diagonal
    else:
        max_correspondence_distance = check_positive(
            max_correspondence_distance, "max_correspondence_distance"
        )
    search_method = None
    if estimation_method is None:
        estimation_method = (
            reg.TransformationEstimationPointToPoint(with_scaling=True)
            if with_scaling
            else reg.TransformationEstimationPointToPlane()
        )
        if not with_scaling:
            search_method = reg.TransformationEstimationPointToPlane(
                reg.TukeyLoss(SEARCH_KERNEL_WIDTH * max_correspondence_distance)
            )
    elif not isinstance(estimation_method, reg.TransformationEstimation):
        raise TypeError(
            "`estimation_method` must be an open3d.pipelines.registration.TransformationEstimation,"
            f" got {type(estimation_method).__name__}"
        )
    elif isinstance(estimation_method, reg.TransformationEstimationForColoredICP):
        # It needs the colours of point clouds; o3dreg aligns surfaces by their geometry.
        raise ValueError(
            "`estimation_method` must estimate from geometry (point-to-point, point-to-plane or "
            "generalized ICP), got TransformationEstimationForColoredICP, which needs colours"
        )
    if criteria is None:
        criteria = reg.ICPConvergenceCriteria(1e-6, 1e-6, 50)
    elif not isinstance(criteria, reg.ICPConvergenceCriteria):
        raise TypeError(
            "`criteria` must be an open3d.pipelines.registration.ICPConvergenceCriteria, "
            f"got {type(criteria).__name__}"
        )
    with _single_thread():
        search = _CandidateSearch(
            vs, fs, vt, ft, max_correspondence_distance, diagonal, target_query, search_method
        )
        if given:
            return _refined_init(search, candidates[0][1], estimation_method, criteria)
        result = search.run(candidates, estimation_method, criteria)
    if with_scaling and cut > PARTIAL_BOUNDARY:
        scale = float(np.cbrt(np.linalg.det(np.asarray(result.transformation)[:3, :3])))
        result.warnings += (
            f"the scale ({scale:.3g}) was found on a target with a long open boundary "
            f"(its length {cut:.2g} times the square root of its area: a partial scan?); "
            "a part of a shape fits a smaller template, so the scale may be wrong: give the "
            "target in the template's units and leave the scaling off",
        )
        logger.warning("registration_rigid: %s", result.warnings[-1])
    return result


def _refined_init(
    search: _CandidateSearch, init: np.ndarray, method: Any, criteria: Any
) -> RigidRegistrationResult:
    """The given ``init`` refined by ICP; said when ICP found no pair to refine it with."""
    final = search.refine(init, method, criteria)
    warnings: tuple[str, ...] = ()
    if final.fitness == 0:
        warnings = (
            f"no target point lies within max_correspondence_distance ({search.distance:.3g}) "
            "of the source moved by `init`: ICP left `init` unrefined; check `init` (and the "
            "units of both surfaces) or raise max_correspondence_distance",
        )
        logger.warning("registration_rigid: %s", warnings[0])
    return RigidRegistrationResult(
        final,
        score=search.score(np.asarray(final.transformation)),
        candidates=1,
        warnings=warnings,
    )


def open_boundary_ratio(
    vertices: np.ndarray, faces: np.ndarray, open_edge: np.ndarray | None = None
) -> float:
    """Total length of a surface's open edges over the square root of its area (scale-free;
    ``open_edge``: the surface's per-triangle open-edge table, where known)."""
    if open_edge is None:
        open_edge, _ = SortedEdges(vertices.shape[0], faces).open_edges()
    length = 0.0
    for k in range(3):
        rows = np.flatnonzero(open_edge[:, k])
        a, b = faces[rows, (k + 1) % 3], faces[rows, (k + 2) % 3]
        length += float(row_norms(vertices[a] - vertices[b]).sum())
    area = 0.5 * float(face_doubled_areas(vertices, faces).sum())
    return length / np.sqrt(area) if area > 0 else 0.0


def _check_target(ft: np.ndarray) -> None:
    if ft.shape[0] < MIN_TARGET_TRIANGLES:
        raise ValueError(
            f"`target` must be a surface of at least {MIN_TARGET_TRIANGLES} non-degenerate "
            f"triangles to register onto, got {ft.shape[0]}: is it the right file?"
        )


class SizeMismatch(ValueError):
    """Source and target differ in size beyond :data:`MAX_SIZE_RATIO` (other units?)."""

    def __init__(self, ratio: float, size_source: float, size_target: float) -> None:
        self.ratio, self.size_source, self.size_target = ratio, size_source, size_target
        super().__init__(
            f"`target` is {ratio:.3g} times the size of `source` (RMS radius {size_target:.4g} "
            f"vs {size_source:.4g}): are they in the same units? Convert one of them, or start "
            "from a similarity: `with_scaling=True` (o3dreg register --with-scaling)"
        )


def _check_sizes(covs: np.ndarray, covt: np.ndarray) -> None:
    ratio = _size_ratio(covs, covt)
    if ratio > MAX_SIZE_RATIO or ratio < 1.0 / MAX_SIZE_RATIO:
        raise SizeMismatch(ratio, float(np.sqrt(np.trace(covs))), float(np.sqrt(np.trace(covt))))


class _SingleThreadHold:
    """Open3D on one thread while any rigid step runs (``with _single_thread():``): its ICP sums
    over threads in no fixed order, so two runs on the same input could differ in the last bits
    and, through the candidate ranking, pick different poses. The thread count is process-wide,
    so overlapping rigid steps (nested, or in two threads) share one hold: the first to enter
    saves the caller's count and the last to leave restores it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._holders = 0
        self._callers_count = 0

    @contextmanager
    def __call__(self) -> Iterator[None]:
        with self._lock:
            if self._holders == 0:
                self._callers_count = o3d.utility.get_max_threads()
                o3d.utility.set_max_threads(1)
            self._holders += 1
        try:
            yield
        finally:
            with self._lock:
                self._holders -= 1
                if self._holders == 0:
                    o3d.utility.set_max_threads(self._callers_count)


_single_thread = _SingleThreadHold()


class _CandidateSearch:
    """ICP from many starts, scored by the symmetric surface distance on the whole target."""

    def __init__(
        self,
        vs: np.ndarray,
        fs: np.ndarray,
        vt: np.ndarray,
        ft: np.ndarray,
        max_correspondence_distance: float,
        diagonal: float,
        target_query: SurfaceDistanceQuery | None = None,
        search_method: Any = None,
    ) -> None:
        self.vs, self.fs = vs, fs
        # The estimation of the search from many starts (SEARCH_KERNEL_WIDTH); None: the
        # refinement's.
        self.search_method = search_method
        # ICP runs on centred copies: Open3D's point-to-plane step linearises the rotation about
        # the origin, which fails far from it (a patient 1e4 mm away diverged to fitness 0).
        self.cs, self.ct = vs.mean(axis=0), vt.mean(axis=0)
        self.src, self.tgt = _cloud(vs - self.cs, fs), _cloud(vt - self.ct, ft)
        self.distance = max_correspondence_distance
        self.diagonal = diagonal
        # ICP from many starts runs with a spatial subsample of the source against a coarse copy
        # of the target: the basin needs the shape, not the detail. Only the two best poses are
        # refined on all points.
        n = SEARCH_SOURCE_POINTS
        keep = spatial_subsample(vs, n) if vs.shape[0] > n else None
        self.search_src = self.src if keep is None else self.src.select_by_index(keep.tolist())
        self.search_points = np.asarray(self.search_src.points) + self.cs
        self.coarse = self.tgt.voxel_down_sample(_voxel_for(vt, SEARCH_POINTS))
        self.coarse_points = np.asarray(self.coarse.points) + self.ct
        self.query = SurfaceDistanceQuery(vt, ft) if target_query is None else target_query
        self.source_query = SurfaceDistanceQuery(vs, fs)

    def score(self, transformation: np.ndarray) -> float:
        """Mean of the mean point-to-surface distances both ways (the source subsample to the
        whole target, the coarse target's points to the moved source surface)."""
        forward = self.query.distance(apply_transformation(transformation, self.search_points))
        # A similarity scales distances by its scale: measure in the source's frame, once built.
        scale = float(np.cbrt(abs(np.linalg.det(transformation[:3, :3]))))
        back = apply_transformation(np.linalg.inv(transformation), self.coarse_points)
        backward = scale * self.source_query.distance(back)
        return float(0.5 * (forward.mean() + backward.mean()))

    def icp(
        self,
        source: Any,
        target: Any,
        distance: float,
        start: np.ndarray,
        method: Any,
        criteria: Any,
        still: float = REFINE_STILL,
    ) -> Any:
        """Open3D's ICP on the centred clouds; the transformation returned in input coordinates.

        Run in bursts of :data:`ICP_BURST` iterations (``criteria.max_iteration`` in all), and
        stopped when a burst moves the source points by less than ``still`` times the target's
        diagonal (RMS): near convergence the nearest-neighbour correspondences often
        alternate between two sets, the inlier RMSE then changes by ~1e-5 at every iteration
        and Open3D's test (fitness and RMSE changes below ``criteria``) never fires. The bursts
        have an even length, so such a cycle returns to the same pose at their ends.
        """
        to_centred, from_centred = np.eye(4), np.eye(4)
        to_centred[:3, 3], from_centred[:3, 3] = -self.ct, self.ct
        into_source, out_of_source = np.eye(4), np.eye(4)
        into_source[:3, 3], out_of_source[:3, 3] = self.cs, -self.cs
        pose = to_centred @ start @ into_source
        points = np.asarray(source.points)
        still *= self.diagonal
        done = 0
        while True:
            burst = min(ICP_BURST, criteria.max_iteration - done)
            result = reg.registration_icp(
                source,
                target,
                distance,
                pose,
                method,
                reg.ICPConvergenceCriteria(
                    criteria.relative_fitness, criteria.relative_rmse, burst
                ),
            )
            done += burst
            previous, pose = pose, np.asarray(result.transformation)
            if done >= criteria.max_iteration:
                break
            moved = apply_transformation(pose, points) - apply_transformation(previous, points)
            if np.sqrt((moved**2).sum(axis=1).mean()) <= still:
                break
        result.transformation = from_centred @ pose @ out_of_source
        return result

    def refine(self, start: np.ndarray, method: Any, criteria: Any) -> Any:
        return self.icp(self.src, self.tgt, self.distance, start, method, criteria)

    def _preselect(
        self, candidates: list[tuple[str, np.ndarray]], pool: Executor
    ) -> list[tuple[str, np.ndarray]]:
        """All named poses, and the sampled rotations nearest the target before ICP (their
        cheap scores computed by ``pool``)."""
        fixed = [c for c in candidates if not c[0].startswith("sampled")]
        sampled = [c for c in candidates if c[0].startswith("sampled")]
        if len(sampled) <= SAMPLED_KEPT:
            return fixed + sampled
        tree = cKDTree(self.coarse_points)
        pts = self.search_points

        def cheap(t: np.ndarray) -> float:
            moved = apply_transformation(t, pts)
            return float(
                tree.query(moved)[0].mean() + cKDTree(moved).query(self.coarse_points)[0].mean()
            )

        order = np.argsort(list(pool.map(cheap, [t for _, t in sampled])), kind="stable")
        return fixed + [sampled[k] for k in order[:SAMPLED_KEPT]]

    def _refined(self, entry: tuple[float, str, Any], icp: Any) -> tuple[float, str, Any]:
        """A searched pose ``entry`` with its refinement ``icp``, scored."""
        score = self.score(np.asarray(icp.transformation))
        logger.debug("rigid start %s refined: score %.4g -> %.4g", entry[1], entry[0], score)
        return score, entry[1], icp

    def tie(self, best: float, other: float) -> bool:
        """Whether a score ``other`` is a near tie with the best score ``best``: within
        :data:`AMBIGUITY_RATIO`, or apart by rounding only (two exact fits score ~1e-17 of the
        diagonal, whose ratio means nothing)."""
        return other < AMBIGUITY_RATIO * best + 1e-9 * self.diagonal

    def distinct(self, a: np.ndarray, b: np.ndarray, score: float | None = None) -> bool:
        """Whether two poses place the source apart by more than ICP's basin
        (:data:`DISTINCT_POSE`), and with the winner's ``score`` by more than the target's noise
        blurs on top (:data:`DISTINCT_NOISE`; the noise is measured only where a pose lies
        within what a noise of :data:`NOISE_PER_SCORE` times ``score`` would blur)."""
        pa, pb = apply_transformation(a, self.vs), apply_transformation(b, self.vs)
        rms = float(np.sqrt(((pa - pb) ** 2).sum(axis=1).mean()))
        basin = DISTINCT_POSE * self.diagonal
        if rms <= basin or score is None:
            return rms > basin
        if rms > basin + DISTINCT_NOISE * NOISE_PER_SCORE * score:
            return True
        return rms > basin + DISTINCT_NOISE * self.noise

    def _blurred(self, score: float) -> bool:
        """Whether the target's noise, rather than a symmetry, can explain a near tie between
        poses whose best scores ``score`` (:data:`NOISY_TIE`, :data:`NOISY_TIE_SCORE`)."""
        if score < NOISY_TIE_SCORE * NOISY_TIE * self.diagonal:
            return False  # too good a fit for a noisy target: no need to measure the noise
        return self.noise > NOISY_TIE * self.diagonal and score >= NOISY_TIE_SCORE * self.noise

    @cached_property
    def noise(self) -> float:
        """The target's noise (:func:`~o3dreg.mesh.noise.noise_level`), measured on first use."""
        return noise_level(self.query.vertices, self.query.faces)

    def run(
        self, candidates: list[tuple[str, np.ndarray]], method: Any, criteria: Any
    ) -> RigidRegistrationResult:
        pool = ThreadPoolExecutor(_threads())
        try:
            return self._run(pool, candidates, method, criteria)
        finally:
            # Starts still queued are not needed any more (after an error); running ones end.
            pool.shutdown(wait=True, cancel_futures=True)

    def _run(
        self,
        pool: Executor,
        candidates: list[tuple[str, np.ndarray]],
        method: Any,
        criteria: Any,
    ) -> RigidRegistrationResult:
        """Search from every candidate, refine the best pose (and a close runner-up), then
        decide between them."""
        tried = self._preselect(candidates, pool)
        searched = self._search(pool, tried, method, criteria)
        mirrored = [entry for entry in searched if entry[1].startswith(MIRROR_IMAGE)]
        scored = [entry for entry in searched if not entry[1].startswith(MIRROR_IMAGE)]
        if scored[0][1] != INPUT_POSE_REFINED:
            # The input pose refined in place competes for the win only: a worse local fit near
            # the input pose says nothing of a symmetry, and must not break a tie.
            scored = [entry for entry in scored if entry[1] != INPUT_POSE_REFINED]
        finals = self._refine_finalists(pool, scored[0], self._runner_up(scored), method, criteria)
        finals = self._beyond_noise(finals, scored, method, criteria)
        result = self._decide(finals, len(tried) - len(mirrored))
        if mirrored and mirrored[0][0] * MIRROR_SEARCH_RATIO < scored[0][0]:
            # Only a mirror image that searched better than the template is refined and
            # compared on the refined scores.
            result.mirror_score = self._refined(
                mirrored[0], self.refine(_pose(mirrored[0]), method, criteria)
            )[0]
            for text in mirror_warnings(result):
                result.warnings += (text,)
                logger.warning("registration_rigid: %s", text)
        return result

    def _search(
        self, pool: Executor, tried: list[tuple[str, np.ndarray]], method: Any, criteria: Any
    ) -> list[tuple[float, str, Any]]:
        """A coarse ICP from every candidate pose, and the input pose refined where it lies
        (:data:`INPUT_POSE_REFINED`), scored; best first."""
        searches = [
            pool.submit(
                self.icp,
                self.search_src,
                self.coarse,
                4.0 * self.distance,
                guess,
                self.search_method or method,
                criteria,
                SEARCH_STILL,
            )
            for _, guess in tried
        ]
        if any(name == "input pose" for name, _ in tried):
            tried = [*tried, (INPUT_POSE_REFINED, np.eye(4))]
            searches.append(pool.submit(self.refine, np.eye(4), method, criteria))
        scored: list[tuple[float, str, Any]] = []
        for (name, _), job in zip(tried, searches):
            icp = job.result()
            score = self.score(np.asarray(icp.transformation))
            logger.debug("rigid candidate %s: fitness %.3f, score %.4g", name, icp.fitness, score)
            scored.append((score, name, icp))
        order = sorted(range(len(scored)), key=lambda k: (scored[k][0], k))
        return [scored[k] for k in order]

    def _runner_up(self, scored: list[tuple[float, str, Any]]) -> tuple[float, str, Any] | None:
        """The best searched pose distinct from the winner ``scored[0]``. Where the winner is
        far from the input pose and several distinct poses tie with it (a shape with more than
        one symmetry: a box fits itself in four poses), the tied one nearest the input pose, so
        that the input pose can break the tie (:meth:`_decide`)."""
        best = scored[0]
        others = [o for o in scored[1:] if self.distinct(_pose(best), _pose(o))]
        runner = others[0] if others else None
        tied = [o for o in others if self.tie(best[0], o[0])]
        if tied and rotation_angle(_pose(best)) >= INPUT_POSE_FAR:
            runner = min(tied, key=lambda o: rotation_angle(_pose(o)))
        return runner

    def _refine_finalists(
        self,
        pool: Executor,
        best: tuple[float, str, Any],
        runner: tuple[float, str, Any] | None,
        method: Any,
        criteria: Any,
    ) -> list[tuple[float, str, Any]]:
        """The winner refined, and the runner-up refined where it could still win; best first.
        The input pose refined in place is a refinement already, scored as one."""
        winner_job = None
        if best[1] != INPUT_POSE_REFINED:
            winner_job = pool.submit(self.refine, _pose(best), method, criteria)
        # A runner-up likely to need refining (by the search scores) is refined beside the
        # winner; the rule below, on the winner's refined score, decides.
        runner_job = None
        if runner is not None and runner[0] < RUNNER_UP_REFINED * best[0]:
            runner_job = pool.submit(self.refine, _pose(runner), method, criteria)
        finals = [best if winner_job is None else self._refined(best, winner_job.result())]
        if runner is not None:
            # A runner-up far behind keeps its search pose and score: no refinement brings it
            # within AMBIGUITY_RATIO of the winner (see RUNNER_UP_REFINED), so it cannot win.
            if runner[0] >= RUNNER_UP_REFINED * finals[0][0]:
                if runner_job is not None:
                    runner_job.cancel()
                finals.append(runner)
            else:
                icp = (
                    runner_job.result()
                    if runner_job is not None
                    else self.refine(_pose(runner), method, criteria)
                )
                finals.append(self._refined(runner, icp))
        finals.sort(key=lambda f: f[0])
        return finals

    def _beyond_noise(
        self,
        finals: list[tuple[float, str, Any]],
        scored: list[tuple[float, str, Any]],
        method: Any,
        criteria: Any,
    ) -> list[tuple[float, str, Any]]:
        """The refined finalists, best first, with the runner-up replaced where the target's
        noise blurs it into the winner (:data:`DISTINCT_NOISE`): by the best searched pose
        distinct from the winner beyond the noise, refined where it could still tie (see
        :data:`RUNNER_UP_REFINED`), or by none. Refining both near poses keeps the better start;
        the ambiguity is judged against a pose that differs from it."""
        best = finals[0][0]
        if len(finals) < 2 or self.distinct(_pose(finals[0]), _pose(finals[1]), best):
            return finals
        win = _pose(finals[0])
        others = [o for o in scored if self.distinct(win, _pose(o), best)]
        if not others:
            return finals[:1]
        other = others[0]
        if other[0] < RUNNER_UP_REFINED * best:
            other = self._refined(other, self.refine(_pose(other), method, criteria))
        return sorted([finals[0], other], key=lambda f: f[0])

    def _decide(
        self, finals: list[tuple[float, str, Any]], candidates: int
    ) -> RigidRegistrationResult:
        """The result from the refined finalists: a near tie is broken by the input pose when
        one of them agrees with it, else reported as ambiguous."""
        win_score, win_name, win = finals[0]
        runner_score: float | None = None
        runner_t: np.ndarray | None = None
        if len(finals) > 1:
            other = _pose(finals[1])
            if self.distinct(_pose(finals[0]), other, finals[0][0]):
                runner_score, runner_t = finals[1][0], other
        warnings: list[str] = []
        near_tie = runner_score is not None and self.tie(win_score, runner_score)
        blurred = False
        if near_tie and runner_t is not None:
            turns = (rotation_angle(_pose(finals[0])), rotation_angle(runner_t))
            near_input = min(turns) <= INPUT_POSE_NEAR and max(turns) >= INPUT_POSE_FAR
            blurred = self._blurred(win_score)
            if near_input and not blurred:
                if turns[1] < turns[0]:  # the runner-up agrees with the input pose: it wins
                    previous = win
                    win, runner_t = finals[1][2], np.asarray(previous.transformation)
                    win_score, runner_score = float(finals[1][0]), win_score
                    win_name = finals[1][1]
                logger.info(
                    "registration_rigid: near tie (%.4g vs %.4g) broken by the input pose "
                    "(poses %.0f and %.0f degrees from it)",
                    win_score,
                    runner_score,
                    *turns,
                )
                near_tie = False
        if near_tie:
            cause = (
                f"the target's noise ({100 * self.noise / self.diagonal:.2g}% of its size) blurs "
                "them, so correspondences may be wrong: denoise the target or start from landmarks"
                if blurred
                else "the shape is nearly symmetric, so correspondences may be wrong: start from "
                "landmarks"
            )
            warnings.append(
                f"{AMBIGUOUS_START}: two distinct poses fit almost equally well "
                f"(symmetric distances {win_score:.3g} and {runner_score:.3g}); {cause}"
            )
            logger.warning("registration_rigid: %s", warnings[-1])
        logger.info(
            "rigid start: %s wins of %d (score %.4g, runner-up %s)",
            win_name,
            candidates,
            win_score,
            "none" if runner_score is None else f"{runner_score:.4g}",
        )
        return RigidRegistrationResult(
            win,
            score=win_score,
            runner_up_score=runner_score,
            runner_up_transformation=runner_t,
            candidates=candidates,
            warnings=tuple(warnings),
            ambiguous=near_tie,
        )


def _pose(entry: tuple[float, str, Any]) -> np.ndarray:
    """The transformation of a scored ``(score, name, icp)`` entry."""
    return np.asarray(entry[2].transformation)


def _threads() -> int:
    """Threads of the candidate search: :data:`SEARCH_THREADS`, at most the usable cores."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(SEARCH_THREADS, cores or 1))


def _cloud(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.PointCloud:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces.astype(np.int32))
    )
    mesh.compute_vertex_normals()
    pcd = o3d.geometry.PointCloud(mesh.vertices)
    pcd.normals = mesh.vertex_normals
    return pcd


def _simplified(vt: np.ndarray, ft: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """A copy of a large surface with about ``count`` vertices (vertex clustering)."""
    # The elastic step's own clustering: the copy does not depend on the input's numbering.
    v, f = cluster_vertices(vt, ft, _voxel_for(vt, count))
    logger.debug("registration_rigid: target of %d vertices simplified to %d", len(vt), len(v))
    return as_mesh_arrays((v, f), "target", drop_degenerate=True)


def _voxel_for(points: np.ndarray, count: int) -> float:
    """A voxel size that leaves roughly ``count`` points of a surface sampled by ``points``."""
    extent = np.ptp(points, axis=0)
    # A surface of extent L holds about (L / voxel)^2 * 3 occupied voxels (three faces' worth).
    area_scale = float(
        np.sort(extent)[1:].prod() + np.sort(extent)[:2].prod() + extent[0] * extent[2]
    )
    return max(float(np.sqrt(2.0 * area_scale / count)), 1e-12)
