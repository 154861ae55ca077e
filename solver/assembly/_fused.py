"""Fused numba kernel for isotropic Yeoh / neo-Hookean solids (no fibre terms).

Same mathematics as `solver.assembly._kernels.element_matrices` with the material of
`solver.constitution._hyperelastic.Yeoh` evaluated in place at each Gauss point, so that no
(m, q, 3, 3, 3, 3) tangent array is ever stored: per Gauss point, with I1b = J^(-2/3) I1,
W1 = dW/dI1b, W11 = d2W/dI1b^2,
  S_iso  = 2 W1 dI1b,   dI1b = J^(-2/3) (I - I1/3 C^-1)
  CC_iso = 4 W11 dI1b (x) dI1b + 4 W1 J^(-2/3) [ -1/3 (I (x) C^-1 + C^-1 (x) I)
           + I1/9 C^-1 (x) C^-1 + I1/3 C^-1 (.) C^-1 ].
The volumetric part (mean dilatation or displacement formulation) is as in `_kernels`.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from solver.assembly._kernels import (add_point_stiffness, finish_element_matrix,
                                      material_stiffness_gradients)

__all__ = ["yeoh_element_matrices"]


@nb.njit(cache=True, inline="always")
def _vol(kind, K, J):
    if kind == 0:
        U = 0.25 * K * (J * J - 1.0 - 2.0 * np.log(J))
        dU = 0.5 * K * (J - 1.0 / J)
        d2U = 0.5 * K * (1.0 + 1.0 / (J * J))
    else:
        U = 0.5 * K * (J - 1.0) ** 2
        dU = K * (J - 1.0)
        d2U = K
    return U, dU, d2U


@nb.njit(cache=True, parallel=True, fastmath=True)
def yeoh_element_matrices(x, hexes, dNdX, dV, volume, params, volkind, mean_dilatation,
                          tangent, Ke, fe, We, minJ, theta_in, p_in, use_state, v_out, dv_out):
    """Element matrices Ke (m,24,24), residuals fe (m,24), energies We (m,), min J (m,).

    params (m, 4) = C10, C20, C30, K per element; volkind (m,) 0 = Simo-Taylor, 1 = quadratic.
    Returns nothing; an element with J <= 0 gets minJ <= 0 and is not computed further.
    """
    m, nq = dV.shape
    for e in nb.prange(m):
        xe = np.empty((8, 3))
        for a in range(8):
            for i in range(3):
                xe[a, i] = x[hexes[e, a], i]
        Fs = np.empty((nq, 3, 3))
        Js = np.empty(nq)
        mj = 1e300
        for q in range(nq):
            for i in range(3):
                for J in range(3):
                    s = 0.0
                    for a in range(8):
                        s += xe[a, i] * dNdX[e, q, a, J]
                    Fs[q, i, J] = s
            F = Fs[q]
            d = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
                 - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
                 + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
            Js[q] = d
            if d < mj:
                mj = d
        minJ[e] = mj
        if not (mj > 0.0):
            We[e] = np.nan
            continue
        c10 = params[e, 0]
        c20 = params[e, 1]
        c30 = params[e, 2]
        Kb = params[e, 3]
        kind = volkind[e]
        Wsum = 0.0
        pe = 0.0
        pres = 0.0
        kee = 0.0
        if mean_dilatation:
            v = 0.0
            for q in range(nq):
                v += Js[q] * dV[e, q]
            theta = v / volume[e]
            U, dU, d2U = _vol(kind, Kb, theta)
            Wsum += U * volume[e]
            pe = dU
            pres = dU
            kee = d2U / volume[e]
            v_out[e] = v
            if use_state:
                # three-field (u, p, theta) Newton with element-wise condensation: residual
                # pressure linearised about the stored dilatation, geometric stiffness with
                # the stored pressure (Simo, Taylor & Pister 1985)
                th = theta_in[e]
                Ut, dUt, d2Ut = _vol(kind, Kb, th)
                pres = dUt + d2Ut * (theta - th)
                pe = p_in[e]
                kee = d2Ut / volume[e]
        K = np.zeros((24, 24))
        f = np.zeros(24)
        dvv = np.zeros(24)
        C = np.empty((3, 3))
        Ci = np.empty((3, 3))
        Fi = np.empty((3, 3))
        S = np.empty((3, 3))
        dI = np.empty((3, 3))
        CC = np.empty((3, 3, 3, 3))
        T1 = np.empty((3, 3, 3, 3))
        A = np.empty((3, 3, 3, 3))
        B = np.empty((8, 3, 3, 3))
        g = np.empty((8, 3))
        P = np.empty((3, 3))
        for q in range(nq):
            F = Fs[q]
            Jq = Js[q]
            w = dV[e, q]
            for I in range(3):
                for J in range(3):
                    s = 0.0
                    for k in range(3):
                        s += F[k, I] * F[k, J]
                    C[I, J] = s
            detC = Jq * Jq
            Ci[0, 0] = (C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]) / detC
            Ci[0, 1] = (C[0, 2] * C[2, 1] - C[0, 1] * C[2, 2]) / detC
            Ci[0, 2] = (C[0, 1] * C[1, 2] - C[0, 2] * C[1, 1]) / detC
            Ci[1, 0] = Ci[0, 1]
            Ci[1, 1] = (C[0, 0] * C[2, 2] - C[0, 2] * C[2, 0]) / detC
            Ci[1, 2] = (C[0, 2] * C[1, 0] - C[0, 0] * C[1, 2]) / detC
            Ci[2, 0] = Ci[0, 2]
            Ci[2, 1] = Ci[1, 2]
            Ci[2, 2] = (C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]) / detC
            # F^-1 = C^-1 F^T
            for I in range(3):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += Ci[I, J] * F[i, J]
                    Fi[I, i] = s
            a23 = detC ** (-1.0 / 3.0)
            I1 = C[0, 0] + C[1, 1] + C[2, 2]
            t = a23 * I1 - 3.0
            Wsum += (c10 * t + c20 * t * t + c30 * t * t * t) * w
            W1 = c10 + 2.0 * c20 * t + 3.0 * c30 * t * t
            W11 = 2.0 * c20 + 6.0 * c30 * t
            for I in range(3):
                for J in range(3):
                    dI[I, J] = a23 * ((1.0 if I == J else 0.0) - I1 / 3.0 * Ci[I, J])
                    S[I, J] = 2.0 * W1 * dI[I, J]
            if not mean_dilatation:
                U, dU, d2U = _vol(kind, Kb, Jq)
                Wsum += U * w
                pq = dU
                kq = Jq * d2U
            else:
                pq = pe
                kq = 0.0
            pr = pres if mean_dilatation else pq
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += dNdX[e, q, a, J] * Fi[J, i]
                    g[a, i] = s
            for i in range(3):
                for J in range(3):
                    s = 0.0
                    for I in range(3):
                        s += F[i, I] * S[I, J]
                    P[i, J] = s
            wJ = w * Jq
            pw = pq * wJ
            kw = kq * wJ
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += P[i, J] * dNdX[e, q, a, J]
                    f[3 * a + i] += w * s + pr * wJ * g[a, i]
                    dvv[3 * a + i] += wJ * g[a, i]
            if not tangent:
                continue
            c4 = 4.0 * W1 * a23
            for I in range(3):
                for J in range(3):
                    dIJ = 1.0 if I == J else 0.0
                    for Kk in range(3):
                        for L in range(3):
                            dKL = 1.0 if Kk == L else 0.0
                            CC[I, J, Kk, L] = (4.0 * W11 * dI[I, J] * dI[Kk, L]
                                               + c4 * (-(dIJ * Ci[Kk, L] + Ci[I, J] * dKL) / 3.0
                                                       + I1 / 9.0 * Ci[I, J] * Ci[Kk, L]
                                                       + I1 / 6.0 * (Ci[I, Kk] * Ci[J, L]
                                                                     + Ci[I, L] * Ci[J, Kk])))
            material_stiffness_gradients(F, CC, dNdX[e, q], w, T1, A, B)
            add_point_stiffness(K, B, dNdX[e, q], S, g, w, pw, kw)
        We[e] = Wsum
        if mean_dilatation:
            for r in range(24):
                dv_out[e, r] = dvv[r]
        for r in range(24):
            fe[e, r] = f[r]
        if not tangent:
            continue
        finish_element_matrix(K, dvv, kee)
        for r in range(24):
            for c in range(24):
                Ke[e, r, c] = K[r, c]
