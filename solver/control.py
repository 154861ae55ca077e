"""The Newton solver's control: settings, load stepping, predictor, convergence and step limit.

Each rule of `solver.newton.newton_solve` that is not Newton's iteration itself is one small
object here, on the pattern of FEBio's `FENewtonSolver` / `FETimeStepController`:
`SolverControl` gathers every setting with a generic default; `StepController` sizes the load
steps (growth after easy steps, shrinking after hard ones, cut-back on failure, a minimum
step); `Predictor` gives the start of a step (the last converged state, or a Lagrange
extrapolation of the last ones in the load fraction); `ConvergenceCriterion` decides
convergence (residual and energy norms, as FEBio's rtol / etol), divergence and stagnation;
`IncrementLimiter` bounds the length of a Newton update (damped Newton far from the solution).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SolverControl", "StepController", "Predictor", "ConvergenceCriterion",
           "IncrementLimiter", "StepResult"]


@dataclass(frozen=True)
class SolverControl:
    """Every setting of `newton_solve`, with generic defaults.

    Load stepping (`StepController`): steps, the initial number of equal load steps (also the
    largest step); min_step, the smallest step before the solve fails; grow, growth of the step
    by `growth` after a step converged within `easy_iterations`; shrink_iterations, halving of
    the next step after a step whose first solve needed more iterations (None: off);
    max_retries, the re-solves of one step a term may ask for (augmentations).
    Newton (`ConvergenceCriterion`): max_iterations per solve; rtol, relative residual
    |r| <= rtol max(|f_int|, |f_ext|); atol, absolute residual; etol, energy norm relative to
    the step's first; stall_iterations, cut a step back when its residual has not fallen to a
    tenth of the first after that many iterations (None: off).
    Line search: line_search (off by default: on nearly incompressible problems the volumetric
    energy often rises at an early full step although undamped Newton converges fastest; the
    halving on an inverted element always acts), line_search_tol, line_search_growth.
    Blow-up guard: blowup_factor, a trial update whose residual exceeds this many times the
    force scale (max(|f_int|, |f_term|, |f_ext|)) of the iterate it starts from is halved
    like one that inverts an element (None: off). Such a residual belongs to no Newton
    iterate: an element driven next to degeneracy, its Gauss points not yet inverted, where
    the exponential fibre law or the isochoric invariants J^(-2/3) I1 grow without bound;
    taken, it leaves Newton crawling out of it for many iterations, or the step diverging.
    A solve's first update starts from a converged state, whose forces are the reactions
    alone (none at rest, none on a free body) and no measure of the step's load: it is
    measured against the largest force scale of the last converged step's iterates instead
    (not at all in the first step).
    Update length (`IncrementLimiter`): max_increment (mm, None: off) on increment_nodes (None:
    every free node).
    Three-field iteration: mixed, iterate on (u, p, theta) with element-wise condensation for
    bodies that support it (same solution, fewer iterations when nearly incompressible).
    Predictor (`Predictor`): "tangent", "secant" or "auto" (secant with the lagged strategy,
    tangent with extra terms under prescribed motion or with exact solves).
    Inexact solves of augmented steps: augmentation_rtol, once the relative residual falls
    below it, the terms are asked (once per solve) whether the step will be augmented anyway
    (`Term.augmentation_due`); if so the solve stops and the step goes to `end_step` (an
    inexact inner solve of the method of multipliers, Bertsekas 1982, sec. 2.5); None: every
    solve converges before `end_step`.
    Linear algebra: linear_solver ("auto", "pardiso", "cholmod", "scipy"); linear_strategy
    "exact" (factorise every tangent), "lagged" (CG preconditioned with an earlier factor,
    `solver.linalg.LaggedFactorSolver`) or "auto" ("lagged" from `lagged_min_dofs` unknowns);
    krylov_rtol, krylov_maxiter, krylov_forcing, krylov_refactor, krylov_precision as in
    `LaggedFactorSolver`.
    Pseudo-transient continuation (`solver.continuation`): ptc_after, the consecutive failed
    (cut-back) load steps after which the solves of the run add the damping delta D to the
    tangent (None: never); ptc_damping, the damping delta_0 each such solve starts with
    (relative to the tangent's diagonal D); ptc_iterations, the iteration limit of such a
    solve (the stagnation test `stall_iterations` is off in it: a damped solve reduces the
    residual slowly at first by design). The budget of continuation, so that a run that
    cannot pass ends soon with `SolveFailed` (a damped solve has no stagnation test: over a
    limit point its residual rises for tens of iterations before it falls):
    ptc_step_iterations, the damped iterations one load step may spend over all its solves
    (re-solves for the contact status or augmentations included; None: no limit);
    ptc_max_failures, the consecutive failed load steps under continuation after which the
    run fails (None: only `min_step` ends it).
    Wall clock: max_seconds, the run's time budget (None: none). Checked after every Newton
    iteration; when it is spent the run ends at once with `SolveFailed` naming the load
    reached, so that a run creeping near a limit point (tens of damped solves, each within its
    own budget) ends when its caller can no longer use it, not after hours.
    """

    steps: int = 10
    min_step: float = 1e-4
    grow: bool = True
    growth: float = 1.5
    easy_iterations: int = 6
    shrink_iterations: int | None = None
    max_retries: int = 5
    max_iterations: int = 25
    rtol: float = 1e-8
    atol: float = 1e-10
    etol: float = 1e-10
    stall_iterations: int | None = None
    line_search: bool = False
    line_search_tol: float = 1.0
    line_search_growth: float = 100.0
    blowup_factor: float | None = 100.0
    max_increment: float | None = None
    increment_nodes: object = None
    mixed: bool = True
    predictor: str = "auto"
    augmentation_rtol: float | None = None
    linear_solver: str = "auto"
    linear_strategy: str = "auto"
    krylov_rtol: float = 1e-8
    krylov_maxiter: int = 10
    krylov_forcing: float = 1e-2
    lagged_min_dofs: int = 20000
    krylov_refactor: int = 8
    krylov_precision: str = "single"
    ptc_after: int | None = 2
    ptc_damping: float = 1.0
    ptc_iterations: int = 60
    ptc_step_iterations: int | None = 120
    ptc_max_failures: int | None = 4
    max_seconds: float | None = None

    def __post_init__(self):
        if self.linear_strategy not in ("auto", "exact", "lagged"):
            raise ValueError(f"linear_strategy must be 'auto', 'exact' or 'lagged', "
                             f"got {self.linear_strategy!r}")
        if self.ptc_after is not None and self.ptc_after < 1:
            raise ValueError(f"ptc_after must be None or >= 1, got {self.ptc_after!r}")
        for name in ("ptc_step_iterations", "ptc_max_failures"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be None or >= 1, got {value!r}")
        if self.blowup_factor is not None and not self.blowup_factor > 1.0:
            raise ValueError(f"blowup_factor must be None or > 1, got {self.blowup_factor!r}")
        if self.max_seconds is not None and not self.max_seconds > 0.0:
            raise ValueError(f"max_seconds must be None or > 0, got {self.max_seconds!r}")
        if not self.ptc_damping > 0.0:
            raise ValueError(f"ptc_damping must be > 0, got {self.ptc_damping!r}")
        if self.predictor not in ("auto", "tangent", "secant"):
            raise ValueError(f"predictor must be 'auto', 'tangent' or 'secant', "
                             f"got {self.predictor!r}")


class StepController:
    """Load-step sizes: the load fraction goes from 0 to 1 in steps of at most 1 / steps.

    After a converged step the step grows by `growth` (up to its initial size) when the last
    solve took at most `easy_iterations` Newton iterations, and is halved (down to `min_step`)
    when the step's first solve took more than `shrink_iterations` (a hard step announces a
    harder next one, and halving costs less than a failed step; Abaqus' and FEBio's automatic
    stepping likewise). A failed step is cut back to half its size; below `min_step` the solve
    fails. A last step shorter than a quarter of the step is merged into the one before.
    """

    def __init__(self, control: SolverControl):
        self.dt_max = 1.0 / max(int(control.steps), 1)
        self.dt = self.dt_max
        self.min_step = control.min_step
        self.grow = control.grow
        self.growth = control.growth
        self.easy_iterations = control.easy_iterations
        self.shrink_iterations = control.shrink_iterations

    def target(self, load: float) -> float:
        """The load fraction the next step solves for."""
        target = min(1.0, load + self.dt)
        return 1.0 if 1.0 - target < 0.25 * self.dt else target

    def converged(self, iterations: int, first_iterations: int) -> None:
        """A step converged; `iterations` of its last solve, `first_iterations` of its first."""
        if self.grow and iterations <= self.easy_iterations:
            self.dt = min(self.dt_max, self.growth * self.dt)
        if self.shrink_iterations and first_iterations > self.shrink_iterations:
            self.dt = max(0.5 * self.dt, self.min_step)

    def converged_damped(self, easy: bool) -> None:
        """A step converged under continuation (`solver.continuation`); `easy`: no update
        needed the damping. The step grows by `growth` after an easy one (the iteration
        count of a damped solve does not measure the step's difficulty)."""
        if self.grow and easy:
            self.dt = min(self.dt_max, self.growth * self.dt)

    def cut_back(self, load: float, target: float) -> bool:
        """The step from `load` to `target` failed: halve it. False when it falls below the
        minimum step (the solve has failed)."""
        self.dt = 0.5 * (target - load)
        return self.dt >= self.min_step


class Predictor:
    """The start of each load step.

    "tangent": the last converged state; the first Newton iteration imposes the prescribed
    increments. "secant": the Lagrange extrapolation in the load fraction of the last
    `points` converged states (x and the three-field state): linear from two, quadratic from
    three (`extrapolation`, default `extrapolate`); not on the first step, nor after a
    cut-back. The solver falls back to the tangent
    start when the extrapolated state is invalid or its solve goes astray.
    """

    def __init__(self, kind: str, points: int, start=None, extrapolation=None):
        self.kind = kind
        self.points = points
        self.extrapolation = extrapolation or extrapolate
        self.history = [] if start is None else [start]
        self.just_cut = False

    def start(self, target):
        """(x, mixed state) extrapolated to `target`, or None for the tangent start."""
        if self.kind != "secant" or len(self.history) < 2 or self.just_cut:
            return None
        return self.extrapolation(self.history[-self.points:], target)

    def converged(self, load, x, mixed) -> None:
        self.just_cut = False
        self.history = self.history[-2:] + [(load, x, mixed)]

    def cut_back(self) -> None:
        self.just_cut = True


def extrapolate(history, target):
    """Lagrange extrapolation in the load fraction through the converged states `history`
    [(load, x, mixed state or None)]: linear (secant) from two, quadratic from three."""
    loads = [h[0] for h in history]
    w = []
    for i, li in enumerate(loads):
        c = 1.0
        for j, lj in enumerate(loads):
            if j != i:
                c *= (target - lj) / (li - lj)
        w.append(c)
    x = sum(c * h[1] for c, h in zip(w, history))
    mixed = None
    if history[0][2] is not None:
        mixed = (sum(c * h[2][0] for c, h in zip(w, history)),
                 sum(c * h[2][1] for c, h in zip(w, history)))
    return x, mixed


@dataclass(frozen=True)
class ConvergenceCriterion:
    """Convergence, divergence and stagnation of one Newton solve.

    Converged: the prescribed values reached (constraint gap <= `tiny`), the residual norm
    |r| <= rtol * scale (scale = max(|f_int|, |f_term|, |f_ext|)) or <= atol, and the energy
    norm |du . r| <= etol * (the step's first energy norm), or a residual already a thousand
    times below the tolerance (the energy norm of a tiny update is noise). At round-off: the
    update is below 1e-11 of the coordinate magnitude (far below any physical effect, ~1e3
    above double precision) with a residual near the tolerance: the iterate cannot improve.
    Diverging: the residual grew a million times over the best of the first three. Stalled:
    after `stall_iterations` iterations the residual never fell to a tenth of the first.
    """

    rtol: float
    atol: float
    etol: float
    stall_iterations: int | None = None

    def converged(self, it, residual, scale, energy, energy0, gap, tiny) -> bool:
        return (gap <= tiny and (residual <= self.rtol * scale or residual <= self.atol)
                and (energy <= self.etol * energy0 or residual <= self.atol
                     or it > 1 and residual <= 1e-3 * self.rtol * scale))

    def at_round_off(self, it, residual, scale, update, size, gap, tiny) -> bool:
        return (it > 1 and gap <= tiny and update <= 1e-11 * size
                and residual <= max(1e3 * self.atol, self.rtol * scale))

    @staticmethod
    def diverges(it, residuals) -> bool:
        return it >= 4 and residuals[-1] > 1e6 * max(min(residuals[:3]), 1e-300)

    def stalled(self, it, residuals) -> bool:
        stall = self.stall_iterations
        return bool(stall) and it >= stall and min(residuals) > 0.1 * residuals[0]


class IncrementLimiter:
    """Step-length limit of a Newton update: no watched node moves more than `max_increment`
    in one iteration (the update is scaled down; damped Newton far from the solution, where a
    contact switching on can make the full update overshoot; near it the full step is taken).
    The watched nodes are free ones: prescribed increments are part of the load."""

    def __init__(self, max_increment, watched_nodes):
        self.max_increment = None if max_increment is None else float(max_increment)
        self.watched_nodes = watched_nodes

    def step_length(self, du) -> float:
        """Factor s in (0, 1] for the update du (n, 3)."""
        if self.max_increment is None:
            return 1.0
        d2 = np.einsum("ij,ij->i", du, du)[self.watched_nodes]
        biggest = float(np.sqrt(np.max(d2, initial=0.0)))
        return self.max_increment / biggest if biggest > self.max_increment else 1.0


@dataclass
class StepResult:
    """The outcome of solving one load step (or one solve of it)."""

    converged: bool
    x: np.ndarray
    iterations: int = 0
    residuals: list = None
    reason: str = ""
    worst_element: int | None = None
    min_J: float = np.nan
    energy0: float | None = None     # the step's first energy norm (kept by its re-solves)
    early: bool = False              # stopped before convergence for an augmentation
    predicted: bool = False          # started from the extrapolated state
    retries: int = 0                 # re-solves the terms asked for (augmentations)
    first_iterations: int | None = None   # iterations of the step's first solve
    out_of_time: bool = False        # stopped because the run's wall-clock budget is spent
    peak_scale: float = 0.0          # the largest force scale of the accepted iterates

    def __post_init__(self):
        if self.residuals is None:
            self.residuals = []

    def failed(self, reason, ev) -> "StepResult":
        self.converged = False
        self.reason = reason
        self.worst_element, self.min_J = ev.worst_element, ev.min_J
        return self
