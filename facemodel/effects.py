"""Sim-to-real effects of the face model: their values, parameters and anatomical fields.

An effect is a switchable part of the FE prediction that the baseline leaves out (contract,
"Effect names"): `sliding` (tissue slides on the moved bone), `muscle_tone` (resting
perioral activation), `swelling` (residual oedema as volumetric growth, F = F_e F_g with
F_g = theta^(1/3) I, theta(x) = 1 + (theta_peak - 1) w(x), w = 1 at the operated bone and a
cosine taper to 0 at SWELLING_RADIUS_MM from it; with a follow-up time theta_peak - 1 is scaled
by the residual fraction of `swelling_residual`), `gravity` (the supine planning CT against the
upright scan: the body-force difference rho g m [(0, sin phi, -cos phi) - (0, -1, 0)] applied from
the pre-op state, a first-order correction about the CT's already loaded state; phi the head's
pitch in the upright scan, 0 by default: (0, +1, -1)), `stiffness` (factor on every
modulus, uniform or per layer) and `bone_execution` (a rigid correction per segment composed
after the plan, or the achieved movements of postop/plan_actual.yaml; the chin rides on the
mandible: a mandible correction moves the chin segment too, `executed_motions`). `sliding.hold`
h in [0, 1] is a setting of sliding (no effect alone): how much the interface between the
tissue and the bone resists the slide, from free (0, the default) to tied (1), through the
elastic interface of `facemodel.simulation` (a layer sheared over the bone slips by the share
1 - h of its surface's movement). `Effects` holds the
values (the value meaning "none" of each gives exactly the baseline); `parse_effects` reads
the `NAME=VALUE` strings of `--effect` and the `model.effects` mapping of a plan; `parameters`
lists each effect's continuous parameters (name, unit, bounds, "none" value) so that a fit can
iterate over them generically (`Effects.value` / `Effects.with_value`).

Sources: swelling resolution, van der Vlis M., Dentino K.M., Vervloet B., Padwa B.L.,
"Postoperative swelling after orthognathic surgery: a prospective volumetric analysis",
J Oral Maxillofac Surg 72:2241-2247, 2014 (3D stereophotogrammetry; about half of the swelling
gone at 3 weeks, ~80 % at 3 months, ~93 % at 12 months); Kau C.H. et al., "Three-dimensional
assessment of facial swelling after orthognathic surgery", 2006, the same time course. Soft
tissue density 1.05 g/cm^3 (Duck F.A., *Physical Properties of Tissue*, 1990).
"""
from __future__ import annotations

import ast
import math
from dataclasses import dataclass, replace

import numpy as np

from facemodel.model import MUSCLES, SEGMENTS

__all__ = ["EFFECT_NAMES", "LAYERS", "Effects", "EffectError", "Parameter", "parse_effects",
           "parameters", "swelling_residual", "swelling_weights", "growth_field",
           "gravity_density", "gravity_direction", "correction_matrix", "correction_params",
           "executed_motions", "executed_segments", "CARRIED_BY", "RHO", "G", "SWELLING_MAX", "GRAVITY_MAX",
           "SWELLING_RADIUS_MM", "MAX_PITCH_DEG", "BONE_DOF"]

EFFECT_NAMES = ("sliding", "muscle_tone", "swelling", "gravity", "stiffness", "bone_execution")
# stiffness layers -> the tissue labels they scale
LAYERS = {"dermis": ("dermis",), "hypodermis": ("hypodermis",), "muscle": tuple(MUSCLES),
          "mucosa": ("mucosa",), "nose": ("nose",)}
