"""A second, independently built family of synthetic heads: superquadrics with Gaussian features.

`facemodel.synthetic` draws heads from the same radial ellipsoid-blend geometry the generic
mesh is built from (`facemodel.head_geometry`), so a registration tuned on them may rely on
that kinship. This family shares nothing with it but the frame (patient RAS, mm, Frankfort
plane near z = 0): the skin is a superquadric ("superellipsoid", Barr, IEEE CG&A 1:11-23,
1981) about a centre C,
    G(p) = (|p_x / a|^n + |p_y / b|^n)^(m / n) + |p_z / c|^m = 1,  p = q - C,
whose radius along a unit ray d is r0(d) = G(d)^(-1/m) (G is homogeneous of degree m), with
the horizontal exponent n in 2.2-3.4 (round to blocky), the vertical one m in 2.0-2.9, a
front semi-axis b_f of its own (flat or deep faces) and the half-width a tapered towards
the jaw. Facial features are anisotropic Gaussian bumps of the base point's (x, z), added
along the ray: a nasal ridge with an asymmetric profile (long above the tip, short below),
alae, a perioral prominence over the dental arches, two lip rolls with an oral fissure between them (a narrow groove ending at the mouth
corners), a chin prominence and labiomental fold, cheek pads, a brow ridge and orbital
hollows. The bone surface is the skin minus a soft-tissue thickness map T of its own (a
smooth lower-face profile with random low-order modulation, plus the soft parts of the
features: nose, lips, fissure, cheeks, most of the chin), at least 4 mm everywhere. Bone
segments (skull, maxilla, mandible, chin) are closed 5 mm shells of that surface over angular
regions cut by a Le Fort I line, the occlusal plane and a genioplasty line (built with
`facemodel._structured.box_surface`); the skin is a geodesic sphere projected along the rays.
Soft-tissue landmarks (Farkas 1994 definitions: extremal points and concavities of the
mid-sagittal profile, the mouth corners at the fissure's ends) are found numerically on the
profile of the exact skin, then taken as the closest points of the triangulated one. Where a
definition has no anatomical answer on a head (labrale inferius where the lower lip's roll
stands behind the fissure's edge, about a quarter of the heads) the head says so
(`AltHead.ill_defined`).

`crop_face` makes the partial skins a planning CBCT or a surface scan gives: the face only
(in front of the ears, down under the chin), cut below the eyes, at mid-nose, or a whole-face
scan, as open surfaces.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

CENTRE = np.array([0.0, 15.0, -35.0])

# (low, high) of each shape parameter
RANGES = {
    "n_h": (2.0, 3.0), "m_v": (2.0, 2.9), "half_width": (64.0, 76.0), "front": (70.0, 82.0),
    "up": (64.0, 76.0), "down": (74.0, 88.0), "jaw_taper": (0.08, 0.28),
    "nose_height": (15.0, 24.0), "nose_width": (7.0, 11.0), "nose_tip_z": (-21.0, -13.0),
    "mouth_z": (-53.0, -45.0), "mouth_half_width": (20.0, 28.0), "fissure_depth": (1.5, 3.0),
    "upper_lip": (4.0, 9.0), "lower_lip": (3.5, 9.0), "lip_offset": (-3.0, 3.0),
    "chin": (6.0, 13.0), "chin_z": (-94.0, -82.0), "fold": (2.0, 5.0), "cheek": (3.0, 8.0), "muzzle": (3.0, 7.0),
    "soft_lower": (10.0, 16.0), "soft_upper": (4.5, 7.0), "chin_bone_fraction": (0.3, 0.6),
    "modulation": (0.0, 0.18), "yaw_deg": (-3.0, 3.0), "pitch_deg": (-4.0, 4.0),
}


@dataclass(frozen=True)
class AltShape:
    """Parameters of a head of this family (mm, degrees; see RANGES)."""

    n_h: float = 2.6
    m_v: float = 2.4
    half_width: float = 70.0
    front: float = 80.0
    up: float = 70.0
    down: float = 80.0
    jaw_taper: float = 0.18
    nose_height: float = 19.0
    nose_width: float = 9.0
    nose_tip_z: float = -20.0
    mouth_z: float = -49.0
    mouth_half_width: float = 24.0
    fissure_depth: float = 2.2
    upper_lip: float = 6.0
    lower_lip: float = 6.0
    lip_offset: float = 0.0
    chin: float = 7.0
    chin_z: float = -88.0
    fold: float = 2.5
    cheek: float = 5.0
    muzzle: float = 9.0
    soft_lower: float = 13.0
    soft_upper: float = 5.5
    chin_bone_fraction: float = 0.45
    modulation: float = 0.1
    phase: tuple = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


def random_alt_shape(seed: int) -> AltShape:
    """Shape of head `seed` of this family (deterministic, uniform in RANGES)."""
    rng = np.random.default_rng(np.random.SeedSequence([20261125, 17, int(seed)]))
    draw = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in RANGES.items()}
    draw["phase"] = tuple(float(v) for v in rng.uniform(0, 2 * np.pi, 3))
    return AltShape(**draw)


def _gauss(u, s):
    return np.exp(-0.5 * (u / s) ** 2)


def _smooth01(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _base_radius(d: np.ndarray, s: AltShape) -> np.ndarray:
    """Superquadric radius along unit rays d (..., 3) from CENTRE (closed form, G homogeneous)."""
    zd = d[..., 2]
    # the half-width narrows towards the jaw: rays going down and forward
    taper = 1.0 - s.jaw_taper * _smooth01(-zd / 0.8) * _smooth01(d[..., 1] / 0.3 + 0.5)
    a = s.half_width * taper
    b = np.where(d[..., 1] > 0, s.front, 95.0)
    c = np.where(zd > 0, s.up, s.down)
    g = (np.abs(d[..., 0] / a) ** s.n_h + np.abs(d[..., 1] / b) ** s.n_h) ** (s.m_v / s.n_h) \
        + np.abs(zd / c) ** s.m_v
    return g ** (-1.0 / s.m_v)


def _features(p: np.ndarray, d: np.ndarray, s: AltShape):
    """(skin bumps, soft part of them) at base points p (..., 3) along rays d (mm)."""
    x, z = p[..., 0], p[..., 2]
    front = _smooth01((d[..., 1] - 0.15) / 0.5)      # only the face carries features
    zt = s.nose_tip_z
    # nasal ridge: rises from the nasion to the tip, falls quickly to the columella
    prof = np.where(z > zt, _gauss(z - zt, 17.0), _gauss(z - zt, 5.5))
    nose = s.nose_height * prof * _gauss(x, s.nose_width * (0.55 + 0.45 * _smooth01((zt + 8 - z) / 12.0)))
    alae = 0.3 * s.nose_height * _gauss(z - (zt - 4.0), 4.0) * (_gauss(x - 14.0, 4.5) + _gauss(x + 14.0, 4.5))
    mz = s.mouth_z
    wide = _smooth01((s.mouth_half_width + 4.0 - np.abs(x)) / 8.0)
    ul = s.upper_lip * _gauss(z - (mz + 5.0), 4.5) * _gauss(x, 0.75 * s.mouth_half_width)
    ll = s.lower_lip * _gauss(z - (mz - 5.5), 4.5) * _gauss(x, 0.7 * s.mouth_half_width) \
        + s.lip_offset * _gauss(z - (mz - 3.0), 3.0) * wide
    fissure = -s.fissure_depth * _gauss(z - mz, 1.3) * wide
    chin = s.chin * _gauss(z - s.chin_z, 7.0) * _gauss(x, 15.0)
    fold = -s.fold * _gauss(z - 0.5 * (mz - 5.5 + s.chin_z), 4.0) * _gauss(x, 14.0)
    cheek = s.cheek * _gauss(z + 32.0, 13.0) * (_gauss(x - 42.0, 14.0) + _gauss(x + 42.0, 14.0))
    # the perioral region stands out of the face over the dental arches
    muzzle = s.muzzle * _gauss(z - (mz - 2.0), 10.0) * _gauss(x, 19.0)
    brow = 4.0 * _gauss(z - 14.0, 6.0) * _gauss(x, 35.0)
    orbit = -6.0 * _gauss(z - 6.0, 8.0) * (_gauss(x - 32.0, 10.0) + _gauss(x + 32.0, 10.0))
    skin = front * (nose + alae + ul + ll + fissure + chin + fold + cheek + muzzle + brow + orbit)
    soft = front * (nose + alae + ul + ll + fissure + (1.0 - s.chin_bone_fraction) * chin + fold
                    + cheek + orbit)
    return skin, soft


def _thickness(p: np.ndarray, d: np.ndarray, s: AltShape) -> np.ndarray:
    """Soft-tissue thickness under the featureless skin: soft_upper above the nose, rising to
    soft_lower over the lower face, modulated by a random low-order field."""
    x, z = p[..., 0], p[..., 2]
    low = _smooth01((-10.0 - z) / 30.0)
    t = s.soft_upper + (s.soft_lower - s.soft_upper) * low
    ph = s.phase
    mod = 1.0 + s.modulation * (np.sin(x / 23.0 + ph[0]) * np.cos(z / 31.0 + ph[1])
                                + 0.5 * np.sin((x + z) / 17.0 + ph[2]))
    return t * mod


def radii(d: np.ndarray, s: AltShape) -> tuple[np.ndarray, np.ndarray]:
    """(skin radius, bone radius) along unit rays d (..., 3) from CENTRE."""
    d = np.asarray(d, dtype=float)
    r0 = _base_radius(d, s)
    p = CENTRE + d * r0[..., None]
    bump, soft = _features(p, d, s)
    skin = r0 + bump
    bone = skin - np.maximum(_thickness(p, d, s) + soft, 4.0)
    return skin, bone


def _ray(theta, phi) -> np.ndarray:
    t, p = np.radians(theta), np.radians(phi)
    return np.stack(np.broadcast_arrays(np.cos(p) * np.sin(t), np.cos(p) * np.cos(t), np.sin(p)), -1)


def _pose(s: AltShape) -> np.ndarray:
    """The head's own small rotation (yaw, pitch) about CENTRE: heads are not all posed alike."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("zx", [s.yaw_deg, s.pitch_deg], degrees=True).as_matrix()


