"""The whole pipeline of the paper on bundled data: CT volume to shape model, with a report.

Steps (each logged, the report says what each produced):

1. read the bundled CT head (VTK "headsq", 93 slices of 64x64, 3.2 x 3.2 x 1.5 mm);
2. bone isosurface at 1150 (raw units, HU 126), largest component, Taubin smoothing: the
   high-density patient mesh (~38k vertices);
3. the low-density template: that mesh decimated to 2500 vertices;
4. a population: the patient mesh under smooth deformations drawn from a known 3-mode linear
   model (3% of the diagonal per mode) plus a small individual part, and rigid motions, each
   independently remeshed (decimated to its own vertex count), with a seed: a known ground truth
   for every template vertex;
5. batch registration of the template onto every patient (single and symmetric distances
   measured on the first);
6. generalised Procrustes analysis and PCA: the paper's Table 4 (variance per mode) and
   Figure 6 (modes 1 and 2 at -3, 0, +3 standard deviations);
7. five landmarks on the template, predicted on a held-out patient by fitting the model, with
   the error against their known positions;
8. ``report.md`` with the tables and the pictures.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from ..io.mesh import write_triangle_mesh
from ..mesh.cleaning import decimate, keep_largest_components, smooth_taubin
from ..registration.elastic import evaluate_elastic, registration_elastic
from ..registration.options import DistanceEstimation
from ..shape.build import build_shape_model
from ..shape.landmark_transfer import TemplateLandmarks, landmark_errors, predict_landmarks
from ..shape.model import ShapeModel
from ..shape.quality import compactness, generalization, specificity
from ..volume.isosurface import isosurface
from ..volume.readers import read_volume
from ..volume.volume import Volume
from .batch import BatchResult, register_batch, resume_key, save_registered
from .datasets import headsq_path
from .population import check_population
from .progress import announce
from .report import write_report
from .synthetic import SmoothWarp

__all__ = ["DemoResult", "make_population", "run_demo"]

logger = logging.getLogger("o3dreg")

#: Bone level of the bundled CT in its raw units (HU = raw - 1024).
BONE_LEVEL = 1150.0


@dataclass(frozen=True, eq=False)
class DemoResult:
    """What :func:`run_demo` produced.

    Attributes
    ----------
    output : pathlib.Path
        The output folder.
    report : pathlib.Path
        ``report.md`` in it.
    model : ShapeModel
    batch : BatchResult
    landmark_error_mean : float
        Mean landmark prediction error on the held-out patient (mm).
    seconds : float
    """

    output: Path
    report: Path
    model: ShapeModel = field(repr=False)
    batch: BatchResult = field(repr=False)
    landmark_error_mean: float
    seconds: float


@dataclass(frozen=True, eq=False)
class Patient:
    """A synthetic patient: its mesh and the map that made it from the reference bone."""

    name: str
    mesh: o3d.geometry.TriangleMesh
    warp: SmoothWarp
    motion: np.ndarray

    def truth(self, points: np.ndarray) -> np.ndarray:
        """Where reference-bone points are on this patient."""
        return self.warp(points) @ self.motion[:3, :3].T + self.motion[:3, 3]


def bone_mesh(volume: Volume, level: float = BONE_LEVEL) -> o3d.geometry.TriangleMesh:
    """Isosurface, largest component and Taubin smoothing: a registration-ready bone surface."""
    mesh = isosurface(volume, level)
    return smooth_taubin(keep_largest_components(mesh, 1), 10)


def make_population(
    reference: o3d.geometry.TriangleMesh,
    number_of_patients: int,
    *,
    number_of_modes: int = 3,
    magnitude: float = 0.03,
    individual: float = 0.005,
    seed: int = 0,
) -> list[Patient]:
    """Patients made from ``reference`` by a smooth warp, a rigid motion and a remeshing each.

    The warps follow a known linear model, as anatomy does: ``number_of_modes`` fixed smooth
    displacement fields (``SmoothWarp.random`` with ``magnitude`` of the diagonal each) combined
    with standard-normal coefficients per patient, plus a small individual warp (``individual``
    of the diagonal). Each patient also gets a rotation of up to 10 degrees and a shift of up to
    10 mm, and is decimated to its own vertex count (80-95% of the reference's), so no two
    patients share a triangulation.
    """
    rng = np.random.default_rng(seed)
    vertices = np.asarray(reference.vertices)
    centre = vertices.mean(axis=0)
    modes = [
        SmoothWarp.random(vertices, magnitude=magnitude, seed=int(rng.integers(2**31)))
        for _ in range(number_of_modes)
    ]
    patients = []
    for k in range(number_of_patients):
        alpha = rng.standard_normal(number_of_modes)
        own = SmoothWarp.random(vertices, magnitude=individual, seed=int(rng.integers(2**31)))
        # A sum of Gaussian bumps is itself a SmoothWarp: the modes' bumps scaled by alpha.
        warp = SmoothWarp(
            np.concatenate([m.centres for m in modes] + [own.centres]),
            np.concatenate([a * m.amplitudes for a, m in zip(alpha, modes)] + [own.amplitudes]),
            own.width,
        )
        rot = Rotation.from_rotvec(
            np.radians(10.0) * rng.uniform(-1, 1, 3) / np.sqrt(3)
        ).as_matrix()
        motion = np.eye(4)
        motion[:3, :3] = rot
        motion[:3, 3] = centre - rot @ centre + rng.uniform(-10.0, 10.0, 3)
        moved = o3d.geometry.TriangleMesh(reference)
        moved.vertices = o3d.utility.Vector3dVector(warp(vertices) @ rot.T + motion[:3, 3])
        count = int(len(vertices) * rng.uniform(0.80, 0.95))
        patients.append(Patient(f"patient{k + 1:02d}", decimate(moved, count), warp, motion))
    return patients


def run_demo(
    output: str | os.PathLike[str],
    *,
    number_of_patients: int = 8,
    seed: int = 0,
    progress: bool = False,
    executor: Any = None,
) -> DemoResult:
    """Run the whole pipeline on the bundled CT and write a report.

    Parameters
    ----------
    output : str or path-like
        An empty or missing folder; it is created.
    number_of_patients : int
        Patients in the model (one more is held out for landmark prediction). Default 8.
    seed : int
        Seed of the synthetic population.
    progress : bool
        Report progress on stderr: each step of the pipeline as it ends, and the batch's
        patients (a bar on a terminal, a line per patient elsewhere).
    executor : concurrent.futures.Executor, optional
        Runs the batch's registrations in parallel.

    Returns
    -------
    DemoResult
    """
    start = time.perf_counter()
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    if any(p for p in out.iterdir() if not p.name.startswith(".")):
        raise OSError(f"`output`: {str(out)!r} is not empty")
    if number_of_patients < 3:
        raise ValueError(f"`number_of_patients` must be >= 3, got {number_of_patients}")
    figures: dict[str, Any] = {"steps": []}

    def step(text: str) -> None:
        logger.info(text)
        figures["steps"].append(text)
        if progress:
            announce(text)

    volume = read_volume(headsq_path())
    reference = bone_mesh(volume)
    ref_vertices = np.asarray(reference.vertices)
    extent = np.ptp(ref_vertices, axis=0)
    step(
        f"CT {volume.shape} voxels, spacing {tuple(float(s) for s in volume.spacing)} mm -> bone "
        f"surface at {BONE_LEVEL:g} ({BONE_LEVEL - 1024:g} HU): {len(ref_vertices)} vertices, "
        f"{extent[0]:.0f} x {extent[1]:.0f} x {extent[2]:.0f} mm"
    )
    write_triangle_mesh(out / "bone.ply", reference)
    template = decimate(reference, 2500)
    template_vertices = np.asarray(template.vertices)
    write_triangle_mesh(out / "template.ply", template)
    # The template's own fit to the bone it was decimated from: detail it cannot follow puts a
    # floor under every patient -> template distance of the registrations below.
    own = evaluate_elastic(template, reference)
    step(
        f"template: {len(template_vertices)} vertices (decimated bone); bone -> template "
        f"mean {own.target_to_source_mean:.2f} mm, max {own.target_to_source_max:.2f} mm: the "
        "detail the template cannot follow, a floor under the patient -> template distances below"
    )

    patients = make_population(reference, number_of_patients + 1, seed=seed)
    held_out = patients[-1]
    patients = patients[:-1]
    (out / "patients").mkdir()
    for p in patients + [held_out]:
        write_triangle_mesh(out / "patients" / f"{p.name}.ply", p.mesh)
    counts = [len(p.mesh.vertices) for p in patients]
    step(
        f"population: {len(patients)} patients ({min(counts)}-{max(counts)} vertices each) + "
        f"{held_out.name} held out, seed {seed}"
    )

    # Single vs symmetric distance on the first patient (the paper's Table 1 comparison). The
    # symmetric one is the batch's own registration of that patient (default options): saved
    # into the batch folder, the batch skips it rather than registering it again.
    first = patients[0]
    comparison = {}
    if progress:
        announce(f"single and symmetric distance on {first.name} (the paper's Table 1)")
    (out / "registered").mkdir()
    for name, method in (("single", DistanceEstimation(symmetric=False)), ("symmetric", None)):
        began = time.perf_counter()
        result = registration_elastic(template, first.mesh, estimation_method=method)
        if method is None:
            save_registered(
                out / "registered",
                first.name,
                result,
                time.perf_counter() - began,
                "<array>",
                key=resume_key(template, first.mesh),
            )
        err = np.linalg.norm(result.vertices - first.truth(template_vertices), axis=1)
        comparison[name] = (result, err)
    figures["comparison"] = comparison
    figures["initial"] = evaluate_elastic(template, first.mesh)

    batch = register_batch(
        template,
        [p.mesh for p in patients],
        out / "registered",
        names=[p.name for p in patients],
        executor=executor,
        progress=progress,
    )
    batch = check_population(batch)
    names, shapes = batch.shapes()
    index = {name: k for k, name in enumerate(names)}
    truth_error = {
        p.name: float(
            np.linalg.norm(shapes[index[p.name]] - p.truth(template_vertices), axis=1).mean()
        )
        for p in patients
        if p.name in index
    }
    figures["truth_error"] = truth_error
    figures["verdicts"] = {r.name: (r.verdict, r.warnings) for r in batch.records}
    flagged = [r.name for r in batch.flagged]
    step(
        f"batch: {len(batch.registered)} registered ({len(batch.accepted)} with verdict ok"
        + (f"; flagged and left out of the model: {', '.join(flagged)}" if flagged else "")
        + f"), {len(batch.failed)} failed"
    )
    # The model is built from the patients whose verdict is 'ok' only.
    kept = [index[r.name] for r in batch.accepted]
    names, shapes = tuple(names[k] for k in kept), shapes[kept]
    if len(names) < 2:
        raise RuntimeError(
            f"only {len(names)} patient(s) registered with verdict 'ok': no model "
            f"({figures['verdicts']})"
        )

    model = build_shape_model(shapes, np.asarray(template.triangles), names=names)
    model.save(out / "model.npz")
    (out / "modes").mkdir()
    model.write_meshes(out / "modes", modes=[0, 1], standard_deviations=(-3.0, 3.0))
    figures["quality"] = {
        "compactness": compactness(model),
        "generalization": generalization(shapes, np.asarray(template.triangles)),
        "specificity": specificity(model, shapes, number_of_samples=50, seed=seed),
    }
    step(f"shape model: {model.number_of_modes} modes from {model.number_of_shapes} patients")

    # Landmarks: extreme template vertices along the axes, known on the held-out patient.
    axes = {
        "right (-x)": np.argmin(template_vertices[:, 0]),
        "left (+x)": np.argmax(template_vertices[:, 0]),
        "anterior (-y)": np.argmin(template_vertices[:, 1]),
        "posterior (+y)": np.argmax(template_vertices[:, 1]),
        "superior (+z)": np.argmax(template_vertices[:, 2]),
    }
    landmarks = TemplateLandmarks.from_vertices(
        template, np.array(list(axes.values())), labels=list(axes)
    )
    prediction = predict_landmarks(model, landmarks, held_out.mesh)
    truth = held_out.truth(landmarks.positions(template_vertices))
    errors = landmark_errors(prediction.positions, truth)
    figures["landmarks"] = (prediction, truth, errors)
    step(f"landmarks on {held_out.name}: mean prediction error {errors.mean():.2f} mm")

    seconds = time.perf_counter() - start
    figures["seconds"] = seconds
    if progress:
        announce("report: pictures, pages and the explorer")
    report = write_report(out, template, patients, batch, model, figures)
    return DemoResult(out, report, model, batch, float(errors.mean()), seconds)
