"""Bookkeeping of the augmented-Lagrangian (Uzawa) loop shared by the contact terms.

At a converged load step a contact term asks for another solve of the same step when its
active set changed or, with augmentation, when the penetration still exceeds the tolerance
(Laursen, *Computational Contact and Impact Mechanics*, 2002, ch. 5: multipliers
lambda <- lambda + eps g after each converged solve). The count restarts at every new load and
is bounded, so a step never loops for ever.

Which load steps are augmented is the loop's `schedule`. "every_step" augments each one down to
the tolerance. "final_only" augments the final state only: fewer solves, but the multipliers
then start the final step far from their values. "carried" (default) gives an intermediate
step one multiplier update without a re-solve and scales the multipliers to the next load (a
predictor of the contact forces), so the Uzawa updates are spread over the load increments;
"every_step" and "final_only" are kept for comparison (experimental: tests only).
"carried_penalty" treats the final load as "carried" treats the others: its state is the
penalty solution with the multipliers carried up to it, and its penetration is whatever
that leaves (the caller reports it). It is a fallback for a final contact state that the
augmentations cannot reach (each update throws the solve out of its basin), not a method of
its own: the answer then depends on the penalty.

The multiplier updates are safeguarded so that none throws away the converged state it is
taken at. A multiplier update at a converged state x* changes the contact forces there by
Delta lambda (each node's force jumps by eps |g| at a penetration g): the next solve starts
from that residual whatever the length of its load step. Two rules follow. (1) A re-solve of
an intermediate step asked for a wrong contact status keeps the multipliers: the status is
what it corrects, the intermediate penetration does not matter, and an update there would be
one more jump per re-solve (up to `max_retries` of them in one step). (2) The carried update
of an intermediate step is applied at the next load in proportion to its load increment,
lambda <- lambda + beta Delta lambda with beta = min(1, dt_next / dt_taken), dt_taken the
increment of the step that computed it: the jump shrinks with the step like the rest of the
load, so that a step cut back after a failure starts closer to equilibrium (the premise of
cutting back, which a full update of fixed size defeats near a limit point of the load path).
The part not applied is not lost: the next carried update is computed afresh at the next
converged state. (3) An intermediate step is re-solved for a wrong contact status at most
`status_resolves` times (1) for each term, then accepted as it is: where a body is pinched between two
surfaces the status can change at every re-solve (each one converged, each from a relative
residual of 0.01-0.1 after the change), and the next load searches the status afresh anyway;
the final load is re-solved until its status holds. This is the method of multipliers with a stepsize beta in (0, 1] on the
multiplier iteration, lambda <- lambda + beta (<lambda - eps g> - lambda), which converges for
any stepsize in (0, 2) on a convex problem (Bertsekas 1982, *Constrained Optimization and
Lagrange Multiplier Methods*, ch. 2); the final load, where the penetration must reach the
tolerance, takes full steps as before (Laursen 2002, ch. 5; FEBio's `laugon` augmentation
likewise takes the full update lambda <- <lambda + eps g> at each converged time step).
The settings every contact term shares are one `AugmentedLagrangian`; `ContactTerm` is the
terms' common base.
"""
from __future__ import annotations

import dataclasses
from abc import abstractmethod
from dataclasses import dataclass

import numpy as np

from solver.terms import Term


@dataclass(frozen=True)
class AugmentedLagrangian:
    """Penalty and augmented-Lagrangian settings of a contact term.

    penalty: eps (kPa/mm, a pressure per unit gap; a nodal term multiplies it by the node's
    tributary area). augmented: Uzawa multiplier updates (False: pure penalty). tolerance:
    deepest penetration (or sliding gap) accepted at convergence (mm). max_augmentations:
    bound on the re-solves of one step. search_radius: how far outside a surface a point is
    looked at (mm); max_depth: how deep inside contact is detected (mm). freeze_after: number
    of evaluations at one load after which the contact status is frozen (None: never);
    freeze_resolves: a re-solve re-decides the status at its first two evaluations only.
    uzawa_schedule: which load steps are augmented (`UzawaLoop`). status_resolves: re-solves
    of an intermediate load step for a wrong contact status ("carried" schedule; None: up to
    max_augmentations); the final load is re-solved until its status holds.
    """

    penalty: float = 100.0
    augmented: bool = True
    tolerance: float = 0.05
    max_augmentations: int = 10
    search_radius: float = 2.0
    max_depth: float = 2.0
    freeze_after: int | None = 4
    freeze_resolves: bool = True
    uzawa_schedule: str = "carried"
    status_resolves: int | None = 1

    def __post_init__(self):
        if not self.penalty > 0:
            raise ValueError(f"penalty must be > 0, got {self.penalty}")
        if self.uzawa_schedule not in UzawaLoop.SCHEDULES:
            raise ValueError(f"schedule must be one of {', '.join(UzawaLoop.SCHEDULES)}, "
                             f"got {self.uzawa_schedule!r}")


