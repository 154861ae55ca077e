"""Geometry kernels of contact: closest points on triangles, pseudo-normals, plane gaps.

* `closest_on_triangle` / `closest_point_on_triangles` (from `solver.geometry`): the closest
  point of a point on a triangle and its region (face, edge, vertex), so that the gap can be
  signed with the angle-weighted pseudo-normals of Baerentzen & Aanaes (2005, IEEE TVCG 11): a point is outside a closed
  surface iff (p - c) . n_pseudo > 0 at its closest point c.
* `TriangleSurface`: a triangulated surface with its face/edge/vertex pseudo-normals and a
  KD-tree on face centroids; `closest(points, radius)` finds, for every point, the exact
  closest point among the faces whose centroid lies within d_nearest + r_max (every point of a
  face is within r_max of its centroid, so the closest face is always among these).
* `plane_gap`: the signed distance g = (x_s - x_1) . n of a node to the plane of a deformable
  triangle (x_1, x_2, x_3) with its exact gradient and Hessian with respect to the 12 nodal
  coordinates (g = V / A, V = (x_s - x_1) . (a x b), A = |a x b|), the linearisation of
  node-to-segment contact (Wriggers, *Computational Contact Mechanics*, 2006, ch. 4) while the
  projection stays inside the triangle.
"""
from __future__ import annotations

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["closest_point_on_triangles", "closest_on_triangle", "TriangleSurface", "plane_gap", "triangulate",
           "nodal_areas", "facet_normals", "psd_projection"]

from solver.geometry import (EDGE_AB, EDGE_BC, EDGE_CA, FACE, VERT_A, VERT_B,  # noqa: F401
                             VERT_C, closest_on_triangle, closest_point_on_triangles,
                             triangulate)


def nodal_areas(nodes: np.ndarray, facets: np.ndarray, n_nodes: int | None = None):
    """Tributary area of every node of a facet set (each facet's area shared equally).

    A quad's area (the norm of its vector area, exact for planar quads) goes a quarter to
    each of its nodes, a triangle's a third: the lumped nodal weights of a uniform pressure.
    """
    facets = np.asarray(facets, dtype=np.int64)
    p = nodes[facets]
    k = facets.shape[1]
    vec = sum(np.cross(p[:, i], p[:, (i + 1) % k]) for i in range(k))
    area = 0.5 * np.linalg.norm(vec, axis=1)
    out = np.zeros(len(nodes) if n_nodes is None else n_nodes)
    np.add.at(out, facets.ravel(), np.repeat(area / k, k))
    return out


