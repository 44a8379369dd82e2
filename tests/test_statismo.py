"""statismo / scalismo HDF5 interchange: layout, dtypes, round trip, version 0.8."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from _helpers import population

from o3dreg import build_shape_model, read_statismo, write_statismo


@pytest.fixture(scope="module")
def model():
    (_tv, tf), _, truths, _, _ = population(6, seed=6, template_resolution=8)
    rng = np.random.default_rng(0)
    return build_shape_model(truths + rng.normal(size=truths.shape) * 0.1, tf)


def test_layout_follows_statismo(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    n, k = model.number_of_points, model.number_of_modes
    with h5py.File(path, "r") as h5:
        assert int(h5["version/majorVersion"][()]) == 0 and int(h5["version/minorVersion"][()]) == 9
        assert h5["model/mean"].shape == (3 * n,) and h5["model/mean"].dtype == np.float32
        assert h5["model/pcaBasis"].shape == (3 * n, k) and h5["model/pcaBasis"].dtype == np.float32
        assert h5["model/pcaVariance"].shape == (k,)
        assert h5["model/noiseVariance"].shape == ()
        assert h5["representer/points"].shape == (3, n)
        assert h5["representer/cells"].shape == (3, model.faces.shape[0])
        assert h5["representer"].attrs["datasetType"] == b"POLYGON_MESH"
        assert h5["representer"].attrs["name"] == b"itkStandardMeshRepresenter"
        basis = h5["model/pcaBasis"][()].astype(np.float64)
        # Version 0.9 stores the orthonormal basis (float32 precision).
        np.testing.assert_allclose(basis.T @ basis, np.eye(k), atol=1e-5)
        np.testing.assert_allclose(h5["model/mean"][()][:3], model.mean[0], rtol=1e-6)


def test_roundtrip_and_version_08(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    back = read_statismo(path, template=(model.mean, model.faces))
    np.testing.assert_allclose(back.mean, model.mean, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(back.variances, model.variances, rtol=1e-6)
    np.testing.assert_allclose(back.modes, model.modes, atol=1e-6)
    np.testing.assert_allclose(back.scores, model.scores, rtol=1e-4, atol=1e-3)
    np.testing.assert_array_equal(back.faces, model.faces)
    # statismo 0.8 stored U D (scaled basis); it is read back to the same model.
    with h5py.File(path, "r+") as h5:
        h5["version/minorVersion"][()] = 8
        scaled = h5["model/pcaBasis"][()] * np.sqrt(h5["model/pcaVariance"][()])
        h5["model/pcaBasis"][...] = scaled
    old = read_statismo(path)
    np.testing.assert_allclose(old.modes, model.modes, atol=1e-5)


def test_statismo_bad_input(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    with pytest.raises(OSError, match="exists"):
        write_statismo(path, model)
    with pytest.raises(ValueError, match=".h5"):
        write_statismo(tmp_path / "m.npz", model)
    with h5py.File(tmp_path / "empty.h5", "w") as h5:
        h5.create_group("model")
    with pytest.raises(ValueError, match="not a statismo shape model"):
        read_statismo(tmp_path / "empty.h5")
    with pytest.raises(ValueError, match="not this model's template"):
        read_statismo(path, template=(model.mean, model.faces[::-1].copy()))
