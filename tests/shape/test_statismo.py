"""statismo / scalismo HDF5 interchange: layout compared with a file scalismo wrote, round trip."""

from __future__ import annotations

import os
import shutil

import h5py
import numpy as np
import pytest
from _helpers import population

from o3dreg import build_shape_model, read_statismo, write_statismo

REFERENCE = os.path.join(
    os.path.dirname(os.path.dirname(__file__)), "data", "statismo", "scalismo-asm-model.h5"
)


@pytest.fixture(scope="module")
def model():
    (_tv, tf), _, truths, _, _ = population(6, seed=6, template_resolution=8)
    rng = np.random.default_rng(0)
    return build_shape_model(truths + rng.normal(size=truths.shape) * 0.1, tf)


def _layout(path):
    """{path: description} of every group, dataset and attribute: kind, dtype, rank."""
    out = {}
    with h5py.File(path, "r") as h5:

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                tid = obj.id.get_type()
                if obj.dtype.kind == "S":
                    kind = ("string", tid.get_strpad(), tid.get_cset(), obj.shape)
                else:
                    kind = ("array", obj.dtype.str, obj.ndim)
                out[name] = kind
            else:
                out[name] = ("group",)
            for attr in obj.attrs:
                aid = h5py.h5a.open(obj.id, attr.encode())
                atype = aid.get_type()
                out[f"{name}@{attr}"] = ("string", atype.get_strpad(), aid.shape)

        h5.visititems(visit)
    return out


