"""The deformation object: a true map of space that can be applied, refined, saved and inspected."""

import numpy as np
import pytest
from _helpers import point_jacobian

from o3dreg import LatticeDeformation, TrilinearLattice


def hierarchy(seed=0, scale=0.05):
    rng = np.random.default_rng(seed)
    levels = []
    for r in (2, 4, 8):
        lat = TrilinearLattice.zeros((-10, -10, -10), (20, 20, 20), (r, r, r))
        levels.append(lat.with_displacements(scale * rng.normal(size=lat.displacements.shape)))
    return LatticeDeformation(tuple(levels))


def sample(n=300, seed=2, lo=-12.0, hi=12.0):
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 3))


def test_empty_deformation_is_identity():
    pts = sample()
    np.testing.assert_array_equal(LatticeDeformation().transform(pts), pts)
    assert LatticeDeformation().min_jacobian_determinant() == 1.0


def test_map_is_the_sum_of_level_displacements():
    d = hierarchy()
    pts = sample()
    expected = pts + sum(lat.displacement(pts) for lat in d.levels)
    np.testing.assert_allclose(d.transform(pts), expected)


def test_refined_single_lattice_is_the_same_map():
    d = hierarchy()
    pts = sample()
    for shape in (None, 16):
        r = d.refined(shape)
        assert len(r.levels) == 1
        np.testing.assert_allclose(r.transform(pts), d.transform(pts), atol=1e-12)
    with pytest.raises(ValueError, match="multiples"):
        d.refined(12)


def test_jacobian_matches_finite_differences():
    d = hierarchy(scale=0.5)
    # Keep away from cell faces, where the one-sided derivatives differ.
    pts = sample(lo=-9.0, hi=9.0)
    fd = point_jacobian(d.transform, pts)
    np.testing.assert_allclose(d.jacobian(pts), fd, atol=1e-6)
    np.testing.assert_allclose(d.jacobian_determinant(pts), np.linalg.det(fd), atol=1e-5)


def test_fold_is_detected():
    lat = TrilinearLattice.zeros((0, 0, 0), (2, 2, 2), (2, 2, 2))
    disp = np.zeros(lat.displacements.shape)
    # Push the centre node 1.5 cells along +x: beyond the next node, the map folds.
    disp[1, 1, 1, 0] = 1.5
    folded = LatticeDeformation((lat.with_displacements(disp),))
    assert folded.min_jacobian_determinant() < 0
    disp[1, 1, 1, 0] = 0.3
    assert LatticeDeformation((lat.with_displacements(disp),)).min_jacobian_determinant() > 0


def test_applies_to_any_points_without_mutating_them():
    d = hierarchy()
    pts = sample()
    before = pts.copy()
    d.transform(pts)
    np.testing.assert_array_equal(pts, before)
    assert d.transform(np.zeros((0, 3))).shape == (0, 3)


def test_save_load_roundtrip(tmp_path):
    d = hierarchy()
    path = tmp_path / "def.npz"
    d.save(path)
    back = LatticeDeformation.load(path)
    pts = sample()
    np.testing.assert_array_equal(back.transform(pts), d.transform(pts))
    assert repr(back) == repr(d)


