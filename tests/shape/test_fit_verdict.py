"""The verdict of a model fit: right patients 'ok'; a mirrored patient, a patient 1.5 times the
population's size and a patient the model cannot describe are not, with their reasons; the
thresholds come from the model's own population (leave-one-out residuals, chi-squared law of
the coefficients, training sizes)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from o3dreg import build_shape_model, fit_shape_model
from o3dreg.cli import main
from o3dreg.shape.fit_verdict import population_residuals, population_sizes, surface_size


def _chiral_base(resolution: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """An ellipsoid (40 x 25 x 15 mm) with three bumps of different sizes at positions that
    no rotation maps onto their mirror image: a shape that is not its own reflection."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    u = np.asarray(sphere.vertices)
    faces = np.asarray(sphere.triangles)
    radius = np.ones(len(u))
    for centre, height in (([1, 0, 0], 0.5), ([0, 1, 0.3], 0.3), ([0.3, 0.2, 1], 0.15)):
        c = np.asarray(centre, float) / np.linalg.norm(centre)
        radius += height * np.exp(-((u - c) ** 2).sum(axis=1) / 0.15)
    return u * radius[:, None] * np.array([40.0, 25.0, 15.0]), faces


def _fields(u: np.ndarray) -> np.ndarray:
    """Four smooth deformation fields of the base shape (mm per unit coefficient)."""
    x, y, z = (u / np.abs(u).max(axis=0)).T
    return np.stack(
        [
            np.column_stack([x, 0 * y, 0 * z]) * 4.0,
            np.column_stack([0 * x, y * z, y]) * 3.0,
            np.column_stack([x * y, 0 * y, z]) * 2.0,
            np.column_stack([0 * x, x, x * z]) * 1.5,
        ]
    )


@pytest.fixture(scope="module")
def chiral():
    base, faces = _chiral_base()
    fields = _fields(base)
    rng = np.random.default_rng(3)

    def shape(seed_rng):
        return base + np.tensordot(seed_rng.normal(size=len(fields)), fields, axes=1)

    shapes = np.stack([shape(rng) for _ in range(14)])
    model = build_shape_model(shapes, faces)
    return model, faces, lambda: shape(rng)


def _posed(vertices, seed):
    rotation = Rotation.from_rotvec(np.random.default_rng(seed).normal(size=3) * 0.2)
    return rotation.apply(vertices) + np.array([5.0, -3.0, 2.0])


def test_new_members_of_the_population_are_ok(chiral):
    model, faces, draw = chiral
    for seed in range(3):
        fit = fit_shape_model(model, (_posed(draw(), seed), faces))
        assert fit.status == "ok", fit.warnings
        assert fit.warnings == ()
        # The fit is right: within a small fraction of the 40 mm shape.
        assert fit.mean_distance < 0.5


def test_a_mirrored_patient_fails_with_the_reflection_named(chiral):
    model, faces, draw = chiral
    mirrored = _posed(draw(), 7) * np.array([-1.0, 1.0, 1.0])
    # Triangles reversed, as a tool that mirrors a mesh properly writes it (normals outward).
    fit = fit_shape_model(model, (mirrored, faces[:, ::-1]))
    assert fit.success  # the optimiser's criteria are met: only the verdict tells
    assert fit.status == "failed"
    assert any("mirror image" in w and "left and right" in w for w in fit.warnings)
    # Written without reversing the triangles: their facing is named too.
    fit = fit_shape_model(model, (mirrored, faces))
    assert fit.status == "failed"
    assert any("wound the other way" in w for w in fit.warnings)


def test_the_mirrored_mean_shape_is_named_without_meaningless_digits(chiral):
    # The mean shape mirrored: its mirror image is the mean, fitted to rounding, and the ratio
    # of the two fits is a number of 14 digits.
    model, faces, _ = chiral
    mirrored = model.mean * np.array([-1.0, 1.0, 1.0])
    fit = fit_shape_model(model, (mirrored, faces[:, ::-1]))
    assert fit.status == "failed"
    (text,) = [w for w in fit.warnings if "mirror image" in w]
    assert "fits the model over 1000 times closer" in text


def test_a_patient_one_and_a_half_times_the_size_fails(chiral):
    model, faces, draw = chiral
    fit = fit_shape_model(model, (_posed(draw() * 1.5, 8), faces))
    assert fit.status == "failed"
    text = " ".join(fit.warnings)
    assert "times the training shapes' median" in text


def test_a_scaling_model_fits_any_size(chiral):
    # Size removed by Procrustes: a patient ten times the size is a member of the population,
    # its distances judged in the model's size (1 mm of noise on a 400 mm patient is 0.1 mm on
    # the 40 mm model: far below the 1%-of-size reference; in the patient's millimetres it
    # would be several times that reference).
    _, faces, draw = chiral
    scaled = build_shape_model(np.stack([draw() for _ in range(14)]), faces, scaling=True)
    patient = _posed(draw() * 10.0, 13)
    patient = patient + np.random.default_rng(5).normal(size=patient.shape)
    fit = fit_shape_model(scaled, (patient, faces))
    assert fit.status == "ok", fit.warnings


