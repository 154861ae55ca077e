"""Sensitivity of a converged static equilibrium to parameters: du/dp = -K^-1 dR/dp.

At a converged state r(u(p), p) = 0 on the free unknowns, with prescribed values u_c(p) on the
constrained ones (Cartesian or local-frame components, `solver.bc`), differentiating gives
K_ff du_f/dp = -(dr_f/dp + K_fc du_c/dp), the direct differentiation method of design
sensitivity analysis (Kleiber et al., *Parameter Sensitivity in Nonlinear Mechanics*, 1997,
ch. 4; Haug, Choi & Komkov 1986). K is the consistent tangent of the body and the extra terms
at the converged configuration (the Q1/P0 body's displacement-based second variation; contact
terms with their converged multipliers). The partial derivatives dr/dp (at fixed x) and du_c/dp
are supplied by the caller (e.g. central differences of the residual, which need no solve);
one symmetric factorisation (`solver.linalg.SymmetricSolver`) serves every parameter. Everything is in transformed unknowns
u_hat = T u where local frames exist and returned in global components.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from solver.bc import ConstraintSet
from solver.linalg import SymmetricSolver

__all__ = ["constraint_set", "tangent_matrix", "linear_response"]


def constraint_set(body, constraints) -> ConstraintSet:
    """The constraint set the Newton solver builds (nodes touched by no element held fixed)."""
    n = body.mesh.n_nodes
    used = np.zeros(n, dtype=bool)
    used[np.asarray(body.mesh.hexes).ravel()] = True
    return ConstraintSet(n, list(constraints), unused_nodes=np.nonzero(~used)[0])


def tangent_matrix(body, terms, x, load: float = 1.0) -> sp.csr_matrix:
    """Full symmetric tangent (3n, 3n) of body + terms at x (global components)."""
    saved = getattr(body, "mixed", None)
    body.mixed = None            # the displacement-based (condensed) second variation
    try:
        ev = body.evaluate(np.ascontiguousarray(x, dtype=float), load, tangent=True)
    finally:
        body.mixed = saved
    if not ev.valid:
        raise ValueError("the configuration has an inverted element; no tangent")
    pat = body.pattern
    U = sp.csr_matrix((ev.data, pat.indices, pat.indptr), shape=(pat.n_dofs, pat.n_dofs))
    K = U + U.T - sp.diags(U.diagonal())
    for term in terms:
        _, Kt = term.assemble(x, load)
        if Kt is not None and Kt.nnz:
            Kt = sp.csr_matrix(Kt)
            K = K + 0.5 * (Kt + Kt.T)
    return sp.csr_matrix(K)


def _rotation(cons: ConstraintSet) -> sp.csr_matrix:
    n = cons.n_nodes
    rows = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, :, None]) + np.zeros((1, 1, 3), int)
    cols = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]) + np.zeros((1, 3, 1), int)
    return sp.csr_matrix((cons.rot.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))


def linear_response(body, constraints, terms, x, dr_dp, duc_dp=None, load: float = 1.0,
                    backend: str = "auto"):
    """du/dp (3n, k) in global components at the converged configuration x (n, 3).

    dr_dp (3n, k): partial derivative of the residual (internal + term forces - external)
    with respect to each parameter at fixed x, global components. duc_dp (n_c, k): derivative
    of the prescribed values at the constrained transformed unknowns (`ConstraintSet.dofs`
    order), or None when no parameter moves a constraint. backend: the linear solver
    (`solver.linalg.SymmetricSolver`: PARDISO's LDL^T when installed, else SuperLU).
    """
    cons = constraint_set(body, constraints)
    dr = np.asarray(dr_dp, dtype=float)
    if dr.ndim == 1:
        dr = dr[:, None]
    k = dr.shape[1]
    K = tangent_matrix(body, terms, x, load)
    if cons.any_frame:
        T = _rotation(cons)
        K = sp.csr_matrix(T @ K @ T.T)
        dr = T @ dr
    free, cdofs = cons.free, cons.dofs
    duc = np.zeros((len(cdofs), k)) if duc_dp is None else np.asarray(duc_dp, float).reshape(len(cdofs), k)
    rhs = -dr[free]
    if np.any(duc != 0.0):
        rhs = rhs - K[free][:, cdofs] @ duc
    # one symmetric (indefinite: LDL^T) factorisation of K_ff, its upper triangle as the
    # Newton solver passes it, and one substitution for all parameters together
    Kff = sp.triu(K[free][:, free], format="csr")
    Kff.sum_duplicates()
    Kff.sort_indices()
    lin = SymmetricSolver(backend)
    lin.factorize(Kff)
    du = np.zeros((3 * cons.n_nodes, k))
    du[free] = lin.apply(np.ascontiguousarray(rhs)).reshape(-1, k)
    lin.release_factor()
    du[cdofs] = duc
    if cons.any_frame:
        du = np.stack([cons.to_global(du[:, j]) for j in range(k)], axis=1)
    return du
