"""Natural boundary conditions as residual terms: follower pressure on quad facets, body force.

Follower pressure p (kPa) on bilinear quad facets acts along the current normal, traction
t = -p n, so that p > 0 pushes into the body. With n da = (x_,xi x x_,eta) dxi deta the nodal
residual contribution is f_a = p int N_a (x_,xi x x_,eta) dxi deta, and its linearisation (the
load stiffness of Bonet & Wood 2008, sec. 8.4.1; Schweizerhof & Ramm 1984) is
K_ai,bk = p int N_a [N_b,eta skew(x_,xi) - N_b,xi skew(x_,eta)]_ik dxi deta. The load stiffness
is symmetric for a closed surface or a surface whose boundary is held; otherwise its symmetric
part is used (the solver's factorisation is symmetric), which keeps convergence linear-to-
quadratic. The body force is the dead load f_a = -load * int rho b N_a dV with rho b in mN/mm^3
(e.g. density 1.0e-3 g/mm^3 times gravity 9810 mm/s^2 = 9.81e-3 mN/mm^3 for soft tissue).

A tangential elastic support (a Robin condition) ties nodes to an anchor moving with a
prescribed displacement a(load) through springs that act in each node's tangent plane only:
with n_i the node's normal and P_i = I - n_i n_i^T, the energy is
1/2 sum_i k_i |P_i (u_i - a_i)|^2, the force f_i = k_i P_i (u_i - a_i) and the stiffness the
constant block k_i P_i (symmetric, positive semi-definite). Between k = 0 (the node slides
freely on its support) and k -> infinity (tied), it models an interface that resists sliding
elastically: a layer of thickness H and shear modulus mu under a shear traction tau on such
a support with k per unit area lets the interface take the share (tau / k) / (tau H / mu +
tau / k) = 1 / (1 + k H / mu) of its surface's tangential displacement (linear elasticity).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from solver.element import gauss_hex, gauss_quad, hex8_shape, quad4_gradients, quad4_shape
from solver.bc import ramped_values
from solver.errors import BoundaryConditionError
from solver.terms import Term

__all__ = ["FollowerPressure", "BodyForce", "NodalForce", "TangentialSupport", "surface_traction"]


def _skew(v):
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


class FollowerPressure(Term):
    """Pressure `pressure` (kPa, ramped by the load fraction) on quad facets (k, 4).

    `pressure` may be a float or a callable load -> float. Facet node order gives the outward
    normal by the right-hand rule (as `solver.mesh.boundary_facets` returns them).
    """

    def __init__(self, facets, pressure, n_nodes: int, symmetric: bool = True):
        facets = np.asarray(facets, dtype=np.int64)
        if facets.ndim != 2 or facets.shape[1] != 4:
            raise BoundaryConditionError(f"pressure facets must be (k, 4) quads, got {facets.shape}")
        if facets.size and (facets.min() < 0 or facets.max() >= n_nodes):
            raise BoundaryConditionError("pressure facets refer to nodes outside the mesh")
        self.facets = facets
        self.pressure = pressure
        self.n_nodes = n_nodes
        self.symmetric = symmetric
        xg, wg = gauss_quad(2)
        self.N = quad4_shape(xg)            # (q, 4)
        self.dN = quad4_gradients(xg)       # (q, 4, 2)
        self.w = wg
        dofs = (3 * facets[:, :, None] + np.arange(3)).reshape(len(facets), 12)
        self._rows = np.repeat(dofs, 12, axis=1).ravel()
        self._cols = np.tile(dofs, (1, 12)).ravel()
        self._dofs = dofs

    def _p(self, load):
        p = self.pressure(load) if callable(self.pressure) else load * float(self.pressure)
        return float(p)

    def assemble(self, x, load):
        p = self._p(load)
        xe = x[self.facets]                                             # (k, 4, 3)
        t1 = np.einsum("kai,qa->kqi", xe, self.dN[..., 0])              # x_,xi
        t2 = np.einsum("kai,qa->kqi", xe, self.dN[..., 1])              # x_,eta
        nda = np.cross(t1, t2)                                          # (k, q, 3)
        fe = p * np.einsum("q,qa,kqi->kai", self.w, self.N, nda).reshape(len(xe), 12)
        f = np.bincount(self._dofs.ravel(), fe.ravel(), minlength=3 * self.n_nodes)
        # K_ai,bk = p sum_q w N_a (N_b,eta skew(t1) - N_b,xi skew(t2))_ik
        s1 = _skew(t1)
        s2 = _skew(t2)
        Kq = (np.einsum("qb,fqik->fqbik", self.dN[..., 1], s1)
              - np.einsum("qb,fqik->fqbik", self.dN[..., 0], s2))
        Ke = p * np.einsum("q,qa,fqbik->faibk", self.w, self.N, Kq).reshape(len(xe), 12, 12)
        K = sp.csr_matrix((Ke.ravel(), (self._rows, self._cols)),
                          shape=(3 * self.n_nodes, 3 * self.n_nodes))
        if self.symmetric:
            K = 0.5 * (K + K.T)
        return f, K

    def energy(self, x, load):
        # -p times the volume enclosed by the facets (exact potential for a closed surface)
        p = self._p(load)
        xe = x[self.facets]
        t1 = np.einsum("kai,qa->kqi", xe, self.dN[..., 0])
        t2 = np.einsum("kai,qa->kqi", xe, self.dN[..., 1])
        xq = np.einsum("kai,qa->kqi", xe, self.N)
        vol = np.einsum("q,kqi,kqi->", self.w, xq, np.cross(t1, t2)) / 3.0
        return float(p * vol)

    def end_step(self, x, load):
        return False


class BodyForce(Term):
    """Dead body force rho*b (mN/mm^3, a (3,) vector) on the hexahedra of a mesh, ramped by load.

    `cells` restricts it to some elements (default all).
    """

    def __init__(self, nodes, hexes, rho_b, cells=None):
        nodes = np.asarray(nodes, dtype=float)
        hexes = np.asarray(hexes, dtype=np.int64)
        if cells is not None:
            hexes = hexes[np.asarray(cells)]
        rho_b = np.asarray(rho_b, dtype=float)
        if rho_b.shape != (3,) or not np.all(np.isfinite(rho_b)):
            raise BoundaryConditionError(f"body force must be a finite (3,) vector, got {rho_b!r}")
        from solver.element import hex8_gradients
        xg, wg = gauss_hex(2)
        N = hex8_shape(xg)
        dN = hex8_gradients(xg)
        detJ = np.linalg.det(np.einsum("mai,qaj->mqij", nodes[hexes], dN))
        nodal = np.einsum("mq,q,qa->ma", detJ, wg, N)                   # int N_a dV
        weights = np.bincount(hexes.ravel(), nodal.ravel(), minlength=len(nodes))
        self.f_unit = -(weights[:, None] * rho_b[None, :]).ravel()      # residual at load 1
        self.n = len(nodes)
        self.X = nodes
        self.rho_b = rho_b

    def assemble(self, x, load):
        return load * self.f_unit, sp.csr_matrix((3 * self.n, 3 * self.n))

    def energy(self, x, load):
        return float(load * self.f_unit @ (x - self.X).ravel())

    def end_step(self, x, load):
        return False


class NodalForce(Term):
    """Dead nodal forces (k, 3) in mN on nodes (k,), ramped by the load fraction."""

    def __init__(self, nodes, forces, n_nodes: int, reference=None):
        nodes = np.atleast_1d(np.asarray(nodes, dtype=np.int64))
        self.X = None if reference is None else np.asarray(reference, dtype=float)
        forces = np.broadcast_to(np.asarray(forces, dtype=float), (len(nodes), 3))
        self.f_unit = np.zeros(3 * n_nodes)
        np.add.at(self.f_unit, (3 * nodes[:, None] + np.arange(3)).ravel(), -forces.ravel())
        self.n = n_nodes

    def assemble(self, x, load):
        return load * self.f_unit, sp.csr_matrix((3 * self.n, 3 * self.n))

    def energy(self, x, load):
        if self.X is None:
            return 0.0
        return float(load * self.f_unit @ (x - self.X).ravel())

    def end_step(self, x, load):
        return False


class TangentialSupport(Term):
    """Springs of stiffness `stiffness` (k,) (mN/mm) in the tangent planes of `normals` (k, 3)
    (unit) at `nodes` (k,), tying them to an anchor displaced by `anchor` ((3,), (k, 3) or a
    callable load -> (k, 3), as `solver.bc.LocalFrame.displacement`: a constant is ramped with
    the load, a callable gives the displacement at the load); `reference` (n, 3): the
    reference nodal coordinates (module text)."""

    static_state = ("nodes", "normals", "stiffness", "anchor", "X", "n", "_P", "_dofs", "_K")

    def __init__(self, nodes, normals, stiffness, anchor, reference):
        nodes = np.atleast_1d(np.asarray(nodes, dtype=np.int64))
        X = np.asarray(reference, dtype=float)
        normals = np.broadcast_to(np.asarray(normals, dtype=float), (len(nodes), 3))
        stiffness = np.broadcast_to(np.asarray(stiffness, dtype=float), (len(nodes),)).copy()
        if len(nodes) and (nodes.min() < 0 or nodes.max() >= len(X)):
            raise BoundaryConditionError("tangential support nodes lie outside the mesh")
        if not (np.all(np.isfinite(stiffness)) and np.all(stiffness >= 0)):
            raise BoundaryConditionError("tangential support stiffness must be finite and >= 0")
        norm = np.linalg.norm(normals, axis=1)
        if len(nodes) and not np.all(np.abs(norm - 1.0) < 1e-6):
            raise BoundaryConditionError("tangential support normals must be unit vectors")
        self.nodes, self.normals, self.stiffness = nodes, normals, stiffness
        self.anchor = anchor
        self.X = X
        self.n = len(X)
        self._P = np.eye(3)[None] - normals[:, :, None] * normals[:, None, :]       # (k, 3, 3)
        self._dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        # the stiffness is constant: assembled once
        Ke = stiffness[:, None, None] * self._P
        rows = np.repeat(self._dofs.reshape(-1, 3), 3, axis=1).ravel()
        cols = np.tile(self._dofs.reshape(-1, 3), (1, 3)).ravel()
        self._K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(3 * self.n, 3 * self.n)).tocsr()

    def _slip(self, x, load):
        # the anchor ramps with the load as a constraint's displacement does
        return np.asarray(x, float)[self.nodes] - self.X[self.nodes] - ramped_values(self.anchor, self.nodes, load)

    def assemble(self, x, load):
        fn = self.stiffness[:, None] * np.einsum("kij,kj->ki", self._P, self._slip(x, load))
        f = np.zeros(3 * self.n)
        np.add.at(f, self._dofs, fn.ravel())
        return f, self._K

    def energy(self, x, load):
        d = self._slip(x, load)
        return float(0.5 * np.sum(self.stiffness * np.einsum("ki,kij,kj->k", d, self._P, d)))

    def end_step(self, x, load):
        return False


def surface_traction(nodes, facets, traction) -> np.ndarray:
    """Consistent nodal forces (n, 3) of a dead traction (3,) (kPa) on reference quad facets.

    f_a = int N_a t dA over each facet; use with `NodalForce` or as `external` of newton_solve.
    """
    nodes = np.asarray(nodes, dtype=float)
    facets = np.asarray(facets, dtype=np.int64)
    t = np.asarray(traction, dtype=float)
    xg, wg = gauss_quad(2)
    N = quad4_shape(xg)
    dN = quad4_gradients(xg)
    xe = nodes[facets]
    t1 = np.einsum("kai,qa->kqi", xe, dN[..., 0])
    t2 = np.einsum("kai,qa->kqi", xe, dN[..., 1])
    dA = np.linalg.norm(np.cross(t1, t2), axis=-1)                       # (k, q)
    w = np.einsum("kq,q,qa->ka", dA, wg, N)
    out = np.zeros((len(nodes), 3))
    np.add.at(out, facets.ravel(), w.ravel()[:, None] * t[None, :])
    return out
