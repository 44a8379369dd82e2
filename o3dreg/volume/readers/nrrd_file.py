"""NRRD files as :class:`Volume`: SimpleITK first, pynrrd for the headers SimpleITK rejects."""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np

from ...io.units import millimetres_per_unit
from ..volume import Volume
from .raw_slices import read_raw_slices
from .sitk_image import from_sitk, sitk_error

# SimpleITK and pynrrd are imported inside the readers (~0.5 s to import; `import o3dreg` loads this
# module).
__all__ = ["read_nrrd"]

logger = logging.getLogger("o3dreg")

# NRRD spaces and the sign flips that take them to LPS.
_NRRD_SPACE_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
}


#: NRRD encodings of text data: read by pynrrd, which checks the numbers (SimpleITK 2.5 crashed
#: on a header saying ascii over raw bytes).
_TEXT_ENCODINGS = ("ascii", "text", "txt")


def read_nrrd(path: str) -> Volume:
    header = _check_geometry_fields(path)
    millimetres = 1.0 if header is None else _millimetres_per_unit(header, path)
    volume = _read_nrrd(path, header)
    if millimetres != 1.0:
        volume = Volume(
            volume.array,
            volume.spacing * millimetres,
            volume.origin * millimetres,
            volume.direction,
        )
    logger.info("read %s: %r", path, volume)
    return volume


def _read_nrrd(path: str, header: dict[str, Any] | None) -> Volume:
    import SimpleITK as sitk

    if header is not None:
        if "type" in header:
            _nrrd_dtype(header, path)  # an unknown type is refused before any reader sees it
        if str(header.get("encoding", "")).lower() in _TEXT_ENCODINGS:
            logger.debug("reading %s (text encoding) with pynrrd", path)
            return _read_nrrd_pynrrd(path)
    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        logger.debug("SimpleITK could not read %s (%s); trying pynrrd", path, sitk_error(exc))
    else:
        return from_sitk(image, path)
    return _read_nrrd_pynrrd(path)


def _millimetres_per_unit(header: dict[str, Any], path: str) -> float:
    """The factor that takes the header's ``space units`` to millimetres (1 without them)."""
    units = header.get("space units")
    if units is None:
        return 1.0
    # Neither reader applies the units. "???" and "none" say they are unknown: taken as mm.
    named = [u for u in units if str(u).strip().strip('"').lower() not in ("", "???", "none")]
    factors = {millimetres_per_unit(str(u)) or 0.0 for u in named}  # 0: a unit not known
    if 0.0 in factors or len(factors) > 1:
        raise ValueError(
            f"`path`: {path!r} has space units {list(units)}; o3dreg reads one unit for all "
            "axes (mm, cm, m or um): convert the file to mm"
        )
    return factors.pop() if factors else 1.0


def _check_geometry_fields(path: str) -> dict[str, Any] | None:
    """Refuse zero or NaN spacings and a NaN origin (SimpleITK reads them as 1 mm and 0); the
    header, where pynrrd reads it."""
    import nrrd

    try:
        header = nrrd.read_header(path)
    except Exception:  # unreadable header: SimpleITK, then pynrrd, say why
        return None
    spacings = header.get("spacings")
    if spacings is not None:
        values = np.asarray(spacings, dtype=np.float64)
        if not np.all(np.isfinite(values)) or np.any(values == 0):
            raise ValueError(
                f"`path`: {path!r} has spacings {values.tolist()}; each must be a non-zero number"
            )
    origin = header.get("space origin")
    if origin is not None:
        values = np.asarray(origin, dtype=np.float64).ravel()
        if values.size != 3 or not np.all(np.isfinite(values)):
            raise ValueError(
                f"`path`: {path!r} has space origin {values.tolist()}; it must be 3 finite numbers"
            )
    return dict(header)


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
    except (nrrd.NRRDError, OSError, ValueError, KeyError, TypeError) as exc:
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


