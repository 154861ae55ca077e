"""Newton updates that are not descent directions: the terms' convexified tangents.

A term whose tangent is indefinite (a node pressed onto a convex obstacle has the tangential
stiffness -p/R) can make the Newton update an ascent direction of the potential, du . r > 0:
Newton then heads for a saddle. The solver solves such an update again with the terms'
positive semi-definite modification (`Term.convexify`) and goes downhill.

* The contact terms' convexified tangents keep the forces, differ from the exact ones by a
  positive semi-definite matrix, and give the exact tangent back when switched off.
* A node on a repulsive bump (a smooth hill of potential, stronger than the elastic stiffness
  that holds the node): from a start near the hill top the exact Newton method converges to
  the unstable equilibrium on the hill; with the convexified update the solve ends in a stable
  one off the hill, at a lower potential.
"""
import numpy as np

import solver
from solver.contact import RigidSurfaceContact, SurfaceContact
from solver.contact._geometry import psd_projection
from solver.examples import block
from solver.terms import Term


def _sphere(radius, refinements):
    """Icosphere (vertices, faces), outward normals."""
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    for _ in range(refinements):
        mids = {}
        out = []
        V = list(V)
        for a, b, c in F:
            m = []
            for i, j in ((a, b), (b, c), (c, a)):
                key = (min(i, j), max(i, j))
                if key not in mids:
                    mids[key] = len(V)
                    V.append(0.5 * (V[i] + V[j]))
                m.append(mids[key])
            out += [[a, m[0], m[2]], [b, m[1], m[0]], [c, m[2], m[1]], m]
        V, F = np.array(V), np.array(out)
    V = V / np.linalg.norm(V, axis=1, keepdims=True) * radius
    return V, F


