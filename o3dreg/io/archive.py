"""Versioned ``.npz`` archives: the file format of deformations and shape models."""

from __future__ import annotations

import os
import zipfile
import zlib
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
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    if not path.endswith(".npz"):
        raise ValueError(f"`path` must end with .npz, got {path!r}")
    payload = {"format": np.array(kind), "version": np.array(version), **arrays}

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)

    return atomic_write(path, write, overwrite=overwrite)


def read_archive(
    path: Any, *, kind: str, version: int, what: str, finite: bool = True
) -> dict[str, np.ndarray]:
    """Read an archive written by :func:`write_archive`, checking its tag and version.

    Every member is read (so a truncated file or a bad CRC is found here, not later) and, with
    ``finite``, every floating-point member must be finite.

    Raises ``OSError`` for a missing or unreadable file and ``ValueError`` for a file that is
    not a complete ``.npz`` archive (empty, truncated, bad CRC), holds something else (``what``
    names it in the message), a newer version, or NaN / infinite values.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise OSError(f"`path`: no such file {path!r}")
    if not os.access(path, os.R_OK):
        raise OSError(f"`path`: {path!r} is not readable")
    if os.path.getsize(path) == 0:
        raise ValueError(f"`path`: {path!r} is empty, not an o3dreg {what}")
    try:
        with zipfile.ZipFile(path) as archive:
            arrays = {
                member.removesuffix(".npy"): _read_member(archive, member)
                for member in archive.namelist()
            }
    except _CORRUPT as exc:
        raise ValueError(
            f"`path`: {path!r} is not a complete .npz archive (truncated or corrupt: "
            f"{type(exc).__name__}: {exc})"
        ) from exc
    if "format" not in arrays or str(arrays["format"]) != kind:
        raise ValueError(f"`path`: {path!r} does not hold an o3dreg {what}")
    try:
        stored = int(arrays["version"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"`path`: {path!r} has no valid format version") from exc
    if stored > version:
        raise ValueError(
            f"`path`: {path!r} has format version {stored}, this o3dreg reads up to {version}"
        )
    if finite:
        for name, value in arrays.items():
            if np.issubdtype(value.dtype, np.inexact) and not np.all(np.isfinite(value)):
                raise ValueError(f"`path`: {path!r}: {name} holds NaN or infinite values")
    return arrays


def _read_member(archive: zipfile.ZipFile, member: str) -> Any:
    """One member as ``np.load`` reads it, decompressed once (``testzip`` and then ``np.load``
    would decompress it twice); reading it to its end makes zipfile check its CRC-32."""
    with archive.open(member) as fh:
        magic = fh.read(len(np.lib.format.MAGIC_PREFIX))
        fh.seek(0)
        if magic != np.lib.format.MAGIC_PREFIX:
            return fh.read()
        array = np.lib.format.read_array(fh, allow_pickle=False)
        fh.read()  # to the end: a bad CRC-32 raises zipfile.BadZipFile here
    return array


# What numpy and zipfile raise for an empty, truncated or damaged archive.
_CORRUPT = (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)
