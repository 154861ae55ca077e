"""Parametric head: the facial skeleton (deep) surface and the skin as radial functions.

Both surfaces are star-shaped about a fixed centre C inside the head and are written as
radii along the ray of direction d(theta, phi) = (cos phi sin theta, cos phi cos theta,
sin phi) (theta: azimuth towards the patient's right, +x; phi: elevation; degrees; RAS, mm):
the deep surface R_b(theta, phi) (bone, teeth and the oral vestibule under the lips) and the
skin R_s = R_b + T, T the soft-tissue thickness along the ray. A surface is then the zero
set of f(p) = |p - C| - R(theta(p), phi(p)), which is what pygalmesh meshes, and the
generic structured mesh is built between R_b and R_s ray by ray.

Dimensions are those of an adult face (frame: origin between the porions, z = 0 on the
Frankfort plane, centre C = (0, 10, -20) mm):
* soft-tissue thickness: upper lip 14-15 mm at labrale superius and A point, lower lip ~15,
  chin 10-12 mm at pogonion, soft menton ~9 mm (Holdaway R.A., Am J Orthod 84:1-28, 1983;
  Legan & Burstone, J Oral Surg 38:744-751, 1980); cheek 12-16 mm, infraorbital ~7 mm,
  nasion ~7 mm (De Greef S. et al., Forensic Sci Int 159S:S126-S146, 2006);
* mouth width ~50 mm, nose projection ~20 mm in front of subnasale, nasion-subnasale ~52 mm,
  subnasale-menton ~70 mm (Farkas L.G., Anthropometry of the Head and Face, Raven 1994);
* dental arch: incisors 88 mm in front of the porions, intercanine width ~34 mm, arch depth
  ~48 mm to the second molars (Bishara S.E. et al., Am J Orthod Dentofac 111:401-409, 1997);
  overjet 2.5 mm, crown height ~10 mm.
Shape parameters (`HeadShape`) move the jaws (class II / III patterns), the chin, the lips,
the soft tissue and the nose, scale the face width and height about C and shift the lower
face sideways (mild asymmetry); they are smooth fields, so the surfaces stay smooth except
at the mouth line, where the upper and lower lips (and incisors) may be offset from each
other between the commissures, as real lips are.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy.interpolate import PchipInterpolator

from solver.geometry import deepest_concavity

CENTRE = np.array([0.0, 10.0, -20.0])
PHI_STOMION = -19.0          # elevation of the mouth line (deg)
THETA_COMMISSURE = 18.0      # azimuth of the commissures (deg): mouth width ~50 mm
PHI_LE_FORT = -4.0           # Le Fort I osteotomy at the midline (deg)
CROWN_SPAN = 7.5             # crown height in elevation (deg): ~10 mm
OVERJET = 2.5                # mm
TEETH_GAP = 0.25             # mm between the lip mucosa and the labial surface of the teeth
# mm from the mouth line to each front crown's incisal edge: the lips close in front of a
# 2 x 1.5 mm interincisal gap, the interocclusal rest space of the mandible's rest position
# (2-4 mm at the incisors; Garnick & Ramfjord, J Prosthet Dent 12:895-911, 1962). With the
# edges on the mouth line the lips' inner corners lie between the incisal edges, and a jaw
# move that slides one arch over the other pinches them there (docs/solver_control.md).
INCISAL_CLEARANCE = 1.5
BONE_SHELL = 7.0             # thickness of the bone segment shells (mm)
OSTEOTOMY_KERF = 0.8         # deg between bone segments

# Soft-tissue landmarks: the ray (theta, phi, side) near which each lies in the radial frame
# (side +1 upper lip, -1 lower): the generic mesh's landmark nodes are the skin nodes nearest
# these rays. The landmarks of a head themselves are located by their anatomical definitions
# on its skin (`anatomical_landmarks`).
LANDMARK_ANGLES = {
    "Prn": (0.0, 1.0, 0), "Sn": (0.0, -7.6, 0), "Ls": (0.0, -14.0, 1),
    "Stms": (0.0, PHI_STOMION, 1), "Stmi": (0.0, PHI_STOMION, -1), "Li": (0.0, -23.0, -1),
    "ChL": (-THETA_COMMISSURE, PHI_STOMION, 0), "ChR": (THETA_COMMISSURE, PHI_STOMION, 0),
    "Pog": (0.0, -40.0, -1), "Me": (0.0, -47.0, -1),
}


@dataclass(frozen=True)
class HeadShape:
    """Shape parameters; the defaults are the generic (mean) head.

    width, height: scale factors of the face about C (x and z); maxilla_ap, mandible_ap:
    antero-posterior position of the jaws (mm, + anterior; maxilla -, mandible + is a class
    III pattern, the opposite class II); chin_projection (mm); lip_thickness (mm added to both
    lips); soft_tissue: factor on all soft-tissue thickness; nose_projection (mm);
    asymmetry: lateral shift of the lower face (mm, + to the patient's right);
    fissure_fade: azimuth span (deg) over which the oral fissure (the groove along the lips'
    contact line) fades out before the commissure at THETA_COMMISSURE. A real mouth corner is
    a sharp feature: the contact line ends in a crease within 1-2 mm (the default, 1 deg ~
    1.4 mm at the corner: where the fissure's lateral end, the cheilion, is defined); the
    generic head keeps its 6 deg fade (`GENERIC`: its committed mesh is built from it).
    """

    width: float = 1.0
    height: float = 1.0
    maxilla_ap: float = 0.0
    mandible_ap: float = 0.0
    chin_projection: float = 0.0
    lip_thickness: float = 0.0
    soft_tissue: float = 1.0
    nose_projection: float = 0.0
    asymmetry: float = 0.0
    fissure_fade: float = 1.0

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "HeadShape":
        names = {f.name for f in fields(cls)}
        return cls(**{k: float(v) for k, v in d.items() if k in names})


GENERIC = HeadShape(fissure_fade=6.0)


# ----------------------------------------------------------------------------- helpers
def smoothstep(e0, e1, x):
    """C1 step from 0 at e0 to 1 at e1 (e1 < e0 gives the decreasing step)."""
    t = np.clip((np.asarray(x, dtype=float) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gauss(x, s):
    return np.exp(-(np.asarray(x) / s) ** 2)


def _smin(a, b, k):
    m = np.minimum(a, b)
    return m - k * np.log(np.exp(-(a - m) / k) + np.exp(-(b - m) / k))


def _smax(a, b, k):
    return -_smin(-a, -b, k)


def direction(theta, phi) -> np.ndarray:
    """Unit ray direction (..., 3) for azimuth theta and elevation phi (degrees)."""
    t, p = np.radians(theta), np.radians(phi)
    cp = np.cos(p)
    return np.stack(np.broadcast_arrays(cp * np.sin(t), cp * np.cos(t), np.sin(p)), axis=-1)


def _ellipsoid_radius(d, centre, axes):
    """Distance from C along unit rays d to an ellipsoid (centre relative to C, inside it)."""
    e = np.asarray(centre, dtype=float)
    a = np.asarray(axes, dtype=float)
    qa = np.sum((d / a) ** 2, axis=-1)
    qb = -2.0 * np.sum(d * e / a**2, axis=-1)
    qc = np.sum((e / a) ** 2, axis=-1) - 1.0
    return (-qb + np.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)


# Dental arch (labial surface of the upper incisors to the molars), horizontal plane:
# x = 29 t^0.35, y = 88 - 48 t, t in [0, 1]; its azimuth seen from C grows with t.
_T = np.linspace(0.0, 1.0, 4001)
_ARCH_X = 29.0 * _T**0.35
_ARCH_Y = 88.0 - 48.0 * _T
_ARCH_TH = np.degrees(np.arctan2(_ARCH_X, _ARCH_Y - CENTRE[1]))
_ARCH_RH = np.hypot(_ARCH_X, _ARCH_Y - CENTRE[1])


def arch_radius_h(theta) -> np.ndarray:
    """Horizontal distance from C to the upper dental arch labial surface at azimuth theta."""
    th = np.clip(np.abs(theta), 0.0, _ARCH_TH[-1])
    return np.interp(th, _ARCH_TH, _ARCH_RH)


# Antero-posterior offsets (mm, horizontal) of the anterior bone profile from the arch.
_OFF_UPPER = PchipInterpolator([-19.0, -12.0, -9.0, -5.5, 0.0, 6.0],
                               [0.0, -0.8, -4.0, -1.5, -2.0, -2.0])
_OFF_LOWER = PchipInterpolator([-70.0, -60.0, -52.0, -46.0, -40.0, -32.0, -26.0, -19.0],
                               [-37.0, -27.0, -17.0, -8.5, -3.0, -7.0, -3.5, -OVERJET])
# Midline soft-tissue thickness of the lower face (mm, along the ray).
_T_MID = PchipInterpolator(
    [-90.0, -77.0, -60.0, -50.0, -46.0, -40.0, -33.0, -26.0, -23.0, -20.0, -19.0, -18.0,
     -14.0, -11.0, -8.0, -3.0, 5.0, 15.0, 45.0],
    [15.0, 15.0, 13.0, 9.5, 9.0, 11.0, 11.5, 14.5, 15.0, 12.5, 12.0, 12.5,
     14.5, 15.5, 15.5, 13.0, 8.0, 7.0, 7.0])
# Nose: thickness profile at the midline and lateral half-width (deg).
_T_NOSE = PchipInterpolator([-12.0, -7.6, -5.0, -2.0, 1.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 45.0],
                            [15.0, 16.0, 24.0, 29.0, 30.5, 28.0, 23.0, 16.0, 10.0, 7.5, 7.0, 7.0])
_W_NOSE = PchipInterpolator([-12.0, -3.0, 8.0, 18.0, 45.0], [10.0, 10.0, 7.5, 6.5, 6.5])


def _side(phi, side):
    """+1 above the mouth line, -1 below; explicit side wins where given (non-zero)."""
    s = np.where(np.asarray(phi) >= PHI_STOMION, 1.0, -1.0)
    if side is None:
        return s
    side = np.asarray(side, dtype=float)
    return np.where(side != 0, np.sign(side), s)


def slit_taper(theta) -> np.ndarray:
    """1 between the commissures (where upper and lower lips may differ), 0 outside."""
    return 1.0 - smoothstep(THETA_COMMISSURE - 6.0, THETA_COMMISSURE, np.abs(theta))


def fissure_taper(theta, shape: HeadShape = GENERIC) -> np.ndarray:
    """1 along the oral fissure, 0 beyond the commissures: the groove of the lips' contact
    line ends at THETA_COMMISSURE, fading over the shape's `fissure_fade` deg (the generic
    head's 6 deg: `slit_taper`)."""
    return 1.0 - smoothstep(THETA_COMMISSURE - shape.fissure_fade, THETA_COMMISSURE, np.abs(theta))


def _upper_weight(theta, phi, side):
    """Weight of the upper jaw (1) against the lower jaw (0): a step at the mouth line
    between the commissures, a smooth transition outside."""
    smooth = smoothstep(PHI_STOMION - 10.0, PHI_STOMION + 6.0, phi)
    step = (_side(phi, side) > 0).astype(float)
    tap = slit_taper(theta)
    return tap * step + (1.0 - tap) * smooth


def _front_radius(theta, phi, side, shape):
    """Anterior (dento-alveolar, symphysis) bone profile along the ray (mm)."""
    up = _upper_weight(theta, phi, side)
    ph = np.asarray(phi, dtype=float)
    off_u = _OFF_UPPER(np.clip(ph, -19.0, 6.0))
    off_l = _OFF_LOWER(np.clip(ph, -70.0, -19.0))
    # Outside the commissures the profiles join continuously at the mouth line.
    off_l = off_l + (1.0 - slit_taper(theta)) * OVERJET * _gauss(ph - PHI_STOMION, 6.0)
    off_l = off_l + shape.chin_projection * _gauss(ph + 41.0, 5.0)
    off = up * off_u + (1.0 - up) * off_l
    cos = np.cos(np.radians(ph))
    return (arch_radius_h(theta) + off) / cos


def _jaw_weights(theta, phi):
    """Smooth weights of the maxillary and mandibular regions (for class II/III shifts)."""
    th = np.abs(theta)
    w_max = smoothstep(PHI_LE_FORT + 5.0, PHI_LE_FORT - 1.0, phi) * (1.0 - smoothstep(30.0, 55.0, th))
    w_mand = (1.0 - smoothstep(75.0, 95.0, th)) * smoothstep(-85.0, -65.0, phi)
    return w_max, w_mand


def deep_radius(theta, phi, shape: HeadShape = GENERIC, side=None) -> np.ndarray:
    """Radius of the deep surface (bone, teeth and vestibule under the lips) along the ray."""
    theta = np.asarray(theta, dtype=float)
    phi = np.asarray(phi, dtype=float)
    d = direction(theta, phi)
    th = np.abs(theta)
    # Facial skeleton: an ellipsoid narrowing towards the jaw, the cranium, a submental floor.
    ax = 60.0 - 10.0 * smoothstep(-5.0, -50.0, phi)
    face = _ellipsoid_radius(d, (0.0, -15.0, -10.0), np.stack(np.broadcast_arrays(ax, 95.0, 85.0), -1))
    cranium = _ellipsoid_radius(d, (0.0, -20.0, 50.0), (72.0, 95.0, 85.0))
    r = _smax(face, cranium, 10.0)
    dz = d[..., 2]
    floor = np.where(dz < -1e-6, 78.0 / np.maximum(-dz, 1e-6), 1e6)
    r = _smin(r, floor, 5.0)
    # Zygomatic prominences and nasal bones.
    r = r + 5.0 * _gauss(th - 45.0, 12.0) * _gauss(phi - 2.0, 9.0)
    r = r + 15.0 * smoothstep(8.0, 28.0, phi) * (1.0 - smoothstep(35.0, 50.0, phi)) * _gauss(theta, 8.5)
    # Anterior dento-alveolar profile and symphysis, blended in around the mouth.
    w = (1.0 - smoothstep(4.0, 34.0, th)) * smoothstep(-64.0, -45.0, phi) * (1.0 - smoothstep(-8.0, 6.0, phi))
    r = (1.0 - w) * r + w * _front_radius(theta, phi, side, shape)
    # Jaw positions (class II / III): antero-posterior shifts of the regions.
    return r + _jaw_shift(theta, phi, side, shape)


def _jaw_shift(theta, phi, side, shape):
    """Radial change that translates the jaw regions antero-posteriorly: a surface facing
    forward moves by dy / d_y along the ray (capped where the ray turns sideways)."""
    if not (shape.maxilla_ap or shape.mandible_ap):
        return 0.0
    up = _upper_weight(theta, phi, side)
    w_max, w_mand = _jaw_weights(theta, phi)
    dy = direction(theta, phi)[..., 1]
    gain = dy / np.maximum(dy * dy, 0.35)
    return gain * (shape.maxilla_ap * up * w_max + shape.mandible_ap * (1.0 - up) * w_mand)


def soft_tissue_thickness(theta, phi, shape: HeadShape = GENERIC) -> np.ndarray:
    """Soft-tissue thickness along the ray (mm) between the deep surface and the skin."""
    theta = np.asarray(theta, dtype=float)
    phi = np.asarray(phi, dtype=float)
    th = np.abs(theta)
    t = 12.0 + 4.0 * _gauss(th - 38.0, 12.0) * _gauss(phi + 15.0, 10.0)   # buccal fat
    t = t + 3.0 * _gauss(th - 24.0, 10.0) * _gauss(phi + 6.0, 8.0)          # malar fat over the canine fossa
    t = t - 5.0 * smoothstep(-5.0, 25.0, phi)                               # infraorbital
    t = t - 3.0 * smoothstep(60.0, 85.0, th)                                # preauricular
    t = t + 3.0 * smoothstep(-50.0, -65.0, phi)                             # submental
    t = t - 3.0 * smoothstep(20.0, 60.0, phi)                               # scalp, far away
    t = t - 4.0 * smoothstep(95.0, 140.0, th)
    mid = _T_MID(np.clip(phi, -90.0, 45.0))
    lips = (PHI_STOMION - 8.0 < phi) & (phi < PHI_STOMION + 8.0)
    mid = mid + shape.lip_thickness * (_gauss(phi + 14.0, 3.5) + _gauss(phi + 23.0, 3.5)) * lips
    w_lip = np.exp(-((th / 24.0) ** 4))
    t = (1.0 - w_lip) * t + w_lip * mid
    # Mouth line: a shallow groove between the lips (the oral fissure), ending at the
    # commissures.
    t = t - 1.5 * _gauss(phi - PHI_STOMION, 1.0) * fissure_taper(theta, shape)
    # Nose.
    tn = _T_NOSE(np.clip(phi, -12.0, 45.0)) + shape.nose_projection * _gauss(phi - 1.0, 8.0)
    wn = nose_weight(theta, phi)
    t = (1.0 - wn) * t + wn * tn
    # scalp: a uniform 5 mm towards the vertex (continuous at the pole)
    t = t + smoothstep(55.0, 80.0, phi) * (5.0 - t)
    return shape.soft_tissue * t


def nose_weight(theta, phi) -> np.ndarray:
    """Weight of the nose (1 on its midline, fading laterally and under subnasale)."""
    phi = np.asarray(phi, dtype=float)
    return _gauss(theta, _W_NOSE(np.clip(phi, -12.0, 45.0))) * smoothstep(-9.5, -6.5, phi) \
        * (1.0 - smoothstep(28.0, 34.0, phi))


def skin_radius(theta, phi, shape: HeadShape = GENERIC, side=None) -> np.ndarray:
    return deep_radius(theta, phi, shape, side) + soft_tissue_thickness(theta, phi, shape)


# ------------------------------------------------------------------- shape warps (x, z)
def _asym_weight(z):
    return smoothstep(-35.0, -80.0, z)


def to_cartesian(theta, phi, rho, shape: HeadShape = GENERIC) -> np.ndarray:
    """Points (..., 3) at radius rho along the rays, with the shape's width/height scaling
    about C and the lateral shift of the lower face applied."""
    q = direction(theta, phi) * np.asarray(rho, dtype=float)[..., None]
    return warp(CENTRE + q, shape)


def warp(q, shape: HeadShape = GENERIC) -> np.ndarray:
    """The shape's global warp of points q of the radial frame: scaling of x (width) and z
    (height) about C, then the lateral shift of the lower face (asymmetry)."""
    p = CENTRE + (np.asarray(q, dtype=float) - CENTRE) * np.array([shape.width, 1.0, shape.height])
    if shape.asymmetry:
        p[..., 0] += shape.asymmetry * _asym_weight(p[..., 2])
    return p


def from_cartesian(p, shape: HeadShape = GENERIC):
    """(theta, phi, rho) in the radial frame of points p (..., 3), undoing the warps."""
    p = np.asarray(p, dtype=float)
    x = p[..., 0] - shape.asymmetry * _asym_weight(p[..., 2]) if shape.asymmetry else p[..., 0]
    q = np.stack([(x - CENTRE[0]) / shape.width, p[..., 1] - CENTRE[1],
                  (p[..., 2] - CENTRE[2]) / shape.height], axis=-1)
    rho = np.linalg.norm(q, axis=-1)
    theta = np.degrees(np.arctan2(q[..., 0], q[..., 1]))
    phi = np.degrees(np.arcsin(np.clip(q[..., 2] / np.maximum(rho, 1e-12), -1.0, 1.0)))
    return theta, phi, rho


# ------------------------------------------------------------------ bone segment regions
def le_fort_line(theta) -> np.ndarray:
    return PHI_LE_FORT + 3.0 * (np.asarray(theta) / 45.0) ** 2


def genioplasty_line(theta) -> np.ndarray:
    return -36.0 - 14.0 * (np.asarray(theta) / 26.0) ** 2


MANDIBLE_BORDER = -62.0      # lower border of the mandible, its underside included (deg)
RAMUS = 50.0                 # azimuth beyond which the ramus replaces the maxilla (deg)


def segment_region(segment: str, theta, phi) -> np.ndarray:
    """Signed angular distance (deg; <= 0 inside) to the region of a bone segment."""
    th = np.abs(np.asarray(theta, dtype=float))
    phi = np.asarray(phi, dtype=float)
    k = OSTEOTOMY_KERF / 2.0
    lf = le_fort_line(th)
    gen = genioplasty_line(th)
    top_crown_u = PHI_STOMION + CROWN_SPAN
    low_crown_l = PHI_STOMION - CROWN_SPAN
    chin = np.maximum(phi - gen, MANDIBLE_BORDER - phi)
    if segment == "chin":
        return np.maximum(chin + k, th - 40.0)
    if segment == "maxilla":
        return np.maximum.reduce([top_crown_u - phi, phi - lf + k, th - RAMUS + k])
    if segment == "mandible":
        body = np.maximum.reduce([phi - low_crown_l, MANDIBLE_BORDER - phi, th - 95.0])
        ramus = np.maximum.reduce([RAMUS - th, phi - 0.0 + k, MANDIBLE_BORDER - phi, th - 95.0])
        return np.maximum(np.minimum(body, ramus), -chin + k)
    if segment == "skull":
        face = np.where(th < RAMUS, lf + k - phi, 0.0 + k - phi)
        return np.maximum.reduce([face, phi - 45.0, th - 105.0])
    raise KeyError(segment)


def bone_radius(theta, phi, shape: HeadShape = GENERIC, side=None) -> np.ndarray:
    """Outer bone surface: the deep surface, except along the dental arches, where the
    alveolar bone follows the arch while the cheek (deep surface) faces the oral cavity."""
    th = np.abs(theta)
    phi = np.asarray(phi, dtype=float)
    r = deep_radius(theta, phi, shape, side)
    # the band lies inside the vestibule (free deep surface: |theta| < 48, phi_s - 10.5 <
    # phi < phi_s + 10), so that bone and deep surface coincide wherever tissue is attached
    band = smoothstep(PHI_STOMION - 10.5, PHI_STOMION - 8.5, phi) \
        * (1.0 - smoothstep(PHI_STOMION + 8.0, PHI_STOMION + 10.0, phi)) \
        * (1.0 - smoothstep(42.0, 46.0, th))
    front = _front_radius(theta, phi, side, shape) + _jaw_shift(theta, phi, side, shape)
    return np.minimum(r, (1.0 - band) * r + band * front)


def teeth_labial_radius(theta, phi, shape: HeadShape = GENERIC, side=None) -> np.ndarray:
    """Labial surface of the teeth along the ray: the arch, TEETH_GAP behind the deep
    surface where the lips rest on the incisors."""
    front = _front_radius(theta, phi, side, shape) + _jaw_shift(theta, phi, side, shape)
    return np.minimum(front, deep_radius(theta, phi, shape, side)) - TEETH_GAP


def _arch_curve(n: int, t_end: float = 0.85):
    """Points (2n+1, 2) of the dental arch labial curve, uniform in arc length, from the last
    tooth on the left to the last on the right, and their outward horizontal normals."""
    t = np.linspace(0.0, t_end, 4001)
    x, y = 29.0 * t**0.35, 88.0 - 48.0 * t
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    u = np.linspace(0.0, s[-1], n + 1)
    xr, yr = np.interp(u, s, x), np.interp(u, s, y)
    pts = np.concatenate([np.stack([-xr[:0:-1], yr[:0:-1]], -1), np.stack([xr, yr], -1)])
    tang = np.gradient(pts, axis=0)
    normal = np.stack([-tang[:, 1], tang[:, 0]], -1)    # outward (labial/buccal)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal[n] = (0.0, 1.0)
    return pts, normal


def mouth_line_z() -> float:
    """z of the mouth line (occlusal plane) at the incisors, generic head."""
    return float(CENTRE[2] + (88.0 - CENTRE[1]) * np.tan(np.radians(PHI_STOMION)))


def teeth_arch(arch: str, shape: HeadShape = GENERIC, n_along: int = 24, n_height: int = 3,
               n_depth: int = 2):
    """Closed triangulated dental arch, 'upper' (maxilla) or 'lower' (mandible): crowns 10 mm
    high from the occlusal plane, the front ones' incisal edges INCISAL_CLEARANCE off the
    mouth line (apart where the lips meet), labial surface TEETH_GAP behind the lip mucosa on
    the incisors (the lower arch OVERJET behind the upper), 7 mm (incisors) to 10 mm (molars)
    deep, shifted with the jaw (maxilla_ap / mandible_ap) and warped with the head."""
    from facemodel._structured import box_surface, orient_outward

    upper = arch == "upper"
    pts, normal = _arch_curve(n_along)
    params, tri = box_surface(len(pts) - 1, n_height, n_depth)
    iu = np.rint(params[:, 0] * (len(pts) - 1)).astype(int)
    frac = np.abs(np.linspace(-1.0, 1.0, len(pts)))[iu]
    depth = 7.0 + 3.0 * frac**2
    xy = pts[iu] - normal[iu] * (TEETH_GAP + depth[:, None] * params[:, 2:3])
    # crowns reaching 9.7 mm from the occlusal surface: the mouth-line cone (phi = PHI_STOMION
    # +- 0.3 deg seen from C, the surface the lips part along) at the front teeth, so that no
    # lip node starts inside a tooth, blending into the flat occlusal plane at the back; the
    # front crowns' incisal edges INCISAL_CLEARANCE further off it (their other end kept)
    rh = np.hypot(xy[:, 0] - CENTRE[0], xy[:, 1] - CENTRE[1])
    az = np.degrees(np.abs(np.arctan2(xy[:, 0] - CENTRE[0], xy[:, 1] - CENTRE[1])))
    w_cone = 1.0 - smoothstep(16.0, 26.0, az)
    sgn = 1.0 if upper else -1.0
    cone = CENTRE[2] + rh * np.tan(np.radians(PHI_STOMION + sgn * 0.3))
    plane = mouth_line_z() + sgn * 0.3
    edge = w_cone * INCISAL_CLEARANCE
    z = (w_cone * cone + (1.0 - w_cone) * plane + sgn * edge
         + sgn * (9.7 - edge) * params[:, 1])
    if upper:
        xy[:, 1] += shape.maxilla_ap
    else:
        xy[:, 1] += shape.mandible_ap - OVERJET
    # keep the front crowns behind the lips where the anterior alveolar profile recedes
    # (crown tips towards the vestibule): pull them back along their rays to the labial
    # radius (the innermost layer 2 mm further in, so that no crown flattens)
    q = np.column_stack([xy, z])
    th, ph, rho = from_cartesian(q)
    side = np.full_like(th, 1.0 if upper else -1.0)
    lim = teeth_labial_radius(th, ph, shape, side=side) - 2.0 * params[:, 2]
    rho = np.where(np.abs(th) < 22.0, np.minimum(rho, lim), rho)
    q = CENTRE + direction(th, ph) * rho[:, None]
    verts = warp(q, shape)
    return verts, orient_outward(verts, tri)


def _segment_bounds(segment: str, theta):
    """Lower and upper elevation (deg) of a bone segment's shell at azimuth theta (the
    regions of `segment_region`, with the ramus step smoothed over 8 deg)."""
    th = np.abs(theta)
    k = OSTEOTOMY_KERF / 2.0
    ramus = smoothstep(RAMUS - 4.0, RAMUS + 4.0, th)
    if segment == "skull":
        return (1.0 - ramus) * (le_fort_line(th) + k) + ramus * k, np.full_like(th, 45.0)
    if segment == "maxilla":
        return np.full_like(th, PHI_STOMION + CROWN_SPAN), le_fort_line(th) - k
    if segment == "chin":
        return np.full_like(th, MANDIBLE_BORDER), genioplasty_line(th) - k
    if segment == "mandible":
        lo = np.maximum(MANDIBLE_BORDER, genioplasty_line(th) + k)
        return lo, (1.0 - ramus) * (PHI_STOMION - CROWN_SPAN) + ramus * (0.0 - k)
    raise KeyError(segment)


SEGMENT_AZIMUTH = {"skull": 105.0, "maxilla": RAMUS - 2.0, "mandible": 95.0, "chin": 25.0}


def bone_shell(segment: str, shape: HeadShape = GENERIC, n_theta: int = 120, n_phi: int = 40,
               n_depth: int = 2):
    """Closed triangulated shell (BONE_SHELL mm thick under the outer bone surface) of a
    bone segment: skull (facial part), maxilla (Le Fort I), mandible, chin (genioplasty)."""
    from facemodel._structured import box_surface, orient_outward

    params, tri = box_surface(n_theta, n_phi, n_depth)
    tmax = SEGMENT_AZIMUTH[segment]
    # the chin ends where the genioplasty line meets the lower border
    if segment == "chin":
        tmax = 26.0 * np.sqrt((-MANDIBLE_BORDER - 36.0 - OSTEOTOMY_KERF / 2) / 14.0)
    theta = (2.0 * params[:, 0] - 1.0) * tmax
    lo, hi = _segment_bounds(segment, theta)
    if segment == "chin":
        hi = np.maximum(hi, lo + 0.5)
    phi = lo + (hi - lo) * params[:, 1]
    side = np.full_like(theta, 1.0 if segment in ("skull", "maxilla") else -1.0)
    outer = bone_radius(theta, phi, shape, side=side)
    rho = outer - BONE_SHELL * (1.0 - params[:, 2])
    verts = to_cartesian(theta, phi, rho, shape)
    return verts, orient_outward(verts, tri)


# ------------------------------------------------------------- anatomical soft-tissue landmarks
STOMION_INSET = 0.3          # deg inside its own lip at which each stomion is taken (~0.5 mm)
# deg: menton is the chin's lowest point along the direction this far in front of straight down
# (the chin's inferior border taken as a line descending MENTON_TILT deg backwards; see
# `anatomical_landmarks`). Of 20-55 deg, 35 makes the point best defined over 64 synthetic
# heads: the profile stays within 0.15 mm of its extreme over a median 3.2 mm of arc, at most
# 4.3 mm on all but one (30 deg: 3.7 / up to 12 mm, the chin's wavy underside has two
# near-equal extremes on several heads)
MENTON_TILT = 35.0


def midline_profile(shape: HeadShape = GENERIC, step: float = 0.02, phi_range=(-70.0, 30.0)):
    """The mid-sagittal skin profile: elevations phi (descending), points (k, 3) on the
    theta = 0 ray curve (the face's own midline, shifted sideways with the lower face on an
    asymmetric head) and the lip side (+1 above the mouth line, -1 below)."""
    phi = np.arange(phi_range[1], phi_range[0] - step / 2, -step)
    side = np.where(phi >= PHI_STOMION, 1.0, -1.0)
    pts = to_cartesian(np.zeros_like(phi), phi, skin_radius(0.0, phi, shape, side=side), shape)
    return phi, pts, side


def _deepest_under_bitangent(p: np.ndarray, i0: int, i1: int) -> tuple[int, int]:
    """On the profile arc p[i0..i1] ((k, 2) as (anterior y, superior z), ordered downwards):
    the anterior convex hull edge that spans the arc's deepest concavity, as (index of the
    deepest point under it, index of the hull vertex that closes it below)."""
    k, _, j, _ = deepest_concavity(p, i0, i1)
    return k, j


def menton_direction() -> np.ndarray:
    """(anterior y, superior z) unit direction along which menton is the chin's extremal
    point: MENTON_TILT deg in front of straight down."""
    a = np.radians(MENTON_TILT)
    return np.array([np.sin(a), -np.cos(a)])


def anatomical_landmarks(shape: HeadShape = GENERIC) -> dict:
    """Soft-tissue landmarks (mm RAS) at their anatomical definitions on the exact skin (Farkas,
    Anthropometry of the Head and Face, 1994; Swennen et al., Three-Dimensional Cephalometry,
    2006), in the head's frame (x right, y anterior, z superior, Frankfort plane z = 0), on the
    mid-sagittal profile (`midline_profile`) except the cheilia:
      Prn  pronasale: the most anterior point of the nose (max y above the mouth);
      Stms / Stmi  stomion superius / inferius: the lowest point of the upper lip and the
           highest of the lower lip, at the mouth line (STOMION_INSET inside each lip, so that
           each sits on its own lip and not on the step between them);
      Sn   subnasale: the deepest point of the nasolabial concavity between pronasale and the
           upper lip, i.e. farthest behind the profile's anterior bitangent that spans it;
      Ls   labrale superius: the most anterior point of the upper lip (below subnasale);
      Li   labrale inferius: the most anterior point of the lower lip, above the labiomental
           fold (the deepest point under the anterior bitangent of lower lip and chin);
      Pog  soft-tissue pogonion: the most anterior point of the chin, below that fold: the
           summit past the bottom of the fold's valley (a chin receding down to the
           mandible's border has none: the fold's lower edge);
      Me   soft-tissue menton: the lowest point of the chin's contour, below pogonion. The
           submental contour of these heads keeps descending backwards (13-22 deg below the
           Frankfort horizontal: they have no throat), so the profile's lowest point in the
           head frame lies on the neck, not on the chin; the chin's lowest point is taken
           against the chin's inferior border, a line descending MENTON_TILT deg backwards,
           steeper than the submental contour and flatter than the chin's front: the profile
           point below pogonion farthest along the direction MENTON_TILT deg in front of
           straight down (where the chin's curve turns into the submental contour, its tangent
           at MENTON_TILT deg);
      ChL / ChR  cheilion: the mouth corners, the lateral ends of the oral fissure
           (theta = +-THETA_COMMISSURE on the mouth line, where its groove and the lips'
           offset end; `HeadShape.fissure_fade`)."""
    phi, pts, side = midline_profile(shape)
    yz = pts[:, 1:]
    upper = np.flatnonzero(phi >= PHI_STOMION + STOMION_INSET)
    lower = np.flatnonzero(phi <= PHI_STOMION - STOMION_INSET)
    out = {}
    i_prn = int(upper[np.argmax(yz[upper, 0])])
    i_stms, i_stmi = int(upper[-1]), int(lower[0])
    i_sn, _ = _deepest_under_bitangent(yz, i_prn, i_stms)
    i_ls = i_sn + int(np.argmax(yz[i_sn:i_stms + 1, 0]))
    i_end = int(np.flatnonzero(phi >= -62.0)[-1])       # the lower border of the mandible
    i_fold, _ = _deepest_under_bitangent(yz, i_stmi, i_end)
    i_li = i_stmi + int(np.argmax(yz[i_stmi:i_fold + 1, 0]))
    # the chin's summit: the most anterior point past the bottom of the fold's valley (where
    # the profile stops receding going down). Taken over the whole arc below the fold, the
    # maximum would jump 10 mm between the fold's lower edge and the summit whenever the two
    # stand within a fraction of a mm of each other (a chin barely in front of its fold); a
    # chin that recedes down to the mandible's border has no summit: its fold's lower edge
    k = i_fold
    while k < i_end and yz[k + 1, 0] <= yz[k, 0]:
        k += 1
    i_pog = i_fold if k >= i_end else k + int(np.argmax(yz[k:i_end + 1, 0]))
    i_me = i_pog + int(np.argmax(yz[i_pog:] @ menton_direction()))
    for name, i in (("Prn", i_prn), ("Sn", i_sn), ("Ls", i_ls), ("Stms", i_stms), ("Stmi", i_stmi),
                    ("Li", i_li), ("Pog", i_pog), ("Me", i_me)):
        out[name] = pts[i].copy()
    for name in ("ChL", "ChR"):
        t, p, sd = LANDMARK_ANGLES[name]
        out[name] = to_cartesian(t, p, skin_radius(t, p, shape, side=sd), shape)
    return {k: out[k] for k in LANDMARK_ANGLES}
