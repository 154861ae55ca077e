"""Newton-Raphson with adaptive load stepping (FEBio-like), `newton_solve`.

The load fraction goes from 0 to 1 in steps (`solver.control.StepController`). Each step
solves r(x) = f_int(x) + sum f_term(x) - f_ext = 0 on the free unknowns with the consistent
tangent, from the start the `Predictor` gives; prescribed values are reached through the
increments of the constrained unknowns (the first iteration acts as a tangent predictor).
A trial update that inverts an element or gives NaN is halved; the `IncrementLimiter` may
shorten it; with `line_search` a safeguarded secant search on g(s) = du . r(x + s du)
(Matthies & Strang 1979; FEBio's line search) is made when the full update raises the
potential, overshoots the minimum along du and makes the residual grow. A step that does not
converge (`ConvergenceCriterion`) is cut back: the last converged state is restored and the
step halved. At a converged step every term's `end_step` may ask for another solve of the
same step (augmented Lagrangian); the re-solve keeps the step's first energy norm as its
reference: it continues the same load increment. Each iteration is logged (logger
"solver.newton") and sent to an optional callback, like FEBio's log: step, load, iteration,
residual, energy and displacement norms, line-search step size.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from solver.assembly._extended import ExtendedPattern, rotate_blocks
from solver.memory import keep_freed_memory
from solver.bc import ConstraintSet
from solver.control import (ConvergenceCriterion, IncrementLimiter, Predictor, SolverControl,
                            StepController, StepResult)
from solver.control import extrapolate as _extrapolate
from solver.continuation import PseudoTransient
from solver.errors import SolveFailed
from solver import linalg as _linalg
from solver.linalg import LaggedFactorSolver, SymmetricSolver, _dot, sym_matvec
from solver.terms import as_term

__all__ = ["newton_solve", "NewtonResult", "StepRecord", "SolverControl"]

log = logging.getLogger("solver.newton")


@dataclass
class StepRecord:
    step: int
    load: float
    iterations: int
    residuals: list
    retries: int = 0


@dataclass
class NewtonResult:
    """Converged (or last converged) state and history."""

    x: np.ndarray                    # current nodal coordinates (n, 3)
    u: np.ndarray                    # displacement (n, 3)
    load: float                      # load fraction reached
    converged: bool
    steps: list = field(default_factory=list)
    iterations: int = 0
    cutbacks: int = 0
    log: list = field(default_factory=list)     # one dict per iteration
    timings: dict = field(default_factory=dict)
    factorizations: int = 0          # numerical factorisations of the tangent
    krylov_iterations: int = 0       # preconditioned CG iterations (lagged-factor strategy)
    linear_strategy: str = "exact"
    predictor: str = "tangent"       # the load-step predictor used ("tangent" or "secant")
    predictor_rejections: int = 0    # steps restarted with the tangent predictor
    early_augmentations: int = 0     # solves stopped early for an augmentation
    convexified: int = 0             # updates solved again with convexified term tangents
                                     # (the exact one was not a descent direction)
    blowups_halved: int = 0          # trial updates halved by the blow-up guard
    continuation_from: float | None = None   # load fraction from which pseudo-transient
                                             # continuation was on (None: never)
    continuation_iterations: int = 0         # iterations solved with the PTC damping
    # the solve at full load from a given guess tried first (`newton_solve(guess=...)`):
    # None when no guess was given, else {"converged", "iterations", "reason"}
    guess: dict | None = None
    # forces the constraints exert on the body (residual at the constrained dofs), (n, 3), in
    # each node's local frame where a LocalFrame is given, zero at unconstrained components
    reactions: np.ndarray | None = None


class _System:
    """Evaluates residual and tangent of body + terms in transformed unknowns."""

    def __init__(self, body, cons: ConstraintSet, terms, external):
        self.body = body
        self.cons = cons
        self.terms = [as_term(t) for t in terms]
        self.external = external
        pat = body.pattern
        # body pattern + the node pairs the terms may couple (contact): term stiffness is
        # summed into it by position, local frames rotate its blocks in place, and the global
        # pattern stays fixed once grown
        pairs = [np.asarray(t.coupling_pairs(), dtype=np.int64).reshape(-1, 2)
                 for t in self.terms]
        pairs = [p for p in pairs if len(p)]
        self.pattern = ExtendedPattern(pat, np.vstack(pairs) if pairs else None)
        self._masks_for = None
        # diagonal entry of the constrained rows (and factor of their right-hand side, the gap):
        # the mean stiffness diagonal at those dofs, fixed at the first tangent, so that the
        # equations du_c = gap are in force units like the others (a Krylov solve's relative
        # residual then weighs them alike; a direct solve is unaffected)
        self.constraint_scale = None
        self.timing = {"assembly": 0.0, "solve": 0.0}
        # the terms' potential is only read by the line search (a contact term's energy is
        # another search and gap evaluation): without it `ev.energy` is the body's alone
        self.need_energy = True

    def _set_constraint_scale(self, diag_c):
        if self.constraint_scale is None:
            d = np.abs(diag_c)
            d = d[np.isfinite(d) & (d > 0.0)]
            self.constraint_scale = float(d.mean()) if len(d) else 1.0

    def evaluate(self, x, load, tangent=True, targets=None):
        """(evaluation, residual r_hat, modified matrix A, coupling K[:, c] gap) at x."""
        t0 = time.perf_counter()
        ev = self.body.evaluate(x, load, tangent=tangent)
        if not ev.valid:
            self.timing["assembly"] += time.perf_counter() - t0
            return ev, None, None, None
        r = ev.force.copy()
        f_int_norm = _norm(r)
        f_term_norm = 0.0
        energy = ev.energy
        Kt = []
        for term in self.terms:
            f, K = term.assemble(x, load)
            # `_norm`, not np.linalg.norm: a BLAS dot wakes OpenBLAS's threads, which then
            # spin on the second core while PARDISO and the numba kernels want it
            f_term_norm = max(f_term_norm, _norm(f))
            r += f
            if self.need_energy:
                energy += term.energy(x, load)
            if tangent and K is not None and K.nnz:
                Kt.append(K)
        if self.external is not None:
            r -= load * self.external
            u = np.ascontiguousarray((x - self.body.mesh.nodes).ravel())
            energy -= load * _dot(self.external, u)
        ev.energy = energy
        ev.force_scale = max(f_int_norm, f_term_norm, _norm(self.external) * load
                             if self.external is not None else 0.0)
        rhat = self.cons.to_local(r)
        A = None
        coupling = None
        if tangent:
            A, coupling = self._matrix(ev.data, Kt, self._gap(x, targets))
        self.timing["assembly"] += time.perf_counter() - t0
        return ev, rhat, A, coupling

    def _gap(self, x, targets):
        """The prescribed values still to impose at the constrained dofs (local frame), as a
        full-length vector; None when there are none or all are met."""
        if targets is None:
            return None
        uh = self.cons.to_local((x - self.body.mesh.nodes).ravel())
        g = targets - uh[self.cons.dofs]
        if not np.any(g != 0.0):
            return None
        gap = np.zeros(len(uh))
        gap[self.cons.dofs] = g
        return gap

    def retangent_terms(self, x, load, ev, targets=None):
        """(A, coupling) at x with the terms' tangents assembled again and the body's
        tangent of the evaluation `ev` at the same x reused: for a term that changed only
        its tangent (`Term.convexify`), the residual and the body's part being unchanged."""
        t0 = time.perf_counter()
        Kt = []
        for term in self.terms:
            _, K = term.assemble(x, load)
            if K is not None and K.nnz:
                Kt.append(K)
        # `_matrix` works in place on a pattern-sized array: the body's data stays intact
        A, coupling = self._matrix(np.array(ev.data, copy=True), Kt, self._gap(x, targets))
        self.timing["assembly"] += time.perf_counter() - t0
        return A, coupling

    @staticmethod
    def _sym_matvec(Ku, v):
        if not Ku.has_sorted_indices:
            Ku.sort_indices()
        return sym_matvec(Ku, v)

    def _matrix(self, data, Kt, gap=None):
        """Constrained upper-triangle matrix and the coupling vector K gap (or None)."""
        cons = self.cons
        coupling = None
        ext = self.pattern
        if Kt or not ext.identity:
            data = ext.data(data, Kt)
        if cons.any_frame:
            rotate_blocks(ext, data, cons.rot, cons.has_frame)
        if self._masks_for != ext.nnz:     # (re)build the constraint masks on the pattern
            cm = cons.mask
            self.zero_mask = cm[ext.rows] | cm[ext.indices]
            self.diag_c = ext.diagonal[cons.dofs]
            self._masks_for = ext.nnz
        if gap is not None:
            coupling = self._sym_matvec(ext.matrix(data), gap)
        self._set_constraint_scale(data[self.diag_c])
        data[self.zero_mask] = 0.0
        data[self.diag_c] = self.constraint_scale
        return ext.matrix(data), coupling


