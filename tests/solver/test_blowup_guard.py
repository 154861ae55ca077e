"""The blow-up guard of `newton_solve` (`SolverControl.blowup_factor`).

A Yeoh block, its base fixed, pulled up at its top by a dead load, with a tether on the top
nodes whose force grows exponentially once they rise beyond a height a: f = c (exp((u - a)/l)
- 1) for u > a, nothing below (a stiffening of the kind an exponential fibre law has). The
increment limiter (0.4 of the linear answer u_lin) makes the first Newton updates short, so a
later update, its tangent not yet knowing the tether, overshoots a by up to 0.2 u_lin = 50 l:
the tether force there is up to e^50 times c, far beyond every force of the iterate it started
from. Without the guard that iterate is taken: Newton either crawls back about l an iteration
(the exponential's Newton steps from above) or its residual diverges and the step is cut back.
With it the update is halved back below the blow-up and Newton converges in one load step.
Both must end at the same equilibrium (the same tolerances on the same mesh: displacements
agree to 1e-6 relative).
"""
import numpy as np
import pytest
import scipy.sparse as sp

import solver
from solver.examples import block
from solver.terms import Term


class _Tether(Term):
    """Vertical force c (exp((u_z - a) / l) - 1) on `nodes` where u_z > a (a stiffening
    tether), with its exact tangent."""

    static_state = ("nodes", "X", "c", "a", "l")

    def __init__(self, nodes, X, c, a, l):
        self.nodes, self.X, self.c, self.a, self.l = np.asarray(nodes), X, c, a, l

    def _parts(self, x):
        u = x[self.nodes, 2] - self.X[self.nodes, 2]
        arg = np.minimum((u - self.a) / self.l, 700.0)
        on = u > self.a
        e = np.exp(np.where(on, arg, 0.0))
        return on, e

    def assemble(self, x, load):
        on, e = self._parts(x)
        f = np.zeros(x.size)
        dofs = 3 * self.nodes + 2
        f[dofs] = np.where(on, self.c * (e - 1.0), 0.0)
        k = np.where(on, self.c * e / self.l, 0.0)
        K = sp.coo_matrix((k, (dofs, dofs)), shape=(x.size, x.size))
        return f, K

    def energy(self, x, load):
        on, e = self._parts(x)
        u = x[self.nodes, 2] - self.X[self.nodes, 2]
        return float(np.sum(np.where(on, self.c * (self.l * (e - 1.0) - (u - self.a)), 0.0)))


def _solve(blowup_factor, steps=1, limited=True):
    nodes, hexes, s = block((1.0, 1.0, 1.0), (2, 2, 2))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(2.0, 0.0, 0.0, K=200.0))
    top = np.asarray(s["zmax"])
    force = 1.0                                    # mN in all, spread over the top nodes
    f_ext = np.zeros(nodes.size)
    f_ext[3 * top + 2] = force / len(top)
    # the linear answer of the untethered block (a first solve), to place the tether
    free = solver.newton_solve(body, [solver.fix(s["zmin"])], external=f_ext, steps=1,
                               rtol=1e-10)
    u_lin = float(free.u[top, 2].mean())
    l = 0.004 * u_lin
    tether = _Tether(top, nodes, c=1e-3 * force / len(top), a=0.6 * u_lin, l=l)
    res = solver.newton_solve(body, [solver.fix(s["zmin"])], terms=[tether], external=f_ext,
                              steps=steps, max_iterations=60, rtol=1e-10, ptc_after=None,
                              max_increment=0.4 * u_lin if limited else None,
                              increment_nodes=top, blowup_factor=blowup_factor, grow=False)
    return res, u_lin, tether


def test_guard_halves_the_overshoot_and_saves_the_crawl():
    guarded, u_lin, tether = _solve(100.0)
    unguarded, _, _ = _solve(None)
    assert guarded.converged and unguarded.converged
    assert unguarded.blowups_halved == 0
    assert guarded.blowups_halved >= 1
    # guarded: one load step, a few limited iterations and Newton's quadratic end
    assert guarded.cutbacks == 0
    assert guarded.iterations <= 15, guarded.iterations
    # unguarded: the crawl back from the overshoot (about 50 iterations of l), or diverging
    # steps cut back; either way at least twice the guarded count
    assert unguarded.iterations >= 2 * guarded.iterations, (unguarded.iterations,
                                                            guarded.iterations)
    # the tether holds the top: its highest node just above a (where the tether's force,
    # c (e^((u-a)/l) - 1), takes the load a few l beyond a), none further
    u_top = guarded.u[tether.nodes, 2]
    assert tether.a < u_top.max() < tether.a + 10 * tether.l
    scale = np.abs(guarded.u).max()
    assert np.abs(guarded.u - unguarded.u).max() < 1e-6 * scale


def test_guard_on_a_steps_first_update():
    """Two load steps, no increment limit: the first (half the load) ends below the tether's
    start a = 0.6 u_lin; the second step's first update, the tangent of the converged state,
    lands at u_lin, 100 tether lengths beyond a. That update starts from a converged state
    (its forces the reactions alone), so the guard measures it against the first step's
    iterates, and halves it. Unguarded, the blown-up iterate is taken and Newton crawls back
    about l an iteration from 100 l beyond a; guarded, the accepted iterates overshoot only
    as far as a residual of 100 times the forces reaches, a few l beyond the root, so the
    crawl back is shorter: at most two thirds of the iterations."""
    guarded, _, tether = _solve(100.0, steps=2, limited=False)
    unguarded, _, _ = _solve(None, steps=2, limited=False)
    assert guarded.converged and unguarded.converged
    assert guarded.blowups_halved >= 1 and unguarded.blowups_halved == 0
    assert guarded.cutbacks == 0
    assert 3 * guarded.iterations <= 2 * unguarded.iterations, (unguarded.iterations,
                                                                guarded.iterations)
    scale = np.abs(guarded.u).max()
    assert np.abs(guarded.u - unguarded.u).max() < 1e-6 * scale


def test_guard_setting_is_checked():
    with pytest.raises(ValueError, match="blowup_factor"):
        solver.SolverControl(blowup_factor=0.5)
