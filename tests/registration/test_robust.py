"""Robust registration on imperfect targets (issue 6): partial targets, outliers, folding,
vertex-order independence, and the new options' validation."""

from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest
from _helpers import FAST, ct_mandible, ct_mandible_masks, warped_blob
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import o3dreg
from o3dreg import (
    DistanceEstimation,
    ElasticLevel,
    LatticeDeformation,
    PartitionedDeformation,
    default_levels,
    evaluate_elastic,
    load_deformation,
    registration_elastic,
)
from o3dreg._geometry import apply_transformation, barycentric
from o3dreg.app.synthetic import SmoothWarp, synthetic_form
from o3dreg.mesh.canonical import canonical_mesh
from o3dreg.registration.distance import BEYOND_BOUNDARY_TOLERANCE, SurfaceDistanceQuery
from o3dreg.registration.elastic import flipped_triangles
from o3dreg.registration.losses import loss_named


def arrays(mesh):
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()


@pytest.fixture(scope="module")
def bunny_warped(bunny_template, bunny_target):
    v, f = arrays(bunny_target)
    warp = SmoothWarp.random(v, magnitude=0.05, seed=1)
    return arrays(bunny_template), (warp(v), f), warp


def cut_top(mesh, fraction):
    v, f = mesh
    lo, hi = v[:, 1].min(), v[:, 1].max()
    cut = hi - fraction * (hi - lo)
    return (v, f[v[f].mean(axis=1)[:, 1] <= cut]), cut


def test_boundary_detection_on_a_square():
    # A unit square of two triangles: a point above its middle is inside, one beside it is beyond
    # the open boundary, one just over the rim (less than a tenth of the mean edge) is not.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    q = SurfaceDistanceQuery(v, f)
    # A point 0.2 past the rim is beyond it (a fifth of an edge: the tolerance only absorbs
    # rounding, or it would pull such points onto the rim).
    pts = np.array(
        [[0.5, 0.5, 0.3], [2.0, 0.5, 0.0], [1.1, 0.5, 0.2], [-1.0, -1.0, 0.0], [1.2, 0.5, 0.0]]
    )
    _, face, closest = q.closest(pts)
    np.testing.assert_array_equal(
        q.beyond_boundary(pts, face, closest), [False, True, False, True, True]
    )
    # closest_with_data: the same closest points, and data where not beyond.
    dist, face2, closest2, with_data = q.closest_with_data(pts)
    np.testing.assert_array_equal(face2, face)
    np.testing.assert_array_equal(closest2, closest)
    np.testing.assert_allclose(dist[0], 0.3)
    np.testing.assert_array_equal(with_data, [True, False, True, False, False])
    assert q.has_boundary
    closed = SurfaceDistanceQuery(*arrays(synthetic_form("sphere", 300)))
    assert not closed.has_boundary
    assert closed.closest_with_data(pts)[3].all()


def beyond_by_numpy(q, points, face, closest):
    """The boundary test of ``SurfaceDistanceQuery.beyond_boundary`` written for every point
    (the query looks only at triangles touching the boundary)."""
    open_edge, on_boundary = q.open_edges
    corners = q.faces[face]
    bary = barycentric(q.vertices[corners], closest)
    tiny = bary <= 1e-9
    hit = (tiny & open_edge[face]).any(axis=1)
    vertex_hit = tiny.sum(axis=1) >= 2
    corner = np.argmax(bary, axis=1)
    hit |= vertex_hit & on_boundary[corners[np.arange(len(face)), corner]]
    diff = points - closest
    n = q.face_normal(face)
    tangent = diff - (diff * n).sum(axis=1, keepdims=True) * n
    return hit & (np.linalg.norm(tangent, axis=1) > BEYOND_BOUNDARY_TOLERANCE * q.mean_edge)


def test_boundary_test_only_looks_at_triangles_touching_the_boundary(bunny_target):
    # The cut bunny: points around it, far and near. Only closest points on triangles with an
    # open edge or corner are tested; the answer must be that of testing every point.
    (v, f), _ = cut_top(arrays(bunny_target), 0.3)
    q = SurfaceDistanceQuery(v, f)
    rng = np.random.default_rng(0)
    pts = v[rng.choice(len(v), 3000)] + rng.normal(scale=5.0, size=(3000, 3))
    # Points on boundary vertices, and beside them (their closest points at a corner).
    rim = np.flatnonzero(q.open_edges[1])[:50]
    pts = np.concatenate([pts, v[rim] + [3.0, 0.0, 0.0], v[rim]])
    _, face, closest = q.closest(pts)
    beyond = q.beyond_boundary(pts, face, closest)
    np.testing.assert_array_equal(beyond, beyond_by_numpy(q, pts, face, closest))
    assert 0 < beyond.sum() < len(pts)  # both answers occur
    assert q._touches_boundary.mean() < 0.1  # few triangles are tested at all


