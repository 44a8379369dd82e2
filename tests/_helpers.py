"""Small helpers shared by the tests (import as ``from _helpers import ...``)."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def mesh_of(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)),
    )


def snapshot(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Copies of a mesh's arrays, to assert later that a call left it untouched."""
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()


def assert_untouched(mesh: o3d.geometry.TriangleMesh, snap: tuple[np.ndarray, np.ndarray]) -> None:
    np.testing.assert_array_equal(np.asarray(mesh.vertices), snap[0])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), snap[1])
