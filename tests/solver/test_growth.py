"""Volumetric growth (F = F_e theta^(1/3) I) in the hexahedral body, and the direct-
differentiation sensitivity of a converged equilibrium (`solver.sensitivity`)."""
import numpy as np
import pytest
from scipy.optimize import brentq

import solver
from solver.examples import block
from solver.sensitivity import linear_response

C10, K = 1.0, 1000.0          # kPa: neo-Hookean-like Yeoh, K = 500 mu (nearly incompressible)


def _rollers(s):
    return [solver.fix(s["xmin"], [0]), solver.fix(s["ymin"], [1]), solver.fix(s["zmin"], [2])]


def test_free_block_grows_stress_free():
    nodes, hexes, s = block((10, 10, 10), (2, 2, 2))
    theta = 1.1
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(C10, K=K), growth=theta)
    res = solver.newton_solve(body, _rollers(s), steps=1)
    # exact solution x = theta^(1/3) X; tolerance: Newton's residual tolerance (rtol 1e-8 on
    # forces of order K * 3 % strain * area) leaves displacements exact to ~1e-9 mm
    assert np.allclose(res.x, np.cbrt(theta) * nodes, atol=1e-7)
    v = np.sum(np.abs(np.linalg.det(np.einsum("mai,mqaJ->mqiJ", res.x[hexes],
                                               solver.SolidBody(solver.HexMesh(nodes, hexes),
                                                                solver.Yeoh(C10, K=K)).dNdX))
                      * solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(C10, K=K)).dV))
    assert v == pytest.approx(theta * 1000.0, rel=1e-9)
    assert np.abs(body.cauchy_stress(res.x)).max() < 1e-6       # kPa, against K ~ 1000 kPa
    assert np.allclose(body.volume_ratio(res.x), 1.0, atol=1e-10)   # elastic part: identity


def _confined_stress(theta, C10, K):
    """Block confined laterally (F = diag(1, 1, lam)), free on top: sigma_zz = 0 fixes lam;
    returns (lam, sigma_xx) of the uncoupled neo-Hookean + Simo-Taylor U on F_e = F/theta^(1/3)."""
    g = np.cbrt(theta)

    def sig(lam):
        Fe = np.diag([1.0, 1.0, lam]) / g
        Je = np.linalg.det(Fe)
        b = Je ** (-2 / 3) * Fe @ Fe.T
        p = 0.5 * K * (Je - 1 / Je)
        return 2 * C10 / Je * (b - np.trace(b) / 3 * np.eye(3)) + p * np.eye(3)
    lam = brentq(lambda l: sig(l)[2, 2], 0.9, 1.5)
    return lam, sig(lam)[0, 0]


def test_confined_block_analytic_stress():
    nodes, hexes, s = block((10, 10, 10), (2, 2, 2))
    theta = 1.06
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(C10, K=K), growth=theta)
    bcs = [solver.fix(s["xmin"], [0]), solver.fix(s["xmax"], [0]), solver.fix(s["ymin"], [1]),
           solver.fix(s["ymax"], [1]), solver.fix(s["zmin"], [2])]
    res = solver.newton_solve(body, bcs, steps=2)
    lam, sxx = _confined_stress(theta, C10, K)
    # homogeneous state: exact in the element up to the Newton tolerance
    assert res.x[s["zmax"], 2].mean() == pytest.approx(10 * lam, rel=1e-8)
    sig = body.cauchy_stress(res.x)
    assert sxx < -0.05                                   # compressed laterally (kPa)
    assert np.allclose(sig[:, 0, 0], sxx, rtol=1e-6)
    assert np.allclose(sig[:, 2, 2], 0.0, atol=1e-6 * abs(sxx))


def test_growth_one_is_the_baseline():
    nodes, hexes, s = block((4, 4, 4), (2, 2, 2))
    x = nodes + 0.1 * np.sin(nodes)
    a = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(C10, 0.5, K=K)).evaluate(x)
    b = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(C10, 0.5, K=K),
                         growth=np.ones(len(hexes))).evaluate(x)
    assert np.array_equal(a.force, b.force) and a.energy == b.energy


def test_sensitivity_matches_finite_differences():
    """du/dp for a growth amplitude and a prescribed top displacement against central
    differences of full solves (block under self-weight, partly grown)."""
    nodes, hexes, s = block((4, 4, 8), (2, 2, 4))
    cen = nodes[hexes].mean(axis=1)
    w = np.exp(-((cen[:, 2] - 2.0) / 3.0) ** 2)
    mat = solver.Yeoh(C10, 0.5, K=200.0)

    def problem(p):
        body = solver.SolidBody(solver.HexMesh(nodes, hexes), mat, growth=1.0 + p[0] * w)
        bcs = [solver.fix(s["zmin"]), solver.Prescribed(s["zmax"], [0.0, 0.0, p[1]], (2,))]
        return body, bcs, [solver.BodyForce(nodes, hexes, [0.0, 0.05, -0.05])]

    def solve(p):
        body, bcs, terms = problem(p)
        return solver.newton_solve(body, bcs, terms, steps=2, rtol=1e-12, atol=1e-14).x

    p0 = np.array([0.08, 0.3])
    x0 = solve(p0)
    body, bcs, terms = problem(p0)
    h = 1e-4
    dr = np.zeros((x0.size, 2))
    duc = []
    from solver.sensitivity import constraint_set
    for j in range(2):
        rs = []
        for sgn in (1, -1):
            p = p0.copy()
            p[j] += sgn * h
            b, c, t = problem(p)
            rs.append(b.evaluate(x0, 1.0, tangent=False).force + sum(tt.assemble(x0, 1.0)[0] for tt in t))
        dr[:, j] = (rs[0] - rs[1]) / (2 * h)
    cs0 = constraint_set(body, bcs)
    duc = np.zeros((len(cs0.dofs), 2))
    for sgn in (1, -1):
        p = p0.copy()
        p[1] += sgn * h
        duc[:, 1] += sgn * constraint_set(*problem(p)[:2]).targets(1.0, nodes) / (2 * h)
    du = linear_response(body, bcs, terms, x0, dr, duc)
    for j in range(2):
        hh = 1e-3
        p = p0.copy(); p[j] += hh
        xp = solve(p)
        p = p0.copy(); p[j] -= hh
        xm = solve(p)
        fd = ((xp - xm) / (2 * hh)).ravel()
        # central differences of full solves: O(h^2) truncation, ~1e-6 relative here
        assert np.abs(du[:, j] - fd).max() < 1e-4 * np.abs(fd).max()
        assert np.abs(fd).max() > 1e-2
