"""Register a 3k-vertex template of the bunny onto the full bunny under a known warp.

Evaluate the initial alignment -> register (single and symmetric distance) -> print the results
and the ground-truth correspondence error -> with ``--draw`` in a terminal, draw them.

    python examples/register_bunny.py
    python examples/register_bunny.py --draw
"""

import sys

import numpy as np
import open3d as o3d

import o3dreg
from o3dreg.app.datasets import load_bunny
from o3dreg.app.synthetic import SmoothWarp

dense = load_bunny()  # 35,947 vertices, millimetres
template = dense.simplify_quadric_decimation(6000)
template.remove_unreferenced_vertices()
warp = SmoothWarp.random(np.asarray(dense.vertices), magnitude=0.05, seed=0)
patient = o3d.geometry.TriangleMesh(dense)
patient.vertices = o3d.utility.Vector3dVector(warp(np.asarray(dense.vertices)))
truth = warp(np.asarray(template.vertices))
diagonal = np.linalg.norm(np.ptp(np.asarray(dense.vertices), axis=0))

print("initial:", o3dreg.evaluate_elastic(template, patient))
for symmetric in (False, True):
    result = o3dreg.registration_elastic(
        template, patient, estimation_method=o3dreg.DistanceEstimation(symmetric=symmetric)
    )
    error = np.linalg.norm(result.vertices - truth, axis=1)
    print(result)
    print(result.distances.table())
    print(
        f"correspondence error: mean {error.mean():.3f} mm "
        f"({100 * error.mean() / diagonal:.2f}% of the diagonal), max {error.max():.2f} mm\n"
    )

if sys.stdout.isatty() and "--draw" in sys.argv:
    registered = result.semilandmark_mesh()
    registered.paint_uniform_color((0.9, 0.4, 0.1))
    patient.compute_vertex_normals()
    o3d.visualization.draw_geometries([patient, registered])
