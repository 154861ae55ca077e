"""`solver.linalg` on symmetric indefinite systems: right-preconditioned GMRES and the lagged
LDL^T factor of `LaggedFactorSolver`'s indefinite mode.

The matrices are a 3D Laplacian (10^3 unknowns, upper-triangle CSR as the Newton solver
supplies it) shifted by sigma into a gap of its spectrum, which is known in closed form:
lambda = sum over the three axes of (2.1 - 2 cos(k pi / 11)), k = 1..10. With sigma = 1.507,
17 eigenvalues are negative, |lambda - sigma| >= 0.118 and <= 10.5. Diagonal perturbations of
at most `DELTA` = 0.03 move every eigenvalue by at most 0.03 (Weyl), so every matrix of the
sequences is indefinite and nonsingular with |lambda| in [0.088, 10.53].

Tolerances: the Krylov solves are checked on the true residual against exactly the relative
tolerance asked (the solver's stopping test is on that residual, recomputed at the end); the
error against a dense direct solve is then bounded by cond(K) * rtol, cond <= 10.53 / 0.088.
"""
import numpy as np
import pytest
import scipy.sparse as sp

from solver.linalg import LaggedFactorSolver, available_backends, preconditioned_gmres

N = 10
SIGMA = 1.507
DELTA = 0.03


def _spectrum(n=N, shift=0.1):
    one = 2.0 + shift - 2.0 * np.cos(np.arange(1, n + 1) * np.pi / (n + 1))
    return (one[:, None, None] + one[None, :, None] + one[None, None, :]).ravel()


