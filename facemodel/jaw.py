"""Mandibular hinge movements and the incisal relation of a face model's dental arches.

In its first 20-25 mm of incisal opening the mandible rotates about the transverse axis
through its condyles, the terminal hinge axis (Posselt U., Acta Odontol Scand 10 Suppl 10,
1952); its closure is the reverse rotation. The axis is placed where the arbitrary hinge axis
of articulator practice puts it, about 13 mm in front of the ear canal at the level of the
Frankfort plane (Teteruck W.R., Lundeen H.C., J Prosthet Dent 16:1039-1046, 1966): in the
generic frame (origin between the porions, z = 0 on the Frankfort plane) the line through
HINGE_POINT along x. A rotation by +angle about +x closes the mouth (incisors up and forward).

`incisal_relation` measures overjet (horizontal distance between the labial incisal edges of
the upper and lower central incisors, normal 2-3 mm) and overbite (their vertical overlap,
normal 2-3 mm; negative: an open bite) on the mid-sagittal section of the arches (Proffit
W.R., Fields H.W., Sarver D.M., Contemporary Orthodontics, 5th ed., Mosby 2013, ch. 6).
`hinge_closure` gives the rotation that raises the lower incisal edge by a given distance and
`opened_model` the face with the mouth opened by the face model itself (an FE solve of the
opening rotation, its equilibrium taken as a new stress-free rest shape), the start of a
closure that the teeth allow.
"""
from __future__ import annotations

import numpy as np

__all__ = ["HINGE_POINT", "hinge_rotation", "hinge_closure", "incisal_edges",
           "incisal_relation", "move_teeth", "opened_model"]

HINGE_POINT = np.array([0.0, 13.0, -3.0])      # mm, RAS; the axis runs along x


def hinge_rotation(angle_deg: float, point=HINGE_POINT) -> np.ndarray:
    """4x4 rigid motion: rotation by `angle_deg` about the transverse (x) axis through
    `point`; positive closes the mouth."""
    a = np.radians(float(angle_deg))
    c, s = np.cos(a), np.sin(a)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(point, float) - R @ np.asarray(point, float)
    return T


def incisal_edges(model) -> dict:
    """Labial incisal edge points (3,) of the upper and lower arches on the mid-sagittal
    plane: of the arch vertices within 1 mm of x = 0, the most anterior of those at the
    occlusal end of the crown (lowest for 'upper', highest for 'lower', within 0.5 mm)."""
    out = {}
    for name, (V, _, _) in model.teeth.items():
        V = np.asarray(V, float)
        mid = V[np.abs(V[:, 0]) < 1.0]
        if not len(mid):
            raise ValueError(f"teeth {name!r} have no vertex near the mid-sagittal plane")
        labial = mid[mid[:, 1] >= mid[:, 1].max() - 0.5]
        out[name] = labial[np.argmin(labial[:, 2])] if name == "upper" else labial[np.argmax(labial[:, 2])]
    return out


def incisal_relation(model) -> dict:
    """Overjet and overbite (mm) of the model's central incisors (see module doc)."""
    e = incisal_edges(model)
    up, lo = e["upper"], e["lower"]
    return {"overjet_mm": float(up[1] - lo[1]), "overbite_mm": float(lo[2] - up[2])}


def hinge_closure(model, closure_mm: float, point=HINGE_POINT) -> float:
    """Angle (deg) of the hinge rotation that raises the lower incisal edge by closure_mm
    (negative: lowers it, an opening)."""
    r = incisal_edges(model)["lower"] - np.asarray(point, float)
    radius = np.hypot(r[1], r[2])
    phase = np.arctan2(r[2], r[1])
    target = (r[2] + closure_mm) / radius
    if abs(target) >= 1.0:
        raise ValueError(f"a {closure_mm} mm closure is beyond the hinge's reach")
    return float(np.degrees(np.arcsin(target) - phase))


def move_teeth(model, motions: dict) -> dict:
    """The model's teeth moved rigidly with their segments' motions {segment: 4x4}."""
    out = {}
    for name, (V, F, seg) in model.teeth.items():
        T = np.asarray(motions.get(seg, np.eye(4)), float)
        out[name] = (np.asarray(V, float) @ T[:3, :3].T + T[:3, 3], np.asarray(F), seg)
    return out


def opened_model(model, opening_mm: float, **simulate_options):
    """(opened model, opening motions): the face with the mandible and chin rotated about the
    hinge axis so that the lower incisal edge is `opening_mm` lower, solved by
    `facemodel.simulation.simulate` (options passed on) and taken as the new rest shape, its
    teeth moved with their bones. Raises `solver.errors.SolveFailed` if the opening fails."""
    from facemodel.simulation import simulate

    angle = hinge_closure(model, -float(opening_mm))
    T = hinge_rotation(angle)
    motions = {seg: T for seg in ("mandible", "chin") if seg in model.segments}
    res = simulate(model, motions, **simulate_options)
    if not res.converged:
        from solver.errors import SolveFailed
        raise SolveFailed(f"the {opening_mm} mm opening stopped at load {res.load:.3f}")
    return model.with_nodes(res.x, teeth=move_teeth(model, motions)), motions
