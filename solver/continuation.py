"""Pseudo-transient continuation (PTC) of Newton's method: `PseudoTransient`.

Newton's method on the static equilibrium r(x) = 0 fails where its tangent K = dr/dx is
singular or indefinite along the way: at a limit point of the load path (the equilibrium the
step starts from disappears, a snap-through), or where a contact status change or a facet
switch makes the residual jump and the full update overshoots by far. Pseudo-transient
continuation (Kelley & Keyes 1998, "Convergence analysis of pseudo-transient continuation",
SIAM J. Numer. Anal. 35(2):508-523; Coffey, Kelley & Keyes 2003) follows instead the
pseudo-time evolution

    D dx/dtau = -r(x)

to its steady state, by one linearly implicit Euler step per iteration:

    (delta_k D + K(x_k)) dx_k = -r(x_k),    x_{k+1} = x_k + dx_k,    delta_k = 1 / dtau_k.

D is a positive diagonal scaling, here the magnitude of the tangent's diagonal at the free
unknowns, |K_ii| (floored at 1e-6 of their mean: an entry cancelled by a contact curvature
still gets damped), so that delta is dimensionless and the same on every mesh and unit system:
delta = 1 halves a Jacobi step. A large delta makes the update a short, scaled gradient step
of the potential (a descent direction whatever the sign of K: a damped dynamic relaxation);
delta -> 0 gives Newton's update back. The pseudo-time step grows by switched evolution
relaxation (SER, Mulder & van Leer 1985):

    delta_{k+1} = delta_k |r(x_{k+1})| / |r(x_k)|,

so the damping falls as fast as the residual: the iteration ends as Newton's, with its local
quadratic convergence (Kelley & Keyes 1998, thm. 2.2). The residual r is never damped: the
damping enters the matrix of the linear system only, and a solve converges on the undamped
residual, |r| <= rtol max(|f_int|, |f_ext|): the converged state is the static equilibrium to
the usual tolerance. Where the load path has a limit point it is the stable equilibrium the
damped dynamics reaches (the one a slow loading of the real, slightly viscous tissue reaches).

`solver.newton.newton_solve` switches PTC on for the rest of a run once `ptc_after`
consecutive load steps failed; the load step then grows after a step none of whose updates
needed the damping (`SolverControl.ptc_after`, `ptc_damping`, `ptc_iterations`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["PseudoTransient"]


class PseudoTransient:
    """The damping delta D of the solves of a run and its schedule.

    delta0: the damping a load step starts with after a failure; positions: indices of the
    free unknowns' diagonal entries in the tangent's data array (the constrained rows,
    equations du_c = gap, are not damped). Within a load step

        delta_k = delta_s * (|r_k| / |r_s|) * c_k,

    r_s the residual after the step's first iteration (which imposes the prescribed
    increments) (SER: the damping follows the
    residual, and comes back when a re-solve after a multiplier update or a contact status
    change starts from a larger one), c_k a ramp: halved after an update taken at full length
    that went downhill (the pseudo-time step grows while the iteration makes progress, also
    where the residual rises on the way over a limit point), doubled after an update the
    step limit or an inverted element shortened or whose damped tangent was indefinite
    along it (`indefinite`: it was solved again with convexified terms), ten times after an update that was not a
    descent direction, `jump` times after an update that raised the residual more than
    `jump` times (the pseudo-time step was far too long: with SER alone the damping falls back
    as soon as the residual does, and near a contact kink the iteration then cycles between
    a nearly converged state and a jump back to a relative residual of 0.1-1, tens of times
    in one solve; the ramp keeps the memory of it and halves again with every good update),
    within [c_min, 1 / c_min], 1 at the start of every solve. delta_s, the damping a step starts with:
    delta0 after a failed step, `relax` times the last after a step that converged with every
    update downhill and at full length (the damping was not needed), unchanged after
    another, at least `fade` delta0 (continuation stays on for the rest of the run: where a
    load path once needed it, later steps meet the same contacts).
    A delta below `floor` counts as zero (Newton's matrix).
    """

    def __init__(self, delta0: float, positions: np.ndarray, growth: float = 2.0,
                 c_min: float = 1e-3, ceiling: float = 1e8, floor: float = 1e-12,
                 fade: float = 1e-3, relax: float = 0.3, jump: float = 10.0):
        self.delta0 = float(delta0)
        self.positions = np.asarray(positions, dtype=np.int64)
        self.growth = float(growth)
        self.c_min = float(c_min)
        self.ceiling = float(ceiling)
        self.floor = float(floor)
        self.fade = float(fade)
        self.relax = float(relax)
        self.jump = float(jump)
        self._last = None           # the residual before the last update
        self.needed = False         # an update of this step was shortened or uphill
        self.indefinite = False     # the last update met an indefinite tangent
        self.start_delta = self.delta0
        self.delta = self.delta0
        self.ramp = 1.0
        self._first = None
        self._opening = False

    def start(self, residual: float, again: bool = False) -> None:
        """A new solve from a state of residual norm `residual`; `again`: a re-solve of the
        same load step (its reference residual is kept: a re-solve from a larger residual
        than the step's is damped more)."""
        self._opening = not again
        if not again or not self._first or not np.isfinite(residual):
            self._first = max(float(residual), 1e-300)
            self.needed = False
        self.ramp = 1.0
        self._last = float(residual) if np.isfinite(residual) else None
        self._set(residual)

    def _set(self, residual):
        rho = float(residual) / self._first if np.isfinite(residual) else 1.0 / self.c_min
        self.delta = min(self.ceiling, self.start_delta * rho * self.ramp)

    def advance(self, residual: float, full: bool = True) -> float:
        """The damping of the next iteration after one that left the residual norm
        `residual`; `full`: its update was taken at full length (not shortened by the step
        limit or for an inverted element). Returns the new delta."""
        opening = self._opening
        if self._opening and np.isfinite(residual):
            # the first iteration of a step imposes the prescribed increments: the residual
            # after it, not the one before, is the step's reference
            self._first = max(self._first, float(residual))
        self._opening = False
        full = full and not self.indefinite
        self.indefinite = False
        jumped = (not opening and self._last is not None and np.isfinite(residual)
                  and residual > self.jump * self._last)
        if jumped:
            self.ramp *= self.jump
        else:
            self.ramp = self.ramp / self.growth if full else self.ramp * self.growth
        self._last = float(residual) if np.isfinite(residual) else None
        self.needed = self.needed or not full or jumped
        self.ramp = min(max(self.ramp, self.c_min), 1.0 / self.c_min)
        self._set(residual)
        return self.delta

    def raise_damping(self) -> float:
        """The damped update is not a descent direction: ten times the damping."""
        self.ramp = min(10.0 * self.ramp, 1.0 / self.c_min)
        self.needed = True
        self.delta = min(self.ceiling, max(10.0 * self.delta, 1e-4 * self.start_delta))
        return self.delta

    def damped(self, A):
        """A + delta D (a copy; A itself when the damping has vanished)."""
        if self.delta <= self.floor:
            return A
        d = np.abs(A.data[self.positions])
        d = np.maximum(d, 1e-6 * max(float(d.mean()) if len(d) else 0.0, 1e-300))
        B = A.copy()
        B.data[self.positions] += self.delta * d
        B.has_sorted_indices = A.has_sorted_indices
        return B

    def step_converged(self) -> bool:
        """A load step converged: the next one starts with `relax` times the damping if
        this one did not need it (at least `fade` delta0)."""
        if not self.needed:
            self.start_delta = max(self.start_delta * self.relax, self.fade * self.delta0)
        return True

    def step_failed(self) -> None:
        """A load step failed (it is cut back): the next one starts from delta0 again."""
        self.start_delta = self.delta0
