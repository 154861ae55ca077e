"""The body's upper-triangle pattern extended by the entries of extra terms (contact).

Contact terms couple nodes that share no element (a lip node and the facet of the other lip
it touches), so their stiffness falls partly outside the body's fixed sparsity pattern. Adding
them as sparse matrices (`K_body + triu(K_term)`) rebuilds the whole global matrix at every
Newton iteration and changes its pattern whenever the contact pairs change, which makes the
sparse direct solver redo its symbolic analysis. Here the pattern is the union of the body's
pattern, the node pairs a term declares it may couple (`coupling_pairs()`, e.g. every slave
node with the master facets near it) and every entry a term has produced so far: it only
grows, so after the first iterations the global matrix has a constant pattern and the term
values are summed into its data array by position (the symmetric part 0.5 (K + K^T) of each
term matrix, upper triangle), with no sparse-matrix arithmetic on the global matrix.

The pattern is kept block-complete (whole 3x3 node blocks; the upper half of the diagonal
ones), so that row 3i+a holds the 3 - a entries of node i's diagonal block and then three
entries per coupled node j > i in increasing order. Local nodal frames (the transformed
unknowns u_hat_i = R_i u_i of `solver.bc.LocalFrame`) then act block by block on the data
array in place, K_hat_ij = R_i K_ij R_j^T (`rotate_blocks`), instead of the sparse product
T K T^T of the whole matrix.
"""
from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp

__all__ = ["ExtendedPattern", "rotate_blocks"]


def _csr_keys(indptr, indices, n):
    """Entry keys row * n + column of a CSR pattern (ascending for sorted rows)."""
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    return rows * n + indices.astype(np.int64)


class ExtendedPattern:
    """Upper-triangle CSR pattern = body pattern + term entries (grows, never shrinks).

    body: the body's `UpperPattern` (n_dofs, indptr, indices). node_pairs: optional (k, 2)
    node pairs whose 3x3 blocks are reserved from the start. `indptr`, `indices`, `rows`,
    `diagonal` describe the current pattern; `grown` counts the growths after construction.
    """

    def __init__(self, body, node_pairs=None):
        self.n_dofs = int(body.n_dofs)
        self._body_keys = _csr_keys(body.indptr, body.indices, self.n_dofs)
        self.grown = 0
        self._set_keys(self._body_keys)
        nodes = np.arange(self.n_dofs // 3)
        pairs = np.stack([nodes, nodes], axis=1)        # every diagonal block complete
        if node_pairs is not None and len(node_pairs):
            pairs = np.vstack([pairs, np.asarray(node_pairs, dtype=np.int64).reshape(-1, 2)])
        self._insert_blocks(pairs[:, 0], pairs[:, 1])

    def _insert_blocks(self, i, j):
        """Add the whole 3x3 blocks of node pairs (i, j) (upper triangle)."""
        a = (3 * np.asarray(i, dtype=np.int64)[:, None] + np.arange(3))[:, :, None]
        b = (3 * np.asarray(j, dtype=np.int64)[:, None] + np.arange(3))[:, None, :]
        r, c = np.broadcast_arrays(a, b)
        self._insert((np.minimum(r, c) * self.n_dofs + np.maximum(r, c)).ravel())

    @property
    def nnz(self) -> int:
        return len(self.keys)

    def _insert(self, keys):
        """Add entry keys (row * n + column) to the pattern (a merge: the pattern's keys are
        sorted, the new ones few)."""
        new = np.unique(keys)
        pos = np.searchsorted(self.keys, new)
        absent = pos == len(self.keys)
        absent[~absent] = self.keys[pos[~absent]] != new[~absent]
        if np.any(absent):
            self._set_keys(np.insert(self.keys, pos[absent], new[absent]))

    def _set_keys(self, keys):
        n = self.n_dofs
        self.keys = keys
        self.rows = keys // n
        self.indices = (keys % n).astype(np.int32)
        counts = np.bincount(self.rows, minlength=n)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.diagonal = np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))
        self.body_positions = np.searchsorted(keys, self._body_keys)
        self.identity = len(keys) == len(self._body_keys)

    def data(self, body_data, term_matrices=()) -> np.ndarray:
        """Data array on this pattern: the body's values plus the symmetric part of each of
        `term_matrices` (scipy sparse (n, n) matrices); grows the pattern first if a term has
        entries outside it."""
        coos = [K.tocoo() for K in term_matrices if K is not None and K.nnz]
        if not coos:
            out = np.zeros(self.nnz)
            out[self.body_positions] = body_data
            return out
        r = np.concatenate([K.row for K in coos]).astype(np.int64)
        c = np.concatenate([K.col for K in coos]).astype(np.int64)
        v = np.concatenate([K.data for K in coos])
        keep = v != 0.0
        r, c, v = r[keep], c[keep], v[keep]
        # symmetric part, upper triangle: K_ii on the diagonal, (K_ij + K_ji) / 2 above it
        v = np.where(r == c, v, 0.5 * v)
        key = np.minimum(r, c) * self.n_dofs + np.maximum(r, c)
        pos = np.searchsorted(self.keys, key)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == key[found]
        if not np.all(found):
            new = key[~found]
            self._insert_blocks(new // self.n_dofs // 3, new % self.n_dofs // 3)
            self.grown += 1
            pos = np.searchsorted(self.keys, key)
        out = np.zeros(self.nnz)
        out[self.body_positions] = body_data
        np.add.at(out, pos, v)
        return out

    def matrix(self, data) -> sp.csr_matrix:
        """The upper-triangle CSR matrix holding `data` (sorted indices)."""
        A = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))
        A.has_sorted_indices = True
        return A


