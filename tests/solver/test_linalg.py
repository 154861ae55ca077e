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


def test_preconditioned_cg_matches_direct():
    # CG with no preconditioner (identity) on the SPD Laplacian: converged to the asked 1e-10
    # relative residual, hence within cond(K) * 1e-10 (~1e-7) of the direct solution
    from solver.linalg import preconditioned_cg, sym_matvec

    K = _spd(8)
    U = _upper(K)
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    assert np.allclose(sym_matvec(U, b), K @ b, rtol=0, atol=1e-12 * np.abs(K @ b).max())
    x, its, status, rel = preconditioned_cg(U, b, lambda r: r.copy(), 1e-10, 500)
    assert status == "converged" and rel <= 1e-10 and its > 1
    xd = SymmetricSolver().solve(U, b)
    assert np.abs(x - xd).max() <= 1e-6 * np.abs(xd).max()


def test_cg_gives_up_early_when_its_rate_cannot_reach_the_tolerance():
    # Unpreconditioned CG on the Laplacian (cond ~ 1e3) converges by a factor far above
    # 0.1 per iteration: asked 1e-8 within 10 iterations it is hopeless, and with
    # predict_from=3 it stops after 3 ("slow") instead of 10 ("maxiter"); the same system with
    # an exact factor as preconditioner converges at once, the rate check never fires. The
    # iterate returned is the same CG iterate (its residual is the true one).
    from solver.linalg import _Pardiso, preconditioned_cg

    K = _spd(8)
    U = _upper(K)
    b = np.random.default_rng(5).standard_normal(K.shape[0])
    ident = lambda r: r.copy()
    x10, its10, status10, rel10 = preconditioned_cg(U, b, ident, 1e-8, 10)
    x3, its3, status3, rel3 = preconditioned_cg(U, b, ident, 1e-8, 10, predict_from=3)
    assert (status10, its10) == ("maxiter", 10) and (status3, its3) == ("slow", 3)
    x3ref, *_ = preconditioned_cg(U, b, ident, 1e-8, 3)
    assert np.array_equal(x3, x3ref) and rel3 > rel10 > 1e-8
    p = _Pardiso(mtype=2)
    p.factorize(U)
    x, its, status, rel = preconditioned_cg(U, b, lambda r: p.apply(r, refine=False), 1e-8, 10,
                                            predict_from=1)
    assert status == "converged" and rel <= 1e-8


def test_single_precision_factor_is_a_preconditioner_not_a_solver():
    # a single-precision Cholesky factor alone solves to ~1e-4..1e-6 relative (float32 round-off
    # times the condition number); as a CG preconditioner it reaches 1e-10 in a few iterations
    from solver.linalg import _Pardiso, preconditioned_cg

    K = _spd(10, shift=0.01)
    U = _upper(K)
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    p = _Pardiso(mtype=2, single=True)
    p.factorize(U)
    x1 = p.apply(b, refine=False)
    r1 = np.linalg.norm(K @ x1 - b) / np.linalg.norm(b)
    assert 1e-12 < r1 < 1e-3, r1
    x, its, status, rel = preconditioned_cg(U, b, lambda r: p.apply(r, refine=False), 1e-10, 20)
    assert status == "converged" and its <= 5 and rel <= 1e-10


def test_indefinite_matrix_switches_to_the_ldlt_preconditioner():
    # a symmetric indefinite matrix: the Cholesky preconditioner fails, the system is solved
    # by GMRES with its LDL^T factor (to the asked 1e-9 on the true residual), and so are the
    # next ones until a new load step begins (the lagged LDL^T factor or a new one)
    K = _spd() - 3.0 * sp.identity(_spd().shape[0])
    b = np.random.default_rng(4).standard_normal(K.shape[0])
    lin = LaggedFactorSolver(rtol=1e-9)
    x = lin.solve(_upper(K), b)
    assert lin.last["direct"] and lin.last["krylov"] == "gmres"
    assert np.linalg.norm(K @ x - b) <= 1e-9 * np.linalg.norm(b)
    K0 = _spd()
    x = lin.solve(_upper(K0), b)
    assert lin.last["krylov"] == "gmres" and lin.indefinite
    assert np.linalg.norm(K0 @ x - b) <= 1e-9 * np.linalg.norm(b)
    lin.begin_step()
    x = lin.solve(_upper(K0), b)
    assert not lin.last["direct"] and lin.last["refactorized"] and lin.last["krylov"] == "cg"
    assert np.linalg.norm(K0 @ x - b) <= 1e-9 * np.linalg.norm(b) * 1.0001


