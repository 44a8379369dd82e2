"""Mesh IO: clear errors, atomic writes, nothing overwritten by accident."""

import struct
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from _helpers import assert_untouched, mesh_of, snapshot

from o3dreg import read_triangle_mesh, write_triangle_mesh
from o3dreg.app.synthetic import synthetic_form
from o3dreg.io.mesh import atomic_write


def test_roundtrip_and_inputs_untouched(tmp_path):
    cube = synthetic_form("cube", 200)
    mesh = mesh_of(np.asarray(cube.vertices), np.asarray(cube.triangles))
    snap = snapshot(mesh)
    path = write_triangle_mesh(tmp_path / "cube.ply", mesh)
    back = read_triangle_mesh(path)
    np.testing.assert_allclose(np.asarray(back.vertices), snap[0])
    np.testing.assert_array_equal(np.asarray(back.triangles), snap[1])
    assert_untouched(mesh, snap)
    assert not mesh.has_vertex_normals()  # the copy got normals, not the caller's mesh


def test_arrays_are_accepted(tmp_path):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    write_triangle_mesh(tmp_path / "tri.obj", (v, np.array([[0, 1, 2]])))
    assert len(read_triangle_mesh(tmp_path / "tri.obj").triangles) == 1


def test_no_overwrite_without_permission(tmp_path):
    mesh = synthetic_form("cube", 200)
    path = tmp_path / "m.ply"
    write_triangle_mesh(path, mesh)
    with pytest.raises(OSError, match="exists; pass overwrite=True"):
        write_triangle_mesh(path, mesh)
    write_triangle_mesh(path, mesh, overwrite=True)


def test_failed_write_leaves_nothing(tmp_path):
    def failing(tmp):
        with open(tmp, "w") as fh:
            fh.write("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(tmp_path / "out.ply", failing)
    assert list(tmp_path.iterdir()) == []


def test_read_errors(tmp_path):
    with pytest.raises(OSError, match="no such file"):
        read_triangle_mesh(tmp_path / "missing.ply")
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(OSError, match="is a folder, not a mesh file"):
        read_triangle_mesh(tmp_path / "folder.ply")
    with pytest.raises(ValueError, match="must end with one of"):
        read_triangle_mesh(tmp_path / "mesh.xyz")
    # Refused before Open3D's reader, which would print a line of its own on standard error.
    nothing = tmp_path / "nothing.ply"
    nothing.write_bytes(b"")
    with pytest.raises(OSError, match="nothing.ply' is empty"):
        read_triangle_mesh(nothing)
    nothing.write_bytes(b"solid x\n")
    with pytest.raises(OSError, match="is not a PLY file"):
        read_triangle_mesh(nothing)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(OSError, match="could not be read as a triangle mesh"):
        read_triangle_mesh(empty)
    points_only = tmp_path / "points.ply"
    o3d.io.write_point_cloud(
        str(points_only), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3)))
    )
    with pytest.raises(OSError, match="0 triangles"):
        read_triangle_mesh(points_only)
    with pytest.raises(TypeError, match="must be a path"):
        read_triangle_mesh(3)


def test_malformed_ply_faces_are_an_error_not_a_smaller_or_garbled_mesh(tmp_path):
    # Open3D runs on past a face record with a wrong corner count: garbage triangles (ASCII),
    # dropped ones, or a crash of the process (binary). Found by a CLI audit: exit 0 with half
    # the template's triangles, and exit 139 with no message.
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=12)
    m = len(sphere.triangles)
    ascii_path = Path(write_triangle_mesh(tmp_path / "a.ply", sphere, write_ascii=True))
    lines = ascii_path.read_text().split("\n")
    first = next(k for k, line in enumerate(lines) if line.startswith("3 "))
    lines[first + 5] = "3 1 2"
    edited = tmp_path / "edited.ply"
    edited.write_text("\n".join(lines))
    with pytest.raises(OSError, match=r"malformed: face 5 is '3 1 2'"):
        read_triangle_mesh(edited)
    binary_path = Path(write_triangle_mesh(tmp_path / "b.ply", sphere))
    data = binary_path.read_bytes()
    record = 1 + 3 * 4  # uchar count, three uint indices
    for face, count in ((0, 1), (m - 1, 255)):
        broken = bytearray(data)
        broken[len(data) - (m - face) * record] = count
        path = tmp_path / f"count{count}.ply"
        path.write_bytes(bytes(broken))
        with pytest.raises(OSError, match=f"1 of its {m} triangle records .*face {face}: {count}"):
            read_triangle_mesh(path)
    assert len(read_triangle_mesh(binary_path).triangles) == m  # the intact files still read
    assert len(read_triangle_mesh(ascii_path).triangles) == m


def polygon_ply(path, counts, big_endian=False, count_type="uchar"):
    """A binary PLY of 6 vertices and three polygons (two quads, a triangle) whose corner
    counts are ``counts`` (the records keep their real lengths)."""
    order = ">" if big_endian else "<"
    fmt = {"uchar": "B", "char": "b", "ushort": "H", "int": "i"}[count_type]
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1]])
    faces = [[0, 1, 2, 3], [0, 1, 5, 4], [1, 2, 5]]
    header = (
        f"ply\nformat binary_{'big' if big_endian else 'little'}_endian 1.0\nelement vertex 6\n"
        "property float x\nproperty float y\nproperty float z\nelement face 3\n"
        f"property list {count_type} int vertex_indices\nend_header\n"
    )
    body = v.astype(order + "f4").tobytes()
    for count, face in zip(counts, faces):
        body += struct.pack(order + fmt, count) + np.array(face, dtype=order + "i4").tobytes()
    path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("count_type", ["uchar", "char", "ushort", "int"])
def test_polygon_ply_records_with_too_few_corners_are_refused(tmp_path, big_endian, count_type):
    # A binary PLY of polygons whose second record's corner count reads 2 (or -1, or 0): before,
    # Open3D's reader crashed the process (exit 139); a count running past the file was already
    # refused by the element count. The intact file reads as 5 triangles.
    good = polygon_ply(tmp_path / "good.ply", [4, 4, 3], big_endian, count_type)
    assert len(read_triangle_mesh(good).triangles) == 5
    if not big_endian and count_type == "uchar":  # ASCII: a line "2 0 3" crashed it as well
        text = tmp_path / "two.ply"
        text.write_text(
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n2 0 3\n"
        )
        with pytest.raises(OSError, match="face 1 is '2 0 3'"):
            read_triangle_mesh(text)
    assert len(read_triangle_mesh(good).triangles) == 5
    bad_counts = [2, 0] + ([-1] if count_type in ("char", "int") else [])
    for bad in bad_counts:
        path = polygon_ply(tmp_path / f"bad{bad}.ply", [4, bad, 3], big_endian, count_type)
        with pytest.raises(OSError, match="face 1 of its 3 is not a polygon of at least 3"):
            read_triangle_mesh(path)


def test_write_errors(tmp_path):
    mesh = synthetic_form("cube", 200)
    with pytest.raises(OSError, match="does not exist"):
        write_triangle_mesh(tmp_path / "no" / "m.ply", mesh)
    with pytest.raises(ValueError, match="must end with one of"):
        write_triangle_mesh(tmp_path / "m.txt", mesh)
