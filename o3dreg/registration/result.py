"""Result value types of the elastic registration."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation
from .._validation import as_mesh_arrays, as_points
from ..io.mesh import to_open3d
from .deformation import LatticeDeformation, PartitionedDeformation
from .distance import SurfaceDistanceQuery

__all__ = [
    "ElasticRegistrationResult",
    "LevelReport",
    "MapQuality",
    "RegistrationVerdict",
    "SurfaceDistances",
]


@dataclass(frozen=True)
class SurfaceDistances:
    """Point-to-surface distances in both directions, in the input's units.

    Attributes
    ----------
    source_to_target_mean, source_to_target_rms, source_to_target_max : float
        From each (moved) source vertex to the target surface.
    target_to_source_mean, target_to_source_rms, target_to_source_max : float
        From each target vertex to the (moved) source surface.
    """

    source_to_target_mean: float
    source_to_target_rms: float
    source_to_target_max: float
    target_to_source_mean: float
    target_to_source_rms: float
    target_to_source_max: float

    @classmethod
    def from_arrays(
        cls, source_to_target: np.ndarray, target_to_source: np.ndarray
    ) -> SurfaceDistances:
        def stats(d: np.ndarray) -> tuple[float, float, float]:
            return float(d.mean()), float(np.sqrt((d * d).mean())), float(d.max())

        return cls(*stats(source_to_target), *stats(target_to_source))

    def __repr__(self) -> str:
        return (
            f"SurfaceDistances(source->target mean={self.source_to_target_mean:.4g} "
            f"max={self.source_to_target_max:.4g}, target->source "
            f"mean={self.target_to_source_mean:.4g} max={self.target_to_source_max:.4g})"
        )

    def table(self, unit: str = "mm") -> str:
        """The paper's Table 1 layout as text."""
        head = f"{'distances (' + unit + ')':<18}{'mean':>10}{'rms':>10}{'max':>10}"
        rows = [
            (
                "source -> target",
                self.source_to_target_mean,
                self.source_to_target_rms,
                self.source_to_target_max,
            ),
            (
                "target -> source",
                self.target_to_source_mean,
                self.target_to_source_rms,
                self.target_to_source_max,
            ),
        ]
        lines = [head] + [f"{name:<18}{a:>10.4g}{b:>10.4g}{c:>10.4g}" for name, a, b, c in rows]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class LevelReport:
    """What happened at one level.

    Attributes
    ----------
    resolution : int
        Cells per axis.
    free_nodes : int
        Nodes optimised (those whose cells hold refined template vertices).
    iterations, evaluations : int
        Accepted steps and cost evaluations.
    initial_cost, final_cost : float
        Total cost (sum of squared residuals) at the start and end of the level.
    mean_distance : float
        Mean template->target point-to-surface distance of the level's points at its end.
    points : int
        Template vertices the level was optimised on (a spatial subsample on coarse levels).
    seconds : float
        Wall time of the level.
    success : bool
    message : str
    """

    resolution: int
    free_nodes: int
    iterations: int
    evaluations: int
    initial_cost: float
    final_cost: float
    mean_distance: float
    points: int
    seconds: float
    success: bool
    message: str

    def __repr__(self) -> str:
        return (
            f"LevelReport(resolution={self.resolution}, free_nodes={self.free_nodes}, "
            f"iterations={self.iterations}, cost {self.initial_cost:.4g} -> {self.final_cost:.4g}, "
            f"seconds={self.seconds:.3f}, success={self.success})"
        )


