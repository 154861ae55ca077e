"""The run's wall-clock budget, `SolverControl.max_seconds`.

A run whose budget is never spent takes the same path to the same answer as one without a
budget; a run whose budget is spent ends at once with `SolveFailed` naming the budget and the
load reached (no cut-back is tried: a shorter step cannot be afforded either), its last
converged state kept. Cook's membrane as in tests/solver/test_guess.py; the per-iteration
callback sleeps so that the budget is spent after a few iterations whatever the machine.
"""
import time

import numpy as np
import pytest

import solver
from tests.solver.test_guess import _cook


def test_a_budget_not_spent_changes_nothing():
    _, body, bcs, f = _cook(4)
    free = solver.newton_solve(body, bcs, external=f, steps=4)
    _, body, bcs, f = _cook(4)
    budget = solver.newton_solve(body, bcs, external=f, steps=4, max_seconds=1e6)
    assert budget.converged and budget.iterations == free.iterations
    # the same iterations on the same data: the same answer to round-off
    assert np.abs(budget.u - free.u).max() <= 1e-12 * np.abs(free.u).max()


def test_a_spent_budget_ends_the_run_with_the_load_reached():
    _, body, bcs, f = _cook(4)
    with pytest.raises(solver.SolveFailed) as err:
        # each iteration takes at least 0.05 s: the 0.12 s budget is spent within three
        solver.newton_solve(body, bcs, external=f, steps=4, max_seconds=0.12,
                            callback=lambda rec: time.sleep(0.05))
    e = err.value
    assert "wall-clock budget of 0.12 s" in str(e)
    assert e.last_converged_load < 1.0 and e.load > e.last_converged_load
    assert e.state.cutbacks == 0
    assert np.all(np.isfinite(e.state.x))


def test_the_budget_must_be_positive():
    with pytest.raises(ValueError, match="max_seconds"):
        solver.SolverControl(max_seconds=0.0)
