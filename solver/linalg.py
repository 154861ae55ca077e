"""Sparse direct solution of the symmetric tangent system, reusing the symbolic factorisation.

Matrices arrive as the upper triangle in CSR form with sorted indices (row <= column). Back
ends: PARDISO (Intel oneMKL, called through our own ctypes binding: pypardiso only locates the
library, its wrapper copies and re-indexes the pattern on every call and passes float64 only)
with a real symmetric indefinite matrix type
(mtype -2, Bunch-Kaufman pivoting, so indefinite tangents near instabilities still factorise);
the analysis phase (reordering and symbolic factorisation) is run once per sparsity pattern and
only the numerical factorisation is repeated. CHOLMOD (scikit-sparse) is used when installed and
asked for; SciPy's SuperLU on the full matrix is the fallback that is always present. "auto"
picks PARDISO when available: it refactorises a tangent of tens of thousands of unknowns
several times faster than CHOLMOD with reference BLAS or SuperLU (`bench/solver_peer.py`).
CHOLMOD is an LL^T factorisation and fails on indefinite tangents; PARDISO's Bunch-Kaufman
LDL^T does not.
A pattern that changes between calls is factorised inside the union of the patterns seen, so
the analysis is repeated only while that union grows. `LaggedFactorSolver` solves a sequence of
Newton systems by conjugate gradients (`preconditioned_cg`, numba kernels) preconditioned with a
single-precision Cholesky factor (mtype 2, iparm[27] = 1) of an earlier tangent, refactorising
only when CG stalls; indefinite tangents by right-preconditioned GMRES (`preconditioned_gmres`,
Saad & Schultz 1986) with the lagged single-precision LDL^T factor of an earlier indefinite
tangent, refactorised likewise (fewer, cheaper factorisations for the same converged Newton
solution).
"""
from __future__ import annotations

import ctypes
import glob
import os
import sys
import time

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import solve_triangular

__all__ = ["SymmetricSolver", "LaggedFactorSolver", "PardisoError", "available_backends",
           "preconditioned_cg", "preconditioned_gmres", "sym_matvec"]


def available_backends() -> list[str]:
    out = []
    try:
        _mkl_pardiso_function()
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


_MKL = None
# seconds spent in PARDISO's phases since the process started (for profiles: `newton_solve`
# reports the share of each solve)
TIMING = {"analysis": 0.0, "factorization": 0.0, "substitution": 0.0}


def _mkl_pardiso_function():
    """MKL's `pardiso` entry point with our own ctypes signature (pypardiso finds the library:
    its wrapper copies and re-indexes the pattern on every call and only passes float64)."""
    global _MKL
    if _MKL is None:
        # the wheel's library next to the interpreter first (pypardiso's own search walks the
        # whole environment with a recursive glob: ~0.5 s)
        lib = None
        for path in sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len):
            try:
                lib = ctypes.CDLL(path)
                break
            except OSError:
                pass
        if lib is None:
            import pypardiso

            lib = ctypes.CDLL(pypardiso.PyPardisoSolver().libmkl._name)
        fn = lib.pardiso
        fn.restype = None
        fn.argtypes = [ctypes.c_void_p] + [ctypes.POINTER(ctypes.c_int32)] * 5 + \
            [ctypes.c_void_p] * 3 + [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32),
                                     ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32),
                                     ctypes.c_void_p, ctypes.c_void_p,
                                     ctypes.POINTER(ctypes.c_int32)]
        _MKL = (lib, fn)
    return _MKL[1]


def _mkl_threads() -> int:
    """MKL's thread count: PARDISO's conditional numerical reproducibility mode (iparm[33] > 0)
    makes its factors and solutions bitwise the same from run to run for that many threads
    (without it, the same matrix gives factors that differ in the last bits with the state of
    the process: a Krylov solve to a loose tolerance then carries the difference into the
    Newton iterates, and a contact solve's path, and its iteration count, changes)."""
    try:
        _mkl_pardiso_function()
        return max(int(_MKL[0].MKL_Get_Max_Threads()), 1)
    except Exception:
        return 1


