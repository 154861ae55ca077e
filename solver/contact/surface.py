"""Two-surface (and self) contact between deformable facet sets: two-pass node-to-segment.

Each pass takes the nodes of one facet set as slaves and the other set, split into triangles,
as master segments (Hallquist, Goudreau & Benson 1985; two-pass symmetric treatment of
Taylor & Papadopoulos 1991, which passes the contact patch test). For a slave node x_s the
search (a KD-tree on the current master centroids, rebuilt at every evaluation) collects the
triangles whose plane projection falls inside the triangle and whose normal opposes the
slave's own surface normal; the nearest one (the triangle of the last search kept while the
projection stays within `pair_hysteresis` outside it) gives the gap g = (x_s - x_1) . n, signed
distance to the triangle's plane (`plane_gap`, exact gradient and Hessian in the 12 nodal
coordinates). The potential, force and tangent are those of `rigid`:
E = (<lambda - eps A_s g>^2 - lambda^2) / (2 eps A_s), f = -p dg/dx,
K = eps A_s dg (x) dg - p d2g/dx2 with p = <lambda - eps A_s g>, so the linearisation is
consistent for a fixed pairing. The pairing and the active set are re-searched at every
evaluation until `freeze_after` evaluations at one load; then they are frozen (status
freezing) so that Newton converges on a smooth problem, and `end_step` asks for another solve
if a fresh search at the converged state disagrees. `end_step` updates the multipliers (Uzawa) until the
deepest penetration is below `tolerance`. A re-solve re-decides the status at its first two
evaluations only, then freezes it (`freeze_resolves`): the status is nearly the one the step
needs.

Crease blending (`crease_blend`). The gap to a triangle's plane jumps when a slave's pairing
passes to the neighbouring triangle across a crease (by the crease angle times the distance
from the edge), and so does its force. Within a band of half-width c = crease_blend |e|
about an interior edge e the gap blends the two planes,
g = g_T + beta (g_N - g_T), beta = 1 - S((d + c) / (2 c)),
d the slave's distance on T's side from the bisector plane of the two triangles through the
edge (its normal kept while the status is frozen, like the pairing), S the smoothstep below:
beta = 1/2 on the bisector, 0 at the distance c on T's side, 1 at c on N's side. Since d
from N is -d from T and S(1 - t) = 1 - S(t), the blended gap is the same whichever of the
two triangles the slave is paired with: it does not jump when the pairing passes from one to
the other within the band (a node near a vertex, within two bands, only nearly so). A slave
is paired with a triangle while its projection lies within the band outside a blended edge,
which also covers the dead zone over a crease (the projection outside both triangles).
The Hessian of the blended gap (the pair then has the slave, T's vertices and the opposite
vertex of each neighbour) is exact for the kept normals.

Release band at the master's free boundary (`edge_release`). Without it a slave whose
projection leaves the master surface over a free (boundary) edge loses its pair at once: its
force jumps from its full value to zero, and under a frozen status the triangle's plane is
extended without bound beyond the edge, pushing (or, frozen, pulling) a node that has slid off.
With a band of width b = edge_release |e| outside each free edge e (length |e|), the pair's
potential is weighted, E = w(d) <lambda - eps A_s g>^2 / (2 eps A_s), where d = (x_s - x_e) . m
is the in-plane distance of the slave from the edge line (m the unit in-plane normal of the
edge pointing into the triangle, taken at the search and kept while the status is frozen,
like the pairing) and w = S(1 + d / b) with the quintic smoothstep S(t) = 6t^5 - 15t^4 + 10t^3
clipped to [0, 1]: w = 1 on the surface, 0 beyond the band, C2 in between. The force
-dE/dx = w p dg/dx - (p^2 / 2 eps A_s) dw/dx then fades continuously to zero as the node
slides off (the second part pushes it off the edge, the reaction of a rounded edge), and the
tangent is the exact second derivative of E for the kept m. Inside the master surface
(d >= 0) nothing changes. A node in the band counts for the augmentation and the status in
proportion to w (its penetration w |g|, its force w p).

Both are off by default (0: the gap, forces and tangent are those of the plain node-to-segment
pairs, bit for bit).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from solver.contact._uzawa import AugmentedLagrangian, ContactTerm, deepest_penetration
from solver.contact._geometry import (facet_normals, nodal_areas, plane_gap, psd_projection,
                                      triangulate)

__all__ = ["SurfaceContact"]


def _smoothstep(t):
    """Quintic smoothstep S(t) = 6t^5 - 15t^4 + 10t^3 on [0, 1] (0 below, 1 above) with its
    first and second derivatives: C2 at both ends."""
    t = np.clip(t, 0.0, 1.0)
    return (t ** 3 * (10.0 - 15.0 * t + 6.0 * t * t), 30.0 * t * t * (1.0 - t) ** 2,
            60.0 * t * (1.0 - t) * (1.0 - 2.0 * t))


def _free_edges(tri):
    """(k, 3) bool: edge j of each triangle (the edge opposite its vertex j) belongs to that
    triangle only (a free boundary edge of the surface)."""
    e = np.concatenate([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]])
    _, inv, cnt = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True,
                            return_counts=True)
    return (cnt[inv.ravel()] == 1).reshape(3, len(tri)).T


def _neighbours(tri):
    """Per triangle and edge j (opposite vertex j): the triangle across it (-1 at a free or
    non-manifold edge), the slots of that triangle's three vertices in the pair layout
    (1 + i for the shared vertex i of the triangle, 4 + j for the opposite one), and the
    opposite vertex's node id (-1 where there is no neighbour)."""
    k = len(tri)
    e = np.concatenate([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]])
    owner = np.tile(np.arange(k), 3)
    side = np.repeat(np.arange(3), k)
    _, inv, cnt = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True,
                            return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    two = cnt[inv[order]] == 2
    first = order[two][0::2]
    second = order[two][1::2]
    neighbour = np.full((k, 3), -1, dtype=np.int64)
    neighbour[owner[first], side[first]] = owner[second]
    neighbour[owner[second], side[second]] = owner[first]
    slots = np.zeros((k, 3, 3), dtype=np.int64)
    opposite = np.full((k, 3), -1, dtype=np.int64)
    for j in range(3):
        has = neighbour[:, j] >= 0
        n = tri[neighbour[has, j]]                                  # (h, 3)
        own = tri[has]
        match = n[:, :, None] == own[:, None, :]                    # (h, 3 of n, 3 of own)
        shared = match.any(axis=2)
        sl = np.where(shared, 1 + match.argmax(axis=2), 4 + j)
        slots[has, j] = sl
        opposite[has, j] = n[~shared]
    return neighbour, slots, opposite


