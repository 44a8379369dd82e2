"""Volumes (CT scans, segmentation masks) with their geometry, and readers for the usual formats.

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

Formats are read with SimpleITK (DICOM series, NIfTI, NRRD, MetaImage); NRRD headers that
SimpleITK rejects (for example a ``spacings`` line together with a ``space`` field, or a
``data file`` list of slices) are read with pynrrd instead.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["VOLUME_SUFFIXES", "Volume", "read_raw_slices", "read_volume"]

logger = logging.getLogger("o3dreg")

#: File suffixes :func:`read_volume` reads (a folder is read as a DICOM series).
VOLUME_SUFFIXES = (".dcm", ".nii", ".nii.gz", ".nrrd", ".nhdr", ".mhd", ".mha")

# Relative tolerance on slice gaps before a DICOM series is declared non-uniform: scanners write
# positions with ~1e-3 mm precision, a missing slice changes one gap by 100 %.
_SLICE_GAP_RTOL = 0.02
# Tolerance on the orthonormality of direction cosines (files store them in float32 or text).
_DIRECTION_ATOL = 1e-3


def _as_vector3(value: Any, name: str, *, positive: bool = False) -> np.ndarray:
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


def _as_direction(value: Any, name: str = "direction") -> np.ndarray:
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
        object.__setattr__(self, "spacing", _as_vector3(self.spacing, "spacing", positive=True))
        object.__setattr__(self, "origin", _as_vector3(self.origin, "origin"))
        object.__setattr__(self, "direction", _as_direction(self.direction))
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
        from .._validation import as_points

        idx = as_points(index, "index", allow_empty=True)
        return self._index_to_world(idx)

    def _index_to_world(self, idx: np.ndarray) -> np.ndarray:
        linear = self.direction * self.spacing[::-1]
        return idx[:, ::-1] @ linear.T + self.origin

    def world_to_index(self, points: Any) -> np.ndarray:
        """Continuous voxel indices ``(p, r, c)`` in array order of world points (n, 3) in mm."""
        from .._validation import as_points

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
        if len(start) != 3 or len(stop) != 3:
            raise ValueError(
                f"`start` and `stop` must have 3 entries, got {len(start)} and {len(stop)}"
            )
        lo = [max(0, int(s)) for s in start]
        hi = [min(n, int(e)) for n, e in zip(self.array.shape, stop, strict=True)]
        if any(h <= b for b, h in zip(lo, hi, strict=True)):
            raise ValueError(f"crop box {lo}..{hi} is empty for shape {self.array.shape}")
        sub = self.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        origin = self._index_to_world(np.array([lo], dtype=np.float64))[0]
        return Volume(sub, self.spacing, origin, self.direction)


# --------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------


def read_volume(path: str | os.PathLike[str], *, series_uid: str | None = None) -> Volume:
    """Read a CT scan or a mask as a :class:`Volume` (values in the file's units; HU for CT).

    Parameters
    ----------
    path : str or path-like
        A folder of DICOM slices (one series), a single DICOM file (``.dcm`` or no suffix), a
        NIfTI file (``.nii``, ``.nii.gz``), an NRRD file (``.nrrd``, or ``.nhdr`` with detached
        data, including a ``data file`` list of slices) or a MetaImage file (``.mhd``, ``.mha``).
    series_uid : str, optional
        The DICOM SeriesInstanceUID to read when the folder holds several series. Without it a
        folder with more than one series raises ``ValueError`` listing them.

    Returns
    -------
    volume : Volume
        Geometry in LPS world millimetres (see the module notes). DICOM values are rescaled
        with each slice's RescaleSlope and RescaleIntercept, so CT values are Hounsfield units;
        the dtype is float32 when the rescale is not integral.

    Raises
    ------
    OSError
        Missing, empty or unreadable file; a folder with no DICOM series.
    ValueError
        Unknown suffix; several DICOM series and no ``series_uid``; missing slices, duplicate
        slices or non-uniform slice spacing; an image that is not 2D or 3D.

    Notes
    -----
    A single 2D image (e.g. one DICOM slice) is returned as a volume with one plane; its plane
    spacing is the slice thickness where the file has one. Such a volume has no surface.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    if series_uid is not None and not isinstance(series_uid, str):
        raise TypeError(f"`series_uid` must be a str, got {type(series_uid).__name__}")
    path = os.fspath(path)
    if os.path.isdir(path):
        return _read_dicom_series(path, series_uid)
    if not os.path.exists(path):
        raise OSError(f"`path`: no such file or folder {path!r}")
    if not os.access(path, os.R_OK):
        raise OSError(f"`path`: {path!r} is not readable")
    if os.path.getsize(path) == 0:
        raise OSError(f"`path`: {path!r} is empty")
    suffix = _volume_suffix(path)
    if suffix in (".nrrd", ".nhdr"):
        return _read_nrrd(path)
    return _read_sitk_file(path)


def _volume_suffix(path: str) -> str:
    lower = path.lower()
    for suffix in VOLUME_SUFFIXES:
        if lower.endswith(suffix):
            return suffix
    if _is_dicom_file(path):
        return ".dcm"
    raise ValueError(
        f"`path` must be a folder of DICOM slices or a file ending with "
        f"{', '.join(VOLUME_SUFFIXES)} (or a DICOM file), got {path!r}"
    )


def _is_dicom_file(path: str) -> bool:
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def _sitk_error(exc: Exception) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in reversed(lines):
        if "ERROR" in line or "Error" in line or "error" in line:
            return line
    return lines[-1] if lines else type(exc).__name__


def _from_sitk(image: Any, source: str) -> Volume:
    import SimpleITK as sitk

    dim = image.GetDimension()
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(
            f"`path`: {source!r} holds {image.GetNumberOfComponentsPerPixel()} components per "
            "voxel; a volume needs one (a scalar image)"
        )
    if dim == 4:
        size = image.GetSize()
        if size[3] != 1:
            raise ValueError(
                f"`path`: {source!r} is a 4D image of size {size}; a volume needs 3 dimensions"
            )
        image = sitk.Extract(image, [*size[:3], 0], [0, 0, 0, 0])
        dim = 3
    if dim == 2:
        array = sitk.GetArrayFromImage(image)[np.newaxis]
        sx, sy = image.GetSpacing()
        thickness = _slice_thickness(image)
        ox, oy = image.GetOrigin()
        direction = np.eye(3)
        direction[:2, :2] = np.asarray(image.GetDirection(), dtype=np.float64).reshape(2, 2)
        return Volume(array, np.array([thickness, sy, sx]), np.array([ox, oy, 0.0]), direction)
    if dim != 3:
        raise ValueError(f"`path`: {source!r} is a {dim}D image; a volume needs 3 dimensions")
    array = sitk.GetArrayFromImage(image)
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)[::-1]
    origin = np.asarray(image.GetOrigin(), dtype=np.float64)
    return Volume(array, spacing, origin, np.asarray(image.GetDirection(), dtype=np.float64))


