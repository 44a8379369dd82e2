"""Validation at the public boundary: one place that turns user input into clean arrays.

Every public function calls these helpers once, then works on arrays it owns. Errors name the
parameter, the expectation and what was received.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import re
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import open3d as o3d

from ._geometry import face_doubled_areas

__all__ = [
    "as_faces",
    "as_mesh_arrays",
    "as_numbers",
    "as_points",
    "as_transformation",
    "check_output_path",
    "check_positive",
    "check_probability",
    "moved_name",
    "named_as",
    "to_open3d",
]


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    return f"{type(value).__name__}"


def as_points(value: Any, name: str, *, allow_empty: bool = False) -> np.ndarray:
    """Return ``value`` as a new ``(n, 3) float64`` array of finite coordinates."""
    if isinstance(value, o3d.geometry.PointCloud):
        value = np.asarray(value.points)
    elif isinstance(value, o3d.geometry.TriangleMesh):
        value = np.asarray(value.vertices)
    if not isinstance(value, (np.ndarray, list, tuple)):
        raise TypeError(f"`{name}` must be an (n, 3) array of points, got {_describe(value)}")
    try:
        arr = np.asarray(value)
    except ValueError:  # rows of different lengths
        raise ValueError(
            f"`{name}` must be an (n, 3) array of points, got a {type(value).__name__} whose "
            "rows differ in length (a (vertices, faces) pair where points are expected?)"
        ) from None
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise TypeError(f"`{name}` must hold real numbers, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"`{name}` must have shape (n, 3), got {arr.shape}")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"`{name}` must hold at least one point, got 0")
    out = np.array(arr, dtype=np.float64, order="C", copy=True)
    if not np.all(np.isfinite(out)):
        bad = int(np.count_nonzero(~np.isfinite(out).all(axis=1)))
        raise ValueError(f"`{name}` must hold finite coordinates, got {bad} row(s) with NaN or inf")
    return out


_MESH_KINDS = (
    "an open3d.geometry.TriangleMesh, an open3d.t.geometry.TriangleMesh, a trimesh.Trimesh, "
    "a triangulated pyvista.PolyData, an object with vertex (.vertices or .points) and face "
    "(.faces or .triangles) arrays, or a (vertices, faces) pair"
)


def _padded_cells_to_triangles(cells: np.ndarray, name: str) -> np.ndarray:
    """Triangles of a VTK-style flat cell array ``[3, i, j, k, 3, ...]`` (pyvista ``faces``)."""
    if not np.issubdtype(cells.dtype, np.integer):
        raise TypeError(f"`{name}.faces` must hold integers, got dtype {cells.dtype}")
    if cells.size == 0:
        return cells.reshape(0, 3)
    # Every 4th entry is 3 from the start <=> every cell is a triangle (by induction).
    if cells.size % 4 == 0 and np.all(cells[::4] == 3):
        return cells.reshape(-1, 4)[:, 1:]
    sizes, at = [], 0
    while at < cells.size:
        sizes.append(int(cells[at]))
        at += int(cells[at]) + 1
    if at != cells.size or min(sizes) < 1:
        raise ValueError(
            f"`{name}.faces` is not a padded cell array [n, i0, ..., n, ...] of {cells.size} "
            "entries"
        )
    other = sum(1 for n in sizes if n != 3)
    raise ValueError(
        f"`{name}` must hold triangles only, got {other} of {len(sizes)} faces with "
        f"{sorted({n for n in sizes if n != 3})} vertices: triangulate it first "
        "(pyvista: mesh.triangulate())"
    )


#: meshio's cell types that are no surface: skipped (their points are on no triangle).
_MESHIO_SKIPPED = ("vertex", "line", "line3", "polyline")


def _meshio_triangles(cells: dict[str, Any], name: str) -> np.ndarray:
    """The triangles of a ``meshio.Mesh``'s cells by type: triangles as they are, quads and
    polygons split into triangle fans (with a warning), never dropped; vertices and lines
    skipped; any other cell (volume, higher order) refused."""
    parts, split = [], []
    for kind, block in cells.items():
        block = np.asarray(block)
        if kind == "triangle":
            parts.append(block)
        elif kind == "quad" or kind.startswith("polygon"):
            k = np.arange(1, block.shape[1] - 1)
            fans = np.stack(
                [np.repeat(block[:, :1], k.size, axis=1), block[:, k], block[:, k + 1]], axis=2
            )
            parts.append(fans.reshape(-1, 3))
            split.append(f"{len(block)} {kind}")
        elif kind not in _MESHIO_SKIPPED:
            raise ValueError(
                f"`{name}` must hold surface cells (triangles, quads, polygons), got {kind!r} "
                "cells: extract the surface first"
            )
    if not parts:
        kinds = ", ".join(sorted(cells)) or "none"
        raise ValueError(f"`{name}` must hold triangle cells, got {kinds}")
    if split:
        logging.getLogger("o3dreg").warning(
            "`%s`: %s cells split into triangle fans", name, ", ".join(split)
        )
    return np.concatenate([p.reshape(-1, 3) for p in parts])


def _mesh_parts(mesh: Any, name: str) -> tuple[Any, Any]:
    """``(vertices, faces)`` array-likes of any supported mesh object, without copying.

    Libraries are recognised by their attributes, never imported: o3dreg depends on none of
    trimesh, pyvista or meshio.
    """
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        return np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        if "positions" not in mesh.vertex or "indices" not in mesh.triangle:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return mesh.vertex.positions.cpu().numpy(), mesh.triangle.indices.cpu().numpy()
    if isinstance(mesh, (tuple, list)):
        if len(mesh) != 2:
            raise ValueError(
                f"`{name}` as a sequence must be a (vertices, faces) pair, got {len(mesh)} items"
            )
        return mesh[0], mesh[1]
    if isinstance(mesh, np.ndarray) or isinstance(mesh, (str, bytes, dict)):
        raise TypeError(f"`{name}` must be {_MESH_KINDS}, got {_describe(mesh)}")
    vertices = next(
        (getattr(mesh, a) for a in ("vertices", "points") if getattr(mesh, a, None) is not None),
        None,
    )
    faces = next(
        (getattr(mesh, a) for a in ("faces", "triangles") if getattr(mesh, a, None) is not None),
        None,
    )
    if faces is None and isinstance(getattr(mesh, "cells_dict", None), dict):
        faces = _meshio_triangles(mesh.cells_dict, name)
    if vertices is None or faces is None:
        raise TypeError(f"`{name}` must be {_MESH_KINDS}, got {_describe(mesh)}")
    if int(getattr(mesh, "n_strips", 0) or 0) > 0:
        raise ValueError(
            f"`{name}` holds triangle strips: triangulate it first (pyvista: mesh.triangulate())"
        )
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    if faces.ndim == 1:
        # pyvista.PolyData (and VTK): a flat, padded cell array.
        faces = _padded_cells_to_triangles(faces, name)
    return vertices, faces


def as_mesh_arrays(
    mesh: Any, name: str, *, min_faces: int = 1, drop_degenerate: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(vertices (n, 3) float64, faces (m, 3) int64)`` copies of a triangle mesh.

    ``mesh`` is an ``open3d.geometry.TriangleMesh``, an ``open3d.t.geometry.TriangleMesh``
    (any device), a ``trimesh.Trimesh``, a triangulated ``pyvista.PolyData`` (its ``faces`` are
    the flat padded array ``[3, i, j, k, 3, ...]``; other polygons are refused), a
    ``meshio.Mesh`` with triangle cells, any object with vertex (``.vertices`` or ``.points``)
    and face (``.faces`` or ``.triangles``) arrays, or a ``(vertices, faces)`` pair. The input
    is never modified: the arrays returned are new. Faces must index existing vertices.
    Degenerate triangles (repeated index or zero area) raise unless ``drop_degenerate`` is true,
    in which case they are removed.
    """
    vertices_in, faces_in = _mesh_parts(mesh, name)
    vertices = as_points(vertices_in, f"{name}.vertices")
    faces = as_faces(faces_in, vertices.shape[0], f"{name}.faces")
    if faces.shape[0] < min_faces:
        raise ValueError(
            f"`{name}` must have at least {min_faces} triangle(s), got {faces.shape[0]}"
        )
    if faces.size:
        degenerate = _degenerate_faces(vertices, faces)
        if degenerate.any():
            if not drop_degenerate:
                raise ValueError(
                    f"`{name}` must not contain degenerate triangles (repeated vertex or zero "
                    f"area), got {int(degenerate.sum())} of {faces.shape[0]}"
                )
            faces = faces[~degenerate]
            if faces.shape[0] < min_faces:
                raise ValueError(
                    f"`{name}` must have at least {min_faces} non-degenerate triangle(s), "
                    f"got {faces.shape[0]}"
                )
    return vertices, faces


