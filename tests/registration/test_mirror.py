"""The mirror check of the rigid search: a target that is the template's other side (left and
right swapped) is warned about, a bilaterally symmetric bone is not."""

import numpy as np
import pytest
from _helpers import FAST, ct_mandible, ct_mandible_masks, mesh_of, warped_blob

from o3dreg import registration_elastic, registration_rigid
from o3dreg._geometry import apply_transformation
from o3dreg.registration.rigid import (
    MIRROR_RATIO,
    RigidRegistrationResult,
    _candidates,
    _mirror_starts,
    mirror_warnings,
    surface_moments,
)


def mirrored(vertices, faces, axis=0):
    """The surface reflected through its centroid across a coordinate plane, its triangles
    rewound so that it stays outward-facing."""
    v = np.array(vertices, dtype=float)
    v[:, axis] = 2.0 * v[:, axis].mean() - v[:, axis]
    return v, np.asarray(faces)[:, ::-1].copy()


def test_the_mirror_starts_are_the_improper_moment_frames(bunny_template, bunny_target):
    source = surface_moments(
        np.asarray(bunny_template.vertices), np.asarray(bunny_template.triangles)
    )
    target = surface_moments(np.asarray(bunny_target.vertices), np.asarray(bunny_target.triangles))
    starts = _mirror_starts(source, _candidates(source, target, False))
    assert len(starts) == 4
    (_, cs, covs), (_, ct, covt) = source, target
    es, et = np.linalg.eigh(covs)[1], np.linalg.eigh(covt)[1]
    signs = []
    for name, t in starts:
        assert name.startswith("mirror image, moment frame")
        rot = t[:3, :3]
        # A reflection: orthogonal with determinant -1 (to rounding).
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(-1.0, abs=1e-12)
        # The source's centroid onto the target's, each principal axis onto the target's same
        # one (either sign).
        np.testing.assert_allclose(apply_transformation(t, cs[None])[0], ct, atol=1e-9)
        axes = et.T @ rot @ es
        np.testing.assert_allclose(np.abs(axes), np.eye(3), atol=1e-9)
        signs.append(tuple(np.sign(np.diag(axes)).astype(int)))
    # The four improper choices of axis signs, each once.
    assert len(set(signs)) == 4 and all(np.prod(s) == -1 for s in signs)


def test_the_mirror_warning_speaks_only_beyond_the_ratio():
    result = RigidRegistrationResult(score=2.0)
    assert mirror_warnings(result) == ()  # the mirror image was not refined
    result.mirror_score = 2.0 / MIRROR_RATIO
    assert not result.mirrored and mirror_warnings(result) == ()
    result.mirror_score = 1.0
    (text,) = mirror_warnings(result)
    assert "left and right swapped" in text and "2 times better" in text


def test_the_bunny_mirrored_is_warned_about_and_the_bunny_is_not(bunny_template, bunny_target):
    vt, ft = np.asarray(bunny_target.vertices), np.asarray(bunny_target.triangles)
    proper = registration_rigid(bunny_template, (vt, ft))
    assert not proper.mirrored
    assert not any("mirror image" in w for w in proper.warnings)
    other = registration_rigid(bunny_template, mirrored(vt, ft))
    # The bunny is chiral: its mirror image fits the mirrored bunny (to the decimation's
    # ~1e-4 of its size) tens of times better than any turn of the bunny itself.
    assert other.mirrored
    assert other.score > 10 * other.mirror_score
    assert any("left and right swapped" in w for w in other.warnings)


def test_a_mirrored_target_makes_the_registration_suspect():
    template, (vt, ft), _ = warped_blob()
    right = registration_elastic(template, (vt, ft), levels=FAST)
    assert right.rigid_start.mirror_score is None
    assert not any("mirror image" in w for w in right.warnings)
    wrong = registration_elastic(template, mirrored(vt, ft, axis=2), levels=FAST)
    # The levels wrap the template onto the mirror image as closely as onto the right side;
    # only the rigid search tells the two apart (the blob's mirror image fits 1.7 times better).
    assert wrong.status == "suspect"
    assert wrong.rigid_start.score > MIRROR_RATIO * wrong.rigid_start.mirror_score
    assert any("left and right swapped" in w for w in wrong.warnings)


def test_a_mandible_mirrored_left_to_right_is_no_mirror(shared_data):
    # A mandible is bilaterally symmetric: its mirror image is itself, to the patient's
    # asymmetry, and fits no better (0.93-1.01 of the template's score on three pairs).
    masks = ct_mandible_masks(shared_data)
    template = ct_mandible(masks[0], 3000)
    target = ct_mandible(masks[1])
    vt, ft = np.asarray(target.vertices), np.asarray(target.triangles)
    for surface in ((vt, ft), mirrored(vt, ft, axis=0)):
        result = registration_rigid(template, mesh_of(*surface))
        assert not result.mirrored, result


def test_a_mirrored_partial_target_is_warned_about(bunny_template, bunny_target):
    # The bunny without its top 40% (a partial scan): its moment frames are not the template's,
    # yet the mirror image, refined, still fits the mirrored part 1.9 times better.
    vt, ft = np.asarray(bunny_target.vertices), np.asarray(bunny_target.triangles)
    keep = (vt[ft][:, :, 1] < vt[:, 1].max() - 0.4 * np.ptp(vt[:, 1])).all(axis=1)
    assert not registration_rigid(bunny_template, (vt, ft[keep])).mirrored
    other = registration_rigid(bunny_template, mirrored(vt, ft[keep]))
    assert other.mirrored
