"""Checks that a mesh file is whole before a reader allocates what its header promises.

A PLY header claiming two billion vertices would make Open3D try to allocate them (tens of GB)
before finding the file short. (A truncated OBJ is found by o3dreg's OBJ reader itself,
``formats.read_obj``.) These checks compare what the header promises
with what the file holds, reading the file once and allocating nothing in proportion to the
claims.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["check_ply_complete"]

_PLY_TYPE_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1,
    "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip

# A PLY header is a few hundred bytes; a longer one is not a header we can trust.
_MAX_PLY_HEADER = 1 << 16


def check_ply_complete(path: str, name: str = "path") -> dict[str, int]:
    """``OSError`` when the PLY file at ``path`` is shorter than its header's elements need.

    Returns the element counts the header declares (``{'vertex': n, 'face': m, ...}``; empty
    for a header not understood), for the caller to compare with what a reader returns.
    """
    with open(path, "rb") as fh:
        head = fh.read(_MAX_PLY_HEADER)
    end = head.find(b"end_header")
    # Refused here, in one line: Open3D's reader would print its own line first.
    if not head:
        raise OSError(f"`{name}`: {path!r} is empty")
    if not head.startswith(b"ply"):
        raise OSError(f"`{name}`: {path!r} is not a PLY file (it does not start with 'ply')")
    if end < 0:
        return {}  # not a PLY header we understand: the reader reports it
    body_start = head.find(b"\n", end)
    body_start = len(head) if body_start < 0 else body_start + 1
    text = head[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    elements: list[tuple[str, int, list[int]]] = []  # name, count, minimal bytes per property
    properties: dict[int, list[list[str]]] = {}  # per element, its property lines' words
    for line in text:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) > 1:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                count = int(words[2])
            except ValueError:
                raise OSError(f"`{name}`: {path!r} has a bad PLY element line {line!r}") from None
            if count < 0:
                raise OSError(f"`{name}`: {path!r} has a negative element count {line!r}")
            elements.append((words[1], count, []))
        elif words[0] == "property" and elements and len(words) >= 3:
            properties.setdefault(len(elements) - 1, []).append(words[1:])
            if words[1] == "list" and len(words) >= 5:
                # The count of the list, and for faces at least three corners.
                corners = 3 if elements[-1][0] == "face" else 0
                elements[-1][2].append(
                    _PLY_TYPE_SIZES.get(words[2], 1) + corners * _PLY_TYPE_SIZES.get(words[3], 1)
                )
            else:
                elements[-1][2].append(_PLY_TYPE_SIZES.get(words[1], 1))
    claims = ", ".join(f"{count} {element}" for element, count, _ in elements)
    declared = {element: count for element, count, _ in elements}
    if not fmt.startswith("binary"):
        # ASCII: one line per element.
        total = sum(count for _, count, _ in elements)
        lines = _count_lines(path, body_start)
        if lines < total:
            raise OSError(
                f"`{name}`: {path!r} is truncated or its header is wrong: the header declares "
                f"{claims} ({total} lines), the file holds {lines}"
            )
        _check_triangle_records(path, name, fmt, body_start, elements, properties)
        return declared
    needed = sum(count * sum(sizes) for _, count, sizes in elements)
    held = os.path.getsize(path) - body_start
    if held < needed:
        raise OSError(
            f"`{name}`: {path!r} is truncated or its header is wrong: the header declares "
            f"{claims} (at least {needed} bytes of data), the file holds {held}"
        )
    _check_triangle_records(path, name, fmt, body_start, elements, properties)
    return declared


_PLY_NUMPY = {
    "char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1",
    "short": "i2", "ushort": "u2", "int16": "i2", "uint16": "u2",
    "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
}  # fmt: skip


def _check_triangle_records(
    path: str,
    name: str,
    fmt: str,
    body_start: int,
    elements: list[tuple[str, int, list[int]]],
    properties: dict[int, list[list[str]]],
) -> None:
    """``OSError`` when the faces of a triangle PLY are not all 3-corner records.

    Open3D reads a face record whose corner count is wrong (an edited ASCII line ``3 1 2``, a
    flipped count byte) by running on into the next records: triangles of garbage, a log line,
    and in the binary case a crash of the process. The common layout is checked here: vertices
    first (fixed-size properties), then faces with the one list property. ASCII: every face line
    holds its count plus that many indices. Binary: when the faces fill the rest of the file
    exactly as triangles would, every count is 3. Other layouts are left to the reader.
    """
    if len(elements) < 2 or elements[0][0] != "vertex" or elements[1][0] != "face":
        return
    face_properties = properties.get(1, [])
    if len(face_properties) != 1 or face_properties[0][0] != "list":
        return
    vertices, faces = elements[0][1], elements[1][1]
    if not fmt.startswith("binary"):
        with open(path, "rb") as fh:
            fh.seek(body_start)
            lines = [line for line in fh.read().splitlines() if line.strip()]
        for number, line in enumerate(lines[vertices : vertices + faces]):
            words = line.split()
            if not words[0].isdigit() or len(words) != int(words[0]) + 1 or int(words[0]) < 3:
                raise OSError(
                    f"`{name}`: {path!r} is malformed: face {number} is {line.decode(errors='replace')!r} "
                    "(a corner count of at least 3 followed by that many vertex indices expected)"
                )
        return
    if any(p[0] == "list" for p in properties.get(0, [])):
        return
    count_type = _PLY_NUMPY.get(face_properties[0][1])
    index_type = _PLY_NUMPY.get(face_properties[0][2])
    if count_type is None or index_type is None:
        return
    order = "<" if fmt == "binary_little_endian" else ">"
    record = np.dtype([("n", order + count_type), ("i", order + index_type, 3)])
    offset = body_start + vertices * sum(elements[0][2])
    if os.path.getsize(path) - offset != faces * record.itemsize:
        # Polygons, or elements after the faces: walk the records one by one.
        _check_polygon_records(path, name, fmt, offset, faces, count_type, index_type)
        return
    counts = np.fromfile(path, dtype=record, count=faces, offset=offset)["n"]
    wrong = np.flatnonzero(counts != 3)
    if wrong.size:
        raise OSError(
            f"`{name}`: {path!r} is malformed: {wrong.size} of its {faces} triangle records "
            f"do not start with the corner count 3 (face {int(wrong[0])}: "
            f"{int(counts[wrong[0]])})"
        )


def _check_polygon_records(
    path: str, name: str, fmt: str, offset: int, faces: int, count_type: str, index_type: str
) -> None:
    """``OSError`` when a binary PLY's face records (polygons) do not each hold at least three
    corners within the file: Open3D's reader crashes the process on a polygon of fewer
    corners (a flipped count byte).

    Polygons of one corner count (all quads, say) are checked at a fixed stride in one read;
    mixed counts are walked record by record.
    """
    order = "<" if fmt == "binary_little_endian" else ">"
    count = np.dtype(order + count_type)
    index_size = np.dtype(index_type).itemsize
    data = np.fromfile(path, dtype=np.uint8, offset=offset)
    if faces == 0:
        return
    if data.size >= count.itemsize:
        first = int(data[: count.itemsize].view(count)[0])
        stride = count.itemsize + first * index_size
        if first >= 3 and data.size >= faces * stride:
            starts = np.arange(faces, dtype=np.int64)[:, None] * stride
            raw = data[starts + np.arange(count.itemsize)].reshape(-1).view(count)
            if (raw == first).all():
                return
    at = 0
    for k in range(faces):
        end = at + count.itemsize
        corners = int(data[at:end].view(count)[0]) if end <= data.size else -1
        at = end + max(corners, 0) * index_size
        if corners < 3 or at > data.size:
            raise OSError(
                f"`{name}`: {path!r} is malformed: face {k} of its {faces} is not a "
                "polygon of at least 3 corners within the file (a corrupted corner count)"
            )


def _count_lines(path: str, start: int) -> int:
    """Non-empty lines from byte ``start`` on (a last line without a newline counts)."""
    lines = 0
    last = b"\n"
    with open(path, "rb") as fh:
        fh.seek(start)
        while block := fh.read(1 << 22):
            lines += block.count(b"\n") - block.count(b"\n\n")
            last = block[-1:]
    return lines + (last != b"\n")
