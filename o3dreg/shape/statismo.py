"""Export and import of shape models in the statismo / scalismo HDF5 layout (h5py).

The layout written is the one scalismo's ``StatismoIO.writeStatismoPDM`` writes and statismo's
``StatismoIO::LoadStatisticalModel`` / ``ModelInfo::Load`` and scalismo's ``readStatismoPDM``
read (statismo format version 0.9):

============================================= ================= ==================================
path                                          type              content
============================================= ================= ==================================
``/version/majorVersion``                     int32 scalar      0
``/version/minorVersion``                     int32 scalar      9 (pcaBasis holds the
                                                                *orthonormal* basis ``U``; 0.8
                                                                stored ``U D``)
``/model/mean``                               float32 (3n,)     x1, y1, z1, x2, ...
``/model/pcaBasis``                           float32 (3n, k)   orthonormal columns
``/model/pcaVariance``                        float32 (k,)      variances
``/model/noiseVariance``                      float32 (1,)      isotropic noise variance
``/representer`` (attributes)                 string (1,)       ``name`` =
                                                                ``itkStandardMeshRepresenter``,
                                                                ``datasetType`` =
                                                                ``POLYGON_MESH``,
                                                                ``version/majorVersion`` = ``0``,
                                                                ``version/minorVersion`` = ``9``
``/representer/points``                       float32 (3, n)    reference (mean) vertices, one
                                                                column each
``/representer/cells``                        int32 (3, m)      triangles, one column each
                                                                (scalismo reads signed 32-bit)
``/modelinfo/build-time``                     string (1,)       time stamp
``/modelinfo/scores``                         float32 (k, s)    standardised training scores
                                                                ``alpha / sqrt(var)`` (written
                                                                when the model has scores)
``/modelinfo/modelBuilder-0/builderName``     string (1,)       ``o3dreg.build_shape_model``
``/modelinfo/modelBuilder-0/buildTime``       string (1,)       time stamp
``/modelinfo/modelBuilder-0/dataInfo/URI_i``  string (1,)       name of training shape ``i``
``/modelinfo/modelBuilder-0/parameters/*``    string (1,)       ``NoiseVariance``,
                                                                ``TotalVariance``, ``Scaling``
============================================= ================= ==================================

statismo reads every entry of ``dataInfo`` and ``parameters`` as a string, so only strings are
written there. Strings are fixed-length, ASCII, null-terminated, as statismo's ``HDF5Utils``
writes them.
"""

from __future__ import annotations

import datetime
import logging
import os
from typing import Any

import numpy as np

from ..io.mesh import atomic_write
from .model import ShapeModel

__all__ = ["read_statismo", "write_statismo"]

BUILDER_NAME = "o3dreg.build_shape_model"

_log = logging.getLogger("o3dreg")


def _h5py() -> Any:
    # Deferred: ~0.1 s to import, and `import o3dreg` loads this module.
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is a dependency
        raise RuntimeError("statismo files need h5py: pip install h5py") from exc
    return h5py


def _fixed_string(text: str) -> np.ndarray:
    """A one-element fixed-length string (UTF-8: ASCII text is unchanged and a name such as
    ``patiënt_0`` keeps its characters, where an ASCII encoding with replacement would write
    ``pati?nt_0`` and let two names collide) with room for the terminating zero."""
    data = text.encode("utf-8")
    return np.array([data], dtype=f"S{len(data) + 1}")


def _nullterm_string(text: str) -> tuple[np.ndarray, Any, Any]:
    """``text`` with its HDF5 null-terminated string type and one-element space (character set
    UTF-8 where the text is not ASCII, ASCII as statismo writes otherwise)."""
    h5py = _h5py()
    value = _fixed_string(text)
    tid = h5py.h5t.C_S1.copy()
    tid.set_size(value.dtype.itemsize)
    tid.set_strpad(h5py.h5t.STR_NULLTERM)
    if not text.isascii():
        tid.set_cset(h5py.h5t.CSET_UTF8)
    return value, tid, h5py.h5s.create_simple((1,))


def _write_string(group: Any, name: str, text: str) -> None:
    h5py = _h5py()
    value, tid, space = _nullterm_string(text)
    dset = h5py.h5d.create(group.id, name.encode(), tid, space)
    dset.write(h5py.h5s.ALL, h5py.h5s.ALL, value, mtype=tid)