def check_referenced(vertices: np.ndarray, faces: np.ndarray, name: str) -> None:
    """Refuse vertices that no triangle uses.

    A template's vertices are the semilandmarks registered onto the patient's surface; a vertex
    off every triangle is no point of that surface, yet it widens the lattices' box (coarser
    cells) and its distance enters the verdict: one stray vertex can move a whole registration
    while the verdict stays ``ok``.
    """
    used = np.zeros(vertices.shape[0], dtype=bool)
    used[faces.ravel()] = True
    if not used.all():
        unused = np.flatnonzero(~used)
        shown = ", ".join(str(i) for i in unused[:5]) + (", ..." if unused.size > 5 else "")
        raise ValueError(
            f"`{name}` must have every vertex on a triangle (its vertices are the semilandmarks), "
            f"got {unused.size} vertex(es) of no triangle (index {shown}); remove them first, "
            "e.g. open3d's mesh.remove_unreferenced_vertices()"
        )


def as_faces(faces: Any, number_of_vertices: int, name: str) -> np.ndarray:
    """Return ``faces`` as a new ``(m, 3) int64`` array of indices in ``[0, number_of_vertices)``.

    Degenerate triangles are kept (see :func:`as_mesh_arrays` to refuse or drop them).
    """
    faces_arr = np.asarray(faces)
    if faces_arr.size == 0:
        faces_arr = faces_arr.reshape(0, 3)
    if not np.issubdtype(faces_arr.dtype, np.integer):
        if np.issubdtype(faces_arr.dtype, np.floating) and np.all(np.mod(faces_arr, 1) == 0):
            faces_arr = faces_arr.astype(np.int64)
        else:
            raise TypeError(f"`{name}` must hold integers, got dtype {faces_arr.dtype}")
    if faces_arr.ndim != 2 or faces_arr.shape[1] != 3:
        raise ValueError(f"`{name}` must have shape (m, 3), got {faces_arr.shape}")
    out = np.array(faces_arr, dtype=np.int64, order="C", copy=True)
    if out.size and (out.min() < 0 or out.max() >= number_of_vertices):
        raise ValueError(
            f"`{name}` must index vertices in [0, {number_of_vertices - 1}], "
            f"got indices in [{out.min()}, {out.max()}]"
        )
    return out


