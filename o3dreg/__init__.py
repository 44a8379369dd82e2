"""o3dreg: elastic registration of 3D surface meshes and statistical shape models of anatomy.

A plugin for the Open3D / libigl ecosystem implementing the multi-resolution trilinear
("octree-spline") registration with a symmetric distance of Berar et al. (2005).

The rooms follow the pipeline: ``volume`` (CT to surface), ``mesh`` (surfaces, whatever the
stage), ``registration`` (template onto patient), ``shape`` (shape models), ``io`` (files) and
``app`` (batches, the model-folder pipeline, the demo, reports) with the command line ``cli`` on
top. Every public name is also here, at the top level.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import logging
import sys
import warnings
from types import ModuleType
from typing import Any

# Before the libraries load (seconds): the command ends cleanly on a signal meanwhile.
from . import _startup

_startup.guard()

__version__ = "0.1.0"

logging.getLogger("o3dreg").addHandler(logging.NullHandler())

#: Module paths that moved to another room, old -> new. Importing an old path gives a module that
#: forwards every name to the new one, with a DeprecationWarning.
MOVED_MODULES = {
    "o3dreg._distinct": "o3dreg.mesh.distinct",
    "o3dreg._edges": "o3dreg.mesh.edges",
    "o3dreg._json": "o3dreg.io.json_text",
    "o3dreg.io.landmarks": "o3dreg.io.landmark_files",
    "o3dreg.registration.batch": "o3dreg.app.batch",
    "o3dreg.registration.landmarks": "o3dreg.registration.landmark_start",
    "o3dreg.registration.sampling": "o3dreg.mesh.sampling",
    "o3dreg.registration.settings": "o3dreg.app.settings",
    "o3dreg.shape.landmarks": "o3dreg.shape.landmark_transfer",
    "o3dreg.volume.cleaning": "o3dreg.mesh.cleaning",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds the old paths of :data:`MOVED_MODULES` (no file is left at an old path)."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any:
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: Any) -> None:
        return None  # the default module object

    def exec_module(self, module: ModuleType) -> None:
        new = MOVED_MODULES[module.__name__]
        warnings.warn(
            f"module {module.__name__} is deprecated: import {new}",
            DeprecationWarning,
            stacklevel=2,
        )
        target = importlib.import_module(new)

        def forward(name: str) -> Any:
            return getattr(target, name)

        setattr(module, "__getattr__", forward)  # noqa: B010 (a module-level __getattr__)
        setattr(module, "__all__", list(getattr(target, "__all__", ())))  # noqa: B010


if not any(isinstance(finder, _MovedModules) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModules())

# Each subpackage's ``__all__`` is the one list of its public names; the top level re-exports them.
from . import app, io, mesh, registration, shape, volume  # noqa: E402
from .app import *  # noqa: E402, F403
from .io import *  # noqa: E402, F403
from .mesh import *  # noqa: E402, F403
from .registration import *  # noqa: E402, F403
from .shape import *  # noqa: E402, F403
from .volume import *  # noqa: E402, F403

__all__ = ["__version__"]
__all__ += io.__all__
__all__ += mesh.__all__
__all__ += volume.__all__
__all__ += registration.__all__
__all__ += shape.__all__
__all__ += app.__all__

# The API docs' reader (griffe) takes the name through ``volume`` for the submodule
# ``volume.isosurface``, not the function that shadows it: name the function directly.
from .volume.isosurface import isosurface as isosurface  # noqa: E402
