"""The body's upper-triangle pattern extended by the entries of extra terms (contact).

Contact terms couple nodes that share no element (a node of one surface and the facet of
the other it touches), so their stiffness falls partly outside the body's fixed sparsity pattern. Adding
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


def _sorted_unique(keys):
    """Sorted distinct values of an int64 array (sort, then drop repeats)."""
    k = np.sort(np.asarray(keys, dtype=np.int64), kind="stable")
    if len(k) == 0:
        return k
    keep = np.empty(len(k), dtype=bool)
    keep[0] = True
    np.not_equal(k[1:], k[:-1], out=keep[1:])
    return k[keep]


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
        nodes = np.arange(self.n_dofs // 3)
        pairs = np.stack([nodes, nodes], axis=1)        # every diagonal block complete
        if node_pairs is not None and len(node_pairs):
            pairs = np.vstack([pairs, np.asarray(node_pairs, dtype=np.int64).reshape(-1, 2)])
        # one pattern build: the body's keys and the blocks' keys, merged by a sort (cheaper
        # than np.union1d's hash-based unique on millions of keys)
        self._set_keys(_sorted_unique(np.concatenate(
            [self._body_keys, self._block_keys(pairs[:, 0], pairs[:, 1])])))

    def _block_keys(self, i, j):
        """Entry keys of the whole 3x3 blocks of node pairs (i, j) (upper triangle)."""
        a = (3 * np.asarray(i, dtype=np.int64)[:, None] + np.arange(3))[:, :, None]
        b = (3 * np.asarray(j, dtype=np.int64)[:, None] + np.arange(3))[:, None, :]
        r, c = np.broadcast_arrays(a, b)
        return (np.minimum(r, c) * self.n_dofs + np.maximum(r, c)).ravel()

    def _insert_blocks(self, i, j):
        """Add the whole 3x3 blocks of node pairs (i, j) (upper triangle)."""
        self._insert(self._block_keys(i, j))

    @property
    def nnz(self) -> int:
        return len(self.keys)

    def _insert(self, keys):
        """Add entry keys (row * n + column) to the pattern (a merge: the pattern's keys are
        sorted, the new ones few)."""
        new = _sorted_unique(keys)
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
        out = np.zeros(self.nnz)
        _place(self.body_positions, np.ascontiguousarray(body_data, dtype=float), out)
        if not coos:
            return out
        r = np.concatenate([K.row for K in coos]).astype(np.int64)
        c = np.concatenate([K.col for K in coos]).astype(np.int64)
        v = np.concatenate([K.data for K in coos]).astype(float)
        # symmetric part, upper triangle: K_ii on the diagonal, (K_ij + K_ji) / 2 above it,
        # each entry found by a binary search within its row (numba: no global key search)
        while True:
            missing = _add_symmetric_part(self.indptr, self.indices, r, c, v, out)
            if missing < 0:
                return out
            # entries outside the pattern (rare: the pairs are reserved): grow, start again
            lo, hi = np.minimum(r, c), np.maximum(r, c)
            key = lo * self.n_dofs + hi
            pos = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
            new = key[(self.keys[pos] != key) & (v != 0.0)]
            self._insert_blocks(new // self.n_dofs // 3, new % self.n_dofs // 3)
            self.grown += 1
            out = np.zeros(self.nnz)
            _place(self.body_positions, np.ascontiguousarray(body_data, dtype=float), out)

    def matrix(self, data) -> sp.csr_matrix:
        """The upper-triangle CSR matrix holding `data` (sorted indices)."""
        A = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))
        A.has_sorted_indices = True
        return A


@nb.njit(cache=True)
def _place(positions, values, out):
    """out[positions] = values (the body's entries in the extended pattern)."""
    for k in range(len(positions)):
        out[positions[k]] = values[k]


@nb.njit(cache=True)
def _add_symmetric_part(indptr, indices, rows, cols, vals, out):
    """Add the symmetric part of the COO entries to the upper-triangle data `out`: K_ii on
    the diagonal, K_ij / 2 at (min, max) otherwise; each position by a binary search in its
    row's sorted column indices. Returns -1, or the index of an entry outside the pattern
    (then `out` is incomplete)."""
    for k in range(len(rows)):
        v = vals[k]
        if v == 0.0:
            continue
        i, j = rows[k], cols[k]
        if i > j:
            i, j = j, i
        if i != j:
            v *= 0.5
        lo, hi = indptr[i], indptr[i + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if indices[mid] < j:
                lo = mid + 1
            else:
                hi = mid
        if lo == indptr[i + 1] or indices[lo] != j:
            return k
        out[lo] += v
    return -1


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
