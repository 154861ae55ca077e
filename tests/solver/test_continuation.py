"""Pseudo-transient continuation (`solver.continuation`): a snap-through Newton cannot pass.

Every node of an elastic block is held by a double-well spring in z, f(u) = k u (u - a)(u - 2a)
(wells at u = 0 and 2a), and springs k2 u in x and y, and pushed along +z by a dead force F
per node. A uniform translation costs no elastic energy, so the equilibrium is the uniform
translation u* solving f(u*) = F. For F above the spring's local maximum f_max =
2 k a^3 / (3 sqrt 3) the branch through u = 0 ends at load F_load = f_max / F (a limit point)
and the solution snaps to the far branch u* > 2a. Under load stepping with the step-length
limit and stagnation test the face uses, Newton cannot pass the limit point: past it, its
update heads back to the limit point (the tangent is negative between the spring's extrema),
every step fails and the step falls below its minimum. With continuation (on after two
failed steps, the default) the solve reaches load 1; the answer is checked against the root of
the cubic and against the undamped residual, recomputed independently of the solver.
"""
import numpy as np
import pytest
import scipy.sparse as sp

import solver
from solver.continuation import PseudoTransient
from solver.errors import SolveFailed
from solver.examples import block
from solver.terms import Term

K_SPRING, A_WELL, K_SIDE, F_NODE = 100.0, 0.5, 100.0, 10.0


class DoubleWell(Term):
    """f_z = k u (u - a)(u - 2a), f_x,y = k2 u at every node (potential k u^2 (u - 2a)^2 / 4)."""

    def __init__(self, X):
        self.X = X

    def forces(self, x):
        u = x - self.X
        f = np.empty_like(u)
        d = np.empty_like(u)
        uz = u[:, 2]
        f[:, 2] = K_SPRING * uz * (uz - A_WELL) * (uz - 2 * A_WELL)
        d[:, 2] = K_SPRING * (3 * uz ** 2 - 6 * A_WELL * uz + 2 * A_WELL ** 2)
        f[:, :2] = K_SIDE * u[:, :2]
        d[:, :2] = K_SIDE
        return f.ravel(), d.ravel()

    def assemble(self, x, load):
        f, d = self.forces(x)
        return f, sp.diags(d).tocoo()

    def energy(self, x, load):
        u = x - self.X
        return float(np.sum(K_SPRING * u[:, 2] ** 2 * (u[:, 2] - 2 * A_WELL) ** 2 / 4)
                     + 0.5 * K_SIDE * np.sum(u[:, :2] ** 2))


def _problem(mu=50.0):
    nodes, hexes, _ = block((1.0, 1.0, 1.0), (2, 2, 2))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.NeoHooke(mu=mu, K=50.0 * mu))
    external = np.zeros((len(nodes), 3))
    external[:, 2] = F_NODE
    return nodes, body, DoubleWell(nodes), external.ravel()


# the face's rules: no node moves more than a length per update, a step whose residual has
# not fallen to a tenth in 8 iterations is cut back
FACE_LIKE = dict(steps=10, max_increment=0.1, stall_iterations=8, rtol=1e-8)


def test_snap_through_fails_without_continuation():
    f_max = 2 * K_SPRING * A_WELL ** 3 / (3 * np.sqrt(3))
    assert F_NODE > 1.5 * f_max                # the limit point is inside the load path
    _, body, term, external = _problem()
    with pytest.raises(SolveFailed) as failed:
        solver.newton_solve(body, [], [term], external=external, ptc_after=None, **FACE_LIKE)
    # it fails at the limit point, not before
    assert failed.value.last_converged_load == pytest.approx(f_max / F_NODE, abs=0.02)


@pytest.mark.parametrize("mu", [5.0, 200.0])
def test_snap_through_with_continuation_reaches_the_far_branch(mu):
    nodes, body, term, external = _problem(mu)
    res = solver.newton_solve(body, [], [term], external=external, **FACE_LIKE)
    assert res.converged and res.load == 1.0
    assert res.continuation_from is not None and res.continuation_iterations > 0
    roots = np.roots([K_SPRING, -3 * A_WELL * K_SPRING, 2 * A_WELL ** 2 * K_SPRING, -F_NODE])
    u_star = max(r.real for r in roots if abs(r.imag) < 1e-9)
    assert u_star > 2 * A_WELL
    # residual <= rtol * (force scale ~ 27 * F): an error in u of that over the spring's
    # stiffness f'(u*) ~ 100 N/mm, far below 1e-6 mm
    np.testing.assert_allclose(res.u[:, 2], u_star, atol=1e-6)
    np.testing.assert_allclose(res.u[:, :2], 0.0, atol=1e-6)
    # the converged residual is the undamped one: body force + spring force - F, recomputed
    ev = body.evaluate(res.x, 1.0, tangent=False)
    r = ev.force + term.forces(res.x)[0] - external
    assert np.linalg.norm(r) <= 1e-8 * np.linalg.norm(external)


