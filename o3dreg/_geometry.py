"""Small geometric kernels shared across modules (arrays in, arrays out)."""

from __future__ import annotations

import numpy as np


def apply_transformation(transformation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points mapped by a ``(4, 4)`` affine transformation (a new array)."""
    return points @ transformation[:3, :3].T + transformation[:3, 3]


def into_frame(frame: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points in the coordinates of a rigid ``frame`` (the transformation from them to
    the points' coordinates): the inverse of ``apply_transformation(frame, ...)``, without
    inverting the matrix."""
    return (points - frame[:3, 3]) @ frame[:3, :3]


def proper_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Proper rotation ``R`` minimising ``|a R^T - b|`` for centred ``(n, 3)`` ``a``, ``b``
    (Kabsch: no reflection)."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    d = 1.0 if d == 0 else d
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def fit_pose(
    source: np.ndarray, target: np.ndarray, scaling: bool, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares rigid (or similarity) map of ``source`` onto ``target`` (Umeyama 1991), as
    a ``(4, 4)`` transformation, optionally with a non-negative weight per point pair; no
    reflection.

    For arrays already checked (``(n, 3)`` float arrays of the same shape, the points not all
    coincident; positive weights): no validation, for inner loops.
    """
    if weights is None:
        mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
        a, b = source - mu_s, target - mu_t
        wa = a
    else:
        w = weights / weights.sum()
        mu_s, mu_t = w @ source, w @ target
        a, b = source - mu_s, target - mu_t
        wa = a * w[:, None]
    r = proper_rotation(wa, b)
    s = 1.0
    if scaling:
        denom = float((wa * a).sum())
        s = float(((wa @ r.T) * b).sum()) / denom if denom > 0 else 1.0
    t = np.eye(4)
    t[:3, :3] = s * r
    t[:3, 3] = mu_t - s * r @ mu_s
    return t


def polar_angles(matrices: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of the polar part of each of ``(k, 3, 3)`` matrices: how far
    a map with these Jacobians turns space locally (180 where one reflects)."""
    u, _, vt = np.linalg.svd(matrices)
    rotations = u @ vt
    cosine = (np.trace(rotations, axis1=1, axis2=2) - 1.0) / 2.0
    angles = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    angles[np.linalg.det(rotations) < 0] = 180.0
    return angles


def rotation_angle(transformation: np.ndarray) -> float:
    """Rotation angle (degrees) of a rigid or similarity transformation."""
    m = transformation[:3, :3]
    r = m / max(float(np.cbrt(abs(np.linalg.det(m)))), 1e-300)
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest coordinate of each axis of ``(n, d)`` points, ``n >= 1`` (a column
    at a time: a reduction over axis 0 of an ``(n, 3)`` array is 20 times slower)."""
    lo = np.array([points[:, k].min() for k in range(points.shape[1])])
    hi = np.array([points[:, k].max() for k in range(points.shape[1])])
    return lo, hi


def det3(m: np.ndarray) -> np.ndarray:
    """Determinants of ``(k, 3, 3)`` matrices by cofactor expansion along the first row,
    ``(k,)``: a few vector operations, where ``np.linalg.det`` factorises each matrix."""
    return (
        m[:, 0, 0] * (m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1])
        - m[:, 0, 1] * (m[:, 1, 0] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 0])
        + m[:, 0, 2] * (m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0])
    )


def barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(k, 3)`` of ``points (k, 3)`` in triangles ``corners (k, 3, 3)``.

    Meant for points on their triangle (closest points): coordinates are clipped at 0 and
    renormalised to sum to 1, which absorbs rounding just outside an edge. A degenerate triangle
    gives the coordinates of its first corner.
    """
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = (v0 * v0).sum(axis=1)
    d01 = (v0 * v1).sum(axis=1)
    d11 = (v1 * v1).sum(axis=1)
    d20 = (v2 * v0).sum(axis=1)
    d21 = (v2 * v1).sum(axis=1)
    denom = d00 * d11 - d01 * d01
    denom = np.where(denom == 0, 1.0, denom)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    bary = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return bary / bary.sum(axis=1, keepdims=True)


#: Triangles per block of the per-triangle kernels below. Blocks keep every temporary small
#: (a few hundred kB): whole-array temporaries on a million triangles are fresh memory whose
#: first touch costs more than the arithmetic.
BLOCK = 1 << 15


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(b - a) x (c - a)`` of every triangle ``(a, b, c)``, ``(m, 3)``: its normal times twice
    its area.

    The same numbers as ``np.cross`` (the same products and differences, in the same order),
    computed a component at a time and a block of triangles at a time: ``np.cross`` is 20 times
    slower on a million triangles.
    """
    # Contiguous columns: strided (m, 3) arithmetic is several times slower.
    cols = [np.ascontiguousarray(vertices[:, i], dtype=np.float64) for i in range(3)]
    out = np.empty((faces.shape[0], 3))
    for start in range(0, faces.shape[0], BLOCK):
        out[start : start + BLOCK] = _cross_block(cols, faces[start : start + BLOCK])
    return out


def turned_triangles(before: np.ndarray, after: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per triangle, whether its normal reverses between two vertex sets (``n_before .
    n_after <= 0``), ``(m,)`` bool; a triangle of zero area before never counts."""
    n0, n1 = face_cross(before, faces), face_cross(after, faces)
    area0 = row_norms(n0)
    valid = area0 > 1e-12 * max(float(area0.max(initial=0.0)), 1e-300)
    return valid & ((n0 * n1).sum(axis=1) <= 0.0)


def face_doubled_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``|(b - a) x (c - a)|`` of every triangle, ``(m,)``: twice its area. The same numbers as
    ``row_norms(face_cross(vertices, faces))``, without the ``(m, 3)`` intermediate."""
    cols = [np.ascontiguousarray(vertices[:, i], dtype=np.float64) for i in range(3)]
    out = np.empty(faces.shape[0])
    for start in range(0, faces.shape[0], BLOCK):
        out[start : start + BLOCK] = row_norms(_cross_block(cols, faces[start : start + BLOCK]))
    return out


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A third of the area of every triangle around each vertex, ``(n,)`` (0 for a vertex of no
    triangle): the area each vertex stands for; they add up to the surface's area."""
    third = face_doubled_areas(vertices, faces) / 6.0
    return np.bincount(faces.ravel(), np.repeat(third, 3), minlength=vertices.shape[0])


def _cross_block(cols: list[np.ndarray], faces: np.ndarray) -> np.ndarray:
    corner = [np.ascontiguousarray(faces[:, k]) for k in range(3)]
    a, b, c = ([col[corner[k]] for col in cols] for k in range(3))
    return np.stack(corner_cross(a, b, c), axis=1)


def corner_cross(a: list[np.ndarray], b: list[np.ndarray], c: list[np.ndarray]) -> list[np.ndarray]:
    """``(b - a) x (c - a)`` of triangles given by their corners' coordinates, one array per
    axis (``a[i]``: coordinate ``i`` of every first corner): the three components, for callers
    that gathered the corners already (:func:`face_cross` gathers them itself)."""
    u = [bi - ai for ai, bi in zip(a, b)]
    w = [ci - ai for ai, ci in zip(a, c)]
    return [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]


def row_norms(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=1)`` of an ``(m, 3)`` array, the same numbers, a column at a
    time (several times faster on a million rows)."""
    return np.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2])
