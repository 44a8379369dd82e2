"""Ordinary and generalised Procrustes analysis of corresponding point sets (semilandmark meshes).

Berar et al. (2005), section 3.3: before the statistical analysis the registered meshes "are
aligned using Procrustes registration on the mean individual ... Gravity centres are first aligned.
Then the optimal rotation that minimizes the distance between the two set of points is obtained."
Size is kept (a rigid alignment); a similarity alignment (Kendall shape space, size removed) is
available with ``scaling=True``. Reflections are never allowed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._geometry import apply_transformation, proper_rotation
from .._geometry import fit_pose as fit_transformation
from .._validation import as_points, check_bool, check_positive

__all__ = [
    "ProcrustesResult",
    "as_shape_array",
    "fit_transformation",
    "generalized_procrustes",
    "procrustes_transform",
]

logger = logging.getLogger("o3dreg")


def as_shape_array(shapes: Any, name: str = "shapes", *, min_shapes: int = 2) -> np.ndarray:
    """Stack corresponding point sets into a ``(k, n, 3) float64`` copy, with clear errors.

    ``shapes`` is a ``(k, n, 3)`` array or a sequence of ``(n, 3)`` arrays / Open3D meshes or
    point clouds, all with the same number of points in the same order.
    """
    if isinstance(shapes, np.ndarray) and shapes.ndim == 3:
        items: list[Any] = list(shapes)
    elif isinstance(shapes, (list, tuple)):
        items = list(shapes)
    else:
        raise TypeError(
            f"`{name}` must be a (k, n, 3) array or a sequence of (n, 3) point sets, "
            f"got {type(shapes).__name__}"
        )
    if len(items) < min_shapes:
        raise ValueError(f"`{name}` must hold at least {min_shapes} shapes, got {len(items)}")
    arrays = [as_points(item, f"{name}[{k}]") for k, item in enumerate(items)]
    n = arrays[0].shape[0]
    for k, arr in enumerate(arrays):
        if arr.shape[0] != n:
            raise ValueError(
                f"`{name}` must all have the same number of points (corresponding "
                f"semilandmarks); {name}[0] has {n}, {name}[{k}] has {arr.shape[0]}"
            )
    return np.stack(arrays)


def procrustes_transform(source: Any, target: Any, *, scaling: bool = False) -> np.ndarray:
    """The rigid (or similarity) transformation best mapping ``source`` onto ``target``.

    Minimises ``sum_i |s R x_i + t - y_i|^2`` over rotations ``R`` (``det R = +1``: reflections
    are excluded), translations ``t`` and, when ``scaling``, a scale ``s > 0``.

    Parameters
    ----------
    source, target : (n, 3) array_like
        Corresponding points (row ``i`` of each is the same semilandmark). Not modified.
    scaling : bool, optional
        Also estimate a uniform scale. Default ``False`` (size kept, as in the paper).

    Returns
    -------
    (4, 4) ndarray
        ``source -> target`` transformation.

    References
    ----------
    .. [1] W. Kabsch, "A solution for the best rotation to relate two sets of vectors", Acta
       Cryst. A32 (1976). :doi:`10.1107/S0567739476001873`
    .. [2] S. Umeyama, "Least-squares estimation of transformation parameters between two point
       patterns", IEEE TPAMI 13(4), 1991. :doi:`10.1109/34.88573`
    """
    a = as_points(source, "source")
    b = as_points(target, "target")
    if a.shape != b.shape:
        raise ValueError(
            f"`source` and `target` must have the same shape, got {a.shape} and {b.shape}"
        )
    scaling = check_bool(scaling, "scaling")
    return fit_transformation(a, b, bool(scaling))


@dataclass(frozen=True, eq=False)
class ProcrustesResult:
    """The outcome of :func:`generalized_procrustes`.

    Attributes
    ----------
    shapes : (k, n, 3) ndarray
        The aligned shapes (in the frame of the mean).
    mean : (n, 3) ndarray
        The Procrustes mean, centred at the origin.
    transformations : (k, 4, 4) ndarray
        ``transformations[i]`` maps input shape ``i`` onto ``shapes[i]``.
    scaling : bool
        Whether sizes were normalised (similarity) or kept (rigid).
    iterations : int
        Mean updates performed.
    success : bool
        Whether the mean converged within ``max_iteration``.
    message : str
    """

    shapes: np.ndarray = field(repr=False)
    mean: np.ndarray = field(repr=False)
    transformations: np.ndarray = field(repr=False)
    scaling: bool
    iterations: int
    success: bool
    message: str

    def __repr__(self) -> str:
        k, n, _ = self.shapes.shape
        kind = "similarity" if self.scaling else "rigid"
        return (
            f"ProcrustesResult(shapes={k}, points={n}, {kind}, iterations={self.iterations}, "
            f"success={self.success})"
        )

    @property
    def residuals(self) -> np.ndarray:
        """RMS distance of each aligned shape to the mean, ``(k,)``."""
        return np.sqrt(((self.shapes - self.mean) ** 2).sum(axis=2).mean(axis=1))


def generalized_procrustes(
    shapes: Any,
    *,
    scaling: bool = False,
    max_iteration: int = 100,
    tolerance: float = 1e-10,
) -> ProcrustesResult:
    """Align corresponding shapes to their common mean (generalised Procrustes analysis).

    Every shape is centred, then rotated (and scaled, with ``scaling``) onto the current mean;
    the mean is recomputed and the alignment repeated until the mean stops moving:
    ``|M_k - M_{k-1}|_F / |M_k|_F < tolerance``. The mean is kept in the orientation of the
    first shape (each new mean is rotated onto the previous one), so results do not drift, and
    with ``scaling`` its centroid size is the mean centroid size of the inputs (units are kept)
    and each shape is scaled into the tangent space at the mean (its projection onto the mean
    is the mean, ``<x_i, M> = |M|^2``), so the shapes do not differ along the mean's own
    direction: a model built from them has no mode of pure size change.

    Parameters
    ----------
    shapes : (k, n, 3) array_like or sequence of (n, 3) array_like / Open3D geometries
        ``k >= 2`` corresponding point sets. Not modified.
    scaling : bool, optional
        ``False`` (default): rigid alignment, sizes kept (the paper). ``True``: similarity.
    max_iteration : int, optional
        Default 100.
    tolerance : float, optional
        Relative change of the mean that stops the iteration. Default 1e-10.

    Returns
    -------
    ProcrustesResult
        Non-convergence is ``success=False`` with a ``message``, not an exception.

    Raises
    ------
    ValueError
        Fewer than 2 shapes, or shapes with different numbers of points.

    References
    ----------
    .. [1] J. C. Gower, "Generalized Procrustes analysis", Psychometrika 40 (1975).
       :doi:`10.1007/BF02291478`
    .. [2] M. Berar, M. Desvignes, G. Bailly, Y. Payan, "3D meshes registration: application to
       statistical skull model", ICIAR 2004, LNCS 3212, section 3.3.
    .. [3] I. L. Dryden, K. V. Mardia, "Statistical Shape Analysis", Wiley 1998, section 4.3
       (tangent coordinates).
    """
    x = as_shape_array(shapes)
    scaling = check_bool(scaling, "scaling")
    # A shape whose points all coincide has no pose or size to align (with scaling it would
    # shrink the mean, and every shape with it, to a point).
    sizes = np.sqrt(((x - x.mean(axis=1, keepdims=True)) ** 2).sum(axis=(1, 2)))
    flat = np.flatnonzero(~(sizes > 1e-12 * sizes.max(initial=0.0)))
    if flat.size:
        raise ValueError(
            f"`shapes` must each have points at more than one place, got shape(s) "
            f"{flat.tolist()} with all their points at one place"
        )
    max_iteration = check_positive(max_iteration, "max_iteration", integer=True)
    tolerance = check_positive(tolerance, "tolerance", allow_zero=True)
    return _generalized_procrustes(x, bool(scaling), max_iteration, tolerance)


def _generalized_procrustes(
    x: np.ndarray, scaling: bool, max_iteration: int, tolerance: float
) -> ProcrustesResult:
    k = x.shape[0]
    centred = x - x.mean(axis=1, keepdims=True)
    size = float(np.sqrt((centred**2).sum(axis=(1, 2))).mean())
    mean = centred[0].copy()
    transforms = np.zeros((k, 4, 4))
    aligned = np.empty_like(x)
    success = False
    iterations = 0
    change = np.inf
    for iterations in range(1, max_iteration + 1):  # noqa: B007
        _align_all(x, mean, scaling, transforms, aligned)
        new_mean = aligned.mean(axis=0)
        new_mean -= new_mean.mean(axis=0)
        # Keep the orientation of the previous mean (a rotation of all shapes is free).
        new_mean = new_mean @ proper_rotation(new_mean, mean).T
        if scaling:
            norm = float(np.sqrt((new_mean**2).sum()))
            new_mean *= size / norm if norm > 0 else 1.0
        norm = float(np.sqrt((new_mean**2).sum()))
        change = float(np.sqrt(((new_mean - mean) ** 2).sum())) / (norm if norm > 0 else 1.0)
        mean = new_mean
        if change < tolerance:
            success = True
            break
    _align_all(x, mean, scaling, transforms, aligned)
    message = (
        f"mean converged in {iterations} iterations (relative change {change:.3g})"
        if success
        else f"mean did not converge in {max_iteration} iterations (relative change {change:.3g})"
    )
    logger.debug("generalized_procrustes: %s", message)
    return ProcrustesResult(
        shapes=aligned,
        mean=mean,
        transformations=transforms,
        scaling=scaling,
        iterations=iterations,
        success=success,
        message=message,
    )


def _align_all(
    x: np.ndarray, mean: np.ndarray, scaling: bool, transforms: np.ndarray, aligned: np.ndarray
) -> None:
    """Each shape rotated (and scaled) onto the centred ``mean``, into ``transforms`` and
    ``aligned``. With ``scaling``, the scale puts each shape in the tangent space at the mean:
    its projection onto the mean is the mean (``<x_i, M> = |M|^2``). The least-squares scale
    would shrink each shape by the cosine of its angle to the mean, a size difference that
    becomes a mode of the model (a mode of uniform scaling in a model meant to have none)."""
    norm2 = float((mean**2).sum())
    for i in range(x.shape[0]):
        transforms[i] = fit_transformation(x[i], mean, scaling)
        aligned[i] = apply_transformation(transforms[i], x[i])
        if scaling:
            along = float((aligned[i] * mean).sum())
            if along > 0:
                transforms[i][:3] *= norm2 / along  # the centroid stays at the origin
                aligned[i] *= norm2 / along
