"""Augmented-Lagrangian bookkeeping: the bounded Uzawa loop."""
import numpy as np

from solver.contact._uzawa import UzawaLoop


def test_uzawa_loop_is_bounded_and_restarts_at_every_load():
    loop = UzawaLoop(max_augmentations=2)
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert not loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)   # bounded
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1)       # new load
    assert not loop.another_solve(1.0, False, True, error=0.05, tolerance=0.1)  # converged
