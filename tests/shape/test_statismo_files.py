"""Models written by statismo's own C++ library: a float32 basis orthonormal only to ~1e-6,
read as a model and used by ``o3dreg model info/modes/explore/fit`` like a model folder."""

from __future__ import annotations

import logging

import h5py
import numpy as np
import pytest
from _helpers import population

from o3dreg import (
    build_shape_model,
    read_statismo,
    write_landmarks,
    write_statismo,
    write_triangle_mesh,
)
from o3dreg.cli import main


@pytest.fixture(scope="module")
def float32_model_file(tmp_path_factory):
    """A model file whose basis is orthonormal only to ~3e-6, as statismo's float32 files are
    (statismo computes the basis in float64 and stores float32; summing thousands of rounded
    products leaves |U^T U - I| of a few 1e-6)."""
    (_tv, tf), _, truths, _, _ = population(6, seed=6, template_resolution=8)
    rng = np.random.default_rng(1)
    model = build_shape_model(truths + rng.normal(size=truths.shape) * 0.1, tf)
    path = tmp_path_factory.mktemp("statismo") / "m.h5"
    write_statismo(path, model)
    with h5py.File(path, "r+") as h5:
        basis = h5["model/pcaBasis"][()].astype(np.float64)
        # Each column lengthened by 2e-6 and tilted by 2e-6 towards the next one (rounding-sized
        # errors, not a new model): |U^T U - I| about 4e-6.
        tilted = basis * (1 + 2e-6) + 2e-6 * np.roll(basis, -1, axis=1)
        h5["model/pcaBasis"][...] = tilted.astype(np.float32)
        stored = h5["model/pcaBasis"][()].astype(np.float64)
    error = np.abs(stored.T @ stored - np.eye(stored.shape[1])).max()
    assert 1e-6 < error < 1e-4, error  # the fixture is what the test claims
    return path, model


def test_a_float32_basis_orthonormal_to_1e_minus_6_loads(float32_model_file, caplog):
    path, model = float32_model_file
    with caplog.at_level(logging.INFO, logger="o3dreg"):
        back = read_statismo(path)
    flat = back.basis
    # Re-orthonormalised in float64: orthonormal to rounding.
    assert np.abs(flat.T @ flat - np.eye(flat.shape[1])).max() < 1e-10
    # The nearest orthonormal basis: each column within a few 1e-6 of the stored one (the size
    # of the perturbation), the variances untouched.
    np.testing.assert_allclose(back.basis, model.basis, atol=2e-5)
    np.testing.assert_allclose(back.variances, model.variances, rtol=1e-6)
    assert "re-orthonormalised" in caplog.text


@pytest.fixture(scope="module")
def rvtkstatismo(shared_data):
    path = shared_data / "statismo" / "rvtkstatismo-mandibles.h5"
    if not path.is_file():
        pytest.skip(f"{path} is absent (research data is not part of the repository)")
    return path


def test_the_model_statismo_wrote_loads(rvtkstatismo):
    model = read_statismo(rvtkstatismo)
    assert model.number_of_points == 7516 and model.number_of_modes == 14
    with h5py.File(rvtkstatismo, "r") as h5:
        stored = h5["model/pcaBasis"][()].astype(np.float64)
        variances = h5["model/pcaVariance"][()].astype(np.float64)
    # The stored basis, to the precision statismo wrote it with (float32, ~2e-6 off orthonormal).
    np.testing.assert_allclose(model.basis, stored, atol=1e-5)
    np.testing.assert_allclose(model.variances, variances, rtol=1e-6)
    assert model.names[0] == "specimen_1" and model.scores.shape == (15, 14)


def test_model_commands_accept_a_statismo_file(float32_model_file, tmp_path, capsys):
    path, model = float32_model_file
    assert main(["model", "info", str(path), "--json"]) == 0
    info = capsys.readouterr().out
    assert f'"points": {model.number_of_points}' in info
    modes = tmp_path / "modes"
    assert main(["model", "modes", str(path), "-o", str(modes), "--modes", "1"]) == 0
    assert sorted(p.name for p in modes.iterdir()) == [
        "mean.ply",
        "mode1_+3sd.ply",
        "mode1_-3sd.ply",
    ]
    page = tmp_path / "e.html"
    assert main(["model", "explore", str(path), "-o", str(page)]) == 0
    assert page.stat().st_size > 1000
    # fit: the landmarks are placed on the model's mean (the reference a statismo file holds).
    patient = tmp_path / "patient.ply"
    write_triangle_mesh(patient, (model.mean + 0.5 * model.modes[0], model.faces))
    write_landmarks(tmp_path / "lm.csv", ["a", "b"], model.mean[[0, 10]])
    code = main(["model", "fit", str(path), str(patient), "--landmarks", str(tmp_path / "lm.csv")])
    assert code == 0, capsys.readouterr().err


def test_a_file_that_is_neither_a_folder_nor_statismo_is_named(tmp_path, capsys):
    other = tmp_path / "model.npz"
    other.write_bytes(b"x")
    assert main(["model", "info", str(other)]) == 2
    assert "MODEL must be a model folder" in capsys.readouterr().err


def test_the_cli_reads_the_model_statismo_wrote(rvtkstatismo, capsys):
    assert main(["model", "info", str(rvtkstatismo), "--json"]) == 0
    assert '"points": 7516' in capsys.readouterr().out
