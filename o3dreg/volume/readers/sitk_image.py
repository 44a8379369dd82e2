"""Images SimpleITK reads (NIfTI, MetaImage, single DICOM files) as :class:`Volume`."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..volume import Volume

# SimpleITK is imported inside the readers (~0.5 s to import; `import o3dreg` loads this
# module).
__all__ = ["from_sitk", "read_sitk_file", "sitk_error"]

logger = logging.getLogger("o3dreg")


def sitk_error(exc: Exception) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in reversed(lines):
        if "ERROR" in line or "Error" in line or "error" in line:
            return line
    return lines[-1] if lines else type(exc).__name__


def from_sitk(image: Any, source: str) -> Volume:
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


def read_sitk_file(path: str) -> Volume:
    import SimpleITK as sitk

    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        raise OSError(f"`path`: could not read {path!r}: {sitk_error(exc)}") from exc
    volume = from_sitk(image, path)
    logger.info("read %s: %r", path, volume)
    return volume