class UzawaLoop:
    """Decides whether a converged step needs another augmented solve, and how the
    multipliers carry over from one load step to the next.

    schedule "every_step": every load step is augmented down to the tolerance (re-solves of
    the same load until the penetration is within it). "final_only": intermediate steps keep
    their penalty solution and the multipliers stay as they are; only the final state is
    augmented. "carried" (default): an intermediate step is re-solved only for a wrong
    contact status; when its penetration exceeds the tolerance it gets one multiplier update
    (lambda <- <lambda - eps g>) without a re-solve, and at the next load those multipliers
    are scaled by the ratio of the loads (`load_factor`, a predictor of the contact forces
    under proportional loading); the final load is augmented down to the tolerance. The Uzawa
    iterations that every_step spends on re-solves of intermediate states, whose penetration
    does not matter, are spread over the load increments instead (on a hyperelastic,
    frictionless problem only the final state is the solution).
    """

    SCHEDULES = ("carried", "every_step", "final_only", "carried_penalty")

    def __init__(self, max_augmentations: int, schedule: str = "carried",
                 status_resolves: int | None = None):
        if schedule not in self.SCHEDULES:
            raise ValueError(f"schedule must be one of {', '.join(self.SCHEDULES)}, "
                             f"got {schedule!r}")
        self.max_augmentations = int(max_augmentations)
        self.schedule = schedule
        self.carried = schedule in ("carried", "carried_penalty")
        self.status_resolves = status_resolves
        self.count = 0
        self.carry = False      # the last `another_solve` asks for an update without re-solve
        self.update = False     # ... asks for a multiplier update (re-solve or carried)
        self._load = None
        self._multiplier_load = None
        self._from = None       # the load the current step started from
        self.carried_increment = None   # load increment of the step that took the carried update

    def another_solve(self, load: float, status_changed: bool, augmented: bool,
                      error: float, tolerance: float) -> bool:
        """Whether the converged step at `load` is solved again; sets `carry` (an update of
        the multipliers without a re-solve) and `update` (the term updates its multipliers,
        lambda <- <lambda - eps g>: for a re-solve or carried, with augmentation only)."""
        if load != self._load:                      # a new step: restart the count
            self._load = load
            self.count = 0
        intermediate = self._intermediate(load)
        self.carry = False
        if (status_changed and intermediate and self.carried
                and self.status_resolves is not None and self.count >= self.status_resolves):
            # rule 3 (module docstring): the intermediate state is accepted with its status
            status_changed = False
        if self.count >= self.max_augmentations or \
                (not status_changed and (not augmented or error <= tolerance or intermediate)):
            self.count = 0
            self.carry = (self.carried and intermediate and augmented
                          and error > tolerance)
            self.update = self.carry
            if self.carry:
                start = self._from if self._from is not None else 0.0
                self.carried_increment = max(load - start, 0.0)
            return False
        self.count += 1
        # a re-solve of an intermediate step is one for the status: it keeps the multipliers
        # (module docstring, rule 1); "final_only" never re-solves an intermediate step with
        # an update either
        self.update = augmented and not (intermediate and self.carried)
        return True

    def carried_fraction(self, load: float, carried_at: float) -> float:
        """The fraction beta = min(1, (load - carried_at) / increment) of a carried multiplier
        correction, computed at the converged load `carried_at` on a step of `increment`
        (`carried_increment`), applied at the first evaluation of the next load `load`
        (module docstring, rule 2)."""
        inc = self.carried_increment
        if not inc or inc <= 0.0:
            return 1.0
        return float(min(1.0, max(0.0, (load - carried_at) / inc)))

    def augmentation_due(self, load: float, augmented: bool, error: float,
                         tolerance: float, margin: float = 1.5) -> bool:
        """Whether a step at `load` that is not yet converged will be augmented anyway: its
        penetration `error` (at the current iterate) exceeds `margin` times the tolerance on
        a step that is augmented down to the tolerance, and the count allows another solve.
        The solver may then stop the penalty solve early and update the multipliers (an
        inexact inner solve of the method of multipliers, Bertsekas 1982, sec. 2.5: the
        penalty solve of a state that is to be corrected need not be converged tightly)."""
        count = self.count if load == self._load else 0     # a new step starts at 0
        return (augmented and not self._intermediate(load) and count < self.max_augmentations
                and error > margin * tolerance)

    def _intermediate(self, load: float) -> bool:
        """A step the schedule does not augment down to the tolerance (before the final
        load, unless "every_step"; every step with "carried_penalty")."""
        if self.schedule == "carried_penalty":
            return True
        return self.schedule != "every_step" and load < 1.0 - 1e-9

    def load_factor(self, load: float) -> float:
        """Factor for the multipliers at an evaluation at `load`: with the "carried" schedule
        load / (load of the previous evaluation) at the first evaluation of a new load (a
        step after a converged one, or a cut-back step: the scaling is undone in proportion),
        else 1."""
        previous, self._multiplier_load = self._multiplier_load, load
        if previous is not None and load != previous:
            self._from = previous
        if not self.carried or not previous or previous <= 0.0 or load == previous:
            return 1.0
        return load / previous


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

    def restart_step(self) -> None:
        """The solver restarts the current step from its converged start (it rejected its
        predictor): the status is searched afresh, as at a new load."""
        self._unfreeze()

    def _frozen(self, load) -> bool:
        """Count the evaluations at this load; True once the status is to be frozen. At the
        first evaluation of a new load the carried multipliers are scaled to it
        (`UzawaLoop.load_factor`; the term defines `_scale_multipliers(factor)`)."""
        factor = self.uzawa.load_factor(load)
        carried = getattr(self, "_carried", None)
        if carried is not None and load != self._carried_at:
            # the carried correction, in proportion to this step's load increment
            beta = self.uzawa.carried_fraction(load, self._carried_at)
            if beta < 1.0:
                for (owner, name), d in zip(self._multiplier_fields(), carried):
                    setattr(owner, name, getattr(owner, name) - (1.0 - beta) * d)
            self._carried = None
        if factor != 1.0:
            self._scale_multipliers(factor)
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