def facet_normals(nodes: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Unit normals (right-hand rule) of triangles; zero for degenerate triangles."""
    p = nodes[tri]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


def psd_projection(M):
    """Nearest positive semi-definite matrices (k, n, n) of symmetric M: negative eigenvalues
    clipped to 0 (the projected Newton tangent of Teran, Sifakis, Irving & Fedkiw 2005)."""
    w, V = np.linalg.eigh(0.5 * (M + np.swapaxes(M, 1, 2)))
    return np.einsum("kij,kj,klj->kil", V, np.maximum(w, 0.0), V)


def _dot(u, v):
    return np.einsum("...i,...i->...", u, v)


class TriangleSurface:
    """A fixed triangulated surface with pseudo-normals and a centroid KD-tree.

    vertices (p, 3), faces (q, 3) with outward normals by the right-hand rule. Degenerate
    faces are dropped.
    """

    def __init__(self, vertices, faces):
        V = np.ascontiguousarray(vertices, dtype=float)
        F = np.asarray(faces, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise ValueError("a triangle surface needs vertices (p, 3) and faces (q, 3)")
        if len(F) == 0:
            raise ValueError("a triangle surface needs at least one face")
        if F.min() < 0 or F.max() >= len(V):
            raise ValueError("face indices out of range of the vertices")
        raw = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        area2 = np.linalg.norm(raw, axis=1)
        keep = area2 > 1e-12 * max(area2.max(), 1e-300)
        F, raw, area2 = F[keep], raw[keep], area2[keep]
        self.vertices, self.faces = V, F
        self.face_normals = raw / area2[:, None]
        # angle-weighted vertex pseudo-normals
        p = V[F]
        vn = np.zeros_like(V)
        for k in range(3):
            e1 = p[:, (k + 1) % 3] - p[:, k]
            e2 = p[:, (k + 2) % 3] - p[:, k]
            cosang = _dot(e1, e2) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
            ang = np.arccos(np.clip(cosang, -1.0, 1.0))
            np.add.at(vn, F[:, k], self.face_normals * ang[:, None])
        self.vertex_normals = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        # edge pseudo-normals: sum of the normals of the (one or two) adjacent faces
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        key = np.sort(e, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        en = np.zeros((len(uniq), 3))
        np.add.at(en, inv.ravel(), np.tile(self.face_normals, (3, 1)))
        en /= np.maximum(np.linalg.norm(en, axis=1, keepdims=True), 1e-300)
        self.face_edges = inv.ravel().reshape(3, len(F)).T       # (q, 3): ab, bc, ca
        self.edge_normals = en
        self.centroids = p.mean(axis=1)
        self.r_max = float(np.linalg.norm(p - self.centroids[:, None], axis=2).max())
        self.tree = cKDTree(self.centroids)

    def pseudo_normal(self, face, region):
        """Pseudo-normal at the closest feature (face, edge or vertex) of each query."""
        n = self.face_normals[face].copy()
        f = self.faces[face]
        for r, k in ((VERT_A, 0), (VERT_B, 1), (VERT_C, 2)):
            m = region == r
            n[m] = self.vertex_normals[f[m, k]]
        for r, k in ((EDGE_AB, 0), (EDGE_BC, 1), (EDGE_CA, 2)):
            m = region == r
            n[m] = self.edge_normals[self.face_edges[face[m], k]]
        return n

    def closest(self, points, radius: float):
        """Closest points on the surface for the points within `radius` of it.

        Returns (index (k,) into points, closest (k, 3), face (k,), region (k,), distance (k,)).
        """
        points = np.asarray(points, dtype=float)
        d0, _ = self.tree.query(points, distance_upper_bound=radius + self.r_max)
        near = np.nonzero(np.isfinite(d0))[0]
        if len(near) == 0:
            e = np.zeros(0, dtype=np.int64)
            return e, np.zeros((0, 3)), e, e, np.zeros(0)
        lists = self.tree.query_ball_point(points[near], d0[near] + self.r_max)
        counts = np.fromiter((len(l) for l in lists), dtype=np.int64, count=len(lists))
        cand = np.fromiter((i for l in lists for i in l), dtype=np.int64, count=counts.sum())
        owner = np.repeat(np.arange(len(near)), counts)
        p = points[near][owner]
        tri = self.vertices[self.faces[cand]]
        q, region = closest_point_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        dist = np.linalg.norm(p - q, axis=1)
        # per point, the candidate with the smallest distance
        order = np.lexsort((dist, owner))
        first = np.ones(len(order), dtype=bool)
        first[1:] = owner[order][1:] != owner[order][:-1]
        best = order[first]
        keep = dist[best] <= radius
        best = best[keep]
        return near[owner[best]], q[best], cand[best], region[best], dist[best]


# node -> variable coefficients of the map (x_s, x_1, x_2, x_3) -> (u, a, b) =
# (x_s - x_1, x_2 - x_1, x_3 - x_1)
_C = np.array([[1.0, 0.0, 0.0], [-1.0, -1.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


@nb.njit(cache=True)
def _cross(p, q, out):
    out[0] = p[1] * q[2] - p[2] * q[1]
    out[1] = p[2] * q[0] - p[0] * q[2]
    out[2] = p[0] * q[1] - p[1] * q[0]


@nb.njit(cache=True)
def _skew_into(v, S, r0, c0, sign):
    """Add sign * [v]_x to S[r0:r0+3, c0:c0+3]."""
    S[r0 + 0, c0 + 1] += -sign * v[2]
    S[r0 + 0, c0 + 2] += sign * v[1]
    S[r0 + 1, c0 + 0] += sign * v[2]
    S[r0 + 1, c0 + 2] += -sign * v[0]
    S[r0 + 2, c0 + 0] += -sign * v[1]
    S[r0 + 2, c0 + 1] += sign * v[0]


@nb.njit(cache=True)
def _plane_gap_kernel(xs, x1, x2, x3, C, hessian, g, grad, hess, nrm, bc):
    """Per row: g = V / A, its gradient and Hessian in z = (u, a, b) (V = u . w, w = a x b,
    A = |w|: dV = (w, b x u, u x a), dA = (0, b x n, n x a), HA = Jw^T (I - n n^T) Jw / A +
    the (a, b) coupling of -[n]_x, Jw = dw/dz), mapped to the 12 nodal coordinates by C."""
    k = xs.shape[0]
    u, a, b, w, n, t = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    dV, dA, gz = np.empty(9), np.empty(9), np.empty(9)
    HV, HA, Hz, Hn = np.empty((9, 9)), np.empty((9, 9)), np.empty((9, 9)), np.empty((9, 9))
    Jw, PJ = np.empty((3, 9)), np.empty((3, 9))
    for e in range(k):
        for i in range(3):
            u[i] = xs[e, i] - x1[e, i]
            a[i] = x2[e, i] - x1[e, i]
            b[i] = x3[e, i] - x1[e, i]
        _cross(a, b, w)
        A = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        for i in range(3):
            n[i] = w[i] / A
        V = u[0] * w[0] + u[1] * w[1] + u[2] * w[2]
        gg = V / A
        g[e] = gg
        # projection xs - g n = x1 + xi a + eta b
        aa = a[0] * a[0] + a[1] * a[1] + a[2] * a[2]
        ab = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
        bb = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]
        ra = 0.0
        rb = 0.0
        for i in range(3):
            r = u[i] - gg * n[i]
            ra += r * a[i]
            rb += r * b[i]
        det = aa * bb - ab * ab
        bc[e, 0] = (bb * ra - ab * rb) / det
        bc[e, 1] = (aa * rb - ab * ra) / det
        for i in range(3):
            nrm[e, i] = n[i]
        # derivatives in z = (u, a, b)
        for i in range(3):
            dV[i] = w[i]
            dA[i] = 0.0
        _cross(b, u, t)
        dV[3:6] = t
        _cross(u, a, t)
        dV[6:9] = t
        _cross(b, n, t)
        dA[3:6] = t
        _cross(n, a, t)
        dA[6:9] = t
        for i in range(9):
            gz[i] = dV[i] / A - V / (A * A) * dA[i]
        for p in range(4):
            for i in range(3):
                s = 0.0
                for al in range(3):
                    s += C[p, al] * gz[3 * al + i]
                grad[e, 3 * p + i] = s
        if not hessian:
            continue
        HV[:, :] = 0.0
        _skew_into(b, HV, 0, 3, -1.0)
        _skew_into(a, HV, 0, 6, 1.0)
        _skew_into(u, HV, 3, 6, -1.0)
        for i in range(9):
            for j in range(i):
                HV[i, j] = HV[j, i]
        Jw[:, :] = 0.0
        _skew_into(b, Jw, 0, 3, -1.0)
        _skew_into(a, Jw, 0, 6, 1.0)
        # HA = Jw^T (I - n n^T) Jw / A + Hn
        for j in range(9):
            s = n[0] * Jw[0, j] + n[1] * Jw[1, j] + n[2] * Jw[2, j]
            for i in range(3):
                PJ[i, j] = Jw[i, j] - n[i] * s
        for i in range(9):
            for j in range(9):
                HA[i, j] = (Jw[0, i] * PJ[0, j] + Jw[1, i] * PJ[1, j] + Jw[2, i] * PJ[2, j]) / A
        Hn[:, :] = 0.0
        _skew_into(n, Hn, 3, 6, -1.0)
        for i in range(9):
            for j in range(9):
                HA[i, j] += Hn[i, j] + Hn[j, i]
        for i in range(9):
            for j in range(9):
                Hz[i, j] = (HV[i, j] / A
                            - (dV[i] * dA[j] + dA[i] * dV[j]) / (A * A)
                            + 2.0 * V / (A * A * A) * dA[i] * dA[j]
                            - V / (A * A) * HA[i, j])
        for p in range(4):
            for q in range(4):
                for i in range(3):
                    for j in range(3):
                        s = 0.0
                        for al in range(3):
                            cp = C[p, al]
                            if cp == 0.0:
                                continue
                            for be in range(3):
                                cq = C[q, be]
                                if cq != 0.0:
                                    s += cp * cq * Hz[3 * al + i, 3 * be + j]
                        hess[e, 3 * p + i, 3 * q + j] = s



def plane_gap(xs, x1, x2, x3, hessian: bool = True):
    """Signed distance of nodes xs to the planes of triangles (x1, x2, x3), all (k, 3).

    Returns (g (k,), grad (k, 12), hess (k, 12, 12) or None, n (k, 3) unit normal,
    (xi, eta) (k, 2) barycentric coordinates of the projection) with the dof order
    (xs, x1, x2, x3), computed row by row in a numba kernel, `_plane_gap_kernel`.
    """
    xs, x1, x2, x3 = (np.ascontiguousarray(v, dtype=float).reshape(-1, 3)
                      for v in (xs, x1, x2, x3))
    k = len(xs)
    g, grad, n, bc = np.empty(k), np.empty((k, 12)), np.empty((k, 3)), np.empty((k, 2))
    hess = np.empty((k, 12, 12) if hessian else (0, 12, 12))
    _plane_gap_kernel(xs, x1, x2, x3, _C, bool(hessian), g, grad, hess, n, bc)
    return g, grad, (hess if hessian else None), n, bc
