"""Cleaning surfaces extracted from scans: components, cropping, smoothing and decimation.

Every function takes an ``open3d.geometry.TriangleMesh`` (or a ``(vertices, faces)`` pair),
returns a new mesh and leaves its input untouched. All are deterministic. Coordinates are in the
mesh's units (millimetres for meshes from CT).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d
from scipy import sparse
from scipy.sparse.csgraph import connected_components as graph_components

from .._geometry import face_doubled_areas
from .._validation import as_mesh_arrays, as_points, check_positive
from ..io.mesh import to_open3d
from .distinct import distinct
from .edges import SortedEdges

__all__ = [
    "Components",
    "connected_components",
    "crop_mesh",
    "decimate",
    "keep_largest_components",
    "mesh_components",
    "remove_small_components",
    "smooth_taubin",
]

logger = logging.getLogger("o3dreg")

# Decimation: accept a vertex count within this fraction below the target.
_DECIMATE_RTOL = 0.02
_DECIMATE_MAX_TRIES = 8
# Above this many times the target, decimate once to half of it before refining the count.
_DECIMATE_PRESIMPLIFY = 8


@dataclass(frozen=True, eq=False, repr=False)
class Components:
    """Connected components of a triangle mesh (triangles sharing an edge), largest first.

    Attributes
    ----------
    labels : (m,) int64 ndarray
        Component of each triangle: 0 is the largest (most vertices), then 1, ...
    vertex_counts : (k,) int64 ndarray
        Number of vertices of each component, in decreasing order.
    triangle_counts : (k,) int64 ndarray
        Number of triangles of each component.
    areas : (k,) float64 ndarray
        Surface area of each component (squared mesh units, mm² for CT).
    """

    labels: np.ndarray
    vertex_counts: np.ndarray
    triangle_counts: np.ndarray
    areas: np.ndarray

    def __len__(self) -> int:
        return int(self.vertex_counts.size)

    def __repr__(self) -> str:
        head = ", ".join(str(int(v)) for v in self.vertex_counts[:5])
        more = ", ..." if len(self) > 5 else ""
        return f"Components(n={len(self)}, vertex_counts=[{head}{more}])"


def connected_components(mesh: Any) -> Components:
    """Find the connected components of a mesh, ordered by vertex count (largest first).

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)

    Returns
    -------
    components : Components
        Ties in vertex count are broken by the lowest triangle index, so the order is
        deterministic.
    """
    vertices, faces = as_mesh_arrays(mesh, "mesh", drop_degenerate=True)
    return mesh_components(vertices, faces)


def _triangle_labels(
    n_vertices: int, faces: np.ndarray, edges: SortedEdges | None = None
) -> np.ndarray:
    """Component of each triangle, triangles sharing an edge being connected, numbered in order
    of first triangle (``edges``: the faces' sorted edges when the caller has them).

    Sorting the edge keys puts the triangles sharing an edge next to each other, and those
    neighbours are the links of a graph of triangles solved with SciPy (5-10x faster than
    Open3D's ``cluster_connected_triangles`` on meshes of 10^5-10^6 triangles).
    """
    m = faces.shape[0]
    if edges is None:
        edges = SortedEdges(n_vertices, faces)
    i, j = edges.triangle_links()
    graph = sparse.csr_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(m, m))
    _, labels = graph_components(graph, directed=False)
    labels = labels.astype(np.int64)
    # SciPy numbers components as it meets them in node order; renumber only if it did not.
    previous = np.maximum.accumulate(np.concatenate([[-1], labels[:-1]]))
    if labels.size and not np.all(labels <= previous + 1):
        _, first_index, raw = np.unique(labels, return_index=True, return_inverse=True)
        rank = np.empty(first_index.size, dtype=np.int64)
        rank[np.argsort(first_index)] = np.arange(first_index.size)
        labels = rank[raw.ravel()]
    return labels


def mesh_components(
    vertices: np.ndarray, faces: np.ndarray, edges: SortedEdges | None = None
) -> Components:
    """:func:`connected_components` of arrays already checked (``(n, 3)`` float vertices,
    ``(m, 3)`` int64 faces indexing them, no degenerate triangle): no validation. ``edges``: the
    faces' sorted edges, where the caller has them (the sort is most of the cost)."""
    raw = _triangle_labels(vertices.shape[0], faces, edges)
    k = int(raw.max()) + 1 if raw.size else 0
    # Vertex count per component: count each (component, vertex) pair once (components may
    # touch at a single vertex).
    if k == 1:
        # One component (the common case of a large surface): its used vertices, no sort.
        used = np.zeros(vertices.shape[0], dtype=bool)
        used[faces.ravel()] = True
        vertex_counts = np.array([np.count_nonzero(used)], dtype=np.int64)
    else:
        pairs = distinct(np.repeat(raw, 3) * vertices.shape[0] + faces.ravel())
        vertex_counts = np.bincount(pairs // vertices.shape[0], minlength=k)
    triangle_counts = np.bincount(raw, minlength=k)
    tri_area = 0.5 * face_doubled_areas(vertices, faces)
    areas = np.bincount(raw, weights=tri_area, minlength=k)
    first = np.full(k, faces.shape[0], dtype=np.int64)
    np.minimum.at(first, raw, np.arange(raw.size))
    order = np.lexsort((first, -vertex_counts))
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(k)
    result = Components(
        labels=rank[raw],
        vertex_counts=vertex_counts[order],
        triangle_counts=triangle_counts[order],
        areas=areas[order],
    )
    for name in ("labels", "vertex_counts", "triangle_counts", "areas"):
        getattr(result, name).flags.writeable = False
    return result


def _submesh(
    vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray
) -> o3d.geometry.TriangleMesh:
    """Mesh of the kept faces, without unreferenced vertices (vertex order preserved)."""
    kept = faces[keep]
    used = np.zeros(vertices.shape[0], dtype=bool)
    used[kept.ravel()] = True
    remap = np.cumsum(used) - 1
    return to_open3d(vertices[used], remap[kept])


def keep_largest_components(mesh: Any, n: int = 1) -> o3d.geometry.TriangleMesh:
    """Keep the ``n`` connected components with the most vertices.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
    n : int, optional
        How many components to keep. Default 1 (the largest).

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
        A new mesh; all components are kept when the mesh has ``n`` or fewer.

    Examples
    --------
    >>> import open3d as o3d
    >>> a = o3d.geometry.TriangleMesh.create_sphere(2.0)
    >>> b = o3d.geometry.TriangleMesh.create_sphere(1.0).translate((5, 0, 0))
    >>> len(keep_largest_components(a + b).vertices) == len(a.vertices)
    True
    """
    count = check_positive(n, "n", integer=True)
    vertices, faces = as_mesh_arrays(mesh, "mesh", drop_degenerate=True)
    components = mesh_components(vertices, faces)
    out = _submesh(vertices, faces, components.labels < count)
    logger.info(
        "kept %d of %d component(s): %d vertices",
        min(count, len(components)),
        len(components),
        len(out.vertices),
    )
    return out


def remove_small_components(mesh: Any, min_vertices: int) -> o3d.geometry.TriangleMesh:
    """Remove the connected components with fewer than ``min_vertices`` vertices.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
    min_vertices : int
        Smallest vertex count of a component that is kept.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh

    Raises
    ------
    ValueError
        Every component is smaller than ``min_vertices``.
    """
    threshold = check_positive(min_vertices, "min_vertices", integer=True)
    vertices, faces = as_mesh_arrays(mesh, "mesh", drop_degenerate=True)
    components = mesh_components(vertices, faces)
    large = components.vertex_counts >= threshold
    if not large.any():
        raise ValueError(
            f"`min_vertices` must not exceed the largest component "
            f"({int(components.vertex_counts[0])} vertices), got {threshold}"
        )
    out = _submesh(vertices, faces, large[components.labels])
    logger.info("removed %d component(s) below %d vertices", int((~large).sum()), threshold)
    return out


def crop_mesh(mesh: Any, *, box: Any = None, plane: Any = None) -> o3d.geometry.TriangleMesh:
    """Keep the triangles whose three vertices lie in a box and/or on one side of a plane.

    Use it for instance to separate the mandible from the skull with a plane under the maxilla,
    then :func:`keep_largest_components`.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
    box : (2, 3) array_like, optional
        ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in world units; bounds included.
    plane : (2, 3) array_like, optional
        ``[point, normal]``: the kept side is ``dot(x - point, normal) >= 0`` (where the normal
        points). The normal need not be unit length.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
        The kept triangles (cut triangles are dropped, not split), unused vertices removed.

    Raises
    ------
    ValueError
        Neither ``box`` nor ``plane`` given, a malformed box or plane, or nothing left.
    """
    if box is None and plane is None:
        raise ValueError("crop_mesh needs `box` or `plane` (or both), got neither")
    box_arr = None
    if box is not None:
        box_arr = as_points(box, "box")
        if box_arr.shape[0] != 2:
            raise ValueError(f"`box` must have shape (2, 3), got {box_arr.shape}")
        if np.any(box_arr[0] > box_arr[1]):
            raise ValueError(f"`box` must have min <= max on every axis, got {box_arr.tolist()}")
    plane_arr = None
    if plane is not None:
        plane_arr = as_points(plane, "plane")
        if plane_arr.shape[0] != 2:
            raise ValueError(
                f"`plane` must have shape (2, 3) (point, normal), got {plane_arr.shape}"
            )
        if not np.linalg.norm(plane_arr[1]) > 0:
            raise ValueError(f"`plane` normal must be non-zero, got {plane_arr[1].tolist()}")
    vertices, faces = as_mesh_arrays(mesh, "mesh", drop_degenerate=True)
    regions: dict[str, tuple[np.ndarray, str]] = {}  # parameter: (vertices inside, as given)
    if box_arr is not None:
        inside = np.all((vertices >= box_arr[0]) & (vertices <= box_arr[1]), axis=1)
        regions["box"] = inside, f"{_xyz(box_arr[0])}..{_xyz(box_arr[1])}"
    if plane_arr is not None:
        inside = (vertices - plane_arr[0]) @ plane_arr[1] >= 0
        regions["plane"] = inside, f"(point {_xyz(plane_arr[0])}, normal {_xyz(plane_arr[1])})"
    keep = np.logical_and.reduce([inside for inside, _ in regions.values()])[faces].all(axis=1)
    if not keep.any():
        # The region that keeps nothing alone (else both), with its values: the one to change.
        empty = [k for k, (inside, _) in regions.items() if not inside[faces].all(axis=1).any()]
        given = " and ".join(f"`{k}` {regions[k][1]}" for k in empty[:1] or regions)
        together = "" if empty else " together (each alone keeps some)"
        raise ValueError(
            f"{given} removed every triangle{together}: the mesh spans "
            f"{_xyz(vertices.min(axis=0), 4)}..{_xyz(vertices.max(axis=0), 4)}"
        )
    out = _submesh(vertices, faces, keep)
    logger.info("cropped to %d of %d triangles", int(keep.sum()), faces.shape[0])
    return out


def _xyz(point: np.ndarray, digits: int = 6) -> str:
    return "[" + ", ".join(f"{float(v):.{digits}g}" for v in point) + "]"


def smooth_taubin(
    mesh: Any, number_of_iterations: int = 10, *, lambda_filter: float = 0.5, mu: float = -0.53
) -> o3d.geometry.TriangleMesh:
    """Taubin smoothing (low-pass, nearly volume preserving), e.g. for staircases of thick slices.

    Each iteration is a Laplacian step of weight ``lambda_filter`` followed by one of weight
    ``mu`` (negative): Open3D's ``filter_smooth_taubin`` (Taubin 1995,
    doi:10.1145/218380.218473), whose Laplacian weights neighbours by inverse distance.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
    number_of_iterations : int, optional
        Number of (lambda, mu) pairs. Default 10. 0 returns a copy.
    lambda_filter : float, optional
        Shrinking step, in (0, 1). Default 0.5.
    mu : float, optional
        Inflating step, negative with ``lambda_filter < -mu < 1``. Default -0.53.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
        Same connectivity, moved vertices.
    """
    iterations = check_positive(
        number_of_iterations, "number_of_iterations", integer=True, allow_zero=True
    )
    lam = check_positive(lambda_filter, "lambda_filter")
    if not lam < 1:
        raise ValueError(f"`lambda_filter` must be in (0, 1), got {lambda_filter!r}")
    if isinstance(mu, bool) or not isinstance(mu, (int, float, np.integer, np.floating)):
        raise TypeError(f"`mu` must be a number, got {type(mu).__name__}")
    if not (np.isfinite(mu) and -1 < mu < -lam):
        raise ValueError(
            f"`mu` must be negative with lambda_filter < -mu < 1 (lambda_filter={lam}), got {mu!r}"
        )
    vertices, faces = as_mesh_arrays(mesh, "mesh")
    source = to_open3d(vertices, faces)
    if iterations == 0:
        return source
    out = source.filter_smooth_taubin(
        number_of_iterations=iterations, lambda_filter=lam, mu=float(mu)
    )
    if not np.all(np.isfinite(np.asarray(out.vertices))):
        raise ValueError(
            "`mesh` gave non-finite vertices when smoothed: it has coincident vertices "
            "(zero-length edges); merge them first"
        )
    return out


def decimate(mesh: Any, number_of_vertices: int) -> o3d.geometry.TriangleMesh:
    """Simplify a mesh to about ``number_of_vertices`` vertices with quadric error decimation.

    Open3D's ``simplify_quadric_decimation`` (Garland & Heckbert 1997) targets a triangle count;
    the target is mapped from the vertex count through the mesh's triangle/vertex ratio (about 2
    for closed surfaces) and refined until the result has between 98 % and 100 % of the
    requested vertices (at most 8 tries; the closest result not above the target is returned).
    Meshes with more than 8 times the target are first decimated once to 4 times the target,
    and the tries run on that mesh.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
    number_of_vertices : int
        Target vertex count (>= 4), e.g. 1000-4000 for a registration template.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
        At most ``number_of_vertices`` vertices; a copy when the mesh already has fewer.
    """
    target = check_positive(number_of_vertices, "number_of_vertices", integer=True)
    if target < 4:
        raise ValueError(f"`number_of_vertices` must be >= 4, got {target}")
    vertices, faces = as_mesh_arrays(mesh, "mesh", drop_degenerate=True)
    if vertices.shape[0] <= target:
        return to_open3d(vertices, faces)
    source = to_open3d(vertices, faces)
    ratio = faces.shape[0] / vertices.shape[0]
    if vertices.shape[0] > _DECIMATE_PRESIMPLIFY * target:
        # One pass to a few times the target, then refine the count on that smaller mesh: each
        # try then costs little, whatever the size of the input.
        source = source.simplify_quadric_decimation(
            target_number_of_triangles=round(_DECIMATE_PRESIMPLIFY / 2 * target * ratio)
        )
        source.remove_degenerate_triangles()
        source.remove_unreferenced_vertices()
        ratio = len(source.triangles) / max(len(source.vertices), 1)
        faces = np.asarray(source.triangles)
    tri_target = max(4, round(target * ratio))
    best: o3d.geometry.TriangleMesh | None = None
    best_count = -1
    low, high = 4, faces.shape[0]
    for _ in range(_DECIMATE_MAX_TRIES):
        out = source.simplify_quadric_decimation(target_number_of_triangles=int(tri_target))
        out.remove_degenerate_triangles()
        out.remove_unreferenced_vertices()
        count = len(out.vertices)
        if count <= target and count > best_count:
            best, best_count = out, count
        if target * (1 - _DECIMATE_RTOL) <= count <= target:
            break
        # Bisection on the triangle target, guided by the observed ratio.
        if count > target:
            high = min(high, tri_target - 1)
        else:
            low = max(low, tri_target + 1)
        if low > high:
            break
        guess = round(tri_target * target / max(count, 1))
        tri_target = int(min(max(guess, low), high))
    if best is None:
        raise RuntimeError(
            f"decimation could not reach {target} vertices (smallest result {count})"
        )
    logger.info("decimated %d -> %d vertices", vertices.shape[0], best_count)
    return best


def drop_small_components(
    vertices: np.ndarray, faces: np.ndarray, fraction: float, edges: SortedEdges | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its connected components smaller than ``fraction`` of the largest (the
    arrays themselves when none is; ``edges``: the faces' sorted edges, where known)."""
    components = mesh_components(vertices, faces, edges)
    big = components.vertex_counts >= fraction * components.vertex_counts[0]
    keep = big[components.labels]
    if keep.all():
        return vertices, faces
    kept = faces[keep]
    used = np.zeros(vertices.shape[0], dtype=bool)
    used[kept.ravel()] = True
    remap = np.cumsum(used) - 1
    logger.info(
        "ignoring %d small target component(s) (%d vertices)",
        int((~big).sum()),
        int((~used).sum()),
    )
    return vertices[used], remap[kept]
