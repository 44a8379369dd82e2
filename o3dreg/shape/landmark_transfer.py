"""Anatomical landmarks defined on the template and carried to every patient.

A landmark is a point of a template triangle, stored as the triangle index and barycentric
coordinates, so it has a position on *any* mesh with the template's triangulation: each
registered patient's semilandmark mesh, the model mean, a fitted model instance. Landmarks are
read from CSV, 3D Slicer markups (``.mrk.json``, ``.fcsv``) or MeshLab picked points (``.pp``) by
:func:`o3dreg.io.landmarks.read_landmarks` (converted to LPS, the meshes' system); positions are
mapped to the nearest template surface point.
"""

from __future__ import annotations

import csv
import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._geometry import barycentric
from .._validation import as_mesh_arrays, as_points, check_positive
from ..io.landmark_files import check_landmark_suffix, read_landmarks, write_landmarks
from ..registration.distance import SurfaceDistanceQuery
from .fit import fit_shape_model
from .model import ShapeModel

__all__ = [
    "LandmarkPrediction",
    "TemplateLandmarks",
    "landmark_errors",
    "load_template_landmarks",
    "predict_landmarks",
    "read_landmarks",
    "write_landmarks",
]

logger = logging.getLogger("o3dreg")


@dataclass(frozen=True, eq=False)
class TemplateLandmarks:
    """Landmarks attached to the template surface.

    Attributes
    ----------
    labels : tuple of str
    triangles : (l,) int ndarray
        Template triangle holding each landmark.
    barycentric : (l, 3) ndarray
        Barycentric coordinates in that triangle (non-negative, summing to 1).
    number_of_vertices : int
        Vertex count of the template (meshes evaluated must have it).
    """

    labels: tuple[str, ...]
    triangles: np.ndarray = field(repr=False)
    barycentric: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    number_of_vertices: int = 0

    def __repr__(self) -> str:
        return f"TemplateLandmarks({len(self.labels)} landmarks: {', '.join(self.labels[:6])})"

    def __len__(self) -> int:
        return len(self.labels)

    @classmethod
    def from_vertices(cls, template: Any, indices: Any, labels: Any = None) -> TemplateLandmarks:
        """Landmarks at template vertices.

        Parameters
        ----------
        template : open3d.geometry.TriangleMesh or (vertices, faces)
        indices : (l,) array_like of int
            Vertex indices; ``ValueError`` if outside ``[0, n - 1]`` or on no triangle.
        labels : sequence of str, optional
            Default ``L1, L2, ...``.
        """
        v, f = as_mesh_arrays(template, "template")
        idx = np.asarray(indices)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            raise TypeError(
                f"`indices` must be a 1-D array of integers, got {idx.dtype} {idx.shape}"
            )
        bad = (idx < 0) | (idx >= v.shape[0])
        if bad.any():
            raise ValueError(
                f"`indices` must be template vertices in [0, {v.shape[0] - 1}], got "
                f"{idx[bad].tolist()} (landmarks outside the template)"
            )
        labels_ = _labels(labels, idx.size)
        tri = np.empty(idx.size, dtype=np.int64)
        bary = np.zeros((idx.size, 3))
        for k, i in enumerate(idx):
            rows, cols = np.nonzero(f == i)
            if rows.size == 0:
                raise ValueError(f"`indices[{k}]` = {int(i)} is a vertex on no template triangle")
            tri[k] = rows[0]
            bary[k, cols[0]] = 1.0
        return cls(labels_, tri, bary, f, v.shape[0])

    @classmethod
    def from_barycentric(
        cls, template: Any, triangles: Any, barycentric: Any, labels: Any = None
    ) -> TemplateLandmarks:
        """Landmarks given by triangle index and barycentric coordinates (checked)."""
        v, f = as_mesh_arrays(template, "template")
        tri = np.asarray(triangles)
        if tri.ndim != 1 or not np.issubdtype(tri.dtype, np.integer):
            raise TypeError(
                f"`triangles` must be a 1-D array of integers, got {tri.dtype} {tri.shape}"
            )
        bary = np.array(barycentric, dtype=np.float64)
        if bary.shape != (tri.size, 3):
            raise ValueError(f"`barycentric` must have shape ({tri.size}, 3), got {bary.shape}")
        bad = (tri < 0) | (tri >= f.shape[0])
        if bad.any():
            raise ValueError(
                f"`triangles` must be template triangles in [0, {f.shape[0] - 1}], got "
                f"{tri[bad].tolist()} (landmarks outside the template)"
            )
        off = (bary.min(axis=1) < -1e-6) | (np.abs(bary.sum(axis=1) - 1.0) > 1e-6)
        if off.any():
            raise ValueError(
                "`barycentric` rows must be >= 0 and sum to 1 (a point inside its triangle), "
                f"got {bary[off].tolist()} (landmarks outside the template)"
            )
        return cls(_labels(labels, tri.size), tri.astype(np.int64), bary, f, v.shape[0])

    @classmethod
    def from_points(
        cls, template: Any, points: Any, labels: Any = None, *, max_distance: float | None = None
    ) -> TemplateLandmarks:
        """Landmarks at the template surface points nearest to ``points`` (e.g. Slicer markups).

        Parameters
        ----------
        template : open3d.geometry.TriangleMesh or (vertices, faces)
        points : (l, 3) array_like
            Positions in template coordinates.
        labels : sequence of str, optional
        max_distance : float, optional
            Points farther than this from the template surface raise ``ValueError`` (landmarks
            outside the template). Default 5 % of the template's bounding-box diagonal.
        """
        v, f = as_mesh_arrays(template, "template")
        pts = as_points(points, "points")
        if max_distance is None:
            max_distance = 0.05 * float(np.linalg.norm(np.ptp(v, axis=0)))
        else:
            max_distance = check_positive(max_distance, "max_distance", allow_zero=True)
        dist, face, closest = SurfaceDistanceQuery(v, f).closest(pts)
        far = dist > max_distance
        labels_ = _labels(labels, pts.shape[0])
        if far.any():
            which = ", ".join(f"{labels_[i]} ({dist[i]:.3g})" for i in np.flatnonzero(far))
            raise ValueError(
                f"`points` must lie within {max_distance:.3g} of the template surface "
                f"(landmarks outside the template): {which}"
            )
        bary = barycentric(v[f[face]], closest)
        return cls(labels_, face.astype(np.int64), bary, f, v.shape[0])

    def positions(self, vertices: Any) -> np.ndarray:
        """Landmark positions on a mesh with the template's triangulation, ``(l, 3)``.

        Parameters
        ----------
        vertices : (n, 3) array_like or open3d.geometry.TriangleMesh
            Vertices of the template, of a registered patient's semilandmark mesh, of the model
            mean or of a fitted instance.
        """
        v = as_points(vertices, "vertices")
        if v.shape[0] != self.number_of_vertices:
            raise ValueError(
                f"`vertices` must have the template's {self.number_of_vertices} vertices, "
                f"got {v.shape[0]}"
            )
        corners = v[self.faces[self.triangles]]  # (l, 3, 3)
        return np.einsum("lk,lkd->ld", self.barycentric, corners)

    def carry(self, shapes: Any) -> np.ndarray:
        """Positions on every shape of a batch: ``(s, l, 3)`` for ``(s, n, 3)`` shapes."""
        return np.stack([self.positions(s) for s in shapes])