def _slice_thickness(image: Any) -> float:
    try:
        if image.HasMetaDataKey("0018|0050"):
            value = float(image.GetMetaData("0018|0050"))
            if np.isfinite(value) and value > 0:
                return value
    except (RuntimeError, ValueError):
        pass
    return 1.0


def _read_sitk_file(path: str) -> Volume:
    import SimpleITK as sitk

    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        raise OSError(f"`path`: could not read {path!r}: {_sitk_error(exc)}") from exc
    volume = _from_sitk(image, path)
    logger.info("read %s: %r", path, volume)
    return volume


# -- DICOM -----------------------------------------------------------------------------------


def _read_dicom_series(folder: str, series_uid: str | None) -> Volume:
    import SimpleITK as sitk

    series = list(sitk.ImageSeriesReader.GetGDCMSeriesIDs(folder))
    if not series:
        raise OSError(f"`path`: no DICOM series found in folder {folder!r}")
    if series_uid is None:
        if len(series) > 1:
            listing = "; ".join(
                f"{uid} ({len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(folder, uid))} files)"
                for uid in sorted(series)
            )
            raise ValueError(
                f"`path`: folder {folder!r} holds {len(series)} DICOM series; pass `series_uid` "
                f"to pick one of: {listing}"
            )
        series_uid = series[0]
    elif series_uid not in series:
        raise ValueError(
            f"`series_uid` must be one of the series in {folder!r}: {sorted(series)}, "
            f"got {series_uid!r}"
        )
    files = list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(folder, series_uid))
    headers = [_dicom_header(f) for f in files]
    _check_slice_positions(files, headers, series_uid)
    rescales = {(h["slope"], h["intercept"]) for h in headers}
    integral = all(float(s).is_integer() and float(i).is_integer() for s, i in rescales)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    if len(rescales) > 1 or not integral:
        # Each slice is rescaled with its own slope and intercept; a float type keeps them all.
        reader.SetOutputPixelType(sitk.sitkFloat32)
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        raise OSError(
            f"`path`: could not read DICOM series in {folder!r}: {_sitk_error(exc)}"
        ) from exc
    if len(files) == 1:
        volume = _from_sitk(image, folder)
        # One slice: keep the slice thickness as plane spacing.
        volume = Volume(
            volume.array,
            np.array([headers[0]["thickness"], *volume.spacing[1:]]),
            volume.origin,
            volume.direction,
        )
    else:
        volume = _from_sitk(image, folder)
    logger.info(
        "read DICOM series %s (%d slices) from %s: %r", series_uid, len(files), folder, volume
    )
    return volume


