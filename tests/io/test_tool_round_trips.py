"""Mesh files exchanged with the tools of the field (meshio, trimesh; PyVista / VTK in the slow
set): every format o3dreg writes reads back, by o3dreg, with the template's vertices in order
and at full precision, and what the other tools write reads in o3dreg as they meant it.

docs/install.md's table of formats and tools is what these tests measure.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import pytest

from o3dreg import read_triangle_mesh, write_triangle_mesh
from o3dreg.io.mesh import MESH_SUFFIXES, SEMILANDMARK_SUFFIXES

#: Formats that store float32 coordinates: a 20 mm mesh comes back within float32's rounding
#: (about 1e-6 relative, 2e-5 mm here).
FLOAT32 = (".stl", ".gltf", ".glb")


@pytest.fixture(scope="module")
def semilandmarks():
    """A sphere whose vertices are shuffled (the order no writer would choose by itself) and
    carry 17 significant digits."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=10)
    v = np.asarray(sphere.vertices) * (1 + 1e-9 * np.pi)
    f = np.asarray(sphere.triangles)
    order = np.random.default_rng(0).permutation(len(v))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return v[order] + np.pi * 1e-7, rank[f]


@pytest.mark.parametrize("ascii", [False, True])
@pytest.mark.parametrize("suffix", MESH_SUFFIXES)
def test_every_written_format_keeps_the_vertex_order_or_is_refused(
    semilandmarks, tmp_path, suffix, ascii
):
    v, f = semilandmarks
    path = tmp_path / f"r{suffix}"
    if suffix not in SEMILANDMARK_SUFFIXES:
        with pytest.raises(ValueError, match="keeps the template's vertex order.*STL stores"):
            write_triangle_mesh(path, (v, f), semilandmarks=True, write_ascii=ascii)
        assert list(tmp_path.iterdir()) == []
        return
    write_triangle_mesh(path, (v, f), semilandmarks=True, write_ascii=ascii)
    back = read_triangle_mesh(path)
    got = np.asarray(back.vertices)
    np.testing.assert_array_equal(np.asarray(back.triangles), f)
    if suffix in FLOAT32:
        np.testing.assert_allclose(got, v, rtol=0, atol=2e-5)
    else:
        # Full float64 precision: the same numbers, bit for bit.
        np.testing.assert_array_equal(got, v)


def test_semilandmarks_must_be_a_bool(semilandmarks, tmp_path):
    with pytest.raises(TypeError, match="`semilandmarks` must be True or False, got str"):
        write_triangle_mesh(tmp_path / "m.ply", semilandmarks, semilandmarks="yes")
    assert list(tmp_path.iterdir()) == []


def test_obj_header_does_not_name_the_temporary_file(semilandmarks, tmp_path):
    path = write_triangle_mesh(tmp_path / "m.obj", semilandmarks)
    head = open(path).read(300)
    assert ".part" not in head and "m.obj" not in head


def test_nan_vertices_are_refused_when_writing(semilandmarks, tmp_path):
    v, f = semilandmarks
    bad = v.copy()
    bad[7, 1] = np.nan
    bad[9, 0] = np.inf
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(bad), o3d.utility.Vector3iVector(f.astype(np.int32))
    )
    for suffix in (".ply", ".obj", ".vtk", ".off", ".glb"):
        # An Open3D mesh (which o3dreg's own reader would then refuse)...
        with pytest.raises(ValueError, match=r"`mesh` must have finite vertices, got 2 .*\[7, 9\]"):
            write_triangle_mesh(tmp_path / f"n{suffix}", mesh)
        # ... and arrays.
        with pytest.raises(ValueError, match="finite"):
            write_triangle_mesh(tmp_path / f"a{suffix}", (bad, f))
    assert list(tmp_path.iterdir()) == []
    assert np.isnan(bad[7, 1]) and np.isnan(np.asarray(mesh.vertices)[7, 1])  # untouched


def test_nan_vertices_are_refused_when_reading(semilandmarks, tmp_path):
    # Open3D reads "nan" as a coordinate; written by another tool, such a file must be refused
    # as the OBJ reader refuses it, not measured (a distance picture coloured by NaN).
    v, f = semilandmarks
    bad = v.copy()
    bad[4, 2] = np.nan
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(bad), o3d.utility.Vector3iVector(f.astype(np.int32))
    )
    for suffix in (".ply", ".stl"):
        path = tmp_path / f"n{suffix}"
        mesh.compute_triangle_normals()
        assert o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=suffix == ".ply")
        with pytest.raises(OSError, match=r"holds 1 vertices with NaN or infinite coordinates"):
            read_triangle_mesh(path)


