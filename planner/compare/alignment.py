"""Rigid superimposition of a post-operative scan on the pre-operative frame.

Trimmed iterative closest point (TrICP, Chetverikov et al., *Image Vis. Comput.* 23, 2005)
with the point-to-plane error of Chen & Medioni (1992), linearised for small rotations
(Low, *Linear least-squares optimization for point-to-plane ICP*, 2004) and applied through the
exact rotation (Rodrigues). Correspondences are the exact closest points on the reference
surface; only pairs whose closest point lies on an *allowed* triangle (the regions surgery does
not touch: forehead, nasal bridge, infra-orbital) and not on the reference boundary are used,
and of those the `keep` fraction with the smallest residuals (the rest are outliers: hair,
swelling, eyes, scan noise). A first coarse stage uses the whole face with a wide gate to
capture the scan from a rough placement; the second stage uses only the unoperated regions.
A scan in its own camera frame can be brought near first by `global_initialisation`: coarse
trimmed ICP from the 24 rotations of the cube group about the matched centroids, keeping the
start with the smallest trimmed residual. `superimpose` runs the ICP from the given frame and,
when the result looks wrong (few inliers, a residual above 0.75 mm on the unoperated regions,
or less than 60% of the scan within 2 mm of the face: a local minimum, e.g. a rotated pose
that fits the rounded forehead and cheeks only), also from the global starts, and keeps the
pose that brings more of the scan within 2 mm of the face.
The root-mean-square residual of the final inliers is the noise floor of the comparison.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner.compare.distances import TriangleSurface

__all__ = ["Alignment", "trimmed_icp", "align_to_reference", "global_initialisation", "superimpose",
           "rotation_matrix", "apply", "rigid_basis", "point_to_plane_step", "unoperated_median_mm", "unoperated_width_scale_pct",
           "OTHER_PATIENT_MEDIAN_MM", "OTHER_PATIENT_SCALE_PCT", "SCALE_MAX_STDERR_PCT",
           "SCALE_IGNORED_REGIONS",
           "DOUBTFUL_MEDIAN_MM"]

# The unoperated regions of one person's pre- and post-op faces agree within the scanner's
# noise (~0.1-0.3 mm; 0.5 mm gives a median of ~0.35 mm): a median distance over them of more
# than 1 mm after superimposition (half the forehead, nasal bridge and infra-orbital skin off
# by over 3x the noise) is another face; above 0.6 mm the scan is doubtful.
OTHER_PATIENT_MEDIAN_MM = 1.0
DOUBTFUL_MEDIAN_MM = 0.6
# The same person's face has the same size in both scans: surface scanners are calibrated to
# ~0.1-0.3 % (0.2 mm over a 200 mm face), and the registered model skin that a prediction stands
# on fits the pre-op skin within ~0.3 mm. A head of nearly the same size can still match the
# unoperated regions within 1 mm once rigidly superimposed (the ICP hides a few % of scale in a
# shift), but not once the width is fitted too (`unoperated_width_scale_pct`): over the
# unoperated regions lying over bone, a scan wider or narrower by more than this many percent
# is another face (the same patient's post-op scans, swollen ones included, stay within ~1 %).
# The preauricular regions are left out: the lateral face swells and sags with posture after
# surgery (the `swelling` and `gravity` effects).
OTHER_PATIENT_SCALE_PCT = 2.5
SCALE_IGNORED_REGIONS = ("preauricular_left", "preauricular_right")
# The width is judged only when the points determine it to this standard error (percent).
SCALE_MAX_STDERR_PCT = 0.5
# A width fit that moves by less than this (0.02 %) has settled: far below the 2.5 % judged.
SETTLED_SCALE = 2e-4


def rotation_matrix(omega: np.ndarray) -> np.ndarray:
    """Rotation by the rotation vector omega (Rodrigues' formula)."""
    omega = np.asarray(omega, float)
    theta = float(np.linalg.norm(omega))
    if theta < 1e-15:
        return np.eye(3)
    k = omega / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid matrix to (n, 3) points."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def rigid_basis(q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(m, 6) change of the residuals n . (p - closest point) per small rotation omega of the
    points about the origin of their offsets q and per translation t: n . (omega x q + t) =
    (q x n) . omega + n . t."""
    return np.concatenate([np.cross(q, n), n], axis=1)


def point_to_plane_step(p: np.ndarray, r: np.ndarray, n: np.ndarray,
                        weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One linearised point-to-plane step (Low 2004): the rotation omega about the (weighted)
    centroid c0 of the points p (m, 3) and the translation t that minimise
    sum w (r + (p - c0) x n . omega + n . t)^2, r = n . (p - closest point) their residuals
    along the unit directions n. Returns (the 4x4 rigid step, applied through the exact
    rotation, omega, t, c0)."""
    w = np.ones(len(p)) if weights is None else np.asarray(weights, float)
    c0 = (w / w.sum()) @ p
    A = rigid_basis(p - c0, n)
    AtA = A.T @ (A * w[:, None])
    # a tiny Tikhonov term keeps nearly symmetric patches (sphere-like foreheads) regular;
    # 1e-9 of the trace changes a well-posed solution by ~1e-9 relative.
    AtA += 1e-9 * np.trace(AtA) * np.eye(6)
    sol = np.linalg.solve(AtA, -A.T @ (w * r))
    omega, t = sol[:3], sol[3:]
    R = rotation_matrix(omega)
    step = np.eye(4)
    step[:3, :3] = R
    step[:3, 3] = c0 + t - R @ c0
    return step, omega, t, c0


@dataclass
class Alignment:
    matrix: np.ndarray                 # 4x4: scan frame -> reference (pre-op) frame
    residual_rms_mm: float             # RMS point-to-surface residual of the final inliers
    residual_mean_abs_mm: float
    n_points: int                      # final inliers
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)   # trimmed RMS per iteration
    strategy: str = "local"            # "local": ICP from the given frame; "global": 24 starts
    face_coverage: float = float("nan")   # scan fraction within 2 mm of the face (pose check)
    unoperated_median_mm: float = float("nan")   # untrimmed agreement on the unoperated regions
    unoperated_width_scale_pct: float = float("nan")   # how much wider the scan's face is there
    # the share of the unoperated regions' area both checks used: the prediction moves the rest
    # (`comparison.STILL_MM`); NaN where the prediction's displacement is not known
    unoperated_still_pct: float = float("nan")

    @property
    def rotation_deg(self) -> float:
        c = (np.trace(self.matrix[:3, :3]) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    @property
    def translation_mm(self) -> float:
        return float(np.linalg.norm(self.matrix[:3, 3]))

    def to_dict(self) -> dict:
        return {
            "residual_rms_mm": self.residual_rms_mm,
            "residual_mean_abs_mm": self.residual_mean_abs_mm,
            "n_points": self.n_points,
            "iterations": self.iterations,
            "converged": self.converged,
            "strategy": self.strategy,
            "face_coverage": self.face_coverage,
            "unoperated_median_mm": self.unoperated_median_mm,
            "unoperated_width_scale_pct": self.unoperated_width_scale_pct,
            "unoperated_still_pct": self.unoperated_still_pct,
            "rotation_deg": self.rotation_deg,
            "translation_mm": self.translation_mm,
            "matrix": self.matrix.tolist(),
        }


def _pairs(reference: TriangleSurface, x: np.ndarray, allowed_faces: np.ndarray | None,
           gate: float, keep: float):
    cp = reference.closest(x)
    ok = ~cp.on_boundary & (cp.distance <= gate)
    if allowed_faces is not None:
        ok &= allowed_faces[cp.face]
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return idx, cp
    if keep < 1.0:
        n_keep = max(int(np.ceil(keep * len(idx))), min(len(idx), 6))
        order = np.argpartition(cp.distance[idx], n_keep - 1)[:n_keep]
        idx = idx[order]
    return idx, cp


def trimmed_icp(
    source: np.ndarray,
    reference: TriangleSurface,
    allowed_faces: np.ndarray | None = None,
    init: np.ndarray | None = None,
    keep: float = 0.9,
    gate: float = 10.0,
    max_iterations: int = 60,
    tol_mm: float = 2e-4,
    min_points: int = 30,
) -> Alignment:
    """Rigidly align `source` points (n, 3) to the `reference` surface.

    Stops when the largest displacement of a source point over one iteration is below `tol_mm`
    (bounded by |omega| R + |t| with R the source radius), or when the trimmed residual stalls.
    """
    T = np.eye(4) if init is None else np.array(init, float)
    centre = source.mean(axis=0)
    radius = float(np.max(np.linalg.norm(source - centre, axis=1))) if len(source) else 0.0
    history: list[float] = []
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        x = apply(T, source)
        idx, cp = _pairs(reference, x, allowed_faces, gate, keep)
        if len(idx) < min_points:
            break
        p = x[idx]
        q = cp.point[idx]
        n = cp.normal[idx]
        r = np.einsum("pi,pi->p", p - q, n)
        history.append(float(np.sqrt(np.mean(r**2))))
        step, omega, t, c0 = point_to_plane_step(p, r, n)
        T = step @ T
        if np.linalg.norm(omega) * (radius + np.linalg.norm(c0 - centre)) + np.linalg.norm(t) < tol_mm:
            converged = True
            break
        # with noise the trimmed set can flip between two near-equal subsets: a stalled
        # residual (relative change < 1e-4 over two iterations) is convergence too
        if len(history) >= 3 and abs(history[-1] - history[-3]) <= 1e-4 * max(history[-1], 1e-6):
            converged = True
            break
    x = apply(T, source)
    idx, cp = _pairs(reference, x, allowed_faces, gate, keep)
    res = cp.signed[idx]
    return Alignment(
        matrix=T,
        residual_rms_mm=float(np.sqrt(np.mean(res**2))) if len(idx) else float("nan"),
        residual_mean_abs_mm=float(np.mean(np.abs(res))) if len(idx) else float("nan"),
        n_points=int(len(idx)),
        iterations=it,
        converged=converged,
        history=history,
    )


def align_to_reference(
    scan_points: np.ndarray,
    reference: TriangleSurface,
    unoperated_faces: np.ndarray,
    keep: float = 0.9,
    gate: float = 5.0,
    coarse_gate: float = 25.0,
    max_points: int = 10000,
    coarse_points: int = 4000,
    seed: int = 0,
    init: np.ndarray | None = None,
) -> Alignment:
    """Coarse whole-face trimmed ICP, then fine trimmed ICP on the unoperated regions.

    At most `max_points` scan points (a fixed random subset) drive the iterations; the
    reported residual uses them too (a random subset has the statistics of the whole).
    """
    pts = np.asarray(scan_points, float)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    coarse = trimmed_icp(pts[:coarse_points], reference, None, init=init, keep=0.6,
                         gate=coarse_gate, max_iterations=30, tol_mm=1e-2)
    fine = trimmed_icp(pts, reference, unoperated_faces, init=coarse.matrix, keep=keep, gate=gate)
    fine.iterations += coarse.iterations
    fine.history = coarse.history + fine.history
    return fine


def _cube_rotations() -> list[np.ndarray]:
    """The 24 proper rotations of the cube (signed permutation matrices with det +1)."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def global_initialisation(scan_points: np.ndarray, reference: TriangleSurface,
                          n_points: int = 1000, seed: int = 0) -> np.ndarray:
    """A rough 4x4 placement of a scan given in an arbitrary frame onto the reference.

    Each of the 24 cube rotations about the scan centroid, with the centroids matched, starts
    a coarse trimmed ICP (half the points kept, 60 mm gate); the four starts with the smallest
    trimmed residual after six iterations are run to convergence and the one bringing most of
    the scan within 2 mm of the reference wins.
    """
    pts = np.asarray(scan_points, float)
    rng = np.random.default_rng(seed)
    if len(pts) > n_points:
        pts = pts[rng.choice(len(pts), n_points, replace=False)]
    c_scan = pts.mean(axis=0)
    c_ref = reference.vertices.mean(axis=0)
    need = len(pts) // 3

    def run(T, iterations):
        return trimmed_icp(pts, reference, None, init=T, keep=0.5, gate=60.0,
                           max_iterations=iterations, tol_mm=1e-2, min_points=need)

    # a few iterations from every start, then the four most promising to convergence
    trials = []
    for R in _cube_rotations():
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c_ref - R @ c_scan
        a = run(T, 6)
        if a.n_points >= need:
            trials.append((a.residual_rms_mm, a.matrix))
    best, best_score = np.eye(4), -1.0
    for _, T in sorted(trials, key=lambda t: t[0])[:4]:
        a = run(T, 30)
        score = _face_coverage(pts, reference, a.matrix) if a.n_points >= need else -1.0
        if score > best_score:
            best, best_score = a.matrix, score
    return best


def _face_coverage(pts: np.ndarray, reference: TriangleSurface, T: np.ndarray,
                   within: float = 2.0) -> float:
    """Fraction of the scan points lying within `within` mm of the face (not beyond its edge)."""
    cp = reference.closest(apply(T, pts[:3000]))
    return float(np.mean(~cp.beyond_boundary & (cp.distance <= within)))


def superimpose(
    scan_points: np.ndarray,
    reference: TriangleSurface,
    unoperated_faces: np.ndarray,
    keep: float = 0.9,
    global_init: bool = False,
    max_points: int = 10000,
    seed: int = 0,
    suspicious_residual_mm: float = 0.75,
    suspicious_coverage: float = 0.6,
    min_points: int = 50,
) -> Alignment:
    """The scan's pose on the reference: local ICP, with a global search when it looks wrong.

    With `global_init` the global starts are used from the outset.
    """
    pts = np.asarray(scan_points, float)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]

    def attempt(init, strategy):
        a = align_to_reference(pts, reference, unoperated_faces, keep=keep, init=init)
        a.strategy = strategy
        a.face_coverage = _face_coverage(pts, reference, a.matrix)
        return a

    if global_init:
        return attempt(global_initialisation(pts, reference), "global")
    local = attempt(None, "local")
    if (local.n_points >= min_points and local.residual_rms_mm <= suspicious_residual_mm
            and local.face_coverage >= suspicious_coverage):
        return local
    wide = attempt(global_initialisation(pts, reference), "global")
    if wide.n_points >= min_points and (local.n_points < min_points
                                        or wide.face_coverage > local.face_coverage):
        return wide
    return local


def unoperated_median_mm(aligned: np.ndarray, reference: TriangleSurface, allowed_faces: np.ndarray,
                         gate: float = 10.0) -> float:
    """Median |distance| (mm) from the aligned scan points over the reference's unoperated
    triangles (`allowed_faces`, boolean per triangle) to the reference, every such point
    counted (untrimmed, unlike the ICP residual): how well the faces agree where surgery did
    not change them. NaN when no scan point lies over them."""
    c = reference.closest(np.asarray(aligned, float))
    sel = np.asarray(allowed_faces)[c.face] & ~c.beyond_boundary & (c.distance <= gate)
    return float(np.median(np.abs(c.signed[sel]))) if sel.any() else float("nan")


def unoperated_width_scale_pct(aligned: np.ndarray, reference: TriangleSurface, allowed_faces: np.ndarray,
                               weights: np.ndarray | None = None, gate: float = 5.0,
                               iterations: int = 20, max_step_pct: float = 2.0) -> tuple[float, float, bool]:
    """How much wider the scan's face is than the reference's (percent, along x) over the
    reference's unoperated triangles, its standard error (percent), and whether the fit
    converged (a scan of a different shape can keep the width drifting: no width fits it).

    The aligned scan points over those triangles are moved by a small rigid motion and a width
    scale about their centroid, x' = x + omega x x + t + s (x - c)_x e_x, chosen to minimise the
    point-to-plane residuals n . (x' - closest point) (linearised least squares, iterated with
    fresh closest points; Chen & Medioni 1992 with a scale unknown added). The linearisation is
    taken at the closest points, which carry no scan noise (with the scan points, noise along the
    normals would bias the scale by ~noise^2 / extent^2). A step changes the scale by at most
    `max_step_pct`, so that a scan of a different shape cannot throw the points out of the
    regions in one step. Only the width is fitted: regions such as the nasal root and the
    infra-orbital skin span ~80 mm across but little height or depth, where a scale would be
    poorly determined and would trade off against the rotation. `weights` (e.g. the scan's
    vertex areas) make the fit independent of how densely the scan samples each part. The
    standard error is that of weighted linear least squares, sigma^2 (A^T W A)^-1; it is
    optimistic for dense, correlated scan points but large when the regions are barely covered.
    The scan is wider by -s. Converged when the scale settles (`_settled`: a step below
    0.02 %, or a cycle of two or three selections at the regions' edge, whose mean is
    returned). NaN (and converged) when fewer than 50 scan points lie over the regions at the
    start; not converged when they leave the regions during the fit.
    """
    x = np.asarray(aligned, float).copy()
    allowed = np.asarray(allowed_faces, bool)
    w_all = np.ones(len(x)) if weights is None else np.asarray(weights, float)
    total, stderr, centre, history = 0.0, float("nan"), None, [0.0]
    for _ in range(iterations):
        cp = reference.closest(x)
        sel = allowed[cp.face] & ~cp.beyond_boundary & (cp.distance <= gate)
        if sel.sum() < 50:
            return (float("nan"), float("nan"), True) if centre is None else (-100.0 * total, stderr, False)
        q, n, r = cp.point[sel], cp.normal[sel], cp.signed[sel]
        if centre is None:
            centre = q.mean(axis=0)
        A = np.hstack([np.cross(q, n), n, n[:, :1] * (q[:, :1] - centre[0])])
        w = w_all[sel] / w_all[sel].mean()
        sw = np.sqrt(w)
        step, *_ = np.linalg.lstsq(A * sw[:, None], -r * sw, rcond=None)
        sigma2 = float(np.sum(w * (r + A @ step) ** 2)) / max(len(r) - 7, 1)
        try:
            stderr = 100.0 * float(np.sqrt(sigma2 * np.linalg.inv((A * w[:, None]).T @ A)[6, 6]))
        except np.linalg.LinAlgError:
            stderr = float("inf")
        limit = max_step_pct / 100.0
        if abs(step[6]) > limit:
            step = step * (limit / abs(step[6]))
        x = x + np.cross(step[:3], x) + step[3:6]
        x[:, 0] += step[6] * (x[:, 0] - centre[0])
        total += step[6]
        history.append(total)
        settled = _settled(history)
        if settled is not None:
            return -100.0 * settled, stderr, True
    return -100.0 * total, stderr, False


def _settled(history: list[float], longest_cycle: int = 3) -> float | None:
    """The settled width scale of a fit whose iterates are `history`, or None while it drifts.
    Settled when the last step is below `SETTLED_SCALE`, or when the fit has come back within
    it to where it stood p = 2..`longest_cycle` iterations before: a few points at the edge of
    the regions (or of the distance gate) leave and re-enter the selection in turn, and the
    fit cycles through those selections, each step undone by the next. The mean over the
    cycle is returned. A fit that keeps drifting (a face of another shape) never comes back.
    `history` starts with the scale before the first step (0)."""
    for p in range(1, min(longest_cycle, len(history) - 1) + 1):
        if abs(history[-1] - history[-1 - p]) < SETTLED_SCALE:
            return float(np.mean(history[-p:]))
    return None
