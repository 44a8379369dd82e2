"""Files of a shape model: the ``.npz`` archive of :meth:`ShapeModel.save` and the PLY meshes of
the mean and the modes (:meth:`ShapeModel.write_meshes`).

The functions take the model as ``Any``: :class:`~o3dreg.ShapeModel` calls them, and this module
does not import the value type back (no import circle).

The statismo HDF5 layout is in :mod:`.statismo`.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from .._validation import check_bool
from ..io.archive import read_archive, write_archive
from ..io.mesh import write_triangle_mesh

__all__ = ["read_model_archive", "write_model_archive", "write_model_meshes"]

_FORMAT = "o3dreg.ShapeModel"
_VERSION = 1


def write_model_archive(
    model: Any, path: str | os.PathLike[str], *, overwrite: bool = False
) -> str:
    """Write the whole model (with the template triangles) to a ``.npz`` file, atomically."""
    arrays: dict[str, Any] = {
        "mean": model.mean,
        "modes": model.modes,
        "variances": model.variances,
        "faces": model.faces,
        "total_variance": np.array(model.total_variance),
        "scores": model.scores,
        "names": np.array(json.dumps(list(model.names))),
        "scaling": np.array(model.scaling),
        "noise_variance": np.array(model.noise_variance),
    }
    return write_archive(path, arrays, kind=_FORMAT, version=_VERSION, overwrite=overwrite)


def read_model_archive(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The fields of a model written by :func:`write_model_archive`, as keyword arguments of
    :class:`ShapeModel` (which validates them)."""
    data = read_archive(path, kind=_FORMAT, version=_VERSION, what="ShapeModel")
    try:
        return {
            "mean": data["mean"],
            "modes": data["modes"],
            "variances": data["variances"],
            "faces": data["faces"],
            "total_variance": float(data["total_variance"]),
            "scores": data["scores"],
            "names": tuple(json.loads(str(data["names"]))),
            "scaling": bool(data["scaling"]),
            "noise_variance": float(data["noise_variance"]),
        }
    except KeyError as exc:
        raise ValueError(f"`path`: {os.fspath(path)!r} is a ShapeModel without {exc}") from exc
    except (json.JSONDecodeError, TypeError, ValueError) as exc:
        raise ValueError(f"`path`: {os.fspath(path)!r} holds a damaged ShapeModel ({exc})") from exc


def write_model_meshes(
    model: Any,
    folder: str | os.PathLike[str],
    *,
    modes: Any = None,
    standard_deviations: Any = (-3.0, 3.0),
    overwrite: bool = False,
) -> list[str]:
    """Write ``mean.ply`` and ``mode{i}_{c:+g}sd.ply`` (1-based ``i``) into ``folder`` (made
    when missing). The arguments and the files already there are checked before anything is
    written: a refused call leaves the folder as it was."""
    overwrite = check_bool(overwrite, "overwrite")
    folder = os.fspath(folder)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OSError(f"`folder`: {folder!r} exists and is not a folder")
    meshes = {"mean.ply": model.mesh()}
    for (m, c), mesh in model.mode_meshes(modes, standard_deviations).items():
        meshes[f"mode{m + 1}_{c:+g}sd.ply"] = mesh
    paths = {name: os.path.join(folder, name) for name in meshes}
    if not overwrite:
        present = [name for name, path in paths.items() if os.path.exists(path)]
        if present:
            raise OSError(
                f"`folder`: {folder!r} already holds {', '.join(present)}; pass overwrite=True "
                "(--overwrite) to replace them; nothing written"
            )
    os.makedirs(folder, exist_ok=True)  # as the docs' examples write into a new "modes" folder
    return [
        write_triangle_mesh(paths[name], mesh, overwrite=overwrite) for name, mesh in meshes.items()
    ]
