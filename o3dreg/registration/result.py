"""Result value types of the elastic registration."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation
from .._validation import as_mesh_arrays, as_points
from ..io.mesh import to_open3d
from .deformation import LatticeDeformation, PartitionedDeformation
from .distance import SurfaceDistanceQuery

__all__ = ["ElasticRegistrationResult", "LevelReport", "SurfaceDistances"]


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
        The ambiguity, when the runner-up came too close (also among the verdict's warnings).
    """

    score: float
    runner_up_score: float | None
    candidates: int
    fitness: float
    inlier_rmse: float
    warnings: tuple[str, ...] = ()

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
        )

    def __repr__(self) -> str:
        runner = "none" if self.runner_up_score is None else f"{self.runner_up_score:.4g}"
        return (
            f"RigidStart(score={self.score:.4g}, runner_up_score={runner}, "
            f"candidates={self.candidates}, ambiguous={bool(self.warnings)})"
        )

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "warnings": list(self.warnings)}


@dataclass(frozen=True, eq=False)
class ElasticRegistrationResult:
    """The outcome of :func:`~o3dreg.registration_elastic`.

    ``T(x) = deformation.transform(transformation @ x)`` maps the source (template) onto the
    target.

    Attributes
    ----------
    transformation : (4, 4) ndarray
        The total rigid (or similarity) part, ``init`` included.
    deformation : LatticeDeformation or PartitionedDeformation
        The elastic map applied after ``transformation`` (partitioned: one lattice hierarchy per
        part, with ``parts='connected'``).
    vertices : (n, 3) ndarray
        The source vertices mapped by ``T``.
    faces : (m, 3) ndarray
        The source triangles (unchanged: the semilandmark mesh's topology).
    distances : SurfaceDistances
        Measured as :func:`~o3dreg.evaluate_elastic` does.
    history : tuple of LevelReport
        One report per level, coarse to fine.
    min_jacobian_determinant : float
        Smallest ``det(dT/dx)`` at the source vertices (``<= 0`` means the map folds there).
    success : bool
        Whether every level met its stopping criteria (``False``: some level hit
        ``max_iteration``). Says nothing about whether the result is right: see ``status``.
    message : str
    min_cell_jacobian_determinant : float
        Smallest ``det(dT/dx)`` over 8 interior samples (local coordinates 1/4 and 3/4) of every
        finest cell holding a source vertex: the map is one-to-one there when positive.
    flipped_triangles : int
        Source triangles whose normal reverses between the rigidly aligned source and the
        result (``n_rigid . n_registered <= 0``): local folds of the surface.
    supported : (n,) bool ndarray or None
        Per source vertex, whether the target has data for it at the end: ``False`` where its
        closest target point lies beyond an open boundary of the target (with
        ``reject_boundary``), its normal disagrees (``max_normal_angle``), or it is farther than
        ``max_distance_factor`` robust scales (see :class:`~o3dreg.DistanceEstimation`).
        Unsupported vertices followed the regularised motion of their neighbours.
        :meth:`semilandmark_mesh` colours them.
    part_labels : (n,) int ndarray or None
        With ``parts='connected'``: the connected component of each source vertex.
    part_deformations : tuple of LatticeDeformation
        With ``parts='connected'``: one deformation per component (``deformation.parts``).
    part_sites : (n, 3) ndarray or None
        With ``parts='connected'``: the rigidly aligned source vertices, which route each point
        of :meth:`transform` to the component of its nearest site.
    status : {'ok', 'suspect', 'failed'}
        The verdict (:func:`~o3dreg.assess_registration`) from measured facts: folds, flipped
        triangles, distances for the target's size, the supported fraction, an ambiguous rigid
        start, a size mismatch, a degenerate target. Only ``'ok'`` results belong in a model
        without a look.
    warnings : tuple of str
        One plain sentence per finding behind ``status`` (empty when ``'ok'``).
    rigid_start : RigidStart or None
        The rigid start's winner and runner-up scores and warnings, when the start was searched
        for (``None`` with a given ``init``).
    """

    transformation: np.ndarray
    deformation: LatticeDeformation | PartitionedDeformation
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    distances: SurfaceDistances
    history: tuple[LevelReport, ...]
    min_jacobian_determinant: float
    success: bool
    message: str
    min_cell_jacobian_determinant: float = 1.0
    flipped_triangles: int = 0
    supported: np.ndarray | None = field(default=None, repr=False)
    part_labels: np.ndarray | None = field(default=None, repr=False)
    part_deformations: tuple[LatticeDeformation, ...] = field(default=(), repr=False)
    part_sites: np.ndarray | None = field(default=None, repr=False)
    status: str = "ok"
    warnings: tuple[str, ...] = ()
    rigid_start: RigidStart | None = None

    def __repr__(self) -> str:
        d = self.distances
        return (
            f"ElasticRegistrationResult(status={self.status!r}, levels={len(self.history)}, "
            f"success={self.success}, "
            f"source->target mean={d.source_to_target_mean:.4g}, "
            f"target->source mean={d.target_to_source_mean:.4g}, "
            f"min_jacobian_determinant={self.min_jacobian_determinant:.3g})"
        )

    def transform(self, points: Any) -> np.ndarray:
        """Map any source-space points (landmarks, other meshes' vertices) with ``T``."""
        pts = as_points(points, "points", allow_empty=True)
        moved = apply_transformation(self.transformation, pts)
        return self.deformation.transform(moved)

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
