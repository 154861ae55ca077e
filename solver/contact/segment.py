"""Segment-to-segment contact between deformable facet sets: Gauss-point-to-segment (GPTS).

Node-to-segment contact fails the contact patch test on non-matching meshes (Taylor &
Papadopoulos 1991; Zavarise & De Lorenzis 2009): the pressure is sampled at the slave nodes and
handed to the master through its shape functions, so a uniform pressure does not give the
consistent nodal forces p int N_A dA of the hexahedra's bilinear faces. Here the traction is a
field sampled at Gauss points of every slave facet (n x n Gauss on s x s sub-squares of each
bilinear quad, collapsed Gauss on triangles; weights w = w_ref J_ref of the reference facet).
Each point x_g = N_a(xi_g) x_a is projected (closest point, local Newton in numba) on the
nearest master facet whose normal opposes the slave's, the master facet taken as the *bilinear*
quad (or linear triangle) of the FE mesh, not split into triangles, so that the master forces
are distributed with the same shape functions as the body's. Candidates come from one KD-tree
query of the points against the current facet centroids. The gap g = (x_g - x_m(zeta)) . n
(n the master normal at the projection) has the gradient dg = n . (dx_g - N_B dx_B) and a
Hessian from the linearised projection (`facet_gap`; Laursen 2002, ch. 5; Wriggers 2006,
ch. 4). The pressure is p = <lambda - eps g> (kPa; penalty eps in kPa/mm, augmented-Lagrangian
multiplier lambda per point). Two formulations:
* "symmetric" (default): the mean of two full passes (each surface the slave in turn, weight
  1/2), potential E = sum_g w (p^2 - lambda^2) / (2 eps) / 2, forces -w p dg on slave and
  master nodes, tangent w (eps dg (x) dg - p d2g): variationally consistent, symmetric (what the
  solver's symmetric factorisation needs), momentum exact. The master forces are the master
  shape functions sampled at slave Gauss points, exact only up to the quadrature of their kinks
  across a non-matching slave facet: the patch test is passed to 0.1 % with 2x2 Gauss on 2x2
  sub-squares (well within the 1 % the patch test asks).
* "two_half_pass" (Sauer & De Lorenzis 2013, CMAME 253; 2015, CMAME 295): each pass applies
  the traction to its slave nodes only, f_a = -sum_g w p N_a n, the other body receiving its
  share from the other pass: each body gets the traction integrated with its own shape
  functions, so the patch test is passed to round-off on any meshes. The tangent
  w N_a (eps n (x) dg - p dn) is exact but not symmetric and the forces derive from no
  potential; the solver uses the symmetric part, so Newton converges linearly (about 2 x
  the iterations of the symmetric form); `energy` is the symmetric form's potential.
A mortar method (Puso & Laursen 2004) would pass the patch test exactly with a symmetric
tangent too, at the price of polygon clipping and its linearisation; the GPTS forms reuse the
point-wise gap machinery of the node-to-segment term. Pairing, status freezing
(`freeze_after`), Uzawa updates (lambda <- p) and the initial-penetration offset are those of
`SurfaceContact`, per Gauss point (or, optionally, with the multipliers a field interpolated
from the slave nodes, updated from their weighted gaps as in mortar methods).
"""
from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from solver.contact._uzawa import AugmentedLagrangian, ContactTerm, deepest_penetration

__all__ = ["SegmentContact", "facet_quadrature"]


def _composite_1d(n: int, m: int, rule: str):
    """Points and weights on [-1, 1] of the n-point Gauss-Legendre or Gauss-Lobatto rule on
    m equal sub-intervals (Lobatto end points shared by neighbours are merged)."""
    if rule == "gauss":
        t, wt = np.polynomial.legendre.leggauss(n)
    elif rule == "lobatto" and n in (2, 3):
        t, wt = (np.array([-1.0, 1.0]), np.array([1.0, 1.0])) if n == 2 else \
            (np.array([-1.0, 0.0, 1.0]), np.array([1 / 3, 4 / 3, 1 / 3]))
    else:
        raise ValueError(f"quadrature rule must be 'gauss' (n >= 1) or 'lobatto' (n = 2, 3), "
                         f"got {rule!r} with n = {n}")
    c = np.arange(m)
    tt = (-1.0 + (2.0 * c[:, None] + 1.0 + t[None, :]) / m).ravel()
    ww = np.tile(wt / m, m)
    pts, inv = np.unique(np.round(tt, 14), return_inverse=True)
    return pts, np.bincount(inv, ww)