def test_damping_schedule():
    """The damping acts on the free diagonal only, follows the residual (switched evolution
    relaxation), falls while updates are taken in full and rises when one was shortened or
    went uphill; a converged step that did not need it starts the next with a tenth of it,
    down to a floor; a failed step starts the next from delta0."""
    A = sp.csr_matrix(np.array([[4.0, 1.0, 0.0], [0.0, -2.0, 1.0], [0.0, 0.0, 9.0]]))
    diag = np.array([0, 2, 4])                  # positions of the diagonal in A.data
    ptc = PseudoTransient(1.0, diag[[0, 1]], fade=1e-3, relax=0.1)
    ptc.start(10.0)
    B = ptc.damped(A)
    np.testing.assert_allclose(B.toarray() - A.toarray(), np.diag([4.0, 2.0, 0.0]))
    assert ptc.delta == 1.0
    assert ptc.advance(10.0) == pytest.approx(0.5)             # full step: ramp halved
    assert ptc.advance(1.0) == pytest.approx(0.025)            # and residual / 10
    assert ptc.advance(1.0, full=False) == pytest.approx(0.05)  # shortened: doubled
    assert ptc.raise_damping() == pytest.approx(0.5)           # uphill: ten times
    # a full update that raised the residual more than ten times: SER's factor (x 20) and
    # ten times the ramp; the good update after it halves the ramp only (the memory stays)
    assert ptc.advance(20.0) == pytest.approx(0.5 * 20 * 10)
    assert ptc.advance(1.0) == pytest.approx(0.5 * 10 / 2)
    ptc.advance(1.0)
    ptc.start(20.0, again=True)     # a re-solve from twice the step's residual
    assert ptc.delta == pytest.approx(2.0)
    assert ptc.step_converged()             # the damping was needed: kept
    ptc.start(10.0)
    assert ptc.delta == 1.0
    ptc.advance(1.0)
    for _ in range(4):
        ptc.step_converged()            # 0.1, 0.01, 0.001, then no lower than 1e-3 delta0
    ptc.start(5.0)
    assert ptc.delta == pytest.approx(1e-3)
    ptc.step_failed()
    ptc.start(5.0)
    assert ptc.delta == 1.0


class Saturating(Term):
    """f_z = f_max tanh(u / a) at every node, f_x,y = k2 u: a spring whose force is bounded
    by f_max (potential f_max a log cosh(u / a))."""

    def __init__(self, X, f_max, a=0.1):
        self.X, self.f_max, self.a = X, f_max, a

    def assemble(self, x, load):
        u = x - self.X
        f = np.empty_like(u)
        d = np.empty_like(u)
        t = np.tanh(u[:, 2] / self.a)
        f[:, 2] = self.f_max * t
        d[:, 2] = self.f_max / self.a * (1.0 - t * t)
        f[:, :2] = K_SIDE * u[:, :2]
        d[:, :2] = K_SIDE
        return f.ravel(), sp.diags(d.ravel()).tocoo()

    def energy(self, x, load):
        u = x - self.X
        return float(np.sum(self.f_max * self.a * np.log(np.cosh(u[:, 2] / self.a)))
                     + 0.5 * K_SIDE * np.sum(u[:, :2] ** 2))


def _hopeless(**settings):
    """The block of `_problem` on springs whose force saturates at half the dead load: a
    uniform translation costs no elastic energy, so no equilibrium exists beyond load 0.5.
    Returns the `SolveFailed` the run ends with."""
    nodes, body, _, external = _problem()
    term = Saturating(nodes, 0.5 * F_NODE)
    with pytest.raises(SolveFailed) as failed:
        solver.newton_solve(body, [], [term], external=external, **FACE_LIKE, **settings)
    return failed.value


def test_continuation_budget_ends_a_hopeless_solve():
    # Without the budget every halving of the step down to `min_step` runs damped solves of
    # `ptc_iterations` each; with it the run fails after `ptc_max_failures` consecutive damped
    # steps, each within `ptc_step_iterations` iterations over all its solves, and says so
    unbounded = _hopeless(ptc_step_iterations=None, ptc_max_failures=None)
    budget = dict(ptc_step_iterations=40, ptc_max_failures=3)
    bounded = _hopeless(**budget)
    for failed in (unbounded, bounded):
        assert failed.last_converged_load <= 0.5 + 1e-9        # no equilibrium beyond 0.5
        assert failed.state.continuation_from is not None
    assert "consecutive load steps failed under pseudo-transient continuation" in str(bounded)
    assert bounded.state.continuation_iterations <= 3 * 40
    # the unbounded run halves the step down to 1e-4 (about ten damped steps of 60)
    assert unbounded.state.continuation_iterations > 3 * bounded.state.continuation_iterations