@pytest.mark.slow
def test_a_ct_mandible_cut_across_its_rami_is_registered_below_the_cut(shared_data):
    # Real data: PDDCA mandible 0522c0003, a 3,000-vertex template decimated from its surface,
    # the surface under a 5% warp with its top 20% (along z, superior) removed: the condyles,
    # coronoid processes and the top of the rami. The rigid step and the defaults, as
    # benchmarks/bench_robust.py --mandibles. The vertices below the cut measured 1.01x the
    # whole target's error (0.118 against 0.117 mm); pulling the vertices within half an edge
    # past the rim onto it dragged the rami down the surface, 1.56x. 1.5x is the aim for partial
    # targets (docs/robustness.md).
    mesh = ct_mandible(next(f for f in ct_mandible_masks(shared_data) if "0522c0003" in f.name))
    template = o3dreg.decimate(mesh, 3000)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    warp = SmoothWarp.random(v, magnitude=0.05, seed=1)
    wv = warp(v)
    cut = wv[:, 2].max() - 0.2 * np.ptp(wv[:, 2])
    partial = (wv, f[wv[f].mean(axis=1)[:, 2] <= cut])
    truth = warp(np.asarray(template.vertices))
    below = truth[:, 2] <= cut
    err = [
        np.linalg.norm(registration_elastic(template, t).vertices - truth, axis=1)[below].mean()
        for t in ((wv, f), partial)
    ]
    assert err[1] < 1.5 * err[0], err


def test_robust_weights_formulas():
    def weights(name, r, threshold):  # the loss whose k sigma is ``threshold``
        loss = loss_named(name)
        return loss.weight(r, threshold / loss.constant)

    r = np.array([0.0, 0.5, 1.0, 2.0, 4.0])
    np.testing.assert_allclose(weights("huber", r, 1.0), [1, 1, 1, 0.5, 0.25])
    np.testing.assert_allclose(weights("cauchy", r, 1.0), 1 / (1 + r**2))
    np.testing.assert_allclose(weights("tukey", r, 2.0), [1, (1 - 1 / 16) ** 2, 0.5625, 0, 0])
    np.testing.assert_array_equal(weights("linear", r, 1.0), 1.0)


def test_partial_target_leaves_the_unsupported_part_alone(bunny_warped):
    template, target, warp = bunny_warped
    truth = warp(template[0])
    partial, cut = cut_top(target, 0.25)
    full = registration_elastic(template, target, init=np.eye(4), levels=FAST)
    part = registration_elastic(template, partial, init=np.eye(4), levels=FAST)
    no_reject = registration_elastic(
        template,
        partial,
        init=np.eye(4),
        levels=FAST,
        estimation_method=DistanceEstimation(reject_boundary=False),
    )
    below = truth[:, 1] <= cut - 5.0  # a 5 mm margin: the rim itself is ambiguous
    above = truth[:, 1] > cut + 5.0
    err = lambda r: np.linalg.norm(r.vertices - truth, axis=1)  # noqa: E731
    # The supported part is registered about as well as with the full target (issue: 1.5x).
    assert err(part)[below].mean() < 1.5 * err(full)[below].mean()
    # Above the cut the template keeps the smooth motion of its neighbours instead of being
    # dragged down onto the rim: measured 3.8 mm against 18.3 mm without the rejection (the warp
    # moves points by up to 12 mm here).
    assert err(part)[above].mean() < 0.7 * err(no_reject)[above].mean()
    # Supported flags: the vertices far above the cut are flagged, those far below are not.
    assert part.supported is not None and part.supported.shape == (template[0].shape[0],)
    assert part.supported[below].mean() > 0.97
    assert (~part.supported[above]).mean() > 0.9
    assert full.supported.mean() > 0.97
    # Exported as vertex colours: red where unsupported.
    colours = np.asarray(part.semilandmark_mesh().vertex_colors)
    np.testing.assert_array_equal(colours[:, 0] != colours[:, 1], ~part.supported)


def debris(mesh, fraction, seed=0):
    v, f = mesh
    rng = np.random.default_rng(seed)
    lo, hi = v.min(axis=0), v.max(axis=0)
    count = int(fraction * v.shape[0])
    diag = np.linalg.norm(hi - lo)
    centres = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(count, 3))
    corners = centres[:, None, :] + 0.01 * diag * rng.normal(size=(count, 3, 3))
    nv = np.vstack([v, corners.reshape(-1, 3)])
    return nv, np.vstack([f, v.shape[0] + np.arange(3 * count).reshape(-1, 3)])


