"""The error model effects are judged against: scan noise plus a model-form discrepancy.

A real face is never the model's: even with no unmodelled effect the baseline misses the post-op
scan by a smooth, spatially correlated gap (mesh, anatomy, thickness and moduli the patient
does not share with the generic model). Judged against the scan noise alone, that gap is
significant everywhere and every effect either "explains" part of it or none does. Following
Kennedy & O'Hagan (*J. R. Stat. Soc. B* 63:425, 2001) the gap on the scan points is modelled as

    r = J theta + delta + eps,   delta ~ GP(0, s_d^2 k_l),   eps ~ N(0, s_n^2 I),

with J theta the effect's signal (`analysis`, linear about the refined fit), delta a zero-mean
Gaussian-process discrepancy with a Matern-3/2 correlation k_l(d) = (1 + sqrt3 d/l)
exp(-sqrt3 d/l) (Rasmussen & Williams, *Gaussian processes for machine learning*, 2006,
eq. 4.17: rough enough for the creases a model-form error leaves, unlike the squared
exponential) and eps the scan noise at the measured floor. The amplitude s_d and the
correlation length l are not assumed: they are estimated from the data by maximising the
marginal likelihood for each model separately (type-II maximum likelihood, the "modular"
calibration of Liu, Bayarri & Berger, *Bayesian Analysis* 4:119, 2009), so under the baseline
the discrepancy absorbs the whole gap, and an effect earns evidence only when its particular
pattern explains the gap better than a generic smooth field of the same amplitude does. This is
the remedy Brynjarsdottir & O'Hagan (*Inverse Problems* 30:114007, 2014) give for calibrating
under model-form error: without a discrepancy term the physical parameters absorb the
discrepancy and the evidence is overstated. The profile log-likelihood of a model with k fitted
parameters is penalised as BIC = -2 log L + k ln(n_eff) with n_eff the independent samples of
the face (area / (pi l^2)), so a k-parameter effect must do better than fit k directions of the
discrepancy by chance. The likelihood is evaluated on an area-uniform subsample of the scan
points (one per cube of side `spacing`, at most `MAX_POINTS`), small enough for a dense
eigendecomposition of the correlation matrix per correlation length, and the bounded
generalised least-squares fit of theta is exact in the whitened coordinates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ErrorModel", "Fit", "subsample", "matern32", "LENGTHS_MM", "MAX_POINTS", "REGION_P"]

MAX_POINTS = 900                      # subsample size of the likelihood
REGION_P = 1e-3                       # a region's gap beyond noise + discrepancy at this p-value
# correlation lengths tried (mm): from a few scan spacings to the size of a face region
LENGTHS_MM = (4.0, 6.0, 9.0, 13.0, 19.0, 28.0, 40.0)
# discrepancy amplitudes tried, relative to the gap's RMS (a log grid, refined by a parabola)
_AMPLITUDES = np.geomspace(0.02, 3.0, 40)


def matern32(d: np.ndarray, ell: float) -> np.ndarray:
    a = np.sqrt(3.0) * np.asarray(d, float) / ell
    return (1.0 + a) * np.exp(-a)


def subsample(points: np.ndarray, weights: np.ndarray, max_points: int = MAX_POINTS) -> np.ndarray:
    """Indices of an area-uniform subsample: per cube of side h the point nearest the cube's
    centroid, h the smallest cube that leaves at most `max_points` (deterministic)."""
    p = np.asarray(points, float)
    if len(p) <= max_points:
        return np.arange(len(p))
    area = float(np.sum(weights))
    h = np.sqrt(area / max_points)
    for _ in range(30):
        cells = np.floor((p - p.min(axis=0)) / h).astype(np.int64)
        _, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.ravel()
        if inv.max() + 1 <= max_points:
            break
        h *= 1.1
    cent = np.zeros((inv.max() + 1, 3))
    np.add.at(cent, inv, p)
    cent /= np.bincount(inv)[:, None]
    dist = np.linalg.norm(p - cent[inv], axis=1)
    order = np.lexsort((dist, inv))
    first = np.ones(len(order), bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


@dataclass
class Fit:
    """One model's profile maximum: parameters, discrepancy amplitude and length, log L."""

    theta: np.ndarray
    sigma_d: float
    ell: float
    loglik: float
    k: int

    def bic(self, n_eff: float) -> float:
        return float(-2.0 * self.loglik + self.k * np.log(max(n_eff, 2.0)))