def test_convexified_rigid_contact_tangent_keeps_forces_and_is_exact_again_when_off():
    """Frozen status (where tangent="projected" gives the exact tangent): convexify(True)
    projects the curvature part all the same."""
    V, F = _sphere(2.0, 3)
    rng = np.random.default_rng(5)
    d = rng.standard_normal((6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = d * rng.uniform(1.9, 2.05, 6)[:, None]
    t = RigidSurfaceContact(x, V, F, slave_nodes=np.arange(6), slave_areas=np.ones(6),
                            penalty=30.0, smooth=True, grid_spacing=0.2, search_radius=1.0,
                            max_depth=1.0, tangent="projected")
    t.multipliers[:] = 3.0
    for _ in range(t.freeze_after + 1):           # freeze the status
        f0, K0 = t.assemble(x, 1.0)
    assert t.convexify(True)
    f1, K1 = t.assemble(x, 1.0)
    t.convexify(False)
    f2, K2 = t.assemble(x, 1.0)
    K0, K1, K2 = K0.toarray(), K1.toarray(), K2.toarray()
    assert np.array_equal(f0, f1) and np.array_equal(f0, f2)
    # convex obstacle, pressing nodes: the exact tangent has the tangential stiffness
    # -p/R ~ -3/2, the convexified one none (eigenvalues to round-off 1e-9)
    assert np.linalg.eigvalsh(K0).min() < -0.1
    assert np.linalg.eigvalsh(K1).min() > -1e-9
    assert np.linalg.eigvalsh(K1 - K0).min() > -1e-9
    assert np.array_equal(K2, K0)


def test_convexified_surface_contact_tangent_is_a_psd_modification():
    """Two-pass node-to-segment contact between two crossing facet pairs under pressure: the
    curvature part -p d2g/dx2 (the rotation of the master plane) is indefinite; convexified,
    the forces stay and the tangent grows by a positive semi-definite matrix."""
    rng = np.random.default_rng(3)
    lower = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    upper = lower + [0.2, 0.3, -0.05]             # penetrating by 0.05 mm
    x = np.vstack([lower, upper]) + 0.01 * rng.standard_normal((8, 3))
    a = np.array([[0, 1, 2, 3]])                  # normal +z
    b = np.array([[7, 6, 5, 4]])                  # normal -z
    t = SurfaceContact(x, a, b, penalty=50.0, search_radius=1.0, max_depth=1.0,
                       ignore_initial_penetration=False)
    for ps in t.passes:
        ps.multipliers[:] = 2.0
    f0, K0 = t.assemble(x, 1.0)
    assert t.convexify(True)
    f1, K1 = t.assemble(x, 1.0)
    t.convexify(False)
    f2, K2 = t.assemble(x, 1.0)
    K0, K1, K2 = (K.toarray() for K in (K0, K1, K2))
    assert np.abs(f0).max() > 0 and np.array_equal(f0, f1)
    # K1 - K0 is the clipped negative part of the curvature: PSD and nonzero (round-off 1e-9)
    w = np.linalg.eigvalsh(K1 - K0)
    assert w.min() > -1e-9 and w.max() > 1e-3
    assert np.allclose(K2, K0, rtol=0, atol=1e-12)


class _Bump(Term):
    """A repulsive hill of potential on some nodes: E = A sum_i exp(-|x_i - c_i|^2 / 2 s^2).
    Its Hessian is negative definite near the hill top (|x - c| < s) and has a positive
    radial eigenvalue beyond: a stand-in for a node pressed onto a convex obstacle."""

    def __init__(self, n, nodes, centres, amplitude, width):
        self.n, self.nodes, self.c = n, np.asarray(nodes), np.asarray(centres, float)
        self.A, self.s = float(amplitude), float(width)
        self.convex = False
        self.calls = 0

    def _parts(self, x):
        d = x[self.nodes] - self.c
        e = self.A * np.exp(-np.einsum("ij,ij->i", d, d) / (2 * self.s ** 2))
        return d, e

    def energy(self, x, load):
        return float(self._parts(x)[1].sum())

    def assemble(self, x, load):
        import scipy.sparse as sp

        d, e = self._parts(x)
        s2 = self.s ** 2
        f = np.zeros((self.n, 3))
        f[self.nodes] = -(e / s2)[:, None] * d                  # dE/dx
        H = (e / s2)[:, None, None] * (d[:, :, None] * d[:, None, :] / s2 - np.eye(3))
        if self.convex:
            H = psd_projection(H)
        dofs = 3 * self.nodes[:, None] + np.arange(3)
        K = sp.coo_matrix((H.ravel(), (np.repeat(dofs, 3, axis=1).ravel(),
                                       np.tile(dofs, (1, 3)).ravel())), shape=(3 * self.n,) * 2)
        return f.ravel(), K

    def convexify(self, on):
        self.convex = bool(on)
        return True


class _BumpWithoutConvexify(_Bump):
    def convexify(self, on):
        return False


def _bump_problem(term_class):
    """A soft unit cube held at its base; a bump centred 0.05 mm beside each top corner, its
    curvature A / s^2 = 40 kPa mm far above the corners' lateral stiffness (mu = 5 kPa); the
    corners move at most 0.05 mm per update (the face's step-length limit, a damped Newton)."""
    nodes, hexes, sets = block((1, 1, 1), (1, 1, 1))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.NeoHooke(mu=5.0, K=250.0))
    top = np.asarray(sets["zmax"])
    centres = nodes[top] + [0.05, 0.0, 0.0]
    term = term_class(len(nodes), top, centres, amplitude=0.4, width=0.1)
    res = solver.newton_solve(body, [solver.fix(sets["zmin"])], [term], steps=1, grow=False,
                              rtol=1e-9, max_iterations=40, min_step=0.5, max_increment=0.05,
                              increment_nodes=top)
    return res, term, centres


def test_an_ascent_update_is_solved_again_with_convexified_terms():
    res, term, centres = _bump_problem(_Bump)
    assert res.converged and res.convexified >= 1
    # the corners left the hill: beyond its inflection radius s = 0.1 mm, where the bump's
    # potential is below e^-1/2 of its top's
    x = res.x[term.nodes]
    assert np.all(np.linalg.norm(x - centres, axis=1) > term.s)
    assert term.energy(res.x, 1.0) < 0.6 * 4 * term.A
    # the same problem without the convexified update converges to the equilibrium on the
    # hill top (within a tenth of its width): an unstable one, which the test above excludes
    ref, ref_term, _ = _bump_problem(_BumpWithoutConvexify)
    assert ref.converged and ref.convexified == 0
    xr = ref.x[ref_term.nodes]
    assert np.all(np.linalg.norm(xr - centres, axis=1) < 0.1 * term.s)
