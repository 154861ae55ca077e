"""The forward model of the diagnosis: a case and effect values -> the predicted skin.

One forward solve is `planner.pipeline.solve_plan` on the case's registered patient model with
the effects given as the `NAME=VALUE` strings of `faceplan predict --effect`, reduced to the
skin surface's vertex positions. Solves are independent tasks: a `Runner` sends them to a
dask.distributed cluster (the patient models are scattered to the workers once) or runs them
in this process, and a `Forward` keeps every result by (case, effects) so that no solve is ever
repeated (the baseline of a case, its finite-difference points and the fitted values are each
solved once, whatever asks for them). A solve that fails (`SolveError`) is reported as such
and the caller treats that parameter value as unreachable.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from facemodel.effects import executed_segments
from planner.errors import InputError, SolveError

__all__ = ["CaseModel", "PatientSurface", "Runner", "Forward", "solve_skin", "prepare_case", "patient_surface"]


@dataclass
class CaseModel:
    """What a forward solve needs (picklable: sent to the workers)."""

    name: str
    model: object                   # registered FaceModel with the patient's segment sets
    plan: object                    # planner.plan.Plan
    bones: dict                     # segment -> (vertices, faces) of its bone surface
    skin_ids: np.ndarray            # model node ids of the skin vertices
    skin_faces: np.ndarray          # (t, 3) triangles over the skin vertices
    region: np.ndarray              # (n_skin,) region index, -1 for none
    region_names: tuple[str, ...]
    unoperated: tuple[str, ...]
    landmark_ids: dict = field(default_factory=dict)   # name -> node id
    plan_actual: object = None      # the achieved movements (postop/plan_actual.yaml)
    follow_up_months: float | None = None
    surface: "PatientSurface | None" = None   # the patient's own pre-op skin over the face

    def predicted_surface(self, skin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the predicted face for the model's skin positions `skin`: the
        patient's pre-op skin carried by the model's displacement when it is known, else the
        model's skin itself."""
        if self.surface is None:
            return np.asarray(skin, float), np.asarray(self.skin_faces)
        return self.surface.carry(skin), self.surface.faces

    @property
    def moved_segments(self) -> tuple[str, ...]:
        return tuple(self.plan.motions())

    @property
    def executed_segments(self) -> tuple[str, ...]:
        """The moved segments with an execution of their own (`facemodel.effects.
        executed_segments`: not the chin when it moves with the mandible, uncut)."""
        return executed_segments(self.plan.motions())


@dataclass
class PatientSurface:
    """The patient's pre-op skin over the modelled face, tied to the model's skin: each vertex
    takes the model's displacement interpolated (barycentric) at its closest point on the
    model's pre-op skin triangles. The prediction of the post-op face is then the patient's own
    face moved as the model moves (the same construction as a post-op truth,
    `facemodel.synthetic.displaced_surface`), so the gap to the post-op scan holds the error of
    the predicted movement and not the registered model's misfit of the pre-op face (its
    faceting and the registration residual, which no effect can change). Linear in the skin
    positions: the derivative of the surface is `carry_velocity` of the skin's."""

    vertices: np.ndarray            # (m, 3) pre-op positions
    faces: np.ndarray               # (t, 3)
    rows: np.ndarray                # (m, 3) skin vertex indices (into skin_ids) of the closest triangle
    bary: np.ndarray                # (m, 3) barycentric weights
    rest: np.ndarray                # (n_skin, 3) the model's pre-op skin positions
    region: np.ndarray              # (m,) region index (that of the nearest model skin vertex)

    def carry(self, skin: np.ndarray) -> np.ndarray:
        return self.vertices + self.carry_velocity(np.asarray(skin, float) - self.rest)

    def carry_velocity(self, dskin: np.ndarray) -> np.ndarray:
        return np.einsum("mj,mjk->mk", self.bary, np.asarray(dskin, float)[self.rows])


# patient skin vertices farther than this from the registered model's skin are not on the
# modelled face (the registered skin fits the pre-op skin within a fraction of a mm there)
SURFACE_GATE_MM = 3.0


def patient_surface(skin_rest: np.ndarray, skin_faces: np.ndarray, region: np.ndarray,
                    vertices: np.ndarray, faces: np.ndarray) -> PatientSurface | None:
    """The patient's pre-op skin (vertices, faces) over the model's face regions, tied to the
    model's skin triangles (see `PatientSurface`); None when it does not lie on the model."""
    from planner.compare.distances import TriangleSurface

    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    X = np.asarray(skin_rest, float)
    T = np.asarray(skin_faces, np.int64)
    cp = TriangleSurface(X, T).closest(V)
    rows = T[cp.face]
    bary = np.clip(np.asarray(cp.bary, float), 0.0, 1.0)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)
    reg = np.asarray(region)[rows[np.arange(len(V)), np.argmax(bary, axis=1)]]
    keep = (np.abs(cp.signed) <= SURFACE_GATE_MM) & (reg >= 0)
    fk = keep[F].all(axis=1)
    if fk.sum() < 100:
        return None
    used = np.zeros(len(V), bool)
    used[F[fk].ravel()] = True
    new = -np.ones(len(V), np.int64)
    new[used] = np.arange(int(used.sum()))
    return PatientSurface(V[used], new[F[fk]], rows[used], bary[used], X, reg[used])


