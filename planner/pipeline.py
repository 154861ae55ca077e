"""From a case folder and its plan to a predicted face: the faceplan prediction pipeline.

Stages (Payan et al., "Facial soft-tissue prediction in orthognathic surgery" method): load the
case and the plan -> Mesh-Match-and-Repair of the generic face mesh onto the patient (cached by
input hash, reused on re-runs) -> assignment of the attachment nodes to the patient's bone
segments (`planner.segments`) -> the plan's rigid segment movements imposed on the attached nodes
(tied, or sliding on the bone as an option), teeth moved with their segments, muscles at the
plan's activations, lip contact on; for a genioplasty (the chin segment moved on the mandible)
the tissue the operation degloves slides on its bone instead of being tied
(`facemodel.attachments.genioplasty_sliding`: the anterior mandible between the vestibule and
the osteotomy and the chin segment's anterior face; the pedicle on the chin's inferior border
stays tied) -> nonlinear FE solve (`facemodel.simulation.simulate`, load
steps with a convergence log) -> outputs written into a temporary folder and moved into place
only when complete (`planner.atomic`): `prediction.vtu`, `skin_predicted.{stl,ply,vtp}` (the model's
skin patch), the predicted whole face `face_predicted.{glb,obj}`, `landmarks_predicted.mrk.json`,
`model.feb` (`planner.export`), renders of the whole face, `report.json` and `report.html`.
Solver failures become `SolveError` (exit 3), bad input `InputError` (exit 2).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from planner import report as rep
from planner.errors import InputError, SolveError
from planner.plan import EFFECTS, Plan, check_against_bones, load_plan
from planner.segments import as_trimesh, assign_segments, with_segments
from solver.mechanics import von_mises

# Effects `--effect NAME=VALUE` can add to a prediction, and how each maps onto the model.
# sliding: 0/1 (1: the soft tissue slides on every moved bone segment); muscle_tone: resting activation of the
# perioral muscles in [0, 1]; stiffness: factor on every tissue's stiffness parameters.
SUPPORTED_EFFECTS = ("sliding", "muscle_tone", "stiffness")
# muscle_tone: the resting tone of the lip sphincter and the chin/lower-lip muscles.
TONE_MUSCLES = ("orbicularis_oris", "mentalis", "depressor_labii_inferioris")


def parse_effects(items: list[str] | None) -> dict[str, float]:
    """`NAME=VALUE` strings (VALUE defaults to 1) -> {name: value}; InputError if unknown."""
    out = {}
    for item in items or []:
        name, _, value = item.partition("=")
        name = name.strip()
        if name not in EFFECTS:
            raise InputError(f"unknown effect {name!r} (known: {', '.join(EFFECTS)})", field="--effect")
        if name not in SUPPORTED_EFFECTS:
            raise InputError(f"effect {name!r} is not available in predictions yet "
                             f"(available: {', '.join(SUPPORTED_EFFECTS)})", field="--effect")
        try:
            v = float(value) if value.strip() else 1.0
        except ValueError:
            raise InputError(f"effect {name}: value must be a number, got {value!r}", field="--effect") from None
        if not np.isfinite(v):
            raise InputError(f"effect {name}: value must be finite", field="--effect")
        if name in ("sliding", "muscle_tone") and not 0.0 <= v <= 1.0:
            raise InputError(f"effect {name}: value must be in [0, 1], got {v:g}", field="--effect")
        if name == "stiffness" and not 0.1 <= v <= 10.0:
            raise InputError(f"effect stiffness: factor must be in [0.1, 10], got {v:g}", field="--effect")
        out[name] = v
    return out


def check_effects(plan: Plan, effects: dict[str, float] | None = None) -> dict[str, float]:
    """The plan's effects overridden by the command line's; InputError for one not available."""
    for name, value in plan.model.effects.items():
        if name not in SUPPORTED_EFFECTS:
            raise InputError(f"effect {name!r} is not available in predictions yet "
                             f"(available: {', '.join(SUPPORTED_EFFECTS)})", file=plan.path,
                             field=f"model.effects.{name}")
        try:
            parse_effects([f"{name}={value}"])
        except InputError as exc:
            raise InputError(str(exc).split(": ", 1)[-1], file=plan.path, field=f"model.effects.{name}") from None
    return dict(plan.model.effects, **(effects or {}))


class Progress:
    """Stage timings and a one-line-per-event progress display on stderr."""

    def __init__(self, echo: bool | Callable[[str], None] = True):
        self.timings: dict[str, float] = {}
        self.log: list[str] = []
        self._echo = echo
        self._t0 = time.perf_counter()

    def say(self, message: str) -> None:
        line = f"[{time.perf_counter() - self._t0:6.1f} s] {message}"
        self.log.append(line)
        if callable(self._echo):
            self._echo(line)
        elif self._echo:
            print(line, file=sys.stderr, flush=True)

    def stage(self, name: str):
        progress = self

        class _Stage:
            def __enter__(self):
                progress.say(f"{name} ...")
                self.t = time.perf_counter()
                return self

            def __exit__(self, exc_type, exc, tb):
                dt = time.perf_counter() - self.t
                progress.timings[name] = progress.timings.get(name, 0.0) + dt
                if exc_type is None:
                    progress.say(f"{name} done in {dt:.2f} s")
                return False

        return _Stage()


@dataclass
class Prediction:
    """A solved prediction on a patient model."""

    model: object                         # patient FaceModel with attachment sets per segment
    plan: Plan
    displacement: np.ndarray              # (n, 3) mm
    stress: np.ndarray | None             # (m, 3, 3) Cauchy stress per element, kPa, if given
    solver: dict
    bone_vertices: dict[str, np.ndarray] = field(default_factory=dict)
    assignment: dict = field(default_factory=dict)
    effects: dict[str, float] = field(default_factory=dict)

    @property
    def predicted_nodes(self) -> np.ndarray:
        return np.asarray(self.model.nodes, float) + self.displacement


# --------------------------------------------------------------------------- model options

def face_materials(model, overrides: dict[str, dict[str, float]] | None = None, stiffness: float = 1.0):
    """Solver materials per tissue label from the default table (`facemodel.materials`: Yeoh for
    passive tissue, the active transversely isotropic `Muscle` for muscles), with the plan's
    parameter overrides and the `stiffness` effect (a factor on every modulus, active stress
    excepted, as `facemodel.materials.parameters` defines it)."""
    from facemodel import materials as fm

    overrides = overrides or {}
    for label in overrides:
        if label not in model.label_names:
            raise InputError(f"unknown tissue label {label!r} (labels: {', '.join(model.label_names)})",
                             field=f"model.materials.{label}")
    out = {}
    for label in model.label_names:
        params = dict(fm.parameters(label, stiffness))
        for k, v in overrides.get(label, {}).items():
            if k not in params:
                raise InputError(f"material {label!r} has no parameter {k!r} "
                                 f"(parameters: {', '.join(params)})", field=f"model.materials.{label}.{k}")
            params[k] = v
        try:
            out[label] = fm.solver_material(label, params)
        except (TypeError, ValueError) as exc:
            raise InputError(f"material {label!r}: {exc}", field=f"model.materials.{label}") from None
    return out


def _sliding_sets(model, segments: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(s for s in segments if len(model.node_sets.get("attach_" + s, ())) > 0)


# --------------------------------------------------------------------------- solve

def _call_simulate(model, motions, *, activations, contact, sliding, materials, progress: Progress,
                   sliding_nodes=None):
    """`facemodel.simulation.simulate` with every Newton iteration sent to the progress log."""
    from facemodel.simulation import simulate

    return simulate(model, motions, activations, contact=contact, sliding=sliding,
                    sliding_nodes=sliding_nodes, materials=materials, log=progress.say)


def _unpack_result(result, model) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """(displacement (n, 3), element Cauchy stress (m, 3, 3), solver statistics) of a
    `facemodel.simulation.SimulationResult`."""
    u = np.asarray(result.displacement, float).reshape(len(model.nodes), 3)
    stress = None if result.cauchy is None else np.asarray(result.cauchy, float)
    stats = {"converged": bool(result.converged), "load": float(result.load),
             "iterations": int(result.iterations), "steps": int(result.steps),
             "time_s": round(float(result.time_s), 3), "info": _jsonable(result.info)}
    return u, stress, stats


def _jsonable(v, depth=0):
    if depth > 4:
        return str(v)
    if isinstance(v, dict):
        return {str(k): _jsonable(x, depth + 1) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x, depth + 1) for x in v][:1000]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist(), depth + 1) if v.size <= 1000 else f"array{v.shape}"
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, (int, float, str, bool)) or v is None:
        return v
    if dataclasses.is_dataclass(v):
        return _jsonable(dataclasses.asdict(v), depth + 1)
    return str(v)


def solve_plan(model, plan: Plan, bones: dict | None = None, *, effects: dict[str, float] | None = None,
               progress: Progress | None = None) -> Prediction:
    """Assign attachments, impose the plan's movements and solve. `bones`: surfaces by name."""
    progress = progress or Progress(echo=False)
    effects = check_effects(plan, effects)
    bone_vertices = {k: np.asarray(as_trimesh(v).vertices, float) for k, v in (bones or {}).items()}
    assignment = {}
    if bones:
        with progress.stage("segments"):
            check_against_bones(plan, bone_vertices)
            a = assign_segments(model, bones, plan)
            model = with_segments(model, a)
            assignment = a.summary()
            for seg, s in assignment.items():
                progress.say(f"  {seg}: {s['nodes']} attachment nodes (median {s['median_distance_mm']} mm from bone)")
    sliding = tuple(plan.model.sliding)
    if effects.get("sliding", 0.0) >= 0.5:     # the effect: tissue slides on every moved segment
        sliding = tuple(n for n, m in plan.motions().items())
    sliding = _sliding_sets(model, sliding)
    activations = dict(plan.muscles)
    tone = effects.get("muscle_tone", 0.0)
    if tone > 0:
        for m in TONE_MUSCLES:
            if m in model.label_names:
                activations[m] = max(activations.get(m, 0.0), tone)
    materials = face_materials(model, plan.model.materials, effects.get("stiffness", 1.0))
    from facemodel.errors import ModelInputError
    from solver import errors as solver_errors

    teeth_shift = {}
    if plan.model.contact and getattr(model, "teeth", None):
        # Contact must start without penetration: after registration some lip nodes can lie
        # inside the rigid arches; each arch is moved back by the measured depth
        # (`facemodel.teeth.clear_teeth`), reported.
        from facemodel.teeth import clear_teeth

        try:
            model, teeth_shift = clear_teeth(model)
        except ValueError as exc:
            raise SolveError(f"lip/teeth contact cannot start: {exc}") from exc
        moved = {k: round(v, 3) for k, v in teeth_shift.items() if v > 0}
        if moved:
            progress.say(f"  teeth moved back to start contact clear of the lips (mm): {moved}")
    motions = plan.motions(include_identity=True)
    # a genioplasty degloves the anterior mandible and chin: that tissue slides on its bone
    # (segments that slide as a whole, `sliding`, keep their own treatment)
    from facemodel.attachments import genioplasty_sliding

    degloved = {s: ids for s, ids in genioplasty_sliding(model, motions).items() if s not in sliding}
    if degloved:
        progress.say("  genioplasty: degloved tissue slides on the bone ("
                     + ", ".join(f"{s} {len(ids)} nodes" for s, ids in degloved.items()) + ")")
    moving = {k: m for k, m in motions.items() if not np.allclose(m, np.eye(4), atol=1e-12)}
    if not moving and not any(a > 0 for a in activations.values()):
        # No bone moves, no muscle contracts, no load: the stress-free reference configuration
        # is in equilibrium whatever the materials, so it is the exact solution.
        progress.say("  nothing moves and no muscle is active: the prediction is the pre-op face")
        u = np.zeros_like(np.asarray(model.nodes, float))
        stats = {"converged": True, "steps": 0, "iterations": 0,
                 "note": "no movement planned: the rest state is the solution"}
        return Prediction(model, plan, u, np.zeros((len(model.hexes), 3, 3)), stats, bone_vertices,
                          assignment, effects)
    with progress.stage("solve"):
        try:
            result = _call_simulate(model, motions, activations=activations, contact=plan.model.contact,
                                    sliding=sliding, materials=materials, progress=progress,
                                    sliding_nodes=degloved)
        except solver_errors.SolveFailed as exc:
            label = ""
            if exc.worst_element is not None and 0 <= exc.worst_element < len(model.labels):
                label = f", worst element {exc.worst_element} ({model.label_names[model.labels[exc.worst_element]]})"
            raise SolveError(f"Newton failed at load step {exc.step} (load {exc.load:.3g}, last converged "
                             f"{exc.last_converged_load:.3g}{label}): {exc}") from exc
        except solver_errors.MaterialError as exc:
            if not plan.model.materials:     # the default table itself: not the user's doing
                raise SolveError(f"material table: {exc}") from exc
            raise InputError(f"material: {exc}", file=plan.path,
                             field=f"model.materials ({exc.parameter})" if exc.parameter else "model.materials") from exc
        except solver_errors.SolverError as exc:
            raise SolveError(f"{type(exc).__name__}: {exc}") from exc
        except ModelInputError as exc:   # simulate refuses input it cannot use; any other
            # exception is a bug and surfaces as one
            raise InputError(f"the face model refused the plan: {exc}", file=plan.path) from exc
        u, stress, stats = _unpack_result(result, model)
    if not stats["converged"] or stats["load"] < 1.0 - 1e-9:
        raise SolveError(f"the solver stopped at load fraction {stats['load']:.3g} without converging; "
                         "a partial state is not a prediction")
    if not np.all(np.isfinite(u)):
        raise SolveError("the solution contains NaN or infinite displacements")
    bad = rep.inverted_elements(np.asarray(model.nodes, float) + u, model.hexes)
    if bad.size:
        raise SolveError(_inverted_message(model, bad))
    folded = rep.folded_corners(np.asarray(model.nodes, float) + u, model.hexes)
    if folded.size:
        progress.say(f"  warning: {folded.size} element(s) have a folded corner (corner Jacobian <= 0) "
                     "but are valid at their Gauss points")
    stats["sliding"] = list(sliding)
    stats["degloved_sliding_nodes"] = {s: int(len(ids)) for s, ids in degloved.items()}
    stats["activations"] = activations
    stats["teeth_clearance_shift_mm"] = {k: round(float(v), 4) for k, v in teeth_shift.items()}
    return Prediction(model, plan, u, stress, stats, bone_vertices, assignment, effects)


