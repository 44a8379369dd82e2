"""Reading and writing triangle meshes with Open3D, with clear errors and atomic writes."""

from __future__ import annotations

import logging
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np
import open3d as o3d

from .._validation import as_mesh_arrays, check_bool, check_output_path, to_open3d
from . import formats
from .integrity import check_ply_complete

__all__ = [
    "MESH_SUFFIXES",
    "atomic_write",
    "check_mesh_suffix",
    "read_triangle_mesh",
    "to_open3d",
    "write_triangle_mesh",
]

logger = logging.getLogger("o3dreg")

#: File suffixes read and written as triangle meshes (see :mod:`o3dreg.io.formats`).
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb", ".vtk", ".vtp", ".vtu")

#: Formats that keep a mesh's vertices, in order, through a write and a read by o3dreg: the
#: vertex index is a semilandmark mesh's correspondence. STL stores each triangle's corners
#: separately (no shared vertices, no order): it cannot hold a semilandmark mesh.
SEMILANDMARK_SUFFIXES = tuple(s for s in MESH_SUFFIXES if s != ".stl")


def check_semilandmark_suffix(path: str, name: str) -> str:
    """:func:`check_mesh_suffix`, and ``ValueError`` for a format that loses the vertex order."""
    suffix = check_mesh_suffix(path, name)
    if suffix not in SEMILANDMARK_SUFFIXES:
        raise ValueError(
            f"`{name}` must be a format that keeps the template's vertex order (the "
            f"correspondence of a semilandmark mesh): one of {', '.join(SEMILANDMARK_SUFFIXES)}; "
            f"got {path!r} (STL stores each triangle's corners separately: it has no shared "
            "vertices and no vertex order)"
        )
    return suffix