@dataclass(frozen=True)
class RigidStart:
    """How the rigid start of a registration was chosen (from its
    :class:`~o3dreg.RigidRegistrationResult`), kept on the elastic result and in its report.

    Attributes
    ----------
    score : float
        The winner's symmetric surface distance after ICP (input units).
    runner_up_score : float or None
        The same for the best distinct pose; ``None`` when there was none.
    candidates : int
        Starting poses tried.
    fitness, inlier_rmse : float
        Open3D's ICP figures for the winner.
    warnings : tuple of str
        The rigid step's warnings (an ambiguity, when the runner-up came too close; a scale
        found on a partial target), also among the verdict's warnings.
    ambiguous : bool
        Whether the runner-up came too close (:attr:`RigidRegistrationResult.ambiguous`) and the
        elastic step did not settle it (``tie_kept``).
    tie_kept : {'winner', 'runner-up'} or None
        Where the runner-up came too close, the elastic registration was run from both poses
        and settled the tie (:func:`~o3dreg.registration.tie.settle_tie`): the pose whose
        registration is kept, the ambiguity warning dropped. ``None`` otherwise.
    tie_fits : (float, float) or None
        The symmetric surface distances (mean of both directions' means) of the registrations
        from the winner's and the runner-up's pose, where both were run.
    mirror_score : float or None
        The score of the template's mirror image where it was refined
        (:attr:`RigidRegistrationResult.mirror_score`): a warning says when it fits better.
    """

    score: float
    runner_up_score: float | None
    candidates: int
    fitness: float
    inlier_rmse: float
    warnings: tuple[str, ...] = ()
    ambiguous: bool = False
    tie_kept: str | None = None
    tie_fits: tuple[float, float] | None = None
    mirror_score: float | None = None

    @classmethod
    def from_rigid(cls, rigid: Any) -> RigidStart:
        """From a :class:`~o3dreg.RigidRegistrationResult`."""
        runner = rigid.runner_up_score
        return cls(
            score=float(rigid.score),
            runner_up_score=None if runner is None else float(runner),
            candidates=int(rigid.candidates),
            fitness=float(rigid.fitness),
            inlier_rmse=float(rigid.inlier_rmse),
            warnings=tuple(rigid.warnings),
            ambiguous=bool(rigid.ambiguous),
            mirror_score=None if rigid.mirror_score is None else float(rigid.mirror_score),
        )

    def __repr__(self) -> str:
        runner = "none" if self.runner_up_score is None else f"{self.runner_up_score:.4g}"
        return (
            f"RigidStart(score={self.score:.4g}, runner_up_score={runner}, "
            f"candidates={self.candidates}, ambiguous={self.ambiguous}"
            + ("" if self.tie_kept is None else f", tie_kept={self.tie_kept!r}")
            + ")"
        )

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "warnings": list(self.warnings)}


@dataclass(frozen=True, eq=False)
class MapQuality:
    """How sound the elastic map of a registration is: its folds and the data behind it.

    Attributes
    ----------
    min_jacobian_determinant : float
        Smallest ``det(dT/dx)`` at the source vertices and at the samples of
        ``min_cell_jacobian_determinant``: the number the verdict judges folds by (``<= 0``
        means the map folds where the source is). Cells without a source vertex are not
        sampled: ``deformation.min_jacobian_determinant()`` samples every cell of the lattice.
    min_cell_jacobian_determinant : float
        Smallest ``det(dT/dx)`` over 8 interior samples (local coordinates 1/4 and 3/4) of every
        finest cell holding a source vertex: the map is one-to-one there when positive.
    flipped_triangles : int
        Source triangles whose normal reverses between the rigidly aligned source and the
        result (``n_rigid . n_registered <= 0``): local folds of the surface.
    supported : (n,) bool ndarray or None
        Per source vertex, whether the target has data for it at the end: ``False`` where a
        correspondence checker of the :class:`~o3dreg.DistanceEstimation` rejects its closest
        target point (beyond an open boundary, normals apart, too far). Unsupported vertices
        followed the regularised motion of their neighbours.
    """

    min_jacobian_determinant: float = 1.0
    min_cell_jacobian_determinant: float = 1.0
    flipped_triangles: int = 0
    supported: np.ndarray | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        return (
            f"MapQuality(min_jacobian_determinant={self.min_jacobian_determinant:.3g}, "
            f"min_cell_jacobian_determinant={self.min_cell_jacobian_determinant:.3g}, "
            f"flipped_triangles={self.flipped_triangles})"
        )


@dataclass(frozen=True)
class RegistrationVerdict:
    """Whether a registration can be used, in one word and in plain sentences.

    Attributes
    ----------
    status : {'ok', 'suspect', 'failed'}
        The verdict (:func:`~o3dreg.assess_registration`) from measured facts: folds, flipped
        triangles, distances for the target's size, the supported fraction, an ambiguous rigid
        start, a size mismatch, a degenerate target. Only ``'ok'`` results belong in a model
        without a look.
    warnings : tuple of str
        One plain sentence per finding behind ``status`` (empty when ``'ok'``).
    rigid_start : RigidStart or None
        The rigid search's winner and runner-up scores and warnings: the start, when none was
        given; with a given ``init``, the search run to check the registration against it
        where the map turns space by more than ``GIVEN_START_TURN`` degrees at a tenth of the
        template's vertices (:func:`~o3dreg.registration.rigid.check_given_start`: a warning
        when the registration ended in a distinct pose that fits clearly worse than the
        search's). ``None`` otherwise, where the search cannot run (sizes in other units) and
        for a template registered in parts.
    """

    status: str = "ok"
    warnings: tuple[str, ...] = ()
    rigid_start: RigidStart | None = None