def prepare_case(name: str, model, plan, bones: dict | None, plan_actual=None,
                 follow_up_months: float | None = None, preop_skin=None) -> CaseModel:
    """The patient model with its attachment sets assigned to the case's bones (kept as they
    are without bones), and the skin; `preop_skin` (vertices, faces): the patient's own pre-op
    skin, on which the predicted movement is carried (`PatientSurface`)."""
    from planner.pipeline import region_of_nodes, skin_surface
    from planner.segments import assign_segments, with_segments

    if bones:
        model = with_segments(model, assign_segments(model, bones, plan))
    _, faces, ids = skin_surface(model)
    region, names = region_of_nodes(model, ids)
    # plain arrays travel to the workers (an unpickled trimesh keeps stale caches)
    arrays = {k: (np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)) for k, m in (bones or {}).items()}
    surface = None
    if preop_skin is not None:
        surface = patient_surface(np.asarray(model.nodes, float)[ids], faces, region, *preop_skin)
    return CaseModel(name, model, plan, arrays, ids, faces, region, tuple(names),
                     tuple(getattr(model, "unoperated_regions", ())),
                     {k: int(v) for k, v in getattr(model, "landmarks", {}).items()},
                     plan_actual, follow_up_months, surface)


def _solve(case: CaseModel, strings: tuple[str, ...], guess=None):
    """The prediction with the effects `strings`; guess: the baseline's displacement, from
    which the full load is solved first (`planner.pipeline.solve_plan`)."""
    from planner.pipeline import Progress, parse_effects, solve_plan

    import trimesh

    # the bones give the segment centroids that bone corrections turn about (the attachment
    # sets are re-assigned to the same result)
    bones = {k: trimesh.Trimesh(v, f, process=False) for k, (v, f) in case.bones.items()}
    return solve_plan(case.model, case.plan, bones or None, effects=parse_effects(list(strings)),
                      plan_actual=case.plan_actual, follow_up_months=case.follow_up_months,
                      progress=Progress(echo=False), guess=guess)


def solve_skin(case: CaseModel, strings: tuple[str, ...], guess=None):
    """(skin vertex positions (n_skin, 3) of the prediction with the effects `strings`, or the
    error message (str) when the model cannot be solved there; the contacts it left unmet,
    {name: mm}); guess as in `_solve`."""
    try:
        pred = _solve(case, strings, guess)
    except SolveError as exc:
        return f"{exc}", {}
    return np.asarray(pred.predicted_nodes, float)[case.skin_ids], pred.contact_unmet


def solve_with_sensitivities(case: CaseModel, names: tuple[str, ...], strings: tuple[str, ...] = (),
                             guess=None):
    """(skin, {parameter: d(skin vertex positions)/dp (n_skin, 3)} or the reason they are not
    available, the displacement (n_nodes, 3) or None, the contacts the solve left unmet
    {name: mm}) of the prediction with the effects `strings` (default: the baseline): the
    direct differentiation at the converged solution (`planner.pipeline.skin_sensitivities`,
    one factorisation for every parameter); guess as in `_solve`."""
    try:
        pred = _solve(case, tuple(strings), guess)
    except SolveError as exc:
        return f"{exc}", None, None, {}
    skin = np.asarray(pred.predicted_nodes, float)[case.skin_ids]
    u = np.asarray(pred.displacement, float)
    unmet = pred.contact_unmet
    try:
        from planner.pipeline import skin_sensitivities
    except ImportError:
        return skin, "the pipeline gives no sensitivities", u, unmet
    try:
        ids, sens = skin_sensitivities(pred, list(names))
    except (ValueError, KeyError, ArithmeticError, RuntimeError) as exc:
        return skin, f"sensitivities not available: {exc}", u, unmet
    if not np.array_equal(np.asarray(ids), np.asarray(case.skin_ids)):
        return skin, "sensitivities on another skin vertex set", u, unmet
    return skin, {k: np.asarray(v, float) for k, v in sens.items()}, u, unmet


