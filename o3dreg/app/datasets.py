"""Small meshes that ship with o3dreg, for examples, tests and the demo."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import open3d as o3d

__all__ = ["headsq_path", "load_bunny"]


def load_bunny() -> o3d.geometry.TriangleMesh:
    """The Stanford bunny (35,947 vertices, open at the base), scaled to millimetres.

    Returns
    -------
    open3d.geometry.TriangleMesh
        A new mesh each call, about 155 x 153 x 120 mm (bounding-box diagonal 250 mm).

    Notes
    -----
    Stanford 3D Scanning Repository; see ``o3dreg/data/ATTRIBUTION.md``.
    """
    path = resources.files("o3dreg") / "data" / "bunny.ply"
    with resources.as_file(path) as p:
        mesh = o3d.io.read_triangle_mesh(str(p))  # type: ignore[arg-type]  # stubs say PathLike only
    mesh.scale(1000.0, center=(0.0, 0.0, 0.0))
    return mesh


def headsq_path() -> Path:
    """Path of the bundled CT head's detached NRRD header (``quarter.nhdr``).

    The VTK "headsq" CT at quarter resolution: 93 axial slices of 64x64 int16, spacing
    3.2 x 3.2 x 1.5 mm; bone above about 1150 (raw values, HU = value - 1024). Read it with
    :func:`o3dreg.read_volume`.
    """
    return Path(str(resources.files("o3dreg") / "data" / "headsq_quarter" / "quarter.nhdr"))
