"""Sparse direct solution of the symmetric tangent system, reusing the symbolic factorisation.

Matrices arrive as the upper triangle in CSR form with sorted indices (row <= column). Back
ends: PARDISO (Intel oneMKL through pypardiso) with a real symmetric indefinite matrix type
(mtype -2, Bunch-Kaufman pivoting, so indefinite tangents near instabilities still factorise);
the analysis phase (reordering and symbolic factorisation) is run once per sparsity pattern and
only the numerical factorisation is repeated. CHOLMOD (scikit-sparse) is used when installed and
asked for; SciPy's SuperLU on the full matrix is the fallback that is always present. "auto"
picks PARDISO when available: on the 28k-DOF Yeoh-cube tangent here PARDISO (mtype -2, analysis
reused) refactorises in 2.7-5.7 s, CHOLMOD (scikit-sparse 0.4.16 built against Debian 12's
SuiteSparse 5.12, supernodal, reference BLAS) in 29-30 s, SciPy SuperLU in 34-38 s, all on the
shared, heavily loaded 2-core machine (solver/README.md). CHOLMOD is an LL^T factorisation and
fails on indefinite tangents; PARDISO's Bunch-Kaufman LDL^T does not. Under that load PARDISO
is faster on one MKL thread (MKL_NUM_THREADS=1: 1.4-1.7 s per factorisation) than on two.
`LaggedFactorSolver` solves a sequence of Newton systems by conjugate gradients preconditioned
with the factor of an earlier tangent, refactorising only when CG stalls (fewer factorisations
for the same converged Newton solution).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["SymmetricSolver", "LaggedFactorSolver", "available_backends"]


def available_backends() -> list[str]:
    out = []
    try:
        import pypardiso  # noqa: F401
        out.append("pardiso")
    except Exception:
        pass
    try:
        import sksparse.cholmod  # noqa: F401
        out.append("cholmod")
    except Exception:
        pass
    out.append("scipy")
    return out


class _Pardiso:
    def __init__(self, mtype: int = -2):
        import pypardiso

        self.ps = pypardiso.PyPardisoSolver(mtype=mtype)
        self.ps.set_iparm(1, 1)     # user-supplied iparm values below
        self.ps.set_iparm(2, 2)     # METIS nested dissection reordering
        self.ps.set_iparm(8, 2)     # up to two iterative refinement steps
        self.ps.set_iparm(10, 8)    # pivot perturbation 1e-8
        self.ps.set_iparm(11, 0)    # no scaling (default for symmetric indefinite)
        self.ps.set_iparm(13, 0)    # no weighted matching (default for symmetric indefinite)
        self.ps.set_iparm(21, 1)    # Bunch-Kaufman 1x1 / 2x2 pivoting
        self.ps.set_iparm(35, 0)    # pypardiso passes one-based indices
        self._pattern = None

    def factorize(self, A: sp.csr_matrix) -> None:
        b = np.zeros(A.shape[0])
        same = (self._pattern is not None and self._pattern[0].shape == A.indptr.shape
                and self._pattern[1].shape == A.indices.shape
                and np.array_equal(self._pattern[0], A.indptr)
                and np.array_equal(self._pattern[1], A.indices))
        if not same:
            self.ps.free_memory(everything=True)
            self.ps.set_phase(11)
            self.ps._call_pardiso(A, b)
            self._pattern = (A.indptr.copy(), A.indices.copy())
        self.ps.set_phase(22)
        self.ps._call_pardiso(A, b)
        self._A = A

    def apply(self, b: np.ndarray, refine: bool = True) -> np.ndarray:
        """Solve with the stored factor (forward/backward substitution, phase 33); without
        `refine` no iterative refinement steps (each costs a further substitution: a
        preconditioner application needs none)."""
        self.ps.set_phase(33)
        self.ps.set_iparm(8, 2 if refine else 0)
        return np.asarray(self.ps._call_pardiso(self._A, b)).ravel()

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        self.factorize(A)
        return self.apply(b)


class _Cholmod:
    def __init__(self):
        from sksparse.cholmod import analyze  # noqa: F401

        self._factor = None
        self._pattern = None

    def solve(self, A, b):
        self.factorize(A)
        return self.apply(b)

    def apply(self, b, refine=True):
        return self._factor(b)

    def factorize(self, A):
        from sksparse.cholmod import analyze

        # scikit-sparse hands CHOLMOD the full symmetric matrix
        L = (A + sp.triu(A, k=1, format="csr").T).tocsc()
        same = (self._pattern is not None and np.array_equal(self._pattern[0], A.indptr)
                and np.array_equal(self._pattern[1], A.indices))
        if not same:
            self._factor = analyze(L, mode="supernodal", ordering_method="nesdis")
            self._pattern = (A.indptr.copy(), A.indices.copy())
        self._factor.cholesky_inplace(L)


class _Scipy:
    def factorize(self, A):
        K = (A + sp.triu(A, k=1).T).tocsc()
        self._lu = spla.splu(K, permc_spec="COLAMD")

    def apply(self, b, refine=True):
        return self._lu.solve(b)

    def solve(self, A, b):
        self.factorize(A)
        return self.apply(b)


class SymmetricSolver:
    """Solve A x = b for symmetric A given as its upper triangle (CSR)."""

    def __init__(self, backend: str = "auto"):
        avail = available_backends()
        if backend == "auto":
            backend = "pardiso" if "pardiso" in avail else "scipy"
        if backend not in ("pardiso", "cholmod", "scipy"):
            raise ValueError(f"unknown linear solver {backend!r}")
        if backend not in avail:
            raise ValueError(f"linear solver {backend!r} is not installed (available: {avail})")
        self.backend = backend
        self._impl = {"pardiso": _Pardiso, "cholmod": _Cholmod, "scipy": _Scipy}[backend]()

        self.factorizations = 0

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """Factorise A (numerically; the analysis is reused per pattern) and solve."""
        self.factorize(A)
        return self.apply(b)

    def factorize(self, A: sp.csr_matrix) -> None:
        if not A.has_sorted_indices:
            A.sort_indices()
        self._impl.factorize(A)
        self.factorizations += 1

    def apply(self, b: np.ndarray, refine: bool = True) -> np.ndarray:
        """Solve with the factor of the matrix last given to `factorize` (`refine`: with the
        back end's iterative refinement against that matrix, PARDISO: two steps)."""
        return self._impl.apply(np.ascontiguousarray(b, dtype=float), refine)


def _sym_operator(A: sp.csr_matrix) -> spla.LinearOperator:
    """The full symmetric matrix as an operator, from its upper triangle (CSR)."""
    At = A.T.tocsr()
    d = A.diagonal()

    def mv(v):
        v = np.ravel(v)
        return A @ v + At @ v - d * v

    return spla.LinearOperator(A.shape, matvec=mv, dtype=float)


class LaggedFactorSolver:
    """Newton systems K_k du = b_k solved with a lagged factor as a Krylov preconditioner.

    The first system is factorised (PARDISO / CHOLMOD / SuperLU through `SymmetricSolver`) and
    solved directly. Later systems, whose tangents K_k are assembled fresh but differ from the
    factorised one only by the change of state since, are solved by preconditioned conjugate
    gradients (SciPy `cg`) on the exact K_k with the stored factor as the preconditioner, to
    the relative residual `rtol` |b_k| (the inexact Newton method of Dembo, Eisenstat &
    Steihaug 1982 with a fixed forcing term, here small enough that the Newton iterates are
    those of exact Newton to about `rtol`). When CG needs more than `maxiter` iterations (the
    factor has gone stale, or the tangent is indefinite so that CG breaks down), K_k itself is
    factorised and solved directly: a "refactorisation". The converged solution is unchanged
    because the Newton residual is always the exact one; only the cost per iteration drops
    when a factorisation (seconds at 30k DOF) is replaced by a few substitutions (a tenth of
    that each). `last` holds the statistics of the last solve (Krylov iterations, whether it
    refactorised, relative residual reached); `krylov_iterations` and `factorizations` count
    over the solver's life.
    """

    def __init__(self, backend: str = "auto", rtol: float = 1e-8, maxiter: int = 8,
                 forcing_max: float = 1e-2):
        self.direct = SymmetricSolver(backend)
        self.backend = self.direct.backend
        self.rtol = float(rtol)
        self.maxiter = int(maxiter)
        self.forcing_max = float(forcing_max)   # loosest relative tolerance a caller may ask
        self.has_factor = False
        self.krylov_iterations = 0
        self.last = {}

    @property
    def factorizations(self) -> int:
        return self.direct.factorizations

    def reset(self) -> None:
        """Forget the factor: the next solve factorises."""
        self.has_factor = False

    def _refactor(self, A, b):
        self.direct.factorize(A)
        self.has_factor = True
        x = self.direct.apply(b)
        self.last = {"krylov_iterations": 0, "refactorized": True, "krylov_residual": 0.0}
        return x

    def solve(self, A: sp.csr_matrix, b: np.ndarray, rtol: float | None = None) -> np.ndarray:
        """Solve A x = b to the relative residual `rtol` (default: the solver's)."""
        rtol = self.rtol if rtol is None else float(rtol)
        if not A.has_sorted_indices:
            A.sort_indices()
        b = np.ascontiguousarray(b, dtype=float)
        if not self.has_factor or self.maxiter <= 0:
            return self._refactor(A, b)
        bn = float(np.linalg.norm(b))
        if bn == 0.0:
            self.last = {"krylov_iterations": 0, "refactorized": False, "krylov_residual": 0.0}
            return np.zeros_like(b)
        K = _sym_operator(A)
        M = spla.LinearOperator(A.shape, dtype=float,
                                matvec=lambda v: self.direct.apply(np.ravel(v), refine=False))
        count = [0]

        def cb(xk):
            count[0] += 1

        x0 = self.direct.apply(b, refine=False)     # lagged-factor solution as initial guess
        x, flag = spla.cg(K, b, x0=x0, rtol=rtol, atol=0.0, maxiter=self.maxiter, M=M,
                          callback=cb)
        rel = float(np.linalg.norm(b - K @ x)) / bn
        self.krylov_iterations += count[0]
        # the recurrence residual CG tests may drift from the true one: accept up to 10x
        if flag != 0 or not rel <= 10.0 * rtol:
            x = self._refactor(A, b)
            self.last["krylov_iterations"] = count[0]
            return x
        self.last = {"krylov_iterations": count[0], "refactorized": False, "krylov_residual": rel}
        return x
