"""Point distribution (statistical shape) models of semilandmark meshes: ``P = M + A alpha``.

Berar et al. (2005), section 3.3: the registered template meshes (same vertices, same triangles
for every patient) are aligned by Procrustes analysis, then a principal component analysis gives
the mean shape ``M``, the modes ``A`` and their variances (the paper's Table 4); a new shape is
synthesised as ``P = M + A alpha`` (eq. 4).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation, barycentric
from .._validation import as_mesh_arrays, as_points, as_transformation, check_positive
from ..io.archive import read_archive, write_archive
from ..io.mesh import to_open3d, write_triangle_mesh
from .procrustes import _fit, _generalized_procrustes, as_shape_array

__all__ = [
    "ModelFit",
    "ShapeModel",
    "ShapeProjection",
    "build_shape_model",
    "fit_shape_model",
]

logger = logging.getLogger("o3dreg")

_FORMAT = "o3dreg.ShapeModel"
_VERSION = 1


@dataclass(frozen=True, eq=False)
class ShapeProjection:
    """A shape expressed in a :class:`ShapeModel` (see :meth:`ShapeModel.project`).

    Attributes
    ----------
    coefficients : (k,) ndarray
        ``alpha`` of eq. (4), in the input's units (the modes are orthonormal).
    transformation : (4, 4) ndarray
        Maps the given shape into the model frame (the pose removed).
    reconstruction : (n, 3) ndarray
        ``M + A alpha``, in the model frame.
    residual : (n, 3) ndarray
        Aligned shape minus reconstruction (what the model cannot represent).
    """

    coefficients: np.ndarray
    transformation: np.ndarray = field(repr=False)
    reconstruction: np.ndarray = field(repr=False)
    residual: np.ndarray = field(repr=False)

    @property
    def mean_error(self) -> float:
        """Mean per-point distance between the aligned shape and its reconstruction."""
        return float(np.linalg.norm(self.residual, axis=1).mean())

    def __repr__(self) -> str:
        return f"ShapeProjection(modes={self.coefficients.size}, mean_error={self.mean_error:.4g})"


@dataclass(frozen=True, eq=False)
class ShapeModel:
    """A linear statistical shape model ``P = M + A alpha`` on a fixed template triangulation.

    Attributes
    ----------
    mean : (n, 3) ndarray
        ``M``, the Procrustes mean (centred at the origin), in the input's units (mm).
    modes : (k, n, 3) ndarray
        ``A``: orthonormal principal directions (each mode has unit norm as a ``3n`` vector).
    variances : (k,) ndarray
        Variance of the training shapes along each mode (sample variance, ``1/(s - 1)``),
        decreasing.
    faces : (m, 3) int ndarray
        The template's triangles (identical for every shape of the model).
    total_variance : float
        Total variance of the training shapes (sum of all PCA variances, including modes
        dropped by ``number_of_modes``): the denominator of the explained-variance ratios.
    scores : (s, k) ndarray
        Coefficients ``alpha`` of the training shapes.
    names : tuple of str
        Names of the training shapes.
    scaling : bool
        ``True`` when the Procrustes alignment removed size (similarity), ``False`` when rigid.
    noise_variance : float
        Variance per coordinate of what the model does not explain (0 for a plain PCA model);
        the default regularisation of :func:`fit_shape_model`.

    Notes
    -----
    With ``s`` training shapes there are at most ``s - 1`` modes: the centred data span at most
    ``s - 1`` dimensions.
    """

    mean: np.ndarray = field(repr=False)
    modes: np.ndarray = field(repr=False)
    variances: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    total_variance: float = field(repr=False)
    scores: np.ndarray = field(repr=False)
    names: tuple[str, ...] = field(default=(), repr=False)
    scaling: bool = False
    noise_variance: float = 0.0

    def __post_init__(self) -> None:
        mean = as_points(self.mean, "mean")
        n = mean.shape[0]
        modes = np.array(self.modes, dtype=np.float64)
        if modes.ndim != 3 or modes.shape[1:] != (n, 3):
            raise ValueError(f"`modes` must have shape (k, {n}, 3), got {modes.shape}")
        variances = np.array(self.variances, dtype=np.float64).reshape(-1)
        if variances.shape != (modes.shape[0],):
            raise ValueError(
                f"`variances` must have shape ({modes.shape[0]},), got {variances.shape}"
            )
        if np.any(variances < 0) or not np.all(np.isfinite(variances)):
            raise ValueError("`variances` must be finite and >= 0")
        _, faces = as_mesh_arrays((mean, self.faces), "faces", min_faces=1, drop_degenerate=True)
        faces = np.array(self.faces, dtype=np.int64).reshape(-1, 3)
        scores = np.array(self.scores, dtype=np.float64)
        if scores.ndim != 2 or scores.shape[1] != modes.shape[0]:
            raise ValueError(f"`scores` must have shape (s, {modes.shape[0]}), got {scores.shape}")
        names = tuple(str(x) for x in self.names) or tuple(
            f"shape{i:03d}" for i in range(scores.shape[0])
        )
        if len(names) != scores.shape[0]:
            raise ValueError(f"`names` must hold {scores.shape[0]} names, got {len(names)}")
        for attr, value in (
            ("mean", mean),
            ("modes", modes),
            ("variances", variances),
            ("faces", faces),
            ("scores", scores),
            ("names", names),
            ("total_variance", float(self.total_variance)),
            ("noise_variance", float(self.noise_variance)),
        ):
            object.__setattr__(self, attr, value)
        for arr in (mean, modes, variances, faces, scores):
            arr.setflags(write=False)

    def __repr__(self) -> str:
        ratios = ", ".join(f"{100 * r:.1f}%" for r in self.explained_variance_ratio[:5])
        return (
            f"ShapeModel(points={self.number_of_points}, modes={self.number_of_modes}, "
            f"shapes={self.number_of_shapes}, explained=[{ratios}])"
        )

    # -- sizes and variances ----------------------------------------------------------------------
    @property
    def number_of_points(self) -> int:
        return int(self.mean.shape[0])

    @property
    def number_of_modes(self) -> int:
        return int(self.modes.shape[0])

    @property
    def number_of_shapes(self) -> int:
        return int(self.scores.shape[0])

    @property
    def standard_deviations(self) -> np.ndarray:
        """``sqrt(variances)``, ``(k,)``."""
        return np.sqrt(self.variances)

    @property
    def explained_variance_ratio(self) -> np.ndarray:
        """Fraction of the total variance explained by each mode, ``(k,)`` (Table 4, row 1)."""
        total = self.total_variance if self.total_variance > 0 else 1.0
        return self.variances / total

    @property
    def cumulative_variance_ratio(self) -> np.ndarray:
        """Cumulated explained variance, ``(k,)`` (Table 4, row 2; the compactness curve)."""
        return np.cumsum(self.explained_variance_ratio)

    @property
    def basis(self) -> np.ndarray:
        """``A`` as a ``(3n, k)`` matrix (coordinates ordered x1, y1, z1, x2, ...)."""
        return self.modes.reshape(self.number_of_modes, -1).T

    def variance_table(self, *, number_of_modes: int | None = None) -> str:
        """The paper's Table 4 as text: variance % and cumulated variance % per mode."""
        k = (
            self.number_of_modes
            if number_of_modes is None
            else min(number_of_modes, self.number_of_modes)
        )
        ratio, cumulative = self.explained_variance_ratio, self.cumulative_variance_ratio
        head = f"{'Parameter':<22}" + "".join(f"{i + 1:>9d}" for i in range(k))
        sd = f"{'Standard deviation':<22}" + "".join(
            f"{v:>9.3g}" for v in self.standard_deviations[:k]
        )
        var = f"{'Variances %':<22}" + "".join(f"{100 * v:>9.2f}" for v in ratio[:k])
        cum = f"{'Cumulated Variance %':<22}" + "".join(f"{100 * v:>9.2f}" for v in cumulative[:k])
        return "\n".join([head, var, cum, sd])

    def variance_records(self) -> list[dict[str, float]]:
        """Table 4 as a list of ``{mode, variance, standard_deviation, ratio, cumulative}``."""
        return [
            {
                "mode": i + 1,
                "variance": float(v),
                "standard_deviation": float(np.sqrt(v)),
                "ratio": float(r),
                "cumulative": float(c),
            }
            for i, (v, r, c) in enumerate(
                zip(self.variances, self.explained_variance_ratio, self.cumulative_variance_ratio)
            )
        ]

    # -- synthesis and projection -----------------------------------------------------------------
    def _coefficients(self, coefficients: Any, standardized: bool) -> np.ndarray:
        if not isinstance(coefficients, (np.ndarray, list, tuple)):
            raise TypeError(
                f"`coefficients` must be an array of numbers, got {type(coefficients).__name__}"
            )
        a = np.asarray(coefficients, dtype=np.float64).reshape(-1)
        if a.size > self.number_of_modes:
            raise ValueError(
                f"`coefficients` must hold at most {self.number_of_modes} values (the model's "
                f"modes), got {a.size}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError("`coefficients` must be finite")
        if standardized:
            a = a * self.standard_deviations[: a.size]
        return a

    def synthesize(self, coefficients: Any, *, standardized: bool = False) -> np.ndarray:
        """``P = M + A alpha`` (eq. 4).

        Parameters
        ----------
        coefficients : (j,) array_like
            ``alpha`` for the first ``j <= k`` modes (the others are 0).
        standardized : bool, optional
            ``True``: ``coefficients`` are in standard deviations of each mode (``alpha_i =
            c_i sqrt(variance_i)``). Default ``False``: in the input's units.

        Returns
        -------
        (n, 3) ndarray
        """
        a = self._coefficients(coefficients, standardized)
        return self._synthesize(a)

    def _synthesize(self, a: np.ndarray) -> np.ndarray:
        return self.mean + np.tensordot(a, self.modes[: a.size], axes=1)

    def mesh(
        self, coefficients: Any = None, *, standardized: bool = False
    ) -> o3d.geometry.TriangleMesh:
        """The shape ``M + A alpha`` as an Open3D mesh (the mean when ``coefficients`` is None)."""
        vertices = (
            self.mean
            if coefficients is None
            else self.synthesize(coefficients, standardized=standardized)
        )
        mesh = to_open3d(np.array(vertices), np.array(self.faces))
        mesh.compute_vertex_normals()
        return mesh

    def mode_shape(self, mode: int, standard_deviations: float) -> np.ndarray:
        """``M + c sqrt(variance_mode) A_mode``: the mean moved along one mode (Figure 6).

        Parameters
        ----------
        mode : int
            0-based mode index.
        standard_deviations : float
            Multiple ``c`` of the mode's standard deviation (the paper shows ``c = +-3``).
        """
        if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)):
            raise TypeError(f"`mode` must be an integer, got {type(mode).__name__}")
        if not 0 <= mode < self.number_of_modes:
            raise ValueError(f"`mode` must be in [0, {self.number_of_modes - 1}], got {mode}")
        c = float(standard_deviations)
        return self.mean + c * self.standard_deviations[mode] * self.modes[mode]

    def mode_meshes(
        self, modes: Any = None, standard_deviations: Any = (-3.0, 3.0)
    ) -> dict[tuple[int, float], o3d.geometry.TriangleMesh]:
        """Meshes of :meth:`mode_shape` for each mode and multiple: ``{(mode, c): mesh}``."""
        modes_ = range(min(2, self.number_of_modes)) if modes is None else modes
        out = {}
        for m in modes_:
            for c in standard_deviations:
                mesh = to_open3d(self.mode_shape(int(m), float(c)), np.array(self.faces))
                mesh.compute_vertex_normals()
                out[(int(m), float(c))] = mesh
        return out

    def project(
        self, shape: Any, *, number_of_modes: int | None = None, align: bool = True
    ) -> ShapeProjection:
        """Express a new shape (same semilandmarks) in the model, its pose removed.

        The shape is aligned onto the mean (rigid, or similarity when the model was built with
        ``scaling``), then ``alpha = A^T (x - M)`` (the modes are orthonormal).

        Parameters
        ----------
        shape : (n, 3) array_like or open3d geometry
            Corresponding points. Not modified.
        number_of_modes : int, optional
            Use only the first modes. Default all.
        align : bool, optional
            Remove the pose first. Default ``True``.
        """
        x = as_points(shape, "shape")
        if x.shape[0] != self.number_of_points:
            raise ValueError(
                f"`shape` must have {self.number_of_points} points (the model's semilandmarks), "
                f"got {x.shape[0]}"
            )
        k = self._check_modes(number_of_modes)
        return self._project(x, k, align)

    def _check_modes(self, number_of_modes: Any) -> int:
        if number_of_modes is None:
            return self.number_of_modes
        k = check_positive(number_of_modes, "number_of_modes", integer=True, allow_zero=True)
        if k > self.number_of_modes:
            raise ValueError(
                f"`number_of_modes` must be <= {self.number_of_modes}, got {number_of_modes}"
            )
        return int(k)

    def _project(self, x: np.ndarray, k: int, align: bool) -> ShapeProjection:
        t = np.eye(4)
        if align:
            # Align, project, and re-align onto the reconstruction (a few passes: the pose that
            # best fits the model instance is not exactly the pose that best fits the mean).
            t = _fit(x, self.mean, self.scaling)
            for _ in range(3):
                y = apply_transformation(t, x)
                a = np.tensordot(self.modes[:k], y - self.mean, axes=([1, 2], [0, 1]))
                t = _fit(x, self._synthesize(a), self.scaling)
        y = apply_transformation(t, x)
        a = np.tensordot(self.modes[:k], y - self.mean, axes=([1, 2], [0, 1]))
        rec = self._synthesize(a)
        return ShapeProjection(a, t, rec, y - rec)

    def sample(
        self, number_of_samples: int, *, seed: int = 0, number_of_modes: int | None = None
    ) -> np.ndarray:
        """Random shapes ``M + A alpha``, ``alpha_i ~ N(0, variance_i)``: ``(count, n, 3)``."""
        count = check_positive(number_of_samples, "number_of_samples", integer=True)
        k = self._check_modes(number_of_modes)
        rng = np.random.default_rng(seed)
        a = rng.standard_normal((count, k)) * self.standard_deviations[:k]
        return self.mean + np.tensordot(a, self.modes[:k], axes=1)

    def check_template(self, template: Any, name: str = "template") -> None:
        """Raise ``ValueError`` unless ``template`` has this model's vertex count and triangles."""
        v, f = as_mesh_arrays(template, name)
        if v.shape[0] != self.number_of_points or not np.array_equal(f, self.faces):
            raise ValueError(
                f"`{name}` is not this model's template: the model has {self.number_of_points} "
                f"points and {self.faces.shape[0]} triangles, got {v.shape[0]} points and "
                f"{f.shape[0]} triangles" + ("" if f.shape != self.faces.shape else " (different)")
            )

    # -- persistence ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> str:
        """Write the whole model (with the template triangles) to a ``.npz`` file, atomically."""
        arrays: dict[str, Any] = {
            "mean": self.mean,
            "modes": self.modes,
            "variances": self.variances,
            "faces": self.faces,
            "total_variance": np.array(self.total_variance),
            "scores": self.scores,
            "names": np.array(json.dumps(list(self.names))),
            "scaling": np.array(self.scaling),
            "noise_variance": np.array(self.noise_variance),
        }
        return write_archive(path, arrays, kind=_FORMAT, version=_VERSION, overwrite=overwrite)

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, template: Any = None) -> ShapeModel:
        """Read a model written by :meth:`save`.

        Parameters
        ----------
        path : str or path-like
        template : open3d.geometry.TriangleMesh or (vertices, faces), optional
            When given, check that the model was built on this template (same vertex count and
            triangle array); ``ValueError`` otherwise.
        """
        data = read_archive(path, kind=_FORMAT, version=_VERSION, what="ShapeModel")
        model = cls(
            mean=data["mean"],
            modes=data["modes"],
            variances=data["variances"],
            faces=data["faces"],
            total_variance=float(data["total_variance"]),
            scores=data["scores"],
            names=tuple(json.loads(str(data["names"]))),
            scaling=bool(data["scaling"]),
            noise_variance=float(data["noise_variance"]),
        )
        if template is not None:
            model.check_template(template)
        return model

    def write_meshes(
        self,
        folder: str | os.PathLike[str],
        *,
        modes: Any = None,
        standard_deviations: Any = (-3.0, 3.0),
        overwrite: bool = False,
    ) -> list[str]:
        """Write ``mean.ply`` and ``mode{i}_{c:+g}sd.ply`` (1-based ``i``) into ``folder``."""
        folder = os.fspath(folder)
        if not os.path.isdir(folder):
            raise OSError(f"`folder`: {folder!r} is not a folder")
        written = [
            write_triangle_mesh(os.path.join(folder, "mean.ply"), self.mesh(), overwrite=overwrite)
        ]
        for (m, c), mesh in self.mode_meshes(modes, standard_deviations).items():
            name = f"mode{m + 1}_{c:+g}sd.ply"
            written.append(
                write_triangle_mesh(os.path.join(folder, name), mesh, overwrite=overwrite)
            )
        return written


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
    faces : (m, 3) array_like of int
        The template's triangles (shared by every shape).
    scaling : bool, optional
        Similarity Procrustes (size removed) instead of rigid (size kept, default, the paper).
    number_of_modes : int, optional
        Keep only the first modes. Default: all modes with non-zero variance, at most ``s - 1``.
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
        Fewer than 2 shapes, different vertex counts, or ``faces`` not indexing the points.

    References
    ----------
    .. [1] T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
       training and application", CVIU 61(1), 1995. :doi:`10.1006/cviu.1995.1004`
    .. [2] M. Berar et al., ICIAR 2004, LNCS 3212, section 3.3, eq. (4) and Table 4.
    """
    x = as_shape_array(shapes)
    if isinstance(faces, o3d.geometry.TriangleMesh):
        faces = np.asarray(faces.triangles)
    _, f = as_mesh_arrays((x[0], faces), "faces", drop_degenerate=True)
    f = np.array(np.asarray(faces), dtype=np.int64).reshape(-1, 3)
    if not isinstance(scaling, bool):
        raise TypeError(f"`scaling` must be a bool, got {type(scaling).__name__}")
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
        names_ = tuple(str(n) for n in names)
        if len(names_) != s:
            raise ValueError(f"`names` must hold {s} names, got {len(names_)}")
    return _build(x, f, scaling, number_of_modes, names_, align)


def _build(
    x: np.ndarray,
    faces: np.ndarray,
    scaling: bool,
    number_of_modes: int | None,
    names: tuple[str, ...],
    align: bool,
) -> ShapeModel:
    s, n, _ = x.shape
    if align:
        gpa = _generalized_procrustes(x, scaling, 100, 1e-10)
        aligned, mean = gpa.shapes, gpa.shapes.mean(axis=0)
    else:
        aligned, mean = x, x.mean(axis=0)
    data = (aligned - mean).reshape(s, -1)
    _, sv, vt = np.linalg.svd(data, full_matrices=False)
    variances = sv**2 / (s - 1)
    total = float(variances.sum())
    # Modes with (numerically) zero variance carry no information.
    keep = int(np.count_nonzero(variances > 1e-12 * max(total, 1e-300)))
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


# -- fitting to a surface ---------------------------------------------------------------------------
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
        Mean distance from the fitted vertices to the patient surface.
    iterations : int
    success : bool
        Whether the relative change of the fit fell below the tolerance.
    message : str
    """

    coefficients: np.ndarray
    transformation: np.ndarray = field(repr=False)
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    mean_distance: float
    iterations: int
    success: bool
    message: str

    def __repr__(self) -> str:
        return (
            f"ModelFit(modes={self.coefficients.size}, mean_distance={self.mean_distance:.4g}, "
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
) -> ModelFit:
    """Fit pose and shape coefficients of ``model`` to a patient surface (iterated closest points).

    Each iteration: (1) closest points ``y_i`` on the patient surface to the current instance;
    and, as in the symmetric distance of eq. (3), closest points of the instance surface to
    samples of the patient surface; (2) pose by weighted Procrustes of all these pairs; (3)
    coefficients minimising ``|S (M + A alpha) - T^-1 y|^2 + regularization * sum_j alpha_j^2 /
    variance_j`` (``S`` selects vertices and barycentric surface points; Tikhonov with
    1/variance: with ``S = I`` this is ``alpha_j = variance_j / (variance_j + regularization)
    A_j^T (T^-1 y - M)``, the posterior mean of probabilistic PCA with noise variance
    ``regularization``). Both directions are weighted to count as ``n`` points.
    Stops when the instance moves by less than ``tolerance`` times the model's size.

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

    Returns
    -------
    ModelFit

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
    k = model._check_modes(number_of_modes)
    if regularization is None:
        reg = None if model.noise_variance <= 0 else model.noise_variance
    else:
        reg = check_positive(regularization, "regularization", allow_zero=True)
    max_iteration = check_positive(max_iteration, "max_iteration", integer=True)
    tolerance = check_positive(tolerance, "tolerance", allow_zero=True)
    if init is not None:
        pose = as_transformation(init, "init")
        return _fit_model(model, vt, ft, pose, k, reg, max_iteration, tolerance)
    from ..registration.distance import SurfaceDistanceQuery
    from ..registration.rigid import registration_rigid

    # Two starts: the rigid registration of the mean (moment-based guess + ICP) and a plain
    # translation of centroids (right when patients share the model's orientation, where the
    # moment guess may pick a symmetric flip); keep the fit with the smaller symmetric distance.
    shift = np.eye(4)
    shift[:3, 3] = vt.mean(axis=0) - model.mean.mean(axis=0)
    starts = [
        np.array(registration_rigid((model.mean, model.faces), (vt, ft)).transformation),
        shift,
    ]
    best, best_cost = None, np.inf
    for pose in starts:
        fit = _fit_model(model, vt, ft, pose, k, reg, max_iteration, tolerance)
        back = SurfaceDistanceQuery(fit.vertices, model.faces).distance(vt).mean()
        cost = fit.mean_distance + float(back)
        if cost < best_cost:
            best, best_cost = fit, cost
    assert best is not None
    return best


def _fit_model(
    model: ShapeModel,
    vt: np.ndarray,
    ft: np.ndarray,
    pose: np.ndarray,
    k: int,
    reg: float | None,
    max_iteration: int,
    tolerance: float,
) -> ModelFit:
    from ..registration.distance import SurfaceDistanceQuery

    query = SurfaceDistanceQuery(vt, ft)
    modes = model.modes[:k]
    variances = model.variances[:k]
    a = np.zeros(k)
    size = float(np.sqrt(((model.mean - model.mean.mean(axis=0)) ** 2).sum(axis=1).mean()))
    current = apply_transformation(pose, model._synthesize(a))
    success = False
    change = np.inf
    iterations = 0
    faces = np.asarray(model.faces)
    n = model.number_of_points
    # Target samples for the target -> instance correspondences (eq. 3's second term).
    stride = max(1, vt.shape[0] // (4 * n))
    samples = vt[::stride]
    for iterations in range(1, max_iteration + 1):  # noqa: B007
        # Forward: instance vertices -> closest target points.
        _, _, closest = query.closest(current)
        # Backward: target samples -> closest points of the instance surface (barycentric).
        _, face, on_instance = SurfaceDistanceQuery(current, faces).closest(samples)
        weights = barycentric(current[faces[face]], on_instance)
        instance = model._synthesize(a)
        src = np.vstack([instance, np.einsum("jc,jcd->jd", weights, instance[faces[face]])])
        dst = np.vstack([closest, samples])
        wts = np.concatenate(
            [np.full(n, 1.0 / n), np.full(samples.shape[0], 1.0 / samples.shape[0])]
        )
        pose = _fit(src, dst, model.scaling, wts)
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
        new = apply_transformation(pose, model._synthesize(a))
        change = float(np.sqrt(((new - current) ** 2).sum(axis=1).mean())) / max(size, 1e-300)
        current = new
        if change < tolerance:
            success = True
            break
    dist = query.distance(current)
    message = (
        f"converged in {iterations} iterations (relative change {change:.3g})"
        if success
        else f"did not converge in {max_iteration} iterations (relative change {change:.3g})"
    )
    return ModelFit(
        coefficients=a,
        transformation=pose,
        vertices=current,
        faces=np.array(model.faces),
        mean_distance=float(dist.mean()),
        iterations=iterations,
        success=success,
        message=message,
    )
