"""Mesh file formats: round trips per suffix, STL corners merged, GLB read back, VTK polydata.

The VTK fixtures are written byte by byte here, following the published formats (VTK File
Formats, legacy and XML; VTK 9 legacy 5.1 ``OFFSETS`` / ``CONNECTIVITY``; zlib-compressed
appended data with its block header), independently of o3dreg's writers.
"""

from __future__ import annotations

import base64
import json
import logging
import struct
import zlib

import numpy as np
import open3d as o3d
import pytest
from _helpers import assert_untouched, mesh_of, snapshot

from o3dreg import read_triangle_mesh, write_triangle_mesh
from o3dreg.io.formats import merge_identical_vertices
from o3dreg.io.mesh import MESH_SUFFIXES


def _same_triangles(back, vertices, faces):
    """``back`` has the same vertices (any order, float32 precision) and oriented triangles."""
    from scipy.spatial import cKDTree

    got = np.asarray(back.vertices)
    distance, index = cKDTree(vertices).query(got)
    # float32 files (STL, glTF, OFF/PLY text with 6-7 digits): 1e-5 of the 10 mm radius.
    assert distance.max() < 1e-4
    assert len(set(index.tolist())) == len(vertices)
    mapped = index[np.asarray(back.triangles)]

    def canonical(tris):
        return sorted(tuple(np.roll(t, -int(np.argmin(t)))) for t in tris.tolist())

    assert canonical(mapped) == canonical(np.asarray(faces))


@pytest.fixture(scope="module")
def sphere():
    return o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=12)


@pytest.mark.parametrize("ascii", [False, True])
@pytest.mark.parametrize("suffix", MESH_SUFFIXES)
def test_every_suffix_round_trips(sphere, tmp_path, suffix, ascii):
    snap = snapshot(sphere)
    path = write_triangle_mesh(tmp_path / f"m{suffix}", sphere, write_ascii=ascii)
    back = read_triangle_mesh(path)
    assert_untouched(sphere, snap)
    # Same vertex and triangle counts (STL corners merged back), same triangles up to float32.
    assert len(back.vertices) == len(sphere.vertices)
    assert len(back.triangles) == len(sphere.triangles)
    _same_triangles(back, *snap)


def test_stl_corners_are_merged(sphere, tmp_path):
    # Open3D reads STL as three vertices per triangle: keep_largest_components then kept one.
    path = str(tmp_path / "open3d.stl")
    mesh = o3d.geometry.TriangleMesh(sphere)
    mesh.compute_triangle_normals()
    assert o3d.io.write_triangle_mesh(path, mesh)
    assert len(o3d.io.read_triangle_mesh(path).vertices) > len(sphere.vertices)
    back = read_triangle_mesh(path)
    assert len(back.vertices) == len(sphere.vertices)
    # One connected surface again: every vertex is shared by several triangles.
    clusters, _, _ = back.cluster_connected_triangles()
    assert len(set(np.asarray(clusters).tolist())) == 1


def test_merge_keeps_first_seen_order():
    v = np.array([[1.0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0]])
    f = np.array([[0, 1, 3], [2, 4, 3]])
    merged, faces = merge_identical_vertices(v, f)
    np.testing.assert_array_equal(merged, [[1, 0, 0], [0, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 1, 2]])


def test_stl_from_a_ply_with_vertex_normals(sphere, tmp_path):
    mesh = o3d.geometry.TriangleMesh(sphere)
    mesh.compute_vertex_normals()
    ply = str(tmp_path / "n.ply")
    o3d.io.write_triangle_mesh(ply, mesh)
    read = read_triangle_mesh(ply)
    assert read.has_vertex_normals() and not read.has_triangle_normals()
    back = read_triangle_mesh(write_triangle_mesh(tmp_path / "n.stl", read))
    assert len(back.vertices) == len(sphere.vertices)
    assert not read.has_triangle_normals()  # the caller's mesh is not given normals


def test_glb_is_valid_gltf(sphere, tmp_path):
    path = write_triangle_mesh(tmp_path / "m.glb", sphere)
    data = open(path, "rb").read()
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_len % 4 == 0
    bin_len, bin_type = struct.unpack_from("<I4s", data, 20 + json_len)
    assert bin_type == b"BIN\0" and 28 + json_len + bin_len == len(data)
    trimesh = pytest.importorskip("trimesh")
    scene = trimesh.load(path)
    geometry = next(iter(scene.geometry.values())) if hasattr(scene, "geometry") else scene
    assert len(geometry.faces) == len(sphere.triangles)


