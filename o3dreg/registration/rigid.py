"""Rigid (or similarity) pre-alignment: the paper's initial rototranslation.

A moment-based initial guess (area-weighted centroids and principal axes of both surfaces, trying
the four proper sign choices of the axes) refined by Open3D's ICP.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .._geometry import apply_transformation
from .._validation import as_mesh_arrays, as_transformation, check_positive

__all__ = ["moment_alignments", "registration_rigid", "surface_moments"]

logger = logging.getLogger("o3dreg")
reg = o3d.pipelines.registration


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
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    area = float(areas.sum())
    if area <= 0:
        raise ValueError("the surface has zero area")
    s = a + b + c
    centroid = (areas[:, None] * s / 3.0).sum(axis=0) / area
    second = np.einsum("t,ti,tj->ij", areas, a, a)
    second += np.einsum("t,ti,tj->ij", areas, b, b)
    second += np.einsum("t,ti,tj->ij", areas, c, c)
    second += np.einsum("t,ti,tj->ij", areas, s, s)
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
    _, cs, covs = surface_moments(*source)
    _, ct, covt = surface_moments(*target)
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


def _cloud(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.PointCloud:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces.astype(np.int32))
    )
    mesh.compute_vertex_normals()
    pcd = o3d.geometry.PointCloud(mesh.vertices)
    pcd.normals = mesh.vertex_normals
    return pcd


def _chamfer(a: np.ndarray, b: np.ndarray, tree_b: cKDTree) -> float:
    """Mean nearest-vertex distance both ways (a cheap score to rank candidates)."""
    d_ab = tree_b.query(a, workers=-1)[0].mean()
    d_ba = cKDTree(a).query(b, workers=-1)[0].mean()
    return float(d_ab + d_ba)


def registration_rigid(
    source: Any,
    target: Any,
    *,
    init: Any = None,
    max_correspondence_distance: float | None = None,
    with_scaling: bool = False,
    estimation_method: Any = None,
    criteria: Any = None,
) -> Any:
    """Rigid or similarity alignment of ``source`` onto ``target``.

    Parameters
    ----------
    source, target : open3d.geometry.TriangleMesh or (vertices, faces)
        ``source`` moves. Not modified.
    init : (4, 4) array_like, optional
        Initial transformation. When given, the moment-based guess is skipped and ICP starts
        from it.
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
        Default: 50 iterations, relative fitness and RMSE 1e-6.

    Returns
    -------
    open3d.pipelines.registration.RegistrationResult
        ``transformation`` maps ``source`` onto ``target`` (``init`` included); ``fitness`` and
        ``inlier_rmse`` as Open3D computes them at ``max_correspondence_distance``.

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
    if init is not None:
        candidates = [as_transformation(init, "init")]
    else:
        candidates = moment_alignments((vs, fs), (vt, ft), with_scaling=with_scaling)
    diagonal = float(np.linalg.norm(np.ptp(vt, axis=0)))
    if max_correspondence_distance is None:
        max_correspondence_distance = 0.05 * diagonal
    else:
        max_correspondence_distance = check_positive(
            max_correspondence_distance, "max_correspondence_distance"
        )
    if not isinstance(with_scaling, bool):
        raise TypeError(f"`with_scaling` must be a bool, got {type(with_scaling).__name__}")
    if estimation_method is None:
        estimation_method = (
            reg.TransformationEstimationPointToPoint(with_scaling=True)
            if with_scaling
            else reg.TransformationEstimationPointToPlane()
        )
    elif not isinstance(estimation_method, reg.TransformationEstimation):
        raise TypeError(
            "`estimation_method` must be an open3d.pipelines.registration.TransformationEstimation,"
            f" got {type(estimation_method).__name__}"
        )
    if criteria is None:
        criteria = reg.ICPConvergenceCriteria(1e-6, 1e-6, 50)
    elif not isinstance(criteria, reg.ICPConvergenceCriteria):
        raise TypeError(
            "`criteria` must be an open3d.pipelines.registration.ICPConvergenceCriteria, "
            f"got {type(criteria).__name__}"
        )
    with _single_thread():
        return _icp(
            vs, fs, vt, ft, candidates, max_correspondence_distance, estimation_method, criteria
        )


@contextlib.contextmanager
def _single_thread() -> Iterator[None]:
    """Run Open3D on one thread: its ICP sums over threads in no fixed order, so two runs on the
    same input could differ in the last bits and, through the candidate ranking, pick different
    poses. On one thread the same input gives a bit-identical result."""
    previous = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(previous)


def _icp(
    vs: np.ndarray,
    fs: np.ndarray,
    vt: np.ndarray,
    ft: np.ndarray,
    candidates: list[np.ndarray],
    max_correspondence_distance: float,
    estimation_method: Any,
    criteria: Any,
) -> Any:
    src, tgt = _cloud(vs, fs), _cloud(vt, ft)
    # Rank the candidates on a coarse copy of the target (about as many points as the source):
    # the ranking needs the shape, not the detail. Only the winner is refined on all points.
    coarse_tgt = tgt.voxel_down_sample(_voxel_for(vt, max(vs.shape[0], 1000)))
    coarse_pts = np.asarray(coarse_tgt.points)
    tree_t = cKDTree(coarse_pts)
    best, best_score = np.eye(4), np.inf
    for guess in candidates:
        coarse = reg.registration_icp(
            src, coarse_tgt, 4.0 * max_correspondence_distance, guess, estimation_method, criteria
        )
        t = np.asarray(coarse.transformation)
        score = _chamfer(apply_transformation(t, vs), coarse_pts, tree_t)
        logger.debug("rigid candidate: fitness %.3f, score %.4g", coarse.fitness, score)
        if score < best_score:
            best, best_score = t, score
    return reg.registration_icp(
        src, tgt, max_correspondence_distance, best, estimation_method, criteria
    )


def _voxel_for(points: np.ndarray, count: int) -> float:
    """A voxel size that leaves roughly ``count`` points of a surface sampled by ``points``."""
    extent = np.ptp(points, axis=0)
    # A surface of extent L holds about (L / voxel)^2 * 3 occupied voxels (three faces' worth).
    area_scale = float(
        np.sort(extent)[1:].prod() + np.sort(extent)[:2].prod() + extent[0] * extent[2]
    )
    return max(float(np.sqrt(2.0 * area_scale / count)), 1e-12)