def _aligned(a, dtype) -> np.ndarray:
    """A C-contiguous copy of `a` as `dtype` on a 64-byte boundary: MKL's conditional
    numerical reproducibility holds for aligned input and output arrays (oneMKL developer
    guide, "Obtaining numerically reproducible results"), which NumPy's allocator does not
    guarantee."""
    a = np.asarray(a)
    dtype = np.dtype(dtype)
    n = a.size
    buf = np.empty(n * dtype.itemsize + 64, dtype=np.uint8)
    off = (-buf.ctypes.data) % 64
    out = buf[off:off + n * dtype.itemsize].view(dtype).reshape(a.shape)
    out[...] = a
    return out


class PardisoError(RuntimeError):
    """PARDISO returned an error code (-4: zero pivot, e.g. a Cholesky factorisation of a
    matrix that is not positive definite)."""

    def __init__(self, code: int, phase: int):
        super().__init__(f"PARDISO error {code} in phase {phase}")
        self.code = code
        self.phase = phase


class _Pardiso:
    """Intel oneMKL PARDISO on an upper-triangle CSR matrix, called directly through ctypes.

    mtype -2: real symmetric indefinite (Bunch-Kaufman LDL^T); mtype 2: real symmetric positive
    definite (Cholesky LL^T, faster, fails with `PardisoError` code -4 when the matrix is not
    positive definite). `single`: factorise in single precision (iparm[27] = 1; matrix, right
    side and solution passed as float32) - about 1.5-2x faster and half the memory, accurate to
    ~1e-4 relative, meant for preconditioners. The pattern is passed zero-based (iparm[34] = 1)
    as int32 arrays kept between calls; the analysis (phase 11: METIS reordering, symbolic
    factorisation) runs once per pattern, each `factorize` is phase 22 only.
    """

    def __init__(self, mtype: int = -2, single: bool = False):
        self._fn = _mkl_pardiso_function()
        self.mtype = int(mtype)
        self.single = bool(single)
        self.dtype = np.float32 if single else np.float64
        self.pt = np.zeros(64, dtype=np.int64)      # PARDISO's opaque handle
        ip = np.zeros(64, dtype=np.int32)           # iparm, zero-based (MKL's C indexing)
        ip[0] = 1                                   # user-supplied values below
        ip[1] = 2                                   # METIS nested dissection reordering
        ip[7] = 2                                   # up to two iterative refinement steps
        ip[9] = 8 if mtype == -2 else 7             # pivot perturbation 1e-8 (1e-7 for SPD)
        ip[10] = 0                                  # no scaling
        ip[12] = 0                                  # no weighted matching
        ip[20] = 1                                  # Bunch-Kaufman 1x1 / 2x2 pivoting
        ip[27] = 1 if single else 0                 # single-precision factor and solve
        ip[33] = _mkl_threads()                     # CNR mode: bitwise reproducible
        ip[34] = 1                                  # zero-based indices
        self.iparm = ip
        self._ia = None
        self._ja = None
        self._a = None
        self.n = 0

    def _call(self, phase: int, b=None, x=None, nrhs: int = 1) -> None:
        err = ctypes.c_int32(0)
        i32 = ctypes.c_int32
        bptr = xptr = None
        if b is not None:
            bptr, xptr = b.ctypes.data, x.ctypes.data
        a = self._a.ctypes.data if self._a is not None else None
        ia = self._ia.ctypes.data if self._ia is not None else None
        ja = self._ja.ctypes.data if self._ja is not None else None
        self._fn(self.pt.ctypes.data, ctypes.byref(i32(1)), ctypes.byref(i32(1)),
                 ctypes.byref(i32(self.mtype)), ctypes.byref(i32(phase)),
                 ctypes.byref(i32(self.n)), a, ia, ja, None, ctypes.byref(i32(nrhs)),
                 self.iparm.ctypes.data, ctypes.byref(i32(0)), bptr, xptr, ctypes.byref(err))
        if err.value != 0:
            raise PardisoError(int(err.value), phase)

    def _timed(self, key, phase, b=None, x=None, nrhs=1):
        t0 = time.perf_counter()
        try:
            self._call(phase, b, x, nrhs)
        finally:
            TIMING[key] += time.perf_counter() - t0

    def _same_pattern(self, A) -> bool:
        return (self._ia is not None and self._ia.shape[0] == A.indptr.shape[0]
                and self._ja.shape[0] == A.indices.shape[0]
                and np.array_equal(self._ia, A.indptr) and np.array_equal(self._ja, A.indices))

    def factorize(self, A: sp.csr_matrix) -> None:
        if self._same_pattern(A):
            self._a = _aligned(A.data, self.dtype)
        else:
            # A pattern that changes between calls (contact pairs coming and going) is embedded
            # in the union of the analysed pattern and the new one: once the union has
            # stopped growing, every factorisation reuses the analysis (explicit zeros cost a
            # little fill, a new analysis costs about a factorisation)
            ib = np.ascontiguousarray(A.indptr, dtype=np.int32)
            jb = np.ascontiguousarray(A.indices, dtype=np.int32)
            if self._ia is not None and self._ia.shape[0] == ib.shape[0]:
                ia, ja = _pattern_union(self._ia, self._ja, ib, jb)
            else:
                ia, ja = ib, jb
            grown = not (self._ia is not None and ia.shape == self._ia.shape
                         and ja.shape == self._ja.shape)
            a = np.zeros(len(ja))
            _embed_values(ia, ja, ib, jb, np.ascontiguousarray(A.data, dtype=float), a)
            self._a = _aligned(a, self.dtype)
            if grown:
                self.release()
                self._ia, self._ja = _aligned(ia, np.int32), _aligned(ja, np.int32)
                self.n = A.shape[0]
                self._timed("analysis", 11)
        self._timed("factorization", 22)

    def apply(self, b: np.ndarray, refine: bool = True) -> np.ndarray:
        """Solve with the stored factor (forward/backward substitution, phase 33); without
        `refine` no iterative refinement steps (each costs a further substitution: a
        preconditioner application needs none). b (n,) or (n, k): k right-hand sides solved in
        one call (PARDISO takes them column after column)."""
        self.iparm[7] = 2 if refine else 0
        if np.ndim(b) == 2:
            bb = _aligned(np.asarray(b).T, self.dtype)     # (k, n): columns
            x = _aligned(np.zeros(bb.shape), self.dtype)
            self._timed("substitution", 33, bb, x, nrhs=bb.shape[0])
            return x.T.astype(np.float64)
        bb = _aligned(b, self.dtype)
        x = _aligned(np.zeros(bb.shape), self.dtype)
        self._timed("substitution", 33, bb, x)
        return x.astype(np.float64, copy=False)

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        self.factorize(A)
        return self.apply(b)

    def release_factor(self) -> None:
        """Free the numerical factor's memory (phase 0), keeping the analysis."""
        if self._ia is not None and self.pt.any():
            self._call(0)

    def release(self) -> None:
        """Free PARDISO's memory for this handle (phase -1)."""
        if self._ia is not None and self.pt.any():
            try:
                self._call(-1)
            except PardisoError:
                pass
        self.pt[:] = 0

    def __del__(self):
        try:
            self.release()
        except Exception:
            pass


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

    def release_factor(self) -> None:
        """Free the factor's memory (PARDISO: the analysis is kept for the next factorize)."""
        if hasattr(self._impl, "release_factor"):
            self._impl.release_factor()


