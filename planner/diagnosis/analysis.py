"""Which effect explains the gap, and how far it shrinks: fitting, cross-validation, verdict.

For every available effect (`planner.diagnosis.effects`) and every case: the sensitivity of the
gap to each continuous parameter at the baseline, J = dr/dtheta, from the model's tangent
(`planner.pipeline.skin_sensitivities`: du/dp = -K^-1 dR/dp at the converged baseline, one
factorisation for all parameters, mapped onto the scan points by `ScanGap.linearised`), or by
finite differences of full forward solves where the tangent is not available (central, or
one-sided second order at a bound), and each discrete choice (a switch such as `sliding=1`)
solved outright; the chosen switch's settings (how freely the tissue slides, `Effect.settings`)
are solved at each of their values and the one most likely under noise + discrepancy is kept. Parameters the data cannot pin down
(Fisher information, `planner.diagnosis.fit`) stay at "none". The identifiable ones are fitted
by bounded Gauss-Newton on the linearised gap, under their Gaussian priors where they have one
(`Candidate.prior_sd`: a bone correction's plausible range, or the accuracy of the measured
movements it is a remainder on, `Effect.measurement`; maximum a posteriori, the prior's term
weighed against the data by the information one unit of the weighted residual carries under
the scan noise, `prior_weight`), then refined by full nonlinear solves at the
fitted values, at most `MAX_REFINEMENTS` solves per case: a step that lowers the weighted
residual (with the prior's term) moves the anchor, whose Jacobian is then the model's tangent there (the solve brings
it), or the Broyden update along the step where a parameter has no tangent; a step that does
not is refused, and the next one is halved (with the tangent) or follows the Broyden-updated
secant (without it) (`refine`).

The model is never exact: the gap carries a smooth model-form discrepancy besides the scan
noise. Each effect is therefore judged against noise + discrepancy (`planner.diagnosis.
discrepancy`: a two-scale discrepancy, a short Gaussian process plus an offset and tilts of
the face, whose amplitudes and length are estimated by maximum likelihood under each model,
Kennedy & O'Hagan 2001), and its reported
values are the generalised least-squares estimates under that error model about the refined
fit (Brynjarsdottir & O'Hagan 2014: ordinary least squares lets the parameters absorb the
discrepancy), under the parameters' priors where they have one (the posterior's mode and
spread; the evidence keeps the data's likelihood there). Effects are ranked by held-out shrinkage of the RMS gap: with one case, spatial
cross-validation over the face regions (each region's gap predicted by the parameters fitted on
all other regions); with several cases, parameters shared by every patient (stiffness, posture)
are fitted leaving each case out in turn and case-specific ones per case with spatial
cross-validation. The held-out prediction uses the local model about the refined fit,
r(theta) = r* + J* (theta - theta*). An effect is `significant` when its BIC under noise +
discrepancy beats the baseline's by strong evidence (`fit.STRONG_EVIDENCE`), it predicts
held-out regions better than the discrepancy alone (`Scored.wins_heldout`), and it removes at
least `MIN_HELDOUT_SHRINK_PCT` of the held-out gap beyond the scan noise and twice that
shrinkage's bootstrap spread;
a model-form gap may remain beside it (its regions are reported). Pairs with the effect of
largest held-out shrinkage (significant or not: two effects can act together where neither
does alone) are tried when it leaves a gap above the noise. A partner with discrete choices (a
switch such as which segments' tissue slides) is paired once per choice, each anchored at a
full solve of the lead's fitted values with that switch, and the pair that fits best after
refinement is kept: with the lead's effect present another switch can fit than alone. A lead
with a switch beside a partner without one swaps roles: its switch is re-chosen beside the
partner's fit. The
verdict is the best significant effect (or pair, when the pair is itself significant, shrinks the held-out gap further than
each of its members and is strongly better in BIC than each member and than the best
significant single effect); else null when no region's gap stands
out of noise + discrepancy, "unexplained" (with those regions) when some does. Its confidence
is the total probability of the models that contain the named effect(s), the probabilities
being held-out ones (pseudo-BMA+ weights of the held-out log predictive densities, among the
baseline and the models that pass both the BIC and the held-out checks: `probabilities`), like
the ranking.

Where the mesh's own error is estimated from a second mesh (`remove_mesh_error`: the gap's
coefficient a on the direction r_ref - r_d, taken out of every gap; each model's own fit
re-estimates it, and the change is taken out of that model's fitted and held-out gaps,
`_mesh_shift`, so that an effect resembling the direction is not charged for the part of it
the baseline's estimate took), the effects are fitted on
the converged model's response too (`mesh_corrections`): the diagnosis mesh responds to an
effect otherwise than the converged model does (a coarse mesh is too stiff where the tissue
bends; near a contact limit its tangent can even overstate a response many times), as its
baseline does, so each parameter's column of the gap's Jacobian is extrapolated with the same
coefficient, J_inf = J_d + kappa (J_ref - J_d), kappa = -a (kappa = 1 when the truth is the
reference mesh's own prediction; Richardson extrapolation, Roache 1998, ch. 5), both Jacobians
from the tangents at the two baselines. The gap of a full solve on the diagnosis mesh at theta
is extrapolated the same way, r = r_d + kappa (r_ref - r_d), with the reference's response
known to first order, r_ref(theta) = r_ref(theta_0) + J_ref (theta - theta_0): where every
parameter of the effect has a reference tangent and no discrete choice shares the solve, with
the solve's own change from the origin (r = (1 - kappa) r_d(theta) + kappa r_0 + kappa J_ref
(theta - theta_0): a spurious nonlinearity of the diagnosis mesh, as near a contact limit,
keeps only the weight 1 - kappa), else with its linear part (r = r_d(theta) + kappa (J_ref -
J_d)(theta - theta_0)). The refinement, the cross-validation and the evidence all see that one
model. A discrete choice (a switch: no derivative) is solved on the second mesh too and its
change of the gap extrapolated the same way, kappa (dr_ref - dr_d), added to every solve made
with it (`choice_corrections`). Parameters without a tangent on both meshes (finite
differences) keep the diagnosis mesh's response, and so do all effects when the second mesh is
the coarser one (`mesh_corrections`).

Values marginal over the patient's moduli (`moduli_marginal`). The reported values and their
standard errors are conditional on the model's layer moduli, which the patient does not
share, and a load's response (a posture, a muscle's tone) depends on them as much as on the
load: the scan fixes roughly load / stiffness. The named effect's standard errors are therefore
also given with the moduli integrated out: at the fitted effect (one more solve per case, with
the tangent sensitivities of every layer's stiffness factor there, `Forward.sensitivities_at`)
each layer's response E_j = dr/dlog f_j enters the error model as one more Gaussian column,
log f_j ~ N(0, s_j^2), so that F = J^T (Sigma + sum_j s_j^2 E_j E_j^T)^-1 J: the
linearised marginal of Kennedy & O'Hagan's calibration inputs (2001, sect. 4.3), as for the
layer proportions (`planner.diagnosis.discrepancy`). The prior is the library's own plausible
range of a layer's stiffness (`effects`: a factor three either way) taken as its 95 % interval,
s_j = ln 3 / 1.96. It widens the reported intervals only: the values, the ranking and the
verdict stay those under the model's moduli, for the `stiffness` effect is itself one of the
effects compared.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner.diagnosis import discrepancy, fit
from planner.diagnosis.gap import correlation_length
from planner.diagnosis.effects import Effect, Parameter, effect_strings, stiffness_effect
from planner.diagnosis.forward import SENSITIVITIES

__all__ = ["CaseData", "Candidate", "analyse", "alternatives", "surface_confounds", "confound_warning", "confound_between",
           "SurfaceConfound", "CONFOUNDED_ON_SURFACE",
           "MIN_HELDOUT_SHRINK_PCT", "MAX_REFINEMENTS", "naming_share"]

# An effect must remove at least this share of the held-out RMS gap beyond the scan noise to be
# named, and twice its bootstrap spread over the cross-validation units. The share is of the gap
# beyond the noise, which keeps its model-form part (the evidence against that part is the BIC
# under noise + discrepancy, not this threshold), not of the whole gap: no effect removes the
# scan's noise, and a share of the whole gap would ask more of an effect the noisier the scan.
MIN_HELDOUT_SHRINK_PCT = 10.0
# A pair is named only if it removes this many more percentage points of the held-out gap than
# each of its members.
MIN_PAIR_GAIN_PCT = 10.0
# The probability that an effect's held-out log predictive density gain over the baseline is
# positive, for it to count as predicting unseen regions better: the one-sided level of a 95 %
# interval, about that of the normal rule "a gain above twice its standard error".
HELDOUT_GAIN_PROBABILITY = 0.975
MAX_REFINEMENTS = 2
PAIR_PARTNERS = 2              # pairs are tried with the best effect and the next best two
N_BOOTSTRAP = 200


@dataclass
class CaseData:
    case: object                  # forward.CaseModel
    gap: object                   # gap.ScanGap
    r0: np.ndarray                # baseline gap on the fixed scan points
    _error: object = None
    gp_n_eff: float | None = None  # independent samples at the baseline's correlation length
    mesh_error: np.ndarray | None = None   # change of the gap on a second mesh (`discrepancy`)
    mesh_reference: str | None = None      # that mesh's resolution
    mesh_coef: float | None = None         # the gap's estimated coefficient on that direction
    mesh_coef_sd: float | None = None      # its posterior standard deviation
    # the second mesh's case model, baseline skin and tangent sensitivities {key: d skin/dp}
    # (`mesh_corrections`); None without them
    reference: object = None
    reference_skin: np.ndarray | None = None
    reference_sens: dict | None = None
    # per parameter key kappa (dr_ref/dv - dr_d/dv) on the scan points, per unit of the value
    # (`mesh_corrections`); empty without a second mesh
    mesh_jac: dict = field(default_factory=dict)
    reference_coarser: bool = False        # the second mesh has fewer nodes than the diagnosis one
    # the second mesh's solves (a `Forward` over the reference models) and this case's index
    # among them: each discrete choice is solved there too (`choice_corrections`)
    reference_forward: object = None
    reference_index: int = 0
    # per discrete choice (its effect strings) kappa (dr_ref - dr_d): the change the choice
    # makes on the second mesh against the diagnosis mesh's, extrapolated (`choice_corrections`)
    choice_mesh: dict = field(default_factory=dict)
    # change of the gap with the other boundary condition of the neck cut (`discrepancy`,
    # "Boundary conditions"), and that condition; None when not solved
    boundary: np.ndarray | None = None
    boundary_condition: str | None = None
    # changes of the gap with each layer group thicker (`discrepancy`, "Layer proportions"),
    # (points, k), and their names; None when not solved
    layers: np.ndarray | None = None
    layer_directions: tuple = ()
    # the covariance of the scan's pose under the baseline's error model (rad, mm;
    # `discrepancy.ErrorModel.pose_covariance`); None until estimated
    pose_cov: np.ndarray | None = None

    @property
    def folds(self) -> dict[str, np.ndarray]:
        return self.gap.region_masks()

    @property
    def error(self) -> discrepancy.ErrorModel:
        """The noise + discrepancy error model on this case's scan points."""
        if self._error is None:
            names = self.gap.region_names
            border = np.isin(self.gap.region, [names.index(r) for r in discrepancy.BORDER_REGIONS if r in names])
            self._error = discrepancy.ErrorModel(self.gap.points, self.gap.weights, self.gap.noise_floor_mm,
                                                 mesh_error=self.mesh_error, boundary=self.boundary,
                                                 layers=self.layers, border=border,
                                                 pose=getattr(self.gap, "_pose", None))
        return self._error


