"""Exact closest points on a triangle mesh: a bounding volume hierarchy compiled with Numba.

The registration asks the same target for the closest points of a few thousand moving template
points tens of times per level. This tree answers in compiled code on every core, without the
GIL (so the rigid step's ICP threads run beside it), and takes a hint per point: the triangle
found last time, whose distance bounds the search before it starts.

The tree: each range of triangles is split in halves at the median of their centroids along
their longest extent, down to leaves of at most :data:`LEAF_SIZE` triangles; each node holds the
bounding box of its triangles. A query descends the nearer child first and skips every node whose box is not nearer
than the best triangle found so far; the closest point on a triangle is found in the Voronoi
region of the point (vertex, edge or face; Ericson, *Real-Time Collision Detection*, 5.1.5),
with flat triangles (a point, a segment, collinear corners) answered by their edges.
"""

from __future__ import annotations

import numba
import numpy as np

from ._compiled import JIT, split

__all__ = ["LEAF_SIZE", "TriangleTree"]

#: Triangles per leaf at most: a leaf's triangles are tested one after the other.
LEAF_SIZE = 2


@numba.njit(**JIT)
def _select(order, centre, axis, s, e, k):  # type: ignore[no-untyped-def]
    """Reorder rows ``s:e`` of ``centre`` and ``order`` alike so that row ``k`` holds the
    element of rank ``k - s`` along ``axis``, none greater before it and none smaller after
    (Hoare's selection, on rows side by side in memory)."""
    lo, hi = s, e - 1
    while lo < hi:
        mid = (lo + hi) // 2
        # The median of three as the pivot (deterministic; sorted input costs no more).
        a, b, c = centre[lo, axis], centre[mid, axis], centre[hi, axis]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = lo, hi
        while i <= j:
            while centre[i, axis] < pivot:
                i += 1
            while centre[j, axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                for x in range(3):
                    centre[i, x], centre[j, x] = centre[j, x], centre[i, x]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@numba.njit(**JIT)
def _build(corners: np.ndarray, leaf_size: int) -> tuple:  # type: ignore[type-arg]
    """Nodes of the tree: each range of triangles is split at the median of its centroids
    along their longest extent; boxes from the leaves up (children are made after their
    parent)."""
    m = corners.shape[0]
    tri_lo = np.empty((m, 3))
    tri_hi = np.empty((m, 3))
    for t in range(m):
        for a in range(3):
            tri_lo[t, a] = min(corners[t, a], corners[t, 3 + a], corners[t, 6 + a])
            tri_hi[t, a] = max(corners[t, a], corners[t, 3 + a], corners[t, 6 + a])
    # The centres of the triangles' boxes, kept in the order of ``order`` as it is shuffled.
    centre = 0.5 * (tri_lo + tri_hi)
    order = np.arange(m)
    # Halving a range longer than a leaf leaves halves of at least (leaf_size + 1) // 2.
    smallest = (leaf_size + 1) // 2
    capacity = max(1, 2 * ((m + smallest - 1) // smallest))
    start = np.empty(capacity, np.int64)
    stop = np.empty(capacity, np.int64)
    left = np.full(capacity, -1, np.int64)
    lo = np.empty((capacity, 3))
    hi = np.empty((capacity, 3))
    stack = np.empty(128, np.int64)
    start[0], stop[0] = 0, m
    count = 1
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        s, e = start[node], stop[node]
        if e - s <= leaf_size:
            continue
        c0, c1, c2 = centre[s, 0], centre[s, 1], centre[s, 2]
        d0, d1, d2 = c0, c1, c2
        for k in range(s + 1, e):
            c0, d0 = min(c0, centre[k, 0]), max(d0, centre[k, 0])
            c1, d1 = min(c1, centre[k, 1]), max(d1, centre[k, 1])
            c2, d2 = min(c2, centre[k, 2]), max(d2, centre[k, 2])
        axis = 0
        if d1 - c1 > d0 - c0:
            axis = 1
        if d2 - c2 > max(d0 - c0, d1 - c1):
            axis = 2
        mid = (s + e) // 2
        _select(order, centre, axis, s, e, mid)
        left[node] = count
        start[count], stop[count] = s, mid
        start[count + 1], stop[count + 1] = mid, e
        stack[top + 1] = count
        stack[top + 2] = count + 1
        top += 2
        count += 2
    for node in range(count - 1, -1, -1):
        if left[node] < 0:
            for a in range(3):
                lo[node, a] = np.inf
                hi[node, a] = -np.inf
            for k in range(start[node], stop[node]):
                t = order[k]
                for a in range(3):
                    lo[node, a] = min(lo[node, a], tri_lo[t, a])
                    hi[node, a] = max(hi[node, a], tri_hi[t, a])
        else:
            first, second = left[node], left[node] + 1
            for a in range(3):
                lo[node, a] = min(lo[first, a], lo[second, a])
                hi[node, a] = max(hi[first, a], hi[second, a])
    return order, start[:count], stop[:count], left[:count], lo[:count], hi[:count]


@numba.njit(inline="always", **JIT)
def _segment(px, py, pz, ax, ay, az, bx, by, bz):  # type: ignore[no-untyped-def]
    """Closest point to ``p`` on the segment ``ab`` (a point when ``a == b``)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    uu = ux * ux + uy * uy + uz * uz
    t = 0.0
    if uu > 0.0:
        t = ((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / uu
        t = min(1.0, max(0.0, t))
    return ax + t * ux, ay + t * uy, az + t * uz


@numba.njit(inline="always", **JIT)
def _closest_on_flat(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # type: ignore[no-untyped-def]
    """Closest point to ``p`` on a flat triangle ``abc`` (a point or a segment): the nearest
    of its edges' closest points."""
    qx, qy, qz = _segment(px, py, pz, ax, ay, az, bx, by, bz)
    best = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
    rx, ry, rz = _segment(px, py, pz, bx, by, bz, cx, cy, cz)
    d = (rx - px) ** 2 + (ry - py) ** 2 + (rz - pz) ** 2
    if d < best:
        qx, qy, qz, best = rx, ry, rz, d
    rx, ry, rz = _segment(px, py, pz, cx, cy, cz, ax, ay, az)
    d = (rx - px) ** 2 + (ry - py) ** 2 + (rz - pz) ** 2
    if d < best:
        qx, qy, qz = rx, ry, rz
    return qx, qy, qz


@numba.njit(inline="always", **JIT)
def _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # type: ignore[no-untyped-def]
    """Closest point to ``p`` on a triangle ``abc`` that is not flat, found in its Voronoi
    region."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return _segment(px, py, pz, ax, ay, az, bx, by, bz)
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return _segment(px, py, pz, ax, ay, az, cx, cy, cz)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        return _segment(px, py, pz, bx, by, bz, cx, cy, cz)
    denom = va + vb + vc
    if not denom > 0.0:  # flat after all, by rounding
        return _closest_on_flat(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    v = vb / denom
    w = vc / denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@numba.njit(inline="always", **JIT)
def _box_distance(box, node, px, py, pz):  # type: ignore[no-untyped-def]
    """Squared distance from ``p`` to the bounding box of ``node`` (0 inside it)."""
    g = max(box[node, 0] - px, 0.0, px - box[node, 3])
    d = g * g
    g = max(box[node, 1] - py, 0.0, py - box[node, 4])
    d += g * g
    g = max(box[node, 2] - pz, 0.0, pz - box[node, 5])
    return d + g * g


@numba.njit(inline="always", **JIT)
def _triangle(corners, flat, k, px, py, pz):  # type: ignore[no-untyped-def]
    if flat[k]:
        return _closest_on_flat(
            px, py, pz,
            corners[k, 0], corners[k, 1], corners[k, 2],
            corners[k, 3], corners[k, 4], corners[k, 5],
            corners[k, 6], corners[k, 7], corners[k, 8],
        )  # fmt: skip
    return _closest_on_triangle(
        px, py, pz,
        corners[k, 0], corners[k, 1], corners[k, 2],
        corners[k, 3], corners[k, 4], corners[k, 5],
        corners[k, 6], corners[k, 7], corners[k, 8],
    )  # fmt: skip


@numba.njit(**JIT)
def _flat(corners):  # type: ignore[no-untyped-def]
    """Per triangle, whether it is flat: a point, a segment or three collinear corners
    (``|ab x ac| <= 1e-10 |ab| |ac|``), where the Voronoi regions of a triangle do not hold."""
    m = corners.shape[0]
    out = np.empty(m, np.bool_)
    for k in range(m):
        ux, uy, uz = (
            corners[k, 3] - corners[k, 0],
            corners[k, 4] - corners[k, 1],
            corners[k, 5] - corners[k, 2],
        )
        wx, wy, wz = (
            corners[k, 6] - corners[k, 0],
            corners[k, 7] - corners[k, 1],
            corners[k, 8] - corners[k, 2],
        )
        nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        nn = nx * nx + ny * ny + nz * nz
        out[k] = nn <= 1e-20 * (ux * ux + uy * uy + uz * uz) * (wx * wx + wy * wy + wz * wz)
    return out


@numba.njit(**JIT)
def _query(  # type: ignore[no-untyped-def]
    corners,
    flat,
    face_of,
    rank,
    start,
    stop,
    left,
    box,
    points,
    hint,
    out_sqr,
    out_face,
    out_point,
    begin,
    end,
):
    """Closest triangle of every point. ``corners`` are in the tree's order (``face_of`` maps
    back to the mesh, ``rank`` forward); ``hint[i] >= 0``: a mesh triangle to start from."""
    for i in range(begin, end):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        found = -1
        qx = qy = qz = 0.0
        if hint[i] >= 0:
            found = rank[hint[i]]
            qx, qy, qz = _triangle(corners, flat, found, px, py, pz)
            best = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
        stack = np.empty(64, np.int64)
        gap = np.empty(64)
        top = 0
        stack[0] = 0
        gap[0] = _box_distance(box, 0, px, py, pz)
        while top >= 0:
            node = stack[top]
            near = gap[top]
            top -= 1
            if near >= best:
                continue
            if left[node] < 0:
                for k in range(start[node], stop[node]):
                    if k == found:
                        continue
                    rx, ry, rz = _triangle(corners, flat, k, px, py, pz)
                    d = (rx - px) ** 2 + (ry - py) ** 2 + (rz - pz) ** 2
                    # Ties go to the smaller triangle index, whatever the order of the search.
                    if d < best or (d == best and face_of[k] < face_of[found]):
                        best, found, qx, qy, qz = d, k, rx, ry, rz
                continue
            a = left[node]
            b = a + 1
            da = _box_distance(box, a, px, py, pz)
            db = _box_distance(box, b, px, py, pz)
            if da > db:
                a, b, da, db = b, a, db, da
            # The nearer child is popped first.
            if db < best:
                top += 1
                stack[top] = b
                gap[top] = db
            if da < best:
                top += 1
                stack[top] = a
                gap[top] = da
        out_sqr[i] = best
        out_face[i] = face_of[found] if found >= 0 else -1
        out_point[i, 0], out_point[i, 1], out_point[i, 2] = qx, qy, qz


class TriangleTree:
    """Bounding volume hierarchy of a triangle mesh's triangles, for exact closest points.

    Parameters
    ----------
    vertices : (n, 3) float64 ndarray
    faces : (m, 3) int64 ndarray
        A triangle mesh with at least one triangle; indices in range.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        # Each triangle's corners side by side: one cache line per triangle test.
        self._corners = np.ascontiguousarray(v[f].reshape(-1, 9))
        order, self._start, self._stop, self._left, lo, hi = _build(self._corners, LEAF_SIZE)
        # Leaves' triangles side by side, in the tree's order; the children of a node too.
        self._corners = np.ascontiguousarray(self._corners[order])
        self._face_of = order
        self._rank = np.empty_like(order)
        self._rank[order] = np.arange(order.size)
        self._box = np.ascontiguousarray(np.hstack([lo, hi]))
        self._flat = _flat(self._corners)

    def __repr__(self) -> str:
        return f"TriangleTree(faces={self._corners.shape[0]}, nodes={self._left.shape[0]})"

    def closest(
        self, points: np.ndarray, hint: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Squared distances, closest triangles and closest points of ``points`` (``(k, 3)``).

        ``hint``: per point a triangle index (or -1) whose distance starts the search; the
        answer is the same with or without it, up to which of several equally close triangles
        is named (the smallest index of those the search reaches).
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        k = pts.shape[0]
        if hint is None:
            hints = np.full(k, -1, dtype=np.int64)
        else:
            hints = np.ascontiguousarray(hint, dtype=np.int64)
        sqr = np.empty(k)
        face = np.empty(k, dtype=np.int64)
        closest = np.empty((k, 3))
        split(
            _query, k, self._corners, self._flat, self._face_of, self._rank, self._start, self._stop,
            self._left, self._box, pts, hints, sqr, face, closest,
        )  # fmt: skip
        return sqr, face, closest
