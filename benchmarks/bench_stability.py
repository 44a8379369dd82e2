"""How stable a registration is on real CT mandibles: against the patient's pose in the scanner,
and against tiny changes of the start.

The 8 PDDCA mandible masks (research data, read from ``../shared/data/mandibles/masks`` or
``$O3DREG_SHARED_DATA``; the script exits with a message when they are absent) are
reconstructed as ``examples/mandible_model.py`` does; the first, decimated to ~2500 vertices, is
the template. For each of the other seven:

* **pose**: the patient turned by 30 degrees about z, 90 degrees about z and 50 degrees about an
  oblique axis, and shifted; registered as a user runs it (the rigid step included); the
  registered vertices turned back and compared with the unturned patient's registration:
  mean and max of the per-vertex distances (mm). ``rigid`` is the same for the rigid step's
  start alone.
* **start**: the unturned registration's start shifted by 0.01 mm (normal, 4 seeds) and given
  as ``init``: the same comparison, and how many template vertices moved by more than 1 mm.

    python benchmarks/bench_stability.py           # default criteria
    python benchmarks/bench_stability.py --tight   # levels stop at 1e-5 (up to 100 steps)
"""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

from mandible_model import data_dir, reconstruct  # noqa: E402

import o3dreg  # noqa: E402

#: The turns (rotation vectors, radians) and the shift (mm) of the pose test.
TURNS = {
    "z 30": np.radians(30.0) * np.array([0.0, 0.0, 1.0]),
    "z 90": np.radians(90.0) * np.array([0.0, 0.0, 1.0]),
    "oblique 50": np.radians(50.0) * np.array([0.36, -0.6, 0.72]),
}
SHIFT = np.array([10.0, -20.0, 30.0])
NUDGE_MM = 0.01
NUDGES = 4


def turn(points: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    return (points - centre) @ rotation.T + centre + SHIFT


def turn_back(points: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    return (points - centre - SHIFT) @ rotation + centre


def gaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tight", action="store_true", help="levels stop at 1e-5")
    args = parser.parse_args()
    masks = sorted(glob.glob(str(data_dir() / "masks" / "*.nrrd")))
    if not masks:
        sys.exit(
            f"no mandible masks in {data_dir() / 'masks'} (research data, not in a fresh clone)"
        )
    criteria = None
    if args.tight:
        criteria = o3dreg.ElasticCriteria(max_iteration=100, relative_cost=1e-5, relative_step=1e-5)
    template = reconstruct(masks[0], 2500)
    tv, tf = np.asarray(template.vertices), np.asarray(template.triangles)
    rng = np.random.default_rng(0)
    print(
        f"template {len(tv)} vertices; criteria "
        f"{'tight (1e-5, 100 steps)' if args.tight else 'default'}; distances in mm"
    )
    print(f"{'patient':10s} {'test':12s} {'rigid':>7s} {'mean':>7s} {'max':>7s} {'>1 mm':>6s}")
    seconds = []
    for path in masks[1:]:
        name = Path(path).name[:9]
        patient = reconstruct(path)
        pv, pf = np.asarray(patient.vertices), np.asarray(patient.triangles)
        start = time.perf_counter()
        here = o3dreg.registration_elastic((tv, tf), (pv, pf), criteria=criteria)
        seconds.append(time.perf_counter() - start)
        t0 = np.asarray(here.transformation)
        rigid_here = tv @ t0[:3, :3].T + t0[:3, 3]
        centre = pv.mean(axis=0)
        for label, rotvec in TURNS.items():
            rotation = Rotation.from_rotvec(rotvec).as_matrix()
            there = o3dreg.registration_elastic(
                (tv, tf), (turn(pv, rotation, centre), pf), criteria=criteria
            )
            t1 = np.asarray(there.transformation)
            rigid_there = turn_back(tv @ t1[:3, :3].T + t1[:3, 3], rotation, centre)
            d = gaps(turn_back(there.vertices, rotation, centre), here.vertices)
            r = gaps(rigid_there, rigid_here).mean()
            print(
                f"{name:10s} {'pose ' + label:12s} {r:7.3f} {d.mean():7.3f} {d.max():7.2f} "
                f"{int((d > 1.0).sum()):6d}"
            )
        for k in range(NUDGES):
            nudged = t0.copy()
            nudged[:3, 3] += rng.normal(0.0, NUDGE_MM, 3)
            again = o3dreg.registration_elastic((tv, tf), (pv, pf), init=nudged, criteria=criteria)
            d = gaps(again.vertices, here.vertices)
            print(
                f"{name:10s} {f'start {k + 1}':12s} {'':>7s} {d.mean():7.3f} {d.max():7.2f} "
                f"{int((d > 1.0).sum()):6d}"
            )
    print(f"one registration: {min(seconds):.2f}-{max(seconds):.2f} s")


if __name__ == "__main__":
    main()
