"""Face simulation: a `FaceModel`, bone movements and muscle activations -> FE solve.

Turns the anatomical model into a problem of the generic solver, following Payan et al.'s
orthognathic-surgery face model (Chabanas, Luboz & Payan 2003; Nazari et al. 2010 for the
muscle and lip-contact set-up): every attachment node set "attach_<segment>" moves with its
bone segment's rigid motion (the skull stays fixed), ramped with the load fraction, but for the
tissue that bridges an osteotomy of the plan, tied to neither segment
(`facemodel.attachments.osteotomy_bridges`), and the tissue on the mandible's proximal segments
(ramus and angle), which a sagittal split leaves with the skull unless `proximal="moved"`
(`facemodel.attachments.attachment_sets`); the teeth
move with their segment and the lip mucosa cannot enter them (rigid contact); the upper and
lower lips cannot enter each other (two-pass deformable contact); each muscle label gets the
active transversely isotropic `solver.constitution.muscle.Muscle` law at its activation
(fibres from the model); segments named in `sliding` let their deep nodes slide on the moving
bone instead of being tied, and `sliding_nodes` lets chosen attached nodes slide (the tissue a
genioplasty degloves). A sliding node keeps its displacement along the bone's outward normal n
(the "deep_bone" facets' area-weighted normal at the node) equal to the bone's, u . n =
u_bone . n, and is free in the tangent plane (a `solver.bc.LocalFrame` condition, frictionless;
the linearisation of "stays on the bone surface": the plane translates with the bone but keeps
its reference orientation, off the exact surface by |u_t|^2 kappa / 2 for a tangential slide
u_t on a bone of curvature kappa, plus theta |u_t| for a bone rotation theta, e.g. 0.15 mm for a
3 mm slide on a 30 mm radius). `sliding_hold` h in [0, 1] makes the sliding segments' interface
resist the slide elastically (`solver.loads.TangentialSupport`: springs in the bone's tangent
plane, anchored to the moving bone): node i gets k_i = h / (1 - h) mu_i A_i / H_i, with A_i its
share of the deep bone facets' area, mu_i the initial shear modulus of the tissue around it and
H_i the soft tissue's thickness there (its distance to the skin), so that a layer of that
thickness sheared over the bone lets the interface take the share 1 - h of its surface's
tangential movement: h = 0 slides freely, h = 1 is tied (the tissue of a genioplasty's
degloving, `sliding_nodes`, slides freely whatever h). Contact-based sliding (`solver.contact.RigidSurfaceContact`,
bilateral) is exact on curved bone but its augmented re-solves cycled on the face. The static
equilibrium is solved by `solver.newton.newton_solve` (Q1/P0 hexahedra, Newton with line
search, load stepping, augmented Lagrangian contact).

The mesh ends at a cut through the neck (node set "neck", its inferior border row). By default
that cut is free (traction-free): the submental tissue hangs from the mandible's lower border
and follows it. `neck="held"` holds the cut in place instead, the tissue continuing down a
neck the operation does not move. The two bracket the truth (the hyoid and the tissue below
follow a mandibular move in part); `planner.diagnosis` uses their difference as a
model-uncertainty direction. The floor of the mouth (node set "floor_of_mouth", the free deep
surface under the mandible) is likewise free by default: the submental tissue rests on no
support. `floor="held"` holds it in place instead, as if tied to suprahyoid muscles and a hyoid
that the operation does not move; the tissue's deep side under the chin then stays while its
skin follows the mandible. The two bracket the floor of the mouth, which in a patient is
stretched between the advanced mandible and a hyoid that follows it only in part.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from facemodel.attachments import PROXIMAL, attachment_sets, bone_frames, segment_motion
from facemodel.errors import ModelInputError
from facemodel.materials import default_materials
from facemodel.model import FLOOR_CONDITIONS, MUSCLES, NECK_CONDITIONS, PROXIMAL_CONDITIONS
from facemodel.solver_settings import FACE_SOLVER
from solver.bc import LocalFrame, Prescribed
from solver.constitution.muscle import Muscle
from solver.contact import RigidSurfaceContact, SurfaceContact, TriangleSurface, ramped_rigid_motion
from solver.contact._geometry import triangulate
from solver.errors import SolveFailed
from solver.loads import BodyForce, TangentialSupport
from solver.mechanics import SolidBody, von_mises
from solver.mesh import HexMesh
from solver.newton import newton_solve

NECK_OWNER = "neck"          # the owner of the held cut's constraint: no segment moves it
FLOOR_OWNER = "floor"        # the owner of the held floor of the mouth's: likewise

__all__ = ["simulate", "build_problem", "held_boundaries", "moved_constraints", "SimulationResult",
           "MUSCLES", "NECK_CONDITIONS", "FLOOR_CONDITIONS", "PROXIMAL_CONDITIONS",
           "lip_penetrations", "rigid_motion_ok", "teeth_advance", "BoneInterface", "interface_stiffness"]

log = logging.getLogger("facemodel.simulation")

def rigid_motion_ok(T, tol: float = 1e-6) -> bool:
    """True if T is a finite 4x4 proper rigid motion."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (np.abs(R.T @ R - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1) < tol
            and np.allclose(T[3], [0, 0, 0, 1], atol=tol))


