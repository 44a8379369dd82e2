"""The point distribution (statistical shape) model of semilandmark meshes: ``P = M + A alpha``.

Berar et al. (2005), section 3.3: the registered template meshes (same vertices, same triangles
for every patient) are aligned by Procrustes analysis, then a principal component analysis gives
the mean shape ``M``, the modes ``A`` and their variances (the paper's Table 4); a new shape is
synthesised as ``P = M + A alpha`` (eq. 4).

This module holds the value type: its sizes, Table 4, synthesis, sampling and the projection of
corresponding points. Building is in :mod:`.build`, fitting to a surface in :mod:`.fit`, files in
:mod:`.model_io`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation
from .._validation import (
    as_faces,
    as_mesh_arrays,
    as_numbers,
    as_points,
    check_bool,
    check_positive,
)
from ..io.mesh import to_open3d
from .model_io import read_model_archive, write_model_archive, write_model_meshes
from .procrustes import fit_transformation

__all__ = ["ShapeModel", "ShapeProjection"]


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
        ``M``, the mean shape (the Procrustes mean, centred at the origin, unless the model was
        built without alignment), in the input's units (mm).
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
        # What every projection and table relies on: a file that breaks it (modes scaled by 5
        # projected shapes 5 times too far) is refused, not loaded.
        if variances.size > 1 and np.any(np.diff(variances) > 1e-12 * variances.max()):
            raise ValueError(f"`variances` must be sorted from largest, got {variances.tolist()}")
        flat = modes.reshape(modes.shape[0], 3 * n)
        gram_error = float(np.abs(flat @ flat.T - np.eye(flat.shape[0])).max(initial=0.0))
        if not gram_error <= 1e-6:
            raise ValueError(
                f"`modes` must be orthonormal (unit-norm, mutually orthogonal 3n-vectors), got "
                f"|A^T A - I| up to {gram_error:.3g}"
            )
        # The template's triangles as given, degenerate ones included: they must equal the
        # template's (check_template) and a triangle flat in the mean need not be in every shape.
        faces = as_faces(self.faces, n, "faces")
        if faces.shape[0] < 1:
            raise ValueError("`faces` must have at least 1 triangle(s), got 0")
        scores = np.array(self.scores, dtype=np.float64)
        if scores.ndim != 2 or scores.shape[1] != modes.shape[0]:
            raise ValueError(f"`scores` must have shape (s, {modes.shape[0]}), got {scores.shape}")
        # The denominators of Table 4 and the fit's regularisation: a NaN or a total below the
        # modes' own variances would give ratios above 1 or a fit that cannot converge.
        total = float(self.total_variance)
        if not (np.isfinite(total) and total >= variances.sum() * (1.0 - 1e-6)):
            raise ValueError(
                "`total_variance` must be finite and at least the sum of `variances` "
                f"({variances.sum():.6g}), got {total!r}"
            )
        noise = float(self.noise_variance)
        if not (np.isfinite(noise) and noise >= 0):
            raise ValueError(f"`noise_variance` must be finite and >= 0, got {noise!r}")
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
            ("total_variance", total),
            ("noise_variance", noise),
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
        # The column length is explicit: a model of no modes has a (3n, 0) basis (``-1`` cannot
        # be inferred from 0 values).
        return self.modes.reshape(self.number_of_modes, 3 * self.number_of_points).T

    def variance_table(self, *, number_of_modes: int | None = None) -> str:
        """The paper's Table 4 as text: variance % and cumulated variance % per mode, the
        standard deviation (of the whole shape vector, input units) and what it moves each
        point by, RMS (the mode is a unit vector over ``3n`` coordinates: ``sd / sqrt(n)``)."""
        k = self.number_of_modes
        if number_of_modes is not None:
            asked = check_positive(
                number_of_modes, "number_of_modes", integer=True, allow_zero=True
            )
            k = min(int(asked), k)
        ratio, cumulative = self.explained_variance_ratio, self.cumulative_variance_ratio
        head = f"{'Parameter':<22}" + "".join(f"{i + 1:>9d}" for i in range(k))
        sd = f"{'Standard deviation':<22}" + "".join(
            f"{v:>9.3g}" for v in self.standard_deviations[:k]
        )
        var = f"{'Variances %':<22}" + "".join(f"{100 * v:>9.2f}" for v in ratio[:k])
        cum = f"{'Cumulated Variance %':<22}" + "".join(f"{100 * v:>9.2f}" for v in cumulative[:k])
        per_point = self.standard_deviations[:k] / np.sqrt(max(self.number_of_points, 1))
        rms = f"{'SD per point (RMS)':<22}" + "".join(f"{v:>9.3g}" for v in per_point)
        return "\n".join([head, var, cum, sd, rms])

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
        a = np.asarray(coefficients, dtype=np.float64)
        if a.ndim > 1:
            raise ValueError(
                f"`coefficients` must be one value per mode (1-D), got shape {a.shape}"
            )
        a = a.reshape(-1)
        if a.size > self.number_of_modes:
            raise ValueError(
                f"`coefficients` must hold at most {self.number_of_modes} values (the model's "
                f"modes), got {a.size}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError("`coefficients` must be finite")
        if check_bool(standardized, "standardized"):
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
        if not np.isfinite(c):
            raise ValueError(f"`standard_deviations` must be finite, got {standard_deviations}")
        return self.mean + c * self.standard_deviations[mode] * self.modes[mode]

    def mode_meshes(
        self, modes: Any = None, standard_deviations: Any = (-3.0, 3.0)
    ) -> dict[tuple[int, float], o3d.geometry.TriangleMesh]:
        """Meshes of :meth:`mode_shape` for each mode and multiple: ``{(mode, c): mesh}``."""
        modes_ = range(min(2, self.number_of_modes)) if modes is None else modes
        multiples = as_numbers(standard_deviations, "standard_deviations")
        if isinstance(modes_, (str, bytes)) or not isinstance(
            modes_, (range, list, tuple, np.ndarray)
        ):
            raise TypeError(
                f"`modes` must be a sequence of mode indices, got {type(modes_).__name__}"
            )
        out = {}
        for m in modes_:
            for c in multiples:
                mesh = to_open3d(self.mode_shape(m, c), np.array(self.faces))
                mesh.compute_vertex_normals()
                out[(int(m), c)] = mesh
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
        k = self.check_number_of_modes(number_of_modes)
        t = np.eye(4)
        if check_bool(align, "align"):
            # Align, project, and re-align onto the reconstruction (a few passes: the pose that
            # best fits the model instance is not exactly the pose that best fits the mean).
            t = fit_transformation(x, self.mean, self.scaling)
            for _ in range(3):
                y = apply_transformation(t, x)
                a = np.tensordot(self.modes[:k], y - self.mean, axes=([1, 2], [0, 1]))
                t = fit_transformation(x, self._synthesize(a), self.scaling)
        y = apply_transformation(t, x)
        a = np.tensordot(self.modes[:k], y - self.mean, axes=([1, 2], [0, 1]))
        rec = self._synthesize(a)
        return ShapeProjection(a, t, rec, y - rec)

    def check_number_of_modes(self, number_of_modes: Any) -> int:
        """The number of modes to use: all when ``None``, else an integer in ``[0, k]``."""
        if number_of_modes is None:
            return self.number_of_modes
        k = check_positive(number_of_modes, "number_of_modes", integer=True, allow_zero=True)
        if k > self.number_of_modes:
            raise ValueError(
                f"`number_of_modes` must be <= {self.number_of_modes}, got {number_of_modes}"
            )
        return int(k)

    def sample(
        self, number_of_samples: int, *, seed: int = 0, number_of_modes: int | None = None
    ) -> np.ndarray:
        """Random shapes ``M + A alpha``, ``alpha_i ~ N(0, variance_i)``: ``(count, n, 3)``."""
        count = check_positive(number_of_samples, "number_of_samples", integer=True)
        k = self.check_number_of_modes(number_of_modes)
        rng = np.random.default_rng(check_positive(seed, "seed", integer=True, allow_zero=True))
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

    # -- persistence (the formats are in .model_io) ----------------------------------------------
    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> str:
        """Write the whole model (with the template triangles) to a ``.npz`` file, atomically."""
        return write_model_archive(self, path, overwrite=overwrite)

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
        try:
            model = cls(**read_model_archive(path))
        except ValueError as exc:
            if str(exc).startswith("`path`"):
                raise
            raise ValueError(f"`path`: {os.fspath(path)!r} holds an invalid model: {exc}") from exc
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
        return write_model_meshes(
            self,
            folder,
            modes=modes,
            standard_deviations=standard_deviations,
            overwrite=overwrite,
        )
