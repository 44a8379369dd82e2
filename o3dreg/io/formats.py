"""Mesh formats o3dreg reads and writes itself: VTK polydata (legacy ``.vtk`` and XML ``.vtp``),
binary glTF (``.glb``) and STL.

Open3D reads and writes PLY, OBJ, OFF, glTF and STL. What it lacks, this module supplies, with
numpy only:

* **VTK polydata**, the format statismo, scalismo, ShapeWorks and 3D Slicer exchange. The
  triangle subset is read: ``POLYGONS`` (triangles; larger polygons are split into fans, with a
  warning) and ``TRIANGLE_STRIPS``; vertices and lines are skipped; point and cell data are
  ignored. Legacy files: versions up to 5.1 (the ``OFFSETS`` / ``CONNECTIVITY`` layout of
  VTK 9), ASCII and BINARY (big-endian). XML files: ``ascii``, inline ``binary`` (base64) and
  ``appended`` (raw or base64) data, uncompressed or zlib-compressed, 32- or 64-bit headers,
  either byte order. Legacy files are written in version 4.2 (read by every VTK and ITK since
  2005, statismo and scalismo included), XML files as version 1.0 with inline base64 data.
* **OBJ** (reading): Open3D renumbers the vertices in the order the faces use them and drops
  faces that are not triangles; here the vertices keep the file's order (a semilandmark mesh
  keeps its correspondence) and polygons are split into triangle fans.
* **GLB**: Open3D 0.18-0.19 writes ``.glb`` files whose buffer view lies outside the buffer, so
  neither Open3D nor other readers can open them; o3dreg writes GLB 2.0 itself (positions are
  float32, as glTF requires) and Open3D reads it.
* **STL** stores each triangle's three corners separately; Open3D returns three vertices per
  triangle. Corners with identical coordinates are merged on reading, so a mesh comes back with
  its connectivity (STL writes float32, so shared corners are bit-identical). STL is written
  here, binary or ASCII, with facet normals computed from the triangles (Open3D writes no ASCII
  STL and refuses a mesh without triangle normals).
"""

from __future__ import annotations

import base64
import json
import logging
import re
import struct
import warnings
import zlib
from typing import Any
from xml.etree import ElementTree

import numpy as np
import open3d as o3d

from .._validation import to_open3d

__all__ = [
    "merge_identical_vertices",
    "read_obj",
    "read_vtk",
    "read_vtp",
    "write_glb",
    "write_stl",
    "write_vtk",
    "write_vtp",
]

_log = logging.getLogger("o3dreg")

# ---------------------------------------------------------------------------------------------
# Shared helpers
# ---------------------------------------------------------------------------------------------


