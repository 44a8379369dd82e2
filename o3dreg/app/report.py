"""The demo's report: Markdown with tables and pictures (rendered headless)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from ..io.mesh import atomic_write, atomic_write_text, to_open3d
from ..registration.distance import SurfaceDistanceQuery
from .explorer import write_model_explorer
from .render import render_mesh, render_shape_modes

logger = logging.getLogger("o3dreg")

__all__ = ["plot_convergence", "plot_variances", "write_report"]


def _pyplot():
    # Deferred: matplotlib.pyplot takes ~1 s to import, and `import o3dreg` needs no pictures.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    plt = _pyplot()
    atomic_write(
        path,
        lambda tmp: fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight"),
        overwrite=True,
    )
    plt.close(fig)
    return path


def plot_variances(model: Any, path: Path) -> Path:
    """Bar chart of the variance explained per mode with the cumulative curve (paper Table 4)."""
    plt = _pyplot()
    ratio = 100 * model.explained_variance_ratio
    modes = np.arange(1, ratio.size + 1)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar(modes, ratio, color="#4c72b0", label="per mode")
    ax.plot(modes, np.cumsum(ratio), "o-", color="#dd8452", label="cumulative")
    ax.axhline(95, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("mode")
    ax.set_ylabel("variance explained (%)")
    ax.set_xticks(modes)
    ax.set_ylim(0, 105)
    ax.legend(loc="center right")
    ax.set_title("Shape model: variance explained per mode")
    return _save(fig, path)


def plot_convergence(results: dict[str, Any], path: Path) -> Path:
    """Mean template->target distance after each level, for each registration given."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, result in results.items():
        cells = [h.resolution for h in result.history]
        ax.plot(range(len(cells)), [h.mean_distance for h in result.history], "o-", label=name)
        ax.set_xticks(range(len(cells)), [f"{c}^3" for c in cells])
    ax.set_yscale("log")
    ax.set_xlabel("level (cells per axis)")
    ax.set_ylabel("mean distance to target (mm)")
    ax.set_title("Convergence per level")
    ax.legend()
    return _save(fig, path)


#: Camera for the demo's CT head: its z axis runs towards the feet (VTK's headsq examples use
#: view-up (0, 0, -1)); a three-quarter view from the front.
_VIEW: dict[str, Any] = {"up": (0.0, 0.0, -1.0), "view": (60.0, 15.0)}


def _render(
    mesh: o3d.geometry.TriangleMesh, path: Path, scalars: np.ndarray | None = None, **kw: Any
) -> Path | None:
    # matplotlib: 0.4 s a picture, where Open3D's Filament on Mesa's software Vulkan took 3-30 s
    # (and minutes on a loaded 2-core machine); the report has nine.
    kw.setdefault("backend", "matplotlib")
    kw = {**_VIEW, **kw}
    try:
        render_mesh(mesh, path, scalars=scalars, **kw)
    except Exception as exc:  # a picture is not worth failing the report for
        logger.warning("could not render %s: %s", path.name, exc)
        return None
    return path