def _degenerate_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    repeated = (
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    )
    doubled_area = face_doubled_areas(vertices, faces)
    # Column by column: a reduction over axis 0 of an (n, 3) array is many times slower.
    scale = max(float(np.ptp(vertices[:, k])) for k in range(3)) if vertices.shape[0] > 1 else 1.0
    # Relative to the mesh extent, so the test is independent of units.
    return repeated | (doubled_area <= (1e-12 * max(scale, 1e-300)) ** 2)


#: How far the singular values of a start's 3x3 block may differ (relative) and still be one
#: scale: above the rounding of a rotation copied with 3 decimals (~1e-3), below any shear or
#: unequal scaling worth a warning (the elastic levels absorb a percent).
SIMILARITY_TOLERANCE = 0.01


def as_transformation(value: Any, name: str = "init", *, similarity: bool = False) -> np.ndarray:
    """Return a ``(4, 4) float64`` affine transformation with last row ``[0, 0, 0, 1]`` that does
    not mirror (its 3x3 block has a positive determinant); with ``similarity``, a rotation, one
    scale and a translation (no shear, no unequal scales).

    A mirroring start turns the registered template inside out (its triangles face inwards) and
    swaps left and right, which no later step undoes and no distance measure sees on a symmetric
    bone; it is refused, with how to register a mirrored shape instead. A start of the
    registrations is refined as a rigid (or similarity) transformation, which keeps a shear as it
    is, unseen by the verdict.
    """
    if not isinstance(value, (np.ndarray, list, tuple)):
        hint = (
            " (its .transformation is one)"
            if isinstance(getattr(value, "transformation", None), np.ndarray)
            else ""
        )
        raise TypeError(f"`{name}` must be a (4, 4) array, got {_describe(value)}{hint}")
    arr = np.array(value, dtype=np.float64, copy=True)
    if arr.shape != (4, 4):
        raise ValueError(f"`{name}` must have shape (4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must hold finite values, got NaN or inf")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"`{name}` must have last row [0, 0, 0, 1], got {arr[3].tolist()}")
    det = float(np.linalg.det(arr[:3, :3]))
    if abs(det) < 1e-12:
        raise ValueError(f"`{name}` must be invertible, got a singular 3x3 block")
    if det < 0:
        raise ValueError(
            f"`{name}` must not mirror (its 3x3 block must have a positive determinant), got "
            f"determinant {det:.4g}: a mirrored start turns the registered template inside out. "
            "To register a mirror image (a left bone onto a right template), mirror the target "
            "mesh itself first: negate one coordinate and reverse its triangles' orientation"
        )
    if similarity:
        scales = np.linalg.svd(arr[:3, :3], compute_uv=False)
        if scales[0] > scales[-1] * (1.0 + SIMILARITY_TOLERANCE):
            shown = ", ".join(f"{s:.4g}" for s in scales)
            raise ValueError(
                f"`{name}` must be a rotation, one scale and a translation, got a 3x3 block "
                f"with scales {shown} along its principal axes (a shear or unequal scales); "
                "apply such a map to the template mesh itself first"
            )
    return arr