def check_mesh_suffix(path: str, name: str) -> str:
    """The lower-case suffix of ``path``; ``ValueError`` naming ``name`` unless a mesh format."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"`{name}` must end with one of {', '.join(MESH_SUFFIXES)}, got {path!r}")
    return suffix


def make_folder(path: str | os.PathLike[str], name: str) -> None:
    """``os.makedirs(path, exist_ok=True)``; its error names the argument ``name`` that gave
    ``path`` (the system's names only the path)."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise OSError(f"`{name}`: cannot create folder {path!r}: {exc.strerror or exc}") from exc


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
        polydata or unstructured grid), ``.vtp`` (VTK XML polydata) or ``.vtu`` (VTK XML
        unstructured grid) file. Vertices keep the file's order; polygons (quads) are split
        into triangles, with a warning; volume cells are refused. STL corners with identical
        coordinates are merged (STL stores each triangle's corners separately). A model 3D
        Slicer saved in RAS and marked ``SPACE=RAS`` is converted to LPS (x and y negated),
        as Slicer reads it.
    name : str, optional
        The parameter name used in error messages.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh

    Raises
    ------
    OSError
        If the file is missing, unreadable, holds no triangles or NaN / infinite coordinates.
    ValueError
        If the suffix is not a mesh format.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_mesh_suffix(path, name)
    if os.path.isdir(path):
        raise OSError(f"`{name}`: {path!r} is a folder, not a mesh file")
    if not os.path.isfile(path):
        raise OSError(f"`{name}`: no such file {path!r}")
    if not os.access(path, os.R_OK):
        raise OSError(f"`{name}`: file {path!r} is not readable")
    declared: dict[str, int] = {}
    if suffix == ".ply":
        declared = check_ply_complete(path, name)
    mesh = formats.read_mesh(path, suffix, name)  # OBJ: checked whole as it is read
    if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
        raise OSError(
            f"`{name}`: {path!r} could not be read as a triangle mesh "
            f"(got {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles)"
        )
    # Open3D stops at a malformed line or record of a PLY body, logs it, and returns what it
    # read so far: fewer faces (or vertices) than the header declares is a broken file, not a
    # smaller mesh. (Polygons split into triangles give more triangles than faces.)
    vertices, faces = declared.get("vertex"), declared.get("face")
    if (vertices is not None and len(mesh.vertices) != vertices) or (
        faces is not None and len(mesh.triangles) < faces
    ):
        raise OSError(
            f"`{name}`: {path!r} is malformed: its header declares {vertices} vertices and "
            f"{faces} faces, {len(mesh.vertices)} vertices and {len(mesh.triangles)} triangles "
            "could be read"
        )
    # Open3D reads "nan" and "inf" as coordinates: a mesh read must be one every step can use.
    bad = ~np.isfinite(np.asarray(mesh.vertices)).all(axis=1)
    if bad.any():
        raise OSError(
            f"`{name}`: {path!r} holds {int(bad.sum())} vertices with NaN or infinite "
            f"coordinates (the first: vertex {int(np.flatnonzero(bad)[0])})"
        )
    # Open3D keeps a face that names a vertex the file does not hold; using it reads memory
    # outside the vertex array (normals, writing: a crash).
    outside = _faces_outside(mesh)
    if outside is not None:
        face, corner = outside
        raise OSError(
            f"`{name}`: {path!r} is malformed: face {face} refers to vertex {corner}, the file "
            f"holds {len(mesh.vertices)} vertices"
        )
    return mesh


def _faces_outside(mesh: o3d.geometry.TriangleMesh) -> tuple[int, int] | None:
    """The first face of ``mesh`` with a corner outside its vertices, and that corner."""
    faces = np.asarray(mesh.triangles)
    bad = ((faces < 0) | (faces >= len(mesh.vertices))).any(axis=1)
    if not bad.any():
        return None
    face = int(np.flatnonzero(bad)[0])
    row = faces[face]
    return face, int(row[(row < 0) | (row >= len(mesh.vertices))][0])


def atomic_write(
    path: str | os.PathLike[str],
    writer: Callable[[str], Any],
    *,
    overwrite: bool = False,
    name: str = "path",
    verify: Callable[[str], None] | None = None,
) -> str:
    """Call ``writer(tmp)`` on a temporary file beside ``path``, then move it into place.

    The temporary file is flushed to disk and, when given, ``verify(tmp)`` checks it (raising
    ``OSError`` for an incomplete file) before it is renamed to ``path``. Nothing is left at
    ``path`` when ``writer`` fails or returns ``False``, when the disk fills up or when
    ``verify`` rejects the file; the temporary file is removed on every exit that runs Python
    code (exceptions, SIGINT, and SIGTERM in the command line). Temporary files left by a killed
    process (SIGKILL, power loss) are hidden (``.NAME.HOST-PID.XXXX.partSUFFIX``) and removed by
    the next write to the same ``path`` once their process is gone.
    """
    path = check_output_path(path, name, overwrite=overwrite)
    folder = os.path.dirname(os.path.abspath(path))
    base, suffix = os.path.splitext(os.path.basename(path))
    _remove_stale_parts(folder, base, suffix)
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{base}.{HOST}-{os.getpid()}.", suffix=f".part{suffix}", dir=folder
        )
    except OSError as exc:
        raise OSError(
            f"`{name}`: cannot write {path!r}: {exc.strerror or exc} (folder {folder!r})"
        ) from None
    os.close(fd)
    try:
        try:
            ok = writer(tmp)
        except OSError as exc:  # the message would name the hidden temporary file
            raise OSError(f"`{name}`: writing {path!r} failed: {exc.strerror or exc}") from exc
        if ok is False or not os.path.exists(tmp) or os.path.getsize(tmp) == 0:
            # Open3D's writers say only False: name the likely cause when it is the disk.
            free = shutil.disk_usage(folder).free
            reason = f": no space left on the device ({free} bytes free)" if free < 1 << 20 else ""
            raise OSError(f"`{name}`: writing {path!r} failed{reason}")
        _flush_to_disk(tmp, path, name)
        if verify is not None:
            verify(tmp)
        # mkstemp creates the file 0600; give the result the permissions of a normal file.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        if overwrite:
            os.replace(tmp, path)
        else:
            _place_new(tmp, path, name)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _place_new(tmp: str, path: str, name: str) -> None:
    """Move ``tmp`` to ``path`` unless ``path`` exists, atomically (another writer may have
    finished first since the check): a hard link fails where ``os.replace`` would overwrite."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise OSError(
            f"`{name}`: {path!r} was created by another writer meanwhile; pass overwrite=True (--overwrite) "
            "to replace it"
        ) from None
    except OSError:  # a file system without hard links: check, then rename
        if os.path.exists(path):
            raise OSError(
                f"`{name}`: {path!r} exists; pass overwrite=True (--overwrite) to replace it"
            ) from None
        os.replace(tmp, path)


# Host name as it appears in temporary names (no dots: they separate the name's fields).
HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())[:32] or "host"


def _flush_to_disk(tmp: str, path: str, name: str) -> None:
    """fsync ``tmp``: a full disk or a failing device shows here, not after the rename."""
    try:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise OSError(f"`{name}`: writing {path!r} failed: {exc.strerror or exc}") from exc


def _remove_stale_parts(folder: str, base: str, suffix: str) -> None:
    """Remove temporary files of ``base + suffix`` whose writer on this host has died."""
    pattern = re.compile(
        rf"^\.{re.escape(base)}\.{re.escape(HOST)}-(\d+)\.[^.]+\.part{re.escape(suffix)}$"
    )
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for entry in names:
        match = pattern.match(entry)
        if match is None or process_alive(int(match.group(1))):
            continue
        try:
            os.unlink(os.path.join(folder, entry))
            logger.info("removed %s, left by an interrupted write", entry)
        except OSError:
            pass  # another writer removed it, or the folder is read-only: harmless either way


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # alive, owned by another user
    return True


def _check_mesh_file(
    tmp: str, path: str, name: str, vertices: int, triangles: int, exact_vertices: bool
) -> None:
    """Read a written mesh back: a writer that stopped early (full disk) is found here.

    Open3D's PLY writer reports success after "RPly: Error closing up", leaving a truncated
    file; reading it back and comparing the counts is the only check that works for every format.
    """
    # Quiet: Open3D's warnings about a truncated file would name the hidden temporary file.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        back = o3d.io.read_triangle_mesh(tmp)  # type: ignore[arg-type]  # stubs: PathLike
    got_v, got_t = len(back.vertices), len(back.triangles)
    if got_t != triangles or (exact_vertices and got_v != vertices):
        raise OSError(
            f"`{name}`: writing {path!r} failed: the file reads back as {got_v} vertices and "
            f"{got_t} triangles, {vertices} and {triangles} were written (disk full?)"
        )


def write_triangle_mesh(
    path: str | os.PathLike[str],
    mesh: Any,
    *,
    overwrite: bool = False,
    write_ascii: bool = False,
    semilandmarks: bool = False,
    name: str = "path",
) -> str:
    """Write a triangle mesh atomically (a crash never leaves a half-written file).

    Every format is read back by :func:`read_triangle_mesh` with the vertices in the order
    written (STL excepted: it has no shared vertices); coordinates are written at full float64
    precision, except where the format stores float32 (STL, glTF).

    Parameters
    ----------
    path : str or path-like
        Output file; its suffix selects the format (see ``MESH_SUFFIXES``).
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
        The mesh to write. It is not modified. Its vertices must be finite.
    overwrite : bool, optional
        Replace an existing file. Default ``False``: an existing file raises ``OSError``.
    write_ascii : bool, optional
        Write a text file where the format allows it.
    semilandmarks : bool, optional
        The vertex order is the mesh's meaning (a registered template: vertex ``i`` corresponds
        across patients): a format that cannot keep it (STL) raises ``ValueError``. Default
        ``False``.
    name : str, optional
        How messages name ``path`` (a command line passes its option). Default ``'path'``.

    Returns
    -------
    path : str
        The path written.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a path, got {type(path).__name__}")
    semilandmarks = check_bool(semilandmarks, "semilandmarks")
    write_ascii = check_bool(write_ascii, "write_ascii")
    check = check_semilandmark_suffix if semilandmarks else check_mesh_suffix
    suffix = check(os.fspath(path), name)
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        if len(mesh.triangles) == 0:
            raise ValueError(
                f"`mesh` must have triangles, got {len(mesh.vertices)} vertices and none; "
                "nothing written"
            )
        outside = _faces_outside(mesh)
        if outside is not None:
            raise ValueError(
                f"`mesh` faces must index its {len(mesh.vertices)} vertices, got face "
                f"{outside[0]} with vertex {outside[1]}; nothing written"
            )
        out = o3d.geometry.TriangleMesh(mesh)
    else:
        out = to_open3d(*as_mesh_arrays(mesh, "mesh"))
    bad = ~np.isfinite(np.asarray(out.vertices)).all(axis=1)
    if bad.any():
        first = np.flatnonzero(bad)[:5].tolist()
        raise ValueError(
            f"`mesh` must have finite vertices, got {int(bad.sum())} with NaN or infinite "
            f"coordinates (vertices {first}{' ...' if bad.sum() > 5 else ''}); nothing written"
        )
    if not out.has_vertex_normals():
        out.compute_vertex_normals()
    vertices, triangles = len(out.vertices), len(out.triangles)

    def verify(tmp: str) -> None:
        # Python's own writers (every format but binary PLY) raise on a full disk; Open3D's
        # do not.
        if suffix == ".ply" and not write_ascii:
            _check_mesh_file(tmp, os.fspath(path), name, vertices, triangles, True)

    return atomic_write(
        path,
        lambda tmp: formats.write_mesh(tmp, out, suffix, write_ascii=write_ascii),
        overwrite=overwrite,
        name=name,
        verify=verify,
    )