RHO = 1.05e-6            # kg/mm^3, soft tissue (Duck 1990)
G = 9810.0               # mm/s^2; rho g in mN/mm^3 = kPa/mm
SWELLING_RADIUS_MM = 15.0
# the peak (first post-operative days) growth ratio: with a follow-up time only
# (peak - 1) x residual acts (at 3 months 20 %, at 12 months 7 %), so the residual swelling
# of 0.5-2 mm of skin at 3-12 months asks for peaks up to ~3 (skin swollen by ~1 cm)
SWELLING_MAX = 4.0
# the posture factor m scales the supine-to-upright body-force difference; above 1 it stands for
# a face softer than the generic model under the same posture change, which the published skin
# changes between supine and upright can ask of it; up to twice the full effect
GRAVITY_MAX = 2.0
# (months after surgery, residual fraction of the peak swelling): van der Vlis et al. 2014
SWELLING_CURVE = ((0.0, 1.0), (0.7, 0.5), (3.0, 0.2), (12.0, 0.07))
BONE_DOF = ("tx", "ty", "tz", "rx", "ry", "rz")
BONE_UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")
MAX_CORRECTION_MM = 10.0
MAX_CORRECTION_DEG = 15.0
# head pitch of the upright scan about the left-right axis (degrees, + = chin down / flexion):
# natural head position scatters by a few degrees about the Frankfort horizontal (Cooke & Wei
# 1988, facemodel.materials [pitch]); 30 deg bounds any scan a patient sits upright for
MAX_PITCH_DEG = 30.0
# segments fixed to another after the operation: the chin segment is plated to the mandible
# (genioplasty) or is part of it (no genioplasty), so it follows the mandible's correction
CARRIED_BY = {"chin": "mandible"}
# a carried segment planned to move as its carrier does, within these tolerances, was not cut:
# far below any surgical movement (a genioplasty moves the chin by millimetres), above the
# rounding of a transform file
SAME_MOTION_MM = 0.01
SAME_MOTION_ROT = 1e-4


class EffectError(ValueError):
    """A bad effect name or value; `field` names the effect (e.g. 'stiffness.dermis')."""

    def __init__(self, message: str, field: str):
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class Parameter:
    """One continuous effect parameter: flat name (as `--effect` takes it), unit, bounds and
    the value meaning "none"."""

    name: str
    effect: str
    unit: str
    lower: float
    upper: float
    none: float
    description: str = ""