def remove_mesh_error(d: CaseData):
    """Take the mesh's estimated discretisation error out of the case's gap (`discrepancy`,
    "The mesh's own error"): its coefficient on the mesh-error direction is estimated on the
    baseline gap under noise + discrepancy (generalised least squares, the other parts of the
    error model, the boundary-condition direction among them, integrated out) and the field is
    subtracted from every gap the diagnosis measures (`ScanGap.mesh_offset`), so that effects
    are fitted, ranked and their shrinkage measured on what the model's physics leaves. The
    direction stays in the error model: a model may still move its coefficient, under its
    prior, about the estimate. The boundary-condition field is not taken out (`discrepancy`,
    "Boundary conditions"). Returns the fit (None without a mesh-error direction)."""
    if d.mesh_error is None or d.error.n_mesh == 0:
        return None
    f = d.error.fit(d.r0)
    off = np.asarray(d.mesh_error, float).reshape(len(d.r0), -1) @ f.mesh_coef
    d.gap.mesh_offset = off if d.gap.mesh_offset is None else d.gap.mesh_offset + off
    d.gap.mesh_error_mm = f.mesh_mm
    d.mesh_coef = float(np.ravel(f.mesh_coef)[0])
    d.mesh_coef_sd = float(d.error.mesh_coefficient_sd(f)[0])
    d.r0 = d.r0 - off
    d.gap.correlation_mm = correlation_length(d.gap.points, d.r0, d.gap.weights)
    return f


