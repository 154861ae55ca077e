"""Soft-tissue landmarks located on a surface by their anatomical definitions.

A landmark predicted on the face is transferred to another surface (the aligned post-op scan,
or the prediction itself) by taking the surface points in a ball around it and refining with
the landmark's definition (Farkas, *Anthropometry of the Head and Face*, 1994):
- profile extremes on the mid-sagittal profile: pronasale (Prn), labrale superius (Ls), labrale
  inferius (Li) and soft-tissue pogonion (Pog) are the most anterior (+y) points, subnasale (Sn)
  the deepest (most posterior) point between columella and upper lip, soft-tissue menton (Me)
  the lowest point of the chin (measured downwards and MENTON_TILT = 35 deg forwards);
- cheilion (ChR on the patient's right, ChL) is the deepest point of the mouth corner, measured
  against a quadric fitted to its neighbourhood.
Refinement is sub-vertex: a quadratic height h(x, s) is fitted by least squares to the points
near the extremal vertex and its stationary point is taken (this averages scan noise out and
makes the result independent of the triangulation; the balls grow with the mesh spacing so
that a piecewise-linear surface is fitted over several facets). Applying the same operator to the
prediction and to the scan makes the landmark error a difference of like with like.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from facemodel.head_geometry import MENTON_TILT

__all__ = ["RULES", "locate_landmark", "LandmarkLocator"]

# name -> (kind, direction d in the mid-sagittal (y, z) plane along which the landmark is
# extreme). Menton's direction is tilted MENTON_TILT (35) degrees anteriorly from straight down,
# so that a submental contour sloping down into the neck does not carry it away from the chin:
# the one convention of the synthetic heads' truth and of registration
# (`facemodel.head_geometry.MENTON_TILT`, where the choice of angle is justified).
_ME = (0.0, float(np.sin(np.radians(MENTON_TILT))), float(-np.cos(np.radians(MENTON_TILT))))
RULES: dict[str, tuple[str, tuple[float, float, float]]] = {
    "Prn": ("profile", (0.0, 1.0, 0.0)),
    "Ls": ("profile", (0.0, 1.0, 0.0)),
    "Li": ("profile", (0.0, 1.0, 0.0)),
    "Pog": ("profile", (0.0, 1.0, 0.0)),
    "Sn": ("profile", (0.0, -1.0, 0.0)),
    "Me": ("profile", _ME),
    "ChR": ("deepest", (0.0, 1.0, 0.0)),
    "ChL": ("deepest", (0.0, 1.0, 0.0)),
}


def _quadratic_fit(u: np.ndarray, v: np.ndarray, h: np.ndarray) -> np.ndarray | None:
    """Least-squares h = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2; None if ill-posed."""
    if len(h) < 8:
        return None
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    coef, _, rank, _ = np.linalg.lstsq(A, h, rcond=None)
    return coef if rank == 6 else None


@dataclass
class LandmarkLocator:
    """Landmark search on one point set (surface vertices, dense enough: <= ~1 mm apart)."""

    points: np.ndarray
    boundary_points: np.ndarray | None = None    # surface boundary vertices (partial scans)
    radius: float = 8.0                          # search ball around the transferred landmark
    fit_radius: float = 3.0                      # quadratic fit around the extremal vertex
    min_points: int = 15

    def __post_init__(self):
        self.points = np.asarray(self.points, float)
        self.tree = cKDTree(self.points)
        self._btree = (cKDTree(self.boundary_points)
                       if self.boundary_points is not None and len(self.boundary_points) else None)

    def locate(self, name: str, guess) -> np.ndarray | None:
        """The landmark near `guess` on this surface, or None where it cannot be found."""
        if name not in RULES:
            return None
        guess = np.asarray(guess, float)
        kind, direction = RULES[name]
        if kind == "deepest" and self._btree is not None:
            # an open mouth fissure (a hole in the skin surface): cheilion is its lateral corner
            corner = self._fissure_corner(guess)
            if corner is not None:
                return corner
        for _ in range(2):  # one re-centring if the extreme sits on the edge of the ball
            idx = np.asarray(self.tree.query_ball_point(guess, self.radius), dtype=np.int64)
            if len(idx) < self.min_points:
                return None
            cand = self.points[idx]
            if kind == "profile":
                point, on_edge = self._profile(cand, guess, np.asarray(direction))
            else:
                point, on_edge = self._deepest(cand, guess)
            if point is None:
                return None
            if not on_edge:
                break
            guess = point
        else:
            return None
        if self._btree is not None and self._btree.query(point)[0] < 2.0:
            return None
        return point

    def _fissure_corner(self, guess):
        idx = self._btree.query_ball_point(guess, 0.5 * self.radius)
        if len(idx) < 3:
            return None
        b = self.boundary_points[idx]
        side = 1.0 if guess[0] >= 0 else -1.0        # ChR on +x (patient's right), ChL on -x
        return b[int(np.argmax(side * b[:, 0]))].copy()

    def _profile(self, cand, guess, d):
        """Extreme of h = d.p on the mid-sagittal profile x = guess_x (d in the y-z plane)."""
        e = np.array([0.0, -d[2], d[1]])                 # along the profile, in the y-z plane
        band = np.abs(cand[:, 0] - guess[0]) < 1.5
        if band.sum() < 5:
            band = np.abs(cand[:, 0] - guess[0]) < 3.0
            if band.sum() < 5:
                return None, False
        b = cand[band]
        k = int(np.argmax(b @ d))
        best = b[k]
        on_edge = np.linalg.norm(best - guess) > self.radius - 1.0
        near = cand[np.linalg.norm(cand - best, axis=1) < self.fit_radius] - best
        coef = _quadratic_fit(near[:, 0], near @ e, near @ d)
        # a flat profile (curvature radius over 500 mm) has no defined extreme
        if coef is None or coef[5] > -1.0 / (2 * 500.0):
            return None, False
        point = best.copy()
        # on the mid-sagittal plane of the transferred landmark, x = guess_x
        xg = float(np.clip(guess[0] - best[0], -self.fit_radius, self.fit_radius))
        s0 = -(coef[2] + coef[4] * xg) / (2 * coef[5])   # stationary along the profile
        if abs(s0) < self.fit_radius:
            h0 = (coef[0] + coef[1] * xg + coef[2] * s0 + coef[3] * xg * xg + coef[4] * xg * s0
                  + coef[5] * s0 * s0)
            point = best + np.array([xg, 0.0, 0.0]) + s0 * e + h0 * d
        return point, on_edge

    def _deepest(self, cand, guess):
        c = cand.mean(axis=0)
        w, vecs = np.linalg.eigh(np.cov((cand - c).T))
        n = vecs[:, 0] * (1.0 if vecs[1, 0] >= 0 else -1.0)     # outward ~ anterior
        e1, e2 = vecs[:, 2], vecs[:, 1]
        u, v, h = (cand - c) @ e1, (cand - c) @ e2, (cand - c) @ n
        coef = _quadratic_fit(u, v, h)
        if coef is None:
            return None, False
        A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
        resid = h - A @ coef
        # smooth the residual over 1.2 mm so that scan noise does not pick the deepest point
        sub = cKDTree(cand)
        groups = sub.query_ball_point(cand, 1.2)
        smooth = np.array([resid[g].mean() for g in groups])
        k = int(np.argmin(smooth))
        best = cand[k]
        on_edge = np.linalg.norm(best - guess) > self.radius - 1.0
        near = np.linalg.norm(cand - best, axis=1) < self.fit_radius
        coef2 = _quadratic_fit(u[near] - u[k], v[near] - v[k], h[near])
        point = best.copy()
        if coef2 is not None:
            H = np.array([[2 * coef2[3], coef2[4]], [coef2[4], 2 * coef2[5]]])
            if np.all(np.linalg.eigvalsh(H) > 0):                  # a pit: a local minimum
                st = np.linalg.solve(H, -coef2[1:3])
                if np.linalg.norm(st) < self.fit_radius:
                    hh = coef2[0] + coef2[1:3] @ st + 0.5 * st @ H @ st
                    point = c + (u[k] + st[0]) * e1 + (v[k] + st[1]) * e2 + hh * n
        return point, on_edge


def locate_landmark(points: np.ndarray, name: str, guess, **kw) -> np.ndarray | None:
    """Convenience wrapper: LandmarkLocator(points, **kw).locate(name, guess)."""
    return LandmarkLocator(points, **kw).locate(name, guess)