def _write_string_attribute(group: Any, name: str, text: str) -> None:
    value, tid, space = _nullterm_string(text)
    attr = _h5py().h5a.create(group.id, name.encode(), tid, space)
    attr.write(value, mtype=tid)


def _read_string(value: Any) -> str:
    arr = np.asarray(value).reshape(-1)
    item = arr[0] if arr.size else b""
    if isinstance(item, bytes):
        return item.split(b"\0", 1)[0].decode("utf-8", errors="replace")
    return str(item)


def write_statismo(
    path: str | os.PathLike[str], model: ShapeModel, *, overwrite: bool = False
) -> str:
    """Write ``model`` as a statismo HDF5 file (readable by statismo and scalismo), atomically.

    The layout is described in the module documentation; it is the layout scalismo writes.

    Parameters
    ----------
    path : str or path-like
        ``.h5`` file.
    model : ShapeModel
    overwrite : bool, optional
        Replace an existing file. Default ``False``.

    Returns
    -------
    str
        The path written.

    References
    ----------
    .. [1] M. Lüthi, R. Blanc, T. Albrecht, et al., "Statismo - A framework for PCA based
       statistical models", The Insight Journal, 2012. :doi:`10.54294/4ha7at`
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    if not path.lower().endswith((".h5", ".hdf5")):
        raise ValueError(f"`path` must end with .h5, got {path!r}")
    if model.faces.size and model.faces.max() > np.iinfo(np.int32).max:
        raise ValueError("`model` has more vertices than statismo's int32 cells can index")
    h5py = _h5py()
    sd = model.standard_deviations
    safe = np.where(sd > 0, sd, 1.0)
    stamp = datetime.datetime.now().strftime("%a %b %d %H:%M:%S %Y")

    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as h5:
            version = h5.create_group("version")
            version.create_dataset("majorVersion", data=np.int32(0))
            version.create_dataset("minorVersion", data=np.int32(9))
            grp = h5.create_group("model")
            grp.create_dataset("mean", data=model.mean.reshape(-1).astype(np.float32))
            grp.create_dataset("pcaBasis", data=model.basis.astype(np.float32))
            grp.create_dataset("pcaVariance", data=model.variances.astype(np.float32))
            grp.create_dataset(
                "noiseVariance", data=np.array([model.noise_variance], dtype=np.float32)
            )
            rep = h5.create_group("representer")
            _write_string_attribute(rep, "name", "itkStandardMeshRepresenter")
            _write_string_attribute(rep, "version/majorVersion", "0")
            _write_string_attribute(rep, "version/minorVersion", "9")
            _write_string_attribute(rep, "datasetType", "POLYGON_MESH")
            rep.create_dataset("points", data=model.mean.T.astype(np.float32))
            rep.create_dataset("cells", data=model.faces.T.astype(np.int32))
            info = h5.create_group("modelinfo")
            _write_string(info, "build-time", stamp)
            if model.scores.shape[0] > 0 and model.number_of_modes > 0:
                info.create_dataset("scores", data=(model.scores / safe).T.astype(np.float32))
            builder = info.create_group("modelBuilder-0")
            _write_string(builder, "builderName", BUILDER_NAME)
            _write_string(builder, "buildTime", stamp)
            data_info = builder.create_group("dataInfo")
            for i, name in enumerate(model.names):
                _write_string(data_info, f"URI_{i}", name)
            parameters = builder.create_group("parameters")
            _write_string(parameters, "NoiseVariance", repr(float(model.noise_variance)))
            _write_string(parameters, "TotalVariance", repr(float(model.total_variance)))
            _write_string(parameters, "Scaling", "1" if model.scaling else "0")

    return atomic_write(path, write, overwrite=overwrite)


def _builder_entries(h5: Any, group: str) -> dict[str, str]:
    """The string entries of ``modelinfo/modelBuilder-0/<group>`` (empty when absent)."""
    key = f"modelinfo/modelBuilder-0/{group}"
    if key not in h5:
        return {}
    return {name: _read_string(h5[key][name][()]) for name in h5[key]}


def _orthonormal_modes(
    basis: np.ndarray, variances: np.ndarray, standardised: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal modes, variances and scores ``alpha`` of the stored model.

    A file's shape is ``mean + U diag(sqrt(var)) a`` with ``a ~ N(0, I)``. statismo's PCA
    builder stores an orthonormal ``U``; a Gaussian-process model (scalismo's low-rank GP, a
    Nyström approximation) stores eigenfunctions sampled at the points, which are neither of
    unit norm nor exactly orthogonal. The same distribution is then written with orthonormal
    modes from the SVD ``U diag(sqrt(var)) = Q S R^T``: modes ``Q``, variances ``S^2``,
    scores ``S R^T a``.
    """
    k = variances.size
    sd = np.sqrt(np.clip(variances, 0, None))
    gram = basis.T @ basis
    error = float(np.abs(gram - np.eye(k)).max(initial=0.0))
    if k == 0 or error <= 1e-12:
        return basis, variances, standardised * sd
    if error <= 1e-4:
        # Orthonormal to float32 precision (statismo's own files: ~2e-6 for thousands of
        # points): the nearest orthonormal basis U (U^T U)^(-1/2) (Loewdin), which moves each
        # column by about ``error``, far below the precision the file was written with.
        w, v = np.linalg.eigh(gram)
        basis = basis @ (v / np.sqrt(w)) @ v.T
        if error > 1e-6:
            _log.info(
                "statismo basis orthonormal to %.2g (float32): re-orthonormalised in float64",
                error,
            )
        return basis, variances, standardised * sd
    q, s, rt = np.linalg.svd(basis * sd, full_matrices=False)
    _log.info(
        "statismo basis is not orthonormal (max |U^T U - I| = %.3g): modes re-orthonormalised, "
        "same distribution",
        error,
    )
    # SVD signs are arbitrary: make each mode's largest component positive (reproducible).
    signs = np.sign(q[np.abs(q).argmax(axis=0), np.arange(k)])
    signs[signs == 0] = 1.0
    q, rt = q * signs, rt * signs[:, None]
    return q, s**2, (standardised @ rt.T) * s


