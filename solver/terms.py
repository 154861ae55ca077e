"""Extra residual terms plugged into the Newton solver (contact, follower pressure, springs...).

A term adds f(x) to the internal-force residual r = f_int + f - f_ext and its derivative
K = df/du to the tangent. Degrees of freedom are numbered node-major: node i owns dofs
3i, 3i+1, 3i+2. `energy` is the term's potential (used by the line search and the log; a
non-conservative term such as a follower pressure returns the work-like value it can define,
or 0.0). `end_step` is called once a load step has converged; returning True asks the solver
to solve the same step again (augmented Lagrangian multiplier update), False to move on.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Term"]


@runtime_checkable
class Term(Protocol):
    def assemble(self, x, load):
        """x: (n, 3) current nodal coordinates; load: load fraction in [0, 1].

        Returns (f (3n,), K scipy.sparse (3n, 3n)), K = df/du (symmetric where possible; any
        format, COO the cheapest: the solver sums its entries into its pattern by position).
        """

    def energy(self, x, load) -> float:
        """Potential of the term at x (mJ)."""

    def end_step(self, x, load) -> bool:
        """Called at a converged step; True asks for another solve of the same step."""