def test_outliers_with_a_robust_loss(bunny_warped):
    template, target, warp = bunny_warped
    truth = warp(template[0])
    noisy = debris(target, 0.05)
    err = lambda r: np.linalg.norm(r.vertices - truth, axis=1).mean()  # noqa: E731
    clean = registration_elastic(template, target, init=np.eye(4), levels=FAST)
    plain = registration_elastic(
        template, noisy, init=np.eye(4), levels=FAST, estimation_method=DistanceEstimation.paper()
    )
    # The defaults without the island filter (which alone removes this debris): the Cauchy loss
    # and the masks, with one unit of weight per barycentre row.
    robust = registration_elastic(
        template,
        noisy,
        init=np.eye(4),
        levels=FAST,
        estimation_method=DistanceEstimation(
            min_target_component=None, barycentre_weighting="uniform"
        ),
    )
    # 5% debris triangles: the robust options keep the error within 1.5x of the clean case and
    # below the plain least-squares error.
    assert err(robust) < 1.5 * err(clean)
    assert err(robust) < err(plain)
    # With rows weighted by the target points they stand for, debris that the island filter
    # does not remove pulls harder (1.6x the clean error with the barycentre term at full
    # weight on 8 cells): still below plain least squares. That is 0.4% of the diagonal, a
    # right registration: the verdict leaves out the debris islands it did not reach.
    unfiltered = DistanceEstimation(min_target_component=None)
    counted = registration_elastic(
        template, noisy, init=np.eye(4), levels=FAST, estimation_method=unfiltered
    )
    assert err(counted) < err(plain)
    assert err(counted) < 0.005 * np.linalg.norm(np.ptp(target[0], axis=0))
    assert counted.status == "ok", counted.warnings
    # 20% debris: the template grows into the debris it reaches (30 mm, 12% of the diagonal),
    # and the verdict says so.
    wrong = registration_elastic(
        template, debris(target, 0.2), init=np.eye(4), levels=FAST, estimation_method=unfiltered
    )
    assert err(wrong) > 10 * err(clean)
    assert wrong.status != "ok"
    assert any("parts of the target" in w for w in wrong.warnings)
    # The defaults ignore the debris islands: the debris-free registration exactly.
    default = registration_elastic(template, noisy, init=np.eye(4), levels=FAST)
    np.testing.assert_array_equal(default.vertices, clean.vertices)


@pytest.mark.parametrize("loss", ["huber", "cauchy", "tukey"])
def test_robust_losses_do_not_hurt_the_clean_case(bunny_warped, loss):
    template, target, warp = bunny_warped
    truth = warp(template[0])
    clean = registration_elastic(
        template,
        target,
        init=np.eye(4),
        levels=FAST,
        estimation_method=DistanceEstimation(loss="linear"),
    )
    robust = registration_elastic(
        template,
        target,
        init=np.eye(4),
        levels=FAST,
        estimation_method=DistanceEstimation(loss=loss),
    )
    e0 = np.linalg.norm(clean.vertices - truth, axis=1).mean()
    e1 = np.linalg.norm(robust.vertices - truth, axis=1).mean()
    assert e1 < 1.2 * e0


def test_folding_guard_keeps_the_map_one_to_one():
    # The paper's single distance squeezes a cone onto a patch of a sphere: unguarded the map
    # collapses (measured det ~ -4e-6); the guard keeps every sampled determinant above 0.05.
    cone, sphere = synthetic_form("cone", 600), synthetic_form("sphere", 3000)
    method = DistanceEstimation.paper(symmetric=False)
    levels = [ElasticLevel(k, 0.1) for k in (2, 4, 8)]
    guarded = registration_elastic(
        cone, sphere, init=np.eye(4), levels=levels, estimation_method=method
    )
    free = registration_elastic(
        cone,
        sphere,
        init=np.eye(4),
        levels=[ElasticLevel(k, 0.1, min_jacobian_determinant=None) for k in (2, 4, 8)],
        estimation_method=method,
    )
    assert guarded.min_cell_jacobian_determinant > 0.04
    assert guarded.min_jacobian_determinant > 0.04
    assert free.min_cell_jacobian_determinant < guarded.min_cell_jacobian_determinant
    # The reported minimum is the one the fold check reads: never above the cells' (a folded
    # map showed 0.08 in its one-line summary beside a warning of -0.76).
    for result in (guarded, free):
        assert result.min_jacobian_determinant <= result.min_cell_jacobian_determinant
    assert free.min_jacobian_determinant < 0 and "folds space" in " ".join(free.warnings)
    assert guarded.flipped_triangles == 0
    # A level the guard stopped says so (not that the model promised too little).
    stopped = [lev.message for lev in guarded.levels if "folding guard refused" in lev.message]
    assert stopped and all(lev.success for lev in guarded.levels)
    assert not any("folding guard refused" in lev.message for lev in free.levels)