@dataclass(frozen=True)
class Effects:
    """Values of every effect; the defaults mean "none" (the baseline prediction).

    sliding: segments whose tissue slides ("*" = every moved segment); stiffness_layers:
    ((layer, factor), ...); bone_execution: ((segment, (tx, ty, tz, rx, ry, rz)), ...) in mm
    and degrees about the segment's planned post-op centroid; plan_actual: use the achieved
    movements of postop/plan_actual.yaml instead of the plan's. gravity_pitch: head pitch of the
    upright scan (degrees, + = chin down), a setting of the gravity effect (no effect alone).
    sliding_hold: the sliding interface's hold, 0 (free) to 1 (tied), a setting of the sliding
    effect (no effect alone).
    """

    sliding: tuple = ()
    sliding_hold: float = 0.0
    muscle_tone: float = 0.0
    swelling: float = 1.0
    gravity: float = 0.0
    gravity_pitch: float = 0.0
    stiffness: float = 1.0
    stiffness_layers: tuple = ()
    bone_execution: tuple = ()
    plan_actual: bool = False

    # -------------------------------------------------------------- views
    @property
    def active(self) -> tuple:
        """Names of the effects not at their "none" value."""
        out = []
        if self.sliding:
            out.append("sliding")
        if self.muscle_tone != 0.0:
            out.append("muscle_tone")
        if self.swelling != 1.0:
            out.append("swelling")
        if self.gravity != 0.0:
            out.append("gravity")
        if self.stiffness != 1.0 or any(f != 1.0 for _, f in self.stiffness_layers):
            out.append("stiffness")
        if self.plan_actual or any(any(v != 0.0 for v in p) for _, p in self.bone_execution):
            out.append("bone_execution")
        return tuple(out)

    def layer_factor(self, layer: str) -> float:
        """Stiffness factor of a layer: the uniform factor times the layer's own."""
        return self.stiffness * dict(self.stiffness_layers).get(layer, 1.0)

    def label_factors(self) -> dict:
        """Stiffness factor per tissue label."""
        return {label: self.layer_factor(layer) for layer, labels in LAYERS.items() for label in labels}

    def correction(self, segment: str) -> tuple:
        return tuple(dict(self.bone_execution).get(segment, (0.0,) * 6))

    def as_dict(self) -> dict:
        """The effects not at "none" in the flat form `--effect` takes (JSON-able)."""
        out = {}
        if self.sliding:
            out["sliding"] = 1.0 if self.sliding == ("*",) else ",".join(self.sliding)
        if self.sliding_hold != 0.0:
            out["sliding.hold"] = self.sliding_hold
        if self.muscle_tone != 0.0:
            out["muscle_tone"] = self.muscle_tone
        if self.swelling != 1.0:
            out["swelling"] = self.swelling
        if self.gravity != 0.0:
            out["gravity"] = self.gravity
        if self.gravity_pitch != 0.0:
            out["gravity.pitch"] = self.gravity_pitch
        if self.stiffness != 1.0:
            out["stiffness"] = self.stiffness
        for layer, f in self.stiffness_layers:
            if f != 1.0:
                out[f"stiffness.{layer}"] = f
        if self.plan_actual:
            out["bone_execution"] = 1.0
        for seg, p in self.bone_execution:
            if any(v != 0.0 for v in p):
                out[f"bone_execution.{seg}"] = [float(v) for v in p]
        return out

    # -------------------------------------------------------------- flat parameters
    def value(self, name: str) -> float:
        """Value of a flat parameter name ('swelling', 'stiffness.dermis',
        'bone_execution.maxilla.ty', ...)."""
        head, _, rest = name.partition(".")
        if head in ("muscle_tone", "swelling", "gravity") and not rest:
            return float(getattr(self, head))
        if name == "gravity.pitch":
            return float(self.gravity_pitch)
        if name == "sliding.hold":
            return float(self.sliding_hold)
        if head == "stiffness":
            return self.stiffness if not rest else dict(self.stiffness_layers).get(rest, 1.0)
        if head == "bone_execution" and rest.count(".") == 1:
            seg, dof = rest.split(".")
            return float(self.correction(seg)[BONE_DOF.index(dof)])
        raise KeyError(f"no continuous effect parameter {name!r}")

    def with_value(self, name: str, v: float) -> "Effects":
        """A copy with one flat parameter set (no range check: fits and finite differences
        may step outside the user-facing bounds)."""
        head, _, rest = name.partition(".")
        v = float(v)
        if head in ("muscle_tone", "swelling", "gravity") and not rest:
            return replace(self, **{head: v})
        if name == "gravity.pitch":
            return replace(self, gravity_pitch=v)
        if name == "sliding.hold":
            return replace(self, sliding_hold=v)
        if head == "stiffness":
            if not rest:
                return replace(self, stiffness=v)
            if rest not in LAYERS:
                raise KeyError(f"unknown stiffness layer {rest!r}")
            d = dict(self.stiffness_layers)
            d[rest] = v
            return replace(self, stiffness_layers=tuple(sorted(d.items())))
        if head == "bone_execution" and rest.count(".") == 1:
            seg, dof = rest.split(".")
            if seg not in SEGMENTS or dof not in BONE_DOF:
                raise KeyError(f"no continuous effect parameter {name!r}")
            d = dict(self.bone_execution)
            p = list(d.get(seg, (0.0,) * 6))
            p[BONE_DOF.index(dof)] = v
            d[seg] = tuple(p)
            return replace(self, bone_execution=tuple(sorted(d.items())))
        raise KeyError(f"no continuous effect parameter {name!r}")


def parameters(effect: str, segments=()) -> list:
    """The continuous parameters of an effect (`segments`: the moved segments, for
    bone_execution's six per segment). `sliding` is a discrete choice (none, every moved
    segment, or one segment) and has none; `stiffness` has the uniform factor and one per
    layer."""
    if effect == "muscle_tone":
        return [Parameter("muscle_tone", effect, "-", 0.0, 1.0, 0.0, "resting perioral activation")]
    if effect == "swelling":
        return [Parameter("swelling", effect, "-", 1.0, SWELLING_MAX, 1.0, "peak volumetric growth ratio")]
    if effect == "gravity":
        return [Parameter("gravity", effect, "-", 0.0, GRAVITY_MAX, 0.0, "posture factor m")]
    if effect == "stiffness":
        return [Parameter("stiffness", effect, "-", 0.1, 10.0, 1.0, "uniform factor")] + [
            Parameter(f"stiffness.{layer}", effect, "-", 0.1, 10.0, 1.0, f"{layer} factor")
            for layer in LAYERS]
    if effect == "bone_execution":
        return [Parameter(f"bone_execution.{seg}.{dof}", effect, unit,
                          -(MAX_CORRECTION_MM if unit == "mm" else MAX_CORRECTION_DEG),
                          MAX_CORRECTION_MM if unit == "mm" else MAX_CORRECTION_DEG, 0.0,
                          f"{seg} correction {dof}")
                for seg in segments for dof, unit in zip(BONE_DOF, BONE_UNITS)]
    if effect == "sliding":
        return []
    raise KeyError(f"unknown effect {effect!r}")