def read_statismo(path: str | os.PathLike[str], *, template: Any = None) -> ShapeModel:
    """Read a statismo / scalismo polygon-mesh shape model.

    Versions 0.8 (``pcaBasis`` = ``U D``) and 0.9 (``U``) are read; a scalar or
    one-element ``noiseVariance`` is accepted. Scores are read from ``/modelinfo/scores`` when
    present (otherwise the model has no training scores); names from the first model builder's
    ``dataInfo``. An active shape model written by scalismo is read as its shape model (the
    intensity profiles are ignored). A basis that is not orthonormal (a Gaussian-process model
    stores eigenfunctions sampled at the points) is turned into orthonormal modes describing the
    same distribution (the SVD of ``U diag(sqrt(var))``), so the variances are in the input's
    units squared, as for a model built by :func:`build_shape_model`.

    Parameters
    ----------
    path : str or path-like
    template : open3d.geometry.TriangleMesh or (vertices, faces), optional
        Check that the model's triangles are this template's.

    Returns
    -------
    ShapeModel
        ``total_variance`` is the sum of the stored variances unless o3dreg wrote it.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise OSError(f"`path`: no such file {path!r}")
    h5py = _h5py()
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise OSError(f"`path`: {path!r} is not a readable HDF5 file ({exc})") from exc
    with h5:
        try:
            major = (
                int(np.asarray(h5["version/majorVersion"]).reshape(-1)[0]) if "version" in h5 else 0
            )
            minor = (
                int(np.asarray(h5["version/minorVersion"]).reshape(-1)[0]) if "version" in h5 else 8
            )
            flat_mean = np.asarray(h5["model/mean"], dtype=np.float64).reshape(-1)
            if flat_mean.size % 3:
                raise ValueError(
                    f"`path`: {path!r} has a model/mean of {flat_mean.size} values, not 3 per point"
                )
            mean = flat_mean.reshape(-1, 3)
            basis = np.asarray(h5["model/pcaBasis"], dtype=np.float64)
            variances = np.asarray(h5["model/pcaVariance"], dtype=np.float64).reshape(-1)
            noise_arr = np.asarray(h5["model/noiseVariance"], dtype=np.float64).reshape(-1)
            noise = float(noise_arr[0]) if noise_arr.size else 0.0
            cells = np.asarray(h5["representer/cells"])
            scores_t = (
                np.asarray(h5["modelinfo/scores"], dtype=np.float64)
                if "modelinfo/scores" in h5
                else None
            )
            parameters = _builder_entries(h5, "parameters")
            data_info = _builder_entries(h5, "dataInfo")
            # o3dreg's other layout keeps these in modelinfo (read the same way).
            if "modelinfo/total-variance" in h5:
                parameters.setdefault(
                    "TotalVariance", str(float(np.asarray(h5["modelinfo/total-variance"])))
                )
            if "modelinfo/scaling" in h5:
                parameters.setdefault("Scaling", str(int(np.asarray(h5["modelinfo/scaling"]))))
        except KeyError as exc:
            raise ValueError(
                f"`path`: {path!r} is not a statismo shape model (missing {exc})"
            ) from exc
    if (major, minor) not in ((0, 8), (0, 9)):
        raise ValueError(
            f"`path`: {path!r} has statismo version {major}.{minor}; 0.8 and 0.9 are read"
        )
    for name, values in (
        ("model/mean", mean),
        ("model/pcaBasis", basis),
        ("model/pcaVariance", variances),
        ("model/noiseVariance", noise_arr),
    ):
        if not np.all(np.isfinite(values)):
            raise ValueError(f"`path`: {path!r} has NaN or infinite values in {name}")
    # Rounding may leave a variance a hair below zero: zero it; a truly negative one is refused.
    tiny = 1e-9 * max(float(np.abs(variances).max(initial=0.0)), 1e-300)
    if np.any(variances < -tiny):
        raise ValueError(f"`path`: {path!r} has negative variances {variances[variances < 0]}")
    variances = np.clip(variances, 0.0, None)
    k = variances.size
    if basis.shape != (mean.size, k):
        raise ValueError(
            f"`path`: {path!r} has model/pcaBasis of shape {basis.shape}, expected "
            f"{(mean.size, k)} (model/mean of {mean.size} values, {k} variances)"
        )
    sd = np.sqrt(np.clip(variances, 0, None))
    if (major, minor) == (0, 8):
        basis = basis / np.where(sd > 0, sd, 1.0)
    if cells.ndim != 2 or 3 not in cells.shape:
        raise ValueError(
            f"`path`: {path!r} has representer/cells of shape {cells.shape}; triangles expected"
        )
    faces = cells.T if cells.shape[0] == 3 else cells
    standardised = np.zeros((0, k))
    # statismo writes a 1 x 1 zero matrix when a model has no scores (with one mode it would
    # read as one training shape of score 0; a model of one shape has no mode).
    placeholder = scores_t is not None and scores_t.shape == (1, 1) and not np.any(scores_t)
    if (
        scores_t is not None
        and scores_t.ndim == 2
        and scores_t.shape[0] == k > 0
        and not placeholder
    ):
        standardised = scores_t.T
    basis, variances, scores = _orthonormal_modes(basis, variances, standardised)
    uris = [data_info.get(f"URI_{i}") for i in range(scores.shape[0])]
    names = (
        tuple(str(u) for u in uris)
        if all(u is not None for u in uris)
        else tuple(f"shape{i:03d}" for i in range(scores.shape[0]))
    )
    try:
        total = float(parameters["TotalVariance"])
    except (KeyError, ValueError):
        total = float(variances.sum())
    if noise < 0:
        raise ValueError(f"`path`: {path!r} has a negative model/noiseVariance ({noise!r})")
    try:
        model = ShapeModel(
            mean=mean,
            modes=basis.T.reshape(k, mean.shape[0], 3),
            variances=variances,
            faces=faces.astype(np.int64),
            total_variance=total,
            scores=scores,
            names=names,
            scaling=parameters.get("Scaling", "0").strip() in ("1", "true", "True"),
            noise_variance=noise,
        )
    except ValueError as exc:
        raise ValueError(f"`path`: {path!r} holds no valid shape model: {exc}") from exc
    if template is not None:
        model.check_template(template)
    return model