@nb.njit(cache=True)
def _pattern_union(ia, ja, ib, jb):
    """CSR pattern (sorted columns) holding the entries of both sorted CSR patterns."""
    n = ia.shape[0] - 1
    indptr = np.zeros(n + 1, dtype=np.int32)
    out = np.empty(ja.shape[0] + jb.shape[0], dtype=np.int32)
    pos = 0
    for i in range(n):
        p, pe = ia[i], ia[i + 1]
        q, qe = ib[i], ib[i + 1]
        while p < pe or q < qe:
            if q >= qe or (p < pe and ja[p] < jb[q]):
                out[pos] = ja[p]
                p += 1
            elif p >= pe or jb[q] < ja[p]:
                out[pos] = jb[q]
                q += 1
            else:
                out[pos] = ja[p]
                p += 1
                q += 1
            pos += 1
        indptr[i + 1] = pos
    return indptr, out[:pos].copy()


@nb.njit(cache=True)
def _embed_values(iu, ju, ia, ja, a, out):
    """out (on the pattern iu, ju, zeroed) += the values a of its sub-pattern ia, ja."""
    n = iu.shape[0] - 1
    for i in range(n):
        p = iu[i]
        for k in range(ia[i], ia[i + 1]):
            c = ja[k]
            while ju[p] < c:
                p += 1
            out[p] += a[k]