# --- OFF as other tools write it ---------------------------------------------------------------

SQUARE = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"


@pytest.mark.parametrize(
    "text",
    [
        "OFF\n4 2 0\n" + SQUARE + "3 0 1 2\n3 0 2 3\n",
        "OFF 4 2 0\n" + SQUARE + "3 0 1 2\n3 0 2 3\n",  # counts on the header line
        "# comment\nOFF\n# another\n4 2 0\n" + SQUARE + "3 0 1 2\n3 0 2 3\n",
        # MeshLab's NSTOFF: x y z nx ny nz s t per vertex.
        "NSTOFF\n4 2 0\n"
        + "".join(f"{line} 0 0 1 0.5 0.5\n" for line in SQUARE.splitlines())
        + "3 0 1 2\n3 0 2 3\n",
        # COFF with vertex and face colours.
        "COFF\n4 2 0\n"
        + "".join(f"{line} 255 0 0 255\n" for line in SQUARE.splitlines())
        + "3 0 1 2 1 0 0\n3 0 2 3 1 0 0\n",
        "OFF\n4 1 0\n" + SQUARE + "4 0 1 2 3\n",  # a quad: two triangles
    ],
)
def test_off_variants(tmp_path, text, caplog):
    path = tmp_path / "s.off"
    path.write_text(text)
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        mesh = read_triangle_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), np.loadtxt(SQUARE.splitlines()))
    np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2], [0, 2, 3]])
    assert ("triangle fans" in caplog.text) == text.startswith("OFF\n4 1")


def test_written_off_is_plain_off(semilandmarks, tmp_path):
    path = write_triangle_mesh(tmp_path / "m.off", semilandmarks)
    assert open(path).readline() == "OFF\n"


def test_truncated_off_is_an_error(tmp_path):
    path = tmp_path / "t.off"
    path.write_text("OFF\n4 2 0\n" + SQUARE + "3 0 1 2\n")
    with pytest.raises(OSError, match="truncated"):
        read_triangle_mesh(path)


# --- meshio ------------------------------------------------------------------------------------

meshio = pytest.importorskip("meshio")

#: Triangles and quads together, as meshio holds a mixed surface.
MIXED_POINTS = np.array(
    [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0.5], [0.5, 2, 0.25]],
    dtype=np.float64,
) + np.array([0.1234567890123, 0.0, 0.0])
TRIANGLES = np.array([[3, 4, 6], [1, 2, 5]])
QUADS = np.array([[0, 1, 4, 3]])
#: The quad as o3dreg splits it (a fan from its first corner).
SPLIT = np.array([[0, 1, 4], [0, 4, 3]])


# meshio's own OFF writer skips quads ("OFF only supports triangle cells"): not tried here.
@pytest.mark.parametrize("suffix", [".vtk", ".vtu", ".ply", ".obj"])
def test_meshio_mixed_triangles_and_quads_read_whole(tmp_path, suffix, caplog):
    path = tmp_path / f"mixed{suffix}"
    mesh = meshio.Mesh(MIXED_POINTS, [("triangle", TRIANGLES), ("quad", QUADS)])
    mesh.write(path, binary=False) if suffix in (".vtk", ".vtu", ".ply") else mesh.write(path)
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        back = read_triangle_mesh(path)
    got = np.asarray(back.vertices)
    # meshio writes the points in order (its ASCII VTU with 11 decimals: 1e-11 relative).
    np.testing.assert_allclose(got, MIXED_POINTS, rtol=1e-10, atol=0)
    triangles = {tuple(t) for t in np.asarray(back.triangles).tolist()}
    # Never a dropped quad: every cell is there, the quad as two triangles.
    assert triangles == {tuple(t) for t in np.vstack([TRIANGLES, SPLIT]).tolist()}


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("suffix", [".vtk", ".vtu"])
def test_meshio_vtk_unstructured_triangles(semilandmarks, tmp_path, suffix, binary):
    v, f = semilandmarks
    path = tmp_path / f"u{suffix}"
    meshio.Mesh(v, [("triangle", f)]).write(path, binary=binary)
    back = read_triangle_mesh(path)
    # Binary: the same numbers; meshio's ASCII VTU keeps 11 decimals (1e-11 of 10 mm).
    np.testing.assert_allclose(np.asarray(back.vertices), v, rtol=0, atol=0 if binary else 1e-10)
    np.testing.assert_array_equal(np.asarray(back.triangles), f)


