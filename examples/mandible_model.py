"""A statistical shape model of mandibles, from CT masks to modes (Berar et al. 2005, 3.3).

Pipeline: reconstruct each mask (marching cubes at 0.5, largest component, Taubin smoothing of
the 2.5-3 mm slice staircase); take the first mandible, decimated to ~2500 vertices, as the
template; register it elastically onto the others (parallel, resumable); align the
semilandmark meshes by generalised Procrustes; PCA; report the variance table (the paper's
Table 4), generalisation, specificity, the effect of sliding semilandmarks, leave-one-out
landmark prediction; draw the first two modes at +-3 standard deviations (Figure 6).

Usage::

    python examples/mandible_model.py [OUTPUT_DIR] [--data FOLDER] [--jobs N] [--docs]

Reads the PDDCA masks ``FOLDER/masks/<id>_Mandible.nrrd`` (default FOLDER:
$O3DREG_SHARED_DATA/mandibles, else ../shared/data/mandibles: the 8 development mandibles);
exits with a message when fewer than 3 masks give a mandible surface. A mask that is empty, in
pieces or far from the others' size is left out with a line saying why. ``--docs`` also writes
the pictures to docs/images/. The masks are research data: nothing derived from them but
figures and statistics is kept.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import hashlib
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

import o3dreg
from o3dreg import (
    TemplateLandmarks,
    build_shape_model,
    compactness,
    generalization,
    generalized_procrustes,
    landmark_errors,
    predict_landmarks,
    register_batch,
    slide_semilandmarks,
    specificity,
    write_statismo,
)
from o3dreg.io.mesh import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
MASK_SUFFIX = "_Mandible.nrrd"
#: The share of a mask's surface area its largest component must hold: with more elsewhere the
#: mandible is in pieces, and its largest piece alone is not the bone.
LARGEST_SHARE = 0.9
#: Taubin iterations that remove the staircase of 2.5-3 mm CT slices, keeping the volume.
SMOOTHING = 30
#: How far a mandible's size (bounding-box diagonal) may stray from the masks' median, as a factor.
SIZE_FACTOR = 1.5


class Unusable(ValueError):
    """Why a mask gives no mandible surface: what was expected and what was found."""


def data_dir() -> Path:
    """The default mandible folder: ``$O3DREG_SHARED_DATA/mandibles``, else
    ``../shared/data/mandibles`` beside the repository."""
    env = os.environ.get("O3DREG_SHARED_DATA")
    base = Path(env) if env else ROOT.parent / "shared" / "data"
    return base / "mandibles"


def patient_masks(folder: Path) -> tuple[list[tuple[str, Path]], list[str]]:
    """The masks of ``folder`` named ``<id>_Mandible.nrrd`` (PDDCA's naming), by id.

    Parameters
    ----------
    folder : Path

    Returns
    -------
    masks : list of (id, Path)
        Sorted by id; the id is everything before the suffix (matched in any case).
    lines : list of str
        One per file left aside: another name, or an id that is not a plain file name (the
        registrations are stored under it).
    """
    masks, lines = [], []
    for path in sorted(folder.iterdir()) if folder.is_dir() else []:
        name = path.name
        if name.startswith("."):  # system files (.DS_Store, ._ resource forks)
            continue
        if len(name) <= len(MASK_SUFFIX) or not name.lower().endswith(MASK_SUFFIX.lower()):
            lines.append(f"ignored {name}: not named <id>{MASK_SUFFIX}")
            continue
        pid = name[: -len(MASK_SUFFIX)]
        if re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9._-]*", pid) is None:
            lines.append(
                f"left out {pid!r}: its id is not a plain file name (letters, digits, . _ -)"
            )
            continue
        masks.append((pid, path))
    return masks, lines


def mask_isosurface(path: str | Path):
    """The marching-cubes surface of a mask at 0.5, every component, and the volume read.

    Raises
    ------
    Unusable
        The mask cannot be read, is empty, gives no surface at 0.5, or is in pieces (its largest
        component holds less than :data:`LARGEST_SHARE` of the surface area).
    """
    name = Path(path).name
    try:
        volume = o3dreg.read_volume(str(path))
    except Exception as exc:  # any reader's failure: the mask is left out, the run goes on
        raise Unusable(f"{name} cannot be read: {exc}") from None
    if not (np.asarray(volume.array) > 0.5).any():
        raise Unusable(f"{name} holds no voxel above 0.5 (an empty mask)")
    try:
        mesh = o3dreg.isosurface(volume, 0.5)
    except (RuntimeError, ValueError) as exc:
        raise Unusable(f"{name} gives no surface at 0.5: {exc}") from None
    areas = o3dreg.connected_components(mesh).areas
    share = float(areas[0] / areas.sum())
    if share < LARGEST_SHARE:
        raise Unusable(
            f"{name} is in pieces: its largest component holds {share:.0%} of the surface "
            f"area, the next {areas[1] / areas.sum():.0%} ({len(areas)} components; the "
            f"mandible's at least {LARGEST_SHARE:.0%} expected)"
        )
    return mesh, volume


def reconstruct(path: str | Path, number_of_vertices: int | None = None):
    """Mask -> smoothed surface (mm), with o3dreg's CT reconstruction functions: the largest
    component of :func:`mask_isosurface` (which raises :class:`Unusable`), smoothed, decimated
    to ``number_of_vertices`` when given."""
    mesh = o3dreg.keep_largest_components(mask_isosurface(path)[0], 1)
    # Thick slices (2.5-3 mm) leave a staircase: Taubin smoothing removes it, keeping volume.
    mesh = o3dreg.smooth_taubin(mesh, SMOOTHING)
    if number_of_vertices is not None and len(mesh.vertices) > number_of_vertices:
        mesh = o3dreg.decimate(mesh, number_of_vertices)
    return mesh


def cached_surface(path: Path, mask: str | Path, number_of_vertices: int | None) -> None:
    """Write :func:`reconstruct` of ``mask`` to ``path`` unless ``path`` already holds it.

    A key beside the mesh (``path`` with ``.json``: the mask's SHA-256 and the vertex count)
    says what it was made from; a mesh without it, or made from another mask or count (an
    output folder reused with other data or settings), is made again.
    """
    key = {
        "mask": hashlib.sha256(Path(mask).read_bytes()).hexdigest(),
        "vertices": number_of_vertices,
    }
    stamp = path.with_suffix(".json")
    if path.exists() and stamp.exists() and stamp.read_text() == json.dumps(key):
        return
    o3dreg.write_triangle_mesh(path, reconstruct(mask, number_of_vertices), overwrite=True)
    atomic_write_text(stamp, json.dumps(key), overwrite=True)


def size_outliers(diagonals: dict[str, float]) -> dict[str, str]:
    """The surfaces not mandible-sized: a bounding-box diagonal more than :data:`SIZE_FACTOR`
    from the median of all (a largest component that is another structure, or a fragment).

    Parameters
    ----------
    diagonals : dict
        ``{id: bounding-box diagonal (mm)}``.

    Returns
    -------
    dict
        ``{id: why}`` for each outlier.
    """
    median = float(np.median(list(diagonals.values()))) if diagonals else 0.0
    return {
        pid: (
            f"its surface is {d:.0f} mm across (bounding-box diagonal), the masks' median "
            f"{median:.0f} mm: not mandible-sized (within x{SIZE_FACTOR:g} of it expected)"
        )
        for pid, d in diagonals.items()
        if not median / SIZE_FACTOR <= d <= median * SIZE_FACTOR
    }


def draw_modes(model, path: Path, modes=(0, 1), sds=(-3.0, 0.0, 3.0)) -> None:
    """Figure 6: each row a mode, columns at -3, 0 and +3 standard deviations (mesh plots)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(3.2 * len(sds), 3.0 * len(modes)), dpi=110)
    mean = model.mean
    lo, hi = mean.min(axis=0), mean.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 * 1.1
    for r, m in enumerate(modes):
        for c, sd in enumerate(sds):
            ax = fig.add_subplot(len(modes), len(sds), r * len(sds) + c + 1, projection="3d")
            v = model.mode_shape(m, sd)
            shift = np.linalg.norm(v - mean, axis=1)
            tri = ax.plot_trisurf(
                v[:, 0], v[:, 1], v[:, 2], triangles=model.faces, cmap="viridis", linewidth=0
            )
            tri.set_array(shift[model.faces].mean(axis=1))
            tri.set_clim(
                0,
                max(
                    float(np.abs(model.standard_deviations[m]) * 3 * np.abs(model.modes[m]).max()),
                    1e-9,
                )
                * 1.0,
            )
            for setter, k in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
                setter(centre[k] - half, centre[k] + half)
            ax.view_init(elev=20, azim=-60)
            ax.set_axis_off()
            ax.set_title(f"mode {m + 1}, {sd:+g} sd", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output", nargs="?", default="/tmp/o3dreg-mandible-model")
    parser.add_argument(
        "--data",
        metavar="FOLDER",
        help="the mandible folder, masks in FOLDER/masks/<id>_Mandible.nrrd (default: "
        "$O3DREG_SHARED_DATA/mandibles, else ../shared/data/mandibles)",
    )
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--template-vertices", type=int, default=2500)
    parser.add_argument("--target-vertices", type=int, default=40000)
    parser.add_argument("--docs", action="store_true", help="write pictures to docs/images/")
    args = parser.parse_args(argv)

    folder = (Path(args.data) if args.data else data_dir()) / "masks"
    found, lines = patient_masks(folder)
    if len(found) < 3:
        print(
            f"{len(found)} mandible mask(s) <id>{MASK_SUFFIX} under {folder}, at least 3 needed "
            "(set O3DREG_SHARED_DATA or --data); nothing to do"
        )
        return 0
    for line in lines:
        print(line)
    out = Path(args.output)
    (out / "surfaces").mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    # 1. Surfaces (cached in OUTPUT/surfaces); a mask without a mandible surface is left out.
    surfaces: dict[str, Path] = {}
    diagonals: dict[str, float] = {}
    for name, mask in found:
        path = out / "surfaces" / f"{name}.ply"
        try:
            cached_surface(path, mask, args.target_vertices)
        except Unusable as exc:
            print(f"left out {name}: {exc}")
            continue
        surfaces[name] = path
        vertices = np.asarray(o3dreg.read_triangle_mesh(path).vertices)
        diagonals[name] = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    for name, why in size_outliers(diagonals).items():
        print(f"left out {name}: {why}")
        del surfaces[name]
    if len(surfaces) < 3:
        print(f"{len(surfaces)} of the {len(found)} masks give a mandible surface, 3 needed")
        return 0
    names = list(surfaces)
    paths = [str(surfaces[name]) for name in names]
    template_path = out / "template.ply"
    cached_surface(template_path, dict(found)[names[0]], args.template_vertices)
    template = o3dreg.read_triangle_mesh(template_path)
    print(
        f"template {names[0]}: {len(template.vertices)} vertices; {time.perf_counter() - start:.0f} s"
    )

    # 2. Batch registration onto the others (resumable: rerun skips finished patients).
    executor = cf.ProcessPoolExecutor(args.jobs) if args.jobs > 1 else None
    try:
        batch = register_batch(
            template,
            paths[1:],
            out / "registrations",
            names=names[1:],
            executor=executor,
            progress=True,
        )
    finally:
        if executor is not None:
            executor.shutdown()
    print(batch.table())
    regnames, shapes = batch.shapes()
    faces = np.asarray(template.triangles)

    # 3. Procrustes + PCA.
    gpa = generalized_procrustes(shapes)
    print(gpa, "RMS to mean (mm):", np.round(gpa.residuals, 2).tolist())
    model = build_shape_model(shapes, faces, names=regnames)
    model.save(out / "model.npz", overwrite=True)
    write_statismo(out / "model.h5", model, overwrite=True)
    print(model)
    print(model.variance_table())

    # 4. Quality.
    comp = compactness(model)
    gen = generalization(shapes, faces)
    spec = specificity(model, shapes, number_of_samples=200, seed=0)
    for curve in (comp, gen, spec):
        print(curve.table())

    # 5. Sliding semilandmarks (least bending energy from the mean), and the model it gives.
    targets = [o3dreg.read_triangle_mesh(p) for p in paths[1:] if Path(p).stem in regnames]
    slid = slide_semilandmarks(shapes, targets, faces=faces)
    slid_model = build_shape_model(slid.shapes, faces, names=regnames)
    slid_gen = generalization(slid.shapes, faces)
    print(slid)
    print(slid_model.variance_table())

    # 6. Landmarks on the template (extreme points: chin, both condyles, both gonial angles,
    # coronoid tips), carried to each patient, predicted leave-one-out by fitting the model.
    v = np.asarray(template.vertices)
    c = v.mean(axis=0)
    axes = np.linalg.svd(v - c, full_matrices=False)[2]
    u = (v - c) @ axes.T
    idx = [
        int(u[:, 0].argmin()),
        int(u[:, 0].argmax()),
        int(u[:, 1].argmin()),
        int(u[:, 1].argmax()),
        int(u[:, 2].argmin()),
        int(u[:, 2].argmax()),
    ]
    landmarks = TemplateLandmarks.from_vertices(
        template, np.array(idx), ["A-", "A+", "B-", "B+", "C-", "C+"]
    )
    truth = landmarks.carry(shapes)
    errors = []
    for i in range(len(regnames)):
        rest = np.delete(shapes, i, axis=0)
        loo = build_shape_model(rest, faces)
        pred = predict_landmarks(loo, landmarks, targets[i])
        errors.append(landmark_errors(pred.positions, truth[i]))
    errors_arr = np.array(errors)
    print(
        "leave-one-out landmark prediction error (mm), mean per landmark:",
        np.round(errors_arr.mean(axis=0), 2).tolist(),
    )

    report = {
        "template": names[0],
        "template_vertices": len(template.vertices),
        "registration": batch.as_dicts(),
        "procrustes_rms_to_mean": gpa.residuals.tolist(),
        "variances": model.variance_records(),
        "compactness": comp.as_dict(),
        "generalization": gen.as_dict(),
        "specificity": spec.as_dict(),
        "sliding": {
            "criterion": slid.criterion,
            "iterations": slid.iterations,
            "procrustes_distances": slid.procrustes_distances.tolist(),
            "total_variance_before": model.total_variance,
            "total_variance_after": slid_model.total_variance,
            "generalization_after": slid_gen.as_dict(),
            "variances_after": slid_model.variance_records(),
        },
        "landmark_loo_errors_mm": errors_arr.tolist(),
        "seconds": time.perf_counter() - start,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))

    pictures = [out]
    if args.docs:
        (ROOT / "docs" / "images").mkdir(parents=True, exist_ok=True)
        pictures.append(ROOT / "docs" / "images")
    for folder in pictures:
        draw_modes(model, folder / "mandible_modes.png")
        gen.plot(
            folder / "mandible_generalization.png", overwrite=True, title="generalisation (LOO)"
        )
        spec.plot(folder / "mandible_specificity.png", overwrite=True)
        comp.plot(folder / "mandible_compactness.png", overwrite=True)
    print(f"done in {time.perf_counter() - start:.0f} s; outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
