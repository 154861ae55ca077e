"""Fused numba kernel for isotropic Yeoh / neo-Hookean solids (no fibre terms).

Same mathematics as `solver.assembly._kernels.element_matrices` with the material of
`solver.constitution._hyperelastic.Yeoh` evaluated in place at each Gauss point, so that no
(m, q, 3, 3, 3, 3) tangent array is ever stored: per Gauss point, with I1b = J^(-2/3) I1,
W1 = dW/dI1b, W11 = d2W/dI1b^2,
  S_iso  = 2 W1 dI1b,   dI1b = J^(-2/3) (I - I1/3 C^-1)
  CC_iso = 4 W11 dI1b (x) dI1b + 4 W1 J^(-2/3) [ -1/3 (I (x) C^-1 + C^-1 (x) I)
           + I1/9 C^-1 (x) C^-1 + I1/3 C^-1 (.) C^-1 ].
The volumetric part (mean dilatation or displacement formulation) is as in `_kernels`.
The stiffness is evaluated in its pushed-forward (spatial) form: with the spatial gradients
g_a = F^-T dN_a/dX, F CC F^T contracted with g_a, g_b turns every term above into a rank-one
3x3 block (Bonet & Wood 2008, sec. 6.6 and 9.4), so each node block costs ~45 flops instead
of the ~200 of the material-form contraction B^T CC B.
"""
from __future__ import annotations

