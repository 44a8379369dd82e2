"""The normal equations of one level on a sparsity pattern fixed for the level.

Every data term of a level moves the template points ``y_i = base_i + W_i u`` with the same
constant trilinear weights ``W`` (at most 8 free nodes per point), and its share of ``J^T J`` is
``sum_i (W_i^T W_i) (x) M_i`` with a symmetric 3x3 matrix ``M_i`` per point (``w_i g_i g_i^T``
for a point-to-surface row, ``s_i^2 I`` for a barycentre row), its share of ``J^T r`` is
``sum_i W_i^T (x) f_i``. So the pattern of ``J^T J`` (node pairs sharing a cell, plus the
regulariser's stencils) and the factor ``W_ia W_ib`` of every point in every pair are known when
the level starts. :class:`NormalAssembly` computes them once; each linearisation is then one
sparse product ``S @ M`` (``S`` the pair factors, ``(pairs, points)``) and a 3x3-block
sparse matrix built on the stored pattern, instead of sparse-times-sparse products whose
pattern scipy rediscovers at every step.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh.distinct import distinct

#: The 6 distinct entries of a symmetric 3x3 matrix, as (row, column), in column order of the
#: ``(n, 6)`` arrays of :meth:`NormalAssembly.matrix`.
SYMMETRIC_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_FULL = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


def symmetric_outer(v: np.ndarray) -> np.ndarray:
    """The 6 distinct entries of ``v_i v_i^T`` for every row of ``v`` ``(n, 3)``: ``(n, 6)``."""
    return np.stack([v[:, a] * v[:, b] for a, b in SYMMETRIC_ENTRIES], axis=1)


class NormalAssembly:
    """Pattern and pair factors of a level's normal equations, and the trilinear weight matrix
    ``W`` (``(n, m)``, free nodes only) they come from.

    Parameters
    ----------
    nodes : (n, 8) int ndarray
        The free-node index of each point's 8 cell corners, ``-1`` for a fixed node.
    weights : (n, 8) ndarray
        Their trilinear weights.
    number_of_free_nodes : int
    node_gram : (m, m) sparse matrix
        A constant node-level matrix added to the diagonal of every 3x3 block (the
        regulariser's ``D^T D``); its pattern joins the points' pattern.
    cells : (n,) int ndarray
        One key per point, equal for points of the same cell (its first corner's lattice node
        number).
    """

    def __init__(
        self,
        nodes: np.ndarray,
        weights: np.ndarray,
        number_of_free_nodes: int,
        node_gram: sp.spmatrix,
        cells: np.ndarray,
    ) -> None:
        m = int(number_of_free_nodes)
        n = nodes.shape[0]
        self.number_of_free_nodes = m
        # Points of one cell share their 8 nodes: the node pairs are found per cell (a few
        # hundred to a few thousand), then looked up for every point.
        _, first, cell_of = np.unique(cells, return_index=True, return_inverse=True)
        cells = nodes[first]
        cell_of = cell_of.ravel()
        a = np.broadcast_to(cells[:, :, None], (cells.shape[0], 8, 8))
        b = np.broadcast_to(cells[:, None, :], (cells.shape[0], 8, 8))
        cell_valid = (a >= 0) & (b >= 0)
        cell_key = np.where(cell_valid, a.astype(np.int64) * m + b, -1)
        gram = sp.coo_matrix(node_gram)
        gram_key = gram.row.astype(np.int64) * m + gram.col
        # Sorted: row-major, the CSR order.
        keys = distinct(np.concatenate([cell_key[cell_valid], gram_key]))
        self.indices = (keys % m).astype(np.int32) if m else np.zeros(0, np.int32)
        self.indptr = np.searchsorted(keys // max(m, 1), np.arange(m + 1)).astype(np.int32)
        self.pairs = keys.size
        cell_slot = np.searchsorted(keys, cell_key)
        # S[pair, point] = W_ia W_ib: the node-level matrix of per-point scalars c is S @ c
        # (:meth:`pair_sums`). Held for the pairs a <= b only (``_half``): the row of (b, a) is
        # that of (a, b) (the same products, W_ib W_ia), copied by ``_mirror``.
        upper = cell_valid & (a <= b)
        valid = upper[cell_of]
        point = np.broadcast_to(np.arange(n)[:, None, None], (n, 8, 8))[valid]
        factor = (weights[:, :, None] * weights[:, None, :])[valid]
        self._half = sp.csr_matrix(
            (factor, (cell_slot[cell_of][valid], point)), shape=(self.pairs, n)
        )
        row, col = keys // max(m, 1), keys % max(m, 1)
        self._mirror = np.searchsorted(keys, np.minimum(row, col) * m + np.maximum(row, col))
        # The regulariser's pairs are distinct entries of a sparse product.
        self.gram_values = np.zeros(self.pairs)
        self.gram_values[np.searchsorted(keys, gram_key)] = gram.data
        # The trilinear weights W (n, m) of the free nodes, and W^T for the right-hand sides.
        rows_w = np.broadcast_to(np.arange(n)[:, None], nodes.shape)
        keep = nodes >= 0
        self.W = sp.csr_matrix((weights[keep], (rows_w[keep], nodes[keep])), shape=(n, m))
        self.WT = self.W.T.tocsr()

    def matrix(
        self, metric: np.ndarray, isotropic: np.ndarray | None = None, with_gram: bool = True
    ) -> sp.bsr_matrix:
        """``sum_i (W_i^T W_i) (x) M_i (+ node_gram (x) I_3)`` as a 3x3-block matrix.

        ``metric`` holds the 6 entries of every ``M_i`` (``(n, 6)``, :data:`SYMMETRIC_ENTRIES`);
        ``isotropic`` (``(n,)``) adds ``c_i I`` to ``M_i``.
        """
        values = self.pair_sums(metric)  # (pairs, 6)
        diagonal = self.gram_values if with_gram else np.zeros(self.pairs)
        if isotropic is not None:
            diagonal = diagonal + self.pair_sums(isotropic)
        blocks = values[:, _FULL]  # (pairs, 3, 3)
        for k in range(3):
            blocks[:, k, k] += diagonal
        m = self.number_of_free_nodes
        return sp.bsr_matrix((blocks, self.indices, self.indptr), shape=(3 * m, 3 * m))

    def pair_sums(self, c: np.ndarray) -> np.ndarray:
        """``S @ c`` for per-point values ``c`` (``(n,)`` or ``(n, k)``)."""
        values = np.asarray(c, dtype=np.float64)
        if values.shape[0] != self._half.shape[1]:
            raise ValueError(
                f"expected values for {self._half.shape[1]} points, got {values.shape}"
            )
        return np.asarray(self._half @ values).take(self._mirror, axis=0)

    def vector(self, f: np.ndarray) -> np.ndarray:
        """``sum_i W_i^T (x) f_i`` for per-point vectors ``f`` ``(n, 3)``, flattened node-major."""
        return np.asarray(self.WT @ f).ravel()
