"""The error model effects are judged against: scan noise plus a two-scale model-form discrepancy.

A real face is never the model's: even with no unmodelled effect the baseline misses the post-op
scan by a spatially correlated gap (mesh, anatomy, thickness and moduli the patient does not
share with the generic model). That gap has two scales: a short one (the faceting of the finite
elements, creases, a few mm) and a long one (a face fuller or flatter than the model's over
whole regions, a fraction of a mm that varies smoothly across the face). Judged against the scan
noise alone, or against a discrepancy of one correlation length that can only describe the short
scale, the long part is significant and every smooth effect "explains" some of it. Following
Kennedy & O'Hagan (*J. R. Stat. Soc. B* 63:425, 2001) the gap on the scan points is modelled as

    r(theta) = r_a + J (theta - theta_a) = delta_s + B beta + eps,
    delta_s ~ GP(0, s_d^2 k_l),  beta ~ N(0, s_L^2 I_m),  eps ~ N(0, s_n^2 I),

so that r(theta) ~ N(0, Sigma), Sigma = s_d^2 K_l + s_L^2 B B^T + s_n^2 I. r(theta) is the gap
left with the effect at theta (`analysis`: linear about the refined fit, J = dr/dtheta);
delta_s the short-scale discrepancy, a Gaussian process with the Matern-3/2 correlation
k_l(d) = (1 + sqrt3 d/l) exp(-sqrt3 d/l) (Rasmussen & Williams, *Gaussian processes for machine
learning*, 2006, eq. 4.17: rough enough for the creases a model-form error leaves); B beta the
long-scale discrepancy, a linear polynomial in the (centred, scaled) coordinates with Gaussian
coefficients (a degenerate Gaussian process, Rasmussen & Williams sect. 2.7; O'Hagan,
*J. R. Stat. Soc. B* 40:1, 1978): an offset and tilts of the whole face (`smooth_basis`);
eps the scan noise at the measured floor. The amplitudes s_d and s_L and the length l are not
assumed: they are estimated from the data by maximising the marginal likelihood for each model
separately (type-II maximum likelihood, the "modular" calibration of Liu, Bayarri & Berger,
*Bayesian Analysis* 4:119, 2009). s_L = 0 is one of the values tried, so the evidence itself
decides whether the long scale is present. With theta profiled (bounded generalised least
squares) the log-likelihood is

    log L = -1/2 [ min_theta,beta ( |W (r(theta) - B beta)|^2 + |beta|^2 / s_L^2 )
                   + sum_i log v_i + log det(I_m + s_L^2 C^T C) + n log 2 pi ],

with K_l = U diag(lambda) U^T, v = s_d^2 lambda + s_n^2, W = diag(v)^-1/2 U^T and C = W B:
minimising over beta with its Gaussian penalty gives exactly the quadratic form of Sigma^-1
(Woodbury), and the determinant lemma gives log det Sigma, so one eigendecomposition per length
serves every amplitude. Under the baseline the discrepancy absorbs the whole gap, and an effect
earns evidence only when its particular pattern explains the gap better than generic fields of
both scales do: the remedy Brynjarsdottir & O'Hagan (*Inverse Problems* 30:114007, 2014) give
for calibrating under model-form error. The profile log-likelihood of a model with k fitted
parameters is penalised as BIC = -2 log L + k ln(n_eff), n_eff the independent samples of the
face (area / (pi l^2)).

In-sample evidence can still favour an effect whose pattern resembles the discrepancy's on this
face by chance. Each model is therefore also judged on held-out data (`heldout_lpd`): the scan
is cut into its regions; each region's gap is predicted from the other regions' by the
conditional Gaussian distribution of the model (the effect's parameters integrated out under a
Gaussian prior of half their range about "none", so that they are in effect fitted on the
other regions; the discrepancy kriged from the other regions' residuals). The log predictive density of the left-out
regions summed (Geisser & Eddy, *J. Am. Stat. Assoc.* 74:153, 1979; Vehtari, Gelman & Gabry,
*Statistics and Computing* 27:1413, 2017, whose standard error of the difference is used) is
compared with the baseline's: an effect that does not predict unseen regions better than the
discrepancy alone does is not named.

The mesh's own error. Part of the model-form error is computable: the finite-element mesh's
discretisation error, a smooth pattern over the operated face (a coarse mesh is too stiff where
the tissue bends most). When the baseline is also solved on a second mesh (`mesh_error`: the
change d of the gap from this mesh's prediction to the other's, on the same scan points and
pose), the discretisation error is a multiple of d: under asymptotic convergence of order p,
e_h = (u - u_h) ~ d / (2^p - 1) from the next coarser mesh and d 2^p / (2^p - 1) from the next
finer one (Richardson extrapolation; Roache, *Verification and validation in computational
science and engineering*, 1998, ch. 5). Its coefficient a enters the error model as one more
Gaussian column, a ~ N(0, MESH_ERROR_SD^2), integrated out like the long-scale coefficients:
Sigma gains MESH_ERROR_SD^2 d d^T. Every model (the baseline and each effect) carries it, so
the mesh error is neither charged to an effect nor absorbed by a discrepancy amplitude large
enough to hide the effects as well.

Boundary conditions. The model's boundary conditions are choices, and an independent model of
the same face makes other ones: the neck cut, free in faceplan's model, is held by models
whose mesh goes on down the neck, and the floor of the mouth, free under the submental tissue
in faceplan's model, is held by models that mesh the suprahyoid muscles down to a hyoid
(`facemodel.simulation`). Where the gap is measured on the chin and the lower face, such a
difference moves the skin as a sliding chin or a bone correction would, and an effect would
be named for it. The baseline is therefore also solved with each boundary's other condition
(`boundary`: one column b per boundary, the change of the gap on the same scan points and
pose), and each b enters the error model like the mesh error, one more Gaussian column with a
coefficient c ~ N(0, BOUNDARY_SD^2): Sigma gains BOUNDARY_SD^2 b b^T. It is not taken out of
the gap (nothing says which condition the patient's tissue is nearer, and an estimate on the
baseline gap would take the part of a true effect that resembles it); every model carries it,
so an effect is named only where it explains the gap beyond what the other boundary condition
could (the structural discrepancy of Brynjarsdottir & O'Hagan, *Inverse Problems* 30:114007,
2014, given as a known direction instead of left to the generic field).

Layer proportions. A CT segments the skin and the bones; the layers between (dermis,
subcutaneous fat, muscle and mucosa) keep the generic mesh's proportions along each column
from bone to skin, which the patient does not share. A deep layer thicker than the model's
fills the lips and cheeks out a little over whole regions, a coherent pattern a bone
correction's rigid parameters can copy. The baseline is therefore also solved with each
layer group `LAYER_STEP` thicker (`facemodel.synthetic.perturb_layers`: the dermis, and the
deep half of the column, the hypodermis between taking the difference, skin and bone
surfaces unchanged), and the changes of the gap enter the error model like the boundary
direction, Gaussian columns with coefficients N(0, 1) (`layers`): a coefficient of 1 is a
layer `LAYER_STEP` thicker, the linearised response of a nuisance parameter of the model
integrated out under its prior (the calibration inputs of Kennedy & O'Hagan 2001, sec. 4.3).

Under the mandible. The regions below the mandible's lower border (submental, submandibular)
hold the tissue whose boundaries the model chooses (the neck cut, the floor of the mouth) and
which the head's posture in the scan (the neck's flexion) moves: a model-form gap is largest
there, and a single amplitude for the whole face would take its size from them and hide the
effects elsewhere. Where the scan sees them (a share of the points of at least
`MIN_BORDER_SHARE`), the short scale is a sum of two independent fields: s_d (g + sqrt(rho) m
h), with g and h of the same Matern kernel and m the mask of those points, so Sigma gains
s_d^2 (K + rho M K M); rho is profiled over `BORDER_RATIOS` (0: the stationary field) with the
amplitude and length of each model.

The scan's pose. The gap is measured with the scan superimposed on the trimmed unoperated
points (`gap.ScanGap.fix_pose`), a least-squares pose rho = M r_u of those points' gap; its error
is M delta_u, the error of the gap there, which a correlated field does not average down with
more points, and it moves the gap of the whole face by the rigid basis R (a small rotation and
translation of the scan). A pose error is thus a field like any the model could leave, and an
effect whose pattern resembles it (a bone rotation trades with the scan's tilt, a bone's
vertical move with the scan's slide along the face) would be fitted to it. The pose is
therefore integrated out: its error is taken as independent of the gap's other errors, with
the covariance the model's own noise + discrepancy gives it,

    C = M_s (s_d^2 K_uu + s_L^2 B_u B_u^T) M_s^T + s_n^2 M M^T,

M_s the pose's estimator on the subsample's trimmed unoperated points u (area-uniform, so
unweighted), M the whole scan's (for the white noise), and Sigma gains R C R^T
(`pose_covariance`). With T = R_s M_s this is a second copy of each field through the pose:
the short scale's kernel becomes K + T K_uu T^T (one eigendecomposition per length, as before),
the long-scale basis gains the columns T B_u under the same amplitude, and the noise's part is
six fixed columns (the mesh-error, boundary and layer directions are changes of gaps measured
with the pose re-fitted already, and have no copy). So every model carries the pose
uncertainty its own discrepancy implies: a model that explains the gap leaves a smaller
discrepancy and a better-held pose. (The gap's
exact covariance after a fitted pose, P Sigma P^T with P = I - T, takes the pose's error to be
the discrepancy's own on the unoperated points and removes it there; a stationary field then
makes it small. It is not used: what differs between models of one face on those points is
each model's response to the operation, which is not stationary.)

The likelihood is evaluated on an area-uniform subsample of the scan points (one per cube of
side `spacing`, at most `MAX_POINTS`), small enough for a dense eigendecomposition of the
correlation matrix per correlation length.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.diagnosis.fit import information_errors

__all__ = ["ErrorModel", "Fit", "subsample", "matern32", "smooth_basis", "LENGTHS_MM", "MAX_POINTS",
           "REGION_P", "MESH_ERROR_SD", "BOUNDARY_SD", "LAYER_STEP", "LAYER_SD", "BORDER_REGIONS",
           "BORDER_RATIOS", "MIN_BORDER_SHARE"]

MAX_POINTS = 900                      # subsample size of the likelihood
REGION_P = 1e-3                       # a region's gap beyond noise + discrepancy at this p-value
# prior standard deviation of the mesh-error coefficient (module text): a mesh's error is
# 1/(2^p - 1) of its change to the next coarser mesh and 2^p/(2^p - 1) of its change to the next
# finer one, p the order of convergence; 2 covers both for every p >= 0.6
MESH_ERROR_SD = 2.0
# prior standard deviation of a boundary-condition direction's coefficient: the direction is
# the change from the model's condition to the other bracket (module text), so the truth lies
# about 0..1 along it
BOUNDARY_SD = 1.0
# layer proportions (module text): each direction is the change of the gap with a layer group
# this fraction thicker, the prior standard deviation of its coefficient LAYER_SD: a fifth of
# a layer's thickness, the scale on which facial soft-tissue layers differ between adults of
# one total thickness, which the CT fixes
LAYER_STEP = 0.2
LAYER_SD = 1.0
# the regions under the mandible (module text, "Under the mandible"), the variance ratios rho of
# their own field tried (a log grid up to a hundredfold variance: a gap ten times the face's
# there), and the share of the subsample they must hold for the term to be fitted at all (below
# it, too few points to tell its amplitude from the face's)
BORDER_REGIONS = ("submental", "submandibular_left", "submandibular_right")
BORDER_RATIOS = (0.0, 1.0, 4.0, 16.0, 64.0)
MIN_BORDER_SHARE = 0.05
# correlation lengths of the short scale (mm): from a few scan spacings to the size of a region
LENGTHS_MM = (4.0, 6.0, 9.0, 13.0, 19.0, 28.0, 40.0)
# short-scale amplitudes tried, relative to the gap's RMS (log grid; the maximum is unimodal in it)
_AMPLITUDES = np.geomspace(0.02, 3.0, 32)
# long-scale amplitudes (per unit-RMS basis function) relative to the gap's RMS; 0: no long scale
_LONG_AMPLITUDES = np.concatenate([[0.0], np.geomspace(0.01, 1.0, 9)])


def matern32(d: np.ndarray, ell: float) -> np.ndarray:
    a = np.sqrt(3.0) * np.asarray(d, float) / ell
    return (1.0 + a) * np.exp(-a)


def smooth_basis(points: np.ndarray) -> np.ndarray:
    """The long-scale basis: 1, x, y, z in coordinates centred on the points' mean and scaled
    by their RMS radius, each column scaled to unit RMS. Degree one: an offset and tilts of the
    whole face. Curvatures are left out on purpose: a quadratic over a face already bends
    within a region's width and would take the pattern of a regional effect (posture, swelling)
    as discrepancy; what bends on that scale is for the effects and the short scale."""
    p = np.asarray(points, float)
    q = p - p.mean(axis=0)
    q /= max(float(np.sqrt(np.mean(np.sum(q * q, axis=1)))), 1e-9)
    x, y, z = q.T
    B = np.stack([np.ones(len(q)), x, y, z], axis=1)
    rms = np.sqrt(np.mean(B * B, axis=0))
    keep = rms > 1e-9
    return B[:, keep] / rms[keep]


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
    """One model's profile maximum: parameters, discrepancy amplitudes and length, log L."""

    theta: np.ndarray
    sigma_d: float
    ell: float
    loglik: float
    k: int
    sigma_long: float = 0.0       # long-scale amplitude per unit-RMS basis function
    long_mm: float = 0.0          # RMS of the long-scale field over the points (s_L sqrt(m))
    mesh_mm: float = 0.0          # RMS of the estimated mesh error over the points
    mesh_coef: np.ndarray | None = None   # its coefficient(s) on the mesh-error direction(s)
    boundary_mm: float = 0.0      # RMS of the estimated boundary-condition field over the points
    boundary_coef: np.ndarray | None = None   # its coefficient(s) on the boundary direction(s)
    layer_mm: float = 0.0         # RMS of the estimated layer-proportion field over the points
    layer_coef: np.ndarray | None = None      # its coefficients on the layer directions
    border_ratio: float = 0.0     # rho: the variance ratio of the field under the mandible
    border_share: float = 0.0     # the share of the points under the mandible

    @property
    def discrepancy_mm(self) -> float:
        """RMS of the whole discrepancy: both scales, the mesh error, the boundary and the
        layer-proportion fields."""
        short = self.sigma_d * np.sqrt(1.0 + self.border_ratio * self.border_share)
        v = float(np.hypot(short, self.long_mm))
        return float(np.hypot(np.hypot(np.hypot(v, self.mesh_mm), self.boundary_mm), self.layer_mm))

    def bic(self, n_eff: float) -> float:
        return float(-2.0 * self.loglik + self.k * np.log(max(n_eff, 2.0)))


