"""Fitting a shape model to a patient surface: pose and coefficients by iterated closest points.

The fitted instance is what :func:`~o3dreg.predict_landmarks` reads landmarks from.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation, barycentric
from .._validation import as_mesh_arrays, as_transformation, check_bool, check_positive
from ..io.mesh import to_open3d
from ..registration.distance import SurfaceDistanceQuery
from ..registration.rigid import SizeMismatch, default_start
from .fit_verdict import assess_model_fit
from .model import ShapeModel
from .procrustes import fit_transformation

__all__ = ["ModelFit", "assess_model_fit", "fit_shape_model"]

#: Without ``init``, each start is fitted to this relative change (at most
#: :data:`COARSE_ITERATIONS` iterations) and only the better one is carried on to the asked
#: tolerance: the choice between starts needs no finer fit, and the loser's last iterations
#: would be wasted. The winner's fit is the one an uninterrupted run gives (the iteration
#: depends on the pose and coefficients alone).
COARSE_TOLERANCE = 1e-3
COARSE_ITERATIONS = 30


@dataclass(frozen=True, eq=False)
class ModelFit:
    """The outcome of :func:`fit_shape_model`.

    Attributes
    ----------
    coefficients : (k,) ndarray
        ``alpha`` (input units) of the fitted instance.
    transformation : (4, 4) ndarray
        Pose: maps the model frame onto the patient (rigid, or similarity for a ``scaling`` model).
    vertices : (n, 3) ndarray
        The fitted instance ``T(M + A alpha)`` in patient coordinates.
    faces : (m, 3) ndarray
    mean_distance : float
        Mean distance from the fitted vertices to the patient surface, over the vertices with
        data (on a partial surface, those whose closest point is not beyond its open boundary;
        all of them on a closed one).
    iterations : int
    success : bool
        Whether the relative change of the fit fell below the tolerance. Says nothing about
        whether the fit is right: see ``status``.
    message : str
    status : {'ok', 'suspect', 'failed'}
        The verdict: the fit measured against the model's own population (see
        :func:`assess_model_fit`).
    warnings : tuple of str
        One plain sentence per finding behind ``status`` (empty when ``'ok'``).
    mahalanobis_distance : float
        ``sqrt(sum_j alpha_j^2 / variance_j)`` of the coefficients.
    """

    coefficients: np.ndarray
    transformation: np.ndarray = field(repr=False)
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    mean_distance: float
    iterations: int
    success: bool
    message: str
    status: str = "ok"
    warnings: tuple[str, ...] = ()
    mahalanobis_distance: float = float("nan")

    def __repr__(self) -> str:
        return (
            f"ModelFit(status={self.status!r}, modes={self.coefficients.size}, "
            f"mean_distance={self.mean_distance:.4g}, "
            f"mahalanobis_distance={self.mahalanobis_distance:.3g}, "
            f"iterations={self.iterations}, success={self.success})"
        )

    def mesh(self) -> o3d.geometry.TriangleMesh:
        mesh = to_open3d(np.array(self.vertices), np.array(self.faces))
        mesh.compute_vertex_normals()
        return mesh


def fit_shape_model(
    model: ShapeModel,
    target: Any,
    *,
    init: Any = None,
    number_of_modes: int | None = None,
    regularization: float | None = None,
    max_iteration: int = 300,
    tolerance: float = 1e-4,
    check_reflection: bool = True,
) -> ModelFit:
    """Fit pose and shape coefficients of ``model`` to a patient surface (iterated closest points).

    Each iteration: (1) closest points ``y_i`` on the patient surface to the current instance
    (on a partial surface, an instance vertex whose closest point lies beyond the open boundary
    is left out: the part of the bone the patient's surface lacks is inferred by the model, not
    pulled onto the rim; the registration's rule: its closest point on an open edge, its
    offset along the surface over a tenth of the mean edge); and, as in the
    symmetric distance of eq. (3), closest points of the instance surface to samples of the
    patient surface; (2) pose by weighted Procrustes of all these pairs; (3)
    coefficients minimising ``|S (M + A alpha) - T^-1 y|^2 + regularization * sum_j alpha_j^2 /
    variance_j`` (``S`` selects vertices and barycentric surface points; Tikhonov with
    1/variance: with ``S = I`` this is ``alpha_j = variance_j / (variance_j + regularization)
    A_j^T (T^-1 y - M)``, the posterior mean of probabilistic PCA with noise variance
    ``regularization``). Both directions are weighted to count as ``n`` points.
    Stops when the instance moves by less than ``tolerance`` times its size (the model's size
    times the pose's scale: the same fit whatever the patient's units).

    Parameters
    ----------
    model : ShapeModel
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface, in its own coordinates. Not modified.
    init : (4, 4) array_like, optional
        Initial pose (model frame -> patient). Default: two fits, one started from the rigid
        registration of the mean mesh onto the patient (:func:`~o3dreg.registration_rigid`),
        one from aligned centroids; the one with the smaller symmetric mean distance is kept.
    number_of_modes : int, optional
        Modes used. Default all.
    regularization : float, optional
        Noise variance per coordinate in squared input units (mm^2). Default: the model's
        ``noise_variance``; when that is 0, estimated at each iteration as the mean squared
        closest-point residual per coordinate (the EM update of probabilistic PCA), so modes
        with less variance than the current misfit are damped.
    max_iteration : int, optional
        Default 300 (alternating pose and shape updates converge linearly, like ICP).
    tolerance : float, optional
        Default 1e-4.
    check_reflection : bool, optional
        Also fit the model to the patient's mirror image, to tell whether the patient is a
        reflection of the model's anatomy (left and right swapped: see
        :func:`assess_model_fit`). Default ``True``; it about doubles the time of a fit.

    Returns
    -------
    ModelFit
        With its verdict (``status``, ``warnings``) from :func:`assess_model_fit`.

    References
    ----------
    .. [1] M. E. Tipping, C. M. Bishop, "Probabilistic principal component analysis", J. R.
       Stat. Soc. B 61(3), 1999. :doi:`10.1111/1467-9868.00196`
    .. [2] P. J. Besl, N. D. McKay, "A method for registration of 3-D shapes", IEEE TPAMI 14(2),
       1992. :doi:`10.1109/34.121791`
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    vt, ft = as_mesh_arrays(target, "target", drop_degenerate=True)
    k = model.check_number_of_modes(number_of_modes)
    if regularization is None:
        reg = None if model.noise_variance <= 0 else model.noise_variance
    else:
        reg = check_positive(regularization, "regularization", allow_zero=True)
    max_iteration = check_positive(max_iteration, "max_iteration", integer=True)
    check_reflection = check_bool(check_reflection, "check_reflection")
    tolerance = check_positive(tolerance, "tolerance", allow_zero=True)
    # One distance query (its AABB tree) per surface, shared by every start fitted to it.
    surface = SurfaceDistanceQuery(vt, ft)
    if init is not None:
        pose = as_transformation(init, "init", similarity=True)
        fit, _ = _fit_model(model, surface, pose, np.zeros(k), reg, max_iteration, tolerance)
    else:
        try:
            fit = _best_fit(model, surface, k, reg, max_iteration, tolerance)
        except SizeMismatch as exc:
            raise ValueError(
                f"`target` is {exc.ratio:.3g} times the size of the model's mean shape (RMS "
                f"radius {exc.size_target:.4g} vs {exc.size_source:.4g}): are they in the same "
                "units? Convert the patient surface, or give the pose as `init`"
            ) from None
    mirrored = None
    if check_reflection:
        # The patient reflected through its centroid (any one plane: the fit's rotation
        # search covers the others), fitted from the same starts.
        flip = vt * np.array([-1.0, 1.0, 1.0])
        flip[:, 0] += 2.0 * vt[:, 0].mean()
        # It only has to tell whether the mirror image fits clearly better (a factor of 1.25
        # or more in distance): a looser tolerance and fewer iterations do.
        mirrored = _best_fit(
            model,
            SurfaceDistanceQuery(flip, ft[:, ::-1]),
            k,
            reg,
            min(max_iteration, 30),
            max(tolerance, 1e-3),
        )
    return assess_model_fit(model, fit, (vt, ft), mirrored=mirrored)


