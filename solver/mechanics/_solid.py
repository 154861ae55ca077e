"""Hyperelastic hexahedral solid body: internal forces, consistent tangent and energy.

Total Lagrangian 8-node hexahedra with 2x2x2 Gauss points. Two treatments of the volumetric
energy of an uncoupled material W = W_iso(C_bar) + U(J):

* ``"mean_dilatation"`` — three-field Q1/P0 Hu-Washizu formulation of Simo, Taylor & Pister
  (1985, CMAME 51) with piecewise-constant pressure and dilatation condensed per element. For
  the uncoupled split the condensed dilatation is the element volume ratio Theta = v/V and the
  potential is  Pi = sum_e [ int_e W_iso dV + V_e U(v_e/V_e) ]  (Bonet & Wood 2008, sec. 8.6;
  FEBio's and FElupe's nearly incompressible hexahedra). The tangent is its exact second
  variation, hence symmetric: p = U'(Theta) enters through d^2 v, and U''(Theta)/V dv (x) dv.
* ``"displacement"`` — the plain compressible formulation, Pi = int (W_iso + U(J)) dV
  (locks for nearly incompressible materials; kept for comparison and compressible use).

Volumetric growth (an eigenstretch field): with `growth` theta_e per element the deformation
gradient splits as F = F_e F_g with F_g = theta^(1/3) I (isotropic growth, Rodriguez, Hoger &
McCulloch 1994, J Biomech 27:455), and the stored energy per reference volume is
theta W(F_e) (the energy of the grown, stress-free intermediate configuration). For a
growth constant over an element this is exactly the same element on a uniformly scaled
reference: shape-function gradients dN/dX theta^(-1/3) (so that x (x) grad N gives F_e), Gauss
weights and element volume times theta (the intermediate volume). The mean dilatation then
becomes Theta = v / (theta V) = the elastic volume ratio, so Q1/P0 and every material law
apply unchanged; a free element with uniform growth reaches v = theta V stress-free.

The isochoric part is evaluated with the material's `isochoric(C, fibres, load)` for every
label group, vectorised over all Gauss points; element matrices come from numba kernels and
are scattered into a fixed CSR pattern (see `solver.assembly`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.assembly import (UpperPattern, element_matrices, element_residuals, scatter_packed,
                             scatter_upper, scatter_vector)
from solver.assembly._kernels import scatter_packed_subset_add, scatter_vector_subset_add
from solver.assembly._fused import yeoh_element_matrices
from solver.constitution._hyperelastic import Yeoh
from solver.constitution.base import inverse_and_det
from solver.element import gauss_hex, hex8_gradients
from solver.errors import MaterialError
from solver.mesh import HexMesh

__all__ = ["SolidBody", "Evaluation", "FORMULATIONS"]

FORMULATIONS = ("mean_dilatation", "displacement")


@dataclass
class Evaluation:
    """Result of evaluating the body at a configuration."""

    force: np.ndarray               # internal force vector (3n,)
    data: np.ndarray | None         # tangent values in the body's CSR upper pattern, or None
    energy: float                   # stored strain energy (mJ)
    valid: bool                     # False if an element is inverted (J <= 0) or NaN appeared
    worst_element: int              # element with the smallest Jacobian determinant
    min_J: float


class SolidBody:
    """A hexahedral hyperelastic body.

    mesh: `HexMesh` (or anything with nodes, hexes, labels). materials: one `Material` for all
    elements, or a dict label -> Material covering every label of the mesh. fibres: optional
    (m, 3) reference fibre directions passed to the materials. growth: optional volumetric
    growth ratio theta > 0 per element (m,) or one for all (F = F_e theta^(1/3) I; see the
    module docstring), ramped with the load fraction like the other loads,
    theta(load) = 1 + (theta - 1) load; `volume_ratio` and `cauchy_stress` then refer to F_e
    at the full growth.
    """

    def __init__(self, mesh, materials, formulation: str = "mean_dilatation", fibres=None,
                 growth=None):
        if not isinstance(mesh, HexMesh):
            mesh = HexMesh(mesh.nodes, mesh.hexes, getattr(mesh, "labels", None))
        if formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
        self.mesh = mesh
        self.formulation = formulation
        labels = mesh.labels
        if not isinstance(materials, dict):
            materials = {int(l): materials for l in np.unique(labels)}
        missing = sorted(set(np.unique(labels).tolist()) - set(materials))
        if missing:
            raise MaterialError(f"no material given for element label(s) {missing}")
        for lab, mat in materials.items():
            if not (hasattr(mat, "isochoric") and hasattr(mat, "volumetric")):
                raise MaterialError(f"material for label {lab} does not follow the Material "
                                    f"protocol (isochoric, volumetric)")
        self.materials = materials
        self.groups = [(mat, np.nonzero(labels == lab)[0]) for lab, mat in materials.items()
                       if np.any(labels == lab)]
        self.single = len(self.groups) == 1
        if fibres is not None:
            fibres = np.asarray(fibres, dtype=float)
            if fibres.shape != (mesh.n_cells, 3):
                raise ValueError(f"fibres must have shape ({mesh.n_cells}, 3), got {fibres.shape}")
        self.fibres = fibres
        X = mesh.nodes[mesh.hexes]                                   # (m, 8, 3)
        xg, wg = gauss_hex(2)
        dNdxi = hex8_gradients(xg)                                   # (q, 8, 3)
        Jac = np.matmul(X.transpose(0, 2, 1)[:, None], dNdxi[None])  # dX/dxi (m, q, 3, 3)
        Jinv, detJ = inverse_and_det(Jac)
        self.dNdX = np.ascontiguousarray(np.matmul(dNdxi[None], Jinv))  # (m, q, 8, 3)
        self.dV = np.ascontiguousarray(detJ * wg[None, :])
        self.growth = None
        self._growth_load = 1.0
        if growth is not None:
            theta = np.broadcast_to(np.asarray(growth, dtype=float), (mesh.n_cells,)).copy()
            if not np.all(np.isfinite(theta)) or not np.all(theta > 0.0):
                raise ValueError("growth ratios must be finite and > 0")
            self.growth = theta
            # the arrays start ungrown (load 0, where Newton starts); `_set_growth` moves them
            # to the grown intermediate configuration of a load fraction
            self._dNdX0, self._dV0 = self.dNdX.copy(), self.dV.copy()
            self._growth_load = 0.0
        self.volume = self.dV.sum(axis=1)                            # V_e
        self.pattern = UpperPattern.build(mesh.hexes, mesh.n_nodes)
        m, nq = self.dV.shape
        self._v = np.empty(m)
        self._dv = np.zeros((m, 24))
        self._Ke = np.empty((m, 24, 24))
        self._fe = np.empty((m, 24))
        # isotropic Yeoh / neo-Hookean everywhere: fused numba kernel (material inlined);
        # on some labels only ("hybrid", e.g. a face with muscles): the fused kernel on those
        # elements, the generic Material-protocol path on the others
        def _is_yeoh(mat):
            return type(mat) in (Yeoh,) or isinstance(mat, Yeoh) and \
                type(mat).isochoric is Yeoh.isochoric

        yeoh_groups = [(mat, idx) for mat, idx in self.groups if _is_yeoh(mat)]
        self.fused = len(yeoh_groups) == len(self.groups)
        self.hybrid = not self.fused and len(yeoh_groups) > 0
        if self.fused or self.hybrid:
            self._params = np.zeros((m, 4))
            self._volkind = np.zeros(m, dtype=np.int64)
            for mat, idx in yeoh_groups:
                self._params[idx] = (mat.C10, mat.C20, mat.C30, mat.K)
                self._volkind[idx] = 0 if mat.volumetric_kind == "simo_taylor" else 1
            self._We = np.zeros(m)
            self._minJ = np.full(m, np.inf)
            self._Kp = np.empty((m, 300))        # packed element upper triangles
            self._fused_elems = np.sort(np.concatenate([idx for _, idx in yeoh_groups]))
        if self.hybrid:
            g = np.sort(np.concatenate([idx for mat, idx in self.groups if not _is_yeoh(mat)]))
            pos = np.full(m, -1, dtype=np.int64)
            pos[g] = np.arange(len(g))
            self._generic_elems = g
            self._generic_groups = [(mat, pos[idx]) for mat, idx in self.groups
                                    if not _is_yeoh(mat)]
            self._generic_slots = np.ascontiguousarray(self.pattern.slots[g])
            self._generic_dofs = np.ascontiguousarray(self.pattern.dofs[g])
            self._g_hexes = np.ascontiguousarray(mesh.hexes[g])
            self._g_dNdX = np.ascontiguousarray(self.dNdX[g])
            self._g_dV = np.ascontiguousarray(self.dV[g])
            self._g_volume = np.ascontiguousarray(self.volume[g])
            self._g_fibres = None if self.fibres is None else np.ascontiguousarray(self.fibres[g])
            self._Ke_g = np.empty((len(g), 24, 24))
            self._fe_g = np.empty((len(g), 24))
            self._dv_g = np.zeros((len(g), 24))
        # three-field (u, p, theta) Newton state of the mean-dilatation elements (fused path):
        # None means theta = v/V and p = U'(theta) are recomputed from u (the purely
        # displacement-based linearisation); set by `begin_mixed` (newton_solve does)
        self.mixed = None

    # ------------------------------------------------------------------ kinematics
    @property
    def n_dofs(self) -> int:
        return 3 * self.mesh.n_nodes

    def deformation_gradient(self, x: np.ndarray) -> np.ndarray:
        """F (m, q, 3, 3) at the Gauss points for current coordinates x (n, 3)."""
        return np.einsum("mai,mqaJ->mqiJ", x[self.mesh.hexes], self.dNdX, optimize=True)

    def _material(self, C, tangent, load, groups=None, fibres=None):
        """Isochoric S, CC, W at all Gauss points; `groups` [(material, positions in C)] and
        `fibres` for an element subset (default: the whole body)."""
        if groups is None:
            groups, fibres = self.groups, self.fibres
        if len(groups) == 1 and len(groups[0][1]) == C.shape[0]:
            mat = groups[0][0]
            fib = None if fibres is None else np.broadcast_to(
                fibres[:, None, :], C.shape[:2] + (3,))
            S, CC, W = mat.isochoric(C, fibres=fib, load=load, tangent=tangent)
            return S, CC, W
        m, nq = C.shape[:2]
        S = np.empty((m, nq, 3, 3))
        CC = np.empty((m, nq, 3, 3, 3, 3)) if tangent else None
        W = np.empty((m, nq))
        for mat, idx in groups:
            fib = None if fibres is None else np.broadcast_to(
                fibres[idx][:, None, :], (len(idx), nq, 3))
            s, cc, w = mat.isochoric(C[idx], fibres=fib, load=load, tangent=tangent)
            S[idx] = s
            W[idx] = w
            if tangent:
                CC[idx] = cc
        return S, CC, W

    def _volumetric(self, J, groups=None):
        """U, U', U'' per Gauss point (J (m, q)) or per element (J (m,)); `groups` as in
        `_material` for an element subset."""
        if groups is None:
            groups = self.groups
        if len(groups) == 1 and len(groups[0][1]) == J.shape[0]:
            return groups[0][0].volumetric(J)
        U = np.empty_like(J)
        dU = np.empty_like(J)
        d2U = np.empty_like(J)
        for mat, idx in groups:
            U[idx], dU[idx], d2U[idx] = mat.volumetric(J[idx])
        return U, dU, d2U

    # ------------------------------------------------------------------ evaluation
    def _set_growth(self, load: float) -> None:
        """Reference arrays at the growth theta(load) = 1 + (theta - 1) load."""
        if self.growth is None or load == self._growth_load:
            return
        theta = 1.0 + (self.growth - 1.0) * float(load)
        self.dNdX = np.ascontiguousarray(self._dNdX0 / np.cbrt(theta)[:, None, None, None])
        self.dV = np.ascontiguousarray(self._dV0 * theta[:, None])
        self.volume = self.dV.sum(axis=1)
        if self.hybrid:
            g = self._generic_elems
            self._g_dNdX = np.ascontiguousarray(self.dNdX[g])
            self._g_dV = np.ascontiguousarray(self.dV[g])
            self._g_volume = np.ascontiguousarray(self.volume[g])
        self._growth_load = float(load)

    def evaluate(self, x: np.ndarray, load: float = 1.0, tangent: bool = True) -> Evaluation:
        """Internal forces, tangent (CSR data of `self.pattern`) and energy at coordinates x."""
        self._set_growth(load)
        if self.fused:
            return self._evaluate_fused(x, tangent)
        if self.hybrid:
            return self._evaluate_hybrid(x, load, tangent)
        part = self._generic_part(x, load, tangent, None)
        if not part[0]:
            return part[1]
        _, fe, Ke, energy, minJ_e = part
        worst = int(np.argmin(minJ_e))
        f = np.empty(self.n_dofs)
        data = None
        if tangent:
            data = np.empty(self.pattern.nnz)
            scatter_upper(Ke, self.pattern.slots, self.pattern.local_rows,
                          self.pattern.local_cols, data)
        scatter_vector(fe, self.pattern.dofs, f)
        valid = bool(np.isfinite(energy) and np.all(np.isfinite(f)))
        return Evaluation(f, data, energy, valid, worst, float(minJ_e[worst]))

    def _generic_part(self, x, load, tangent, subset):
        """Element forces / matrices through the Material protocol for all elements (subset
        None) or the hybrid body's non-Yeoh elements. Returns (True, fe, Ke or None, energy,
        min J per element) or (False, invalid Evaluation)."""
        if subset is None:
            elems = None
            hexes, dNdX, dV, volume = self.mesh.hexes, self.dNdX, self.dV, self.volume
            groups, fibres = self.groups, self.fibres
            Ke, fe, dv = self._Ke, self._fe, self._dv
        else:
            elems = self._generic_elems
            hexes, dNdX, dV, volume = self._g_hexes, self._g_dNdX, self._g_dV, self._g_volume
            groups, fibres = self._generic_groups, self._g_fibres
            Ke, fe, dv = self._Ke_g, self._fe_g, self._dv_g
        F = np.einsum("mai,mqaJ->mqiJ", x[hexes], dNdX, optimize=True)
        Finv, Jq = inverse_and_det(F)
        m, nq = Jq.shape
        minJ_e = Jq.min(axis=1)
        worst = int(np.argmin(minJ_e))
        if not np.all(np.isfinite(Jq)) or minJ_e[worst] <= 0.0:
            bad = np.nonzero(~(minJ_e > 0))[0]
            worst = int(bad[0]) if len(bad) else worst
            mj = float(np.nan_to_num(minJ_e[worst], nan=-np.inf))
            if elems is not None:
                worst = int(elems[worst])
            return False, Evaluation(np.full(self.n_dofs, np.nan), None, np.nan, False, worst,
                                     mj)
        C = np.einsum("mqkI,mqkJ->mqIJ", F, F, optimize=True)
        S, CC, W = self._material(C, tangent, load, groups, fibres)
        energy = float(np.sum(W * dV))
        if self.formulation == "mean_dilatation":
            v = np.einsum("mq,mq->m", Jq, dV)
            if elems is None:
                self._v[:] = v
            else:
                self._v[elems] = v
            theta = v / volume
            U, dU, d2U = self._volumetric(theta, groups)
            energy += float(np.sum(U * volume))
            pres = dU
            if self.mixed is not None:
                # three-field Newton: residual pressure linearised about the stored dilatation,
                # geometric stiffness with the stored pressure
                th, p_state = self.mixed
                if elems is not None:
                    th, p_state = th[elems], p_state[elems]
                _, dUt, d2Ut = self._volumetric(th, groups)
                pres = dUt + d2Ut * (theta - th)
                dU, d2U = p_state, d2Ut
            pq = np.ascontiguousarray(np.broadcast_to(dU[:, None], (m, nq)))
            prq = np.ascontiguousarray(np.broadcast_to(pres[:, None], (m, nq)))
            kq = np.zeros((m, nq))
            ke = d2U / volume
        else:
            U, dU, d2U = self._volumetric(Jq, groups)
            energy += float(np.sum(U * dV))
            pq = np.ascontiguousarray(dU)
            prq = pq
            kq = np.ascontiguousarray(Jq * d2U)
            ke = np.zeros(m)
        if tangent:
            element_matrices(F, S, np.ascontiguousarray(CC), dNdX, dV, Jq, Finv,
                             pq, kq, ke, Ke, fe, prq, dv)
            if elems is not None:
                self._dv[elems] = dv
        else:
            element_residuals(F, np.ascontiguousarray(S), dNdX, dV, Jq, Finv, prq, fe)
            Ke = None
        return True, fe, Ke, energy, minJ_e

    def _evaluate_hybrid(self, x, load, tangent):
        """Fused Yeoh kernel on the Yeoh elements, the Material protocol on the others."""
        part = self._generic_part(x, load, tangent, "generic")
        if not part[0]:
            return part[1]
        _, fe_g, Ke_g, energy_g, minJ_g = part
        x = np.ascontiguousarray(x, dtype=float)
        use = self.mixed is not None and self.formulation == "mean_dilatation"
        th, pp = self.mixed if use else (self._v, self._v)
        elems = self._fused_elems
        yeoh_element_matrices(x, self.mesh.hexes, self.dNdX, self.dV, self.volume, self._params,
                              self._volkind, self.formulation == "mean_dilatation", tangent,
                              self._Kp, self._fe, self._We, self._minJ, th, pp, use,
                              self._v, self._dv, elems)
        minJ = self._minJ.copy()
        minJ[self._generic_elems] = minJ_g
        worst = int(np.argmin(minJ))
        if not minJ[worst] > 0.0 or not np.all(np.isfinite(minJ)):
            bad = np.nonzero(~(minJ > 0))[0]
            worst = int(bad[0]) if len(bad) else worst
            return Evaluation(np.full(self.n_dofs, np.nan), None, np.nan, False, worst,
                              float(np.nan_to_num(minJ[worst], nan=-np.inf)))
        f = np.empty(self.n_dofs)
        scatter_vector(fe_g, self._generic_dofs, f)
        scatter_vector_subset_add(self._fe, self.pattern.dofs, elems, f)
        data = None
        if tangent:
            data = np.empty(self.pattern.nnz)
            scatter_upper(Ke_g, self._generic_slots, self.pattern.local_rows,
                          self.pattern.local_cols, data)
            scatter_packed_subset_add(self._Kp, self.pattern.slots, elems, data)
        energy = energy_g + float(self._We[elems].sum())
        valid = bool(np.isfinite(energy) and np.all(np.isfinite(f)))
        return Evaluation(f, data, energy, valid, worst, float(minJ[worst]))

    # ------------------------------------------------------------------ three-field state
    @property
    def supports_mixed(self) -> bool:
        return self.formulation == "mean_dilatation"

    def begin_mixed(self, x):
        """Start three-field Newton from x (at load 0): theta = v/V, p = U'(theta) per element."""
        if not self.supports_mixed:
            return
        self._set_growth(0.0)
        theta = self._volume_ratio(x)
        self.mixed = (theta, self._volumetric(theta)[1])

    def mixed_snapshot(self):
        """(theta, p, v, dv) of the last tangent evaluation, to update after a solve."""
        if self.mixed is None:
            return None
        return (self.mixed[0].copy(), self.mixed[1].copy(), self._v.copy(), self._dv.copy())

    def mixed_update(self, snapshot, du):
        """Condensed update theta <- (v + dv.du)/V, p <- U'(theta0) + U''(theta0) dtheta."""
        if snapshot is None:
            return
        theta0, p0, v, dv = snapshot
        dve = np.einsum("mr,mr->m", dv, du.reshape(-1)[self.pattern.dofs])
        theta = (v + dve) / self.volume
        _, dU, d2U = self._volumetric(theta0)
        self.mixed = (theta, dU + d2U * (theta - theta0))

    def mixed_restore(self, snapshot):
        if snapshot is not None:
            self.mixed = (snapshot[0].copy(), snapshot[1].copy())

    def _evaluate_fused(self, x, tangent):
        x = np.ascontiguousarray(x, dtype=float)
        use = self.mixed is not None and self.formulation == "mean_dilatation"
        th, pp = self.mixed if use else (self._v, self._v)
        yeoh_element_matrices(x, self.mesh.hexes, self.dNdX, self.dV, self.volume, self._params,
                              self._volkind, self.formulation == "mean_dilatation", tangent,
                              self._Kp, self._fe, self._We, self._minJ, th, pp, use,
                              self._v, self._dv, self._fused_elems)
        worst = int(np.argmin(self._minJ))
        minJ = float(self._minJ[worst])
        if not minJ > 0.0 or not np.all(np.isfinite(self._minJ)):
            bad = np.nonzero(~(self._minJ > 0))[0]
            worst = int(bad[0]) if len(bad) else worst
            return Evaluation(np.full(self.n_dofs, np.nan), None, np.nan, False, worst,
                              float(np.nan_to_num(self._minJ[worst], nan=-np.inf)))
        f = np.empty(self.n_dofs)
        scatter_vector(self._fe, self.pattern.dofs, f)
        data = None
        if tangent:
            data = np.empty(self.pattern.nnz)
            scatter_packed(self._Kp, self.pattern.slots, data)
        energy = float(self._We.sum())
        valid = bool(np.isfinite(energy) and np.all(np.isfinite(f)))
        return Evaluation(f, data, energy, valid, worst, minJ)

    # ------------------------------------------------------------------ post-processing
    def cauchy_stress(self, x: np.ndarray, load: float = 1.0) -> np.ndarray:
        """Element-averaged Cauchy stress (m, 3, 3) in kPa."""
        self._set_growth(1.0)
        F = self.deformation_gradient(x)
        _, Jq = inverse_and_det(F)
        C = np.einsum("mqkI,mqkJ->mqIJ", F, F, optimize=True)
        S, _, _ = self._material(C, False, load)
        sig = np.einsum("mqiI,mqIJ,mqjJ->mqij", F, S, F, optimize=True) / Jq[..., None, None]
        if self.formulation == "mean_dilatation":
            theta = np.einsum("mq,mq->m", Jq, self.dV) / self.volume
            p = self._volumetric(theta)[1][:, None]
        else:
            p = self._volumetric(Jq)[1]
        sig = sig + p[..., None, None] * np.eye(3)
        return np.einsum("mqij,mq->mij", sig, self.dV) / self.volume[:, None, None]

    def volume_ratio(self, x: np.ndarray) -> np.ndarray:
        """Element volume ratio v/V (the mean dilatation; elastic, v / (theta V), with growth
        at its full value) -> (m,)."""
        self._set_growth(1.0)
        return self._volume_ratio(x)

    def _volume_ratio(self, x: np.ndarray) -> np.ndarray:
        F = self.deformation_gradient(x)
        _, Jq = inverse_and_det(F)
        return np.einsum("mq,mq->m", Jq, self.dV) / self.volume
