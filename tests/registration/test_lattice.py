"""Trilinear lattices: the analytic truths of eq. (1)."""

import numpy as np
import pytest
from _helpers import point_jacobian

from o3dreg import LatticeDeformation, TrilinearLattice


def random_lattice(shape=(3, 4, 2), seed=0, origin=(-1.0, 2.0, 0.5), size=(6.0, 8.0, 3.0)):
    rng = np.random.default_rng(seed)
    lat = TrilinearLattice.zeros(origin, size, shape)
    return lat.with_displacements(rng.normal(size=lat.displacements.shape))


def points_in(lat, n=500, seed=1, margin=0.0):
    rng = np.random.default_rng(seed)
    return lat.origin - margin + rng.uniform(size=(n, 3)) * (lat.size + 2 * margin)


def test_weights_are_a_partition_of_unity():
    lat = random_lattice()
    _, w = lat.weights(points_in(lat, margin=1.0))
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-14)


def test_identity_lattice_is_identity():
    lat = TrilinearLattice.zeros((0, 0, 0), (1, 1, 1), (4, 4, 4))
    pts = points_in(lat, margin=0.5)
    np.testing.assert_array_equal(LatticeDeformation((lat,)).transform(pts), pts)


def test_nodes_are_interpolated_exactly():
    lat = random_lattice()
    nodes = lat.node_positions()
    np.testing.assert_allclose(
        lat.displacement(nodes), lat.displacements.reshape(-1, 3), atol=1e-12
    )


def test_cell_map_is_the_trilinear_polynomial_of_eq1():
    # One cell: T(q) = P [1, x, y, z, xy, yz, zx, xyz]^T for some 3x8 matrix P; recover P from
    # the corners and check it predicts interior points.
    lat = random_lattice(shape=(1, 1, 1), origin=(0, 0, 0), size=(1, 1, 1))
    defo = LatticeDeformation((lat,))

    def basis(p):
        x, y, z = p.T
        return np.stack([np.ones_like(x), x, y, z, x * y, y * z, z * x, x * y * z], axis=1)

    corners = lat.node_positions()
    coeffs, *_ = np.linalg.lstsq(basis(corners), defo.transform(corners), rcond=None)
    inner = points_in(lat, seed=3)
    np.testing.assert_allclose(basis(inner) @ coeffs, defo.transform(inner), atol=1e-12)


def test_affine_displacement_is_reproduced_exactly():
    # Trilinear interpolation reproduces any affine field exactly.
    lat = TrilinearLattice.zeros((0, 0, 0), (2, 3, 4), (2, 3, 5))
    a = np.array([[0.1, -0.2, 0.05], [0.0, 0.3, 0.1], [-0.1, 0.02, 0.2]])
    b = np.array([0.5, -1.0, 2.0])
    lat = lat.with_displacements(lat.node_positions() @ a.T + b)
    pts = points_in(lat)
    np.testing.assert_allclose(lat.displacement(pts), pts @ a.T + b, atol=1e-12)


def test_field_is_continuous_across_cell_faces():
    lat = random_lattice(shape=(4, 4, 4), origin=(0, 0, 0), size=(4, 4, 4))
    rng = np.random.default_rng(5)
    for axis in range(3):
        pts = rng.uniform(0.0, 4.0, size=(200, 3))
        pts[:, axis] = rng.integers(1, 4, size=200).astype(float)  # on interior faces
        eps = np.zeros(3)
        eps[axis] = 1e-9
        jump = lat.displacement(pts + eps) - lat.displacement(pts - eps)
        # A jump would be O(1); continuity leaves O(eps * gradient).
        assert np.abs(jump).max() < 1e-7


def test_displacement_gradient_matches_finite_differences():
    lat = random_lattice()
    pts = points_in(lat, n=100)
    fd = point_jacobian(lat.displacement, pts)
    # Central differences of a polynomial of degree 1 per axis are exact up to rounding.
    np.testing.assert_allclose(lat.displacement_gradient(pts), fd, atol=1e-6)


