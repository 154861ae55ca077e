"""`solver.linalg`: the direct symmetric solve and the lagged-factor CG solver on a 3D
Laplacian-like SPD system (upper-triangle CSR, as the Newton solver supplies it).

Tolerances: the direct solve is backward stable, so the residual is ~1e-14 relative; 1e-10
leaves room for the conditioning (~1e3). The CG solve is asked for 1e-9 relative residual and is
checked against exactly that (SciPy's stopping test is on the same residual norm).
"""
import numpy as np
import scipy.sparse as sp

from solver.linalg import LaggedFactorSolver, SymmetricSolver


def _spd(n=12, shift=0.1):
    one = sp.diags([-1.0, 2.0 + shift, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    K = (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye)
         + sp.kron(sp.kron(eye, eye), one)).tocsr()
    return K


def _upper(K):
    U = sp.triu(K, format="csr")
    U.sort_indices()
    return U


def test_direct_solve():
    K = _spd()
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    x = SymmetricSolver().solve(_upper(K), b)
    assert np.linalg.norm(K @ x - b) < 1e-10 * np.linalg.norm(b)


def test_lagged_factor_cg_and_refactorisation():
    K0 = _spd()
    rng = np.random.default_rng(1)
    b = rng.standard_normal(K0.shape[0])
    lin = LaggedFactorSolver(rtol=1e-9, maxiter=40)
    lin.solve(_upper(K0), b)
    assert lin.last["refactorized"] and lin.factorizations == 1
    # a moderately changed matrix (as the tangent changes between Newton iterations): CG with
    # the old factor, no new factorisation
    K1 = K0 + sp.diags(0.3 * rng.random(K0.shape[0]))
    x = lin.solve(_upper(K1), b)
    assert not lin.last["refactorized"] and lin.factorizations == 1
    assert lin.last["krylov_iterations"] > 0
    assert np.linalg.norm(K1 @ x - b) <= 1e-9 * np.linalg.norm(b) * 1.0001
    # a strongly changed one with too few iterations allowed: refactorised, solved directly
    lin.maxiter = 1
    K2 = 5.0 * K0 + sp.diags(3.0 * rng.random(K0.shape[0]))
    x = lin.solve(_upper(K2), b)
    assert lin.last["refactorized"] and lin.factorizations == 2
    assert np.linalg.norm(K2 @ x - b) < 1e-10 * np.linalg.norm(b)