def facet_quadrature(n: int, n_vertices: int, subdivisions: int = 1, rule: str = "gauss"):
    """Reference quadrature of a facet: (N (q, nv) shape functions, dN (q, nv, 2), w (q,)).

    Quads: n x n Gauss-Legendre on each of subdivisions x subdivisions equal sub-squares of
    [-1, 1]^2 (composite rule), bilinear shape functions (node order counter-clockwise from
    (-1, -1)); exact for polynomials of degree 2n - 1 per direction, and the composite rule
    samples an integrand with kinks (the master shape functions seen from a non-matching
    slave facet) s^2 times more finely. Triangles: the n x n Gauss rule collapsed onto the unit
    triangle (Duffy), exact for polynomials of total degree 2n - 2; `subdivisions` splits the
    triangle into s^2 similar ones. rule "lobatto" (quads, n = 2 or 3: composite trapezoid or
    Simpson per direction) puts points on the facet's corners and edges, so that the contact
    constraint is enforced at the nodes too (exact to degree 2n - 3 per direction).
    """
    if n < 1 or subdivisions < 1:
        raise ValueError(f"quadrature order and subdivisions must be >= 1, got {n}, "
                         f"{subdivisions}")
    m = int(subdivisions)
    if n_vertices == 4:
        tt, ww = _composite_1d(n, m, rule)
        xi, eta = (a.ravel() for a in np.meshgrid(tt, tt, indexing="ij"))
        w = np.outer(ww, ww).ravel()
        sx = np.array([-1.0, 1.0, 1.0, -1.0])
        sy = np.array([-1.0, -1.0, 1.0, 1.0])
        N = 0.25 * (1 + xi[:, None] * sx) * (1 + eta[:, None] * sy)
        dN = np.stack([0.25 * sx * (1 + eta[:, None] * sy),
                       0.25 * sy * (1 + xi[:, None] * sx)], axis=2)
        return N, dN, w
    if n_vertices == 3:
        if rule != "gauss":
            raise ValueError("triangular facets take the 'gauss' quadrature rule only")
        t, wt = np.polynomial.legendre.leggauss(n)
        s = 0.5 * (t + 1.0)
        ws = 0.5 * wt
        a, b = (v.ravel() for v in np.meshgrid(s, s, indexing="ij"))
        w0 = (np.outer(ws, ws).ravel()) * (1.0 - b)
        u0, v0 = a * (1.0 - b), b
        # m^2 similar sub-triangles: the upright ones (i, j) and the inverted ones
        us, vs, ws_ = [], [], []
        for i in range(m):
            for j in range(m - i):
                us.append((i + u0) / m)
                vs.append((j + v0) / m)
                ws_.append(w0 / m ** 2)
                if i + j < m - 1:
                    us.append((i + 1 - u0) / m)
                    vs.append((j + 1 - v0) / m)
                    ws_.append(w0 / m ** 2)
        u, v, w = np.concatenate(us), np.concatenate(vs), np.concatenate(ws_)
        N = np.stack([1.0 - u - v, u, v], axis=1)
        dN = np.broadcast_to(np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]]),
                             (len(u), 3, 2)).copy()
        return N, dN, w
    raise ValueError(f"facets must be triangles or quads, got {n_vertices} vertices")


@nb.njit(cache=True)
def _shape(nv, u, v, N, dN, d2):
    """Shape functions of a facet at (u, v): bilinear quad on [-1, 1]^2 (nv = 4) or linear
    triangle (nv = 3); N (nv,), dN (nv, 2), d2 (nv,) the mixed second derivative."""
    if nv == 4:
        sx = (-1.0, 1.0, 1.0, -1.0)
        sy = (-1.0, -1.0, 1.0, 1.0)
        for a in range(4):
            N[a] = 0.25 * (1 + u * sx[a]) * (1 + v * sy[a])
            dN[a, 0] = 0.25 * sx[a] * (1 + v * sy[a])
            dN[a, 1] = 0.25 * sy[a] * (1 + u * sx[a])
            d2[a] = 0.25 * sx[a] * sy[a]
    else:
        N[0], N[1], N[2] = 1.0 - u - v, u, v
        dN[0, 0], dN[0, 1], dN[1, 0], dN[1, 1], dN[2, 0], dN[2, 1] = -1.0, -1.0, 1.0, 0.0, 0.0, 1.0
        d2[0], d2[1], d2[2] = 0.0, 0.0, 0.0


