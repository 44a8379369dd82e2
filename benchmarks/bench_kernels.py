"""o3dreg's compiled kernels against the libraries they replaced, on the registration's queries.

The case: the bundled 36k-vertex bunny (69k triangles) as the target and its ~3k-vertex
decimation as the template, moved by the medium known warp (5% of the diagonal), as in
``bench_registration.py``. Each figure is the best of ``--repeat`` runs in this process; ratios
are against the peer measured in the same run.

* closest points: ``o3dreg._bvh.TriangleTree`` (built, then queried by the 3k template points,
  with and without each point's previous triangle as a hint) against libigl's ``AABB``;
  distances compared to the last bit allowed (1e-12 relative);
* nearest two template points of the 36k target points: ``o3dreg._nearest.nearest_two`` against
  SciPy's ``cKDTree`` (built, then ``query(k=2, workers=-1)``); distances compared exactly.

    python benchmarks/bench_kernels.py
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def best(run: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()

    import igl
    from _cases import bunny_case
    from scipy.spatial import cKDTree

    from o3dreg._bvh import TriangleTree
    from o3dreg._nearest import nearest_two

    case = bunny_case("medium", 3000)
    v = np.ascontiguousarray(case.target.vertices, dtype=np.float64)
    f = np.ascontiguousarray(case.target.triangles, dtype=np.int64)
    points = np.ascontiguousarray(case.template.vertices, dtype=np.float64)
    r = args.repeat

    def igl_tree():  # type: ignore[no-untyped-def]
        tree = igl.AABB()
        tree.init(v, f)
        return tree

    rows = []
    rows.append(("tree build, 69k triangles", best(lambda: TriangleTree(v, f), r),
                 "libigl AABB.init", best(igl_tree, r)))  # fmt: skip
    ours, theirs = TriangleTree(v, f), igl_tree()
    sqr, face, _ = ours.closest(points)
    ref, _, _ = theirs.squared_distance(v, f, points)
    assert np.allclose(sqr, ref, rtol=1e-12, atol=1e-12 * float(np.ptp(v) ** 2))
    nearby = points + 0.01  # the next evaluation's points: moved a little
    igl_query = best(lambda: theirs.squared_distance(v, f, nearby), r)
    rows.append(("closest points of 3k points", best(lambda: ours.closest(nearby), r),
                 "libigl AABB.squared_distance", igl_query))  # fmt: skip
    rows.append(("  ... from last time's triangles", best(lambda: ours.closest(nearby, face), r),
                 "libigl AABB.squared_distance", igl_query))  # fmt: skip
    d, _ = nearest_two(points, v)
    e, _ = cKDTree(points).query(v, k=2, workers=-1)
    assert np.array_equal(d, e)
    rows.append(("nearest two of 3k sites, 36k points", best(lambda: nearest_two(points, v), r),
                 "SciPy cKDTree + query(k=2, workers=-1)",
                 best(lambda: cKDTree(points).query(v, k=2, workers=-1), r)))  # fmt: skip

    print(f"bunny: target {len(v)} vertices / {len(f)} triangles, template {len(points)} vertices")
    print(f"{'o3dreg kernel':<40}{'ms':>8}  {'peer':<40}{'ms':>8}{'peer / o3dreg':>15}")
    for name, t, peer, tp in rows:
        print(f"{name:<40}{1e3 * t:>8.2f}  {peer:<40}{1e3 * tp:>8.2f}{tp / t:>15.1f}")


if __name__ == "__main__":
    main()
