"""Tissue sliding on a moving rigid surface (bilateral frictionless contact), inclined frame."""
import numpy as np
import pytest

from solver.bc import fix
from solver.constitution import Yeoh
from solver.contact import RigidSurfaceContact
from solver.mechanics import SolidBody
from solver.mesh import HexMesh
from solver.newton import newton_solve

THETA = np.radians(30.0)
E_X = np.array([1.0, 0.0, 0.0])
T_DIR = np.array([0.0, np.cos(THETA), np.sin(THETA)])       # in-plane direction, up the slope
N_DIR = np.array([0.0, -np.sin(THETA), np.cos(THETA)])      # plane normal


def inclined_block(n=(2, 2, 3), size=(2.0, 2.0, 3.0)):
    """Block with local axes (e_x, t, n): xi along x, eta up the slope, zeta along the normal."""
    g = [np.linspace(0, L, k + 1) for L, k in zip(size, n)]
    A, B, C = np.meshgrid(*g, indexing="ij")
    local = np.stack([A.ravel(), B.ravel(), C.ravel()], axis=1)
    nx, ny, nz = n
    idx = np.arange(len(local)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz),
                                              indexing="ij"))
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1],
                      idx[i, j + 1, k + 1]], axis=1)
    frame = np.stack([E_X, T_DIR, N_DIR])                  # rows: local axes
    return local @ frame, hexes, local


def rigid_plane(origin, u, v, half=20.0):
    """Square plane through origin spanned by u, v (normal u x v), two triangles."""
    c = [origin + half * (su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return np.array(c), np.array([[0, 1, 2], [0, 2, 3]])


def yeoh_uniaxial(lam, C10, C20):
    t = lam ** 2 + 2 / lam - 3
    return 2 * (C10 + 2 * C20 * t) * (lam ** 2 - 1 / lam)


@pytest.mark.parametrize("tangential", [0.0, 3.0])
def test_block_between_sliding_inclined_planes_is_in_uniaxial_compression(tangential):
    """Bottom face slides on a plane moved by 0.45 mm along its normal (plus a tangential
    shift that a frictionless sliding must ignore), top face slides on a fixed parallel
    plane, one side slides on a plane normal to the slope, x = 0 is a symmetry plane.
    Analytic: homogeneous uniaxial compression along n, lam = (H - delta) / H."""
    H, delta = 3.0, 0.45
    nodes, hexes, local = inclined_block()
    C10, C20 = 2.5, 1.175
    body = SolidBody(HexMesh(nodes, hexes), Yeoh(C10, C20, 0.0, K=2500.0))
    tol = 1e-9
    bottom = np.nonzero(local[:, 2] < tol)[0]
    top = np.nonzero(local[:, 2] > H - tol)[0]
    side = np.nonzero(local[:, 1] < tol)[0]
    move = np.eye(4)
    move[:3, 3] = delta * N_DIR + tangential * T_DIR
    terms = []
    for nodes_on, origin, (u, v), motion in (
            (bottom, np.zeros(3), (E_X, T_DIR), move),
            (top, H * N_DIR, (E_X, T_DIR), None),
            (side, np.zeros(3), (N_DIR, E_X), None)):
        V, F = rigid_plane(origin, u, v)
        terms.append(RigidSurfaceContact(nodes, V, F, slave_nodes=nodes_on, motion=motion,
                                         penalty=200.0, bilateral=True, tolerance=1e-6,
                                         search_radius=10.0))
    cons = [fix(np.nonzero(local[:, 0] < tol)[0], (0,))]
    res = newton_solve(body, cons, terms, steps=3, max_retries=30)
    lam = (H - delta) / H
    lat = lam ** -0.5                                   # incompressible lateral stretch
    expected = (local * [lat, lat, lam]) @ np.stack([E_X, T_DIR, N_DIR]) + delta * N_DIR
    # homogeneous solution; AL tolerance 1e-6 mm and J - 1 ~ sigma/K ~ 1e-3 of the lateral
    # stretch (K/mu = 500): nodal positions to 5e-3 mm
    assert np.abs(res.x - expected).max() < 5e-3
    # the normal reaction on the moving plane equals the uniaxial stress times current area
    fb = terms[0].contact_forces(res.x, 1.0)
    force = (fb @ N_DIR).sum()                          # the plane pushes along +n
    area = (2.0 * lat) ** 2
    assert force == pytest.approx(-yeoh_uniaxial(lam, C10, C20) * area, rel=1e-2)
    # frictionless: no tangential force on the sliding faces
    assert np.abs(fb @ T_DIR).max() < 1e-8 * np.abs(fb).max()


def test_tied_block_follows_a_tangential_bone_shift_but_sliding_block_does_not():
    """The same bone shift along the slope: tied bottom nodes carry the block along, sliding
    bottom nodes let it stay where the other constraints hold it."""
    H = 3.0
    nodes, hexes, local = inclined_block()
    body = SolidBody(HexMesh(nodes, hexes), Yeoh(2.5, 1.175, 0.0, K=2500.0))
    tol = 1e-9
    bottom = np.nonzero(local[:, 2] < tol)[0]
    side = np.nonzero(local[:, 1] < tol)[0]
    shift = 2.0 * T_DIR
    move = np.eye(4)
    move[:3, 3] = shift
    V, F = rigid_plane(np.zeros(3), E_X, T_DIR)
    slide = RigidSurfaceContact(nodes, V, F, slave_nodes=bottom, motion=move, penalty=200.0,
                                bilateral=True, tolerance=1e-6, search_radius=10.0)
    Vs, Fs = rigid_plane(np.zeros(3), N_DIR, E_X)
    side_term = RigidSurfaceContact(nodes, Vs, Fs, slave_nodes=side, penalty=200.0,
                                    bilateral=True, tolerance=1e-6, search_radius=10.0)
    cons = [fix(np.nonzero(local[:, 0] < tol)[0], (0,))]
    res = newton_solve(body, cons, [slide, side_term], steps=2, max_retries=30)
    assert np.abs(res.u).max() < 1e-4                    # nothing moved: frictionless
    from solver.bc import Prescribed
    tied = newton_solve(body, cons[:0] + [Prescribed(bottom, shift)], [], steps=2)
    assert np.allclose(tied.u[bottom], shift)
    assert np.allclose(tied.u, shift, atol=1e-6)          # free block carried rigidly