@nb.njit(cache=True)
def _project(points, facets, x, start, zeta):
    """Closest-point projection of points[i] on the facet facets[i] (bilinear quad or linear
    triangle) by Newton on r . t_alpha = 0 from `start` (Wriggers 2006, sec. 4.3); the local
    coordinates go to zeta[i]."""
    nv = facets.shape[1]
    N = np.empty(nv)
    dN = np.empty((nv, 2))
    d2 = np.empty(nv)
    for i in range(points.shape[0]):
        u, v = start[0], start[1]
        for _ in range(30):
            _shape(nv, u, v, N, dN, d2)
            r0 = points[i, 0]
            r1 = points[i, 1]
            r2 = points[i, 2]
            t = np.zeros((2, 3))
            xm = np.zeros(3)
            for a in range(nv):
                xa = x[facets[i, a]]
                for c in range(3):
                    t[0, c] += dN[a, 0] * xa[c]
                    t[1, c] += dN[a, 1] * xa[c]
                    xm[c] += d2[a] * xa[c]
            for a in range(nv):
                xa = x[facets[i, a]]
                r0 -= N[a] * xa[0]
                r1 -= N[a] * xa[1]
                r2 -= N[a] * xa[2]
            R0 = r0 * t[0, 0] + r1 * t[0, 1] + r2 * t[0, 2]
            R1 = r0 * t[1, 0] + r1 * t[1, 1] + r2 * t[1, 2]
            A00 = t[0, 0] ** 2 + t[0, 1] ** 2 + t[0, 2] ** 2
            A11 = t[1, 0] ** 2 + t[1, 1] ** 2 + t[1, 2] ** 2
            A01 = t[0, 0] * t[1, 0] + t[0, 1] * t[1, 1] + t[0, 2] * t[1, 2] \
                - (r0 * xm[0] + r1 * xm[1] + r2 * xm[2])
            det = A00 * A11 - A01 * A01
            if det == 0.0:
                break
            du = (A11 * R0 - A01 * R1) / det
            dv = (A00 * R1 - A01 * R0) / det
            u += du
            v += dv
            if abs(du) + abs(dv) < 1e-13:
                break
        zeta[i, 0] = u
        zeta[i, 1] = v


def facet_shape(nv, zeta):
    """Vectorised `_shape`: N (k, nv), dN (k, nv, 2), d2 (k, nv) at local coordinates zeta."""
    u, v = zeta[:, 0], zeta[:, 1]
    if nv == 4:
        sx = np.array([-1.0, 1.0, 1.0, -1.0])
        sy = np.array([-1.0, -1.0, 1.0, 1.0])
        N = 0.25 * (1 + u[:, None] * sx) * (1 + v[:, None] * sy)
        dN = np.stack([0.25 * sx * (1 + v[:, None] * sy), 0.25 * sy * (1 + u[:, None] * sx)],
                      axis=2)
        d2 = np.broadcast_to(0.25 * sx * sy, N.shape)
        return N, dN, d2
    N = np.stack([1.0 - u - v, u, v], axis=1)
    dN = np.broadcast_to(np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]]), (len(u), 3, 2))
    return N, dN, np.zeros_like(N)


def facet_gap(xg, xm, zeta, derivatives=True, hessian=False):
    """Gap of points xg (k, 3) to facets with nodes xm (k, nv, 3) at their closest points
    (local coordinates zeta (k, 2), from `_project`), with its first derivatives.

    Returns (g (k,), n (k, 3) unit outward normal at the projection, N (k, nv) shape
    functions there, dg (k, 3 + 3 nv), dn (k, 3, 3 + 3 nv) or None, the Hessian of g
    (k, 3 + 3 nv, 3 + 3 nv) or None), derivatives with respect to (x_g, x_1, ..., x_nv).
    g = (x_g - x_m(zeta)) . n; dg = n . (dx_g - N_B dx_B) (the
    stationarity of the projection removes the zeta terms); dn follows from
    dzeta = A^-1 Z (linearised condition r . t_alpha = 0, A_ab = t_a . t_b - r . x_,ab) and
    dt_a = N_B,a dx_B + x_,ab dzeta_b, dn = (I - n n) / |t_1 x t_2| (dt_1 x t_2 + t_1 x dt_2)
    (Laursen 2002, ch. 5; Wriggers 2006, ch. 4). The Hessian is the derivative of
    dg = (n, -N_B n): rows of x_g dn, rows of x_B -N_B dn - n (x) N_B,a dzeta_a.
    """
    k, nv = xm.shape[:2]
    N, dN, d2 = facet_shape(nv, zeta)
    t = np.einsum("kab,kai->kbi", dN, xm)                             # (k, 2, 3)
    r = xg - np.einsum("ka,kai->ki", N, xm)
    c = np.cross(t[:, 0], t[:, 1])
    L = np.linalg.norm(c, axis=1)
    n = c / L[:, None]
    g = np.einsum("ki,ki->k", r, n)
    m = 3 + 3 * nv
    dg = np.concatenate([n, (-N[:, :, None] * n[:, None, :]).reshape(k, 3 * nv)], axis=1)
    if not derivatives:
        return g, n, N, dg, None, None
    x12 = np.einsum("ka,kai->ki", d2, xm)                              # x_,12 (k, 3)
    A = np.einsum("kai,kbi->kab", t, t)
    A[:, 0, 1] -= np.einsum("ki,ki->k", r, x12)
    A[:, 1, 0] = A[:, 0, 1]
    # Z: d(r . t_a) at fixed zeta = t_a . (dx_g - N_B dx_B) + r . N_B,a dx_B
    Z = np.zeros((k, 2, m))
    Z[:, :, 0:3] = t
    Z[:, :, 3:] = (-N[:, None, :, None] * t[:, :, None, :]
                   + np.swapaxes(dN, 1, 2)[:, :, :, None] * r[:, None, None, :]).reshape(k, 2, -1)
    dzeta = np.linalg.solve(A, Z)                                      # (k, 2, m)
    # dt_a (k, 2, 3, m): N_B,a I on the facet nodes, x_,ab dzeta_b
    dt = np.zeros((k, 2, 3, m))
    eye = np.eye(3)
    dt[:, :, :, 3:] = (np.swapaxes(dN, 1, 2)[:, :, None, :, None] * eye[None, None, :, None, :]
                       ).reshape(k, 2, 3, -1)
    dt[:, 0] += x12[:, :, None] * dzeta[:, None, 1, :]
    dt[:, 1] += x12[:, :, None] * dzeta[:, None, 0, :]
    dc = np.cross(dt[:, 0], t[:, 1][:, :, None], axisa=1, axisb=1, axisc=1) \
        + np.cross(t[:, 0][:, :, None], dt[:, 1], axisa=1, axisb=1, axisc=1)
    P = (eye - n[:, :, None] * n[:, None, :]) / L[:, None, None]
    dn = np.einsum("kij,kjm->kim", P, dc)
    H = None
    if hessian:
        dNB = np.einsum("kba,kam->kbm", dN, dzeta)                      # (k, nv, m)
        H = np.concatenate([dn[:, None], -N[:, :, None, None] * dn[:, None]
                            - n[:, None, :, None] * dNB[:, :, None, :]], axis=1).reshape(k, m, m)
    return g, n, N, dg, dn, H


