"""Mesh files (Open3D's readers and writers, checked) and the versioned ``.npz`` archives."""

from .mesh import read_triangle_mesh, write_triangle_mesh

__all__ = ["read_triangle_mesh", "write_triangle_mesh"]