def _dicom_header(path: str) -> dict[str, Any]:
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    try:
        reader.ReadImageInformation()
    except RuntimeError as exc:
        raise OSError(f"`path`: could not read DICOM file {path!r}: {_sitk_error(exc)}") from exc

    def tag(key: str, default: str | None = None) -> str | None:
        return reader.GetMetaData(key) if reader.HasMetaDataKey(key) else default

    def numbers(key: str) -> list[float] | None:
        text = tag(key)
        if text is None:
            return None
        try:
            return [float(v) for v in text.strip().split("\\")]
        except ValueError:
            return None

    thickness = numbers("0018|0050")
    return {
        "position": numbers("0020|0032"),
        "orientation": numbers("0020|0037"),
        "slope": float((numbers("0028|1053") or [1.0])[0]),
        "intercept": float((numbers("0028|1052") or [0.0])[0]),
        "thickness": thickness[0] if thickness and thickness[0] > 0 else 1.0,
    }


def _check_slice_positions(files: list[str], headers: list[dict[str, Any]], uid: str) -> None:
    if len(files) < 2:
        return
    if any(h["position"] is None or h["orientation"] is None for h in headers):
        raise ValueError(
            f"DICOM series {uid}: some slices have no ImagePositionPatient or "
            "ImageOrientationPatient; cannot place the slices"
        )
    orientation = np.asarray(headers[0]["orientation"], dtype=np.float64)
    normal = np.cross(orientation[:3], orientation[3:])
    positions = np.array([np.dot(h["position"], normal) for h in headers])
    gaps = np.diff(positions)
    order = "ascending" if np.median(gaps) > 0 else "descending"
    gaps = np.abs(gaps)
    duplicates = np.flatnonzero(gaps < 1e-3)
    if duplicates.size:
        names = ", ".join(os.path.basename(files[i + 1]) for i in duplicates[:5])
        raise ValueError(
            f"DICOM series {uid}: {duplicates.size} slice(s) share a position with the previous "
            f"one ({names}); the folder may hold duplicated or multi-phase images"
        )
    typical = float(np.median(gaps))
    bad = np.flatnonzero(np.abs(gaps - typical) > _SLICE_GAP_RTOL * typical)
    if bad.size:
        details = ", ".join(f"{gaps[i]:.4g} mm after {os.path.basename(files[i])}" for i in bad[:5])
        raise ValueError(
            f"DICOM series {uid}: non-uniform slice spacing (typical {typical:.4g} mm, "
            f"{order}; {bad.size} irregular gap(s): {details}); missing slices?"
        )


# -- NRRD ------------------------------------------------------------------------------------

# NRRD spaces and the sign flips that take them to LPS.
_NRRD_SPACE_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
}


def _read_nrrd(path: str) -> Volume:
    import SimpleITK as sitk

    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        logger.debug("SimpleITK could not read %s (%s); trying pynrrd", path, _sitk_error(exc))
    else:
        volume = _from_sitk(image, path)
        logger.info("read %s: %r", path, volume)
        return volume
    volume = _read_nrrd_pynrrd(path)
    logger.info("read %s with pynrrd: %r", path, volume)
    return volume


def _read_nrrd_pynrrd(path: str) -> Volume:
    import nrrd

    try:
        header = nrrd.read_header(path)
    except (nrrd.NRRDError, OSError, ValueError, UnicodeDecodeError) as exc:
        raise OSError(f"`path`: could not read NRRD header {path!r}: {exc}") from exc
    sizes = [int(s) for s in header.get("sizes", [])]
    if len(sizes) != 3:
        if len(sizes) == 2:
            sizes = [*sizes, 1]
        else:
            raise ValueError(f"`path`: {path!r} is a {len(sizes)}D NRRD; a volume needs 3")
    spacing_xyz, origin, direction = _nrrd_geometry(header, path)
    spacing = spacing_xyz[::-1]
    data_file = header.get("data file") or header.get("datafile")
    slice_files = _nrrd_slice_files(data_file, path) if data_file else None
    if slice_files is not None:
        if header.get("encoding", "raw") != "raw":
            raise ValueError(
                f"`path`: {path!r} lists {len(slice_files)} data files with encoding "
                f"{header.get('encoding')!r}; only raw encoding is supported for lists of files"
            )
        dtype = _nrrd_dtype(header, path)
        return read_raw_slices(
            slice_files,
            shape=(sizes[1], sizes[0]),
            dtype=dtype,
            byte_order=header.get("endian", "little") if dtype.itemsize > 1 else "native",
            spacing=spacing,
            origin=origin,
            direction=direction,
        )
    try:
        data, _ = nrrd.read(path, index_order="C")
    except (nrrd.NRRDError, OSError, ValueError) as exc:
        raise OSError(f"`path`: could not read NRRD data of {path!r}: {exc}") from exc
    if data.ndim == 2:
        data = data[np.newaxis]
    return Volume(np.ascontiguousarray(data), spacing, origin, direction)


