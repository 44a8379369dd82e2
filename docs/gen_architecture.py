"""Draw docs/images/architecture.svg: how data flows from a CT volume to a shape model.

Run after moving a module or renaming what one stage hands the next:
``python docs/gen_architecture.py``. ``tests/test_docs.py`` fails when the picture is stale or
names a module that does not exist. Plain SVG text, no dependency.
"""

from __future__ import annotations

from html import escape
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: The main chain, top to bottom: (stage, module, what it does, what it hands the next box).
CHAIN = [
    ("data", "", "CT scan or mask: DICOM series, NIfTI, NRRD, MetaImage, raw slices", "a path"),
    (
        "volume",
        "o3dreg.volume.readers",
        "read_volume: one reader module per format",
        "Volume (voxels, spacing, origin, direction; LPS mm)",
    ),
    (
        "volume",
        "o3dreg.volume.isosurface",
        "isosurface: marching cubes placed in world mm",
        "open3d TriangleMesh (the bone surface)",
    ),
    (
        "volume",
        "o3dreg.mesh.cleaning",
        "keep_largest_components, smooth_taubin, decimate, crop_mesh",
        "bone meshes: a decimated template and the patients",
    ),
    (
        "registration",
        "o3dreg.registration.rigid",
        "registration_rigid: surface moments, then ICP",
        "4x4 pose (init)",
    ),
    (
        "registration",
        "o3dreg.registration.elastic",
        "registration_elastic: a coarse-to-fine driver over the levels",
        "ElasticRegistrationResult: the template's vertices on the patient",
    ),
    (
        "registration",
        "o3dreg.app.batch",
        "register_batch: every patient, resumable, in parallel",
        "(s, n, 3) corresponding shapes + the template's triangles",
    ),
    (
        "shape",
        "o3dreg.shape.build",
        "build_shape_model: generalised Procrustes, then PCA",
        "ShapeModel (mean, modes, variances)",
    ),
    (
        "shape",
        "o3dreg.shape.fit",
        "fit_shape_model: pose and coefficients on a new patient",
        "ModelFit (the fitted instance)",
    ),
    (
        "shape",
        "o3dreg.shape.landmark_transfer",
        "predict_landmarks: template landmarks carried by the fit",
        "LandmarkPrediction (landmarks on the patient)",
    ),
]

#: Modules beside a box of the chain: (module of that box, module beside it, what it holds).
BESIDE = [
    ("o3dreg.volume.readers", "o3dreg.volume.volume", "the Volume type"),
    ("o3dreg.registration.rigid", "o3dreg.registration.landmark_start", "a start from landmarks"),
    (
        "o3dreg.registration.elastic",
        "o3dreg.registration.options",
        "ElasticLevel, DistanceEstimation",
    ),
    ("o3dreg.registration.elastic", "o3dreg.registration.terms", "DistanceTerm: bind per level"),
    ("o3dreg.registration.elastic", "o3dreg.registration.losses", "L2Loss, CauchyLoss, ..."),
    ("o3dreg.registration.elastic", "o3dreg.registration.checkers", "Boundary-, NormalAngle-, ..."),
    ("o3dreg.registration.elastic", "o3dreg.registration._target", "TargetSurface, prepared once"),
    ("o3dreg.registration.elastic", "o3dreg.registration._cost", "LevelProblem: one level's cost"),
    ("o3dreg.registration.elastic", "o3dreg.registration._terms", "terms at a level: r, J"),
    ("o3dreg.registration.elastic", "o3dreg.registration._solvers", "LevenbergMarquardt, SciPy"),
    ("o3dreg.registration.elastic", "o3dreg.registration.deformation", "LatticeDeformation"),
    ("o3dreg.registration.elastic", "o3dreg.registration.distance", "SurfaceDistanceQuery"),
    ("o3dreg.registration.elastic", "o3dreg.registration.result", "the result, LevelReport"),
    ("o3dreg.registration.elastic", "o3dreg.registration.verdict", "assess_registration"),
    ("o3dreg.app.batch", "o3dreg.app.settings", "RegistrationSettings"),
    ("o3dreg.shape.build", "o3dreg.shape.procrustes", "generalized_procrustes"),
    ("o3dreg.shape.build", "o3dreg.shape.sliding", "slide_semilandmarks (optional)"),
    ("o3dreg.shape.build", "o3dreg.shape.quality", "compactness, generalization, ..."),
    ("o3dreg.shape.fit", "o3dreg.shape.model", "ShapeModel: synthesis, projection"),
    ("o3dreg.shape.fit", "o3dreg.shape.model_io", ".npz and PLY files (statismo: .h5)"),
]

#: Stages: (key, title, fill colour of the band).
STAGES = [
    ("volume", "stage 1, CT -> bone mesh: o3dreg/volume/, o3dreg/mesh/", "#eef5fb"),
    ("registration", "stage 2, registration: o3dreg/registration/ (batches: app/)", "#fdf3e7"),
    ("shape", "stage 3, shape model: o3dreg/shape/", "#eef8ee"),
]

