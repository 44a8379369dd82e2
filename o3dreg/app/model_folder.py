"""Build a model folder: batch registration, Procrustes, PCA, quality curves and the files.

A model folder holds ``template.ply`` (the template the model is defined on), ``model.npz``
(:meth:`~o3dreg.ShapeModel.save`), ``model.h5`` (statismo layout), ``mean.ply`` and ``modes/``,
``variance.txt`` (the paper's Table 4), ``quality/`` (tables and PNG plots), ``registrations/``
(one semilandmark mesh, deformation and record per patient), ``report.json`` and
``explorer.html`` (:func:`~o3dreg.app.explorer.write_model_explorer`).
``o3dreg build-model`` is a thin adapter over :func:`build_model_folder`.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d

from ..io.mesh import atomic_write_text, read_triangle_mesh, write_triangle_mesh
from ..registration.batch import BatchResult, register_batch
from ..registration.options import ElasticLevel
from ..shape.build import build_shape_model
from ..shape.model import ShapeModel
from ..shape.quality import QualityCurve, compactness, generalization, specificity
from ..shape.sliding import SlidingResult, slide_semilandmarks
from ..shape.statismo import write_statismo
from .explorer import write_model_explorer

logger = logging.getLogger("o3dreg")


@dataclass(frozen=True, repr=False)
class ModelFolder:
    """What :func:`build_model_folder` wrote.

    Attributes
    ----------
    path : str
        The model folder.
    batch : BatchResult
        One record per patient (registered, skipped as finished, or failed).
    model : ShapeModel or None
        The shape model; ``None`` when fewer than two patients were registered.
    curves : list of QualityCurve
        Compactness, specificity and (three patients or more) generalisation.
    sliding : SlidingResult or None
        The semilandmark sliding, when asked for.
    report : dict
        The content of ``report.json`` (empty when no model was built).
    """

    path: str
    batch: BatchResult
    model: ShapeModel | None
    curves: list[QualityCurve]
    sliding: SlidingResult | None
    report: dict[str, Any]

    def __repr__(self) -> str:
        shapes = 0 if self.model is None else len(self.model.names)
        return (
            f"ModelFolder(path={self.path!r}, patients={len(self.batch.records)}, "
            f"shapes={shapes}, failed={len(self.batch.failed)})"
        )


def build_model_folder(
    template: o3d.geometry.TriangleMesh,
    targets: Sequence[str],
    output: str,
    *,
    executor: Executor | None = None,
    force: bool = False,
    progress: bool = False,
    levels: Sequence[ElasticLevel] | None = None,
    scaling: bool = False,
    slide: bool = False,
) -> ModelFolder:
    """Register ``template`` onto every patient file and write a model folder (resumable).

    Parameters
    ----------
    template : open3d.geometry.TriangleMesh
        The template (moves; ~1k-4k vertices).
    targets : sequence of str
        Patient mesh files.
    output : str
        The model folder (created). A folder holding a model of another template (other
        triangles) is refused unless ``force``.
    executor : concurrent.futures.Executor, optional
        Runs the registrations (a process pool, a Dask client's executor); serial by default.
    force : bool, optional
        Register finished patients again.
    progress : bool, optional
        Show a progress bar.
    levels : sequence of ElasticLevel, optional
        The lattice hierarchy (default :func:`~o3dreg.default_levels`).
    scaling : bool, optional
        Similarity Procrustes (size removed).
    slide : bool, optional
        Slide the semilandmarks before the PCA.

    Returns
    -------
    ModelFolder
        What was written; ``model`` is ``None`` when fewer than two patients were registered.
    """
    out = output
    os.makedirs(out, exist_ok=True)
    template_path = os.path.join(out, "template.ply")
    if os.path.exists(template_path):
        previous = read_triangle_mesh(template_path)
        same = np.array_equal(np.asarray(previous.triangles), np.asarray(template.triangles))
        if not same and not force:
            raise ValueError(
                f"{out!r} holds a model of another template; use another folder or --force"
            )
    write_triangle_mesh(template_path, template, overwrite=True)
    batch = register_batch(
        template,
        list(targets),
        os.path.join(out, "registrations"),
        executor=executor,
        force=force,
        progress=progress,
        levels=None if levels is None else list(levels),
    )
    names, shapes = batch.shapes()
    if len(names) < 2:
        return ModelFolder(out, batch, None, [], None, {})
    faces = np.asarray(template.triangles)
    slid = None
    if slide:
        surfaces = [read_triangle_mesh(r.source) for r in batch.registered]
        slid = slide_semilandmarks(shapes, surfaces, scaling=scaling)
        shapes = slid.shapes
    model = build_shape_model(shapes, faces, names=names, scaling=scaling)
    model.save(os.path.join(out, "model.npz"), overwrite=True)
    write_statismo(os.path.join(out, "model.h5"), model, overwrite=True)
    os.makedirs(os.path.join(out, "modes"), exist_ok=True)
    model.write_meshes(os.path.join(out, "modes"), overwrite=True)
    write_triangle_mesh(os.path.join(out, "mean.ply"), model.mesh(), overwrite=True)
    atomic_write_text(
        os.path.join(out, "variance.txt"), model.variance_table() + "\n", overwrite=True
    )
    quality_dir = os.path.join(out, "quality")
    os.makedirs(quality_dir, exist_ok=True)
    curves = [compactness(model), specificity(model, shapes, number_of_samples=100, seed=0)]
    if len(names) >= 3:
        curves.append(generalization(shapes, faces, scaling=scaling))
    for curve in curves:
        curve.plot(os.path.join(quality_dir, f"{curve.name}.png"), overwrite=True)
        atomic_write_text(
            os.path.join(quality_dir, f"{curve.name}.txt"), curve.table() + "\n", overwrite=True
        )
    report = {
        "model_dir": out,
        "patients": batch.as_dicts(),
        "registered": list(names),
        "failed": [r.name for r in batch.failed],
        "variances": model.variance_records(),
        "quality": {c.name: c.as_dict() for c in curves},
        "sliding": None
        if slid is None
        else {"iterations": slid.iterations, "message": slid.message},
    }
    atomic_write_text(
        os.path.join(out, "report.json"), json.dumps(report, indent=2) + "\n", overwrite=True
    )
    write_model_explorer(os.path.join(out, "explorer.html"), model, registrations=batch)
    return ModelFolder(out, batch, model, curves, slid, report)