import numba as nb
import numpy as np

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
                          tangent, Ke, fe, We, minJ, theta_in, p_in, use_state, v_out, dv_out,
                          elems):
    """Element matrices Ke (m, 300: the upper triangle of each 24 x 24 matrix, row by row),
    residuals fe (m,24), energies We (m,), min J (m,).

    params (m, 4) = C10, C20, C30, K per element; volkind (m,) 0 = Simo-Taylor, 1 = quadratic.
    Only the elements listed in `elems` are computed (the others' rows are left untouched).
    Returns nothing; an element with J <= 0 gets minJ <= 0 and is not computed further.
    """
    nq = dV.shape[1]
    for ie in nb.prange(elems.shape[0]):
        e = elems[ie]
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
        b = np.empty((3, 3))
        tau = np.empty((3, 3))
        Fi = np.empty((3, 3))
        g = np.empty((8, 3))
        Q0 = np.empty(24)           # per dof 3a+i: u_a = d g_a, v_a = b g_a, g_a
        Q1 = np.empty(24)
        Q2 = np.empty(24)
        H0 = np.empty(24)           # the same times H
        H1 = np.empty(24)
        H2 = np.empty(24)
        Ag = np.empty((3, 24))
        Bg = np.empty((8, 24))
        D = np.zeros((8, 8))
        tg = np.empty((8, 3))
        for q in range(nq):
            F = Fs[q]
            Jq = Js[q]
            w = dV[e, q]
            # left Cauchy-Green b = F F^T, I1 = tr b
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for k in range(3):
                        s += F[i, k] * F[j, k]
                    b[i, j] = s
            I1 = b[0, 0] + b[1, 1] + b[2, 2]
            # F^-1 from the cofactors
            Fi[0, 0] = (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]) / Jq
            Fi[0, 1] = (F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]) / Jq
            Fi[0, 2] = (F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]) / Jq
            Fi[1, 0] = (F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]) / Jq
            Fi[1, 1] = (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) / Jq
            Fi[1, 2] = (F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]) / Jq
            Fi[2, 0] = (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]) / Jq
            Fi[2, 1] = (F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]) / Jq
            Fi[2, 2] = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) / Jq
            a23 = (Jq * Jq) ** (-1.0 / 3.0)
            t = a23 * I1 - 3.0
            Wsum += (c10 * t + c20 * t * t + c30 * t * t * t) * w
            W1 = c10 + 2.0 * c20 * t + 3.0 * c30 * t * t
            W11 = 2.0 * c20 + 6.0 * c30 * t
            # Kirchhoff stress of the isochoric part tau = F S F^T = 2 W1 d, with
            # d = F dI1b F^T = J^(-2/3) (b - I1/3 1)
            for i in range(3):
                for j in range(3):
                    tau[i, j] = 2.0 * W1 * a23 * (b[i, j] - (I1 / 3.0 if i == j else 0.0))
            if not mean_dilatation:
                U, dU, d2U = _vol(kind, Kb, Jq)
                Wsum += U * w
                pq = dU
                kq = Jq * d2U
            else:
                pq = pe
                kq = 0.0
            pr = pres if mean_dilatation else pq
            # spatial gradients g_ai = dN_a/dX_J F^-1_Ji
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += dNdX[e, q, a, J] * Fi[J, i]
                    g[a, i] = s
            wJ = w * Jq
            pw = pq * wJ
            kw = kq * wJ
            # f_a = w tau g_a + p w J g_a  (= w P dN_a + ...)
            for a in range(8):
                for i in range(3):
                    s = 0.0
                    for j in range(3):
                        s += tau[i, j] * g[a, j]
                    tg[a, i] = s
                    f[3 * a + i] += w * s + pr * wJ * g[a, i]
                    dvv[3 * a + i] += wJ * g[a, i]
            if not tangent:
                continue
            # Material stiffness pushed forward (dN_a = F^T g_a): the Yeoh tangent
            # CC_iso = 4 W11 dI (x) dI + c4 [-1/3 (1 (x) C^-1 + C^-1 (x) 1) + I1/9 C^-1 (x) C^-1
            #          + I1/6 (C^-1_IK C^-1_JL + C^-1_IL C^-1_JK)]   (c4 = 4 W1 J^(-2/3))
            # becomes, per node block (a, b),
            #   w [4 W11 u_a u_b^T - c4/3 (v_a g_b^T + g_a v_b^T) + c4 I1/9 g_a g_b^T
            #      + c4 I1/6 (g_a.g_b 1 + g_b g_a^T)],  u = d g, v = b g,
            # plus the geometric term (g_a.tau g_b) w 1 and the pressure terms
            # pw (g_a g_b^T - g_b g_a^T) + kw g_a g_b^T. With Q_a = [u_a v_a g_a] the rank-3 part
            # is Q_a H Q_b^T, H = w [[4 W11, 0, 0], [0, 0, -c4/3], [0, -c4/3, c4 I1/9]] + (pw + kw)
            # in H[2, 2].
            c4 = 4.0 * W1 * a23
            h00 = w * 4.0 * W11
            h12 = -w * c4 / 3.0
            h22 = w * c4 * I1 / 9.0 + pw + kw
            eps = w * c4 * I1 / 6.0 - pw
            sig = w * c4 * I1 / 6.0
            # flattened per dof c = 3 b + k: columns of Q (u, v, g) and of Q H, and for the
            # term eps g_bi g_ak the vectors A_i[c] = g_b(c),i and B_a[c] = g_a,k(c), so that
            # every row of the upper triangle is one contiguous (vectorisable) loop
            for a in range(8):
                for i in range(3):
                    su = 0.0
                    sv = 0.0
                    for j in range(3):
                        su += a23 * (b[i, j] - (I1 / 3.0 if i == j else 0.0)) * g[a, j]
                        sv += b[i, j] * g[a, j]
                    c = 3 * a + i
                    Q0[c] = su
                    Q1[c] = sv
                    Q2[c] = g[a, i]
                    H0[c] = h00 * su
                    H1[c] = h12 * g[a, i]
                    H2[c] = h12 * sv + h22 * g[a, i]
                    for k in range(3):
                        Ag[k, c] = g[a, k]
            for a in range(8):
                for c in range(24):
                    Bg[a, c] = g[a, c % 3]
                for bb in range(a, 8):
                    sab = 0.0
                    tab = 0.0
                    for j in range(3):
                        sab += g[a, j] * g[bb, j]
                        tab += g[a, j] * tg[bb, j]
                    D[a, bb] = sig * sab + w * tab
            for r in range(24):
                a = r // 3
                i = r % 3
                h0 = H0[r]
                h1 = H1[r]
                h2 = H2[r]
                for c in range(r, 24):
                    K[r, c] += (h0 * Q0[c] + h1 * Q1[c] + h2 * Q2[c]
                                + eps * Ag[i, c] * Bg[a, c])
                for bb in range(a, 8):
                    if 3 * bb + i >= r:
                        K[r, 3 * bb + i] += D[a, bb]
        We[e] = Wsum
        if mean_dilatation:
            for r in range(24):
                dv_out[e, r] = dvv[r]
        for r in range(24):
            fe[e, r] = f[r]
        if not tangent:
            continue
        # upper triangle, row by row (np.triu_indices order), with the condensed
        # mean-dilatation term kee dv dv^T
        p = 0
        for r in range(24):
            for c in range(r, 24):
                Ke[e, p] = K[r, c] + kee * dvv[r] * dvv[c]
                p += 1