def _solve_task(case: CaseModel, request, guess=None):
    """A request is effect strings (a solve, from the baseline's displacement `guess` when
    given), ("sensitivities", names) at the baseline or ("sensitivities", names, strings)
    with the effects `strings` (from `guess`)."""
    import os

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if request and request[0] == SENSITIVITIES:
        if len(request) > 2 and request[2]:
            return solve_with_sensitivities(case, tuple(request[1]), tuple(request[2]), guess)
        return solve_with_sensitivities(case, tuple(request[1]))
    return solve_skin(case, request, guess)


SENSITIVITIES = "sensitivities"


class Runner:
    """Runs independent solves: on a dask.distributed `client`, or here when it is None."""

    def __init__(self, client=None):
        self.client = client
        self._scattered: dict[int, object] = {}

    @property
    def n_workers(self) -> int:
        if self.client is None:
            return 1
        return max(1, len(self.client.scheduler_info().get("workers", {})))

    def map(self, cases: list[CaseModel], requests: list[tuple[int, tuple[str, ...]]],
            on_done: Callable[[int], None] | None = None, guesses: dict | None = None) -> list:
        """Results of the requests (case index, effect strings); guesses: {case index: the
        baseline's displacement} for the effect solves to start from."""
        guesses = guesses or {}
        if self.client is None:
            out = []
            for k, (i, s) in enumerate(requests):
                out.append(_solve_task(cases[i], s, guesses.get(i)))
                if on_done:
                    on_done(k)
            return out
        return self.gather(self.submit(cases, requests, guesses), on_done)

    def submit(self, cases: list[CaseModel], requests: list[tuple[int, tuple[str, ...]]],
               guesses: dict | None = None) -> list | None:
        """The requests sent to the cluster without waiting: their futures (for `gather`), or
        None when solves run in this process (they are then solved when asked for)."""
        if self.client is None:
            return None
        guesses = guesses or {}
        futures = []
        for i, s in requests:
            if id(cases[i]) not in self._scattered:
                self._scattered[id(cases[i])] = self.client.scatter(cases[i], broadcast=True)
            g = guesses.get(i)
            if g is not None:
                key = ("guess", id(cases[i]), id(g))
                if key not in self._scattered:
                    self._scattered[key] = self.client.scatter(g, broadcast=True)
                g = self._scattered[key]
            futures.append(self.client.submit(_solve_task, self._scattered[id(cases[i])], s, g,
                                              pure=False))
        return futures

    def gather(self, futures: list, on_done: Callable[[int], None] | None = None) -> list:
        """The results of `submit`'s futures, `on_done(k)` called as the k-th completes."""
        from distributed import as_completed

        index = {f.key: k for k, f in enumerate(futures)}
        for f in as_completed(futures):
            if on_done:
                on_done(index[f.key])
        return self.client.gather(futures)


