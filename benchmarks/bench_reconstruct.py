"""Time and memory of CT -> bone surface on a synthetic 512 x 512 x 300 int16 scan.

Run: ``.venv/bin/python benchmarks/bench_reconstruct.py [--planes 300] [--size 512]``

The scan is a head-sized "skull": an ellipsoidal bone shell (1200 HU, 6 mm thick) around soft
tissue (40 HU) in air (-1000 HU), 0.5 x 0.5 x 1.0 mm voxels. It is written once as a MetaImage
file; each stage then runs in a fresh subprocess that reports its wall time, the peak of
Python/numpy allocations (tracemalloc) and the process's peak resident memory (ru_maxrss).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

_STAGE = r"""
import json, resource, sys, time, tracemalloc
import numpy as np
import o3dreg
path, threshold = sys.argv[1], float(sys.argv[2])
out = {"rss_after_import_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
tracemalloc.start()
t = time.perf_counter()
volume = o3dreg.read_volume(path)
out["read_s"] = time.perf_counter() - t
out["read_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
out["volume_mib"] = volume.array.nbytes / 2**20
tracemalloc.reset_peak()
t = time.perf_counter()
mesh = o3dreg.isosurface(volume, threshold)
out["isosurface_s"] = time.perf_counter() - t
out["isosurface_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
out["vertices"] = len(mesh.vertices)
tracemalloc.reset_peak()
t = time.perf_counter()
mesh = o3dreg.keep_largest_components(mesh)
out["largest_s"] = time.perf_counter() - t
t = time.perf_counter()
mesh = o3dreg.smooth_taubin(mesh, 10)
out["smooth_s"] = time.perf_counter() - t
t = time.perf_counter()
mesh = o3dreg.decimate(mesh, 4000)
out["decimate_s"] = time.perf_counter() - t
out["cleaning_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
out["final_vertices"] = len(mesh.vertices)
out["rss_peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def make_scan(path: str, planes: int, size: int) -> None:
    import numpy as np
    import SimpleITK as sitk

    spacing = (0.5, 0.5, 1.0)  # x, y, z (ITK order)
    array = np.empty((planes, size, size), dtype=np.int16)
    y, x = np.mgrid[:size, :size].astype(np.float32)
    x = (x - size / 2) * spacing[0]
    y = (y - size / 2) * spacing[1]
    outer = np.array([90.0, 110.0, 0.45 * planes * spacing[2]], dtype=np.float32)  # semi-axes
    inner = outer - 6.0
    for p in range(planes):
        z = np.float32((p - planes / 2) * spacing[2])
        r_out = (x / outer[0]) ** 2 + (y / outer[1]) ** 2 + (z / outer[2]) ** 2
        r_in = (x / inner[0]) ** 2 + (y / inner[1]) ** 2 + (z / inner[2]) ** 2
        plane = np.full((size, size), -1000, dtype=np.int16)
        plane[r_out < 1.0] = 1200
        plane[r_in < 1.0] = 40
        array[p] = plane
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    image.SetOrigin((-size / 4, -size / 4, 0.0))
    sitk.WriteImage(image, path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planes", type=int, default=300)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--threshold", type=float, default=400.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "scan.mha")
        t = time.perf_counter()
        make_scan(path, args.planes, args.size)
        print(f"synthetic scan {args.size} x {args.size} x {args.planes} int16 written in "
              f"{time.perf_counter() - t:.1f} s")  # fmt: skip
        proc = subprocess.run(
            [sys.executable, "-c", _STAGE, path, str(args.threshold)],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            return proc.returncode
        result = json.loads(proc.stdout.strip().splitlines()[-1])
    for key, value in result.items():
        print(f"{key:>22}: {value:.2f}" if isinstance(value, float) else f"{key:>22}: {value}")
    ratio = result["isosurface_peak_mib"] / result["volume_mib"]
    print(f"isosurface peak allocations = {ratio:.2f} x the volume")
    return 0


if __name__ == "__main__":
    sys.exit(main())
