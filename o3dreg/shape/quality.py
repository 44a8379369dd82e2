"""Quality of a shape model: compactness, generalisation and specificity.

The three measures of Davies et al. (2002) / Styner et al. (2003), each as a curve against the
number of modes, with a text table and a PNG plot (matplotlib, Agg backend).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._geometry import apply_transformation
from .._validation import check_bool, check_positive
from ..io.mesh import atomic_write
from .build import pca_model, template_faces
from .model import ShapeModel
from .procrustes import as_shape_array, fit_transformation

__all__ = ["QualityCurve", "compactness", "generalization", "specificity"]

logger = logging.getLogger("o3dreg")


@dataclass(frozen=True, eq=False)
class QualityCurve:
    """One model-quality measure against the number of modes.

    Attributes
    ----------
    name : str
        ``'compactness'``, ``'generalization'`` or ``'specificity'``.
    modes : (j,) int ndarray
        Number of modes used.
    values : (j,) ndarray
        Compactness: cumulative explained variance ratio. Generalisation and specificity: mean
        per-point distance in the input's units (lower is better).
    errors : (j,) ndarray
        Standard deviation over left-out shapes (generalisation) or samples (specificity);
        zeros for compactness.
    unit : str
    """

    name: str
    modes: np.ndarray = field(repr=False)
    values: np.ndarray = field(repr=False)
    errors: np.ndarray = field(repr=False)
    unit: str = "mm"

    def __repr__(self) -> str:
        vals = ", ".join(f"{v:.3g}" for v in self.values[:6])
        span = f"{int(self.modes[0])}..{int(self.modes[-1])}" if len(self.modes) else "none"
        return f"QualityCurve({self.name}, modes {span}: [{vals}])"

    def table(self) -> str:
        """Text table: modes, value, spread (compactness has none: no spread column)."""
        if self.name == "compactness":
            lines = [f"{self.name}", f"{'modes':>6}{'cumulative %':>16}"]
            lines += [f"{int(m):>6d}{100 * v:>16.4g}" for m, v in zip(self.modes, self.values)]
            return "\n".join(lines)
        lines = [f"{self.name}", f"{'modes':>6}{f'mean ({self.unit})':>16}{'sd':>12}"]
        for m, v, e in zip(self.modes, self.values, self.errors):
            lines.append(f"{int(m):>6d}{v:>16.4g}{e:>12.3g}")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "modes": [int(m) for m in self.modes],
            "values": [float(v) for v in self.values],
            "errors": [float(e) for e in self.errors],
            "unit": self.unit,
        }

    def plot(
        self, path: str | os.PathLike[str], *, overwrite: bool = False, title: str | None = None
    ) -> str:
        """Save the curve as a PNG (atomically); returns the path."""
        # Deferred: matplotlib.pyplot takes ~1 s to import, and `import o3dreg` loads this module.
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        path = os.fspath(path)
        if not path.lower().endswith(".png"):
            raise ValueError(f"`path` must end with .png, got {path!r}")
        fig, ax = plt.subplots(figsize=(4.5, 3.2), dpi=120)
        values = 100 * self.values if self.name == "compactness" else self.values
        errors = 100 * self.errors if self.name == "compactness" else self.errors
        ax.errorbar(
            self.modes, values, yerr=errors if errors.any() else None, marker="o", capsize=3
        )
        ax.set_xlabel("number of modes")
        ax.set_ylabel(
            "cumulative variance (%)"
            if self.name == "compactness"
            else f"mean distance ({self.unit})"
        )
        ax.set_title(title or self.name)
        ax.set_xticks(self.modes)
        ax.grid(True, alpha=0.3)
        fig.tight_layout()

        def write(tmp: str) -> None:
            fig.savefig(tmp, format="png")

        try:
            return atomic_write(path, write, overwrite=overwrite)
        finally:
            plt.close(fig)


def compactness(model: ShapeModel) -> QualityCurve:
    """Cumulative explained variance against the number of modes.

    References
    ----------
    .. [1] R. H. Davies, C. J. Twining, T. F. Cootes, J. C. Waterton, C. J. Taylor, "A minimum
       description length approach to statistical shape modeling", IEEE TMI 21(5), 2002.
       :doi:`10.1109/TMI.2002.1009388`
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    k = model.number_of_modes
    return QualityCurve(
        "compactness",
        np.arange(1, k + 1),
        model.cumulative_variance_ratio.copy(),
        np.zeros(k),
        unit="",
    )


