"""`solver.assembly.UpperPattern`: the upper-triangle CSR pattern built from the node graph
equals the one SciPy builds from all element dof pairs (exact integer equality), and scattering
element matrices through its slots equals SciPy's COO summation (round-off only: 1e-12 relative),
on a randomly renumbered block mesh with an isolated node (which keeps its diagonal entries).
"""
import numpy as np
import scipy.sparse as sp

from solver.assembly import UpperPattern, scatter_upper
from solver.examples import block


def test_pattern_and_scatter_match_scipy():
    rng = np.random.default_rng(0)
    nodes, hexes, _ = block((1.0, 1.0, 1.0), (3, 2, 4))
    n = len(nodes) + 1                                       # one node in no element
    hexes = rng.permutation(n)[hexes]
    pat = UpperPattern.build(hexes, n)
    m = len(hexes)
    Ke = rng.standard_normal((m, 24, 24))
    Ke = Ke + Ke.transpose(0, 2, 1)
    dofs = pat.dofs
    rows = np.repeat(dofs, 24, axis=1).ravel()
    cols = np.tile(dofs, (1, 24)).ravel()
    full = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    ref = sp.triu(full + sp.identity(3 * n) * 0.0, format="csr")
    ref.sort_indices()
    # reference pattern: every element pair plus every diagonal
    ones = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n, 3 * n))
    ref_pat = sp.triu(ones + sp.identity(3 * n), format="csr")
    ref_pat.sort_indices()
    assert np.array_equal(pat.indptr, ref_pat.indptr)
    assert np.array_equal(pat.indices, ref_pat.indices)
    assert np.array_equal(pat.indices[pat.diagonal], np.arange(3 * n))
    data = np.empty(pat.nnz)
    scatter_upper(Ke, pat.slots, pat.local_rows, pat.local_cols, data)
    A = pat.matrix(data)
    # element blocks are symmetric, so the upper pairs of each element carry all its entries
    # of the upper triangle; compare with SciPy's summation of the full element matrices
    diff = abs(A - ref).max()
    assert diff <= 1e-12 * abs(ref).max(), diff
