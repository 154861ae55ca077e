"""Initial alignment of the generic model to the patient: a similarity transform x -> s R x + t.

With landmarks the transform is the least-squares similarity of Umeyama ("Least-squares
estimation of transformation parameters between two point patterns", IEEE PAMI 13, 1991).
Without them it comes from the surfaces: candidate rotations map the area-weighted principal
axes of the generic skin onto those of the patient skin under each of the 24 proper signed
axis permutations (sign disambiguation), plus the identity (both are in patient RAS), and each
candidate is refined by a symmetric trimmed ICP (Chetverikov et al., "The trimmed iterative
closest point algorithm", ICPR 2002) with point-to-plane similarity steps. The
trim keeps the best-matching fraction of pairs in both directions, so a partial, holed or noisy
patient surface, or one that extends beyond the generic face (scalp, neck), does not bias the
fit; the symmetric term stops the scale from collapsing onto a patch.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from registration.surface import TargetSurface


@dataclass(frozen=True)
class Similarity:
    scale: float
    rotation: np.ndarray  # (3, 3), det +1
    translation: np.ndarray  # (3,)

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x) @ self.rotation.T + self.translation

    def apply_vectors(self, v: np.ndarray) -> np.ndarray:
        return np.asarray(v) @ self.rotation.T

    def compose(self, first: "Similarity") -> "Similarity":
        """self o first."""
        return Similarity(self.scale * first.scale, self.rotation @ first.rotation,
                          self.scale * self.rotation @ first.translation + self.translation)

    def inverse(self) -> "Similarity":
        return Similarity(1.0 / self.scale, self.rotation.T, -self.rotation.T @ self.translation / self.scale)

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    @property
    def rotation_deg(self) -> float:
        c = np.clip((np.trace(self.rotation) - 1.0) / 2.0, -1.0, 1.0)
        return float(np.degrees(np.arccos(c)))

    @staticmethod
    def identity() -> "Similarity":
        return Similarity(1.0, np.eye(3), np.zeros(3))


def umeyama(src: np.ndarray, dst: np.ndarray, weights=None, with_scale: bool = True) -> Similarity:
    """Similarity minimising sum w |s R src + t - dst|^2 (Umeyama 1991, eqs. 34-42)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    u, d, vt = np.linalg.svd(cov)
    sgn = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2] = -1.0
    r = u @ np.diag(sgn) @ vt
    var_s = np.sum(w * np.sum(xs**2, axis=1))
    s = float(np.sum(d * sgn) / var_s) if with_scale and var_s > 0 else 1.0
    return Similarity(s, r, mu_d - s * r @ mu_s)


def _principal_frame(points: np.ndarray):
    c = points.mean(0)
    _, vecs = np.linalg.eigh(np.cov((points - c).T))
    vecs = vecs[:, ::-1]
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] *= -1
    return c, vecs