@dataclass
class Candidate:
    """One effect, or a pair, fitted to every case."""

    name: str
    effects: tuple[Effect, ...]
    shared: bool
    n_cases: int
    params: tuple[Parameter, ...] = ()
    choices: list = field(default_factory=list)        # per case: (key, value) pairs fixed
    theta: list = field(default_factory=list)          # per case fitted coordinates
    anchor_r: list = field(default_factory=list)       # per case r at the anchor
    J: list = field(default_factory=list)              # per case dr/dtheta
    C: list = field(default_factory=list)              # per case mesh correction of dr/dtheta
    M: list = field(default_factory=list)              # per case mesh correction of the choices
    # per case kappa J_ref where every parameter has a second mesh's tangent and no discrete
    # choice shares the solves (`corrected`); None otherwise
    KR: list = field(default_factory=list)
    # per case: every parameter has the model's tangent there (the refinement's solves then
    # bring the tangent at their values, `refine`)
    tangent: list = field(default_factory=list)
    # per case group (its first case index): the factor of the next refinement step (`refine`)
    step: dict = field(default_factory=dict)
    free: np.ndarray | None = None
    se: np.ndarray | None = None
    failed: str | None = None
    sensitivity: str = "finite differences"
    solves: int = 0

    @property
    def lower(self):
        return np.array([p.bounds[0] for p in self.params])

    @property
    def upper(self):
        return np.array([p.bounds[1] for p in self.params])

    @property
    def origin(self):
        return np.array([p.origin for p in self.params])

    def values(self, c: int, theta: np.ndarray | None = None) -> dict:
        theta = self.theta[c] if theta is None else theta
        out = dict(self.choices[c]) if self.choices else {}
        for p, t in zip(self.params, theta):
            v = p.value(t)
            if not np.isclose(v, p.none, rtol=0, atol=1e-9):
                out[p.key] = round(v, 6)
        return out

    def strings(self, c: int, theta: np.ndarray | None = None) -> tuple[str, ...]:
        return effect_strings(self.values(c, theta))

    def prior_sd(self, c: int) -> np.ndarray:
        """Per parameter the standard deviation of its Gaussian prior about "none" in case c
        (fit coordinate, inf: flat; `Parameter.prior`, narrowed where the case's choices hold
        the parameter's effect's measurement, `Effect.measured`)."""
        choice = self.choices[c] if self.choices else ()
        measured = {p.key for e in self.effects if e.measured(choice) for p in e.parameters}
        return np.array([p.prior(p.key in measured) for p in self.params], float)

    def has_prior(self, c: int) -> bool:
        """Has a free parameter a Gaussian prior in case c?"""
        return self.free is not None and bool(np.isfinite(self.prior_sd(c)[self.free]).any())

    def penalty(self, c: int, theta: np.ndarray, weight: float) -> float:
        """The prior's term of case c's least-squares objective at theta: `weight` sum
        ((theta - none) / sd)^2 over the free parameters (`fit.linear_fit`)."""
        if self.free is None or not self.params:
            return 0.0
        z = (np.asarray(theta, float) - self.origin)[self.free] / self.prior_sd(c)[self.free]
        return float(weight * np.sum(z ** 2))       # 0 where flat (inf)

    def has_tangent(self, c: int) -> bool:
        return bool(self.tangent) and bool(self.tangent[c]) and len(self.params) > 0

    def jacobian_at(self, c: int, d: "CaseData", skin: np.ndarray, sens: dict, theta: np.ndarray) -> np.ndarray:
        """dr/dtheta of `corrected` at theta from the diagnosis mesh's tangent there, `sens`
        {key: d skin/d value} at the solve `skin` (per theta by `Parameter.dvalue`); the mesh
        corrections are those of the origin (the reference's response is known there only)."""
        Jd = np.stack([d.gap.linearised(skin, sens[p.key]) * p.dvalue(t)
                       for p, t in zip(self.params, np.asarray(theta, float))], axis=1)
        if self.KR and self.KR[c] is not None:
            return (1.0 + float(d.mesh_coef)) * Jd + self.KR[c]
        if self.C and np.any(self.C[c]):
            return Jd + self.C[c]
        return Jd

    def corrected(self, c: int, d: "CaseData", r: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """The gap r of a full solve at theta on case d's diagnosis mesh extrapolated to the
        converged mesh (module text): r_d + kappa (r_ref - r_d) with the reference's response
        linear, r_ref(theta) - r_ref(theta_0) = J_ref (theta - theta_0). Where every parameter
        has a reference tangent and no discrete choice shares the solve, the diagnosis mesh's
        own change from the origin is the solve's, r - r0 (r0 the baseline gap); else its
        linear part, J_d (theta - theta_0) (the correction C (theta - theta_0)). The discrete
        choices the solve was made with add their own correction (`M`, `choice_corrections`)."""
        dtheta = np.asarray(theta, float) - self.origin
        if self.M and self.M[c] is not None:
            r = r + self.M[c]             # the discrete choices' change, extrapolated
        if self.KR and self.KR[c] is not None:
            k = -float(d.mesh_coef)
            return (1.0 - k) * r + k * d.r0 + self.KR[c] @ dtheta
        if not self.C or not np.any(self.C[c]):
            return r
        return r + self.C[c] @ dtheta


def _rss(d: CaseData, r: np.ndarray, mask=None) -> float:
    w = d.gap.weights if mask is None else d.gap.weights[mask]
    r = r if mask is None else r[mask]
    return float(np.sum(w * r * r))


def _ok(skin) -> bool:
    return not isinstance(skin, str)


# --------------------------------------------------------------------------- sensitivities

def _fd_params(e: Effect, tangent_c) -> list[int]:
    """Indices of the effect's parameters that need finite differences in one case."""
    have = tangent_c if isinstance(tangent_c, dict) else {}
    return [k for k, p in enumerate(e.parameters) if p.key not in have]


def _fd_points(e: Effect, ks: list[int]):
    theta0 = e.origin
    pts = fit.finite_difference_points(theta0, np.array([p.step for p in e.parameters]),
                                       np.array([p.bounds[0] for p in e.parameters]),
                                       np.array([p.bounds[1] for p in e.parameters]))
    return [pt for pt in pts if pt[0] in ks]


def _sensitivity_requests(data: list[CaseData], effects: list[Effect], tangent: list) -> list:
    reqs = []
    for e in effects:
        for c in range(len(data)):
            for k, a, b in _fd_points(e, _fd_params(e, tangent[c])):
                for off in (a, b):
                    t = e.origin.copy()
                    t[k] += off
                    reqs.append((c, effect_strings(e.values(t))))
            for choice in e.choices:
                reqs.append((c, effect_strings(dict(choice))))
    return reqs


def _single_candidate(e: Effect, data: list[CaseData], forward, tangent: list) -> Candidate:
    """The effect's anchors and Jacobians: the tangent sensitivities where given, else the
    finite-difference solves of `_sensitivity_requests`."""
    n = len(data)
    cand = Candidate(e.name, (e,), e.shared and n > 1, n, e.parameters)
    methods = set()
    for c, d in enumerate(data):
        anchor = d.r0
        choice = ()
        if e.choices:       # the best switch position for this case (the whole-face fit)
            best = None
            for ch in e.choices:
                key = effect_strings(dict(ch))
                skin = forward.solve([(c, key)])[0]
                cand.solves += 1
                if not _ok(skin):
                    continue
                m = d.choice_mesh.get(key)
                r = d.gap.distances(skin) + (0.0 if m is None else m)
                if best is None or _rss(d, r) < best[0]:
                    best = (_rss(d, r), ch, r, m)
            if best is None:
                cand.failed = f"case {d.case.name}: every choice failed to solve"
                return cand
            _, choice, anchor, m_best = best
            choice, anchor = _best_setting(e, d, c, tuple(choice), anchor, m_best, forward, cand)
            cand.M.append(m_best)
        else:
            cand.M.append(None)
        cand.choices.append(tuple(choice))
        cand.anchor_r.append(anchor)
        J = np.zeros((len(d.r0), len(e.parameters)))
        C = np.zeros_like(J)
        fd = _fd_params(e, tangent[c])
        skin0 = forward.baseline(c)
        for k, p in enumerate(e.parameters):
            if k not in fd:
                # d r / d theta = d r / d value * d value / d theta (value = exp(theta) for factors)
                J[:, k] = d.gap.linearised(skin0, tangent[c][p.key]) * p.dvalue(p.origin)
                methods.add("tangent")
                if p.key in d.mesh_jac:
                    C[:, k] = d.mesh_jac[p.key] * p.dvalue(p.origin)
        for k, a, b in _fd_points(e, fd):
            rs = []
            for off in (a, b):
                t = e.origin.copy()
                t[k] += off
                skin = forward.solve([(c, effect_strings(e.values(t)))])[0]
                cand.solves += 1
                if not _ok(skin):
                    cand.failed = f"case {d.case.name}: {e.parameters[k].key} at {e.parameters[k].value(t[k]):.4g} failed: {skin}"
                    return cand
                rs.append(d.gap.distances(skin))
            J[:, k] = fit.finite_difference_jacobian(d.r0, [(a, b, rs[0], rs[1])])[:, 0]
            methods.add("finite differences")
        cand.J.append(J + C)
        cand.C.append(C)
        cand.tangent.append(not fd)
        exact = not e.choices and len(e.parameters) > 0 and all(p.key in d.mesh_jac for p in e.parameters)
        cand.KR.append(C - float(d.mesh_coef) * J if exact else None)      # kappa J_ref = C + kappa J_d
        cand.theta.append(cand.origin.copy())
    cand.sensitivity = " and ".join(sorted(methods)) if methods else "none (discrete choices)"
    return cand


def _best_setting(e: Effect, d: CaseData, c: int, choice: tuple, anchor, m, forward, cand: Candidate):
    """The chosen switch with its settings (`Effect.settings`, e.g. how freely the tissue
    slides): each setting's values are solved with the switch and the one whose gap has the
    highest profile likelihood under noise + discrepancy is kept (the switch's default among
    them). Likelihood, not the residual's size: a setting can leave a smaller gap whose
    structure the discrepancy explains worse (the generalised least squares of the fitted
    values, for the same reason). The free switch's mesh correction `m` stands for its
    settings. Returns (choice, anchor)."""
    for key, values in e.settings:
        variants = [choice + ((key, v),) for v in values]
        skins = forward.solve([(c, effect_strings(dict(v))) for v in variants])
        cand.solves += len(variants)
        best = (d.error.fit(anchor).loglik, choice, anchor)
        for v, skin in zip(variants, skins):
            if not _ok(skin):
                continue
            r = d.gap.distances(skin) + (0.0 if m is None else m)
            ll = d.error.fit(r).loglik
            if ll > best[0]:
                best = (ll, v, r)
        _, choice, anchor = best
    return choice, anchor


def _switched(cand: Candidate) -> bool:
    return any(e.choices for e in cand.effects)


def _discrete(cand: Candidate) -> int:
    """The discrete choices a candidate makes per case: its switches and their settings."""
    return sum((1 if e.choices else 0) + len(e.settings) for e in cand.effects)


# --------------------------------------------------------------------------- fitting

def _identify(cand: Candidate, data: list[CaseData]) -> None:
    """Standard errors and the free (identifiable) parameters: the least determined parameter
    (largest standard error relative to its range) is fixed at "none" until every remaining
    one is pinned to `fit.IDENTIFIABLE_FRACTION` of its range, under the scan noise over its own
    independent samples (`ScanGap.noise_n_eff`). Under displacement-only loading
    this leaves out one stiffness layer (the uniform direction) and fits the others relative
    to it."""
    k = len(cand.params)
    if k == 0:
        cand.free = np.zeros(0, bool)
        cand.se = np.zeros(0)
        return
    rng = cand.upper - cand.lower

    def errors(free):
        sub = np.zeros(k)
        sub[:] = np.inf
        if not free.any():
            return sub
        if cand.shared:
            J = np.concatenate([Jc[:, free] for Jc in cand.J])
            w = np.concatenate([d.gap.weights for d in data])
            sigma = max(d.gap.noise_floor_mm for d in data)
            sub[free] = fit.standard_errors(J, w, sigma, sum(d.gap.noise_n_eff() for d in data))
        else:
            sub[free] = np.max([fit.standard_errors(cand.J[c][:, free], d.gap.weights, d.gap.noise_floor_mm,
                                                    d.gap.noise_n_eff()) for c, d in enumerate(data)], axis=0)
        return sub

    free = np.ones(k, bool)
    se = errors(free)
    while free.any():
        rel = np.where(free, se / rng, -np.inf)
        worst = int(np.argmax(rel))
        if rel[worst] <= fit.IDENTIFIABLE_FRACTION:
            break
        free[worst] = False
        se_new = errors(free)
        se = np.where(free, se_new, se)
    cand.se = se
    cand.free = free


def prior_weight(data: list[CaseData], cases: list[int], masks=None) -> float:
    """The weight of the prior's term in the least-squares objective sum w r^2 over `cases`
    (`masks`: the points each keeps): sigma^2 W / n_eff, the weighted squared residual that one
    unit of Fisher information is worth under the scan noise (`fit.standard_errors`: the noise
    floor over its own independent samples, pooled as `_identify` pools them), so that a
    parameter's prior weighs against the data as its standard error does."""
    masks = [None] * len(cases) if masks is None else masks
    W = sum(float(np.sum(data[c].gap.weights if m is None else data[c].gap.weights[m])) for c, m in zip(cases, masks))
    full = sum(float(np.sum(data[c].gap.weights)) for c in cases)
    n = sum(data[c].gap.noise_n_eff() for c in cases) * W / max(full, 1e-300)
    sigma = max(data[c].gap.noise_floor_mm for c in cases)
    return float(sigma ** 2 * W / max(n, 1e-300))


def _fit_theta(cand: Candidate, data: list[CaseData], cases: list[int], masks=None,
               offsets: list | None = None) -> np.ndarray:
    """Linearised bounded fit about the anchors over `cases` (shared parameters) or of one case,
    under the parameters' priors (`Candidate.prior_sd`, those of the first case); `offsets`
    (per case, or None): a field taken out of each anchor's gap first (`_mesh_shift`)."""
    theta_a = cand.theta[cases[0]]
    if not cand.free.any():
        return theta_a.copy()
    if masks is None:
        masks = [None] * len(cases)
    anchors = cand.anchor_r if offsets is None else [a - o for a, o in zip(cand.anchor_r, offsets)]
    r = np.concatenate([anchors[c] if m is None else anchors[c][m] for c, m in zip(cases, masks)])
    J = np.concatenate([cand.J[c] if m is None else cand.J[c][m] for c, m in zip(cases, masks)])
    w = np.concatenate([data[c].gap.weights if m is None else data[c].gap.weights[m] for c, m in zip(cases, masks)])
    prior = ({"prior_sd": cand.prior_sd(cases[0]), "prior_weight": prior_weight(data, cases, masks)}
             if cand.has_prior(cases[0]) else {})
    return fit.linear_fit(r, J, w, theta_a, cand.lower, cand.upper, cand.free, fixed_value=cand.origin, **prior)


def _groups(cand: Candidate) -> list[list[int]]:
    return [list(range(cand.n_cases))] if cand.shared else [[c] for c in range(cand.n_cases)]


def _refinable(cands: list[Candidate], data: list[CaseData]) -> list[Candidate]:
    """The candidates with identifiable parameters (`_identify` run on each)."""
    for c in cands:
        if c.failed is None:
            _identify(c, data)
    return [c for c in cands if c.failed is None and c.free is not None and c.free.any()]


def _proposals(active: list[Candidate], data: list[CaseData]) -> list:
    """The next Gauss-Newton step of each candidate and case group, (candidate, cases, theta),
    shortened by the group's step factor (`refine`), where it moves a parameter by more than 2 %
    of its range."""
    out = []
    for cand in active:
        for g in _groups(cand):
            new = _fit_theta(cand, data, g)
            step = cand.step.get(g[0], 1.0)
            if step < 1.0:
                new = np.clip(cand.theta[g[0]] + step * (new - cand.theta[g[0]]), cand.lower, cand.upper)
            rng = cand.upper - cand.lower
            if np.all(np.abs(new - cand.theta[g[0]]) <= 0.02 * rng):
                continue
            out.append((cand, g, new))
    return out


def _request(cand: Candidate, c: int, theta: np.ndarray) -> tuple:
    """The solve of case c at theta: with the tangent of every parameter there where the
    model gives it at the origin (`Candidate.tangent`), else the plain solve."""
    strings = cand.strings(c, theta)
    if cand.has_tangent(c):
        return (c, (SENSITIVITIES, tuple(p.key for p in cand.params), strings))
    return (c, strings)


def _requests(proposals: list) -> list:
    """The solves of `_proposals`, candidate by candidate (`_request`)."""
    return [_request(cand, c, new) for cand, g, new in proposals for c in g]


def first_refinement_requests(cands: list[Candidate], data: list[CaseData]) -> list:
    """The solves `refine`'s first step will ask for (the same requests), for
    `Forward.prefetch`."""
    return _requests(_proposals(_refinable(cands, data), data))


def refine(cands: list[Candidate], data: list[CaseData], forward) -> None:
    """Bounded Gauss-Newton steps with full solves, all candidates' solves batched together.

    A step that lowers the weighted residual, with the prior's term (`Candidate.penalty`),
    moves the anchor there. Its Jacobian is then the
    model's tangent at the new anchor where every parameter has one (the solve brings it:
    `_request`), a Gauss-Newton step on the exact local model; else the Broyden update along
    the step. A step that does not lower the residual, or cannot be solved, leaves the anchor;
    with the tangent the next step is then halved (the response between the two points is not
    the anchor's linear model: a contact that closes or a fold that forms on the way can make
    the far point another equilibrium branch, whose secant would mislead every later step and
    the held-out prediction, which uses the anchor's Jacobian), without it the Jacobian takes
    the Broyden update along the refused step, the next step following the secant."""
    active = _refinable(cands, data)
    for _ in range(MAX_REFINEMENTS):
        proposals = _proposals(active, data)
        if not proposals:
            break
        results = iter(forward.solve(_requests(proposals)))
        for cand, g, new in proposals:
            got = [next(results) for _ in g]
            cand.solves += len(g)
            skins = [out[0] if cand.has_tangent(c) else out for c, out in zip(g, got)]
            if not all(_ok(s) for s in skins):
                cand.step[g[0]] = 0.5 * cand.step.get(g[0], 1.0)
                continue            # that value cannot be solved: keep the anchor
            rs = [cand.corrected(c, data[c], data[c].gap.distances(s), new) for c, s in zip(g, skins)]
            lam = prior_weight(data, g) if cand.has_prior(g[0]) else 0.0
            old = sum(_rss(data[c], cand.anchor_r[c]) for c in g) + cand.penalty(g[0], cand.theta[g[0]], lam)
            better = sum(_rss(data[c], r) for c, r in zip(g, rs)) + cand.penalty(g[0], new, lam) < old
            exact = all(cand.has_tangent(c) and isinstance(out[1], dict) for c, out in zip(g, got))
            for c, r, s, out in zip(g, rs, skins, got):
                dtheta = new - cand.theta[c]
                if better and exact:
                    cand.J[c] = cand.jacobian_at(c, data[c], s, out[1], new)
                elif better or not cand.has_tangent(c):
                    # no tangent at the new point (none asked, or not available): the secant
                    cand.J[c] = fit.broyden(cand.J[c], dtheta, r - cand.anchor_r[c])
                if better:
                    cand.theta[c] = new.copy()
                    cand.anchor_r[c] = r
            if better:
                cand.step[g[0]] = 1.0
            elif cand.has_tangent(g[0]):
                cand.step[g[0]] = 0.5 * cand.step.get(g[0], 1.0)


# --------------------------------------------------------------------------- held-out

def heldout_residuals(cand: Candidate, data: list[CaseData], offsets: list | None = None) -> list[np.ndarray]:
    """Per case the gap predicted for data not used in the fit (see the module text);
    `offsets` (per case, or None): a field taken out of each anchor's gap first, the model's
    own mesh-error field (`_mesh_shift`)."""
    out = []
    n = cand.n_cases
    anchors = cand.anchor_r if offsets is None else [a - o for a, o in zip(cand.anchor_r, offsets)]
    for c, d in enumerate(data):
        r_ho = np.array(anchors[c], float)
        if cand.free is None or not cand.free.any():
            out.append(r_ho)
            continue
        if cand.shared and n > 1:
            others = [o for o in range(n) if o != c]
            th = _fit_theta(cand, data, others, offsets=offsets)
            r_ho = anchors[c] + cand.J[c] @ (th - cand.theta[c])
        else:
            for name, m in d.folds.items():
                th = _fit_theta(cand, data, [c], [~m], offsets=offsets)
                r_ho[m] = anchors[c][m] + cand.J[c][m] @ (th - cand.theta[c])
        out.append(r_ho)
    return out


def _pooled_rms(data, rs, masks=None) -> float:
    num = den = 0.0
    for k, (d, r) in enumerate(zip(data, rs)):
        m = None if masks is None else masks[k]
        w = d.gap.weights if m is None else d.gap.weights[m]
        rr = r if m is None else r[m]
        num += float(np.sum(w * rr * rr))
        den += float(np.sum(w))
    return float(np.sqrt(num / max(den, 1e-300)))


def _fold_units(data) -> list[tuple[int, np.ndarray]]:
    units = []
    for c, d in enumerate(data):
        folds = d.folds or {"all": np.ones(len(d.r0), bool)}
        units.extend((c, m) for m in folds.values())
    return units


def _beyond_noise(s0, s1, noise):
    """Shrinkage (%) of the gap beyond the scan noise from weighted sums of squares before
    (s0) and after (s1) and the noise's expected share (noise = sigma^2 x weight): 1 -
    sqrt(max(s1 - noise, 0) / (s0 - noise)); NaN where the gap before is within the noise."""
    s0, s1, noise = (np.asarray(x, float) for x in (s0, s1, noise))
    excess = s0 - noise
    with np.errstate(invalid="ignore", divide="ignore"):
        out = 100.0 * (1.0 - np.sqrt(np.maximum(s1 - noise, 0.0) / excess))
    return np.where(excess > 0, out, np.nan)


def shrink_spread(data, r0s, rhos, seed: int = 0) -> tuple[float, float]:
    """Bootstrap standard deviations (percentage points) over the cross-validation units
    (regions of every case) of the held-out shrinkage of the whole gap and of the gap beyond
    the scan noise (`beyond_noise_shrink`)."""
    units = _fold_units(data)
    if len(units) < 2:
        return 0.0, 0.0
    num0 = np.array([_rss(data[c], r0s[c], m) for c, m in units])
    num1 = np.array([_rss(data[c], rhos[c], m) for c, m in units])
    noise = np.array([data[c].gap.noise_floor_mm ** 2 * float(data[c].gap.weights[m].sum()) for c, m in units])
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(units), size=(N_BOOTSTRAP, len(units)))
    s0, s1, sn = num0[idx].sum(axis=1), num1[idx].sum(axis=1), noise[idx].sum(axis=1)
    shrink = 100.0 * (1.0 - np.sqrt(s1 / np.maximum(s0, 1e-300)))
    beyond = _beyond_noise(s0, s1, sn)
    beyond = beyond[np.isfinite(beyond)]
    return float(np.std(shrink)), (float(np.std(beyond)) if len(beyond) > 1 else np.inf)