def test_folding_guard_holds_at_the_template_points():
    # A sphere onto the open ring (paper Table 2, single distance): the map is stretched most
    # where the template points are, between the guard's 8 samples of their cells (det is a
    # cubic there). With the points among the samples, no template point lies where it folds.
    sphere, ring = synthetic_form("sphere", 1000), synthetic_form("open_ring", 1000)
    result = registration_elastic(
        sphere,
        ring,
        init=np.eye(4),
        levels=o3dreg.paper_levels(),
        estimation_method=DistanceEstimation.paper(symmetric=False),
    )
    points = result.deformation.jacobian_determinant(
        apply_transformation(result.transformation, np.asarray(sphere.vertices))
    )
    assert points.min() > 0 and result.min_jacobian_determinant > 0
    assert "folds" not in " ".join(result.warnings)


def test_flipped_triangles_counts_reversed_normals():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    moved = v.copy()
    moved[3] = [-0.5, -0.5, 0.0]  # the second triangle turns over
    assert flipped_triangles(v, v, f) == 0
    assert flipped_triangles(v, moved, f) == 1


def test_target_vertex_order_does_not_matter():
    cube, sphere = synthetic_form("cube", 300), synthetic_form("sphere", 2000)
    v, f = arrays(sphere)
    v = v * np.array([1.1, 0.9, 1.0])
    rng = np.random.default_rng(3)
    perm = rng.permutation(v.shape[0])
    inverse = np.argsort(perm)
    pv, pf = v[perm], inverse[f][rng.permutation(f.shape[0])]
    pf = np.roll(pf, 1, axis=1)  # rotate every triangle (orientation kept)
    a = registration_elastic(cube, (v, f), init=np.eye(4), levels=FAST)
    b = registration_elastic(cube, (pv, pf), init=np.eye(4), levels=FAST)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert a.distances == b.distances
    again = registration_elastic(cube, (v, f), init=np.eye(4), levels=FAST)
    np.testing.assert_array_equal(a.vertices, again.vertices)


def test_canonical_mesh_merges_duplicates_and_soups():
    sphere = synthetic_form("sphere", 200)
    v, f = arrays(sphere)
    soup_v = v[f].reshape(-1, 3)  # every triangle with its own 3 vertices (an STL soup)
    soup_f = np.arange(soup_v.shape[0]).reshape(-1, 3)
    cv, cf = canonical_mesh(soup_v, soup_f)
    rv, rf = canonical_mesh(v, f)
    np.testing.assert_array_equal(cv, rv)
    np.testing.assert_array_equal(cf, rf)
    assert not SurfaceDistanceQuery(cv, cf).has_boundary


def test_new_options_validate():
    with pytest.raises(ValueError, match="`loss` must be one of"):
        DistanceEstimation(loss="l1")
    with pytest.raises(ValueError, match="`max_normal_angle` must be in"):
        DistanceEstimation(max_normal_angle=270.0)
    with pytest.raises(ValueError, match="`loss_scale` must be a finite number > 0"):
        DistanceEstimation(loss_scale=0.0)
    with pytest.raises(TypeError, match="`reject_boundary` must be True or False"):
        DistanceEstimation(reject_boundary=1)
    with pytest.raises(ValueError, match="`min_jacobian_determinant` must be in"):
        ElasticLevel(2, min_jacobian_determinant=1.5)
    assert "loss='cauchy'" in repr(DistanceEstimation(loss="cauchy"))


def two_plates(step):
    def plate(z0):
        box = o3d.geometry.TriangleMesh.create_box(40.0, 40.0, 1.0)
        box = box.subdivide_midpoint(int(np.ceil(np.log2(40.0 / step))))
        return box.translate((-20.0, -20.0, z0))

    lower, upper = plate(0.0), plate(5.0)  # 1 mm plates, 4 mm gap
    va, fa = arrays(lower)
    vb, fb = arrays(upper)
    return np.vstack([va, vb]), np.vstack([fa, fb + va.shape[0]]), va.shape[0]


