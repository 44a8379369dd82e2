"""o3dreg: elastic registration of 3D surface meshes and statistical shape models of anatomy.

A plugin for the Open3D / libigl ecosystem implementing the multi-resolution trilinear
("octree-spline") registration with a symmetric distance of Berar et al. (2005).
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger("o3dreg").addHandler(logging.NullHandler())

# Each subpackage's ``__all__`` is the one list of its public names; the top level re-exports them.
from . import io, registration, shape, volume  # noqa: E402
from .io import *  # noqa: E402, F403
from .registration import *  # noqa: E402, F403
from .shape import *  # noqa: E402, F403
from .volume import *  # noqa: E402, F403

__all__ = ["__version__"]
__all__ += io.__all__
__all__ += registration.__all__
__all__ += volume.__all__
__all__ += shape.__all__

# The API docs' reader (griffe) takes the name through ``volume`` for the submodule
# ``volume.isosurface``, not the function that shadows it: name the function directly.
from .volume.isosurface import isosurface as isosurface  # noqa: E402
