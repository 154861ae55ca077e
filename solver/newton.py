"""Newton-Raphson with line search and adaptive load stepping (FEBio-like), `newton_solve`.

The load fraction goes from 0 to 1 in steps. Each step solves r(x) = f_int(x) + sum f_term(x)
- f_ext = 0 on the free unknowns with the consistent tangent; prescribed values are reached
through the increments of the constrained unknowns (the first iteration acts as a tangent
predictor). A trial update that inverts an element or gives NaN is halved; otherwise, if the
full update raises the potential (no Armijo decrease) and overshoots the minimum along du
(the directional residual g(1) = du . r(x + du) > `line_search_tol` |g(0)|) while the residual
norm grows more than `line_search_growth` times, a safeguarded
secant search on g is made (Matthies & Strang 1979; FEBio's line search) when `line_search`
is on. It is off by default: on nearly incompressible problems the volumetric energy often
rises at an early full step although undamped Newton converges fastest (Cook's membrane:
6 iterations per step undamped, 10-14 with the search); the halving on inversion always acts. A step
that does not converge within `max_iterations` (or diverges, or cannot avoid inversion) is
cut back: the last converged state is restored and the step halved, down to `min_step`. After an
easy step the step grows again (never beyond the initial size). Convergence needs both the
residual norm |r_free| <= rtol * max(|f_int|, |f_ext|) (or <= atol) and the energy norm
|du . r| <= etol * (first energy norm of the step; a re-solve of the step asked by a term's
`end_step`, an augmentation, keeps that reference: it continues the same load increment).
Terms that augment (contact) may have a solve stopped before convergence when the step is to
be augmented anyway (`augmentation_rtol`). Each iteration is logged (module `logging`,
logger "solver.newton") and sent to an optional callback, like FEBio's log: step, load,
iteration, residual norm, energy norm, displacement norm, line-search step size.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from solver.assembly._extended import ExtendedPattern, rotate_blocks
from solver.bc import ConstraintSet
from solver.errors import SolveFailed
from solver import linalg as _linalg
from solver.linalg import LaggedFactorSolver, SymmetricSolver, _dot, sym_matvec

__all__ = ["newton_solve", "NewtonResult", "StepRecord"]

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
    # forces the constraints exert on the body (residual at the constrained dofs), (n, 3), in
    # each node's local frame where a LocalFrame is given, zero at unconstrained components
    reactions: np.ndarray | None = None


class _System:
    """Evaluates residual and tangent of body + terms in transformed unknowns."""

    def __init__(self, body, cons: ConstraintSet, terms, external):
        self.body = body
        self.cons = cons
        self.terms = list(terms)
        self.external = external
        pat = body.pattern
        # body pattern + the node pairs the terms may couple (contact): term stiffness is
        # summed into it by position, local frames rotate its blocks in place, and the global
        # pattern stays fixed once grown
        pairs = [np.asarray(t.coupling_pairs(), dtype=np.int64).reshape(-1, 2)
                 for t in self.terms if hasattr(t, "coupling_pairs")]
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
            # `_norm`, not np.linalg.norm: a BLAS dot wakes OpenBLAS's threads, which then spin
            # on the second core while PARDISO and the numba kernels want it (orbicularis oris
            # worst case, standard face: 0.30 -> 0.26 s per Newton iteration with contact)
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
            gap = None
            if targets is not None:
                uh = self.cons.to_local((x - self.body.mesh.nodes).ravel())
                g = targets - uh[self.cons.dofs]
                if np.any(g != 0.0):
                    gap = np.zeros(len(rhat))
                    gap[self.cons.dofs] = g
            A, coupling = self._matrix(ev.data, Kt, gap)
        self.timing["assembly"] += time.perf_counter() - t0
        return ev, rhat, A, coupling

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


def newton_solve(body, constraints=(), terms=(), external=None, *, steps: int = 10,
                 min_step: float = 1e-4, max_iterations: int = 25, rtol: float = 1e-8,
                 atol: float = 1e-10, etol: float = 1e-10, line_search: bool = False,
                 line_search_tol: float = 1.0, line_search_growth: float = 100.0, max_retries: int = 5, grow: bool = True,
                 x0=None, linear_solver: str = "auto", callback=None,
                 step_callback=None, mixed: bool = True, linear_strategy: str = "auto",
                 krylov_rtol: float = 1e-8, krylov_maxiter: int = 10, krylov_forcing: float = 1e-2,
                 lagged_min_dofs: int = 20000, krylov_refactor: int = 8,
                 krylov_precision: str = "single", predictor: str = "auto",
                 max_increment: float | None = None,
                 increment_nodes=None,
                 stall_iterations: int | None = None,
                 shrink_iterations: int | None = None,
                 augmentation_rtol: float | None = 0.5) -> NewtonResult:
    """Solve the static equilibrium of `body` from load fraction 0 to 1.

    body: `solver.mechanics.SolidBody`; constraints: `Prescribed` / `LocalFrame` list;
    terms: objects following `solver.terms.Term`; external: optional dead nodal force vector
    (3n,) at load 1; steps: initial number of equal load steps (also the largest step size);
    callback(record: dict) receives every iteration's log record; step_callback(result) each
    converged step. mixed: for mean-dilatation bodies that support it, iterate on the
    three-field (u, p, theta) system with element-wise condensation (the pressure and dilatation
    are updated from the linearised constraint rather than recomputed from u), which converges
    in markedly fewer iterations on nearly incompressible problems; the converged solution is
    the same. Raises `SolveFailed` (with the last converged state) if the load cannot
    be reached.

    linear_strategy: "exact" factorises every tangent (Newton's method with direct solves);
    "lagged" keeps the Cholesky factor of an earlier tangent (single precision by default,
    `krylov_precision`) across iterations and load steps and solves each Newton system with the
    fresh tangent by conjugate gradients preconditioned with it (`solver.linalg.
    LaggedFactorSolver`): an inexact Newton method (Dembo, Eisenstat & Steihaug 1982) whose
    forcing term is the squared relative residual or a tenth of the Newton tolerance over the
    residual, whichever is looser (quadratic convergence kept), at most `krylov_forcing`, at
    least `krylov_rtol`, refactorising
    when CG needs more than `krylov_maxiter` iterations, or before the next solve when it
    needed more than `krylov_refactor`; a tangent that is not positive definite is solved
    directly (symmetric indefinite LDL^T) for the rest of the load step. The residual is always
    exact, so the converged solution is that of exact Newton (to the convergence tolerance),
    with far fewer factorisations. "auto" takes "lagged" from `lagged_min_dofs` unknowns on
    (where a factorisation costs seconds) and "exact" below. Each log record holds
    `krylov_iterations` and `factorized`.

    predictor: "tangent" starts each step from the last converged state, the first iteration
    imposing the prescribed increments (a tangent predictor); "secant" starts it from the
    extrapolation of the last converged states in the load fraction (quadratic through three,
    or linear, x_n + (dt_n+1/dt_n)(x_n - x_n-1), with extra terms), falling back to the
    tangent predictor when that state is invalid, on the first step and after a cut-back, and
    restarting the step with it when the solve from the extrapolated state fails or its
    residual grows at the second iteration (`predictor_rejections`); it saves about one
    Newton iteration per step on smooth load paths. "auto" takes "secant" with the lagged strategy, except with extra
    terms under prescribed motion (contact with surfaces that move with the prescribed
    bones), and "tangent" otherwise; `NewtonResult.predictor` records the choice.
    max_increment: if given (mm), a Newton update that would move some free node farther is
    scaled down to that length (damped Newton far from the solution, e.g. when contact
    switches on; near the solution updates are small and the full step is taken).
    increment_nodes: the nodes `max_increment` watches (default: every free node), e.g. the
    nodes of the contact surfaces, so that the rest of the body may follow large prescribed
    motions in one update.
    stall_iterations: if given, a step whose residual has not fallen below a tenth of its
    first iteration's after that many iterations is cut back at once (no progress).
    shrink_iterations: if given, a step whose first solve needed more than that many
    iterations is followed by a step of half its size (iteration-based increment control, as
    Abaqus' and FEBio's automatic time stepping: a hard step announces a harder next one, and
    halving it costs less than a failed step's cut-back); the re-solves of a step's
    augmentation do not count.
    augmentation_rtol: once the relative residual of a solve falls below it, the terms that
    define `augmentation_due(x, load)` are asked (once per solve) whether the step will be
    augmented anyway (contact penetrating well beyond its tolerance on a step augmented to
    it); if one says so the solve stops there and the step goes on to `end_step`, whose
    multiplier update and re-solve then start from this partly converged state (an inexact
    inner solve of the augmented Lagrangian method: the penalty solution of a state that the
    update will change need not be converged; the update from a rough iterate may ask for one
    more). The step still ends with a solve converged to `rtol`, its penetration checked by
    `end_step`. None: every solve is converged before `end_step`. Standard face, Newton
    iterations with 0.5 (asked from the first iteration on) / 1e-2 (from the second) / None:
    orbicularis oris worst case of `bench/contact.py` 17 / 18 / 20, demo plan 40 / 43 / 43;
    with 0.5 / 1e-2: `faceplan synth` seed 7 49 / 50, seed 11 63 / 60 (its last step needs a
    second update), 8 mm closure 24 / 24.
    """
    mesh = body.mesh
    X = mesh.nodes
    n = mesh.n_nodes
    used = np.zeros(n, dtype=bool)
    used[mesh.hexes.ravel()] = True
    cons = ConstraintSet(n, list(constraints), unused_nodes=np.nonzero(~used)[0])
    if external is not None:
        external = np.asarray(external, dtype=float).ravel()
        if external.shape != (3 * n,):
            raise ValueError(f"external must have shape ({3 * n},), got {external.shape}")
    system = _System(body, cons, terms, external)
    system.max_increment = None if max_increment is None else float(max_increment)
    system.need_energy = bool(line_search)
    system.stall_iterations = None if not stall_iterations else int(stall_iterations)
    held = np.zeros(n, dtype=bool)
    held[np.asarray(cons.dofs, dtype=np.int64) // 3] = True
    system.watched_nodes = np.nonzero(~held)[0]        # the nodes `max_increment` limits
    if increment_nodes is not None:
        system.watched_nodes = np.intersect1d(system.watched_nodes,
                                              np.asarray(increment_nodes, dtype=np.int64))
    if linear_strategy not in ("auto", "exact", "lagged"):
        raise ValueError(f"linear_strategy must be 'auto', 'exact' or 'lagged', got {linear_strategy!r}")
    if linear_strategy == "auto":
        linear_strategy = "lagged" if 3 * n >= lagged_min_dofs else "exact"
    if linear_strategy == "lagged":
        lin = LaggedFactorSolver(linear_solver, rtol=krylov_rtol, maxiter=krylov_maxiter,
                                 forcing_max=krylov_forcing, refactor_iterations=krylov_refactor,
                                 precision=krylov_precision)
    else:
        lin = SymmetricSolver(linear_solver)
    if predictor not in ("auto", "tangent", "secant"):
        raise ValueError(f"predictor must be 'auto', 'tangent' or 'secant', got {predictor!r}")
    if predictor == "auto":
        # the secant predictor with the lagged strategy; but with extra terms under prescribed
        # motion, the tangent predictor: the terms (contact with surfaces moving with the
        # bones) make the extrapolated state a poor start (demo plan, standard face: the
        # secant predictor stalls and cuts back down to the minimum step at load 0.8; the
        # tangent predictor converges in 43 Newton iterations without a cut-back)
        predictor = "secant" if linear_strategy == "lagged" else "tangent"
        if system.terms and len(cons.dofs) and np.any(cons.targets(1.0, X) != 0.0):
            predictor = "tangent"
    # the extrapolation is quadratic (three converged states) on a smooth load path, linear
    # with extra terms: contact switching on kinks the path, and a parabola through the kink
    # overshoots (orbicularis oris on the standard face: quadratic predictor 0.45 mm deep into
    # the other lip at load 0.75, then a stall and two cut-backs, 48 Newton iterations; linear
    # 21 against 22 with the tangent predictor)
    extrapolation_points = 2 if system.terms else 3
    x = X.copy() if x0 is None else np.array(x0, dtype=float)
    free = cons.free
    mixed = bool(mixed and getattr(body, "supports_mixed", False))
    if mixed:
        body.begin_mixed(x)
    elif getattr(body, "supports_mixed", False):
        body.mixed = None
    result = NewtonResult(x=x, u=x - X, load=0.0, converged=False,
                          linear_strategy=linear_strategy, predictor=predictor)
    t_start = time.perf_counter()
    pardiso0 = dict(_linalg.TIMING)
    dt_max = 1.0 / max(int(steps), 1)
    dt = dt_max
    load = 0.0
    step_no = 0
    cut = 0

    def uhat(xx):
        return cons.to_local((xx - X).ravel())

    # converged states (load, x, mixed state) for the extrapolating predictor
    history = [] if x0 is not None else [(0.0, x.copy(), None if not mixed else
                                          (body.mixed[0].copy(), body.mixed[1].copy()))]
    just_cut = False
    while load < 1.0 - 1e-12:
        step_no += 1
        target = min(1.0, load + dt)
        if 1.0 - target < 0.25 * dt:
            target = 1.0
        x_conv = x.copy()
        mixed_conv = None if not mixed else (body.mixed[0].copy(), body.mixed[1].copy())
        retries = 0
        first_its = None
        if isinstance(lin, LaggedFactorSolver):
            lin.begin_step()
        x_pred = None
        if predictor == "secant" and len(history) >= 2 and not just_cut:
            x_pred = _extrapolate(history[-extrapolation_points:], target)
        e0 = None
        early = augmentation_rtol
        while True:
            ok, x_new, info = _solve_step(system, lin, x_conv, target, uhat, free, cons,
                                          max_iterations, rtol, atol, etol, line_search,
                                          line_search_tol, line_search_growth, step_no,
                                          callback, result, x_pred=x_pred, e0=e0,
                                          early=early)
            x_pred = None
            # a re-solve of the step (the terms' augmentation) continues the same load
            # increment: its energy criterion keeps the step's first energy norm
            e0 = info["e0"]
            if not ok and info["predicted"]:
                # the solve from the extrapolated start went astray or failed: solve the step
                # again from its converged start with the tangent predictor, before any
                # cut-back
                if mixed:
                    body.mixed = (mixed_conv[0].copy(), mixed_conv[1].copy())
                for t in system.terms:
                    if hasattr(t, "restart_step"):
                        t.restart_step()
                if isinstance(lin, LaggedFactorSolver):
                    lin.reset()
                log.info("step %d: %s; tangent predictor", step_no, info["reason"])
                result.predictor_rejections += 1
                e0 = None
                continue
            if first_its is None:
                first_its = info["iterations"]
            if not ok:
                break
            again = any([bool(t.end_step(x_new, target)) for t in system.terms])
            result.early_augmentations += bool(info["early"])
            if info["early"] and not again:
                # stopped early for an augmentation that did not come: converge the solve
                early, x_conv = None, x_new
                continue
            if not again or retries >= max_retries:
                break
            retries += 1
            x_conv = x_new
        if ok:
            just_cut = False
            history = history[-2:] + [(target, x_new.copy(), None if not mixed else
                                       (body.mixed[0].copy(), body.mixed[1].copy()))]
            x = x_new
            load = target
            result.steps.append(StepRecord(step_no, load, info["iterations"], info["residuals"],
                                           retries))
            result.x, result.u, result.load = x, x - X, load
            log.info("step %d converged at load %.4g in %d iterations", step_no, load,
                     info["iterations"])
            if step_callback is not None:
                step_callback(result)
            if grow and info["iterations"] <= 6:
                dt = min(dt_max, 1.5 * dt)
            if shrink_iterations and first_its > shrink_iterations:
                dt = max(0.5 * dt, min_step)
        else:
            cut += 1
            just_cut = True
            result.cutbacks = cut
            x = x_conv
            if mixed:
                body.mixed = (mixed_conv[0].copy(), mixed_conv[1].copy())
            if isinstance(lin, LaggedFactorSolver):
                lin.reset()
            dt = 0.5 * (target - load)
            log.warning("step %d failed at load %.4g (%s); cutting back to step %.4g",
                        step_no, target, info["reason"], dt)
            if dt < min_step:
                result.timings = dict(system.timing, total=time.perf_counter() - t_start)
                result.factorizations = lin.factorizations
                raise SolveFailed(
                    f"Newton's method failed in step {step_no} at load fraction {target:.4g} "
                    f"(last converged {load:.4g}): {info['reason']}; worst element "
                    f"{info['worst_element']} (min J {info['min_J']:.3g}); step size fell below "
                    f"{min_step:g}",
                    step=step_no, load=target, last_converged_load=load,
                    worst_element=info["worst_element"], state=result)
    ev, rhat, _, _ = system.evaluate(x, load, tangent=False)
    reac = np.zeros(3 * n)
    reac[cons.dofs] = rhat[cons.dofs]
    result.reactions = reac.reshape(n, 3)
    result.converged = True
    result.factorizations = lin.factorizations
    result.timings = dict(system.timing, total=time.perf_counter() - t_start,
                          **{f"pardiso_{k}": v - pardiso0[k] for k, v in _linalg.TIMING.items()})
    return result


def _norm(v) -> float:
    # numba loop, not NumPy's BLAS (its threads cost milliseconds per call on a loaded machine)
    v = np.ascontiguousarray(v, dtype=float)
    return float(np.sqrt(_dot(v, v)))


def _extrapolate(history, target):
    """Lagrange extrapolation in the load fraction through the last two or three converged
    states (x and the three-field state): linear (secant) from two, quadratic from three."""
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


def _forcing(lin, rhs_norm, goal, scale):
    """Relative tolerance (forcing term) of the Newton system's CG solve:
    eta = min(krylov_forcing, max((|b| / scale)^2, 0.1 goal / |b|)), at least krylov_rtol.
    A forcing term of the order of the relative residual squared keeps Newton's quadratic
    convergence (Dembo, Eisenstat & Steihaug 1982, thm. 3.3: eta_k = O(|r_k|) suffices);
    a linear residual of a tenth of the Newton tolerance `goal` is always accurate enough for
    the next iterate to converge (no oversolving in the last iteration of a step, Kelley 1995,
    sec. 6.3). Measured on the cube: 11 Newton iterations either way, 34 CG iterations instead
    of 43 with the tenth-of-tolerance target alone; Eisenstat & Walker's adaptive choice 2
    (eta up to 0.1) took 16 Newton iterations instead of 13.
    """
    if rhs_norm <= 0.0:
        return lin.forcing_max
    eta = max((rhs_norm / scale) ** 2, 0.1 * goal / rhs_norm)
    return max(lin.rtol, min(lin.forcing_max, eta))


def _solve_step(system, lin, x0, target, uhat, free, cons, max_it, rtol, atol, etol,
                line_search, ls_tol, line_search_growth, step_no, callback, result,
                x_pred=None, e0=None, early=None):
    X = system.body.mesh.nodes
    xscale = float(np.abs(X).max()) + 1.0
    targets = cons.targets(target, X)
    ev = None
    body = system.body
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
    info = {"iterations": 0, "residuals": [], "reason": "", "worst_element": None, "min_J": np.nan,
            "e0": e0, "early": False, "predicted": predicted}
    due = [t.augmentation_due for t in system.terms if hasattr(t, "augmentation_due")]
    if not early or not due:
        early = None
    if not ev.valid:
        info.update(reason="invalid start state", worst_element=ev.worst_element, min_J=ev.min_J)
        return False, x, info
    rnorm_hist = []
    for it in range(1, max_it + 1):
        gap = targets - uhat(x)[cons.dofs]
        rhs = -r if cpl is None else -r - cpl
        rhs[cons.dofs] = system.constraint_scale * gap
        t0 = time.perf_counter()
        try:
            if isinstance(lin, LaggedFactorSolver):
                # forcing term: loose while far from the solution, tighter as the residual
                # falls, so that the convergence stays (nearly) quadratic
                scale = max(ev.force_scale, 1e-300)
                eta = _forcing(lin, _norm(rhs), rtol * scale, scale)
                du_hat = lin.solve(A, rhs, rtol=eta)
            else:
                du_hat = lin.solve(A, rhs)
        except Exception as exc:        # a singular or failed factorisation cuts the step back
            info.update(reason=f"linear solver failed ({exc})", worst_element=ev.worst_element,
                        min_J=ev.min_J)
            return False, x, info
        system.timing["solve"] += time.perf_counter() - t0
        stats = getattr(lin, "last", None) or {"krylov_iterations": 0, "refactorized": True}
        result.krylov_iterations += stats["krylov_iterations"]
        if not np.all(np.isfinite(du_hat)):
            info.update(reason="linear solve gave NaN", worst_element=ev.worst_element, min_J=ev.min_J)
            return False, x, info
        du = cons.to_global(du_hat).reshape(-1, 3)
        snap = system.body.mixed_snapshot() if getattr(system.body, "mixed", None) is not None else None
        # directional derivative of the potential along du (the coupling to the constrained
        # increments included), its magnitude is FEBio's "energy norm" of the iteration
        g0 = -_dot(du_hat[free], rhs[free])
        en_norm0 = abs(g0)
        has_gap = bool(np.any(gap != 0.0))
        # Near convergence (relative residual below 10 sqrt(rtol), from where a quadratically
        # converging iteration lands below rtol) the new iterate is evaluated without its
        # tangent first: if it has converged the tangent is not needed (one assembly saved per
        # load step); if not, the tangent is assembled afterwards (one residual evaluation lost)
        lazy = (not line_search and not has_gap
                and _norm(r[free]) <= 10.0 * np.sqrt(rtol) * max(ev.force_scale, 1e-300))
        # line search: halve on invalid states, then secant on g(s) = du . r(x + s du)
        s = 1.0
        if system.max_increment is not None:
            # step-length limiter: no node moves more than max_increment in one iteration
            # (a damped Newton step far from the solution; near it the full step is taken)
            # (measured on the free nodes: prescribed increments are part of the load)
            d2 = np.einsum("ij,ij->i", du, du)[system.watched_nodes]
            biggest = float(np.sqrt(np.max(d2, initial=0.0)))
            if biggest > system.max_increment:
                s = system.max_increment / biggest
                lazy = False
        for _ in range(12):
            if snap is not None:
                system.body.mixed_update(snap, s * du)
            ev1, r1, A1, c1 = system.evaluate(x + s * du, target, targets=targets,
                                              tangent=not lazy)
            if ev1.valid:
                break
            lazy = False
            s *= 0.5
        else:
            info.update(reason="every trial update inverts an element",
                        worst_element=ev1.worst_element, min_J=ev1.min_J)
            return False, x, info
        if line_search and s == 1.0 and g0 < 0 and not has_gap:
            g1 = float(du_hat[free] @ r1[free])
            # accept the full step when the potential decreases enough (Armijo) or the
            # directional residual has dropped (FEBio's criterion); else a secant search
            armijo = np.isfinite(ev1.energy) and ev1.energy <= ev.energy + 1e-4 * g0
            grew = np.linalg.norm(r1[free]) > line_search_growth * max(np.linalg.norm(r[free]), 1e-300)
            if not armijo and g1 > ls_tol * abs(g0) and grew:
                sa, ga = 0.0, g0
                sb, gb = 1.0, g1
                best = (abs(g1), 1.0)
                for _ in range(4):
                    sn = sb - gb * (sb - sa) / (gb - ga) if gb != ga else 0.5 * sb
                    sn = float(np.clip(sn, 0.1 * sb, 0.9 * sb if gb > 0 else 2.0))
                    if snap is not None:
                        system.body.mixed_update(snap, sn * du)
                    ev2, r2, _, _ = system.evaluate(x + sn * du, target, tangent=False)
                    if not ev2.valid:
                        break
                    g2 = float(du_hat[free] @ r2[free])
                    if abs(g2) < best[0]:
                        best = (abs(g2), sn)
                    if abs(g2) <= ls_tol * abs(g0):
                        break
                    sa, ga, sb, gb = sb, gb, sn, g2
                s = best[1]
                if snap is not None:
                    system.body.mixed_update(snap, s * du)
                if True:
                    ev1, r1, A1, c1 = system.evaluate(x + s * du, target, targets=targets)
                    if not ev1.valid:
                        s = 1.0
                        if snap is not None:
                            system.body.mixed_update(snap, du)
                        ev1, r1, A1, c1 = system.evaluate(x + du, target, targets=targets)
        x = x + s * du
        ev, r, A, cpl = ev1, r1, A1, c1
        rn = _norm(r[free])
        en = abs(s * _dot(du_hat[free], r[free]))
        if e0 is None:
            e0 = info["e0"] = max(en_norm0, 1e-300)
        dn = abs(s) * _norm(du.ravel())
        gap_after = float(np.max(np.abs(targets - uhat(x)[cons.dofs]))) if len(cons.dofs) else 0.0
        scale = max(ev.force_scale, 1e-300)
        rec = {"step": step_no, "load": target, "iteration": it, "residual_norm": rn,
               "relative_residual": rn / scale, "energy_norm": en_norm0,
               "energy_ratio": en_norm0 / e0, "displacement_norm": dn, "line_search": s,
               "constraint_gap": gap_after, "min_J": ev.min_J,
               "krylov_iterations": stats["krylov_iterations"],
               "factorized": bool(stats["refactorized"])}
        result.log.append(rec)
        result.iterations += 1
        rnorm_hist.append(rn)
        log.info("step %3d load %.4f it %2d |R| %.3e (rel %.2e) E %.3e |du| %.3e s %.3g "
                 "cg %d%s", step_no, target, it, rn, rn / scale, en_norm0, dn, s,
                 stats["krylov_iterations"], " fact" if stats["refactorized"] else "")
        if callback is not None:
            callback(rec)
        info["iterations"] = it
        info["residuals"].append(rn)
        info["worst_element"], info["min_J"] = ev.worst_element, ev.min_J
        tiny = 1e-10 * max(1.0, float(np.abs(targets).max()) if len(targets) else 1.0)
        if gap_after <= tiny and (rn <= rtol * scale or rn <= atol) and \
                (en_norm0 <= etol * e0 or rn <= atol or it > 1 and rn <= 1e-3 * rtol * scale):
            return True, x, info
        # predictor safeguard: a solve started from the extrapolated state whose residual
        # grows at its second iteration is abandoned at once, Newton heads elsewhere from
        # there (the demo plan with the secant predictor: 7.8e3 -> 7.4e4 at load 0.5, where
        # the unguarded solve stalled and cut back); the caller restarts the step with the
        # tangent predictor
        if predicted and it == 2 and rn > rnorm_hist[0]:
            info["reason"] = f"predictor rejected (|R| {rnorm_hist[0]:.3e} -> {rn:.3e})"
            return False, x, info
        # the step will be augmented anyway: its multiplier update need not wait for the
        # penalty solve to converge (asked once per solve)
        if early is not None and gap_after <= tiny and rn <= early * scale:
            early = None
            if any([bool(f(x, target)) for f in due]):
                info["early"] = True
                log.info("step %d: stopped at relative residual %.2e for an augmentation",
                         step_no, rn / scale)
                return True, x, info
        # Stagnation at round-off: near zero load the internal forces (and so the relative
        # scale) vanish while the residual cannot fall below the round-off of forces assembled
        # from absolute coordinates (~eps |K| |X|). A correction of 1e-11 of the coordinate
        # magnitude (1e-9 mm on a 100 mm face) is far below any physical effect and ~1e3 above
        # double-precision resolution: the iterate cannot be improved, so it is converged.
        if it > 1 and gap_after <= tiny and dn <= 1e-11 * xscale and rn <= max(1e3 * atol, rtol * scale):
            info["reason"] = "converged at round-off"
            return True, x, info
        if it >= 4 and rn > 1e6 * max(min(rnorm_hist[:3]), 1e-300):
            info["reason"] = "residual diverges"
            return False, x, info
        # no progress: after `stall_iterations` iterations the residual has never fallen to a
        # tenth of the first one (Newton wanders, e.g. contact switching within too large a
        # step); cutting back now saves the remaining iterations of a lost step
        stall = system.stall_iterations
        if stall and it >= stall and min(rnorm_hist) > 0.1 * rnorm_hist[0]:
            info["reason"] = f"no progress in {it} iterations (|R| = {rn:.3e})"
            return False, x, info
        if A is None:               # evaluated without the tangent and not converged
            ev, r, A, cpl = system.evaluate(x, target, targets=targets)
    info["reason"] = f"no convergence in {max_it} iterations (|R| = {rn:.3e})"
    return False, x, info
