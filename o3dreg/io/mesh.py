"""Reading and writing triangle meshes with Open3D, with clear errors and atomic writes."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np
import open3d as o3d

from .._validation import as_mesh_arrays, check_output_path
from . import formats

__all__ = [
    "MESH_SUFFIXES",
    "atomic_write",
    "check_mesh_suffix",
    "read_triangle_mesh",
    "to_open3d",
    "write_triangle_mesh",
]

#: File suffixes read and written as triangle meshes (Open3D's, plus VTK polydata: see
#: :mod:`o3dreg.io.formats`).
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb", ".vtk", ".vtp")


def check_mesh_suffix(path: str, name: str) -> str:
    """The lower-case suffix of ``path``; ``ValueError`` naming ``name`` unless a mesh format."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"`{name}` must end with one of {', '.join(MESH_SUFFIXES)}, got {path!r}")
    return suffix


def atomic_write_text(
    path: str | os.PathLike[str], text: str, *, overwrite: bool = False, name: str = "path"
) -> str:
    """Write ``text`` (UTF-8) to ``path`` atomically; see :func:`atomic_write`."""

    def writer(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    return atomic_write(path, writer, overwrite=overwrite, name=name)


def read_triangle_mesh(
    path: str | os.PathLike[str], *, name: str = "path"
) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh and check that it has vertices and triangles.

    Parameters
    ----------
    path : str or path-like
        A ``.ply``, ``.obj``, ``.stl``, ``.off``, ``.gltf``, ``.glb``, ``.vtk`` (legacy VTK
        polydata) or ``.vtp`` (VTK XML polydata) file. STL corners with identical coordinates
        are merged (STL stores each triangle's corners separately).
    name : str, optional
        The parameter name used in error messages.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh

    Raises
    ------
    OSError
        If the file is missing, unreadable or holds no triangles.
    ValueError
        If the suffix is not a mesh format.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_mesh_suffix(path, name)
    if not os.path.isfile(path):
        raise OSError(f"`{name}`: no such file {path!r}")
    if not os.access(path, os.R_OK):
        raise OSError(f"`{name}`: file {path!r} is not readable")
    mesh = formats.read_mesh(path, suffix)
    if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
        raise OSError(
            f"`{name}`: {path!r} could not be read as a triangle mesh "
            f"(got {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles)"
        )
    return mesh


def to_open3d(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Build an Open3D mesh from ``(n, 3)`` vertices and ``(m, 3)`` faces (copied)."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(faces, dtype=np.int32)),
    )
    return mesh


def atomic_write(
    path: str | os.PathLike[str],
    writer: Callable[[str], Any],
    *,
    overwrite: bool = False,
    name: str = "path",
) -> str:
    """Call ``writer(tmp)`` on a temporary file beside ``path``, then move it into place.

    Nothing is left at ``path`` when ``writer`` fails or returns ``False``.
    """
    path = check_output_path(path, name, overwrite=overwrite)
    folder = os.path.dirname(os.path.abspath(path))
    base, suffix = os.path.splitext(os.path.basename(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=f".part{suffix}", dir=folder)
    os.close(fd)
    try:
        ok = writer(tmp)
        if ok is False or not os.path.exists(tmp) or os.path.getsize(tmp) == 0:
            raise OSError(f"`{name}`: writing {path!r} failed")
        # mkstemp creates the file 0600; give the result the permissions of a normal file.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def write_triangle_mesh(
    path: str | os.PathLike[str],
    mesh: Any,
    *,
    overwrite: bool = False,
    write_ascii: bool = False,
    name: str = "path",
) -> str:
    """Write a triangle mesh atomically (a crash never leaves a half-written file).

    Parameters
    ----------
    path : str or path-like
        Output file; its suffix selects the format (see ``MESH_SUFFIXES``).
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
        The mesh to write. It is not modified.
    overwrite : bool, optional
        Replace an existing file. Default ``False``: an existing file raises ``OSError``.
    write_ascii : bool, optional
        Write a text file where the format allows it.

    Returns
    -------
    path : str
        The path written.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a path, got {type(path).__name__}")
    suffix = check_mesh_suffix(os.fspath(path), name)
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        out = o3d.geometry.TriangleMesh(mesh)
    else:
        out = to_open3d(*as_mesh_arrays(mesh, "mesh"))
    if not out.has_vertex_normals():
        out.compute_vertex_normals()
    return atomic_write(
        path,
        lambda tmp: formats.write_mesh(tmp, out, suffix, write_ascii=write_ascii),
        overwrite=overwrite,
        name=name,
    )