# --- VTK fixtures written by hand --------------------------------------------------------------

SQUARE = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]])


def _legacy_42_ascii():
    # A quad (split into a fan), a strip of two triangles, a line and a vertex (skipped).
    return (
        b"# vtk DataFile Version 4.2\nhand made\nASCII\nDATASET POLYDATA\n"
        b"POINTS 6 float\n0 0 0 1 0 0 1 1 0\n0 1 0 2 0 0 2 1 0\n"
        b"METADATA\nINFORMATION 0\n\n"
        b"VERTICES 1 2\n1 0\nLINES 1 3\n2 0 1\n"
        b"POLYGONS 1 5\n4 0 1 2 3\n"
        b"TRIANGLE_STRIPS 1 5\n4 1 4 2 5\n"
        b"POINT_DATA 6\nSCALARS s float 1\nLOOKUP_TABLE default\n0 1 2 3 4 5\n"
    )


def _legacy_51(binary):
    offsets, connectivity = np.array([0, 3, 6]), np.array([0, 1, 2, 0, 2, 3])
    head = b"# vtk DataFile Version 5.1\nvtk output\n" + (b"BINARY\n" if binary else b"ASCII\n")
    head += b"DATASET POLYDATA\nPOINTS 4 double\n"
    if binary:
        body = SQUARE[:4].astype(">f8").tobytes() + b"\n"
        body += b"POLYGONS 3 6\nOFFSETS vtktypeint64\n" + offsets.astype(">i8").tobytes()
        body += b"\nCONNECTIVITY vtktypeint64\n" + connectivity.astype(">i8").tobytes() + b"\n"
    else:
        body = b" ".join(str(x).encode() for x in SQUARE[:4].ravel()) + b"\n"
        body += b"POLYGONS 3 6\nOFFSETS vtktypeint64\n0 3 6\nCONNECTIVITY vtktypeint64\n"
        body += b"0 1 2 0 2 3\n"
    return head + body + b"CELL_DATA 2\n"


def test_legacy_vtk_42_ascii_with_fans_strips_and_attributes(tmp_path, caplog):
    path = tmp_path / "a.vtk"
    path.write_bytes(_legacy_42_ascii())
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        mesh = read_triangle_mesh(path)
    assert "split into triangle fans" in caplog.text
    assert len(mesh.vertices) == 6
    # Quad 0-1-2-3 -> (0,1,2), (0,2,3); strip 1-4-2-5 -> (1,4,2), (2,4,5) (the second flipped).
    np.testing.assert_array_equal(
        np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3], [1, 4, 2], [2, 4, 5]]
    )
    normals = np.asarray(mesh.compute_triangle_normals().triangle_normals)
    np.testing.assert_allclose(normals, [[0, 0, 1]] * 4)  # consistently oriented


