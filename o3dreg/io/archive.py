"""Versioned ``.npz`` archives: the file format of deformations and shape models."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .mesh import atomic_write


def write_archive(
    path: str | os.PathLike[str],
    arrays: dict[str, Any],
    *,
    kind: str,
    version: int,
    overwrite: bool,
) -> str:
    """Write ``arrays`` with a ``format`` tag and ``version`` to a compressed ``.npz``, atomically."""
    path = os.fspath(path)
    if not path.endswith(".npz"):
        raise ValueError(f"`path` must end with .npz, got {path!r}")
    payload = {"format": np.array(kind), "version": np.array(version), **arrays}

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)

    return atomic_write(path, write, overwrite=overwrite)


def read_archive(path: Any, *, kind: str, version: int, what: str) -> dict[str, np.ndarray]:
    """Read an archive written by :func:`write_archive`, checking its tag and version.

    Raises ``OSError`` for a missing or unreadable file and ``ValueError`` for a file holding
    something else (``what`` names it in the message) or a newer version.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise OSError(f"`path`: no such file {path!r}")
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise OSError(f"`path`: {path!r} is not a readable .npz file ({exc})") from exc
    with data:
        if "format" not in data or str(data["format"]) != kind:
            raise ValueError(f"`path`: {path!r} does not hold an o3dreg {what}")
        if int(data["version"]) > version:
            raise ValueError(
                f"`path`: {path!r} has format version {int(data['version'])}, "
                f"this o3dreg reads up to {version}"
            )
        return {name: data[name] for name in data.files}
