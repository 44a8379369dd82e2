"""Small geometric kernels shared across modules (arrays in, arrays out)."""

from __future__ import annotations

import numpy as np


def apply_transformation(transformation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points mapped by a ``(4, 4)`` affine transformation (a new array)."""
    return points @ transformation[:3, :3].T + transformation[:3, 3]


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