def _inverted_message(model, bad: np.ndarray) -> str:
    x = np.asarray(model.nodes, float)
    where = []
    for e in bad[:4]:
        hx = np.asarray(model.hexes[e])
        segs = [s for s in model.segments if np.isin(hx, model.node_sets.get("attach_" + s, ())).any()]
        where.append(f"element {int(e)} ({model.label_names[model.labels[e]]}, at "
                     f"{np.round(x[hx].mean(axis=0), 1).tolist()} mm, attached to {'+'.join(segs) or 'no bone'})")
    return (f"{bad.size} element(s) of the predicted face are inverted (Jacobian <= 0 at a Gauss point): "
            + "; ".join(where) + ". The relative movement of neighbouring bone segments shears the "
            "soft tissue between them more than this mesh resolution can follow: use a finer "
            "--resolution, --effect sliding=1, or a smaller relative movement")


# --------------------------------------------------------------------------- outputs

def skin_surface(model, positions: np.ndarray | None = None):
    """Skin triangles from the model's skin quads: (vertices, faces, node ids of the vertices)."""
    quads = np.asarray(model.facet_sets["skin"], int)
    ids, inverse = np.unique(quads, return_inverse=True)
    local = inverse.reshape(quads.shape)
    tris = np.concatenate([local[:, [0, 1, 2]], local[:, [0, 2, 3]]])
    x = np.asarray(model.nodes if positions is None else positions, float)[ids]
    return x, tris, ids


