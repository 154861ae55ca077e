"""Homogeneous deformations of a hexahedral block vs. analytic incompressible Yeoh stresses.

Yeoh C = (0.5, -0.1, 0.02) kPa (issue 2, check 1). W1 = C10 + 2 C20 (I1-3) +
3 C30 (I1-3)^2; uniaxial P = 2 W1 (l - l^-2), equibiaxial P = 2 W1 (l - l^-5), planar
P = 2 W1 (l - l^-3), simple shear sigma12 = 2 W1 gamma. Tolerance 0.5% (the issue's). The
discretisation is exact for homogeneous states; what remains is the residual compressibility,
an O(sigma/K) error: at K/C10 = 1e3 it is ~0.1% for uniaxial, planar and shear (Cauchy stresses
<= 1.3 kPa), but 2.8% for the equibiaxial stretch of 2 (sigma_xx = 8 kPa, volume change 1%), so
that case runs at K/C10 = 1e5 (still within the issue's "K/C10 >= 1e3").
"""
import numpy as np
import pytest

import solver
from solver.examples import block

C = (0.5, -0.1, 0.02)
K = 1e3 * C[0]


def W1(I1):
    t = I1 - 3.0
    return C[0] + 2 * C[1] * t + 3 * C[2] * t * t


def _cube(formulation="mean_dilatation", K=K):
    nodes, hexes, sets = block((1, 1, 1), (2, 2, 2))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(*C, K=K),
                            formulation=formulation)
    return nodes, body, sets


def test_published_values():
    # the reference values, from the formulas above
    l = 1.5
    assert 2 * W1(l * l + 2 / l) * (l - l ** -2) == pytest.approx(0.852361, abs=1e-6)
    l = 2.0
    assert 2 * W1(2 * l * l + l ** -4) * (l - l ** -5) == pytest.approx(4.036860, abs=1e-6)
    assert 2 * W1(3 + 1.0) * 1.0 == pytest.approx(0.72, abs=1e-12)


@pytest.mark.parametrize("formulation", ["mean_dilatation", "displacement"])
def test_uniaxial(formulation):
    nodes, body, s = _cube(formulation)
    lam = 1.5
    bcs = [solver.fix(s["xmin"], [0]), solver.fix(s["ymin"], [1]), solver.fix(s["zmin"], [2]),
           solver.Prescribed(s["xmax"], [lam - 1, 0, 0], [0])]
    res = solver.newton_solve(body, bcs, steps=3)
    P = res.reactions[s["xmax"], 0].sum()          # reference area 1
    assert P == pytest.approx(0.852361, rel=5e-3)
    # lateral contraction of an incompressible material: l^-1/2
    lat = 1 + res.u[s["ymax"], 1].mean()
    assert lat == pytest.approx(lam ** -0.5, rel=5e-3)


def test_equibiaxial():
    nodes, body, s = _cube(K=1e5 * C[0])
    lam = 2.0
    bcs = [solver.fix(s["xmin"], [0]), solver.fix(s["ymin"], [1]), solver.fix(s["zmin"], [2]),
           solver.Prescribed(s["xmax"], [lam - 1, 0, 0], [0]),
           solver.Prescribed(s["ymax"], [0, lam - 1, 0], [1])]
    res = solver.newton_solve(body, bcs, steps=4)
    P = res.reactions[s["xmax"], 0].sum()
    assert P == pytest.approx(4.036860, rel=5e-3)


def test_planar():
    nodes, body, s = _cube()
    lam = 1.5
    bcs = [solver.fix(s["xmin"], [0]), solver.fix(np.arange(len(nodes)), [1]),
           solver.fix(s["zmin"], [2]), solver.Prescribed(s["xmax"], [lam - 1, 0, 0], [0])]
    res = solver.newton_solve(body, bcs, steps=3)
    P = res.reactions[s["xmax"], 0].sum()
    expected = 2 * W1(lam * lam + 1 + lam ** -2) * (lam - lam ** -3)
    assert P == pytest.approx(expected, rel=5e-3)


def test_simple_shear():
    nodes, body, s = _cube()
    gamma = 1.0
    boundary = np.unique(np.concatenate([s[k] for k in s]))
    disp = np.zeros((len(boundary), 3))
    disp[:, 0] = gamma * nodes[boundary, 1]
    res = solver.newton_solve(body, [solver.Prescribed(boundary, disp)], steps=2)
    sig = body.cauchy_stress(res.x)
    assert np.allclose(sig[:, 0, 1], 0.72, rtol=5e-3)
    assert np.allclose(sig[:, 0, 1], sig[:, 1, 0], rtol=1e-12, atol=1e-12)
