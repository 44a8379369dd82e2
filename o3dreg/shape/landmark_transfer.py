"""Anatomical landmarks defined on the template and carried to every patient.

A landmark is attached to a template triangle: the triangle index, the barycentric coordinates
of its foot point on that triangle, and its offset from the foot point in the local frame there
(two tangent directions and the surface normal). It therefore has a position on *any* mesh with
the template's triangulation: each registered patient's semilandmark mesh, the model mean, a
fitted model instance. A landmark inside the bone (annotations placed on voxel centres lie
0.5-4 mm below a marching-cubes surface) keeps its depth; a landmark on the surface has a zero
offset. Landmarks are read from CSV, 3D Slicer markups (``.mrk.json``, ``.fcsv``) or MeshLab
picked points (``.pp``) by :func:`o3dreg.read_landmarks` (converted to LPS, the
meshes' system).

The offset is measured in the template's size (the RMS distance of its vertices from their
centroid) and rotates with the local frame, so a rigid motion or a uniform scaling of the mesh
carries the landmark exactly, and the identity leaves it where it was given.
"""

from __future__ import annotations

import csv
import inspect
import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._geometry import barycentric
from .._validation import (
    as_faces,
    as_mesh_arrays,
    as_points,
    check_bool,
    check_positive,
    check_referenced,
)
from ..io.landmark_files import (
    check_landmark_suffix,
    read_landmarks,
    select_labels,
    write_landmarks,
)
from ..registration.distance import SurfaceDistanceQuery
from ..registration.elastic import registration_elastic
from ..registration.options import default_levels
from ..registration.verdict import worst_status
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

#: Landmarks farther from a surface than this fraction of its bounding-box diagonal are not on
#: the anatomy it shows (refused by :meth:`TemplateLandmarks.from_points`; named by ``o3dreg
#: register --landmarks``, where they still steer the start).
LANDMARK_REACH = 0.05


class OffTemplateError(ValueError):
    """Landmarks too far from the template surface (:meth:`TemplateLandmarks.from_points`).

    Attributes
    ----------
    far : tuple of str
        The labels of the landmarks off the template, in the order given.
    distances : tuple of float
        Their distances from the template surface.
    near : tuple of str
        The labels of the others (on the template), in the order given.
    max_distance : float
        The distance they were refused beyond.
    """

    def __init__(
        self,
        message: str,
        far: tuple[str, ...],
        distances: tuple[float, ...],
        near: tuple[str, ...],
        max_distance: float,
    ) -> None:
        super().__init__(message)
        self.far = far
        self.distances = distances
        self.near = near
        self.max_distance = max_distance


