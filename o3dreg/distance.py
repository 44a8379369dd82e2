"""Point-to-surface distances with libigl's AABB tree, built once per surface."""

from __future__ import annotations

import igl
import numpy as np

__all__ = ["SurfaceDistanceQuery"]


class SurfaceDistanceQuery:
    """Closest points on a triangle mesh, for many queries against one surface.

    The AABB tree is built once at construction (the expensive part) and reused by every call,
    as the registration queries the same target surface at each iteration.

    Parameters
    ----------
    vertices : (n, 3) ndarray
    faces : (m, 3) int ndarray
        A valid triangle mesh (see :func:`o3dreg._validation.as_mesh_arrays`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self._tree = igl.AABB()
        self._tree.init(self.vertices, self.faces)
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        normals = np.cross(b - a, c - a)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.face_normals = normals / np.where(length > 0, length, 1.0)

    def __repr__(self) -> str:
        return (
            f"SurfaceDistanceQuery(vertices={self.vertices.shape[0]}, faces={self.faces.shape[0]})"
        )

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface point of each query point.

        Returns
        -------
        distances : (k,) ndarray
            Euclidean point-to-surface distances (not squared).
        face_index : (k,) int ndarray
            Triangle holding each closest point.
        closest : (k, 3) ndarray
            The closest points.
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        sqr, face, closest = self._tree.squared_distance(self.vertices, self.faces, pts)
        return np.sqrt(sqr), face, closest

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Point-to-surface distances, ``(k,)``."""
        return self.closest(points)[0]

    def gradient(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distances, closest points and the gradient of the unsigned distance at each point.

        The gradient of ``d(x) = |x - c(x)|`` is the unit vector ``(x - c) / d``; on the surface,
        where it is undefined, the triangle's normal is used (the point-to-plane limit).
        """
        dist, face, closest = self.closest(points)
        diff = np.ascontiguousarray(points) - closest
        on_surface = dist <= 1e-12 * max(1.0, float(np.abs(self.vertices).max()))
        safe = np.where(on_surface, 1.0, dist)
        grad = diff / safe[:, None]
        grad[on_surface] = self.face_normals[face[on_surface]]
        return dist, closest, grad