def region_of_nodes(model, ids: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Per skin vertex its region index into the returned names (-1 for none)."""
    names = list(model.regions)
    region = np.full(len(ids), -1, dtype=np.int32)
    pos = {int(n): i for i, n in enumerate(ids)}
    # Smaller regions first so that a node in two regions gets the more specific one.
    for r in sorted(range(len(names)), key=lambda r: -len(model.regions[names[r]])):
        for n in np.asarray(model.regions[names[r]], int):
            i = pos.get(int(n))
            if i is not None:
                region[i] = r
    return region, names


def write_volume(pred: Prediction, path: Path) -> None:
    """`prediction.vtu` (meshio): predicted node positions, displacement, labels, stress.

    Label names are not stored in the VTU (string arrays are not portable across VTU readers);
    they are in report.json under `label_names`, indexed by the cell data `label`."""
    import meshio

    model = pred.model
    hexes = np.asarray(model.hexes, np.int64)
    point_data = {"displacement": pred.displacement,
                  "displacement_magnitude": np.linalg.norm(pred.displacement, axis=1)}
    cell_data = {"label": [np.asarray(model.labels, np.int32)]}
    if pred.stress is not None and len(pred.stress) == len(hexes):
        cell_data["stress"] = [pred.stress.reshape(len(hexes), 9)]
        cell_data["von_mises"] = [von_mises(pred.stress)]
    meshio.Mesh(pred.predicted_nodes, [("hexahedron", hexes)], point_data=point_data,
                cell_data=cell_data).write(path)


def write_skin(pred: Prediction, out: Path) -> dict:
    """The model's skin patch: `skin_predicted.{stl,ply,vtp}` (the vtp with region, node id and
    displacement point data) and `region_names.json`."""
    import pyvista as pv
    import trimesh

    model = pred.model
    x_pre, tris, ids = skin_surface(model)
    x_post = pred.predicted_nodes[ids]
    mesh = trimesh.Trimesh(x_post, tris, process=False)
    mesh.export(out / "skin_predicted.stl")
    mesh.export(out / "skin_predicted.ply")
    region, names = region_of_nodes(model, ids)
    cells = np.hstack([np.full((len(tris), 1), 3), tris]).ravel()
    poly = pv.PolyData(x_post, cells)
    poly.point_data["region"] = region
    poly.point_data["node_id"] = ids.astype(np.int64)
    poly.point_data["displacement"] = pred.displacement[ids]
    poly.point_data["displacement_magnitude"] = np.linalg.norm(pred.displacement[ids], axis=1)
    poly.field_data["region_names"] = np.array(names)
    poly.save(str(out / "skin_predicted.vtp"))
    (out / "region_names.json").write_text(json.dumps(names))
    return {"pre": (x_pre, tris), "post": (x_post, tris), "magnitude": poly.point_data["displacement_magnitude"]}


def midline_profile(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Segments (k, 2, 3) where the skin surface crosses the mid-sagittal plane x = 0."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return np.asarray(trimesh.intersections.mesh_plane(mesh, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]))


# Landmarks on the facial midline: their mean fixes the mid-sagittal plane of the profile.
MIDLINE_LANDMARKS = ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me")
# Views of the pre-op and predicted faces, and those of the displacement map.
FACE_VIEWS = ("frontal", "profile", "profile_left", "three_quarter", "three_quarter_left", "submental")
DISPLACEMENT_VIEWS = ("frontal", "profile", "three_quarter")
ISOLINES_MM = (1.0, 2.0, 3.0)


def head_frame_of(model, resolution: str | None) -> np.ndarray:
    """The patient's head axes in the scan: the rotation of the best rigid fit of the generic
    model of `resolution` (built in the canonical RAS pose) onto the registered patient model
    (`render.head_frame`); the identity when the generic model does not match node for node."""
    from planner import render

    if resolution is None:
        return np.eye(3)
    try:
        import generic_mesh

        generic = generic_mesh.load(resolution)
    except (ValueError, KeyError, FileNotFoundError):
        return np.eye(3)
    if np.shape(generic.nodes) != np.shape(model.nodes):
        return np.eye(3)
    return render.head_frame(generic.nodes, model.nodes)


def whole_face(pred: Prediction, patient_skin=None):
    """The pre-op whole face (the patient's skin, or the model's skin patch without one) and
    the predicted whole face (`export.blend_face`)."""
    from planner.export import BlendedFace, blend_face

    x_pre, tris, ids = skin_surface(pred.model)
    u = pred.displacement[ids]
    if patient_skin is None:
        return (x_pre, tris), BlendedFace(x_pre + u, tris, u, np.ones(len(ids)))
    v = np.asarray(patient_skin.vertices, float)
    f = np.asarray(patient_skin.faces, np.int64)
    return (v, f), blend_face(v, f, x_pre, tris, u)


def profile_chart(pre, post, path: Path, landmarks_pre=None, landmarks_post=None, notes=None,
                  frame=None) -> Path | None:
    """The mid-sagittal skin profile before and after, seen from the patient's right (anterior
    to the right, superior up), equal axes in mm, with the landmarks named and `notes` (the
    soft-to-hard tissue ratios) beside them. The plane: the head frame's sagittal plane
    through the mean of the midline landmarks (x = 0 without them)."""
    from planner import render

    frame = np.eye(3) if frame is None else np.asarray(frame, float)
    origin = np.zeros(3)
    mid = [landmarks_pre[n] for n in MIDLINE_LANDMARKS if landmarks_pre and n in landmarks_pre]
    if mid:
        origin = np.mean(np.asarray(mid, float), axis=0)
    sets = [{n: p for n, p in d.items() if n in MIDLINE_LANDMARKS} for d in (landmarks_pre, landmarks_post)
            if d is not None]
    return render.landmark_profile_chart([pre, post], path, labels=("pre-op", "predicted"),
                                         landmarks=sets, notes=notes, frame=frame, origin=origin)


def _ratio_notes(landmarks: dict) -> dict[str, str]:
    return {n: f"soft/hard {e['soft_to_hard_ratio_ap']:.2f}" for n, e in landmarks.items()
            if e.get("soft_to_hard_ratio_ap") is not None}


def write_images(pre_face, post_face, images: Path, *, frame=None, landmarks_pre=None,
                 landmarks_post=None, notes=None, patch=None):
    """Pictures of the whole face: pre-op and predicted from every view with the same camera,
    the displacement map with iso-lines, the landmark profile, an overlay and a turntable GIF.
    Returns (list of (path, caption), list of (view, pre-op path, predicted path))."""
    from planner import render

    images.mkdir(parents=True, exist_ok=True)
    out: list[tuple[Path, str]] = []
    pre_v, pre_f = pre_face
    box = render.union_bounds([render.to_polydata(pre_face), render.to_polydata((post_face.vertices, post_face.faces))])
    pre_imgs = render.render_views(pre_face, images / "preop", title="pre-op face", views=FACE_VIEWS,
                                   frame=frame, bounds=box, landmarks=landmarks_pre)
    post_imgs = render.render_views((post_face.vertices, post_face.faces), images / "predicted",
                                    title="predicted face", views=FACE_VIEWS, frame=frame, bounds=box,
                                    landmarks=landmarks_post, title_position="upper_right")
    pairs = [(view, pre_imgs[view], post_imgs[view]) for view in FACE_VIEWS]
    mag = post_face.magnitude
    top = max(float(mag.max()), 1e-6)
    for view, path in render.render_views((post_face.vertices, post_face.faces), images / "displacement",
                                          scalars=mag, cmap="YlOrRd", clim=(0.0, top),
                                          scalar_bar_title="mm", title="soft-tissue displacement (mm)",
                                          views=DISPLACEMENT_VIEWS, frame=frame, bounds=box,
                                          isolines=[v for v in ISOLINES_MM if v < top]).items():
        out.append((path, f"displacement magnitude (mm, lines at 1, 2, 3 mm), "
                          f"{render.VIEW_TITLES[view]}"))
    path = profile_chart(pre_face, (post_face.vertices, post_face.faces), images / "profile_midline.png",
                         landmarks_pre, landmarks_post, notes, frame)
    if path is not None:
        out.append((path, "mid-sagittal profile: pre-op vs predicted, landmarks with the "
                          "soft-to-hard tissue ratio of their antero-posterior movement"))
    # the predicted face where the model moved it, over the pre-op face: elsewhere the two
    # coincide and the pre-op one is shown
    moved = (post_face.magnitude > 0.05)[np.asarray(post_face.faces)].any(axis=1)
    overlay = [pre_face] + ([(post_face.vertices, np.asarray(post_face.faces)[moved])] if moved.any() else [])
    for view, path in render.render_overlay(overlay, images / "overlay", labels=["pre-op", "predicted"][:len(overlay)],
                                            views=("profile",), frame=frame, opacity=[1.0, 1.0],
                                            title="profile: predicted (orange) where in front of pre-op (grey)").items():
        out.append((path, f"overlay pre-op vs predicted, {render.VIEW_TITLES[view]}"))
    gif = render.render_turntable((post_face.vertices, post_face.faces), images / "turntable.gif", frame=frame)
    out.append((gif, "predicted face, turntable"))
    return out, pairs


def write_exports(pred: Prediction, post_face, out: Path) -> dict[str, str]:
    """Files other tools open: the predicted whole face (GLB, OBJ), the predicted landmarks
    (3D Slicer markups) and the model with the plan (FEBio 4 input)."""
    from facemodel import materials as fm
    from planner import export

    export.write_mesh_glb(post_face.vertices, post_face.faces, out / "face_predicted.glb")
    export.write_mesh_obj(post_face.vertices, post_face.faces, out / "face_predicted.obj")
    export.write_markups(rep.predicted_landmarks(pred.model, pred.displacement),
                         out / "landmarks_predicted.mrk.json")
    model = pred.model
    stiffness = float(pred.effects.get("stiffness", 1.0)) if pred.effects else 1.0
    overrides = pred.plan.model.materials or {}
    materials = {}
    for label in model.label_names:
        p = dict(fm.parameters(label, stiffness))
        p.update(overrides.get(label, {}))
        materials[label] = p
    motions = {s: np.eye(4) for s in getattr(model, "segments", ())}
    motions.update(pred.plan.motions(include_identity=True))
    export.write_feb(model, motions, materials, out / "model.feb")
    return {"face_glb": "face_predicted.glb", "face_obj": "face_predicted.obj",
            "landmarks": "landmarks_predicted.mrk.json", "febio": "model.feb"}


def build_report(pred: Prediction, progress: Progress, inputs: dict, registration: dict | None) -> dict:
    model, u = pred.model, pred.displacement
    jac = rep.corner_jacobians(pred.predicted_nodes, model.hexes)
    ref = rep.corner_jacobians(model.nodes, model.hexes)
    gjac = rep.gauss_jacobians(pred.predicted_nodes, model.hexes)
    gref = rep.gauss_jacobians(model.nodes, model.hexes)
    return {
        "faceplan": 1,
        "inputs": inputs,
        "plan": pred.plan.as_dict(),
        "effects": pred.effects,
        "segments": rep.segment_movements(pred.plan, pred.bone_vertices),
        "attachment_assignment": pred.assignment,
        "regions": rep.region_movements(model, u),
        "landmarks": rep.landmark_movements(model, u, pred.plan, pred.bone_vertices),
        "landmarks_predicted": rep.predicted_landmarks(model, u),
        "label_names": list(model.label_names),
        "soft_tissue": {"max_displacement_mm": round(float(np.linalg.norm(u, axis=1).max()), 4),
                        "n_nodes": int(len(u)), "n_elements": int(len(model.hexes))},
        "mesh_quality": {"inverted_elements": int((gjac <= 0).any(axis=1).sum()),
                         "min_gauss_jacobian_ratio": round(float((gjac / gref).min()), 4),
                         "folded_corner_elements": int((jac <= 0).any(axis=1).sum()),
                         "min_corner_jacobian_ratio": round(float((jac / ref).min()), 4)},
        "registration": registration or {},
        "solver": pred.solver,
        "timings_s": {k: round(v, 3) for k, v in progress.timings.items()},
        "log": progress.log[-200:],
    }


def check_solution(pred: Prediction) -> None:
    """Refuse (SolveError) to treat as a prediction a state the solver did not finish: not
    converged, short of the full load, NaN/infinite displacements or stresses, or an element
    inverted at a Gauss point."""
    s = pred.solver or {}
    if s.get("converged") is False or float(s.get("load", 1.0)) < 1.0 - 1e-9:
        raise SolveError(f"the solution is not converged (load fraction {s.get('load')}); nothing written")
    if not np.all(np.isfinite(pred.displacement)) or (
            pred.stress is not None and not np.all(np.isfinite(pred.stress))):
        raise SolveError("the solution contains NaN or infinite values; nothing written")
    bad = rep.inverted_elements(pred.predicted_nodes, pred.model.hexes)
    if bad.size:
        raise SolveError(_inverted_message(pred.model, bad) + "; nothing written")


def write_outputs(pred: Prediction, out_dir: Path, progress: Progress, inputs: dict,
                  registration: dict | None = None, render: bool = True,
                  extra: Callable[[Path], None] | None = None, kind: str = "predict",
                  patient_skin=None) -> Path:
    """Write every output into `out_dir` atomically (whole or not at all); `extra(tmp)` may add
    files to the folder before it is moved into place. kind: the command named in the output
    marker (`planner.atomic`: only a previous output of that command is replaced).
    `patient_skin` (a trimesh): the case's pre-op skin, the base of the predicted whole face
    (the model's skin patch without it)."""
    from planner.atomic import atomic_output_dir
    from planner.html_report import write_html_report

    out_dir = Path(out_dir)
    check_solution(pred)
    t_start = time.perf_counter()
    with atomic_output_dir(out_dir, kind, inputs=[inputs.get("case")]) as tmp:
        with progress.stage("write meshes"):
            write_volume(pred, tmp / "prediction.vtu")
            write_skin(pred, tmp)
            pre_face, post_face = whole_face(pred, patient_skin)
            files = write_exports(pred, post_face, tmp)
        lm = rep.landmark_movements(pred.model, pred.displacement, pred.plan, pred.bone_vertices)
        images, pairs = [], []
        if render:
            with progress.stage("render"):
                frame = head_frame_of(pred.model, inputs.get("resolution"))
                images, pairs = write_images(
                    pre_face, post_face, tmp / "images", frame=frame,
                    landmarks_pre={n: e["preop"] for n, e in lm.items()},
                    landmarks_post={n: e["predicted"] for n, e in lm.items()}, notes=_ratio_notes(lm))
        progress.timings["outputs"] = time.perf_counter() - t_start
        progress.timings["total"] = time.perf_counter() - progress._t0
        report = build_report(pred, progress, inputs, registration)
        report["files"] = dict(files, html="report.html")
        report["whole_face"] = {"base": "patient pre-op skin" if patient_skin is not None else "model skin patch",
                                "vertices": int(len(post_face.vertices)),
                                "vertices_moved_by_model": int((post_face.weight > 0).sum()),
                                "max_displacement_mm": round(float(post_face.magnitude.max()), 4)}
        (tmp / "report.json").write_text(json.dumps(report, indent=2))
        tables = {"Landmarks (soft tissue, mm)": (
            ["landmark", "dx", "dy (AP)", "dz", "|d|", "soft/hard AP ratio"],
            [[n, *e["displacement_mm"], e["magnitude_mm"], e.get("soft_to_hard_ratio_ap", "")]
             for n, e in report["landmarks"].items()])}
        from planner import render as _render

        write_html_report(tmp / "report.html", "faceplan prediction",
                          {k: v for k, v in report.items() if k != "log"},
                          images=[(p, c) for p, c in images], tables=tables,
                          before_after=[(_render.VIEW_TITLES[v], a, b) for v, a, b in pairs])
        if extra is not None:
            extra(tmp)
    progress.say(f"prediction written to {out_dir}")
    return out_dir


# --------------------------------------------------------------------------- case level

def _file_digest(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    p = Path(path)
    files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]
    for q in files:
        h.update(q.read_bytes())
    return h.hexdigest()[:16]


def register_case(case, resolution: str, progress: Progress, threshold: float | None = None):
    """The generic model of `resolution` registered onto the case (Mesh-Match-and-Repair; the
    registration caches its result by input hash, so a re-run reuses it). threshold: the
    repair's scaled-Jacobian threshold (None: the registration's default, 0.2)."""
    import generic_mesh
    import registration
    from registration import errors as reg_errors

    generic = generic_mesh.load(resolution)
    try:
        patient, reg_report = registration.mesh_match_and_repair(
            generic, case.skin, case.bones, landmarks=case.landmarks or None,
            teeth=case.teeth or None, threshold=threshold)
    except (InputError, SolveError):
        raise
    except reg_errors.RegistrationInputError as exc:
        raise InputError(f"registration: {exc}", file=exc.file or str(case.root),
                         field=exc.field or "registration") from exc
    except reg_errors.RegistrationFailure as exc:
        raise SolveError(f"registration of the generic face onto the patient failed: {exc}") from exc
    summary = _jsonable(reg_report) if reg_report is not None else {}
    if isinstance(summary, dict):
        from planner.registration_gate import registration_notes

        summary["quality_gate"] = registration_notes(summary)
        for note in summary["quality_gate"]:     # shown even with --quiet
            print(f"faceplan: warning: registration: {note}", file=sys.stderr)
        cached = summary.get("cached", summary.get("cache_hit"))
        if cached is not None:
            progress.say(f"  registration {'reused from cache' if cached else 'computed'}")
    return patient, summary


def predict_case(case_dir, out: str | Path | None = None, *, resolution: str | None = None,
                 effects: dict[str, float] | None = None, max_translation_mm: float | None = None,
                 max_rotation_deg: float | None = None, render: bool = True,
                 echo: bool | Callable[[str], None] = True,
                 extra: Callable[[Path], None] | None = None, kind: str = "predict",
                 materials: dict[str, dict[str, float]] | None = None) -> Path:
    """Run the whole prediction for a case folder; return the output folder (checked before
    any work by `planner.atomic.prepare_output`; kind: the command named in its marker).
    `materials` (e.g. `planner.calibration.materials.read_materials`) is merged into the
    plan's model.materials."""
    from planner.atomic import prepare_output
    from planner.case import load_case

    out_dir = prepare_output(out if out is not None else Path(case_dir) / "predict", kind,
                             inputs=[case_dir])
    progress = Progress(echo)
    with progress.stage("load case"):
        case = load_case(case_dir)
        plan_path = case.require_plan()
        plan = load_plan(plan_path, max_translation_mm=max_translation_mm, max_rotation_deg=max_rotation_deg)
        if materials:
            from planner.calibration.materials import with_materials
            plan = with_materials(plan, materials)
        bone_vertices = {k: np.asarray(v.vertices, float) for k, v in case.bones.items()}
        check_against_bones(plan, bone_vertices)
        check_effects(plan, effects)
        res = resolution or plan.model.resolution
        progress.say(f"  case {case.info.id}: {len(case.bones)} bone surface(s), plan moves "
                     f"{', '.join(plan.motions()) or 'nothing'}; resolution {res}")
    with progress.stage("registration"):
        patient, reg = register_case(case, res, progress)
    pred = solve_plan(patient, plan, case.bones, effects=effects, progress=progress)
    inputs = {
        "case": str(Path(case_dir).resolve()), "case_id": case.info.id,
        "skin": str(case.skin_path) if case.skin_path else None,
        "bones": sorted(case.bones), "landmarks": sorted(case.landmarks),
        "plan": str(plan_path), "resolution": res,
        "sha256": {"plan": _file_digest(plan_path),
                   **({"skin": _file_digest(case.skin_path)} if case.skin_path else {})},
    }
    return write_outputs(pred, out_dir, progress, inputs, reg, render=render, extra=extra, kind=kind,
                         patient_skin=case.skin)


# --------------------------------------------------------------------------- demo

DEMO_PLAN = {
    "faceplan": 1,
    "frame": "RAS",
    "segments": {
        # Le Fort I: 5 mm advancement, 1 mm up, and a 2 deg pitch about the upper incisor
        # region that raises the posterior maxilla (rotation about +x, right-hand rule).
        "maxilla": {"translation": [0.0, 5.0, 1.0],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0, "center": [0.0, 60.0, -25.0]}},
        # BSSO: 3 mm mandibular setback of the distal segment.
        "mandible": {"translation": [0.0, -3.0, 0.0]},
        # Genioplasty: the chin segment rides with the mandible and is advanced 5 mm and raised
        # 1 mm on it; movements are pre-op -> post-op, so 2 mm forward overall.
        "chin": {"translation": [0.0, 2.0, 1.0]},
    },
    "muscles": {"orbicularis_oris": 0.0, "mentalis": 0.0},
    "model": {"contact": True},
}


