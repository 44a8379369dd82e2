"""Mesh formats o3dreg reads and writes itself, with numpy and the standard library only:
VTK (legacy ``.vtk``, XML ``.vtp`` and ``.vtu``), OBJ, OFF, ASCII PLY, glTF (``.gltf``,
``.glb``) and STL. Open3D writes binary PLY and reads binary and ASCII PLY.

Every format keeps the vertices in the order written (a semilandmark mesh keeps its
correspondence), STL excepted, and text is written at full float64 precision. A model 3D
Slicer saved in RAS and marked so (``SPACE=RAS`` in the header of a ``.vtk``, ``.stl``,
``.ply`` or ``.obj``, a ``SPACE`` field in a ``.vtp`` / ``.vtu``; Slicer's default is
``SPACE=LPS``) is read in LPS, as Slicer reads it (see :func:`slicer_space`):

* **VTK**, the format statismo, scalismo, ShapeWorks and 3D Slicer exchange. The triangle subset
  is read: polygons, quads and pixels (split into triangle fans, with a warning), triangles and
  triangle strips; vertices and lines are skipped; volume cells are refused; point, cell and
  field data are ignored (a legacy file's dataset ``FIELD`` block before ``POINTS``, as VTK 9
  and PyVista write it, is passed over by its arrays' sizes). Legacy files: ``POLYDATA`` and
  ``UNSTRUCTURED_GRID`` (as meshio writes it), versions up to 5.1 (the ``OFFSETS`` /
  ``CONNECTIVITY`` layout of VTK 9), ASCII and BINARY (big-endian). XML files (``PolyData``, ``UnstructuredGrid``): ``ascii``, inline ``binary``
  (base64) and ``appended`` (raw or base64) data, uncompressed or zlib-compressed, 32- or 64-bit
  headers, either byte order. Legacy files are written in version 4.2 (read by every VTK and
  ITK since 2005, statismo and scalismo included), XML files as version 1.0 with inline base64
  data.
* **OBJ**: Open3D's reader renumbers the vertices in the order the faces use them and drops
  faces that are not triangles; here the vertices keep the file's order and polygons are split
  into triangle fans. Written with ``v`` and ``f`` lines only.
* **OFF**: any of Geomview's ``[ST][C][N]OFF`` keywords (MeshLab writes ``NSTOFF``), the counts
  on the keyword's line or the next; written as plain ``OFF`` (meshio and PyVista refuse
  ``NOFF``, which Open3D writes).
* **glTF**: read in the file's vertex order (Open3D's reader renumbers); written by o3dreg
  (positions float32, as glTF requires). Open3D 0.18-0.19 writes ``.glb`` files whose buffer
  view lies outside the buffer, so no reader opens them. Triangle lists, strips and fans,
  sparse accessors and normalized (quantized) positions are read; Draco and meshopt
  compression are refused (the vertices are not in the accessors).
* **STL** stores each triangle's three corners separately. Corners with identical coordinates
  are merged on reading (STL writes float32, so shared corners are bit-identical); the vertex
  order is lost, so a semilandmark mesh is never written as STL. Written here, binary or ASCII,
  with facet normals computed from the triangles.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import re
import struct
import urllib.parse
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
    # VTK's legacy writer stores a vtkIdType array as 32-bit ints whatever VTK's id size, and
    # its reader reads it so (vtkDataWriter / vtkDataReader: "currently writing vtkIdType as
    # int"): a 5.1 CONNECTIVITY of PyVista's ``PolyData.from_regular_faces`` is such an array.
    "vtkidtype": ">i4",
}

#: Data types of field data arrays as VTK's legacy writer stores them in binary: ``signed_char``
#: and ``vtktypeuint64`` besides the above.
_FIELD_TYPES = {
    **{name: dtype for name, dtype in _LEGACY_TYPES.items() if dtype is not None},
    "signed_char": ">i1",
    "vtktypeuint64": ">u8",
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

    def raw_line(self) -> str | None:
        """The next line as it is, empty or not (``None`` at the end)."""
        if self.pos >= len(self.data):
            return None
        end = self.data.find(b"\n", self.pos)
        end = len(self.data) if end < 0 else end
        text = self.data[self.pos : end].decode("ascii", errors="replace").rstrip("\r")
        self.pos = end + 1
        return text

    def skip_bytes(self, size: int, what: str) -> None:
        if self.pos + size > len(self.data):
            raise OSError(f"{self.path!r}: binary data ends early (in {what})")
        self.pos += size

    def skip_tokens(self, count: int, what: str) -> None:
        """Pass ``count`` whitespace-separated ASCII values, without reading them as numbers."""
        seen = 0
        while seen < count:
            text = self.line()
            if text is None:
                raise OSError(f"{self.path!r}: expected {count} values in {what}, the file ends")
            seen += len(text.split())
        if seen != count:
            raise OSError(f"{self.path!r}: expected {count} values in {what}, got {seen}")

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

    A dataset ``FIELD`` block before the geometry is passed over (strings, bits and numbers,
    with their ``METADATA``); point, cell and field data after it are not read.

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
    kind = dataset[1].upper() if len(dataset) > 1 and dataset[0].upper() == "DATASET" else ""
    if kind not in ("POLYDATA", "UNSTRUCTURED_GRID"):
        raise OSError(
            f"{path!r}: DATASET POLYDATA or UNSTRUCTURED_GRID is read, got "
            f"{dataset[1] if len(dataset) > 1 else 'nothing'}"
        )
    vertices: np.ndarray | None = None
    triangles: list[np.ndarray] = []
    cells: tuple[np.ndarray, np.ndarray] | None = None
    components = 1  # of the last array read, which a METADATA block may name
    while (text := reader.line()) is not None:
        words = text.split()
        key = words[0].upper()
        if kind == "UNSTRUCTURED_GRID" and key in ("CELLS", "CELL_TYPES"):
            components = 1
            if key == "CELLS":
                cells = _legacy_cells(reader, words, version, binary, path)
                continue
            if cells is None:
                raise OSError(f"{path!r}: CELL_TYPES before CELLS")
            types = reader.numbers(int(words[1]), ">i4", binary).astype(np.int64)
            triangles.append(_typed_cells_to_triangles(*cells, types, path))
            continue
        if key == "POINTS":
            n = int(words[1])
            vertices = reader.numbers(3 * n, _legacy_dtype(words[2], path), binary).reshape(n, 3)
            vertices, components = vertices.astype(np.float64), 3
        elif key in ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"):
            components = 1
            offsets, connectivity = _legacy_cells(reader, words, version, binary, path)
            if key in ("POLYGONS", "TRIANGLE_STRIPS"):
                triangles.append(
                    _cells_to_triangles(
                        offsets, connectivity, strips=key == "TRIANGLE_STRIPS", path=path
                    )
                )
        elif key == "METADATA":
            _skip_metadata(reader, components)
        elif key == "FIELD" and cells is None and not triangles:
            # The dataset's field data, which VTK writes before POINTS (PyVista's
            # field_data): arrays of known sizes, passed over.
            _skip_field(reader, words, binary, path)
        elif key in ("POINT_DATA", "CELL_DATA", "FIELD"):
            break  # attributes follow the geometry: nothing more to read
        else:
            raise OSError(f"{path!r}: unexpected keyword {words[0]!r} in POLYDATA")
    if vertices is None:
        raise OSError(f"{path!r}: no POINTS section")
    if kind == "UNSTRUCTURED_GRID" and cells is not None and not triangles:
        raise OSError(f"{path!r}: CELLS without CELL_TYPES")
    faces = np.concatenate(triangles) if triangles else np.zeros((0, 3), dtype=np.int64)
    return _check_mesh(vertices, faces.astype(np.int64), path)


def _legacy_cells(
    reader: _LegacyReader, words: list[str], version: float, binary: bool, path: str
) -> tuple[np.ndarray, np.ndarray]:
    """CSR ``(offsets with a leading 0, connectivity)`` of a legacy cell section."""
    count, size = int(words[1]), int(words[2])
    if version >= 5.0:
        # VTK 9: "KEY offsets connectivity", then OFFSETS and CONNECTIVITY arrays.
        off_words = (reader.line() or "").split()
        offsets = reader.numbers(count, _legacy_dtype(off_words[1], path), binary)
        con_words = (reader.line() or "").split()
        connectivity = reader.numbers(size, _legacy_dtype(con_words[1], path), binary)
        return offsets.astype(np.int64), connectivity.astype(np.int64)
    # Before VTK 9: one row per cell, "npts i0 i1 ...", int32 in binary files.
    flat = reader.numbers(size, ">i4", binary).astype(np.int64)
    offsets_list, connectivity_parts, at = [0], [], 0
    for _ in range(count):
        if at >= flat.size:
            raise OSError(f"{path!r}: cell list shorter than its count")
        npts = int(flat[at])
        connectivity_parts.append(flat[at + 1 : at + 1 + npts])
        offsets_list.append(offsets_list[-1] + npts)
        at += npts + 1
    connectivity = np.concatenate(connectivity_parts) if connectivity_parts else np.zeros(0)
    return np.array(offsets_list, dtype=np.int64), connectivity.astype(np.int64)


def _skip_metadata(reader: _LegacyReader, components: int) -> None:
    """Pass an array's ``METADATA`` block (VTK >= 8), its keyword line already read:
    ``COMPONENT_NAMES`` (one line per component, empty for an unnamed one) and ``INFORMATION n``
    keys, ended by an empty line."""
    while (text := reader.raw_line()) is not None and text.strip():
        if text.strip().upper() == "COMPONENT_NAMES":
            for _ in range(components):
                reader.raw_line()


def _skip_field(reader: _LegacyReader, words: list[str], binary: bool, path: str) -> None:
    """Pass a ``FIELD name n`` block, its keyword line already read: ``n`` arrays, each a line
    ``name numComponents numTuples dataType``, its values (ASCII, or big-endian binary
    followed by a newline) and possibly a ``METADATA`` block."""
    try:
        count = int(words[2])
        if count < 0:
            raise ValueError(count)
    except (IndexError, ValueError):
        raise OSError(
            f"{path!r}: 'FIELD name numArrays' expected, got {' '.join(words)!r}"
        ) from None
    for _ in range(count):
        header = reader.line()
        if header is None:
            raise OSError(f"{path!r}: FIELD {words[1]!r} ends before its {count} arrays")
        parts = header.split()
        if parts == ["NULL_ARRAY"]:
            continue
        try:
            name, components, tuples = parts[0], int(parts[1]), int(parts[2])
            kind = parts[3].lower()
            if components < 0 or tuples < 0:
                raise ValueError(header)
        except (IndexError, ValueError):
            raise OSError(
                f"{path!r}: FIELD {words[1]!r}: an array line 'name numComponents numTuples "
                f"dataType' expected, got {header!r}"
            ) from None
        what, values = f"FIELD array {name!r}", components * tuples
        if kind in ("string", "utf8_string"):
            _skip_strings(reader, values, binary, what)
        elif (kind == "bit" or kind in _FIELD_TYPES) and not binary:
            reader.skip_tokens(values, what)
        elif kind == "bit":  # packed, eight to a byte
            reader.skip_bytes((values + 7) // 8, what)
        elif kind in _FIELD_TYPES:
            reader.skip_bytes(values * np.dtype(_FIELD_TYPES[kind]).itemsize, what)
        else:
            raise OSError(f"{path!r}: {what} has data type {parts[3]!r}, which is not supported")
        at = reader.pos
        if (reader.line() or "").upper() == "METADATA":
            _skip_metadata(reader, components)
        else:
            reader.pos = at


def _skip_strings(reader: _LegacyReader, count: int, binary: bool, what: str) -> None:
    """Pass ``count`` strings: ASCII, one line each (empty for an empty string); binary, each
    after a 1, 2, 4 or 8-byte big-endian length whose two top bits say its size."""
    if not binary:
        for _ in range(count):
            if reader.raw_line() is None:
                raise OSError(f"{reader.path!r}: expected {count} strings in {what}, file ends")
        return
    for _ in range(count):
        if reader.pos >= len(reader.data):
            raise OSError(f"{reader.path!r}: binary data ends early (in {what})")
        size = {3: 1, 2: 2, 1: 4, 0: 8}[reader.data[reader.pos] >> 6]
        reader.skip_bytes(size, what)
        head = int.from_bytes(reader.data[reader.pos - size : reader.pos], "big")
        reader.skip_bytes(head & ((1 << (8 * size - 2)) - 1), what)


#: VTK cell types: skipped (vertices, lines), surface cells split into triangles.
_VTK_SKIPPED = {1: "vertex", 2: "poly-vertex", 3: "line", 4: "polyline"}
_VTK_TRIANGLE, _VTK_STRIP, _VTK_POLYGON, _VTK_PIXEL, _VTK_QUAD = 5, 6, 7, 8, 9


def _typed_cells_to_triangles(
    offsets: np.ndarray, connectivity: np.ndarray, types: np.ndarray, path: str
) -> np.ndarray:
    """Triangles of an unstructured grid's surface cells (triangles; quads, polygons and
    pixels split into two or more triangles, with a warning; strips). Vertices and lines are
    skipped; a volume or higher-order cell is refused (it is not a triangle surface)."""
    sizes = np.diff(offsets)
    if types.size != sizes.size:
        raise OSError(f"{path!r}: {sizes.size} cells but {types.size} cell types")
    other = sorted(set(types.tolist()) - set(_VTK_SKIPPED) - {5, 6, 7, 8, 9})
    if other:
        raise OSError(
            f"{path!r} holds cells of VTK type {other} (volume or higher-order cells): a "
            "triangle surface is read (extract its surface first)"
        )
    parts: list[np.ndarray] = []
    pixel = types == _VTK_PIXEL
    if pixel.any():
        # A pixel's corners are in grid order (0, 1, 3, 2 around it): reorder into a quad.
        starts = offsets[:-1][pixel]
        corners = connectivity[starts[:, None] + np.arange(4)]
        connectivity = connectivity.copy()
        connectivity[starts[:, None] + np.arange(4)] = corners[:, [0, 1, 3, 2]]
    for kind, strips in ((None, False), (_VTK_STRIP, True)):
        chosen = np.isin(types, [_VTK_TRIANGLE, _VTK_POLYGON, _VTK_PIXEL, _VTK_QUAD])
        if kind is not None:
            chosen = types == kind
        if not chosen.any():
            continue
        starts, counts = offsets[:-1][chosen], sizes[chosen]
        sub_offsets = np.concatenate([[0], np.cumsum(counts)])
        index = np.repeat(starts - sub_offsets[:-1], counts) + np.arange(sub_offsets[-1])
        parts.append(
            _cells_to_triangles(sub_offsets, connectivity[index], strips=strips, path=path)
        )
    return np.concatenate(parts) if parts else np.zeros((0, 3), dtype=np.int64)


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
        if type_name == "String":  # NUL-terminated strings: read as their bytes
            type_name = "UInt8"
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

    Returns ``(vertices (n, 3) float64, faces (m, 3) int64)``, as the file holds them (3D
    Slicer's ``SPACE`` field is not applied: :func:`read_mesh` does).
    """
    vertices, faces, _ = _read_vtk_xml(path)
    return vertices, faces


