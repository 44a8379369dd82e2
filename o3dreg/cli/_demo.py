"""``o3dreg demo``: the whole pipeline of the paper on data bundled with o3dreg."""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
from typing import Any

from ..app.demo import run_demo
from ..io.mesh import atomic_write_text, process_alive
from ._common import add_jobs_option, add_json_option, emit, emit_json, process_pool

MARKER = ".o3dreg-demo"

EPILOG = """what it does:
  bundled CT head -> bone mesh (marching cubes, largest component, smoothing) -> template
  (decimated) -> a population of patients (smooth deformations from a known 3-mode model, rigid motions,
  independent remeshing; a known ground truth) -> batch registration -> Procrustes -> PCA shape
  model -> landmarks predicted on a held-out patient -> report.md with tables and pictures.

examples:
  o3dreg demo                       # writes ./o3dreg-demo/report.md
  o3dreg demo -o out --patients 12 --jobs 2"""


def add_parser(sub: Any) -> None:
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
        help="output folder (default ./o3dreg-demo; the files an earlier demo wrote there are "
        "replaced; a folder holding any other file is refused)",
    )
    p.add_argument("--patients", type=int, default=8, help="patients in the model (default 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic population")
    add_jobs_option(p)
    add_json_option(p)
    p.set_defaults(func=run)


_MARKER_HEADER = "made by o3dreg demo; the files it wrote (removed by the next demo run):"


#: The hidden folder inside the output where a demo run writes, moved into place when it ends.
STAGING_PREFIX = ".o3dreg-demo-run."


def _files_under(folder: str) -> set[str]:
    found = set()
    for root, dirs, files in os.walk(folder):
        if root == folder:
            dirs[:] = [d for d in dirs if not d.startswith(STAGING_PREFIX)]
        for name in files:
            found.add(os.path.relpath(os.path.join(root, name), folder))
    return found - {MARKER}


def prepare_output(folder: str) -> tuple[str, set[str]]:
    """Create ``folder`` and return it with the files an earlier demo wrote there (which the new
    run replaces when it has finished: an interrupted or failed run leaves them).

    Refused: a non-empty folder without the demo's marker, and a demo folder holding any file
    the marker does not list (added since, or left by a demo that was killed).
    """
    folder = os.path.abspath(folder)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OSError(f"--output: {folder!r} exists and is not a folder")
    present = _files_under(folder) if os.path.isdir(folder) else set()
    marker = os.path.join(folder, MARKER)
    if present:
        if not os.path.isfile(marker):
            raise OSError(
                f"--output: {folder!r} is not empty and was not made by `o3dreg demo`; "
                "choose another folder"
            )
        with open(marker, encoding="utf-8") as fh:
            listed = {line.strip() for line in fh.read().splitlines()[1:] if line.strip()}
        foreign = sorted(present - listed)
        if foreign:
            raise OSError(
                f"--output: {folder!r} holds {len(foreign)} file(s) an earlier `o3dreg demo` "
                f"did not write ({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); "
                "move them or choose another folder"
            )
    os.makedirs(folder, exist_ok=True)
    if not present:
        _write_marker(folder, set())
    # Staging folders of runs killed outright (SIGKILL, power loss).
    for entry in os.listdir(folder):
        if entry.startswith(STAGING_PREFIX):
            pid = entry[len(STAGING_PREFIX) :].split(".")[0]
            if not pid.isdigit() or not process_alive(int(pid)):
                shutil.rmtree(os.path.join(folder, entry), ignore_errors=True)
    return folder, present


def _replace_demo(folder: str, staging: str, earlier: set[str]) -> None:
    """Remove the ``earlier`` demo's files from ``folder`` and move the new run's in."""
    # The marker lists both while they are swapped: a swap cut short leaves no file unlisted.
    _write_marker(folder, earlier | _files_under(staging))
    for name in earlier:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(folder, name))
    for root, _, _ in sorted(os.walk(folder), key=lambda w: -len(w[0])):
        if root != folder and not root.startswith(staging) and not os.listdir(root):
            os.rmdir(root)
    for entry in os.listdir(staging):
        os.replace(os.path.join(staging, entry), os.path.join(folder, entry))
    _write_marker(folder, _files_under(folder))


def _write_marker(folder: str, files: set[str]) -> None:
    atomic_write_text(
        os.path.join(folder, MARKER),
        "\n".join([_MARKER_HEADER, *sorted(files)]) + "\n",
        overwrite=True,
    )


def run(args: argparse.Namespace) -> int:
    if args.patients < 3:
        raise ValueError(f"--patients must be >= 3, got {args.patients}")
    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    folder, earlier = prepare_output(args.output)
    show = not args.quiet and not args.json
    emit(f"o3dreg demo: CT -> bone -> template -> {args.patients} patients -> shape model", args)
    # The run writes into a hidden folder and replaces the earlier demo's files only once it
    # has finished: Ctrl-C or an error leaves them as they were.
    staging = tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}.", dir=folder)
    start = time.perf_counter()
    try:
        with process_pool(args.jobs) as pool:
            result = run_demo(
                staging,
                number_of_patients=args.patients,
                seed=args.seed,
                progress=show,
                executor=pool,
            )
        _replace_demo(folder, staging, earlier)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    report = os.path.join(folder, os.path.relpath(result.report, staging))
    emit(result.batch.table(), args)
    emit("", args)
    emit(result.model.variance_table(), args)
    emit("", args)
    emit(
        f"landmarks predicted on the held-out patient: mean error "
        f"{result.landmark_error_mean:.2f} mm",
        args,
    )
    # The pipeline's time (the report's "total time") and the run's, pictures and pages included.
    emit(
        f"report: {report}  (pipeline {result.seconds:.0f} s; "
        f"{time.perf_counter() - start:.0f} s with the report, pictures and explorer)",
        args,
    )
    if args.json:
        emit_json(
            {
                "output": folder,
                "report": report,
                "patients": [r.name for r in result.batch.records],
                "failed": [r.name for r in result.batch.failed],
                "flagged": {
                    r.name: {"verdict": r.verdict, "warnings": list(r.warnings)}
                    for r in result.batch.flagged
                },
                "explained_variance_ratio": result.model.explained_variance_ratio.tolist(),
                "landmark_error_mean_mm": result.landmark_error_mean,
                "seconds": result.seconds,
            }
        )
    sys.stdout.flush()
    if result.batch.flagged:
        print(
            "o3dreg demo: flagged and left out of the model: "
            + "; ".join(f"{r.name} ({r.verdict})" for r in result.batch.flagged),
            file=sys.stderr,
        )
    return 0 if not result.batch.failed and not result.batch.flagged else 1