def _best_fit(
    model: ShapeModel,
    surface: SurfaceDistanceQuery,
    k: int,
    reg: float | None,
    max_iteration: int,
    tolerance: float,
) -> ModelFit:
    # Two starts: the rigid registration of the mean (moment-based guess + ICP) and a plain
    # translation of centroids (right when patients share the model's orientation, where the
    # moment guess may pick a symmetric flip); keep the fit with the smaller symmetric distance.
    vt = surface.vertices
    shift = np.eye(4)
    shift[:3, 3] = vt.mean(axis=0) - model.mean.mean(axis=0)
    # registration_rigid on the validated patient, scored with its tree (built once here).
    # The fit tells a mirrored patient by fitting its mirror image (check_reflection).
    rigid = default_start(
        model.mean, model.faces, surface, with_scaling=model.scaling, mirror=False
    )
    starts = [np.array(rigid.transformation), shift]
    coarse_tolerance = max(tolerance, COARSE_TOLERANCE)
    coarse_iterations = min(max_iteration, COARSE_ITERATIONS)
    best, best_cost, change = None, np.inf, np.inf
    for pose in starts:
        fit, last = _fit_model(
            model, surface, pose, np.zeros(k), reg, coarse_iterations, coarse_tolerance
        )
        cost = _symmetric_distance(fit, vt)
        if cost < best_cost:
            best, best_cost, change = fit, cost, last
    assert best is not None
    if best.iterations < max_iteration and change >= tolerance:
        best, _ = _fit_model(
            model,
            surface,
            best.transformation,
            best.coefficients,
            reg,
            max_iteration,
            tolerance,
            done=best.iterations,
        )
    return best


