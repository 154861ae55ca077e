"""The surgical plan file: rigid bone-segment movements, muscle activations and model options.

A plan (YAML, `faceplan: 1`) gives, for each moved bone segment, a rigid motion x -> R x + t as a
4x4 homogeneous matrix in patient RAS (mm). Three equivalent forms are read:

* `translation` and/or `rotation` about a `center`: x' = R (x - c) + c + t, the rotation applied
  first. `rotation` is either axis-angle (`axis`, `angle_deg`, right-hand rule) or Euler angles
  `euler_deg: [a1, a2, a3]` with `order` (default `xyz`): rotations about the *fixed* RAS axes
  applied in the order written, so `xyz` means R = Rz(a3) · Ry(a2) · Rx(a1) (pitch about the
  left-right axis first, then roll about the antero-posterior axis, then yaw about the vertical);
* `matrix`: the 4x4 rigid matrix (rotation orthonormal with det = +1, last row 0 0 0 1);
* `itk_transform`: an ITK text transform file as 3D Slicer saves it (see
  `planner.itk_transform`: Slicer writes the inverse, resampling transform in LPS; we invert and
  convert to RAS).

`frame: LPS` converts points, axes and matrices to RAS on reading (x, y negated; ITK files are
always LPS whatever the plan frame). Optional `cut_planes` (each `point` + `normal`) define a
segment as the part of a bone surface (`from`, default the segment's own surface) lying on the
side the normals point to, to split one CT bone surface into segments. Everything is validated
and every refusal is an `InputError` naming the file and the field; movements beyond anatomical
sense (more than 25 mm of any bone point or 30 degrees) are refused unless `limits` in the plan
(or the caller) raise them. YAML is read strictly (`read_yaml`, also for case.yaml): a key given
twice and files over 1 MB are refused; numbers in exponent form without a
decimal point (`-3e0`, which YAML 1.1 reads as text) are numbers, as in YAML 1.2.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from facemodel.model import FLOOR_CONDITIONS, MUSCLES, NECK_CONDITIONS, PROXIMAL_CONDITIONS
from planner.errors import InputError
from planner.itk_transform import LPS_FROM_RAS, read_itk_transform

FORMAT_VERSION = 1
SEGMENTS = ("skull", "maxilla", "mandible", "chin")
FIXED_SEGMENT = "skull"
RESOLUTIONS = ("coarse", "standard", "fine")
EFFECTS = ("sliding", "muscle_tone", "swelling", "gravity", "stiffness", "bone_execution")
DEFAULT_MAX_TRANSLATION_MM = 25.0
DEFAULT_MAX_ROTATION_DEG = 30.0
# Rigidity tolerance on R^T R - I and det R - 1: plans are typed or exported with 6+ decimals;
# 1e-4 accepts that rounding while a 0.1 % scale (a genuine non-rigid matrix) is refused.
RIGID_TOL = 1e-4

_TOP_KEYS = ("faceplan", "frame", "segments", "muscles", "model", "limits", "description", "name")
_SEGMENT_KEYS = ("translation", "rotation", "matrix", "itk_transform", "cut_planes", "from",
                 "description")
_ROTATION_KEYS = ("axis", "angle_deg", "euler_deg", "order", "center")
_MODEL_KEYS = ("resolution", "sliding", "contact", "materials", "effects", "neck", "floor",
               "proximal")
_LIMIT_KEYS = ("translation_mm", "rotation_deg")


@dataclass(frozen=True)
class CutPlane:
    """Half-space {x : (x - point) . normal >= 0} in RAS mm (normal is unit)."""

    point: np.ndarray
    normal: np.ndarray

    def keeps(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, float) - self.point) @ self.normal >= 0.0


@dataclass(frozen=True)
class SegmentPlan:
    """A bone segment's planned rigid movement (4x4, RAS) and where its bone comes from."""

    name: str
    matrix: np.ndarray
    form: str                              # "identity", "translation_rotation", "matrix", "itk_transform"
    cut_planes: tuple[CutPlane, ...] = ()
    source: str | None = None              # bone surface the cut planes split (None: own surface)

    @property
    def rotation_deg(self) -> float:
        return rotation_angle_deg(self.matrix)

    def apply(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        return x @ self.matrix[:3, :3].T + self.matrix[:3, 3]


@dataclass(frozen=True)
class ModelOptions:
    resolution: str = "standard"
    sliding: tuple[str, ...] = ()          # segments whose soft tissue slides instead of being tied
                                           # (`sliding: true` in the plan: every moved segment)
    contact: bool = True
    materials: dict[str, dict[str, float]] = field(default_factory=dict)
    effects: dict = field(default_factory=dict)   # flat {name: value} (facemodel.effects)
    neck: str = "free"                     # the neck cut: "free" or "held" (facemodel.simulation)
    floor: str = "free"                    # the floor of the mouth: "free" or "held" (likewise)
    proximal: str = "seated"               # the BSSO's proximal segments: "seated" or "moved"


@dataclass(frozen=True)
class Plan:
    path: str
    version: int
    frame: str
    segments: dict[str, SegmentPlan]
    muscles: dict[str, float]
    model: ModelOptions
    max_translation_mm: float = DEFAULT_MAX_TRANSLATION_MM
    max_rotation_deg: float = DEFAULT_MAX_ROTATION_DEG

    def motions(self, include_identity: bool = False) -> dict[str, np.ndarray]:
        """Segment -> 4x4 RAS movement for every segment the plan moves (with
        `include_identity`, also the segments listed with a zero movement)."""
        return {n: s.matrix for n, s in self.segments.items()
                if include_identity or not np.allclose(s.matrix, np.eye(4))}

    def as_dict(self) -> dict[str, Any]:
        """The plan as understood (RAS, matrices), for the report."""
        return {
            "file": self.path, "version": self.version, "frame_in_file": self.frame,
            "segments": {n: {"form": s.form, "matrix_ras": s.matrix.round(6).tolist(),
                             "rotation_deg": round(s.rotation_deg, 4),
                             "cut_planes": [{"point": c.point.tolist(), "normal": c.normal.tolist()}
                                            for c in s.cut_planes],
                             "from": s.source}
                         for n, s in self.segments.items()},
            "muscles": dict(self.muscles),
            "model": {"resolution": self.model.resolution, "sliding": list(self.model.sliding),
                      "contact": self.model.contact, "materials": self.model.materials,
                      "effects": dict(self.model.effects), "neck": self.model.neck,
                      "floor": self.model.floor, "proximal": self.model.proximal},
            "limits": {"translation_mm": self.max_translation_mm, "rotation_deg": self.max_rotation_deg},
        }


def rotation_angle_deg(matrix: np.ndarray) -> float:
    r = np.asarray(matrix)[:3, :3]
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def axis_angle_matrix(axis, angle_deg: float) -> np.ndarray:
    """Rotation matrix (Rodrigues) about a unit axis by an angle in degrees, right-hand rule."""
    a = np.asarray(axis, float)
    a = a / np.abs(a).max()         # scaled first: the norm of a huge axis must not overflow
    a = a / np.linalg.norm(a)
    t = math.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def euler_matrix(angles_deg, order: str = "xyz") -> np.ndarray:
    """Rotations about fixed axes applied in `order` (extrinsic): `xyz` -> Rz · Ry · Rx."""
    r = np.eye(3)
    for axis_name, angle in zip(order, angles_deg):
        axis = np.eye(3)["xyz".index(axis_name)]
        r = axis_angle_matrix(axis, angle) @ r
    return r


class _Reader:
    """Walks the YAML tree, keeping the dotted field path for error messages."""

    def __init__(self, file: str):
        self.file = file

    def fail(self, fieldname: str, message: str):
        raise InputError(message, file=self.file, field=fieldname)

    def mapping(self, value, fieldname: str, allowed: tuple[str, ...]) -> dict:
        if not isinstance(value, dict):
            self.fail(fieldname, f"must be a mapping, got {type(value).__name__}")
        for key in value:
            if not isinstance(key, str) or key not in allowed:
                self.fail(f"{fieldname}.{key}" if fieldname else str(key),
                          f"unknown key {key!r} (allowed: {', '.join(allowed)})")
        return value

    def number(self, value, fieldname: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(fieldname, f"must be a number, got {value!r}")
        try:
            value = float(value)
        except OverflowError:
            self.fail(fieldname, "number too large")
        if not math.isfinite(value):
            self.fail(fieldname, "must be finite (NaN or infinity given)")
        return value

    def vector(self, value, fieldname: str, n: int = 3) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) != n:
            self.fail(fieldname, f"must be a list of {n} numbers, got {value!r}")
        return np.array([self.number(v, f"{fieldname}[{i}]") for i, v in enumerate(value)])

    def unit(self, value, fieldname: str) -> np.ndarray:
        v = self.vector(value, fieldname)
        norm = np.linalg.norm(v)
        if norm < 1e-9:
            self.fail(fieldname, "must be a non-zero vector")
        return v / norm


def _rigid_matrix(r: _Reader, value, fieldname: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        r.fail(fieldname, "must be a 4x4 matrix (a list of 4 rows of 4 numbers)")
    m = np.array([r.vector(row, f"{fieldname}[{i}]", 4) for i, row in enumerate(value)])
    return _check_rigid(r, m, fieldname)


def _check_rigid(r: _Reader, m: np.ndarray, fieldname: str) -> np.ndarray:
    if not np.all(np.isfinite(m)):
        r.fail(fieldname, "contains NaN or infinity")
    if np.abs(m[3] - [0, 0, 0, 1]).max() > RIGID_TOL:
        r.fail(fieldname, f"last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    err = np.abs(rot.T @ rot - np.eye(3)).max()
    if err > RIGID_TOL:
        r.fail(fieldname, f"not a rigid motion: rotation part is not orthonormal (|R^T R - I| = {err:.3g})")
    det = np.linalg.det(rot)
    if abs(det - 1.0) > RIGID_TOL:
        r.fail(fieldname, f"not a rigid motion: det R = {det:.6g} (must be +1; a reflection or scaling)")
    # Project the rounding away (closest rotation, polar decomposition) so downstream is exact.
    u, _, vt = np.linalg.svd(rot)
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:3, 3]
    return out


def _rotation(r: _Reader, value, fieldname: str) -> tuple[np.ndarray, np.ndarray]:
    v = r.mapping(value, fieldname, _ROTATION_KEYS)
    center = r.vector(v["center"], f"{fieldname}.center") if "center" in v else np.zeros(3)
    has_axis = "axis" in v or "angle_deg" in v
    has_euler = "euler_deg" in v or "order" in v
    if has_axis and has_euler:
        r.fail(fieldname, "give either axis + angle_deg or euler_deg (+ order), not both")
    if has_axis:
        if "axis" not in v or "angle_deg" not in v:
            r.fail(fieldname, "axis-angle rotation needs both axis and angle_deg")
        axis = r.unit(v["axis"], f"{fieldname}.axis")
        return axis_angle_matrix(axis, r.number(v["angle_deg"], f"{fieldname}.angle_deg")), center
    if "euler_deg" not in v:
        r.fail(fieldname, "needs axis + angle_deg or euler_deg")
    order = v.get("order", "xyz")
    if not isinstance(order, str) or len(order) != 3 or set(order) - set("xyz"):
        r.fail(f"{fieldname}.order", f"must be three letters of x, y, z (e.g. xyz, zyx), got {order!r}")
    angles = r.vector(v["euler_deg"], f"{fieldname}.euler_deg")
    return euler_matrix(angles, order), center


def _segment(r: _Reader, name: str, value, plan_dir: Path, frame_change: np.ndarray,
             max_t: float) -> SegmentPlan:
    fieldname = f"segments.{name}"
    if value is None:
        value = {}
    v = r.mapping(value, fieldname, _SEGMENT_KEYS)
    forms = [k for k in ("matrix", "itk_transform") if k in v]
    if "translation" in v or "rotation" in v:
        forms.append("translation/rotation")
    if len(forms) > 1:
        r.fail(fieldname, f"give one movement form, not {' and '.join(forms)}")
    form = "identity"
    if "matrix" in v:
        m = frame_change @ _rigid_matrix(r, v["matrix"], f"{fieldname}.matrix") @ frame_change
        form = "matrix"
    elif "itk_transform" in v:
        ref = v["itk_transform"]
        if not isinstance(ref, str) or not ref.strip():
            r.fail(f"{fieldname}.itk_transform", "must be a file name (relative to the plan file)")
        tpath = (plan_dir / ref).resolve()
        try:
            raw = read_itk_transform(tpath)
        except InputError as exc:
            r.fail(f"{fieldname}.itk_transform", str(exc))
        m = _check_rigid(r, raw, f"{fieldname}.itk_transform")
        form = "itk_transform"
    else:
        m = np.eye(4)
        if "rotation" in v:
            rot, center = _rotation(r, v["rotation"], f"{fieldname}.rotation")
            m[:3, :3] = rot
            m[:3, 3] = center - rot @ center
            form = "translation_rotation"
        if "translation" in v:
            t = r.vector(v["translation"], f"{fieldname}.translation")
            if np.linalg.norm(t) > max_t:
                r.fail(f"{fieldname}.translation", f"translation of {np.linalg.norm(t):.1f} mm is beyond "
                       f"anatomical sense (limit {max_t:g} mm; raise limits.translation_mm if intended)")
            m[:3, 3] += t
            form = "translation_rotation"
        m = frame_change @ m @ frame_change
    planes = []
    if "cut_planes" in v:
        cps = v["cut_planes"]
        if not isinstance(cps, list) or not cps:
            r.fail(f"{fieldname}.cut_planes", "must be a non-empty list of {point, normal}")
        for i, cp in enumerate(cps):
            f = f"{fieldname}.cut_planes[{i}]"
            cpm = r.mapping(cp, f, ("point", "normal"))
            if "point" not in cpm or "normal" not in cpm:
                r.fail(f, "needs point and normal")
            p = r.vector(cpm["point"], f + ".point")
            n = r.unit(cpm["normal"], f + ".normal")
            planes.append(CutPlane(frame_change[:3, :3] @ p, frame_change[:3, :3] @ n))
    source = v.get("from")
    if source is not None and (not isinstance(source, str) or not source):
        r.fail(f"{fieldname}.from", "must be the name of a bone surface")
    if source is not None and not planes:
        r.fail(f"{fieldname}.from", "only meaningful with cut_planes")
    return SegmentPlan(name, m, form, tuple(planes), source)


def parse_plan(data: Any, file: str = "plan.yaml", plan_dir: Path | None = None, *,
               max_translation_mm: float | None = None, max_rotation_deg: float | None = None,
               segments: tuple[str, ...] = SEGMENTS) -> Plan:
    """Validate a loaded YAML tree and return the `Plan` in RAS."""
    r = _Reader(file)
    plan_dir = Path(plan_dir or ".")
    top = r.mapping(data, "", _TOP_KEYS)
    if "faceplan" not in top:
        r.fail("faceplan", f"missing format version (add 'faceplan: {FORMAT_VERSION}')")
    version = top["faceplan"]
    if isinstance(version, bool) or version != FORMAT_VERSION:
        r.fail("faceplan", f"unsupported format version {version!r} (this faceplan reads version {FORMAT_VERSION})")
    frame = top.get("frame", "RAS")
    if frame not in ("RAS", "LPS"):
        r.fail("frame", f"must be RAS or LPS, got {frame!r}")
    frame_change = LPS_FROM_RAS if frame == "LPS" else np.eye(4)

    limits = r.mapping(top.get("limits") or {}, "limits", _LIMIT_KEYS)
    max_t = r.number(limits.get("translation_mm", DEFAULT_MAX_TRANSLATION_MM), "limits.translation_mm")
    max_r = r.number(limits.get("rotation_deg", DEFAULT_MAX_ROTATION_DEG), "limits.rotation_deg")
    if max_t <= 0 or max_r <= 0 or max_r > 180:
        r.fail("limits", "limits must be positive (rotation_deg at most 180)")
    if max_translation_mm is not None:
        max_t = max(max_t, float(max_translation_mm))
    if max_rotation_deg is not None:
        max_r = max(max_r, float(max_rotation_deg))

    seg_tree = top.get("segments")
    if seg_tree is None:
        seg_tree = {}
    if not isinstance(seg_tree, dict):
        r.fail("segments", f"must map segment names to movements, got {type(seg_tree).__name__}")
    for name in seg_tree:
        if name not in segments:
            r.fail(f"segments.{name}", f"unknown segment {name!r} (known: {', '.join(segments)})")
    plans = {}
    for name, value in seg_tree.items():
        sp = _segment(r, name, value, plan_dir, frame_change, max_t)
        if name == FIXED_SEGMENT and not np.allclose(sp.matrix, np.eye(4), atol=1e-9):
            r.fail(f"segments.{name}", f"{FIXED_SEGMENT} is the fixed reference and cannot move")
        angle = sp.rotation_deg
        if angle > max_r:
            r.fail(f"segments.{name}", f"rotation of {angle:.1f} deg is beyond anatomical sense "
                   f"(limit {max_r:g} deg; raise limits.rotation_deg if intended)")
        plans[name] = sp
    for name, sp in plans.items():
        if sp.source is not None and sp.source == name:
            r.fail(f"segments.{name}.from", "a segment cannot be cut from itself")

    muscles_tree = top.get("muscles") or {}
    if not isinstance(muscles_tree, dict):
        r.fail("muscles", "must map muscle names to activations in [0, 1]")
    for name in muscles_tree:
        if name not in MUSCLES:
            r.fail(f"muscles.{name}", f"unknown muscle {name!r} (known: {', '.join(MUSCLES)})")
    muscles = {}
    for name, a in muscles_tree.items():
        a = r.number(a, f"muscles.{name}")
        if not 0.0 <= a <= 1.0:
            r.fail(f"muscles.{name}", f"activation must be in [0, 1], got {a:g}")
        muscles[name] = a

    mt = r.mapping(top.get("model") or {}, "model", _MODEL_KEYS)
    resolution = mt.get("resolution", "standard")
    if resolution not in RESOLUTIONS:
        r.fail("model.resolution", f"must be one of {', '.join(RESOLUTIONS)}, got {resolution!r}")
    sliding = mt.get("sliding", False)
    if isinstance(sliding, bool):
        # true: the soft tissue slides on every osteotomised (moved) segment, where surgery
        # detaches it from the bone; it stays tied to the fixed skull.
        sliding_t = tuple(n for n, sp in plans.items()
                          if not np.allclose(sp.matrix, np.eye(4))) if sliding else ()
    elif isinstance(sliding, list) and all(isinstance(s, str) for s in sliding):
        for s in sliding:
            if s not in segments:
                r.fail("model.sliding", f"unknown segment {s!r} (known: {', '.join(segments)})")
        sliding_t = tuple(sliding)
    else:
        r.fail("model.sliding", "must be true/false or a list of segment names")
    contact = mt.get("contact", True)
    if not isinstance(contact, bool):
        r.fail("model.contact", "must be true or false")
    materials = {}
    mats = mt.get("materials") or {}
    if not isinstance(mats, dict):
        r.fail("model.materials", "must map a tissue label to {parameter: value}")
    for label, params in mats.items():
        if not isinstance(label, str) or not isinstance(params, dict) or not params:
            r.fail(f"model.materials.{label}", "must map parameter names to numbers")
        materials[label] = {}
        for pname, pval in params.items():
            if not isinstance(pname, str):
                r.fail(f"model.materials.{label}", f"parameter name must be text, got {pname!r}")
            val = r.number(pval, f"model.materials.{label}.{pname}")
            if val <= 0:
                r.fail(f"model.materials.{label}.{pname}", "material parameters must be positive")
            materials[label][pname] = val
    # model.effects: the names and values of `--effect` (dotted names or nested mappings),
    # validated by facemodel.effects and kept in its flat form
    from facemodel.effects import EffectError, parse_effects

    eff = mt.get("effects") or {}
    if not isinstance(eff, dict):
        r.fail("model.effects", f"must be a mapping, got {type(eff).__name__}")
    try:
        effects = parse_effects(eff).as_dict()
    except EffectError as exc:
        r.fail(f"model.effects.{exc.field}", str(exc))
    held = {}
    for key, conditions in (("neck", NECK_CONDITIONS), ("floor", FLOOR_CONDITIONS),
                            ("proximal", PROXIMAL_CONDITIONS)):
        held[key] = mt.get(key, conditions[0])
        if held[key] not in conditions:
            r.fail(f"model.{key}", f"must be one of {', '.join(conditions)}, got {held[key]!r}")
    model = ModelOptions(resolution, sliding_t, contact, materials, effects, **held)
    return Plan(file, int(version), frame, plans, muscles, model, max_t, max_r)


MAX_YAML_BYTES = 1_000_000   # a plan or case.yaml is a few hundred bytes; 1 MB is never one
# YAML 1.2 floats that YAML 1.1 (PyYAML) leaves as text: an exponent without a decimal point
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys and reads `-3e0` as a number."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue            # reported by the SafeLoader as an unhashable key
            if key in seen:
                raise yaml.MarkedYAMLError(
                    f"in the mapping starting on line {node.start_mark.line + 1}", None,
                    f"the key {key!r} appears twice (line {seen[key] + 1} and line "
                    f"{key_node.start_mark.line + 1}); which one is meant cannot be guessed",
                    key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789"))


def read_yaml(path: str | Path, file: str | None = None, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """The YAML tree of `path`, read strictly (see the module docstring); InputError naming
    `file` (default the path) otherwise."""
    path = Path(path)
    file = file or str(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise InputError(f"the file is {size / 1e6:.1f} MB; a faceplan YAML file is at most "
                             f"{max_bytes / 1e6:g} MB (is it the right file?)", file=file, field="size")
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"unreadable file ({exc.strerror or exc})", file=file, field="file") from None
    except UnicodeDecodeError:
        raise InputError("not a text file (not UTF-8)", file=file, field="encoding") from None
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "yaml"
        problem = getattr(exc, "problem", None) or (str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        raise InputError(f"unreadable YAML: {problem}", file=file, field=where) from None
    except RecursionError:
        raise InputError("unreadable YAML: nested too deeply", file=file, field="yaml") from None


def load_plan(path: str | Path, **limits) -> Plan:
    """Read and validate a plan file (see module docstring); `InputError` on any problem."""
    path = Path(path)
    name = path.name
    if not path.is_file():
        raise InputError("plan file not found", file=str(path))
    data = read_yaml(path, name)
    if data is None:
        raise InputError("empty plan file", file=name)
    return parse_plan(data, name, path.parent, **limits)


def check_against_bones(plan: Plan, bone_vertices: dict[str, np.ndarray]) -> dict[str, float]:
    """Check the plan against the case's bone surfaces; return each moved segment's largest
    bone-point displacement (mm).

    Every segment named must have a bone surface, or be cut (cut planes) from one that exists;
    no bone point may move more than the plan's translation limit.
    """
    r = _Reader(plan.path)
    moved = {}
    for name, sp in plan.segments.items():
        source = sp.source or name
        if source not in bone_vertices:
            if sp.cut_planes and sp.source is None:
                r.fail(f"segments.{name}.from", f"no bone surface preop/bone/{name}.*: name the "
                       f"surface to cut it from (available: {', '.join(sorted(bone_vertices)) or 'none'})")
            r.fail(f"segments.{name}", f"segment has no bone surface preop/bone/{source}.* "
                   f"(available: {', '.join(sorted(bone_vertices)) or 'none'})")
        v = np.asarray(bone_vertices[source], float)
        for cp in sp.cut_planes:
            v = v[cp.keeps(v)]
        if v.size == 0:
            r.fail(f"segments.{name}.cut_planes", f"the cut planes leave no part of bone surface {source!r}")
        d = float(np.linalg.norm(sp.apply(v) - v, axis=1).max())
        if d > plan.max_translation_mm:
            r.fail(f"segments.{name}", f"moves bone points by up to {d:.1f} mm, beyond anatomical sense "
                   f"(limit {plan.max_translation_mm:g} mm; raise limits.translation_mm if intended)")
        moved[name] = d
    return moved