class ErrorModel:
    """Noise + discrepancy on one case's scan points (see the module text)."""

    def __init__(self, points: np.ndarray, weights: np.ndarray, sigma_n: float,
                 lengths: tuple[float, ...] = LENGTHS_MM, max_points: int = MAX_POINTS):
        self.idx = subsample(points, weights, max_points)
        self.points = np.asarray(points, float)[self.idx]
        self.area = float(np.sum(weights))
        self.sigma_n = float(max(sigma_n, 1e-6))
        d = np.linalg.norm(self.points[:, None] - self.points[None], axis=2)
        self.lengths = tuple(float(x) for x in lengths)
        self._eig = []
        for ell in self.lengths:
            lam, U = np.linalg.eigh(matern32(d, ell))
            self._eig.append((np.clip(lam, 0.0, None), U))

    def n_eff(self, ell: float) -> float:
        """Independent samples of the face for correlation length ell: area / (pi l^2)."""
        return float(np.clip(self.area / (np.pi * ell ** 2), 2.0, len(self.idx)))

    def _loglik(self, z: np.ndarray, lam: np.ndarray, s_d: float) -> float:
        v = s_d * s_d * lam + self.sigma_n ** 2
        return float(-0.5 * (np.sum(z * z / v) + np.sum(np.log(v)) + len(z) * np.log(2 * np.pi)))

    def fit(self, r: np.ndarray, J: np.ndarray | None = None, theta_a: np.ndarray | None = None,
            lower=None, upper=None, free=None, extra_k: int = 0) -> Fit:
        """Profile maximum of log N(r + J (theta - theta_a); 0, s_d^2 K_l + s_n^2 I) over the
        free parameters within bounds, s_d and l; `r` and `J` on all scan points (the
        subsample is taken here). k = free parameters + `extra_k` (discrete choices)."""
        from scipy.optimize import lsq_linear

        r = np.asarray(r, float)[self.idx]
        nfree = 0
        if J is not None and free is not None and np.any(free):
            free = np.asarray(free, bool)
            Jf = np.asarray(J, float)[self.idx][:, free]
            nfree = int(free.sum())
            lo = np.asarray(lower, float)[free] - theta_a[free]
            hi = np.asarray(upper, float)[free] - theta_a[free]
        scale = float(np.sqrt(np.mean(r * r))) or self.sigma_n
        best = None
        for ell, (lam, U) in zip(self.lengths, self._eig):
            zr = U.T @ r
            zJ = U.T @ Jf if nfree else None
            here = -np.inf
            for s_d in scale * _AMPLITUDES:
                x = np.zeros(nfree)
                if nfree:
                    sv = 1.0 / np.sqrt(s_d * s_d * lam + self.sigma_n ** 2)
                    res = lsq_linear(zJ * sv[:, None], -zr * sv, bounds=(lo, hi), method="bvls")
                    x = res.x
                z = zr + (zJ @ x if nfree else 0.0)
                ll = self._loglik(z, lam, s_d)
                if best is None or ll > best[0]:
                    best = (ll, s_d, ell, x)
                if ll < here - 1e-9:
                    break               # past this length's maximum in s_d (unimodal)
                here = ll
        ll, s_d, ell, x = best
        theta = None
        if theta_a is not None:
            theta = np.array(theta_a, float)
            if nfree:
                theta[free] = theta_a[free] + x
        return Fit(theta, float(s_d), float(ell), float(ll), nfree + int(extra_k))

    def standard_errors(self, J: np.ndarray, fit: Fit) -> np.ndarray:
        """Standard errors of the parameters (columns of J) under the error model `fit`:
        sqrt(diag((J^T Sigma^-1 J)^-1)), inf along directions the data do not see."""
        lam, U = self._eig[self.lengths.index(fit.ell)]
        sv = 1.0 / np.sqrt(fit.sigma_d ** 2 * lam + self.sigma_n ** 2)
        A = (U.T @ np.asarray(J, float)[self.idx]) * sv[:, None]
        F = A.T @ A
        try:
            cov = np.linalg.inv(F)
        except np.linalg.LinAlgError:
            return np.full(F.shape[0], np.inf)
        return np.sqrt(np.clip(np.diag(cov), 0.0, None))

    def region_pvalue(self, r: np.ndarray, mask: np.ndarray, fit: Fit) -> float:
        """P-value of a region's gap under the error model `fit`: the quadratic form
        r_m^T Sigma_m^-1 r_m of the region's subsampled points is chi-square with as many
        degrees of freedom as points when the gap is noise + discrepancy."""
        from scipy.stats import chi2

        sel = np.asarray(mask, bool)[self.idx]
        m = int(sel.sum())
        if m == 0:
            return 1.0
        p = self.points[sel]
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        S = fit.sigma_d ** 2 * matern32(d, fit.ell) + self.sigma_n ** 2 * np.eye(m)
        x = np.asarray(r, float)[self.idx][sel]
        q = float(x @ np.linalg.solve(S, x))
        return float(chi2.sf(q, m))

    def residual_level(self, fit: Fit) -> float:
        """RMS of the gap the error model expects without any effect: sqrt(s_d^2 + s_n^2)."""
        return float(np.hypot(fit.sigma_d, self.sigma_n))
