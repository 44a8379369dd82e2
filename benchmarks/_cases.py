"""Benchmark cases with ground truth: a template, a warped dense target, and where each template
vertex should land. Shared by the benchmark scripts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from o3dreg.app.datasets import load_bunny
from o3dreg.app.synthetic import SmoothWarp

#: Warp magnitudes as a fraction of the bounding-box diagonal.
MAGNITUDES = {"small": 0.02, "medium": 0.05, "large": 0.1}


@dataclass
class Case:
    name: str
    template: o3d.geometry.TriangleMesh
    target: o3d.geometry.TriangleMesh
    truth: np.ndarray  # (n, 3) where each template vertex belongs on the target
    diagonal: float


def template_of(
    mesh: o3d.geometry.TriangleMesh, template_vertices: int
) -> o3d.geometry.TriangleMesh:
    """``mesh`` decimated to about ``template_vertices`` vertices, as the bench cases' templates
    are (Open3D's quadric decimation to twice as many triangles)."""
    template = mesh.simplify_quadric_decimation(2 * template_vertices)
    template.remove_unreferenced_vertices()
    return template


def bunny_case(magnitude: str = "medium", template_vertices: int = 3000, seed: int = 1) -> Case:
    """The bundled bunny (35,947 vertices) under a known smooth warp; a decimated template."""
    dense = load_bunny()
    template = template_of(dense, template_vertices)
    vertices = np.asarray(dense.vertices)
    warp = SmoothWarp.random(vertices, magnitude=MAGNITUDES[magnitude], seed=seed)
    target = o3d.geometry.TriangleMesh(dense)
    target.vertices = o3d.utility.Vector3dVector(warp(vertices))
    truth = warp(np.asarray(template.vertices))
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    return Case(f"bunny-{magnitude}", template, target, truth, diagonal)