@pytest.mark.parametrize("binary", [False, True])
def test_legacy_vtk_51_offsets_and_connectivity(tmp_path, binary):
    path = tmp_path / "b.vtk"
    path.write_bytes(_legacy_51(binary))
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_legacy_vtk_42_binary_int32_cells(tmp_path):
    cells = np.array([3, 0, 1, 2, 3, 0, 2, 3], dtype=">i4")
    data = (
        b"# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\nPOINTS 4 float\n"
        + SQUARE[:4].astype(">f4").tobytes()
        + b"\nPOLYGONS 2 8\n"
        + cells.tobytes()
        + b"\n"
    )
    path = tmp_path / "c.vtk"
    path.write_bytes(data)
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("cells", ["POLYGONS", "CELLS"])
def test_legacy_vtk_51_binary_vtkidtype_arrays_are_32_bit(tmp_path, cells):
    # VTK's legacy writer stores a vtkIdType array as 32-bit ints (vtkDataWriter: "currently
    # writing vtkIdType as int"), and its reader reads them so. PyVista 0.49 / VTK 9.7 write
    # ``pv.PolyData.from_regular_faces(...).save("x.vtk")`` with "CONNECTIVITY vtkIdType":
    # read as 64-bit, the file was refused ("binary data ends early", "unexpected keyword").
    offsets, connectivity = np.array([0, 3, 6]), np.array([0, 1, 2, 0, 2, 3])
    kind = b"POLYDATA" if cells == "POLYGONS" else b"UNSTRUCTURED_GRID"
    data = (
        b"# vtk DataFile Version 5.1\nvtk output\nBINARY\nDATASET " + kind + b"\n"
        + b"POINTS 4 double\n" + SQUARE[:4].astype(">f8").tobytes() + b"\n"
        + cells.encode() + b" 3 6\nOFFSETS vtktypeint64\n" + offsets.astype(">i8").tobytes()
        + b"\nCONNECTIVITY vtkIdType\n" + connectivity.astype(">i4").tobytes() + b"\n"
        + (b"CELL_TYPES 2\n" + np.array([5, 5], ">i4").tobytes() + b"\n" if cells == "CELLS" else b"")
        + b"CELL_DATA 2\nSCALARS lab int\nLOOKUP_TABLE default\n" + np.array([7, 8], ">i4").tobytes()
    )  # fmt: skip
    path = tmp_path / "idtype.vtk"
    path.write_bytes(data)
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def _field_data(binary):
    """Dataset field data as VTK 9's legacy writer puts it before POINTS (PyVista's
    ``field_data``): each array ``name numComponents numTuples dataType``, its values, and in a
    METADATA block one line per component name, empty for an unnamed one."""
    out = b"FIELD FieldData 5\nTimeValue 2 1 double\n"
    out += np.array([1.5, 2.5], ">f8").tobytes() + b"\n" if binary else b"1.5 2.5\n"
    # The first component has no name: its line is empty, not the end of the block.
    out += b"METADATA\nCOMPONENT_NAMES\n\nsecond\nINFORMATION 1\n"
    out += b"NAME UNITS_LABEL LOCATION vtkDataArray\nDATA s\n\n"
    strings = [b"patient 7", b"", b"x" * 70, b"a\nPOINTS 1 float"]
    out += b"name 1 4 string\n"
    if binary:
        # A length byte 0b11xxxxxx below 64, two bytes 0b10xxxxxx... up to 16383; the bytes as
        # they are (a newline inside a string is not the end of a line).
        for text in strings:
            head = 0xC0 | len(text) if len(text) < 64 else 0x8000 | len(text)
            out += head.to_bytes(1 if len(text) < 64 else 2, "big") + text
        out += b"\n"
    else:
        out += b"patient%207\n\n" + b"x" * 70 + b"\na%0APOINTS%201%20float\n\n"
    out += b"flags 1 10 bit\n"
    out += bytes([0b10110010, 0b11000000]) + b"\n" if binary else b"1 0 1 1 0 0 1 0\n1 1\n"
    out += b"ids 2 3 vtkIdType\n"  # written as 32-bit int
    out += np.arange(6).astype(">i4").tobytes() + b"\n" if binary else b"0 1 2 3 4 5\n"
    return out + b"empty 1 0 float\n\n"


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("version", ["4.2", "5.1"])
def test_legacy_vtk_with_dataset_field_data_before_points(tmp_path, binary, version):
    if version == "5.1":
        data = _legacy_51(binary)
    else:
        cells = np.array([3, 0, 1, 2, 3, 0, 2, 3])
        data = b"# vtk DataFile Version 4.2\nvtk output\n" + (b"BINARY" if binary else b"ASCII")
        data += b"\nDATASET POLYDATA\nPOINTS 4 double\n"
        if binary:
            data += SQUARE[:4].astype(">f8").tobytes() + b"\nPOLYGONS 2 8\n"
            data += cells.astype(">i4").tobytes() + b"\n"
        else:
            data += b" ".join(str(x).encode() for x in SQUARE[:4].ravel())
            data += b"\nPOLYGONS 2 8\n" + b" ".join(str(x).encode() for x in cells) + b"\n"
    at = data.index(b"POINTS")
    path = tmp_path / "field.vtk"
    path.write_bytes(data[:at] + _field_data(binary) + data[at:])
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_legacy_vtk_field_data_of_an_unknown_type_or_size_is_named(tmp_path):
    data = _legacy_51(True)
    at = data.index(b"POINTS")
    path = tmp_path / "variant.vtk"
    path.write_bytes(data[:at] + b"FIELD FieldData 1\nv 1 1 variant\n1 1\n" + data[at:])
    with pytest.raises(
        OSError, match=r"FIELD array 'v' has data type 'variant', which is not supported"
    ):
        read_triangle_mesh(path)
    # A negative size would move the binary cursor backwards.
    path.write_bytes(data[:at] + b"FIELD FieldData 1\nt 1 -8 double\n" + data[at:])
    with pytest.raises(OSError, match=r"an array line .* expected, got 't 1 -8 double'"):
        read_triangle_mesh(path)