def test_breakdown_on_indefinite_system_then_back_to_cg():
    # the factor of an SPD matrix is kept; the next system is indefinite: CG meets negative
    # curvature (or fails), the system is solved with an LDL^T factor and GMRES (1e-9 on the
    # true residual), the Cholesky factor's memory is freed, and after begin_step CG works
    # again with a new factor
    K0 = _spd()
    b = np.random.default_rng(5).standard_normal(K0.shape[0])
    lin = LaggedFactorSolver(rtol=1e-9, maxiter=40)
    lin.solve(_upper(K0), b)
    assert not lin.last["direct"]
    K1 = K0 - 3.0 * sp.identity(K0.shape[0])
    x = lin.solve(_upper(K1), b)
    assert lin.last["direct"] and np.linalg.norm(K1 @ x - b) <= 1e-9 * np.linalg.norm(b)
    assert lin.indefinite and not lin.has_factor
    lin.begin_step()
    x = lin.solve(_upper(K0), b)
    assert not lin.last["direct"] and lin.last["refactorized"]
    assert np.linalg.norm(K0 @ x - b) <= 1e-9 * np.linalg.norm(b) * 1.0001


def test_changing_pattern_reuses_the_analysis_of_the_union():
    # a matrix whose pattern loses and regains entries (contact pairs): factorised in the
    # union pattern, analysed only when the union grows; the solutions are exact (1e-10)
    from solver.linalg import TIMING

    K0 = _spd(6)
    n = K0.shape[0]
    extra = sp.coo_matrix(([0.5, 0.5], ([0, 5], [7, 60])), shape=(n, n))
    K1 = (K0 + extra + extra.T).tocsr()             # two more coupling pairs
    b = np.random.default_rng(6).standard_normal(n)
    lin = SymmetricSolver()
    if lin.backend != "pardiso":
        return
    for K in (K1, K0, K1, K0):
        before = TIMING["analysis"]
        x = lin.solve(_upper(K), b)
        analysed = TIMING["analysis"] > before
        assert np.linalg.norm(K @ x - b) < 1e-10 * np.linalg.norm(b)
        if K is K0 and lin.factorizations > 1:
            assert not analysed                      # a sub-pattern of the union
    assert lin._impl._ja.shape[0] == _upper(K1).nnz


def test_several_right_hand_sides_in_one_substitution():
    # k right-hand sides at once (the sensitivities' du/dp for every parameter) give the same
    # columns as k single solves; an indefinite matrix (shifted Laplacian, negative
    # eigenvalues) exercises the LDL^T factor. Backward stable: residual ~1e-14 relative,
    # 1e-10 leaves room for the conditioning (~1e3)
    K = _spd(n=8, shift=-0.6)
    B = np.random.default_rng(5).standard_normal((K.shape[0], 4))
    for backend in SymmetricSolver.__init__.__defaults__[:1] + ("scipy",):
        lin = SymmetricSolver(backend)
        lin.factorize(_upper(K))
        X = lin.apply(B)
        assert X.shape == B.shape
        for j in range(B.shape[1]):
            assert np.linalg.norm(K @ X[:, j] - B[:, j]) < 1e-10 * np.linalg.norm(B[:, j])
            assert np.allclose(X[:, j], lin.apply(B[:, j]), rtol=0, atol=1e-10 * np.abs(X).max())


_REPRODUCIBLE_SOLVE = """
import hashlib, sys
import numpy as np, scipy.sparse as sp
from solver.linalg import SymmetricSolver
junk = [np.empty(int(s)) for s in sys.argv[1:]]   # a different allocation history per process
n = 16
one = sp.diags([-1.0, 1.4, -1.0], [-1, 0, 1], shape=(n, n))
eye = sp.identity(n)
K = (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one))
rng = np.random.default_rng(3)
K = (K + sp.diags(0.01 * rng.standard_normal(n ** 3))).tocsr()
U = sp.triu(K, format="csr"); U.sort_indices()
b = rng.standard_normal(n ** 3)
lin = SymmetricSolver("pardiso")
lin.factorize(U)
x = lin.apply(b)
print(hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest())
"""


def test_pardiso_gives_bitwise_the_same_solution_in_every_process():
    # The solver's claim: the same matrix gives bitwise the same factor and solution whatever
    # the process's state (PARDISO's conditional numerical reproducibility mode on 64-byte
    # aligned arrays), so a Newton path (and its iteration count) does not change between a run
    # with a fresh and one with a cached model. Three processes with different allocation
    # histories (hence differently aligned NumPy buffers) solve one indefinite system; their
    # solutions must agree to the last bit (tolerance 0: that is the claim).
    import subprocess
    import sys

    import pytest

    from solver.linalg import _aligned, available_backends

    if "pardiso" not in available_backends():
        pytest.skip("PARDISO (MKL) is not installed")
    a = _aligned(np.arange(7.0), np.float32)
    assert a.ctypes.data % 64 == 0 and np.array_equal(a, np.arange(7.0, dtype=np.float32))
    digests = {subprocess.run([sys.executable, "-c", _REPRODUCIBLE_SOLVE, *sizes], check=True,
                              capture_output=True, text=True).stdout.strip()
               for sizes in ([], ["3"], ["1", "5", "1001"])}
    assert len(digests) == 1, digests