@nb.njit(cache=True)
def _sym_upper_matvec(indptr, indices, data, x, y):
    """y = A x for the symmetric A given by its upper triangle (CSR), in one pass."""
    n = x.shape[0]
    for i in range(n):
        y[i] = 0.0
    for i in range(n):
        xi = x[i]
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            a = data[k]
            s += a * x[j]
            if j != i:
                y[j] += a * xi
        y[i] += s


@nb.njit(cache=True)
def _dot(a, b):
    # a plain loop: NumPy's BLAS dot spawns threads that, on a loaded machine, cost
    # milliseconds per call on 30k-long vectors
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@nb.njit(cache=True)
def _cg_update(x, r, p, Ap, alpha):
    """x += alpha p, r -= alpha Ap; returns |r|^2."""
    s = 0.0
    for i in range(x.shape[0]):
        x[i] += alpha * p[i]
        r[i] -= alpha * Ap[i]
        s += r[i] * r[i]
    return s


@nb.njit(cache=True)
def _cg_direction(p, z, beta):
    for i in range(p.shape[0]):
        p[i] = z[i] + beta * p[i]


def sym_matvec(A: sp.csr_matrix, x: np.ndarray) -> np.ndarray:
    """The full symmetric matrix times x, from its upper triangle (CSR)."""
    y = np.empty(A.shape[0])
    _sym_upper_matvec(A.indptr, A.indices, A.data, np.ascontiguousarray(x, dtype=float), y)
    return y


def _start(A, b, x0, work):
    """Initial iterate and residual of a Krylov solve: (0, b), or (x0, b - A x0) with the
    product written into `work`."""
    if x0 is None:
        return np.zeros_like(b), b.copy()
    x = np.array(x0, dtype=float)
    _sym_upper_matvec(A.indptr, A.indices, A.data, x, work)
    return x, b - work


def preconditioned_cg(A: sp.csr_matrix, b: np.ndarray, precondition, rtol: float,
                      maxiter: int, x0: np.ndarray | None = None, predict_from: int = 0):
    """Preconditioned conjugate gradients (Hestenes & Stiefel 1952; Saad 2003, alg. 9.1) on the
    symmetric matrix given by its upper triangle, to |b - A x| <= rtol |b|.

    Returns (x, iterations, status, relative residual) with status "converged", "maxiter",
    "breakdown" (a direction of non-positive curvature p.Ap <= 0 or a non-positive r.z: the
    matrix or the preconditioner is not positive definite) or "slow": with `predict_from` > 0,
    from that iteration on the solve stops as soon as the mean rate of the residual so far,
    (|r_k| / |b|)^(1/k), would need more than `maxiter` iterations in all to reach rtol (a
    stale preconditioner: the caller refactorises at once instead of after `maxiter`
    iterations). Each iteration is one product with A and one preconditioner application.
    """
    indptr, indices, data = A.indptr, A.indices, A.data
    bn = float(np.sqrt(_dot(b, b)))
    if bn == 0.0:
        return np.zeros_like(b), 0, "converged", 0.0
    Ap = np.empty_like(b)
    x, r = _start(A, b, x0, Ap)
    rr = _dot(r, r)
    goal = (rtol * bn) ** 2
    if rr <= goal:
        return x, 0, "converged", float(np.sqrt(rr)) / bn
    z = precondition(r)
    rz = _dot(r, z)
    p = z.copy()
    status = "maxiter"
    it = 0
    while it < maxiter:
        if not rz > 0.0:
            status = "breakdown"
            break
        it += 1
        _sym_upper_matvec(indptr, indices, data, p, Ap)
        pAp = _dot(p, Ap)
        if not pAp > 0.0:
            status = "breakdown"
            break
        rr = _cg_update(x, r, p, Ap, rz / pAp)
        if rr <= goal:
            status = "converged"
            break
        if predict_from and it >= predict_from:
            # mean rate so far, log10 of the residual reduction per iteration; stop when it
            # needs more than `maxiter` iterations to reach rtol (a stale preconditioner)
            rate = 0.5 * np.log(max(rr, 1e-300) / (bn * bn)) / it
            if not (rate < 0.0 and np.log(rtol) / rate <= maxiter):
                status = "slow"
                break
        z = precondition(r)
        rz_new = _dot(r, z)
        _cg_direction(p, z, rz_new / rz)
        rz = rz_new
    # the recurrence residual may drift from the true one: report the true one
    _sym_upper_matvec(indptr, indices, data, x, Ap)
    res = b - Ap
    return x, it, status, float(np.sqrt(_dot(res, res))) / bn