def beyond_noise_shrink(data, r0s, rhos) -> float:
    """Held-out shrinkage (%) of the gap beyond the scan noise, pooled over the cases:
    1 - sqrt(max(RMS_ho^2 - s_n^2, 0) / (RMS_0^2 - s_n^2)), s_n the noise floor. The scan's
    noise is in every gap and no effect can remove it, so the share of the whole gap an effect
    removes is capped at 1 - s_n / RMS_0 (a few tens of percent when the effect changes the
    face by about the noise); this is the share of what an effect could remove. NaN when the
    gap is within the noise."""
    s0 = sum(_rss(d, r) for d, r in zip(data, r0s))
    s1 = sum(_rss(d, r) for d, r in zip(data, rhos))
    sn = sum(d.gap.noise_floor_mm ** 2 * float(d.gap.weights.sum()) for d in data)
    return float(_beyond_noise(s0, s1, sn))


# --------------------------------------------------------------------------- summary

@dataclass
class Scored:
    cand: Candidate
    rms_after: float
    heldout_rms: float
    shrink_pct: float
    heldout_shrink_pct: float
    spread_pct: float
    bic: float
    identifiable: bool
    heldout: list
    fitted: list
    significant: bool = False
    probability: float = 0.0
    gp: list = field(default_factory=list)       # per case discrepancy.Fit
    gp_bic: float = np.nan
    theta: list = field(default_factory=list)    # per case fitted coordinates (reported)
    lpd: np.ndarray | None = None                # held-out log predictive density per fold
    lpd_gain: float = np.nan                     # sum over folds against the baseline
    lpd_gain_se: float = np.nan                  # its standard error over the folds
    lpd_gain_prob: float = np.nan                # Bayesian-bootstrap probability that it is > 0
    noise_shrink_pct: float = np.nan             # held-out shrinkage of the gap beyond the noise
    noise_spread_pct: float = np.inf             # its bootstrap spread
    mesh_kappa: list | None = None               # per case kappa of the Jacobian's extrapolation
    mesh_kappa_sd: list | None = None            # ... and its posterior standard deviation
    se_model: list = field(default_factory=list)  # per case standard errors under noise + discrepancy
    # per case standard errors with the layer moduli integrated out too (`moduli_marginal`),
    # and what they were integrated over; empty / None when not computed
    se_marginal: list = field(default_factory=list)
    marginal: dict | None = None

    def values(self, c: int) -> dict:
        return self.cand.values(c, self.theta[c] if self.theta else None)

    @property
    def wins_heldout(self) -> bool:
        """Predicts the held-out regions better than the discrepancy alone: a log predictive
        density gain of at least half the strong-evidence BIC difference (a pseudo Bayes factor
        of e^3, Geisser & Eddy 1979, on Kass & Raftery's scale), positive with a probability of
        at least `HELDOUT_GAIN_PROBABILITY` over the folds (`fit.gain_probability`: the
        Bayesian bootstrap, not the normal approximation, because the folds are a face's few
        regions and an effect acts on some of them only)."""
        return bool(np.isfinite(self.lpd_gain) and self.lpd_gain >= fit.STRONG_EVIDENCE / 2.0
                    and self.lpd_gain_prob >= HELDOUT_GAIN_PROBABILITY)