# ------------------------------------------------------------------ parsing

def _number(raw, name: str) -> float:
    if isinstance(raw, bool):
        return float(raw)
    if isinstance(raw, (int, float, np.floating, np.integer)):
        v = float(raw)
    else:
        text = str(raw).strip()
        if not text:
            return 1.0
        try:
            v = float(text)
        except ValueError:
            raise EffectError(f"effect {name}: value must be a number, got {raw!r}", name) from None
    if not math.isfinite(v):
        raise EffectError(f"effect {name}: value must be finite", name)
    return v


def _in(v: float, lo: float, hi: float, name: str, what: str = "value") -> float:
    if not lo <= v <= hi:
        raise EffectError(f"effect {name}: {what} must be in [{lo:g}, {hi:g}], got {v:g}", name)
    return v


def _vector6(raw, name: str) -> tuple:
    if isinstance(raw, str):
        try:
            raw = ast.literal_eval(raw.strip())
        except (ValueError, SyntaxError):
            raise EffectError(f"effect {name}: value must be a list [tx, ty, tz, rx, ry, rz] "
                              f"(mm, degrees), got {raw!r}", name) from None
    if not isinstance(raw, (list, tuple)) or len(raw) != 6:
        raise EffectError(f"effect {name}: value must be a list of 6 numbers [tx, ty, tz, rx, "
                          f"ry, rz] (mm, degrees), got {raw!r}", name)
    v = tuple(_number(x, name) for x in raw)
    for x, unit in zip(v, BONE_UNITS):
        lim = MAX_CORRECTION_MM if unit == "mm" else MAX_CORRECTION_DEG
        _in(x, -lim, lim, name, f"each {'translation' if unit == 'mm' else 'rotation'} ({unit})")
    return v


