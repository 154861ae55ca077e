"""Node-to-rigid-surface contact and sliding (penalty / augmented Lagrangian `Term`s).

Nodes of a deformable body (the slave facets' nodes) against a rigid triangulated surface that
moves with a prescribed rigid motion T(load) = [R | t] during the solve (a rigid obstacle carried
by a prescribed part, a rigid surface under sliding tissue, a press plate). The surface's search structure is
built once in its own frame: a node x is pulled back, y = R^T (x - t), its closest point c on
the fixed surface and the pseudo-normal sign give the signed gap g(x) = s |y - c| (outward
positive), with gradient dg/dx = R n and Hessian (I - n n) / g off the face interiors (zero
inside a face). With the node's penalty eps_i = eps * A_i (eps in kPa/mm, A_i the node's
tributary area, so that eps * g is a pressure) and multiplier lambda_i (mN) the potential is

    E_i = ( <lambda_i - eps_i g>^2 - lambda_i^2 ) / (2 eps_i)      unilateral contact,
    E_i = ( (lambda_i - eps_i g)^2 - lambda_i^2 ) / (2 eps_i)      bilateral (sliding),

the contact force on the node p_i n with p_i = <lambda_i - eps_i g> (Macaulay bracket for
contact), the tangent eps_i n (x) n - p_i d2g/dx2 (Wriggers 2006, ch. 5-6; Laursen 2002). After a
converged step `end_step` applies the Uzawa update lambda_i <- p_i (Simo & Laursen 1992) until
the largest penetration (contact) or gap (sliding) is below `tolerance`. After `freeze_after`
evaluations at one load the active set is frozen (status freezing), and `end_step` asks for
another solve when the converged state has a different status; such a re-solve re-decides the
status at its first two evaluations only (`freeze_resolves`).
With `smooth=True` the faceted gap is replaced by a C2 tricubic-spline signed distance sampled
once in the surface's frame (`solver.contact._sdf`), with its exact gradient and Hessian in the
tangent eps_i n (x) n - p_i d2g/dx2. With `tangent="projected"` the curvature part -p_i d2g/dx2
enters the tangent with its negative eigenvalues clipped to zero (projected Newton, Teran et al.
2005): pressed onto a convex obstacle (a sharp edge) it is a negative tangential
stiffness that can make the tangent indefinite when the pressure is large against the tissue's
stiffness, and Newton then wanders. It is projected while the contact status is free (the
first `freeze_after` evaluations of a solve, far from the solution); once the status is frozen
the exact tangent gives back quadratic convergence. The residual is always exact, so the
solution is the same. Frictionless; optional `stick=True` (experimental, tests only) adds a
tangential penalty that ties a node to the surface point where it first touched (sticking, the
infinite-friction limit).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from solver.contact._sdf import SignedDistanceGrid
from solver.contact._uzawa import AugmentedLagrangian, ContactTerm
from solver.contact._geometry import (EDGE_AB, EDGE_BC, EDGE_CA, FACE, TriangleSurface,
                                      closest_point_on_triangles, nodal_areas, psd_projection)

__all__ = ["RigidSurfaceContact", "ramped_rigid_motion"]


def ramped_rigid_motion(T, load: float) -> np.ndarray:
    """Rigid motion at a load fraction: rotation vector and translation scaled by `load`."""
    T = np.asarray(T, dtype=float)
    rv = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(load * rv).as_matrix()
    out[:3, 3] = load * T[:3, 3]
    return out


class RigidSurfaceContact(ContactTerm):
    """Contact (or bilateral sliding) of slave nodes against a moving rigid surface.

    nodes: (n, 3) reference coordinates of the whole mesh (for the slave areas and the dof
    count). slave_facets: (k, 3|4) facets of the deformable body whose nodes are tested
    (their tributary areas scale the penalty), or `slave_nodes` with `slave_areas`.
    vertices, faces: the rigid surface in its reference position, outward normals.
    motion: a 4x4 rigid matrix reached at load 1 (ramped with `ramped_rigid_motion`), a
    callable load -> 4x4, or None (fixed). settings: `AugmentedLagrangian` (penalty eps in
    kPa/mm, tolerance: largest penetration or sliding gap accepted at convergence, mm; nodes
    farther than search_radius from the surface are ignored, contact is detected up to
    max_depth inside it, for open surfaces; ...), any field of which may be given as a keyword
    argument instead. bilateral: sliding constraint (the nodes stay on the surface, free
    tangentially) instead of contact.
    smooth: use the C2 spline signed distance of `solver.contact._sdf.SignedDistanceGrid`
    (grid step `grid_spacing`) instead of the faceted surface: no gradient jumps across facet
    edges, so nodes pressed onto convex edges do not make Newton cycle (the facets' corners
    are rounded over about one grid step).
    """

    DEFAULTS = AugmentedLagrangian(search_radius=5.0, max_depth=np.inf)
    static_state = ("surface", "grid", "settings")

    def __init__(self, nodes, vertices, faces, *, settings: AugmentedLagrangian | None = None,
                 slave_facets=None, slave_nodes=None, slave_areas=None, motion=None,
                 bilateral: bool = False, stick: bool = False, smooth: bool = False,
                 grid_spacing: float | None = None, tangent: str = "exact", **contact):
        nodes = np.asarray(nodes, dtype=float)
        self._configure(settings, contact)
        search_radius, max_depth = self.search_radius, self.max_depth
        if tangent not in ("exact", "projected"):
            raise ValueError(f"tangent must be 'exact' or 'projected', got {tangent!r}")
        self.tangent = tangent
        self.n_nodes = len(nodes)
        if slave_facets is not None:
            slave_facets = np.asarray(slave_facets, dtype=np.int64)
            areas = nodal_areas(nodes, slave_facets, self.n_nodes)
            slave_nodes = np.unique(slave_facets)
            slave_areas = areas[slave_nodes]
        elif slave_nodes is None:
            raise ValueError("give slave_facets or slave_nodes")
        self.slaves = np.asarray(slave_nodes, dtype=np.int64)
        if slave_areas is None:
            slave_areas = np.ones(len(self.slaves))
        self.areas = np.asarray(slave_areas, dtype=float)
        if len(self.areas) != len(self.slaves) or np.any(self.areas <= 0):
            raise ValueError("slave_areas must be positive, one per slave node")
        self.surface = TriangleSurface(vertices, faces)
        self.grid = None
        if smooth:
            # exact distances wherever a gap can be used: search radius outside, depth inside
            depth = max_depth if np.isfinite(max_depth) else search_radius
            band = min(search_radius + depth, 100.0)
            self.grid = SignedDistanceGrid.shared(self.surface, band=band, spacing=grid_spacing)
        self._hess = None
        self.motion = motion
        self.eps = self.penalty * self.areas
        self.bilateral = bool(bilateral)
        self.stick = bool(stick)
        self.multipliers = np.zeros(len(self.slaves))
        self.anchor = np.full((len(self.slaves), 3), np.nan)     # stick points, surface frame
        self.last = None
        self._active = None
        self._face = None
        self._convex = False

    def convexify(self, on: bool) -> bool:
        """With on=True the curvature part -p_i d2g/dx2 of the tangent is projected (its
        negative eigenvalues clipped to zero, as with tangent="projected" before the status
        is frozen) at every assembly until convexify(False); the forces are unchanged.
        Returns True: a node pressed onto a convex part of the surface has a negative
        tangential stiffness."""
        self._convex = bool(on)
        return True

    # ------------------------------------------------------------------ geometry
    def transform(self, load: float) -> np.ndarray:
        if self.motion is None:
            return np.eye(4)
        if callable(self.motion):
            return np.asarray(self.motion(load), dtype=float)
        return ramped_rigid_motion(self.motion, load)

    def gaps(self, x, load, frozen: bool = False):
        """Signed gaps of all slave nodes (nan where farther than the search radius).

        With `frozen`, each node keeps the face found at the last unfrozen evaluation (its
        closest point is taken on that face), so that a node deep in a thin body does not
        flip between the faces of both sides within a Newton solve.
        With a smooth (`smooth=True`) surface, g is the spline signed distance and `normal`
        its gradient (unit up to the interpolation error), the region always FACE.
        Returns (g (s,), normal (s, 3) current, region (s,), y (s, 3) pulled-back positions).
        """
        T = self.transform(load)
        R, t = T[:3, :3], T[:3, 3]
        y = (np.asarray(x)[self.slaves] - t) @ R
        radius = self.search_radius + float(np.max(self.multipliers / self.eps, initial=0.0))
        if self.grid is not None:
            phi, grad, hess, on_grid = self.grid.evaluate(y)
            near = on_grid & (phi <= radius)
            g = np.where(near, phi, np.nan)
            n = np.where(near[:, None], grad, 0.0) @ R.T
            self._hess = np.einsum("ia,kab,jb->kij", R, hess, R)
            return g, n, np.full(len(g), FACE), y
        if frozen and self._face is not None:
            idx = np.nonzero(self._face >= 0)[0]
            face = self._face[idx]
            tri = self.surface.vertices[self.surface.faces[face]]
            c, region = closest_point_on_triangles(y[idx], tri[:, 0], tri[:, 1], tri[:, 2])
            dist = np.linalg.norm(y[idx] - c, axis=1)
        else:
            idx, c, face, region, dist = self.surface.closest(y, radius)
            self._face = np.full(len(self.slaves), -1)
            self._face[idx] = face
        g = np.full(len(self.slaves), np.nan)
        n0 = np.zeros((len(self.slaves), 3))
        reg = np.full(len(self.slaves), -1)
        d = y[idx] - c
        # a point whose closest feature is an edge or vertex but which lies on the normal
        # line of the face (e.g. exactly above the diagonal of a flat quad) is a face point:
        # the distance has no curvature there
        fn = self.surface.face_normals[face]
        along = np.abs(np.einsum("ij,ij->i", d, fn)) >= (1.0 - 1e-9) * dist
        region = np.where(along, FACE, region)
        pn = self.surface.pseudo_normal(face, region)
        # Off the face interiors (closest feature an edge or a vertex) the gap is the signed
        # distance s |y - c| with the unit gradient s (y - c)/|y - c|, continuous across the
        # Voronoi regions of the features (the pseudo-normal only gives the sign).
        inside_face = region == FACE
        sgn = np.where(np.einsum("ij,ij->i", d, pn) >= 0.0, 1.0, -1.0)
        safe = np.maximum(dist, 1e-300)[:, None]
        ni = np.where(inside_face[:, None], pn, sgn[:, None] * d / safe)
        gi = np.where(inside_face, np.einsum("ij,ij->i", d, pn), sgn * dist)
        g[idx], n0[idx], reg[idx] = gi, ni, region
        return g, n0 @ R.T, reg, y

    # ------------------------------------------------------------------ Term protocol
    def _pressure(self, g, frozen=False):
        """Contact forces p_i = <lambda_i - eps_i g_i> and the active set.

        With `frozen`, the active set of the last unfrozen evaluation is kept (status
        freezing: the bracket is dropped on it, a frozen-active node may pull) so that Newton
        converges on a smooth problem; `end_step` then checks the status.
        """
        p = self.multipliers - self.eps * np.nan_to_num(g, nan=np.inf)
        if self.bilateral:
            active = ~np.isnan(g)
        elif frozen and self._active is not None:
            active = self._active & ~np.isnan(g)
        else:
            active = (p > 0.0) & (g > -self.max_depth)
            self._active = active.copy()
        p = np.where(active, p, 0.0)
        return p, active


    def assemble(self, x, load):
        frozen = self._frozen(load)
        g, n, reg, y = self.gaps(x, load, frozen)
        p, active = self._pressure(g, frozen)
        f = np.zeros(3 * self.n_nodes)
        nodes = self.slaves[active]
        na, pa, ga, ea = n[active], p[active], g[active], self.eps[active]
        dofs = 3 * nodes[:, None] + np.arange(3)
        np.add.at(f, dofs.ravel(), (-pa[:, None] * na).ravel())
        Kb = ea[:, None, None] * na[:, :, None] * na[:, None, :]
        off = reg[active] != FACE
        if self.grid is not None:
            curvature = -pa[:, None, None] * self._hess[active]
            if (self.tangent == "projected" and not frozen) or self._convex:
                curvature = psd_projection(curvature)
            Kb += curvature
        elif np.any(off):
            # curvature of the distance to a vertex, d2g/dx2 = (I - n n)/g, or to an edge's
            # line, (I - n n - t t)/g with t the unit edge direction (no curvature along the
            # edge), in the tangent -p d2g/dx2; |g| is kept above 1e-4 mm so that a node
            # resting exactly on an edge has a finite (if very stiff) tangential stiffness
            P = np.eye(3) - na[off, :, None] * na[off, None, :]
            t = self._edge_directions(reg[active][off], self._face[active][off], load)
            P -= t[:, :, None] * t[:, None, :]
            go = ga[off]
            greg = np.where(go >= 0, 1.0, -1.0) * np.maximum(np.abs(go), 1e-4)
            curvature = (-pa[off] / greg)[:, None, None] * P
            Kb[off] += psd_projection(curvature) if self._convex else curvature
        if self.stick:
            fs, Ks = self._stick_terms(load, active, y, n)
            f += fs
            Kb += Ks
        rows = np.repeat(dofs, 3, axis=1).ravel()
        cols = np.tile(dofs, (1, 3)).ravel()
        K = sp.coo_matrix((Kb.ravel(), (rows, cols)), shape=(3 * self.n_nodes,) * 2)
        self.last = dict(gap=g, pressure=p, normal=n, active=active)
        return f, K

    def _edge_directions(self, region, face, load):
        """Unit direction (current frame) of the edge of `face` named by `region` (edge
        regions), zero for vertex regions."""
        F = self.surface.faces[face]
        t = np.zeros((len(face), 3))
        for r, (i, j) in ((EDGE_AB, (0, 1)), (EDGE_BC, (1, 2)), (EDGE_CA, (2, 0))):
            m = region == r
            if np.any(m):
                e = self.surface.vertices[F[m, j]] - self.surface.vertices[F[m, i]]
                t[m] = e / np.linalg.norm(e, axis=1, keepdims=True)
        return t @ self.transform(load)[:3, :3].T

    def _stick_terms(self, load, active, y, n):
        """Tangential tie of active nodes to their first contact point (penalty eps_i)."""
        T = self.transform(load)
        R = T[:3, :3]
        new = active & np.isnan(self.anchor[:, 0])
        self.anchor[new] = y[new]
        fs = np.zeros(3 * self.n_nodes)
        Ks = np.zeros((int(active.sum()), 3, 3))
        ia = np.nonzero(active)[0]
        na = n[ia]
        Pt = np.eye(3) - na[:, :, None] * na[:, None, :]
        d = (y[ia] - self.anchor[ia]) @ R.T
        ft = self.eps[ia, None] * np.einsum("kij,kj->ki", Pt, d)
        dofs = 3 * self.slaves[ia][:, None] + np.arange(3)
        np.add.at(fs, dofs.ravel(), ft.ravel())
        Ks[:] = self.eps[ia, None, None] * Pt
        return fs, Ks

    def energy(self, x, load) -> float:
        frozen = self._is_frozen(load)
        g, n, _, y = self.gaps(x, load, frozen)
        p, _ = self._pressure(g, frozen)
        lam = self.multipliers
        e = float(np.sum((p * p - lam * lam) / (2.0 * self.eps)))
        if self.stick:
            ia = np.nonzero((p > 0) & ~np.isnan(self.anchor[:, 0]))[0]
            R = self.transform(load)[:3, :3]
            d = (y[ia] - self.anchor[ia]) @ R.T
            dt = d - np.einsum("ij,ij->i", d, n[ia])[:, None] * n[ia]
            e += float(0.5 * np.sum(self.eps[ia] * np.einsum("ij,ij->i", dt, dt)))
        return e

    def augmentation_due(self, x, load) -> bool:
        """Whether the current (not converged) iterate at `load` penetrates so deep that the
        step will be augmented (`UzawaLoop.augmentation_due`); the solve's status is kept."""
        if self.bilateral:
            return False
        saved = (self._face, self._active, self._hess)
        try:
            frozen = self._is_frozen(load)
            g, _, _, _ = self.gaps(x, load, frozen)
            p, _ = self._pressure(g, frozen)
            err = float(np.max(-g[p > 0], initial=0.0))
        finally:
            self._face, self._active, self._hess = saved
        return self.uzawa.augmentation_due(load, self.augmented, err, self.tolerance)

    def end_step(self, x, load) -> bool:
        before = self._multiplier_values()
        frozen_active = self._active.copy() if self._active is not None else None
        was_frozen = self._is_frozen(load)
        self._unfreeze()
        g, _, _, _ = self.gaps(x, load)
        p, active = self._pressure(g)
        # a frozen solve whose contact status is wrong at convergence is solved again
        # (changes of nodes that sit within the tolerance of the switch, in gap
        # units (lambda - eps g) / eps, do not count: grazing nodes would cycle for ever)
        q = (self.multipliers - self.eps * np.nan_to_num(g, nan=np.inf)) / self.eps
        flip = (frozen_active != active) & (np.abs(q) > self.tolerance) \
            if frozen_active is not None else np.zeros(len(q), dtype=bool)
        changed = bool(was_frozen and not self.bilateral and np.any(flip))
        if self.bilateral:
            err = np.nanmax(np.abs(g), initial=0.0)
        else:
            err = float(np.max(-g[p > 0], initial=0.0))
        self.last_error = err
        again = self.uzawa.another_solve(load, changed, self.augmented, err, self.tolerance)
        # Uzawa update (also when only the frozen status was wrong: it settles the status;
        # and on an intermediate step the "carried" schedule takes to the next load)
        if self.uzawa.update:
            self.multipliers = p
        self._note_carried(before, load)
        if again:
            self._freeze_resolve(load)
        return again

    def _scale_multipliers(self, factor: float) -> None:
        self.multipliers = self.multipliers * factor

    # ------------------------------------------------------------------ results
    def penetration(self, x, load: float = 1.0) -> float:
        """Deepest penetration (mm, >= 0) of a slave node within `max_depth` at x."""
        g, *_ = self.gaps(x, load)
        g = g[np.isfinite(g) & (g > -self.max_depth)]
        return float(max(0.0, -g.min())) if len(g) else 0.0

    def contact_forces(self, x, load: float = 1.0) -> np.ndarray:
        """Force (s, 3) that the rigid surface exerts on each slave node (mN)."""
        g, n, _, _ = self.gaps(x, load)
        return self._pressure(g)[0][:, None] * n

    def contact_pressure(self, x, load: float = 1.0) -> np.ndarray:
        """Contact pressure (kPa) at each slave node: force / tributary area."""
        g, _, _, _ = self.gaps(x, load)
        return self._pressure(g)[0] / self.areas