@dataclass(frozen=True, eq=False)
class TemplateLandmarks:
    """Landmarks attached to the template surface.

    Attributes
    ----------
    labels : tuple of str
    triangles : (l,) int ndarray
        Template triangle holding each landmark.
    barycentric : (l, 3) ndarray
        Barycentric coordinates in that triangle (non-negative, summing to 1) of each
        landmark's foot point.
    faces : (m, 3) int ndarray
        The template's triangles.
    number_of_vertices : int
        Vertex count of the template (meshes evaluated must have it).
    offsets : (l, 3) ndarray or None
        Each landmark's offset from its foot point in the local frame there (first tangent,
        second tangent, outward normal; see :meth:`frames`), in units of :attr:`size`: a
        landmark 2 mm inside a template of size 40 mm has ``offsets[:, 2] = -0.05``. ``None``:
        every landmark on the surface.
    size : float
        The template's size (RMS distance of its vertices from their centroid) the offsets are
        measured in; a mesh of another size scales them by its own.
    """

    labels: tuple[str, ...]
    triangles: np.ndarray = field(repr=False)
    barycentric: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    number_of_vertices: int = 0
    offsets: np.ndarray | None = field(default=None, repr=False)
    size: float = 1.0

    def __post_init__(self) -> None:
        # The constructor is public: a landmark that names no triangle, or a point outside its
        # triangle, would surface as an IndexError or NaN far from here.
        count = self.number_of_vertices
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 3:
            raise ValueError(f"`number_of_vertices` must be an integer >= 3, got {count!r}")
        faces = as_faces(self.faces, int(count), "faces")
        if isinstance(self.labels, str):
            raise TypeError("`labels` must be a sequence of labels, got a str")
        labels = _labels(self.labels, len(self.labels))
        n = len(labels)
        tri = _template_indices(self.triangles, faces.shape[0], "triangles")
        if tri.size != n:
            raise ValueError(f"`triangles` must hold one triangle per label ({n}), got {tri.size}")
        bary = _barycentric_rows(self.barycentric, n)
        offsets = self.offsets
        if offsets is not None:
            offsets = np.array(offsets, dtype=np.float64)
            if offsets.shape != (n, 3) or not np.isfinite(offsets).all():
                raise ValueError(
                    f"`offsets` must be None or {n} finite rows of 3, got shape {offsets.shape}"
                )
        size = check_positive(self.size, "size")
        for name, value in (
            ("labels", labels),
            ("triangles", tri.astype(np.int64)),
            ("barycentric", bary),
            ("faces", faces),
            ("number_of_vertices", int(count)),
            ("offsets", offsets),
            ("size", size),
        ):
            object.__setattr__(self, name, value)

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
        idx = _template_indices(indices, v.shape[0], "indices")
        if idx.size == 0:  # as from_points: landmarks are asked for, none is an error
            raise ValueError("`indices` must hold at least one vertex, got none")
        labels_ = _labels(labels, idx.size)
        tri = np.empty(idx.size, dtype=np.int64)
        bary = np.zeros((idx.size, 3))
        for k, i in enumerate(idx):
            rows, cols = np.nonzero(f == i)
            if rows.size == 0:
                raise ValueError(f"`indices[{k}]` = {int(i)} is a vertex on no template triangle")
            tri[k] = rows[0]
            bary[k, cols[0]] = 1.0
        return cls(labels_, tri, bary, f, v.shape[0], None, mesh_size(v))

    @classmethod
    def from_barycentric(
        cls, template: Any, triangles: Any, barycentric: Any, labels: Any = None
    ) -> TemplateLandmarks:
        """Landmarks given by triangle index and barycentric coordinates (checked)."""
        v, f = as_mesh_arrays(template, "template")
        tri = _template_indices(triangles, f.shape[0], "triangles")
        if tri.size == 0:
            raise ValueError("`triangles` must hold at least one triangle, got none")
        bary = _barycentric_rows(barycentric, tri.size)
        return cls(_labels(labels, tri.size), tri, bary, f, v.shape[0], None, mesh_size(v))

    @classmethod
    def from_points(
        cls,
        template: Any,
        points: Any,
        labels: Any = None,
        *,
        max_distance: float | None = None,
        on_surface: bool = False,
    ) -> TemplateLandmarks:
        """Landmarks at given positions (e.g. Slicer markups), attached to the template surface.

        Each point is attached to the template triangle holding its nearest surface point (the
        foot point) and keeps its offset from it: :meth:`positions` on the template returns
        ``points`` (to rounding), on a registered or fitted mesh the point at the same depth.

        Parameters
        ----------
        template : open3d.geometry.TriangleMesh or (vertices, faces)
        points : (l, 3) array_like
            Positions in template coordinates. Not modified.
        labels : sequence of str, optional
        max_distance : float, optional
            Points farther than this from the template surface raise
            :class:`OffTemplateError` (a ``ValueError`` naming them: landmarks outside the
            template). Default :data:`LANDMARK_REACH` (5 %) of the template's bounding-box
            diagonal.
        on_surface : bool, optional
            Move each landmark onto its foot point (offset 0). Default ``False``: landmarks
            keep their depth.
        """
        v, f = as_mesh_arrays(template, "template")
        pts = as_points(points, "points")
        on_surface = check_bool(on_surface, "on_surface")
        if max_distance is None:
            max_distance = LANDMARK_REACH * float(np.linalg.norm(np.ptp(v, axis=0)))
        else:
            max_distance = check_positive(max_distance, "max_distance", allow_zero=True)
        dist, face, closest = SurfaceDistanceQuery(v, f).closest(pts)
        far = dist > max_distance
        labels_ = _labels(labels, pts.shape[0])
        if far.any():
            which = ", ".join(f"{labels_[i]} ({dist[i]:.3g})" for i in np.flatnonzero(far))
            raise OffTemplateError(
                f"`points` must lie within {max_distance:.3g} of the template surface "
                f"(landmarks outside the template): {which}",
                tuple(labels_[i] for i in np.flatnonzero(far)),
                tuple(float(dist[i]) for i in np.flatnonzero(far)),
                tuple(labels_[i] for i in np.flatnonzero(~far)),
                float(max_distance),
            )
        tri = face.astype(np.int64)
        bary = barycentric(v[f[tri]], closest)
        if on_surface:
            return cls(labels_, tri, bary, f, v.shape[0], None, mesh_size(v))
        plain = cls(labels_, tri, bary, f, v.shape[0], None, mesh_size(v))
        foot, frames = plain.frames(v)
        # The offset in the frame's axes (rows of ``frames``), in units of the template's size.
        local = np.einsum("lad,ld->la", frames, pts - foot) / plain.size
        return cls(labels_, tri, bary, f, v.shape[0], local, plain.size)

    def frames(self, vertices: Any) -> tuple[np.ndarray, np.ndarray]:
        """Foot points and local frames of the landmarks on a mesh with the template's triangles.

        Parameters
        ----------
        vertices : (n, 3) array_like or open3d.geometry.TriangleMesh
            The mesh's vertices. Not modified.

        Returns
        -------
        feet : (l, 3) ndarray
            The points of the landmarks' triangles at their barycentric coordinates.
        frames : (l, 3, 3) ndarray
            Orthonormal rows per landmark: the first tangent (the triangle's first edge, made
            orthogonal to the normal), the second tangent, and the outward normal (the
            barycentric blend of the area-weighted vertex normals; the triangle's own normal
            where that blend vanishes). A rigid motion of the mesh rotates the frames with it.
        """
        v = self._vertices(vertices)
        corners = v[self.faces[self.triangles]]  # (l, 3, 3)
        feet = np.einsum("lk,lkd->ld", self.barycentric, corners)
        cross = np.cross(
            v[self.faces[:, 1]] - v[self.faces[:, 0]], v[self.faces[:, 2]] - v[self.faces[:, 0]]
        )
        vertex_normals = np.zeros_like(v)
        for k in range(3):
            np.add.at(vertex_normals, self.faces[:, k], cross)
        normal = np.einsum(
            "lk,lkd->ld", self.barycentric, vertex_normals[self.faces[self.triangles]]
        )
        own = cross[self.triangles]
        length = np.linalg.norm(normal, axis=1)
        flat = length <= 1e-12 * np.maximum(np.linalg.norm(own, axis=1), 1e-300)
        normal[flat] = own[flat]
        normal = normal / np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
        edge = corners[:, 1] - corners[:, 0]
        first = edge - (edge * normal).sum(axis=1)[:, None] * normal
        first = first / np.maximum(np.linalg.norm(first, axis=1), 1e-300)[:, None]
        second = np.cross(normal, first)
        return feet, np.stack([first, second, normal], axis=1)

    def _vertices(self, vertices: Any) -> np.ndarray:
        v = as_points(vertices, "vertices")
        if v.shape[0] != self.number_of_vertices:
            raise ValueError(
                f"`vertices` must have the template's {self.number_of_vertices} vertices, "
                f"got {v.shape[0]}"
            )
        return v

    @property
    def depths(self) -> np.ndarray:
        """Signed distance of each landmark along the template's outward normal at its foot
        point, in the template's units (negative: inside), ``(l,)``."""
        if self.offsets is None:
            return np.zeros(len(self.labels))
        return self.offsets[:, 2] * self.size

    def positions(self, vertices: Any) -> np.ndarray:
        """Landmark positions on a mesh with the template's triangulation, ``(l, 3)``.

        The foot point at the landmark's barycentric coordinates, plus its offset in the local
        frame there (:meth:`frames`), scaled by the mesh's size relative to the template's.

        Parameters
        ----------
        vertices : (n, 3) array_like or open3d.geometry.TriangleMesh
            Vertices of the template, of a registered patient's semilandmark mesh, of the model
            mean or of a fitted instance. Not modified.
        """
        v = self._vertices(vertices)
        if self.offsets is None or not self.offsets.any():
            corners = v[self.faces[self.triangles]]  # (l, 3, 3)
            return np.einsum("lk,lkd->ld", self.barycentric, corners)
        feet, frames = self.frames(v)
        return feet + mesh_size(v) * np.einsum("la,lad->ld", self.offsets, frames)

    def on_surface(self) -> TemplateLandmarks:
        """The same landmarks moved onto their foot points (zero offsets)."""
        return TemplateLandmarks(
            self.labels,
            self.triangles,
            self.barycentric,
            self.faces,
            self.number_of_vertices,
            None,
            self.size,
        )

    def carry(self, shapes: Any) -> np.ndarray:
        """Positions on every shape of a batch: ``(s, l, 3)`` for ``(s, n, 3)`` shapes."""
        return np.stack([self.positions(s) for s in shapes])

    @classmethod
    def from_annotated_shapes(
        cls,
        template: Any,
        shapes: Any,
        points: Any,
        labels: Any = None,
        *,
        max_distance: float | None = None,
    ) -> TemplateLandmarks:
        """Landmarks of the template from the annotations of several registered patients.

        Each patient's annotation is attached to its semilandmark mesh (the template's triangles
        on the patient, e.g. a registration's ``result.vertices``) as :meth:`from_points` does,
        read back on the template (same triangle, barycentric coordinates and local offset),
        and the template positions are averaged over the patients. One annotator's placement
        error on one patient then weighs ``1 / s``: the landmarks a shape model built from the
        same patients predicts best on average.

        Parameters
        ----------
        template : open3d.geometry.TriangleMesh or (vertices, faces)
        shapes : (s, n, 3) array_like or sequence of (n, 3) array_like
            The patients' semilandmark meshes' vertices, in each patient's coordinates.
        points : (s, l, 3) array_like
            Each patient's annotation of the same ``l`` landmarks, in its coordinates.
        labels : sequence of str, optional
        max_distance : float, optional
            As in :meth:`from_points`, for each patient's annotation and its mesh, and for the
            averaged positions and the template.

        Returns
        -------
        TemplateLandmarks
            Attached to the template with their (averaged) offsets.
        """
        v, f = as_mesh_arrays(template, "template")
        x = np.asarray(shapes, dtype=np.float64)
        if x.ndim != 3 or x.shape[1:] != v.shape or x.shape[0] < 1:
            raise ValueError(
                f"`shapes` must be (s, {v.shape[0]}, 3) semilandmark meshes of the template, "
                f"got shape {x.shape}"
            )
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 3 or pts.shape[0] != x.shape[0] or pts.shape[2] != 3:
            raise ValueError(
                f"`points` must be ({x.shape[0]}, l, 3): one annotation per shape, got {pts.shape}"
            )
        if not (np.isfinite(x).all() and np.isfinite(pts).all()):
            raise ValueError("`shapes` and `points` must be finite")
        back = np.stack(
            [
                cls.from_points(
                    (shape, f), annotation, labels, max_distance=max_distance
                ).positions(v)
                for shape, annotation in zip(x, pts)
            ]
        )
        return cls.from_points((v, f), back.mean(axis=0), labels, max_distance=max_distance)


