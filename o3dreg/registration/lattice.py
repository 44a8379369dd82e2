"""Trilinear lattices: the elementary cubes of eq. (1) of Berar et al. (2005).

A lattice covers an axis-aligned box split into ``shape = (nx, ny, nz)`` cells and stores one
displacement vector per node. Inside a cell the displacement is the trilinear interpolation of its
8 corner nodes, which is exactly the map ``[1, x, y, z, xy, yz, zx, xyz] -> R^3`` of eq. (1);
parametrising by node displacements makes the field continuous across cell faces by construction.
Points outside the box take the displacement of the nearest point of the box (clamping), so the
field is continuous everywhere.

Nodes are numbered ``(i * (ny + 1) + j) * (nz + 1) + k`` for node ``(i, j, k)`` along ``(x, y, z)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..mesh.distinct import distinct

__all__ = ["TrilinearLattice", "corner_offsets"]


def corner_offsets() -> np.ndarray:
    """The 8 cell corners as ``(8, 3)`` bits ``(a, b, c)``, ``a`` along x."""
    return np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


_CORNERS = corner_offsets()


def _corner_products(fx: Factors, fy: Factors, fz: Factors) -> np.ndarray:
    """``fx[a] * fy[b] * fz[c]`` for the 8 corners ``(a, b, c)`` of :data:`_CORNERS`
    (``4 a + 2 b + c``): ``(n, 8)``, from each axis's two factors (``(n,)`` columns: products of
    whole columns, several times faster than broadcasting over small axes)."""
    xy = [fx[a] * fy[b] for a in (0, 1) for b in (0, 1)]
    return np.stack([xy[k >> 1] * fz[k & 1] for k in range(8)], axis=1)


#: Per axis, the factors of bit 0 and bit 1 of every point's corners (``(n,)`` each).
Factors = tuple[np.ndarray, np.ndarray]


def _factors(t: np.ndarray) -> tuple[Factors, Factors, Factors]:
    """The trilinear factors ``(1 - t, t)`` of each axis from local coordinates ``t (n, 3)``."""
    x, y, z = np.ascontiguousarray(t.T)
    return (1.0 - x, x), (1.0 - y, y), (1.0 - z, z)


def cell_counts(shape: Any) -> tuple[int, int, int]:
    """``shape`` as 3 positive integer cell counts, or a ``ValueError`` naming it."""
    given = tuple(shape) if isinstance(shape, (tuple, list, np.ndarray)) else (shape,)
    if len(given) != 3 or not all(
        isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 1 for s in given
    ):
        raise ValueError(f"`shape` must be 3 positive integer cell counts, got {shape!r}")
    return (int(given[0]), int(given[1]), int(given[2]))


#: Most nodes of one lattice: 257^3, 0.4 GB of displacements (a 256-cell refinement).
MAX_NODES = 257**3


@dataclass(frozen=True, eq=False)
class TrilinearLattice:
    """A trilinear displacement field on a regular grid of cells.

    Attributes
    ----------
    origin : (3,) ndarray
        World coordinates of the box's minimum corner (node ``(0, 0, 0)``), in the input's units.
    size : (3,) ndarray
        Box extent along x, y, z.
    shape : tuple of 3 int
        Number of cells along x, y, z.
    displacements : (nx + 1, ny + 1, nz + 1, 3) ndarray
        Displacement vector at every node. Zero means the identity map.
    """

    origin: np.ndarray
    size: np.ndarray
    shape: tuple[int, int, int]
    displacements: np.ndarray = field(repr=False)

    @classmethod
    def zeros(cls, origin, size, shape) -> TrilinearLattice:
        """An identity lattice (all displacements zero)."""
        shape = cell_counts(shape)
        count = int(np.prod([s + 1 for s in shape], dtype=np.float64))
        if count > MAX_NODES:
            raise ValueError(
                f"`shape` must have at most {MAX_NODES} nodes (24 bytes of displacements each), "
                f"got {shape}: {count} nodes"
            )
        nodes = tuple(s + 1 for s in shape) + (3,)
        return cls(origin, size, shape, np.zeros(nodes))  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        shape = cell_counts(self.shape)
        origin = np.array(self.origin, dtype=np.float64).reshape(-1)
        size = np.array(self.size, dtype=np.float64).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"`origin` must be 3 finite coordinates, got {origin.tolist()}")
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise ValueError(f"`size` must be 3 finite positive extents, got {size.tolist()}")
        # A value type: its own copy of the displacements, which no caller can change later.
        displacements = np.array(self.displacements, dtype=np.float64)
        expected = tuple(s + 1 for s in shape) + (3,)
        if displacements.shape != expected:
            raise ValueError(
                f"`displacements` must have shape {expected}, got {displacements.shape}"
            )
        if not np.all(np.isfinite(displacements)):
            raise ValueError("`displacements` must be finite (NaN or infinite values found)")
        for value in (origin, size, displacements):
            value.setflags(write=False)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "displacements", displacements)

    def __repr__(self) -> str:
        nx, ny, nz = self.shape
        return (
            f"TrilinearLattice(shape=({nx}, {ny}, {nz}), cell_size={np.round(self.cell_size, 4).tolist()}, "
            f"max_displacement={self.max_displacement:.4g})"
        )

    # -- geometry -------------------------------------------------------------------------------
    @property
    def cell_size(self) -> np.ndarray:
        """Edge lengths of one cell along x, y, z."""
        return self.size / np.asarray(self.shape, dtype=np.float64)

    @property
    def node_shape(self) -> tuple[int, int, int]:
        nx, ny, nz = self.shape
        return (nx + 1, ny + 1, nz + 1)

    @property
    def number_of_nodes(self) -> int:
        return int(np.prod(self.node_shape))

    @property
    def max_displacement(self) -> float:
        d = self.displacements.reshape(-1, 3)
        return float(np.sqrt((d * d).sum(axis=1)).max()) if d.size else 0.0

    def node_positions(self) -> np.ndarray:
        """World coordinates of all nodes, ``(number_of_nodes, 3)``, in node order."""
        axes = [
            self.origin[a] + self.cell_size[a] * np.arange(self.node_shape[a]) for a in range(3)
        ]
        grid = np.meshgrid(*axes, indexing="ij")
        return np.stack([g.ravel() for g in grid], axis=1)

    def node_index(self, ijk: np.ndarray) -> np.ndarray:
        """Flat node numbers of integer node coordinates ``(..., 3)``."""
        _, ny1, nz1 = self.node_shape
        return (ijk[..., 0] * ny1 + ijk[..., 1]) * nz1 + ijk[..., 2]

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell of each point and its local coordinates.

        Returns
        -------
        cells : (n, 3) int ndarray
            Cell index along x, y, z.
        local : (n, 3) ndarray
            Position inside the cell in ``[0, 1]^3`` (after clamping to the box).
        inside : (n, 3) bool ndarray
            Whether the point lies within the box along each axis (clamped axes have a zero
            derivative).
        """
        shape = np.asarray(self.shape)
        s = (points - self.origin) / self.cell_size
        inside = (s >= 0.0) & (s <= shape)
        s = np.clip(s, 0.0, shape)
        cells = np.minimum(np.floor(s).astype(np.int64), shape - 1)
        return cells, s - cells, inside

    def occupied_cells(self, points: np.ndarray) -> np.ndarray:
        """The cells holding at least one of ``points`` (clamped to the box), ``(k, 3)`` integer
        indices in lexicographic order (``np.unique(cells, axis=0)``)."""
        cells, _, _ = self.locate(points)
        flat = distinct(self.node_index(cells), self.number_of_nodes)
        _, ny1, nz1 = self.node_shape
        return np.stack([flat // (ny1 * nz1), (flat // nz1) % ny1, flat % nz1], axis=1)

    def cell_samples(self, cells: np.ndarray) -> np.ndarray:
        """8 interior points of each cell ``(k, 3)`` (integer indices), at local coordinates 1/4
        and 3/4 along each axis: where the Jacobian determinant of a trilinear map is sampled
        (it is a polynomial of degree 2 in each coordinate; these samples avoid the faces the
        cells share). Returns ``(8 k, 3)``, cell-major."""
        local = 0.25 + 0.5 * _CORNERS
        return self.origin + (cells[:, None, :] + local[None, :, :]).reshape(-1, 3) * self.cell_size

    def basis(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The 8 nodes of each point's cell, their trilinear weights and the weights' spatial
        derivatives: ``(n, 8)``, ``(n, 8)``, ``(n, 8, 3)`` with ``[p, k, a] = d w_k / d x_a``.

        The one place where the trilinear basis and its gradient are written. The derivative is
        exact inside each cell (one-sided on a cell face) and zero along axes where the point
        lies outside the box (the field is clamped there).
        """
        cells, t, inside = self.locate(points)
        fx, fy, fz = _factors(t)
        step = 1.0 / self.cell_size
        dx, dy, dz = (
            (np.where(inside[:, a], -step[a], 0.0), np.where(inside[:, a], step[a], 0.0))
            for a in range(3)
        )
        w = _corner_products(fx, fy, fz)
        grads = np.stack(
            [
                _corner_products(dx, fy, fz),
                _corner_products(fx, dy, fz),
                _corner_products(fx, fy, dz),
            ],
            axis=2,
        )
        nodes = self._corner_nodes(cells)
        return nodes, w, grads

    def weights(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 8 nodes of each point's cell and their trilinear weights.

        Returns
        -------
        nodes : (n, 8) int ndarray
        weights : (n, 8) ndarray
            Non-negative, summing to one for every point (partition of unity).
        """
        cells, t, _ = self.locate(points)
        return self._corner_nodes(cells), _corner_products(*_factors(t))

    def _corner_nodes(self, cells: np.ndarray) -> np.ndarray:
        """Flat numbers of the 8 corner nodes of each cell ``(n, 3)``, in :data:`_CORNERS`
        order: ``(n, 8)`` (the node numbering is linear in the node coordinates)."""
        return self.node_index(cells)[:, None] + self.node_index(_CORNERS)[None, :]

    def weight_matrix(self, points: np.ndarray) -> sp.csr_matrix:
        """Sparse ``(n, number_of_nodes)`` matrix ``W`` with ``displacement(points) = W @ D``."""
        nodes, w = self.weights(points)
        n = points.shape[0]
        rows = np.repeat(np.arange(n), 8)
        return sp.csr_matrix((w.ravel(), (rows, nodes.ravel())), shape=(n, self.number_of_nodes))

    # -- the field ------------------------------------------------------------------------------
    def displacement(self, points: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Displacement at ``points (n, 3)``; added to ``out`` (``(n, 3)``) when given."""
        return self._field(points, False, out)

    def displacement_gradient(
        self, points: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Spatial derivative of the displacement, ``(n, 3, 3)`` with ``[p, c, a] = d u_c / d x_a``;
        added to ``out`` when given.

        Exact inside each cell; on a cell face it is the one-sided derivative of the cell the point
        is assigned to. Zero along axes where the point lies outside the box (clamped field).
        """
        return self._field(points, True, out)

    def _field(self, points: np.ndarray, gradient: bool, out: np.ndarray | None) -> np.ndarray:
        """The displacement or its gradient at ``points`` (the weights of :meth:`weights` or
        :meth:`basis` summed over the 8 corners)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        shape = (pts.shape[0], 3, 3) if gradient else (pts.shape[0], 3)
        if out is not None and out.shape != shape:
            raise ValueError(f"`out` must have shape {shape}, got {out.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("the lattice's field is evaluated at finite points only")
        d = self.displacements.reshape(-1, 3)
        if gradient:
            nodes, _, grads = self.basis(pts)
            # (n, 3, 8) @ (n, 8, 3): a batched product, several times faster than einsum here.
            # take: a gather of rows several times faster than fancy indexing.
            field = np.matmul(d.take(nodes, axis=0).transpose(0, 2, 1), grads)
        else:
            nodes, w = self.weights(pts)
            field = np.einsum("nk,nkc->nc", w, d.take(nodes, axis=0))
        if out is None:
            return np.asarray(field)
        out += field
        return out

    def with_displacements(self, displacements: np.ndarray) -> TrilinearLattice:
        """A copy of this lattice with other node displacements."""
        return TrilinearLattice(
            self.origin,
            self.size,
            self.shape,
            np.asarray(displacements, dtype=np.float64).reshape(self.displacements.shape),
        )

    def refined(self, shape) -> TrilinearLattice:
        """The same field on a finer grid whose cell counts are multiples of this one's.

        A trilinear function restricted to a sub-cell is trilinear, so sampling the field at the
        new nodes reproduces it exactly: the map is unchanged.
        """
        shape = cell_counts(shape)
        if any(s % o for s, o in zip(shape, self.shape)):
            raise ValueError(
                f"`shape` must be 3 multiples of the lattice shape {self.shape}, got {shape}"
            )
        finer = TrilinearLattice.zeros(self.origin, self.size, shape)
        values = self.displacement(finer.node_positions())
        return finer.with_displacements(values)

    def same_box(self, other: TrilinearLattice) -> bool:
        return bool(np.allclose(self.origin, other.origin) and np.allclose(self.size, other.size))
