"""o3dreg against its peers, side by side, on the same cases, in one run.

Every (case, method) runs in its own process (peak memory is its own: ``ru_maxrss``); the cases
are built once in the parent and handed over as ``.npz`` files. o3dreg runs ``--repeat`` times
(best time kept); peers once. Ratios are to o3dreg (symmetric) measured in the same run.

    python benchmarks/bench_peers.py                     # all cases, all methods
    python benchmarks/bench_peers.py --cases bunny-medium --json out.json

Cases (template ~3k vertices decimated from the undeformed surface, target ~30k vertices under a
known smooth warp: ground truth for every template vertex):

* ``bunny-small/medium/large``: the bundled bunny, warps of 2/5/10% of its diagonal;
* ``bunny-noise``: medium, target vertices moved along their normals by N(0, 0.25% diag);
* ``bunny-partial``: medium, target triangles above 75% of the height removed (top 25% cut);
* ``bunny-outliers``: medium, plus 5% outlier *vertices* (as many as 5% of the target's), carried
  by tiny disconnected triangles (0.5% of the diagonal) scattered in the box: a mesh method sees
  them as surface, a point method as points;
* ``cone-medium``: the paper's closed cone (3k -> 30k), medium warp;
* ``mandible-medium``: a CT mandible (../shared/data, research data; skipped when absent).

Peers (their settings are recorded beside their numbers):

* ``nricp_amberg`` / ``nricp_sumner`` (trimesh 4): default step schedules. Their thresholds are
  absolute (``distance_threshold=0.1``) and tuned for unit-size meshes, so both run on the meshes
  centred and scaled by the bounding-box diagonal (then mapped back);
* ``cpd``: pycpd ``DeformableRegistration`` (Myronenko & Song), on points normalised to zero
  mean and unit variance (the CPD paper's normalisation, where its defaults alpha=2, beta=2 hold),
  ``low_rank=True`` (100 eigenvectors), ``w=0`` (``w=0.1`` for outliers/partial cases), 50
  iterations; the target is subsampled to 3000 points (dense CPD holds an M x N matrix:
  3k x 30k doubles = 0.7 GB per array and seconds per iteration). Run on bunny-medium and
  bunny-outliers only: with 5000 points and 100 iterations one case took 219 s;
* ``icp``: Open3D point-to-plane rigid ICP, the floor (max correspondence 5% of the diagonal).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

ROOT = Path(__file__).resolve().parents[1]

METHODS = {
    "o3dreg": "symmetric distance (eq. 3), default levels 2-4-8-16 (lambda 0.1), init=identity",
    "o3dreg-single": "single distance (eq. 2), default levels, init=identity",
    "nricp_amberg": "trimesh.registration.nricp_amberg, default steps, unit-diagonal coordinates",
    "nricp_sumner": "trimesh.registration.nricp_sumner, default steps, unit-diagonal coordinates",
    "cpd": "pycpd.DeformableRegistration alpha=2 beta=2 low_rank=True max_iterations=50 "
    "tolerance=1e-4, normalised points, target subsampled to 3000 points (seed 0); "
    "bunny-medium and bunny-outliers only (200+ s per case otherwise)",
    "icp": "open3d point-to-plane ICP, max correspondence 5% diagonal, 50 iterations",
}
CPD_CASES = ("bunny-medium", "bunny-outliers")
CASES = (
    "bunny-small",
    "bunny-medium",
    "bunny-large",
    "bunny-noise",
    "bunny-partial",
    "bunny-outliers",
    "cone-medium",
    "mandible-medium",
)


# -- cases ------------------------------------------------------------------------------------
def _warped_case(dense, magnitude: float, template_vertices: int, seed: int) -> dict:
    import open3d as o3d

    from o3dreg.app.synthetic import SmoothWarp

    template = o3d.geometry.TriangleMesh(dense).simplify_quadric_decimation(2 * template_vertices)
    template.remove_unreferenced_vertices()
    vertices = np.asarray(dense.vertices)
    warp = SmoothWarp.random(vertices, magnitude=magnitude, seed=seed)
    return {
        "template_vertices": np.asarray(template.vertices),
        "template_faces": np.asarray(template.triangles),
        "target_vertices": warp(vertices),
        "target_faces": np.asarray(dense.triangles),
        "truth": warp(np.asarray(template.vertices)),
        "diagonal": float(np.linalg.norm(np.ptp(vertices, axis=0))),
    }


def _mandible_mesh(number_of_vertices: int):
    """The first development mandible whose mask gives one surface, or ``None`` (a line says
    why for each mask passed over, and where none was found)."""
    from mandible_model import Unusable, data_dir, mask_isosurface, patient_masks

    import o3dreg

    folder = data_dir() / "masks"
    masks, lines = patient_masks(folder) if folder.is_dir() else ([], [])
    for line in lines:
        print(line)
    for pid, path in masks:
        try:
            whole = mask_isosurface(path)[0]
        except Unusable as exc:
            print(f"passed over {pid}: {exc}")
            continue
        mesh = o3dreg.smooth_taubin(o3dreg.keep_largest_components(whole, 1), 10)
        return o3dreg.decimate(mesh, number_of_vertices)
    print(f"no mandible mask serves in {folder} (research data, not shipped)")
    return None


def build_case(name: str, seed: int = 1) -> dict | None:
    """The arrays of one case, or ``None`` when its data is absent."""
    from _cases import MAGNITUDES

    from o3dreg.app.datasets import load_bunny
    from o3dreg.app.synthetic import synthetic_form

    rng = np.random.default_rng(seed)
    if name.startswith("bunny"):
        magnitude = name.split("-")[1] if name.split("-")[1] in MAGNITUDES else "medium"
        case = _warped_case(load_bunny(), MAGNITUDES[magnitude], 3000, seed)
    elif name == "cone-medium":
        case = _warped_case(synthetic_form("cone", 30000), MAGNITUDES["medium"], 3000, seed)
    elif name == "mandible-medium":
        mandible = _mandible_mesh(30000)
        if mandible is None:
            print(f"skip {name}")
            return None
        case = _warped_case(mandible, MAGNITUDES["medium"], 3000, seed)
    else:
        raise ValueError(f"unknown case {name!r}")
    tv, tf, diag = case["target_vertices"], case["target_faces"], case["diagonal"]
    if name == "bunny-noise":
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(tv), o3d.utility.Vector3iVector(tf)
        )
        mesh.compute_vertex_normals()
        normals = np.asarray(mesh.vertex_normals)
        case["target_vertices"] = tv + normals * rng.normal(0.0, 0.0025 * diag, (len(tv), 1))
    elif name == "bunny-partial":
        # The bunny's up axis is +y: drop triangles with a vertex in the top quarter of the height.
        lo, hi = tv[:, 1].min(), tv[:, 1].max()
        keep = (tv[tf, 1] < lo + 0.75 * (hi - lo)).all(axis=1)
        used = np.unique(tf[keep])
        remap = np.full(len(tv), -1)
        remap[used] = np.arange(used.size)
        case["target_vertices"], case["target_faces"] = tv[used], remap[tf[keep]]
    elif name == "bunny-outliers":
        count = int(0.05 * len(tv)) // 3
        lo, hi = tv.min(axis=0), tv.max(axis=0)
        pad = 0.1 * (hi - lo)
        centres = rng.uniform(lo - pad, hi + pad, (count, 3))
        offsets = rng.normal(size=(count, 3, 3))
        offsets *= 0.005 * diag / np.linalg.norm(offsets, axis=2, keepdims=True)
        extra = (centres[:, None, :] + offsets).reshape(-1, 3)
        case["target_vertices"] = np.concatenate([tv, extra])
        case["target_faces"] = np.concatenate([tf, len(tv) + np.arange(3 * count).reshape(-1, 3)])
    return case


# -- methods ----------------------------------------------------------------------------------
def rss_mb() -> float:
    """Peak resident memory of this process (MB).

    ``VmHWM`` from /proc where there is one: Linux keeps ``ru_maxrss`` across ``exec``, so a
    child would otherwise report its parent's peak at fork time.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _normalise(case: dict) -> tuple[np.ndarray, float]:
    centre = case["target_vertices"].mean(axis=0)
    return centre, case["diagonal"]


