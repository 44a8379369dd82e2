"""The elastic deformation of space: a hierarchy of trilinear lattices.

``T(x) = x + sum_k u_k(x)`` where ``u_k`` is the displacement field of level ``k`` (a
:class:`~o3dreg.registration.lattice.TrilinearLattice`; all levels share one box). Each level adds detail to the
coarser ones, as in the multi-resolution scheme of Berar et al. (2005), Fig. 3, and the
octree-splines of Szeliski and Lavallee (1996). The map applies to any points: template vertices,
landmarks, other meshes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import reduce
from math import gcd
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .._geometry import det3, into_frame, rotation_angle, row_norms
from .._validation import as_points, check_positive
from ..io.archive import read_archive, write_archive
from .lattice import TrilinearLattice, cell_counts

__all__ = ["LatticeDeformation", "PartitionedDeformation", "load_deformation"]

_FORMAT = "o3dreg.LatticeDeformation"
#: Version 2 added the lattice frame (version 1 files: lattices aligned with the world axes).
_VERSION = 2
_PARTITIONED_FORMAT = "o3dreg.PartitionedDeformation"
_PARTITIONED_VERSION = 2


def _lcm(a: int, b: int) -> int:
    return a * b // gcd(a, b)


@dataclass(frozen=True, eq=False)
class LatticeDeformation:
    """A map of space ``T(x) = x + sum_k u_k(x)`` made of nested trilinear lattices.

    Attributes
    ----------
    levels : tuple of TrilinearLattice
        Coarse to fine; all share the same box. An empty tuple is the identity.
    frame : (4, 4) ndarray or None
        Where the lattices lie: the rigid transformation from lattice coordinates to the
        coordinates the map applies to (``None``: the same coordinates, lattices aligned with
        the axes). :func:`~o3dreg.registration_elastic` lays its lattices along the template's
        own axes, through its start's rotation, so that a patient turned in the scanner gets
        the same deformation, turned with it. Then ``T(y) = y + R u(R^T (y - t))``, with ``u``
        the lattices' displacement in their own coordinates.

    Notes
    -----
    Outside the common box every level is clamped, so ``T`` is continuous on all of space and
    moves far points rigidly by the displacement of the nearest box point.
    """

    levels: tuple[TrilinearLattice, ...] = ()
    frame: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        levels = tuple(self.levels)
        for lat in levels:
            if not isinstance(lat, TrilinearLattice):
                raise TypeError(
                    f"`levels` must hold TrilinearLattice objects, got {type(lat).__name__}"
                )
            if not lat.same_box(levels[0]):
                raise ValueError("`levels` must all cover the same box (origin and size)")
        object.__setattr__(self, "levels", levels)
        object.__setattr__(self, "frame", _checked_frame(self.frame))

    def __repr__(self) -> str:
        shapes = [lat.shape[0] if len(set(lat.shape)) == 1 else lat.shape for lat in self.levels]
        frame = ""
        if self.frame is not None:  # how far the lattices are turned from the axes
            frame = f", frame=turned {rotation_angle(self.frame):.3g} deg"
        return (
            f"LatticeDeformation(levels={shapes}, max_displacement={self.max_displacement:.4g}"
            f"{frame})"
        )

    @property
    def max_displacement(self) -> float:
        """Largest node displacement summed over levels (an upper bound on |T(x) - x|)."""
        return float(sum(lat.max_displacement for lat in self.levels))

    def with_level(self, lattice: TrilinearLattice) -> LatticeDeformation:
        """A new deformation with ``lattice`` appended as its finest level."""
        return LatticeDeformation((*self.levels, lattice), self.frame)

    def in_frame(self, frame: Any) -> LatticeDeformation:
        """The same lattices laid in ``frame`` (see :attr:`frame`; ``None``: the axes)."""
        return LatticeDeformation(self.levels, frame)

    def _local(self, pts: np.ndarray) -> np.ndarray:
        """Points in lattice coordinates."""
        return pts if self.frame is None else into_frame(self.frame, pts)

    # -- the map --------------------------------------------------------------------------------
    def displacement(self, points: Any) -> np.ndarray:
        """``T(x) - x`` at ``points (n, 3)``."""
        pts = self._local(as_points(points, "points", allow_empty=True))
        out = np.zeros(pts.shape)
        for lat in self.levels:
            lat.displacement(pts, out=out)
        return out if self.frame is None else out @ self.frame[:3, :3].T

    def transform(self, points: Any) -> np.ndarray:
        """Apply the map: ``T(points)`` as a new ``(n, 3)`` array (the input is not modified)."""
        pts = as_points(points, "points", allow_empty=True)
        return pts + self.displacement(pts)

    def jacobian(self, points: Any) -> np.ndarray:
        """Jacobian matrices ``dT/dx`` at ``points``, ``(n, 3, 3)`` (row: output, column: input)."""
        pts = self._local(as_points(points, "points", allow_empty=True))
        jac = np.broadcast_to(np.eye(3), (pts.shape[0], 3, 3)).copy()
        for lat in self.levels:
            lat.displacement_gradient(pts, out=jac)
        if self.frame is None:
            return jac
        rotation = self.frame[:3, :3]
        return rotation @ jac @ rotation.T

    def jacobian_determinant(self, points: Any) -> np.ndarray:
        """``det(dT/dx)`` at ``points``: positive where the map preserves orientation."""
        return det3(self.jacobian(points))

    def inverse_transform(self, points: Any, *, max_iterations: int = 50) -> np.ndarray:
        """The points this map sends onto ``points``: ``x`` with ``T(x) = points``.

        Newton's method on ``T(x) - points`` with the map's Jacobian, from ``points - u(points)``
        (``u`` the displacement), each step halved until it lowers the point's residual. Where the
        map is one-to-one (:meth:`LatticeDeformation.min_jacobian_determinant` ``> 0``; a
        registration's status ``'ok'`` vouches for the cells that hold template vertices) the
        answer is unique and a few steps reach it; where it folds, the point found is one of
        several.

        Parameters
        ----------
        points : (n, 3) array_like
            Points in the space the map goes to. Not modified.
        max_iterations : int, optional
            Newton steps at most. Default 50.

        Returns
        -------
        (n, 3) ndarray
            ``x`` with ``|T(x) - points|`` below ``1e-9`` times the larger of 1 and the points'
            largest absolute coordinate.

        Raises
        ------
        ValueError
            If some point has not reached that tolerance within ``max_iterations`` steps (the map
            folds there, or its Jacobian is singular), naming how many and the largest residual.

        Examples
        --------
        >>> import numpy as np
        >>> from o3dreg import LatticeDeformation, TrilinearLattice
        >>> lattice = TrilinearLattice.zeros((0, 0, 0), (2, 2, 2), (2, 2, 2))
        >>> shift = np.zeros(lattice.displacements.shape)
        >>> shift[1, 1, 1] = (0.3, 0.0, 0.0)
        >>> deformation = LatticeDeformation((lattice.with_displacements(shift),))
        >>> x = np.array([[0.9, 1.1, 1.0]])
        >>> bool(np.allclose(deformation.inverse_transform(deformation.transform(x)), x))
        True
        """
        return _inverse_points(self, points, max_iterations=max_iterations)

    def min_jacobian_determinant(self, samples_per_cell: int = 3) -> float:
        """Smallest Jacobian determinant over a regular sample of every finest cell.

        ``det`` is a polynomial inside each cell; sampling ``samples_per_cell`` points per axis at
        cell-interior positions (the corners are included through neighbouring cells) gives an
        estimate of its minimum. A value ``<= 0`` means the map folds (is not one-to-one).
        """
        n = check_positive(samples_per_cell, "samples_per_cell", integer=True)
        if n < 2:
            raise ValueError(f"`samples_per_cell` must be at least 2, got {samples_per_cell!r}")
        if not self.levels:
            return 1.0
        if self.frame is not None:  # the same determinants, sampled in lattice coordinates
            return self.in_frame(None).min_jacobian_determinant(samples_per_cell)
        finest = self.common_shape()
        origin, size = self.levels[0].origin, self.levels[0].size
        cells = np.asarray(finest)
        axes = [
            origin[a] + size[a] * np.linspace(0.0, 1.0, cells[a] * (n - 1) + 1) for a in range(3)
        ]
        grid = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([g.ravel() for g in grid], axis=1)
        # The corner of a cell is shared; nudge inwards so each sample uses a single cell's formula.
        centre = origin + size / 2
        pts = pts + (centre - pts) * 1e-9
        return float(self.jacobian_determinant(pts).min())

    # -- refinement -----------------------------------------------------------------------------
    def common_shape(self) -> tuple[int, int, int]:
        """Cells per axis of the coarsest lattice refining every level (the least common
        multiple of their cell counts)."""
        return tuple(  # type: ignore[return-value]
            reduce(_lcm, (lat.shape[a] for lat in self.levels)) for a in range(3)
        )

    def refined(self, shape: Any = None) -> LatticeDeformation:
        """The same map as a single lattice.

        Parameters
        ----------
        shape : int or tuple of 3 int, optional
            Cells per axis of the result: a common multiple of every level's cells. Default: the
            least common multiple (the finest level for a 2^k hierarchy).

        Returns
        -------
        LatticeDeformation
            One level whose map equals this one everywhere (to rounding).
        """
        if not self.levels:
            raise ValueError("cannot refine the identity deformation: it has no lattice")
        common = self.common_shape()
        if shape is None:
            shape = common
        elif isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
            shape = (shape,) * 3
        shape = cell_counts(shape)
        if any(s % c for s, c in zip(shape, common)):
            raise ValueError(f"`shape` must be 3 positive multiples of {common}, got {shape}")
        total = TrilinearLattice.zeros(self.levels[0].origin, self.levels[0].size, shape)
        nodes = total.node_positions()
        values = np.zeros_like(nodes)
        for lat in self.levels:
            values += lat.displacement(nodes)
        return LatticeDeformation((total.with_displacements(values),), self.frame)

    # -- persistence ----------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> str:
        """Write the deformation to a ``.npz`` file (atomically)."""
        return write_archive(
            path, _lattice_arrays(self, ""), kind=_FORMAT, version=_VERSION, overwrite=overwrite
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> LatticeDeformation:
        """Read a deformation written by :meth:`save` (see also :func:`load_deformation`)."""
        try:
            data = read_archive(path, kind=_FORMAT, version=_VERSION, what="LatticeDeformation")
        except ValueError as exc:
            if _holds(path, _PARTITIONED_FORMAT):
                raise ValueError(
                    f"`path`: {os.fspath(path)!r} holds a PartitionedDeformation (one map per "
                    "part): read it with PartitionedDeformation.load or load_deformation"
                ) from exc
            raise
        return _lattice_from(data, "", path)


def _checked_frame(frame: Any) -> np.ndarray | None:
    """``frame`` as a read-only (4, 4) rigid transformation, ``None`` for none or the identity."""
    if frame is None:
        return None
    m = np.array(frame, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"`frame` must be a finite (4, 4) matrix, got shape {m.shape}")
    rotation = m[:3, :3]
    rigid = (
        np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
        and np.linalg.det(rotation) > 0
        and np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0])
    )
    if not rigid:
        raise ValueError(
            "`frame` must be a rigid transformation (a rotation, a translation, last row "
            f"0 0 0 1), got {m.tolist()}"
        )
    if np.array_equal(m, np.eye(4)):
        return None
    m.flags.writeable = False
    return m


def _lattice_arrays(deformation: LatticeDeformation, prefix: str) -> dict[str, Any]:
    arrays: dict[str, Any] = {f"{prefix}number_of_levels": np.array(len(deformation.levels))}
    arrays[f"{prefix}frame"] = np.eye(4) if deformation.frame is None else deformation.frame
    for k, lat in enumerate(deformation.levels):
        arrays[f"{prefix}level{k}_origin"] = lat.origin
        arrays[f"{prefix}level{k}_size"] = lat.size
        arrays[f"{prefix}level{k}_shape"] = np.asarray(lat.shape)
        arrays[f"{prefix}level{k}_displacements"] = lat.displacements
    return arrays


def _lattice_from(data: dict[str, np.ndarray], prefix: str, path: Any) -> LatticeDeformation:
    levels = []
    try:
        count = int(data[f"{prefix}number_of_levels"])
        if count < 0:
            raise ValueError(f"{prefix}number_of_levels is {count}")
        for k in range(count):
            shape = tuple(int(s) for s in data[f"{prefix}level{k}_shape"])
            if len(shape) != 3 or min(shape) < 1:
                raise ValueError(f"{prefix}level{k}_shape is {shape}")
            levels.append(
                TrilinearLattice(
                    data[f"{prefix}level{k}_origin"].astype(np.float64),
                    data[f"{prefix}level{k}_size"].astype(np.float64),
                    shape,  # type: ignore[arg-type]
                    data[f"{prefix}level{k}_displacements"].astype(np.float64),
                )
            )
        # Version 1 had no frame: its lattices are aligned with the axes.
        frame = data.get(f"{prefix}frame")
        return LatticeDeformation(tuple(levels), None if frame is None else frame)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"`path`: {os.fspath(path)!r} is not a valid deformation: {exc}") from exc


def _holds(path: Any, kind: str) -> bool:
    """Whether ``path`` is a readable archive of ``kind`` (for error messages)."""
    try:
        with np.load(os.fspath(path), allow_pickle=False) as data:
            return "format" in data and str(data["format"]) == kind
    except Exception:  # empty, truncated, not a zip: the reader called next says which
        return False


@dataclass(frozen=True, eq=False)
class PartitionedDeformation:
    """One map of space made of one :class:`LatticeDeformation` per part of the template.

    A point moves with the deformation of the part of its nearest site (the rigidly aligned
    template vertices, labelled by part): the map of ``registration_elastic(...,
    parts='connected')``, where each connected component of the template has its own lattice
    hierarchy. Each part's map is continuous; the whole is not across the surfaces equidistant
    from two parts.

    Attributes
    ----------
    parts : tuple of LatticeDeformation
        One map per part.
    sites : (k, 3) ndarray
        Points that route the map (in the space the deformation applies to).
    labels : (k,) int ndarray
        The part of each site, in ``[0, len(parts))``.
    """

    parts: tuple[LatticeDeformation, ...]
    sites: np.ndarray = field(repr=False)
    labels: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        parts = tuple(self.parts)
        if not parts:
            raise ValueError("`parts` must hold at least one LatticeDeformation, got none")
        for part in parts:
            if not isinstance(part, LatticeDeformation):
                raise TypeError(
                    f"`parts` must hold LatticeDeformation objects, got {type(part).__name__}"
                )
        sites = as_points(self.sites, "sites").copy()
        labels = np.asarray(self.labels)
        if labels.shape != (sites.shape[0],) or not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(
                f"`labels` must be {sites.shape[0]} integers (one per site), "
                f"got {labels.dtype} array of shape {labels.shape}"
            )
        if labels.min() < 0 or labels.max() >= len(parts):
            raise ValueError(
                f"`labels` must be in [0, {len(parts)}), got values in "
                f"[{labels.min()}, {labels.max()}]"
            )
        object.__setattr__(self, "parts", parts)
        object.__setattr__(self, "sites", sites)
        object.__setattr__(self, "labels", labels.astype(np.int64))
        object.__setattr__(self, "_tree", cKDTree(sites))

    def __repr__(self) -> str:
        return (
            f"PartitionedDeformation(parts={len(self.parts)}, sites={self.sites.shape[0]}, "
            f"max_displacement={self.max_displacement:.4g})"
        )

    @property
    def max_displacement(self) -> float:
        """Largest bound over the parts (see :attr:`LatticeDeformation.max_displacement`)."""
        return max(part.max_displacement for part in self.parts)

    def part_of(self, points: Any) -> np.ndarray:
        """The part each point moves with (that of its nearest site), ``(n,)``."""
        pts = as_points(points, "points", allow_empty=True)
        if pts.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        return self.labels[self._tree.query(pts)[1]]  # type: ignore[attr-defined]

    def _per_part(self, points: Any, value: str, shape: tuple[int, ...]) -> np.ndarray:
        pts = as_points(points, "points", allow_empty=True)
        part = self.part_of(pts)
        out = np.zeros((pts.shape[0], *shape))
        for k, deformation in enumerate(self.parts):
            sel = part == k
            if sel.any():
                out[sel] = getattr(deformation, value)(pts[sel])
        return out

    def displacement(self, points: Any) -> np.ndarray:
        """``T(x) - x`` at ``points (n, 3)``."""
        return self._per_part(points, "displacement", (3,))

    def transform(self, points: Any) -> np.ndarray:
        """Apply the map: ``T(points)`` as a new ``(n, 3)`` array (the input is not modified)."""
        pts = as_points(points, "points", allow_empty=True)
        return pts + self.displacement(pts)

    def jacobian(self, points: Any) -> np.ndarray:
        """``dT/dx`` at ``points``, ``(n, 3, 3)``: each part's own."""
        return self._per_part(points, "jacobian", (3, 3))

    def jacobian_determinant(self, points: Any) -> np.ndarray:
        """``det(dT/dx)`` at ``points``."""
        return det3(self.jacobian(points))

    def inverse_transform(self, points: Any, *, max_iterations: int = 50) -> np.ndarray:
        """``x`` with ``T(x) = points``, ``(n, 3)``: as
        :meth:`LatticeDeformation.inverse_transform` (Newton's method; near a boundary between
        parts the point found is the one whose part maps it there)."""
        return _inverse_points(self, points, max_iterations=max_iterations)

    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> str:
        """Write the map (every part, the sites and labels) to a ``.npz`` file (atomically)."""
        arrays: dict[str, Any] = {
            "number_of_parts": np.array(len(self.parts)),
            "sites": self.sites,
            "labels": self.labels,
        }
        for k, part in enumerate(self.parts):
            arrays.update(_lattice_arrays(part, f"part{k}_"))
        return write_archive(
            path,
            arrays,
            kind=_PARTITIONED_FORMAT,
            version=_PARTITIONED_VERSION,
            overwrite=overwrite,
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> PartitionedDeformation:
        """Read a map written by :meth:`save`."""
        data = read_archive(
            path,
            kind=_PARTITIONED_FORMAT,
            version=_PARTITIONED_VERSION,
            what="PartitionedDeformation",
        )
        try:
            count = int(data["number_of_parts"])
            sites, labels = data["sites"].astype(np.float64), data["labels"].astype(np.int64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"`path`: {os.fspath(path)!r} is not a valid deformation: {exc}"
            ) from exc
        if count < 1:
            raise ValueError(f"`path`: {os.fspath(path)!r} has number_of_parts {count}")
        parts = tuple(_lattice_from(data, f"part{k}_", path) for k in range(count))
        return cls(parts, sites, labels)


def load_deformation(path: str | os.PathLike[str]) -> LatticeDeformation | PartitionedDeformation:
    """Read any deformation o3dreg writes (``o3dreg register --deformation``, batch folders).

    Returns
    -------
    LatticeDeformation or PartitionedDeformation
        Whichever the file holds (a :class:`PartitionedDeformation` for registrations with
        ``parts='connected'`` of a template with several parts).
    """
    if _holds(path, _PARTITIONED_FORMAT):
        return PartitionedDeformation.load(path)
    return LatticeDeformation.load(path)


def _inverse_points(
    deformation: LatticeDeformation | PartitionedDeformation,
    points: Any,
    *,
    max_iterations: int = 50,
) -> np.ndarray:
    """``x`` with ``T(x) = points``: see :meth:`LatticeDeformation.inverse_transform`."""
    target = as_points(points, "points", allow_empty=True)
    max_iterations = check_positive(max_iterations, "max_iterations", integer=True, allow_zero=True)
    if target.shape[0] == 0:
        return target.copy()
    tolerance = 1e-9 * max(1.0, float(np.abs(target).max()))
    x = target - deformation.displacement(target)
    residual = deformation.transform(x) - target
    norm = row_norms(residual)
    for _ in range(max_iterations):
        active = np.flatnonzero(norm > tolerance)
        if active.size == 0:
            break
        jacobian = deformation.jacobian(x[active])
        singular = np.abs(det3(jacobian)) <= 1e-12
        jacobian[singular] = np.eye(3)  # a fixed-point step there: x - (T(x) - points)
        step = np.linalg.solve(jacobian, residual[active][..., None])[..., 0]
        trial = x[active] - step
        moved = deformation.transform(trial) - target[active]
        trial_norm = row_norms(moved)
        scale = np.ones(active.size)
        for _ in range(19):
            # Only the points whose step did not lower their residual take a halved one.
            worse = np.flatnonzero(trial_norm >= norm[active])
            if not worse.size:
                break
            scale[worse] *= 0.5
            trial[worse] = x[active[worse]] - scale[worse, None] * step[worse]
            moved[worse] = deformation.transform(trial[worse]) - target[active[worse]]
            trial_norm[worse] = row_norms(moved[worse])
        better = trial_norm < norm[active]  # a point no halving improved stays where it was
        kept = active[better]
        x[kept], residual[kept], norm[kept] = trial[better], moved[better], trial_norm[better]
    left = norm > tolerance
    if left.any():
        raise ValueError(
            f"{int(left.sum())} of {target.shape[0]} points have no inverse image within "
            f"{max_iterations} Newton steps (largest residual {norm.max():.3g}): the map folds "
            "there or is singular; check min_jacobian_determinant"
        )
    return x