def mesh_size(vertices: np.ndarray) -> float:
    """RMS distance of ``vertices (n, 3)`` from their centroid (1 for a single point)."""
    size = float(np.sqrt(((vertices - vertices.mean(axis=0)) ** 2).sum(axis=1).mean()))
    return size if size > 0 else 1.0


def _labels(labels: Any, count: int) -> tuple[str, ...]:
    if labels is None:
        return tuple(f"L{i + 1}" for i in range(count))
    out = tuple(str(x) for x in labels)
    if len(out) != count:
        raise ValueError(f"`labels` must hold {count} labels, got {len(out)}")
    repeated = _repeated(out)
    if repeated:
        raise ValueError(f"`labels` repeats landmark labels {repeated}")
    return out


def _template_indices(values: Any, count: int, name: str) -> np.ndarray:
    """``values`` checked as a 1-D array of indices of the template's ``count`` vertices or
    triangles (``name``: which, as the parameter is called), as int64."""
    idx = np.asarray(values)
    if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
        raise TypeError(f"`{name}` must be a 1-D array of integers, got {idx.dtype} {idx.shape}")
    bad = (idx < 0) | (idx >= count)
    if bad.any():
        what = "vertices" if name == "indices" else name
        raise ValueError(
            f"`{name}` must be template {what} in [0, {count - 1}], got {idx[bad].tolist()} "
            "(landmarks outside the template)"
        )
    return idx.astype(np.int64)