DEMO_HEAD = Path(__file__).parent / "data" / "demo_head.npz"


def write_demo_case(folder: str | Path, plan: dict | None = None) -> Path:
    """Write the embedded synthetic head (`facemodel.synthetic.synthetic_head(7)`, stored in
    `planner/data/demo_head.npz`: skin, bone segments, landmarks) as a case folder with a plan
    (default: the bimaxillary demo plan)."""
    import trimesh
    import yaml

    folder = Path(folder)
    data = np.load(DEMO_HEAD)
    (folder / "preop" / "bone").mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(data["skin_vertices"].astype(float), data["skin_faces"], process=False).export(
        folder / "preop" / "skin.stl")
    for key in data.files:
        if key.startswith("bone_") and key.endswith("_vertices"):
            seg = key[len("bone_"):-len("_vertices")]
            trimesh.Trimesh(data[key].astype(float), data[f"bone_{seg}_faces"], process=False).export(
                folder / "preop" / "bone" / f"{seg}.stl")
    landmarks = {str(n): [float(c) for c in p] for n, p in zip(data["landmark_names"], data["landmark_points"])}
    (folder / "preop" / "landmarks.json").write_text(json.dumps(landmarks, indent=1))
    (folder / "case.yaml").write_text(yaml.safe_dump({"id": f"synthetic-{int(data['seed'])}", "synthetic": True,
                                                      "seed": int(data["seed"]),
                                                      "notes": "embedded synthetic head of the faceplan demo"}))
    (folder / "plan.yaml").write_text(
        "# faceplan demo: bimaxillary surgery (Le Fort I advancement, BSSO setback, genioplasty)\n"
        + yaml.safe_dump(plan or DEMO_PLAN, sort_keys=False))
    return folder


def run_demo(out_dir: str | Path, *, resolution: str = "coarse", render: bool = True,
             echo: bool | Callable[[str], None] = True) -> Path:
    """The bimaxillary demo on the embedded synthetic head: the whole prediction into
    `out_dir`, with the case folder it was made from in `out_dir/case`."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory(prefix="faceplan-demo-") as tmp:
        case = write_demo_case(Path(tmp) / "case",
                               dict(DEMO_PLAN, model=dict(DEMO_PLAN["model"], resolution=resolution)))

        def keep_case(folder: Path) -> None:
            shutil.copytree(case, folder / "case", ignore=shutil.ignore_patterns("predict", ".*"))

        return predict_case(case, out_dir, resolution=resolution, render=render, echo=echo,
                            extra=keep_case, kind="demo")
