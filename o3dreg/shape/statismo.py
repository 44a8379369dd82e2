"""Export and import of shape models in the statismo / scalismo HDF5 layout (h5py).

The layout written (statismo format version 0.9, as ``StatisticalModel::Save`` and scalismo's
``StatisticalModelIO`` write it):

========================== ======================= ===============================================
path                       type                    content
========================== ======================= ===============================================
``/version/majorVersion``  int32 scalar            0
``/version/minorVersion``  int32 scalar            9 (pcaBasis holds the *orthonormal* basis)
``/model/mean``            float32 ``(3n,)``       x1, y1, z1, x2, ...
``/model/pcaBasis``        float32 ``(3n, k)``     orthonormal columns ``U`` (version 0.8 stored
                                                   ``U D``, ``D = sqrt(variance)``)
``/model/pcaVariance``     float32 ``(k,)``        variances
``/model/noiseVariance``   float32 scalar          isotropic noise variance
``/representer``           group, attributes       ``name`` = ``itkStandardMeshRepresenter``,
                                                   ``version`` = ``0.1``, ``datasetType`` =
                                                   ``POLYGON_MESH``
``/representer/points``    float32 ``(3, n)``      reference (mean) vertices, one column each
``/representer/cells``     uint32 ``(3, m)``       triangles, one column each
``/modelinfo/scores``      float32 ``(k, s)``      training coefficients (statismo stores the
                                                   standardised scores ``alpha / sqrt(var)``)
``/modelinfo/build-time``  string                  time stamp
========================== ======================= ===============================================
"""

from __future__ import annotations

import datetime
import os
from typing import Any

import numpy as np

from ..io.mesh import atomic_write
from .model import ShapeModel

__all__ = ["read_statismo", "write_statismo"]


def _h5py() -> Any:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is a dependency
        raise RuntimeError("statismo files need h5py: pip install h5py") from exc
    return h5py


def write_statismo(
    path: str | os.PathLike[str], model: ShapeModel, *, overwrite: bool = False
) -> str:
    """Write ``model`` as a statismo HDF5 file (readable by statismo and scalismo), atomically.

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
    h5py = _h5py()
    sd = model.standard_deviations
    safe = np.where(sd > 0, sd, 1.0)

    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as h5:
            version = h5.create_group("version")
            version.create_dataset("majorVersion", data=np.int32(0))
            version.create_dataset("minorVersion", data=np.int32(9))
            grp = h5.create_group("model")
            grp.create_dataset("mean", data=model.mean.reshape(-1).astype(np.float32))
            grp.create_dataset("pcaBasis", data=model.basis.astype(np.float32))
            grp.create_dataset("pcaVariance", data=model.variances.astype(np.float32))
            grp.create_dataset("noiseVariance", data=np.float32(model.noise_variance))
            rep = h5.create_group("representer")
            rep.attrs["name"] = np.bytes_("itkStandardMeshRepresenter")
            rep.attrs["version"] = np.bytes_("0.1")
            rep.attrs["datasetType"] = np.bytes_("POLYGON_MESH")
            rep.create_dataset("points", data=model.mean.T.astype(np.float32))
            rep.create_dataset("cells", data=model.faces.T.astype(np.uint32))
            info = h5.create_group("modelinfo")
            info.create_dataset("scores", data=(model.scores / safe).T.astype(np.float32))
            info.create_dataset("build-time", data=np.bytes_(datetime.datetime.now().isoformat()))
            info.create_dataset("total-variance", data=np.float64(model.total_variance))
            info.create_dataset("scaling", data=np.int32(model.scaling))
            builder = info.create_group("modelBuilder-0")
            builder.create_dataset("builderName", data=np.bytes_("o3dreg.build_shape_model"))
            builder.create_dataset("buildTime", data=np.bytes_(datetime.datetime.now().isoformat()))

    return atomic_write(path, write, overwrite=overwrite)


def read_statismo(path: str | os.PathLike[str], *, template: Any = None) -> ShapeModel:
    """Read a statismo / scalismo polygon-mesh shape model.

    Versions 0.8 (``pcaBasis`` = ``U D``) and 0.9 (orthonormal ``U``) are read; a scalar or
    one-element ``noiseVariance`` is accepted. Scores are read from ``/modelinfo/scores`` when
    present (otherwise the model has no training scores).

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
            major = int(np.asarray(h5["version/majorVersion"])) if "version" in h5 else 0
            minor = int(np.asarray(h5["version/minorVersion"])) if "version" in h5 else 8
            mean = np.asarray(h5["model/mean"], dtype=np.float64).reshape(-1, 3)
            basis = np.asarray(h5["model/pcaBasis"], dtype=np.float64)
            variances = np.asarray(h5["model/pcaVariance"], dtype=np.float64).reshape(-1)
            noise = float(np.asarray(h5["model/noiseVariance"], dtype=np.float64).reshape(-1)[0])
            cells = np.asarray(h5["representer/cells"])
            scores_t = (
                np.asarray(h5["modelinfo/scores"], dtype=np.float64)
                if "modelinfo/scores" in h5
                else None
            )
            total = (
                float(np.asarray(h5["modelinfo/total-variance"]))
                if "modelinfo/total-variance" in h5
                else float(variances.sum())
            )
            scaling = (
                bool(int(np.asarray(h5["modelinfo/scaling"])))
                if "modelinfo/scaling" in h5
                else False
            )
        except KeyError as exc:
            raise ValueError(
                f"`path`: {path!r} is not a statismo shape model (missing {exc})"
            ) from exc
    if (major, minor) not in ((0, 8), (0, 9)):
        raise ValueError(
            f"`path`: {path!r} has statismo version {major}.{minor}; 0.8 and 0.9 are read"
        )
    k = variances.size
    if basis.shape != (mean.size, k):
        raise ValueError(f"`path`: pcaBasis has shape {basis.shape}, expected {(mean.size, k)}")
    sd = np.sqrt(np.clip(variances, 0, None))
    if (major, minor) == (0, 8):
        basis = basis / np.where(sd > 0, sd, 1.0)
    if cells.ndim != 2 or 3 not in cells.shape:
        raise ValueError(f"`path`: representer/cells has shape {cells.shape}; triangles expected")
    faces = cells.T if cells.shape[0] == 3 else cells
    scores = np.zeros((0, k))
    if scores_t is not None and scores_t.ndim == 2 and scores_t.shape[0] == k:
        scores = scores_t.T * sd
    model = ShapeModel(
        mean=mean,
        modes=basis.T.reshape(k, -1, 3),
        variances=variances,
        faces=faces.astype(np.int64),
        total_variance=total,
        scores=scores,
        names=tuple(f"shape{i:03d}" for i in range(scores.shape[0])),
        scaling=scaling,
        noise_variance=noise,
    )
    if template is not None:
        model.check_template(template)
    return model