def _barycentric_rows(barycentric: Any, count: int) -> np.ndarray:
    """``count`` rows of barycentric coordinates of points inside their triangles, checked."""
    bary = np.array(barycentric, dtype=np.float64)
    if bary.shape != (count, 3):
        raise ValueError(f"`barycentric` must have shape ({count}, 3), got {bary.shape}")
    off = (
        ~np.isfinite(bary).all(axis=1)
        | (bary.min(axis=1, initial=0.0) < -1e-6)
        | (np.abs(bary.sum(axis=1) - 1.0) > 1e-6)
    )
    if off.any():
        raise ValueError(
            "`barycentric` rows must be finite, >= 0 and sum to 1 (a point inside its "
            f"triangle), got {bary[off].tolist()} (landmarks outside the template)"
        )
    return bary


def _repeated(labels: tuple[str, ...]) -> list[str]:
    """The labels that occur more than once (a prediction or an error per label is then
    ambiguous)."""
    return sorted({lab for lab in labels if labels.count(lab) > 1})


# -- files ------------------------------------------------------------------------------------------
def load_template_landmarks(
    path: str | os.PathLike[str],
    template: Any,
    *,
    labels: Any = None,
    max_distance: float | None = None,
    on_surface: bool = False,
) -> TemplateLandmarks:
    """Read landmarks and attach them to the template surface.

    A CSV with columns ``label,vertex`` gives template vertices; ``label,triangle,b0,b1,b2``
    gives triangles and barycentric coordinates; positions (``label,l,p,s`` CSV, Slicer
    ``.mrk.json`` / ``.fcsv``, MeshLab ``.pp``: see :func:`~o3dreg.read_landmarks`, which
    converts them to LPS, the template's system) are attached to the nearest template surface
    point and keep their offset from it, unless ``on_surface`` (see
    :meth:`TemplateLandmarks.from_points`).

    Parameters
    ----------
    path : str or path-like
        The landmark file.
    template : open3d.geometry.TriangleMesh or (vertices, faces)
        The surface the landmarks are placed on. Not modified.
    labels : sequence of str, optional
        The file's landmarks to use, in this order (e.g. ``['chin', 'mand_r', 'mand_l']``
        from a file that also holds landmarks off the template's anatomy). Default: every
        landmark of the file, in its order.
    max_distance : float, optional
        As in :meth:`TemplateLandmarks.from_points`, for positions.
    on_surface : bool, optional
        As in :meth:`TemplateLandmarks.from_points`, for positions.

    Returns
    -------
    TemplateLandmarks
        The chosen landmarks, labelled as in the file.

    Raises
    ------
    OffTemplateError
        A ``ValueError``: positions farther than ``max_distance`` from the template surface,
        named, with the ``labels`` of the others to choose.
    ValueError
        A label of ``labels`` the file does not hold (naming the file's labels), repeated
        labels, or malformed rows.

    Examples
    --------
    A file with a landmark off the template (``far``), the others chosen:

    >>> import os, tempfile
    >>> import numpy as np
    >>> from o3dreg import load_template_landmarks, write_landmarks
    >>> template = (np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]]), np.array([[0, 1, 2]]))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = os.path.join(folder, "lm.csv")
    ...     _ = write_landmarks(path, ["a", "far", "b"], [[1, 1, 0], [0, 0, 90], [5, 2, 0]])
    ...     load_template_landmarks(path, template, labels=["b", "a"]).labels
    ('b', 'a')
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_landmark_suffix(path, "path")
    if suffix == ".csv":
        if not os.path.isfile(path):
            raise OSError(f"`path`: no such file {path!r}")
        try:
            with open(path, newline="", encoding="utf-8-sig") as fh:
                # Column names as written by people: any case, spaces around them.
                rows = [
                    {k.strip().lower(): v for k, v in r.items() if isinstance(k, str)}
                    for r in csv.DictReader(fh)
                ]
        except UnicodeDecodeError as exc:
            raise ValueError(
                f"`path`: {path!r} is not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
                f"{exc.start}): save it as UTF-8"
            ) from None
        keys = set(rows[0]) if rows else set()
        if "vertex" in keys or {"triangle", "b0", "b1", "b2"} <= keys:
            lab = [str(r.get("label") or "").strip() or f"L{k + 1}" for k, r in enumerate(rows)]
            repeated = _repeated(tuple(lab)) if labels is None else []
            if repeated:
                raise ValueError(f"`path`: {path!r} repeats landmark labels {repeated}")
            chosen = select_labels(lab, labels, repr(path))
            rows, lab = [rows[k] for k in chosen], [lab[k] for k in chosen]
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
    available, points = read_landmarks(path)
    repeated = _repeated(tuple(available)) if labels is None else []
    if repeated:
        raise ValueError(f"`path`: {path!r} repeats landmark labels {repeated}")
    chosen = select_labels(available, labels, repr(path))
    try:
        return TemplateLandmarks.from_points(
            template,
            points[chosen],
            [available[k] for k in chosen],
            max_distance=max_distance,
            on_surface=on_surface,
        )
    except OffTemplateError as exc:
        hint = (
            f"; choose the landmarks on the template with `labels` (labels={list(exc.near)})"
            if exc.near
            else "; none lies on it: are the landmarks placed on this template, in its frame?"
        )
        raise OffTemplateError(
            f"`path`: {path!r}: {exc}{hint}", exc.far, exc.distances, exc.near, exc.max_distance
        ) from None


# -- prediction -------------------------------------------------------------------------------------
#: How :func:`predict_landmarks` brings the fitted instance onto the patient surface.
PREDICTION_ONTO = ("registration", "closest")

#: The registration of a fitted instance onto its patient starts at the default level of this
#: many cells: the fit has placed the instance already, and the coarse levels' barycentre term
#: at full weight would slide its vertices along smooth parts of the surface (on the synthetic
#: population of the tests, 1.1 mm of drift against 0.2 mm from 8 cells on; on CT mandibles the
#: two give the same landmarks, docs/shape-model.md).
PREDICTION_FIRST_RESOLUTION = 8


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
    vertices : (n, 3) ndarray
        The mesh the landmarks were read from, with the model's triangles: the fitted instance
        brought onto the patient surface (``on_target=True``), or the instance itself.
    registration : ElasticRegistrationResult or None
        The elastic registration of the fitted instance onto the patient surface
        (``onto='registration'``), ``None`` otherwise.
    """

    labels: tuple[str, ...]
    positions: np.ndarray = field(repr=False)
    fit: Any
    vertices: np.ndarray = field(repr=False)
    registration: Any = field(default=None, repr=False)

    @property
    def status(self) -> str:
        """The worse of the fit's verdict and the registration's (``'ok'``, ``'suspect'``,
        ``'failed'``)."""
        found = [self.fit.status]
        if self.registration is not None:
            found.append(self.registration.status)
        return worst_status(*found)

    @property
    def warnings(self) -> tuple[str, ...]:
        """The fit's warnings, then the registration's (prefixed ``registration:``)."""
        extra = () if self.registration is None else self.registration.warnings
        return tuple(self.fit.warnings) + tuple(f"registration: {w}" for w in extra)

    def __repr__(self) -> str:
        return (
            f"LandmarkPrediction({len(self.labels)} landmarks, status={self.status!r}, "
            f"fit={self.fit!r})"
        )

    def as_dict(self) -> dict[str, list[float]]:
        return {label: [float(c) for c in p] for label, p in zip(self.labels, self.positions)}


