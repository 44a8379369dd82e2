"""What sliding semilandmarks does to the registered correspondences, where the truth is known.

* **Synthetic truth** (the demo's population): the bundled CT's bone decimated to 2500 vertices
  is registered onto 8 patients made from it by known smooth warps (``make_population``, seed
  0); the truth of a template vertex is its warped position. Error: mean distance of the
  semilandmarks to their truths (mm), registered and then slid with each criterion.
* **Real annotations** (the 8 development mandibles of ``bench_landmarks.py``, where
  ``../shared/data/mandibles`` is present): for each chosen template, the registrations onto the
  7 other patients, slid together; error: the template's 3 annotations read off each
  semilandmark mesh (triangle, barycentric coordinates, offset) against the patient's own (mm).

Both with :func:`~o3dreg.slide_semilandmarks`' defaults (5 iterations at most, tolerance 1e-3 of
the mean's radius) and the template's faces (no triangle turned over). Also printed: how far the
points moved, the shortest semilandmark edge against the registered meshes' (bunching), the
iterations and the time.

    python benchmarks/bench_sliding.py                  # templates 0, 3 and 6 of the mandibles
    python benchmarks/bench_sliding.py --templates all  # all 8 (about 25 minutes)
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_landmarks

import o3dreg
from o3dreg import TemplateLandmarks, slide_semilandmarks

CRITERIA = ("bending", "procrustes")


def shortest_edge(shapes: np.ndarray, faces: np.ndarray) -> float:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float(np.linalg.norm(shapes[:, edges[:, 0]] - shapes[:, edges[:, 1]], axis=2).min())


def compare(name: str, shapes: np.ndarray, surfaces: list, faces: np.ndarray, error) -> None:
    """One row per criterion: error, movement, shortest edge, iterations, seconds."""
    print(
        f"{name:<32}{'registered':<12}{error(shapes):>8.3f}{'':>9}"
        f"{shortest_edge(shapes, faces):>10.4f}"
    )
    for criterion in CRITERIA:
        start = time.perf_counter()
        slid = slide_semilandmarks(shapes, surfaces, criterion=criterion, faces=faces)
        seconds = time.perf_counter() - start
        moved = float(np.linalg.norm(slid.shapes - shapes, axis=2).mean())
        print(
            f"{'':<32}{criterion:<12}{error(slid.shapes):>8.3f}{moved:>9.3f}"
            f"{shortest_edge(slid.shapes, faces):>10.4f}{slid.iterations:>6}{seconds:>8.1f}",
            flush=True,
        )


def synthetic() -> None:
    from o3dreg.app.datasets import headsq_path
    from o3dreg.app.demo import bone_mesh, make_population

    reference = bone_mesh(o3dreg.read_volume(headsq_path()))
    template = o3dreg.decimate(reference, 2500)
    vertices, faces = np.asarray(template.vertices), np.asarray(template.triangles)
    patients = make_population(reference, 8, seed=0)
    shapes = np.stack([o3dreg.registration_elastic(template, p.mesh).vertices for p in patients])
    truth = np.stack([p.truth(vertices) for p in patients])

    def error(moved: np.ndarray) -> float:
        return float(np.linalg.norm(moved - truth, axis=2).mean())

    compare("demo population (8)", shapes, [p.mesh for p in patients], faces, error)


def mandibles(chosen: str, folder: Path) -> None:
    if not (folder / "masks").is_dir() or not (folder / "landmarks").is_dir():
        print(f"skip the mandibles: no masks and landmarks in {folder} (research data)")
        return
    data = bench_landmarks.load(3000, folder)
    ids = sorted(data)
    if len(ids) < 3:
        print(f"skip the mandibles: {len(ids)} patient(s) of {folder} serve, at least 3 needed")
        return
    try:
        picked = bench_landmarks.chosen_templates(None if chosen == "all" else chosen, ids)
    except ValueError as exc:
        sys.exit(f"bench_sliding.py: error: {exc}")
    for tid in picked:
        template = data[tid]["template"]
        attached = TemplateLandmarks.from_points(template, data[tid]["landmarks"])
        others = [p for p in ids if p != tid]
        shapes = np.stack(
            [o3dreg.registration_elastic(template, data[p]["surface"]).vertices for p in others]
        )
        truth = np.stack([data[p]["landmarks"] for p in others])

        def error(moved: np.ndarray, attached=attached, truth=truth) -> float:
            carried = np.stack([attached.positions(s) for s in moved])
            return float(np.linalg.norm(carried - truth, axis=2).mean())

        surfaces = [data[p]["surface"] for p in others]
        compare(f"mandibles, template {tid}", shapes, surfaces, template[1], error)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--templates",
        default="0,3,6",
        help="comma-separated mandible templates: patient ids, or indices into the patients "
        "that serve, sorted by id; or all",
    )
    parser.add_argument(
        "--data",
        metavar="FOLDER",
        help="the mandible folder: masks/<id>_Mandible.nrrd and landmarks/<id>_Landmarks.fcsv "
        "(default: $O3DREG_SHARED_DATA/mandibles, else ../shared/data/mandibles)",
    )
    parser.add_argument("--skip-synthetic", action="store_true")
    args = parser.parse_args()
    folder = Path(args.data) if args.data else bench_landmarks.data_dir()
    logging.getLogger("o3dreg").setLevel(logging.ERROR)
    print(f"{'data':<32}{'points':<12}{'error':>8}{'moved':>9}{'min edge':>10}{'its':>6}{'s':>8}")
    if not args.skip_synthetic:
        synthetic()
    mandibles(args.templates, folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
