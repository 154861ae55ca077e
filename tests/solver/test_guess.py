"""The full load solved from a nearby solution on the same mesh, `newton_solve(guess=...)`.

A nonlinear elastic problem with a unique equilibrium has the same solution whichever path
Newton takes to it. Cook's membrane (nearly incompressible neo-Hookean, Q1/P0, as in
tests/solver/test_cook.py) with its shear modulus 10 % higher, started from the solution with
the original modulus, converges at full load in one step to the answer the load-stepped solve
reaches. A guess from which the full load does not converge (one that inverts the elements)
leaves the solve to step the load from the reference state, as without it. With a contact term
(the block pressed on a rigid plane of tests/solver/test_contact_blocks.py) a deeper press
started from the shallower one's solution is augmented from there as in any load step and ends
at the contact state of the stepped solve.
"""
import numpy as np
import pytest

import solver
from solver.examples import cook_membrane
from tests.solver.test_contact_blocks import _pressed_block

MU, K = 80.1938, 400942.0


def _cook(n, mu=MU):
    nodes, hexes, s = cook_membrane(n, thickness=1.0)
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.NeoHooke(mu=mu, K=K),
                            formulation="mean_dilatation")
    f = solver.surface_traction(nodes, s["right_facets"], [0.0, 6.25, 0.0])
    bcs = [solver.fix(s["left"]), solver.fix(np.arange(len(nodes)), [2])]
    return nodes, body, bcs, f.ravel()


@pytest.fixture(scope="module")
def cook():
    nodes, body, bcs, f = _cook(8)
    before = solver.newton_solve(body, bcs, external=f, steps=4)
    nodes, body, bcs, f = _cook(8, 1.1 * MU)
    stepped = solver.newton_solve(body, bcs, external=f, steps=4)
    return nodes, before, stepped


def test_a_nearby_solution_converges_at_full_load_to_the_stepped_answer(cook):
    nodes, before, stepped = cook
    _, body, bcs, f = _cook(8, 1.1 * MU)
    direct = solver.newton_solve(body, bcs, external=f, steps=4, guess=before.x)
    assert direct.converged and direct.guess["converged"]
    assert len(direct.steps) == 1 and direct.steps[0].load == 1.0
    # a 10 % stiffer membrane deflects visibly less: the guess is not the answer
    assert np.abs(before.u - stepped.u).max() > 0.05 * np.abs(stepped.u).max()
    # the same equilibrium: both solves stop at the relative residual rtol (1e-6 by default),
    # where the displacement agrees to that order times the conditioning of the nearly
    # incompressible tangent; 1e-5 of the tip deflection (~7 mm) is 7e-5 mm
    assert np.abs(direct.u - stepped.u).max() < 1e-5 * np.abs(stepped.u).max()
    # and in fewer Newton iterations than stepping the load four times from rest
    assert direct.iterations < stepped.iterations


def test_a_guess_that_does_not_converge_falls_back_to_load_steps(cook):
    nodes, before, stepped = cook
    _, body, bcs, f = _cook(8, 1.1 * MU)
    bad = nodes * np.array([-1.0, 1.0, 1.0])          # mirrored: every element inverted
    with np.errstate(invalid="ignore", divide="ignore"):
        res = solver.newton_solve(body, bcs, external=f, steps=4, guess=bad)
    assert res.converged and not res.guess["converged"]
    assert len(res.steps) >= 4
    assert np.abs(res.u - stepped.u).max() < 1e-5 * np.abs(stepped.u).max()


def test_a_guess_of_the_wrong_shape_is_refused():
    nodes, body, bcs, f = _cook(4)
    with pytest.raises(ValueError, match="guess must have shape"):
        solver.newton_solve(body, bcs, external=f, guess=nodes[:-1])


def test_contact_augmented_from_a_nearby_solution_ends_at_the_stepped_contact_state():
    body, contact, cons = _pressed_block()
    shallow = solver.newton_solve(body, cons, [contact], steps=4, max_retries=20)
    deeper = [solver.bc.Prescribed(c.nodes, [0.0, 0.0, -0.45], (2,)) if i == 0 else c
              for i, c in enumerate(cons)]
    body, contact, _ = _pressed_block()
    stepped = solver.newton_solve(body, deeper, [contact], steps=4, max_retries=20)
    p_stepped = contact.contact_pressure(stepped.x, 1.0)
    body, contact, _ = _pressed_block()
    direct = solver.newton_solve(body, deeper, [contact], steps=4, max_retries=20,
                                 guess=shallow.x)
    assert direct.guess["converged"] and len(direct.steps) == 1
    g, *_ = contact.gaps(direct.x, 1.0)
    assert -np.nanmin(g) < 1e-3                                  # augmented to tolerance
    # the stepped solve's homogeneous pressure: both end within the contact tolerance (1e-3 mm
    # of a 2 mm block, a strain of 5e-4 whose stress is ~1e-3 of the pressure)
    p = contact.contact_pressure(direct.x, 1.0)
    assert p.mean() == pytest.approx(p_stepped.mean(), rel=5e-3)
    assert np.abs(direct.x - stepped.x).max() < 2e-3