def _place(q: np.ndarray, s: AltShape) -> np.ndarray:
    return CENTRE + (np.asarray(q) - CENTRE) @ _pose(s).T


def skin_surface(s: AltShape, subdivisions: int = 6):
    """Closed skin (trimesh): a geodesic sphere (subdivisions 6: 41k vertices, ~1.8 mm edges
    on the face) projected along its rays."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    d = np.asarray(ico.vertices)
    r, _ = radii(d, s)
    return trimesh.Trimesh(_place(CENTRE + d * r[:, None], s), np.asarray(ico.faces), process=False)


# angular regions (theta, phi about CENTRE, deg) of the bone segments
def _le_fort(theta):
    return 5.0 + 3.0 * (np.asarray(theta) / 45.0) ** 2


def _genioplasty(theta):
    return -29.0 - 9.0 * (np.asarray(theta) / 22.0) ** 2


BORDER = -44.0      # lower border of the mandible (elevation)
OCCLUSAL = -10.0    # the occlusal plane between maxilla and mandible
KERF = 0.8


def _segment_bounds(seg: str, theta):
    th = np.abs(theta)
    if seg == "skull":
        return _le_fort(th) + KERF, np.full_like(th, 48.0)
    if seg == "maxilla":
        return np.full_like(th, OCCLUSAL + KERF), _le_fort(th) - KERF
    if seg == "mandible":
        return np.maximum(BORDER, _genioplasty(th) + KERF), np.full_like(th, OCCLUSAL - KERF)
    if seg == "chin":
        return np.full_like(th, BORDER - 2.0), np.maximum(_genioplasty(th) - KERF, BORDER - 1.0)
    raise KeyError(seg)


SEGMENT_AZIMUTH = {"skull": 100.0, "maxilla": 48.0, "mandible": 90.0,
                   "chin": 22.0 * np.sqrt((-BORDER - 29.0) / 9.0)}
SHELL = 5.0


def bone_surfaces(s: AltShape, n_theta: int = 90, n_phi: int = 24) -> dict:
    """Closed shells (trimesh per segment) SHELL mm thick under the bone surface."""
    import trimesh

    from facemodel._structured import box_surface, orient_outward

    out = {}
    for seg, tmax in SEGMENT_AZIMUTH.items():
        frac = tmax / 100.0
        params, tri = box_surface(max(6, int(n_theta * frac)), n_phi if seg != "maxilla" else 8, 2)
        theta = (2.0 * params[:, 0] - 1.0) * tmax
        lo, hi = _segment_bounds(seg, theta)
        phi = lo + (hi - lo) * params[:, 1]
        d = _ray(theta, phi)
        _, bone = radii(d, s)
        rho = bone - SHELL * (1.0 - params[:, 2])
        v = _place(CENTRE + d * rho[:, None], s)
        out[seg] = trimesh.Trimesh(v, orient_outward(v, tri), process=False)
    return out


def _profile(s: AltShape, step: float = 0.05):
    phi = np.arange(40.0, -70.0, -step)
    d = _ray(np.zeros_like(phi), phi)
    r, _ = radii(d, s)
    return phi, CENTRE + d * r[:, None]


def _deepest_between(yz: np.ndarray, i0: int, i1: int) -> int:
    """Index of the profile point farthest behind the chord from i0 to i1."""
    a, b = yz[i0], yz[i1]
    t = b - a
    nrm = np.array([t[1], -t[0]]) / np.linalg.norm(t)
    if nrm[0] > 0:
        nrm = -nrm
    return i0 + int(np.argmax((yz[i0:i1 + 1] - a) @ nrm))


def _labrale_inferius(pts: np.ndarray, s: AltShape) -> tuple[int, bool]:
    """Labrale inferius on the profile `pts` (head frame): the most anterior point of the lower
    lip, between the fissure and the chin; and whether it is a prominence (a point inside that
    range). Where the lower lip's roll stands behind the fissure's lower edge the definition
    gives that edge, not the lip's vermilion border."""
    lower = np.flatnonzero((pts[:, 2] < s.mouth_z - 0.4) & (pts[:, 2] > s.chin_z + 4.0))
    j = int(np.argmax(pts[lower, 1]))
    return int(lower[j]), j > 0