def _read_vtk_xml(path: str) -> tuple[np.ndarray, np.ndarray, str | None]:
    """:func:`read_vtp`'s vertices and faces, and the coordinate system 3D Slicer wrote in the
    file's field data (a string array ``SPACE``: ``"RAS"`` or ``"LPS"``; ``None`` without)."""
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
    grid = root.get("type") == "UnstructuredGrid"
    if root.tag != "VTKFile" or root.get("type") not in ("PolyData", "UnstructuredGrid"):
        raise OSError(
            f"{path!r}: VTKFile type='PolyData' or 'UnstructuredGrid' is read, got "
            f"{root.get('type')!r}"
        )
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
        if grid:
            found = {a.get("Name"): a for a in piece.findall("Cells/DataArray")}
            if int(piece.get("NumberOfCells", "0")) == 0:
                base += n
                continue
            if not {"connectivity", "offsets", "types"} <= set(found):
                raise OSError(f"{path!r}: Cells without connectivity, offsets and types")
            connectivity = arrays.read(found["connectivity"]).astype(np.int64)
            offsets = np.concatenate([[0], arrays.read(found["offsets"]).astype(np.int64)])
            types = arrays.read(found["types"]).astype(np.int64)
            triangle_parts.append(
                _typed_cells_to_triangles(offsets, connectivity, types, path) + base
            )
            base += n
            continue
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
    space = None
    for field in root.iter("FieldData"):
        for array in field:
            if array.get("Name") == "SPACE" and array.get("type") == "String":
                text = bytes(arrays.read(array).astype(np.uint8)).split(b"\0", 1)[0]
                space = text.decode("ascii", errors="replace").strip().upper()
    return (*_check_mesh(vertices, faces.astype(np.int64), path), space)


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
    m = len(faces)
    piece = f'NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" NumberOfPolys="{m}"'
    _write_vtk_xml(path, "PolyData", piece, "Polys", vertices, faces, ascii)