def test_without_the_reflection_check_a_mirrored_patient_is_not_caught_by_size(chiral):
    # The size and residual checks do not misfire on a mirrored patient of the right size:
    # what catches it is the mirror fit, which check_reflection=False leaves out.
    model, faces, draw = chiral
    mirrored = _posed(draw(), 9) * np.array([-1.0, 1.0, 1.0])
    fit = fit_shape_model(model, (mirrored, faces[:, ::-1]), check_reflection=False)
    assert not any("size" in w for w in fit.warnings)


def test_fit_bad_input(chiral):
    model, faces, draw = chiral
    with pytest.raises(TypeError, match="`check_reflection` must be True or False, got str"):
        fit_shape_model(model, (draw(), faces), check_reflection="yes")


def test_population_references_are_the_models_own(chiral):
    model, faces, _ = chiral
    rms, maha = population_residuals(model, model.number_of_modes)
    assert rms.shape == maha.shape == (model.number_of_shapes,)
    # Four deformation fields, aligned by Procrustes (a small rotation per shape): a shape
    # left out is described by the others' modes to a small fraction of the 40 mm size.
    assert rms.max() < 0.01 * 40
    sizes = population_sizes(model)
    assert sizes.shape == (model.number_of_shapes,)
    # Size scales linearly: the size of a shape scaled by 2 is twice its size.
    v = model.mean
    np.testing.assert_allclose(surface_size(2 * v, faces), 2 * surface_size(v, faces), rtol=1e-12)


def test_surface_size_of_a_sphere():
    # Every point of a sphere of radius r is r from its centre: the RMS radius is r (the
    # triangulated sphere lies inside by its sagitta: 0.5% at resolution 40).
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=40)
    size = surface_size(np.asarray(sphere.vertices), np.asarray(sphere.triangles))
    assert 9.9 < size <= 10.0


def test_model_fit_exits_1_unless_ok(chiral, tmp_path, capsys):
    from o3dreg import write_landmarks, write_triangle_mesh

    model, faces, draw = chiral
    model.save(tmp_path / "model.npz")
    write_triangle_mesh(tmp_path / "template.ply", (model.mean, faces))
    write_landmarks(tmp_path / "lm.csv", ["a", "b"], model.mean[[0, 5]])
    good = tmp_path / "good.ply"
    write_triangle_mesh(good, (_posed(draw(), 11), faces))
    big = tmp_path / "big.ply"
    write_triangle_mesh(big, (_posed(draw() * 1.5, 12), faces))
    lm = str(tmp_path / "lm.csv")
    assert main(["model", "fit", str(tmp_path), str(good), "--landmarks", lm]) == 0
    assert "verdict: ok" in capsys.readouterr().out
    assert main(["model", "fit", str(tmp_path), str(big), "--landmarks", lm, "--json"]) == 1
    captured = capsys.readouterr()
    assert '"status": "failed"' in captured.out
    assert "verdict failed" in captured.err


@pytest.mark.slow
def test_the_mandible_model_statismo_wrote(shared_data):
    path = shared_data / "statismo" / "rvtkstatismo-mandibles.h5"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    from o3dreg import read_statismo

    model = read_statismo(path)
    rng = np.random.default_rng(0)
    a = rng.normal(size=model.number_of_modes) * model.standard_deviations
    patient = model.mean + np.tensordot(a, model.modes, axes=1)
    patient = patient + rng.normal(size=patient.shape) * 0.2  # 0.2 mm surface noise
    assert fit_shape_model(model, (patient, model.faces)).status == "ok"
    centre = patient.mean(axis=0)
    big = fit_shape_model(model, ((patient - centre) * 1.5 + centre, model.faces))
    assert big.status == "failed"
    mirrored = fit_shape_model(model, (patient * [-1, 1, 1], model.faces[:, ::-1]))
    assert mirrored.status == "failed"


def _without_end(vertices, faces, fraction):
    """The surface without the triangles beyond ``1 - fraction`` of its first principal
    extent (the 40 mm axis before the pose): a patient the field of view cut."""
    x = vertices @ np.linalg.svd(vertices - vertices.mean(axis=0), full_matrices=False)[2][0]
    x = x if abs(x.max()) > abs(x.min()) else -x
    end = x.max() - fraction * np.ptp(x)
    return faces[(x[faces] < end).all(axis=1)]


def test_a_partial_patient_is_judged_on_the_part_it_covers(chiral):
    # A right-sized patient without the last 40% of its long axis: its surface's own size is
    # 0.83 times the training shapes' median, beyond the 3 standard deviations of their log
    # sizes (16%) the size check allows (measured), yet its fit is right. Its size is compared
    # with the training shapes' over the triangles it covers; a patient of the wrong scale is
    # still caught the same way.
    model, faces, draw = chiral
    shape = draw()
    partial = _without_end(shape, faces, 0.4)
    patient = _posed(shape, 21)
    assert surface_size(patient, partial) < 0.85 * np.median(population_sizes(model))
    fit = fit_shape_model(model, (patient, partial))
    assert fit.status == "ok", fit.warnings
    big = fit_shape_model(model, (_posed(shape * 1.5, 21), partial))
    assert big.status != "ok" and any("size" in w for w in big.warnings), big.warnings