def test_connected_parts_are_registered_separately():
    tv, tf, split = two_plates(4.0)
    dv, df, dsplit = two_plates(2.0)
    dv[:dsplit, 0] -= 3.0
    dv[dsplit:, 0] += 3.0
    truth = tv.copy()
    truth[:split, 0] -= 3.0
    truth[split:, 0] += 3.0
    joint = registration_elastic((tv, tf), (dv, df), init=np.eye(4))
    parts = registration_elastic((tv, tf), (dv, df), init=np.eye(4), parts="connected")
    err = lambda r: np.linalg.norm(r.vertices - truth, axis=1).mean()  # noqa: E731

    def relative_shift(r):
        dx = r.vertices[:, 0] - tv[:, 0]
        return dx[split:].mean() - dx[:split].mean()

    # The plates slide 6 mm relative to each other. An in-plane shift is seen only at the rims,
    # so neither recovers all of it, but one map of space drags the plates together where one
    # hierarchy per plate does not (each plate alone does the same). Both runs are deterministic.
    assert relative_shift(parts) > relative_shift(joint) + 0.3
    # The parts' error is below the joint map's with one unit per barycentre row (1.0 against
    # 2.3 mm). With rows counted (the default) the joint map's error on these two thin plates
    # moves between 1.2 and 2.4 mm with rounding, against 1.7-1.8 mm for the parts: no order
    # between them to assert there.
    uniform = DistanceEstimation(barycentre_weighting="uniform")
    joint_u = registration_elastic((tv, tf), (dv, df), init=np.eye(4), estimation_method=uniform)
    parts_u = registration_elastic(
        (tv, tf), (dv, df), init=np.eye(4), parts="connected", estimation_method=uniform
    )
    assert err(parts_u) < err(joint_u)
    np.testing.assert_array_equal(np.unique(parts.part_labels[:split]), [0])
    np.testing.assert_array_equal(np.unique(parts.part_labels[split:]), [1])
    assert len(parts.part_deformations) == 2
    # transform() routes each point to its part's deformation.
    np.testing.assert_allclose(parts.transform(tv), parts.vertices, atol=1e-9)
    with pytest.raises(ValueError, match="`parts` must be 'joint' or 'connected'"):
        registration_elastic((tv, tf), (dv, df), parts="each")


def test_each_part_is_registered_as_it_would_be_alone():
    # parts='connected' runs the same coarse-to-fine driver on each part as a joint registration
    # of that part alone onto its share of the target (the target vertices whose nearest source
    # vertex is in the part, the triangles whose three corners are): identical results.
    tv, tf, _ = two_plates(4.0)
    dv, df, dsplit = two_plates(2.0)
    dv[:dsplit, 0] -= 3.0
    dv[dsplit:, 0] += 3.0
    parts = registration_elastic((tv, tf), (dv, df), init=np.eye(4), levels=FAST, parts="connected")
    cv, cf = canonical_mesh(dv, df)
    labels = parts.part_labels
    target_labels = labels[cKDTree(tv).query(cv)[1]]
    for part in (0, 1):
        sel = np.flatnonzero(labels == part)
        remap = np.full(tv.shape[0], -1)
        remap[sel] = np.arange(sel.size)
        pf = remap[tf[np.all(labels[tf] == part, axis=1)]]
        part_faces = cf[np.all(target_labels[cf] == part, axis=1)]
        used = np.unique(part_faces)
        tmap = np.full(cv.shape[0], -1)
        tmap[used] = np.arange(used.size)
        alone = registration_elastic(
            (tv[sel], pf), (cv[used], tmap[part_faces]), init=np.eye(4), levels=FAST
        )
        np.testing.assert_array_equal(parts.vertices[sel], alone.vertices)
        assert len(parts.part_deformations[part].levels) == len(alone.deformation.levels) == 3
        for a, b in zip(parts.part_deformations[part].levels, alone.deformation.levels):
            np.testing.assert_array_equal(a.displacements, b.displacements)


def test_small_target_components_can_be_ignored(bunny_template, bunny_target):
    # Debris: 600 tiny disconnected triangles around a lightly warped bunny.
    rng = np.random.default_rng(3)
    v, f = np.asarray(bunny_target.vertices), np.asarray(bunny_target.triangles)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centres = rng.uniform(lo, hi, size=(600, 3))
    corners = (centres[:, None, :] + rng.normal(scale=1.5, size=(600, 3, 3))).reshape(-1, 3)
    debris = (np.vstack([v, corners]), np.vstack([f, v.shape[0] + np.arange(1800).reshape(-1, 3)]))
    levels = [ElasticLevel(2), ElasticLevel(4)]
    # The paper's plain least squares, with and without the island filter (on by default).
    plain = registration_elastic(
        bunny_template,
        debris,
        init=np.eye(4),
        levels=levels,
        estimation_method=DistanceEstimation.paper(),
    )
    clean = registration_elastic(
        bunny_template,
        debris,
        init=np.eye(4),
        levels=levels,
        estimation_method=DistanceEstimation.paper(min_target_component=0.01),
    )
    reference = registration_elastic(
        bunny_template,
        bunny_target,
        init=np.eye(4),
        levels=levels,
        estimation_method=DistanceEstimation.paper(),
    )
    err = lambda r: np.linalg.norm(r.vertices - reference.vertices, axis=1).mean()  # noqa: E731
    # Ignoring the 3-vertex islands gives the debris-free registration back (same target).
    assert err(clean) < 1e-6
    assert err(plain) > 10 * err(clean) + 0.05
    with pytest.raises(ValueError, match="min_target_component"):
        DistanceEstimation(min_target_component=0.0)