@nb.njit(cache=True)
def _select(owner, cand, key, previous, inside, bonus, n_points, best_out):
    """Per point, the candidate of least key (a point keeps its previous facet while its
    projection stays strictly inside it: key - bonus); best_out[point] = candidate row or -1."""
    best_key = np.full(n_points, np.inf)
    for r in range(owner.shape[0]):
        o = owner[r]
        k = key[r]
        if cand[r] == previous[o] and inside[r]:
            k -= bonus
        if k < best_key[o]:
            best_key[o] = k
            best_out[o] = r


def _inside(nv, zeta, tol):
    """Local coordinates inside the facet (within tol): (k,) bool; the margin (k,) (< 0 out)."""
    if nv == 4:
        margin = 1.0 - np.abs(zeta).max(axis=1)
    else:
        margin = np.minimum(np.minimum(zeta[:, 0], zeta[:, 1]), 1.0 - zeta.sum(axis=1))
    return margin >= -tol, margin


class _HalfPass:
    """Gauss points of one facet set against the facets of the other."""

    def __init__(self, nodes, slave_facets, master_facets, order, subdivisions, rule):
        slave_facets = np.asarray(slave_facets, dtype=np.int64)
        master_facets = np.asarray(master_facets, dtype=np.int64)
        for f in (slave_facets, master_facets):
            if f.ndim != 2 or f.shape[1] not in (3, 4):
                raise ValueError(f"facets must be (k, 3) triangles or (k, 4) quads, got {f.shape}")
        nv = slave_facets.shape[1]
        N, dN, w = facet_quadrature(order, nv, subdivisions, rule)
        q = len(w)
        self.nv = nv
        self.facets = slave_facets
        self.N = np.tile(N, (len(slave_facets), 1))                        # (k, nv)
        self.dN = np.tile(dN, (len(slave_facets), 1, 1))                   # (k, nv, 2)
        self.point_nodes = np.repeat(slave_facets, q, axis=0)              # (k, nv)
        self.facet_of = np.repeat(np.arange(len(slave_facets)), q)         # (k,)
        self.slaves = np.unique(slave_facets)
        # reference area weights w J_ref
        tang = np.einsum("kai,kaj->kij", nodes[self.point_nodes], self.dN)  # (k, 3, 2)
        J = np.linalg.norm(np.cross(tang[:, :, 0], tang[:, :, 1]), axis=1)
        self.weights = np.tile(w, len(slave_facets)) * J
        self.master = master_facets
        # Newton start of the projection: the facet's centre
        self.start = np.zeros(2) if master_facets.shape[1] == 4 else np.full(2, 1 / 3)
        k = len(self.weights)
        self.multipliers = np.zeros(k)          # kPa, at the points
        self.node_multipliers = np.zeros(len(nodes))   # kPa, nodal field (nodal_multipliers)
        self.offset = np.zeros(k)               # initial penetration ignored (mm)
        self.previous = np.full(k, -1)          # paired master facet, last search
        self.zeta = np.zeros((k, 2))            # its local coordinates, last evaluation
        self.active = np.zeros(k, dtype=bool)   # in contact, last evaluation

    def points(self, x):
        """Current Gauss point positions (k, 3) and unit slave normals (k, 3)."""
        xe = x[self.point_nodes]
        xg = np.einsum("ka,kai->ki", self.N, xe)
        tang = np.einsum("kai,kaj->kij", xe, self.dN)
        nrm = np.cross(tang[:, :, 0], tang[:, :, 1])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        return xg, nrm

    def project(self, xg, facets, x):
        zeta = np.empty((len(xg), 2))
        if len(xg):
            _project(np.ascontiguousarray(xg), np.ascontiguousarray(facets), x, self.start, zeta)
        return zeta

    def search(self, x, radius, max_depth, inside_tol=1e-3, cos_opposed=-0.2):
        """Pair every Gauss point with its master facet (or -1); updates `previous`."""
        p = x[self.master]
        cen = p.mean(axis=1)
        rmax = float(np.linalg.norm(p - cen[:, None], axis=2).max())
        xg, ng = self.points(x)
        # all (point, facet) pairs within reach, as arrays (no per-point Python lists)
        near = cKDTree(xg).sparse_distance_matrix(cKDTree(cen), radius + rmax,
                                                  output_type="ndarray")
        owner, cand = near["i"].astype(np.int64), near["j"].astype(np.int64)
        # a point is never in contact with a facet that shares a node with its own facet
        shared = np.zeros(len(cand), dtype=bool)
        for a in range(self.nv):
            shared |= np.any(self.master[cand] == self.point_nodes[owner, a][:, None], axis=1)
        cand, owner = cand[~shared], owner[~shared]
        best = np.full(len(xg), -1)
        if len(cand):
            zeta = self.project(xg[owner], self.master[cand], x)
            inside, margin = _inside(self.master.shape[1], zeta, inside_tol)
            ok = inside & np.all(np.isfinite(zeta), axis=1)
            cand, owner, zeta, margin = cand[ok], owner[ok], zeta[ok], margin[ok]
            g, nm, *_ = facet_gap(xg[owner], p[cand], zeta, derivatives=False)
            ok = (np.einsum("ij,ij->i", ng[owner], nm) < cos_opposed) \
                & (g + self.offset[owner] > -max_depth) & (g + self.offset[owner] < radius)
            cand, owner, g, margin, zeta = cand[ok], owner[ok], g[ok], margin[ok], zeta[ok]
            # nearest facet, projections strictly inside preferred over those inside only
            # within the tolerance, hysteresis for the previous facet (as in `surface`)
            key = np.abs(g) + np.where(margin < 0.0, 2.0 * (rmax + 1.0), 0.0)
            rows = np.full(len(xg), -1)
            _select(owner, cand, key, self.previous, margin >= -1e-12, 0.05 * rmax, len(xg),
                    rows)
            has = rows >= 0
            best[has] = cand[rows[has]]
        self.previous = best
        return best

    def evaluate(self, x, pairing, derivatives=True, hessian=False):
        """(points (k,), g, n, dg (k, m), dn (k, 3, m) or None, H (k, m, m) or None) of the
        paired Gauss points, derivatives with respect to (x_g, master facet nodes)."""
        s = np.nonzero(pairing >= 0)[0]
        xg = np.einsum("ka,kai->ki", self.N[s], x[self.point_nodes[s]])
        facets = self.master[pairing[s]]
        zeta = self.project(xg, facets, x)
        self.zeta[s] = zeta
        g, n, Nm, dg, dn, H = facet_gap(xg, x[facets], zeta, derivatives, hessian)
        return s, g + self.offset[s], n, dg, dn, H

    def dofs(self, s):
        nodes = np.concatenate([self.point_nodes[s], self.master[self.previous[s]]], axis=1)
        return (3 * nodes[:, :, None] + np.arange(3)).reshape(len(s), -1)