def _mesh_shift(d: CaseData, f) -> np.ndarray | float:
    """The mesh-error field a model's own fit under noise + discrepancy puts on top of the one
    taken out of the gap (`remove_mesh_error`, estimated on the baseline gap): 0 without a
    mesh-error direction."""
    if f is None or d.mesh_error is None or f.mesh_coef is None or not np.size(f.mesh_coef):
        return 0.0
    return np.asarray(d.mesh_error, float).reshape(len(d.r0), -1) @ np.ravel(f.mesh_coef)


def score(cand: Candidate, data: list[CaseData], rms0: float, n_eff: float) -> Scored:
    gp, gp_bic = evidence(cand, data)
    theta = [np.array(t, float) for t in cand.theta]
    fitted = [np.asarray(r) for r in cand.anchor_r]
    if not (cand.shared and len(data) > 1) and cand.free is not None and cand.free.any():
        # the estimate under noise + discrepancy (generalised least squares about the refined
        # fit, linear model): least squares alone lets the parameters absorb the part of the
        # discrepancy that resembles the effect (Brynjarsdottir & O'Hagan 2014). The candidate
        # keeps its least-squares anchor (the solves and the pairs build on it)
        for c, f in enumerate(gp):
            fitted[c] = cand.anchor_r[c] + cand.J[c] @ (f.theta - cand.theta[c])
            theta[c] = f.theta.copy()
    # the mesh-error field this model's own fit puts on top of the baseline's (`_mesh_shift`):
    # taken out of its fitted and held-out gaps as the baseline's was out of the baseline gap,
    # so that an effect is not charged for the part of it that the baseline's estimate took
    shifts = [_mesh_shift(d, f) for d, f in zip(data, gp)]
    for c, shift in enumerate(shifts):
        fitted[c] = fitted[c] - shift
    heldout = heldout_residuals(cand, data, offsets=shifts)
    # the held-out density integrates the mesh-error coefficient out under its prior itself, so
    # it sees the gaps without the model's shift: those fitted on the other cases where the
    # parameters are shared by several, else the anchors it refits per fold (`heldout_lpd`)
    if not any(np.any(x) for x in shifts):
        heldout_gap = heldout
    else:
        heldout_gap = heldout_residuals(cand, data) if cand.shared and len(data) > 1 else None
    rms_after = _pooled_rms(data, fitted)
    rms_ho = _pooled_rms(data, heldout)
    W = sum(float(d.gap.weights.sum()) for d in data)
    rss = sum(_rss(d, r) for d, r in zip(data, fitted))
    n_free = int(cand.free.sum()) if cand.free is not None else 0
    k = n_free * (1 if cand.shared else cand.n_cases)
    k += _discrete(cand) * cand.n_cases
    identifiable = bool(n_free > 0 or _switched(cand))
    if _switched(cand) and not n_free:
        # a switch is identifiable when turning it on moves the gap above the noise
        change = _pooled_rms(data, [a - d.r0 for a, d in zip(cand.anchor_r, data)])
        sigma = max(d.gap.noise_floor_mm for d in data)
        identifiable = bool(change * np.sqrt(n_eff) > 3.0 * sigma)
    r0s = [d.r0 for d in data]
    spread, noise_spread = shrink_spread(data, r0s, heldout)
    out = Scored(cand, rms_after, rms_ho, 100.0 * (1 - rms_after / max(rms0, 1e-12)),
                 100.0 * (1 - rms_ho / max(rms0, 1e-12)), spread,
                 fit.bic(rss, W, n_eff, k), identifiable, heldout, fitted)
    out.noise_shrink_pct, out.noise_spread_pct = beyond_noise_shrink(data, r0s, heldout), noise_spread
    out.gp, out.gp_bic, out.theta = gp, gp_bic, theta
    out.se_model = model_form_errors(cand, data, gp)
    out.lpd = heldout_lpd(cand, data, gp, heldout_gap)
    return out


def model_form_errors(cand: Candidate, data: list[CaseData], fits: list,
                      nuisance: list | None = None) -> list[np.ndarray]:
    """Per case the standard errors of the reported estimates (fit coordinates; NaN for the
    parameters held at "none") under the error model each was fitted with: sqrt(diag(F^-1)),
    F = J^T Sigma^-1 J + P^-1 with Sigma = noise + discrepancy (`discrepancy.ErrorModel`),
    summed over the cases for parameters shared by every patient, and P the parameters' prior
    covariance (`Candidate.prior_sd`; 0 precision where flat): the posterior's spread, which a
    measured effect (`Effect.measurement`) holds within the measurement's accuracy. The identifiability test
    (`_identify`) asks whether the scan noise alone could pin a parameter; these ask how well
    the data pin it once the model's own form error is counted too, the spread a user should
    read on a fitted value: a correlated discrepancy leaves far fewer independent samples than
    scan points, so they are wider, often many times. `nuisance`: per case columns integrated
    out besides (`discrepancy.ErrorModel.information`)."""
    k = len(cand.params)
    out = [np.full(k, np.nan) for _ in data]
    free = cand.free
    if not k or free is None or not free.any() or len(fits) != len(data) or len(cand.J) != len(data):
        return out
    nuisance = nuisance or [None] * len(data)
    infos = [d.error.information(cand.J[c][:, free], fits[c], nuisance[c]) for c, d in enumerate(data)]
    # the parameters' priors add their precision (once for a shared parameter)
    for c in range(1 if cand.shared and len(data) > 1 else len(data)):
        infos[c] = infos[c] + np.diag(1.0 / cand.prior_sd(c)[free] ** 2)
    if cand.shared and len(data) > 1:
        se = fit.information_errors(sum(infos))
        for o in out:
            o[free] = se
    else:
        for o, F in zip(out, infos):
            o[free] = fit.information_errors(F)
    return out


def moduli_marginal(s: Scored | None, data: list[CaseData], forward, stiffness: Effect | None,
                    say=lambda m: None, spread: dict[str, float] | None = None) -> None:
    """The standard errors of the named effect's values with the patient's layer moduli
    integrated out (module text, "Values marginal over the moduli"): sets `s.se_marginal`
    (per case, fit coordinates, NaN where not free) and `s.marginal` (the prior, or why there
    is none). Nothing for an effect that fits the moduli itself, one without free parameters,
    or a model without stiffness factors (`stiffness` None). `spread`: {layer: standard
    deviation of log modulus} measured for the patient (`faceplan diagnose --materials`, from
    a calibration), in place of the library's range for those layers."""
    if s is None or s.cand.free is None or not s.cand.free.any() or not s.gp:
        return
    cand = s.cand
    if stiffness is None or not stiffness.parameters or any(e.name == "stiffness" for e in cand.effects):
        return
    names = tuple(p.key for p in stiffness.parameters)
    spread = spread or {}
    layer = [p.key.partition(".")[2] for p in stiffness.parameters]
    sd = np.array([spread[l] if l in spread else (p.bounds[1] - p.bounds[0]) / (2.0 * 1.96)
                   for l, p in zip(layer, stiffness.parameters)])
    strings = [cand.strings(c, s.theta[c] if s.theta else None) for c in range(len(data))]
    say(f"layer moduli's sensitivities at the fitted {cand.name}, to integrate them out of its intervals")
    results = forward.sensitivities_at([(c, st) for c, st in enumerate(strings)], [names] * len(data))
    columns = []
    for d, (skin, sens) in zip(data, results):
        if not _ok(skin) or not isinstance(sens, dict):
            why = skin if not _ok(skin) else sens
            s.marginal = {"over": None, "reason": f"case {d.case.name}: {why}"}
            say(f"  not integrated: {s.marginal['reason']}")
            return
        # d r / d log f = d r / d f at f = 1 (the fitted effect holds the generic moduli)
        columns.append(np.stack([d.gap.linearised(skin, sens[k]) for k in names], axis=1) * sd)
    s.se_marginal = model_form_errors(cand, data, s.gp, nuisance=columns)
    s.marginal = {"over": {k: {"log_sd": round(float(x), 4),
                               "source": "calibration" if l in spread else "library range"}
                           for k, l, x in zip(names, layer, sd)},
                  "prior": "log-normal per layer: the calibration's spread where given (--materials), "
                           "else the stiffness effect's plausible range (a factor "
                           f"{stiffness.parameters[0].upper:g} either way) as its 95 % interval",
                  "at": [list(st) for st in strings]}


