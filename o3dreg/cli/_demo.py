"""``o3dreg demo``: the whole pipeline of the paper on data bundled with o3dreg."""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import shutil
import sys

from ..app.demo import run_demo
from ._common import emit, emit_json

MARKER = ".o3dreg-demo"

EPILOG = """what it does:
  bundled CT head -> bone mesh (marching cubes, largest component, smoothing) -> template
  (decimated) -> a population of patients (smooth deformations from a known 3-mode model, rigid motions,
  independent remeshing; a known ground truth) -> batch registration -> Procrustes -> PCA shape
  model -> landmarks predicted on a held-out patient -> report.md with tables and pictures.

examples:
  o3dreg demo                       # writes ./o3dreg-demo/report.md
  o3dreg demo -o out --patients 12 --jobs 2"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the whole pipeline (CT -> shape model -> report) on bundled data",
        description="Run the paper's pipeline on the bundled CT head and write a report.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "-o",
        "--output",
        default="o3dreg-demo",
        help="output folder (default ./o3dreg-demo; a folder from an earlier demo is replaced, "
        "any other non-empty folder is refused)",
    )
    p.add_argument("--patients", type=int, default=8, help="patients in the model (default 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic population")
    p.add_argument("--jobs", type=int, default=1, help="parallel registrations (processes)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.set_defaults(func=run)


def prepare_output(folder: str) -> str:
    """Create ``folder``; replace it only if an earlier demo made it."""
    folder = os.path.abspath(folder)
    if os.path.exists(folder):
        if not os.path.isdir(folder):
            raise OSError(f"--output: {folder!r} exists and is not a folder")
        if os.listdir(folder) and not os.path.isfile(os.path.join(folder, MARKER)):
            raise OSError(
                f"--output: {folder!r} is not empty and was not made by `o3dreg demo`; "
                "choose another folder"
            )
        shutil.rmtree(folder)
    os.makedirs(folder)
    with open(os.path.join(folder, MARKER), "w", encoding="utf-8") as fh:
        fh.write("made by o3dreg demo; replaced by the next demo run\n")
    return folder


def run(args: argparse.Namespace) -> int:
    if args.patients < 3:
        raise ValueError(f"--patients must be >= 3, got {args.patients}")
    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    folder = prepare_output(args.output)
    show = not args.quiet and not args.json
    emit(f"o3dreg demo: CT -> bone -> template -> {args.patients} patients -> shape model", args)
    pool = cf.ProcessPoolExecutor(args.jobs) if args.jobs > 1 else None
    try:
        result = run_demo(
            folder, number_of_patients=args.patients, seed=args.seed, progress=show, executor=pool
        )
    finally:
        if pool is not None:
            pool.shutdown()
    emit(result.batch.table(), args)
    emit("", args)
    emit(result.model.variance_table(), args)
    emit("", args)
    emit(
        f"landmarks predicted on the held-out patient: mean error "
        f"{result.landmark_error_mean:.2f} mm",
        args,
    )
    emit(f"report: {result.report}  ({result.seconds:.0f} s)", args)
    if args.json:
        emit_json(
            {
                "output": str(result.output),
                "report": str(result.report),
                "patients": [r.name for r in result.batch.records],
                "failed": [r.name for r in result.batch.failed],
                "explained_variance_ratio": result.model.explained_variance_ratio.tolist(),
                "landmark_error_mean_mm": result.landmark_error_mean,
                "seconds": result.seconds,
            }
        )
    sys.stdout.flush()
    return 0 if not result.batch.failed else 1
