"""Cubic B-spline free-form deformation (FFD) fitted to scattered displacements.

A lattice of control displacements c_ijk with spacing h defines the smooth volumetric map
u(x) = sum_{l,m,n=0..3} B_l(s) B_m(t) B_n(r) c_{i+l-1, j+m-1, k+n-1} (Rueckert et al.,
"Nonrigid registration using free-form deformations", IEEE TMI 18, 1999). Given data points
p_a with wanted displacements r_a and weights w_a, the control displacements minimise
sum_a w_a |u(p_a) - r_a|^2 + lambda * tr(A^T W A)/n * sum_axes |D2 c|^2 + eps |c|^2,
a sparse symmetric positive definite system over the control points that support any data or
evaluation point: a thin-plate-like bending penalty on the lattice (second differences along
each axis), scaled by the mean data stiffness so that lambda is dimensionless. Each control
displacement is then clipped to 0.4 h per component, below the bound 1/K = 0.40 h of Choi and
Lee ("Injectivity conditions of 2D and 3D uniform cubic B-spline functions", Graph. Models 62,
2000) that makes the FFD a diffeomorphism; composing such maps level after level (coarse to
fine, as in the multilevel B-splines of Lee, Wolberg and Shin, IEEE TVCG 3, 1997) keeps the
volumetric transform free of folds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

INJECTIVE_FRACTION = 0.4 * 0.98  # of the spacing, per component (Choi & Lee bound with margin)


def bspline_weights(t: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline basis values (n, 4) at local coordinates t in [0, 1)."""
    t2, t3 = t * t, t * t * t
    return np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=-1) / 6.0


@dataclass(frozen=True)
class BSplineLattice:
    origin: np.ndarray
    spacing: float
    shape: tuple[int, int, int]

    @staticmethod
    def covering(points: np.ndarray, spacing: float) -> "BSplineLattice":
        lo, hi = points.min(0), points.max(0)
        origin = lo - spacing
        shape = tuple(int(v) for v in np.ceil((hi - lo) / spacing).astype(int) + 4)
        return BSplineLattice(origin, float(spacing), shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def basis(self, points: np.ndarray) -> sp.csr_matrix:
        """Sparse (n, size) matrix of the 64 tensor-product weights of each point."""
        g = (np.asarray(points, float) - self.origin) / self.spacing
        i0 = np.floor(g).astype(np.int64)
        i0 = np.clip(i0, 1, np.array(self.shape) - 3)
        t = np.clip(g - i0, 0.0, 1.0)
        w = [bspline_weights(t[:, d]) for d in range(3)]  # each (n, 4)
        offs = np.arange(4) - 1
        ix = (i0[:, 0, None] + offs)[:, :, None, None]
        iy = (i0[:, 1, None] + offs)[:, None, :, None]
        iz = (i0[:, 2, None] + offs)[:, None, None, :]
        cols = (ix * self.shape[1] + iy) * self.shape[2] + iz
        vals = w[0][:, :, None, None] * w[1][:, None, :, None] * w[2][:, None, None, :]
        n = len(g)
        rows = np.repeat(np.arange(n), 64)
        return sp.csr_matrix((vals.reshape(-1), (rows, cols.reshape(-1))), shape=(n, self.size))

    def second_differences(self) -> sp.csr_matrix:
        """Stacked second-difference operators along x, y, z over the whole lattice."""
        idx = np.arange(self.size).reshape(self.shape)
        blocks = []
        for axis in range(3):
            a = np.moveaxis(idx, axis, 0)
            if a.shape[0] < 3:
                continue
            c0, c1, c2 = a[:-2].ravel(), a[1:-1].ravel(), a[2:].ravel()
            m = len(c0)
            rows = np.repeat(np.arange(m), 3)
            cols = np.stack([c0, c1, c2], axis=1).ravel()
            vals = np.tile([1.0, -2.0, 1.0], m)
            blocks.append(sp.csr_matrix((vals, (rows, cols)), shape=(m, self.size)))
        return sp.vstack(blocks).tocsr()


_PARDISO: list = []


def _pardiso():
    """One PARDISO solver per process (creating one searches the disk for oneMKL)."""
    if not _PARDISO:
        try:
            import pypardiso

            _PARDISO.append(pypardiso.PyPardisoSolver(mtype=2))  # real symmetric pos. definite
        except (ImportError, OSError):  # platforms without oneMKL wheels
            _PARDISO.append(None)
    return _PARDISO[0]


def solve_spd(system: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray:
    """Direct solve of the sparse SPD control-point system: PARDISO (oneMKL, through
    pypardiso) when available, else SuperLU with a symmetric minimum-degree ordering."""
    solver = _pardiso() if system.shape[0] > 500 else None
    if solver is not None:
        solver.set_phase(13)
        upper = sp.triu(system, format="csr")
        upper.sort_indices()
        out = solver.solve(upper, np.ascontiguousarray(rhs))
        solver.free_memory(everything=True)
        return np.asarray(out).reshape(rhs.shape)
    return splu(system.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                options={"SymmetricMode": True}).solve(rhs)


class FFDFit:
    """Regularised least-squares fits of control displacements on one lattice.

    The active control points are fixed at construction (the support of the points the map will
    move); each fit solves its sparse SPD system directly (`solve_spd`)."""

    def __init__(self, lattice: BSplineLattice, support_points: np.ndarray, smoothness: float,
                 ridge: float = 1e-6):
        self.lattice = lattice
        mask = np.asarray(lattice.basis(support_points).getnnz(axis=0) > 0).ravel()
        self.active = np.flatnonzero(mask)
        # stencils reaching inactive control points see them at zero displacement: the map
        # fades out beyond the mesh instead of being left undetermined at the fringe
        d2 = lattice.second_differences()
        touches = np.asarray(d2[:, self.active].getnnz(axis=1) > 0).ravel()
        d2 = d2[touches][:, self.active]
        self.bending = (d2.T @ d2).tocsr()
        self.smoothness = smoothness
        self.ridge = ridge

    def fit(self, points: np.ndarray, residuals: np.ndarray, weights: np.ndarray) -> np.ndarray:
        a = self.lattice.basis(points)[:, self.active]
        aw = a.T.multiply(weights[None, :]).tocsr()
        ata = (aw @ a).tocsr()
        scale = float(ata.diagonal().mean()) or 1.0
        system = (ata + self.smoothness * scale * self.bending
                  + self.ridge * scale * sp.identity(len(self.active))).tocsr()
        rhs = np.asarray(aw @ residuals)
        c = solve_spd(system, rhs)
        limit = INJECTIVE_FRACTION * self.lattice.spacing
        return np.clip(c, -limit, limit)

    def evaluate(self, control: np.ndarray, points: np.ndarray) -> np.ndarray:
        return self.lattice.basis(points)[:, self.active] @ control