@nb.njit(cache=True)
def _arnoldi_step(V, j, w, h):
    """Modified Gram-Schmidt: w -= sum_i h_i V_i over the basis vectors V[0..j], h_i = V_i.w
    taken as w is updated (Saad 2003, alg. 6.2); h[j + 1] = |w| afterwards, returned."""
    n = w.shape[0]
    for i in range(j + 1):
        s = 0.0
        for k in range(n):
            s += V[i, k] * w[k]
        h[i] = s
        for k in range(n):
            w[k] -= s * V[i, k]
    s = 0.0
    for k in range(n):
        s += w[k] * w[k]
    h[j + 1] = np.sqrt(s)
    return h[j + 1]


@nb.njit(cache=True)
def _givens_update(h, j, cs, sn, g):
    """Apply the earlier plane rotations to the new Hessenberg column h[0..j+1], make and apply
    the rotation that zeroes h[j+1], rotate the right side g; returns |g[j+1]|, the residual
    norm of the least-squares problem (that of the true residual, in exact arithmetic)."""
    for i in range(j):
        t = cs[i] * h[i] + sn[i] * h[i + 1]
        h[i + 1] = -sn[i] * h[i] + cs[i] * h[i + 1]
        h[i] = t
    rho = np.hypot(h[j], h[j + 1])
    if rho == 0.0:
        cs[j], sn[j] = 1.0, 0.0
    else:
        cs[j], sn[j] = h[j] / rho, h[j + 1] / rho
    h[j] = rho
    h[j + 1] = 0.0
    g[j + 1] = -sn[j] * g[j]
    g[j] = cs[j] * g[j]
    return abs(g[j + 1])


@nb.njit(cache=True)
def _add_combination(x, Z, y, m):
    """x += sum_i y_i Z_i over the first m rows of Z."""
    for i in range(m):
        yi = y[i]
        for k in range(x.shape[0]):
            x[k] += yi * Z[i, k]


