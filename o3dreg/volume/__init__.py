"""Stage 1: CT and mask volumes to bone surfaces (the ``Volume`` type, readers, isosurface).

The surfaces are cleaned with :mod:`o3dreg.mesh`.
"""

from typing import Any

from .._validation import moved_name
from .isosurface import isosurface
from .readers import read_raw_slices, read_volume
from .volume import Volume

__all__ = [
    "Volume",
    "isosurface",
    "read_raw_slices",
    "read_volume",
]


def __getattr__(name: str) -> Any:
    # The cleaning functions live in o3dreg.mesh; the names here still work, with a warning.
    return moved_name(__name__, name, "o3dreg.mesh.cleaning")