@dataclass
class SimulationResult:
    """Solved face: nodal fields, stresses, contact state and solver statistics."""

    x: np.ndarray                   # (n, 3) deformed nodal coordinates, mm
    displacement: np.ndarray        # (n, 3) mm
    cauchy: np.ndarray              # (m, 3, 3) element-averaged Cauchy stress, kPa
    von_mises: np.ndarray           # (m,) kPa
    volume_ratio: np.ndarray        # (m,) element v/V
    converged: bool
    load: float
    iterations: int
    steps: int
    time_s: float
    info: dict = field(default_factory=dict)
    newton: object = None           # solver.newton.NewtonResult
    terms: dict = field(default_factory=dict)
    problem: tuple = ()             # (SolidBody, constraints, terms) as solved, for sensitivities


def _typical_size(X, facets):
    if not len(facets):
        return 1.0
    p = X[facets]
    e = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    return float(np.median(e))


def _local_shear_modulus(model, by_label, facets) -> float:
    """Median initial shear modulus of the elements touching the given facets' nodes."""
    facets = np.asarray(facets, dtype=np.int64)
    touch = np.zeros(len(model.nodes), dtype=bool)
    touch[facets.ravel()] = True
    hexes = np.asarray(model.hexes)
    near = np.nonzero(touch[hexes].any(axis=1))[0]
    mus = np.array([_shear_modulus(by_label[int(l)]) for l in np.asarray(model.labels)[near]])
    return float(np.median(mus)) if len(mus) else 5.0


class BoneInterface(TangentialSupport):
    """The elastic interface of tissue sliding on a bone segment (module text): a
    `TangentialSupport` anchored to the segment's ramped rigid motion. `segment` names it and
    setting `motion` (4x4) re-anchors it, as a rigid teeth arch is moved
    (`planner.pipeline.effect_sensitivities`)."""

    def __init__(self, nodes, normals, stiffness, reference, motion, segment: str):
        super().__init__(nodes, normals, stiffness, None, reference)
        self.segment = segment
        self.motion = motion

    @property
    def motion(self):
        return self._motion

    @motion.setter
    def motion(self, T):
        self._motion = np.asarray(T, dtype=float)
        self.anchor = _rigid_displacement(self.X[self.nodes], self._motion)


def interface_stiffness(model, by_label, nodes) -> np.ndarray:
    """mu_i A_i / H_i (mN/mm) at deep bone nodes (module text): A_i a quarter of the area of
    each "deep_bone" facet at the node, mu_i the median initial shear modulus of the elements
    around it, H_i its distance to the nearest skin node (at least 1 mm)."""
    from scipy.spatial import cKDTree

    nodes = np.asarray(nodes, dtype=np.int64)
    X = np.asarray(model.nodes, dtype=float)
    F = np.asarray(model.facet_sets.get("deep_bone", np.zeros((0, 4))), dtype=np.int64)
    p = X[F]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)
    A = np.bincount(F.ravel(), np.repeat(area / 4.0, 4), minlength=len(X))[nodes]
    skin = np.asarray(model.node_sets["skin"], dtype=np.int64)
    H = np.maximum(cKDTree(X[skin]).query(X[nodes])[0], 1.0)
    hexes = np.asarray(model.hexes, dtype=np.int64)
    labels = np.asarray(model.labels, dtype=np.int64)
    mu_label = {li: _shear_modulus(m) for li, m in by_label.items()}
    mu_elem = np.array([mu_label.get(int(l), 5.0) for l in labels])
    row = np.full(len(X), -1, np.int64)
    row[nodes] = np.arange(len(nodes))
    e, a = np.nonzero(row[hexes] >= 0)
    return _median_per_node(row[hexes[e, a]], mu_elem[e], len(nodes), 5.0) * A / H


