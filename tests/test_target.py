"""The target surface a registration prepares once: canonical order, debris removed, its levels
of detail and its nested subsamples."""

import numpy as np
import open3d as o3d

from o3dreg.registration._target import TargetSurface, canonical_mesh


def sphere(radius: float, resolution: int, centre=(0.0, 0.0, 0.0)):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices) + centre, np.asarray(mesh.triangles)


def test_the_target_is_canonical_and_loses_its_debris():
    big, debris = sphere(10.0, 30), sphere(0.5, 4, centre=(30.0, 0.0, 0.0))
    v = np.concatenate([debris[0], big[0]])
    f = np.concatenate([debris[1], big[1] + len(debris[0])])
    before = v.copy(), f.copy()
    kept = TargetSurface(v, f, min_component=0.05)
    # Exactly the big sphere, in the order canonical_mesh gives it alone.
    expected = canonical_mesh(*big)
    np.testing.assert_array_equal(kept.vertices, expected[0])
    np.testing.assert_array_equal(kept.faces, expected[1])
    everything = TargetSurface(v, f)
    assert everything.vertices.shape[0] == v.shape[0]
    np.testing.assert_array_equal(v, before[0])  # inputs are not modified
    np.testing.assert_array_equal(f, before[1])


def test_subsamples_are_nested_and_drawn_once():
    target = TargetSurface(*sphere(10.0, 60))
    large = target.subsample(2000)
    small = target.subsample(500)
    assert small.shape[0] < large.shape[0] < target.vertices.shape[0]
    # Every point of the smaller subsample is a point of the larger one (drawn from it).
    rows = {tuple(p) for p in large}
    assert all(tuple(p) in rows for p in small)
    assert target.subsample(500) is small


def test_levels_of_detail_only_where_coarser_than_the_target():
    target = TargetSurface(*sphere(10.0, 60))
    edge = target.query.mean_edge
    coarse, fine = 4.0 * edge, 1.0 * edge
    target.build_levels_of_detail([coarse, fine])
    simplified = target.at_detail(coarse)
    assert simplified is not target.query
    assert simplified.vertices.shape[0] < target.vertices.shape[0]
    # A voxel under twice the mean edge gets the full target.
    assert target.at_detail(fine) is target.query
    # The simplified surface stays within about a voxel of the full one.
    assert target.query.distance(simplified.vertices).max() < coarse