def generalization(
    shapes: Any, faces: Any, *, scaling: bool = False, max_modes: int | None = None
) -> QualityCurve:
    """Leave-one-out reconstruction error against the number of modes.

    For each shape ``i``, a model is built from the ``s - 1`` others (Procrustes + PCA), shape
    ``i`` is aligned to it and projected on its first ``m`` modes; the error is the mean
    per-point distance between the aligned shape and its reconstruction, averaged over ``i``.

    Parameters
    ----------
    shapes : (s, n, 3) array_like or sequence of (n, 3)
        ``s >= 3`` training shapes.
    faces : (m, 3) array_like of int
    scaling : bool, optional
        Similarity Procrustes. Default ``False`` (rigid).
    max_modes : int, optional
        Largest number of modes evaluated (at most ``s - 2``). Default ``s - 2``.

    Returns
    -------
    QualityCurve
        ``modes`` starts at 0 (the mean alone).
    """
    x = as_shape_array(shapes, min_shapes=3)
    f = template_faces(faces, x.shape[1])
    scaling = check_bool(scaling, "scaling")
    s = x.shape[0]
    top = s - 2
    if max_modes is not None:
        top = min(top, check_positive(max_modes, "max_modes", integer=True))
    errors = np.zeros((s, top + 1))
    for i in range(s):
        rest = np.delete(x, i, axis=0)
        # The others may all be one shape (a population with a repeated patient): the model is
        # then the mean alone.
        names = tuple(f"s{j}" for j in range(s - 1))
        model = pca_model(rest, f, scaling, None, names, True, distinct=False, warn_mirrored=False)
        for m in range(top + 1):
            kk = min(m, model.number_of_modes)
            errors[i, m] = model.project(x[i], number_of_modes=kk).mean_error
    logger.info("generalization: %s", ", ".join(f"{v:.3g}" for v in errors.mean(axis=0)))
    return QualityCurve(
        "generalization", np.arange(top + 1), errors.mean(axis=0), errors.std(axis=0)
    )


def specificity(
    model: ShapeModel,
    shapes: Any,
    *,
    number_of_samples: int = 200,
    seed: int = 0,
    max_modes: int | None = None,
) -> QualityCurve:
    """Mean distance of random model instances to the nearest training shape.

    For ``m = 1 .. k`` modes, ``number_of_samples`` shapes ``M + A alpha`` with ``alpha_j ~
    N(0, variance_j)`` are drawn; each sample's distance to a training shape is the mean
    per-point distance after Procrustes alignment, and the nearest training shape counts.

    Parameters
    ----------
    model : ShapeModel
    shapes : (s, n, 3) array_like or sequence of (n, 3)
        The training shapes (any pose: each is aligned to the model).
    number_of_samples : int, optional
        Default 200.
    seed : int, optional
        Seed of the samples. Default 0.
    max_modes : int, optional
        Default all the model's modes.
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    x = as_shape_array(shapes, min_shapes=1)
    if x.shape[1] != model.number_of_points:
        raise ValueError(
            f"`shapes` must have the model's {model.number_of_points} points, got {x.shape[1]}"
        )
    count = check_positive(number_of_samples, "number_of_samples", integer=True)
    top = (
        model.number_of_modes
        if max_modes is None
        else min(model.number_of_modes, check_positive(max_modes, "max_modes", integer=True))
    )
    aligned = np.stack(
        [apply_transformation(fit_transformation(s, model.mean, model.scaling), s) for s in x]
    )
    rng = np.random.default_rng(check_positive(seed, "seed", integer=True, allow_zero=True))
    z = rng.standard_normal((count, model.number_of_modes))
    values, spreads = np.zeros(top), np.zeros(top)
    for m in range(1, top + 1):
        a = z[:, :m] * model.standard_deviations[:m]
        samples = model.mean + np.tensordot(a, model.modes[:m], axes=1)
        best = np.full(count, np.inf)
        for ref in aligned:
            for j in range(count):
                t = fit_transformation(ref, samples[j], model.scaling)
                d = float(np.linalg.norm(apply_transformation(t, ref) - samples[j], axis=1).mean())
                best[j] = min(best[j], d)
        values[m - 1], spreads[m - 1] = best.mean(), best.std()
    logger.info("specificity: %s", ", ".join(f"{v:.3g}" for v in values))
    return QualityCurve("specificity", np.arange(1, top + 1), values, spreads)