@pytest.mark.parametrize("suffix", [".off", ".stl", ".ply", ".obj"])
def test_o3dreg_reads_what_meshio_writes(semilandmarks, tmp_path, suffix):
    v, f = semilandmarks
    path = tmp_path / f"m{suffix}"
    meshio.Mesh(v, [("triangle", f)]).write(path)
    back = read_triangle_mesh(path)
    got = np.asarray(back.vertices)
    if suffix == ".stl":
        np.testing.assert_allclose(got[np.asarray(back.triangles)], v[f], atol=2e-5)
        return
    # meshio writes float64 text with 16 or more digits, binary PLY as float64.
    np.testing.assert_allclose(got, v, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(np.asarray(back.triangles), f)


def test_a_meshio_mesh_in_memory_keeps_its_quads(caplog):
    from o3dreg import evaluate_elastic

    mesh = meshio.Mesh(MIXED_POINTS, [("triangle", TRIANGLES), ("quad", QUADS)])
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        distances = evaluate_elastic(mesh, (MIXED_POINTS, np.vstack([TRIANGLES, SPLIT])))
    assert "1 quad cells split into triangle fans" in caplog.text
    # The same surface both ways: every distance is zero (to rounding).
    assert distances.source_to_target_max < 1e-12
    assert distances.target_to_source_max < 1e-12
    tetra = meshio.Mesh(MIXED_POINTS, [("tetra", np.array([[0, 1, 3, 4]]))])
    with pytest.raises(ValueError, match="`source` must hold surface cells.*'tetra'"):
        evaluate_elastic(tetra, mesh)


def test_meshio_volume_cells_are_refused(tmp_path):
    tetra = meshio.Mesh(MIXED_POINTS[:5], [("tetra", np.array([[0, 1, 3, 4]]))])
    path = tmp_path / "tet.vtu"
    tetra.write(path)
    with pytest.raises(OSError, match="volume or higher-order cells"):
        read_triangle_mesh(path)


# meshio reads no legacy POLYDATA .vtk (what o3dreg, statismo and Slicer write): .vtu is the
# VTK file for meshio.
@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".vtu", ".stl"])
def test_meshio_reads_what_o3dreg_writes(semilandmarks, tmp_path, suffix):
    v, f = semilandmarks
    path = write_triangle_mesh(tmp_path / f"w{suffix}", (v, f))
    mesh = meshio.read(path)
    triangles = np.vstack([c.data for c in mesh.cells if c.type == "triangle"])
    if suffix == ".stl":
        # STL: three corners per triangle, float32; the same triangles.
        corners = mesh.points[triangles]
        np.testing.assert_allclose(corners, v[f], atol=2e-5)
        return
    np.testing.assert_array_equal(mesh.points, v)
    np.testing.assert_array_equal(triangles, f)


# --- trimesh -----------------------------------------------------------------------------------

trimesh = pytest.importorskip("trimesh")


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".glb", ".gltf", ".stl"])
def test_trimesh_reads_what_o3dreg_writes(semilandmarks, tmp_path, suffix):
    v, f = semilandmarks
    path = write_triangle_mesh(tmp_path / f"w{suffix}", (v, f))
    mesh = trimesh.load(path, process=False, force="mesh")
    if suffix == ".stl":
        np.testing.assert_allclose(np.asarray(mesh.vertices)[mesh.faces], v[f], atol=2e-5)
        return
    atol = 2e-5 if suffix in FLOAT32 else 0.0
    np.testing.assert_allclose(np.asarray(mesh.vertices), v, rtol=0, atol=atol)
    np.testing.assert_array_equal(np.asarray(mesh.faces), f)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".glb", ".stl"])
def test_o3dreg_reads_what_trimesh_writes(semilandmarks, tmp_path, suffix):
    v, f = semilandmarks
    path = tmp_path / f"t{suffix}"
    trimesh.Trimesh(v, f, process=False).export(path)
    back = read_triangle_mesh(path)
    got = np.asarray(back.vertices)
    if suffix == ".stl":
        # STL corners merged back: the same triangles, in the order the file's corners come.
        np.testing.assert_allclose(got[np.asarray(back.triangles)], v[f], atol=2e-5)
        return
    # trimesh writes PLY as float32 and OBJ / OFF text with 8-10 decimals: float32's
    # rounding on the 10 mm sphere at most.
    np.testing.assert_allclose(got, v, rtol=0, atol=2e-5)
    np.testing.assert_array_equal(np.asarray(back.triangles), f)


# --- PyVista / VTK (slow: VTK is a large install) ----------------------------------------------


