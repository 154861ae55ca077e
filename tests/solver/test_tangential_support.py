"""The tangential elastic support (`solver.loads.TangentialSupport`) against exact answers.

* Its stiffness is the central finite difference of its force, and its force the gradient of
  its energy (1e-8 relative: the term is quadratic, so the differences are exact up to
  round-off).
* It acts in the tangent plane only: a slip along the normal costs no energy and no force.
* A column in simple shear on the support (the top displaced by U along x, every node held in
  y and z, so that the only deformation is a shear of the layer and a slip at its base): the
  layer of height H and shear modulus mu in series with the interface of stiffness k per unit
  area slips by s = U / (1 + k H / mu) (module text of `solver.loads`). Tolerance 1e-3
  relative: the finite-strain terms of simple shear are of order gamma^2 = 4e-4 at the strains
  used (gamma <= 0.02), and the free sides of the column carry the normal stress they would
  need to stay homogeneous only to that order. With k = 0 the base slides freely (s = U, a
  rigid translation); with k large it is nearly tied.
"""
import numpy as np
import pytest

import solver
from solver.examples import block


def _support(n=5, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n + 3, 3))
    nodes = np.arange(1, n + 1)
    normals = rng.standard_normal((n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    k = rng.uniform(0.5, 2.0, n)
    anchor = rng.standard_normal((n, 3))
    term = solver.TangentialSupport(nodes, normals, k, lambda load: load * anchor, X)
    return term, X, nodes, normals, rng


def test_stiffness_and_force_are_derivatives():
    term, X, nodes, normals, rng = _support()
    x = X + 0.3 * rng.standard_normal(X.shape)
    f, K = term.assemble(x, 0.7)
    K = K.toarray()
    assert np.abs(K - K.T).max() < 1e-14
    h = 1e-6
    Kfd = np.empty_like(K)
    g = np.empty(x.size)
    for j in range(x.size):
        e = np.zeros(x.size)
        e[j] = h
        xp, xm = (x.ravel() + e).reshape(-1, 3), (x.ravel() - e).reshape(-1, 3)
        Kfd[:, j] = (term.assemble(xp, 0.7)[0] - term.assemble(xm, 0.7)[0]) / (2 * h)
        g[j] = (term.energy(xp, 0.7) - term.energy(xm, 0.7)) / (2 * h)
    assert np.abs(K - Kfd).max() < 1e-8 * np.abs(K).max()
    assert np.abs(f - g).max() < 1e-8 * np.abs(f).max()


def test_normal_slip_is_free():
    term, X, nodes, normals, rng = _support(seed=1)
    x = X.copy()
    x[nodes] += term.anchor(1.0) + 0.4 * normals          # anchor plus a normal offset only
    f, _ = term.assemble(x, 1.0)
    assert np.abs(f).max() < 1e-12
    assert abs(term.energy(x, 1.0)) < 1e-12


@pytest.mark.parametrize("kH_over_mu", [0.0, 1.0, 4.0])
def test_sheared_column_slips_as_a_series_spring(kH_over_mu):
    mu, H, U = 3.0, 4.0, 0.08                      # gamma <= U / H = 0.02
    nodes, hexes, s = block((1.0, 1.0, H), (1, 1, 4))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), {0: solver.NeoHooke(mu, 1000.0 * mu)})
    base, top = s["zmin"], s["zmax"]
    middle = np.setdiff1d(np.arange(len(nodes)), np.union1d(base, top))
    k_area = kH_over_mu * mu / H
    area = np.full(len(base), 0.25)                 # the unit base face shared by its 4 nodes
    frames = np.broadcast_to(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), (len(base), 3, 3))
    cons = [solver.Prescribed(top, [U, 0.0, 0.0]),
            solver.Prescribed(middle, 0.0, (1, 2)),
            solver.LocalFrame(base, frames, fixed=(0, 2))]
    terms = [solver.TangentialSupport(base, [0.0, 0.0, 1.0], k_area * area, 0.0, nodes)]
    res = solver.newton_solve(body, cons, terms, steps=1)
    slip = res.u[base, 0]
    expected = U / (1.0 + kH_over_mu)
    assert np.allclose(slip, expected, rtol=1e-3, atol=1e-3 * U)


def test_bad_input_is_refused():
    X = np.zeros((3, 3))
    with pytest.raises(solver.BoundaryConditionError):
        solver.TangentialSupport([0], [0, 0, 2.0], 1.0, 0.0, X)        # not a unit normal
    with pytest.raises(solver.BoundaryConditionError):
        solver.TangentialSupport([0], [0, 0, 1.0], -1.0, 0.0, X)       # negative stiffness
    with pytest.raises(solver.BoundaryConditionError):
        solver.TangentialSupport([5], [0, 0, 1.0], 1.0, 0.0, X)        # outside the mesh
