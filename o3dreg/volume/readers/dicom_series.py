"""A folder of DICOM slices (one series) as a :class:`Volume`, slice positions checked."""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np

from ..volume import Volume
from .sitk_image import from_sitk, sitk_error

# SimpleITK is imported inside the readers (~0.5 s to import; `import o3dreg` loads this
# module).
__all__ = ["is_dicom_file", "read_dicom_series"]

logger = logging.getLogger("o3dreg")

# Relative tolerance on slice gaps before a DICOM series is declared non-uniform: scanners write
# positions with ~1e-3 mm precision, a missing slice changes one gap by 100 %.
_SLICE_GAP_RTOL = 0.02


def read_dicom_series(folder: str, series_uid: str | None) -> Volume:
    import SimpleITK as sitk

    series = list(sitk.ImageSeriesReader.GetGDCMSeriesIDs(folder))
    if not series:
        below = _folders_with_dicom_files(folder)
        if below:
            shown = "; ".join(f"{name} ({count} files)" for name, count in below[:5])
            more = f" and {len(below) - 5} more" if len(below) > 5 else ""
            raise OSError(
                f"`path`: no DICOM series found in folder {folder!r} itself; the DICOM files "
                f"are in folders below it (a DICOM medium's layout): {shown}{more}; give the "
                "folder of one series"
            )
        raise OSError(f"`path`: no DICOM series found in folder {folder!r}")
    _check_every_file_listed(folder, series)
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
    for name, header in zip(files, headers, strict=True):
        _check_pixel_data_size(name, header)
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
            f"`path`: could not read DICOM series in {folder!r}: {sitk_error(exc)}"
        ) from exc
    if len(files) == 1 and image.GetSize()[2] == 1:
        volume = from_sitk(image, folder)
        # One slice: keep the slice thickness as plane spacing. (A multi-frame file holds its
        # planes' spacing in its own geometry.)
        volume = Volume(
            volume.array,
            np.array([headers[0]["thickness"], *volume.spacing[1:]]),
            volume.origin,
            volume.direction,
        )
    else:
        volume = from_sitk(image, folder)
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
        raise OSError(f"`path`: could not read DICOM file {path!r}: {sitk_error(exc)}") from exc

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
    size = reader.GetSize()
    return {
        "pixel_bytes": int(np.prod(size, dtype=np.int64))
        * reader.GetNumberOfComponents()
        * int((numbers("0028|0100") or [0])[0])
        // 8,
        "transfer_syntax": (tag("0002|0010") or "").strip().rstrip("\0"),
        "position": numbers("0020|0032"),
        "orientation": numbers("0020|0037"),
        "pixel_spacing": numbers("0028|0030"),
        "slope": float((numbers("0028|1053") or [1.0])[0]),
        "intercept": float((numbers("0028|1052") or [0.0])[0]),
        "thickness": thickness[0] if thickness and thickness[0] > 0 else 1.0,
    }