def _proper_signed_permutations():
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def _samples(surface: TargetSurface, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    f = rng.choice(len(surface.faces), size=n, p=surface.face_areas / surface.area)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("ni,nid->nd", w, surface.vertices[surface.faces[f]]), surface.face_normals[f]


@dataclass
class IcpResult:
    similarity: Similarity
    rms_mm: float  # RMS of the kept pairs
    inliers: float  # fraction of samples with a valid pair closer than the inlier distance
    score: float  # truncated quadratic error, both directions (lower is better), mm^2


def trimmed_icp(source: TargetSurface, target: TargetSurface, init: Similarity, *,
                n_points: int = 800, iterations: int = 30, keep: float = 0.9,
                inlier_mm: float = 5.0, scale_bounds=(0.6, 1.6), tol: float = 1e-4,
                seed: int = 0, extra=(), fix_scale: bool = False, step_tol: float = 0.0) -> IcpResult:
    """Symmetric trimmed ICP between two triangulated surfaces (similarity, point-to-plane).

    Forward pairs: source samples -> closest point on the target; reverse pairs: target samples
    -> closest point on the source (queried in source space through the inverse transform).
    Pairs whose closest point is on an open border of the other surface or whose normals face
    away from each other are dropped (partial overlap), then the worst (1 - keep) of each set
    (noise); a linearised point-to-plane similarity step on what remains, both directions
    weighted equally. `extra`: further (points (k, 3) of the source, target surface) pairs, e.g.
    the model's bone attachment nodes and the patient's bone segment they belong to, matched
    forwards like the samples (trimmed, point-to-plane) and weighted as much as the skin's
    forward pairs together; their truncated error enters the score likewise. fix_scale: a
    rigid refinement at the starting scale. Iterations stop when the RMS changes by less than
    `tol` (relative) or, with step_tol > 0, when the step moves the pairs by less than step_tol
    mm (rotation and scale over the pairs' spread, plus translation)."""
    rng = np.random.default_rng(seed)
    src, src_n = _samples(source, n_points, rng)
    tgt, tgt_n = _samples(target, n_points, rng)
    tf = init
    prev = np.inf
    rms, inl, score = np.inf, 0.0, inlier_mm**2
    for _ in range(iterations):
        moved = tf.apply(src)
        cf = target.closest(moved)
        ok_f = ~cf.on_boundary & (np.einsum("ij,ij->i", tf.apply_vectors(src_n), cf.normal) > 0.0)
        back = (tgt - tf.translation) @ tf.rotation / tf.scale
        cr = source.closest(back)
        ok_r = ~cr.on_boundary & (np.einsum("ij,ij->i", tf.apply_vectors(cr.normal), tgt_n) > 0.0)
        d_f, d_r = cf.distance, tf.scale * cr.distance
        if ok_f.sum() < 10 or ok_r.sum() < 10:
            return IcpResult(tf, np.inf, 0.0, inlier_mm**2)
        trunc_f = np.where(ok_f, np.minimum(d_f, inlier_mm), inlier_mm)
        trunc_r = np.where(ok_r, np.minimum(d_r, inlier_mm), inlier_mm)
        score = float(0.5 * np.mean(trunc_f**2) + 0.5 * np.mean(trunc_r**2))
        ok_f &= d_f <= np.quantile(d_f[ok_f], keep)
        ok_r &= d_r <= np.quantile(d_r[ok_r], keep)
        # point-to-plane step (Chen & Medioni 1992) for a similarity, linearised about the
        # current pose: moved point m, partner q, normal n; unknowns small rotation w, scale
        # increment d, translation t: (m + w x m + d m + t - q) . n = 0
        m = [moved[ok_f], tf.apply(cr.points[ok_r])]
        q = [cf.points[ok_f], tgt[ok_r]]
        n = [cf.normal[ok_f], tgt_n[ok_r]]
        w = [np.full(ok_f.sum(), 0.5 / ok_f.sum()), np.full(ok_r.sum(), 0.5 / ok_r.sum())]
        extra_score = []
        for pts, surf in extra:
            mp = tf.apply(pts)
            ce = surf.closest(mp)
            extra_score.append(float(np.mean(np.minimum(ce.distance, inlier_mm) ** 2)))
            ok = ~ce.on_boundary
            if ok.sum() < 3:
                continue
            ok &= ce.distance <= np.quantile(ce.distance[ok], keep)
            m.append(mp[ok]); q.append(ce.points[ok]); n.append(ce.normal[ok])
            w.append(np.full(ok.sum(), 0.5 / (len(extra) * ok.sum())))
        if extra_score:
            score = 0.5 * (score + float(np.mean(extra_score)))
        m, q, n, w = (np.concatenate(a) for a in (m, q, n, w))
        rms = float(np.sqrt(0.5 * np.mean(d_f[ok_f] ** 2) + 0.5 * np.mean(d_r[ok_r] ** 2)))
        inl = 0.5 * (np.mean(ok_f & (d_f < inlier_mm)) + np.mean(ok_r & (d_r < inlier_mm)))
        centre = w @ m / w.sum()
        mc = m - centre
        rows = np.hstack([np.cross(mc, n), np.einsum("ij,ij->i", mc, n)[:, None], n])
        rhs = -np.einsum("ij,ij->i", m - q, n)
        sw = np.sqrt(w)[:, None]
        # a light ridge keeps the step defined when the overlap is a near-symmetric patch
        if fix_scale:
            rows[:, 3] = 0.0
        lhs = (rows * sw).T @ (rows * sw) + 1e-6 * np.eye(7)
        step = np.linalg.solve(lhs, (rows * sw).T @ (rhs * sw[:, 0]))
        rot = Rotation.from_rotvec(step[:3]).as_matrix()
        inc = Similarity(1.0 + step[3], rot, centre + step[4:] - (1.0 + step[3]) * rot @ centre)
        new = inc.compose(tf)
        if not scale_bounds[0] <= new.scale <= scale_bounds[1]:
            new = Similarity(float(np.clip(new.scale, *scale_bounds)), new.rotation, new.translation)
        tf = new
        if abs(prev - rms) < tol * max(rms, 1e-9):
            break
        # the pose itself has stopped moving (motion of the pairs' spread below step_tol mm)
        spread = float(np.sqrt(w @ np.sum(mc**2, axis=1) / w.sum()))
        if step_tol and spread * (np.linalg.norm(step[:3]) + abs(step[3])) + np.linalg.norm(step[4:]) < step_tol:
            break
        prev = rms
    return IcpResult(tf, rms, float(inl), score)


def align_surfaces(source: TargetSurface, target: TargetSurface, *, good_rms_mm: float = 3.0,
                   seed: int = 0, extra=(), fix_scale: bool = False, step_tol: float = 0.0) -> IcpResult:
    """Similarity taking the generic skin `source` onto the patient skin `target`.

    The identity (both surfaces are in patient RAS and mm) is tried first and kept when its
    ICP converges with an RMS below `good_rms_mm` and at least half the samples matched.
    Otherwise the candidates are: the identity result, the identity rotation and the 24 proper
    signed permutations of the principal axes (sign disambiguation) started with matched
    centroids, each refined by a short trimmed ICP on few points; the three with the lowest
    truncated quadratic error (a pair farther than the inlier distance, or without a valid
    closest point, costs the inlier distance squared: the robust score of partial matching)
    are refined on more points and the best is returned. `extra` (see `trimmed_icp`): the bones,
    matched along with the skin by the candidates: a face fitted upside down on the patient's
    face matches the skin almost as well as the right pose (truncated scores within ~5 % on
    some heads) and the skin alone leaves a right candidate stuck 10-20 deg off, but the bones
    under the face tell them apart (`registration.mesh_match`)."""
    first = trimmed_icp(source, target, Similarity.identity(), n_points=400, iterations=20, seed=seed)
    if first.rms_mm < good_rms_mm and first.inliers >= 0.5:
        if extra:
            return _finish_with_bones(source, target, first.similarity, seed, extra)
        return trimmed_icp(source, target, first.similarity, n_points=1500, iterations=30, seed=seed + 1)
    rng = np.random.default_rng(seed)
    ps, _ = _samples(source, 3000, rng)
    pt, _ = _samples(target, 3000, rng)
    cs, fs = _principal_frame(ps)
    ct, ft = _principal_frame(pt)
    rotations = [np.eye(3)] + [ft @ p @ fs.T for p in _proper_signed_permutations()]
    inits = [Similarity(1.0, r, ct - r @ cs) for r in rotations]
    if extra:   # the identity's result again, now with the bones
        first = trimmed_icp(source, target, first.similarity, n_points=400, iterations=20, seed=seed,
                            extra=extra)
    trials = [first] + [trimmed_icp(source, target, init, n_points=150, iterations=30, seed=seed,
                                    extra=extra) for init in inits]
    trials.sort(key=lambda t: t.score)
    refined = [trimmed_icp(source, target, t.similarity, n_points=1500, iterations=40, seed=seed + 1,
                           extra=extra) for t in trials[:3]]
    refined.sort(key=lambda t: t.score)
    if extra:
        return _finish_with_bones(source, target, refined[0].similarity, seed, extra)
    return refined[0]


def _finish_with_bones(source, target, start: Similarity, seed: int, extra) -> IcpResult:
    """The pose and scale from the skin and the bones together, then the skin alone refines
    the pose at that scale. A face-only skin (a scan, a CBCT ending below the eyes) leaves the
    skin-only fit a flat valley in pitch and scale -- its optimum then depends on where the
    search starts, i.e. on how the patient lies in the scanner -- while the bones under it,
    the skull above all, fix both; the skin finishes the pose (its surface is the one the
    registration fits) without rescaling the head onto a part of the face."""
    joint = trimmed_icp(source, target, start, n_points=1500, iterations=60, seed=seed + 1, extra=extra,
                        tol=0.0, step_tol=0.05)
    return trimmed_icp(source, target, joint.similarity, n_points=1500, iterations=100, seed=seed + 1,
                       fix_scale=True, tol=0.0, step_tol=0.05)