def _edge_frames(pt):
    """For triangles pt (k, 3, 3): per edge j (opposite vertex j), the unit in-plane normal
    pointing into the triangle (k, 3, 3), the altitude from vertex j (k, 3) and the edge
    length (k, 3)."""
    p1 = pt[:, [1, 2, 0]]
    p2 = pt[:, [2, 0, 1]]
    e = p2 - p1
    v = pt - p1
    ee = np.maximum(np.einsum("kji,kji->kj", e, e), 1e-300)
    m = v - (np.einsum("kji,kji->kj", v, e) / ee)[:, :, None] * e
    alt = np.linalg.norm(m, axis=2)
    return m / np.maximum(alt, 1e-300)[:, :, None], alt, np.sqrt(ee)


def _near_triangles(tri_points, points, radius):
    """Candidate (triangle, point) pairs: every triangle (k, 3, 3) whose centroid lies within
    `radius` plus the triangles' largest centroid-to-vertex distance of a point (one KD-tree
    query on the centroids). Returns (triangle ids, point ids, that largest distance rmax)."""
    cen = tri_points.mean(axis=1)
    rmax = float(np.linalg.norm(tri_points - cen[:, None], axis=2).max(initial=0.0))
    lists = cKDTree(cen).query_ball_point(points, radius + rmax)
    counts = np.fromiter((len(l) for l in lists), dtype=np.int64, count=len(lists))
    cand = np.fromiter((i for l in lists for i in l), dtype=np.int64, count=counts.sum())
    return cand, np.repeat(np.arange(len(points)), counts), rmax


