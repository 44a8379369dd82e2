"""Headerless raw slices (or one raw file) as a :class:`Volume`."""

from __future__ import annotations

import glob
import logging
import os
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..volume import Volume, as_direction, as_vector3

__all__ = ["read_raw_slices"]

logger = logging.getLogger("o3dreg")

_BYTE_ORDERS = {"little": "<", "big": ">", "native": "="}


def _natural_key(text: str) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def read_raw_slices(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    shape: Sequence[int],
    dtype: Any,
    spacing: Any,
    byte_order: str = "little",
    origin: Any = (0.0, 0.0, 0.0),
    direction: Any = None,
    header_bytes: int = 0,
) -> Volume:
    """Read a stack of headerless raw slices (or one raw file) as a :class:`Volume`.

    Parameters
    ----------
    paths : str, path-like or sequence of them
        The slice files in plane order, or one string with glob wildcards (``*``, ``?``, ``[``)
        whose matches are sorted naturally (``slice.2`` before ``slice.10``), or one file
        holding the whole volume.
    shape : sequence of int
        ``(rows, columns)`` of one slice, or ``(planes, rows, columns)`` of the whole volume.
    dtype : numpy dtype-like
        The stored voxel type, e.g. ``"int16"``.
    spacing : (3,) sequence of float
        Voxel size in millimetres in array-axis order (plane, row, column).
    byte_order : {"little", "big", "native"}, optional
        Byte order of the files. Default ``"little"``.
    origin, direction : optional
        Geometry as in :class:`Volume`.
    header_bytes : int, optional
        Bytes to skip at the start of every file. Default 0.

    Returns
    -------
    volume : Volume
        Voxel values in native byte order, shape ``(planes, rows, columns)``.

    Raises
    ------
    OSError
        A file is missing, or its size does not match ``shape`` and ``dtype``.
    ValueError
        Bad ``shape``, ``byte_order``, ``spacing``; no file matches the pattern.
    """
    files = _raw_file_list(paths)
    if not isinstance(shape, (list, tuple, np.ndarray)) or len(shape) not in (2, 3):
        raise ValueError(
            f"`shape` must be (rows, columns) or (planes, rows, columns), got {shape!r}"
        )
    if any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1 for s in shape):
        raise ValueError(f"`shape` must hold positive integers, got {tuple(shape)!r}")
    if byte_order not in _BYTE_ORDERS:
        raise ValueError(f"`byte_order` must be one of {sorted(_BYTE_ORDERS)}, got {byte_order!r}")
    try:
        stored = np.dtype(dtype)
    except TypeError as exc:
        raise TypeError(f"`dtype` must be a numpy dtype, got {dtype!r}") from exc
    if not (np.issubdtype(stored, np.integer) or np.issubdtype(stored, np.floating)):
        raise ValueError(f"`dtype` must be an integer or floating type, got {stored}")
    if isinstance(header_bytes, bool) or not isinstance(header_bytes, (int, np.integer)):
        raise TypeError(f"`header_bytes` must be an int, got {type(header_bytes).__name__}")
    if header_bytes < 0:
        raise ValueError(f"`header_bytes` must be >= 0, got {header_bytes}")
    spacing_arr = as_vector3(spacing, "spacing", positive=True)
    origin_arr = as_vector3(origin, "origin")
    direction_arr = as_direction(direction)
    stored = stored.newbyteorder(_BYTE_ORDERS[byte_order])
    if len(shape) == 3:
        full = (int(shape[0]), int(shape[1]), int(shape[2]))
        if full[0] % len(files):
            raise ValueError(
                f"`shape` {full} has {full[0]} planes, not a multiple of the {len(files)} files"
            )
    else:
        full = (len(files), int(shape[0]), int(shape[1]))
    planes_per_file = full[0] // len(files)
    array = np.empty(full, dtype=stored.newbyteorder("="))
    per_file = planes_per_file * full[1] * full[2]
    for n, name in enumerate(files):
        if not os.path.isfile(name):
            raise OSError(f"`paths`: no such file {name!r}")
        expected = header_bytes + per_file * stored.itemsize
        size = os.path.getsize(name)
        if size != expected:
            raise OSError(
                f"`paths`: {name!r} has {size} bytes, expected {expected} "
                f"({planes_per_file} x {full[1]} x {full[2]} values of {stored.name}"
                f"{f' after {header_bytes} header bytes' if header_bytes else ''})"
            )
        data = np.fromfile(name, dtype=stored, count=per_file, offset=header_bytes)
        array[n * planes_per_file : (n + 1) * planes_per_file] = data.reshape(
            planes_per_file, full[1], full[2]
        )
    volume = Volume(array, spacing_arr, origin_arr, direction_arr)
    logger.info("read %d raw file(s): %r", len(files), volume)
    return volume


def _raw_file_list(paths: Any) -> list[str]:
    if isinstance(paths, (str, os.PathLike)):
        text = os.fspath(paths)
        if any(ch in text for ch in "*?["):
            files = sorted(glob.glob(text), key=_natural_key)
            if not files:
                raise ValueError(f"`paths`: no file matches {text!r}")
            return files
        return [text]
    if not isinstance(paths, (list, tuple)):
        raise TypeError(f"`paths` must be a path, a glob pattern or a list of paths, got {paths!r}")
    if not paths:
        raise ValueError("`paths` must name at least one file, got an empty list")
    for p in paths:
        if not isinstance(p, (str, os.PathLike)):
            raise TypeError(f"`paths` must hold paths, got {type(p).__name__}")
    return [os.fspath(p) for p in paths]
