"""The solver's control objects (`solver.control`) and the `Term` hooks, against their rules.

* StepController: growth after easy steps up to the initial size, halving after a hard first
  solve, cut-back to half the failed step and failure below the minimum step (exact
  arithmetic on powers of two: compared exactly).
* Predictor / extrapolate: Lagrange extrapolation reproduces a linear path from two states and
  a quadratic one from three (to 1e-12, round-off of a few products).
* ConvergenceCriterion and IncrementLimiter: their thresholds on hand-made figures.
* newton_solve: the keyword arguments and `control=SolverControl(...)` give the same solve
  (the same iterations, x to round-off 1e-12 mm); a term that does not derive from `Term` (only
  `assemble`, `energy`, `end_step`) is solved like the same term deriving from it; an unknown
  setting is refused.
"""
import numpy as np
import pytest
import scipy.sparse as sp

import solver
from solver.control import (ConvergenceCriterion, IncrementLimiter, Predictor, SolverControl,
                            StepController, extrapolate)
from solver.examples import block
from solver.terms import Term, as_term


def test_step_controller_grows_shrinks_and_cuts_back():
    c = StepController(SolverControl(steps=4, min_step=1.0 / 64, shrink_iterations=7))
    assert c.target(0.0) == 0.25
    c.cut_back(0.0, 0.25)
    assert c.dt == 0.125
    c.converged(iterations=3, first_iterations=3)        # easy: grows by 1.5
    assert c.dt == 0.1875
    c.converged(iterations=3, first_iterations=3)
    assert c.dt == 0.25                                   # never beyond the initial size
    c.converged(iterations=9, first_iterations=9)        # hard first solve: halved
    assert c.dt == 0.125
    assert c.target(0.9) == 1.0                           # a short last step is merged
    assert c.cut_back(0.5, 0.5 + 1.0 / 32)               # 1/64 is still allowed
    assert not c.cut_back(0.5, 0.5 + 1.0 / 64)           # 1/128 is below the minimum


def test_extrapolation_is_exact_on_linear_and_quadratic_paths():
    x1 = np.array([[1.0, 2.0, 3.0]])
    v = np.array([[0.5, -1.0, 2.0]])
    a = np.array([[0.3, 0.1, -0.7]])
    path = lambda t: x1 + t * v + t * t * a       # noqa: E731
    lin = lambda t: x1 + t * v                    # noqa: E731
    x, mixed = extrapolate([(0.2, lin(0.2), None), (0.5, lin(0.5), None)], 0.8)
    assert mixed is None and np.allclose(x, lin(0.8), atol=1e-12)
    x, _ = extrapolate([(0.1, path(0.1), None), (0.3, path(0.3), None),
                        (0.6, path(0.6), None)], 0.9)
    assert np.allclose(x, path(0.9), atol=1e-12)
    p = Predictor("secant", 2, (0.0, lin(0.0), None))
    assert p.start(0.5) is None                   # one state: no extrapolation
    p.converged(0.25, lin(0.25), None)
    assert np.allclose(p.start(0.5)[0], lin(0.5), atol=1e-12)
    p.cut_back()
    assert p.start(0.5) is None                   # after a cut-back: tangent start
    assert Predictor("tangent", 2, (0.0, lin(0.0), None)).start(0.5) is None


