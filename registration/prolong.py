"""Carry a registration (or any nodal field) from one hexahedral mesh to another of the same body.

Two generic meshes of the same tissue at different resolutions (`generic_mesh`: the same
(theta, phi, depth) parameterisation, other grids) fill the same volume. A registration maps
the coarser generic mesh onto the patient node by node; inside each of its elements the map
is the element's trilinear interpolation, x(p) = sum_a N_a(xi(p)) x_a, with xi(p) the
natural coordinates of p in the generic element (Hughes, The Finite Element Method, 1987,
sec. 3.5). The finer mesh's generic nodes are located in the coarser generic mesh (the
element containing each, by Newton inversion of the trilinear map; a node just outside the
coarser mesh's boundary, where the finer mesh follows the curved surfaces more closely, takes
the nearest element and a short trilinear extrapolation), and the same interpolation carries
any nodal field: the registered positions (a registration of the finer mesh without
registering it again) or a solution's displacement (a start for a solve on the finer mesh).
Groups keep a point in the elements of its own side where one mesh is cut by a slit that the
other mesh also has (the mouth: a lower-lip node must not take an upper-lip element across
the gap).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numba
from scipy.spatial import cKDTree

from solver.element import HEX8_CORNERS, hex8_shape

__all__ = ["Location", "locate_points", "carry"]

# candidate elements per point (nearest centroids); more than the 8 elements around a node
# of a structured grid, for elements much longer than thick
CANDIDATES = 16
NEWTON_ITERATIONS = 20
# natural-coordinate change that ends the inversion: 1e-13 of an element's [-1, 1] span is
# below the round-off of the map itself on a 200 mm head
XI_TOL = 1e-13
# natural-coordinate bound of the inversion: a thin element (a 1.8 mm dermis layer) may have
# to extrapolate a point a few of its thicknesses away, where the other mesh bulges further
XI_BOUND = 8.0
_CORNERS = np.ascontiguousarray(HEX8_CORNERS)


@dataclass(frozen=True)
class Location:
    """Points located in a hexahedral mesh: element (n,), natural coordinates xi (n, 3) in
    [-1, 1]^3 (beyond it for a point outside the mesh) and the distance (n,) in mm from the
    point to the element's clamped image (0 inside)."""

    element: np.ndarray
    xi: np.ndarray
    outside_mm: np.ndarray

    def weights(self) -> np.ndarray:
        """Shape-function weights (n, 8) of the points in their elements."""
        return hex8_shape(self.xi)


@numba.njit(cache=True)
def _shape(xi, N, dN):
    """Trilinear shape functions N (8,) and derivatives dN (8, 3) at xi (3,) (VTK order)."""
    for a in range(8):
        c0, c1, c2 = _CORNERS[a, 0], _CORNERS[a, 1], _CORNERS[a, 2]
        t0, t1, t2 = 1.0 + c0 * xi[0], 1.0 + c1 * xi[1], 1.0 + c2 * xi[2]
        N[a] = t0 * t1 * t2 / 8.0
        dN[a, 0] = c0 * t1 * t2 / 8.0
        dN[a, 1] = c1 * t0 * t2 / 8.0
        dN[a, 2] = c2 * t0 * t1 / 8.0


@numba.njit(cache=True)
def _invert(p, C, xi):
    """Natural coordinates xi (3,) of point p under the trilinear map of corners C (8, 3):
    Newton's method from the centre, each iterate kept within [-XI_BOUND, XI_BOUND]^3 so
    that a far candidate cannot run away, until the update is below XI_TOL (or
    NEWTON_ITERATIONS). Returns False if the Jacobian is singular."""
    N = np.empty(8)
    dN = np.empty((8, 3))
    J = np.empty((3, 3))
    r = np.empty(3)
    xi[:] = 0.0
    for _ in range(NEWTON_ITERATIONS):
        _shape(xi, N, dN)
        for i in range(3):
            r[i] = p[i]
            for j in range(3):
                J[i, j] = 0.0
            for a in range(8):
                r[i] -= N[a] * C[a, i]
                for j in range(3):
                    J[i, j] += dN[a, j] * C[a, i]
        det = (J[0, 0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
               - J[0, 1] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
               + J[0, 2] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]))
        if abs(det) < 1e-12:
            return False
        step = np.linalg.solve(J, r)
        size = 0.0
        for i in range(3):
            new = min(XI_BOUND, max(-XI_BOUND, xi[i] + step[i]))
            size = max(size, abs(new - xi[i]))
            xi[i] = new
        if size < XI_TOL:       # converged (quadratically): the next steps change nothing
            return True
    return True