def newton_solve(body, constraints=(), terms=(), external=None, control: SolverControl | None = None,
                 *, x0=None, guess=None, callback=None, step_callback=None,
                 **settings) -> NewtonResult:
    """Solve the static equilibrium of `body` from load fraction 0 to 1.

    body: `solver.mechanics.SolidBody`; constraints: `Prescribed` / `LocalFrame` list;
    terms: `solver.terms.Term`s (or objects with its `assemble`, `energy`, `end_step`);
    external: optional dead nodal force vector (3n,) at load 1; control: `SolverControl` (the
    settings, generic defaults); any of its fields may also be given as a keyword argument,
    which overrides it. x0: start coordinates (default the reference ones); guess: coordinates
    (n, 3) of a solution of a nearby problem on the same mesh (other material parameters,
    loads or prescribed values): the full load is first solved in one step from there
    (`_Run.solve_from_guess`), and only if that fails is the load stepped from x0 (the attempt's
    iterations counted, the terms' state it changed undone); callback(record: dict) receives
    every iteration's log record; step_callback(result) each converged step.
    Raises `SolveFailed` (with the last converged state) if the load cannot be reached.
    """
    control = dataclasses.replace(control or SolverControl(), **settings)
    # the iterations allocate and free arrays of tens of MB: keep their pages in the process
    keep_freed_memory()
    if guess is not None:
        guess = np.asarray(guess, dtype=float)
        if guess.shape != body.mesh.nodes.shape:
            raise ValueError(f"guess must have shape {body.mesh.nodes.shape}, got {guess.shape}")
    run = _Run(body, constraints, terms, external, control, x0 if guess is None else guess,
               callback)
    if guess is not None:
        if run.solve_from_guess():
            if step_callback is not None:
                step_callback(run.result)
            return run.finish(run.result.x, 1.0, converged=True)
        run.start_from(x0)          # the attempt's iterations stay in the counts
    result, stepper, predictor = run.result, run.stepper, run.predictor
    x, load, step_no = run.x, 0.0, 0
    failures = 0                # consecutive failed load steps
    damped_failures = 0         # ... of them under continuation
    while load < 1.0 - 1e-12:
        step_no += 1
        target = stepper.target(load)
        step = run.solve_load_step(x, target, step_no)
        if step.converged:
            x, load = step.x, target
            if step.peak_scale > 0.0:
                run.step_scale = step.peak_scale
            predictor.converged(target, x.copy(), run.mixed_state())
            result.steps.append(StepRecord(step_no, load, step.iterations, step.residuals,
                                           step.retries))
            result.x, result.u, result.load = x, x - run.X, load
            log.info("step %d converged at load %.4g in %d iterations", step_no, load,
                     step.iterations)
            if step_callback is not None:
                step_callback(result)
            failures = damped_failures = 0
            if run.ptc is None:
                stepper.converged(step.iterations, step.first_iterations)
            else:
                # under continuation the iteration count of a damped solve does not measure
                # the step's difficulty: the step grows when no update needed the damping
                stepper.converged_damped(not run.ptc.needed)
                run.ptc.step_converged()
        else:
            # the shorter step starts from the converged state, with the terms as they were
            # there: not from the failed solve's iterate (at the higher load) nor with the
            # multipliers its augmentations updated
            if step.out_of_time:
                run.finish(x, load, converged=False)
                raise _failed(step_no, target, load, step, result, "no time left for a shorter step")
            result.cutbacks += 1
            predictor.cut_back()
            run.restore_step_start()
            run.restore_terms()
            ok = stepper.cut_back(load, target)
            log.warning("step %d failed at load %.4g (%s); cutting back to step %.4g",
                        step_no, target, step.reason, stepper.dt)
            failures += 1
            if run.ptc is not None:
                run.ptc.step_failed()
                damped_failures += 1
                if ok and control.ptc_max_failures and damped_failures >= control.ptc_max_failures:
                    # continuation damps any step: shortening it further does not help where
                    # so many damped steps in a row failed; fail now rather than halving down
                    # to `min_step` at the cost of a budget of damped iterations per halving
                    run.finish(x, load, converged=False)
                    raise _failed(step_no, target, load, step, result,
                                  f"{damped_failures} consecutive load steps failed under "
                                  f"pseudo-transient continuation (on from load "
                                  f"{result.continuation_from:.4g})")
            elif (ok and control.ptc_after is not None
                  and failures >= control.ptc_after):
                # Newton failed on repeatedly shortened steps: a limit point or a jump of the
                # residual (contact) rather than a too long step; from here on every solve is
                # damped (`solver.continuation`) until the damping has faded over converged steps
                run.start_continuation(load)
            if not ok:
                run.finish(x, load, converged=False)
                raise _failed(step_no, target, load, step, result,
                              f"step size fell below {control.min_step:g}")
    return run.finish(x, load, converged=True)