def preconditioned_gmres(A: sp.csr_matrix, b: np.ndarray, precondition, rtol: float,
                         maxiter: int, x0: np.ndarray | None = None,
                         history: list | None = None, predict_from: int = 0):
    """Right-preconditioned GMRES (Saad & Schultz 1986; Saad 2003, alg. 9.5, with the
    preconditioned basis kept as in FGMRES, alg. 9.6, so that no substitution is spent on the
    update) on the symmetric matrix given by its upper triangle, to |b - A x| <= rtol |b|.

    Valid for a symmetric indefinite matrix with an indefinite preconditioner (e.g. the
    Bunch-Kaufman LDL^T factor of an earlier tangent), where CG and MINRES are not. With right
    preconditioning the residual GMRES minimises is the true, unpreconditioned one, so the
    stopping test is on the caller's residual; the true residual is recomputed at the end (one
    product) and reported. One cycle of at most `maxiter` iterations, no restart (the caller
    refactorises instead). Returns (x, iterations, status, relative residual) as
    `preconditioned_cg`, status "converged", "maxiter", "breakdown" (not finite) or "slow":
    with `predict_from` > 0, from that iteration on the solve stops as soon as the mean rate
    of the residual so far would need more than `maxiter` iterations in all to reach rtol (a
    stale preconditioner, as in `preconditioned_cg`; x is then the minimiser over the Krylov
    space built so far). `history`, if given, receives the relative residual estimate of each
    iteration.
    """
    indptr, indices, data = A.indptr, A.indices, A.data
    n = b.shape[0]
    bn = float(np.sqrt(_dot(b, b)))
    if bn == 0.0:
        return np.zeros_like(b), 0, "converged", 0.0
    w = np.empty_like(b)
    x, r = _start(A, b, x0, w)
    beta = float(np.sqrt(_dot(r, r)))
    goal = rtol * bn
    if beta <= goal:
        return x, 0, "converged", beta / bn
    m = max(int(maxiter), 1)
    V = np.empty((m + 1, n))
    Z = np.empty((m, n))
    H = np.zeros((m + 1, m))
    h = np.zeros(m + 1)
    cs = np.zeros(m)
    sn = np.zeros(m)
    g = np.zeros(m + 1)
    g[0] = beta
    V[0] = r / beta
    status = "maxiter"
    it = 0
    for j in range(m):
        Z[j] = precondition(V[j])
        _sym_upper_matvec(indptr, indices, data, Z[j], w)
        hn = _arnoldi_step(V, j, w, h)
        res = _givens_update(h, j, cs, sn, g)
        H[: j + 1, j] = h[: j + 1]
        it = j + 1
        if history is not None:
            history.append(res / bn)
        if not np.isfinite(res):
            status = "breakdown"
            break
        if res <= goal or hn == 0.0:     # hn = 0: the Krylov space holds the solution
            status = "converged"
            break
        if predict_from and it >= predict_from and it < m:
            rate = np.log(max(res, 1e-300) / beta) / it
            if not (rate < 0.0 and np.log(goal / beta) / rate <= m):
                status = "slow"
                break
        V[j + 1] = w / hn
    if status != "breakdown":
        y = solve_triangular(H[:it, :it], g[:it])      # the rotated, upper Hessenberg
        _add_combination(x, Z, y, it)
    _sym_upper_matvec(indptr, indices, data, x, w)
    res = b - w
    rel = float(np.sqrt(_dot(res, res))) / bn
    if not np.isfinite(rel):
        status = "breakdown"
    return x, it, status, rel