@nb.njit(cache=True)
def _rotate_blocks(indptr, indices, data, rot, has_frame):
    n = rot.shape[0]
    B = np.empty((3, 3))
    for i in range(n):
        p0, p1, p2 = indptr[3 * i], indptr[3 * i + 1], indptr[3 * i + 2]
        if has_frame[i]:                    # the diagonal block, from its upper half
            B[0, 0], B[0, 1], B[0, 2] = data[p0], data[p0 + 1], data[p0 + 2]
            B[1, 1], B[1, 2], B[2, 2] = data[p1], data[p1 + 1], data[p2]
            B[1, 0], B[2, 0], B[2, 1] = B[0, 1], B[0, 2], B[1, 2]
            C = rot[i] @ B @ rot[i].T
            data[p0], data[p0 + 1], data[p0 + 2] = C[0, 0], C[0, 1], C[0, 2]
            data[p1], data[p1 + 1], data[p2] = C[1, 1], C[1, 2], C[2, 2]
        for m in range((indptr[3 * i + 1] - p0 - 3) // 3):
            q0, q1, q2 = p0 + 3 + 3 * m, p1 + 2 + 3 * m, p2 + 1 + 3 * m
            j = indices[q0] // 3
            if not (has_frame[i] or has_frame[j]):
                continue
            for b in range(3):
                B[0, b], B[1, b], B[2, b] = data[q0 + b], data[q1 + b], data[q2 + b]
            C = rot[i] @ B @ rot[j].T
            for b in range(3):
                data[q0 + b], data[q1 + b], data[q2 + b] = C[0, b], C[1, b], C[2, b]


def rotate_blocks(pattern: ExtendedPattern, data: np.ndarray, rot: np.ndarray,
                  has_frame: np.ndarray) -> None:
    """K_hat = T K T^T in place on the upper-triangle `data` of the block-complete `pattern`,
    T = blockdiag(rot[i]); only blocks touching a node with a frame change."""
    _rotate_blocks(pattern.indptr, pattern.indices, data, np.ascontiguousarray(rot, dtype=float),
                   np.asarray(has_frame, dtype=np.bool_))