class SegmentContact(ContactTerm):
    """Frictionless segment-to-segment contact between two deformable facet sets.

    Experimental: verified by the patch and block tests, not used by the face model (which
    uses `SurfaceContact`).

    nodes: (n, 3) reference coordinates. surface_a, surface_b: (k, 3|4) facets with outward
    normals (right-hand rule), the same conventions as `SurfaceContact`; both act as slave in
    turn. formulation: "symmetric" (mean of two full passes: potential, symmetric tangent) or
    "two_half_pass" (exact patch test, unsymmetric tangent); see the module docstring.
    penalty: eps (kPa/mm, traction per unit gap: the same meaning as `SurfaceContact`'s, whose
    nodal penalty is eps times the nodal area). quadrature, subdivisions, rule: n x n Gauss
    ("gauss") or Gauss-Lobatto ("lobatto": points on the nodes too) points on s x s
    sub-squares of each slave facet (default 2, 2, "gauss": 16 points per quad).
    nodal_multipliers: False (default), one multiplier per Gauss point (Uzawa lambda_g <- p_g,
    `tolerance` bounds the deepest point's penetration); True, a multiplier field
    interpolated from the slave nodes (lambda_a <- <lambda_a - eps g_a>), one constraint per
    node on its weighted gap g_a = sum_g w N_a g / sum_g w N_a as in mortar methods
    (`tolerance` bounds the weighted gaps, which average penetrating and open points, so on a
    contact band one or two facets wide the points penetrate deeper than the tolerance).
    search_radius, max_depth, max_augmentations, freeze_after,
    ignore_initial_penetration and uzawa_schedule as in `SurfaceContact` (`settings`, an
    `AugmentedLagrangian`, or its fields as keyword arguments).
    Results: `penetration(x)`, `contact_pressure(x)` (per surface: node ids, kPa),
    `contact_forces(x)` ((n, 3) mN on the nodes), `initial_penetration`, `last_error`.
    """

    def __init__(self, nodes, surface_a, surface_b, *, settings: AugmentedLagrangian | None = None,
                 quadrature: int = 2, subdivisions: int = 2, rule: str = "gauss",
                 nodal_multipliers: bool = False, formulation: str = "symmetric",
                 ignore_initial_penetration: bool = True, **contact):
        nodes = np.asarray(nodes, dtype=float)
        self._configure(settings, contact)
        if formulation not in ("symmetric", "two_half_pass"):
            raise ValueError(f"formulation must be 'symmetric' or 'two_half_pass', "
                             f"got {formulation!r}")
        self.formulation = formulation
        self.nodal_multipliers = bool(nodal_multipliers)
        self.symmetric = formulation == "symmetric"
        # symmetric: the mean of the two full passes (each weighted 1/2); half passes: each
        # pass carries the whole traction of its slave side
        self.pass_weight = 0.5 if self.symmetric else 1.0
        self.n_nodes = len(nodes)
        self.passes = [_HalfPass(nodes, surface_a, surface_b, quadrature, subdivisions, rule),
                       _HalfPass(nodes, surface_b, surface_a, quadrature, subdivisions, rule)]
        self._last = None
        self.initial_penetration = 0.0
        if ignore_initial_penetration:
            for ps in self.passes:
                pairing = ps.search(nodes, self.search_radius, self.max_depth)
                s, g, *_ = ps.evaluate(nodes, pairing, derivatives=False)
                ps.offset[s] = np.maximum(-g, 0.0)
                ps.previous[:] = -1
                self.initial_penetration = max(self.initial_penetration,
                                               float(ps.offset.max(initial=0.0)))

    # --- pairing and pressures -------------------------------------------------------------
    def _evaluate(self, x, derivatives=True, frozen=False):
        """Per pass: (pass, points, g, n, dg, dn, H, lambda, p, active)."""
        x = np.asarray(x, dtype=float)
        out = []
        for ps in self.passes:
            reach = self.search_radius + float(np.max(ps.multipliers, initial=0.0)) / self.penalty
            if frozen:
                pairing = ps.previous
            else:
                pairing = ps.search(x, reach, self.max_depth)
            s, g, n, dg, dn, H = ps.evaluate(x, pairing, derivatives,
                                             derivatives and self.symmetric)
            lam = ps.multipliers[s]
            if frozen:
                # status freezing: the active set of the last search acts (pulling too), so
                # that Newton sees a smooth problem; `end_step` corrects the status
                a = ps.active[s] & (g > -self.max_depth) & (g < reach)
                p = np.where(a, lam - self.penalty * g, 0.0)
            else:
                p = np.maximum(lam - self.penalty * g, 0.0)
                a = p > 0
                ps.active[:] = False
                ps.active[s] = a
            out.append((ps, s, g, n, dg, dn, H, lam, p, a))
        return out

    # --- Term protocol ---------------------------------------------------------------------
    def assemble(self, x, load):
        f = np.zeros(3 * self.n_nodes)
        rows, cols, vals = [], [], []
        eps = self.penalty
        ev = self._evaluate(x, frozen=self._frozen(load))
        # the solver asks for the energy at the state it has just assembled: keep it
        self._last = (np.array(x, dtype=float), load, self._evals,
                      [(e[0], e[1], e[7], e[8], e[9]) for e in ev])
        for ps, s, g, n, dg, dn, H, lam, p, a in ev:
            if not np.any(a):
                continue
            s, n, dg, dn, p = s[a], n[a], dg[a], dn[a], p[a]
            w, N = ps.weights[s] * self.pass_weight, ps.N[s]
            k, nv = N.shape
            dofs = ps.dofs(s)                                    # (k, 3 nv + 3 nv_master)
            if self.symmetric:
                # full pass: E = w (p^2 - lambda^2) / (2 eps) in y = (x_g, master nodes),
                # f_y = -w p dg, K_y = w (eps dg (x) dg - p H), then x_g = N_b x_b (B^T . B)
                fy = -(w * p)[:, None] * dg
                Ky = w[:, None, None] * (eps * dg[:, :, None] * dg[:, None, :]
                                         - p[:, None, None] * H[a])
                fe = np.concatenate([(N[:, :, None] * fy[:, None, 0:3]).reshape(k, -1),
                                     fy[:, 3:]], axis=1)
                KB = np.concatenate([(Ky[:, :, None, 0:3] * N[:, None, :, None]).reshape(
                    k, Ky.shape[1], -1), Ky[:, :, 3:]], axis=2)           # K_y B
                Ke = np.concatenate([(N[:, :, None, None] * KB[:, None, 0:3, :]).reshape(
                    k, 3 * nv, -1), KB[:, 3:, :]], axis=1)                # B^T K_y B
                f += np.bincount(dofs.ravel(), fe.ravel(), minlength=len(f))
                row_dofs = dofs
            else:
                # half pass: slave forces f_a = -w p N_a n only; d(p n) = -eps n (x) dg + p dn
                fs = -(w * p)[:, None, None] * N[:, :, None] * n[:, None, :]      # (k, nv, 3)
                f += np.bincount(dofs[:, :3 * nv].ravel(), fs.ravel(), minlength=len(f))
                M = w[:, None, None] * (eps * n[:, :, None] * dg[:, None, :]
                                        - p[:, None, None] * dn)
                MB = np.concatenate([(N[:, None, :, None] * M[:, :, None, 0:3]).reshape(
                    k, 3, 3 * nv), M[:, :, 3:]], axis=2)
                Ke = (N[:, :, None, None] * MB[:, None, :, :]).reshape(k, 3 * nv, -1)
                row_dofs = dofs[:, :3 * nv]
            # Gauss points of one slave facet on one master facet share their dofs: sum their
            # element matrices first (fewer triplets for the sparse assembly)
            pair = ps.facet_of[s] * len(ps.master) + ps.previous[s]
            order = np.argsort(pair, kind="stable")
            first = np.ones(len(order), dtype=bool)
            first[1:] = pair[order][1:] != pair[order][:-1]
            starts = np.nonzero(first)[0]
            Ke = np.add.reduceat(Ke[order], starts, axis=0)
            dofs, row_dofs = dofs[order][starts], row_dofs[order][starts]
            m = dofs.shape[1]
            rows.append(np.repeat(row_dofs, m, axis=1).ravel())
            cols.append(np.tile(dofs, (1, row_dofs.shape[1])).ravel())
            vals.append(Ke.ravel())
        n_dofs = 3 * self.n_nodes
        if rows:
            K = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                      np.concatenate(cols))),
                              shape=(n_dofs, n_dofs))
        else:
            K = sp.coo_matrix((n_dofs, n_dofs))
        return f, K

    def energy(self, x, load) -> float:
        """Mean of the two full-pass penalty potentials sum_g w (p^2 - lambda^2) / (2 eps)."""
        last = self._last
        if last is not None and last[1] == load and last[2] == self._evals \
                and np.array_equal(last[0], x):
            ev = last[3]                       # the state assembled last (same x, load, status)
        else:
            ev = [(v[0], v[1], v[7], v[8], v[9])
                  for v in self._evaluate(x, False, self._is_frozen(load))]
        e = 0.0
        for ps, s, lam, p, a in ev:
            pp = np.zeros(len(ps.weights))
            pp[s] = np.where(a, p, 0.0)
            e += 0.5 * float(np.sum(ps.weights * (pp * pp - ps.multipliers ** 2))) \
                / (2.0 * self.penalty)
        return e

    def end_step(self, x, load) -> bool:
        multipliers = self._multiplier_values()
        before = [ps.previous.copy() for ps in self.passes]
        before_active = [ps.active.copy() for ps in self.passes]
        was_frozen = self._is_frozen(load)
        self._unfreeze()
        ev = self._evaluate(x, derivatives=False)
        moved = False
        if was_frozen:
            for (ps, s, g, n, dg, dn, H, lam, p, a), old, olda in zip(ev, before, before_active):
                act = s[a]
                moved |= bool(np.any(old[act] != ps.previous[act]))
                # status flips within the tolerance of the switch (gap units) do not count
                q = np.full(len(ps.weights), np.inf)
                q[s] = lam / self.penalty - g
                moved |= bool(np.any((olda != ps.active) & (np.abs(q) > self.tolerance)))
        err = 0.0
        updates = []
        for ps, s, g, n, dg, dn, H, lam, p, a in ev:
            if self.nodal_multipliers:
                # weighted (mortar-like) gap of every slave node over its paired points,
                # g_a = sum_g w N_a g / sum_g w N_a, and the nodal Uzawa update
                # lambda_a <- <lambda_a - eps g_a>, interpolated back to the points
                wN = ps.weights[s, None] * ps.N[s]
                idx = ps.point_nodes[s].ravel()
                num = np.bincount(idx, (wN * g[:, None]).ravel(), minlength=self.n_nodes)
                den = np.bincount(idx, wN.ravel(), minlength=self.n_nodes)
                has = den > 0
                gap = np.zeros(self.n_nodes)
                gap[has] = num[has] / den[has]
                lam_nodes = np.where(has, np.maximum(ps.node_multipliers - self.penalty * gap,
                                                     0.0), 0.0)
                on = lam_nodes > 0
                if np.any(on):
                    err = max(err, float(np.max(-gap[on])))
                updates.append(lam_nodes)
            else:
                if np.any(a):
                    err = max(err, float(-g[a].min()))
                new = np.zeros_like(ps.multipliers)
                new[s] = p
                updates.append(new)
        self.last_error = err
        again = self.uzawa.another_solve(load, moved, self.augmented, err, self.tolerance)
        if self.uzawa.update:                               # Uzawa update
            for ps, new in zip(self.passes, updates):
                if self.nodal_multipliers:
                    ps.node_multipliers = new
                    new = np.einsum("ka,ka->k", ps.N, new[ps.point_nodes])
                ps.multipliers = new
        self._note_carried(multipliers, load)
        return again

    def _multiplier_fields(self) -> list:
        return [(ps, "multipliers") for ps in self.passes] + (
            [(ps, "node_multipliers") for ps in self.passes] if self.nodal_multipliers else [])

    def _scale_multipliers(self, factor: float) -> None:
        for ps in self.passes:
            ps.multipliers = ps.multipliers * factor
            if self.nodal_multipliers:
                ps.node_multipliers = ps.node_multipliers * factor

    # --- results ---------------------------------------------------------------------------
    def penetration(self, x, load: float = 1.0) -> float:
        """Deepest penetration (mm, >= 0) of a Gauss point of either surface at x."""
        return deepest_penetration(g for _, _, g, *_ in self._evaluate(x, derivatives=False))

    def contact_pressure(self, x, load: float = 1.0):
        """Per surface (a, then b): (node ids, pressure kPa) at x, the normal contact force
        the body receives at each node (both passes) over the node's lumped area
        sum_g w N_a: -f . n_a / A_a, n_a the area-weighted outward node normal. For two half
        passes this is the slave Gauss-point pressure projected on the nodes (lumped L2)."""
        x = np.asarray(x, dtype=float)
        f = self.contact_forces(x)
        res = []
        for ps in self.passes:
            xg, ng = ps.points(x)
            area = np.bincount(ps.point_nodes.ravel(), (ps.weights[:, None] * ps.N).ravel(),
                               minlength=self.n_nodes)
            nn = np.zeros((self.n_nodes, 3))
            for c in range(3):
                nn[:, c] = np.bincount(ps.point_nodes.ravel(), (ps.weights[:, None] * ps.N
                                                               * ng[:, c:c + 1]).ravel(),
                                       minlength=self.n_nodes)
            nn = nn[ps.slaves]
            nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300)
            fn = -np.einsum("ki,ki->k", f[ps.slaves], nn)
            res.append((ps.slaves, fn / np.maximum(area[ps.slaves], 1e-300)))
        return res

    def contact_forces(self, x, load: float = 1.0):
        """Contact forces (n, 3) acting on the nodes (mN) at x: minus the residual term."""
        f = np.zeros(3 * self.n_nodes)
        for ps, s, g, n, dg, dn, H, lam, p, a in self._evaluate(x, derivatives=False):
            s, dg, p = s[a], dg[a], p[a]
            w, N = ps.weights[s] * self.pass_weight, ps.N[s]
            dofs = ps.dofs(s)
            fy = (w * p)[:, None] * dg
            fe = np.concatenate([(N[:, :, None] * fy[:, None, 0:3]).reshape(len(s), -1),
                                 fy[:, 3:]], axis=1)
            if not self.symmetric:
                fe, dofs = fe[:, :3 * ps.nv], dofs[:, :3 * ps.nv]
            np.add.at(f, dofs.ravel(), fe.ravel())
        return f.reshape(-1, 3)