@pytest.mark.slow
def test_evaluate_and_register_agree_on_a_pyvista_polyline():
    # A triangle surface with a polyline in the same PolyData: the polyline's points are on no
    # triangle. registration_elastic refuses such a source; evaluate_elastic measured the
    # polyline's points as if they were surface.
    pv = pytest.importorskip("pyvista")
    from o3dreg import evaluate_elastic, registration_elastic

    both = pv.Sphere(radius=5, theta_resolution=12, phi_resolution=12).merge(
        pv.Line((0, 0, 8), (10, 0, 8), resolution=20)
    )
    target = o3d.geometry.TriangleMesh.create_sphere(5, 10)
    for function in (evaluate_elastic, registration_elastic):
        with pytest.raises(ValueError, match="every vertex on a triangle"):
            function(both, target)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".vtk", ".vtp", ".vtu", ".ply", ".obj", ".off", ".stl"])
def test_pyvista_reads_what_o3dreg_writes(semilandmarks, tmp_path, suffix):
    pv = pytest.importorskip("pyvista")
    v, f = semilandmarks
    path = write_triangle_mesh(tmp_path / f"w{suffix}", (v, f))
    mesh = pv.read(path)
    if suffix == ".stl":
        # VTK's STL reader merges corners itself, in its own order: the same triangle set.
        surface = mesh.extract_surface() if not isinstance(mesh, pv.PolyData) else mesh
        assert surface.n_cells == len(f)
        return
    cells = mesh.faces if isinstance(mesh, pv.PolyData) else mesh.cells  # .vtu: a grid
    points = np.asarray(mesh.points, dtype=np.float64)
    # VTK's PLY, OBJ and OFF readers keep float32 coordinates.
    atol = 2e-5 if suffix in (".ply", ".obj", ".off") else 0.0
    np.testing.assert_allclose(points, v, rtol=0, atol=atol)
    np.testing.assert_array_equal(cells.reshape(-1, 4)[:, 1:], f)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".vtk", ".vtp", ".vtu", ".ply", ".obj", ".stl"])
def test_o3dreg_reads_what_pyvista_writes(semilandmarks, tmp_path, suffix):
    pv = pytest.importorskip("pyvista")
    v, f = semilandmarks
    cells = np.column_stack([np.full(len(f), 3), f]).ravel()
    mesh = pv.PolyData(v, cells)
    path = tmp_path / f"p{suffix}"
    if suffix == ".vtu":
        mesh.cast_to_unstructured_grid().save(path)
    else:
        mesh.save(path)
    back = read_triangle_mesh(path)
    got = np.asarray(back.vertices)
    if suffix == ".stl":
        np.testing.assert_allclose(got[np.asarray(back.triangles)], v[f], atol=2e-5)
        return
    # VTK stores PolyData points as given (float64) in .vtk / .vtp / .vtu; its PLY and OBJ
    # writers use float32 / 6-9 digits.
    atol = 2e-5 if suffix in (".ply", ".obj") else 0.0
    np.testing.assert_allclose(got, v, rtol=0, atol=atol)
    np.testing.assert_array_equal(np.asarray(back.triangles), f)


def test_register_refuses_stl_output_before_any_work(tmp_path, capsys):
    from o3dreg.cli import main

    sphere = o3d.geometry.TriangleMesh.create_sphere(5.0, 8)
    write_triangle_mesh(tmp_path / "t.ply", sphere)
    write_triangle_mesh(tmp_path / "p.ply", sphere)
    code = main(
        [
            "register",
            str(tmp_path / "t.ply"),
            str(tmp_path / "p.ply"),
            "-o",
            str(tmp_path / "r.stl"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "--output" in err and "vertex order" in err and "STL" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.ply", "t.ply"]


def test_gltf_written_by_open3d_and_by_trimesh_reads_in_order(semilandmarks, tmp_path):
    # Open3D writes .gltf with its buffer as a data URI; trimesh writes buffers as .bin files
    # beside it. Both read with the vertices in the order written (float32 positions).
    v, f = semilandmarks
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32))
    )
    o3d.io.write_triangle_mesh(str(tmp_path / "o.gltf"), mesh)
    scene = trimesh.Scene(trimesh.Trimesh(v, f, process=False))
    for name, data in scene.export(file_type="gltf").items():
        (tmp_path / name).write_bytes(data)
    for path in (tmp_path / "o.gltf", tmp_path / "model.gltf"):
        back = read_triangle_mesh(path)
        np.testing.assert_allclose(np.asarray(back.vertices), v, rtol=0, atol=2e-5)
        np.testing.assert_array_equal(np.asarray(back.triangles), f)
