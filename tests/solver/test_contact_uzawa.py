"""Augmented-Lagrangian bookkeeping: the multiplier predictor across load steps."""
import numpy as np

from solver.contact._uzawa import MultiplierPredictor, UzawaLoop


def test_multipliers_extrapolate_linearly_from_accepted_steps():
    pred = MultiplierPredictor(clip=True)
    lam = np.array([0.0, 0.0, 0.0])
    # nothing accepted yet: the first step starts from the given multipliers
    assert np.array_equal(pred.predict(0.25, lam), lam)
    pred.accept(0.25, [1.0, 2.0, 0.0])
    # one accepted step: proportional to the load from the unloaded state (lambda = 0 at 0)
    assert np.allclose(pred.predict(0.5, lam), [2.0, 4.0, 0.0])
    # augmented solves at the same load keep their updated multipliers
    assert np.array_equal(pred.predict(0.5, np.array([5.0, 5.0, 5.0])), [5.0, 5.0, 5.0])
    pred.accept(0.5, [2.5, 3.0, 0.5])
    # secant through the last two accepted states, (0.25, l1) and (0.5, l2), at 0.625
    got = pred.predict(0.625, np.zeros(3))
    assert np.allclose(got, [2.5 + 0.5 * 1.5, 3.0 + 0.5 * 1.0, 0.5 + 0.5 * 0.5])


def test_a_cut_back_step_is_predicted_afresh_and_unilateral_multipliers_stay_positive():
    pred = MultiplierPredictor(clip=True)
    pred.accept(0.5, [4.0, 1.0])
    pred.accept(1.0 / 1.5, [5.0, 0.5])        # falling contact force on the second node
    first = pred.predict(1.0, np.zeros(2))
    assert first[1] == 0.0 and first[0] > 5.0  # clipped at 0 (a unilateral force)
    # the step to 1.0 fails (Newton cuts back to 0.8): its augmented multipliers are dropped
    again = pred.predict(0.8, np.array([99.0, 99.0]))
    slope = (np.array([5.0, 0.5]) - [4.0, 1.0]) / (1.0 / 1.5 - 0.5)
    assert np.allclose(again, np.maximum([5.0, 0.5] + (0.8 - 1.0 / 1.5) * slope, 0.0))
    # bilateral (sliding) multipliers may change sign
    free = MultiplierPredictor(clip=False)
    free.accept(0.5, [1.0])
    free.accept(1.0, [-1.0])
    assert np.allclose(free.predict(1.5, np.zeros(1)), [-3.0])


def test_uzawa_loop_is_bounded_and_restarts_at_every_load():
    loop = UzawaLoop(max_augmentations=2)
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert not loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)   # bounded
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1)       # new load
    assert not loop.another_solve(1.0, False, True, error=0.05, tolerance=0.1)  # converged
