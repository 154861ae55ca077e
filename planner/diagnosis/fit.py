"""The statistics of the diagnosis: bounded least squares, Fisher information, model evidence.

The gap r(theta) (signed distances on the scan's fixed points, area weights w) is modelled
about an anchor theta_a as r(theta) = r_a + J (theta - theta_a), J = dr/dtheta (Gauss-Newton);
the fitted parameters minimise sum w r^2 within the effect's bounds, plus a Gaussian prior's
term for the parameters that have one (`linear_fit`, a bounded linear least-squares problem,
the prior as one more row per parameter, solved exactly by scipy's `lsq_linear`; Tikhonov
regularisation, the maximum a posteriori estimate); the anchor moves to each
full nonlinear solve and J is updated by Broyden's rank-one secant rule (Broyden 1965; Dennis &
Schnabel, *Numerical methods for unconstrained optimization*, 1983, sect. 8.1), which for one
parameter is the secant slope through the two solves.

Identifiability: under Gaussian noise of standard deviation sigma (the noise floor) on n_eff
independent samples, the Fisher information of theta is F = (n_eff / W) J^T diag(w) J / sigma^2
(W = sum w: each independent sample stands for W / n_eff of area); the Cramer-Rao standard
error of parameter k is sqrt((F^-1)_kk). A parameter the data pin to less than a tenth of its
plausible range is identifiable; the others are fixed at their "none" value and reported
`identifiable: false` (a uniform stiffness factor under displacement-only loading has J = 0).

Model choice: the Bayesian information criterion (Schwarz 1978) with the noise variance
unknown, BIC = n_eff ln(RSS / W) + k ln(n_eff), and model probabilities exp(-BIC / 2)
normalised over the models compared (Burnham & Anderson, *Model selection and multimodel
inference*, 2002, sect. 6.4). A difference of 6 or more is "strong" evidence (Kass & Raftery,
*J. Am. Stat. Assoc.* 90, 1995). The probability a verdict reports is a held-out one: pseudo-BMA+
weights of the models' held-out log predictive densities (`predictive_weights`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["linear_fit", "broyden", "standard_errors", "information_errors", "bic", "model_probabilities",
           "predictive_weights", "gain_probability", "finite_difference_points", "finite_difference_jacobian", "STRONG_EVIDENCE",
           "IDENTIFIABLE_FRACTION"]

STRONG_EVIDENCE = 6.0          # BIC difference for strong evidence (Kass & Raftery 1995)
IDENTIFIABLE_FRACTION = 0.1    # standard error below this fraction of the parameter's range


def linear_fit(r_a: np.ndarray, J: np.ndarray, w: np.ndarray, theta_a: np.ndarray,
               lower: np.ndarray, upper: np.ndarray, free: np.ndarray | None = None,
               fixed_value: np.ndarray | None = None, prior_sd: np.ndarray | None = None,
               prior_weight: float = 1.0) -> np.ndarray:
    """theta in [lower, upper] minimising sum w (r_a + J (theta - theta_a))^2 + prior_weight
    sum ((theta - fixed_value) / prior_sd)^2 (the free parameters with a finite `prior_sd`: a
    Gaussian prior about `fixed_value`, the maximum a posteriori estimate when prior_weight is
    the weighted squared residual one unit of information is worth); parameters not `free`
    stay at `fixed_value` (default theta_a)."""
    from scipy.optimize import lsq_linear

    theta_a = np.asarray(theta_a, float)
    k = len(theta_a)
    free = np.ones(k, bool) if free is None else np.asarray(free, bool)
    theta = (theta_a if fixed_value is None else np.asarray(fixed_value, float)).copy()
    if not free.any() or len(r_a) == 0:
        return theta
    sw = np.sqrt(np.asarray(w, float))
    # the fixed parameters' offset from the anchor moves the free ones' target
    b = -(r_a + J[:, ~free] @ (theta[~free] - theta_a[~free])) * sw
    A = J[:, free] * sw[:, None]
    if prior_sd is not None:
        # one row per free parameter, sqrt(weight) (x + theta_a - centre) / sd: zero where flat
        s = np.sqrt(prior_weight) / np.asarray(prior_sd, float)[free]
        A = np.concatenate([A, np.diag(s)])
        b = np.concatenate([b, -s * (theta_a[free] - theta[free])])
    lo, hi = np.asarray(lower, float)[free], np.asarray(upper, float)[free]
    # the problem is solved about the anchor: x = theta - theta_a
    res = lsq_linear(A, b, bounds=(lo - theta_a[free], hi - theta_a[free]), method="bvls")
    theta[free] = theta_a[free] + res.x
    return np.clip(theta, lower, upper)


def broyden(J: np.ndarray, dtheta: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """Broyden's rank-one update of J after a step dtheta that changed r by dr."""
    dtheta = np.asarray(dtheta, float)
    n2 = float(dtheta @ dtheta)
    if n2 <= 0:
        return J
    return J + np.outer(dr - J @ dtheta, dtheta) / n2


def standard_errors(J: np.ndarray, w: np.ndarray, sigma: float, n_eff: float) -> np.ndarray:
    """Cramer-Rao standard errors of the parameters under white noise `sigma` over `n_eff`
    independent samples (inf where not determined)."""
    W = float(np.sum(w))
    return information_errors((n_eff / W) * (J.T * w) @ J / max(sigma, 1e-9) ** 2)


