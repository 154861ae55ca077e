"""Loads and local-frame constraints against exact answers.

* Follower pressure: the load stiffness equals a central finite difference of the pressure
  forces (1e-6 relative, the same argument as in test_tangent), and on a closed surface it is
  symmetric and the force is the gradient of p * enclosed volume.
* Body force: total reaction equals the total weight exactly (equilibrium, to the solver's
  residual tolerance, 1e-6 relative), and a slender column under its own weight shortens as the
  1D incompressible Yeoh column does (uniaxial nominal stress rho g (H - Z) in each slice;
  tolerance 2%: the lateral expansion varies along the height, which the 1D model neglects).
* Local frames: a block stretched along a rotated axis between two frictionless (normal-only)
  supports given as local frames reaches the homogeneous uniaxial state: the normal reaction is
  the analytic Yeoh force (0.5%, as in test_homogeneous) and the lateral stretch is l^-1/2.
"""
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

import solver
from solver.examples import block

C = (0.5, -0.1, 0.02)


def uniaxial_P(lam):
    t = lam * lam + 2 / lam - 3
    return 2 * (C[0] + 2 * C[1] * t + 3 * C[2] * t * t) * (lam - lam ** -2)


def test_follower_pressure_tangent_fd():
    nodes, hexes, s = block((1, 1, 1), (2, 2, 1))
    rng = np.random.default_rng(1)
    x = nodes + 0.1 * rng.standard_normal(nodes.shape)
    fac = solver.boundary_facets(hexes)
    term = solver.FollowerPressure(fac[:5], 1.7, len(nodes), symmetric=False)
    f, K = term.assemble(x, 1.0)
    K = K.toarray()
    h = 1e-6
    Kfd = np.empty_like(K)
    for j in range(x.size):
        xp = x.ravel().copy()
        xm = x.ravel().copy()
        xp[j] += h
        xm[j] -= h
        Kfd[:, j] = (term.assemble(xp.reshape(-1, 3), 1.0)[0] - term.assemble(xm.reshape(-1, 3), 1.0)[0]) / (2 * h)
    assert np.abs(K - Kfd).max() < 1e-6 * np.abs(Kfd).max()


def test_follower_pressure_closed_surface_is_conservative():
    nodes, hexes, s = block((1, 1, 1), (2, 2, 2))
    rng = np.random.default_rng(2)
    x = nodes + 0.05 * rng.standard_normal(nodes.shape)
    term = solver.FollowerPressure(solver.boundary_facets(hexes), 0.8, len(nodes), symmetric=False)
    f, K = term.assemble(x, 1.0)
    K = K.toarray()
    assert np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()
    h = 1e-6
    g = np.array([(term.energy((x.ravel() + h * e).reshape(-1, 3), 1.0)
                   - term.energy((x.ravel() - h * e).reshape(-1, 3), 1.0)) / (2 * h)
                  for e in np.eye(x.size)])
    assert np.abs(g - f).max() < 1e-6 * np.abs(f).max()


def test_body_force_column():
    H, rho_g = 10.0, 0.02                    # mN/mm^3; max nominal stress 0.2 kPa
    nodes, hexes, s = block((1, 1, H), (2, 2, 20))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(*C, K=1e4 * C[0]))
    bf = solver.BodyForce(nodes, hexes, [0, 0, -rho_g])
    bcs = [solver.fix(s["zmin"], [2]), solver.fix(s["xmin"], [0]), solver.fix(s["ymin"], [1])]
    res = solver.newton_solve(body, bcs, [bf], steps=2)
    weight = rho_g * H
    assert res.reactions[s["zmin"], 2].sum() == pytest.approx(weight, rel=1e-6)
    # 1D column: slice at Z carries P(Z) = -rho g (H - Z); dz/dZ = lam(P)
    lam_of = lambda P: brentq(lambda l: uniaxial_P(l) - P, 0.3, 1.0 + 1e-12) if P < 0 else 1.0
    top = quad(lambda Z: lam_of(-rho_g * (H - Z)), 0, H, limit=200)[0] - H
    u_top = res.u[s["zmax"], 2].mean()
    assert u_top == pytest.approx(top, rel=0.02)


def test_local_frame_uniaxial_rotated():
    R = Rotation.from_euler("xyz", [30, -20, 50], degrees=True).as_matrix()
    nodes0, hexes, s = block((1, 1, 1), (2, 2, 2))
    nodes = nodes0 @ R.T                      # block axes e_i -> R e_i
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(*C, K=1e3 * C[0]))
    lam = 1.5
    n = R[:, 2]                               # stretch along the rotated z axis
    frame = np.array([R[:, 2], R[:, 0], R[:, 1]])        # rows: normal, in-plane axes
    bottom, top = s["zmin"], s["zmax"]
    origin = np.nonzero(np.all(nodes0 == 0, axis=1))[0]
    on_x = np.setdiff1d(np.intersect1d(bottom, s["ymin"]), origin)   # bottom edge along e_x
    rest = np.setdiff1d(bottom, np.concatenate([origin, on_x]))
    cons = [solver.LocalFrame(origin, frame, (0, 1, 2)),           # no rigid translation
            solver.LocalFrame(on_x, frame, (0, 2)),                 # no rotation about n
            solver.LocalFrame(rest, frame, (0,)),                   # frictionless support
            solver.LocalFrame(top, frame, (0,), (lam - 1) * n)]     # normal displacement only
    res = solver.newton_solve(body, cons, steps=3)
    # reactions are reported in each node's local frame: component 0 is along n
    F = res.reactions[top, 0].sum()
    assert F == pytest.approx(uniaxial_P(lam), rel=5e-3)
    # the top corner above the origin moved only along n; lateral stretch lam^-1/2
    corner = np.nonzero(np.all(np.isclose(nodes0, [1, 1, 1]), axis=1))[0][0]
    local = frame @ res.x[corner]
    assert local[0] == pytest.approx(lam, rel=1e-9)
    assert local[1] == pytest.approx(lam ** -0.5, rel=5e-3)
    assert local[2] == pytest.approx(lam ** -0.5, rel=5e-3)
