"""Figures for docs/benchmarks.md: error vs time of every method (from bench_peers.py's JSON)
and registrations of the bunny-medium case coloured by correspondence error.

    python benchmarks/bench_peers.py --json peers.json
    python benchmarks/plot_peers.py peers.json docs/images
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

MARKERS = {
    "o3dreg": "o",
    "o3dreg-single": "s",
    "nricp_amberg": "^",
    "nricp_sumner": "v",
    "cpd": "D",
    "icp": "x",
}


def plot_error_vs_time(rows: list[dict], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from o3dreg.io.mesh import atomic_write

    fig = Figure(figsize=(8, 5.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    cases = list(dict.fromkeys(r["case"] for r in rows))
    colours = {c: f"C{k}" for k, c in enumerate(cases)}
    for r in rows:
        ax.scatter(
            r["seconds"],
            r["error_mean_pct_diag"],
            marker=MARKERS.get(r["method"], "o"),
            color=colours[r["case"]],
            s=45,
        )
    for method, marker in MARKERS.items():
        ax.scatter([], [], marker=marker, color="k", label=method)
    for case, colour in colours.items():
        ax.scatter([], [], marker="o", color=colour, label=case)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time (s, 2 cores, log)")
    ax.set_ylabel("mean correspondence error (% of bbox diagonal, log)")
    ax.set_title("Template 3k -> target 30k vertices: error vs time, every method and case")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.subplots_adjust(right=0.72)
    # A tight box keeps the legend beside the axes whole, whatever its labels' lengths.
    atomic_write(
        path, lambda tmp: fig.savefig(tmp, format="png", bbox_inches="tight"), overwrite=True
    )


def render_registrations(folder: Path) -> None:
    import time

    from bench_peers import build_case, register

    from o3dreg.app.render import render_mesh

    case = build_case("bunny-medium")
    assert case is not None
    case["name"] = "bunny-medium"
    for method in ("o3dreg", "nricp_amberg", "icp"):
        start = time.perf_counter()
        moved = register(method, case)
        seconds = time.perf_counter() - start
        err = np.linalg.norm(moved - case["truth"], axis=1)
        render_mesh(
            (moved, case["template_faces"]),
            folder / f"bench-bunny-medium-{method}.png",
            scalars=err,
            vmin=0.0,
            vmax=5.0,
            cmap="magma",
            view=(-20, 15),
            up=(0, 1, 0),
            size=(560, 420),
            title=f"{method}: bunny-medium, error mean {err.mean():.2f} mm ({seconds:.1f} s)",
            label="correspondence error (mm)",
        )
        print(f"wrote {folder}/bench-bunny-medium-{method}.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("json", help="output of bench_peers.py --json")
    parser.add_argument("folder", help="where the PNGs go")
    parser.add_argument("--no-renders", action="store_true")
    args = parser.parse_args()
    folder = Path(args.folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = json.loads(Path(args.json).read_text())["rows"]
    plot_error_vs_time(rows, folder / "bench-error-vs-time.png")
    print(f"wrote {folder}/bench-error-vs-time.png")
    if not args.no_renders:
        render_registrations(folder)


if __name__ == "__main__":
    main()