def test_max_distance_factor_keeps_the_correspondences_it_should():
    # A sphere of radius 40 onto one of radius 50: every template vertex starts 10 mm from the
    # target, so every distance is within a few robust scales of the median and none may be
    # dropped. Measured in input units instead of robust scales (sigma read as 1.0), the factor
    # would drop all 402 vertices and leave the template where it was.
    small = synthetic_form("sphere", 400)
    big = synthetic_form("sphere", 2000)
    big.scale(1.25, center=(0.0, 0.0, 0.0))
    levels = [ElasticLevel(2), ElasticLevel(4)]
    method = DistanceEstimation(max_distance_factor=3.0)
    result = registration_elastic(
        small, big, init=np.eye(4), levels=levels, estimation_method=method
    )
    assert result.success
    assert result.supported is not None and result.supported.all()
    # Same accuracy as without the factor (within 5%: the same problem, no correspondence lost).
    plain = registration_elastic(small, big, init=np.eye(4), levels=levels)
    assert result.distances.source_to_target_mean < 0.2
    assert result.distances.source_to_target_mean < 1.05 * plain.distances.source_to_target_mean


@pytest.mark.parametrize("turned", [False, True])
def test_a_multi_part_deformation_is_one_map_that_saves_and_reproduces(tmp_path, turned):
    tv, tf, _ = two_plates(4.0)
    dv, df, dsplit = two_plates(2.0)
    dv[:dsplit, 0] -= 3.0
    dv[dsplit:, 0] += 3.0
    start = np.eye(4)
    if turned:  # the patient turned, started with the turn: the parts' lattices lie along it
        start[:3, :3] = Rotation.from_rotvec([0.4, -0.3, 0.6]).as_matrix()
        start[:3, 3] = (5.0, -2.0, 1.0)
        dv = dv @ start[:3, :3].T + start[:3, 3]
    levels = [ElasticLevel(2), ElasticLevel(4)]
    result = registration_elastic((tv, tf), (dv, df), init=start, levels=levels, parts="connected")
    assert isinstance(result.deformation, PartitionedDeformation)
    for part in result.part_deformations:
        assert (part.frame is not None) == turned
    # The registered vertices are the map applied to the template (both parts, not only the
    # largest one: saving only that one put the other plate 12 mm off).
    np.testing.assert_allclose(result.transform(tv), result.vertices, atol=1e-9)
    path = tmp_path / "parts.npz"
    result.deformation.save(path)
    back = load_deformation(path)
    assert isinstance(back, PartitionedDeformation)
    # The saved map applies after the start (the rigidly moved points).
    moved = tv @ start[:3, :3].T + start[:3, 3]
    probe = np.vstack([moved, moved + np.random.default_rng(0).normal(scale=2.0, size=tv.shape)])
    np.testing.assert_array_equal(back.transform(probe), result.deformation.transform(probe))
    np.testing.assert_array_equal(
        PartitionedDeformation.load(path).transform(moved), result.vertices
    )
    with pytest.raises(ValueError, match="PartitionedDeformation"):
        LatticeDeformation.load(path)
    # evaluate_elastic with the (reloaded) map measures what the registration reported: exactly
    # along the axes; in a frame, the levels measured in its coordinates (rounding apart).
    again = evaluate_elastic((tv, tf), (dv, df), result.transformation, back)
    if not turned:
        assert again == result.distances
    for name, value in vars(result.distances).items():
        assert getattr(again, name) == pytest.approx(value, rel=1e-9, abs=1e-12), name