class LaggedFactorSolver:
    """Newton systems K_k du = b_k solved by a Krylov method preconditioned with the factor of
    an earlier K.

    A factor of some tangent K_j (j <= k) is kept, across Newton iterations and load steps, and
    each new system, assembled with the fresh tangent K_k, is solved by a preconditioned Krylov
    method to the relative residual asked by the caller: the inexact Newton method of Dembo,
    Eisenstat & Steihaug (1982), whose forcing terms the caller chooses (Eisenstat & Walker
    1996). The Newton residual is always the exact one, so the converged solution is that of
    exact Newton; only the cost per iteration drops, a factorisation (seconds at 30k unknowns)
    being replaced by a few substitutions (hundredths).

    Positive definite tangents: conjugate gradients (`preconditioned_cg`) with a Cholesky factor
    (PARDISO mtype 2), in single precision by default (`precision="single"`: about twice as
    fast to compute, and a factor accurate to ~1e-4 is as good a preconditioner as an exact
    one). It is refreshed ("refactorisation") when CG does not converge within `maxiter`
    iterations, or before the next solve when the last one needed more than
    `refactor_iterations` (the factor is going stale). From iteration `predict_from` on, CG
    on the kept factor also gives up as soon as its mean rate predicts more than `maxiter`
    iterations (`preconditioned_cg`'s "slow" status), so that a factor made stale by a large
    change of the tangent (contact switching on) costs 3 substitutions, not 10.

    Indefinite tangents (Cholesky fails, or CG meets a direction of non-positive curvature):
    the solver switches to its indefinite mode until `begin_step` is called. There the
    preconditioner is the Bunch-Kaufman LDL^T factor (PARDISO mtype -2, same precision) of an
    earlier indefinite tangent, and the Krylov method is right-preconditioned GMRES
    (`preconditioned_gmres`), valid for an indefinite matrix with an indefinite preconditioner
    (CG and MINRES are not) and stopping on the true residual; the LDL^T factor is renewed
    under the same rules as the Cholesky one (GMRES on a stale factor gives up from iteration
    `predict_from` on, as CG does). A system that GMRES does not solve even with the
    fresh factor (a nearly singular tangent, where the single-precision factor is too
    perturbed) is solved by the double-precision LDL^T factorisation with iterative refinement
    (`SymmetricSolver`), as is every system when `maxiter` <= 0. Without PARDISO the back
    end's double-precision factor (CHOLMOD / SuperLU) serves all roles.

    `last` holds the statistics of the last solve: Krylov iterations, "refactorized" (a
    factor was computed for this system), "direct" (it was an LDL^T factorisation, of the
    indefinite mode or the double-precision fallback), "krylov" ("cg", "gmres" or "" for a
    direct solve), the relative residual reached; `krylov_iterations` and `factorizations`
    count over the solver's life, `ldlt_factorizations` the LDL^T ones among them.
    """

    def __init__(self, backend: str = "auto", rtol: float = 1e-8, maxiter: int = 10,
                 forcing_max: float = 1e-2, refactor_iterations: int = 8,
                 precision: str = "single", predict_from: int = 3):
        if precision not in ("single", "double"):
            raise ValueError(f"precision must be 'single' or 'double', got {precision!r}")
        self.direct = SymmetricSolver(backend)
        self.backend = self.direct.backend
        if self.backend == "pardiso":
            self._precond = _Pardiso(mtype=2, single=precision == "single")
            self._ldl = _Pardiso(mtype=-2, single=precision == "single")
        else:
            self._precond = None            # the direct solver's factor
            self._ldl = None
        self.precision = precision if self.backend == "pardiso" else "double"
        self.rtol = float(rtol)
        self.maxiter = int(maxiter)
        self.forcing_max = float(forcing_max)   # loosest relative tolerance a caller may ask
        self.refactor_iterations = int(refactor_iterations)
        self.predict_from = int(predict_from)   # 0: CG runs its `maxiter` iterations
        self.has_factor = False
        self.stale = False
        self.indefinite = False             # indefinite mode: LDL^T preconditioner, GMRES
        self._ldl_factor = False
        self._ldl_stale = False
        self._step_refactorizations = 0     # factors renewed (not the first one) in this step
        self.krylov_iterations = 0
        self._factorizations = 0
        self.ldlt_factorizations = 0
        self.last = {}

    @property
    def factorizations(self) -> int:
        return self._factorizations + self.direct.factorizations

    def reset(self) -> None:
        """Forget the factors: the next solve factorises."""
        self.has_factor = False
        self.stale = False
        self._ldl_factor = False
        self._ldl_stale = False

    def begin_step(self) -> None:
        """A new load step: try the preconditioned CG path again after indefinite systems, and
        refactorise at once if the factor had to be renewed during the previous step (not its
        first): a load increment changes the tangent most, and a factor that went stale within
        the last step would make CG fail on the new step's first system, in vain."""
        if self.indefinite:             # back to CG: free the LDL^T factor's memory
            self._release_ldl()
        self.indefinite = False
        if self._step_refactorizations > 0:
            self.stale = True
        self._step_refactorizations = 0

    def _release_ldl(self) -> None:
        if self._ldl is not None:
            self._ldl.release_factor()
        self.direct.release_factor()
        self._ldl_factor = False
        self._ldl_stale = False

    def _factorize_preconditioner(self, A) -> bool:
        try:
            if self._precond is not None:
                self._precond.factorize(A)
                self._step_refactorizations += self._factorizations > 0
                self._factorizations += 1
            else:
                self._step_refactorizations += self.direct.factorizations > 0
                self.direct.factorize(A)
        except Exception:                   # not positive definite (or singular)
            self.has_factor = False
            return False
        self.has_factor = True
        self.stale = False
        return True

    def _record(self, x, its, refactorized, rel, direct, krylov):
        """Keep the statistics of this solve in `last` and return its solution x."""
        self.last = {"krylov_iterations": its, "refactorized": refactorized,
                     "krylov_residual": rel, "direct": direct, "krylov": krylov}
        return x

    def _apply(self, v):
        if self._precond is not None:
            return self._precond.apply(v, refine=False)
        return self.direct.apply(v, refine=False)

    def _apply_ldl(self, v):
        if self._ldl is not None:
            return self._ldl.apply(v, refine=False)
        return self.direct.apply(v, refine=False)

    def _factorize_ldl(self, A) -> None:
        """Factorise the indefinite tangent (LDL^T); a singular one raises, as a direct solve."""
        self._ldl_factor = False
        if self._ldl is not None:
            self._ldl.factorize(A)
            self._factorizations += 1
        else:
            self.direct.factorize(A)
        self._step_refactorizations += 1
        self.ldlt_factorizations += 1
        self._ldl_factor = True
        self._ldl_stale = False

    def _enter_indefinite(self) -> None:
        if not self.indefinite and self._precond is not None and self.has_factor:
            self._precond.release_factor()  # one factor in memory at a time
        self.indefinite = True
        self.has_factor = False

    def _direct(self, A, b, its):
        """The double-precision LDL^T solve with iterative refinement (backward stable)."""
        self._enter_indefinite()
        if self._ldl is not None and self._ldl_factor:
            self._ldl.release_factor()
        self._ldl_factor = False
        x = self.direct.solve(A, b)
        self.ldlt_factorizations += 1
        if self._ldl is None:               # the direct solver's factor is the preconditioner
            self._ldl_factor = True
            self._ldl_stale = False
        return self._record(x, its, True, 0.0, True, "")

    def _solve_indefinite(self, A, b, rtol, its):
        """GMRES preconditioned with the lagged LDL^T factor; refactorised when it stalls."""
        self._enter_indefinite()
        x = None
        if self._ldl_factor and not self._ldl_stale:
            x, k, status, rel = preconditioned_gmres(A, b, self._apply_ldl, rtol, self.maxiter,
                                                     predict_from=self.predict_from)
            self.krylov_iterations += k
            its += k
            if rel <= rtol:
                self._ldl_stale = k > self.refactor_iterations
                return self._record(x, its, False, rel, False, "gmres")
            if not np.all(np.isfinite(x)):
                x = None
        try:
            self._factorize_ldl(A)
        except PardisoError:                # singular in single precision: the double solve
            return self._direct(A, b, its)
        # with the fresh factor GMRES converges in one iteration (a double-precision factor)
        # or a few (single precision: each one gains ~1e-4)
        x, k, status, rel = preconditioned_gmres(A, b, self._apply_ldl, rtol,
                                                 max(self.maxiter, 10), x0=x)
        self.krylov_iterations += k
        its += k
        if rel <= rtol:
            return self._record(x, its, True, rel, True, "gmres")
        return self._direct(A, b, its)

    def solve(self, A: sp.csr_matrix, b: np.ndarray, rtol: float | None = None) -> np.ndarray:
        """Solve A x = b to the relative residual `rtol` (default: the solver's)."""
        rtol = self.rtol if rtol is None else float(rtol)
        if not A.has_sorted_indices:
            A.sort_indices()
        b = np.ascontiguousarray(b, dtype=float)
        if self.maxiter <= 0:
            return self._direct(A, b, 0)
        if self.indefinite:
            return self._solve_indefinite(A, b, rtol, 0)
        its = 0
        x = None
        if self.has_factor and not self.stale:
            x, its, status, rel = preconditioned_cg(A, b, self._apply, rtol, self.maxiter,
                                                    predict_from=self.predict_from)
            self.krylov_iterations += its
            if status == "converged" or rel <= rtol:
                self.stale = its > self.refactor_iterations
                return self._record(x, its, False, rel, False, "cg")
            if status == "breakdown":
                return self._solve_indefinite(A, b, rtol, its)
            if not np.all(np.isfinite(x)):
                x = None
        if not self._factorize_preconditioner(A):
            return self._solve_indefinite(A, b, rtol, its)
        # with the fresh factor CG converges in a few iterations (one for an exact factor)
        x, its2, status, rel = preconditioned_cg(A, b, self._apply, rtol,
                                                 max(self.maxiter, 10), x0=x)
        self.krylov_iterations += its2
        if status != "converged" and not rel <= rtol:
            return self._solve_indefinite(A, b, rtol, its + its2)
        return self._record(x, its + its2, True, rel, False, "cg")