def _median_per_node(rows: np.ndarray, values: np.ndarray, n: int, empty: float) -> np.ndarray:
    """The median of `values` grouped by `rows` (0..n-1), `empty` where a row has none: the
    values sorted within their rows, the middle one (the mean of the two middle ones for an
    even count), as np.median of each group."""
    order = np.lexsort((values, rows))
    v = np.asarray(values, float)[order]
    count = np.bincount(rows, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    out = np.full(n, float(empty))
    has = count > 0
    lo, hi = start[has] + (count[has] - 1) // 2, start[has] + count[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out


def _shear_modulus(mat) -> float:
    mu = getattr(mat, "shear_modulus", None)
    if mu is not None:
        return float(mu)
    p = getattr(mat, "parameters", {})
    for k in ("C10",):
        if k in p:
            return 2.0 * float(p[k][0] if isinstance(p[k], tuple) else p[k])
    return 5.0


def held_boundaries(model, attach: dict, *, neck: str = "free", floor: str = "free") -> list:
    """[(owner, node ids)] of the boundaries held in place (module text): "neck" for
    `neck="held"`, "floor" for `floor="held"`. Nodes no bone moves: the attached ones of
    `attach` {segment: ids} keep their bone's motion, and a node both sets hold is held once
    (by the neck). Raises `ModelInputError` for a condition it does not know or a model
    without the node set."""
    tied_ids = np.concatenate([np.asarray(v, dtype=np.int64) for v in attach.values()]
                              or [np.zeros(0, np.int64)])
    out = []
    for option, value, conditions, set_name, owner, what in (
            ("neck", neck, NECK_CONDITIONS, "neck", NECK_OWNER, "its inferior border"),
            ("floor", floor, FLOOR_CONDITIONS, "floor_of_mouth", FLOOR_OWNER,
             "the free deep surface under the mandible")):
        if value not in conditions:
            raise ModelInputError(f"{option} must be one of {', '.join(conditions)}, got {value!r}")
        if value != "held":
            continue
        if set_name not in model.node_sets:
            raise ModelInputError(f"{option}: held asked for, but the face model has no node set "
                                  f"{set_name!r} ({what})")
        held = np.setdiff1d(np.asarray(model.node_sets[set_name], dtype=np.int64), tied_ids)
        if len(held):
            out.append((owner, held))
            tied_ids = np.union1d(tied_ids, held)
    return out


def build_problem(model, motions=None, activations=None, *, contact=True, sliding=(),
                  sliding_nodes=None, materials=None, growth=None, body_force=None,
                  penalty_factor=1.0, contact_tolerance=0.05, neck="free", lip_penalty=None,
                  uzawa_schedule="carried", floor="free", proximal="seated", sliding_hold=0.0):
    """The FE problem `simulate` solves: (SolidBody, constraints, contact terms {name: term},
    other terms [body force], lip facet size or None); arguments as `simulate`'s. The body's
    `constraint_segments` names the segment each constraint follows, its `proximal_nodes` counts
    the attached nodes a sagittal split leaves with the skull, its `bridge_nodes` counts
    the attached nodes released as osteotomy bridges. lip_penalty: factor on
    the lip-lip penalty (None: `FACE_SOLVER.lip_penalty`); uzawa_schedule: the contact terms'
    augmentation schedule (`solver.contact._uzawa.UzawaLoop`)."""
    lip_penalty = FACE_SOLVER.lip_penalty if lip_penalty is None else float(lip_penalty)
    motions = dict(motions or {})
    activations = dict(activations or {})
    segments = tuple(model.segments)
    for seg, T in motions.items():
        if seg not in segments:
            raise ModelInputError(f"unknown bone segment {seg!r} (segments: {', '.join(segments)})")
        if not rigid_motion_ok(T):
            raise ModelInputError(f"the motion of segment {seg!r} is not a 4x4 rigid transform")
    names = tuple(model.label_names)
    for m, a in activations.items():
        if m not in names:
            raise ModelInputError(f"unknown muscle {m!r} (labels: {', '.join(names)})")
        if not (np.isfinite(a) and 0.0 <= a <= 1.0):
            raise ModelInputError(f"activation of {m!r} must be in [0, 1], got {a}")
    sliding = tuple(sliding or ())
    for seg in sliding:
        if seg not in segments:
            raise ModelInputError(f"cannot slide on unknown segment {seg!r}")
    hold = float(sliding_hold)
    if not (np.isfinite(hold) and 0.0 <= hold <= 1.0):
        raise ModelInputError(f"sliding_hold must be in [0, 1], got {sliding_hold}")
    if hold >= 1.0:
        sliding = ()                    # an interface that holds fully is tied

    X = np.asarray(model.nodes, dtype=float)
    labels = np.asarray(model.labels, dtype=np.int64)
    table = default_materials(model) if materials is None else dict(materials)
    by_label = {}
    for li, name in enumerate(names):
        if not np.any(labels == li):
            continue
        if name not in table:
            raise ModelInputError(f"no material for tissue label {name!r}")
        mat = table[name]
        a = float(activations.get(name, 0.0))
        if isinstance(mat, Muscle):
            mat = mat.with_activation(a)
        elif a > 0:
            raise ModelInputError(f"label {name!r} has activation {a} but no active material")
        by_label[li] = mat
    fibres = getattr(model, "fibres", None)
    body = SolidBody(HexMesh(X, model.hexes, labels), by_label,
                     fibres=None if fibres is None else np.asarray(fibres, dtype=float),
                     growth=growth)

    # --- essential conditions: attachments tied to their bone (sliding ones excepted)
    attach = attachment_sets(model, motions, proximal=proximal)     # validates `proximal`
    constraints, terms = [], {}
    owners = []                                     # the segment each constraint follows
    sliding_nodes = dict(sliding_nodes or {})
    for seg in sliding_nodes:
        if seg not in segments:
            raise ModelInputError(f"cannot slide on unknown segment {seg!r}")
    on_bone = np.zeros(len(X), dtype=bool)          # nodes of the deep facets on the bone
    on_bone[np.asarray(model.facet_sets.get("deep_bone", np.zeros((0, 4))), dtype=np.int64)] = True
    extra = []
    for seg, ids in attach.items():
        T = segment_motion(motions, seg)
        degloved = np.intersect1d(np.asarray(sliding_nodes.get(seg, ()), dtype=np.int64), ids)
        glide = degloved
        if seg in sliding:
            # the whole segment: every attached node on its bone surface slides
            glide = np.union1d(glide, ids[on_bone[ids]])
        tied = np.setdiff1d(ids, glide)
        if len(glide):
            frames = bone_frames(model, glide)
            constraints.append(LocalFrame(glide, frames, fixed=(0,),
                                          displacement=_rigid_displacement(X[glide], T)))
            owners.append(seg)
            held = ~np.isin(glide, degloved)
            if seg in sliding and hold > 0.0 and held.any():
                k = hold / (1.0 - hold) * interface_stiffness(model, by_label, glide[held])
                extra.append(BoneInterface(glide[held], frames[held, 0], k, X, T, seg))
        if len(tied):
            constraints.append(Prescribed(tied, _rigid_displacement(X[tied], T)))
            owners.append(seg)
    for owner, held in held_boundaries(model, attach, neck=neck, floor=floor):
        constraints.append(Prescribed(held, 0.0))
        owners.append(owner)

    # --- contact: lips against each other, lip mucosa against the teeth
    lip_size = None
    if contact:
        fs = model.facet_sets
        up = np.asarray(fs.get("lip_upper_contact", np.zeros((0, 4))), dtype=np.int64)
        lo = np.asarray(fs.get("lip_lower_contact", np.zeros((0, 4))), dtype=np.int64)
        if not (len(up) and len(lo)):
            raise ModelInputError("contact asked for, but the model has no lip contact surfaces "
                                  "(facet sets lip_upper_contact and lip_lower_contact); "
                                  "solve with contact=False to go without lip contact")
        h = lip_size = _typical_size(X, np.vstack([up, lo]))
        mu = _local_shear_modulus(model, by_label, np.vstack([up, lo]))
        terms["lip_contact"] = SurfaceContact(
            X, up, lo, penalty=penalty_factor * lip_penalty * 3.0 * mu / h,
            tolerance=contact_tolerance, uzawa_schedule=uzawa_schedule,
            search_radius=max(1.0, h), max_depth=max(2.0, h),
            pair_hysteresis=FACE_SOLVER.pair_hysteresis,
            edge_release=FACE_SOLVER.lip_edge_release,
            crease_blend=FACE_SOLVER.lip_crease_blend)
        mucosa = [np.asarray(fs[k], dtype=np.int64) for k in ("lip_upper_teeth", "lip_lower_teeth")
                  if k in fs and len(fs[k])]
        if mucosa:
            mucosa = np.vstack(mucosa)
            h = _typical_size(X, mucosa)
            mu = _local_shear_modulus(model, by_label, mucosa)
            for name, (V, F, seg) in dict(getattr(model, "teeth", {}) or {}).items():
                terms[f"teeth_{name}"] = RigidSurfaceContact(
                    X, np.asarray(V, float), np.asarray(F, np.int64), slave_facets=mucosa,
                    motion=segment_motion(motions, seg),
                    penalty=penalty_factor * 3.0 * mu / h, tolerance=contact_tolerance,
                    search_radius=max(2.0, h), max_depth=max(3.0, 1.5 * h), smooth=True,
                    tangent="projected", uzawa_schedule=uzawa_schedule)
                terms[f"teeth_{name}"].segment = seg     # the segment whose motion it follows

    if body_force is not None:
        extra.append(BodyForce(X, model.hexes, body_force))
    body.constraint_segments = tuple(owners)
    listed = np.unique(np.concatenate([np.asarray(model.node_sets.get("attach_" + s, ()), np.int64)
                                       for s in segments] or [np.zeros(0, np.int64)]))
    body.bridge_nodes = int(len(listed) - sum(len(v) for v in attach.values()))
    body.proximal_nodes = int(len(attach.get(PROXIMAL, ())))
    return body, constraints, terms, extra, lip_size


def moved_constraints(X, constraints, owners, motions) -> list:
    """The constraints of `build_problem` with each segment's rigid motion replaced by
    `motions[segment]` (segments not in `motions` keep theirs)."""
    import dataclasses

    out = []
    for c, seg in zip(constraints, owners):
        if seg in motions:
            c = dataclasses.replace(c, displacement=_rigid_displacement(X[c.nodes], motions[seg]))
        out.append(c)
    return out


def simulate(model, motions: dict | None = None, activations: dict | None = None, *,
             contact: bool = True, sliding=(), sliding_nodes: dict | None = None,
             materials: dict | None = None, growth=None, body_force=None,
             n_steps: int = 4, log=None, penalty_factor: float = 1.0,
             contact_tolerance: float = 0.05, max_iterations: int = 25,
             guess=None, max_seconds: float | None = None, neck: str = "free",
             floor: str = "free", proximal: str = "seated", sliding_hold: float = 0.0) -> SimulationResult:
    """Solve the face for bone `motions` {segment: 4x4} and muscle `activations` {muscle: a}.

    contact: lip-lip and lip-teeth contact on/off. sliding: segments whose deep nodes slide
    on their bone surface instead of being tied. sliding_nodes: {segment: node ids} attached
    nodes that slide on that segment's bone (normal displacement with the bone, tangential free:
    a `LocalFrame` in `facemodel.attachments.bone_frames`) while its other nodes stay tied (the
    tissue a genioplasty degloves, `facemodel.attachments.genioplasty_sliding`).
    materials: {label name: Material} replacing the defaults (muscle labels may give any
    material; a `Muscle` gets its activation).
    growth: volumetric growth ratio per element (m,) (swelling, `facemodel.effects.growth_field`;
    the solver's F = F_e theta^(1/3) I). body_force: (3,) dead body-force density in mN/mm^3
    (gravity, `facemodel.effects.gravity_density`), ramped with the load.
    n_steps: initial number of load steps. log: optional callable receiving one text line per
    Newton iteration. penalty_factor: contact penalty eps = factor * 3 mu / h (mu the
    median shear modulus of the tissue at the contact surface, h its median facet edge). contact_tolerance:
    largest lip/teeth penetration accepted (mm). guess: the displacement field (n, 3) of a
    nearby solution on this model (the same case with other effect values): the full load is
    solved from it first, the load stepped only if that fails (`solver.newton.newton_solve`).
    max_seconds: the solve's wall-clock budget (`SolverControl.max_seconds`; None: none),
    shared with the soft-contact fallbacks below (`FaceSolverSettings.fallback_budget_share`).
    neck: "free" (default) or "held", the boundary condition of the neck cut (module text);
    floor: likewise, of the floor of the mouth (node set "floor_of_mouth"). proximal:
    "seated" (default) or "moved", the mandible's proximal segments when the mandible moves
    (`facemodel.attachments.attachment_sets`). sliding_hold: the sliding segments' interface, 0 (free,
    default) to 1 (tied) (module text).
    Raises `facemodel.errors.ModelInputError` (a
    ValueError) for motions, activations, materials or model parts it cannot use (contact
    asked of a model without lip contact surfaces) and `solver.errors.SolveFailed` if Newton
    fails. A solve with lip contact that fails is made again with the softer lip-lip contacts
    of `FaceSolverSettings.fallback_lip_penalties` in turn (the final load at the penalty
    solution) before the first failure is raised; `info["contact_fallback"]` says when such an
    answer is returned.
    """
    def problem(**contact_options):
        return build_problem(
            model, motions, activations, contact=contact, sliding=sliding, sliding_nodes=sliding_nodes,
            materials=materials, growth=growth, body_force=body_force, penalty_factor=penalty_factor,
            contact_tolerance=contact_tolerance, neck=neck, floor=floor, proximal=proximal,
            sliding_hold=sliding_hold, **contact_options)

    body, constraints, terms, extra, lip_size = problem()
    X = np.asarray(model.nodes, dtype=float)
    labels = np.asarray(model.labels, dtype=np.int64)
    activations = dict(activations or {})
    sliding = tuple(sliding or ())

    def callback(rec):
        if log is not None:
            log(f"step {rec['step']} load {rec['load']:.3f} it {rec['iteration']} "
                f"|R| {rec['residual_norm']:.3e} (rel {rec['relative_residual']:.2e}) "
                f"|du| {rec['displacement_norm']:.3e} ls {rec['line_search']:.2g}")

    t0 = time.perf_counter()
    # the increment limit of the contact nodes: not below a fraction of the teeth's advance in
    # the first load step (`FaceSolverSettings.max_increment`), whatever the lip facets' size
    teeth = any(isinstance(t, RigidSurfaceContact) for t in terms.values())
    advance = teeth_advance(model, motions, 1.0 / max(int(n_steps), 1)) if teeth else 0.0

    def solve(body, constraints, terms, extra, lip_size, seconds):
        control = FACE_SOLVER.control(n_steps, max_iterations, _contact_nodes(terms), lip_size, advance)
        if seconds is not None:
            control = replace(control, max_seconds=float(seconds))
        return newton_solve(body, constraints, list(terms.values()) + extra, control=control,
                            callback=callback, guess=None if guess is None else X + np.asarray(guess, float))

    fallback = None
    factors = tuple(FACE_SOLVER.fallback_lip_penalties or ()) if "lip_contact" in terms else ()

    def budget(last: bool, first: bool = False):
        # each attempt but the last gets a share of what is left (`fallback_budget_share`);
        # the first has the whole budget ahead of it
        if max_seconds is None:
            return None
        left = max_seconds - (0.0 if first else time.perf_counter() - t0)
        return left if last else FACE_SOLVER.fallback_budget_share * left

    try:
        res = solve(body, constraints, terms, extra, lip_size, budget(not factors, first=True))
    except SolveFailed as failure:
        # typically a final lip contact state the augmentations cannot reach (the stomion
        # corner pinched between the incisors and the other lip: docs/solver_control.md); any
        # failure with lip contact is solved again with the softer lip-lip penalties of
        # `FaceSolverSettings.fallback_lip_penalties` in turn, the final load left at the
        # penalty solution ("carried_penalty"); the penetration that leaves is reported
        # (contact_unmet_mm) and so is the fallback. Failing every one, the first failure stands.
        attempts = []
        for n, f in enumerate(factors):
            left = budget(n == len(factors) - 1)
            if left is not None and left <= 0.0:
                break
            factor = f * FACE_SOLVER.lip_penalty
            logging.getLogger("facemodel.simulation").warning(
                "the face solve failed (%s); solving again with the lip-lip penalty x %g, the final "
                "contact state left at its penalty solution", attempts[-1]["reason"] if attempts else failure,
                factor)
            problem_fb = problem(lip_penalty=factor, uzawa_schedule="carried_penalty")
            try:
                res = solve(*problem_fb, left)
            except SolveFailed as again:
                attempts.append({"lip_penalty_factor": factor, "reason": str(again),
                                 "failed_at_load": float(again.load)})
                continue
            body, constraints, terms, extra, lip_size = problem_fb
            fallback = {"reason": str(failure), "failed_at_load": float(failure.load),
                        "last_converged_load": float(failure.last_converged_load),
                        "lip_penalty_factor": factor, "uzawa_schedule": "carried_penalty",
                        "softer_attempts_failed": attempts}
            break
        if fallback is None:        # every softer solve failed, or the time budget ran out
            raise failure from None
    elapsed = time.perf_counter() - t0
    x = res.x
    sig = body.cauchy_stress(x, 1.0)
    vm = von_mises(sig)
    info = {"n_nodes": len(X), "n_elements": len(labels), "n_constrained_nodes":
            int(sum(len(c.nodes) for c in constraints)), "terms": list(terms),
            "activations": activations, "sliding": list(sliding),
            "cutbacks": res.cutbacks, "factorizations": res.factorizations,
            "convexified_updates": res.convexified, "blowups_halved": res.blowups_halved,
            "continuation_from_load": res.continuation_from,
            "continuation_iterations": res.continuation_iterations,
            "krylov_iterations": res.krylov_iterations, "timings": res.timings,
            "guess": res.guess, "contact_fallback": fallback,
            "osteotomy_bridge_nodes": body.bridge_nodes, "proximal_segment_nodes": body.proximal_nodes}
    if contact:
        info["penetration_mm"] = {k: float(t.penetration(x)) for k, t in terms.items()}
        # the augmentations are bounded (`AugmentedLagrangian.max_augmentations`): a solve
        # whose last one left a contact deeper than the tolerance converged, but not to the
        # contact state asked for. Twice the tolerance is the margin: the term's final search
        # can pair a node other than its frozen solve did (docs/solver_control.md)
        info["contact_tolerance_mm"] = float(contact_tolerance)
        info["contact_unmet_mm"] = {k: v for k, v in info["penetration_mm"].items()
                                    if v > 2.0 * contact_tolerance}
        if "lip_contact" in terms:
            # lips overlapping before any movement (a registered mesh can have them so) are
            # left as they are; contact acts against further penetration only
            info["initial_lip_overlap_mm"] = float(terms["lip_contact"].initial_penetration)
    log_ = logging.getLogger("facemodel.simulation")
    log_.info("face solved in %.1f s, %d iterations", elapsed, res.iterations)
    return SimulationResult(x=x, displacement=x - X, cauchy=sig, von_mises=vm,
                            volume_ratio=body.volume_ratio(x), converged=bool(res.converged),
                            load=float(res.load), iterations=int(res.iterations),
                            steps=len(res.steps), time_s=elapsed, info=info, newton=res,
                            terms=terms, problem=(body, constraints, list(terms.values()) + extra))


def _contact_nodes(terms):
    """Slave nodes of the contact terms (lip surfaces, lip mucosa), or None without contact."""
    out = []
    for t in terms.values():
        if isinstance(t, SurfaceContact):
            out += [ps.slaves for ps in t.passes]
        else:
            out.append(t.slaves)
    return np.unique(np.concatenate(out)) if out else None


def teeth_advance(model, motions: dict | None, load: float) -> float:
    """The largest displacement (mm) of a tooth vertex of `model.teeth` at load fraction
    `load` under its segment's ramped rigid motion in `motions` (0 without teeth): how far
    the teeth, rigid contact surfaces, advance into the lip mucosa over that load."""
    out = 0.0
    for V, _, seg in dict(getattr(model, "teeth", {}) or {}).values():
        V = np.asarray(V, dtype=float)
        T = ramped_rigid_motion(segment_motion(dict(motions or {}), seg), load)
        d = V @ T[:3, :3].T + T[:3, 3] - V
        out = max(out, float(np.sqrt(np.einsum("ij,ij->i", d, d).max(initial=0.0))))
    return out


def _rigid_displacement(Xs, T):
    """Callable load -> (k, 3) displacement of points Xs under the ramped rigid motion."""
    T = np.asarray(T, dtype=float)

    def disp(load):
        Tl = ramped_rigid_motion(T, load)
        return Xs @ Tl[:3, :3].T + Tl[:3, 3] - Xs
    return disp


def lip_penetrations(model, x, load: float = 1.0, motions: dict | None = None,
                     band: float = 3.0) -> dict:
    """Independent check of a solved face: deepest penetration (mm, >= 0) of
    the lower-lip nodes into the upper lip and vice versa (closest point with pseudo-normal
    sign on the current lip surfaces), and of the lip mucosa nodes into each moved teeth
    surface; nodes deeper than `band` (other side of a thin surface) are not counted."""
    x = np.asarray(x, dtype=float)
    out = {}
    fs = model.facet_sets
    pairs = [("lower_in_upper", "lip_lower_contact", "lip_upper_contact"),
             ("upper_in_lower", "lip_upper_contact", "lip_lower_contact")]
    for key, slave, master in pairs:
        if slave in fs and master in fs and len(fs[slave]) and len(fs[master]):
            surf = TriangleSurface(x, triangulate(fs[master]))
            nodes = np.setdiff1d(np.unique(fs[slave]), np.unique(fs[master]))
            out[key] = _depth(surf, x[nodes], band)
    mucosa = [np.asarray(fs[k]) for k in ("lip_upper_teeth", "lip_lower_teeth") if k in fs]
    if mucosa:
        nodes = np.unique(np.vstack(mucosa))
        for name, (V, F, seg) in dict(getattr(model, "teeth", {}) or {}).items():
            T = ramped_rigid_motion(segment_motion(motions or {}, seg), load)
            Vm = np.asarray(V, float) @ T[:3, :3].T + T[:3, 3]
            out[f"in_teeth_{name}"] = _depth(TriangleSurface(Vm, F), x[nodes], band)
    return out


def _depth(surf, pts, band):
    """Deepest point (mm) behind the surface, not counting points whose closest feature is
    on the boundary of an open surface (those are beside it, not inside)."""
    idx, c, face, region, dist = surf.closest(pts, band)
    if not len(idx):
        return 0.0
    F = surf.faces
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, inv, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    edge_open = (counts == 1)[inv.ravel()].reshape(3, len(F)).T          # (q, 3): ab, bc, ca
    vert_open = np.zeros(len(surf.vertices), dtype=bool)
    vert_open[uniq[counts == 1].ravel()] = True
    on_border = np.zeros(len(idx), dtype=bool)
    for r, k in ((1, 0), (2, 1), (3, 2)):                                # vertices a, b, c
        m = region == r
        on_border[m] = vert_open[F[face[m], k]]
    for r, k in ((4, 0), (5, 1), (6, 2)):                                # edges ab, bc, ca
        m = region == r
        on_border[m] = edge_open[face[m], k]
    pn = surf.pseudo_normal(face, region)
    s = np.einsum("ij,ij->i", pts[idx] - c, pn)
    inside = (s < 0) & (dist < band) & ~on_border
    return float(dist[inside].max()) if np.any(inside) else 0.0