def mesh_corrections(d: CaseData, skin0, sens) -> dict:
    """{key: kappa (dr_ref/dv - dr_d/dv)} on the case's scan points, per unit of each parameter
    value with a tangent sensitivity on both meshes (module text); {} without a second mesh's
    sensitivities or an estimated mesh-error coefficient (kappa = -a), and with a coarser
    second mesh: extrapolating away from a coarser mesh amplifies that mesh's own errors (near
    a contact limit a coarse tangent can overstate a response several times) by a factor that
    no fit checks, where the baseline's mesh-error coefficient is fitted under its prior."""
    if d.mesh_coef is None or not isinstance(sens, dict) or not isinstance(d.reference_sens, dict) \
            or d.reference_coarser:
        return {}
    keys = [k for k in sens if k in d.reference_sens]
    if not keys:
        return {}
    kappa = -float(d.mesh_coef)
    ref = d.reference
    v_ref, f_ref = ref.predicted_surface(d.reference_skin)
    out = {}
    for key in keys:
        jd = d.gap.linearised(skin0, sens[key])
        dv = d.reference_sens[key]
        dv = ref.surface.carry_velocity(dv) if ref.surface is not None else np.asarray(dv, float)
        jr = d.gap.linearised_on(v_ref, f_ref, dv)
        if np.all(np.isfinite(jd)) and np.all(np.isfinite(jr)):
            out[key] = kappa * (jr - jd)
    return out


def choice_corrections(data: list[CaseData], effects: list[Effect], forward, say=lambda s: None) -> None:
    """Per case and discrete choice (a switch such as `sliding=1`) the choice's change of the
    gap extrapolated to the converged mesh as the parameters' Jacobians are
    (`mesh_corrections`): `CaseData.choice_mesh[key] = kappa (dr_ref - dr_d)`, dr the change of
    the gap the choice makes from the baseline on the second mesh (its own solve there) and on
    the diagnosis mesh. A switch has no derivative to extrapolate, and its response depends on
    the mesh as the baseline's does (docs/diagnosis.md gives a coarse face's sliding against the
    standard one's), so fitting the converged model's baseline with the
    diagnosis mesh's switch would mix two models. Only where the baseline's mesh error was
    estimated against a finer second mesh (`mesh_corrections`, the same rule); the choices of
    every case go to the second mesh in one batch. A choice the second mesh cannot solve keeps
    the diagnosis mesh's response."""
    todo = [(c, d) for c, d in enumerate(data) if d.mesh_coef is not None and d.reference_forward is not None
            and not d.reference_coarser]
    keys = sorted({effect_strings(dict(ch)) for e in effects for ch in e.choices} - {()})
    if not todo or not keys:
        return
    say(f"{len(keys) * len(todo)} solve(s) of the discrete choices on the second mesh")
    by_forward: dict[int, list] = {}
    for c, d in todo:
        by_forward.setdefault(id(d.reference_forward), []).append((c, d))
    for group in by_forward.values():
        fwd = group[0][1].reference_forward
        skins = iter(fwd.solve([(d.reference_index, k) for _, d in group for k in keys]))
        for c, d in group:
            kappa = -float(d.mesh_coef)
            ref = d.reference
            r_ref0 = d.gap.distances_to(*ref.predicted_surface(d.reference_skin))
            for k in keys:
                skin_ref = next(skins)
                skin_d = forward.solve([(c, k)])[0]
                if not (_ok(skin_ref) and _ok(skin_d)):
                    continue
                dr_ref = d.gap.distances_to(*ref.predicted_surface(skin_ref)) - r_ref0
                dr_d = d.gap.distances(skin_d) - d.r0
                if np.all(np.isfinite(dr_ref)) and np.all(np.isfinite(dr_d)):
                    d.choice_mesh[k] = kappa * (dr_ref - dr_d)
                    say(f"  {d.case.name}: {' '.join(k)} changes the gap by {d.gap.rms(dr_ref):.2f} mm RMS on the "
                        f"second mesh, {d.gap.rms(dr_d):.2f} mm on the diagnosis mesh; extrapolated "
                        f"(kappa {kappa:.2f}): a correction of {d.gap.rms(d.choice_mesh[k]):.2f} mm RMS")


def heldout_lpd(cand: Candidate | None, data: list[CaseData], fits: list, heldout: list | None = None
                ) -> np.ndarray:
    """Per cross-validation fold (every region of every case) the log predictive density of
    its gap under noise + discrepancy with the candidate fitted without it
    (`discrepancy.ErrorModel.heldout_lpd`); shared parameters of several cases are those
    fitted on the other cases (`heldout`), the discrepancy then predicts each region from the
    case's other regions. `cand` None: the baseline."""
    out = []
    for c, (d, f) in enumerate(zip(data, fits)):
        folds = list(d.folds.values()) or [np.ones(len(d.r0), bool)]
        if cand is None:
            out.append(d.error.heldout_lpd(d.r0, folds, f))
        elif cand.shared and len(data) > 1 or cand.free is None or not cand.free.any():
            r = heldout[c] if heldout is not None else cand.anchor_r[c]
            out.append(d.error.heldout_lpd(r, folds, f))
        else:
            out.append(d.error.heldout_lpd(cand.anchor_r[c], folds, f, cand.J[c], cand.theta[c],
                                           cand.lower, cand.upper, cand.free, cand.origin, cand.prior_sd(c)))
    return np.concatenate(out)


def evidence(cand: Candidate | None, data: list[CaseData]) -> tuple[list, float]:
    """Per case the profile fit under noise + discrepancy (`discrepancy.ErrorModel`) and the
    pooled BIC. Case-specific parameters are refitted by generalised least squares about the
    refined fit; shared ones (several cases) stay at their pooled fit. `cand` None: the
    baseline."""
    fits = []
    for c, d in enumerate(data):
        if cand is None:
            fits.append(d.error.fit(d.r0))
            continue
        n_choice = _discrete(cand)
        free = cand.free if cand.free is not None else np.zeros(len(cand.params), bool)
        if cand.shared and len(data) > 1:
            f = d.error.fit(cand.anchor_r[c], extra_k=n_choice)
            f.k = 0 if c else int(free.sum()) + n_choice * len(data)
        else:
            f = d.error.fit(cand.anchor_r[c], cand.J[c], cand.theta[c], cand.lower, cand.upper, free,
                            extra_k=n_choice, prior_sd=cand.prior_sd(c), origin=cand.origin)
        fits.append(f)
    loglik = sum(f.loglik for f in fits)
    k = sum(f.k for f in fits)
    # one sample size for every model: the baseline's independent samples (its correlation
    # length), so that the penalty per parameter is the same whatever a model's own length
    n = sum(d.gp_n_eff if d.gp_n_eff else d.error.n_eff(f.ell) for d, f in zip(data, fits))
    return fits, float(-2.0 * loglik + k * np.log(max(n, 2.0)))


def _pair(a: Candidate, b: Candidate, data: list[CaseData], b_choices: list | None = None) -> Candidate:
    """a+b: b's continuous parameters added to a's, the anchors at a's fit. b_choices: per case
    the partner's discrete choices in place of its own (their mesh corrections from
    `CaseData.choice_mesh`); the anchors are then not a solve, `_pairs_with` makes them."""
    n = len(data)
    cand = Candidate(f"{a.name}+{b.name}", a.effects + b.effects, a.shared and b.shared and n > 1, n,
                     a.params + b.params)
    for c, d in enumerate(data):
        own = tuple(b.choices[c] if b.choices else ())
        mb = b.M[c] if b.M else None
        if b_choices is not None and tuple(b_choices[c]) != own:
            own = tuple(b_choices[c])
            mb = d.choice_mesh.get(effect_strings(dict(own)))
        cand.choices.append(tuple(a.choices[c] if a.choices else ()) + own)
        cand.theta.append(np.concatenate([a.theta[c], b.origin]))
        cand.J.append(np.concatenate([a.J[c], b.J[c]], axis=1))
        cand.C.append(np.concatenate([a.C[c], b.C[c]], axis=1))
        cand.KR.append(np.concatenate([a.KR[c], b.KR[c]], axis=1)
                       if a.KR[c] is not None and b.KR[c] is not None else None)
        ms = [m for m in (a.M[c] if a.M else None, mb) if m is not None]
        cand.M.append(sum(ms) if ms else None)
        cand.anchor_r.append(a.anchor_r[c])
        cand.tangent.append(bool(a.tangent) and bool(b.tangent) and a.tangent[c] and b.tangent[c])
    cand.sensitivity = a.sensitivity
    return cand


