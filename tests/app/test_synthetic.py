"""The paper's synthetic forms: vertex counts, closed and outward-oriented, analytic volumes."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers import signed_volume

from o3dreg.app.synthetic import FORMS, asymmetric_blob, synthetic_form

#: Analytic volumes (mm^3) of the shapes whose signed distance functions are sampled.
VOLUMES = {
    "sphere": 4.0 / 3.0 * np.pi * 40.0**3,
    "cube": 70.0**3,
    "open_ring": np.pi * (45.0**2 - 20.0**2) * 24.0,
    "cone": np.pi * 40.0**2 * 80.0 / 3.0,
}
#: Euler characteristic 2 - 2g: the ring has genus 1.
EULER = {"sphere": 2, "cube": 2, "open_ring": 0, "cone": 2}


# A polyhedron whose vertices lie on a convex surface holds less volume than it; the shortfall
# shrinks like (edge / radius)^2: measured -1.9% (ring) at 1000 vertices, -0.4% at 3000 and
# -0.2% at 10000. The tolerances leave 1.5x margin over those.
@pytest.mark.parametrize(("number_of_vertices", "tolerance"), [(1000, 0.03), (3000, 0.0075)])
@pytest.mark.parametrize("name", FORMS)
def test_form_is_closed_with_analytic_volume(name, number_of_vertices, tolerance):
    mesh = synthetic_form(name, number_of_vertices)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert abs(len(vertices) - number_of_vertices) <= 0.03 * number_of_vertices
    # Closed: every edge shared by exactly two triangles, every vertex a single fan.
    assert mesh.is_edge_manifold(allow_boundary_edges=False)
    assert mesh.is_vertex_manifold()
    assert mesh.is_orientable()
    assert mesh.euler_poincare_characteristic() == EULER[name]
    # Positive signed volume: triangles are oriented with outward normals.
    volume = signed_volume((vertices, faces))
    assert volume > 0
    assert volume == pytest.approx(VOLUMES[name], rel=tolerance)


def test_forms_are_about_90_mm_wide_and_centred():
    for name in FORMS:
        vertices = np.asarray(synthetic_form(name, 1000).vertices)
        extent = np.ptp(vertices, axis=0)
        assert 45.0 < extent.max() < 95.0, name
        # 4 mm: marching cubes and decimation blunt the cone's apex (z = 34 instead of 40 at
        # 1000 vertices), which moves its box centre down by 3 mm.
        assert np.allclose((vertices.max(axis=0) + vertices.min(axis=0)) / 2.0, 0.0, atol=4.0)


def test_synthetic_form_rejects_bad_input():
    with pytest.raises(ValueError, match="`name` must be one of"):
        synthetic_form("torus", 1000)
    with pytest.raises(ValueError, match="`number_of_vertices` must be >= 100"):
        synthetic_form("sphere", 50)


def test_the_asymmetric_blob_is_closed_outward_and_has_no_symmetry():
    from o3dreg.registration.distance import SurfaceDistanceQuery
    from o3dreg.registration.rigid import surface_moments

    mesh = asymmetric_blob(1.5)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_vertex_manifold()
    assert mesh.euler_poincare_characteristic() == 2  # a sphere's topology, the handle joined
    assert signed_volume((vertices, faces)) > 0  # outward
    assert 75 < np.ptp(vertices, axis=0).max() < 90
    # No symmetry: turned half a turn about any of its principal axes (the turns a shape with
    # a symmetry would map onto itself), or mirrored across their planes, a part of it lies
    # centimetres off itself (the 1.5 mm voxel's facets alone leave a fraction of a millimetre).
    _, centre, covariance = surface_moments(vertices, faces)
    query = SurfaceDistanceQuery(vertices, faces)
    for axis in np.linalg.eigh(covariance)[1].T:
        half_turn = 2 * np.outer(axis, axis) - np.eye(3)
        for motion in (half_turn, np.eye(3) - 2 * np.outer(axis, axis)):
            moved = (vertices - centre) @ motion.T + centre
            assert query.distance(moved).max() > 10.0, (axis, motion)