def _flatten(mapping: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in mapping.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def parse_effects(items=None, *, segments=SEGMENTS) -> Effects:
    """`NAME=VALUE` strings (a list) or a mapping {name: value} (nested mappings and dotted
    names alike, as `model.effects` gives them) -> `Effects`; `EffectError` naming the field
    otherwise. Later items override earlier ones."""
    if items is None:
        pairs = []
    elif isinstance(items, dict):
        pairs = list(_flatten(items).items())
    else:
        pairs = []
        for item in items:
            name, sep, value = str(item).partition("=")
            pairs.append((name.strip(), value if sep else ""))
    kw = {}
    layers = {}
    bone = {}
    for name, raw in pairs:
        head, _, rest = name.partition(".")
        if head not in EFFECT_NAMES:
            raise EffectError(f"unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)})", name)
        if head == "sliding":
            if rest == "hold":
                kw["sliding_hold"] = _in(_number(raw, name), 0.0, 1.0, name, "interface hold")
                continue
            if rest:
                raise EffectError("effect sliding takes one sub-name, hold: sliding=1, sliding=SEGMENT "
                                  "or sliding.hold=H", name)
            text = str(raw).strip().lower() if not isinstance(raw, (bool, int, float)) else raw
            if isinstance(text, str) and text and text not in ("0", "1", "0.0", "1.0", "true", "false",
                                                                 "yes", "no"):
                segs = tuple(s.strip() for s in text.split(",") if s.strip())
                for s in segs:
                    if s not in segments:
                        raise EffectError(f"effect sliding: unknown segment {s!r} (segments: "
                                          f"{', '.join(segments)})", name)
                kw["sliding"] = segs
            else:
                on = text in ("", "1", "1.0", "true", "yes") if isinstance(text, str) else float(text)
                if not isinstance(on, bool) and on not in (0.0, 1.0):
                    raise EffectError(f"effect sliding: value must be 0, 1 or a segment name, got {raw!r}", name)
                kw["sliding"] = ("*",) if on else ()
        elif head == "muscle_tone":
            if rest:
                raise EffectError("effect muscle_tone takes no sub-name", name)
            kw["muscle_tone"] = _in(_number(raw, name), 0.0, 1.0, name)
        elif head == "swelling":
            if rest:
                raise EffectError("effect swelling takes no sub-name", name)
            kw["swelling"] = _in(_number(raw, name), 1.0, SWELLING_MAX, name, "growth ratio")
        elif head == "gravity":
            if rest == "pitch":
                kw["gravity_pitch"] = _in(_number(raw, name), -MAX_PITCH_DEG, MAX_PITCH_DEG, name,
                                          "head pitch (degrees)")
            elif rest:
                raise EffectError("effect gravity takes one sub-name: gravity.pitch=DEGREES", name)
            else:
                kw["gravity"] = _in(_number(raw, name), 0.0, GRAVITY_MAX, name, "posture factor")
        elif head == "stiffness":
            v = _in(_number(raw, name), 0.1, 10.0, name, "factor")
            if not rest:
                kw["stiffness"] = v
            elif rest in LAYERS:
                layers[rest] = v
            else:
                raise EffectError(f"effect stiffness: unknown layer {rest!r} (layers: "
                                  f"{', '.join(LAYERS)})", name)
        elif head == "bone_execution":
            if not rest:
                v = _number(raw, name)
                if v not in (0.0, 1.0):
                    raise EffectError("effect bone_execution: value must be 1 (the movements of "
                                      "postop/plan_actual.yaml) or 0; per segment use "
                                      "bone_execution.SEGMENT=[tx, ty, tz, rx, ry, rz]", name)
                kw["plan_actual"] = v == 1.0
            elif rest in segments:
                bone[rest] = _vector6(raw, name)
            else:
                raise EffectError(f"effect bone_execution: unknown segment {rest!r} (segments: "
                                  f"{', '.join(segments)})", name)
    if layers:
        kw["stiffness_layers"] = tuple(sorted(layers.items()))
    if bone:
        kw["bone_execution"] = tuple(sorted(bone.items()))
    return Effects(**kw)


def merge(base: Effects, override: Effects) -> Effects:
    """`base` (a plan's effects) with every effect `override` (the command line) sets."""
    return parse_effects({**base.as_dict(), **override.as_dict()})


# ------------------------------------------------------------------ fields

def swelling_residual(months: float | None) -> float:
    """Fraction of the peak swelling still present `months` after surgery (1 when None):
    log-linear interpolation of `SWELLING_CURVE` (van der Vlis et al. 2014), held at the
    12-month value beyond (no data later)."""
    if months is None:
        return 1.0
    t = np.array([p[0] for p in SWELLING_CURVE])
    r = np.log([p[1] for p in SWELLING_CURVE])
    return float(np.exp(np.interp(max(0.0, float(months)), t, r)))


def swelling_weights(model, segments, radius: float = SWELLING_RADIUS_MM) -> np.ndarray:
    """w per element (m,): 1 at the attachment nodes of the operated `segments`, a cosine taper
    0.5 (1 + cos(pi d / radius)) of the distance d from the element centroid to them, 0 beyond
    `radius`."""
    from scipy.spatial import cKDTree

    X = np.asarray(model.nodes, float)
    ids = [np.asarray(model.node_sets.get("attach_" + s, ()), np.int64) for s in segments]
    ids = np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)
    m = len(model.hexes)
    if not len(ids):
        return np.zeros(m)
    cen = X[np.asarray(model.hexes)].mean(axis=1)
    d, _ = cKDTree(X[ids]).query(cen)
    return np.where(d < radius, 0.5 * (1.0 + np.cos(np.pi * np.minimum(d, radius) / radius)), 0.0)


def growth_field(model, segments, theta_peak: float, months: float | None = None) -> np.ndarray | None:
    """Growth ratio theta per element, or None when there is no swelling."""
    if theta_peak == 1.0:
        return None
    amp = (theta_peak - 1.0) * swelling_residual(months)
    return 1.0 + amp * swelling_weights(model, segments)


def gravity_direction(pitch_deg: float = 0.0) -> np.ndarray:
    """Unit direction of gravity in the head's (RAS) frame for the upright posture with the
    head pitched by `pitch_deg` about the left-right (x) axis, + = chin down (flexion).

    A head flexed by phi is the head frame turned by R = Rx(-phi) in the room (a positive
    rotation about +x lifts the anterior axis towards superior, i.e. chin up); the room's
    gravity (0, 0, -1) seen in the head frame is R^T (0, 0, -1) = Rx(phi) (0, 0, -1) =
    (0, sin phi, -cos phi): with the chin down gravity gains an anterior component (the
    face looking at the floor, phi = 90 deg, is pulled straight forward)."""
    a = math.radians(float(pitch_deg))
    return np.array([0.0, math.sin(a), -math.cos(a)])