#: The flat keyword arguments :class:`ElasticRegistrationResult` still takes, by group.
_QUALITY_FIELDS = (
    "min_jacobian_determinant",
    "min_cell_jacobian_determinant",
    "flipped_triangles",
    "supported",
)
_VERDICT_FIELDS = ("status", "warnings", "rigid_start")


@dataclass(frozen=True, eq=False, init=False)
class ElasticRegistrationResult:
    """The outcome of :func:`~o3dreg.registration_elastic`.

    ``T(x) = deformation.transform(transformation @ x)`` maps the source (template) onto the
    target.

    Attributes
    ----------
    transformation : (4, 4) ndarray
        The total rigid (or similarity) part, ``init`` included.
    deformation : LatticeDeformation or PartitionedDeformation
        The elastic map applied after ``transformation``. With ``parts='connected'``, a
        :class:`~o3dreg.PartitionedDeformation` holding one lattice hierarchy per part (its
        ``parts``, ``labels`` and ``sites``).
    vertices : (n, 3) ndarray
        The source vertices mapped by ``T``.
    faces : (m, 3) ndarray
        The source triangles (unchanged: the semilandmark mesh's topology).
    distances : SurfaceDistances
        Measured as :func:`~o3dreg.evaluate_elastic` does.
    levels : tuple of LevelReport
        One report per level, coarse to fine.
    quality : MapQuality
        The map's folds and the source vertices with data.
    success : bool
        Whether every level met its stopping criteria (``False``: some level hit
        ``max_iteration``). Says nothing about whether the result is right: see ``verdict``.
    message : str
    verdict : RegistrationVerdict
        ``status`` (only ``'ok'`` means nothing looked wrong), ``warnings`` and ``rigid_start``.

    The flat names of the groups' fields (``status``, ``warnings``, ``rigid_start``,
    ``min_jacobian_determinant``, ``min_cell_jacobian_determinant``, ``flipped_triangles``,
    ``supported``), ``history`` (the ``levels``) and ``part_labels``, ``part_deformations``,
    ``part_sites`` (the partitioned deformation's) read as attributes too, and the flat names
    are accepted as keyword arguments (``dataclasses.replace(result, status=...)``).
    """

    transformation: np.ndarray
    deformation: LatticeDeformation | PartitionedDeformation
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    distances: SurfaceDistances
    levels: tuple[LevelReport, ...]
    quality: MapQuality
    success: bool
    message: str
    verdict: RegistrationVerdict

    def __init__(
        self,
        transformation: np.ndarray,
        deformation: LatticeDeformation | PartitionedDeformation,
        vertices: np.ndarray,
        faces: np.ndarray,
        distances: SurfaceDistances,
        *,
        levels: tuple[LevelReport, ...] = (),
        quality: MapQuality | None = None,
        success: bool = True,
        message: str = "",
        verdict: RegistrationVerdict | None = None,
        **flat: Any,
    ) -> None:
        levels = tuple(flat.pop("history", levels))
        quality = _with_fields(quality or MapQuality(), _QUALITY_FIELDS, flat)
        verdict = _with_fields(verdict or RegistrationVerdict(), _VERDICT_FIELDS, flat)
        if flat:
            raise TypeError(f"ElasticRegistrationResult got unexpected arguments {sorted(flat)}")
        values = (transformation, deformation, vertices, faces, distances, levels, quality)
        names = ("transformation", "deformation", "vertices", "faces", "distances", "levels")
        for name, value in zip((*names, "quality"), values):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "success", success)
        object.__setattr__(self, "message", message)
        object.__setattr__(self, "verdict", verdict)

    def __repr__(self) -> str:
        d = self.distances
        return (
            f"ElasticRegistrationResult(status={self.status!r}, levels={len(self.levels)}, "
            f"success={self.success}, "
            f"source->target mean={d.source_to_target_mean:.4g}, "
            f"target->source mean={d.target_to_source_mean:.4g}, "
            f"min_jacobian_determinant={self.min_jacobian_determinant:.3g})"
        )

    # -- the flat names of the grouped fields (read-only) ----------------------------------------
    @property
    def history(self) -> tuple[LevelReport, ...]:
        """:attr:`levels`."""
        return self.levels

    @property
    def status(self) -> str:
        return self.verdict.status

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.verdict.warnings

    @property
    def rigid_start(self) -> RigidStart | None:
        return self.verdict.rigid_start

    @property
    def min_jacobian_determinant(self) -> float:
        return self.quality.min_jacobian_determinant

    @property
    def min_cell_jacobian_determinant(self) -> float:
        return self.quality.min_cell_jacobian_determinant

    @property
    def flipped_triangles(self) -> int:
        return self.quality.flipped_triangles

    @property
    def supported(self) -> np.ndarray | None:
        return self.quality.supported

    @property
    def part_labels(self) -> np.ndarray | None:
        """The part of each source vertex (``parts='connected'``), else ``None``."""
        d = self.deformation
        return d.labels if isinstance(d, PartitionedDeformation) else None

    @property
    def part_deformations(self) -> tuple[LatticeDeformation, ...]:
        """One deformation per part (``parts='connected'``), else empty."""
        d = self.deformation
        return d.parts if isinstance(d, PartitionedDeformation) else ()

    @property
    def part_sites(self) -> np.ndarray | None:
        """The rigidly aligned source vertices that route each point to its part
        (``parts='connected'``), else ``None``."""
        d = self.deformation
        return d.sites if isinstance(d, PartitionedDeformation) else None

    def transform(self, points: Any) -> np.ndarray:
        """Map any source-space points (landmarks, other meshes' vertices) with ``T``."""
        pts = as_points(points, "points", allow_empty=True)
        moved = apply_transformation(self.transformation, pts)
        return self.deformation.transform(moved)

    def inverse_transform(self, points: Any, *, max_iterations: int = 50) -> np.ndarray:
        """Map target-space points back to the source: ``x`` with ``T(x) = points``.

        The deformation is inverted by Newton's method
        (:meth:`~o3dreg.LatticeDeformation.inverse_transform`), then ``transformation``. With
        two registrations of one pair, source onto target and target onto source, a landmark
        of the source carried by the first map and by the inverse of the second gives two
        estimates; a bias that each direction makes the same way (a protrusion the map does
        not quite reach) has opposite signs in the two and cancels in their mean (figures in
        docs/shape-model.md).

        Parameters
        ----------
        points : (n, 3) array_like
            Points in target coordinates. Not modified.
        max_iterations : int, optional
            Newton steps at most. Default 50.

        Returns
        -------
        (n, 3) ndarray
            Source-space points; ``transform`` maps them onto ``points`` (to ``1e-9`` times the
            points' largest absolute coordinate, or 1 if larger).

        Raises
        ------
        ValueError
            If some point was not inverted within ``max_iterations`` steps (the map folds there:
            see :attr:`min_jacobian_determinant`).
        """
        moved = self.deformation.inverse_transform(points, max_iterations=max_iterations)
        return apply_transformation(np.linalg.inv(self.transformation), moved)

    def semilandmark_mesh(self, target: Any = None) -> o3d.geometry.TriangleMesh:
        """The template's triangles on the registered vertex positions.

        Parameters
        ----------
        target : open3d.geometry.TriangleMesh or (vertices, faces), optional
            When given, every vertex is moved to its closest point on this surface.

        Returns
        -------
        open3d.geometry.TriangleMesh
            Same vertex count and triangles for every patient: the semilandmark mesh. When
            :attr:`supported` is known and some vertex is unsupported, the mesh carries vertex
            colours: grey ``(0.7, 0.7, 0.7)`` for supported vertices, red ``(1, 0, 0)`` for
            unsupported ones (a PLY file written with Open3D keeps them as ``red``, ``green``,
            ``blue`` vertex properties; ``supported == (red == green)``).
        """
        vertices = self.vertices
        if target is not None:
            tv, tf = as_mesh_arrays(target, "target", drop_degenerate=True)
            vertices = SurfaceDistanceQuery(tv, tf).closest(vertices)[2]
        mesh = to_open3d(vertices, self.faces)
        mesh.compute_vertex_normals()
        if self.supported is not None and not self.supported.all():
            colours = np.where(self.supported[:, None], 0.7, np.array([1.0, 0.0, 0.0]))
            mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
        return mesh


def _with_fields(group: Any, names: tuple[str, ...], flat: dict[str, Any]) -> Any:
    """``group`` with the fields among ``names`` that ``flat`` gives (taken out of ``flat``)."""
    changes = {name: flat.pop(name) for name in names if name in flat}
    return dataclasses.replace(group, **changes) if changes else group