# Transfer syntaxes whose pixel data is stored uncompressed (its size is known from the header).
_UNCOMPRESSED = {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2"}


def _check_pixel_data_size(path: str, header: dict[str, Any]) -> None:
    """``OSError`` for an uncompressed slice shorter than its pixel data (a truncated copy)."""
    if header["transfer_syntax"] in _UNCOMPRESSED and header["pixel_bytes"] > 0:
        size = os.path.getsize(path)
        if size < header["pixel_bytes"]:
            raise OSError(
                f"`path`: DICOM file {path!r} is truncated: {size} bytes, its pixel data "
                f"alone needs {header['pixel_bytes']}"
            )


def _check_every_file_listed(folder: str, series: list[str]) -> None:
    """``OSError`` naming the DICOM files of ``folder`` GDCM left out of every series.

    GDCM silently skips files it cannot parse (e.g. a slice truncated mid-way), which would
    make a series look complete but shorter.
    """
    import SimpleITK as sitk

    listed = {
        os.path.abspath(f)
        for uid in series
        for f in sitk.ImageSeriesReader.GetGDCMSeriesFileNames(folder, uid)
    }
    left_out = []
    for entry in sorted(os.listdir(folder)):
        path = os.path.abspath(os.path.join(folder, entry))
        if entry.upper() == "DICOMDIR":  # the index of a DICOM medium, no image
            continue
        if path not in listed and os.path.isfile(path) and is_dicom_file(path):
            left_out.append(entry)
    if left_out:
        raise OSError(
            f"`path`: {len(left_out)} DICOM file(s) in {folder!r} could not be read "
            f"(truncated or damaged?): {', '.join(left_out[:5])}"
            f"{', ...' if len(left_out) > 5 else ''}"
        )


def _folders_with_dicom_files(folder: str, depth: int = 4) -> list[tuple[str, int]]:
    """Folders below ``folder`` (``depth`` levels at most) that hold DICOM files, relative to it,
    with their counts (each folder's first few files are looked at, not every one)."""
    found = []
    for root, dirs, files in os.walk(folder):
        level = os.path.relpath(root, folder).count(os.sep) + 1
        if root == folder:
            continue
        if level >= depth:
            dirs.clear()
        names = [f for f in files if f.upper() != "DICOMDIR"]
        if any(is_dicom_file(os.path.join(root, f)) for f in names[:3]):
            found.append((os.path.relpath(root, folder), len(names)))
    return sorted(found)


def is_dicom_file(path: str) -> bool:
    """Whether ``path`` starts like a DICOM Part 10 file (``DICM`` after the 128-byte preamble)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def _check_slice_positions(files: list[str], headers: list[dict[str, Any]], uid: str) -> None:
    if len(files) < 2:
        return
    if any(h["position"] is None or h["orientation"] is None for h in headers):
        raise ValueError(
            f"DICOM series {uid}: some slices have no ImagePositionPatient or "
            "ImageOrientationPatient; cannot place the slices"
        )
    orientation = np.asarray(headers[0]["orientation"], dtype=np.float64)
    # The volume is built from the first slice's orientation and pixel spacing, with the
    # slices stacked along its normal: anything else would be placed wrong without a word.
    turned = [
        os.path.basename(f)
        for f, h in zip(files, headers)
        if np.abs(np.asarray(h["orientation"], dtype=np.float64) - orientation).max() > 1e-4
    ]
    if turned:
        raise ValueError(
            f"DICOM series {uid}: {len(turned)} slice(s) lie in another orientation than the "
            f"first ({', '.join(turned[:5])}); one volume needs parallel slices"
        )
    pixel = headers[0]["pixel_spacing"]
    if pixel is not None:
        other = [
            os.path.basename(f)
            for f, h in zip(files, headers)
            if h["pixel_spacing"] is not None
            and np.abs(np.subtract(h["pixel_spacing"], pixel)).max() > 1e-4 * max(pixel)
        ]
        if other:
            raise ValueError(
                f"DICOM series {uid}: {len(other)} slice(s) have another pixel spacing than the "
                f"first's {pixel} mm ({', '.join(other[:5])}); they would be placed at the "
                "wrong size"
            )
    normal = np.cross(orientation[:3], orientation[3:])
    start = np.asarray(headers[0]["position"], dtype=np.float64)
    offsets = np.array([np.asarray(h["position"], dtype=np.float64) - start for h in headers])
    sideways = offsets - np.outer(offsets @ normal, normal)
    drift = float(np.sqrt((sideways**2).sum(axis=1)).max())
    # 5% of a pixel: far above the rounding of written positions, far below a tilt's shift.
    if drift > 0.05 * (min(pixel) if pixel else 1.0):
        raise ValueError(
            f"DICOM series {uid}: the slices are not stacked along their normal (gantry tilt "
            f"or a moving table: a slice lies {drift:.3g} mm sideways of the first one's "
            "normal); the volume would be sheared. Resample the series onto a regular grid "
            "first"
        )
    positions = offsets @ normal + float(start @ normal)
    # Repeated positions anywhere in the list (GDCM may not put a duplicate beside its twin,
    # where it would read as an irregular gap).
    rank = np.argsort(positions, kind="stable")
    twins = rank[1:][np.abs(np.diff(positions[rank])) < 1e-3]
    if twins.size:
        names = ", ".join(os.path.basename(files[i]) for i in np.sort(twins)[:5])
        raise ValueError(
            f"DICOM series {uid}: {twins.size} slice(s) share a position with another slice "
            f"({names}); the folder may hold duplicated or multi-phase images"
        )
    gaps = np.diff(positions)
    order = "ascending" if np.median(gaps) > 0 else "descending"
    gaps = np.abs(gaps)
    typical = float(np.median(gaps))
    bad = np.flatnonzero(np.abs(gaps - typical) > _SLICE_GAP_RTOL * typical)
    if bad.size:
        details = ", ".join(f"{gaps[i]:.4g} mm after {os.path.basename(files[i])}" for i in bad[:5])
        raise ValueError(
            f"DICOM series {uid}: non-uniform slice spacing (typical {typical:.4g} mm, "
            f"{order}; {bad.size} irregular gap(s): {details}); missing slices?"
        )
