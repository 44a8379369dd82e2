"""A verdict on every registration: ``'ok'``, ``'suspect'`` or ``'failed'``, with its reasons.

A wrong registration looks like a good one in its convergence flag: the optimiser met its
criteria wherever it ended. The verdict is made from measured facts instead, each compared with
a threshold stated here with its reason:

* folds: the map of space is not one-to-one where a cell's Jacobian determinant is ``<= 0``;
* flipped triangles: template triangles turned inside out;
* distances large for the target's size (95th percentiles both ways, over the target's
  bounding-box diagonal), target components the registration did not reach left out when they
  are small (islands), the target -> template threshold grown by the target's measured noise;
* the fraction of template vertices the target supports, against what a target smaller than
  the template (a large cut) can support;
* a rigid start with two distinct, almost equally good poses (a near-symmetric shape);
* sizes that still differ by a large factor after the rigid step (different units);
* a degenerate target (a few triangles, or almost no area next to the template).

In a batch, :func:`population_outliers` marks patients whose distances or Procrustes residual
stand out among the others (a robust z-score), which catches a registration that is wrong but
locally tidy (:func:`o3dreg.app.population.check_population`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .._geometry import apply_transformation, bounds, corner_cross, face_cross, row_norms
from .._validation import as_mesh_arrays
from ..mesh.cleaning import Components, mesh_components
from ..mesh.noise import noise_level
from .distance import SurfaceDistanceQuery
from .result import RigidStart
from .rigid import MIN_TARGET_TRIANGLES

__all__ = [
    "STATUSES",
    "assess_registration",
    "population_outliers",
    "worst_status",
]

#: The verdicts, best first.
STATUSES = ("ok", "suspect", "failed")

#: Flipped triangles beyond this fraction of the template's are suspect, beyond the second a
#: failure. Where the map does not fold (every cell's determinant positive) the surface keeps its
#: orientation and a flip is one thin triangle's linear interpolation on a tightly curved part
#: (the demo's right registrations have 0-1 of 5000): one, or a handful, is not a finding; a
#: fold is.
FLIPPED_SUSPECT_FRACTION = 0.001
FLIPPED_FAILED_FRACTION = 0.01
#: 95% of the supported template vertices within this fraction of the target's diagonal of it:
#: the demo's good registrations reach 0.2%; a wrong part of the anatomy is several percent away.
DISTANCE_SUSPECT = 0.02
DISTANCE_FAILED = 0.05
#: On a closed target (no open edge) every template vertex has data: 1% of them beyond this
#: fraction of the diagonal is a part of the template the target does not have (a sphere
#: spanning a ring's aperture: 5.1-8.4%), below the 5% the 95th percentile reads. The `ok`
#: registrations of paper Table 2 stay under 0.7%, the annotated mandibles' under 1.4%.
PART_DISTANCE_SUSPECT = 0.05
#: The same for target vertices to the registered template. Looser: a target may hold more than
#: the template models (a longer scan, debris the cleaning kept).
TARGET_DISTANCE_SUSPECT = 0.05
#: A target component that the registration did not reach (no supported template vertex has its
#: closest point there) and whose area, with that of the other unreached ones, is at most this
#: fraction of the reached components' is left out of the target -> template distances: an
#: island (debris, a neighbouring bone) the template does not model. A larger unreached part
#: may be what the template should have fitted, and is judged.
UNREACHED_AREA_FRACTION = 0.5
#: A noisy target's vertices lie off any smooth surface by its noise: the target -> template
#: threshold grows by this many times the target's measured noise (:func:`noise_level`; 95% of
#: normal noise lies within 1.96 standard deviations), by at most half the threshold (noise
#: hides misfits of its own size: the threshold is at most 7.5% of the diagonal).
NOISE_ALLOWANCE = 2.0
NOISE_ALLOWANCE_MAX = 0.5
#: A template vertex beyond a cut has no data: its closest target point lies on the open
#: boundary (:meth:`~o3dreg.registration.distance.SurfaceDistanceQuery.beyond_boundary`). Noise
#: tilts the triangles along a noisy cut, so the closest point of a vertex far beyond it falls
#: inside one of them, within about the noise of the boundary, and the vertex counts as
#: supported, 5-30 mm away. For the template -> target distances a vertex farther than
#: :data:`DISTANCE_SUSPECT` whose closest point lies within this many noise levels of the open
#: boundary (its open edges) is taken as beyond it. On the bunny cut by 20-60% under noise of
#: 0.5-1% of the diagonal (``bench_robust.py --noisy-cuts``) bands of 1 to 2.5 clear 3 of the 4
#: right results flagged; 3 lets a wrong one (19% of the diagonal off) pass.
RIM_NOISE_BAND = 1.5
#: Such a vertex is beyond the cut only when its offset from the rim leaves the surface by at
#: most this many degrees (the surface's normal there: :data:`RIM_NORMAL_FACES`): past a cut the
#: template continues along the surface (60 degrees reach 120 degrees of a sphere's arc past the
#: rim; the sphere cut to its bottom 40% needs 101). A vertex above a target with open edges
#: everywhere (a perforated or crumbled scan) is off along the normal: a template 13% of the
#: diagonal off a noisy sphere with 30% of its triangles missing would pass as ``ok``. On the
#: noisy-cut benchmark it changes no verdict.
RIM_TANGENT_ANGLE = 60.0
#: The target's normal at the rim: the summed vector areas of this many nearest triangles.
RIM_NORMAL_FACES = 64
#: The areas that decide what an island is are measured through cubes of this many times the
#: target's noise (:func:`_component_areas`): noise larger than a component's triangles crumples
#: it and multiplies its area (a copy of the bunny at 0.3 times its size, under noise of 0.5% of
#: the diagonal per axis, measures 0.84 times the whole bunny's area instead of 0.09), while the
#: vector area of each cube's patch depends only on the patch's boundary. Measured on that case
#: (clean areas in brackets): the bunny 53.6k (52.7k), its copy 5.7k (4.7k); cubes of 3 noise
#: levels leave 64k and 9.5k, of 8 noise levels 48.9k and 4.1k (the curvature within a cube
#: starts to cancel too). On a clean target the cubes are smaller than its triangles.
AREA_NOISE = 5.0
#: Fraction of template vertices the target supports: half is expected when the template
#: covers twice the target (a face-only scan, a partial bone); below 30% most of the shape is
#: invented by the regularisation.
SUPPORTED_SUSPECT = 0.3
SUPPORTED_FAILED = 0.1
#: A target smaller than the template (a large cut) cannot support more than about the ratio
#: of the areas: the suspect fraction is then :data:`SUPPORTED_SUSPECT` times that ratio over
#: this one (a target of at least half the template's area keeps the plain threshold; a sphere
#: cut to its bottom 20% of height, a quarter of the template's area, supports 23% of a right
#: registration's vertices).
SUPPORTED_AREA_RATIO = 0.5
#: Sizes (RMS radius about the centroid) of the rigidly aligned template and the target
#: differing by more than this factor: different units (see registration.rigid.MAX_SIZE_RATIO).
SIZE_RATIO_FAILED = 3.0
#: A target with fewer triangles (:data:`~o3dreg.registration.rigid.MIN_TARGET_TRIANGLES`, which
#: the rigid step refuses), or with less than this fraction of the aligned template's area,
#: cannot determine a registration.
MIN_TARGET_AREA_FRACTION = 0.01
#: Population check: modified z-score (Iglewicz and Hoaglin 1993) above which a value is an
#: outlier, and how many times the median it must also exceed (a wrong registration stands out
#: by far; natural variation between patients does not double a registration's distances).
OUTLIER_Z = 3.5
OUTLIER_MEDIAN_FACTOR = 2.0
#: Fewer patients than this give no reliable median absolute deviation: no population check.
MIN_POPULATION = 5


def worst_status(*statuses: str) -> str:
    """The worst of several verdicts (``'ok'`` when none is given)."""
    return max(statuses, key=STATUSES.index, default="ok")


def assess_registration(result: Any, source: Any, target: Any, *, rigid: Any = None) -> Any:
    """The registration with its verdict: ``status`` and ``warnings`` filled in.

    Parameters
    ----------
    result : ElasticRegistrationResult
        A registration of ``source`` onto ``target``.
    source, target : open3d.geometry.TriangleMesh or (vertices, faces)
        The template and the surface it was registered onto. Not modified.
    rigid : RigidRegistrationResult, optional
        The rigid start, when it was searched for: its ambiguity warning is carried over, and
        its scores become ``rigid_start``.

    Returns
    -------
    ElasticRegistrationResult
        A copy with ``status`` in ``{'ok', 'suspect', 'failed'}``, ``rigid_start`` (when
        ``rigid`` is given; otherwise the result's own) and ``warnings``, one plain
        sentence per finding (empty for ``'ok'``). ``success`` (the stopping criteria were
        met) is unchanged: it says nothing about whether the result is right.
    """
    vs, fs = as_mesh_arrays(source, "source")
    vt, ft = as_mesh_arrays(target, "target", drop_degenerate=True)
    aligned = apply_transformation(np.asarray(result.transformation), vs)
    start = getattr(result, "rigid_start", None)
    if rigid is not None:
        start = RigidStart.from_rigid(rigid)
    assessed = judge(result, aligned, fs, vt, ft)
    return assessed if start is None else with_rigid_start(assessed, start)


def judge(
    result: Any,
    aligned: np.ndarray,
    fs: np.ndarray,
    vt: np.ndarray,
    ft: np.ndarray,
    *,
    forward: np.ndarray | None = None,
    backward: np.ndarray | None = None,
    target_moments: Moments | None = None,
) -> Any:
    """The verdict of :func:`assess_registration` on validated arrays, without a rigid start.

    ``aligned`` is the source after ``result.transformation``. A caller that has measured them
    already passes ``forward`` (each of ``result.vertices`` to the surface ``(vt, ft)``),
    ``backward`` (each of ``vt`` to the registered surface) and ``target_moments``
    (:func:`moments` of the target); the verdict then queries nothing again.
    """
    if target_moments is None:
        target_moments = moments(vt, ft)
    source_moments = moments(aligned, fs)
    findings: list[tuple[str, str]] = []
    findings += _degenerate_target(source_moments, target_moments, ft)
    findings += _folds(result)
    findings += _distances(result, vt, ft, forward, backward)
    findings += _support(result, source_moments[0], target_moments[0])
    findings += _sizes(source_moments, target_moments, fs, ft)
    status = worst_status(*(s for s, _ in findings))
    return dataclasses.replace(
        result, status=status, warnings=tuple(w for _, w in findings), rigid_start=None
    )


def with_rigid_start(result: Any, start: RigidStart) -> Any:
    """An assessed ``result`` (no rigid start of its own) with the rigid start it was given:
    ``rigid_start`` set, its ambiguity warnings appended as ``'suspect'`` findings. What
    :func:`assess_registration` adds for ``rigid``, without measuring the registration again."""
    return dataclasses.replace(
        result,
        status=worst_status(result.status, *("suspect" for _ in start.warnings)),
        warnings=tuple(result.warnings) + tuple(start.warnings),
        rigid_start=start,
    )


#: A surface's area and, when it is positive, its size: the trace of its covariance
#: ``1/A int |x - c|^2 dA`` (as from :func:`~o3dreg.registration.rigid.surface_moments`).
Moments = tuple[float, "float | None"]


def moments(vertices: np.ndarray, faces: np.ndarray) -> Moments:
    """Area and size of a surface (``None`` for a surface of zero area).

    The exact integrals of :func:`~o3dreg.registration.rigid.surface_moments`, only the trace of
    the covariance, a coordinate at a time (a million-triangle target in a fraction of the time).
    """
    if faces.shape[0] == 0:
        return 0.0, None
    cols = [np.ascontiguousarray(vertices[:, i]) for i in range(3)]
    area, first, second = 0.0, np.zeros(3), np.zeros(3)
    # In blocks of triangles: a million-triangle target needs no (m,) temporaries. Each corner
    # coordinate is gathered once, for the areas and the moments both.
    for start in range(0, faces.shape[0], MOMENTS_BLOCK):
        block = faces[start : start + MOMENTS_BLOCK]
        a, b, c = ([col[block[:, k]] for col in cols] for k in range(3))
        cross = corner_cross(a, b, c)
        areas = 0.5 * np.sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2])
        area += float(areas.sum())
        for i in range(3):
            s = a[i] + b[i] + c[i]
            first[i] += float(areas @ s)
            second[i] += float(areas @ (a[i] * a[i] + b[i] * b[i] + c[i] * c[i] + s * s))
    if not area > 0.0:
        return 0.0, None
    centroid = first / (3.0 * area)
    return area, float((second / (12.0 * area) - centroid * centroid).sum())


#: Triangles per block of :func:`moments`.
MOMENTS_BLOCK = 1 << 18


def _diagonal(vertices: np.ndarray) -> float:
    if not vertices.shape[0]:
        return 0.0
    lo, hi = bounds(vertices)
    return float(np.linalg.norm(hi - lo))


def _degenerate_target(source: Moments, target: Moments, ft: np.ndarray) -> list[tuple[str, str]]:
    if ft.shape[0] < MIN_TARGET_TRIANGLES:
        return [("failed", f"the target is degenerate: {ft.shape[0]} triangle(s)")]
    area_t, area_s = target[0], source[0]
    if area_t < MIN_TARGET_AREA_FRACTION * area_s:
        return [
            (
                "failed",
                f"the target is degenerate: its area ({area_t:.3g}) is "
                f"{100 * area_t / area_s:.2g}% of the template's",
            )
        ]
    return []


def _folds(result: Any) -> list[tuple[str, str]]:
    out = []
    det = float(result.min_cell_jacobian_determinant)
    det = min(det, float(result.min_jacobian_determinant))
    flipped = int(result.flipped_triangles)
    triangles = max(int(result.faces.shape[0]), 1)
    if det <= 0.0:
        out.append(
            (
                "suspect",
                f"the deformation folds space (smallest Jacobian determinant {det:.3g} <= 0): "
                "it is not one-to-one there",
            )
        )
    # Without a fold the map keeps the surface's orientation: the vertices slid along it.
    slid = "" if det <= 0.0 else SLID
    if flipped > FLIPPED_FAILED_FRACTION * triangles:
        out.append(
            (
                "failed",
                f"{flipped} of {triangles} template triangles are turned inside out{slid}",
            )
        )
    elif flipped > max(1.0, FLIPPED_SUSPECT_FRACTION * triangles):
        out.append(("suspect", f"{flipped} template triangles turned inside out{slid}"))
    return out


#: What flipped triangles mean where the map does not fold, and the cure. A template coarse for
#: the target's sharp edges and corners slides around them under the barycentre term (a
#: 400-vertex cube onto a cube: 7.2 mm, 44 flips; with the single distance 0.07 mm, 1 flip).
SLID = (
    " while the map does not fold: its vertices slid along the target, as a template coarse "
    "for sharp edges and corners does under the symmetric distance (the single distance, "
    "DistanceEstimation(symmetric=False), or a denser template avoids it)"
)


def _distances(
    result: Any,
    vt: np.ndarray,
    ft: np.ndarray,
    forward: np.ndarray | None,
    backward: np.ndarray | None,
) -> list[tuple[str, str]]:
    diagonal = _diagonal(vt)
    if diagonal <= 0.0 or ft.shape[0] == 0:
        return []
    out = []
    if forward is None:
        forward = SurfaceDistanceQuery(vt, ft).distance(result.vertices)
    supported = getattr(result, "supported", None)
    judged = np.ones(forward.size, dtype=bool)
    if supported is not None and supported.any():
        judged = np.asarray(supported, dtype=bool)
    p95 = float(np.percentile(forward[judged], 95))
    if p95 > DISTANCE_SUSPECT * diagonal:
        past = _past_noisy_rim(result.vertices, forward, vt, ft, DISTANCE_SUSPECT * diagonal)
        if (judged & ~past).any():
            p95 = float(np.percentile(forward[judged & ~past], 95))
    if p95 > DISTANCE_SUSPECT * diagonal:
        status = "failed" if p95 > DISTANCE_FAILED * diagonal else "suspect"
        out.append(
            (
                status,
                f"template vertices are far from the target: 5% of them beyond {p95:.3g} "
                f"({100 * p95 / diagonal:.2g}% of the target's size)",
            )
        )
    else:
        p99 = float(np.percentile(forward[judged], 99))
        if p99 > PART_DISTANCE_SUSPECT * diagonal and not SurfaceDistanceQuery(vt, ft).has_boundary:
            out.append(
                (
                    "suspect",
                    f"a part of the template is far from the closed target: 1% of its vertices "
                    f"beyond {p99:.3g} ({100 * p99 / diagonal:.2g}% of the target's size), where "
                    "the target has no surface (a hole it spans, another topology) or on the "
                    "wrong anatomy",
                )
            )
    if backward is None:
        backward = SurfaceDistanceQuery(result.vertices, result.faces).distance(vt)
    b95 = float(np.percentile(backward, 95))
    noise = 0.0
    if b95 > TARGET_DISTANCE_SUSPECT * diagonal:
        noise = noise_level(vt, ft)
        reached = _reached(result, vt, ft, noise)
        if reached is not None:
            diagonal = _diagonal(vt[reached])
            b95 = float(np.percentile(backward[reached], 95))
    threshold = TARGET_DISTANCE_SUSPECT * diagonal
    if b95 > threshold:
        threshold += min(NOISE_ALLOWANCE * noise, NOISE_ALLOWANCE_MAX * threshold)
    if b95 > threshold:
        out.append(
            (
                "suspect",
                f"parts of the target are far from the registered template: 5% of its "
                f"vertices beyond {b95:.3g} ({100 * b95 / diagonal:.2g}% of its size)",
            )
        )
    return out


def _past_noisy_rim(
    points: np.ndarray, distances: np.ndarray, vt: np.ndarray, ft: np.ndarray, far: float
) -> np.ndarray:
    """Which ``points`` lie beyond a noisy cut: farther than ``far`` from the target, with
    their closest target point within :data:`RIM_NOISE_BAND` noise levels of its open boundary,
    and off the boundary along the surface rather than above it (:data:`RIM_TANGENT_ANGLE`;
    ``distances``: each point's to the target)."""
    past = np.zeros(points.shape[0], dtype=bool)
    query = SurfaceDistanceQuery(vt, ft)
    open_edge = query.open_edges[0]
    candidates = np.flatnonzero(distances > far)
    if not open_edge.any() or candidates.size == 0:
        return past
    band = RIM_NOISE_BAND * noise_level(vt, ft)
    if not band > 0.0:
        return past
    face, corner = np.nonzero(open_edge)  # edge k of a face is opposite its corner k
    start = vt[ft[face, (corner + 1) % 3]]
    along = vt[ft[face, (corner + 2) % 3]] - start
    closest = query.closest_few(points[candidates])[2]
    gap, rim = _nearest_on_segments(closest, start, along, band)
    near = np.flatnonzero(gap <= band)
    if near.size == 0:
        return past
    # A vertex beyond a cut continues the surface past its rim; one above a surface with holes
    # everywhere (a perforated or crumbled scan) is off along the normal: a misfit.
    normal = _smooth_normals(vt, ft, rim[near])
    offset = points[candidates[near]] - rim[near]
    rise = np.abs((offset * normal).sum(axis=1))
    along_surface = rise <= np.sin(np.radians(RIM_TANGENT_ANGLE)) * row_norms(offset)
    past[candidates[near[along_surface]]] = True
    return past


def _nearest_on_segments(
    points: np.ndarray, start: np.ndarray, along: np.ndarray, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each of ``points`` to the nearest segment ``start + t along`` (t in [0, 1])
    and that nearest point, for segments within ``reach`` (``inf`` and NaN beyond).

    The segments are cut into pieces no longer than about the typical one, whose midpoints a
    k-d tree holds: only the pieces within ``reach`` plus half a piece are measured (a dense
    distance table of a large target's boundary, 1e5 open edges, takes gigabytes)."""
    length = row_norms(along)
    piece = max(2.0 * float(np.median(length)), reach, 1e-300)
    count = np.maximum(1, np.ceil(length / piece)).astype(np.int64)
    segment = np.repeat(np.arange(length.size), count)
    k = np.arange(segment.size) - np.repeat(np.cumsum(count) - count, count)
    step = along[segment] / count[segment, None]
    first = start[segment] + k[:, None] * step
    tree = cKDTree(first + 0.5 * step)
    radius = reach + 0.5 * float(row_norms(step).max())
    gap = np.full(points.shape[0], np.inf)
    nearest = np.full(points.shape, np.nan)
    for chunk in np.array_split(np.arange(points.shape[0]), max(1, points.shape[0] // 4096)):
        found = tree.query_ball_point(points[chunk], radius)
        sizes = np.fromiter((len(f) for f in found), dtype=np.int64, count=len(found))
        if not sizes.any():
            continue
        who = np.repeat(chunk, sizes)
        which = np.fromiter((j for f in found for j in f), dtype=np.int64, count=int(sizes.sum()))
        offset = points[who] - first[which]
        seg = step[which]
        t = np.clip((offset * seg).sum(axis=1) / np.maximum((seg * seg).sum(axis=1), 1e-300), 0, 1)
        foot = first[which] + t[:, None] * seg
        d = row_norms(points[who] - foot)
        # The nearest piece of each point: sorted by distance, the first of each point's run.
        order = np.lexsort((d, who))
        keep = order[np.r_[True, who[order][1:] != who[order][:-1]]]
        gap[who[keep]] = d[keep]
        nearest[who[keep]] = foot[keep]
    return gap, nearest


def _smooth_normals(vt: np.ndarray, ft: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Unit normals of the target surface about each of ``at``: the summed vector areas of the
    :data:`RIM_NORMAL_FACES` triangles nearest to it (noise tilts each triangle; their sum keeps
    the surface's direction). Zero where they cancel."""
    cross = face_cross(vt, ft)
    tree = cKDTree(vt[ft].mean(axis=1))
    _, nearest = tree.query(at, k=min(RIM_NORMAL_FACES, ft.shape[0]))
    summed = cross[nearest.reshape(at.shape[0], -1)].sum(axis=1)
    size = row_norms(summed)
    return np.divide(summed, size[:, None], out=np.zeros_like(summed), where=size[:, None] > 0)


def _reached(result: Any, vt: np.ndarray, ft: np.ndarray, noise: float) -> np.ndarray | None:
    """The target vertices of the components the registration reached, when the others are
    islands it may ignore (:func:`reached_faces`); ``None`` to judge them all."""
    points = result.vertices
    supported = getattr(result, "supported", None)
    if supported is not None and supported.any():
        points = points[supported]
    faces = reached_faces(points, vt, ft, lambda: noise)
    if faces is None:
        return None
    reached = np.zeros(vt.shape[0], dtype=bool)
    reached[ft[faces].ravel()] = True
    return reached


def reached_faces(
    points: np.ndarray,
    vt: np.ndarray,
    ft: np.ndarray,
    noise: Callable[[], float],
    *,
    components: Components | None = None,
    query: SurfaceDistanceQuery | None = None,
) -> np.ndarray | None:
    """The target triangles of the components holding the closest point of some of
    ``points``, when the other components are islands (their area at most
    :data:`UNREACHED_AREA_FRACTION` of the reached ones', measured through the target's
    noise, asked of ``noise`` only then: :func:`_component_areas`); ``None`` when the target is
    one component, every component is reached, or the unreached ones are too large to be
    islands. ``components`` and ``query``: the target's, where the caller has them."""
    if components is None:
        components = mesh_components(vt, ft)
    if len(components) < 2:
        return None
    face = (query or SurfaceDistanceQuery(vt, ft)).closest_few(points)[1]
    used = np.zeros(len(components), dtype=bool)
    used[components.labels[face]] = True
    if used.all():
        return None
    cube = AREA_NOISE * noise()
    areas = _component_areas(vt, ft, components.labels, len(components), cube)
    if areas[~used].sum() > UNREACHED_AREA_FRACTION * areas[used].sum():
        return None
    return used[components.labels]


def _component_areas(
    vt: np.ndarray, ft: np.ndarray, labels: np.ndarray, count: int, cube: float
) -> np.ndarray:
    """The area of each of ``count`` components (``labels``: each triangle's), as the sum over
    cubes of side ``cube`` of the length of its triangles' summed vector areas there (by their
    centroids). A patch's vector area depends only on its boundary: the crumple that noise
    smaller than the cubes puts into a surface cancels out (:data:`AREA_NOISE`). Exact for
    ``cube`` 0."""
    cross = face_cross(vt, ft)
    if not cube > 0.0:
        return np.bincount(labels, weights=0.5 * row_norms(cross), minlength=count)
    centroids = (vt[ft[:, 0]] + vt[ft[:, 1]] + vt[ft[:, 2]]) / 3.0
    keys = np.floor((centroids - bounds(centroids)[0]) / cube).astype(np.int64)
    _, cell = np.unique(np.column_stack([labels, keys]), axis=0, return_inverse=True)
    cell = cell.ravel()
    summed = np.stack([np.bincount(cell, weights=cross[:, k]) for k in range(3)], axis=1)
    owner = np.zeros(summed.shape[0], dtype=np.int64)
    owner[cell] = labels
    return np.bincount(owner, weights=0.5 * row_norms(summed), minlength=count)


def _support(result: Any, area_s: float, area_t: float) -> list[tuple[str, str]]:
    supported = getattr(result, "supported", None)
    if supported is None or supported.size == 0:
        return []
    fraction = float(np.count_nonzero(supported)) / supported.size
    # What the target can support: about the ratio of the areas where it is the smaller.
    coverable = min(1.0, area_t / area_s / SUPPORTED_AREA_RATIO) if area_s > 0.0 else 1.0
    if fraction < SUPPORTED_FAILED or fraction < SUPPORTED_SUSPECT * coverable:
        status = "failed" if fraction < SUPPORTED_FAILED else "suspect"
        return [
            (
                status,
                f"the target supports only {100 * fraction:.0f}% of the template's vertices; "
                "the rest follow the regularisation",
            )
        ]
    return []


def _sizes(
    source: Moments, target: Moments, fs: np.ndarray, ft: np.ndarray
) -> list[tuple[str, str]]:
    size_s, size_t = source[1], target[1]
    if ft.shape[0] == 0 or fs.shape[0] == 0 or size_s is None or size_t is None:
        return []  # zero area: reported as a degenerate target
    ratio = float(np.sqrt(max(size_t, 1e-300) / max(size_s, 1e-300)))
    if ratio > SIZE_RATIO_FAILED or ratio < 1.0 / SIZE_RATIO_FAILED:
        return [
            (
                "failed",
                f"after the rigid step the target is {ratio:.3g} times the template's size: "
                "different units? Convert one of them, or start from a similarity "
                "(--with-scaling)",
            )
        ]
    return []


def population_outliers(
    values: Mapping[str, float], *, threshold: float = OUTLIER_Z
) -> dict[str, float]:
    """The names whose value is far above the others' (a robust z-score).

    ``z = 0.6745 (x - median) / MAD`` (the modified z-score of Iglewicz and Hoaglin, 1993: the
    median absolute deviation ``MAD`` scaled to a standard deviation for normal data). A value is
    an outlier when ``z > threshold`` and it is also more than :data:`OUTLIER_MEDIAN_FACTOR`
    times the median. Only large values are outliers: a registration is never wrong for being
    too close.

    Parameters
    ----------
    values : mapping of str to float
        One value per patient (a distance, a Procrustes residual). Non-finite values are left
        out of the statistics and not reported.
    threshold : float, optional
        Default :data:`OUTLIER_Z` (3.5, the value Iglewicz and Hoaglin recommend).

    Returns
    -------
    dict of str to float
        The outliers and their z-scores. Empty with fewer than :data:`MIN_POPULATION` finite
        values, or when the values do not vary.
    """
    finite = {k: float(v) for k, v in values.items() if np.isfinite(v)}
    if len(finite) < MIN_POPULATION:
        return {}
    x = np.array(list(finite.values()))
    median = float(np.median(x))
    mad = float(np.median(np.abs(x - median)))
    if mad <= 0.0:
        # More than half the values equal: the mean absolute deviation, scaled alike.
        # For normal data MAD = 0.6745 sigma and the mean deviation 0.7979 sigma.
        mad = float(np.mean(np.abs(x - median))) * 0.6745 / 0.7979
    if mad <= 0.0:
        return {}
    out = {}
    for name, v in finite.items():
        z = 0.6745 * (v - median) / mad
        if z > threshold and v > OUTLIER_MEDIAN_FACTOR * median:
            out[name] = float(z)
    return out