def write_vtu(path: str, vertices: np.ndarray, faces: np.ndarray, *, ascii: bool = False) -> None:
    """Write a VTK XML ``UnstructuredGrid`` file of triangle cells (VTK type 5)."""
    types = np.full(len(faces), _VTK_TRIANGLE, dtype=np.uint8)
    _write_vtk_xml(
        path, "UnstructuredGrid", f'NumberOfCells="{len(faces)}"', "Cells", vertices, faces,
        ascii, _xml_array("types", "UInt8", types, ascii, 1),
    )  # fmt: skip


def _write_vtk_xml(
    path: str,
    kind: str,
    piece: str,
    cells: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    ascii: bool,
    *extra: str,
) -> None:
    """A VTK XML file (version 1.0) of one piece: the points, then the triangles under the
    element ``cells`` (connectivity, offsets and the ``extra`` arrays)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    parts = [
        '<?xml version="1.0"?>',
        f'<VTKFile type="{kind}" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        f"<{kind}>",
        f'<Piece NumberOfPoints="{len(vertices)}" {piece}>',
        "<Points>",
        _xml_array("Points", "Float64", vertices, ascii, 3),
        "</Points>",
        f"<{cells}>",
        _xml_array("connectivity", "Int64", faces.reshape(-1), ascii, 1),
        _xml_array("offsets", "Int64", 3 * np.arange(1, m + 1, dtype=np.int64), ascii, 1),
        *extra,
        f"</{cells}>",
        "</Piece>",
        f"</{kind}>",
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
        lines = _obj_lines(fh.read())
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


def _obj_lines(data: bytes) -> list[bytes]:
    """The lines of an OBJ file as the format reads them: a line ending in a backslash goes on
    on the next, leading whitespace and a comment after the data are dropped (comment lines
    are kept whole: Open3D writes its counts there), an ``fo`` line is read as ``f``."""
    if b"\\" in data:
        data = re.sub(rb"\\\r?\n", b" ", data)
    lines = [line.lstrip() for line in data.splitlines()]
    lines = [
        line.split(b"#", 1)[0] if b"#" in line and line[:1] != b"#" else line for line in lines
    ]
    # ``fo`` (face outline) is the older specification's name for a face.
    return [b"f" + line[2:] if line[:3] in (b"fo ", b"fo\t") else line for line in lines]


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


def _gltf(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None
) -> tuple[dict[str, Any], bytes]:
    """The glTF 2.0 document and its one buffer: one mesh, one triangle primitive, positions
    (float32, as glTF requires) in the vertices' order."""
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
    return gltf, binary