def test_convergence_criterion_and_increment_limiter():
    c = ConvergenceCriterion(rtol=1e-6, atol=1e-10, etol=1e-8, stall_iterations=3)
    assert c.converged(2, 0.5e-6, 1.0, 1e-9, 1.0, 0.0, 1e-10)
    assert not c.converged(2, 2e-6, 1.0, 1e-9, 1.0, 0.0, 1e-10)       # residual too large
    assert not c.converged(2, 0.5e-6, 1.0, 1e-7, 1.0, 0.0, 1e-10)     # energy too large
    assert not c.converged(2, 0.5e-6, 1.0, 1e-9, 1.0, 1e-3, 1e-10)    # target not reached
    assert c.stalled(3, [1.0, 0.5, 0.2]) and not c.stalled(3, [1.0, 0.5, 0.05])
    assert c.diverges(4, [1.0, 2.0, 3.0, 2e6]) and not c.diverges(3, [1.0, 2.0, 2e6])
    du = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 10.0]])
    assert IncrementLimiter(None, np.arange(2)).step_length(du) == 1.0
    assert IncrementLimiter(2.0, np.array([0])).step_length(du) == pytest.approx(0.4)
    assert IncrementLimiter(20.0, np.arange(2)).step_length(du) == 1.0


class _Spring(Term):
    """Linear springs pulling nodes towards anchors: f = k (x - a), a conservative term."""

    def __init__(self, nodes, anchors, k, n):
        self.nodes, self.anchors, self.k, self.n = nodes, anchors, k, n

    def assemble(self, x, load):
        f = np.zeros(3 * self.n)
        dofs = (3 * self.nodes[:, None] + np.arange(3)).ravel()
        f[dofs] = self.k * (x[self.nodes] - self.anchors).ravel()
        return f, sp.coo_matrix((np.full(len(dofs), self.k), (dofs, dofs)),
                                shape=(3 * self.n, 3 * self.n))

    def energy(self, x, load):
        return 0.5 * self.k * float(np.sum((x[self.nodes] - self.anchors) ** 2))

    def end_step(self, x, load):
        return False


class _PlainSpring:
    """The same spring not deriving from `Term`: only assemble, energy and end_step."""

    def __init__(self, *args):
        self.spring = _Spring(*args)

    def assemble(self, x, load):
        return self.spring.assemble(x, load)

    def energy(self, x, load):
        return self.spring.energy(x, load)

    def end_step(self, x, load):
        return False


def _problem():
    nodes, hexes, s = block((1, 1, 1), (2, 2, 2))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes),
                            {0: solver.Yeoh(C10=0.5, C20=-0.1, C30=0.02, K=50.0)})
    bcs = [solver.fix(s["zmin"]), solver.Prescribed(s["zmax"], [0.0, 0.0, 0.3])]
    top = np.asarray(s["xmax"])
    spring = (top, nodes[top] + [0.2, 0.0, 0.0], 0.1, len(nodes))
    return body, bcs, spring


def test_keywords_and_control_give_the_same_solve():
    body, bcs, spring = _problem()
    a = solver.newton_solve(body, bcs, [_Spring(*spring)], steps=3, rtol=1e-9)
    body, bcs, spring = _problem()
    b = solver.newton_solve(body, bcs, [_Spring(*spring)],
                            control=SolverControl(steps=3, rtol=1e-9))
    assert a.converged and b.converged and a.iterations == b.iterations
    assert np.abs(a.x - b.x).max() < 1e-12
    with pytest.raises(TypeError):
        solver.newton_solve(body, bcs, steps=3, no_such_setting=1)


def test_a_term_without_the_base_class_still_works():
    body, bcs, spring = _problem()
    a = solver.newton_solve(body, bcs, [_Spring(*spring)], steps=3)
    body, bcs, spring = _problem()
    plain = _PlainSpring(*spring)
    adapted = as_term(plain)
    assert isinstance(adapted, Term) and adapted.spring is plain.spring
    assert adapted.augmentation_due(None, 1.0) is False and len(adapted.coupling_pairs()) == 0
    b = solver.newton_solve(body, bcs, [plain], steps=3)
    assert a.iterations == b.iterations and np.abs(a.x - b.x).max() < 1e-12
    # the spring pulls the x = 1 face towards +x against its lateral contraction: a real
    # effect, not a zero term
    body, bcs, spring = _problem()
    c = solver.newton_solve(body, bcs, steps=3)
    assert (a.u[spring[0], 0] - c.u[spring[0], 0]).mean() > 1e-3
