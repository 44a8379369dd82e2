"""Building a shape model: Procrustes alignment, then a principal component analysis.

Berar et al. (2005), section 3.3: the registered template meshes are aligned by Procrustes
analysis; the PCA of the aligned vertices gives the mean ``M``, the modes ``A`` and their variances
(Table 4).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import open3d as o3d

from .._validation import as_faces, as_mesh_arrays, check_bool, check_positive
from .model import ShapeModel
from .procrustes import as_shape_array, generalized_procrustes

__all__ = ["build_shape_model"]

logger = logging.getLogger("o3dreg")

#: Aligned shapes whose points lie within this fraction of the mean shape's size (RMS distance
#: of its points from their centroid) of their mean positions, RMS, are one shape: what is left
#: is rounding (the same mesh twice, or one shape in two poses, aligned by Procrustes).
SAME_SHAPE = 1e-9

#: Modes with less than this fraction of the total variance are left out: a thousandth of the
#: population's spread, they hold what Procrustes leaves of pose (rotations act non-linearly)
#: and rounding, far below a registration's accuracy. Kept, their tiny variances made a fit's
#: coefficients on them 5-13 standard deviations for an exact model instance (Mahalanobis 16.7
#: instead of 1.8).
MIN_VARIANCE_RATIO = 1e-6


def template_faces(faces: Any, points: int) -> np.ndarray:
    """A new ``(m, 3) int64`` array: ``faces`` as given, or the triangles of a template mesh."""
    if isinstance(faces, o3d.utility.Vector3iVector):  # an Open3D mesh's ``triangles``
        faces = np.asarray(faces)
    if isinstance(faces, np.ndarray):
        return as_faces(faces, points, "faces")
    if isinstance(faces, (list, tuple)) and not (
        len(faces) == 2 and np.ndim(np.asarray(faces[0], dtype=object)) == 2
    ):
        return as_faces(faces, points, "faces")  # a sequence of triangles, not (V, F)
    vertices, triangles = as_mesh_arrays(faces, "faces")
    if vertices.shape[0] != points:
        raise ValueError(
            f"`faces` as a mesh must have as many vertices as each shape has points ({points}), "
            f"got {vertices.shape[0]}"
        )
    return triangles


def build_shape_model(
    shapes: Any,
    faces: Any,
    *,
    scaling: bool = False,
    number_of_modes: int | None = None,
    names: Any = None,
    align: bool = True,
) -> ShapeModel:
    """Build a PCA shape model from corresponding shapes (semilandmark meshes).

    The shapes are aligned by :func:`~o3dreg.generalized_procrustes` (unless ``align`` is
    false), centred on their mean, and the principal modes are the right singular vectors of
    the ``(s, 3n)`` centred data matrix ``X = U S V^T``: ``A = V``, variances ``S^2 / (s - 1)``.

    Parameters
    ----------
    shapes : (s, n, 3) array_like or sequence of (n, 3) array_like / Open3D meshes
        ``s >= 2`` shapes with the same points in the same order. Not modified.
    faces : (m, 3) array_like of int, or a mesh
        The template's triangles (shared by every shape), or the template itself: any mesh
        that the registration functions take (Open3D legacy or tensor ``TriangleMesh``,
        ``trimesh.Trimesh``, triangulated ``pyvista.PolyData``, ``(vertices, faces)``); its
        triangles are used, and it must have as many vertices as each shape has points. Not
        modified.
    scaling : bool, optional
        Similarity Procrustes (size removed) instead of rigid (size kept, default, the paper).
    number_of_modes : int, optional
        Keep only the first modes. Default: all modes with at least
        :data:`MIN_VARIANCE_RATIO` of the total variance, at most ``s - 1``.
    names : sequence of str, optional
        Names of the shapes (patients).
    align : bool, optional
        Run Procrustes first. Default ``True``.

    Returns
    -------
    ShapeModel

    Raises
    ------
    ValueError
        Fewer than 2 shapes, shapes that do not differ (after alignment, within
        :data:`SAME_SHAPE` of their size: a model of no variance), different vertex counts, or
        ``faces`` not indexing the points (a mesh: other vertex count than the shapes).
    TypeError
        ``faces`` neither an array of triangles nor a mesh.

    References
    ----------
    .. [1] T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
       training and application", CVIU 61(1), 1995. :doi:`10.1006/cviu.1995.1004`
    .. [2] M. Berar et al., ICIAR 2004, LNCS 3212, section 3.3, eq. (4) and Table 4.
    """
    x = as_shape_array(shapes)
    f = template_faces(faces, x.shape[1])
    scaling = check_bool(scaling, "scaling")
    align = check_bool(align, "align")
    s = x.shape[0]
    if number_of_modes is not None:
        number_of_modes = check_positive(number_of_modes, "number_of_modes", integer=True)
        if number_of_modes > s - 1:
            raise ValueError(
                f"`number_of_modes` must be <= {s - 1} (shapes - 1), got {number_of_modes}"
            )
    if names is None:
        names_ = tuple(f"shape{i:03d}" for i in range(s))
    else:
        if isinstance(names, str):
            raise TypeError(f"`names` must be a sequence of {s} names, got one string {names!r}")
        names_ = tuple(str(n) for n in names)
        if len(names_) != s:
            raise ValueError(f"`names` must hold {s} names, got {len(names_)}")
    return pca_model(x, f, scaling, number_of_modes, names_, align)


#: A shape is taken for mirrored when its best reflection onto the mean leaves less than this
#: share of the residual of its best rotation (a shape of the population fits best turned).
MIRRORED_RESIDUAL = 0.5


def mirrored_shapes(aligned: np.ndarray, mean: np.ndarray) -> list[int]:
    """The shapes among ``aligned`` (rotated onto ``mean`` already) whose best orthogonal map
    onto the mean is a reflection leaving under :data:`MIRRORED_RESIDUAL` of the residual."""
    out = []
    target = mean - mean.mean(axis=0)
    for k, shape in enumerate(aligned):
        centred = shape - shape.mean(axis=0)
        u, _, vt = np.linalg.svd(centred.T @ target)
        if np.linalg.det(u @ vt) >= 0:
            continue  # the best orthogonal map is a rotation: the shape is not mirrored
        turned = float(((centred - target) ** 2).sum())  # already at its best rotation
        mirrored = float(((centred @ (u @ vt) - target) ** 2).sum())
        if mirrored < MIRRORED_RESIDUAL * turned:
            out.append(k)
    return out


def pca_model(
    x: np.ndarray,
    faces: np.ndarray,
    scaling: bool,
    number_of_modes: int | None,
    names: tuple[str, ...],
    align: bool,
    *,
    distinct: bool = True,
    warn_mirrored: bool = True,
) -> ShapeModel:
    """The model of validated shapes; with ``distinct``, shapes that do not differ raise (the
    leave-one-out models of :func:`~o3dreg.generalization` may be the mean alone); with
    ``warn_mirrored``, a mirrored shape is named in a warning (once, by the model of all of
    them: not again by each leave-one-out model)."""
    s, n, _ = x.shape
    if align:
        gpa = generalized_procrustes(x, scaling=scaling)
        aligned, mean = gpa.shapes, gpa.shapes.mean(axis=0)
        for k in mirrored_shapes(aligned, mean) if warn_mirrored else []:
            logger.warning(
                "shape model: shape %d (%s) fits the mean shape far better mirrored than turned: "
                "are its left and right swapped? Mirror it back (negate one coordinate) or "
                "leave it out; its mirror image becomes a mode of the model",
                k,
                names[k],
            )
    else:
        aligned, mean = x, x.mean(axis=0)
    data = (aligned - mean).reshape(s, -1)
    if distinct:
        spread = float(np.sqrt((data**2).sum() / (s * n)))
        size = float(np.sqrt(((mean - mean.mean(axis=0)) ** 2).sum(axis=1).mean()))
        if not spread > SAME_SHAPE * size:
            shown = ", ".join(names[:6]) + (", ..." if s > 6 else "")
            raise ValueError(
                f"`shapes` must hold at least 2 distinct shapes to build a model, got {s} that "
                f"are the same shape{' after Procrustes alignment' if align else ''} ({shown}: "
                f"RMS distance of their points from the mean shape {spread:.3g}, for a shape of "
                f"RMS radius {size:.4g}): is one patient's mesh given under several names?"
            )
    _, sv, vt = np.linalg.svd(data, full_matrices=False)
    variances = sv**2 / (s - 1)
    total = float(variances.sum())
    keep = int(np.count_nonzero(variances > MIN_VARIANCE_RATIO * max(total, 1e-300)))
    keep = min(keep, s - 1)
    if number_of_modes is not None:
        keep = min(keep, number_of_modes)
    vt = vt[:keep]
    # Sign convention: the largest |component| of each mode is positive (deterministic output).
    signs = np.sign(vt[np.arange(keep), np.abs(vt).argmax(axis=1)])
    vt = vt * np.where(signs == 0, 1.0, signs)[:, None]
    scores = data @ vt.T
    logger.info(
        "shape model: %d shapes, %d points, %d modes, first ratios %s",
        s,
        n,
        keep,
        ", ".join(f"{v / total:.3f}" for v in variances[: min(keep, 5)]) if total > 0 else "-",
    )
    return ShapeModel(
        mean=mean,
        modes=vt.reshape(keep, n, 3),
        variances=variances[:keep],
        faces=faces,
        total_variance=total,
        scores=scores,
        names=names,
        scaling=scaling,
    )