def test_layout_matches_a_file_scalismo_wrote(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    ours, reference = _layout(path), _layout(REFERENCE)
    # Every group, dataset and attribute scalismo wrote is there, with its dtype and rank.
    for key, kind in reference.items():
        assert key in ours, key
        assert ours[key] == kind, (key, ours[key], kind)
    # What o3dreg adds: scores, names and parameters in statismo's own places.
    extra = set(ours) - set(reference)
    assert {"modelinfo/scores", "modelinfo/modelBuilder-0/parameters/TotalVariance"} <= extra
    for key in extra:
        assert key.startswith("modelinfo/"), key


def test_every_dataset_statismo_and_scalismo_read(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    n, k, m = model.number_of_points, model.number_of_modes, model.faces.shape[0]
    with h5py.File(path, "r") as h5:
        # statismo HDF5Utils::readInt / scalismo readInt: int32 scalars.
        for name, value in (("majorVersion", 0), ("minorVersion", 9)):
            ds = h5[f"version/{name}"]
            assert ds.shape == () and ds.dtype == np.int32 and ds[()] == value
        # readVector / readArrayFloat: float32 vectors; readMatrix / readNDArrayFloat: float32 2-D.
        assert h5["model/mean"].shape == (3 * n,) and h5["model/mean"].dtype == np.float32
        assert h5["model/pcaBasis"].shape == (3 * n, k)
        assert h5["model/pcaBasis"].dtype == np.float32
        assert h5["model/pcaVariance"].shape == (k,)
        assert h5["model/pcaVariance"].dtype == np.float32
        assert h5["model/noiseVariance"].dtype == np.float32
        assert h5["model/noiseVariance"].size == 1
        assert h5["representer/points"].shape == (3, n)
        assert h5["representer/points"].dtype == np.float32
        # scalismo's readNDArrayInt casts to signed 32-bit: uint32 would fail there.
        assert h5["representer/cells"].shape == (3, m)
        assert h5["representer/cells"].dtype == np.int32
        np.testing.assert_array_equal(h5["representer/cells"][()].T, model.faces)
        rep = h5["representer"].attrs
        assert rep["datasetType"][0] == b"POLYGON_MESH"
        assert rep["name"][0] == b"itkStandardMeshRepresenter"
        # statismo BuilderInfo::Load opens these and reads every child as a string.
        builder = h5["modelinfo/modelBuilder-0"]
        for name in ("builderName", "buildTime"):
            assert builder[name].dtype.kind == "S"
        for group in ("dataInfo", "parameters"):
            assert isinstance(builder[group], h5py.Group)
            for child in builder[group].values():
                assert isinstance(child, h5py.Dataset) and child.dtype.kind == "S"
        assert len(builder["dataInfo"]) == len(model.names)
        # ModelInfo::Load reads scores as a (k, s) float matrix.
        assert h5["modelinfo/scores"].shape == (k, model.scores.shape[0])
        basis = h5["model/pcaBasis"][()].astype(np.float64)
        # Version 0.9 stores the orthonormal basis (float32 precision).
        np.testing.assert_allclose(basis.T @ basis, np.eye(k), atol=1e-5)
        np.testing.assert_allclose(h5["model/mean"][()][:3], model.mean[0], rtol=1e-6)
        # Strings are null-terminated fixed-length ASCII, with the terminator's byte.
        tid = builder["builderName"].id.get_type()
        assert tid.get_strpad() == h5py.h5t.STR_NULLTERM
        assert tid.get_size() == len(b"o3dreg.build_shape_model") + 1


def test_roundtrip_and_version_08(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    back = read_statismo(path, template=(model.mean, model.faces))
    np.testing.assert_allclose(back.mean, model.mean, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(back.variances, model.variances, rtol=1e-6)
    np.testing.assert_allclose(back.modes, model.modes, atol=1e-6)
    np.testing.assert_allclose(back.scores, model.scores, rtol=1e-4, atol=1e-3)
    np.testing.assert_array_equal(back.faces, model.faces)
    assert back.names == model.names
    assert back.scaling == model.scaling
    assert back.total_variance == pytest.approx(model.total_variance, rel=1e-12)
    # statismo 0.8 stored U D (scaled basis); it is read back to the same model.
    with h5py.File(path, "r+") as h5:
        h5["version/minorVersion"][()] = 8
        scaled = h5["model/pcaBasis"][()] * np.sqrt(h5["model/pcaVariance"][()])
        h5["model/pcaBasis"][...] = scaled
    old = read_statismo(path)
    np.testing.assert_allclose(old.modes, model.modes, atol=1e-5)


def test_reads_the_model_scalismo_wrote():
    model = read_statismo(REFERENCE)
    assert model.number_of_points == 1400 and model.number_of_modes == 50
    assert model.faces.shape == (2800, 3)
    with h5py.File(REFERENCE, "r") as h5:
        mean = h5["model/mean"][()].astype(np.float64).reshape(-1, 3)
        basis = h5["model/pcaBasis"][()].astype(np.float64)
        variances = h5["model/pcaVariance"][()].astype(np.float64)
        cells = h5["representer/cells"][()]
    np.testing.assert_array_equal(model.mean, mean)
    np.testing.assert_array_equal(model.faces, cells.T)
    # This model is a low-rank Gaussian process: its stored basis holds eigenfunctions sampled
    # at the points (column norms^2 ~ 1,380, not 1), so the modes are re-orthonormalised.
    assert np.abs(basis.T @ basis - np.eye(50)).max() > 1.0
    np.testing.assert_allclose(model.basis.T @ model.basis, np.eye(50), atol=1e-10)
    assert np.all(np.diff(model.variances) <= 0)
    # ... describing the same distribution: equal covariance U diag(var) U^T, probed with random
    # vectors (the 4,200 x 4,200 matrices are not formed). float32 basis: relative 1e-5.
    probes = np.random.default_rng(0).normal(size=(3 * 1400, 5))
    stored = basis @ (variances[:, None] * (basis.T @ probes))
    ours = model.basis @ (model.variances[:, None] * (model.basis.T @ probes))
    np.testing.assert_allclose(ours, stored, rtol=1e-6, atol=1e-6 * np.abs(stored).max())
    # Total variance: trace of the covariance.
    assert model.variances.sum() == pytest.approx((variances * (basis**2).sum(axis=0)).sum())
    assert model.scores.shape == (0, 50) and model.noise_variance == 0.0


def test_a_model_scalismo_wrote_survives_a_round_trip(tmp_path):
    model = read_statismo(REFERENCE)
    back = read_statismo(write_statismo(tmp_path / "again.h5", model))
    # Written once more as float32: orthonormal to float32 precision, so read as stored.
    np.testing.assert_array_equal(back.mean, model.mean)
    np.testing.assert_allclose(back.basis, model.basis, atol=1e-6)
    np.testing.assert_allclose(back.variances, model.variances, rtol=1e-6)
    np.testing.assert_array_equal(back.faces, model.faces)


def test_statismo_bad_input(model, tmp_path):
    path = write_statismo(tmp_path / "m.h5", model)
    with pytest.raises(OSError, match="exists"):
        write_statismo(path, model)
    with pytest.raises(ValueError, match=".h5"):
        write_statismo(tmp_path / "m.npz", model)
    with pytest.raises(TypeError, match="ShapeModel"):
        write_statismo(tmp_path / "n.h5", (model.mean, model.faces))
    with h5py.File(tmp_path / "empty.h5", "w") as h5:
        h5.create_group("model")
    with pytest.raises(ValueError, match="not a statismo shape model"):
        read_statismo(tmp_path / "empty.h5")
    with pytest.raises(ValueError, match="not this model's template"):
        read_statismo(path, template=(model.mean, model.faces[::-1].copy()))


def test_a_scaled_basis_is_the_same_model(model, tmp_path):
    # U c with variances var / c^2 is the same distribution; its scores a (standardised) too.
    path = write_statismo(tmp_path / "m.h5", model)
    c = np.linspace(2.0, 3.0, model.number_of_modes)
    with h5py.File(path, "r+") as h5:
        h5["model/pcaBasis"][...] = h5["model/pcaBasis"][()] * c
        h5["model/pcaVariance"][...] = h5["model/pcaVariance"][()] / c**2
    back = read_statismo(path)
    np.testing.assert_allclose(back.variances, model.variances, rtol=1e-5)
    signs = np.sign(np.sum(back.basis * model.basis, axis=0))
    np.testing.assert_allclose(back.basis * signs, model.basis, atol=1e-5)
    np.testing.assert_allclose(back.scores * signs, model.scores, rtol=1e-4, atol=1e-3)


def test_damaged_statismo_files_are_value_errors(model, tmp_path):
    # NaN in the basis would raise LinAlgError and a mean of 3k+1 values numpy's reshape error;
    # a variance of -1e-9 (rounding) must not make a whole file unreadable.
    path = write_statismo(tmp_path / "m.h5", model)

    def damaged(name, dataset, change):
        out = tmp_path / name
        shutil.copyfile(path, out)
        with h5py.File(out, "r+") as h5:
            values = np.asarray(h5[dataset])
            del h5[dataset]
            h5[dataset] = change(values)
        return out

    nan = damaged(
        "nan.h5",
        "model/pcaBasis",
        lambda b: np.where(np.arange(b.size).reshape(b.shape) == 3, np.nan, b),
    )
    with pytest.raises(ValueError, match="NaN or infinite values in model/pcaBasis"):
        read_statismo(nan)
    short = damaged("short.h5", "model/mean", lambda m: m.reshape(-1)[:-1])
    with pytest.raises(ValueError, match="not 3 per point"):
        read_statismo(short)
    # The basis not matching the mean: named with the file.
    narrow = damaged("narrow.h5", "model/pcaBasis", lambda b: b[:-3])
    with pytest.raises(ValueError, match=r"narrow.h5' has model/pcaBasis of shape \("):
        read_statismo(narrow)
    rounding = damaged(
        "rounding.h5", "model/pcaVariance", lambda v: np.append(v[:-1], -1e-12 * v.max())
    )
    back = read_statismo(rounding)
    assert back.variances[-1] == 0.0
    # The noise variance is the fit's default regularisation: NaN would stop the fit's SVD.
    noisy = damaged("noise.h5", "model/noiseVariance", lambda v: np.full_like(v, np.nan))
    with pytest.raises(ValueError, match="NaN or infinite values in model/noiseVariance"):
        read_statismo(noisy)
    negative = damaged("negative.h5", "model/noiseVariance", lambda v: np.full_like(v, -2.0))
    with pytest.raises(ValueError, match="negative model/noiseVariance"):
        read_statismo(negative)


def test_names_beyond_ascii_survive_a_round_trip(tmp_path):
    # Written as ASCII with replacement ("pati?nt_0"), two names could collide.
    (_, tf), _, truths, _, _ = population(4, seed=1)
    names = ["patiënt_0", "patiënt_1", "pätient_2", "p3"]
    model = build_shape_model(truths, tf, names=names)
    back = read_statismo(write_statismo(tmp_path / "u.h5", model))
    assert list(back.names) == names


@pytest.mark.parametrize("modes", [1, 3])
def test_statismos_no_scores_placeholder_is_no_training_shape(tmp_path, modes):
    # statismo writes a 1 x 1 zero scores matrix for a model without scores; with one mode
    # it read as one training shape of score 0 ("shape000").
    (_tv, tf), _, truths, _, _ = population(modes + 1, seed=6, template_resolution=8)
    built = build_shape_model(truths, tf)
    assert built.number_of_modes == modes
    path = write_statismo(tmp_path / "m.h5", built)
    with h5py.File(path, "r+") as h5:
        del h5["modelinfo/scores"]
        h5["modelinfo/scores"] = np.zeros((1, 1), np.float32)
        del h5["modelinfo/modelBuilder-0/dataInfo"]
        h5["modelinfo/modelBuilder-0"].create_group("dataInfo")
    read = read_statismo(path)
    assert read.number_of_shapes == 0 and read.scores.shape == (0, modes)
    np.testing.assert_allclose(read.variances, built.variances, rtol=1e-5)


def test_model_of_no_modes_round_trips(model, tmp_path):
    """A model of the mean alone (no modes: the constructor takes it) has a (3n, 0) basis and
    is written and read back as such."""
    n = model.number_of_points
    empty = type(model)(
        mean=model.mean,
        modes=np.zeros((0, n, 3)),
        variances=np.zeros(0),
        faces=model.faces,
        total_variance=model.total_variance,
        scores=np.zeros((model.number_of_shapes, 0)),
    )
    assert empty.basis.shape == (3 * n, 0)
    back = read_statismo(write_statismo(tmp_path / "mean.h5", empty))
    assert back.number_of_modes == 0 and back.modes.shape == (0, n, 3)
    np.testing.assert_allclose(back.mean, model.mean, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(back.faces, model.faces)
