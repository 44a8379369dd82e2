"""A mesh in canonical order, consistently oriented, and simplified by vertex clustering.

What is computed from a mesh in canonical order does not depend on how its vertices and
triangles were numbered: the registration prepares its target this way, and its levels of detail
are vertex-clustered copies in the same order.
"""

from __future__ import annotations

import igl
import numpy as np

from .._geometry import bounds, face_doubled_areas
from .sampling import morton_order, voxel_ranks

__all__ = ["canonical_mesh", "cluster_vertices", "oriented_faces", "sorted_triangles"]


def canonical_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with its vertices and triangles in a canonical order.

    Exact duplicate vertices are merged, vertices are sorted along a Morton curve (ties by
    ``(x, y, z)``: :func:`~o3dreg.mesh.sampling.morton_order`), each triangle is rotated
    (orientation kept) to start at its smallest index, triangles are sorted and repeated ones (and
    those that merging made degenerate) removed. Everything computed from the result is then
    independent of the input's vertex and face numbering, and triangle soups (STL) get their
    connectivity back, so open boundaries are found. The Morton order keeps
    nearby vertices, and so nearby triangles, near each other in memory: libigl's AABB tree of
    the result builds and answers queries 10-15% faster than on the same mesh sorted by ``x``.
    """
    order = morton_order(vertices)
    sorted_v = vertices[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = np.any(sorted_v[1:] != sorted_v[:-1], axis=1)
    ids = np.cumsum(new) - 1
    remap = np.empty(order.size, dtype=np.int64)
    remap[order] = ids
    v = sorted_v[new]
    f0, f1, f2 = (remap[faces[:, k]] for k in range(3))
    keep = (f0 != f1) & (f1 != f2) & (f2 != f0)
    f0, f1, f2 = f0[keep], f1[keep], f2[keep]
    if f0.size == 0:
        return v, np.zeros((0, 3), dtype=np.int64)
    return _drop_unused(v, sorted_triangles(f0, f1, f2, v.shape[0]))


def oriented_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The triangles with each connected piece oriented one way: its majority's, by area.

    Scans and meshes from other tools may hold patches wound the other way. The template's
    normals are compared with the target's (``max_normal_angle``), so such a patch would reject
    correct correspondences and leave part of the template without data. libigl's
    ``bfs_orient`` orients each piece like its first triangle; a piece whose first triangle is
    the odd one out is turned back.
    """
    oriented, piece = igl.bfs_orient(np.ascontiguousarray(faces, dtype=np.int64))
    oriented = np.asarray(oriented, dtype=np.int64)
    piece = np.asarray(piece, dtype=np.int64).ravel()
    turned = ~np.all(oriented == faces, axis=1)
    area = face_doubled_areas(vertices, faces)
    turned_area = np.bincount(piece, weights=area * turned)
    back = (turned_area > 0.5 * np.bincount(piece, weights=area))[piece]
    oriented[back] = oriented[back, ::-1]
    return oriented


def cluster_vertices(
    vertices: np.ndarray, faces: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh simplified by vertex clustering on a grid of cubes of side ``voxel``.

    Open3D's ``simplify_vertex_clustering`` with the ``Average`` contraction, followed by its
    ``remove_degenerate_triangles`` and ``remove_unreferenced_vertices``: the grid starts half a
    voxel below the smallest coordinates; the vertices of a voxel become one, their mean; a
    triangle is kept when its corners fall in three voxels, once per orientation; vertices of no
    kept triangle go. Here in NumPy, 3-4 times faster than Open3D on a million vertices, in an
    order that does not depend on the input's (the means along a Morton curve, triangles as
    :func:`canonical_mesh` sorts them) and with each mean summed in input order (Open3D sums in
    the order of a hash set, which the platform's standard library decides).
    """
    cluster = voxel_ranks(vertices, voxel, bounds(vertices)[0] - 0.5 * voxel)
    count = np.bincount(cluster)
    v = np.stack([np.bincount(cluster, weights=vertices[:, k]) / count for k in range(3)], axis=1)
    order = morton_order(v)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    v, cluster = v[order], rank[cluster]
    f0, f1, f2 = (cluster[faces[:, k]] for k in range(3))
    keep = (f0 != f1) & (f1 != f2) & (f2 != f0)
    f0, f1, f2 = f0[keep], f1[keep], f2[keep]
    v, f = _drop_unused(v, sorted_triangles(f0, f1, f2, v.shape[0]))
    return v, f.reshape(-1, 3)


def sorted_triangles(f0: np.ndarray, f1: np.ndarray, f2: np.ndarray, n: int) -> np.ndarray:
    """Triangles ``(f0, f1, f2)`` (no two corners equal) each rotated, orientation kept, to start
    at its smallest index, sorted lexicographically, repeats removed: ``(k, 3)``."""
    second, third = f1 < f0, f2 < np.minimum(f0, f1)  # the smallest is f1, or f2
    r0 = np.where(third, f2, np.where(second, f1, f0))
    r1 = np.where(third, f0, np.where(second, f2, f1))
    r2 = np.where(third, f1, np.where(second, f0, f2))
    m = np.int64(n)
    if n < 2**21:
        # One int64 key per triangle (three indices of 21 bits): a plain sort, decoded, is the
        # lexicographic order at a fraction of the cost of lexsort on a million triangles, and
        # repeated triangles are repeated keys.
        key = np.sort((r0 * m + r1) * m + r2)
        unique = np.ones(key.size, dtype=bool)
        unique[1:] = key[1:] != key[:-1]
        key = key[unique]
        return np.stack([key // (m * m), (key // m) % m, key % m], axis=1)
    f = np.stack([r0, r1, r2], axis=1)
    f = f[np.lexsort((f[:, 2], f[:, 1], f[:, 0]))]
    repeated = np.zeros(f.shape[0], dtype=bool)
    repeated[1:] = np.all(f[1:] == f[:-1], axis=1)
    return f[~repeated]


def _drop_unused(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without the vertices no triangle uses (renumbered in order)."""
    used = np.zeros(v.shape[0], dtype=bool)
    used[f.ravel()] = True
    if used.all():
        return v, f
    remap = np.cumsum(used) - 1
    return v[used], remap[f]