def _vtp(arrays_xml, appended=b"", header="UInt32", compressor=None, encoding="raw"):
    attrs = f'type="PolyData" version="1.0" byte_order="LittleEndian" header_type="{header}"'
    if compressor:
        attrs += f' compressor="{compressor}"'
    out = f'<?xml version="1.0"?>\n<VTKFile {attrs}>\n<PolyData>\n'.encode()
    out += b'<Piece NumberOfPoints="4" NumberOfPolys="2">\n' + arrays_xml + b"</Piece>\n"
    out += b"</PolyData>\n"
    if appended:
        out += f'<AppendedData encoding="{encoding}">\n_'.encode() + appended
        out += b"\n</AppendedData>\n"
    return out + b"</VTKFile>\n"


def _arrays_xml(fmt, points, conn, offs):
    return (
        f'<Points><DataArray type="Float32" NumberOfComponents="3" format="{fmt}"{points}'
        f"</Points>\n<Polys>"
        f'<DataArray type="Int32" Name="connectivity" format="{fmt}"{conn}'
        f'<DataArray type="Int32" Name="offsets" format="{fmt}"{offs}'
        f"</Polys>\n"
    ).encode()


ARRAYS = (
    SQUARE[:4].astype("<f4"),
    np.array([0, 1, 2, 0, 2, 3], dtype="<i4"),
    np.array([3, 6], dtype="<i4"),
)


def test_vtp_ascii(tmp_path):
    bodies = [">" + " ".join(str(x) for x in a.ravel()) + "</DataArray>" for a in ARRAYS]
    path = tmp_path / "a.vtp"
    path.write_bytes(_vtp(_arrays_xml("ascii", *bodies)))
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_vtp_inline_binary_header_and_data_encoded_apart(tmp_path):
    # VTK's inline binary: the UInt32 byte count and the data are two base64 streams.
    def encode(a):
        raw = a.tobytes()
        header = base64.b64encode(struct.pack("<I", len(raw)))
        return ">" + (header + base64.b64encode(raw)).decode() + "</DataArray>"

    path = tmp_path / "b.vtp"
    path.write_bytes(_vtp(_arrays_xml("binary", *(encode(a) for a in ARRAYS))))
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_vtp_appended_raw_zlib_uint64(tmp_path):
    # VTK 9's default writer: appended raw data, zlib blocks, UInt64 headers
    # [number of blocks, block size, last block size, compressed sizes...].
    blob, offsets = b"", []
    for a in ARRAYS:
        raw = a.tobytes()
        packed = zlib.compress(raw)
        offsets.append(len(blob))
        blob += struct.pack("<4Q", 1, len(raw), len(raw), len(packed)) + packed
    bodies = [f' offset="{o}"/>' for o in offsets]
    xml = _arrays_xml("appended", *bodies)
    path = tmp_path / "c.vtp"
    path.write_bytes(_vtp(xml, blob, header="UInt64", compressor="vtkZLibDataCompressor"))
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_vtp_appended_base64(tmp_path):
    blob, offsets = b"", []
    for a in ARRAYS:
        raw = a.tobytes()
        offsets.append(len(blob))
        blob += base64.b64encode(struct.pack("<I", len(raw))) + base64.b64encode(raw)
    bodies = [f' offset="{o}"/>' for o in offsets]
    path = tmp_path / "d.vtp"
    path.write_bytes(_vtp(_arrays_xml("appended", *bodies), blob, encoding="base64"))
    mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