FOOTER = [
    "o3dreg/mesh/: generic mesh code every stage uses (edges, distinct values, canonical order,"
    " components, cleaning, subsampling).",
    "o3dreg/io/: mesh files (read_triangle_mesh, write_triangle_mesh), landmark files, .npz"
    " archives; used by every stage.",
    "o3dreg/app/: batches (settings, resume, Dask), the pipelines that chain the stages (demo,"
    " model_folder), reports, pictures.",
    "o3dreg/cli/: argparse adapters over app/ and the library (o3dreg register, reconstruct,"
    " build-model, model, demo, view).",
]

WIDTH = 1060
BOX_X, BOX_W, BOX_H = 40, 430, 50
STEP = 98  # box top to next box top: the arrow and its label sit in the gap
SIDE_X, SIDE_H = 680, 22
TOP = 20


def modules() -> list[str]:
    """Every module the picture names."""
    return sorted({m for _, m, _, _ in CHAIN if m} | {m for _, m, _ in BESIDE})


def _text(x: float, y: float, text: str, size: int = 13, **attrs: str) -> str:
    extra = "".join(f' {k.replace("_", "-")}="{v}"' for k, v in attrs.items())
    return f'<text x="{x:g}" y="{y:g}" font-size="{size}"{extra}>{escape(text)}</text>'


def render() -> str:
    """The SVG text."""
    out: list[str] = []
    # A box with many modules beside it takes more height, so its list stays clear of the arrows.
    tops, y = {}, TOP + 10
    for _, module, _, _ in CHAIN:
        tops[module or "data"] = y
        count = sum(owner == module for owner, _, _ in BESIDE)
        y += max(STEP, count * SIDE_H + 40)
    bottom = y
    bottom += 8
    height = bottom + 20 * len(FOOTER) + 10
    # Stage bands behind the boxes.
    for key, title, fill in STAGES:
        rows = [tops[m] for stage, m, _, _ in CHAIN if stage == key]
        # The last stage also holds the final result's line under its last box.
        y0, y1 = min(rows) - 30, max(rows) + BOX_H + (30 if key == STAGES[-1][0] else 10)
        out.append(
            f'<rect x="10" y="{y0}" width="{WIDTH - 20}" height="{y1 - y0}" rx="8" '
            f'fill="{fill}" stroke="#c8c8c8"/>'
        )
        out.append(
            _text(
                WIDTH - 20, y0 + 17, title, 13, font_weight="bold", fill="#555", text_anchor="end"
            )
        )
    for i, (_, module, does, hands) in enumerate(CHAIN):
        y = tops[module or "data"]
        fill = "#ffffff" if module else "#f4f4f4"
        out.append(
            f'<rect x="{BOX_X}" y="{y}" width="{BOX_W}" height="{BOX_H}" rx="6" '
            f'fill="{fill}" stroke="#333"/>'
        )
        if module:
            out.append(_text(BOX_X + 10, y + 20, module, 14, font_weight="bold"))
            out.append(_text(BOX_X + 10, y + 39, does, 12))
        else:
            out.append(_text(BOX_X + 10, y + 30, does, 13, font_style="italic"))
        # The arrow to the next box, labelled with what it carries.
        x = BOX_X + BOX_W / 2
        y0 = y + BOX_H
        if i + 1 < len(CHAIN):
            y1 = tops[CHAIN[i + 1][1]]
            out.append(
                f'<line x1="{x:g}" y1="{y0}" x2="{x:g}" y2="{y1 - 2}" stroke="#333" '
                f'stroke-width="1.6" marker-end="url(#arrow)"/>'
            )
            out.append(_text(x + 12, y0 + 28, hands, 12, fill="#1f4e8c"))
        else:
            out.append(_text(BOX_X + 10, y0 + 19, "-> " + hands, 12, fill="#1f4e8c"))
        # Modules beside this box, listed down from its top.
        beside = [(m, what) for owner, m, what in BESIDE if owner == module]
        for k, (m, what) in enumerate(beside):
            by = y + k * SIDE_H
            out.append(
                f'<line x1="{BOX_X + BOX_W}" y1="{y + BOX_H / 2:g}" x2="{SIDE_X}" '
                f'y2="{by + SIDE_H / 2 + 4:g}" stroke="#999" stroke-dasharray="3,3"/>'
            )
            out.append(_text(SIDE_X + 4, by + 15, f"{m.removeprefix('o3dreg.')}: {what}", 12))
    for k, line in enumerate(FOOTER):
        out.append(_text(20, bottom + k * 20, line, 12, fill="#333"))
    head = (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" '
        f'viewBox="0 0 {WIDTH} {height}" font-family="DejaVu Sans, Arial, sans-serif">\n'
        "<title>o3dreg: how data flows from a CT volume to a shape model</title>\n"
        '<defs><marker id="arrow" viewBox="0 0 10 10" refX="9" refY="5" markerWidth="7" '
        'markerHeight="7" orient="auto"><path d="M0,0 L10,5 L0,10 z" fill="#333"/></marker>'
        "</defs>\n"
        f'<rect width="{WIDTH}" height="{height}" fill="#ffffff"/>\n'
    )
    return head + "\n".join(out) + "\n</svg>\n"


def main() -> None:
    path = HERE / "images" / "architecture.svg"
    path.write_text(render(), encoding="utf-8")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