def test_the_field_is_the_trilinear_basis_summed():
    # The field and its gradient against the basis (``basis``: nodes, weights and their
    # derivatives) summed by hand, inside the box, on its faces and outside it (clamped).
    lat = random_lattice(shape=(3, 4, 2))
    pts = points_in(lat, n=400, margin=1.5)
    pts[:20] = lat.node_positions()[:20]  # exactly on nodes and faces
    nodes, w, grads = lat.basis(pts)
    d = lat.displacements.reshape(-1, 3)[nodes]  # (n, 8, 3)
    # Rounding of 8 products of O(1) numbers.
    np.testing.assert_allclose(lat.displacement(pts), (w[:, :, None] * d).sum(1), atol=1e-13)
    expected = (d[:, :, :, None] * grads[:, :, None, :]).sum(1)
    np.testing.assert_allclose(lat.displacement_gradient(pts), expected, atol=1e-13)


def test_the_field_adds_to_out_and_refuses_what_it_cannot_place():
    lat = random_lattice()
    pts = points_in(lat, n=50)
    out = np.ones((50, 3))
    assert lat.displacement(pts, out=out) is out
    np.testing.assert_array_equal(out, 1.0 + lat.displacement(pts))
    with pytest.raises(ValueError, match="out"):
        lat.displacement_gradient(pts, out=np.zeros((50, 3)))
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        lat.displacement(bad)


def test_outside_the_box_is_clamped():
    lat = random_lattice()
    inside = lat.origin + lat.size * np.array([0.3, 1.0, 0.6])
    outside = inside + np.array([0.0, 5.0, 0.0])
    np.testing.assert_allclose(lat.displacement(outside[None]), lat.displacement(inside[None]))
    assert np.all(lat.displacement_gradient(outside[None])[0][:, 1] == 0.0)


def test_refinement_keeps_the_map():
    lat = random_lattice()
    fine = lat.refined((6, 8, 6))
    pts = points_in(lat, margin=0.7)
    np.testing.assert_allclose(fine.displacement(pts), lat.displacement(pts), atol=1e-12)


def test_refinement_requires_multiples():
    with pytest.raises(ValueError, match="multiples"):
        random_lattice().refined((4, 4, 4))


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match="shape"):
        TrilinearLattice.zeros((0, 0, 0), (1, 1, 1), (0, 2, 2))
    lat = random_lattice()
    with pytest.raises(ValueError, match="displacements"):
        TrilinearLattice(lat.origin, lat.size, lat.shape, np.zeros((2, 2, 2, 3)))


def test_a_lattice_holds_only_finite_boxes_and_fields():
    lat = random_lattice()
    d = np.array(lat.displacements)
    with pytest.raises(ValueError, match="`shape` must be 3 positive integer cell counts"):
        TrilinearLattice.zeros((0, 0, 0), (1, 1, 1), (2.7, 2, 2))  # not truncated to 2
    with pytest.raises(ValueError, match="`shape` must be 3 positive integer"):
        lat.refined(4.5)
    with pytest.raises(ValueError, match="`origin` must be 3 finite coordinates"):
        TrilinearLattice((0.0, np.nan, 0.0), lat.size, lat.shape, d)
    with pytest.raises(ValueError, match="`origin` must be 3 finite coordinates"):
        TrilinearLattice((0.0, 1.0), lat.size, lat.shape, d)
    with pytest.raises(ValueError, match="`size` must be 3 finite positive extents"):
        TrilinearLattice(lat.origin, (1.0, np.nan, 1.0), lat.shape, d)
    d[0, 0, 0, 0] = np.nan
    # A lattice saved with a NaN could not be read back: refused when made.
    with pytest.raises(ValueError, match="`displacements` must be finite"):
        TrilinearLattice(lat.origin, lat.size, lat.shape, d)


def test_a_lattice_owns_its_displacements():
    lat = random_lattice()
    d = np.zeros_like(lat.displacements)
    own = TrilinearLattice(lat.origin, lat.size, lat.shape, d)
    d[...] = 1.0  # the caller's array changes; the lattice's map does not
    assert not own.displacements.any()
    with pytest.raises(ValueError, match="read-only"):
        own.displacements[0, 0, 0, 0] = 1.0


def test_deformation_parameters_are_checked():
    lat = random_lattice()
    deformation = LatticeDeformation((lat,))
    with pytest.raises(ValueError, match="`shape` must be 3 positive integer"):
        deformation.refined((6.9, 8, 4))
    with pytest.raises(ValueError, match="`samples_per_cell` must be at least 2"):
        deformation.min_jacobian_determinant(1)
    with pytest.raises(TypeError, match="`samples_per_cell` must be an integer"):
        deformation.min_jacobian_determinant("a")