def test_vtk_files_that_are_not_triangle_polydata(tmp_path):
    grid = tmp_path / "grid.vtk"
    grid.write_bytes(b"# vtk DataFile Version 4.2\nx\nASCII\nDATASET STRUCTURED_POINTS\n")
    with pytest.raises(
        OSError, match="POLYDATA or UNSTRUCTURED_GRID is read, got STRUCTURED_POINTS"
    ):
        read_triangle_mesh(grid)
    text = tmp_path / "text.vtk"
    text.write_text("hello\n")
    with pytest.raises(OSError, match="not a legacy VTK file"):
        read_triangle_mesh(text)
    points = tmp_path / "points.vtk"
    points.write_bytes(
        b"# vtk DataFile Version 4.2\nx\nASCII\nDATASET POLYDATA\nPOINTS 1 float\n0 0 0\n"
    )
    with pytest.raises(OSError, match="holds no triangle mesh"):
        read_triangle_mesh(points)
    bad = tmp_path / "bad.vtk"
    bad.write_bytes(_legacy_51(False).replace(b"0 1 2 0 2 3", b"0 1 2 0 2 9"))
    with pytest.raises(OSError, match="outside"):
        read_triangle_mesh(bad)
    image = tmp_path / "image.vtp"
    image.write_bytes(b'<?xml version="1.0"?><VTKFile type="ImageData"></VTKFile>')
    with pytest.raises(OSError, match="type='PolyData' or 'UnstructuredGrid' is read"):
        read_triangle_mesh(image)


def test_arrays_written_as_vtk(tmp_path):
    mesh = mesh_of(SQUARE[:4], [[0, 1, 2], [0, 2, 3]])
    for suffix in (".vtk", ".vtp"):
        back = read_triangle_mesh(write_triangle_mesh(tmp_path / f"s{suffix}", mesh))
        # Binary, float64 points: exact.
        np.testing.assert_array_equal(np.asarray(back.vertices), SQUARE[:4])
        np.testing.assert_array_equal(np.asarray(back.triangles), [[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("ascii", [False, True])
@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".vtk", ".vtp"])
def test_semilandmark_formats_keep_the_vertex_order(sphere, tmp_path, suffix, ascii):
    # The vertex index is the correspondence between patients: written and read back, every
    # vertex and triangle is where it was (float32 formats: within 1e-5 of the 10 mm radius).
    path = write_triangle_mesh(tmp_path / f"m{suffix}", sphere, write_ascii=ascii)
    back = read_triangle_mesh(path)
    np.testing.assert_allclose(np.asarray(back.vertices), np.asarray(sphere.vertices), atol=1e-4)
    np.testing.assert_array_equal(np.asarray(back.triangles), np.asarray(sphere.triangles))


def test_obj_of_another_writer_keeps_its_order_and_its_polygons(tmp_path, caplog):
    # Texture and normal indices, a quad, a negative (relative) index, a vertex with a colour,
    # comments and groups: the vertices in the file's order, the quad as a fan of 2 triangles.
    path = tmp_path / "other.obj"
    path.write_text(
        "# another writer\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0 0.5 0.5 0.5\nv 0 1 0\n"
        "vt 0 0\nvn 0 0 1\ng faces\nf 1/1/1 2/1/1 3/1/1 4/1/1\nv 2 0 0\nf 2//1 5//1 -3//1\n"
    )
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(
        np.asarray(mesh.vertices), [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]]
    )
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    assert "triangle fans" in caplog.text
    # The same file of triangles only takes the vectorised path: the same numbers.
    plain = tmp_path / "plain.obj"
    plain.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1//7 3//7 4//7\n")
    np.testing.assert_array_equal(
        np.asarray(read_triangle_mesh(plain).triangles), [[0, 1, 2], [0, 2, 3]]
    )
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 x\n")
    with pytest.raises(OSError, match="malformed face"):
        read_triangle_mesh(bad)


