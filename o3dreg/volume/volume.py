"""The :class:`Volume` value type: a 3D voxel array with the geometry that places it in the patient.

A :class:`Volume` is a 3D voxel array plus the geometry that places it in the patient:

* ``array`` has axes in (plane, row, column) order, as in scikit-image: ``array[p, r, c]``.
  For an axial CT the planes are the slices (z), the rows run along y and the columns along x.
* ``spacing`` is the voxel size in millimetres **in that same array-axis order**
  (plane, row, column), i.e. ``(dz, dy, dx)`` for an axial CT.
* ``origin`` is the world position (x, y, z) in millimetres of the centre of voxel ``[0, 0, 0]``.
* ``direction`` is the ``(3, 3)`` matrix of direction cosines as ITK, DICOM and NRRD write it:
  column 0 is the world direction of the column index (i, along x for an unrotated scan),
  column 1 of the row index (j), column 2 of the plane index (k). The identity is an unrotated
  axial scan.

World coordinates are millimetres in the file's patient space as SimpleITK reports it: LPS
(x to the patient's left, y to posterior, z to superior) for DICOM, NRRD and MetaImage. NIfTI
stores RAS; SimpleITK converts it to LPS (x and y negated), so every reader returns LPS.

The readers (one module per format) live in :mod:`o3dreg.volume.readers`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validation import as_points

__all__ = ["Volume", "as_direction", "as_vector3"]

# Tolerance on the orthonormality of direction cosines (files store them in float32 or text).
_DIRECTION_ATOL = 1e-3


def as_vector3(value: Any, name: str, *, positive: bool = False) -> np.ndarray:
    if isinstance(value, (str, bytes)) or not isinstance(
        value, (np.ndarray, list, tuple, int, float, np.number)
    ):
        raise TypeError(f"`{name}` must be a sequence of 3 numbers, got {type(value).__name__}")
    try:
        arr = np.array(value, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"`{name}` must hold 3 numbers, got {value!r}") from exc
    if arr.shape != (3,):
        raise ValueError(f"`{name}` must have shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite, got {arr.tolist()}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"`{name}` must be > 0 along every axis, got {arr.tolist()}")
    return arr


def as_direction(value: Any, name: str = "direction") -> np.ndarray:
    if value is None:
        return np.eye(3)
    if not isinstance(value, (np.ndarray, list, tuple)):
        raise TypeError(f"`{name}` must be a (3, 3) array, got {type(value).__name__}")
    try:
        arr = np.array(value, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"`{name}` must hold numbers, got {value!r}") from exc
    if arr.size == 9 and arr.ndim == 1:
        arr = arr.reshape(3, 3)  # ITK's flat, row-major form
    if arr.shape != (3, 3):
        raise ValueError(f"`{name}` must have shape (3, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite, got {arr.tolist()}")
    if not np.allclose(arr.T @ arr, np.eye(3), atol=_DIRECTION_ATOL):
        raise ValueError(
            f"`{name}` must be orthonormal (direction cosines), got {np.round(arr, 6).tolist()}"
        )
    return arr


@dataclass(frozen=True, eq=False, repr=False)
class Volume:
    """A 3D voxel array placed in world (patient) space, in millimetres.

    Parameters
    ----------
    array : (P, R, C) ndarray
        Voxel values in (plane, row, column) order: ``array[p, r, c]``. Real numbers or bool.
        The volume keeps a read-only view of it (no copy).
    spacing : (3,) array_like of float
        Voxel size in millimetres in array-axis order (plane, row, column) = (dz, dy, dx).
    origin : (3,) array_like of float, optional
        World (x, y, z) position in millimetres of the centre of voxel ``[0, 0, 0]``.
        Default ``(0, 0, 0)``.
    direction : (3, 3) array_like of float, optional
        Orthonormal direction cosines in the ITK / DICOM / NRRD convention: column 0 is the world
        direction of the column index, column 1 of the row index, column 2 of the plane index.
        Default identity (an unrotated axial scan).

    Notes
    -----
    The world position of voxel ``array[p, r, c]`` is::

        origin + direction @ ([c, r, p] * spacing[::-1])

    :meth:`index_to_world` computes it from indices in array order ``(p, r, c)``; :attr:`affine`
    is the same map as a 4x4 matrix acting on ``(c, r, p, 1)``, as nibabel and ITK write it.

    Examples
    --------
    >>> import numpy as np
    >>> v = Volume(np.zeros((3, 4, 5), np.int16), spacing=(2.5, 1.0, 0.5), origin=(10, 20, 30))
    >>> v.index_to_world([[1, 2, 4]]).tolist()
    [[12.0, 22.0, 32.5]]
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        array = self.array
        if not isinstance(array, np.ndarray):
            raise TypeError(f"`array` must be a numpy array, got {type(array).__name__}")
        if not (
            np.issubdtype(array.dtype, np.integer)
            or np.issubdtype(array.dtype, np.floating)
            or array.dtype == np.bool_
        ):
            raise TypeError(f"`array` must hold real numbers or bool, got dtype {array.dtype}")
        if array.ndim != 3:
            raise ValueError(
                f"`array` must be 3D (plane, row, column), got {array.ndim}D shape {array.shape}"
            )
        if array.size == 0:
            raise ValueError(f"`array` must not be empty, got shape {array.shape}")
        view = array.view()
        view.flags.writeable = False
        object.__setattr__(self, "array", view)
        object.__setattr__(self, "spacing", as_vector3(self.spacing, "spacing", positive=True))
        object.__setattr__(self, "origin", as_vector3(self.origin, "origin"))
        object.__setattr__(self, "direction", as_direction(self.direction))
        for name in ("spacing", "origin", "direction"):
            getattr(self, name).flags.writeable = False

    def __repr__(self) -> str:
        def fmt(values: np.ndarray) -> str:
            return "(" + ", ".join(f"{v:.6g}" for v in values) + ")"

        rotated = "" if np.allclose(self.direction, np.eye(3)) else ", rotated"
        return (
            f"Volume(shape={self.array.shape}, dtype={self.array.dtype}, "
            f"spacing={fmt(self.spacing)} mm, origin={fmt(self.origin)} mm{rotated})"
        )

    @property
    def shape(self) -> tuple[int, int, int]:
        """The array shape ``(P, R, C)``."""
        p, r, c = self.array.shape
        return (p, r, c)

    @property
    def affine(self) -> np.ndarray:
        """``(4, 4)`` map from voxel index ``(c, r, p, 1)`` (column first) to ``(x, y, z, 1)``.

        The same convention as nibabel's ``img.affine`` and ITK, but in LPS world coordinates.
        """
        out = np.eye(4)
        out[:3, :3] = self.direction * self.spacing[::-1]
        out[:3, 3] = self.origin
        return out

    def index_to_world(self, index: Any) -> np.ndarray:
        """World (x, y, z) millimetres of continuous voxel indices in array order.

        Parameters
        ----------
        index : (n, 3) array_like
            Indices ``(p, r, c)`` in array-axis order (as returned by scikit-image).

        Returns
        -------
        points : (n, 3) float64 ndarray
        """
        idx = as_points(index, "index", allow_empty=True)
        linear = self.direction * self.spacing[::-1]
        return idx[:, ::-1] @ linear.T + self.origin

    def world_to_index(self, points: Any) -> np.ndarray:
        """Continuous voxel indices ``(p, r, c)`` in array order of world points (n, 3) in mm."""
        pts = as_points(points, "points", allow_empty=True)
        ijk = (pts - self.origin) @ self.direction / self.spacing[::-1]
        return np.ascontiguousarray(ijk[:, ::-1])

    def crop(self, start: Sequence[int], stop: Sequence[int]) -> Volume:
        """The sub-volume ``array[start[0]:stop[0], ...]`` with its origin moved (a view, no copy).

        Parameters
        ----------
        start, stop : sequence of 3 int
            Half-open index ranges in array-axis order; clipped to the array.
        """
        for name, value in (("start", start), ("stop", stop)):
            given = np.asarray(value)
            if given.shape != (3,) or given.dtype.kind not in "iu":
                raise ValueError(f"`{name}` must be 3 integer indices, got {value!r}")
        lo = [max(0, int(s)) for s in start]
        hi = [min(n, int(e)) for n, e in zip(self.array.shape, stop, strict=True)]
        if any(h <= b for b, h in zip(lo, hi, strict=True)):
            raise ValueError(f"crop box {lo}..{hi} is empty for shape {self.array.shape}")
        sub = self.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        origin = self.index_to_world(np.array([lo], dtype=np.float64))[0]
        return Volume(sub, self.spacing, origin, self.direction)