def test_save_refuses_to_overwrite_and_leaves_nothing_partial(tmp_path):
    d = hierarchy()
    path = tmp_path / "def.npz"
    d.save(path)
    with pytest.raises(OSError, match="exists"):
        d.save(path)
    d.save(path, overwrite=True)
    with pytest.raises(ValueError, match=r"\.npz"):
        d.save(tmp_path / "def.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["def.npz"]


def test_load_bad_files(tmp_path):
    with pytest.raises(OSError, match="no such file"):
        LatticeDeformation.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a complete .npz archive"):
        LatticeDeformation.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(ValueError, match="does not hold"):
        LatticeDeformation.load(other)


def test_levels_must_share_the_box():
    a = TrilinearLattice.zeros((0, 0, 0), (1, 1, 1), (2, 2, 2))
    b = TrilinearLattice.zeros((0, 0, 0), (2, 2, 2), (4, 4, 4))
    with pytest.raises(ValueError, match="same box"):
        LatticeDeformation((a, b))
    with pytest.raises(TypeError, match="TrilinearLattice"):
        LatticeDeformation(("x",))  # type: ignore[arg-type]


def test_points_are_validated():
    with pytest.raises(ValueError, match=r"`points` must have shape \(n, 3\)"):
        hierarchy().transform(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="finite"):
        hierarchy().transform(np.array([[np.nan, 0.0, 0.0]]))


def a_frame(seed=5):
    """A rigid transformation: a rotation about an oblique axis, and a shift."""
    from scipy.spatial.transform import Rotation

    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_rotvec(np.array([0.3, -0.5, 0.8]) * 0.9).as_matrix()
    frame[:3, 3] = np.random.default_rng(seed).normal(scale=5.0, size=3)
    return frame


def test_a_framed_deformation_is_the_axis_one_conjugated_by_its_frame():
    # T(y) = F(T0(F^-1 y)) for the rigid frame F and the same lattices along the axes, T0.
    d, frame = hierarchy(scale=0.5), a_frame()
    framed = d.in_frame(frame)
    pts = sample()
    inverse = np.linalg.inv(frame)
    local = pts @ inverse[:3, :3].T + inverse[:3, 3]
    expected = d.transform(local) @ frame[:3, :3].T + frame[:3, 3]
    np.testing.assert_allclose(framed.transform(pts), expected, atol=1e-12)
    np.testing.assert_array_equal(framed.frame, frame)
    assert repr(framed).endswith("frame=turned 51 deg)")  # |rotation vector| 0.891 rad
    assert "frame" not in repr(d)
    assert d.frame is None and framed.in_frame(None).frame is None
    assert LatticeDeformation(d.levels, np.eye(4)).frame is None  # the identity is no frame
    # The determinant does not depend on the frame; refining and adding levels keep it.
    assert framed.min_jacobian_determinant() == d.min_jacobian_determinant()
    np.testing.assert_array_equal(framed.refined().frame, frame)
    np.testing.assert_allclose(framed.refined().transform(pts), framed.transform(pts), atol=1e-12)
    np.testing.assert_array_equal(framed.with_level(d.levels[0]).frame, frame)


def test_a_framed_jacobian_matches_finite_differences():
    framed = hierarchy(scale=0.5).in_frame(a_frame())
    # Points well inside the box in lattice coordinates (away from the clamped outside).
    local = sample(lo=-8.0, hi=8.0)
    frame = framed.frame
    pts = local @ frame[:3, :3].T + frame[:3, 3]
    np.testing.assert_allclose(
        framed.jacobian(pts), point_jacobian(framed.transform, pts), atol=1e-6
    )


def test_the_frame_is_saved_and_old_files_have_none(tmp_path):
    framed = hierarchy().in_frame(a_frame())
    path = tmp_path / "framed.npz"
    framed.save(path)
    back = LatticeDeformation.load(path)
    np.testing.assert_array_equal(back.frame, framed.frame)
    pts = sample()
    np.testing.assert_array_equal(back.transform(pts), framed.transform(pts))
    # A version 1 file (before frames): lattices along the axes.
    with np.load(path) as data:
        old = {k: data[k] for k in data.files if k != "frame"}
    old["version"] = np.array(1)
    np.savez(tmp_path / "old.npz", **old)
    back = LatticeDeformation.load(tmp_path / "old.npz")
    assert back.frame is None
    np.testing.assert_array_equal(back.transform(pts), hierarchy().transform(pts))


def test_a_frame_must_be_rigid():
    d = hierarchy()
    with pytest.raises(ValueError, match=r"`frame` must be a finite \(4, 4\)"):
        d.in_frame(np.eye(3))
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="`frame` must be a rigid transformation"):
        d.in_frame(scaled)
    mirrored = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="`frame` must be a rigid transformation"):
        d.in_frame(mirrored)


def test_inverse_transform_undoes_the_map():
    d = hierarchy(scale=0.3)
    assert d.min_jacobian_determinant() > 0
    pts = sample(lo=-11.0, hi=11.0)  # inside the box and around it
    images = d.transform(pts)
    before = images.copy()
    back = d.inverse_transform(images)
    np.testing.assert_allclose(back, pts, atol=1e-8)
    np.testing.assert_array_equal(images, before)
    np.testing.assert_allclose(d.transform(back), images, atol=1e-8)
    framed = LatticeDeformation(d.levels, _rigid_frame())
    np.testing.assert_allclose(framed.inverse_transform(framed.transform(pts)), pts, atol=1e-8)


def test_inverse_transform_of_the_identity_and_of_no_points():
    pts = sample()
    np.testing.assert_array_equal(LatticeDeformation().inverse_transform(pts), pts)
    assert hierarchy().inverse_transform(np.zeros((0, 3))).shape == (0, 3)


def test_inverse_transform_says_when_it_did_not_converge():
    d = hierarchy(scale=0.3)
    with pytest.raises(ValueError, match="no inverse image within 0 Newton steps"):
        d.inverse_transform(d.transform(sample()), max_iterations=0)
    with pytest.raises(TypeError, match="max_iterations"):
        d.inverse_transform(sample(), max_iterations=2.5)
    with pytest.raises(ValueError, match="max_iterations"):
        d.inverse_transform(sample(), max_iterations=-1)
    with pytest.raises(ValueError, match="points"):
        d.inverse_transform(np.zeros((3, 2)))


def _rigid_frame():
    angle = 0.4
    frame = np.eye(4)
    frame[:3, :3] = [
        [np.cos(angle), -np.sin(angle), 0.0],
        [np.sin(angle), np.cos(angle), 0.0],
        [0.0, 0.0, 1.0],
    ]
    frame[:3, 3] = (1.0, -2.0, 0.5)
    return frame
