"""A verdict on every model fit: ``'ok'``, ``'suspect'`` or ``'failed'``, with its reasons.

A fit converges wherever it ends: on a patient that is a mirror image of the model's anatomy,
or larger than any shape the model was built from, it stops with a small change and a plausible
mean distance while its landmarks are tens of millimetres off. The verdict measures the fit
against the model's own population, each threshold derived from the model:

* **residual**: the fit's mean distance to the patient against the model's leave-one-out
  residuals (each training shape left out, the model rebuilt from the others in coefficient
  space, the shape projected on it: the residual a new member of the population leaves,
  measured point to point, which is larger than the closest-point distance of a fit), and at
  least 1% of the model's size;
* **coefficients**: their Mahalanobis distance ``sqrt(sum_j alpha_j^2 / variance_j)`` against
  the chi-squared distribution of ``k`` degrees of freedom the model assumes, and against the
  largest leave-one-out distance of its training shapes;
* **size**: the patient's surface size against the sizes of the training shapes (models built
  without ``scaling`` only: a ``scaling`` model holds no sizes); a partial patient (a surface
  with an open boundary) against the same part of them, the triangles it covers;
* **reflection**: the patient's mirror image, fitted the same way, fits clearly better (the
  best alignment has determinant ``< 0``: left and right swapped); and the patient's triangles
  face away from the model's at most fitted points.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.stats import chi2

from .._geometry import face_doubled_areas
from .._text import ratio_text
from ..registration.distance import SurfaceDistanceQuery
from ..registration.verdict import worst_status
from .model import ShapeModel

__all__ = ["assess_model_fit", "population_residuals", "population_sizes"]

#: A fit's mean (closest-point) distance above this many times the model's median
#: leave-one-out residual (RMS, point to point: a new member of the population leaves about
#: that, its closest-point mean less) is suspect, above the second a failure. A patient 1.5
#: times the model's size leaves about 3 times the median; a right fit less than one.
RESIDUAL_SUSPECT = 2.0
RESIDUAL_FAILED = 4.0
#: The reference residual is at least this fraction of the model's size (the RMS radius of its
#: mean surface): a 1.5-times patient leaves several percent of it, a right fit a fraction of a
#: percent.
RESIDUAL_FLOOR = 0.01
#: Coefficients whose squared Mahalanobis distance has a chi-squared (k degrees of freedom)
#: tail probability below this are outside the model: suspect; below the second, failed.
#: Each threshold is also at least the largest leave-one-out distance of a training shape (a
#: small population's new members reach further than the chi-squared law says).
MAHALANOBIS_SUSPECT_P = 1e-3
MAHALANOBIS_FAILED_P = 1e-9
#: The patient's size (RMS distance of its surface from its centroid, area-weighted) outside
#: the training sizes by more than this many of their standard deviations (of log size) is
#: suspect, the second a failure; each at least the given fraction (a patient's surface cut
#: differently from the training shapes changes its size by a few percent).
SIZE_SUSPECT_SD, SIZE_SUSPECT_MIN = 3.0, 0.10
SIZE_FAILED_SD, SIZE_FAILED_MIN = 6.0, 0.25
#: A partial patient's size is compared with the training shapes' over the triangles it
#: covers; covering fewer than this fraction of them, it is not compared (too small a part to
#: say anything about scale).
SIZE_MIN_COVERED = 0.25
#: The mirror image fits with a symmetric mean distance below this fraction of the patient's:
#: the patient is a reflection of the model's anatomy. A bilaterally symmetric bone fits
#: itself and its mirror image alike (ratio near 1); a mirrored patient's own fit leaves
#: several times its mirror image's.
MIRROR_FAILED = 0.5
MIRROR_SUSPECT = 0.8
#: Fraction of fitted vertices where the patient's surface faces away from the fitted model's
#: above which the patient's triangles are wound the other way.
FACING_AWAY = 0.5


def surface_size(vertices: np.ndarray, faces: np.ndarray) -> float:
    """RMS distance of a surface's points from its area centroid (area-weighted, exact for
    triangles: ``int x x^T dA = A / 12 (sum v_i v_i^T + (sum v_i)(sum v_i)^T)``)."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    area = face_doubled_areas(np.asarray(vertices, dtype=np.float64), np.asarray(faces)) / 2.0
    total = float(area.sum())
    if total <= 0:
        return 0.0
    centroid = (area[:, None] * corners.mean(axis=1)).sum(axis=0) / total
    c = corners - centroid
    second = (area / 12.0) * ((c**2).sum(axis=(1, 2)) + (c.sum(axis=1) ** 2).sum(axis=1))
    return float(np.sqrt(max(second.sum() / total, 0.0)))


def population_sizes(model: ShapeModel, faces: np.ndarray | None = None) -> np.ndarray:
    """:func:`surface_size` of each training shape ``M + A alpha_i`` (``(s,)``), over ``faces``
    (some of the model's triangles; default all)."""
    faces = model.faces if faces is None else faces
    return np.array(
        [
            surface_size(model.mean + np.tensordot(a, model.modes, axes=1), faces)
            for a in model.scores
        ]
    )


