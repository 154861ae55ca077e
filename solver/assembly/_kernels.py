"""Numba kernels for the hexahedral solid: element tangent/residual and sparse refill.

For each element and Gauss point (total Lagrangian), with F the deformation gradient, S the
second Piola-Kirchhoff stress and CC its material tangent, the element contributions are
(Bonet & Wood, *Nonlinear Continuum Mechanics for FE Analysis*, 2008, ch. 8-9)

  f_ai  += dV F_iI S_IJ dN_a/dX_J
  K_aibk += dV [ dN_a/dX_J F_iI CC_IJKL F_kK dN_b/dX_L + delta_ik dN_a/dX_I S_IJ dN_b/dX_J ]

and a pressure-like volumetric part expressed with spatial gradients g_ai = dN_a/dx_i:

  f_ai  += p_q J dV g_ai,
  K_aibk += p_q J dV (g_ai g_bk - g_ak g_bi) + k_q J dV g_ai g_bk       (per Gauss point)
  K_aibk += k_e dv_ai dv_bk, with dv_ai = sum_q J dV g_ai                 (per element)

which covers the displacement formulation (p_q = U'(J), k_q = J U''(J), k_e = 0) and the
condensed Q1/P0 mean dilatation of Simo, Taylor & Pister (1985) (p_q = U'(v/V) for every q,
k_q = 0, k_e = U''(v/V)/V). The element matrices are symmetric; the upper triangle (global row
<= column) is scattered into the data array of a fixed CSR pattern built once.
"""
from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["element_matrices", "element_residuals", "scatter_upper", "scatter_packed",
           "scatter_vector",
           "upper_pairs"]


def upper_pairs(n: int = 24):
    """Local (row, col) index pairs with row <= col of an n x n element matrix."""
    r, c = np.triu_indices(n)
    return r.astype(np.int64), c.astype(np.int64)


@nb.njit(cache=True, inline="always")
def material_stiffness_gradients(Fq, Cq, dN, w, T1, A, B):
    """B_aikL = w dN_aJ F_iI CC_IJKL F_kK: the material-tangent part of the element stiffness
    (contracted with dN_bL it gives the material stiffness block K_aibk). T1, A are work arrays."""
    for i in range(3):
        for J in range(3):
            for Kk in range(3):
                for L in range(3):
                    s = 0.0
                    for I in range(3):
                        s += Fq[i, I] * Cq[I, J, Kk, L]
                    T1[i, J, Kk, L] = s
    for i in range(3):
        for J in range(3):
            for k in range(3):
                for L in range(3):
                    s = 0.0
                    for Kk in range(3):
                        s += T1[i, J, Kk, L] * Fq[k, Kk]
                    A[i, J, k, L] = s * w
    for a in range(8):
        for i in range(3):
            for k in range(3):
                for L in range(3):
                    s = 0.0
                    for J in range(3):
                        s += dN[a, J] * A[i, J, k, L]
                    B[a, i, k, L] = s


@nb.njit(cache=True, inline="always")
def add_point_stiffness(K, B, dN, Sq, g, w, pw, kw):
    """Upper node blocks (a <= b) of one Gauss point's stiffness: material part (B dN_b),
    geometric stress part delta_ik dN_a S dN_b, and the pressure terms
    pw (g_ai g_bk - g_ak g_bi) + kw g_ai g_bk."""
    for a in range(8):
        for b in range(a, 8):
            s = 0.0
            for I in range(3):
                for J in range(3):
                    s += dN[a, I] * Sq[I, J] * dN[b, J]
            s *= w
            for i in range(3):
                for k in range(3):
                    t = 0.0
                    for L in range(3):
                        t += B[a, i, k, L] * dN[b, L]
                    t += pw * (g[a, i] * g[b, k] - g[a, k] * g[b, i]) + kw * g[a, i] * g[b, k]
                    if i == k:
                        t += s
                    K[3 * a + i, 3 * b + k] += t