def merge_identical_vertices(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical coordinates; keep first-seen order.

    Returns new ``(vertices, faces)``; the inputs are not modified.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # Number the unique points in order of first appearance (stable, as the file lists them).
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return vertices[first[order]].copy(), rank[inverse][np.asarray(faces)].astype(np.int64)


def _cells_to_triangles(
    offsets: np.ndarray, connectivity: np.ndarray, *, strips: bool, path: str
) -> np.ndarray:
    """Triangles of polygons (fans) or triangle strips given CSR ``offsets`` (with a leading 0)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    connectivity = np.asarray(connectivity, dtype=np.int64)
    sizes = np.diff(offsets)
    if sizes.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if np.any(sizes < 0) or offsets[-1] > connectivity.size:
        raise OSError(f"{path!r}: cell offsets are inconsistent with the connectivity")
    if not strips and np.all(sizes == 3):
        return connectivity[offsets[0] : offsets[-1]].reshape(-1, 3).copy()
    triangles: list[np.ndarray] = []
    if not strips and np.any(sizes > 3):
        _log.warning(
            "%s: %d polygon(s) with more than 3 vertices split into triangle fans",
            path,
            int(np.count_nonzero(sizes > 3)),
        )
    for start, size in zip(offsets[:-1], sizes):
        cell = connectivity[start : start + size]
        if size < 3:
            continue
        k = np.arange(size - 2)
        if strips:
            tri = np.stack([cell[k], cell[k + 1], cell[k + 2]], axis=1)
            # Every second triangle of a strip is listed clockwise: swap two corners.
            tri[1::2, [0, 1]] = tri[1::2, [1, 0]]
        else:
            tri = np.stack([np.full(size - 2, cell[0]), cell[k + 1], cell[k + 2]], axis=1)
        triangles.append(tri)
    if not triangles:
        return np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(triangles).astype(np.int64)


def _check_mesh(
    vertices: np.ndarray, faces: np.ndarray, path: str
) -> tuple[np.ndarray, np.ndarray]:
    if vertices.size == 0 or faces.size == 0:
        raise OSError(
            f"{path!r} holds no triangle mesh (got {len(vertices)} points, {len(faces)} triangles)"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise OSError(f"{path!r}: triangles index points outside [0, {len(vertices) - 1}]")
    if not np.all(np.isfinite(vertices)):
        raise OSError(f"{path!r}: points hold NaN or inf")
    return vertices, faces


# ---------------------------------------------------------------------------------------------
# Legacy VTK (.vtk)
# ---------------------------------------------------------------------------------------------

_LEGACY_TYPES = {
    "bit": None,
    "unsigned_char": ">u1",
    "char": ">i1",
    "unsigned_short": ">u2",
    "short": ">i2",
    "unsigned_int": ">u4",
    "int": ">i4",
    "unsigned_long": ">u8",
    "long": ">i8",
    "float": ">f4",
    "double": ">f8",
    "vtktypeint64": ">i8",
    "vtktypeint32": ">i4",
    "vtkidtype": ">i8",
}


class _LegacyReader:
    """A cursor over a legacy VTK file: keyword lines, then ASCII numbers or big-endian bytes."""

    def __init__(self, data: bytes, path: str) -> None:
        self.data, self.path, self.pos = data, path, 0

    def line(self) -> str | None:
        """The next non-empty line, or ``None`` at the end."""
        while self.pos < len(self.data):
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            text = self.data[self.pos : end].decode("ascii", errors="replace").strip()
            self.pos = end + 1
            if text:
                return text
        return None

    def numbers(self, count: int, dtype: str, binary: bool) -> np.ndarray:
        if binary:
            size = np.dtype(dtype).itemsize * count
            if self.pos + size > len(self.data):
                raise OSError(f"{self.path!r}: binary data ends early")
            out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
            self.pos += size
            return out.astype(np.dtype(dtype).newbyteorder("="))
        values: list[str] = []
        while len(values) < count:
            text = self.line()
            if text is None:
                raise OSError(f"{self.path!r}: expected {count} numbers, the file ends")
            values.extend(text.split())
        if len(values) != count:
            raise OSError(f"{self.path!r}: expected {count} numbers, got {len(values)}")
        kind = np.float64 if np.dtype(dtype).kind == "f" else np.int64
        try:
            return np.array(values, dtype=kind)
        except ValueError as exc:
            raise OSError(f"{self.path!r}: not a number in a data block ({exc})") from exc


def _legacy_dtype(name: str, path: str) -> str:
    dtype = _LEGACY_TYPES.get(name.lower())
    if dtype is None:
        raise OSError(f"{path!r}: data type {name!r} is not supported")
    return dtype


def read_vtk(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Read the triangles of a legacy VTK ``POLYDATA`` file (ASCII or BINARY, versions <= 5.1).

    Returns ``(vertices (n, 3) float64, faces (m, 3) int64)``.
    """
    with open(path, "rb") as fh:
        reader = _LegacyReader(fh.read(), path)
    header = reader.line()
    if header is None or not header.lower().startswith("# vtk datafile version"):
        raise OSError(f"{path!r} is not a legacy VTK file (no '# vtk DataFile Version' line)")
    version = float(re.findall(r"[\d.]+", header)[0]) if re.findall(r"[\d.]+", header) else 0.0
    reader.line()  # title
    mode = (reader.line() or "").upper()
    if mode not in ("ASCII", "BINARY"):
        raise OSError(f"{path!r}: third line must be ASCII or BINARY, got {mode!r}")
    binary = mode == "BINARY"
    dataset = (reader.line() or "").split()
    if len(dataset) < 2 or dataset[0].upper() != "DATASET" or dataset[1].upper() != "POLYDATA":
        kind = dataset[1] if len(dataset) > 1 else "nothing"
        raise OSError(f"{path!r}: only DATASET POLYDATA is read, got {kind}")
    vertices: np.ndarray | None = None
    triangles: list[np.ndarray] = []
    while (text := reader.line()) is not None:
        words = text.split()
        key = words[0].upper()
        if key == "POINTS":
            n = int(words[1])
            vertices = reader.numbers(3 * n, _legacy_dtype(words[2], path), binary).reshape(n, 3)
            vertices = vertices.astype(np.float64)
        elif key in ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"):
            count, size = int(words[1]), int(words[2])
            if version >= 5.0:
                # VTK 9: "KEY offsets connectivity", then OFFSETS and CONNECTIVITY arrays.
                off_words = (reader.line() or "").split()
                offsets = reader.numbers(count, _legacy_dtype(off_words[1], path), binary)
                con_words = (reader.line() or "").split()
                connectivity = reader.numbers(size, _legacy_dtype(con_words[1], path), binary)
            else:
                # Before VTK 9: one row per cell, "npts i0 i1 ...", int32 in binary files.
                flat = reader.numbers(size, ">i4", binary).astype(np.int64)
                offsets_list, connectivity_parts, at = [0], [], 0
                for _ in range(count):
                    npts = int(flat[at])
                    connectivity_parts.append(flat[at + 1 : at + 1 + npts])
                    offsets_list.append(offsets_list[-1] + npts)
                    at += npts + 1
                offsets = np.array(offsets_list)
                connectivity = (
                    np.concatenate(connectivity_parts) if connectivity_parts else np.zeros(0)
                )
            if key in ("POLYGONS", "TRIANGLE_STRIPS"):
                triangles.append(
                    _cells_to_triangles(
                        offsets, connectivity, strips=key == "TRIANGLE_STRIPS", path=path
                    )
                )
        elif key == "METADATA":
            # Information keys (VTK >= 8), ended by an empty line.
            while reader.pos < len(reader.data):
                end = reader.data.find(b"\n", reader.pos)
                end = len(reader.data) if end < 0 else end
                blank = not reader.data[reader.pos : end].strip()
                reader.pos = end + 1
                if blank:
                    break
        elif key in ("POINT_DATA", "CELL_DATA", "FIELD"):
            break  # attributes follow the geometry: nothing more to read
        else:
            raise OSError(f"{path!r}: unexpected keyword {words[0]!r} in POLYDATA")
    if vertices is None:
        raise OSError(f"{path!r}: no POINTS section")
    faces = np.concatenate(triangles) if triangles else np.zeros((0, 3), dtype=np.int64)
    return _check_mesh(vertices, faces.astype(np.int64), path)


def write_vtk(path: str, vertices: np.ndarray, faces: np.ndarray, *, ascii: bool = False) -> None:
    """Write a legacy VTK 4.2 ``POLYDATA`` file (points as double, triangles as ``POLYGONS``)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    cells = np.column_stack([np.full(m, 3, dtype=np.int64), faces])
    with open(path, "wb") as fh:
        fh.write(b"# vtk DataFile Version 4.2\nwritten by o3dreg\n")
        fh.write(b"ASCII\n" if ascii else b"BINARY\n")
        fh.write(b"DATASET POLYDATA\n")
        fh.write(f"POINTS {len(vertices)} double\n".encode())
        if ascii:
            np.savetxt(fh, vertices, fmt="%.17g")
        else:
            fh.write(vertices.astype(">f8").tobytes())
            fh.write(b"\n")
        fh.write(f"POLYGONS {m} {4 * m}\n".encode())
        if ascii:
            np.savetxt(fh, cells, fmt="%d")
        else:
            if faces.size and faces.max() > np.iinfo(np.int32).max:
                raise ValueError("legacy VTK 4.2 indexes points with int32: too many points")
            fh.write(cells.astype(">i4").tobytes())
            fh.write(b"\n")


# ---------------------------------------------------------------------------------------------
# XML VTK polydata (.vtp)
# ---------------------------------------------------------------------------------------------

_XML_TYPES = {
    "Int8": "i1",
    "UInt8": "u1",
    "Int16": "i2",
    "UInt16": "u2",
    "Int32": "i4",
    "UInt32": "u4",
    "Int64": "i8",
    "UInt64": "u8",
    "Float32": "f4",
    "Float64": "f8",
}


def _b64decode_pieces(text: bytes) -> bytes:
    """Decode base64 that may be several padded streams written one after another."""
    text = re.sub(rb"\s+", b"", text)
    out, start = [], 0
    for match in re.finditer(rb"=+", text):
        out.append(base64.b64decode(text[start : match.end()]))
        start = match.end()
    if start < len(text):
        out.append(base64.b64decode(text[start:]))
    return b"".join(out)


class _XmlArrays:
    """Decodes the ``DataArray`` elements of one VTK XML file."""

    def __init__(self, root: ElementTree.Element, appended: bytes | None, path: str) -> None:
        self.path = path
        self.order = "<" if root.get("byte_order", "LittleEndian") == "LittleEndian" else ">"
        self.header = self.order + ("u8" if root.get("header_type") == "UInt64" else "u4")
        self.compressed = root.get("compressor") is not None
        if self.compressed and "ZLib" not in (root.get("compressor") or ""):
            raise OSError(f"{path!r}: compressor {root.get('compressor')!r} is not supported")
        self.appended = appended
        self.appended_base64 = False
        self.offsets: list[int] = []
        app = root.find("AppendedData")
        if app is not None:
            self.appended_base64 = app.get("encoding", "raw") == "base64"
            self.offsets = sorted(
                int(a.get("offset", "0")) for a in root.iter("DataArray") if a.get("offset")
            )

    def _unpack(self, raw: bytes, dtype: str) -> tuple[np.ndarray, int]:
        """Values from ``header + data`` bytes; also the number of bytes used."""
        hsize = np.dtype(self.header).itemsize
        if not self.compressed:
            nbytes = int(np.frombuffer(raw, self.header, 1)[0])
            body = raw[hsize : hsize + nbytes]
            return np.frombuffer(body, dtype), hsize + nbytes
        nblocks = int(np.frombuffer(raw, self.header, 1)[0])
        head = np.frombuffer(raw, self.header, 3 + nblocks).astype(np.int64)
        sizes = head[3:]
        at = hsize * (3 + nblocks)
        parts = []
        for size in sizes:
            parts.append(zlib.decompress(raw[at : at + size]))
            at += int(size)
        return np.frombuffer(b"".join(parts), dtype), at

    def read(self, element: ElementTree.Element) -> np.ndarray:
        type_name = element.get("type", "")
        if type_name not in _XML_TYPES:
            raise OSError(f"{self.path!r}: DataArray type {type_name!r} is not supported")
        dtype = self.order + _XML_TYPES[type_name]
        fmt = element.get("format", "ascii")
        if fmt == "ascii":
            kind = np.float64 if _XML_TYPES[type_name][0] == "f" else np.int64
            return np.array((element.text or "").split(), dtype=kind)
        if fmt == "binary":
            values, _ = self._unpack(_b64decode_pieces((element.text or "").encode()), dtype)
        elif fmt == "appended":
            if self.appended is None:
                raise OSError(f"{self.path!r}: appended DataArray without AppendedData")
            offset = int(element.get("offset", "0"))
            if self.appended_base64:
                later = [o for o in self.offsets if o > offset]
                end = later[0] if later else len(self.appended)
                raw = _b64decode_pieces(self.appended[offset:end])
            else:
                raw = self.appended[offset:]
            values, _ = self._unpack(raw, dtype)
        else:
            raise OSError(f"{self.path!r}: DataArray format {fmt!r} is not supported")
        return values.astype(np.dtype(dtype).newbyteorder("="))


def read_vtp(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Read the triangles of a VTK XML ``PolyData`` file (``.vtp``).

    Returns ``(vertices (n, 3) float64, faces (m, 3) int64)``.
    """
    with open(path, "rb") as fh:
        data = fh.read()
    appended = None
    start = data.find(b"<AppendedData")
    if start >= 0:
        # Raw appended bytes are not XML: cut them off and parse the rest.
        underscore = data.index(b"_", data.index(b">", start)) + 1
        end = data.rfind(b"</AppendedData>")
        appended = data[underscore : end if end > underscore else len(data)]
        tag = data[start : data.index(b">", start) + 1]
        data = data[:start] + tag + b"</AppendedData></VTKFile>"
    try:
        root = ElementTree.fromstring(data)
    except ElementTree.ParseError as exc:
        raise OSError(f"{path!r} is not a VTK XML file ({exc})") from exc
    if root.tag != "VTKFile" or root.get("type") != "PolyData":
        raise OSError(f"{path!r}: only VTKFile type='PolyData' is read, got {root.get('type')!r}")
    if appended is not None:
        app = root.find("AppendedData")
        if app is not None and app.get("encoding", "raw") == "base64":
            appended = appended.strip()
    arrays = _XmlArrays(root, appended, path)
    vertices_parts, triangle_parts, base = [], [], 0
    for piece in root.iter("Piece"):
        n = int(piece.get("NumberOfPoints", "0"))
        points = piece.find("Points/DataArray")
        if n == 0:
            continue
        if points is None:
            raise OSError(f"{path!r}: a Piece without Points")
        vertices_parts.append(arrays.read(points).astype(np.float64).reshape(n, 3))
        for section, strips in (("Polys", False), ("Strips", True)):
            if int(piece.get(f"NumberOf{section}", "0")) == 0:
                continue
            found = {a.get("Name"): a for a in piece.findall(f"{section}/DataArray")}
            if "connectivity" not in found or "offsets" not in found:
                raise OSError(f"{path!r}: {section} without connectivity and offsets")
            connectivity = arrays.read(found["connectivity"]).astype(np.int64)
            offsets = np.concatenate([[0], arrays.read(found["offsets"]).astype(np.int64)])
            triangle_parts.append(
                _cells_to_triangles(offsets, connectivity, strips=strips, path=path) + base
            )
        base += n
    if not vertices_parts:
        raise OSError(f"{path!r}: no points")
    vertices = np.concatenate(vertices_parts)
    faces = np.concatenate(triangle_parts) if triangle_parts else np.zeros((0, 3), np.int64)
    return _check_mesh(vertices, faces.astype(np.int64), path)


def _xml_array(name: str, type_name: str, values: np.ndarray, ascii: bool, ncomp: int) -> str:
    comps = f' NumberOfComponents="{ncomp}"' if ncomp > 1 else ""
    head = f'<DataArray type="{type_name}" Name="{name}"{comps} format='
    if ascii:
        fmt = "%.17g" if values.dtype.kind == "f" else "%d"
        body = " ".join(fmt % v for v in values.reshape(-1))
        return f'{head}"ascii">{body}</DataArray>'
    raw = np.ascontiguousarray(values, dtype="<" + _XML_TYPES[type_name]).tobytes()
    # UInt64 header (byte count), then the data: one base64 stream, as VTK reads it.
    encoded = base64.b64encode(struct.pack("<Q", len(raw)) + raw).decode("ascii")
    return f'{head}"binary">{encoded}</DataArray>'


def write_vtp(path: str, vertices: np.ndarray, faces: np.ndarray, *, ascii: bool = False) -> None:
    """Write a VTK XML ``PolyData`` file (version 1.0, inline base64 or ascii data)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    parts = [
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        "<PolyData>",
        f'<Piece NumberOfPoints="{len(vertices)}" NumberOfVerts="0" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{m}">',
        "<Points>",
        _xml_array("Points", "Float64", vertices, ascii, 3),
        "</Points>",
        "<Polys>",
        _xml_array("connectivity", "Int64", faces.reshape(-1), ascii, 1),
        _xml_array("offsets", "Int64", 3 * np.arange(1, m + 1, dtype=np.int64), ascii, 1),
        "</Polys>",
        "</Piece>",
        "</PolyData>",
        "</VTKFile>",
        "",
    ]
    with open(path, "w", encoding="ascii") as fh:
        fh.write("\n".join(parts))


# ---------------------------------------------------------------------------------------------
# Wavefront OBJ (read)
# ---------------------------------------------------------------------------------------------


def _obj_numbers_per_corner(faces_text: bytes, faces: int) -> int:
    """How many numbers each face corner holds when all ``faces`` are triangles written alike:
    1 (``i``), 2 (``i//n``) or 3 (``i/t/n``); 0 when that cannot be told from the counts of
    ``/`` and ``//`` (then the faces are read line by line)."""
    slashes, doubled = faces_text.count(b"/"), faces_text.count(b"//")
    if slashes == 0:
        return 1
    if slashes == 6 * faces and doubled == 3 * faces:
        return 2  # two slashes per corner, one "//" per corner: every corner is i//n
    if slashes == 6 * faces and doubled == 0:
        return 3
    return 0


def _numbers(text: bytes, dtype: Any) -> np.ndarray | None:
    """The whitespace-separated numbers of ``text``, parsed in C; it stops at a token that is
    not a number (the caller compares the count with what it expects). None if it cannot."""
    with warnings.catch_warnings():
        # "could not be read to its end": the short count says it.
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            return np.fromstring(  # type: ignore[call-overload,no-any-return]
                text.decode("ascii", errors="replace"), dtype=dtype, sep=" "
            )
        except ValueError:
            return None


def read_obj(path: str, name: str = "path") -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an OBJ file, the vertices in the file's order.

    Open3D's OBJ reader numbers the vertices in the order the faces first use them (and splits
    a vertex per texture or normal index), so a semilandmark mesh read back lost its
    correspondence, and it drops every face that is not a triangle. Here the ``v`` lines are
    the vertices, in order (a ``w`` or colour after ``x y z`` is ignored); the ``f`` lines are
    the faces, ``i``, ``i/t``, ``i//n`` or ``i/t/n`` (negative ``i`` counting back from the
    last vertex read), polygons split into triangle fans with a warning. Other lines (texture
    coordinates, normals, groups, materials, lines, points) are ignored.

    ``OSError`` (``name`` the parameter the path came from) for a file shorter than it says:
    faces that refer to vertices the file does not hold, or fewer vertices or triangles than
    the counts Open3D writes in its comments (``# number of vertices: N``).
    """
    with open(path, "rb") as fh:
        lines = fh.read().splitlines()
    vertex_lines = [line[2:] for line in lines if line[:2] in (b"v ", b"v\t")]
    face_lines = [line[2:] for line in lines if line[:2] in (b"f ", b"f\t")]
    declared = {
        match.group(1).decode(): int(match.group(2))
        for match in (_OBJ_COUNT.match(line.strip()) for line in lines if line[:1] == b"#")
        if match
    }
    vertices, faces = _obj_arrays(lines, vertex_lines, face_lines, path, name)
    if faces.size and faces.max() >= vertices.shape[0]:
        raise OSError(
            f"`{name}`: {path!r} is truncated or damaged: a face refers to vertex "
            f"{int(faces.max()) + 1}, the file holds {vertices.shape[0]}"
        )
    for what, held in (("vertices", vertices.shape[0]), ("triangles", faces.shape[0])):
        if what in declared and held < declared[what]:
            raise OSError(
                f"`{name}`: {path!r} is truncated: it declares {declared[what]} {what} and "
                f"holds {held}"
            )
    return _check_mesh(vertices, faces, path)


#: The counts Open3D writes at the top of an OBJ file.
_OBJ_COUNT = re.compile(rb"^#\s*number of (vertices|triangles):\s*(\d+)\s*$")


def _obj_arrays(
    lines: list[bytes], vertex_lines: list[bytes], face_lines: list[bytes], path: str, name: str
) -> tuple[np.ndarray, np.ndarray]:
    # The common file (x y z vertices, triangles of positive indices, every corner written
    # alike: ``i``, ``i//n`` or ``i/t/n``) in a few NumPy calls; any other (colours, polygons,
    # negative indices, mixed corners, a malformed line) line by line.
    faces_text = b" ".join(face_lines)
    per_corner = _obj_numbers_per_corner(faces_text, len(face_lines))
    vertices = _numbers(b" ".join(vertex_lines), np.float64)
    corners = _numbers(faces_text.replace(b"/", b" "), np.int64) if per_corner else None
    if (
        per_corner
        and vertices is not None
        and corners is not None
        and vertices.size == 3 * len(vertex_lines)
        and corners.size == 3 * per_corner * len(face_lines)
    ):
        corners = corners[::per_corner]
        if corners.size == 0 or corners.min() > 0:
            return vertices.reshape(-1, 3), corners.reshape(-1, 3) - 1
    coordinates: list[bytes] = []
    offsets = [0]
    connectivity: list[int] = []
    for number, line in enumerate(lines, start=1):
        head = line[:2]
        if head in (b"v ", b"v\t"):
            xyz = line.split()[1:4]
            if len(xyz) < 3:
                raise OSError(
                    f"`{name}`: {path!r} line {number}: a vertex needs x, y, z, got {line!r}"
                )
            coordinates.extend(xyz)
        elif head in (b"f ", b"f\t"):
            seen = len(coordinates) // 3
            try:
                face = [int(token.split(b"/", 1)[0]) for token in line.split()[1:]]
            except ValueError:
                face = []
            if len(face) < 3 or 0 in face:
                raise OSError(
                    f"`{name}`: {path!r} has a malformed face line "
                    f"{line.decode(errors='replace').strip()!r} (line {number})"
                )
            connectivity.extend(c - 1 if c > 0 else seen + c for c in face)
            offsets.append(len(connectivity))
    try:
        vertex_array = np.array(coordinates, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise OSError(f"`{name}`: {path!r}: a vertex coordinate is not a number") from None
    faces = _cells_to_triangles(
        np.array(offsets), np.array(connectivity, dtype=np.int64), strips=False, path=path
    )
    return vertex_array, faces


# ---------------------------------------------------------------------------------------------
# STL
# ---------------------------------------------------------------------------------------------


def write_stl(path: str, vertices: np.ndarray, faces: np.ndarray, *, ascii: bool = False) -> None:
    """Write an STL file (binary, or ASCII) with unit facet normals (zero for degenerate ones)."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    if ascii:
        with open(path, "w", encoding="ascii") as fh:
            fh.write("solid o3dreg\n")
            for n, (a, b, c) in zip(normals, corners):
                fh.write(f"  facet normal {n[0]:.9g} {n[1]:.9g} {n[2]:.9g}\n    outer loop\n")
                for p in (a, b, c):
                    fh.write(f"      vertex {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}\n")
                fh.write("    endloop\n  endfacet\n")
            fh.write("endsolid o3dreg\n")
        return
    record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    table = np.zeros(len(corners), dtype=record)
    table["normal"], table["corners"] = normals, corners
    with open(path, "wb") as fh:
        fh.write(b"binary STL written by o3dreg".ljust(80, b" "))
        fh.write(struct.pack("<I", len(corners)))
        fh.write(table.tobytes())


# ---------------------------------------------------------------------------------------------
# Binary glTF (.glb)
# ---------------------------------------------------------------------------------------------


def write_glb(
    path: str, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Write a binary glTF 2.0 file: one mesh, one triangle primitive (float32 positions)."""
    positions = np.ascontiguousarray(vertices, dtype="<f4")
    indices = np.ascontiguousarray(faces, dtype="<u4").reshape(-1)
    blobs: list[bytes] = [positions.tobytes(), indices.tobytes()]
    attributes: dict[str, int] = {"POSITION": 0}
    accessors: list[dict[str, Any]] = [
        {
            "bufferView": 0,
            "componentType": 5126,  # FLOAT
            "count": len(positions),
            "type": "VEC3",
            "min": positions.min(axis=0).astype(float).tolist(),
            "max": positions.max(axis=0).astype(float).tolist(),
        },
        {"bufferView": 1, "componentType": 5125, "count": int(indices.size), "type": "SCALAR"},
    ]
    targets = [34962, 34963]  # ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER
    if normals is not None and len(normals) == len(positions):
        unit = np.asarray(normals, dtype=np.float64)
        length = np.linalg.norm(unit, axis=1, keepdims=True)
        unit = np.where(length > 0, unit / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
        blobs.append(np.ascontiguousarray(unit, dtype="<f4").tobytes())
        attributes["NORMAL"] = 2
        accessors.append(
            {"bufferView": 2, "componentType": 5126, "count": len(unit), "type": "VEC3"}
        )
        targets.append(34962)
    views, binary, offset = [], b"", 0
    for blob, target in zip(blobs, targets):
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob), "target": target})
        pad = (-len(blob)) % 4  # every view starts on a 4-byte boundary
        binary += blob + b"\0" * pad
        offset += len(blob) + pad
    gltf = {
        "asset": {"version": "2.0", "generator": "o3dreg"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": 1, "mode": 4}]}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)  # JSON chunk padded with spaces
    total = 12 + 8 + len(text) + 8 + len(binary)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<4sII", b"glTF", 2, total))
        fh.write(struct.pack("<I4s", len(text), b"JSON") + text)
        fh.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)


# ---------------------------------------------------------------------------------------------
# Dispatch by suffix (used by o3dreg.io.mesh)
# ---------------------------------------------------------------------------------------------

#: Suffixes read and written here rather than by Open3D alone.
OWN_SUFFIXES = (".vtk", ".vtp")


def read_mesh(path: str, suffix: str, name: str = "path") -> Any:
    """Read ``path`` as an ``open3d.geometry.TriangleMesh`` (empty when Open3D finds nothing;
    ``name``: the parameter the path came from, for the OBJ reader's messages)."""

    if suffix == ".vtk":
        return to_open3d(*read_vtk(path))
    if suffix == ".vtp":
        return to_open3d(*read_vtp(path))
    if suffix == ".obj":
        return to_open3d(*read_obj(path, name))
    mesh = o3d.io.read_triangle_mesh(path)  # type: ignore[arg-type]  # stubs say PathLike only
    if suffix == ".stl" and len(mesh.triangles):
        vertices, faces = merge_identical_vertices(
            np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        )
        mesh = to_open3d(vertices, faces)
    return mesh


def write_mesh(path: str, mesh: Any, suffix: str, *, write_ascii: bool = False) -> bool:
    """Write an ``open3d.geometry.TriangleMesh`` (a copy the caller owns) to ``path``."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if suffix == ".vtk":
        write_vtk(path, vertices, faces, ascii=write_ascii)
        return True
    if suffix == ".vtp":
        write_vtp(path, vertices, faces, ascii=write_ascii)
        return True
    if suffix == ".glb":
        normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
        write_glb(path, vertices, faces, normals)
        return True
    if suffix == ".stl":
        # Open3D needs triangle normals (a mesh read from PLY may have vertex normals only)
        # and writes no ASCII STL: both forms are written here.
        write_stl(path, vertices, faces, ascii=write_ascii)
        return True
    return bool(o3d.io.write_triangle_mesh(path, mesh, write_ascii=write_ascii))  # type: ignore[arg-type]