def test_the_cli_writes_the_map_of_every_part(tmp_path):
    from o3dreg.cli import main
    from o3dreg.io.mesh import to_open3d

    tv, tf, _ = two_plates(4.0)
    dv, df, dsplit = two_plates(2.0)
    dv[:dsplit, 0] -= 3.0
    dv[dsplit:, 0] += 3.0
    o3d.io.write_triangle_mesh(str(tmp_path / "t.ply"), to_open3d(tv, tf))
    o3d.io.write_triangle_mesh(str(tmp_path / "p.ply"), to_open3d(dv, df))
    args = ["register", str(tmp_path / "t.ply"), str(tmp_path / "p.ply")]
    args += ["-o", str(tmp_path / "o.ply"), "--levels", "2,4", "--no-rigid", "--quiet"]
    # On flat plates the barycentre term slides the vertices along the plane towards their
    # Voronoi centroids (Lloyd's relaxation, linear convergence): the 2-cell level needs more
    # than the default 20 steps (exit 1, "not converged"); 60 let every level converge.
    code = main(
        [*args, "--parts", "connected", "--max-iteration", "60"]
        + ["--deformation", str(tmp_path / "d.npz")]
    )
    assert code == 0  # written, every level converged, verdict ok
    written = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "o.ply")).vertices)
    template = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "t.ply")).vertices)
    # The saved map reproduces the written mesh (to the PLY's float precision).
    moved = load_deformation(tmp_path / "d.npz").transform(template)
    np.testing.assert_allclose(moved, written, atol=1e-4)


def test_the_paper_switch_and_the_robust_defaults():
    default, paper = DistanceEstimation(), DistanceEstimation.paper()
    assert (default.loss, default.max_normal_angle, default.min_target_component) == (
        "cauchy",
        90.0,
        0.01,
    )
    assert default.reject_boundary
    assert (paper.loss, paper.max_normal_angle, paper.min_target_component) == (
        "linear",
        None,
        None,
    )
    assert not paper.reject_boundary and paper.symmetric
    assert not DistanceEstimation.paper(symmetric=False).symmetric
    assert "loss='linear'" in repr(paper) and "max_normal_angle=None" in repr(paper)


def test_a_target_oriented_inside_out_is_registered_the_same(bunny_warped):
    # Meshes from different tools disagree on which side is out; the normal test of the
    # defaults must not reject every correspondence of an inside-out target.
    template, (v, f), warp = bunny_warped
    truth = warp(template[0])
    right = registration_elastic(template, (v, f), init=np.eye(4), levels=FAST)
    flipped = registration_elastic(template, (v, f[:, ::-1]), init=np.eye(4), levels=FAST)
    assert flipped.supported is not None and flipped.supported.mean() > 0.97
    # The same problem; the coarse levels' simplified targets are clustered from a differently
    # ordered mesh, so the results agree to a small fraction of the error, not bit for bit.
    err = lambda r: np.linalg.norm(r.vertices - truth, axis=1).mean()  # noqa: E731
    assert abs(err(flipped) - err(right)) < 0.05 * err(right)
    assert np.linalg.norm(flipped.vertices - right.vertices, axis=1).mean() < 0.05


def test_the_cli_starts_from_the_library_defaults_or_the_paper():
    from o3dreg.cli import build_parser
    from o3dreg.cli._registration_options import estimation_method

    def method(*extra):
        return estimation_method(
            build_parser().parse_args(["register", "a", "b", "-o", "c", *extra])
        )

    assert method() == DistanceEstimation()
    assert method("--paper") == DistanceEstimation.paper()
    assert method("--paper", "--no-symmetric") == DistanceEstimation.paper(symmetric=False)
    tuned = method("--loss", "huber", "--max-normal-angle", "180", "--min-target-component", "0")
    assert tuned == DistanceEstimation(
        loss="huber", max_normal_angle=180.0, min_target_component=None
    )


def test_the_relative_orientation_from_a_subsample_and_a_level_of_detail(bunny_warped):
    # The target's orientation is decided from 1000 template vertices against the finest
    # simplified copy of the target: the same sign as every vertex against the full target.
    from o3dreg.registration._target import TargetSurface
    from o3dreg.registration.elastic import ORIENTATION_POINTS, _relative_orientation

    (tv, tf), (v, f), _ = bunny_warped
    assert tv.shape[0] > ORIENTATION_POINTS
    for faces, sign in ((f, 1.0), (f[:, ::-1], -1.0)):
        surface = TargetSurface.from_mesh(v, faces)
        surface.build_levels_of_detail([4.0 * surface.query.mean_edge])
        assert surface.finest_detail() is not surface.query
        assert _relative_orientation(tv, tf, surface.finest_detail()) == sign
        assert _relative_orientation(tv, tf, surface.query) == sign