def register(method: str, case: dict) -> np.ndarray:
    """The template's vertices moved by ``method`` onto the target."""
    sv, sf = case["template_vertices"], case["template_faces"]
    tv, tf = case["target_vertices"], case["target_faces"]
    if method.startswith("o3dreg"):
        import o3dreg

        result = o3dreg.registration_elastic(
            (sv, sf),
            (tv, tf),
            init=np.eye(4),
            estimation_method=o3dreg.DistanceEstimation(symmetric=method == "o3dreg"),
        )
        return result.vertices
    if method.startswith("nricp"):
        import trimesh
        import trimesh.registration as treg

        centre, scale = _normalise(case)
        source = trimesh.Trimesh((sv - centre) / scale, sf, process=False)
        target = trimesh.Trimesh((tv - centre) / scale, tf, process=False)
        moved = np.asarray(getattr(treg, method)(source, target))
        return moved * scale + centre
    if method == "cpd":
        from pycpd import DeformableRegistration

        rng = np.random.default_rng(0)
        pick = rng.choice(len(tv), min(3000, len(tv)), replace=False)
        points = tv[pick]
        mean, std = points.mean(axis=0), float(points.std())
        w = 0.1 if case["name"] in ("bunny-outliers", "bunny-partial") else 0.0
        reg = DeformableRegistration(
            X=(points - mean) / std,
            Y=(sv - mean) / std,
            alpha=2.0,
            beta=2.0,
            w=w,
            low_rank=True,
            max_iterations=50,
            tolerance=1e-4,
        )
        moved, _ = reg.register()
        return np.asarray(moved) * std + mean
    if method == "icp":
        import open3d as o3d

        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sv))
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(tv), o3d.utility.Vector3iVector(tf.astype(np.int32))
        )
        mesh.compute_vertex_normals()
        target = o3d.geometry.PointCloud(mesh.vertices)
        target.normals = mesh.vertex_normals
        result = o3d.pipelines.registration.registration_icp(
            source,
            target,
            0.05 * case["diagonal"],
            np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50),
        )
        t = np.asarray(result.transformation)
        return sv @ t[:3, :3].T + t[:3, 3]
    raise ValueError(f"unknown method {method!r}")


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _folds(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per interior edge: the two adjacent faces' normals make more than 120 degrees."""
    normals = _face_normals(vertices, faces)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    e, o = edges[order], owner[order]
    same = (e[1:] == e[:-1]).all(axis=1)
    a, b = o[:-1][same], o[1:][same]
    return (normals[a] * normals[b]).sum(axis=1) < -0.5


def measure(case: dict, moved: np.ndarray) -> dict:
    import o3dreg

    sf, truth, diag = case["template_faces"], case["truth"], case["diagonal"]
    err = np.linalg.norm(moved - truth, axis=1)
    d = o3dreg.evaluate_elastic((moved, sf), (case["target_vertices"], case["target_faces"]))
    flips = (_face_normals(moved, sf) * _face_normals(truth, sf)).sum(axis=1) < 0
    folds = _folds(moved, sf) & ~_folds(truth, sf)
    return {
        "error_mean": float(err.mean()),
        "error_p95": float(np.percentile(err, 95)),
        "error_max": float(err.max()),
        "error_mean_pct_diag": float(100 * err.mean() / diag),
        "s2t_mean": d.source_to_target_mean,
        "s2t_max": d.source_to_target_max,
        "t2s_mean": d.target_to_source_mean,
        "t2s_max": d.target_to_source_max,
        "flipped_pct": float(100 * flips.mean()),
        "folded_edges_pct": float(100 * folds.mean()),
    }


def run_child(method: str, path: str) -> dict:
    with np.load(path) as data:
        case = {k: data[k] for k in data.files}
    case["diagonal"] = float(case["diagonal"])
    case["name"] = str(case["name"])
    # Imports are not timed, for any method (o3dreg's pulls in Open3D, about a second).
    if method.startswith("o3dreg"):
        import o3dreg  # noqa: F401
    elif method.startswith("nricp"):
        import trimesh.registration  # noqa: F401
    elif method == "icp":
        import open3d  # noqa: F401
    baseline = rss_mb()
    start = time.perf_counter()
    moved = register(method, case)
    seconds = time.perf_counter() - start
    peak = rss_mb()
    return {
        "method": method,
        "case": case["name"],
        "template_vertices": len(case["template_vertices"]),
        "target_vertices": len(case["target_vertices"]),
        "seconds": seconds,
        "peak_rss_mb": peak,
        "rss_growth_mb": peak - baseline,
        **measure(case, moved),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--child", nargs=2, metavar=("METHOD", "NPZ"), help=argparse.SUPPRESS)
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--repeat", type=int, default=3, help="o3dreg runs (best time kept)")
    parser.add_argument("--json", help="write every row to this JSON file")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(run_child(*args.child)))
        return

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases:
            case = build_case(name)
            if case is None:
                continue
            path = os.path.join(tmp, f"{name}.npz")
            np.savez(path, name=name, **case)
            for method in args.methods:
                if method == "cpd" and name not in CPD_CASES:
                    continue
                runs = []
                for _ in range(args.repeat if method.startswith("o3dreg") else 1):
                    out = subprocess.run(
                        [sys.executable, __file__, "--child", method, path],
                        capture_output=True,
                        text=True,
                    )
                    if out.returncode != 0:
                        print(f"FAILED {name} {method}: {out.stderr[-500:]}", file=sys.stderr)
                        break
                    runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
                if runs:
                    rows.append(min(runs, key=lambda r: r["seconds"]))
                    print(f"done {name} {method}: {rows[-1]['seconds']:.2f} s", file=sys.stderr)
    print_table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "settings": METHODS}, indent=1))


