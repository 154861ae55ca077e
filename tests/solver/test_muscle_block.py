"""Muscle blocks solved with the FE core: isometric fibre bundle and free contraction."""
import numpy as np
import pytest
from scipy.optimize import brentq

from solver.bc import Prescribed, fix
from solver.constitution.muscle import Muscle, force_length
from solver.mechanics import SolidBody
from solver.mesh import HexMesh
from solver.newton import newton_solve


def box(n, size):
    """Structured hex box [0, Lx] x [0, Ly] x [0, Lz] with n = (nx, ny, nz) cells, VTK order."""
    nx, ny, nz = n
    g = [np.linspace(0, L, k + 1) for L, k in zip(size, n)]
    X, Y, Z = np.meshgrid(*g, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz),
                                              indexing="ij"))
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1],
                      idx[i, j + 1, k + 1]], axis=1)
    return nodes, hexes


PARAMS = dict(C10=2.5, C20=1.175, C30=0.0, K=25000.0, k1=5.0, k2=4.0, T_max=100.0,
              lam_opt=1.1, width=0.5, G_T=1.0, G_T_active=10.0)


def _solve(activation, ends_fixed):
    nodes, hexes = box((3, 2, 2), (12.0, 4.0, 4.0))
    mesh = HexMesh(nodes, hexes)
    fibres = np.tile([1.0, 0.0, 0.0], (len(hexes), 1))
    body = SolidBody(mesh, Muscle(**PARAMS, activation=activation), fibres=fibres)
    x0, x1 = nodes[:, 0] < 1e-9, nodes[:, 0] > 12.0 - 1e-9
    cons = [fix(np.nonzero(x0)[0], (0,)), fix(np.nonzero(nodes[:, 1] < 1e-9)[0], (1,)),
            fix(np.nonzero(nodes[:, 2] < 1e-9)[0], (2,))]
    if ends_fixed:
        cons.append(fix(np.nonzero(x1)[0], (0,)))
    res = newton_solve(body, cons, steps=4)
    return nodes, body, res, x1


def _homogeneous_isometric_stress(mat, a0=(1.0, 0.0, 0.0)):
    """Exact homogeneous solution of the isometric bundle: F = diag(1, s, s) with the lateral
    Cauchy stress zero (scalar root in s), returns (s, sigma_11)."""
    def sigma(s):
        F = np.diag([1.0, s, s])
        C = (F.T @ F)[None]
        S, _, _ = mat.isochoric(C, np.array([a0]))
        J = s * s
        _, dU, _ = mat.volumetric(np.array([J]))
        return F @ S[0] @ F.T / J + dU[0] * np.eye(3)
    s = brentq(lambda s: sigma(s)[1, 1], 0.9, 1.1, xtol=1e-14)
    return s, sigma(s)[0, 0]


def test_isometric_fibre_bundle_gives_the_analytic_active_force():
    """Both ends held at fixed length, lateral faces free: F = a T_max f(1) A0 / lam_opt."""
    a = 0.8
    nodes, body, res, x1 = _solve(a, ends_fixed=True)
    force = res.reactions[x1, 0].sum()            # internal force at the held end (mN)
    mat = Muscle(**PARAMS, activation=a)
    s, s11 = _homogeneous_isometric_stress(mat)
    # the FE state is the homogeneous one: force to the solver tolerance (1e-6 relative)
    assert force == pytest.approx(s11 * (4.0 * s) ** 2, rel=1e-6)
    assert np.allclose(res.x[:, 1], s * nodes[:, 1], atol=1e-8)
    # incompressible limit: the active force a T_max f(1) A0 / lam_opt (the nominal stress follows
    # the force-length relation; at the held length lam = 1, A = A0); the finite bulk modulus
    # (K / T_max = 250) changes J by O(sigma/K) ~ 1e-3, which moves f and A by as much: 1 %
    expected = a * 100.0 * force_length(1.0, 1.1, 0.5) / 1.1 * 16.0
    assert force == pytest.approx(expected, rel=1e-2)


def test_free_block_contracts_along_fibres_and_bulges_laterally_at_constant_volume():
    a = 1.0
    nodes, body, res, x1 = _solve(a, ends_fixed=False)
    mat = Muscle(**PARAMS, activation=a)
    lam = brentq(lambda s: mat.uniaxial_fibre_stress(s), 0.3, 1.0)
    assert lam < 0.95                                    # a real contraction
    F = body.deformation_gradient(res.x)
    # free, homogeneous: total stress zero, so U'(J) = 0 and J = 1 (solver tolerance)
    J = np.linalg.det(F)
    assert np.abs(J - 1.0).max() < 1e-3
    assert np.allclose(F[..., 0, 0], lam, rtol=1e-6)
    assert np.allclose(F[..., 1, 1], lam ** -0.5, rtol=1e-6)
    assert np.allclose(F[..., 2, 2], lam ** -0.5, rtol=1e-6)