def _bounded_quadratic(H: np.ndarray, g: np.ndarray, lo, hi, k: int) -> np.ndarray:
    """argmin of y^T H y / 2 + g^T y (H positive definite) with the first k entries of y in
    (lo, hi) and the others free: the unconstrained minimum when it is inside the bounds, else
    bounded least squares on the Cholesky factor (|R y + R^-T g|^2 is the same quadratic)."""
    from scipy.optimize import lsq_linear

    R = np.linalg.cholesky(H).T
    y = -np.linalg.solve(H, g)
    if k == 0 or (np.all(y[:k] >= lo - 1e-12) and np.all(y[:k] <= hi + 1e-12)):
        return y
    b = -np.linalg.solve(R.T, g)
    nb = len(g) - k
    lo_all = np.concatenate([lo, np.full(nb, -np.inf)])
    hi_all = np.concatenate([hi, np.full(nb, np.inf)])
    return lsq_linear(R, b, bounds=(lo_all, hi_all), method="bvls").x


class ErrorModel:
    """Noise + two-scale discrepancy on one case's scan points (see the module text)."""

    def __init__(self, points: np.ndarray, weights: np.ndarray, sigma_n: float,
                 lengths: tuple[float, ...] = LENGTHS_MM, max_points: int = MAX_POINTS,
                 long_scale: bool = True, mesh_error: np.ndarray | None = None,
                 boundary: np.ndarray | None = None, layers: np.ndarray | None = None,
                 border: np.ndarray | None = None, pose: tuple | None = None):
        self.idx = subsample(points, weights, max_points)
        self.points = np.asarray(points, float)[self.idx]
        self.area = float(np.sum(weights))
        self.sigma_n = float(max(sigma_n, 1e-6))
        self._d = np.linalg.norm(self.points[:, None] - self.points[None], axis=2)
        self.lengths = tuple(float(x) for x in lengths)
        self.B = smooth_basis(self.points) if long_scale else np.zeros((len(self.idx), 0))
        self.n_long = self.B.shape[1]
        # the scan's pose (module text, "The scan's pose"): T = R_s M_s carries an error of the
        # gap on the subsample's trimmed unoperated points into the whole face's rigid field;
        # the long scale's copy through it joins the basis, the scan noise's a fixed field
        self._T = self._pose_u = self._noise_pose = None
        noise_pose = None
        if pose is not None:
            R, keep, M = pose
            Rs = np.asarray(R, float)[self.idx]
            u = np.isin(self.idx, keep)
            if u.sum() >= 12 and np.linalg.matrix_rank(Rs[u]) == 6:
                self._Ms, self._pose_u = np.linalg.pinv(Rs[u]), u
                self._T = Rs @ self._Ms
                self._noise_pose = self.sigma_n ** 2 * (np.asarray(M, float) @ np.asarray(M, float).T)
                lam, V = np.linalg.eigh(self._noise_pose)
                noise_pose = np.zeros((len(points), 6))
                noise_pose[self.idx] = Rs @ (V * np.sqrt(np.clip(lam, 0.0, None)))
                self.B = np.concatenate([self.B, self._T @ self.B[u]], axis=1)
        self.long_amplitudes = _LONG_AMPLITUDES if long_scale else np.zeros(1)
        # the mesh-error direction (module text, "The mesh's own error"): one column on the
        # subsample, its coefficient under a fixed Gaussian prior
        # and the boundary-condition directions (module text, "Boundary conditions"), after it,
        # then the layer-proportion directions ("Layer proportions"), then the scan noise's
        # pose field ("The scan's pose": six columns scaled by their standard deviations)
        cols, sd2 = [], []
        for field_, sd in ((mesh_error, MESH_ERROR_SD), (boundary, BOUNDARY_SD), (layers, LAYER_SD), (noise_pose, 1.0)):
            m = np.zeros((len(self.idx), 0))
            if field_ is not None:
                m = np.asarray(field_, float).reshape(len(points), -1)[self.idx]
                keep = np.all(np.isfinite(m), axis=0) & (np.sqrt(np.mean(m * m, axis=0)) > 1e-9)
                m = m[:, keep]
            cols.append(m)
            sd2.append(np.full(m.shape[1], sd ** 2))
        self.n_mesh = cols[0].shape[1]
        self.n_boundary = cols[1].shape[1]
        self.n_layers = cols[2].shape[1]
        self.N = np.concatenate(cols, axis=1)
        self._nsd2 = np.concatenate(sd2)
        BN = np.concatenate([self.B, self.N], axis=1)
        # the points under the mandible (module text): their own field where there are enough
        m = np.zeros(len(self.idx)) if border is None else np.asarray(border, bool)[self.idx].astype(float)
        self.border_share = float(m.mean())
        self.has_border = self.border_share >= MIN_BORDER_SHARE
        self.ratios = BORDER_RATIOS if self.has_border else (0.0,)
        self._mm = np.outer(m, m) if self.has_border else None
        self._eig = []                  # (ell, rho, eigenvalues, eigenvectors, U^T [B N])
        for ell in self.lengths:
            for rho in self.ratios:
                lam, U = np.linalg.eigh(self._kernel(ell, rho))
                self._eig.append((ell, rho, np.clip(lam, 0.0, None), U, U.T @ BN))

    def _kernel(self, ell: float, rho: float, pose: bool = True) -> np.ndarray:
        """The short scale's correlation on the subsample: K + rho M K M (module text, "Under
        the mandible"), plus its copy through the scan's pose, T K_uu T^T ("The scan's pose";
        `pose` False: without it)."""
        K = matern32(self._d, ell)
        if rho:
            K = K + rho * self._mm * K
        if pose and self._T is not None:
            u = self._pose_u
            K = K + self._T @ K[np.ix_(u, u)] @ self._T.T
        return K

    def pose_covariance(self, fit: Fit) -> np.ndarray | None:
        """Covariance C of the scan's pose under the error model `fit` (module text, "The
        scan's pose"): M_s (s_d^2 K_uu + s_L^2 B_u B_u^T) M_s^T + sigma_n^2 M M^T. Rotations
        (rad) about and translations (mm) along x, y, z; None without a pose."""
        if self._T is None:
            return None
        u = self._pose_u
        K = self._kernel(fit.ell, fit.border_ratio, pose=False)[np.ix_(u, u)]
        B = self.B[u, :self.n_long]
        C = self._Ms @ (fit.sigma_d ** 2 * K + fit.sigma_long ** 2 * (B @ B.T)) @ self._Ms.T + self._noise_pose
        return 0.5 * (C + C.T)

    def n_eff(self, ell: float) -> float:
        """Independent samples of the face for correlation length ell: area / (pi l^2)."""
        return float(np.clip(self.area / (np.pi * ell ** 2), 2.0, len(self.idx)))

    def covariance(self, fit: Fit, sel: np.ndarray | None = None) -> np.ndarray:
        """Sigma on the subsample (rows/columns `sel`) under the error model `fit`."""
        sel = np.ones(len(self.idx), bool) if sel is None else np.asarray(sel, bool)
        B, N = self.B[sel], self.N[sel]
        K = self._kernel(fit.ell, fit.border_ratio)[np.ix_(sel, sel)]
        return (fit.sigma_d ** 2 * K + fit.sigma_long ** 2 * (B @ B.T)
                + (N * self._nsd2) @ N.T + self.sigma_n ** 2 * np.eye(int(sel.sum())))

    def _profiles(self, zr, zJ, C, v, longs, lo, hi, prec=None, centre=None):
        """(log posterior, x, s_L, mesh-error coefficients, log L) at the best long-scale
        amplitude among `longs`, for fixed s_d and l: bounded GLS of theta (offset x from the
        anchor) with the long-scale and mesh-error coefficients under their Gaussian priors, in
        the normal equations of the whitened system (module text; the eigenbasis of K_l makes
        the whitening diagonal). The columns of C are the long-scale basis, then the mesh error.
        `prec`: per parameter the precision of its Gaussian prior (0: flat), about the offset
        -`centre` (the anchor's distance from the prior's centre is `centre`); the log
        posterior then holds the prior's term, log L the data's alone."""
        w = 1.0 / v
        k = zJ.shape[1] if zJ is not None else 0
        G = np.concatenate([zJ if k else np.zeros((len(zr), 0)), -C], axis=1)
        Gw = G * w[:, None]
        H0 = G.T @ Gw
        g0 = Gw.T @ zr
        q0 = float(zr @ (zr * w))
        if prec is not None and k:
            # (x + centre)^T P (x + centre) added to the quadratic
            H0[:k, :k] += np.diag(prec)
            g0[:k] += prec * centre
            q0 += float(centre @ (prec * centre))
        base = float(np.sum(np.log(v))) + len(zr) * np.log(2 * np.pi)
        q_mesh = self.N.shape[1]
        m = C.shape[1] - q_mesh
        best = None
        for s_l in longs:
            if s_l > 0 and m:
                sel = np.arange(k + m + q_mesh)
                pv = np.concatenate([np.full(m, s_l * s_l), self._nsd2])
            else:
                sel = np.concatenate([np.arange(k), k + m + np.arange(q_mesh)])
                pv = self._nsd2
            H, g = H0[np.ix_(sel, sel)], g0[sel]
            logdet = 0.0
            if len(pv):
                Hc = H[k:, k:]
                logdet = float(np.linalg.slogdet(np.eye(len(pv)) + pv[:, None] * Hc)[1])
                H = H.copy()
                H[k:, k:] += np.diag(1.0 / pv)
            if len(g):
                y = _bounded_quadratic(H + 1e-12 * np.trace(H) * np.eye(len(g)) / len(g), g, lo, hi, k)
                q = q0 + float(y @ H @ y) + 2.0 * float(g @ y)
                x = y[:k]
                nu = y[len(g) - q_mesh:]
            else:
                q, x, nu = q0, np.zeros(0), np.zeros(0)
            ll = -0.5 * (q + logdet + base)
            prior = 0.0 if prec is None or not k else float(np.sum(prec * (x + centre) ** 2))
            if best is None or ll > best[0]:
                best = (ll, x, float(s_l), nu, ll + 0.5 * prior)
        return best

    def fit(self, r: np.ndarray, J: np.ndarray | None = None, theta_a: np.ndarray | None = None,
            lower=None, upper=None, free=None, extra_k: int = 0, long_scale: bool = True,
            prior_sd: np.ndarray | None = None, origin: np.ndarray | None = None) -> Fit:
        """Profile maximum of log N(r + J (theta - theta_a); 0, Sigma) over the free parameters
        within bounds, s_d, l and s_L; `r` and `J` on all scan points (the subsample is taken
        here). k = free parameters + `extra_k` (discrete choices). `long_scale` False: s_L = 0.
        `prior_sd`: per parameter the standard deviation of a Gaussian prior about `origin`
        (inf: flat); the maximum is then the posterior's (theta and the amplitudes together),
        and `Fit.loglik` the data's log likelihood there."""
        r = np.asarray(r, float)[self.idx]
        nfree = 0
        lo = hi = np.zeros(0)
        prec = centre = None
        if J is not None and free is not None and np.any(free):
            free = np.asarray(free, bool)
            Jf = np.asarray(J, float)[self.idx][:, free]
            nfree = int(free.sum())
            lo = np.asarray(lower, float)[free] - theta_a[free]
            hi = np.asarray(upper, float)[free] - theta_a[free]
            if prior_sd is not None:
                prec = 1.0 / np.asarray(prior_sd, float)[free] ** 2      # 0 where flat (inf)
                centre = (np.asarray(theta_a, float) - np.asarray(origin, float))[free]
                if not prec.any():
                    prec = centre = None
        scale = float(np.sqrt(np.mean(r * r))) or self.sigma_n
        longs = self.long_amplitudes if long_scale else np.zeros(1)
        best = None
        for ell, rho, lam, U, UB in self._eig:
            zr = U.T @ r
            zJ = U.T @ Jf if nfree else None
            here = -np.inf
            for s_d in scale * _AMPLITUDES:
                v = s_d * s_d * lam + self.sigma_n ** 2
                top = self._profiles(zr, zJ, UB, v, scale * longs, lo, hi, prec, centre)
                if best is None or top[0] > best[0]:
                    best = (top[0], s_d, ell, top[1], top[2], top[3], rho, top[4])
                if top[0] < here - 1e-9:
                    break               # past this length's maximum in s_d (unimodal)
                here = top[0]
        _, s_d, ell, x, s_l, nu, rho, ll = best
        theta = None
        if theta_a is not None:
            theta = np.array(theta_a, float)
            if nfree:
                theta[free] = theta_a[free] + x
        B = self.B[:, :self.n_long]
        long_mm = float(s_l * np.sqrt(np.mean(np.sum(B * B, axis=1)))) if B.size else 0.0
        nu = np.asarray(nu, float)
        q, b = self.n_mesh, self.n_mesh + self.n_boundary
        y = b + self.n_layers

        def rms(lo, hi):
            return float(np.sqrt(np.mean((self.N[:, lo:hi] @ nu[lo:hi]) ** 2))) if hi > lo else 0.0

        return Fit(theta, float(s_d), float(ell), float(ll), nfree + int(extra_k), float(s_l), long_mm,
                   rms(0, q), nu[:q], rms(q, b), nu[q:b], rms(b, y), nu[b:y],
                   float(rho), self.border_share if rho else 0.0)

    def mesh_coefficient_sd(self, fit: Fit) -> np.ndarray:
        """Posterior standard deviations of the mesh-error coefficients under the error model
        `fit`: the coefficients c ~ N(0, s^2) enter the gap as N c, so that with Sigma the
        whole covariance (which holds s^2 N N^T) Var(c | gap) = s^2 - s^4 diag(N^T Sigma^-1 N).
        Near the prior's s where the direction is far below the noise: the gap then barely
        informs its coefficient."""
        if self.n_mesh == 0:
            return np.zeros(0)
        N = self.N[:, :self.n_mesh]
        s2 = self._nsd2[:self.n_mesh]
        q = np.einsum("ij,ij->j", N, np.linalg.solve(self.covariance(fit), N))
        return np.sqrt(np.clip(s2 - s2 * s2 * q, 0.0, None))

    def information(self, J: np.ndarray, fit: Fit, nuisance: np.ndarray | None = None) -> np.ndarray:
        """Fisher information J^T Sigma^-1 J of the parameters (columns of J, on all scan
        points; the subsample is taken here) under the error model `fit`. `nuisance`: columns
        on all scan points, each the response to a nuisance parameter times its prior
        standard deviation; the parameters are then integrated out, Sigma + E E^T."""
        Jw = np.asarray(J, float)[self.idx]
        S = self.covariance(fit)
        if nuisance is not None:
            E = np.asarray(nuisance, float).reshape(len(np.asarray(J)), -1)[self.idx]
            S = S + E @ E.T
        return Jw.T @ np.linalg.solve(S, Jw)

    def standard_errors(self, J: np.ndarray, fit: Fit, nuisance: np.ndarray | None = None) -> np.ndarray:
        """Standard errors of the parameters (columns of J) under the error model `fit`:
        sqrt(diag((J^T Sigma^-1 J)^-1)), inf along directions the data do not see;
        `nuisance` as in `information`."""
        return information_errors(self.information(J, fit, nuisance))

    def region_pvalue(self, r: np.ndarray, mask: np.ndarray, fit: Fit) -> float:
        """P-value of a region's gap under the error model `fit`: the quadratic form
        r_m^T Sigma_m^-1 r_m of the region's subsampled points is chi-square with as many
        degrees of freedom as points when the gap is noise + discrepancy."""
        from scipy.stats import chi2

        sel = np.asarray(mask, bool)[self.idx]
        m = int(sel.sum())
        if m == 0:
            return 1.0
        S = self.covariance(fit, sel)
        x = np.asarray(r, float)[self.idx][sel]
        q = float(x @ np.linalg.solve(S, x))
        return float(chi2.sf(q, m))

    def heldout_lpd(self, r: np.ndarray, folds: list[np.ndarray], fit: Fit, J: np.ndarray | None = None,
                    theta_a: np.ndarray | None = None, lower=None, upper=None, free=None,
                    origin: np.ndarray | None = None, prior_sd: np.ndarray | None = None) -> np.ndarray:
        """Per fold (a mask on all scan points) the log predictive density of its gap given the
        other folds. The effect's free parameters are integrated out under a Gaussian prior
        centred on "none" (`origin`) with their own prior's standard deviation where they have
        one (`prior_sd`, finite), else half their range, so the gap
        is Gaussian with covariance Sigma + J P J^T (Sigma: the error model `fit`) and the
        fold's predictive distribution is the conditional Gaussian given the other folds: the
        parameters are in effect fitted on the other folds, and a parameter they do not
        determine widens the prediction instead of spoiling it."""
        from scipy.linalg import cho_factor, cho_solve

        e = np.asarray(r, float)[self.idx].copy()
        S = self.covariance(fit)
        if J is not None and free is not None and np.any(free):
            free = np.asarray(free, bool)
            Jf = np.asarray(J, float)[self.idx][:, free]
            theta_a = np.asarray(theta_a, float)
            o = theta_a if origin is None else np.asarray(origin, float)
            e = e + Jf @ (o[free] - theta_a[free])
            sd = 0.5 * (np.asarray(upper, float)[free] - np.asarray(lower, float)[free])
            if prior_sd is not None:
                own = np.asarray(prior_sd, float)[free]
                sd = np.where(np.isfinite(own), own, sd)
            S = S + (Jf * sd ** 2) @ Jf.T
        out = []
        for mask in folds:
            te = np.asarray(mask, bool)[self.idx]
            tr = ~te
            if te.sum() == 0 or tr.sum() == 0:
                out.append(0.0)
                continue
            cf = cho_factor(S[np.ix_(tr, tr)], lower=True)
            Smo = S[np.ix_(te, tr)]
            mu = Smo @ cho_solve(cf, e[tr])
            C = S[np.ix_(te, te)] - Smo @ cho_solve(cf, Smo.T)
            dev = e[te] - mu
            logdet = np.linalg.slogdet(C)[1]
            out.append(float(-0.5 * (dev @ np.linalg.solve(C, dev) + logdet + te.sum() * np.log(2 * np.pi))))
        return np.array(out)

    def residual_level(self, fit: Fit) -> float:
        """RMS of the gap the error model expects without any effect: noise and both scales of
        the discrepancy."""
        return float(np.hypot(fit.discrepancy_mm, self.sigma_n))
