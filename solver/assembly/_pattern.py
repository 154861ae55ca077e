"""The sparsity pattern of the global tangent, built once per mesh and refilled every iteration.

Only the upper triangle (row <= column) of the symmetric tangent is stored, in CSR form with
sorted column indices — the layout that PARDISO's symmetric matrix types and CHOLMOD (as the
lower triangle of the transposed CSC matrix) consume directly. For every element and every
local pair (r <= c) of its 24 degrees of freedom, `slots` gives the position of that entry in the
CSR data array, so refilling the matrix is a single scatter-add.
"""
from __future__ import annotations

from dataclasses import dataclass

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
        dofs = element_dofs(cells)
        n_dofs = 3 * n_nodes
        lr, lc = upper_pairs(dofs.shape[1])
        gr = dofs[:, lr]
        gc = dofs[:, lc]
        row = np.minimum(gr, gc).ravel()
        col = np.maximum(gr, gc).ravel()
        key = row * n_dofs + col
        # every dof has a diagonal entry even if no element touches it (isolated nodes)
        diag_key = np.arange(n_dofs, dtype=np.int64) * (n_dofs + 1)
        ukey, inv = np.unique(np.concatenate([key, diag_key]), return_inverse=True)
        inv = inv.ravel()
        urow = ukey // n_dofs
        ucol = ukey % n_dofs
        indptr = np.zeros(n_dofs + 1, dtype=np.int64)
        np.add.at(indptr, urow + 1, 1)
        indptr = np.cumsum(indptr)
        slot_dtype = np.int32 if len(ukey) < 2**31 - 1 else np.int64
        slots = inv[: len(key)].reshape(len(cells), -1).astype(slot_dtype)
        diagonal = inv[len(key):].astype(np.int64)
        return cls(n_dofs, indptr, ucol.astype(np.int32 if n_dofs < 2**31 else np.int64),
                   slots, lr, lc, dofs, diagonal)

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The upper-triangle CSR matrix holding `data` (no copy of the pattern arrays)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))
