"""Gaussian-process emulator of a site's forward curve over the Yeoh parameters, and the
parallel forward runs it is trained on.

The parameters are theta = (ln C10, C20/C10, ln dermis_ratio) in a box; a design is a Latin
hypercube in that box (`scipy.stats.qmc.LatinHypercube`, McKay, Beckman & Conover 1979), its
forward runs (`planner.calibration.slab.forward_curve`) execute as dask.distributed tasks on a
LocalCluster or an existing scheduler. The emulator follows Higdon et al. (JASA 103:570-583,
2008): the curves, as logarithms (the apex height and the force scale roughly as a power of the
modulus, so their logarithm is close to linear in ln C10), are reduced by principal components
(kept until 99.999 % of the variance), and each component score is a Gaussian process of theta
(scikit-learn `GaussianProcessRegressor`, constant x anisotropic Matern 5/2 + white noise,
hyper-parameters by maximum likelihood). The prediction of the curve is the back-transformed
mean, its variance the sum of the components' variances (plus the discarded variance) mapped
to the curve's scale, so that the calibration can add the emulator's uncertainty to the
measurement noise (Kennedy & O'Hagan 2001).
"""
from __future__ import annotations

import contextlib
import sys
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.stats import qmc

from planner.calibration.slab import ForwardError, MeshOptions, Site, forward_curve

__all__ = ["PARAMETERS", "PRIOR_BOX", "Emulator", "latin_hypercube", "run_forward",
           "dask_client", "fit_emulator"]

PARAMETERS = ("ln_C10", "C20_over_C10", "ln_dermis_ratio")
# C10 0.5-30 kPa (E0 = 6 C10: 3-180 kPa, the span of face-tissue values in the literature),
# C20/C10 0-1.5 (the face model's 0.47 inside), dermis 1-12 times the hypodermis
PRIOR_BOX = np.array([[np.log(0.5), np.log(30.0)], [0.0, 1.5], [0.0, np.log(12.0)]])


def to_params(theta) -> tuple[float, float, float]:
    """(C10, C20, ratio) of theta = (ln C10, C20/C10, ln ratio)."""
    c10 = float(np.exp(theta[0]))
    return c10, float(theta[1]) * c10, float(np.exp(theta[2]))


def latin_hypercube(box, n: int, seed: int) -> np.ndarray:
    """n points of an optimised Latin hypercube in the box (d, 2)."""
    box = np.asarray(box, dtype=float)
    u = qmc.LatinHypercube(d=len(box), optimization="random-cd", seed=seed).random(n)
    return box[:, 0] + u * (box[:, 1] - box[:, 0])


def _forward_task(site: Site, x, theta, opt: MeshOptions):
    """One forward run (in a worker): the curve, or None if the solve fails."""
    import logging

    import numba

    # one thread per task: the cluster's processes are the parallelism
    numba.set_num_threads(1)
    logging.getLogger("solver").setLevel(logging.ERROR)
    try:
        return forward_curve(site, *to_params(theta), x, opt)
    except ForwardError:
        return None


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, n_workers: int = 2):
    """A dask.distributed client: on `scheduler` (address) if given, else on a LocalCluster of
    `n_workers` single-threaded processes, closed on exit."""
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            from planner.errors import InputError
            raise InputError(f"cannot connect to the dask scheduler: {exc}",
                             field="--scheduler") from None
        try:
            yield client
        finally:
            client.close()
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=50)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def run_forward(client, jobs, opt: MeshOptions, label: str = "forward runs", echo: bool = True):
    """Run the jobs [(site, x, theta), ...] on the cluster; curves (or None) in job order."""
    from dask.distributed import as_completed

    futures = [client.submit(_forward_task, s, x, th, opt, pure=False) for s, x, th in jobs]
    index = {f.key: i for i, f in enumerate(futures)}
    out = [None] * len(futures)
    for done, fut in enumerate(as_completed(futures), start=1):
        out[index[fut.key]] = fut.result()
        if echo and (done == len(futures) or done % max(1, len(futures) // 10) == 0):
            print(f"  {label}: {done}/{len(futures)}", file=sys.stderr, flush=True)
    return out


@dataclass
class Emulator:
    """Emulator of one site's curve (log scale) on the parameter box."""

    box: np.ndarray
    mean: np.ndarray                # (k,) mean log-curve
    components: np.ndarray          # (c, k) principal directions
    gps: list                       # one fitted GaussianProcessRegressor per component
    residual_var: np.ndarray        # (k,) log-variance not carried by the kept components
    n_runs: int

    def _u(self, theta):
        theta = np.atleast_2d(theta)
        return (theta - self.box[:, 0]) / (self.box[:, 1] - self.box[:, 0])

    def predict_log(self, theta, return_var: bool = True):
        """Mean (m, k) and variance (m, k) of the log-curve at theta (m, 3)."""
        u = self._u(theta)
        means, sds = zip(*(gp.predict(u, return_std=True) for gp in self.gps))
        S = np.stack(means, 1)                      # (m, c)
        mu = self.mean + S @ self.components
        if not return_var:
            return mu
        V = np.stack(sds, 1) ** 2
        var = V @ self.components ** 2 + self.residual_var
        return mu, var

    def predict(self, theta):
        """Curve mean (m, k) and standard deviation (m, k) in measured units."""
        mu, var = self.predict_log(theta)
        y = np.exp(mu)
        return y, y * np.sqrt(var)


def fit_emulator(box, thetas, curves, seed: int = 0) -> Emulator:
    """Fit the emulator to forward runs thetas (n, 3) -> curves (n, k); failed runs (None or
    non-positive values) are left out."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    box = np.asarray(box, dtype=float)
    ok = [i for i, c in enumerate(curves) if c is not None and np.all(np.asarray(c) > 0)]
    if len(ok) < 5:
        raise ForwardError(f"only {len(ok)} of {len(curves)} forward runs succeeded")
    T = np.asarray(thetas, dtype=float)[ok]
    Y = np.log(np.asarray([curves[i] for i in ok], dtype=float))
    mean = Y.mean(0)
    Yc = Y - mean
    _, sv, Vt = np.linalg.svd(Yc, full_matrices=False)
    frac = np.cumsum(sv ** 2) / max(np.sum(sv ** 2), 1e-300)
    c = int(np.searchsorted(frac, 1.0 - 1e-5) + 1)
    c = min(c, len(sv))
    comps = Vt[:c]
    scores = Yc @ comps.T
    resid = Yc - scores @ comps
    residual_var = resid.var(0)
    u = (T - box[:, 0]) / (box[:, 1] - box[:, 0])
    gps = []
    for j in range(c):
        kernel = (ConstantKernel(1.0, (1e-4, 1e4))
                  * Matern(length_scale=np.ones(T.shape[1]), length_scale_bounds=(1e-2, 1e2), nu=2.5)
                  + WhiteKernel(1e-6, (1e-12, 1e-2)))
        gp = GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=2,
                                      random_state=seed + j)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gp.fit(u, scores[:, j])
        gps.append(gp)
    return Emulator(box, mean, comps, gps, residual_var, len(ok))