class _Pass:
    """One slave node set against one master triangle set."""

    def __init__(self, nodes, slave_facets, master_facets, hysteresis, release=0.0,
                 blend=0.0):
        n = len(nodes)
        self.hysteresis = float(hysteresis)
        areas = nodal_areas(nodes, slave_facets, n)
        self.slaves = np.unique(np.asarray(slave_facets, dtype=np.int64))
        self.areas = areas[self.slaves]
        self.slave_tri = triangulate(slave_facets)
        self.master = triangulate(master_facets)
        # release band outside the master's free edges (module docstring; 0: none)
        self.release = float(release)
        self.free = (_free_edges(self.master) if self.release > 0
                     else np.zeros(self.master.shape, dtype=bool))
        # crease blending across interior edges (module docstring; 0: none): the neighbour
        # across each edge, the slots of its vertices in the pair's node layout (slave,
        # triangle's vertices, the neighbours' opposite vertices) and its opposite vertex
        self.blend = float(blend)
        self.layout = 7 if self.blend > 0 else 4
        if self.blend > 0:
            self.neighbour, self.nb_slots, self.nb_opposite = _neighbours(self.master)
        # per slave, the in-plane edge normals (3, 3) and band widths (3,) of its paired
        # triangle, taken at the search and kept while the status is frozen (width 0: no band)
        self.edge_normal = np.zeros((len(self.slaves), 3, 3))
        self.band = np.zeros((len(self.slaves), 3))
        self.blend_band = np.zeros((len(self.slaves), 3))
        self.multipliers = np.zeros(len(self.slaves))
        self.offset = np.zeros(len(self.slaves))            # initial penetration ignored (mm)
        self.previous = np.full(len(self.slaves), -1)       # paired triangle, last evaluation
        self.active = np.zeros(len(self.slaves), dtype=bool)  # in contact, last evaluation
        # slave -> its own triangles, to compute the slave node normals
        self.slave_pos = np.full(n, -1)
        self.slave_pos[self.slaves] = np.arange(len(self.slaves))

    def slave_normals(self, x):
        fn = facet_normals(x, self.slave_tri)
        p = x[self.slave_tri]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        nn = np.zeros((len(x), 3))
        np.add.at(nn, self.slave_tri.ravel(), np.repeat(fn * area[:, None], 3, axis=0))
        nn = nn[self.slaves]
        return nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300)

    def edge_normals(self, x, t, pt):
        """Per pair triangle t (vertices pt) and edge j: the unit normal of the plane through
        the edge in which d_j is measured (k, 3, 3), and the edge length (k, 3). At an edge
        with crease blending: the normal of the bisector plane of the two triangles,
        (m_T - m_N) / |m_T - m_N| with m_T, m_N their in-plane normals pointing into each, so
        that d measured from either triangle is the same up to sign (the blend is the same
        from both sides); elsewhere T's own in-plane normal m_T."""
        m, _, elen = _edge_frames(pt)
        if self.blend > 0:
            opp = self.nb_opposite[t]
            for j in range(3):
                has = opp[:, j] >= 0
                if not np.any(has):
                    continue
                a = pt[has][:, (j + 1) % 3]
                e = pt[has][:, (j + 2) % 3] - a
                e /= np.linalg.norm(e, axis=1, keepdims=True)
                v = x[opp[has, j]] - a
                mn = v - np.einsum("ki,ki->k", v, e)[:, None] * e
                mn /= np.maximum(np.linalg.norm(mn, axis=1, keepdims=True), 1e-300)
                mu = m[has, j] - mn
                m[has, j] = mu / np.maximum(np.linalg.norm(mu, axis=1, keepdims=True), 1e-300)
        return m, elen

    def pairs(self, x, radius, max_depth, hessian=True, inside_tol=1e-3, cos_opposed=-0.2):
        """Contact pairs: (slave positions (k,), master triangle (k,), g, grad, hess, dofs,
        w, dw, d2w)."""
        tri = self.master
        p = x[tri]
        xs = x[self.slaves]
        cand, owner, rmax = _near_triangles(p, xs, radius)
        # a node is never in contact with a triangle it belongs to
        own = np.any(tri[cand] == self.slaves[owner][:, None], axis=1)
        cand, owner = cand[~own], owner[~own]
        if len(cand) == 0:
            return self.evaluate_pairs(x, np.zeros(0, dtype=np.int64),
                                       np.zeros(0, dtype=np.int64), hessian)
        pc = p[cand]
        g, _, _, nm, bc = plane_gap(xs[owner], pc[:, 0], pc[:, 1], pc[:, 2], hessian=False)
        ns = self.slave_normals(x)[owner]
        # barycentric coordinate of the projection per vertex j: 0 on the edge opposite j
        lam = np.stack([1.0 - bc.sum(axis=1), bc[:, 0], bc[:, 1]], axis=1)
        free = self.free[cand]
        blended = (self.neighbour[cand] >= 0) if self.blend > 0 else np.zeros_like(free)
        if np.any(free) or np.any(blended):
            # a projection beyond a free edge is kept within the release band, one beyond a
            # blended interior edge within the blend band (where the blended gap is defined;
            # this also covers the dead zone over a crease, where the projection falls outside
            # both triangles)
            m, elen = self.edge_normals(x, cand, pc)
            d = np.einsum("kji,kji->kj", xs[owner][:, None, :] - pc[:, [1, 2, 0]], m)
            width = np.where(free, self.release, self.blend) * elen
            band_ok = np.all(~(free | blended) | (d >= -width), axis=1)
        else:
            band_ok = np.ones(len(cand), dtype=bool)
        strict = lam.min(axis=1)
        # a slave keeps the triangle of its last search while its projection stays within
        # the hysteresis band outside it (`pair_hysteresis`, barycentric): a node over the
        # crease between two master triangles then does not flip from one plane to the other
        # at each Newton iteration (free edges: the release band instead)
        minbc = np.where(free | blended, 1.0, lam).min(axis=1)
        kept = (cand == self.previous[owner]) & (minbc >= -max(self.hysteresis, 1e-12)) \
            & band_ok
        inside = ((minbc >= -inside_tol) | kept) & band_ok
        ok = inside & (np.einsum("ij,ij->i", ns, nm) < cos_opposed) \
            & (g > -max_depth) & (g < radius)
        cand, owner, g, kept, strict = cand[ok], owner[ok], g[ok], kept[ok], strict[ok]
        # nearest plane per slave, preferring projections strictly inside a triangle over
        # those inside only within the tolerance; the kept triangle is preferred unless
        # another plane is much nearer
        key = np.abs(g) + np.where((strict < 0.0) & ~kept, 2.0 * (rmax + 1.0), 0.0)
        key = np.where(kept, key - 0.05 * rmax, key)
        order = np.lexsort((key, owner))
        first = np.ones(len(order), dtype=bool)
        first[1:] = owner[order][1:] != owner[order][:-1]
        best = order[first]
        s, t = owner[best], cand[best]
        self.previous[:] = -1
        self.previous[s] = t
        return self.evaluate_pairs(x, s, t, hessian, refresh=True)

    def frozen_pairs(self, x, radius, max_depth, hessian=True):
        """The pairs of the last search, kept whatever the projection (status freezing)."""
        s = np.nonzero(self.previous >= 0)[0]
        out = self.evaluate_pairs(x, s, self.previous[s], hessian)
        keep = (out[2] > -max_depth) & (out[2] < radius)
        return tuple(None if a is None else a[keep] for a in out)

    def evaluate_pairs(self, x, s, t, hessian=True, refresh=False):
        """Gap g (crease-blended, module docstring), its gradient and Hessian in the pair's
        coordinates, the dofs, and the release weight w with its gradient and Hessian (None
        without a release band) of the pairs (slave positions s, master triangles t) at x. The pair's nodes are the slave,
        the triangle's three vertices and, with crease blending, the vertex opposite each
        edge in the neighbouring triangle (the slave again where there is none, with zero
        entries). refresh: take the edge normals of the bands from x (a search) instead of
        the kept ones."""
        k, L = len(s), self.layout
        tri = self.master[t]
        nodes = np.empty((k, L), dtype=np.int64)
        nodes[:, 0] = self.slaves[s]
        nodes[:, 1:4] = tri
        if L == 7:
            opp = self.nb_opposite[t]
            nodes[:, 4:] = np.where(opp >= 0, opp, self.slaves[s][:, None])
        dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(k, 3 * L)
        pt = x[tri]
        xs = x[self.slaves[s]]
        g, G, H, _, _ = plane_gap(xs, pt[:, 0], pt[:, 1], pt[:, 2], hessian=hessian)
        if H is None:
            H = np.zeros((k, 0, 0))
        if L > 4:                   # the neighbours' opposite vertices: zero entries so far
            G = np.concatenate([G, np.zeros((k, 3 * L - 12))], axis=1)
            if hessian:
                H = np.pad(H, ((0, 0), (0, 3 * L - 12), (0, 3 * L - 12)))
        # the release weight and its derivatives: w = 1 (dw, d2w None) without a release band
        w, dw, d2w = np.ones(k), None, None
        if k and (self.release > 0 or self.blend > 0):
            if refresh:
                m, elen = self.edge_normals(x, t, pt)
                self.edge_normal[s] = m
                self.band[s] = np.where(self.free[t], self.release * elen, 0.0)
                if self.blend > 0:
                    self.blend_band[s] = np.where(self.neighbour[t] >= 0, self.blend * elen,
                                                  0.0)
            m = self.edge_normal[s]
            # d_j = (x_s - x_{j+1}) . m_j, linear for the kept m_j: gradient +m_j at the slave,
            # -m_j at vertex j+1
            d = np.einsum("kji,kji->kj", xs[:, None, :] - pt[:, [1, 2, 0]], m)
            D = np.zeros((k, 3, L, 3))
            D[:, :, 0, :] = m
            for j in range(3):
                D[:, j, 1 + (j + 1) % 3, :] -= m[:, j]
            D = D.reshape(k, 3, 3 * L)
            if self.blend > 0:
                g, G, H = self._blend(x, s, t, xs, g, G, H, d, D, hessian)
            if self.release > 0:
                w, dw, d2w = self._release_weight(s, d, D, hessian)
        g = g + self.offset[s]
        return s, t, g, G, H, dofs, w, dw, d2w

    def _blend(self, x, s, t, xs, g, G, H, d, D, hessian):
        """g_b = g_T + sum_j beta_j (g_j - g_T), g_j the gap to the plane of the neighbour
        across edge j, beta_j = 1 - S((d_j + c_j) / (2 c_j)) (1/2 on the edge, 0 at the
        distance c_j inside T), with its exact gradient and Hessian for the kept m_j."""
        gb, Gb, Hb = g.copy(), G.copy(), H.copy()
        cb = self.blend_band[s]
        L3 = G.shape[1]
        for j in range(3):
            rows = np.nonzero((cb[:, j] > 0) & (d[:, j] < cb[:, j]))[0]
            if not len(rows):
                continue
            nb = self.neighbour[t[rows], j]
            q = x[self.master[nb]]
            gj, grj, hsj, _, _ = plane_gap(xs[rows], q[:, 0], q[:, 1], q[:, 2], hessian=hessian)
            slots = self.nb_slots[t[rows], j]                           # (r, 3)
            idx = np.concatenate([np.zeros((len(rows), 1), dtype=np.int64), slots], axis=1)
            idx = (3 * idx[:, :, None] + np.arange(3)).reshape(len(rows), 12)
            Gj = np.zeros((len(rows), L3))
            np.put_along_axis(Gj, idx, grj, axis=1)
            c = cb[rows, j]
            S, S1, S2 = _smoothstep((d[rows, j] + c) / (2.0 * c))
            beta = 1.0 - S
            db = -(S1 / (2.0 * c))[:, None] * D[rows, j]               # (r, L3)
            dg = gj - g[rows]
            dG = Gj - G[rows]
            gb[rows] += beta * dg
            Gb[rows] += beta[:, None] * dG + dg[:, None] * db
            if hessian:
                Hj = np.zeros((len(rows), L3, L3))
                rr = np.arange(len(rows))[:, None, None]
                Hj[rr, idx[:, :, None], idx[:, None, :]] = hsj
                Dj = D[rows, j]
                Hb[rows] += (beta[:, None, None] * (Hj - H[rows])
                             + db[:, :, None] * dG[:, None, :] + dG[:, :, None] * db[:, None, :]
                             - (dg * S2 / (4.0 * c * c))[:, None, None]
                             * Dj[:, :, None] * Dj[:, None, :])
        return gb, Gb, Hb

    def _release_weight(self, s, d, D, hessian):
        """w = prod_j S(1 + d_j / b_j) over the free edges j of each pair's triangle
        (module docstring), with its exact gradient and Hessian for the kept normals m_j
        (d_j is then linear in the coordinates)."""
        k, L3 = D.shape[0], D.shape[2]
        w = np.ones(k)
        dw = np.zeros((k, L3))
        d2w = np.zeros((k, L3, L3) if hessian else (k, 0, 0))
        band = self.band[s]
        idx = np.nonzero(np.any(band > 0, axis=1))[0]
        if not len(idx):
            return w, dw, d2w
        b, dd, Dq = band[idx], d[idx], D[idx]
        has = b > 0
        bs = np.where(has, b, 1.0)
        S, S1, S2 = _smoothstep(1.0 + dd / bs)
        S = np.where(has, S, 1.0)
        S1 = np.where(has, S1 / bs, 0.0)
        S2 = np.where(has, S2 / bs ** 2, 0.0)
        # products of the other factors
        others = np.stack([S[:, 1] * S[:, 2], S[:, 2] * S[:, 0], S[:, 0] * S[:, 1]], axis=1)
        w[idx] = S.prod(axis=1)
        dw[idx] = np.einsum("qj,qjd->qd", S1 * others, Dq)
        if hessian:
            c = S1[:, :, None] * S1[:, None, :] * S[:, [[0, 2, 1], [2, 1, 0], [1, 0, 2]]]
            diag = np.arange(3)
            c[:, diag, diag] = S2 * others
            d2w[idx] = np.einsum("qjl,qjd,qle->qde", c, Dq, Dq)
        return w, dw, d2w


