"""Triangle meshes, whatever the stage: components, cleaning, cropping, smoothing, decimation, and
the shared kernels behind them (sorted edges, distinct values, canonical order, subsampling,
noise)."""

from .cleaning import (
    Components,
    connected_components,
    crop_mesh,
    decimate,
    keep_largest_components,
    remove_small_components,
    smooth_taubin,
)

__all__ = [
    "Components",
    "connected_components",
    "crop_mesh",
    "decimate",
    "keep_largest_components",
    "remove_small_components",
    "smooth_taubin",
]
