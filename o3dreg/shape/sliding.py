"""Sliding semilandmarks: let registered template vertices slide along each patient's surface.

The elastic registration fixes *where* each template vertex lands on the patient surface only up
to the regularisation: a vertex may sit anywhere along the surface at the same distance cost.
Sliding removes this arbitrary tangential component: each semilandmark moves in the tangent
plane of the patient surface (from the patient mesh's triangle under it) to minimise either the
Procrustes distance to the mean or the thin-plate bending energy of the deformation from the
mean, and is then projected back onto the patient surface. Means and slides alternate until
the shapes stop moving.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg

from .._geometry import apply_transformation, turned_triangles
from .._validation import as_faces, as_mesh_arrays, check_positive
from ..registration.distance import SurfaceDistanceQuery
from .procrustes import as_shape_array, generalized_procrustes

__all__ = ["SlidingResult", "slide_semilandmarks"]

logger = logging.getLogger("o3dreg")

CRITERIA = ("procrustes", "bending")

#: The bending criterion solves a dense system of 2 unknowns per free point, beside the
#: ``(n + 4)^2`` thin-plate matrix and its inverse: about ``90 n^2`` bytes at its peak (8000
#: points: 5.8 GB; a 3000-vertex template: 0.8 GB). More points are refused before any work
#: rather than left to exhaust the memory.
BENDING_MAX_POINTS = 8000

#: A move that turns a semilandmark triangle over is halved this many times for the vertices of
#: the turned triangles, then dropped for them (they stay where they are).
FOLD_HALVINGS = 6


@dataclass(frozen=True, eq=False)
class SlidingResult:
    """The outcome of :func:`slide_semilandmarks`.

    Attributes
    ----------
    shapes : (s, n, 3) ndarray
        Slid semilandmarks, in each patient's coordinates (on its surface).
    criterion : str
    iterations : int
    displacements : (iterations,) ndarray
        Mean distance moved by the semilandmarks at each iteration.
    procrustes_distances : (iterations + 1,) ndarray
        Mean RMS distance of the aligned shapes to their mean: of the shapes given, then after
        each iteration (the first one includes their projection onto the surfaces).
    success : bool
    message : str
    """

    shapes: np.ndarray = field(repr=False)
    criterion: str
    iterations: int
    displacements: np.ndarray = field(repr=False)
    procrustes_distances: np.ndarray = field(repr=False)
    success: bool
    message: str

    def __repr__(self) -> str:
        return (
            f"SlidingResult({self.criterion}, iterations={self.iterations}, "
            f"procrustes distance {self.procrustes_distances[0]:.4g} -> "
            f"{self.procrustes_distances[-1]:.4g}, success={self.success})"
        )


def _tangent_bases(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each normal (and to each other)."""
    helper = np.where(np.abs(normals[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return t1, t2


def _bending_matrix(reference: np.ndarray) -> np.ndarray:
    """Bending energy matrix ``Be`` (upper-left ``n x n`` block of ``L^-1``) of a 3D TPS.

    With the 3D kernel ``U(r) = r`` it is negative semidefinite: the bending energy is
    ``-Y^T (I_3 (x) Be) Y``. Zero when an affine map fits any values at the points (at most 4
    points, 3 in a plane)."""
    n = reference.shape[0]
    # The affine maps' dimension at these points (centred: an offset origin does not hide it).
    affine = np.linalg.matrix_rank(np.hstack([np.ones((n, 1)), reference - reference.mean(0)]))
    if n <= affine:
        # An affine map carries these points anywhere: no deformation of them bends, and an
        # inverse would be rounding noise that the step's ridge blows up.
        return np.zeros((n, n))
    p = np.hstack([np.ones((n, 1)), reference])
    k = np.linalg.norm(reference[:, None, :] - reference[None, :, :], axis=2)  # U(r) = r in 3D
    big = np.zeros((n + 4, n + 4))
    big[:n, :n] = k
    big[:n, n:] = p
    big[n:, :n] = p.T
    # L^-1 (3x faster than its pseudo-inverse), checked on a few columns; the pseudo-inverse
    # where L is singular (points repeated, or all in one plane).
    try:
        inverse = np.linalg.inv(big)
    except np.linalg.LinAlgError:
        inverse = None
    if inverse is not None:
        cols = np.linspace(0, n + 3, 8).astype(int)
        check = big @ inverse[:, cols]
        check[cols, np.arange(cols.size)] -= 1.0
        if np.all(np.isfinite(check)) and np.abs(check).max() < 1e-6:
            return inverse[:n, :n]
    return np.linalg.pinv(big, hermitian=True)[:n, :n]


def slide_semilandmarks(
    shapes: Any,
    targets: Any,
    *,
    criterion: str = "bending",
    max_iteration: int = 5,
    tolerance: float = 1e-3,
    fixed: Any = None,
    scaling: bool = False,
    faces: Any = None,
) -> SlidingResult:
    """Slide semilandmarks along the patient surfaces to minimise a criterion against the mean.

    One iteration: generalised Procrustes of the current shapes -> mean; for every shape, the
    mean is mapped into the shape's frame, each free point moves within the tangent plane of the
    patient surface at its position (normal of the patient triangle under it) so as to minimise

    * ``'procrustes'``: the squared distance to the mapped mean (the point's tangential offset
      to its mean position is removed), or
    * ``'bending'``: the thin-plate-spline bending energy ``-Y^T (I_3 (x) Be) Y`` of the map from
      the mean to the shape (Bookstein 1997; Gunz et al. 2005), solved for all tangential
      offsets at once (dense: ``n`` up to a few thousand);

    then it is projected back to the closest point of the patient surface. Stops when the mean
    displacement falls below ``tolerance`` times the mean shape's RMS radius.

    Each point slides on its own, so a large slide (a patient far from the mean) can carry a
    point past its neighbours and turn triangles of the semilandmark mesh over. Given the
    mesh's ``faces``, no move (the first projection onto the surfaces included) turns a
    triangle over relative to the shape given: the move of the vertices of a triangle it would
    turn is halved, :data:`FOLD_HALVINGS` times at most, then dropped for them.

    Parameters
    ----------
    shapes : (s, n, 3) array_like or sequence of (n, 3)
        Registered semilandmarks, each in its patient's coordinates. Not modified.
    targets : sequence of open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surfaces, one per shape.
    criterion : {'bending', 'procrustes'}, optional
        Default ``'bending'``, as in geomorph's ``gpagen`` and Morpho's ``slider3d``: it keeps
        each shape's deformation from the mean smooth and leaves the registered
        correspondences close to where they were. ``'procrustes'`` removes every tangential
        difference from the mean, genuine ones included: it moves points far from their
        correspondents and, iterated, bunches them (see the shape-model guide).
    max_iteration : int, optional
        Default 5.
    tolerance : float, optional
        Default 1e-3.
    fixed : (l,) array_like of int, optional
        Indices of points that do not slide (true landmarks).
    scaling : bool, optional
        Similarity instead of rigid Procrustes. Default ``False``.
    faces : (m, 3) array_like of int, optional
        The triangles of the semilandmark meshes (the template's): with them, moves that would
        turn a triangle over are held back. Without them nothing guards the meshes.

    Returns
    -------
    SlidingResult

    References
    ----------
    .. [1] F. L. Bookstein, "Landmark methods for forms without landmarks: morphometrics of group
       differences in outline shape", Medical Image Analysis 1(3), 1997.
       :doi:`10.1016/S1361-8415(97)85012-8`
    .. [2] P. Gunz, P. Mitteroecker, F. L. Bookstein, "Semilandmarks in three dimensions", in
       Modern Morphometrics in Physical Anthropology, 2005. :doi:`10.1007/0-387-27614-9_3`
    """
    x = as_shape_array(shapes)
    if not isinstance(targets, (list, tuple)):
        raise TypeError(f"`targets` must be a sequence of meshes, got {type(targets).__name__}")
    if len(targets) != x.shape[0]:
        raise ValueError(
            f"`targets` must hold {x.shape[0]} surfaces (one per shape), got {len(targets)}"
        )
    surfaces = [
        as_mesh_arrays(t, f"targets[{i}]", drop_degenerate=True) for i, t in enumerate(targets)
    ]
    if criterion not in CRITERIA:
        raise ValueError(f"`criterion` must be one of {CRITERIA}, got {criterion!r}")
    max_iteration = check_positive(max_iteration, "max_iteration", integer=True)
    tolerance = check_positive(tolerance, "tolerance", allow_zero=True)
    free = np.ones(x.shape[1], dtype=bool)
    if fixed is not None:
        given = np.asarray(fixed).reshape(-1)
        # A boolean mask read as integers would fix points 0 and 1; a float index be truncated.
        if given.size and given.dtype.kind not in "iu":
            raise TypeError(
                f"`fixed` must be integer indices of points, got an array of {given.dtype}"
            )
        idx = given.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= x.shape[1]):
            raise ValueError(f"`fixed` must index points in [0, {x.shape[1] - 1}]")
        free[idx] = False
    check_bending_size(x.shape[1], criterion)
    tris = None if faces is None else as_faces(faces, x.shape[1], "faces")
    return _slide(x, surfaces, criterion, max_iteration, tolerance, free, scaling, tris)


def check_bending_size(points: int, criterion: str = "bending", name: str = "criterion") -> None:
    """Refuse ``criterion='bending'`` on more than :data:`BENDING_MAX_POINTS` points (its dense
    solve would take ``90 n^2`` bytes), naming the cures; ``name``: what the caller calls the
    choice."""
    if criterion == "bending" and points > BENDING_MAX_POINTS:
        raise ValueError(
            f"`{name}`: sliding by bending energy solves a dense system over all {points} "
            f"points (about {90 * points**2 / 1e9:.0f} GB); it takes at most "
            f"{BENDING_MAX_POINTS}: use a template of fewer vertices, or "
            + ("criterion='procrustes'" if name == "criterion" else "do without sliding")
        )


def _slide(
    x: np.ndarray,
    surfaces: list[tuple[np.ndarray, np.ndarray]],
    criterion: str,
    max_iteration: int,
    tolerance: float,
    free: np.ndarray,
    scaling: bool,
    faces: np.ndarray | None,
) -> SlidingResult:
    queries = [SurfaceDistanceQuery(v, f) for v, f in surfaces]
    # No move may turn a triangle over relative to the shape as given.
    current = np.stack([_projected(q, s, np.zeros_like(s), s, faces) for q, s in zip(queries, x)])
    displacements: list[float] = []
    distances: list[float] = [float(generalized_procrustes(x, scaling=scaling).residuals.mean())]
    success = False
    iterations = 0
    for iterations in range(1, max_iteration + 1):
        gpa = generalized_procrustes(current, scaling=scaling)
        mean = gpa.shapes.mean(axis=0)
        if iterations > 1:
            distances.append(float(gpa.residuals.mean()))
        radius = float(np.sqrt(((mean - mean.mean(axis=0)) ** 2).sum(axis=1).mean()))
        be = _bending_matrix(mean) if criterion == "bending" else None
        moved = np.empty_like(current)
        for i, (query, shape) in enumerate(zip(queries, current)):
            _, face, _ = query.closest(shape)
            normals = query.face_normals[face]
            t1, t2 = _tangent_bases(normals)
            # The mean in this shape's frame.
            target = apply_transformation(np.linalg.inv(gpa.transformations[i]), mean)
            if criterion == "procrustes":
                diff = target - shape
                step = (diff * t1).sum(1)[:, None] * t1 + (diff * t2).sum(1)[:, None] * t2
            else:
                assert be is not None
                step = _bending_step(shape, t1, t2, be, free)
            step[~free] = 0.0
            moved[i] = _projected(query, shape, step, x[i], faces)
        disp = float(np.linalg.norm(moved - current, axis=2).mean())
        displacements.append(disp)
        current = moved
        logger.debug("sliding iteration %d: mean displacement %.4g", iterations, disp)
        if disp < tolerance * max(radius, 1e-300):
            success = True
            break
    final = generalized_procrustes(current, scaling=scaling)
    distances.append(float(final.residuals.mean()))
    message = (
        f"converged in {iterations} iterations"
        if success
        else f"stopped after {max_iteration} iterations (mean displacement {displacements[-1]:.3g})"
    )
    return SlidingResult(
        shapes=current,
        criterion=criterion,
        iterations=iterations,
        displacements=np.array(displacements),
        procrustes_distances=np.array(distances),
        success=success,
        message=message,
    )


def _projected(
    query: SurfaceDistanceQuery,
    shape: np.ndarray,
    step: np.ndarray,
    given: np.ndarray,
    faces: np.ndarray | None,
) -> np.ndarray:
    """``shape + step`` projected onto the surface; with ``faces``, the move of the vertices
    of triangles it would turn over relative to ``given`` (the shape as given) is halved, then
    dropped (those stay where they are)."""
    moved = query.closest(shape + step)[2]
    if faces is None:
        return moved
    before = turned_triangles(given, shape, faces)  # none for the shape given: not this move's
    share = np.ones(shape.shape[0])
    for attempt in range(FOLD_HALVINGS + shape.shape[0]):
        new = turned_triangles(given, moved, faces) & ~before
        if not new.any():
            return moved
        held = np.unique(faces[new])
        # Halved FOLD_HALVINGS times, then dropped; each later round drops more vertices, so
        # the loop ends with every move dropped at worst (the shape itself).
        share[held] = 0.0 if attempt >= FOLD_HALVINGS else share[held] * 0.5
        moved = query.closest(shape + step * share[:, None])[2]
        still = share == 0.0
        moved[still] = shape[still]
    return shape


def _bending_step(
    shape: np.ndarray, t1: np.ndarray, t2: np.ndarray, be: np.ndarray, free: np.ndarray
) -> np.ndarray:
    """Tangential offsets of the free points at the stationary point of ``(Y + U t)^T (I_3 (x)
    Be) (Y + U t)``: the least bending energy (``Be`` is negative semidefinite)."""
    idx = np.flatnonzero(free)
    m = idx.size
    if m == 0:
        return np.zeros_like(shape)
    a1, a2 = t1[idx], t2[idx]
    bff = be[np.ix_(idx, idx)]
    if not bff.any():  # no slide of these points bends: every position is as good
        return np.zeros_like(shape)
    # U^T (I_3 (x) Be) U in 2 x 2 blocks: (U_a^T (I_3 (x) Be) U_b)_ij = Be_ij (a_i . b_j).
    lhs = np.empty((2 * m, 2 * m))
    lhs[:m, :m] = bff * (a1 @ a1.T)
    lhs[:m, m:] = bff * (a1 @ a2.T)
    lhs[m:, :m] = lhs[:m, m:].T
    lhs[m:, m:] = bff * (a2 @ a2.T)
    # (I_3 (x) Be) Y, per coordinate. Be annihilates constants, but not in rounding: a patient's
    # offset origin (1e6 mm) would leave an error along the affine maps that the ridge amplifies.
    bey = (be @ (shape - shape.mean(axis=0)))[idx]
    rhs = -np.concatenate([(a1 * bey).sum(1), (a2 * bey).sum(1)])
    # -lhs is positive semidefinite (slides along affine null directions cost nothing): a tiny
    # ridge makes it definite, and Cholesky solves it at half the cost of a general
    # factorisation (2m unknowns, dense).
    lhs *= -1.0
    lhs[np.diag_indices(2 * m)] += 1e-9 * max(float(np.trace(lhs)) / (2 * m), 1e-300)
    try:
        t = scipy.linalg.cho_solve(scipy.linalg.cho_factor(lhs), -rhs)
    except np.linalg.LinAlgError:  # rounding left an eigenvalue below zero
        t = np.linalg.solve(lhs, -rhs)
    step = np.zeros_like(shape)
    step[idx] = t[:m, None] * a1 + t[m:, None] * a2
    return step