def information_errors(F: np.ndarray) -> np.ndarray:
    """sqrt(diag(F^-1)) of a Fisher information F, inf for the parameters along a direction
    the data do not see (F's null space)."""
    F = np.asarray(F, float)
    k = F.shape[0]
    se = np.full(k, np.inf)
    evals, evecs = np.linalg.eigh(F)
    if evals.max(initial=0.0) <= 0:
        return se
    ok = evals > 1e-12 * evals.max()
    if ok.all():
        cov = (evecs / evals) @ evecs.T
        return np.sqrt(np.clip(np.diag(cov), 0.0, None))
    # a direction the data cannot see: the parameters along it are undetermined
    cov = (evecs[:, ok] / evals[ok]) @ evecs[:, ok].T
    null = np.abs(evecs[:, ~ok]).max(axis=1) > 1e-6
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se[null] = np.inf
    return se


def bic(rss: float, weight: float, n_eff: float, k: int) -> float:
    """BIC with unknown noise variance: n_eff ln(RSS / W) + k ln(n_eff)."""
    return float(n_eff * np.log(max(rss, 1e-300) / weight) + k * np.log(max(n_eff, 1.0)))


def model_probabilities(bics: dict[str, float]) -> dict[str, float]:
    """exp(-BIC / 2) normalised over the models."""
    names = list(bics)
    b = np.array([bics[n] for n in names], float)
    p = np.exp(-(b - b.min()) / 2.0)
    p /= p.sum()
    return dict(zip(names, p.tolist()))


def predictive_weights(lpd: dict[str, np.ndarray], draws: int = 1000, seed: int = 0) -> dict[str, float]:
    """Pseudo-BMA+ weights of the models from their pointwise held-out log predictive densities
    (one value per cross-validation fold, the same folds for every model; Yao, Vehtari, Simpson
    & Gelman 2018, Bayesian Analysis 13:917, eq. 8-9): w_k is the mean over Bayesian-bootstrap
    draws alpha ~ Dirichlet(1, ..., 1) of softmax_k(n sum_i alpha_i lpd_ik). The bootstrap
    keeps a gain carried by a few folds from taking all the weight: the weights say how surely
    a model predicts unseen data better, not only which does. A fixed seed makes them a
    function of the data alone."""
    names = list(lpd)
    L = np.stack([np.asarray(lpd[n], float) for n in names], axis=1)       # (folds, models)
    n = L.shape[0]
    if n == 0:
        return {m: 1.0 / len(names) for m in names}
    z = _bootstrap_sums(L, draws, seed)                                       # (draws, models)
    z -= z.max(axis=1, keepdims=True)
    w = np.exp(z)
    w /= w.sum(axis=1, keepdims=True)
    return dict(zip(names, w.mean(axis=0).tolist()))


def _bootstrap_sums(values: np.ndarray, draws: int, seed: int) -> np.ndarray:
    """Bayesian-bootstrap draws (Rubin 1981) of the sum over folds of `values` (folds first):
    n sum_i alpha_i v_i with alpha ~ Dirichlet(1, ..., 1), one row per draw."""
    v = np.asarray(values, float)
    alpha = np.random.default_rng(seed).dirichlet(np.ones(len(v)), size=draws)   # (draws, folds)
    return len(v) * alpha @ v


def gain_probability(diff: np.ndarray, draws: int = 4000, seed: int = 0) -> float:
    """The probability that a summed held-out gain is positive, from its per-fold values: the
    share of Bayesian-bootstrap draws of the sum (`_bootstrap_sums`) above zero. Unlike the
    normal approximation sum +- 2 sqrt(n) sd, which holds for many exchangeable folds, it keeps
    the skew of a few folds: a gain carried by the one region an effect acts on, with no fold
    that loses, is not discounted for its concentration, and one large loss among many small
    gains counts as the loss it is (Sivula, Magnusson, Matamoros & Vehtari, arXiv:2008.10296, on
    the normal approximation's miscalibration with few folds). A fixed seed makes it a function
    of the data alone; 4000 draws give it to about +-0.0025 near 0.975."""
    d = np.asarray(diff, float)
    if d.size == 0:
        return 0.0
    return float(np.mean(_bootstrap_sums(d, draws, seed) > 0.0))


def finite_difference_points(theta0: np.ndarray, step: np.ndarray, lower: np.ndarray,
                             upper: np.ndarray) -> list[tuple[int, float, float]]:
    """Per parameter the two evaluation offsets: central (-h, +h) inside the bounds, else
    one-sided second order (+h, +2h) or (-h, -2h) at a bound."""
    out = []
    for k, (t, h, lo, hi) in enumerate(zip(theta0, step, lower, upper)):
        if t - h >= lo - 1e-12 and t + h <= hi + 1e-12:
            out.append((k, -h, h))
        elif t + 2 * h <= hi + 1e-12:
            out.append((k, h, 2 * h))
        else:
            out.append((k, -h, -2 * h))
    return out


def finite_difference_jacobian(r0: np.ndarray, evaluations: list[tuple[float, float, np.ndarray, np.ndarray]]
                               ) -> np.ndarray:
    """Columns dr/dtheta_k from (offset a, offset b, r(theta0 + a e_k), r(theta0 + b e_k)):
    central (a = -b) or one-sided second order (b = 2a: (-3 r0 + 4 r(a) - r(2a)) / 2a)."""
    cols = []
    for a, b, ra, rb in evaluations:
        if np.isclose(a, -b):
            cols.append((rb - ra) / (b - a))
        else:
            cols.append((-3.0 * r0 + 4.0 * ra - rb) / (2.0 * a))
    return np.stack(cols, axis=1) if cols else np.zeros((len(r0), 0))