def check_positive(
    value: Any, name: str, *, integer: bool = False, allow_zero: bool = False
) -> Any:
    """Check that ``value`` is a finite positive number (or integer) and return it."""
    kind = "an integer" if integer else "a number"
    ok_type = (
        isinstance(value, (int, np.integer))
        if integer
        else isinstance(value, (int, float, np.integer, np.floating))
    )
    if isinstance(value, bool) or not ok_type:
        raise TypeError(f"`{name}` must be {kind}, got {_describe(value)}")
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"`{name}` must be a finite {kind.split()[-1]} {bound}, got {value!r}")
    return int(value) if integer else float(value)


def check_bool(value: Any, name: str) -> bool:
    """Check that ``value`` is ``True`` or ``False`` (a NumPy bool too) and return it as a bool."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"`{name}` must be True or False, got {_describe(value)}")
    return bool(value)


def check_probability(value: Any, name: str) -> float:
    """Check that ``value`` is a number in ``[0, 1]`` and return it as float."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"`{name}` must be a number in [0, 1], got {_describe(value)}")
    if not 0.0 <= float(value) <= 1.0:
        raise ValueError(f"`{name}` must be in [0, 1], got {value!r}")
    return float(value)


def as_numbers(value: Any, name: str) -> list[float]:
    """Check that ``value`` is a sequence of finite numbers (a 1-D array too) and return them as
    floats."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)):
        raise TypeError(f"`{name}` must be a sequence of numbers, got {_describe(value)}")
    out = []
    for item in value:
        if isinstance(item, (bool, np.bool_)) or not isinstance(
            item, (int, float, np.integer, np.floating)
        ):
            raise TypeError(f"`{name}` must hold numbers, got {_describe(item)}")
        if not np.isfinite(item):
            raise ValueError(f"`{name}` must hold finite numbers, got {item!r}")
        out.append(float(item))
    return out


def check_output_path(path: Any, name: str, *, overwrite: bool) -> str:
    """Check an output path: a string or path-like whose folder exists."""
    # "no" or "False" must not read as true: a refusing writer would replace the file.
    overwrite = check_bool(overwrite, "overwrite")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a path, got {_describe(path)}")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    # Asked of the path as given: the system resolves "x/../out.ply" through x, which
    # abspath would drop.
    if not os.path.isdir(folder) or not os.path.isdir(os.path.dirname(path) or "."):
        raise OSError(f"`{name}`: folder {os.path.dirname(path) or folder!r} does not exist")
    if os.path.isdir(path):
        raise OSError(f"`{name}`: {path!r} is a folder; give a file name")
    if os.path.exists(path) and not overwrite:
        raise OSError(f"`{name}`: {path!r} exists; pass overwrite=True (--overwrite) to replace it")
    return path


#: A value quoted in a message (``repr`` of a str): quotes not inside a word ("the model's").
_QUOTED = re.compile(r"""(?<!\w)('[^'\n]*'|"[^"\n]*")(?!\w)""")


@contextlib.contextmanager
def named_as(name: str, parameter: str = "path") -> Iterator[None]:
    """Errors raised in the block name ``name`` where they name ```parameter``` (outside the
    values they quote, such as a file's name).

    A reader's helpers name its ``path``; a caller passing ``name`` (a command line: the
    option or positional the user typed) gets its own name in their messages. Nothing changes
    when ``name`` is ``parameter`` (library callers).
    """
    try:
        yield
    except (TypeError, ValueError, OSError, RuntimeError) as exc:
        text = str(exc)
        # Outside the quoted values only: a file the user named 'lm`path`.fcsv' keeps its name.
        parts = _QUOTED.split(text)
        new = "".join(
            part if k % 2 else part.replace(f"`{parameter}`", f"`{name}`")
            for k, part in enumerate(parts)
        )
        # Only the built-in types are remade: a subclass may carry fields its message omits.
        if name == parameter or new == text or type(exc).__module__ != "builtins":
            raise
        renamed = type(exc)(new)
        raise renamed.with_traceback(exc.__traceback__) from exc.__cause__


def to_open3d(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Build an Open3D mesh from ``(n, 3)`` vertices and ``(m, 3)`` faces (copied)."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(faces, dtype=np.int32)),
    )
    return mesh


def moved_name(old_module: str, name: str, new_module: str) -> Any:
    """``new_module.name`` looked up through ``old_module``, which no longer holds it, with a
    ``DeprecationWarning``; ``AttributeError`` for a name ``new_module`` does not export.

    A package's ``__getattr__`` calls it for the public names that moved to another room, so
    user code keeps working while it learns the new path.
    """
    module = importlib.import_module(new_module)
    if name not in getattr(module, "__all__", ()):
        raise AttributeError(f"module {old_module!r} has no attribute {name!r}")
    warnings.warn(
        f"{old_module}.{name} is deprecated: import it from {new_module}",
        DeprecationWarning,
        stacklevel=3,
    )
    return getattr(module, name)