def test_obj_indented_commented_and_continued_lines_read_as_the_plain_file(tmp_path):
    # Indented statements, a comment after the data and a statement continued on the next line
    # (a trailing backslash) are OBJ as the format describes it: the same mesh as the plain file.
    plain = tmp_path / "plain.obj"
    plain.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    other = tmp_path / "other.obj"
    other.write_text(
        "# number of vertices: 4\n  v 0 0 0\n\tv 1 0 0 # corner\nv 1 \\\n 1 0\nv 0 1 0\n"
        "  f 1 2 3   # first\nf 1 \\\r\n3 4\n"
    )
    # ``fo`` (face outline), the older specification's name for a face.
    outline = tmp_path / "outline.obj"
    outline.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nfo 1 2 3\nfo\t1 3 4\n")
    for path in (plain, other, outline):
        mesh = read_triangle_mesh(path)
        np.testing.assert_array_equal(
            np.asarray(mesh.vertices), [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
        )
        np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


# -- glTF written by hand from the glTF 2.0 specification --------------------------------------


def _gltf(tmp_path, positions, primitive, *, accessor=None, blobs=(), node=None, required=()):
    """A .gltf of one primitive whose accessor 0 holds ``positions`` (bufferView 0; then one
    buffer view per blob of ``blobs``), edited by ``accessor`` (``None``: key removed); its
    path."""
    positions = np.ascontiguousarray(positions)
    data, views = b"", []
    for blob in (positions.tobytes(), *blobs):
        views.append({"buffer": 0, "byteOffset": len(data), "byteLength": len(blob)})
        data += blob + b"\0" * ((-len(blob)) % 4)
    position = {"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3"}
    position = {k: v for k, v in {**position, **(accessor or {})}.items() if v is not None}
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, **(node or {})}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, **primitive}]}],
        "buffers": [
            {
                "byteLength": len(data),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode(),
            }
        ],
        "bufferViews": views,
        "accessors": [position],
    }
    if required:
        doc["extensionsUsed"] = doc["extensionsRequired"] = list(required)
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("required", [["KHR_draco_mesh_compression"], []])
def test_gltf_compressed_with_draco_is_refused_not_read_as_zeros(tmp_path, required):
    # A Draco primitive's accessors have no bufferView (the vertices are in the compressed
    # stream): read as they stand, every vertex was at the origin and every triangle (0, 0, 0),
    # with no error.
    path = _gltf(
        tmp_path,
        SQUARE[:4].astype("<f4"),
        {"extensions": {"KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {}}}},
        accessor={"bufferView": None},
        required=required,
    )
    with pytest.raises(OSError, match="KHR_draco_mesh_compression"):
        read_triangle_mesh(path)


def test_gltf_sparse_accessor_and_strips_and_fans(tmp_path):
    # Positions as a sparse accessor over zeros (vertices 1-3 given), a triangle strip (mode 5)
    # and a fan (mode 6): every vertex where it is, every triangle facing +z.
    where = np.array([1, 2, 3], dtype="<u2").tobytes()
    values = SQUARE[1:4].astype("<f4").tobytes()
    sparse = {
        "count": 3,
        "indices": {"bufferView": 1, "componentType": 5123},
        "values": {"bufferView": 2},
    }
    for mode, corners in ((5, [0, 1, 3, 2]), (6, [0, 1, 2, 3])):
        path = _gltf(
            tmp_path,
            np.zeros((4, 3), "<f4"),
            {"mode": mode, "indices": 1},
            accessor={"sparse": sparse},
            blobs=(where, values, np.array(corners, dtype="<u4").tobytes()),
        )
        doc = json.loads(path.read_text())
        doc["accessors"].append(
            {"bufferView": 3, "componentType": 5125, "count": 4, "type": "SCALAR"}
        )
        path.write_text(json.dumps(doc))
        mesh = read_triangle_mesh(path)
        np.testing.assert_array_equal(np.asarray(mesh.vertices), SQUARE[:4])
        assert len(mesh.triangles) == 2, (mode, np.asarray(mesh.triangles))
        normals = np.asarray(mesh.compute_triangle_normals().triangle_normals)
        np.testing.assert_allclose(normals, [[0, 0, 1]] * 2)


def test_gltf_normalized_quantized_positions(tmp_path):
    # KHR_mesh_quantization: int16 positions flagged normalized stand for [-1, 1], placed by the
    # node's scale (gltfpack -vpn). Read as raw integers, the mesh was 32767 times too large.
    quantized = np.zeros((4, 4), dtype="<i2")  # 8-byte stride: VEC3 of int16 padded
    quantized[:, :3] = np.round(SQUARE[:4] * 32767)
    path = _gltf(
        tmp_path,
        quantized,
        {"indices": 1},
        accessor={"componentType": 5122, "normalized": True},
        blobs=(np.array([0, 1, 2, 0, 2, 3], dtype="<u2").tobytes(),),
        node={"scale": [10.0, 10.0, 10.0]},
        required=["KHR_mesh_quantization"],
    )
    doc = json.loads(path.read_text())
    doc["bufferViews"][0]["byteStride"] = 8
    doc["accessors"].append({"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"})
    path.write_text(json.dumps(doc))
    mesh = read_triangle_mesh(path)
    np.testing.assert_allclose(np.asarray(mesh.vertices), SQUARE[:4] * 10, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])


# -- 3D Slicer's coordinate system mark --------------------------------------------------------


def _slicer_model(suffix, space):
    """The triangle 0-1-2 of SQUARE moved to (30, -40, 50), as 3D Slicer's
    vtkMRMLModelStorageNode writes a model with its coordinate system marked ``SPACE=...``."""
    points = SQUARE[:3] + [30.0, -40.0, 50.0]
    rows = "\n".join(" ".join(f"{c:g}" for c in p) for p in points)
    mark = f"3D Slicer output. SPACE={space}"
    if suffix == ".vtk":  # the title line
        text = f"# vtk DataFile Version 4.2\n{mark}\nASCII\nDATASET POLYDATA\n"
        return (text + f"POINTS 3 float\n{rows}\nPOLYGONS 1 4\n3 0 1 2\n").encode()
    if suffix == ".stl":  # the 80-byte header of a binary file
        record = struct.pack("<12fH", 0, 0, 1, *points.ravel(), 0)
        return mark.encode().ljust(80, b" ") + struct.pack("<I", 1) + record
    if suffix == ".ply":  # a header comment
        head = f"ply\nformat ascii 1.0\ncomment VTK generated PLY File\ncomment SPACE={space}\n"
        head += "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        head += "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        return (head + rows + "\n3 0 1 2\n").encode()
    if suffix == ".obj":  # vtkOBJExporter's comment line
        body = "\n".join(f"v {r}" for r in rows.split("\n"))
        return f"#  {mark}\n\nmtllib m.mtl\n\n{body}\nf 1 2 3\n".encode()
    # .vtp: a field data string array SPACE (ASCII: its characters' codes and a 0)
    codes = " ".join(str(b) for b in space.encode()) + " 0"
    return (
        '<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" '
        'byte_order="LittleEndian"><PolyData><FieldData>'
        f'<Array type="String" Name="SPACE" NumberOfTuples="1" format="ascii">{codes}</Array>'
        '</FieldData><Piece NumberOfPoints="3" NumberOfPolys="1"><Points>'
        '<DataArray type="Float32" NumberOfComponents="3" format="ascii">'
        f"{rows}</DataArray></Points><Polys>"
        '<DataArray type="Int64" Name="connectivity" format="ascii">0 1 2</DataArray>'
        '<DataArray type="Int64" Name="offsets" format="ascii">3</DataArray>'
        "</Polys></Piece></PolyData></VTKFile>\n"
    ).encode()


@pytest.mark.parametrize("suffix", [".vtk", ".stl", ".ply", ".obj", ".vtp"])
def test_a_model_3d_slicer_wrote_in_ras_is_read_in_lps(tmp_path, suffix):
    # Slicer (>= 4.11) marks the system of a model it saves: SPACE=LPS by default, SPACE=RAS when
    # chosen on saving or exporting segments. A RAS model was read as if LPS: turned 180 degrees
    # about the S axis against the CT and the landmarks (x and y negated), without a word.
    lps = SQUARE[:3] + [30.0, -40.0, 50.0]
    for space, expected in (("RAS", lps * [-1, -1, 1]), ("LPS", lps)):
        path = tmp_path / f"model_{space}{suffix}"
        path.write_bytes(_slicer_model(suffix, space))
        mesh = read_triangle_mesh(path)
        np.testing.assert_allclose(np.asarray(mesh.vertices), expected, atol=1e-5)
        # Negating x and y is a rotation: the triangle still faces +z.
        normals = np.asarray(mesh.compute_triangle_normals().triangle_normals)
        np.testing.assert_allclose(normals, [[0, 0, 1]], atol=1e-9)
