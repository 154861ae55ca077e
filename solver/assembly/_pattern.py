"""The sparsity pattern of the global tangent, built once per mesh and refilled every iteration.

Only the upper triangle (row <= column) of the symmetric tangent is stored, in CSR form with
sorted column indices — the layout that PARDISO's symmetric matrix types and CHOLMOD (as the
lower triangle of the transposed CSC matrix) consume directly. For every element and every
local pair (r <= c) of its 24 degrees of freedom, `slots` gives the position of that entry in the
CSR data array, so refilling the matrix is a single scatter-add. The pattern is built from the
node graph (numba kernels: neighbour lists, then 3x3 node blocks, then the slots by binary
search in the sorted neighbour lists), without sorting the m x 300 element pairs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from solver.assembly._kernels import upper_pairs

__all__ = ["UpperPattern", "element_dofs"]


def element_dofs(cells: np.ndarray) -> np.ndarray:
    """Global dofs (node-major: 3i, 3i+1, 3i+2) of each cell -> (m, 3 * nodes_per_cell)."""
    cells = np.asarray(cells, dtype=np.int64)
    return (3 * cells[:, :, None] + np.arange(3)[None, None, :]).reshape(len(cells), -1)


@dataclass(frozen=True, eq=False)
class UpperPattern:
    """CSR upper-triangle pattern for cells (m, k) and the scatter slots (m, n_pairs)."""

    n_dofs: int
    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray
    local_rows: np.ndarray
    local_cols: np.ndarray
    dofs: np.ndarray
    diagonal: np.ndarray        # position of each diagonal entry in the data array

    @classmethod
    def build(cls, cells: np.ndarray, n_nodes: int) -> "UpperPattern":
        cells = np.ascontiguousarray(cells, dtype=np.int64)
        dofs = element_dofs(cells)
        n_dofs = 3 * n_nodes
        lr, lc = upper_pairs(dofs.shape[1])
        # node graph (each node's neighbours j >= i through shared cells, sorted), then the
        # dof pattern of its 3x3 blocks and the slot of every element pair: one numba pass
        # each, no sort of the m * 300 element pairs
        order = np.argsort(cells.ravel(), kind="stable")
        cell_ptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.add.at(cell_ptr, cells.ravel() + 1, 1)
        cell_ptr = np.cumsum(cell_ptr)
        node_cells = order // cells.shape[1]
        nptr, nbr = _node_graph(cells, cell_ptr, node_cells, n_nodes)
        indptr, indices, diagonal = _dof_pattern(nptr, nbr, np.diff(cell_ptr) > 0, n_nodes)
        index_dtype = np.int32 if n_dofs < 2**31 else np.int64
        slots = _element_slots(cells, nptr, nbr, indptr, lr, lc)
        slot_dtype = np.int32 if len(indices) < 2**31 - 1 else np.int64
        return cls(n_dofs, indptr, indices.astype(index_dtype), slots.astype(slot_dtype), lr, lc,
                   dofs, diagonal)

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The upper-triangle CSR matrix holding `data` (no copy of the pattern arrays)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))


@nb.njit(cache=True)
def _node_graph(cells, cell_ptr, node_cells, n_nodes):
    """Sorted upper neighbour lists (j >= i, i itself first) of the node graph, CSR."""
    k = cells.shape[1]
    mark = np.full(n_nodes, -1, dtype=np.int64)
    count = np.zeros(n_nodes + 1, dtype=np.int64)
    for i in range(n_nodes):
        c = 1
        mark[i] = i
        for p in range(cell_ptr[i], cell_ptr[i + 1]):
            e = node_cells[p]
            for a in range(k):
                j = cells[e, a]
                if j > i and mark[j] != i:
                    mark[j] = i
                    c += 1
        count[i + 1] = c
    nptr = np.cumsum(count)
    nbr = np.empty(nptr[-1], dtype=np.int64)
    mark[:] = -1
    for i in range(n_nodes):
        pos = nptr[i]
        nbr[pos] = i
        pos += 1
        mark[i] = i
        for p in range(cell_ptr[i], cell_ptr[i + 1]):
            e = node_cells[p]
            for a in range(k):
                j = cells[e, a]
                if j > i and mark[j] != i:
                    mark[j] = i
                    nbr[pos] = j
                    pos += 1
        nbr[nptr[i] + 1:pos] = np.sort(nbr[nptr[i] + 1:pos])
    return nptr, nbr


@nb.njit(cache=True)
def _dof_pattern(nptr, nbr, used, n_nodes):
    """Upper-triangle CSR of the 3x3 node blocks: row 3i+a holds 3i+a..3i+2, then 3j..3j+2
    for each neighbour j > i in order (a node in no cell: its diagonal entries only). Also the
    position of each diagonal entry."""
    n_dofs = 3 * n_nodes
    indptr = np.zeros(n_dofs + 1, dtype=np.int64)
    for i in range(n_nodes):
        deg = nptr[i + 1] - nptr[i] - 1
        for a in range(3):
            indptr[3 * i + a + 1] = (3 - a) + 3 * deg if used[i] else 1
    for r in range(n_dofs):
        indptr[r + 1] += indptr[r]
    indices = np.empty(indptr[-1], dtype=np.int64)
    diagonal = np.empty(n_dofs, dtype=np.int64)
    for i in range(n_nodes):
        for a in range(3):
            r = 3 * i + a
            pos = indptr[r]
            diagonal[r] = pos
            if not used[i]:
                indices[pos] = r
                continue
            for b in range(a, 3):
                indices[pos] = 3 * i + b
                pos += 1
            for p in range(nptr[i] + 1, nptr[i + 1]):
                j = nbr[p]
                for b in range(3):
                    indices[pos] = 3 * j + b
                    pos += 1
    return indptr, indices, diagonal


@nb.njit(cache=True)
def _element_slots(cells, nptr, nbr, indptr, lr, lc):
    """Position in the CSR data of every local upper pair (lr[p] <= lc[p]) of every cell."""
    m, k = cells.shape
    npair = lr.shape[0]
    slots = np.empty((m, npair), dtype=np.int64)
    for e in range(m):
        for p in range(npair):
            na = cells[e, lr[p] // 3]
            ia = lr[p] % 3
            nb_ = cells[e, lc[p] // 3]
            ib = lc[p] % 3
            ra = 3 * na + ia
            rb = 3 * nb_ + ib
            if ra > rb:
                na, nb_ = nb_, na
                ia, ib = ib, ia
            row = 3 * na + ia
            if na == nb_:
                slots[e, p] = indptr[row] + (ib - ia)
            else:
                lo = nptr[na] + 1
                hi = nptr[na + 1]
                while lo < hi:          # binary search of nb_ in na's sorted neighbours
                    mid = (lo + hi) // 2
                    if nbr[mid] < nb_:
                        lo = mid + 1
                    else:
                        hi = mid
                slots[e, p] = indptr[row] + (3 - ia) + 3 * (lo - nptr[na] - 1) + ib
    return slots
