"""Extra residual terms plugged into the Newton solver (contact, follower pressure, springs...).

A term adds f(x) to the internal-force residual r = f_int + f - f_ext and its derivative
K = df/du to the tangent. Degrees of freedom are numbered node-major: node i owns dofs
3i, 3i+1, 3i+2. `Term` declares every hook the solver calls, each with a default that does
nothing (as FEBio's `FESurfacePairConstraint` does), so the solver never asks whether a term
has a method: a term overrides `assemble` and the hooks it needs. A class that does not derive
from `Term` but defines `assemble`, `energy` and `end_step` still works: the solver wraps it
with `as_term`.
"""
from __future__ import annotations

import copy
from abc import ABC, abstractmethod

import numpy as np

__all__ = ["Term", "as_term"]

_NO_PAIRS = np.zeros((0, 2), dtype=np.int64)


class Term(ABC):
    """A residual term with the solver's hooks, all optional but `assemble`."""

    @abstractmethod
    def assemble(self, x, load):
        """x: (n, 3) current nodal coordinates; load: load fraction in [0, 1].

        Returns (f (3n,), K scipy.sparse (3n, 3n) or None), K = df/du (symmetric where
        possible; any format, COO the cheapest: the solver sums its entries into its pattern
        by position).
        """

    def energy(self, x, load) -> float:
        """Potential of the term at x (mJ), read by the line search; a non-conservative term
        returns the work-like value it can define, or 0.0."""
        return 0.0

    def end_step(self, x, load) -> bool:
        """Called at a converged step; True asks for another solve of the same step (an
        augmented Lagrangian multiplier update)."""
        return False

    def coupling_pairs(self) -> np.ndarray:
        """(k, 2) node pairs the term may couple beyond the body's elements (contact), so that
        the global sparsity pattern is reserved once before the solve."""
        return _NO_PAIRS

    def restart_step(self) -> None:
        """The solver restarts the current step from its converged start (it rejected its
        predictor): forget any state decided during the abandoned solve."""

    def augmentation_due(self, x, load) -> bool:
        """Whether the step at `load`, not yet converged at x, will be augmented anyway (the
        solver may then stop the solve early, `SolverControl.augmentation_rtol`)."""
        return False

    def convexify(self, on: bool) -> bool:
        """Assemble (on=True) a positive semi-definite modification of the term's tangent in
        place of its exact one from now on, the force unchanged (the solver asks for it when
        a Newton update is not a descent direction of the potential; on=False: back to the
        exact tangent). Returns whether the term has an indefinite part it modifies; the
        default has none."""
        return False

    # attributes that never change during a solve (geometry, settings): not part of the
    # state `save_step` copies
    static_state: tuple = ()

    def save_step(self):
        """The term's state at the start of a load step (multipliers, contact status,
        counters: a copy of its attributes but `static_state`), for `restore_step`."""
        return copy.deepcopy({k: v for k, v in vars(self).items()
                              if k not in self.static_state})

    def restore_step(self, state) -> None:
        """Back to the state `save_step` returned: the solver cuts a failed step back and
        solves a shorter one from the step's converged start, which must not carry what the
        failed solves changed (augmented multipliers, a status decided at the higher load)."""
        if state is not None:
            vars(self).update(copy.deepcopy(state))


class _Adapted(Term):
    """A term object that does not derive from `Term`: its own methods where it has them,
    the defaults elsewhere; any other attribute is the wrapped object's."""

    def __init__(self, term):
        self.term = term
        for name in ("energy", "end_step", "coupling_pairs", "restart_step",
                     "augmentation_due", "save_step", "restore_step", "convexify"):
            method = getattr(term, name, None)
            if callable(method):
                setattr(self, name, method)

    def assemble(self, x, load):
        return self.term.assemble(x, load)

    def save_step(self):
        # a foreign object's state is its own business: without its own hooks it is not copied
        return None

    def __getattr__(self, name):
        return getattr(self.__dict__["term"], name)


def as_term(term) -> Term:
    """`term` itself if it derives from `Term`, else an adapter giving it the default hooks."""
    return term if isinstance(term, Term) else _Adapted(term)