def _labels(labels: Any, count: int) -> tuple[str, ...]:
    if labels is None:
        return tuple(f"L{i + 1}" for i in range(count))
    out = tuple(str(x) for x in labels)
    if len(out) != count:
        raise ValueError(f"`labels` must hold {count} labels, got {len(out)}")
    return out


# -- files ------------------------------------------------------------------------------------------
def load_template_landmarks(
    path: str | os.PathLike[str], template: Any, *, max_distance: float | None = None
) -> TemplateLandmarks:
    """Read landmarks and attach them to the template surface.

    A CSV with columns ``label,vertex`` gives template vertices; ``label,triangle,b0,b1,b2``
    gives triangles and barycentric coordinates; positions (``label,l,p,s`` CSV, Slicer
    ``.mrk.json`` / ``.fcsv``, MeshLab ``.pp``: see :func:`~o3dreg.read_landmarks`, which
    converts them to LPS, the template's system) are mapped to the nearest template surface
    point (see :meth:`TemplateLandmarks.from_points`).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_landmark_suffix(path, "path")
    if suffix == ".csv":
        if not os.path.isfile(path):
            raise OSError(f"`path`: no such file {path!r}")
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        if rows:
            keys = {k.strip().lower() for k in rows[0] if k}
            lab = [str(r.get("label") or f"L{k + 1}").strip() for k, r in enumerate(rows)]
            try:
                if "vertex" in keys:
                    idx = np.array([int(r["vertex"]) for r in rows])
                    return TemplateLandmarks.from_vertices(template, idx, lab)
                if {"triangle", "b0", "b1", "b2"} <= keys:
                    tri = np.array([int(r["triangle"]) for r in rows])
                    bary = np.array([[float(r[c]) for c in ("b0", "b1", "b2")] for r in rows])
                    return TemplateLandmarks.from_barycentric(template, tri, bary, lab)
            except (TypeError, ValueError, KeyError) as exc:
                if isinstance(exc, ValueError) and "template" in str(exc):
                    raise
                raise ValueError(f"`path`: {path!r} has malformed landmark rows: {exc}") from exc
    labels, points = read_landmarks(path)
    return TemplateLandmarks.from_points(template, points, labels, max_distance=max_distance)


# -- prediction -------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LandmarkPrediction:
    """Landmarks predicted on a patient by fitting a shape model.

    Attributes
    ----------
    labels : tuple of str
    positions : (l, 3) ndarray
        In patient coordinates.
    fit : ModelFit
        The fitted model instance (pose, coefficients, distances).
    """

    labels: tuple[str, ...]
    positions: np.ndarray = field(repr=False)
    fit: Any

    def __repr__(self) -> str:
        return f"LandmarkPrediction({len(self.labels)} landmarks, fit={self.fit!r})"

    def as_dict(self) -> dict[str, list[float]]:
        return {label: [float(c) for c in p] for label, p in zip(self.labels, self.positions)}


def predict_landmarks(
    model: Any, landmarks: TemplateLandmarks, target: Any, **fit_options: Any
) -> LandmarkPrediction:
    """Predict template landmarks on a new patient: fit ``model`` to its surface, read them off.

    Parameters
    ----------
    model : ShapeModel
        Built on the template the landmarks were defined on.
    landmarks : TemplateLandmarks
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface.
    **fit_options
        Passed to :func:`~o3dreg.fit_shape_model` (``init``, ``number_of_modes``,
        ``regularization``, ``max_iteration``, ``tolerance``).

    Returns
    -------
    LandmarkPrediction
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    if not isinstance(landmarks, TemplateLandmarks):
        raise TypeError(f"`landmarks` must be TemplateLandmarks, got {type(landmarks).__name__}")
    if landmarks.number_of_vertices != model.number_of_points or not np.array_equal(
        landmarks.faces, model.faces
    ):
        raise ValueError(
            "`landmarks` were defined on another template than the model's "
            f"({landmarks.number_of_vertices} vs {model.number_of_points} vertices)"
        )
    fit = fit_shape_model(model, target, **fit_options)
    return LandmarkPrediction(landmarks.labels, landmarks.positions(fit.vertices), fit)


def landmark_errors(predicted: Any, truth: Any) -> np.ndarray:
    """Euclidean distance between predicted and true landmark positions, ``(l,)``."""
    p = as_points(predicted, "predicted")
    t = as_points(truth, "truth")
    if p.shape != t.shape:
        raise ValueError(
            f"`predicted` and `truth` must have the same shape, got {p.shape} and {t.shape}"
        )
    return np.linalg.norm(p - t, axis=1)