class Forward:
    """Predicted skins by (case, effects), each solved once."""

    def __init__(self, cases: list[CaseModel], runner: Runner | None = None,
                 say: Callable[[str], None] | None = None):
        self.cases = cases
        self.runner = runner or Runner()
        self.say = say or (lambda s: None)
        self._store: dict[tuple[int, tuple[str, ...]], object] = {}
        # per case index, the baseline's displacement: every effect solve starts from it (the
        # effects change the problem by a little; `solver.newton.newton_solve(guess=...)`)
        self._guess: dict[int, np.ndarray] = {}
        # per (case, effects) solved, the contacts the solve left deeper than twice their
        # tolerance (`facemodel.simulation`: a converged prediction, not the contact state
        # asked for), {name: mm}; absent when every contact was met
        self._unmet: dict = {}
        # requests started by `prefetch` and not yet collected: key -> future
        self._pending: dict = {}
        self.n_solves = 0
        self.solve_time_s = 0.0

    def _key(self, r):
        # by the case object: the same patient listed twice is solved once
        return (id(self.cases[r[0]]), r[1])

    def prefetch(self, requests: list[tuple[int, tuple[str, ...]]]) -> None:
        """Start the solves of `requests` on the cluster now, without waiting for them: a later
        `solve` of the same requests collects them. Solves that do not depend on each other's
        results (a baseline, the same case with another boundary condition, the case on
        another mesh) then share the workers instead of running one batch after the other.
        With solves run in this process (or a runner that cannot submit) nothing starts: they
        are solved when asked for, with the same results."""
        submit = getattr(self.runner, "submit", None)
        todo, seen = [], set()
        for r in requests:
            k = self._key(r)
            if k not in self._store and k not in self._pending and k not in seen:
                seen.add(k)
                todo.append(r)
        if not todo or submit is None:
            return
        futures = submit(self.cases, todo, self._guess)
        if futures is None:
            return
        for r, f in zip(todo, futures):
            self._pending[self._key(r)] = f

    def solve(self, requests: list[tuple[int, tuple[str, ...]]]) -> list:
        """Skins (or error messages) for (case index, effect strings) requests."""
        todo, seen = [], set()
        for r in requests:
            if self._key(r) not in self._store and self._key(r) not in seen:
                seen.add(self._key(r))
                todo.append(r)
        if todo:
            t0 = time.perf_counter()
            self.say(f"  {len(todo)} forward solve(s) on {self.runner.n_workers} worker(s) ...")

            def done(k):
                i, s = todo[k]
                if s and s[0] == SENSITIVITIES:
                    what = (", ".join(s[2]) if len(s) > 2 and s[2] else "baseline") + " and sensitivities"
                else:
                    what = ", ".join(s) or "baseline"
                self.say(f"    solved {self.cases[i].name} [{what}]")

            if any(self._key(r) in self._pending for r in todo):
                new = [r for r in todo if self._key(r) not in self._pending]
                fresh = iter(self.runner.submit(self.cases, new, self._guess) if new else ())
                futures = [self._pending.pop(self._key(r)) if self._key(r) in self._pending
                           else next(fresh) for r in todo]
                results = self.runner.gather(futures, done)
            else:
                results = self.runner.map(self.cases, todo, done, self._guess)
            for r, out in zip(todo, results):
                if r[1] and r[1][0] == SENSITIVITIES:
                    out, unmet = out[:3], out[3]
                    # the skin is the plain solve's of the same effects: a later plain request
                    # takes it from the store
                    plain = (r[0], tuple(r[1][2]) if len(r[1]) > 2 else ())
                    self._unmet_of(plain, unmet)
                    self._store.setdefault(self._key(plain), out[0])
                else:
                    out, unmet = out
                self._unmet_of(r, unmet)
                self._store[self._key(r)] = out
            self.n_solves += len(todo)
            self.solve_time_s += time.perf_counter() - t0
        return [self._store[self._key(r)] for r in requests]

    @staticmethod
    def sensitivity_requests(names_per_case: list[tuple[str, ...]]) -> list:
        """The requests of `sensitivities` (for `prefetch`)."""
        return [(i, (SENSITIVITIES, tuple(n))) for i, n in enumerate(names_per_case)]

    def sensitivities(self, names_per_case: list[tuple[str, ...]]) -> list:
        """Per case (baseline skin, {name: d skin/dp} or reason) in one parallel batch; the
        baseline skins are stored as the baseline solves (`solve`)."""
        out = self.solve(self.sensitivity_requests(names_per_case))
        for i, (skin, _, u) in enumerate(out):
            if u is not None and not isinstance(skin, str):
                self._guess[i] = u
        return [(skin, sens) for skin, sens, _ in out]

    def sensitivities_at(self, requests: list[tuple[int, tuple[str, ...]]], names_per_request: list) -> list:
        """Per (case index, effect strings) request the (skin, {name: d skin/dp} or reason) of
        the prediction with those effects, in one parallel batch from the baselines'
        displacements; the skins are stored as the plain solves of the same effects (`solve`)."""
        reqs = [(i, (SENSITIVITIES, tuple(n), tuple(s))) for (i, s), n in zip(requests, names_per_request)]
        out = self.solve(reqs)
        return [(skin, sens) for skin, sens, _ in out]

    def _unmet_of(self, r, unmet: dict) -> None:
        if unmet:
            self._unmet[self._key(r)] = dict(unmet)

    def contact_unmet(self, i: int, strings: tuple[str, ...] = ()) -> dict:
        """The contacts the solve of case `i` with the effects `strings` (default: the
        baseline) left deeper than twice their tolerance, {name: mm} ({} when met)."""
        return dict(self._unmet.get(self._key((i, tuple(strings))), {}))

    def baseline_displacement(self, i: int) -> np.ndarray | None:
        """The baseline's displacement field of case `i` (nodes, 3) once its tangent solve has
        run, else None: the start of the solves of nearby problems."""
        return self._guess.get(i)

    def start_from(self, i: int, displacement: np.ndarray) -> None:
        """Solve case `i`'s requests from `displacement` (a nearby problem's solution on the
        same mesh) instead of from rest."""
        self._guess[i] = np.asarray(displacement, float)

    def baseline(self, i: int) -> np.ndarray:
        skin = self.solve([(i, ())])[0]
        if isinstance(skin, str):
            raise SolveError(f"case {self.cases[i].name}: the baseline prediction failed: {skin}")
        return skin


def check_strings(strings: tuple[str, ...]) -> None:
    from planner.pipeline import parse_effects

    try:
        parse_effects(list(strings))
    except InputError as exc:     # the library built a value the pipeline refuses: a bug
        raise RuntimeError(f"effect values refused by the pipeline: {exc}") from exc
