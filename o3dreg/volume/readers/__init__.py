"""Readers of CT scans and masks: one module per format, :func:`read_volume` picks one.

World coordinates are millimetres in the file's patient space as SimpleITK reports it: LPS
(x to the patient's left, y to posterior, z to superior) for DICOM, NRRD and MetaImage. NIfTI
stores RAS; SimpleITK converts it to LPS (x and y negated), so every reader returns LPS.

Formats are read with SimpleITK (DICOM series, NIfTI, NRRD, MetaImage); NRRD headers that
SimpleITK rejects (for example a ``spacings`` line together with a ``space`` field, or a
``data file`` list of slices) are read with pynrrd instead.
"""

from __future__ import annotations

import os

from ..._validation import named_as
from ..volume import Volume
from .dicom_series import is_dicom_file, read_dicom_series
from .nrrd_file import read_nrrd
from .raw_slices import read_raw_slices
from .sitk_image import read_sitk_file

__all__ = ["VOLUME_SUFFIXES", "read_raw_slices", "read_volume"]

#: File suffixes :func:`read_volume` reads (a folder is read as a DICOM series).
VOLUME_SUFFIXES = (".dcm", ".nii", ".nii.gz", ".nrrd", ".nhdr", ".mhd", ".mha")


def read_volume(
    path: str | os.PathLike[str], *, series_uid: str | None = None, name: str = "path"
) -> Volume:
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
    name : str, optional
        How messages name ``path`` (a command line passes its positional). Default ``'path'``.

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
    with named_as(name):
        return _read_volume(path, series_uid)


def _read_volume(path: str | os.PathLike[str], series_uid: str | None) -> Volume:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    if series_uid is not None and not isinstance(series_uid, str):
        raise TypeError(f"`series_uid` must be a str, got {type(series_uid).__name__}")
    path = os.fspath(path)
    if os.path.isdir(path):
        return read_dicom_series(path, series_uid)
    if not os.path.exists(path):
        raise OSError(f"`path`: no such file or folder {path!r}")
    if not os.access(path, os.R_OK):
        raise OSError(f"`path`: {path!r} is not readable")
    if os.path.getsize(path) == 0:
        raise OSError(f"`path`: {path!r} is empty")
    suffix = _volume_suffix(path)
    if series_uid is not None:
        raise ValueError(
            f"`series_uid` selects a DICOM series in a folder of slices; {path!r} is a "
            f"{suffix} file, which holds one volume: leave `series_uid` out"
        )
    if suffix in (".nrrd", ".nhdr"):
        return read_nrrd(path)
    return read_sitk_file(path)


def _volume_suffix(path: str) -> str:
    lower = path.lower()
    for suffix in VOLUME_SUFFIXES:
        if lower.endswith(suffix):
            return suffix
    if is_dicom_file(path):
        return ".dcm"
    raise ValueError(
        f"`path` must be a folder of DICOM slices or a file ending with "
        f"{', '.join(VOLUME_SUFFIXES)} (or a DICOM file), got {path!r}"
    )