def print_table(rows: list[dict]) -> None:
    head = (
        f"{'case':<16}{'method':<14}{'time s':>7}{'x o3d':>7}{'peak MB':>8}{'err mean':>9}"
        f"{'%diag':>7}{'p95':>7}{'max':>7}{'x o3d':>6}{'s>t mean':>9}{'max':>6}{'t>s mean':>9}"
        f"{'max':>6}{'flip%':>6}{'fold%':>6}"
    )
    print(head)
    for case in dict.fromkeys(r["case"] for r in rows):
        group = [r for r in rows if r["case"] == case]
        ref = next((r for r in group if r["method"] == "o3dreg"), group[0])
        print(
            f"{case} (template {ref['template_vertices']}, target {ref['target_vertices']} vertices)"
        )
        for r in group:
            print(
                f"{'':<16}{r['method']:<14}{r['seconds']:>7.2f}{r['seconds'] / ref['seconds']:>7.1f}"
                f"{r['peak_rss_mb']:>8.0f}{r['error_mean']:>9.3f}{r['error_mean_pct_diag']:>7.3f}"
                f"{r['error_p95']:>7.2f}{r['error_max']:>7.2f}"
                f"{r['error_mean'] / ref['error_mean']:>6.1f}{r['s2t_mean']:>9.3f}"
                f"{r['s2t_max']:>6.1f}{r['t2s_mean']:>9.3f}{r['t2s_max']:>6.1f}"
                f"{r['flipped_pct']:>6.2f}{r['folded_edges_pct']:>6.2f}"
            )
    print("\nsettings (seed 1 for warps, noise and outliers; seed 0 for CPD's subsample):")
    for method, text in METHODS.items():
        print(f"  {method}: {text}")


if __name__ == "__main__":
    main()
