"""Contact in FE solves: block on a rigid plane, two-block patch test, Hertz line contact."""
import numpy as np
import pytest

from solver.bc import Prescribed, fix
from solver.constitution import NeoHooke, Yeoh
from solver.contact import RigidSurfaceContact, SurfaceContact
from solver.mechanics import SolidBody
from solver.mesh import HexMesh, boundary_facets
from solver.newton import newton_solve


def box(n, size, origin=(0.0, 0.0, 0.0), grading=None):
    """Structured hex box with n = (nx, ny, nz) cells, VTK node order.

    grading: optional per-axis callables mapping [0, 1] -> [0, 1] (monotone) for graded cells.
    """
    g = []
    for a, (L, k) in enumerate(zip(size, n)):
        t = np.linspace(0, 1, k + 1)
        if grading is not None and grading[a] is not None:
            t = grading[a](t)
        g.append(origin[a] + L * t)
    X, Y, Z = np.meshgrid(*g, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    nx, ny, nz = n
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz),
                                              indexing="ij"))
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1],
                      idx[i, j + 1, k + 1]], axis=1)
    return nodes, hexes


def facets_on(nodes, hexes, axis, value):
    f = boundary_facets(hexes)
    return f[np.all(np.abs(nodes[f][:, :, axis] - value) < 1e-9, axis=1)]


def plane(z=0.0, half=50.0):
    """Rigid plane z = const (two triangles, normal +z)."""
    V = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return V, np.array([[0, 1, 2], [0, 2, 3]])


def yeoh_uniaxial(lam, C10, C20=0.0, C30=0.0):
    """Cauchy stress of incompressible uniaxial stress of a Yeoh solid at stretch lam."""
    t = lam ** 2 + 2 / lam - 3
    return 2 * (C10 + 2 * C20 * t + 3 * C30 * t * t) * (lam ** 2 - 1 / lam)


def test_block_pressed_on_rigid_plane():
    """Frictionless plane + symmetry planes: homogeneous uniaxial compression."""
    nodes, hexes = box((3, 3, 3), (2.0, 2.0, 2.0))
    mat = Yeoh(2.5, 1.175, 0.0, K=2500.0)
    body = SolidBody(HexMesh(nodes, hexes), mat)
    V, F = plane(0.0)
    bottom = facets_on(nodes, hexes, 2, 0.0)
    contact = RigidSurfaceContact(nodes, V, F, slave_facets=bottom, penalty=50.0,
                                  tolerance=1e-3, search_radius=1.0)
    top = np.nonzero(nodes[:, 2] > 2.0 - 1e-9)[0]
    cons = [Prescribed(top, [0.0, 0.0, -0.4], (2,)),
            fix(np.nonzero(nodes[:, 0] < 1e-9)[0], (0,)),
            fix(np.nonzero(nodes[:, 1] < 1e-9)[0], (1,))]
    res = newton_solve(body, cons, [contact], steps=4, max_retries=20)
    fc = contact.contact_forces(res.x, 1.0)
    applied = -res.reactions[top, 2].sum()                       # force pushing the top down
    # equilibrium of the whole block (solver tolerance rtol 1e-8): reaction = contact load
    assert fc[:, 2].sum() == pytest.approx(applied, rel=1e-6)
    g, *_ = contact.gaps(res.x, 1.0)
    assert -np.nanmin(g) < 1e-3                                   # augmented to tolerance
    # homogeneous: every contact node carries the same pressure (1 %)
    p = contact.contact_pressure(res.x, 1.0)
    assert np.all(p > 0)
    assert p.std() / p.mean() < 1e-2
    # and it is the analytic uniaxial Cauchy stress at the measured stretch (deformed area)
    lam = (res.x[top, 2].mean() - res.x[contact.slaves, 2].mean()) / 2.0
    width = res.x[:, 0].max()
    sigma = -yeoh_uniaxial(lam, 2.5, 1.175)
    # J = 1 up to sigma/K ~ 2e-3: the current-area pressure matches to 1 %
    assert applied / width ** 2 == pytest.approx(sigma, rel=1e-2)