class SurfaceContact(ContactTerm):
    """Frictionless contact between two deformable facet sets (or a set with itself).

    nodes: (n, 3) reference coordinates of the mesh. surface_a, surface_b: (k, 3|4) facets,
    outward normals (right-hand rule). settings: `AugmentedLagrangian` (penalty, tolerance,
    search radius, ...; any of its fields may be given as a keyword argument instead: pairs
    are kept for gaps in (-max_depth, search_radius)). two_pass: both sets act as slaves in
    turn (symmetric; otherwise a's nodes against b's facets only).
    ignore_initial_penetration: surfaces that already overlap in the reference configuration
    (e.g. surfaces of a registered mesh) are not pushed apart: each slave node's initial
    penetration is added to its gap as a fixed offset (LS-DYNA's "ignore initial
    penetrations"), so contact acts only against further penetration; the largest offset is
    `initial_penetration` (mm).
    pair_hysteresis: a slave keeps the master triangle of its last search while its projection
    lies within this barycentric distance outside it (the triangle's plane is extended that
    far), instead of switching to a neighbour as soon as it crosses the shared edge: a node
    over a crease between two triangles otherwise flips between their planes at each Newton
    iteration while the status is searched (0: no hysteresis).
    edge_release: width of the release band outside the master surface's free edges, as a
    fraction of the edge's length (module docstring): a slave sliding off the edge of the
    master surface is released smoothly over the band instead of losing its force at once
    (0: no band, the force drops to zero as the projection leaves the surface).
    crease_blend: half-width of the band about each interior edge of the master surface, as
    a fraction of the edge's length, over which the gap blends the planes of the two
    triangles (module docstring): the gap, force and tangent are then continuous as a slave
    crosses from one triangle to the next (0: the gap jumps from one plane to the other).
    """

    static_state = ("_reference", "settings")

    def __init__(self, nodes, surface_a, surface_b, *, settings: AugmentedLagrangian | None = None,
                 two_pass: bool = True, ignore_initial_penetration: bool = True,
                 pair_hysteresis: float = 0.0, edge_release: float = 0.0,
                 crease_blend: float = 0.0, **contact):
        nodes = np.asarray(nodes, dtype=float)
        self._configure(settings, contact)
        if not 0.0 <= pair_hysteresis < 0.5:
            raise ValueError(f"pair_hysteresis must be in [0, 0.5), got {pair_hysteresis}")
        if not 0.0 <= edge_release <= 2.0:
            raise ValueError(f"edge_release must be in [0, 2], got {edge_release}")
        if not 0.0 <= crease_blend <= 0.5:
            raise ValueError(f"crease_blend must be in [0, 0.5], got {crease_blend}")
        self.n_nodes = len(nodes)
        self._reference = nodes
        self.passes = [_Pass(nodes, surface_a, surface_b, pair_hysteresis, edge_release,
                             crease_blend)]
        if two_pass:
            self.passes.append(_Pass(nodes, surface_b, surface_a, pair_hysteresis, edge_release,
                                     crease_blend))
        self._resolve_load, self._resolved = None, []
        self._convex = False
        self.initial_penetration = 0.0
        if ignore_initial_penetration:
            for ps in self.passes:
                s, _, g, *_ = ps.pairs(nodes, self.search_radius, self.max_depth, hessian=False)
                ps.offset[s] = np.maximum(-g, 0.0)
                ps.previous[:] = -1
                self.initial_penetration = max(self.initial_penetration,
                                               float(ps.offset.max(initial=0.0)))

    def convexify(self, on: bool) -> bool:
        """With on=True the curvature part -p d2g/dx2 of each pair's tangent (the rotation
        of the master plane, indefinite in the 12 coordinates of slave and master nodes) is
        projected onto the positive semi-definite matrices (negative eigenvalues clipped to
        zero) until convexify(False); the forces are unchanged."""
        self._convex = bool(on)
        return True

    def coupling_pairs(self, reach: float | None = None) -> np.ndarray:
        """(k, 2) node pairs this term may couple: each slave node with the nodes of the
        master triangles within `reach` of it in the reference configuration (default: twice
        the search radius plus the largest depth), so that the global sparsity pattern can be
        reserved before the solve (`solver.assembly._extended.ExtendedPattern`)."""
        reach = 2.0 * self.search_radius + self.max_depth if reach is None else float(reach)
        out = []
        for ps in self.passes:
            tri, owner, _ = _near_triangles(self._reference[ps.master],
                                            self._reference[ps.slaves], reach)
            out.append(np.stack([np.repeat(ps.slaves[owner], 3), ps.master[tri].ravel()], axis=1))
            if ps.layout == 7:
                # crease blending couples the slave and the triangle's vertices with the
                # neighbours' opposite vertices
                opp = ps.nb_opposite[tri]
                has = opp >= 0
                out.append(np.stack([np.repeat(ps.slaves[owner], 3)[has.ravel()],
                                     opp[has]], axis=1))
                opp = ps.nb_opposite
                for i in range(3):
                    has = opp >= 0
                    out.append(np.stack([np.repeat(ps.master[:, i], 3)[has.ravel()],
                                         opp[has]], axis=1))
        pairs = np.vstack(out) if out else np.zeros((0, 2), dtype=np.int64)
        return np.unique(np.sort(pairs, axis=1), axis=0)

    def _evaluate(self, x, hessian=True, frozen=False):
        out = []
        for ps in self.passes:
            radius = self.search_radius + float(
                np.max(ps.multipliers / (self.penalty * ps.areas), initial=0.0))
            search = ps.frozen_pairs if frozen else ps.pairs
            s, t, g, grad, hess, dofs, w, dw, d2w = search(np.asarray(x, dtype=float), radius,
                                               self.max_depth, hessian)
            eps = self.penalty * ps.areas[s]
            lam = ps.multipliers[s]
            if frozen:
                # status freezing: the active set of the last search is kept as it is
                p = np.where(ps.active[s], lam - eps * g, 0.0)
            else:
                p = np.maximum(lam - eps * g, 0.0)
                ps.active[:] = False
                ps.active[s] = p > 0
            out.append((ps, s, g, grad, hess, dofs, eps, lam, p, w, dw, d2w))
        return out

    def assemble(self, x, load):
        f = np.zeros(3 * self.n_nodes)
        rows, cols, vals = [], [], []
        frozen = self._frozen(load)
        for ps, s, g, grad, hess, dofs, eps, lam, p, w, dw, d2w in self._evaluate(
                x, frozen=frozen):
            # frozen: every node of the frozen active set acts, pulling too (p < 0), so that
            # the problem Newton sees is smooth; `end_step` corrects the status afterwards
            a = ps.active[s] if frozen else p > 0
            a &= w > 0
            if not np.any(a):
                continue
            gr, hs, dd, pa, wa = grad[a], hess[a], dofs[a], p[a], w[a]
            # E = w psi(g), psi = p^2 / (2 eps): dE = -w p dg + psi dw
            force = -(wa * pa)[:, None] * gr
            curvature = -(wa * pa)[:, None, None] * hs
            if dw is not None:
                psi = pa * pa / (2.0 * eps[a])
                dwa = dw[a]
                force = force + psi[:, None] * dwa
                curvature = curvature - pa[:, None, None] * (
                    gr[:, :, None] * dwa[:, None, :] + dwa[:, :, None] * gr[:, None, :]) \
                    + psi[:, None, None] * d2w[a]
            np.add.at(f, dd.ravel(), force.ravel())
            if self._convex:
                curvature = psd_projection(curvature)
            Ke = (wa * eps[a])[:, None, None] * gr[:, :, None] * gr[:, None, :] + curvature
            nd = dd.shape[1]
            rows.append(np.repeat(dd, nd, axis=1).ravel())
            cols.append(np.tile(dd, (1, nd)).ravel())
            vals.append(Ke.ravel())
        n = 3 * self.n_nodes
        if rows:
            K = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                      np.concatenate(cols))), shape=(n, n))
        else:
            K = sp.coo_matrix((n, n))
        return f, K


    def energy(self, x, load) -> float:
        e = 0.0
        frozen = self._is_frozen(load)
        for ps, s, g, grad, hess, dofs, eps, lam, p, w, dw, d2w in self._evaluate(
                x, False, frozen):
            e += float(np.sum((w * p * p - lam * lam) / (2.0 * eps)))
            # multipliers of slaves that lost their pairing contribute -lambda^2 / (2 eps)
            lost = np.setdiff1d(np.nonzero(ps.multipliers)[0], s)
            e -= float(np.sum(ps.multipliers[lost] ** 2
                              / (2.0 * self.penalty * ps.areas[lost])))
        return e

    def penetration(self, x, load: float = 1.0) -> float:
        """Deepest penetration (mm, >= 0) over both passes at coordinates x (a node in the
        release band in proportion to its weight w)."""
        return deepest_penetration(ev[2] * ev[9] for ev in self._evaluate(x, hessian=False))

    def augmentation_due(self, x, load) -> bool:
        """Whether the current (not converged) iterate at `load` penetrates so deep that the
        step will be augmented (`UzawaLoop.augmentation_due`); the status (pairing, active
        set) of the solve is left as it is."""
        saved = [(ps.previous.copy(), ps.active.copy(), ps.edge_normal.copy(),
                  ps.band.copy(), ps.blend_band.copy()) for ps in self.passes]
        try:
            err = self._active_penetration(self._evaluate(x, hessian=False,
                                                          frozen=self._is_frozen(load)))
        finally:
            for ps, (prev, act, en, band, bb) in zip(self.passes, saved):
                ps.previous, ps.active, ps.edge_normal, ps.band = prev, act, en, band
                ps.blend_band = bb
        return self.uzawa.augmentation_due(load, self.augmented, err, self.tolerance)

    def end_step(self, x, load) -> bool:
        multipliers = self._multiplier_values()
        before = [ps.previous.copy() for ps in self.passes]
        before_active = [ps.active.copy() for ps in self.passes]
        was_frozen = self._is_frozen(load)
        frozen_q = []
        if was_frozen:
            # the contact forces of the frozen solve in gap units, (lambda - eps g) / eps, on
            # the frozen pairing and active set
            for ps, old, olda in zip(self.passes, before, before_active):
                q = np.zeros(len(ps.slaves))
                s = np.nonzero((old >= 0) & olda)[0]
                if len(s):
                    ev = ps.evaluate_pairs(x, s, old[s], hessian=False)
                    q[s] = ev[6] * (ps.multipliers[s] / (self.penalty * ps.areas[s]) - ev[2])
                frozen_q.append(q)
        if load != self._resolve_load:
            self._resolve_load = load
            self._resolved = [np.zeros(len(ps.slaves), dtype=bool) for ps in self.passes]
        self._unfreeze()
        ev = self._evaluate(x, hessian=False)
        changed = False
        for (ps, s, g, grad, hess, dofs, eps, lam, p, w, *_), q_old, done in zip(
                ev, frozen_q, self._resolved):
            # A frozen solve whose contact forces differ from those of a fresh search at the
            # converged state (a status flip, or a node now over another triangle whose plane
            # is elsewhere) by more than the tolerance, in gap units, is solved again. Grazing
            # nodes (within the tolerance of the switch) do not count, and each node asks for
            # this at most once per load step: a node over a convex crease between two
            # triangles has no consistent pairing (the dead zone of node-to-segment contact,
            # Wriggers 2006 sec. 9.1), it would alternate between them for ever; its
            # penetration still counts below (augmentation)
            q_new = np.zeros(len(ps.slaves))
            q_new[s] = w * p / eps
            off = (np.abs(q_new - q_old) > self.tolerance) & ~done
            done |= off
            changed |= bool(np.any(off))
        err = self._active_penetration(ev)
        self.last_error = err
        again = self.uzawa.another_solve(load, changed, self.augmented, err, self.tolerance)
        if again:
            self._freeze_resolve(load)
        if self.uzawa.update:                               # Uzawa update
            for ps, s, g, grad, hess, dofs, eps, lam, p, *_ in ev:
                new = np.zeros_like(ps.multipliers)
                new[s] = p
                ps.multipliers = new
        self._note_carried(multipliers, load)
        return again

    def _multiplier_fields(self) -> list:
        return [(ps, "multipliers") for ps in self.passes]

    @staticmethod
    def _active_penetration(ev) -> float:
        """Deepest penetration (mm, >= 0) of the nodes in contact (pressing, and active in
        the status of the evaluation `ev`; a node in the release band in proportion to its
        weight)."""
        err = 0.0
        for ps, s, g, grad, hess, dofs, eps, lam, p, w, *_ in ev:
            act = (p > 0) & ps.active[s] & (w > 0)
            if np.any(act):
                err = max(err, float(-(w * g)[act].min()))
        return err

    def _scale_multipliers(self, factor: float) -> None:
        for ps in self.passes:
            ps.multipliers = ps.multipliers * factor

    def contact_forces(self, x, load: float = 1.0) -> np.ndarray:
        """Contact forces (n, 3) acting on the nodes (mN) at x: minus the residual term."""
        f = np.zeros(3 * self.n_nodes)
        for ps, s, g, grad, hess, dofs, eps, lam, p, w, dw, _ in self._evaluate(
                x, hessian=False):
            a = p > 0
            force = (w[a] * p[a])[:, None] * grad[a]
            if dw is not None:
                force = force - (p[a] ** 2 / (2.0 * eps[a]))[:, None] * dw[a]
            np.add.at(f, dofs[a].ravel(), force.ravel())
        return f.reshape(-1, 3)

    def contact_pressure(self, x, load: float = 1.0):
        """Per pass: (slave node ids, pressure kPa) at coordinates x."""
        res = []
        for ps, s, g, grad, hess, dofs, eps, lam, p, w, *_ in self._evaluate(x, hessian=False):
            pr = np.zeros(len(ps.slaves))
            pr[s] = w * p / ps.areas[s]
            res.append((ps.slaves, pr))
        return res