def gravity_density(m: float, pitch_deg: float = 0.0) -> np.ndarray | None:
    """Body-force density difference (mN/mm^3) upright scan minus supine CT, posture factor m:
    rho g m [g_up(pitch) - (0, -1, 0)] in RAS with g_up = `gravity_direction(pitch)` (pitch 0:
    rho g m (0, +1, -1)); the supine CT lies face up (gravity posterior, -y). None for m = 0."""
    if m == 0.0:
        return None
    return RHO * G * float(m) * (gravity_direction(pitch_deg) - np.array([0.0, -1.0, 0.0]))


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def correction_matrix(params, centre) -> np.ndarray:
    """4x4 rigid correction from (tx, ty, tz, rx, ry, rz) (mm, degrees): the rotation
    R = Rz Ry Rx (about the RAS axes, right-hand rule) about `centre`, then the translation."""
    p = np.asarray(params, float)
    R = _rot(2, p[5]) @ _rot(1, p[4]) @ _rot(0, p[3])
    c = np.asarray(centre, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + p[:3]
    return T


def correction_params(T, centre) -> tuple:
    """Inverse of `correction_matrix`: the six parameters of a rigid 4x4 about `centre`."""
    T = np.asarray(T, float)
    R = T[:3, :3]
    ry = math.degrees(math.asin(-np.clip(R[2, 0], -1.0, 1.0)))
    rx = math.degrees(math.atan2(R[2, 1], R[2, 2]))
    rz = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    c = np.asarray(centre, float)
    t = T[:3, 3] - (c - R @ c)
    return (float(t[0]), float(t[1]), float(t[2]), rx, ry, rz)


def executed_segments(motions: dict) -> tuple[str, ...]:
    """The segments with an execution of their own among those the plan moves (`motions`:
    segment -> 4x4 planned movement): every moved segment but a carried one (`CARRIED_BY`)
    planned to move exactly as its carrier. Such a segment was not cut (the chin without a
    genioplasty is part of the mandible's distal segment), so the carrier's execution is its
    own and a separate correction of it would describe no surgery."""
    out = []
    for seg, T in motions.items():
        carrier = CARRIED_BY.get(seg)
        if carrier in motions:
            A, B = np.asarray(T, float), np.asarray(motions[carrier], float)
            if (np.abs(A[:3, :3] - B[:3, :3]).max() <= SAME_MOTION_ROT
                    and np.abs(A[:3, 3] - B[:3, 3]).max() <= SAME_MOTION_MM):
                continue
        out.append(seg)
    return tuple(out)


def executed_motions(motions: dict, corrections, centroids: dict) -> dict:
    """Segment -> 4x4 achieved movement: each planned movement `motions[seg]` followed by its
    rigid correction (tx, ty, tz, rx, ry, rz) about the segment's centroid as moved (`centroids`:
    pre-op centroids), with the carried segments (`CARRIED_BY`) riding on their carrier.

    For a segment s carried by c (the chin by the mandible) with corrections C_c and C_s:
        actual_c = C_c(centre = planned c centroid) . plan_c
        actual_s = C_s(centre = centroid of s moved by C_c . plan_s) . C_c . plan_s
    i.e. the carrier's correction is a rigid motion of the room applied to the carrier's
    planned pose, and everything fixed to the carrier (the chin plated to the mandible after a
    genioplasty, or the chin still part of it without one) undergoes the same motion; the
    segment's own correction, if any, comes last. A segment the plan does not list has the
    identity as planned movement. `corrections`: {segment: 6 values} or ((segment, values), ...);
    a segment with a correction but no centroid raises KeyError."""
    motions = {k: np.asarray(v, float) for k, v in motions.items()}
    corr = {s: tuple(float(v) for v in p) for s, p in dict(corrections).items()
            if any(float(v) != 0.0 for v in p)}
    # carriers first, so that a carried segment sees its carrier's correction
    order = sorted(corr.keys() | {s for s, c in CARRIED_BY.items() if c in corr},
                   key=lambda s: s in CARRIED_BY)
    applied = {}
    for seg in order:
        T = motions.get(seg, np.eye(4))
        carrier = CARRIED_BY.get(seg)
        if carrier in applied:
            T = applied[carrier] @ T
        if seg in corr:
            c0 = centroids[seg]
            c = T[:3, :3] @ np.asarray(c0, float) + T[:3, 3]
            C = correction_matrix(corr[seg], c)
            applied[seg] = C
            T = C @ T
        motions[seg] = T
    return motions