#: The NRRD spaces without anatomical meaning (the format's world frames).
_NRRD_GENERIC_SPACES = (
    "3d-right-handed",
    "3d-left-handed",
    "scanner-xyz",
    "3d-right-handed-time",
    "3d-left-handed-time",
    "scanner-xyz-time",
)


def _nrrd_geometry(header: dict[str, Any], path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    space = str(header.get("space", "")).lower()
    flips = np.asarray(_NRRD_SPACE_TO_LPS.get(space, (1.0, 1.0, 1.0)))
    if space in _NRRD_GENERIC_SPACES:
        # No anatomical axes to keep: the coordinates are used as they are.
        logger.info("NRRD %s: space %r has no anatomical axes; taken as LPS", path, space)
    elif space and space not in _NRRD_SPACE_TO_LPS:
        # An anatomical guess that can swap left and right: said where it is seen.
        logger.warning("NRRD %s: space %r is not LPS, RAS or LAS; taken as LPS", path, space)
    directions = header.get("space directions")
    if directions is not None:
        rows = [np.asarray(d, dtype=np.float64) for d in directions]
        rows = [r for r in rows if r.ndim == 1 and r.size == 3 and np.all(np.isfinite(r))]
        if len(rows) == 2 and len(header.get("sizes", [])) == 2:
            rows.append(np.cross(rows[0], rows[1]) / np.linalg.norm(np.cross(rows[0], rows[1])))
        if len(rows) != 3:
            shown = np.asarray(directions, dtype=object).tolist()
            raise ValueError(f"`path`: {path!r} has unusable space directions {shown}")
        matrix = np.stack(rows, axis=1) * flips[:, None]  # columns: i, j, k axes in world
        spacing = np.linalg.norm(matrix, axis=0)
        if np.any(spacing == 0):
            raise ValueError(
                f"`path`: {path!r} has a zero space direction {np.asarray(directions).tolist()}"
            )
        direction = matrix / spacing
    else:
        spacings = header.get("spacings")
        spacing = np.asarray(spacings, dtype=np.float64)[:3] if spacings is not None else np.ones(3)
        if spacing.size == 2:
            spacing = np.append(spacing, 1.0)
        if not np.all(np.isfinite(spacing)) or np.any(spacing == 0):
            raise ValueError(
                f"`path`: {path!r} has spacings {spacing.tolist()}; each must be a non-zero number"
            )
        # A negative spacing runs that axis the other way (as SimpleITK reads it): the size is
        # its magnitude, the sign goes to the direction (dropping it would mirror the mesh).
        # In the file's space: a RAS file's x and y axes run the other way in LPS.
        direction = np.diag(flips * np.sign(spacing))
        spacing = np.abs(spacing)
    origin_in = header.get("space origin")
    origin = np.zeros(3)
    mins = header.get("axis mins")
    if origin_in is None and mins is not None and directions is None:
        # The per-axis form (no space): the first sample lies at the axis minimum, or half a
        # sample beyond it when samples are cell-centred, the default (as ITK reads it).
        mins = np.asarray(mins, dtype=np.float64)[:3]
        centers = header.get("centers", header.get("centerings", ()))
        if isinstance(centers, str):  # pynrrd keeps the "centers" spelling as one string
            centers = centers.split()
        node = [str(c).lower() == "node" for c in centers]
        half = np.array([0.0 if n else 0.5 for n in node] + [0.5] * 3)[:3]
        origin = (mins + half[: mins.size] * spacing[: mins.size]) * flips[: mins.size]
        if origin.size == 2:
            origin = np.append(origin, 0.0)
        if not np.all(np.isfinite(origin)):
            raise ValueError(f"`path`: {path!r} has axis mins {mins.tolist()}; they must be finite")
    if origin_in is not None:
        origin = np.asarray(origin_in, dtype=np.float64)[:3] * flips
        if not np.all(np.isfinite(origin)):
            raise ValueError(
                f"`path`: {path!r} has space origin {origin.tolist()}; it must be finite"
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