def _laplacian(n=N, shift=0.1):
    one = sp.diags([-1.0, 2.0 + shift, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    return (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye)
            + sp.kron(sp.kron(eye, eye), one)).tocsr()


def _upper(K):
    U = sp.triu(K, format="csr")
    U.sort_indices()
    return U


LAM = np.abs(_spectrum() - SIGMA)
COND = (LAM.max() + DELTA) / (LAM.min() - DELTA)   # bound over the perturbed sequence


def _indefinite(delta=0.0, seed=0):
    K = _laplacian() - SIGMA * sp.identity(N ** 3)
    if delta:
        K = K + sp.diags(delta * np.random.default_rng(seed).random(N ** 3))
    return K.tocsr()


def test_spectrum_is_indefinite_with_a_gap():
    # the closed-form spectrum against LAPACK (1e-10: eigvalsh is backward stable, |K| ~ 12)
    lam = np.linalg.eigvalsh(_indefinite().toarray())
    assert np.allclose(np.sort(lam), np.sort(_spectrum() - SIGMA), atol=1e-10)
    assert (lam < 0).sum() == 17 and LAM.min() > 0.11


def test_gmres_without_preconditioner_matches_direct_solve():
    # unpreconditioned GMRES on the indefinite matrix: the true residual reported meets the
    # asked 1e-10, and the error is within cond * 1e-10 of the dense solution
    K = _indefinite()
    b = np.random.default_rng(1).standard_normal(K.shape[0])
    x, its, status, rel = preconditioned_gmres(_upper(K), b, lambda v: v, 1e-10, 400)
    assert status == "converged" and rel <= 1e-10
    assert np.linalg.norm(K @ x - b) <= 1e-10 * np.linalg.norm(b)
    xd = np.linalg.solve(K.toarray(), b)
    assert np.linalg.norm(x - xd) <= COND * 1e-10 * np.linalg.norm(xd)


def test_gmres_with_exact_factor_converges_in_one_iteration():
    # right preconditioning with the exact inverse: A M^-1 = I, one iteration, and the starting
    # guess is honoured (a converged start costs no iteration)
    K = _indefinite()
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    Kd = K.toarray()
    inv = np.linalg.inv(Kd)
    x, its, status, rel = preconditioned_gmres(_upper(K), b, lambda v: inv @ v, 1e-12, 5)
    assert its == 1 and status == "converged" and rel <= 1e-12
    x2, its2, status2, _ = preconditioned_gmres(_upper(K), b, lambda v: inv @ v, 1e-10, 5,
                                               x0=x)
    assert its2 == 0 and status2 == "converged"


def test_gmres_gives_up_early_when_its_rate_cannot_reach_the_tolerance():
    # Unpreconditioned GMRES on the indefinite matrix (cond ~ 1e2, eigenvalues on both sides
    # of 0) gains far less than a factor 10 per iteration: asked 1e-8 within 10 iterations it
    # is hopeless, and with predict_from=3 it stops after 3 ("slow") instead of 10
    # ("maxiter"), returning the minimiser over its 3-dimensional Krylov space (the same
    # iterate as a 3-iteration solve); with the exact inverse as preconditioner it converges
    # at its first iteration and the rate check never fires
    K = _indefinite()
    U = _upper(K)
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    x10, its10, status10, rel10 = preconditioned_gmres(U, b, lambda v: v, 1e-8, 10)
    x3, its3, status3, rel3 = preconditioned_gmres(U, b, lambda v: v, 1e-8, 10, predict_from=3)
    assert (status10, its10) == ("maxiter", 10) and (status3, its3) == ("slow", 3)
    x3ref, *_ = preconditioned_gmres(U, b, lambda v: v, 1e-8, 3)
    # the same arithmetic up to the basis length allocated: 1e-12 relative
    assert np.allclose(x3, x3ref, rtol=0, atol=1e-12 * np.abs(x3ref).max())
    assert rel3 >= rel10 > 1e-8
    inv = np.linalg.inv(K.toarray())
    x, its, status, rel = preconditioned_gmres(U, b, lambda v: inv @ v, 1e-8, 10, predict_from=1)
    assert status == "converged" and its == 1 and rel <= 1e-8


@pytest.mark.skipif("pardiso" not in available_backends(), reason="PARDISO not installed")
@pytest.mark.parametrize("precision", ["single", "double"])
def test_slowly_changing_indefinite_systems_reuse_the_ldlt_factor(precision):
    # a Newton-like sequence: the tangent drifts by small diagonal changes; after the first
    # system (Cholesky fails -> LDL^T factor) the others are solved by GMRES with the lagged
    # factor: fewer factorisations than systems, each to the asked relative residual on the
    # true residual, within cond * rtol of the dense direct solution
    rtol = 1e-8
    lin = LaggedFactorSolver(rtol=rtol, precision=precision)
    rng = np.random.default_rng(3)
    systems = 6
    lagged = 0
    for k in range(systems):
        K = _indefinite(DELTA * k / (systems - 1), seed=k)
        b = rng.standard_normal(K.shape[0])
        x = lin.solve(_upper(K), b)
        last = lin.last
        assert last["krylov"] == "gmres" and lin.indefinite
        assert np.linalg.norm(K @ x - b) <= rtol * np.linalg.norm(b)
        xd = np.linalg.solve(K.toarray(), b)
        assert np.linalg.norm(x - xd) <= COND * rtol * np.linalg.norm(xd)
        lagged += not last["refactorized"]
    # the Cholesky attempt on the first system fails without counting; LDL^T factorisations:
    assert lin.ldlt_factorizations == lin.factorizations < systems
    assert lagged >= 1


@pytest.mark.skipif("pardiso" not in available_backends(), reason="PARDISO not installed")
def test_far_matrix_triggers_ldlt_refactorisation_then_cg_after_begin_step():
    # the factor of K0 is a poor preconditioner for a far matrix (the Laplacian shifted by
    # 0.661 instead of 1.507, in the gap between its 1st and 2nd eigenvalues: one negative
    # eigenvalue, |lambda| >= 0.118; the preconditioned operator's eigenvalues
    # (l - 0.661) / (l - 1.507) spread over [-6.2, 8.2]): the lagged GMRES stalls within maxiter,
    # the LDL^T is refactorised and the tolerance is met; after begin_step an SPD system goes
    # back to the Cholesky factor and CG
    rtol = 1e-9
    lin = LaggedFactorSolver(rtol=rtol, maxiter=5)
    b = np.random.default_rng(4).standard_normal(N ** 3)
    K0 = _indefinite()
    lin.solve(_upper(K0), b)
    assert lin.last["refactorized"] and lin.factorizations == 1
    K1 = (_laplacian() - 0.661 * sp.identity(N ** 3)).tocsr()
    x = lin.solve(_upper(K1), b)
    assert lin.last["refactorized"] and lin.last["krylov"] == "gmres"
    assert lin.factorizations == 2 and lin.last["krylov_iterations"] >= 5
    assert np.linalg.norm(K1 @ x - b) <= rtol * np.linalg.norm(b)
    lin.begin_step()
    Kspd = _laplacian()
    x = lin.solve(_upper(Kspd), b)
    assert lin.last["krylov"] == "cg" and not lin.indefinite
    assert np.linalg.norm(Kspd @ x - b) <= rtol * np.linalg.norm(b)


def test_without_krylov_iterations_every_system_is_a_direct_solve():
    # maxiter = 0: the double-precision LDL^T with iterative refinement for each system
    # (backward stable: 1e-10 relative residual at cond ~ 100)
    lin = LaggedFactorSolver(maxiter=0)
    b = np.random.default_rng(6).standard_normal(N ** 3)
    for k in range(2):
        K = _indefinite(DELTA * k, seed=k)
        x = lin.solve(_upper(K), b)
        assert lin.last["direct"] and lin.last["krylov"] == ""
        assert np.linalg.norm(K @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert lin.factorizations == 2


def test_scipy_backend_lagged_lu_factor_on_indefinite_systems():
    # without PARDISO the back end's double-precision factor (SuperLU) serves both roles: an
    # LU factor does not fail on an indefinite matrix, so CG may solve the first system on its
    # exact factor; CG on a lagged factor then meets negative curvature, the system gets a
    # fresh factor and GMRES, and the next ones GMRES on that lagged factor: 2 factorisations
    # for 5 systems, each to the asked 1e-9 on the true residual
    lin = LaggedFactorSolver("scipy", rtol=1e-9)
    rng = np.random.default_rng(7)
    for k in range(5):
        K = _indefinite(DELTA * k / 4, seed=k)
        b = rng.standard_normal(N ** 3)
        x = lin.solve(_upper(K), b)
        assert np.linalg.norm(K @ x - b) <= 1e-9 * np.linalg.norm(b)
        if k >= 2:
            assert lin.last["krylov"] == "gmres" and not lin.last["refactorized"]
    assert lin.factorizations == 2