def _pairs_with(a: Candidate, b: Candidate, data: list[CaseData], forward) -> list[Candidate]:
    """The pairs of lead a with partner b to refine (module text). A partner without discrete
    choices gives one, anchored at a's fit. A partner with them gives one per choice (the same
    switch in every case) and its own per-case choices, each anchored at the full solve of a's
    fitted values with that switch: the linear model about a's anchor does not hold a switch's
    change, and a refinement step that is not better than a's anchor is refused, so anchored
    there a pair whose switch only helps beside a's effect would stay a's fit. Variants whose
    anchor solve fails are left out (all failing: the one anchored at a's fit)."""
    n = len(data)
    switches = [ch for e in b.effects for ch in e.choices]
    if not switches or not b.choices:
        return [_pair(a, b, data)]
    options = [list(b.choices)]
    for ch in switches:
        opt = [tuple(ch)] * n
        if opt not in options:
            options.append(opt)
    variants = [_pair(a, b, data, opt) for opt in options]
    skins = iter(forward.solve([(c, v.strings(c)) for v in variants for c in range(n)]))
    kept = []
    for v in variants:
        results = [next(skins) for _ in range(n)]
        v.solves += n
        if all(_ok(s) for s in results):
            v.anchor_r = [v.corrected(c, data[c], data[c].gap.distances(s), v.theta[c])
                          for c, s in enumerate(results)]
            kept.append(v)
    return kept or [_pair(a, b, data)]


def _best_fit(cands: list[Candidate], data: list[CaseData]) -> Candidate:
    """The candidate whose anchors leave the smallest weighted residual over every case."""
    return min(cands, key=lambda cand: sum(_rss(d, r) for d, r in zip(data, cand.anchor_r)))


def analyse(data: list[CaseData], effects: list[Effect], forward, say=lambda s: None,
            tangent: bool = True, moduli_spread: dict[str, float] | None = None) -> dict:
    """Fit, rank and judge every effect; returns the pieces of diagnosis.json. `tangent`:
    use the model's tangent sensitivities where it gives them (else finite differences).
    `moduli_spread`: the patient's measured layer moduli spread (`moduli_marginal`)."""
    n_eff = sum(d.gap.n_eff() for d in data)
    W = sum(float(d.gap.weights.sum()) for d in data)
    rms0 = _pooled_rms(data, [d.r0 for d in data])
    bic0 = fit.bic(sum(_rss(d, d.r0) for d in data), W, n_eff, 0)
    say("noise + discrepancy error model of the baseline gap")
    base_fits, _ = evidence(None, data)
    for d, f in zip(data, base_fits):
        d.pose_cov = d.error.pose_covariance(f)
        d.gp_n_eff = d.error.n_eff(f.ell)
        d.gap.discrepancy_mm = f.discrepancy_mm
        d.gap.discrepancy_ell_mm = f.ell
        d.gap.error_test = (lambda em, f: (lambda r, m: em.region_pvalue(r, m, f)))(d.error, f)
        say(f"  {d.case.name}: discrepancy {f.sigma_d:.2f} mm at correlation length {f.ell:.0f} mm and "
            f"{f.long_mm:.2f} mm smooth over the face, "
            + (f"mesh error {d.gap.mesh_error_mm:.2f} mm (removed), " if d.mesh_error is not None else "")
            + f"noise {d.gap.noise_floor_mm:.2f} mm"
            + ("" if d.pose_cov is None else
               f"; the scan's pose uncertain by {np.degrees(np.sqrt(np.diag(d.pose_cov)[:3])).max():.2f} deg "
               f"and {np.sqrt(np.diag(d.pose_cov)[3:]).max():.2f} mm (integrated out)"))
    gp0 = evidence(None, data)[1]
    lpd0 = heldout_lpd(None, data, base_fits)
    names = tuple(p.key for e in effects for p in e.parameters)
    sens = [None] * len(data)
    notes = []
    if tangent and names:
        say(f"tangent sensitivities of {len(names)} parameter(s) at the baseline")
        for c, (_, s) in enumerate(forward.sensitivities([names] * len(data))):
            sens[c] = s
            if not isinstance(s, dict):
                notes.append(f"{data[c].case.name}: {s}; finite differences instead")
                say(f"  {notes[-1]}")
    for c, d in enumerate(data):
        d.mesh_jac = mesh_corrections(d, forward.baseline(c), sens[c])
        if d.mesh_jac:
            say(f"  {d.case.name}: {len(d.mesh_jac)} parameter(s) fitted on the response extrapolated to the "
                f"converged mesh (kappa {-d.mesh_coef:.2f} ± {d.mesh_coef_sd:.2f})")
    reqs = _sensitivity_requests(data, effects, sens)
    say(f"{len(set(reqs))} solve(s) for finite differences and discrete choices")
    forward.prefetch(reqs)
    # the effects the tangent alone sets up (no switch, no finite differences) need none of
    # those solves: their first nonlinear refinement starts now beside them, the very requests
    # `refine` makes, so no worker waits for a batch's slowest solve
    early = {id(e): _single_candidate(e, data, forward, sens) for e in effects
             if not e.choices and all(not _fd_params(e, s) for s in sens)}
    forward.prefetch(first_refinement_requests(list(early.values()), data))
    forward.solve(reqs)                                             # one parallel batch
    choice_corrections(data, effects, forward, say)
    cands = [early[id(e)] if id(e) in early else _single_candidate(e, data, forward, sens) for e in effects]
    say("fitting and refining with full nonlinear solves")
    refine(cands, data, forward)
    scored = [score(c, data, rms0, n_eff) for c in cands if c.failed is None]
    failed = [c for c in cands if c.failed is not None]
    _judge(scored, gp0, lpd0)
    ranked = sorted([s for s in scored if s.identifiable], key=lambda s: -s.heldout_shrink_pct)
    # the gap left by the best effect: pairs when it is still significant somewhere
    sig_before = any(_significant_regions(data, [d.r0 for d in data], noise_only=True))
    pairs = []
    best = next((s for s in ranked if s.significant), None)
    # the greedy step starts from the effect with the largest held-out shrinkage, significant
    # or not: two effects can interact (tone with sliding tissue moves the chin as neither
    # does alone); the solves it asks for do not depend on the judging
    lead = ranked[0] if ranked else None
    if sig_before and lead is not None and _significant_regions(data, lead.heldout, noise_only=True):
        partners = [s for s in ranked if s is not lead and not set(e.name for e in s.cand.effects)
                    & set(e.name for e in lead.cand.effects)][:PAIR_PARTNERS]
        if partners:
            say(f"{lead.cand.name} leaves a significant gap: trying pairs with "
                + ", ".join(p.cand.name for p in partners))
            # the switch is re-chosen beside the other effect's fit whichever of the two leads
            variants = [_pairs_with(*((p.cand, lead.cand) if _switched(lead.cand) and not _switched(p.cand)
                                      else (lead.cand, p.cand)), data, forward) for p in partners]
            refine([v for vs in variants for v in vs], data, forward)
            pair_cands = [_best_fit(vs, data) for vs in variants]
            pairs = [score(c, data, rms0, n_eff) for c in pair_cands]
            _judge(pairs, gp0, lpd0)
    prob = probabilities(gp0, lpd0, scored + pairs)
    for s in scored + pairs:
        s.probability = prob[s.cand.name]
        extrapolated = [bool(np.any(C)) or (bool(s.cand.M) and s.cand.M[c] is not None)
                        for c, C in enumerate(s.cand.C)]
        if s.cand.C and all(extrapolated):
            s.mesh_kappa = [-float(d.mesh_coef) for d in data]
            s.mesh_kappa_sd = [float(d.mesh_coef_sd) for d in data]
    best = _leading(ranked, best)
    verdict = _verdict(data, best, pairs, prob, scored, gp0=gp0)
    moduli_marginal(verdict.get("_scored"), data, forward, stiffness_effect(), say, moduli_spread)
    return {"rms0": rms0, "bic0": bic0, "gp_bic0": gp0, "baseline_error": base_fits, "n_eff": n_eff, "scored": scored, "pairs": pairs, "notes": notes,
            "failed": failed, "verdict": verdict, "probabilities": prob, "best": best,
            "winner": verdict.get("_scored")}


def probabilities(gp0: float, lpd0: np.ndarray, scored: list[Scored]) -> dict[str, float]:
    """Model probabilities from held-out prediction: pseudo-BMA+ weights (`fit.
    predictive_weights`) of the held-out log predictive densities per fold, over the baseline
    and the models with strong evidence against it (BIC under noise + discrepancy) that also
    predict held-out regions better than the discrepancy alone; the others get 0: an effect
    whose in-sample evidence is weak or does not carry over to unseen regions has fitted the
    discrepancy. The verdict ranks effects on held-out data, so its confidence is measured on
    held-out data too: a model that wins in-sample (BIC) by fitting more freely does not take
    the probability from one that predicts unseen regions as well."""
    pool = {"baseline": np.asarray(lpd0, float)}
    for s in scored:
        if s.identifiable and s.wins_heldout and gp0 - s.gp_bic >= fit.STRONG_EVIDENCE:
            pool[s.cand.name] = np.asarray(s.lpd, float)
    prob = fit.predictive_weights(pool)
    return {"baseline": prob["baseline"], **{s.cand.name: prob.get(s.cand.name, 0.0) for s in scored}}


