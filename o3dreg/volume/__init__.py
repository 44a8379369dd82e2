"""Stage 1: CT and mask volumes to bone surfaces (the ``Volume`` type, readers, isosurface, cleaning)."""

from .cleaning import (
    Components,
    connected_components,
    crop_mesh,
    decimate,
    keep_largest_components,
    remove_small_components,
    smooth_taubin,
)
from .isosurface import isosurface
from .readers import read_raw_slices, read_volume
from .volume import Volume

__all__ = [
    "Components",
    "Volume",
    "connected_components",
    "crop_mesh",
    "decimate",
    "isosurface",
    "keep_largest_components",
    "read_raw_slices",
    "read_volume",
    "remove_small_components",
    "smooth_taubin",
]