def write_report(
    out: Path,
    template: o3d.geometry.TriangleMesh,
    patients: list[Any],
    batch: Any,
    model: Any,
    figures: dict[str, Any],
) -> Path:
    """Write ``out/report.md`` and its pictures under ``out/images``."""
    images = out / "images"
    images.mkdir(exist_ok=True)
    first = patients[0]
    single = figures["comparison"]["single"][0]
    symmetric = figures["comparison"]["symmetric"][0]
    faces = np.asarray(template.triangles)

    # Pictures.
    plot_variances(model, images / "variances.png")
    plot_convergence({"single": single, "symmetric": symmetric}, images / "convergence.png")
    target_v = np.asarray(first.mesh.vertices)
    target_f = np.asarray(first.mesh.triangles)
    d_forward = SurfaceDistanceQuery(target_v, target_f).distance(symmetric.vertices)
    pictures = {}
    pictures["forward"] = _render(
        to_open3d(symmetric.vertices, faces),
        images / "registered_template_to_patient.png",
        d_forward,
        title="registered template: distance to the patient surface",
        label="mm",
        vmin=0.0,
        vmax=1.5,
    )
    for name, result in (("single", single), ("symmetric", symmetric)):
        back = SurfaceDistanceQuery(result.vertices, faces).distance(target_v)
        pictures[f"backward_{name}"] = _render(
            first.mesh,
            images / f"patient_to_template_{name}.png",
            back,
            title=f"patient: distance to the registered template ({name})",
            label="mm",
            vmin=0.0,
            vmax=3.0,
        )
    try:
        pictures["modes"] = Path(render_shape_modes(model, images / "modes.png", **_VIEW))
    except Exception as exc:  # a picture is not worth failing the report for
        logger.warning("could not render modes.png: %s", exc)

    try:
        explorer = write_model_explorer(
            out / "explorer.html",
            model,
            registrations=batch,
            targets={p.name: p.mesh for p in patients},
            up=_VIEW["up"],
            view=_VIEW["view"],
        )
    except Exception as exc:  # the page is not worth failing the report for
        logger.warning("could not write explorer.html: %s", exc)
        explorer = None

    def img(key: str, caption: str) -> str:
        path = pictures.get(key)
        return (
            f"![{caption}](images/{path.name})" if path else f"*({caption}: no renderer available)*"
        )

    initial = figures["initial"]
    lines = [
        "# o3dreg demo report",
        "",
        "The pipeline of Berar et al. (2005) on the bundled CT head: CT volume -> bone mesh -> "
        "template -> registration of a population -> Procrustes -> shape model -> landmarks.",
        "",
        *(
            [
                "**[Open the interactive explorer](explorer.html)** (one file, works offline): "
                "the mode sliders, the variance table, and every patient's registered template "
                "coloured by its distance to the patient.",
                "",
            ]
            if explorer
            else []
        ),
        "## Steps",
        "",
        *[f"{k + 1}. {text}" for k, text in enumerate(figures["steps"])],
        f"{len(figures['steps']) + 1}. total time {figures['seconds']:.1f} s",
        "",
        f"## Single vs symmetric distance ({first.name})",
        "",
        "Point-to-surface distances in mm; correspondence error against the known position of "
        "every template vertex.",
        "",
        "| method | template->patient mean | max | patient->template mean | max | correspondence error mean | levels time (s) |",
        "|---|---|---|---|---|---|---|",
        f"| initial | {initial.source_to_target_mean:.3f} | {initial.source_to_target_max:.2f} | "
        f"{initial.target_to_source_mean:.3f} | {initial.target_to_source_max:.2f} | | |",
    ]
    for name, (result, err) in figures["comparison"].items():
        d = result.distances
        lines.append(
            f"| {name} | {d.source_to_target_mean:.3f} | {d.source_to_target_max:.2f} | "
            f"{d.target_to_source_mean:.3f} | {d.target_to_source_max:.2f} | {err.mean():.3f} | "
            f"{sum(h.seconds for h in result.history):.2f} |"
        )
    lines += [
        "",
        img(
            "forward",
            "template registered onto the patient, coloured by distance to the patient surface",
        ),
        "",
        img(
            "backward_symmetric",
            "patient coloured by distance to the registered template (symmetric)",
        ),
        img("backward_single", "patient coloured by distance to the registered template (single)"),
        "",
        "![Mean distance to the patient after each level](images/convergence.png)",
        "",
        "## Batch registration",
        "",
        "```text",
        batch.table(),
        "```",
        "",
        "Each patient's verdict beside its correspondence error against the ground truth (mean "
        "distance of every registered template vertex from its known position, mm). Only "
        "patients with verdict `ok` are in the model.",
        "",
        "| patient | verdict | correspondence error (mm) | in the model | reasons |",
        "|---|---|---|---|---|",
        *[
            f"| {name} | {verdict} | "
            + (f"{figures['truth_error'][name]:.2f}" if name in figures["truth_error"] else "-")
            + f" | {'yes' if name in model.names else 'no'} | "
            + ("; ".join(warnings) if warnings else "")
            + " |"
            for name, (verdict, warnings) in figures["verdicts"].items()
        ],
        "",
        "## Shape model (paper Table 4)",
        "",
        "```text",
        model.variance_table(),
        "```",
        "",
        "Standard deviations in mm of the whole shape vector (the coordinates of all "
        f"{len(model.mean)} vertices); the last row is what one standard deviation moves each "
        "vertex, RMS.",
        "",
        "![Variance explained per mode](images/variances.png)",
        "",
        "Modes 1 and 2 at -3, 0 and +3 standard deviations (paper Figure 6), coloured by the "
        "displacement from the mean along the surface normal (red outwards, blue inwards):",
        "",
        img("modes", "modes 1 and 2 at -3, 0 and +3 SD"),
    ]
    quality = figures["quality"]
    lines += ["", "## Model quality", ""]
    for name, curve in quality.items():
        lines += [
            f"**{name}**",
            "",
            "```text",
            curve.table(),
            "```",
            "",
        ]
    prediction, truth, errors = figures["landmarks"]
    lines += [
        "## Landmark prediction on the held-out patient",
        "",
        "| landmark | predicted (mm) | truth (mm) | error (mm) |",
        "|---|---|---|---|",
    ]
    for label, p, t, e in zip(prediction.labels, prediction.positions, truth, errors):
        lines.append(
            f"| {label} | {p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f} | {t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f} | {e:.2f} |"
        )
    judged = "the model's fit" + (
        " and the registration of its instance onto the patient's surface"
        if prediction.registration is not None
        else ""
    )
    lines += [
        "",
        f"Mean error {errors.mean():.2f} mm; verdict {prediction.status} ({judged}).",
        *[f"- {w}" for w in prediction.warnings],
        "",
    ]
    text = "\n".join(lines)
    path = out / "report.md"
    atomic_write_text(path, text, overwrite=True)
    return path
