"""How o3dreg's time and peak memory grow with the target and the template, and where time goes.

Targets: the bundled bunny decimated to ``n / 4**k`` vertices then Loop-subdivided ``k`` times
(10k, 36k, 144k, 1M vertices), under the medium known warp; template 3k. Templates: 1k, 3k, 10k
and 20k vertices onto the 36k bunny. Each run is its own process (meshes handed over as .npz, so
the peak memory ``ru_maxrss`` is the registration's plus the interpreter's and the inputs').
The profile is cProfile of the medium case, grouped by o3dreg stage.

    python benchmarks/bench_scaling.py            # scaling tables + profile
    python benchmarks/bench_scaling.py --profile  # profile only
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

TARGETS = {10_000: 0, 36_000: None, 144_000: 1, 1_000_000: 3}
TEMPLATES = (1000, 3000, 10000, 20000)

#: Profile groups: (label, substring of "file:function" in cProfile's keys).
STAGES = [
    ("cost evaluation _cost.LevelProblem.evaluate (total)", "_cost.py:evaluate"),
    ("  point-to-surface SurfaceDistanceQuery.closest", "distance.py:closest"),
    ("accepted points: barycentre re-assignment (SciPy k-d tree)", "_cost.py:reweighted"),
    ("level starts: scales, first queries, pattern", "_cost.py:__init__"),
    ("normal equations (fixed pattern)", "normal_equations"),
    ("solve the damped system DampedSystem.solve_damped", "_solvers.py:solve_damped"),
    ("lattice weights / Jacobian (lattice.py)", "lattice.py"),
    ("target levels of detail (vertex clustering)", "_target.py:build_levels_of_detail"),
    ("libigl AABB tree builds SurfaceDistanceQuery._tree", "distance.py:_tree"),
    ("final distances both ways (TargetSurface.distances)", "_target.py:distances"),
]


def target_mesh(n: int):

    from o3dreg.app.datasets import load_bunny

    bunny = load_bunny()
    k = TARGETS[n]
    if k is None:
        return bunny
    base = bunny.simplify_quadric_decimation(2 * n // 4**k)
    base.remove_unreferenced_vertices()
    return base.subdivide_loop(k) if k else base


def make_case(target, template_vertices: int) -> dict:
    from o3dreg.app.datasets import load_bunny
    from o3dreg.app.synthetic import SmoothWarp

    bunny = load_bunny()
    template = bunny.simplify_quadric_decimation(2 * template_vertices)
    template.remove_unreferenced_vertices()
    warp = SmoothWarp.random(np.asarray(bunny.vertices), magnitude=0.05, seed=1)
    return {
        "sv": np.asarray(template.vertices),
        "sf": np.asarray(template.triangles),
        "tv": warp(np.asarray(target.vertices)),
        "tf": np.asarray(target.triangles),
        "truth": warp(np.asarray(template.vertices)),
    }


def child(path: str) -> dict:
    import o3dreg

    with np.load(path) as data:
        case = {k: data[k] for k in data.files}
    from bench_peers import rss_mb

    base = rss_mb()
    start = time.perf_counter()
    result = o3dreg.registration_elastic(
        (case["sv"], case["sf"]), (case["tv"], case["tf"]), init=np.eye(4)
    )
    seconds = time.perf_counter() - start
    err = np.linalg.norm(result.vertices - case["truth"], axis=1)
    peak = rss_mb()
    return {
        "template": len(case["sv"]),
        "target": len(case["tv"]),
        "seconds": seconds,
        "peak_mb": peak,
        "growth_mb": peak - base,
        "error_mean": float(err.mean()),
        "levels_s": [round(h.seconds, 3) for h in result.history],
    }


def run(case: dict, tmp: str) -> dict:
    path = os.path.join(tmp, "case.npz")
    np.savez(path, **case)
    out = subprocess.run(
        [sys.executable, __file__, "--child", path], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def profile() -> None:
    from _cases import bunny_case

    import o3dreg

    case = bunny_case("medium", 3000)
    o3dreg.registration_elastic(case.template, case.target, init=np.eye(4))  # warm-up
    prof = cProfile.Profile()
    start = time.perf_counter()
    prof.enable()
    o3dreg.registration_elastic(case.template, case.target, init=np.eye(4))
    prof.disable()
    total = time.perf_counter() - start
    stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
    print(f"\nprofile: bunny medium, 3k -> 36k, {total:.3f} s wall (cProfile on)")
    print(f"{'stage':<58}{'calls':>7}{'cum s':>8}{'% total':>8}")
    for label, key in STAGES:
        calls, cum = 0, 0.0
        for (file, _line, func), (_cc, nc, _tt, ct, _callers) in stats.items():
            if key in f"{os.path.basename(file)}:{func}" or key in func:
                calls += nc
                cum += ct
        print(f"{label:<58}{calls:>7}{cum:>8.3f}{100 * cum / total:>8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--profile", action="store_true", help="profile only")
    parser.add_argument(
        "--targets",
        type=lambda text: [int(n) for n in text.split(",")],
        default=list(TARGETS),
        help=f"target sizes to run, comma-separated, of {list(TARGETS)} (default: all)",
    )
    parser.add_argument("--no-templates", action="store_true", help="skip the template scaling")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return
    if not args.profile:
        with tempfile.TemporaryDirectory() as tmp:
            print("target scaling (template ~3k vertices):")
            print(f"{'target':>9}{'template':>9}{'time s':>8}{'peak MB':>9}{'err mm':>8}  levels s")
            for n in args.targets:
                r = run(make_case(target_mesh(n), 3000), tmp)
                print(
                    f"{r['target']:>9}{r['template']:>9}{r['seconds']:>8.2f}{r['peak_mb']:>9.0f}"
                    f"{r['error_mean']:>8.3f}  {r['levels_s']}",
                    flush=True,
                )
            if args.no_templates:
                return
            print("template scaling (target: the 36k bunny):")
            bunny = target_mesh(36_000)
            for m in TEMPLATES:
                r = run(make_case(bunny, m), tmp)
                print(
                    f"{r['target']:>9}{r['template']:>9}{r['seconds']:>8.2f}{r['peak_mb']:>9.0f}"
                    f"{r['error_mean']:>8.3f}  {r['levels_s']}",
                    flush=True,
                )
    profile()


if __name__ == "__main__":
    main()