class ContactTerm(StatusFreezing, Term):
    """Common base of the contact terms: their `AugmentedLagrangian` settings (given as
    `settings`, any field of which a keyword argument overrides, over the class' `DEFAULTS`),
    status freezing, and the results every contact term gives: `penetration(x)`,
    `contact_forces(x, load=1.0)` and `contact_pressure(x, load=1.0)`."""

    DEFAULTS = AugmentedLagrangian()

    def _configure(self, settings: AugmentedLagrangian | None, overrides: dict) -> None:
        settings = dataclasses.replace(settings or self.DEFAULTS, **overrides)
        self.settings = settings
        self.penalty = float(settings.penalty)
        self.augmented = bool(settings.augmented)
        self.tolerance = float(settings.tolerance)
        self.uzawa = UzawaLoop(settings.max_augmentations, settings.uzawa_schedule,
                               settings.status_resolves)
        self.search_radius = float(settings.search_radius)
        self.max_depth = float(settings.max_depth)
        self.freeze_after = settings.freeze_after
        self.freeze_resolves = bool(settings.freeze_resolves)
        self.last_error = 0.0
        self._carried, self._carried_at = None, None
        self._unfreeze()

    def _multiplier_fields(self) -> list:
        """(owner, attribute name) of every multiplier array of the term."""
        return [(self, "multipliers")]

    def _multiplier_values(self) -> list:
        """Copies of the multiplier arrays (before an update)."""
        return [np.array(getattr(o, n), dtype=float, copy=True)
                for o, n in self._multiplier_fields()]

    def _note_carried(self, before: list, load: float) -> None:
        """After `end_step`'s update: a carried update (`UzawaLoop.carry`) is remembered as
        the correction it made, to be applied at the next load in proportion to its step
        (`StatusFreezing._frozen`); at the first evaluation of the next load the multipliers
        are before + beta (after - before)."""
        if self.uzawa.carry:
            self._carried = [np.asarray(getattr(o, n), dtype=float) - b
                             for (o, n), b in zip(self._multiplier_fields(), before)]
            self._carried_at = load
        else:
            self._carried, self._carried_at = None, None

    @abstractmethod
    def penetration(self, x, load: float = 1.0) -> float:
        """Deepest penetration (mm, >= 0) at coordinates x."""

    @abstractmethod
    def contact_forces(self, x, load: float = 1.0) -> np.ndarray:
        """Contact forces on the body's nodes (mN) at x."""

    @abstractmethod
    def contact_pressure(self, x, load: float = 1.0):
        """Contact pressure (kPa) at the slave nodes at x."""