def test_a_target_patch_wound_backwards_registers_as_the_well_wound_target(
    bunny_template, bunny_target
):
    # Half the bunny's triangles wound the other way (a mesh stitched from two tools): the
    # normal check rejected the template's correspondences there (1436 of 3045 vertices without
    # data, 2.0 mm mean error against 0.22, verdict ok). The target is oriented first: the same
    # registration as on the well-wound target, to the bit.
    v, f = np.asarray(bunny_target.vertices), np.asarray(bunny_target.triangles)
    half = v[f].mean(axis=1)[:, 0] > np.median(v[:, 0])
    mixed = f.copy()
    mixed[half] = mixed[half][:, ::-1]
    levels = [ElasticLevel(2), ElasticLevel(4)]
    well = registration_elastic(bunny_template, (v, f), init=np.eye(4), levels=levels)
    wound = registration_elastic(bunny_template, (v, mixed), init=np.eye(4), levels=levels)
    np.testing.assert_array_equal(wound.vertices, well.vertices)
    np.testing.assert_array_equal(wound.supported, well.supported)


def test_debris_does_not_pull_the_finest_level(bunny_warped):
    # The default finest level pulls the template towards target points it does not reach;
    # debris the island filter left (min_target_component=None) is such points. Farther than a
    # cell, or discounted by the loss in the scale of the whole target, it does not pull: 5%
    # debris ends within 10% of the error of the finest level without the term (measured 0.98x;
    # 7.6x when the scale is measured on the far points alone and nothing is capped).
    template, target, warp = bunny_warped
    truth = warp(template[0])
    noisy = debris(target, 0.05)
    unfiltered = DistanceEstimation(min_target_component=None)
    finest = default_levels()[-1]
    without = [*default_levels()[:-1], replace(finest, symmetric_scale=0.0)]
    errors = [
        np.linalg.norm(
            registration_elastic(
                template, noisy, estimation_method=unfiltered, levels=levels
            ).vertices
            - truth,
            axis=1,
        ).mean()
        for levels in (default_levels(), without)
    ]
    assert errors[0] < 1.1 * errors[1], errors


def test_a_densely_sampled_island_pulls_no_more_than_its_area():
    # A sphere scaled by 1.1 beside an island a third its size, 150 mm away, whose triangles
    # are 15 times smaller: twice as many vertices as the sphere on a ninth of its area. The
    # island is kept (it is no debris by area), and its vertices all but fill the barycentre
    # term's sample. Counted per target vertex, their small robust weights summed on the few
    # template vertices facing the island pulled those ~5 mm out (1.85 mm mean error); counted
    # by the area they stand for, the island weighs what a ninth of the target does and the
    # error stays that of the sphere alone (0.41 mm measured; 0.26 with the island).
    template = arrays(synthetic_form("sphere", 400))
    main_v, main_f = arrays(synthetic_form("sphere", 2000))
    island_v, island_f = arrays(synthetic_form("sphere", 4000))
    target = (
        np.concatenate([1.1 * main_v, 0.33 * island_v + [150.0, 0.0, 0.0]]),
        np.concatenate([main_f, island_f + len(main_v)]),
    )
    result = registration_elastic(template, target, init=np.eye(4))
    error = np.linalg.norm(result.vertices - 1.1 * template[0], axis=1)
    assert error.mean() < 0.6 and error.max() < 1.5, (error.mean(), error.max())


def test_an_island_the_start_does_not_reach_does_not_pull_the_template():
    # The asymmetric blob beside a copy of itself at 30% of its size, half a diagonal away:
    # no template vertex has its closest point on the copy after the rigid step, so the levels
    # leave it out and end where they end without it (measured 0.23% of the diagonal from the
    # truth both ways). Kept in the levels (min_target_component=None, every piece counts),
    # it pulls the side facing it (0.35%, the worst vertex 1.2% against 0.58%).
    template, (warped, ft), truth = warped_blob()
    diagonal = np.linalg.norm(np.ptp(warped, axis=0))
    centre = warped.mean(axis=0)
    island = (warped - centre) * 0.3 + centre + [0.5 * diagonal, 0.0, 0.0]
    target = (np.vstack([warped, island]), np.vstack([ft, ft + len(warped)]))

    def error(result):
        return np.linalg.norm(result.vertices - truth, axis=1).mean() / diagonal

    alone = error(o3dreg.registration_elastic(template, (warped, ft)))
    beside = o3dreg.registration_elastic(template, target)
    every_piece = DistanceEstimation(min_target_component=None)
    pulled = error(o3dreg.registration_elastic(template, target, estimation_method=every_piece))
    # The same result up to the subsample of the target the levels draw (0.01% of the diagonal).
    assert error(beside) == pytest.approx(alone, abs=1e-4)
    assert pulled > 1.3 * alone
    assert beside.status == "ok"