_NRRD_TYPES = {
    "int8": "i1", "signed char": "i1", "uchar": "u1", "unsigned char": "u1", "uint8": "u1",
    "short": "i2", "short int": "i2", "signed short": "i2", "int16": "i2",
    "ushort": "u2", "unsigned short": "u2", "uint16": "u2",
    "int": "i4", "signed int": "i4", "int32": "i4", "uint": "u4", "unsigned int": "u4",
    "uint32": "u4", "longlong": "i8", "int64": "i8", "ulonglong": "u8", "uint64": "u8",
    "float": "f4", "double": "f8",
}  # fmt: skip


def _nrrd_dtype(header: dict[str, Any], path: str) -> np.dtype:
    name = str(header.get("type", "")).lower()
    if name not in _NRRD_TYPES:
        raise ValueError(f"`path`: {path!r} has unsupported NRRD type {name!r}")
    return np.dtype(_NRRD_TYPES[name])


def _nrrd_geometry(header: dict[str, Any], path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    space = str(header.get("space", "")).lower()
    flips = np.asarray(_NRRD_SPACE_TO_LPS.get(space, (1.0, 1.0, 1.0)))
    if space and space not in _NRRD_SPACE_TO_LPS:
        logger.info("NRRD %s: space %r is not LPS, RAS or LAS; taken as LPS", path, space)
    directions = header.get("space directions")
    if directions is not None:
        rows = [np.asarray(d, dtype=np.float64) for d in directions]
        rows = [r for r in rows if r.ndim == 1 and r.size == 3 and np.all(np.isfinite(r))]
        if len(rows) == 2:
            rows.append(np.cross(rows[0], rows[1]) / np.linalg.norm(np.cross(rows[0], rows[1])))
        if len(rows) != 3:
            raise ValueError(f"`path`: {path!r} has unusable space directions {directions!r}")
        matrix = np.stack(rows, axis=1) * flips[:, None]  # columns: i, j, k axes in world
        spacing = np.linalg.norm(matrix, axis=0)
        direction = matrix / spacing
    else:
        spacings = header.get("spacings")
        spacing = np.asarray(spacings, dtype=np.float64)[:3] if spacings is not None else np.ones(3)
        if spacing.size == 2:
            spacing = np.append(spacing, 1.0)
        spacing = np.where(np.isfinite(spacing) & (spacing > 0), np.abs(spacing), 1.0)
        direction = np.eye(3)
    origin_in = header.get("space origin")
    origin = (
        np.asarray(origin_in, dtype=np.float64)[:3] * flips
        if origin_in is not None and np.all(np.isfinite(np.asarray(origin_in, dtype=float)))
        else np.zeros(3)
    )
    return spacing, origin, direction


def _nrrd_slice_files(data_file: Any, header_path: str) -> list[str] | None:
    """Expand a ``data file`` field that lists several files; None when it names one file."""
    folder = os.path.dirname(os.path.abspath(header_path))
    if isinstance(data_file, (list, tuple)):
        names = [str(d) for d in data_file]
    else:
        text = str(data_file).strip()
        if text.upper().startswith("LIST"):
            raise ValueError(
                f"`path`: {header_path!r} uses 'data file: LIST'; write the file names in a "
                "list and call read_raw_slices instead"
            )
        parts = text.split()
        if len(parts) >= 4 and "%" in parts[0]:
            start, stop, step = (int(p) for p in parts[1:4])
            if step == 0:
                raise ValueError(f"`path`: {header_path!r} has a data file step of 0")
            names = [parts[0] % i for i in range(start, stop + (1 if step > 0 else -1), step)]
        else:
            return None
    return [n if os.path.isabs(n) else os.path.join(folder, n) for n in names]


# -- raw slices ------------------------------------------------------------------------------

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
    spacing_arr = _as_vector3(spacing, "spacing", positive=True)
    origin_arr = _as_vector3(origin, "origin")
    direction_arr = _as_direction(direction)
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