@nb.njit(cache=True, inline="always")
def finish_element_matrix(K, dv, kee):
    """Add the condensed mean-dilatation term kee dv dv^T and symmetrise from the upper node
    blocks (within a diagonal node block both triangles were computed: average them)."""
    if kee != 0.0:
        for r in range(24):
            for c in range(24):
                K[r, c] += kee * dv[r] * dv[c]
    for r in range(24):
        for c in range(r + 1, 24):
            if (r // 3) == (c // 3):
                v = 0.5 * (K[r, c] + K[c, r])
                K[r, c] = v
                K[c, r] = v
            else:
                K[c, r] = K[r, c]


@nb.njit(cache=True, parallel=True, fastmath=False)
def element_matrices(F, S, CC, dNdX, dV, Jq, Finv, pq, kq, ke, Ke, fe, prq, dv_out):
    """Fill Ke (m, 24, 24), fe (m, 24) and dv_out (m, 24) for all elements.

    pq is the pressure of the geometric (d^2 v) stiffness, prq the pressure of the residual;
    they differ only in the three-field Newton iterations (see `solver.mechanics`)."""
    m, nq = dV.shape
    for e in nb.prange(m):
        K = np.zeros((24, 24))
        f = np.zeros(24)
        dv = np.zeros(24)
        A = np.empty((3, 3, 3, 3))
        T1 = np.empty((3, 3, 3, 3))
        B = np.empty((8, 3, 3, 3))
        g = np.empty((8, 3))
        P = np.empty((3, 3))
        for q in range(nq):
            w = dV[e, q]
            Fq = F[e, q]
            Sq = S[e, q]
            Cq = CC[e, q]
            dN = dNdX[e, q]
            # first Piola stress P = F S
            for i in range(3):
                for J in range(3):
                    s = 0.0
                    for I in range(3):
                        s += Fq[i, I] * Sq[I, J]
                    P[i, J] = s
            material_stiffness_gradients(Fq, Cq, dN, w, T1, A, B)
            # spatial gradients g_ai = dN_aJ Finv_Ji
            Fi = Finv[e, q]
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += dN[a, J] * Fi[J, i]
                    g[a, i] = s
            wJ = w * Jq[e, q]
            pw = pq[e, q] * wJ
            prw = prq[e, q] * wJ
            kw = kq[e, q] * wJ
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += P[i, J] * dN[a, J]
                    f[3 * a + i] += w * s + prw * g[a, i]
                    dv[3 * a + i] += wJ * g[a, i]
            add_point_stiffness(K, B, dN, Sq, g, w, pw, kw)
        finish_element_matrix(K, dv, ke[e])
        for r in range(24):
            fe[e, r] = f[r]
            dv_out[e, r] = dv[r]
            for c in range(24):
                Ke[e, r, c] = K[r, c]


@nb.njit(cache=True, parallel=True)
def element_residuals(F, S, dNdX, dV, Jq, Finv, pq, fe):
    """Fill fe (m, 24) only (residual without tangent, for line searches)."""
    m, nq = dV.shape
    for e in nb.prange(m):
        for r in range(24):
            fe[e, r] = 0.0
        for q in range(nq):
            w = dV[e, q]
            Fq = F[e, q]
            Sq = S[e, q]
            dN = dNdX[e, q]
            Fi = Finv[e, q]
            pw = pq[e, q] * w * Jq[e, q]
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    gi = 0.0
                    for J in range(3):
                        t = 0.0
                        for I in range(3):
                            t += Fq[i, I] * Sq[I, J]
                        s += t * dN[a, J]
                        gi += dN[a, J] * Fi[J, i]
                    fe[e, 3 * a + i] += w * s + pw * gi


@nb.njit(cache=True)
def scatter_upper(Ke, slots, lr, lc, data):
    """data[slots[e, p]] += Ke[e, lr[p], lc[p]] for the element upper pairs; data zeroed first."""
    for j in range(data.shape[0]):
        data[j] = 0.0
    m, npair = slots.shape
    for e in range(m):
        for p in range(npair):
            data[slots[e, p]] += Ke[e, lr[p], lc[p]]


@nb.njit(cache=True)
def scatter_packed(Kp, slots, data):
    """data[slots[e, p]] += Kp[e, p] (Kp: packed element upper triangles); data zeroed first."""
    for j in range(data.shape[0]):
        data[j] = 0.0
    m, npair = slots.shape
    for e in range(m):
        for p in range(npair):
            data[slots[e, p]] += Kp[e, p]


@nb.njit(cache=True)
def scatter_packed_subset_add(Kp, slots, elems, data):
    """data[slots[e, p]] += Kp[e, p] for the elements e in `elems` (data not zeroed)."""
    npair = slots.shape[1]
    for i in range(elems.shape[0]):
        e = elems[i]
        for p in range(npair):
            data[slots[e, p]] += Kp[e, p]


@nb.njit(cache=True)
def scatter_vector_subset_add(fe, dofs, elems, out):
    """out[dofs[e, r]] += fe[e, r] for the elements e in `elems` (out not zeroed)."""
    nd = dofs.shape[1]
    for i in range(elems.shape[0]):
        e = elems[i]
        for r in range(nd):
            out[dofs[e, r]] += fe[e, r]


@nb.njit(cache=True)
def scatter_vector(fe, dofs, out):
    """out[dofs[e, r]] += fe[e, r]; out zeroed first."""
    for j in range(out.shape[0]):
        out[j] = 0.0
    m, nd = dofs.shape
    for e in range(m):
        for r in range(nd):
            out[dofs[e, r]] += fe[e, r]