def ill_defined_landmarks(s: AltShape) -> tuple:
    """The landmarks whose definition has no anatomical answer on head shape `s`: labrale
    inferius where the lower lip's roll stands behind the fissure's edge (`_labrale_inferius`).
    `alt_landmarks` still gives the definition's point; a benchmark judges these apart."""
    _, pts = _profile(s)
    return () if _labrale_inferius(pts, s)[1] else ("Li",)


def alt_landmarks(s: AltShape, skin=None) -> dict:
    """Soft-tissue landmarks of the exact skin (head frame before its pose), then posed and,
    given the triangulated skin, taken as its closest points."""
    phi, pts = _profile(s)
    yz = pts[:, 1:]
    mz = s.mouth_z
    above = np.flatnonzero((pts[:, 2] > mz + 15.0) & (pts[:, 2] < s.nose_tip_z + 25))
    i_prn = int(above[np.argmax(yz[above, 0])])
    i_stms = int(np.flatnonzero(pts[:, 2] >= mz + 0.5)[-1])
    # subnasale: the deepest point behind the chord from pronasale to the upper stomion;
    # labrale superius: the most anterior point of the upper lip below it
    i_sn = _deepest_between(yz, i_prn, i_stms)
    i_ls = i_sn + int(np.argmax(yz[i_sn:i_stms + 1, 0]))
    i_stmi = int(np.flatnonzero(pts[:, 2] <= mz - 0.5)[0])
    i_li, _ = _labrale_inferius(pts, s)
    # soft pogonion: the most anterior point of the chin's prominence
    chin = np.flatnonzero(np.abs(pts[:, 2] - s.chin_z) < 10.0)
    i_pog = int(chin[np.argmax(yz[chin, 0])])
    a = np.radians(35.0)
    below = np.flatnonzero((np.arange(len(pts)) >= i_pog) & (pts[:, 2] > s.chin_z - 20.0))
    i_me = int(below[np.argmax(yz[below] @ np.array([np.sin(a), -np.cos(a)]))])
    out = {k: pts[i].copy() for k, i in (("Prn", i_prn), ("Sn", i_sn), ("Ls", i_ls), ("Stms", i_stms),
                                         ("Stmi", i_stmi), ("Li", i_li), ("Pog", i_pog), ("Me", i_me))}
    # cheilia: the fissure's lateral ends on the mouth line (where its groove has faded to
    # half its depth), found along the line z = mouth_z on the skin
    xs = np.linspace(0.0, s.mouth_half_width + 8.0, 400)
    for name, sign in (("ChR", 1.0), ("ChL", -1.0)):
        # rays through points of the base surface at height mouth_z: solve by fixed point
        theta = np.degrees(np.arctan2(sign * xs, 80.0))
        phi_m = np.degrees(np.arctan2(mz - CENTRE[2], 80.0)) * np.ones_like(xs)
        d = _ray(theta, phi_m)
        wide = _smooth01((s.mouth_half_width + 4.0 - xs) / 8.0)
        k = int(np.argmin(np.abs(wide - 0.5)))
        r, _ = radii(d[k], s)
        out[name] = CENTRE + d[k] * r
    names = ["Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "ChL", "ChR", "Pog", "Me"]
    out = {k: _place(out[k], s) for k in names}
    if skin is not None:
        import trimesh

        on, _, _ = trimesh.proximity.closest_point(skin, np.array([out[k] for k in names]))
        out = {k: np.asarray(v, float) for k, v in zip(names, on)}
    return out


@dataclass(frozen=True, eq=False)
class AltHead:
    seed: int
    shape: AltShape
    skin: object          # trimesh.Trimesh (closed, or open once cropped)
    bones: dict           # segment -> trimesh.Trimesh
    teeth: dict = field(default_factory=dict)
    landmarks: dict = field(default_factory=dict)
    # landmarks whose definition is degenerate on this head (`ill_defined_landmarks`)
    ill_defined: tuple = ()


def alt_head(seed: int, subdivisions: int = 6) -> AltHead:
    """Head `seed` of this family: closed skin, bone segments and landmarks."""
    s = random_alt_shape(seed)
    skin = skin_surface(s, subdivisions)
    return AltHead(int(seed), s, skin, bone_surfaces(s), {}, alt_landmarks(s, skin), ill_defined_landmarks(s))


# crop heights (z, mm, in the head frame before its pose): the partial skins of practice
CUTS = {"scan": 30.0, "below_eyes": -2.0, "mid_nose": -14.0}


def crop_face(head, cut: str = "below_eyes", *, ear_y: float = 30.0, chin_margin_mm: float = 12.0):
    """The head with its skin cut to the face region: in front of the ears (y > ear_y), down
    under the chin (to chin_margin_mm below menton) and up to the height CUTS[cut] (a CBCT
    field of view ending below the eyes or at mid-nose; "scan": a face scan to the forehead).
    The cut is made in the head's own frame (before its pose) and only the connected piece
    around the nose is kept: an open surface."""
    import trimesh

    pose = _pose(head.shape) if isinstance(head, AltHead) else np.eye(3)
    centre = CENTRE if isinstance(head, AltHead) else np.zeros(3)
    v = np.asarray(head.skin.vertices)
    local = centre + (v - centre) @ pose          # undo the pose (pose.T inverse)
    z_top = CUTS[cut] if cut in CUTS else float(cut)
    me = np.asarray(head.landmarks["Me"], float)
    z_bottom = (centre + (me - centre) @ pose)[2] - chin_margin_mm
    keep_v = (local[:, 1] > ear_y) & (local[:, 2] < z_top) & (local[:, 2] > z_bottom)
    f = np.asarray(head.skin.faces)
    faces = f[keep_v[f].all(axis=1)]
    mesh = trimesh.Trimesh(v, faces, process=False)
    parts = mesh.split(only_watertight=False)
    prn = np.asarray(head.landmarks["Prn"], float)
    best = min(parts, key=lambda m: float(np.min(np.linalg.norm(m.vertices - prn, axis=1))))
    best = trimesh.Trimesh(np.asarray(best.vertices), np.asarray(best.faces), process=False)
    return type(head)(**{**{k: getattr(head, k) for k in head.__dataclass_fields__}, "skin": best})
