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


def test_extended_pattern_adds_term_matrices_by_position():
    """`ExtendedPattern`: body data + the symmetric part of term matrices (some entries
    outside the body pattern, some below the diagonal, an unsymmetric one) equals SciPy's
    triu(K_body + (K_t + K_t^T)/2) to round-off (1e-12 relative: the same sums in another
    order); the pattern grows once, by the whole 3x3 block of the new node pair, not again for
    the same entries, and node pairs reserved up front make it grow not at all."""
    from solver.assembly._extended import ExtendedPattern

    rng = np.random.default_rng(1)
    nodes, hexes, _ = block((1.0, 1.0, 1.0), (2, 2, 2))
    n = len(nodes)
    pat = UpperPattern.build(hexes, n)
    body = rng.standard_normal(pat.nnz)
    Kb = pat.matrix(body)
    far = (0, n - 1)                        # opposite corners: in no common element
    r = np.array([3 * far[0], 3 * far[1] + 2, 5, 7])
    c = np.array([3 * far[1] + 1, 3 * far[0], 5, 4])
    Kt = sp.csr_matrix((rng.standard_normal(4), (r, c)), shape=(3 * n, 3 * n))
    ext = ExtendedPattern(pat)
    data = ext.data(body, [Kt, 2.0 * Kt])
    assert ext.grown == 1 and ext.nnz == pat.nnz + 9
    ref = sp.triu(Kb + 1.5 * (Kt + Kt.T), format="csr")
    got = ext.matrix(data)
    assert abs(got - ref).max() <= 1e-12 * abs(ref).max()
    assert np.array_equal(ext.indices[ext.diagonal], np.arange(3 * n))
    ext.data(body, [Kt])
    assert ext.grown == 1
    reserved = ExtendedPattern(pat, node_pairs=[far])
    d2 = reserved.data(body, [Kt, 2.0 * Kt])
    assert reserved.grown == 0 and reserved.nnz == pat.nnz + 9    # the whole 3x3 block
    assert abs(reserved.matrix(d2) - ref).max() <= 1e-12 * abs(ref).max()


def test_rotate_blocks_equals_the_transformed_matrix():
    """`rotate_blocks` on the upper-triangle data equals triu(T K T^T) with T the block
    diagonal of the nodal rotations (random rotations on a third of the nodes, identity
    elsewhere; a term entry outside the body pattern included), to 1e-12 relative (the same
    products in another order)."""
    from scipy.spatial.transform import Rotation

    from solver.assembly._extended import ExtendedPattern, rotate_blocks

    rng = np.random.default_rng(2)
    nodes, hexes, _ = block((1.0, 1.0, 1.0), (2, 3, 2))
    n = len(nodes)
    pat = UpperPattern.build(hexes, n)
    body = rng.standard_normal(pat.nnz)
    Kt = sp.csr_matrix(([0.7], ([1], [3 * (n - 1) + 2])), shape=(3 * n, 3 * n))
    ext = ExtendedPattern(pat)
    data = ext.data(body, [Kt])
    K = ext.matrix(data.copy())
    K = (K + sp.triu(K, k=1).T).toarray()
    rot = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    framed = rng.random(n) < 1 / 3
    rot[framed] = Rotation.random(int(framed.sum()), random_state=3).as_matrix()
    T = sp.block_diag(list(rot)).toarray()
    ref = np.triu(T @ K @ T.T)
    rotate_blocks(ext, data, rot, framed)
    got = ext.matrix(data).toarray()
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()