def write_glb(
    path: str, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Write a binary glTF 2.0 file: one mesh, one triangle primitive (float32 positions)."""
    gltf, binary = _gltf(vertices, faces, normals)
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)  # JSON chunk padded with spaces
    total = 12 + 8 + len(text) + 8 + len(binary)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<4sII", b"glTF", 2, total))
        fh.write(struct.pack("<I4s", len(text), b"JSON") + text)
        fh.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)


def write_gltf(
    path: str, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Write a glTF 2.0 JSON file with its buffer inside (a base64 data URI): one file, one
    mesh, one triangle primitive (float32 positions), vertices in order."""
    gltf, binary = _gltf(vertices, faces, normals)
    encoded = base64.b64encode(binary).decode("ascii")
    gltf["buffers"][0]["uri"] = f"data:application/octet-stream;base64,{encoded}"
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(gltf, fh, separators=(",", ":"))


# ---------------------------------------------------------------------------------------------
# Text formats written at full precision: OBJ, OFF, ASCII PLY
# ---------------------------------------------------------------------------------------------

#: Shortest text that reads back as the same float64 (17 significant digits).
_FULL = "%.17g"


def _rows(values: np.ndarray, fmt: str) -> str:
    """``values`` (2-D) as text lines, one row each (NumPy's formatting, in C)."""
    if values.size == 0:
        return ""
    buf = io.StringIO()
    np.savetxt(buf, values, fmt=fmt)
    return buf.getvalue()


def write_obj(path: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a Wavefront OBJ file: ``v x y z`` at full float64 precision, then ``f a b c``
    (1-based). The counts are written as comments (as Open3D does), so :func:`read_obj` finds a
    truncated file."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    with open(path, "w", encoding="ascii") as fh:
        fh.write("# written by o3dreg\n")
        fh.write(f"# number of vertices: {len(vertices)}\n")
        fh.write(f"# number of triangles: {len(faces)}\n")
        fh.write(_rows(vertices, f"v {_FULL} {_FULL} {_FULL}"))
        fh.write(_rows(faces + 1, "f %d %d %d"))


def write_off(path: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a plain ``OFF`` file (no normals: ``NOFF`` is refused by meshio and PyVista) at
    full float64 precision."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"OFF\n{len(vertices)} {len(faces)} 0\n")
        fh.write(_rows(vertices, f"{_FULL} {_FULL} {_FULL}"))
        fh.write(_rows(faces, "3 %d %d %d"))


def write_ply_ascii(
    path: str, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Write an ASCII PLY file: double coordinates (and normals) at full precision."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    columns = [vertices]
    props = ["x", "y", "z"]
    if normals is not None and len(normals) == len(vertices):
        columns.append(np.asarray(normals, dtype=np.float64))
        props += ["nx", "ny", "nz"]
    header = ["ply", "format ascii 1.0", "comment written by o3dreg"]
    header.append(f"element vertex {len(vertices)}")
    header += [f"property double {name}" for name in props]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "w", encoding="ascii") as fh:
        fh.write("\n".join(header) + "\n")
        fh.write(_rows(np.hstack(columns), " ".join([_FULL] * len(props))))
        fh.write(_rows(faces, "3 %d %d %d"))


# ---------------------------------------------------------------------------------------------
# OFF (read)
# ---------------------------------------------------------------------------------------------

#: ``[ST][C][N][4][n]OFF``: texture coordinates, colours, normals, 4-D, n-D (Geomview; the
#: first three in any order: MeshLab writes ``NSTOFF``).
_OFF_KEY = re.compile(r"^((?:ST|C|N)*)(4)?(n)?OFF$")


def read_off(path: str, name: str = "path") -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an ASCII OFF file (Geomview's format and its variants).

    The keyword may carry prefixes (``NOFF``, ``COFF``, ``STOFF``, ``NSTOFF``, ...: extra
    numbers per vertex, ignored) and the counts may follow it on the same line (``OFF n m e``);
    ``#`` starts a comment. Polygons are split into triangle fans (with a warning). 4-D,
    n-D and binary OFF files are refused.
    """
    with open(path, "rb") as fh:
        text = fh.read().decode("latin-1")
    tokens_by_line = [line.split("#", 1)[0].split() for line in text.splitlines()]
    lines = [t for t in tokens_by_line if t]
    if not lines:
        raise OSError(f"`{name}`: {path!r} is empty")
    head = lines[0]
    match = _OFF_KEY.match(head[0])
    if match is None:
        raise OSError(f"`{name}`: {path!r} is not an OFF file (first word {head[0]!r})")
    if match.group(2) or match.group(3):
        raise OSError(f"`{name}`: {path!r} is a {head[0]} file (4-D or n-D): 3-D OFF is read")
    rest = head[1:]
    if rest[:1] == ["BINARY"]:
        raise OSError(f"`{name}`: {path!r} is a binary OFF file: ASCII OFF is read")
    at = 1
    if len(rest) < 2:
        if at >= len(lines):
            raise OSError(f"`{name}`: {path!r} ends before its counts")
        rest = lines[at]
        at += 1
    try:
        nv, nf = int(rest[0]), int(rest[1])
    except (ValueError, IndexError):
        raise OSError(
            f"`{name}`: {path!r}: counts 'vertices faces edges' expected, got {rest}"
        ) from None
    if at + nv + nf > len(lines):
        raise OSError(
            f"`{name}`: {path!r} is truncated: it declares {nv} vertices and {nf} faces, "
            f"{len(lines) - at} lines follow"
        )
    try:
        vertices = np.array([row[:3] for row in lines[at : at + nv]], dtype=np.float64)
    except ValueError:
        raise OSError(f"`{name}`: {path!r}: a vertex is not three numbers") from None
    if vertices.shape != (nv, 3):
        raise OSError(f"`{name}`: {path!r}: a vertex line holds fewer than 3 numbers")
    offsets, connectivity = [0], []
    for number, row in enumerate(lines[at + nv : at + nv + nf]):
        try:
            k = int(row[0])
            corners = [int(c) for c in row[1 : 1 + k]]
        except ValueError:
            corners, k = [], -1
        if k < 1 or len(corners) != k:
            raise OSError(f"`{name}`: {path!r}: face {number + 1} is malformed: {' '.join(row)!r}")
        connectivity.extend(corners)
        offsets.append(len(connectivity))
    faces = _cells_to_triangles(
        np.array(offsets), np.array(connectivity, dtype=np.int64), strips=False, path=path
    )
    return _check_mesh(vertices, faces, path)


# ---------------------------------------------------------------------------------------------
# glTF (.gltf, .glb): read in the file's vertex order
# ---------------------------------------------------------------------------------------------

_GLTF_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "i2", 5123: "u2", 5125: "u4", 5126: "f4"}
_GLTF_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _gltf_document(path: str) -> tuple[dict[str, Any], list[bytes]]:
    """The JSON document and the bytes of every buffer (GLB chunk, data URI or file beside)."""
    with open(path, "rb") as fh:
        data = fh.read()
    binary_chunk = b""
    if data[:4] == b"glTF":
        if len(data) < 20:
            raise OSError(f"{path!r}: a GLB file shorter than its header")
        _, _, total = struct.unpack_from("<4sII", data, 0)
        at, doc_bytes = 12, b""
        while at + 8 <= min(total, len(data)):
            size, kind = struct.unpack_from("<I4s", data, at)
            chunk = data[at + 8 : at + 8 + size]
            if len(chunk) != size:
                raise OSError(f"{path!r}: GLB chunk ends early (truncated file)")
            if kind == b"JSON":
                doc_bytes = chunk
            elif kind == b"BIN\0" and not binary_chunk:
                binary_chunk = chunk
            at += 8 + size + ((-size) % 4 if at + 8 + size < total else 0)
        text = doc_bytes
    else:
        text = data
    try:
        doc = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise OSError(f"{path!r} is not a glTF file ({exc})") from None
    buffers: list[bytes] = []
    folder = os.path.dirname(os.path.abspath(path))
    for k, buffer in enumerate(doc.get("buffers", [])):
        uri = buffer.get("uri")
        if uri is None:
            buffers.append(binary_chunk)
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            try:
                with open(os.path.join(folder, urllib.parse.unquote(uri)), "rb") as fh:
                    buffers.append(fh.read())
            except OSError as exc:
                raise OSError(f"{path!r}: buffer {k} ({uri!r}) cannot be read: {exc}") from None
    return doc, buffers


def _gltf_view(
    doc: dict[str, Any], buffers: list[bytes], view_index: int, offset: int, size: int, path: str
) -> tuple[bytes, int]:
    """The buffer and start of ``size`` bytes from ``offset`` into buffer view
    ``view_index``; ``OSError`` when they reach beyond the buffer (a truncated file)."""
    view = doc["bufferViews"][view_index]
    buffer = buffers[view["buffer"]]
    start = int(view.get("byteOffset", 0)) + offset
    if start + size > len(buffer):
        raise OSError(
            f"{path!r}: buffer view {view_index} reaches beyond its buffer (truncated file)"
        )
    return buffer, start


def _gltf_accessor(doc: dict[str, Any], buffers: list[bytes], index: int, path: str) -> np.ndarray:
    """The values of accessor ``index``: its buffer view (zeros without one), sparse
    substitutions applied, normalized integers mapped to [0, 1] or [-1, 1] (glTF 2.0, 3.6)."""
    accessor = doc["accessors"][index]
    dtype = np.dtype("<" + _GLTF_COMPONENTS[accessor["componentType"]])
    width = _GLTF_WIDTH[accessor["type"]]
    count = int(accessor["count"])
    if "bufferView" not in accessor:
        values = np.zeros((count, width), dtype=dtype)  # all zeros, as the specification says
    else:
        size = dtype.itemsize * width
        offset = int(accessor.get("byteOffset", 0))
        stride = int(doc["bufferViews"][accessor["bufferView"]].get("byteStride", 0)) or size
        span = stride * (count - 1) + size if count else 0
        try:
            buffer, start = _gltf_view(doc, buffers, accessor["bufferView"], offset, span, path)
        except OSError:
            raise OSError(
                f"{path!r}: accessor {index} reaches beyond its buffer (truncated file)"
            ) from None
        values = np.array(
            np.ndarray(
                (count, width),
                dtype=dtype,
                buffer=buffer,
                offset=start,
                strides=(stride, dtype.itemsize),
            )
        )
    sparse = accessor.get("sparse")
    if sparse is not None:
        # Values at a few indices replace those of the base (or of the zeros): a tool's way to
        # store a few moved vertices (morph targets, edits) without repeating the others.
        n = int(sparse["count"])
        kind = np.dtype("<" + _GLTF_COMPONENTS[sparse["indices"]["componentType"]])
        buffer, start = _gltf_view(
            doc, buffers, sparse["indices"]["bufferView"],
            int(sparse["indices"].get("byteOffset", 0)), n * kind.itemsize, path,
        )  # fmt: skip
        where = np.frombuffer(buffer, kind, n, start).astype(np.int64)
        buffer, start = _gltf_view(
            doc, buffers, sparse["values"]["bufferView"],
            int(sparse["values"].get("byteOffset", 0)), n * width * dtype.itemsize, path,
        )  # fmt: skip
        if n and (where.min() < 0 or where.max() >= count):
            raise OSError(f"{path!r}: accessor {index} has sparse indices outside [0, {count})")
        values[where] = np.frombuffer(buffer, dtype, n * width, start).reshape(n, width)
    if accessor.get("normalized") and dtype.kind in "iu":
        # KHR_mesh_quantization: integer positions that stand for [0, 1] or [-1, 1].
        top = float(np.iinfo(dtype).max)
        return np.maximum(values.astype(np.float64) / top, -1.0)
    return values


def _gltf_node_matrix(node: dict[str, Any]) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    matrix = np.eye(4)
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    matrix[:3, :3] = rotation * np.asarray(node.get("scale", [1.0, 1.0, 1.0]), dtype=np.float64)
    matrix[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return matrix


#: glTF extensions whose data o3dreg cannot decode (the geometry is not in the accessors).
_GLTF_COMPRESSION = {
    "KHR_draco_mesh_compression",
    "EXT_meshopt_compression",
    "KHR_meshopt_compression",
}


def read_gltf(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a glTF 2.0 file (``.gltf`` or ``.glb``), in the file's order.

    Every triangle primitive (mode 4, and strips and fans, modes 5 and 6; indexed or not) of
    every mesh of the default scene, each node's transformation applied; primitives follow each
    other in the order the scene lists them. Sparse accessors and normalized integer positions
    (``KHR_mesh_quantization``) are decoded; Draco- or meshopt-compressed files are refused
    (their vertices are not in the accessors). A one-primitive file (what o3dreg and most tools
    write) keeps its vertex order, so a semilandmark mesh keeps its correspondence (Open3D's
    reader renumbers the vertices).
    """
    doc, buffers = _gltf_document(path)
    required = doc.get("extensionsRequired") if isinstance(doc, dict) else None
    compressed = sorted(set(required or []) & _GLTF_COMPRESSION)
    if compressed:
        # Their accessors hold no data (Draco) or their buffers a placeholder (meshopt): read
        # as they stand, every vertex would be at the origin.
        raise OSError(
            f"{path!r} is compressed with {', '.join(compressed)}, which o3dreg does not "
            "decode: export it without mesh compression"
        )
    try:
        scenes = doc.get("scenes") or [{"nodes": list(range(len(doc.get("nodes", []))))}]
        roots = scenes[int(doc.get("scene", 0))].get("nodes", [])
        vertex_parts: list[np.ndarray] = []
        face_parts: list[np.ndarray] = []
        base = 0
        stack = [(int(n), np.eye(4)) for n in reversed(roots)]
        while stack:
            index, parent = stack.pop()
            node = doc["nodes"][index]
            world = parent @ _gltf_node_matrix(node)
            for child in reversed(node.get("children", [])):
                stack.append((int(child), world))
            if "mesh" not in node:
                continue
            for primitive in doc["meshes"][node["mesh"]]["primitives"]:
                mode = primitive.get("mode", 4)
                if mode not in (4, 5, 6) or "POSITION" not in primitive["attributes"]:
                    continue  # points and lines
                position = doc["accessors"][primitive["attributes"]["POSITION"]]
                draco = "KHR_draco_mesh_compression" in primitive.get("extensions", {})
                if draco and "bufferView" not in position and "sparse" not in position:
                    raise OSError(
                        f"{path!r} holds a Draco-compressed primitive (KHR_draco_mesh_compression) "
                        "without uncompressed data, which o3dreg does not decode: export it "
                        "without mesh compression"
                    )
                points = _gltf_accessor(doc, buffers, primitive["attributes"]["POSITION"], path)
                points = points.astype(np.float64)
                if not np.allclose(world, np.eye(4)):
                    points = points @ world[:3, :3].T + world[:3, 3]
                if "indices" in primitive:
                    corners = _gltf_accessor(doc, buffers, primitive["indices"], path)
                    corners = corners.reshape(-1).astype(np.int64)
                else:
                    corners = np.arange(len(points), dtype=np.int64)
                k = np.arange(max(corners.size - 2, 0))
                if mode == 4:  # a list of triangles (an index list that is not: refused)
                    whole = corners.size if "indices" in primitive else corners.size // 3 * 3
                    faces = corners[:whole].reshape(-1, 3)
                elif mode == 5:  # a strip: every second triangle's first two corners swapped
                    faces = np.stack([corners[k], corners[k + 1], corners[k + 2]], axis=1)
                    faces[1::2, [0, 1]] = faces[1::2, [1, 0]]
                elif k.size:  # a fan around the first corner
                    faces = np.stack(
                        [np.full(k.size, corners[0]), corners[k + 1], corners[k + 2]], 1
                    )
                else:
                    faces = np.zeros((0, 3), dtype=np.int64)
                vertex_parts.append(points)
                face_parts.append(faces + base)
                base += len(points)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise OSError(
            f"{path!r} is not a glTF triangle mesh ({type(exc).__name__}: {exc})"
        ) from None
    if not vertex_parts:
        raise OSError(f"{path!r} holds no triangle primitive")
    return _check_mesh(np.concatenate(vertex_parts), np.concatenate(face_parts), path)


# ---------------------------------------------------------------------------------------------
# Dispatch by suffix (used by o3dreg.io.mesh)
# ---------------------------------------------------------------------------------------------

#: Suffixes read and written here rather than by Open3D alone.
OWN_SUFFIXES = (".vtk", ".vtp", ".vtu", ".obj", ".off", ".gltf", ".glb", ".stl")


def read_mesh(path: str, suffix: str, name: str = "path") -> Any:
    """Read ``path`` as an ``open3d.geometry.TriangleMesh`` (empty when Open3D finds nothing;
    ``name``: the parameter the path came from, for the OBJ reader's messages), in LPS where
    3D Slicer wrote it in RAS and said so (see :func:`slicer_space`)."""
    if suffix in (".vtp", ".vtu"):
        vertices, faces, space = _read_vtk_xml(path)
        return _to_lps(to_open3d(vertices, faces), space, path)
    if suffix == ".vtk":
        mesh = to_open3d(*read_vtk(path))
    elif suffix == ".obj":
        mesh = to_open3d(*read_obj(path, name))
    elif suffix == ".off":
        return to_open3d(*read_off(path, name))
    elif suffix in (".gltf", ".glb"):
        return to_open3d(*read_gltf(path))
    else:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(path)  # type: ignore[arg-type]  # stubs: PathLike
        if suffix == ".stl" and len(mesh.triangles):
            vertices, faces = merge_identical_vertices(
                np.asarray(mesh.vertices), np.asarray(mesh.triangles)
            )
            mesh = to_open3d(vertices, faces)
    return _to_lps(mesh, slicer_space(path, suffix), path)


#: 3D Slicer's mark of a model's coordinate system (``vtkMRMLModelStorageNode``, Slicer >= 4.11).
_SLICER_SPACE = re.compile(rb"SPACE=(RAS|LPS)\b", re.IGNORECASE)


def slicer_space(path: str, suffix: str) -> str | None:
    """The coordinate system 3D Slicer wrote into a model file's header, ``"RAS"`` or
    ``"LPS"``; ``None`` when the header has no such mark.

    Slicer (``vtkMRMLModelStorageNode``, since 4.11) writes ``SPACE=LPS`` (its default) or
    ``SPACE=RAS`` (chosen when saving or exporting segments) in the legacy ``.vtk`` title line,
    the ``.stl`` header (``solid`` line), a ``.ply`` comment and an ``.obj`` comment line; in
    ``.vtp`` / ``.vtu`` files, a field data string array ``SPACE`` (read with the file). A file
    without the mark is taken as it is (LPS, as Slicer reads it).
    """
    if suffix not in (".vtk", ".stl", ".ply", ".obj"):
        return None
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if suffix == ".vtk":
        lines = head.split(b"\n", 2)
        texts = lines[1:2]  # the title
    elif suffix == ".stl":
        texts = [head[:80].split(b"\n", 1)[0]]  # the binary header, or the "solid" line
    elif suffix == ".ply":
        header = head.split(b"end_header", 1)[0]
        texts = [line for line in header.split(b"\n") if line.startswith(b"comment")]
    else:
        texts = [line for line in head.split(b"\n") if line.lstrip().startswith(b"#")]
    for text in texts:
        match = _SLICER_SPACE.search(text)
        if match:
            return match.group(1).decode().upper()
    return None


def _to_lps(mesh: Any, space: str | None, path: str) -> Any:
    """``mesh`` in LPS: x and y (and the normals') negated when ``space`` is ``"RAS"``."""
    if space != "RAS":
        return mesh
    flip = np.array([-1.0, -1.0, 1.0])
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * flip)
    if mesh.has_vertex_normals():
        mesh.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals) * flip)
    if mesh.has_triangle_normals():
        mesh.triangle_normals = o3d.utility.Vector3dVector(np.asarray(mesh.triangle_normals) * flip)
    _log.info("%s: written in RAS (SPACE=RAS, 3D Slicer's mark): converted to LPS", path)
    return mesh


def write_mesh(path: str, mesh: Any, suffix: str, *, write_ascii: bool = False) -> bool:
    """Write an ``open3d.geometry.TriangleMesh`` (a copy the caller owns) to ``path``."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
    if suffix == ".vtk":
        write_vtk(path, vertices, faces, ascii=write_ascii)
    elif suffix == ".vtp":
        write_vtp(path, vertices, faces, ascii=write_ascii)
    elif suffix == ".vtu":
        write_vtu(path, vertices, faces, ascii=write_ascii)
    elif suffix == ".glb":
        write_glb(path, vertices, faces, normals)
    elif suffix == ".gltf":
        write_gltf(path, vertices, faces, normals)
    elif suffix == ".stl":
        # Open3D needs triangle normals (a mesh read from PLY may have vertex normals only)
        # and writes no ASCII STL: both forms are written here.
        write_stl(path, vertices, faces, ascii=write_ascii)
    elif suffix == ".obj":
        write_obj(path, vertices, faces)
    elif suffix == ".off":
        write_off(path, vertices, faces)
    elif suffix == ".ply" and write_ascii:
        write_ply_ascii(path, vertices, faces, normals)
    else:
        # Binary PLY: Open3D writes double coordinates (full precision).
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            return bool(o3d.io.write_triangle_mesh(path, mesh, write_ascii=write_ascii))  # type: ignore[arg-type]
    return True
