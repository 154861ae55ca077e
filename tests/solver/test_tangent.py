"""Consistent tangent: the assembled tangent equals a central finite-difference derivative of
the residual (issue 2, check 2), for every material and formulation, on distorted elements,
for the fused Yeoh kernel and for the generic material-protocol path; and Newton converges
quadratically in the log.

Central differences with h = 1e-6 (relative to element size 0.5) have truncation error
O(h^2 |f'''|) ~ 1e-12 and round-off O(eps |f| / h) ~ 1e-10 relative, so 1e-6 relative (the
issue's tolerance) is far above the noise and far below any real tangent error (a missing term
is O(1)).
"""
import numpy as np
import pytest

import solver
from solver.examples import block

MATERIALS = {
    "neo-Hookean": solver.NeoHooke(mu=1.0, K=50.0),
    "Yeoh": solver.Yeoh(0.5, -0.1, 0.02, K=50.0),
    "Yeoh-quadratic-U": solver.Yeoh(2.5, 1.175, 0.3, K=80.0, volumetric="quadratic"),
}


@pytest.fixture(scope="module")
def distorted():
    nodes, hexes, _ = block((1, 1, 1), (2, 1, 1))
    rng = np.random.default_rng(3)
    nodes = nodes + 0.08 * rng.standard_normal(nodes.shape)
    x = nodes + 0.12 * rng.standard_normal(nodes.shape)      # a general (rotated, sheared) state
    return nodes, hexes, x


def _fd_check(body, x, h=1e-6):
    ev = body.evaluate(x)
    Ku = body.pattern.matrix(ev.data).toarray()
    K = Ku + np.triu(Ku, 1).T
    Kfd = np.empty_like(K)
    xf = x.ravel()
    for j in range(xf.size):
        xp = xf.copy()
        xm = xf.copy()
        xp[j] += h
        xm[j] -= h
        Kfd[:, j] = (body.evaluate(xp.reshape(-1, 3), tangent=False).force
                     - body.evaluate(xm.reshape(-1, 3), tangent=False).force) / (2 * h)
    # residual = derivative of the energy
    g = np.empty(xf.size)
    for j in range(xf.size):
        xp = xf.copy()
        xm = xf.copy()
        xp[j] += h
        xm[j] -= h
        g[j] = (body.evaluate(xp.reshape(-1, 3), tangent=False).energy
                - body.evaluate(xm.reshape(-1, 3), tangent=False).energy) / (2 * h)
    return (np.abs(K - Kfd).max() / np.abs(Kfd).max(),
            np.abs(g - ev.force).max() / np.abs(ev.force).max())


@pytest.mark.parametrize("name", sorted(MATERIALS))
@pytest.mark.parametrize("formulation", ["mean_dilatation", "displacement"])
@pytest.mark.parametrize("fused", [True, False])
def test_tangent_matches_finite_differences(distorted, name, formulation, fused):
    nodes, hexes, x = distorted
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), MATERIALS[name], formulation=formulation)
    assert body.fused                      # isotropic Yeoh family: fused kernel by default
    body.fused = fused                     # False: generic path through Material.isochoric
    errK, errf = _fd_check(body, x)
    assert errK < 1e-6
    assert errf < 1e-6


def test_mixed_labels_generic_path(distorted):
    nodes, hexes, x = distorted
    labels = np.array([0, 1])
    mats = {0: MATERIALS["Yeoh"], 1: MATERIALS["neo-Hookean"]}
    body = solver.SolidBody(solver.HexMesh(nodes, hexes, labels), mats)
    errK, errf = _fd_check(body, x)
    assert errK < 1e-6 and errf < 1e-6


def test_quadratic_convergence_in_log():
    nodes, hexes, s = block((1, 1, 1), (3, 3, 3))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(0.5, -0.1, 0.02, K=500))
    records = []
    solver.newton_solve(body, [solver.fix(s["zmin"]), solver.Prescribed(s["zmax"], [0.2, 0, 0.4])],
                        steps=2, rtol=1e-12, callback=records.append)
    r = [rec["relative_residual"] for rec in records if rec["step"] == 1]
    # asymptotic quadratic rate: log r_{k+1} / log r_k -> 2; demand > 1.6 on the last pair
    # above round-off (1e-13), which linear or superlinear-only convergence cannot give
    pairs = [(a, b) for a, b in zip(r[:-1], r[1:]) if b > 1e-13 and a < 1e-2]
    assert pairs, r
    a, b = pairs[-1]
    assert np.log(b) / np.log(a) > 1.6, r
