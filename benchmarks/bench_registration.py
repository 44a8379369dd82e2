"""Time, peak memory and correspondence error of o3dreg against non-rigid ICP peers.

The case: a ~3k-vertex template decimated from the bundled bunny, registered onto the full
36k-vertex bunny under a known smooth warp (5% of the diagonal: the "medium" case). Every method
runs in its own process, so peak memory is its own. Ratios are against o3dreg measured in the same
run.

    python benchmarks/bench_registration.py                 # all methods
    python benchmarks/bench_registration.py --skip-peers    # o3dreg only (seconds)
    python benchmarks/bench_registration.py --rounds 5      # 5 rounds: the ratios' spread
    python benchmarks/bench_registration.py --skip-peers --inverse-consistent --magnitude small

``--inverse-consistent`` adds ``o3dreg-inverse-consistent``: the warped bunny, decimated like the
template, is also registered back onto the unwarped one, and each template vertex is the mean of
its forward image and of the point that backward map sends onto it
(``ElasticRegistrationResult.inverse_transform``); its time counts both registrations.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

METHODS = {
    "o3dreg": "symmetric distance, default levels 2-4-8-16, init=identity",
    "o3dreg+rigid": "symmetric distance, default levels, rigid pre-alignment included",
    "o3dreg-single": "single distance (paper eq. 2), default levels, init=identity",
    "o3dreg-inverse-consistent": "o3dreg both ways (the target decimated like the template, "
    "onto the unwarped bunny), the mean of the forward and backward images",
    "nricp_amberg": "trimesh.registration.nricp_amberg, default steps (its documented schedule)",
    "nricp_sumner": "trimesh.registration.nricp_sumner, default steps",
}


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Clock:
    """Seconds spent inside the libraries o3dreg calls, by kind, while a registration runs.

    The wrappers replace the names o3dreg's modules look up at call time (libigl's ``AABB``,
    SciPy's ``cKDTree``, ``cg``, ``spsolve`` and the dense factorisations, and the k-d tree
    search in two halves, ``in_halves``); everything else is o3dreg's own Python and NumPy
    glue. Wall time on the calling thread: a call inside a timed call (a half of a split search)
    and the worker thread's half are already in the outer call's time.
    """

    KINDS = ("libigl closest points", "k-d tree queries", "tree builds", "SciPy solves")

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(self.KINDS, 0.0)
        self._inside = False

    def timed(self, kind: str, fn):
        def call(*args, **kwargs):
            if self._inside or threading.current_thread() is not threading.main_thread():
                return fn(*args, **kwargs)
            self._inside = True
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[kind] += time.perf_counter() - start
                self._inside = False

        return call

    def install(self) -> None:
        import types

        import igl
        import scipy.linalg
        import scipy.sparse.linalg
        from scipy.spatial import cKDTree

        from o3dreg.registration import _terms, distance, rigid

        clock = self

        class AABB:
            def __init__(self) -> None:
                self._tree = igl.AABB()
                self.init = clock.timed("tree builds", self._tree.init)
                self.squared_distance = clock.timed(
                    "libigl closest points", self._tree.squared_distance
                )

        class KDTree:
            def __init__(self, *args, **kwargs) -> None:
                self._tree = clock.timed("tree builds", cKDTree)(*args, **kwargs)
                self.query = clock.timed("k-d tree queries", self._tree.query)
                self.query_ball_point = clock.timed("k-d tree queries", self._tree.query_ball_point)

        distance.igl = types.SimpleNamespace(AABB=AABB)
        for module in (_terms, distance, rigid):
            module.cKDTree = KDTree
        _terms.in_halves = clock.timed("k-d tree queries", _terms.in_halves)
        for module, names in (
            (scipy.sparse.linalg, ("cg", "spsolve")),
            (scipy.linalg, ("cho_factor", "cho_solve", "solve")),
        ):
            for name in names:
                setattr(module, name, self.timed("SciPy solves", getattr(module, name)))


def run_one(method: str, magnitude: str, template_vertices: int, shares: bool = False) -> dict:
    from _cases import bunny_case, template_of

    import o3dreg

    case = bunny_case(magnitude, template_vertices)
    clock = _Clock()
    if shares and method.startswith("o3dreg"):
        clock.install()
    baseline = rss_mb()
    start = time.perf_counter()
    if method.startswith("o3dreg"):
        result = o3dreg.registration_elastic(
            case.template,
            case.target,
            init=None if method == "o3dreg+rigid" else np.eye(4),
            estimation_method=o3dreg.DistanceEstimation(symmetric=method != "o3dreg-single"),
        )
        moved = result.vertices
        if method == "o3dreg-inverse-consistent":
            from o3dreg.app.datasets import load_bunny

            back = template_of(case.target, template_vertices)
            backward = o3dreg.registration_elastic(back, load_bunny(), init=np.eye(4))
            moved = 0.5 * (moved + backward.inverse_transform(np.asarray(case.template.vertices)))
        profile = {
            f"level_{h.resolution}": {"s": round(h.seconds, 3), "evaluations": h.evaluations}
            for h in result.history
        }
    else:
        import trimesh
        import trimesh.registration as treg

        source = trimesh.Trimesh(
            np.asarray(case.template.vertices), np.asarray(case.template.triangles), process=False
        )
        target = trimesh.Trimesh(
            np.asarray(case.target.vertices), np.asarray(case.target.triangles), process=False
        )
        fn = getattr(treg, method)
        moved = np.asarray(fn(source, target))
        profile = {}
    seconds = time.perf_counter() - start
    err = np.linalg.norm(moved - case.truth, axis=1)
    d = o3dreg.evaluate_elastic((moved, np.asarray(case.template.triangles)), case.target)
    return {
        "method": method,
        "case": case.name,
        "template_vertices": len(case.template.vertices),
        "target_vertices": len(case.target.vertices),
        "seconds": seconds,
        "peak_rss_mb": rss_mb(),
        "rss_growth_mb": rss_mb() - baseline,
        "error_mean": float(err.mean()),
        "error_p95": float(np.percentile(err, 95)),
        "error_max": float(err.max()),
        "error_mean_pct_diag": float(100 * err.mean() / case.diagonal),
        "s2t_mean": d.source_to_target_mean,
        "t2s_mean": d.target_to_source_mean,
        "profile": profile,
        "library_seconds": clock.seconds if shares else {},
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--method", choices=list(METHODS), help="run one method in this process (internal)"
    )
    parser.add_argument("--magnitude", default="medium", choices=["small", "medium", "large"])
    parser.add_argument("--template-vertices", type=int, default=3000)
    parser.add_argument("--skip-peers", action="store_true")
    parser.add_argument(
        "--inverse-consistent",
        action="store_true",
        help="add o3dreg-inverse-consistent (see above)",
    )
    parser.add_argument(
        "--repeat", type=int, default=3, help="o3dreg runs per method (best time kept)"
    )
    parser.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="measure every method this many times in turn and print each round's time ratios "
        "against o3dreg and their median (the table is the first round's)",
    )
    parser.add_argument("--shares", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.method:
        print(json.dumps(run_one(args.method, args.magnitude, args.template_vertices, args.shares)))
        return
    methods = [m for m in METHODS if not (args.skip_peers and not m.startswith("o3dreg"))]
    if not args.inverse_consistent:
        methods.remove("o3dreg-inverse-consistent")
    if args.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {args.rounds}")
    # Each round measures every method once more, side by side: the machine's speed drifts
    # over minutes, so a ratio is read within one round.
    rounds = [measure_round(args, methods) for _ in range(args.rounds)]
    rows = rounds[0]
    ref = rows[0]
    print(
        f"case {ref['case']}: template {ref['template_vertices']} vertices -> target "
        f"{ref['target_vertices']} vertices; errors are distances to the ground-truth position"
    )
    width = max(15, *(len(r["method"]) + 2 for r in rows))
    head = (
        f"{'method':<{width}}{'time s':>8}{'x o3dreg':>9}{'peak MB':>9}{'growth MB':>10}"
        f"{'err mean':>9}{'% diag':>8}{'p95':>7}{'max':>7}{'x o3dreg':>9}{'s->t':>7}{'t->s':>7}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['method']:<{width}}{r['seconds']:>8.3f}{r['seconds'] / ref['seconds']:>9.1f}"
            f"{r['peak_rss_mb']:>9.0f}{r['rss_growth_mb']:>10.0f}{r['error_mean']:>9.3f}"
            f"{r['error_mean_pct_diag']:>8.3f}{r['error_p95']:>7.2f}{r['error_max']:>7.2f}"
            f"{r['error_mean'] / ref['error_mean']:>9.2f}{r['s2t_mean']:>7.3f}{r['t2s_mean']:>7.3f}"
        )
    print("\nsettings:")
    for r in rows:
        print(f"  {r['method']}: {METHODS[r['method']]}")
    if ref["profile"]:
        print(f"  o3dreg per level: {ref['profile']}")
    if args.rounds > 1:
        print(f"\ntime / o3dreg's in each of {args.rounds} rounds, and the median:")
        for k, method in enumerate(methods[1:], start=1):
            ratios = [r[k]["seconds"] / r[0]["seconds"] for r in rounds]
            cells = " ".join(f"{x:5.1f}" for x in ratios)
            print(f"  {method:<{width}}{cells}   median {float(np.median(ratios)):.1f}")
    print_shares(args, [m for m in methods if m.startswith("o3dreg")])


def measure_round(args: argparse.Namespace, methods: list[str]) -> list[dict]:
    """One run of each method in its own process (o3dreg's best of ``--repeat``)."""
    rows = []
    for method in methods:
        runs = []
        for _ in range(args.repeat if method.startswith("o3dreg") else 1):
            out = subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--method",
                    method,
                    "--magnitude",
                    args.magnitude,
                    "--template-vertices",
                    str(args.template_vertices),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        rows.append(min(runs, key=lambda r: r["seconds"]))
        print(f"done {method}: {rows[-1]['seconds']:.2f} s", file=sys.stderr)
    return rows


def print_shares(args: argparse.Namespace, methods: list[str]) -> None:
    """Where each o3dreg method's time goes: one more run of each with the library calls timed
    (the wrappers cost microseconds a call; this run's total is not the one in the table)."""
    print("\nwhere the time goes (one timed run each; the rest is o3dreg's Python and NumPy glue):")
    print(
        f"  {'method':<15}{'total s':>8}"
        + "".join(f"{k:>23}" for k in _Clock.KINDS)
        + f"{'glue':>16}"
    )
    for method in methods:
        out = subprocess.run(
            [sys.executable, __file__, "--method", method, "--magnitude", args.magnitude,
             "--template-vertices", str(args.template_vertices), "--shares"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        r = json.loads(out.stdout.strip().splitlines()[-1])
        total, parts = r["seconds"], r["library_seconds"]
        glue = total - sum(parts.values())
        cells = "".join(
            f"{parts[k]:>10.3f} s {100 * parts[k] / total:>4.0f}% " for k in _Clock.KINDS
        )
        print(f"  {method:<15}{total:>8.3f}{cells}{glue:>9.3f} s {100 * glue / total:>3.0f}%")


if __name__ == "__main__":
    main()