@numba.njit(cache=True)
def _locate(P, X, H, cand, allowed, elem, XI, dist):
    N = np.empty(8)
    dN = np.empty((8, 3))
    C = np.empty((8, 3))
    xi = np.empty(3)
    xc = np.empty(3)
    for q in range(P.shape[0]):
        best = np.inf
        for c in range(cand.shape[1]):
            if not allowed[q, c]:
                continue
            e = cand[q, c]
            for a in range(8):
                for i in range(3):
                    C[a, i] = X[H[e, a], i]
            if not _invert(P[q], C, xi):
                continue
            excess = 0.0
            for i in range(3):
                xc[i] = min(1.0, max(-1.0, xi[i]))
                excess = max(excess, abs(xi[i] - xc[i]))
            _shape(xc, N, dN)
            d2 = 0.0
            for i in range(3):
                s = P[q, i]
                for a in range(8):
                    s -= N[a] * C[a, i]
                d2 += s * s
            # inside (to the inversion's round-off) first, then the nearest clamped image
            score = 0.0 if excess <= 1e-9 else 1.0 + np.sqrt(d2)
            if score < best:
                best = score
                elem[q] = e
                XI[q] = xi
                dist[q] = np.sqrt(d2)
                if score == 0.0:
                    break


def locate_points(points, nodes, hexes, *, point_group=None, element_group=None,
                  candidates: int = CANDIDATES) -> Location:
    """The element of `nodes`/`hexes` containing each of `points` (n, 3), with its natural
    coordinates. A point inside no candidate element takes the one whose clamped image is
    nearest. point_group (n,) / element_group (m,): integers; a point of group g > 0 only
    takes elements of group g or 0, a point of group 0 any element."""
    P = np.ascontiguousarray(points, dtype=float)
    X = np.ascontiguousarray(nodes, dtype=float)
    H = np.ascontiguousarray(hexes, dtype=np.int64)
    grouped = point_group is not None and element_group is not None
    k = min(int(candidates) * (2 if grouped else 1), len(H))   # room for the other side's
    _, cand = cKDTree(X[H].mean(axis=1)).query(P, k=k)
    cand = np.ascontiguousarray(cand.reshape(len(P), k), dtype=np.int64)
    allowed = np.ones(cand.shape, bool)
    if grouped:
        pg = np.asarray(point_group, np.int64)[:, None]
        eg = np.asarray(element_group, np.int64)[cand]
        allowed = (pg == 0) | (eg == 0) | (eg == pg)
    elem = np.full(len(P), -1, np.int64)
    xi = np.zeros((len(P), 3))
    dist = np.full(len(P), np.inf)
    _locate(P, X, H, cand, allowed, elem, xi, dist)
    if np.any(elem < 0):
        raise ValueError(f"{int(np.sum(elem < 0))} point(s) have no element of their group among "
                         f"their {k} nearest elements")
    return Location(element=elem, xi=xi, outside_mm=dist)


def carry(location: Location, hexes, field) -> np.ndarray:
    """A nodal field (N, d) of the located-in mesh interpolated at the located points (n, d)."""
    F = np.asarray(field, float)
    H = np.asarray(hexes, np.int64)
    return np.einsum("qa,qa...->q...", location.weights(), F[H[location.element]])
