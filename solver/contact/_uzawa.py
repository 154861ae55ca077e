"""Bookkeeping of the augmented-Lagrangian (Uzawa) loop shared by the contact terms.

At a converged load step a contact term asks for another solve of the same step when its
active set changed or, with augmentation, when the penetration still exceeds the tolerance
(Laursen, *Computational Contact and Impact Mechanics*, 2002, ch. 5: multipliers
lambda <- lambda + eps g after each converged solve). The count restarts at every new load and
is bounded, so a step never loops for ever. With `final_only` only the final load step is
augmented down to the tolerance (intermediate steps are re-solved only for a wrong contact
status): fewer solves on small models (coarse demo 35 -> 17 s), but on the standard face the
multipliers then lag and the later steps cut back more (pipeline bench 135 -> 240 s), so it is off
by default.
"""
from __future__ import annotations

import numpy as np


class UzawaLoop:
    """Decides whether a converged step needs another augmented solve."""

    def __init__(self, max_augmentations: int, final_only: bool = False):
        self.max_augmentations = int(max_augmentations)
        self.final_only = bool(final_only)
        self.count = 0
        self._load = None

    def another_solve(self, load: float, status_changed: bool, augmented: bool,
                      error: float, tolerance: float) -> bool:
        if load != self._load:                      # a new step: restart the count
            self._load = load
            self.count = 0
        # with `final_only`, intermediate load steps keep the penalty solution (their
        # penetration does not matter; the multipliers carry on): augmented solves are spent
        # on the final state only
        intermediate = self.final_only and load < 1.0 - 1e-9
        if self.count >= self.max_augmentations or \
                (not status_changed and (not augmented or error <= tolerance or intermediate)):
            self.count = 0
            return False
        self.count += 1
        return True


class MultiplierPredictor:
    """Extrapolates the contact multipliers to a new load step from the last two accepted ones.

    The augmented-Lagrangian multipliers converge, step by step, to the contact forces; starting
    a new step from the previous step's forces leaves the penetration of the force increment,
    which costs one or two more augmented solves per step. Like the secant predictor of the
    displacements, lambda(L) = lambda_n + (L - L_n) (lambda_n - lambda_n-1) / (L_n - L_n-1),
    from the accepted states (L_n, lambda_n) (the first from the unloaded state, lambda = 0 at
    L = 0: a proportional scaling); `clip` keeps unilateral multipliers >= 0. A step that is cut
    back is predicted afresh from the same accepted states, so that a failed step's multipliers
    never carry over.
    """

    def __init__(self, clip: bool = True):
        self.clip = bool(clip)
        self.history: list[tuple[float, np.ndarray]] = []
        self._load = None

    def accept(self, load: float, values: np.ndarray) -> None:
        """Record the multipliers of a converged, accepted step at `load`."""
        values = np.array(values, dtype=float)
        if self.history and self.history[-1][0] == load:
            self.history[-1] = (load, values)
        else:
            if not self.history and load > 0:
                self.history.append((0.0, np.zeros_like(values)))
            self.history = self.history[-1:] + [(load, values)]
        self._load = load

    def predict(self, load: float, current: np.ndarray) -> np.ndarray:
        """Multipliers to start the step at `load` with (the current ones at the same load)."""
        if load == self._load or len(self.history) < 2 or load <= self.history[-1][0]:
            self._load = load
            return current
        self._load = load
        (l0, v0), (l1, v1) = self.history[-2], self.history[-1]
        out = v1 + (load - l1) / (l1 - l0) * (v1 - v0)
        return np.maximum(out, 0.0) if self.clip else out