def _judge(scored: list[Scored], gp0: float, lpd0: np.ndarray) -> None:
    """Significant: strong evidence against the baseline under noise + discrepancy, held-out
    regions predicted better than by the discrepancy alone (`Scored.wins_heldout`), and a
    held-out shrinkage of the gap beyond the scan noise (`beyond_noise_shrink`) of at least
    `MIN_HELDOUT_SHRINK_PCT` and of twice its bootstrap spread."""
    for s in scored:
        diff = np.asarray(s.lpd, float) - lpd0
        s.lpd_gain = float(diff.sum())
        s.lpd_gain_se = float(np.sqrt(len(diff)) * np.std(diff)) if len(diff) > 1 else 0.0
        s.lpd_gain_prob = fit.gain_probability(diff)
        s.significant = bool(s.identifiable and gp0 - s.gp_bic >= fit.STRONG_EVIDENCE and s.wins_heldout
                             and bool(s.noise_shrink_pct >= naming_share(s.noise_spread_pct)))


def naming_share(spread_pct: float) -> float:
    """The held-out shrinkage of the gap beyond the noise (%) an effect must reach to be named,
    given that shrinkage's bootstrap spread: `MIN_HELDOUT_SHRINK_PCT`, and twice the spread."""
    return max(MIN_HELDOUT_SHRINK_PCT, 2.0 * spread_pct)


def _significant_regions(data: list[CaseData], rs: list[np.ndarray], noise_only: bool = False) -> list[str]:
    out = []
    for d, r in zip(data, rs):
        for name, m in d.folds.items():
            if d.gap.significant(d.gap.rms(r, m), m, noise_only, r) and name not in out:
                out.append(name)
    return out


def _explained_regions(data, before, after) -> list[str]:
    """Regions above the noise whose held-out gap the effect shrinks by the named share."""
    out = []
    for d, r0, r1 in zip(data, before, after):
        for name, m in d.folds.items():
            a, b = d.gap.rms(r0, m), d.gap.rms(r1, m)
            if d.gap.significant(a, m, True) and b <= a * (1 - MIN_HELDOUT_SHRINK_PCT / 100) and name not in out:
                out.append(name)
    return out


def _leading(ranked: list, best):
    """The significant effect the verdict names: the largest held-out shrinkage, unless another
    significant effect's shrinkage is within the leader's bootstrap spread of it; among those
    the shrinkage cannot tell apart, the one of highest (held-out) probability. Two effects
    that remove the same share of the gap on unseen regions are told apart by how well they
    predict them, and the verdict's effect is then never one whose confidence is near 0 while
    another carries it."""
    if best is None:
        return None
    tied = [s for s in ranked if s.significant
            and s.heldout_shrink_pct >= best.heldout_shrink_pct - max(best.spread_pct, 0.0)]
    return max(tied, key=lambda s: s.probability) if tied else best


def _pair_earns(pair, members: list, best) -> bool:
    """Whether a significant `pair` earns its second effect: on held-out data it removes
    `MIN_PAIR_GAIN_PCT` more of the gap than each of its `members` (scored alone), significant
    or not, so that a member that explains the gap without being named (its held-out density
    no better than the discrepancy's) does not let a partner that fits the model-form rest
    (bone execution's 18 parameters) be named with it; and in the evidence it is strongly
    better in BIC than each member alone and than the `best` significant single effect (None:
    none), so that each effect is needed beside the other: a partner whose only gain is to
    even out a member's held-out regions is not evidence of a second effect."""
    rivals = list(members) + ([best] if best is not None else [])
    return bool(pair.significant
                and all(pair.heldout_shrink_pct >= m.heldout_shrink_pct + MIN_PAIR_GAIN_PCT for m in members)
                and all(r.gp_bic - pair.gp_bic >= fit.STRONG_EVIDENCE for r in rivals))


@dataclass(frozen=True)
class SurfaceConfound:
    """Two effects whose signatures coincide where a surface scan measures, so that the scan
    alone cannot rule out one beside the other: `why` (a clause) says where they coincide,
    `settled_by` (a noun phrase) names the data that separate them, and `settling_field` is
    the case attribute that holds those data (every case having it settles the pair)."""
    effects: frozenset
    why: str
    settled_by: str
    settling_field: str


CONFOUNDED_ON_SURFACE = (
    SurfaceConfound(
        frozenset({"sliding", "bone_execution"}),
        why="the gap is measured along the skin's normal, where tissue that lags its moved bone and a "
            "bone moved less than planned look alike",
        settled_by="the bones' achieved movements (postop/plan_actual.yaml, from a post-op CBCT)",
        settling_field="plan_actual"),
)


def confound_between(named: str, other: str) -> SurfaceConfound | None:
    """The entry of `CONFOUNDED_ON_SURFACE` pairing `other` with an effect of `named` (a single
    effect or a pair "a+b"), None when there is none."""
    members = set(named.split("+"))
    return next((c for c in CONFOUNDED_ON_SURFACE
                 if other in c.effects and members & (c.effects - {other})), None)


def alternatives(winner, scored, gp0: float) -> list[dict]:
    """The single effects outside the named one(s) that also explain the gap in-sample with
    strong evidence (BIC gain over the baseline >= `fit.STRONG_EVIDENCE` under noise +
    discrepancy), best evidence first: what the data do not rule out beside the verdict.
    Each with its held-out figures, which decided that it was not named."""
    named = set(winner.cand.name.split("+"))
    gains = [(float(gp0 - s.gp_bic), s) for s in scored if s.cand.name not in named and s.identifiable]
    out = []
    for gain, s in sorted([g for g in gains if np.isfinite(g[0]) and g[0] >= fit.STRONG_EVIDENCE],
                          key=lambda g: -g[0]):
        out.append({"effect": s.cand.name, "bic_gain": round(gain, 1),
                    "heldout_shrink_pct": round(float(s.heldout_shrink_pct), 2),
                    "heldout_lpd_gain": None if not np.isfinite(s.lpd_gain) else round(float(s.lpd_gain), 2),
                    "heldout_lpd_gain_probability": None if not np.isfinite(s.lpd_gain_prob)
                    else round(float(s.lpd_gain_prob), 4),
                    "significant": bool(s.significant)})
    return out


def surface_confounds(named: str, alts: list[dict], cases) -> list[str]:
    """Alternatives a surface scan cannot separate from the named effect
    (`CONFOUNDED_ON_SURFACE`): those that predict unseen regions better than the baseline
    more likely than not, unless every one of `cases` holds the data that settle the pair."""
    out = []
    for a in alts:
        if (a["heldout_lpd_gain_probability"] or 0.0) < 0.5:
            continue
        c = confound_between(named, a["effect"])
        if c is not None and not all(getattr(case, c.settling_field, None) is not None for case in cases):
            out.append(a["effect"])
    return out


def confound_warning(verdict: dict) -> list[str]:
    """The warning a verdict carries for each alternative in `confounded_on_surface`."""
    out = []
    for name in verdict.get("confounded_on_surface") or ():
        a = next(x for x in verdict["alternatives"] if x["effect"] == name)
        c = confound_between(verdict["effect"], name)
        out.append(f"{name} also explains the gap (BIC gain {a['bic_gain']:g} over the baseline, a held-out "
                   f"gain with probability {a['heldout_lpd_gain_probability']:.2f}) beside the named "
                   f"{verdict['effect']}: {c.why}; {c.settled_by} would tell them apart")
    return out


def _verdict(data, best, pairs, prob, scored=(), gp0: float = np.nan) -> dict:
    """The winning effect when one is significant; else `null` when no region's gap exceeds
    noise + discrepancy (the model-form error the baseline is expected to carry),
    `unexplained` (with those regions) when some does. A significant effect beats the noise by
    construction (strong evidence against noise + discrepancy, held-out gain, a share of the
    gap beyond the noise): no region need hold a systematic gap as large as the noise itself
    (the `above_noise` size rule of the localization), which an effect of about the noise's
    size spread over the face does not reach."""
    r0s = [d.r0 for d in data]
    above_noise = _significant_regions(data, r0s, noise_only=True)
    winner = best
    single = {s.cand.name: s for s in scored}
    for p in sorted(pairs, key=lambda s: -s.heldout_shrink_pct):
        if _pair_earns(p, [single[m] for m in p.cand.name.split("+") if m in single], best):
            winner = p
            break
    if winner is None:
        sig = _significant_regions(data, r0s)
        # effects with strong evidence and a held-out density gain that remove too little of the
        # held-out gap to be named: they hold the probability the baseline does not
        supported = [s.cand.name for s in sorted(list(scored) + list(pairs), key=lambda s: -s.probability)
                     if s.probability > 0.0 and not s.significant]
        return {"effect": "unexplained" if sig else None, "confidence": round(prob["baseline"], 4), "regions": sig,
                "supported_not_named": supported}
    # the probability that the named effect(s) are present: the total probability of every
    # model compared that contains them (a posterior inclusion probability, Barbieri & Berger,
    # Ann. Stat. 32:870, 2004), not only of the one model named
    named = set(winner.cand.name.split("+"))
    conf = sum(p for m, p in prob.items() if m != "baseline" and named <= set(m.split("+")))
    alts = alternatives(winner, scored, gp0)
    return {"effect": winner.cand.name, "confidence": round(conf, 4),
            "alternatives": alts,
            "confounded_on_surface": surface_confounds(winner.cand.name, alts, [d.case for d in data]),
            "regions": _explained_regions(data, r0s, winner.heldout) or above_noise,
            "remaining_significant_regions": _significant_regions(data, winner.heldout),
            "remaining_above_noise_regions": _significant_regions(data, winner.heldout, noise_only=True),
            "_scored": winner}
