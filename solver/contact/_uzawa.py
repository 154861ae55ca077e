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



def deepest_penetration(gaps) -> float:
    """Deepest penetration (mm, >= 0) among arrays of signed gaps (negative inside)."""
    return max([0.0] + [float(-g.min()) for g in gaps if len(g)])


class StatusFreezing:
    """Status freezing shared by the contact terms (Wriggers 2006, sec. 10.3): the contact
    status (active set, pairing) is searched afresh at each of the first `freeze_after`
    evaluations at one load and kept from then on, so that Newton converges on a smooth
    problem; `end_step` checks it at the converged state. The term sets `freeze_after`
    (None: never frozen), `freeze_resolves` and calls `_unfreeze()` in its constructor."""

    freeze_after: int | None = 4
    freeze_resolves: bool = True

    def _unfreeze(self) -> None:
        self._evals_load, self._evals = None, 0

    def _frozen(self, load) -> bool:
        """Count the evaluations at this load; True once the status is to be frozen."""
        if load != self._evals_load:
            self._evals_load, self._evals = load, 0
        self._evals += 1
        return self._is_frozen(load)

    def _is_frozen(self, load) -> bool:
        """Whether the last evaluation at `load` had the status frozen (without counting)."""
        return (self.freeze_after is not None and load == self._evals_load
                and self._evals > self.freeze_after)

    def _freeze_resolve(self, load) -> None:
        """Another solve of the same step (with `freeze_resolves`) re-decides the status only
        at its first two evaluations, at the converged state (where `end_step` just made a
        fresh search) and after the first update (which catches the nodes that the new
        multipliers push into contact), then freezes it: the status is nearly the one the
        step needs, so the re-solve does not spend `freeze_after` iterations re-deciding it;
        a status still wrong after it is caught by the next `end_step`."""
        if self.freeze_resolves and self.freeze_after is not None:
            self._evals_load, self._evals = load, max(self.freeze_after - 2, 0)