def predict_landmarks(
    model: Any,
    landmarks: TemplateLandmarks,
    target: Any,
    *,
    on_target: bool = True,
    onto: str = "registration",
    registration_options: dict[str, Any] | None = None,
    **fit_options: Any,
) -> LandmarkPrediction:
    """Predict template landmarks on a new patient: fit ``model`` to its surface, read them off.

    The model is fitted to the patient (:func:`~o3dreg.fit_shape_model`): it says where on the
    bone each vertex lies, but a model of a few patients fits a new bone only to a millimetre or
    two. With ``on_target`` (default) the fitted instance is then brought onto the patient's
    own surface, by ``onto``:

    * ``'registration'`` (default): an elastic registration of the instance onto the surface
      (:func:`~o3dreg.registration_elastic` from where the fit left it: ``init`` the identity,
      the default levels from :data:`PREDICTION_FIRST_RESOLUTION` cells on), a smooth map of
      space: neighbouring vertices move together, so what the model could not
      express is fitted as in a registration of the template, with the model's instance as the
      start;
    * ``'closest'``: every vertex to its closest surface point, independently (a vertex off a
      ridge can land on its other side).

    The landmarks are read on that mesh as :meth:`TemplateLandmarks.positions` does: each at its
    barycentric point plus its offset in the local frame there, so a landmark defined inside
    the bone is predicted inside the patient's bone at the same depth (scaled with the mesh's
    size). Nothing is moved onto the surface unless the landmarks were made so
    (``on_surface``). docs/shape-model.md compares the readings on CT mandibles.

    Parameters
    ----------
    model : ShapeModel
        Built on the template the landmarks were defined on.
    landmarks : TemplateLandmarks
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface.
    on_target : bool, optional
        Read the landmarks on the fitted instance brought onto the patient surface (default),
        or on the instance itself (``False``: the model's shape alone).
    onto : {'registration', 'closest'}, optional
        How the instance is brought onto the surface (see above); ignored without
        ``on_target``.
    registration_options : dict, optional
        Keyword arguments of :func:`~o3dreg.registration_elastic` for ``onto='registration'``
        (``levels``, ``estimation_method``, ``criteria``...; ``init`` defaults to the identity,
        ``levels`` to the default levels from :data:`PREDICTION_FIRST_RESOLUTION` cells on).
    **fit_options
        Passed to :func:`~o3dreg.fit_shape_model` (``init``, ``number_of_modes``,
        ``regularization``, ``max_iteration``, ``tolerance``, ``check_reflection``).

    Returns
    -------
    LandmarkPrediction
        Its ``status`` is the worse of the fit's verdict and the registration's.
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
    on_target = check_bool(on_target, "on_target")
    if onto not in PREDICTION_ONTO:
        raise ValueError(f"`onto` must be one of {PREDICTION_ONTO}, got {onto!r}")
    if not isinstance(registration_options, (dict, type(None))):
        raise TypeError(
            "`registration_options` must be a dict of registration_elastic keyword arguments, "
            f"got {type(registration_options).__name__}"
        )
    options = dict(registration_options or {})
    # Checked before the fit: a misspelt option would otherwise surface only after it.
    unknown = sorted(set(options) - _REGISTRATION_KEYWORDS)
    if unknown:
        raise TypeError(
            f"`registration_options` must be keyword arguments of registration_elastic, got "
            f"{', '.join(map(repr, unknown))}"
        )
    if on_target and onto == "registration":
        # The instance has the model's triangles: a mesh the registration refuses is refused
        # here, before the fit.
        _check_registrable(model.mean, model.faces)
    fit = fit_shape_model(model, target, **fit_options)
    vertices = np.array(fit.vertices)
    registration = None
    if on_target and onto == "closest":
        vt, ft = as_mesh_arrays(target, "target", drop_degenerate=True)
        vertices = SurfaceDistanceQuery(vt, ft).closest(vertices)[2]
    elif on_target:
        options.setdefault("init", np.eye(4))
        if options.get("levels") is None:
            options["levels"] = [
                lev
                for lev in default_levels(vertices)
                if lev.resolution >= PREDICTION_FIRST_RESOLUTION
            ]
        registration = registration_elastic((vertices, model.faces), target, **options)
        vertices = np.array(registration.vertices)
    return LandmarkPrediction(
        landmarks.labels, landmarks.positions(vertices), fit, vertices, registration
    )


#: The keyword arguments :func:`predict_landmarks` passes on to the registration.
_REGISTRATION_KEYWORDS = frozenset(
    name
    for name, p in inspect.signature(registration_elastic).parameters.items()
    if p.kind is inspect.Parameter.KEYWORD_ONLY
)


def _check_registrable(vertices: np.ndarray, faces: np.ndarray) -> None:
    """Refuse a model whose instances cannot be a registration's template (a model read from
    another tool may hold degenerate triangles or vertices of no triangle)."""
    try:
        v, f = as_mesh_arrays((vertices, faces), "the model's mesh")
        check_referenced(v, f, "the model's mesh")
    except ValueError as exc:
        raise ValueError(
            f"`onto='registration'` registers the model's fitted instance onto the patient, and "
            f"{exc}; "
            "read the landmarks on its closest points instead (onto='closest')"
        ) from exc


def landmark_errors(predicted: Any, truth: Any) -> np.ndarray:
    """Euclidean distance between predicted and true landmark positions, ``(l,)``."""
    p = as_points(predicted, "predicted")
    t = as_points(truth, "truth")
    if p.shape != t.shape:
        raise ValueError(
            f"`predicted` and `truth` must have the same shape, got {p.shape} and {t.shape}"
        )
    return np.linalg.norm(p - t, axis=1)