def _covered_faces(model: ShapeModel, fit: Any, surface: SurfaceDistanceQuery) -> np.ndarray:
    """The model's triangles the patient's surface covers: on a partial surface (an open
    boundary), those whose three fitted vertices have their closest point inside the boundary;
    all of them on a closed surface."""
    faces = np.asarray(model.faces)
    if not surface.has_boundary:
        return faces
    kept = surface.closest_with_data(np.asarray(fit.vertices))[3]
    return faces[kept[faces].all(axis=1)]


def population_residuals(model: ShapeModel, number_of_modes: int) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out residuals and Mahalanobis distances of the training shapes.

    For each training shape: the model rebuilt from the others (PCA of their coefficients,
    which hold the training shapes exactly in the stored modes), ``number_of_modes`` modes kept,
    the shape projected on it. Returns ``(rms, mahalanobis)``, each ``(s,)``: the RMS per-vertex
    residual (input units; the variance the stored modes leave out, ``total_variance -
    sum(variances)``, added as every shape's share) and the Mahalanobis distance of the
    projection in the rebuilt model. Empty with fewer than 3 training shapes.
    """
    scores = np.asarray(model.scores, dtype=np.float64)
    s = scores.shape[0]
    if s < 3 or scores.shape[1] == 0:
        return np.zeros(0), np.zeros(0)
    n = model.number_of_points
    left_out = max(float(model.total_variance - model.variances.sum()), 0.0)
    rms, maha = np.empty(s), np.empty(s)
    for i in range(s):
        others = np.delete(scores, i, axis=0)
        centre = others.mean(axis=0)
        _, sv, vt = np.linalg.svd(others - centre, full_matrices=False)
        keep = min(number_of_modes, int(np.count_nonzero(sv > 1e-9 * sv[0])) if sv.size else 0)
        r = scores[i] - centre
        coords = vt[:keep] @ r
        resid = r - vt[:keep].T @ coords
        rms[i] = np.sqrt((float(resid @ resid) + left_out) / n)
        var = sv[:keep] ** 2 / (s - 2)
        maha[i] = np.sqrt(float((coords**2 / np.maximum(var, 1e-300)).sum()))
    return rms, maha


def assess_model_fit(model: ShapeModel, fit: Any, target: Any, *, mirrored: Any = None) -> Any:
    """``fit`` (a :class:`~o3dreg.ModelFit`) with its verdict: ``status`` and ``warnings``.

    Parameters
    ----------
    model : ShapeModel
    fit : ModelFit
        The fit of ``model`` to ``target``.
    target : (vertices, faces)
        The patient surface the fit was made to.
    mirrored : ModelFit, optional
        The fit of the same model to the patient's mirror image; it tells a reflected patient
        (see the module documentation). Without it, only the facing of the triangles is checked.

    Returns
    -------
    ModelFit
        A copy of ``fit`` with ``status``, ``warnings`` and ``mahalanobis_distance`` set.
    """
    vt, ft = (np.asarray(a) for a in target)
    # One distance query of the patient (its AABB tree) for the size and facing checks.
    patient_surface = SurfaceDistanceQuery(vt, ft)
    k = int(fit.coefficients.size)
    variances = model.variances[:k]
    alpha = np.asarray(fit.coefficients, dtype=np.float64)
    positive = variances > 0
    d = float(np.sqrt((alpha[positive] ** 2 / variances[positive]).sum())) if k else 0.0
    found: list[tuple[str, str]] = []
    if not fit.success:
        found.append(("suspect", f"the fit did not converge: {fit.message}"))
    rms, loo_maha = population_residuals(model, k)

    # Residual against the population's leave-one-out residuals (plus the model's noise).
    reference = float(np.median(rms)) if rms.size else 0.0
    reference = float(np.sqrt(reference**2 + 3.0 * max(model.noise_variance, 0.0)))
    # A population of exactly linear shapes leaves no residual: a patient's surface, its
    # triangulation and noise, still do. The reference is at least 1% of the model's size.
    reference = max(reference, RESIDUAL_FLOOR * surface_size(model.mean, model.faces))
    # A scaling model's shapes are in the model's size: the fit's distance, in the patient's
    # units, is compared after removing the pose's scale.
    scale = float(abs(np.linalg.det(np.asarray(fit.transformation)[:3, :3]))) ** (1.0 / 3.0)
    if reference > 0 and scale > 0:
        ratio = fit.mean_distance / scale / reference
        for level, factor in (("failed", RESIDUAL_FAILED), ("suspect", RESIDUAL_SUSPECT)):
            if ratio > factor:
                found.append(
                    (
                        level,
                        f"the fitted model is {fit.mean_distance:.3g} from the patient on average, "
                        f"{ratio:.1f} times the residual the model's own training shapes leave "
                        f"when each is left out ({reference * scale:.3g}): the patient is not a "
                        "shape this model describes",
                    )
                )
                break

    # Coefficients far outside the model.
    dof = int(np.count_nonzero(positive))
    if dof:
        largest = float(loo_maha.max()) if loo_maha.size else 0.0
        for level, p in (("failed", MAHALANOBIS_FAILED_P), ("suspect", MAHALANOBIS_SUSPECT_P)):
            limit = max(float(np.sqrt(chi2.isf(p, dof))), largest)
            if level == "failed":
                limit = max(limit, 2.0 * largest)
            if d > limit:
                found.append(
                    (
                        level,
                        f"the shape coefficients lie {d:.3g} standard deviations (Mahalanobis) "
                        f"from the model's mean, beyond {limit:.3g} (chance below {p:g} for "
                        f"{dof} modes; the farthest training shape left out: {largest:.3g}): "
                        "the fit had to stretch the model far outside its population",
                    )
                )
                break

    # Size outside the population's (a model without scaling keeps the training sizes). A
    # partial patient is compared with the same part of the training shapes: the triangles it
    # covers.
    covered = None
    if not model.scaling and model.scores.shape[0] >= 3:
        covered = _covered_faces(model, fit, patient_surface)
    if covered is not None and covered.shape[0] >= SIZE_MIN_COVERED * model.faces.shape[0]:
        sizes = population_sizes(model, covered)
        share = covered.shape[0] / max(model.faces.shape[0], 1)
        part = "" if share >= 1.0 else f"; over the {share:.0%} of the model's triangles it covers"
        logs = np.log(sizes[sizes > 0])
        patient = surface_size(vt, ft)
        if logs.size >= 3 and patient > 0:
            centre, spread = float(np.median(logs)), float(logs.std(ddof=1))
            off = abs(np.log(patient) - centre)
            for level, n_sd, least in (
                ("failed", SIZE_FAILED_SD, SIZE_FAILED_MIN),
                ("suspect", SIZE_SUSPECT_SD, SIZE_SUSPECT_MIN),
            ):
                if off > max(n_sd * spread, np.log1p(least)):
                    found.append(
                        (
                            level,
                            f"the patient's size ({patient:.3g}, RMS radius of its surface) is "
                            f"{np.exp(np.log(patient) - centre):.3g} times the training shapes' "
                            f"median ({np.exp(centre):.3g}; they range over "
                            f"{sizes.min():.3g}-{sizes.max():.3g}{part}): another scale or "
                            "other units than the model's population",
                        )
                    )
                    break

    # Reflection: the mirror image fits clearly better, or the triangles face the other way.
    if mirrored is not None:
        own = _symmetric_distance(fit.vertices, fit.faces, fit.mean_distance, vt)
        other_vt = vt * np.array([-1.0, 1.0, 1.0])
        other_vt[:, 0] += 2.0 * vt[:, 0].mean()
        other = _symmetric_distance(
            mirrored.vertices, mirrored.faces, mirrored.mean_distance, other_vt
        )
        if own > 0:
            ratio = other / own
            for level, limit in (("failed", MIRROR_FAILED), ("suspect", MIRROR_SUSPECT)):
                if ratio < limit:
                    found.append(
                        (
                            level,
                            f"the patient's mirror image fits the model {ratio_text(own, other)} times "
                            "closer than the patient (the best alignment is a reflection, "
                            "determinant < 0): the patient is a mirror image of the model's "
                            "anatomy, left and right are swapped",
                        )
                    )
                    break
    away = _facing_away(fit.vertices, fit.faces, patient_surface)
    if away > FACING_AWAY:
        found.append(
            (
                "suspect",
                f"the patient's surface faces away from the fitted model's at {away:.0%} of the "
                "fitted points: its triangles are wound the other way (inside out, or a mirror "
                "image written without reversing them)",
            )
        )
    status = worst_status(*(level for level, _ in found))
    return dataclasses.replace(
        fit,
        status=status,
        warnings=tuple(text for _, text in found),
        mahalanobis_distance=d,
    )


def _symmetric_distance(
    vertices: np.ndarray, faces: np.ndarray, forward: float, vt: np.ndarray
) -> float:
    back = SurfaceDistanceQuery(vertices, faces).distance(vt).mean()
    return forward + float(back)


def _unit_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def _facing_away(vertices: np.ndarray, faces: np.ndarray, patient: SurfaceDistanceQuery) -> float:
    """Fraction of the fitted vertices whose closest patient triangle faces the other way
    (the fit's vertex normal, the sum of its triangles' unit normals, against the patient
    triangle's normal)."""
    faces = np.asarray(faces)
    face_normals = _unit_normals(vertices, faces)
    vertex_normals = np.zeros_like(vertices)
    for c in range(3):
        np.add.at(vertex_normals, faces[:, c], face_normals)
    _, face, _ = patient.closest(vertices)
    dots = (vertex_normals * patient.face_normal(face)).sum(axis=1)
    used = np.linalg.norm(vertex_normals, axis=1) > 0
    return float(np.mean(dots[used] < 0)) if used.any() else 0.0
