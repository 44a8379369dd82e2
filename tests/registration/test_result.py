"""The result of an elastic registration: a few grouped fields, the flat names still readable."""

import dataclasses

import numpy as np
import open3d as o3d
import pytest
from _helpers import FAST

from o3dreg import (
    ElasticRegistrationResult,
    MapQuality,
    PartitionedDeformation,
    RegistrationVerdict,
    registration_elastic,
)


@pytest.fixture(scope="module")
def two_parts():
    # Two separate spheres: parts='connected' gives a partitioned deformation.
    a = o3d.geometry.TriangleMesh.create_sphere(radius=5.0, resolution=8)
    b = o3d.geometry.TriangleMesh.create_sphere(radius=5.0, resolution=8).translate((20.0, 0, 0))
    source = a + b
    target = o3d.geometry.TriangleMesh(source).scale(1.05, center=source.get_center())
    return registration_elastic(source, target, init=np.eye(4), levels=FAST[:2], parts="connected")


def test_a_few_grouped_fields(two_parts):
    names = [f.name for f in dataclasses.fields(ElasticRegistrationResult)]
    assert len(names) <= 10
    assert isinstance(two_parts.quality, MapQuality)
    assert isinstance(two_parts.verdict, RegistrationVerdict)
    assert two_parts.history is two_parts.levels
    assert two_parts.status == two_parts.verdict.status
    assert two_parts.min_jacobian_determinant == two_parts.quality.min_jacobian_determinant
    assert two_parts.supported is two_parts.quality.supported


def test_the_deformation_holds_its_parts(two_parts):
    d = two_parts.deformation
    assert isinstance(d, PartitionedDeformation)
    assert two_parts.part_deformations == d.parts and len(d.parts) == 2
    np.testing.assert_array_equal(two_parts.part_labels, d.labels)
    np.testing.assert_array_equal(two_parts.part_sites, d.sites)


def test_flat_names_are_read_only_and_replace_takes_them(two_parts):
    with pytest.raises(AttributeError):
        two_parts.status = "failed"  # type: ignore[misc]
    changed = dataclasses.replace(two_parts, status="suspect", flipped_triangles=3)
    assert changed.verdict.status == "suspect" and changed.quality.flipped_triangles == 3
    assert changed.min_cell_jacobian_determinant == two_parts.min_cell_jacobian_determinant
    assert two_parts.status != "suspect" or two_parts.flipped_triangles != 3
    with pytest.raises(TypeError, match="unexpected"):
        dataclasses.replace(two_parts, colour="red")


def test_inverse_transform_maps_target_points_back_to_the_source(two_parts):
    # Points around both parts (the partitioned map) and a similarity start.
    rng = np.random.default_rng(3)
    source = rng.uniform(-6.0, 6.0, (200, 3)) + rng.integers(0, 2, (200, 1)) * [20.0, 0.0, 0.0]
    scaled = dataclasses.replace(two_parts, transformation=np.diag([1.1, 1.1, 1.1, 1.0]))
    for result in (two_parts, scaled):
        back = result.inverse_transform(result.transform(source))
        np.testing.assert_allclose(back, source, atol=1e-7)


def test_a_part_without_target_is_named_in_the_message():
    # Two spheres onto one: the second has no target point near it, no level runs for it and it
    # keeps the start's pose; the message says so rather than "all levels converged" alone.
    a = o3d.geometry.TriangleMesh.create_sphere(radius=5.0, resolution=10)
    b = o3d.geometry.TriangleMesh.create_sphere(radius=5.0, resolution=10).translate((14, 0, 0))
    target = o3d.geometry.TriangleMesh.create_sphere(radius=5.5, resolution=30)
    result = registration_elastic(a + b, target, init=np.eye(4), levels=FAST[:2], parts="connected")
    assert "part(s) [1] have no target near them" in result.message
    moved = result.vertices[len(a.vertices) :]
    np.testing.assert_array_equal(moved, np.asarray(b.vertices))
    assert not result.supported[len(a.vertices) :].any()
