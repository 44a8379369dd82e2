"""Meshes from other libraries at every entry point: one validator, inputs never modified.

pyvista needs the ~565 MB vtk wheel and is not installed for the tests: a stand-in with
PolyData's attributes (``points``, a flat padded ``faces`` array ``[3, i, j, k, ...]``,
``n_strips``) checks that path; trimesh is in the test extra and is used as itself.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest

from o3dreg import build_shape_model, evaluate_elastic, read_triangle_mesh, write_triangle_mesh
from o3dreg._validation import as_mesh_arrays

BOX = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
V = np.asarray(BOX.vertices).copy()
F = np.asarray(BOX.triangles).astype(np.int64)


class PolyDataStandIn:
    """What o3dreg reads of a pyvista.PolyData: ``points``, padded ``faces``, ``n_strips``."""

    def __init__(self, points, faces, n_strips=0):
        self.points = points
        self.faces = faces
        self.n_strips = n_strips


def _padded(faces):
    return np.column_stack([np.full(len(faces), 3), faces]).ravel()


def _meshes():
    import trimesh

    return {
        "open3d": o3d.geometry.TriangleMesh(BOX),
        "open3d.t": o3d.t.geometry.TriangleMesh.from_legacy(BOX),
        "trimesh": trimesh.Trimesh(V.copy(), F.copy(), process=False),
        "pyvista": PolyDataStandIn(V.astype(np.float32), _padded(F)),
        "meshio": SimpleNamespace(points=V.copy(), cells_dict={"triangle": F.copy()}),
        "duck": SimpleNamespace(vertices=V.tolist(), triangles=F.tolist()),
        "pair": (V.copy(), F.copy()),
    }


def _arrays_of(mesh):
    """Copies of the arrays an object exposes, to check afterwards that nothing changed."""
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        return mesh.vertex.positions.numpy().copy(), mesh.triangle.indices.numpy().copy()
    if isinstance(mesh, tuple):
        return mesh[0].copy(), mesh[1].copy()
    points = getattr(mesh, "vertices", getattr(mesh, "points", None))
    faces = getattr(mesh, "faces", getattr(mesh, "triangles", getattr(mesh, "cells_dict", None)))
    faces = faces["triangle"] if isinstance(faces, dict) else faces
    return np.array(points).copy(), np.array(faces).copy()


@pytest.mark.parametrize("kind", list(_meshes()))
def test_every_kind_gives_the_same_arrays_and_stays_untouched(kind):
    mesh = _meshes()[kind]
    before = _arrays_of(mesh)
    vertices, faces = as_mesh_arrays(mesh, "mesh")
    # float32 positions (tensor mesh, pyvista stand-in): the box's coordinates are exact.
    np.testing.assert_array_equal(vertices, V)
    np.testing.assert_array_equal(faces, F)
    assert vertices.dtype == np.float64 and faces.dtype == np.int64
    # New arrays: writing into them never reaches the caller's mesh.
    vertices += 100.0
    faces[:] = 0
    after = _arrays_of(mesh)
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1], before[1])


@pytest.mark.parametrize("kind", ["open3d.t", "trimesh", "pyvista", "meshio"])
def test_entry_points_take_every_kind(kind, tmp_path):
    mesh = _meshes()[kind]
    before = _arrays_of(mesh)
    # A registration evaluation: identical meshes are 0 apart, whatever their kind.
    distances = evaluate_elastic(mesh, _meshes()["pair"])
    assert distances.source_to_target_max == pytest.approx(0.0, abs=1e-9)
    back = read_triangle_mesh(write_triangle_mesh(tmp_path / "m.ply", mesh))
    np.testing.assert_array_equal(np.asarray(back.triangles), F)
    after = _arrays_of(mesh)
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1], before[1])


def test_pyvista_polygons_other_than_triangles_are_refused():
    quad = PolyDataStandIn(V, np.array([4, 0, 1, 2, 3, 3, 4, 5, 6]))
    with pytest.raises(ValueError, match=r"triangles only, got 1 of 2 faces with \[4\] vertices"):
        as_mesh_arrays(quad, "source")
    with pytest.raises(ValueError, match="triangulate"):
        as_mesh_arrays(quad, "source")
    strips = PolyDataStandIn(V, _padded(F), n_strips=2)
    with pytest.raises(ValueError, match="triangle strips"):
        as_mesh_arrays(strips, "source")
    broken = PolyDataStandIn(V, np.array([3, 0, 1]))
    with pytest.raises(ValueError, match="not a padded cell array"):
        as_mesh_arrays(broken, "source")


def test_what_is_not_a_mesh_is_refused_naming_the_kinds():
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(V))
    for value in (cloud, V, "mesh.ply", {"vertices": V, "faces": F}, 3):
        with pytest.raises(TypeError, match=r"`target` must be .*trimesh\.Trimesh.*pyvista"):
            as_mesh_arrays(value, "target")
    with pytest.raises(ValueError, match="must hold triangle cells, got line"):
        as_mesh_arrays(SimpleNamespace(points=V, cells_dict={"line": F[:, :2]}), "target")
    with pytest.raises(ValueError, match=r"\(vertices, faces\) pair, got 3 items"):
        as_mesh_arrays((V, F, F), "target")
    with pytest.raises(ValueError, match="`target.vertices` must hold at least one point"):
        as_mesh_arrays(o3d.t.geometry.TriangleMesh(), "target")


@pytest.mark.parametrize("kind", list(_meshes()))
def test_build_shape_model_takes_the_template_as_any_mesh_kind(kind):
    # The template given as faces, in any kind the registration takes: the same model as with
    # its triangle array, and the template untouched.
    rng = np.random.default_rng(0)
    shapes = V[None] + 0.05 * rng.standard_normal((4, *V.shape))
    mesh = _meshes()[kind]
    before = _arrays_of(mesh)
    model = build_shape_model(shapes, mesh)
    reference = build_shape_model(shapes, F)
    np.testing.assert_array_equal(np.asarray(model.mesh().triangles), F)
    np.testing.assert_array_equal(model.mean, reference.mean)
    np.testing.assert_array_equal(model.variances, reference.variances)
    after = _arrays_of(mesh)
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1], before[1])


def test_build_shape_model_refuses_a_template_of_another_size():
    # Three shapes that differ (translated copies are one shape: a model of no variance).
    shapes = np.stack([V, V * (1.0, 1.1, 1.0), V * (1.0, 1.0, 0.9)])
    other = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).subdivide_midpoint(1)
    with pytest.raises(ValueError, match=r"`faces` as a mesh .* \(8\), got 26"):
        build_shape_model(shapes, other)
    # A list of triangles stays a list of triangles (two of them is not a (V, F) pair).
    model = build_shape_model(shapes, F[:2].tolist())
    np.testing.assert_array_equal(np.asarray(model.mesh().triangles), F[:2])


@pytest.mark.parametrize("kind", list(_meshes()))
def test_default_levels_take_the_template_as_any_mesh_kind(kind):
    from o3dreg import default_levels

    # The levels depend on the template's vertices only, whatever kind holds them: the 1 x 2 x 3
    # box's second extent spans 8.9 cells of the 16-cell level, so no fifth level.
    expected = [lev.resolution for lev in default_levels(V)]
    assert expected == [2, 4, 8, 16]
    assert [lev.resolution for lev in default_levels(_meshes()[kind])] == expected


def test_points_of_ragged_rows_are_refused_by_name():
    from o3dreg._validation import as_points

    with pytest.raises(ValueError, match=r"`points` must be an \(n, 3\) array.*rows differ"):
        as_points([[0.0, 1.0, 2.0], [0.0, 1.0]], "points")