def _symmetric_distance(fit: ModelFit, vt: np.ndarray) -> float:
    """Mean distance of the fitted vertices to the patient plus that of the patient's vertices
    to the fitted surface (the criterion that chooses between starts)."""
    back = SurfaceDistanceQuery(fit.vertices, fit.faces).distance(vt).mean()
    return fit.mean_distance + float(back)


def _fit_model(
    model: ShapeModel,
    query: SurfaceDistanceQuery,
    pose: np.ndarray,
    a: np.ndarray,
    reg: float | None,
    max_iteration: int,
    tolerance: float,
    done: int = 0,
) -> tuple[ModelFit, float]:
    """The fit from pose ``pose`` and coefficients ``a`` (``k`` of them), continuing a fit that
    took ``done`` of the ``max_iteration`` iterations, and the relative change of its last
    iteration."""
    vt = query.vertices
    k = a.size
    modes = model.modes[:k]
    variances = model.variances[:k]
    size = float(np.sqrt(((model.mean - model.mean.mean(axis=0)) ** 2).sum(axis=1).mean()))
    current = apply_transformation(pose, _instance(model, a))
    success = False
    change = np.inf
    iterations = done
    faces = np.asarray(model.faces)
    n = model.number_of_points
    # Target samples for the target -> instance correspondences (eq. 3's second term).
    stride = max(1, vt.shape[0] // (4 * n))
    samples = vt[::stride]
    for iterations in range(done + 1, max_iteration + 1):  # noqa: B007
        # Forward: instance vertices -> closest target points, but for those beyond the open
        # boundary of a partial target (a part the patient's surface lacks), which would be
        # pulled onto its rim.
        _, _, closest, kept = query.closest_with_data(current)
        # Backward: target samples -> closest points of the instance surface (barycentric).
        _, face, on_instance = SurfaceDistanceQuery(current, faces).closest(samples)
        weights = barycentric(current[faces[face]], on_instance)
        instance = _instance(model, a)
        src = np.vstack([instance, np.einsum("jc,jcd->jd", weights, instance[faces[face]])])
        dst = np.vstack([closest, samples])
        forward = kept / max(int(kept.sum()), 1)
        wts = np.concatenate([forward, np.full(samples.shape[0], 1.0 / samples.shape[0])])
        pose = fit_transformation(src, dst, model.scaling, wts)
        inverse = np.linalg.inv(pose)
        y = apply_transformation(inverse, dst)
        sigma2 = reg
        if sigma2 is None:
            scale = float(abs(np.linalg.det(pose[:3, :3]))) ** (2.0 / 3.0)
            resid = ((apply_transformation(pose, src) - dst) ** 2).sum(axis=1)
            sigma2 = max(float((wts * resid).sum()) / 2.0 / 3.0 / scale, 1e-12)
        # Model terms of every correspondence: S (M + A a), S = [I; W] (rows of barycentric).
        sm = np.vstack([model.mean, np.einsum("jc,jcd->jd", weights, model.mean[faces[face]])])
        sa = np.concatenate(
            [modes, np.einsum("jc,kjcd->kjd", weights, modes[:, faces[face]])], axis=1
        )
        # Normal equations, data weighted so each direction counts as n points (eq. 3).
        w = wts * n
        lhs = np.einsum("kjd,j,ljd->kl", sa, w, sa) + sigma2 * np.diag(
            1.0 / np.maximum(variances, 1e-300)
        )
        rhs = np.einsum("kjd,j,jd->k", sa, w, y - sm)
        a = np.linalg.solve(lhs, rhs) if k else a
        new = apply_transformation(pose, _instance(model, a))
        # Relative to the instance's size in the patient's units (a similarity pose scales it).
        scale = float(np.cbrt(abs(np.linalg.det(pose[:3, :3]))))
        moved = float(np.sqrt(((new - current) ** 2).sum(axis=1).mean()))
        change = moved / max(size * scale, 1e-300)
        current = new
        if change < tolerance:
            success = True
            break
    dist, _, _, kept = query.closest_with_data(current)
    message = (
        f"converged in {iterations} iterations (relative change {change:.3g})"
        if success
        else f"did not converge in {max_iteration} iterations (relative change {change:.3g})"
    )
    fit = ModelFit(
        coefficients=a,
        transformation=pose,
        vertices=current,
        faces=np.array(model.faces),
        mean_distance=float(dist[kept].mean()) if kept.any() else float(dist.mean()),
        iterations=iterations,
        success=success,
        message=message,
    )
    return fit, change


def _instance(model: ShapeModel, a: np.ndarray) -> np.ndarray:
    """``M + A alpha`` for the first ``a.size`` modes (eq. 4), without input checks."""
    return model.mean + np.tensordot(a, model.modes[: a.size], axes=1)