def _failed(step_no, target, load, step, result, why) -> SolveFailed:
    """The error ending a run whose step `step_no` (to load `target`, from the converged
    `load`) failed, with where, why and the run's state."""
    return SolveFailed(
        f"Newton's method failed in step {step_no} at load fraction {target:.4g} "
        f"(last converged {load:.4g}): {step.reason}; worst element "
        f"{step.worst_element} (min J {step.min_J:.3g}); {why}",
        step=step_no, load=target, last_converged_load=load,
        worst_element=step.worst_element, state=result)


class _Run:
    """One `newton_solve`: the system, its control objects and the solves of a load step."""

    def __init__(self, body, constraints, terms, external, control, x0, callback):
        mesh = body.mesh
        self.X = X = mesh.nodes
        n = mesh.n_nodes
        used = np.zeros(n, dtype=bool)
        used[mesh.hexes.ravel()] = True
        cons = ConstraintSet(n, list(constraints), unused_nodes=np.nonzero(~used)[0])
        if external is not None:
            external = np.asarray(external, dtype=float).ravel()
            if external.shape != (3 * n,):
                raise ValueError(f"external must have shape ({3 * n},), got {external.shape}")
        self.body, self.cons, self.control, self.callback = body, cons, control, callback
        self.system = system = _System(body, cons, terms, external)
        # the terms' potential is only read by the line search
        system.need_energy = bool(control.line_search)
        held = np.zeros(n, dtype=bool)
        held[np.asarray(cons.dofs, dtype=np.int64) // 3] = True
        watched = np.nonzero(~held)[0]
        if control.increment_nodes is not None:
            watched = np.intersect1d(watched, np.asarray(control.increment_nodes, dtype=np.int64))
        self.limiter = IncrementLimiter(control.max_increment, watched)
        self.criterion = ConvergenceCriterion(control.rtol, control.atol, control.etol,
                                              control.stall_iterations or None)
        strategy = control.linear_strategy
        if strategy == "auto":
            strategy = "lagged" if 3 * n >= control.lagged_min_dofs else "exact"
        if strategy == "lagged":
            self.lin = LaggedFactorSolver(
                control.linear_solver, rtol=control.krylov_rtol, maxiter=control.krylov_maxiter,
                forcing_max=control.krylov_forcing, refactor_iterations=control.krylov_refactor,
                precision=control.krylov_precision)
        else:
            self.lin = SymmetricSolver(control.linear_solver)
        kind = control.predictor
        if kind == "auto":
            # secant with the lagged strategy; tangent when extra terms meet prescribed
            # motion: terms that move with the prescribed boundary (contact with moving
            # surfaces) make the extrapolated state a poor start
            kind = "secant" if strategy == "lagged" else "tangent"
            if system.terms and len(cons.dofs) and np.any(cons.targets(1.0, X) != 0.0):
                kind = "tangent"
        self.mixed = bool(control.mixed and getattr(body, "supports_mixed", False))
        if not self.mixed and getattr(body, "supports_mixed", False):
            body.mixed = None
        self.kind = kind
        self.start_from(x0)
        self.result = NewtonResult(x=self.x, u=self.x - X, load=0.0, converged=False,
                                   linear_strategy=strategy, predictor=kind)
        self.size = float(np.abs(X).max()) + 1.0
        self.t_start = time.perf_counter()
        self.pardiso0 = dict(_linalg.TIMING)
        self._start_mixed = None
        self._term_states = []
        self.ptc = None             # the `PseudoTransient` damping once continuation is on
        # the largest force scale of the iterates of the last converged load step: the
        # blow-up guard's reference at a step's first iteration (None before one converged)
        self.step_scale = None

    def start_from(self, x0):
        """The load stepping starts at load 0 from x0 (None: the reference coordinates): the
        three-field state, the predictor's history and the step controller afresh (also
        after a solve from a guess that failed, whose counts stay in the result)."""
        X = self.X
        self.x = X.copy() if x0 is None else np.array(x0, dtype=float)
        if self.mixed:
            self.body.begin_mixed(self.x)
        # a quadratic extrapolation overshoots where contact switching on kinks the load
        # path: with extra terms it is linear
        start = None if x0 is not None else (0.0, self.x.copy(), self.mixed_state())
        self.predictor = Predictor(self.kind, 2 if self.system.terms else 3, start, _extrapolate)
        self.stepper = StepController(self.control)
        if isinstance(self.lin, LaggedFactorSolver):
            self.lin.reset()

    def solve_from_guess(self) -> bool:
        """The full load solved in one load step from the start coordinates, the solution of
        a nearby problem on the same mesh (continuation in a parameter of the problem rather
        than in the load: a solve that differs from a converged one by a small change of a
        material, load or prescribed value starts inside Newton's basin of convergence, where
        stepping the load from rest repeats the whole path). The three-field state starts
        from the guess's own dilatations and pressures, the terms from their present state
        (contact searched afresh, multipliers augmented as in any step). True when the step
        converged (the result holds it); else the terms' state is back to what it was.
        `result.guess` records the attempt. A solution of another mesh interpolated is not
        such a guess (its elements inherit the other mesh's sub-element volume changes and
        prescribed values: docs/effects.md)."""
        result = self.result
        step = self.solve_load_step(self.x, 1.0, 1)
        result.guess = {"converged": bool(step.converged), "iterations": int(result.iterations),
                        "reason": None if step.converged else step.reason}
        if step.converged:
            result.steps.append(StepRecord(1, 1.0, step.iterations, step.residuals, step.retries))
            result.x, result.u, result.load = step.x, step.x - self.X, 1.0
            log.info("converged at full load from the guess in %d iterations", result.iterations)
            return True
        log.warning("the full load did not converge from the guess (%s): stepping the load",
                    step.reason)
        self.restore_terms()
        return False

    def start_continuation(self, load):
        """Pseudo-transient continuation for the rest of the run (`solver.continuation`)."""
        diag = self.system.pattern.diagonal[np.asarray(self.cons.free, dtype=np.int64)]
        self.ptc = PseudoTransient(self.control.ptc_damping, diag)
        self.result.continuation_from = load
        log.warning("pseudo-transient continuation from load %.4g on", load)

    # --- state of the three-field iteration --------------------------------------------------
    def mixed_state(self):
        body = self.body
        return None if not self.mixed else (body.mixed[0].copy(), body.mixed[1].copy())

    def restore_step_start(self):
        """Back to the three-field state at the start of the step; the lagged factor is
        dropped (the next solve starts afresh)."""
        if self.mixed:
            self.body.mixed = (self._start_mixed[0].copy(), self._start_mixed[1].copy())
        if isinstance(self.lin, LaggedFactorSolver):
            self.lin.reset()

    def restore_terms(self):
        """The terms' state at the start of the step (`Term.restore_step`)."""
        for t, state in zip(self.system.terms, self._term_states):
            t.restore_step(state)

    def uhat(self, x):
        return self.cons.to_local((x - self.X).ravel())

    # --- one load step -----------------------------------------------------------------------
    def solve_load_step(self, x, target, step_no):
        """Solve the step to `target` from the converged x: the predictor's start (restarted
        from x with the tangent predictor if that solve goes astray), then the re-solves the
        terms ask for at convergence (augmentations, at most `max_retries`; a solve stopped
        early for an augmentation that does not come is converged first). Returns the
        `StepResult`; the terms' state at the step start is kept for a cut-back
        (`restore_terms`)."""
        control, result, terms = self.control, self.result, self.system.terms
        start = x.copy()
        self._start_mixed = self.mixed_state()
        self._term_states = [t.save_step() for t in terms]
        if isinstance(self.lin, LaggedFactorSolver):
            self.lin.begin_step()
        x_pred = self.predictor.start(target)
        energy0, early = None, control.augmentation_rtol
        retries, first_iterations = 0, None
        damped = 0                  # iterations of the step's damped solves
        while True:
            budget = None
            if self.ptc is not None and control.ptc_step_iterations:
                budget = control.ptc_step_iterations - damped
                if budget < 1:
                    step.converged = False
                    step.reason = (f"the step's {control.ptc_step_iterations} damped "
                                   f"iterations spent over {retries + 1} solves")
                    break
            step = self._solve(start, target, step_no, x_pred, energy0, early, budget)
            if self.ptc is not None:
                damped += step.iterations
            x_pred, energy0 = None, step.energy0
            if not step.converged and step.predicted:
                # the solve from the extrapolated start went astray: solve the step again
                # from its converged start with the tangent predictor, before any cut-back
                self.restore_step_start()
                for t in terms:
                    t.restart_step()
                log.info("step %d: %s; tangent predictor", step_no, step.reason)
                result.predictor_rejections += 1
                energy0 = None
                continue
            if first_iterations is None:
                first_iterations = step.iterations
            if not step.converged:
                break
            if self.out_of_time():
                # converged, but the re-solves the terms ask for cannot be afforded
                step.converged, step.out_of_time = False, True
                step.reason = f"the run's wall-clock budget of {control.max_seconds:g} s is spent"
                break
            again = any([bool(t.end_step(step.x, target)) for t in terms])
            result.early_augmentations += bool(step.early)
            if step.early and not again:
                early, start = None, step.x
                continue
            if not again or retries >= control.max_retries:
                break
            retries += 1
            start = step.x
        step.retries, step.first_iterations = retries, first_iterations
        return step

    # --- one Newton solve ----------------------------------------------------------------------
    def _solve(self, x0, target, step_no, x_pred=None, energy0=None, early=None,
               budget=None) -> StepResult:
        """Newton iterations at load `target` from x0 (or the extrapolated x_pred); under
        continuation at most `budget` iterations (what is left of the step's budget)."""
        system, cons, lin, body = self.system, self.cons, self.lin, self.body
        criterion, control, result = self.criterion, self.control, self.result
        free = cons.free
        targets = cons.targets(target, self.X)
        ev = None
        predicted = False
        if x_pred is not None:
            x_pred, mixed_pred = x_pred
            saved = body.mixed_snapshot() if mixed_pred is not None else None
            if saved is not None:
                body.mixed = (mixed_pred[0].copy(), mixed_pred[1].copy())
            x = x_pred.copy()
            ev, r, A, cpl = system.evaluate(x, target, targets=targets)
            predicted = bool(ev.valid)
            if not ev.valid:            # extrapolated too far: start from the converged state
                ev = None
                if saved is not None:
                    body.mixed_restore(saved)
        if ev is None:
            x = x0.copy()
            ev, r, A, cpl = system.evaluate(x, target, targets=targets)
        step = StepResult(converged=False, x=x, energy0=energy0, predicted=predicted)
        if not ev.valid:
            return step.failed("invalid start state", ev)
        tiny = 1e-10 * max(1.0, float(np.abs(targets).max()) if len(targets) else 1.0)
        residuals = []
        ptc = self.ptc
        max_iterations = control.max_iterations
        if ptc is not None:
            ptc.start(_norm(r[free]), again=energy0 is not None)
            max_iterations = max(max_iterations, control.ptc_iterations)
            if budget is not None:
                max_iterations = max(1, min(max_iterations, int(budget)))
        for it in range(1, max_iterations + 1):
            gap = targets - self.uhat(x)[cons.dofs]
            out = self._descent_direction(x, target, targets, step_no, it, ev, r, A, cpl, gap)
            if isinstance(out, str):        # a singular or failed factorisation: cut back
                return step.failed(out, ev)
            du_hat, rhs, stats, r, A, cpl = out
            du = cons.to_global(du_hat).reshape(-1, 3)
            # directional derivative of the potential along du (the coupling to the
            # constrained increments included): its magnitude is FEBio's energy norm
            g0 = -_dot(du_hat[free], rhs[free])
            energy = abs(g0)
            s, ev1, r, A, cpl = self._update(x, du, du_hat, g0, ev, r, target, targets,
                                             has_gap=bool(np.any(gap != 0.0)), guarded=it > 1)
            if s is None:
                return step.failed("every trial update inverts an element or blows the "
                                   "residual up", ev1)
            ev = ev1
            step.peak_scale = max(step.peak_scale, ev.force_scale)
            if step.energy0 is None:
                step.energy0 = max(energy, 1e-300)
            x = x + s * du
            step.x = x
            rn = _norm(r[free])
            dn = abs(s) * _norm(du.ravel())
            gap_after = float(np.max(np.abs(targets - self.uhat(x)[cons.dofs]))) \
                if len(cons.dofs) else 0.0
            scale = max(ev.force_scale, 1e-300)
            self._log(step_no, target, it, rn, scale, energy, step.energy0, dn, s, gap_after,
                      ev, stats)
            residuals.append(rn)
            if ptc is not None:
                ptc.advance(rn, full=s == 1.0)
                result.continuation_iterations += 1
            step.iterations, step.residuals = it, list(residuals)
            step.worst_element, step.min_J = ev.worst_element, ev.min_J
            if criterion.converged(it, rn, scale, energy, step.energy0, gap_after, tiny):
                step.converged = True
                return step
            # predictor safeguard: a solve from the extrapolated state whose residual grows
            # at its second iteration is abandoned (the step restarts with the tangent one)
            if predicted and it == 2 and rn > residuals[0]:
                step.reason = f"predictor rejected (|R| {residuals[0]:.3e} -> {rn:.3e})"
                return step
            # the step will be augmented anyway: the multiplier update need not wait for the
            # penalty solve to converge (asked once per solve)
            if early is not None and gap_after <= tiny and rn <= early * scale:
                early = None
                if any([bool(t.augmentation_due(x, target)) for t in system.terms]):
                    step.converged = step.early = True
                    log.info("step %d: stopped at relative residual %.2e for an augmentation",
                             step_no, rn / scale)
                    return step
            if criterion.at_round_off(it, rn, scale, dn, self.size, gap_after, tiny):
                step.converged, step.reason = True, "converged at round-off"
                return step
            if self.out_of_time():
                step.out_of_time = True
                step.reason = (f"the run's wall-clock budget of {control.max_seconds:g} s is spent "
                               f"(|R| = {rn:.3e})")
                return step
            if criterion.diverges(it, residuals):
                step.reason = "residual diverges"
                return step
            if ptc is None and criterion.stalled(it, residuals):
                step.reason = f"no progress in {it} iterations (|R| = {rn:.3e})"
                return step
            if A is None:               # evaluated without the tangent and not converged
                ev, r, A, cpl = system.evaluate(x, target, targets=targets)
        step.reason = f"no convergence in {max_iterations} iterations (|R| = {rn:.3e})"
        if budget is not None and max_iterations >= budget:
            step.reason += (f"; the step's {control.ptc_step_iterations} damped iterations "
                            f"spent")
        return step

    def _linear_solve(self, A, rhs, ev):
        """The Newton system A du = rhs (the lagged strategy's forcing term from the
        residual); (du_hat, statistics) or the reason of a failure (str)."""
        lin, control, system = self.lin, self.control, self.system
        t0 = time.perf_counter()
        try:
            if isinstance(lin, LaggedFactorSolver):
                scale = max(ev.force_scale, 1e-300)
                eta = _forcing(lin, _norm(rhs), control.rtol * scale, scale)
                du_hat = lin.solve(A, rhs, rtol=eta)
            else:
                du_hat = lin.solve(A, rhs)
        except Exception as exc:
            return f"linear solver failed ({exc})"
        system.timing["solve"] += time.perf_counter() - t0
        stats = getattr(lin, "last", None) or {"krylov_iterations": 0, "refactorized": True}
        self.result.krylov_iterations += stats["krylov_iterations"]
        if not np.all(np.isfinite(du_hat)):
            return "linear solve gave NaN"
        return du_hat, stats

    def _descent_direction(self, x, target, targets, step_no, it, ev, r, A, cpl, gap):
        """The Newton update at x: (du_hat, rhs, statistics, r, A, coupling), or the reason
        of a failure (str).

        With a positive definite tangent the update is a descent direction of the potential
        (du . r = -du . A du < 0; an inexact CG solve started from zero keeps this: its
        iterate is A-orthogonal to its residual). du . r >= 0 means the tangent is indefinite
        along du (a contact term's curvature -p d2g/dx2 of a node pressed onto a convex
        surface, a negative stiffness as large as the tissue's): Newton then heads for a
        saddle and, the problem being smooth, cycles about it instead of converging. The
        terms are then asked for a positive semi-definite modification of their tangents
        (`Term.convexify`: the curvature parts projected, the residual unchanged, the
        projected Newton method of Teran, Sifakis, Irving & Fedkiw 2005; a modified-Hessian
        Newton method, Nocedal & Wright 2006, sec. 3.4) and the update is solved again with
        it. The next iteration starts again from the exact tangent: where it gives a descent
        direction Newton converges quadratically, where the projected curvature matters the
        modified one converges only linearly.
        """
        system, cons, free = self.system, self.cons, self.cons.free

        def solve(r, cpl):
            rhs = -r if cpl is None else -r - cpl
            rhs[cons.dofs] = system.constraint_scale * gap
            M = A if self.ptc is None else self.ptc.damped(A)
            return rhs, self._linear_solve(M, rhs, ev)

        rhs, out = solve(r, cpl)
        if isinstance(out, str):
            return out
        g0 = -_dot(out[0][free], rhs[free])
        if g0 > 0.0 and any([bool(t.convexify(True)) for t in system.terms]):
            self.result.convexified += 1
            if self.ptc is not None:
                self.ptc.indefinite = True      # the damping grows instead of falling
            log.info("step %d it %d: the update is not a descent direction (du.r = %.3e > 0): "
                     "convexified contact tangents", step_no, it, g0)
            try:
                # the forces are unchanged: only the terms' tangents are assembled again
                A, cpl = system.retangent_terms(x, target, ev, targets=targets)
            finally:
                for t in system.terms:
                    t.convexify(False)
            rhs, out = solve(r, cpl)
            if isinstance(out, str):
                return out
            g0 = -_dot(out[0][free], rhs[free])
        # under continuation the damping is raised until the update goes downhill (the
        # damped matrix is positive definite for a large enough damping); with prescribed
        # increments to impose the update is not one of the potential at fixed constraints
        tries = 0
        while self.ptc is not None and g0 > 0.0 and tries < 6 and not np.any(gap != 0.0):
            tries += 1
            self.ptc.raise_damping()
            log.info("step %d it %d: damped update not a descent direction: damping %.2e",
                     step_no, it, self.ptc.delta)
            rhs, out = solve(r, cpl)
            if isinstance(out, str):
                return out
            g0 = -_dot(out[0][free], rhs[free])
        return out[0], rhs, out[1], r, A, cpl

    def _update(self, x, du, du_hat, g0, ev, r, target, targets, has_gap, guarded=False):
        """The accepted length s of the update du and the evaluation at x + s du: limited by
        the `IncrementLimiter`, halved while it inverts an element or its residual blows up
        (`SolverControl.blowup_factor`; measured against x's force scale where x is an iterate
        of this solve (`guarded`), else against the last converged step's iterates), then, with
        the line search on, a secant search when the full step overshoots. s is None when
        every trial is rejected."""
        system, control, body, free = self.system, self.control, self.body, self.cons.free
        snap = body.mixed_snapshot() if getattr(body, "mixed", None) is not None else None
        # Near convergence (relative residual below 10 sqrt(rtol), from where a quadratically
        # converging iteration lands below rtol) the new iterate is evaluated without its
        # tangent first: if it has converged the tangent is not needed
        lazy = (not control.line_search and not has_gap
                and _norm(r[free]) <= 10.0 * np.sqrt(control.rtol) * max(ev.force_scale, 1e-300))
        s = self.limiter.step_length(du)
        if s < 1.0:
            lazy = False
        # the blow-up guard's bound on the trial residual (None: not applied, see SolverControl)
        reference = ev.force_scale if guarded else self.step_scale
        bound = None
        if control.blowup_factor is not None and reference is not None and reference > 0.0:
            bound = control.blowup_factor * reference
        for _ in range(12):
            if snap is not None:
                body.mixed_update(snap, s * du)
            ev1, r1, A1, c1 = system.evaluate(x + s * du, target, targets=targets,
                                              tangent=not lazy)
            if ev1.valid and (bound is None or _norm(r1[free]) <= bound):
                break
            if ev1.valid:
                self.result.blowups_halved += 1
            lazy = False
            s *= 0.5
        else:
            return None, ev1, None, None, None
        if control.line_search and s == 1.0 and g0 < 0 and not has_gap:
            s1 = _secant_search(system, body, snap, x, du, du_hat, free, g0, ev, r, ev1, r1,
                                target, control)
            if s1 is not None:
                s = s1
                if snap is not None:
                    body.mixed_update(snap, s * du)
                ev1, r1, A1, c1 = system.evaluate(x + s * du, target, targets=targets)
                if not ev1.valid:
                    s = 1.0
                    if snap is not None:
                        body.mixed_update(snap, du)
                    ev1, r1, A1, c1 = system.evaluate(x + du, target, targets=targets)
        return s, ev1, r1, A1, c1

    def _log(self, step_no, target, it, rn, scale, energy, energy0, dn, s, gap_after, ev, stats):
        rec = {"step": step_no, "load": target, "iteration": it, "residual_norm": rn,
               "relative_residual": rn / scale, "energy_norm": energy,
               "energy_ratio": energy / energy0, "displacement_norm": dn, "line_search": s,
               "constraint_gap": gap_after, "min_J": ev.min_J,
               "krylov_iterations": stats["krylov_iterations"],
               "factorized": bool(stats["refactorized"]),
               "damping": self.ptc.delta if self.ptc is not None else 0.0}
        self.result.log.append(rec)
        self.result.iterations += 1
        log.info("step %3d load %.4f it %2d |R| %.3e (rel %.2e) E %.3e |du| %.3e s %.3g "
                 "cg %d%s%s", step_no, target, it, rn, rn / scale, energy, dn, s,
                 stats["krylov_iterations"], " fact" if stats["refactorized"] else "",
                 f" ptc {self.ptc.delta:.2e}" if self.ptc is not None else "")
        if self.callback is not None:
            self.callback(rec)

    def out_of_time(self) -> bool:
        """The run's wall-clock budget (`SolverControl.max_seconds`) is spent."""
        budget = self.control.max_seconds
        return budget is not None and time.perf_counter() - self.t_start > budget

    def finish(self, x, load, converged):
        """Reactions, timings and counts into the result."""
        result, system = self.result, self.system
        result.factorizations = self.lin.factorizations
        if not converged:
            result.timings = dict(system.timing, total=time.perf_counter() - self.t_start)
            return result
        n = len(self.X)
        ev, rhat, _, _ = system.evaluate(x, load, tangent=False)
        reac = np.zeros(3 * n)
        reac[self.cons.dofs] = rhat[self.cons.dofs]
        result.reactions = reac.reshape(n, 3)
        result.converged = True
        result.timings = dict(system.timing, total=time.perf_counter() - self.t_start,
                              **{f"pardiso_{k}": v - self.pardiso0[k]
                                 for k, v in _linalg.TIMING.items()})
        return result


def _secant_search(system, body, snap, x, du, du_hat, free, g0, ev, r, ev1, r1, target, control):
    """Safeguarded secant search on g(s) = du . r(x + s du) (Matthies & Strang 1979), made
    only when the full update neither decreases the potential enough (Armijo) nor the
    directional residual (FEBio's criterion) and the residual grows `line_search_growth`
    times. Returns the step length, or None to take the full step."""
    ls_tol = control.line_search_tol
    g1 = float(du_hat[free] @ r1[free])
    armijo = np.isfinite(ev1.energy) and ev1.energy <= ev.energy + 1e-4 * g0
    grew = np.linalg.norm(r1[free]) > control.line_search_growth * max(np.linalg.norm(r[free]),
                                                                       1e-300)
    if armijo or g1 <= ls_tol * abs(g0) or not grew:
        return None
    sa, ga = 0.0, g0
    sb, gb = 1.0, g1
    best = (abs(g1), 1.0)
    for _ in range(4):
        sn = sb - gb * (sb - sa) / (gb - ga) if gb != ga else 0.5 * sb
        sn = float(np.clip(sn, 0.1 * sb, 0.9 * sb if gb > 0 else 2.0))
        if snap is not None:
            body.mixed_update(snap, sn * du)
        ev2, r2, _, _ = system.evaluate(x + sn * du, target, tangent=False)
        if not ev2.valid:
            break
        g2 = float(du_hat[free] @ r2[free])
        if abs(g2) < best[0]:
            best = (abs(g2), sn)
        if abs(g2) <= ls_tol * abs(g0):
            break
        sa, ga, sb, gb = sb, gb, sn, g2
    return best[1]


def _norm(v) -> float:
    # numba loop, not NumPy's BLAS (its threads cost milliseconds per call on a loaded machine)
    v = np.ascontiguousarray(v, dtype=float)
    return float(np.sqrt(_dot(v, v)))


def _forcing(lin, rhs_norm, goal, scale):
    """Relative tolerance (forcing term) of the Newton system's CG solve:
    eta = min(krylov_forcing, max((|b| / scale)^2, 0.1 goal / |b|)), at least krylov_rtol.
    A forcing term of the order of the relative residual squared keeps Newton's quadratic
    convergence (Dembo, Eisenstat & Steihaug 1982, thm. 3.3: eta_k = O(|r_k|) suffices);
    a linear residual of a tenth of the Newton tolerance `goal` is always accurate enough for
    the next iterate to converge (no oversolving in the last iteration of a step, Kelley 1995,
    sec. 6.3).
    """
    if rhs_norm <= 0.0:
        return lin.forcing_max
    eta = max((rhs_norm / scale) ** 2, 0.1 * goal / rhs_norm)
    return max(lin.rtol, min(lin.forcing_max, eta))
