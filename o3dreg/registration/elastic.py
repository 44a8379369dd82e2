"""The elastic registration pipeline step and its ``evaluate_*`` twin.

Berar, Desvignes, Bailly, Payan (2005), "3D meshes registration: application to statistical skull
model", section 2.2: a rigid pre-alignment, then a coarse-to-fine hierarchy of trilinear
transformations of space minimising the symmetric distance of eq. (3) plus a regularisation, by
Levenberg-Marquardt.

The registration in three pieces: :func:`_coarse_to_fine` here, a short driver over the levels
(as scikit-image's ``_coarse_to_fine``); each level's problem, :class:`LevelProblem`
(``_cost``: residuals, Jacobian, normal equations of the terms in ``_terms``); the solver
objects of ``_solvers`` that minimise it (Levenberg-Marquardt, or SciPy's ``least_squares``).
What is minimised comes from the strategies a :class:`~o3dreg.DistanceEstimation` holds
(``terms``, ``losses``, ``checkers``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from .._geometry import (
    apply_transformation,
    bounds,
    face_cross,
    face_doubled_areas,
    into_frame,
    polar_angles,
    row_norms,
    turned_triangles,
)
from .._validation import (
    as_mesh_arrays,
    as_transformation,
    check_bool,
    check_positive,
    check_referenced,
)
from ..mesh.distinct import distinct
from ..mesh.sampling import morton_order, spatial_subsample
from ._cost import LevelProblem, bound_masks
from ._robust import support
from ._solvers import SolveInfo, solve
from ._target import TARGET_VOXELS_PER_CELL, TargetSurface
from ._terms import BarycentreTerm
from .checkers import CheckerContext, CorrespondenceChecker, NormalAngleChecker
from .deformation import LatticeDeformation, PartitionedDeformation
from .distance import SurfaceDistanceQuery
from .lattice import TrilinearLattice
from .losses import RobustLoss
from .options import (
    MAX_LEVELS,
    DistanceEstimation,
    ElasticCriteria,
    ElasticLevel,
    default_levels,
)
from .result import (
    ElasticRegistrationResult,
    LevelReport,
    MapQuality,
    RigidStart,
    SurfaceDistances,
)
from .rigid import check_given_start, default_start
from .terms import DistanceTerm
from .tie import local_turn, settle_tie
from .verdict import judge, with_rigid_start

__all__ = ["evaluate_elastic", "registration_elastic"]

logger = logging.getLogger("o3dreg")

#: Template vertices (an even subsample) whose normals decide the target's relative orientation.
ORIENTATION_POINTS = 1000


def lattice_box(
    points: Sequence[np.ndarray], padding: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """A cube enclosing all ``points`` with ``padding`` times its side added on every face.

    Returns
    -------
    origin : (3,) ndarray
        Minimum corner.
    size : (3,) ndarray
        Equal sides (cubic cells, as the paper's elementary cubes).
    """
    corners = [bounds(np.asarray(p)) for p in points if len(p)]
    lo = np.min([c[0] for c in corners], axis=0)
    hi = np.max([c[1] for c in corners], axis=0)
    side = float((hi - lo).max())
    side = side if side > 0 else 1.0
    full = side * (1.0 + 2.0 * padding)
    centre = (lo + hi) / 2.0
    return centre - full / 2.0, np.full(3, full)


def _check_levels(levels: Any, source: np.ndarray) -> list[ElasticLevel]:
    if levels is None:
        return default_levels(source)
    if isinstance(levels, ElasticLevel):
        levels = [levels]
    if not isinstance(levels, (list, tuple)):
        raise TypeError(
            f"`levels` must be a non-empty list of ElasticLevel, got {type(levels).__name__}"
        )
    if not levels:
        raise ValueError("`levels` must be a non-empty list of ElasticLevel, got an empty one")
    for k, lev in enumerate(levels):
        if not isinstance(lev, ElasticLevel):
            raise TypeError(f"`levels[{k}]` must be an ElasticLevel, got {type(lev).__name__}")
    if len(levels) > MAX_LEVELS:
        raise ValueError(
            f"`levels` must hold at most {MAX_LEVELS} levels (each keeps its lattice in the "
            f"deformation), got {len(levels)}"
        )
    return list(levels)


def _check_estimation(estimation_method: Any) -> DistanceEstimation:
    if estimation_method is None:
        return DistanceEstimation()
    if not isinstance(estimation_method, DistanceEstimation):
        raise TypeError(
            "`estimation_method` must be a DistanceEstimation, "
            f"got {type(estimation_method).__name__}"
        )
    return estimation_method


def _check_options(
    criteria: Any, padding: Any, callback: Any, parts: Any, with_scaling: Any, has_init: bool
) -> tuple[ElasticCriteria, float]:
    """The checks of :func:`registration_elastic`'s remaining options; its criteria and padding."""
    if criteria is None:
        criteria = ElasticCriteria()
    elif not isinstance(criteria, ElasticCriteria):
        raise TypeError(f"`criteria` must be an ElasticCriteria, got {type(criteria).__name__}")
    padding = check_positive(padding, "padding", allow_zero=True)
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable, got {type(callback).__name__}")
    if parts not in ("joint", "connected"):
        raise ValueError(f"`parts` must be 'joint' or 'connected', got {parts!r}")
    with_scaling = check_bool(with_scaling, "with_scaling")
    if with_scaling and has_init:
        raise ValueError(
            "`with_scaling` applies to the start computed without `init`; with `init` given "
            "there is no rigid step (got with_scaling=True and an init)"
        )
    return criteria, padding


def registration_elastic(
    source: Any,
    target: Any,
    *,
    init: Any = None,
    levels: Sequence[ElasticLevel] | None = None,
    estimation_method: DistanceEstimation | None = None,
    criteria: ElasticCriteria | None = None,
    padding: float = 0.1,
    callback: Callable[[LevelReport], Any] | None = None,
    parts: str = "joint",
    with_scaling: bool = False,
) -> ElasticRegistrationResult:
    """Register a low-density template onto a high-density surface, elastically.

    ``T(x) = deformation(transformation @ x)``: a rigid pre-alignment followed by a hierarchy of
    trilinear lattices (coarse to fine), each level minimising eq. (3) of Berar et al. (2005)
    with Levenberg-Marquardt and an analytic sparse Jacobian. The template is typically a
    low-density mesh (a few thousand vertices), the target a dense scan; degenerate target
    triangles are dropped.

    Parameters
    ----------
    source : open3d.geometry.TriangleMesh or (vertices, faces)
        The template: the surface that moves. Not modified.
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface the source is matched to. Not modified.
    init : (4, 4) array_like, optional
        The rigid (or similarity) transformation of the source. Default ``None``: computed by
        :func:`~o3dreg.registration_rigid` (moment-based guess refined by ICP); where that start
        is ambiguous, the levels run from its runner-up's pose as well and settle the tie where
        they tell the two apart (:func:`~o3dreg.registration.tie.settle_tie`).
    levels : list of ElasticLevel, optional
        The hierarchy, coarse to fine, at most 16 levels. Default
        :func:`~o3dreg.default_levels` of the source (2, 4, 8, 16 cells per axis, and 32 for an
        elongated source).
    estimation_method : DistanceEstimation, optional
        What is minimised. Default ``DistanceEstimation()``: the symmetric distance with the
        robust settings for real scans (partial targets, debris);
        ``DistanceEstimation.paper()`` is the paper's plain least squares.
    criteria : ElasticCriteria, optional
        Default stopping rule of every level. Default ``ElasticCriteria()``.
    padding : float, optional
        Margin added around the data on each side of the lattice box, as a fraction of its
        largest extent. Default 0.1.
    callback : callable, optional
        Called with the :class:`~o3dreg.LevelReport` of each level when it finishes.
    parts : {'joint', 'connected'}, optional
        ``'joint'`` (default): one deformation of space for the whole source. ``'connected'``:
        when the source has several connected components (separate bones, nearby plates), each
        is registered with its own lattice hierarchy (its own box) after the common rigid
        alignment, against the target vertices whose nearest rigidly aligned source vertex
        belongs to it (target triangles whose three corners go to the same component). Nearby
        but distinct structures are then not dragged together by one map of space. The result's
        ``deformation`` is then a :class:`~o3dreg.PartitionedDeformation`: it maps each point
        with the deformation of its nearest (rigidly aligned) source vertex's component, and
        saves and loads as one file, and holds the parts (``parts``, ``labels``, ``sites``).
    with_scaling : bool, optional
        Make the start computed without ``init`` a similarity (``registration_rigid(...,
        with_scaling=True)``, on the target as prepared here): for a template of another size or
        in other units. Default ``False``: a rigid start. Refused with an ``init``.

    Returns
    -------
    ElasticRegistrationResult
        ``success`` is ``False`` (with a ``message``) when a level stopped at ``max_iteration``;
        no exception is raised for non-convergence. ``status`` and ``warnings`` are the verdict
        of :func:`~o3dreg.assess_registration`: only ``'ok'`` means nothing looked wrong.

    Raises
    ------
    TypeError, ValueError
        For invalid meshes or options, naming the parameter.

    References
    ----------
    .. [1] M. Berar, M. Desvignes, G. Bailly, Y. Payan, "3D meshes registration: application to
       statistical skull model", ICIAR 2004, LNCS 3212, pp. 100-107. :doi:`10.1007/978-3-540-30126-4_13`
    .. [2] R. Szeliski, S. Lavallee, "Matching 3-D anatomical surfaces with non-rigid deformations
       using octree-splines", IJCV 18(2), 1996. :doi:`10.1007/BF00054999`

    Examples
    --------
    >>> import open3d as o3d
    >>> from o3dreg import ElasticLevel, registration_elastic
    >>> template = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=12)
    >>> patient = o3d.geometry.TriangleMesh.create_sphere(radius=11.0, resolution=40)
    >>> result = registration_elastic(template, patient, init=np.eye(4),
    ...                               levels=[ElasticLevel(2), ElasticLevel(4)])
    >>> result.distances.source_to_target_mean < 0.05
    True
    """
    vs, fs = as_mesh_arrays(source, "source")
    check_referenced(vs, fs, "source")
    target_arrays = as_mesh_arrays(target, "target", drop_degenerate=True)
    levels_ = _check_levels(levels, vs)
    estimation_method = _check_estimation(estimation_method)
    surface = TargetSurface.from_mesh(*target_arrays, estimation_method.min_target_component)
    criteria, padding = _check_options(
        criteria, padding, callback, parts, with_scaling, init is not None
    )

    rigid_start = None
    if init is None:
        rigid_start = default_start(vs, fs, surface.query, with_scaling=with_scaling)
        rigid = np.array(rigid_start.transformation)
    else:
        rigid = as_transformation(init, "init", similarity=True)
    run = _LevelRun(vs, fs, surface, levels_, estimation_method, criteria, padding, parts)
    done = run(rigid, callback)
    start = None
    if rigid_start is not None:
        start = RigidStart.from_rigid(rigid_start)
        if rigid_start.ambiguous and rigid_start.runner_up_transformation is not None:
            done, start = _settled(run, done, rigid_start)
    elif _turned_locally(done.result.deformation, done.points):
        # A given start is checked against the rigid search (one part: parts move apart).
        checked = check_given_start(vs, fs, surface.query, rigid, done.result.vertices)
        start = None if checked is None else RigidStart.from_rigid(checked)
    return done.result if start is None else with_rigid_start(done.result, start)


class _Done(NamedTuple):
    """A registration from one start: the assessed result (no rigid start yet) and the
    template rigidly aligned there."""

    result: ElasticRegistrationResult
    points: np.ndarray


@dataclass(frozen=True)
class _LevelRun:
    """The levels of :func:`registration_elastic` from a rigid start, on inputs validated."""

    vs: np.ndarray
    fs: np.ndarray
    surface: TargetSurface
    levels: list[ElasticLevel]
    method: DistanceEstimation
    criteria: ElasticCriteria
    padding: float
    parts: str

    def __call__(self, rigid: np.ndarray, callback: Any) -> _Done:
        """The assessed registration from the start ``rigid``."""
        fs, surface = self.fs, self.surface
        points = apply_transformation(rigid, self.vs)
        pulled = surface
        if self.method.min_target_component is not None:
            # Islands the start does not reach are left to the verdict, not pulled towards;
            # the result is measured and judged on the whole target.
            pulled = surface.without_islands(points)
        # The levels work along the template's own axes (the start's rotation): the lattices,
        # the bending energy, the target's levels of detail and subsamples then do not depend
        # on how the patient lies in the scanner.
        frame = _lattice_frame(rigid)
        local, local_points = pulled, points
        if frame is not None:
            local = pulled.in_frame(frame)
            local_points = into_frame(frame, points)
        labels = template_parts(self.vs.shape[0], fs) if self.parts == "connected" else None
        options = (self.method, self.criteria, self.padding, callback)
        if labels is not None and labels.max() > 0:
            fit = _register_parts(local_points, fs, local, labels, self.levels, *options)
        else:
            fit = _coarse_to_fine(local_points, fs, local, self.levels, *options)
        if frame is not None:
            fit = _laid_in(frame, fit, points)
        forward = fit.forward if pulled is surface else None
        measured = surface.distances(fit.moved, fs, forward=forward)
        success = not fit.failures
        result = ElasticRegistrationResult(
            transformation=rigid,
            deformation=fit.deformation,
            vertices=fit.moved,
            faces=fs,
            distances=measured.summary(),
            levels=fit.history,
            quality=_map_quality(points, fs, fit),
            success=success,
            message=fit.converged if success else "; ".join(fit.failures),
        )
        # The verdict from the distances just measured and the target's moments (as
        # assess_registration(result, (vs, fs), (vt, ft)) would measure them).
        vt, ft = surface.mesh
        assessed = judge(
            result,
            points,
            fs,
            vt,
            ft,
            forward=measured.forward,
            backward=measured.backward,
            target_moments=surface.moments,
        )
        return _Done(assessed, points)


def _settled(run: _LevelRun, done: _Done, rigid: Any) -> tuple[_Done, RigidStart]:
    """An ambiguous rigid start's tie, settled where the registration from its runner-up's pose
    tells the two apart (:func:`~o3dreg.registration.tie.settle_tie`); ``done`` is the
    registration from its winner's. The runner-up's levels are not reported to the callback."""
    if not isinstance(done.result.deformation, LatticeDeformation):
        return done, RigidStart.from_rigid(rigid)  # parts: each moves on its own
    other = run(np.array(rigid.runner_up_transformation), None)
    turns = (
        local_turn(done.result.deformation, done.points, done.result.vertices),
        local_turn(other.result.deformation, other.points, other.result.vertices),
    )
    lo, hi = bounds(run.surface.vertices)
    diagonal = float(np.linalg.norm(hi - lo))
    kept, start = settle_tie(rigid, (done.result, other.result), turns, diagonal)
    return (done, other)[kept], start


class _Fit(NamedTuple):
    """What the levels made of a template (or of each of its parts): the pieces of an
    :class:`ElasticRegistrationResult` that do not need the target -> template distances."""

    deformation: LatticeDeformation | PartitionedDeformation
    moved: np.ndarray
    history: tuple[LevelReport, ...]
    failures: tuple[str, ...]
    #: Distance of every moved vertex to the whole target (``None``: to be measured).
    forward: np.ndarray | None
    supported: np.ndarray
    det: float
    cell_det: float
    converged: str = "all levels converged"


#: A map from a given start that turns space by more than this many degrees at a tenth of the
#: template's vertices has its pose checked by the rigid search: from a right start the levels
#: turn the template locally by less (the bunny under warps of 2-10% of its diagonal: 1.7-8.4
#: degrees; an asymmetric blob and a long bone under a 5% warp: 6-13), while a start 90-135
#: degrees off that they wrap onto the wrong parts leaves turns of 19-77 degrees. Below it the
#: search (0.2 s on the bunny) is not run.
GIVEN_START_TURN = 10.0


def _turned_locally(deformation: Any, points: np.ndarray) -> bool:
    """Whether a one-part ``deformation`` turns space at the template ``points`` (rigidly
    aligned) beyond :data:`GIVEN_START_TURN` at a tenth of them."""
    if not isinstance(deformation, LatticeDeformation):
        return False
    angles = polar_angles(deformation.jacobian(points))
    return bool(np.percentile(angles, 90) > GIVEN_START_TURN)


def _map_quality(points: np.ndarray, fs: np.ndarray, fit: _Fit) -> MapQuality:
    """The folds of ``fit``'s map and its flipped triangles, against the template ``(points,
    fs)`` in its start pose."""
    return MapQuality(
        min_jacobian_determinant=min(fit.det, fit.cell_det),
        min_cell_jacobian_determinant=fit.cell_det,
        flipped_triangles=flipped_triangles(points, fit.moved, fs),
        supported=fit.supported,
    )


def _coarse_to_fine(
    points: np.ndarray,
    fs: np.ndarray,
    surface: TargetSurface,
    levels_: list[ElasticLevel],
    estimation_method: DistanceEstimation,
    criteria: ElasticCriteria,
    padding: float,
    callback: Callable[[LevelReport], Any] | None,
) -> _Fit:
    """The levels, coarse to fine, of one deformation of space: the template ``(points, fs)``
    (rigidly aligned) onto ``surface``. Inputs validated; no distances back from the target and
    no verdict yet (the caller measures them on the whole target).

    Each level poses its problem (:class:`_Hierarchy`), a solver minimises it, and its lattice
    joins the deformation; the next level starts where this one ended.
    """
    hierarchy = _Hierarchy.prepare(points, fs, surface, levels_, estimation_method, padding)
    deformation = LatticeDeformation(())
    previous = np.zeros_like(points)
    history: list[LevelReport] = []
    failures: list[str] = []
    problem: LevelProblem | None = None
    ended: _LevelEnd | None = None
    for k, level in enumerate(levels_):
        start = time.perf_counter()
        problem, use = hierarchy.problem(level, previous, deformation, ended)
        info = solve(problem, level.criteria or criteria, level.solver)
        ended = _LevelEnd.of(problem, use, info.evaluation)
        level_lattice = problem.scatter(info.evaluation.u)
        deformation = deformation.with_level(level_lattice)
        previous = previous + level_lattice.displacement(points)
        report = _level_report(level, problem, info, use.size, time.perf_counter() - start)
        _log_level(k, len(levels_), report)
        history.append(report)
        if not info.success:
            failures.append(f"level {k + 1} ({level.resolution} cells): {info.message}")
        if callback is not None:
            callback(report)
    return hierarchy.fit(deformation, points + previous, history, failures, problem, ended)


@dataclass
class _Hierarchy:
    """What every level of one deformation shares, set up once: the template, the target, the
    lattice box, the strategies of the estimation and the target's orientation."""

    points: np.ndarray
    faces: np.ndarray
    surface: TargetSurface
    origin: np.ndarray
    size: np.ndarray
    loss: RobustLoss
    checkers: tuple[CorrespondenceChecker, ...]
    terms: tuple[DistanceTerm, ...]
    #: ``-1`` when the target is oriented inside out relative to the template.
    orientation: float
    #: Area-weighted samples of the template surface, made when a term first asks for the
    #: Voronoi offsets (:meth:`voronoi_offsets`).
    samples: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def prepare(
        cls,
        points: np.ndarray,
        fs: np.ndarray,
        surface: TargetSurface,
        levels: list[ElasticLevel],
        method: DistanceEstimation,
        padding: float,
    ) -> _Hierarchy:
        origin, size = lattice_box([points, surface.vertices], padding)
        surface.build_levels_of_detail(
            _detail_voxel(size, lev) for lev in levels if lev.simplify_target
        )
        checkers = method.checkers
        orientation = 1.0
        if _tests_normals(checkers):
            orientation = _relative_orientation(points, fs, surface.finest_detail())
        return cls(
            points, fs, surface, origin, size, method.robust_loss, checkers, method.terms,
            orientation,
        )  # fmt: skip

    def problem(
        self,
        level: ElasticLevel,
        previous: np.ndarray,
        deformation: LatticeDeformation,
        ended: _LevelEnd | None = None,
    ) -> tuple[LevelProblem, np.ndarray]:
        """The problem of ``level`` from the template moved by the coarser levels
        (``previous``, ``deformation``; ``ended``: where the last of them left its points), and
        the template points it is posed on."""
        points, surface = self.points, self.surface
        lattice = TrilinearLattice.zeros(self.origin, self.size, (level.resolution,) * 3)
        moved = points + previous
        active = self._active(level, moved)
        # Coarse lattices have few nodes: a spatial subsample of the data determines them as well
        # as all of it, at a fraction of the cost of each distance query.
        use = _level_sample(lattice, points, level.points_per_node, moved)
        level_query = _level_query(surface, self.size, level)
        normals = None
        if _tests_normals(self.checkers):
            normals = self.orientation * vertex_normals(moved, self.faces)[use]
        start = None  # the closest points where the last level left these points, if it did
        if ended is not None:
            start = ended.closest_on(level_query, use, moved[use])
        problem = LevelProblem(
            points[use],
            previous[use],
            lattice,
            active[use],
            level_query,
            self.terms,
            level.regularization,
            level.energy,
            target_samples=_LevelTargetSamples(self.surface, self.points.shape[0], use.size),
            indices=use,
            symmetric_scale=level.symmetric_scale,
            barycentre_reach=level.barycentre_reach,
            voronoi_offsets=lambda: self.voronoi_offsets((points + previous)[use], deformation),
            loss=self.loss,
            checkers=self.checkers,
            # Whether the target has open edges is a property of the full target: a simplified
            # copy of a closed surface can have spurious ones.
            target_has_boundary=surface.query.has_boundary,
            min_jacobian_determinant=level.min_jacobian_determinant
            if level.solver == "lm"
            else None,
            normals=normals,
            prior=deformation if deformation.levels else None,
            start=start,
            nearest_known=None
            if ended is None
            else lambda sample: ended.nearest_on(sample, use, moved[use]),
            template_mesh=lambda: (moved, self.faces),
        )
        return problem, use

    def voronoi_offsets(self, used: np.ndarray, deformation: LatticeDeformation) -> np.ndarray:
        """The offsets of :func:`_barycentre_offsets` of the template points ``used`` (moved by
        ``deformation``)."""
        if self.samples is None:
            self.samples = _surface_samples(self.points, self.faces)
        surface_samples, sample_weights = self.samples
        return _barycentre_offsets(used, surface_samples, deformation, sample_weights)

    def _active(self, level: ElasticLevel, moved: np.ndarray) -> np.ndarray:
        """The template points whose cells the level refines (all, or where the residual is
        above the level's ``adaptive_quantile``)."""
        if level.adaptive_quantile is None:
            return np.ones(moved.shape[0], dtype=bool)
        dist = self.surface.query.distance(moved)
        active = dist > np.quantile(dist, level.adaptive_quantile)
        if not active.any():
            active = dist >= dist.max()
        return active

    def fit(
        self,
        deformation: LatticeDeformation,
        moved: np.ndarray,
        history: list[LevelReport],
        failures: list[str],
        last: LevelProblem | None,
        ended: _LevelEnd | None = None,
    ) -> _Fit:
        """The fit of the levels (``last``: the finest level's problem, for its scales;
        ``ended``: where it left its points)."""
        query, points = self.surface.query, self.points
        # Once for the forward distances and the support (where the last level did not measure
        # them on the whole target already); without the full target's tree when the levels
        # only queried its levels of detail.
        found = None
        if ended is not None:
            found = ended.closest_on(query, np.arange(points.shape[0]), moved)
        if found is None:
            found = query.closest_few(moved)
        normals = None
        if _tests_normals(self.checkers):
            normals = self.orientation * vertex_normals(moved, self.faces)
        sigma = None if last is None else last.sigma
        masks = bound_masks(self.checkers, CheckerContext(query, normals=normals, sigma=sigma))
        return _Fit(
            deformation=deformation,
            moved=moved,
            history=tuple(history),
            failures=tuple(failures),
            forward=found[0],
            # Whether each template vertex has data: the masks of the last level, on all
            # vertices and the full target at the final positions.
            supported=support(masks, moved, *found),
            det=float(deformation.jacobian_determinant(points).min())
            if deformation.levels
            else 1.0,
            cell_det=_min_cell_determinant(deformation, points),
        )


@dataclass(frozen=True)
class _LevelEnd:
    """The template points a level was posed on (``indices``), where its last evaluation left
    them (``moved``), and their closest points on the surface it measured (``query``).

    The next level starts there, and the fit is measured there: the positions it computes
    (the template moved by the levels' maps) are these to rounding, and one query of the whole
    target is saved each time. The distance to a surface changes no more than the point moves,
    so a kept closest point is as close as a new query's to within twice that rounding; the
    closest point itself may differ only where two parts of the surface are equally near (it
    jumps there), and either is then a closest point.
    """

    query: SurfaceDistanceQuery
    indices: np.ndarray
    moved: np.ndarray
    faces: np.ndarray
    closest: np.ndarray
    terms: tuple[Any, ...] = ()

    #: Positions farther apart than this fraction of the coordinates' magnitude are not the
    #: same to rounding (a trilinear map evaluated two ways differs by ~1e-15 of it).
    ROUNDING = 1e-9

    @classmethod
    def of(cls, problem: LevelProblem, indices: np.ndarray, ev: Any) -> _LevelEnd | None:
        g = ev.geometry
        if g is None:
            return None
        return cls(
            problem.target, indices, g.moved, g.faces, g.closest, tuple(problem.distance_terms)
        )

    def nearest_on(
        self, sample: np.ndarray, indices: np.ndarray, moved: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The nearest of the template points ``indices`` at ``moved`` of every point of the
        target ``sample`` and its distance, from the search state of this level's barycentre
        term on the same sample (exact, and only the points whose nearest may have changed are
        searched again), or ``None`` unless that term and the same template points exist."""
        held = [t for t in self.terms if isinstance(t, BarycentreTerm)]
        if not held or held[0].target_points is not sample:
            return None
        if indices.size != self.indices.size:
            return None
        rows = _rows_of(self.indices, indices)  # this level's order -> the new level's rows
        if rows is None:
            return None
        distance, nearest = held[0].measure(moved.take(rows, axis=0))
        return distance, rows.take(nearest)

    def closest_on(
        self, query: SurfaceDistanceQuery, indices: np.ndarray, moved: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``query.closest(moved)`` for the template points ``indices`` at ``moved``, or
        ``None`` unless this level measured ``query`` at all of them, at ``moved`` to
        rounding."""
        if query is not self.query:
            return None
        rows = _rows_of(indices, self.indices)
        if rows is None:
            return None
        before = self.moved.take(rows, axis=0)
        scale = max(1.0, float(np.abs(moved).max(initial=0.0)))
        if float(np.abs(moved - before).max()) > self.ROUNDING * scale:
            return None
        closest = self.closest.take(rows, axis=0)
        return row_norms(moved - closest), self.faces.take(rows), closest


def _rows_of(wanted: np.ndarray, among: np.ndarray) -> np.ndarray | None:
    """The position in ``among`` of every template vertex number in ``wanted``, or ``None``
    when ``wanted`` is empty or holds a number ``among`` does not."""
    if wanted.size == 0:
        return None
    slot = np.full(int(max(among.max(initial=-1), wanted.max())) + 1, -1, dtype=np.int64)
    slot[among] = np.arange(among.size)
    rows = slot[wanted]
    return None if np.any(rows < 0) else rows


def _tests_normals(checkers: tuple[CorrespondenceChecker, ...]) -> bool:
    return any(isinstance(c, NormalAngleChecker) for c in checkers)


def _level_report(
    level: ElasticLevel, problem: LevelProblem, info: SolveInfo, points: int, seconds: float
) -> LevelReport:
    return LevelReport(
        resolution=level.resolution,
        free_nodes=int(problem.free_nodes.size),
        iterations=info.iterations,
        evaluations=info.evaluations,
        initial_cost=info.initial_cost,
        final_cost=info.evaluation.cost,
        mean_distance=float(info.evaluation.distances.mean()),
        points=int(points),
        seconds=seconds,
        success=info.success,
        message=info.message,
    )


def _log_level(k: int, count: int, report: LevelReport) -> None:
    logger.info(
        "level %d/%d (%d cells/axis, %d free nodes): cost %.4g -> %.4g in %d iterations, "
        "%.3f s: %s",
        k + 1,
        count,
        report.resolution,
        report.free_nodes,
        report.initial_cost,
        report.final_cost,
        report.iterations,
        report.seconds,
        report.message,
    )


def _detail_voxel(size: np.ndarray, level: ElasticLevel) -> float:
    """The voxel of the target's level of detail for ``level`` (lattice box of sides ``size``)."""
    return float(size.min()) / level.resolution / TARGET_VOXELS_PER_CELL


def _level_query(
    surface: TargetSurface, size: np.ndarray, level: ElasticLevel
) -> SurfaceDistanceQuery:
    """What ``level`` measures distances to: the target, or its level of detail."""
    if not level.simplify_target:
        return surface.query
    return surface.at_detail(_detail_voxel(size, level))


def _lattice_frame(transformation: np.ndarray) -> np.ndarray | None:
    """Where the lattices of a registration started at ``transformation`` lie: its rotation (the
    nearest rotation, for a similarity or affine start) and translation, so that the lattices
    follow the template's own axes; ``None`` for the identity (the axes)."""
    if np.array_equal(transformation, np.eye(4)):
        return None
    u, _, vt = np.linalg.svd(transformation[:3, :3])
    if np.linalg.det(u @ vt) < 0:  # a mirroring start: the nearest proper rotation
        u = u * np.array([1.0, 1.0, -1.0])
    frame = np.eye(4)
    frame[:3, :3] = u @ vt
    frame[:3, 3] = transformation[:3, 3]
    return frame


def _laid_in(frame: np.ndarray, fit: _Fit, points: np.ndarray) -> _Fit:
    """A fit made in the coordinates of ``frame`` back in the target's: the deformation with its
    lattices laid in ``frame`` and the moved vertices it gives (``points``: the rigidly aligned
    source, the sites of a partitioned map)."""
    if isinstance(fit.deformation, PartitionedDeformation):
        pieces = tuple(part.in_frame(frame) for part in fit.deformation.parts)
        deformation: LatticeDeformation | PartitionedDeformation = PartitionedDeformation(
            pieces, points, fit.deformation.labels
        )
    else:
        deformation = fit.deformation.in_frame(frame)
    # The result's vertices are its map applied to the aligned source (what `transform` and a
    # saved map give); the same as the fit's, moved by the frame, to rounding.
    moved = deformation.transform(points)
    return fit._replace(deformation=deformation, moved=moved)


def template_parts(number_of_vertices: int, faces: np.ndarray) -> np.ndarray:
    """The part of every template vertex for ``parts='connected'``: its component through shared
    triangle edges, numbered by first vertex; isolated vertices get their own labels. (Vertex
    labels; the public :func:`~o3dreg.connected_components` labels triangles for cleaning.)"""
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = sp.csr_matrix((np.ones(a.size), (a, b)), shape=(number_of_vertices, number_of_vertices))
    _, labels = csgraph.connected_components(graph, directed=False)
    return np.asarray(labels, dtype=np.int64)


def _register_parts(
    points: np.ndarray,
    fs: np.ndarray,
    surface: TargetSurface,
    labels: np.ndarray,
    levels: list[ElasticLevel],
    method: DistanceEstimation,
    criteria: ElasticCriteria,
    padding: float,
    callback: Any,
) -> _Fit:
    """``parts='connected'``: the levels for each source component (``points``: the source
    rigidly aligned), in one partitioned deformation."""
    vt, ft = surface.mesh
    _, nearest = cKDTree(points).query(vt)
    target_labels = labels[nearest]
    face_labels = target_labels[ft]
    moved = points.copy()
    supported = np.zeros(points.shape[0], dtype=bool)
    history: list[LevelReport] = []
    deformations: list[LatticeDeformation] = []
    failures: list[str] = []
    det, cell_det = 1.0, 1.0
    count = int(labels.max()) + 1
    idle: list[int] = []  # parts no target point is nearest to: no level runs for them
    for part in range(count):
        sel = np.flatnonzero(labels == part)
        remap = np.full(points.shape[0], -1, dtype=np.int64)
        remap[sel] = np.arange(sel.size)
        pf = remap[fs[np.all(labels[fs] == part, axis=1)]]
        tf = ft[np.all(face_labels == part, axis=1)]
        if pf.shape[0] == 0 or tf.shape[0] == 0:
            deformations.append(LatticeDeformation(()))
            idle.append(part)
            continue
        used = distinct(tf, vt.shape[0])
        tmap = np.full(vt.shape[0], -1, dtype=np.int64)
        tmap[used] = np.arange(used.size)
        # The part's target prepared as a whole target is (in its own canonical order), without
        # the pieces the split left below ``min_target_component`` of the part's largest.
        part_surface = TargetSurface.from_mesh(vt[used], tmap[tf], method.min_target_component)
        fit = _coarse_to_fine(
            points[sel], pf, part_surface, levels, method, criteria, padding, callback
        )
        moved[sel] = fit.moved
        supported[sel] = fit.supported
        history.extend(fit.history)
        assert isinstance(fit.deformation, LatticeDeformation)
        deformations.append(fit.deformation)
        det = min(det, fit.det)
        cell_det = min(cell_det, fit.cell_det)
        if fit.failures:
            failures.append(f"part {part}: " + "; ".join(fit.failures))
    whole = _Fit(
        deformation=PartitionedDeformation(tuple(deformations), points, labels),
        moved=moved,
        history=tuple(history),
        failures=tuple(failures),
        forward=None,  # the parts measured theirs to their own targets
        supported=supported,
        det=det,
        cell_det=cell_det,
        converged=f"{count} parts: all levels converged"
        if not idle
        else f"{count} parts: all levels converged; part(s) {idle} have no target near them "
        "and keep the start's pose (no level ran for them)",
    )
    return whole


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero for vertices of no non-degenerate triangle)."""
    fn = face_cross(vertices, faces)
    # Each vertex's triangles summed in order of corner, then of triangle.
    corners = faces.T.ravel()
    n = vertices.shape[0]
    out = np.stack([np.bincount(corners, np.tile(fn[:, d], 3), minlength=n) for d in range(3)], 1)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(length > 0, length, 1.0)


def flipped_triangles(before: np.ndarray, after: np.ndarray, faces: np.ndarray) -> int:
    """Triangles whose normal reverses (``n_before . n_after <= 0``) between two vertex sets;
    triangles of zero area before are not counted."""
    return int(np.count_nonzero(turned_triangles(before, after, faces)))


def _min_cell_determinant(deformation: LatticeDeformation, points: np.ndarray) -> float:
    """Smallest ``det(dT/dx)`` at 8 interior samples (local 1/4, 3/4) of every finest cell that
    holds a template vertex."""
    if not deformation.levels:
        return 1.0
    shape = deformation.common_shape()
    lat = TrilinearLattice.zeros(deformation.levels[0].origin, deformation.levels[0].size, shape)
    pts = lat.cell_samples(lat.occupied_cells(points))
    return float(deformation.jacobian_determinant(pts).min())


def _relative_orientation(
    points: np.ndarray, faces: np.ndarray, query: SurfaceDistanceQuery
) -> float:
    """``-1`` when the target is oriented the other way round from the (aligned) template, else 1.

    Meshes from different tools disagree on which side is out (marching cubes, scanners). The
    median cosine between each template vertex normal and the normal of the target triangle
    holding its closest point tells which: near +1 when both face the same way, near -1 when
    one is inside out. The normal test of ``max_normal_angle`` then compares the normals reversed
    rather than rejecting every correspondence.

    A median sign needs neither every template vertex nor every target triangle: an even
    subsample of :data:`ORIENTATION_POINTS` vertices against ``query``, which may be a level of
    detail of the target (each closest-point query of a template far from the target visits many
    boxes of a dense target's tree).
    """
    normals = vertex_normals(points, faces)
    if points.shape[0] > ORIENTATION_POINTS:
        keep = spatial_subsample(points, ORIENTATION_POINTS)
        points, normals = points[keep], normals[keep]
    _, face, _ = query.closest(points)
    cos = (normals * query.face_normal(face)).sum(axis=1)
    if cos.size and float(np.median(cos)) < 0.0:
        logger.info(
            "the target is oriented inside out relative to the template (median normal cosine "
            "%.2f): normals are compared reversed",
            float(np.median(cos)),
        )
        return -1.0
    return 1.0


def _surface_samples(
    vertices: np.ndarray, faces: np.ndarray, order: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted samples of a surface: a barycentric grid of ``order`` steps per triangle."""
    grid = (
        np.array(
            [(i, j, order - i - j) for i in range(order + 1) for j in range(order + 1 - i)],
            dtype=float,
        )
        / order
    )
    corners = vertices[faces]  # (m, 3, 3)
    samples = np.einsum("gk,mkd->mgd", grid, corners).reshape(-1, 3)
    area = 0.5 * face_doubled_areas(vertices, faces)
    weights = np.repeat(area / grid.shape[0], grid.shape[0])
    return samples, weights


def _barycentre_offsets(
    used: np.ndarray, samples: np.ndarray, deformation: LatticeDeformation, weights: np.ndarray
) -> np.ndarray:
    """Offset from each used template vertex to the centroid of its own Voronoi cell.

    The barycentre term pulls template vertex ``i`` to the centroid ``b_i`` of the target
    vertices nearest to it. Even at the true correspondence, ``b_i`` is not ``y_i``: it is the
    centroid of ``i``'s Voronoi cell on the surface, which lies towards the side where the
    template's own vertices are sparser (a decimated template is denser where the surface bends).
    Left alone, the term slides vertices along the surface until the cells are centred (Lloyd's
    relaxation), trading correspondence for even spacing. The same centroid measured on the
    (deformed) template's own surface, ``c_i``, has the same bias; pulling ``y_i + (c_i - y_i)``
    to ``b_i`` keeps the spreading effect of eq. (3) without the drift.
    """
    moved = deformation.transform(samples) if deformation.levels else samples
    _, nearest = cKDTree(used).query(moved)
    n = used.shape[0]
    total = np.bincount(nearest, weights, minlength=n)
    centroid = np.stack(
        [np.bincount(nearest, weights * moved[:, c], minlength=n) for c in range(3)], axis=1
    )
    has = total > 0
    offsets = np.zeros_like(used)
    offsets[has] = centroid[has] / total[has, None] - used[has]
    return offsets


@dataclass(frozen=True)
class _LevelTargetSamples:
    """Even subsamples of the target for a level posed on ``count`` of the template's ``total``
    points (:class:`~o3dreg.registration.terms.TargetSamples`)."""

    surface: TargetSurface
    total: int
    count: int

    def points(self, per_point: float) -> np.ndarray:
        # The budget of the whole template first, so that every level's subsample nests in it.
        self.surface.subsample(int(per_point * self.total))
        return self.surface.subsample(int(per_point * self.count))

    def areas(self, per_point: float) -> np.ndarray:
        self.points(per_point)
        return self.surface.subsample_areas(int(per_point * self.count))


def _level_sample(
    lattice: TrilinearLattice, points: np.ndarray, per_node: float | None, moved: np.ndarray
) -> np.ndarray:
    """Indices of the template points a level optimises on (all, or a spatial subsample), in
    the Morton order of their ``moved`` positions: the level's batches of closest-point
    queries then visit the trees' nodes in a cache-friendly order."""
    use = np.arange(points.shape[0])
    if per_node is not None:
        nodes, _ = lattice.weights(points)
        budget = max(1000, int(per_node * distinct(nodes, lattice.number_of_nodes).size))
        use = spatial_subsample(points, budget)
    return use[morton_order(moved[use])]


def evaluate_elastic(
    source: Any,
    target: Any,
    transformation: Any = None,
    deformation: LatticeDeformation | PartitionedDeformation | None = None,
    *,
    estimation_method: DistanceEstimation | None = None,
) -> SurfaceDistances:
    """Measure an alignment with the metric of :func:`registration_elastic`.

    Parameters
    ----------
    source : open3d.geometry.TriangleMesh or (vertices, faces)
        The template: the surface that moves. Not modified.
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface the source is matched to. Not modified.
    transformation : (4, 4) array_like, optional
        Rigid part applied first. Default identity.
    deformation : LatticeDeformation or PartitionedDeformation, optional
        Elastic part applied after ``transformation`` (a result's ``deformation``, or one read by
        :func:`~o3dreg.load_deformation`). Default none.
    estimation_method : DistanceEstimation, optional
        The registration's, for the target it measures on: pieces of the target smaller than
        its ``min_target_component`` of the largest are left out, as the registration leaves
        them out of its distances. Default ``DistanceEstimation()`` (the registration's
        default); ``DistanceEstimation(min_target_component=None)`` measures every piece.

    Returns
    -------
    SurfaceDistances
        Point-to-surface distances from the moved source vertices to the target surface and from
        the target vertices to the moved source surface.
    """
    vs, fs = as_mesh_arrays(source, "source")
    check_referenced(vs, fs, "source")  # as registration_elastic: every vertex on a triangle
    method = _check_estimation(estimation_method)
    surface = TargetSurface.from_mesh(
        *as_mesh_arrays(target, "target", drop_degenerate=True), method.min_target_component
    )
    t = np.eye(4) if transformation is None else as_transformation(transformation, "transformation")
    if deformation is not None and not isinstance(
        deformation, (LatticeDeformation, PartitionedDeformation)
    ):
        raise TypeError(
            "`deformation` must be a LatticeDeformation or PartitionedDeformation, "
            f"got {type(deformation).__name__}"
        )
    moved = apply_transformation(t, vs)
    if deformation is not None:
        moved = deformation.transform(moved)
    return surface.distances(moved, fs).summary()
