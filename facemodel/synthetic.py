"""Synthetic patients: random plausible heads from the parametric head geometry.

A seed draws shape parameters (`head_geometry.HeadShape`: face width and height, class II /
III jaw positions, chin projection, lip and soft-tissue thickness, nose, mild asymmetry; the
mouth corners are anatomical ones, the oral fissure ending in a crease, `fissure_fade`) in
ranges of adult orthognathic patients (jaw discrepancies of a few mm to ~8 mm, the range of
cephalometric norms +-2 SD, e.g. McNamara J.A., Am J Orthod 86:449-469, 1984), with a
guaranteed difference from the generic head so that registration has real work (RMS skin
difference over the face of at least MIN_DIFFERENCE mm). The skin is the zero set of the
radial implicit function |q - C| - R_skin(theta, phi); it is meshed either by projecting a
geodesic sphere along the rays (default: watertight by construction and bit-reproducible;
graded by a conformal Moebius zoom so that the face has facets of ~0.75-1 mm as a CT-derived
skin would, 41k vertices in all)
or by CGAL's restricted-Delaunay surface mesher through pygalmesh (facet angle, size and
distance criteria, Boissonnat & Oudot, Graph Models 67:405-451, 2005; the implicit function
is tabulated on a (theta, phi) grid and evaluated by a numba kernel, so that the mesher's
scalar queries stay cheap; CGAL's triangulation is not reproducible run to run). The bone
segments (skull, maxilla, mandible, chin) are closed shells of the facial skeleton cut along
Le Fort I, the mouth line and a genioplasty line, swept as structured surfaces of the same
radial bone function; the teeth are swept closed arches; landmarks are placed by their
anatomical definitions on the exact skin, then picked on the triangulated skin (closest point).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from facemodel import head_geometry as hg

MIN_DIFFERENCE = 3.0     # mm RMS skin difference from the generic head
# The patient skin as a scan: a CT-derived skin (marching cubes on 0.5-1 mm voxels) has
# vertices every 0.5-1 mm; the synthetic scan has facets of SCAN_SIZE mm over the face (the
# geodesic sphere graded by SCAN_ZOOM towards FACE_CENTRE, `face_zoom`), coarser at the back
FACE_CENTRE = (0.0, -15.0)   # (theta, phi) deg: between the nose and the chin
SCAN_SIZE = 1.0              # mm (measured median edges: lips 0.74, nose 0.97, chin 1.02 mm)
SCAN_ZOOM = 2.5


# (low, high) ranges of the shape parameters drawn for a synthetic patient
RANGES = {
    "width": (0.93, 1.07), "height": (0.93, 1.07), "maxilla_ap": (-4.0, 3.0),
    "mandible_ap": (-7.0, 7.0), "chin_projection": (-3.0, 3.0), "lip_thickness": (-2.0, 2.0),
    "soft_tissue": (0.85, 1.2), "nose_projection": (-3.0, 3.0), "asymmetry": (-2.5, 2.5),
}


@dataclass(frozen=True, eq=False)
class SyntheticHead:
    seed: int
    shape: hg.HeadShape
    skin: object                     # trimesh.Trimesh, closed
    bones: dict                      # segment -> trimesh.Trimesh, closed
    teeth: dict                      # "upper"/"lower" -> (vertices, faces, segment)
    landmarks: dict = field(default_factory=dict)   # name -> (3,) mm RAS


def face_difference(shape: hg.HeadShape, reference: hg.HeadShape = hg.GENERIC) -> float:
    """RMS distance (mm) between the skins of two shapes over the face (rays of the face)."""
    th, ph = np.meshgrid(np.linspace(-80, 80, 81), np.linspace(-70, 20, 46))
    a = hg.to_cartesian(th, ph, hg.skin_radius(th, ph, shape), shape)
    b = hg.to_cartesian(th, ph, hg.skin_radius(th, ph, reference), reference)
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def random_shape(seed: int) -> hg.HeadShape:
    """Shape parameters of patient `seed` (deterministic), at least MIN_DIFFERENCE mm RMS
    away from the generic head (deviations scaled up from the mean if needed)."""
    rng = np.random.default_rng(np.random.SeedSequence([20261122, int(seed)]))
    base = hg.GENERIC.as_dict()
    draw = {k: rng.uniform(lo, hi) for k, (lo, hi) in RANGES.items()}
    # a real orthognathic patient: the jaws are off by at least 3 mm in one direction
    if abs(draw["mandible_ap"] - draw["maxilla_ap"]) < 3.0:
        draw["mandible_ap"] = draw["maxilla_ap"] + (3.0 if draw["mandible_ap"] >= draw["maxilla_ap"] else -3.0)
    shape = hg.HeadShape.from_dict(draw)
    for _ in range(20):
        if face_difference(shape) >= MIN_DIFFERENCE:
            break
        draw = {k: base[k] + 1.25 * (v - base[k]) for k, v in draw.items()}
        shape = hg.HeadShape.from_dict(draw)
    return shape


# ------------------------------------------------------------------------- skin (pygalmesh)
@numba.njit(cache=True)
def _skin_implicit(x, y, z, table, t0, p0, step, cx, cy, cz, width, height, asym):
    """|q - C| - R_skin(theta, phi) at a point, R_skin bilinear in a (phi, theta) table."""
    if asym != 0.0:
        s = min(max((z + 35.0) / -45.0, 0.0), 1.0)
        x = x - asym * s * s * (3.0 - 2.0 * s)
    qx = (x - cx) / width
    qy = y - cy
    qz = (z - cz) / height
    rho = math.sqrt(qx * qx + qy * qy + qz * qz)
    theta = math.degrees(math.atan2(qx, qy))
    phi = math.degrees(math.asin(max(-1.0, min(1.0, qz / max(rho, 1e-12)))))
    n_p, n_t = table.shape
    ft = (theta - t0) / step
    fp = (phi - p0) / step
    i = min(max(int(ft), 0), n_t - 2)
    j = min(max(int(fp), 0), n_p - 2)
    a = min(max(ft - i, 0.0), 1.0)
    b = min(max(fp - j, 0.0), 1.0)
    r = (1 - b) * ((1 - a) * table[j, i] + a * table[j, i + 1]) \
        + b * ((1 - a) * table[j + 1, i] + a * table[j + 1, i + 1])
    return rho - r


def skin_table(shape: hg.HeadShape, step: float = 0.25):
    """Skin radius tabulated over the whole sphere: (table (phi, theta), theta0, phi0, step)."""
    t = np.arange(-180.0, 180.0 + step / 2, step)
    p = np.arange(-90.0, 90.0 + step / 2, step)
    T, P = np.meshgrid(t, p)
    return np.ascontiguousarray(hg.skin_radius(T, P, shape)), float(t[0]), float(p[0]), float(step)


def face_zoom(d: np.ndarray, zoom: float, centre=FACE_CENTRE) -> np.ndarray:
    """Unit directions d (n, 3) moved towards the face's centre direction (theta, phi) =
    `centre` by the Moebius zoom of the sphere: stereographic projection from the opposite
    pole, the plane scaled by 1 / zoom, projected back. The map is conformal (triangles keep
    their angles); it scales spacings at angle a from the centre by
    sec^2(a/2) / (zoom (1 + tan^2(a/2) / zoom^2)): 1 / zoom at the centre, 2 zoom / (1 + zoom^2)
    at 90 deg, zoom at the opposite pole (the back of the head). zoom = 1 is the identity."""
    d = np.asarray(d, dtype=float)
    if zoom == 1.0:
        return d
    c = hg.direction(*centre)
    e1 = np.array([1.0, 0.0, 0.0])                     # c has no x component
    e2 = np.cross(c, e1)
    local = d @ np.stack([e1, e2, c], axis=1)          # (n, 3) with c as the pole
    w = local[:, :2] / (1.0 + local[:, 2:3]) / zoom    # the opposite pole maps to infinity
    w = np.where(np.isfinite(w), w, 0.0)
    r2 = np.sum(w * w, axis=1, keepdims=True)
    z = (1.0 - r2) / (1.0 + r2)
    back = np.column_stack([2.0 * w / (1.0 + r2), z])
    far = local[:, 2] <= -1.0 + 1e-12                  # the opposite pole stays where it is
    back[far] = (0.0, 0.0, -1.0)
    return back @ np.stack([e1, e2, c], axis=0)


def skin_surface(shape: hg.HeadShape, size: float = 3.0, distance: float = 0.25, seed: int = 0,
                 table_step: float = 0.25, mesher: str = "sphere", zoom: float = 1.0):
    """The closed skin of a head shape (trimesh).

    mesher "sphere" (default): a geodesic sphere (icosahedron subdivided to edges of about
    `size` mm on the face), graded by `face_zoom` (zoom > 1: the face's facets `zoom` times
    denser than a uniform sphere of the same level would have them, the back of the head's
    coarser), projected on the star-shaped skin along its rays: watertight by construction and
    bit-identical for a seed. mesher "pygalmesh": CGAL's restricted Delaunay
    surface mesher on the implicit function (facets of at most `size` mm, within `distance`
    mm of the surface, angles >= 25 deg): better-shaped triangles, but CGAL orders its
    refinement by memory address, so the triangulation (not the surface) varies between
    runs."""
    import trimesh

    if mesher == "sphere":
        # a geodesic sphere of level L has edges of about 105 / 2^L mm on the face (radius
        # ~95 mm from C); the zoom divides them by `zoom` there. The level rounds log2 up from
        # a quarter (not a half) so that facets are at most ~20 % over `size`
        level = int(np.clip(np.ceil(np.log2(105.0 / (size * zoom)) - 0.25), 3, 7))
        ico = trimesh.creation.icosphere(subdivisions=level, radius=1.0)
        d = face_zoom(np.asarray(ico.vertices), zoom)
        theta = np.degrees(np.arctan2(d[:, 0], d[:, 1]))
        phi = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
        verts = hg.to_cartesian(theta, phi, hg.skin_radius(theta, phi, shape), shape)
        out = trimesh.Trimesh(verts, np.asarray(ico.faces), process=False)
        if out.volume < 0:
            out.invert()
        return _canonical(out)
    if mesher != "pygalmesh":
        raise ValueError(f"mesher must be 'sphere' or 'pygalmesh', got {mesher!r}")
    import pygalmesh

    table, t0, p0, step = skin_table(shape, table_step)
    args = (table, t0, p0, step, *map(float, hg.CENTRE), float(shape.width), float(shape.height),
            float(shape.asymmetry))
    c = hg.CENTRE

    class Skin(pygalmesh.DomainBase):
        def __init__(self):
            super().__init__()

        def eval(self, x):
            # the mesher's origin is the ray centre C, inside the head
            return _skin_implicit(x[0] + c[0], x[1] + c[1], x[2] + c[2], *args)

        def get_bounding_sphere_squared_radius(self):
            return 220.0**2

    mesh = pygalmesh.generate_surface_mesh(
        Skin(), min_facet_angle=25.0, max_radius_surface_delaunay_ball=size,
        max_facet_distance=distance, verbose=False, seed=seed)
    tri = np.concatenate([cell.data for cell in mesh.cells if cell.type == "triangle"])
    out = trimesh.Trimesh(mesh.points + c, tri, process=True)
    parts = out.split(only_watertight=False)
    if len(parts) > 1:       # drop tiny spurious bubbles, if any
        out = max(parts, key=lambda m: len(m.faces))
    if not out.is_winding_consistent:
        trimesh.repair.fix_winding(out)
    if out.volume < 0:
        out.invert()
    return _canonical(out)


def _canonical(mesh):
    """The same surface with faces in a canonical order (each face rotated to start at its
    smallest vertex, keeping its orientation; faces sorted), so that output is identical
    between runs whatever order the mesher emits its facets in."""
    import trimesh

    v = np.asarray(mesh.vertices)
    order = np.lexsort(v.T[::-1])
    rank = np.empty(len(v), dtype=np.int64)
    rank[order] = np.arange(len(v))
    v = v[order]
    f = rank[np.asarray(mesh.faces)]
    r = np.argmin(f, axis=1)
    f = np.stack([f[np.arange(len(f)), (r + k) % 3] for k in range(3)], axis=1)
    f = f[np.lexsort(f.T[::-1])]
    return trimesh.Trimesh(v, f, process=False)


# Structured grid sizes of the bone shells (columns, rows) per segment.
SHELL_GRID = {"skull": (120, 36), "maxilla": (60, 10), "mandible": (120, 24), "chin": (30, 12)}


def bone_surfaces(shape: hg.HeadShape, scale: float = 1.0) -> dict:
    """Closed shells of the bone segments (trimesh per segment), swept structured surfaces
    of the same radial bone function (their sharp osteotomy edges are exact this way)."""
    import trimesh

    out = {}
    for seg, (nt, nphi) in SHELL_GRID.items():
        v, f = hg.bone_shell(seg, shape, n_theta=max(4, int(nt * scale)), n_phi=max(3, int(nphi * scale)))
        out[seg] = trimesh.Trimesh(v, f, process=False)
    return out


def landmarks(shape: hg.HeadShape, skin=None) -> dict:
    """Soft-tissue landmarks (mm RAS) of a head shape.

    Each landmark is placed by its anatomical definition on the exact skin, in the head's
    frame (`head_geometry.anatomical_landmarks`: pronasale, subnasale, labrale superius and
    inferius and soft pogonion as extremal points and concavities of the mid-sagittal
    profile; the stomia at the lip ends on the mouth line, 0.5 mm inside their own lip;
    menton and the cheilia on their rays). Given the head's triangulated `skin` (trimesh),
    every landmark is then the closest point of that surface, i.e. the point an observer
    picks on the scanned surface: a triangulation with ~3 mm edges cuts convex tips
    (pronasale ~0.5 mm) and bridges the step between the lips (in a strong class III the
    upper lip ends up to ~2.3 mm behind the triangles that join it to the protruding lower
    lip; on the default ~1 mm scan, a fraction of a mm), and a true landmark lies on the
    skin the patient data show."""
    out = hg.anatomical_landmarks(shape)
    if skin is not None:
        import trimesh

        names = list(out)
        on_skin, _, _ = trimesh.proximity.closest_point(skin, np.array([out[k] for k in names]))
        out = {k: np.asarray(v, dtype=float) for k, v in zip(names, on_skin)}
    return out


def synthetic_head(seed: int, size: float = SCAN_SIZE, distance: float = 0.25,
                   table_step: float = 0.25, mesher: str = "sphere",
                   zoom: float = SCAN_ZOOM) -> SyntheticHead:
    """Patient `seed`: shape, skin, bone segments, teeth and landmarks (deterministic). The
    skin by default as a scan (SCAN_SIZE mm facets over the face, SCAN_ZOOM grading)."""
    shape = random_shape(seed)
    teeth = {"upper": (*hg.teeth_arch("upper", shape), "maxilla"),
             "lower": (*hg.teeth_arch("lower", shape), "mandible")}
    skin = skin_surface(shape, size, distance, seed=int(seed) % 2**31, table_step=table_step,
                        mesher=mesher, zoom=zoom)
    return SyntheticHead(seed=int(seed), shape=shape, skin=skin, bones=bone_surfaces(shape),
                         teeth=teeth, landmarks=landmarks(shape, skin))


# ------------------------------------------------------------------ post-operative truth models
# The post-operative "truth" of a synthetic case is predicted on a model that is not the one a
# diagnosis fits: the generic face with its layers re-proportioned and its moduli perturbed per
# case (`perturb_layers`, `perturbed_materials`), then seen as a scanner sees it
# (`scan_like_surface`).

PERTURB_LAYER = 0.2       # +-20 % dermis and deep (muscle/mucosa) layer thickness
PERTURB_MODULUS = 0.15    # +-15 % per layer on the generic moduli
BULK_RATIO = (500.0, 2000.0)   # K / mu of the truth model (the generic uses 1000)


def perturb_layers(model, n_layers: int, dermis: float = 1.0, deep: float = 1.0):
    """The generic face with its dermis (outer layer) and deep layers (the inner half: muscles,
    mucosa) `dermis` and `deep` times as thick; the hypodermis between takes the difference
    and the deep and skin surfaces stay where they are. Works on the column structure of the
    generic mesh (`generic_mesh.builder`: node id = column * (n_layers + 1) + layer, deep to
    skin): every interior node slides along its column's polyline."""
    from dataclasses import replace

    X = np.asarray(model.nodes, float)
    nk = int(n_layers)
    if len(X) % (nk + 1):
        raise ValueError(f"the mesh has no columns of {nk + 1} nodes")
    P = X.reshape(-1, nk + 1, 3)
    seg = np.linalg.norm(np.diff(P, axis=1), axis=2)                  # (c, nk)
    L = np.concatenate([np.zeros((len(P), 1)), np.cumsum(seg, axis=1)], axis=1)
    total = L[:, -1:]
    n_deep = nk // 2
    l_deep = np.minimum(L[:, n_deep:n_deep + 1] * deep, 0.45 * total)
    l_derm = np.minimum((total - L[:, nk - 1:nk]) * dermis, 0.45 * total)
    new = L.copy()
    k = np.arange(nk + 1)[None, :]
    old_deep, old_top = L[:, n_deep:n_deep + 1], L[:, nk - 1:nk]
    inner = np.where(k <= n_deep, L * l_deep / np.maximum(old_deep, 1e-12),
                     l_deep + (L - old_deep) * (total - l_derm - l_deep)
                     / np.maximum(old_top - old_deep, 1e-12))
    new = np.where(k < nk, inner, total)
    new[:, nk - 1:nk] = total - l_derm
    new[:, 0] = 0.0
    out = np.empty_like(P)
    for c in range(len(P)):
        for d in range(3):
            out[c, :, d] = np.interp(new[c], L[c], P[c, :, d])
    return replace(model, nodes=out.reshape(-1, 3))


def perturbed_materials(rng) -> tuple:
    """Material overrides of a truth model ({label: {C10, C20, K}}, the plan's
    `model.materials` form) and their record: each layer's moduli times a factor in
    1 +- PERTURB_MODULUS, K = ratio * mu with the ratio in BULK_RATIO."""
    from facemodel import materials as fm
    from facemodel.effects import LAYERS

    ratio = float(rng.uniform(*BULK_RATIO))
    factors = {layer: float(rng.uniform(1 - PERTURB_MODULUS, 1 + PERTURB_MODULUS)) for layer in LAYERS}
    out = {}
    for layer, labels in LAYERS.items():
        for label in labels:
            p = fm.material(label).parameters
            c10, c20 = p["C10"] * factors[layer], p["C20"] * factors[layer]
            out[label] = {"C10": c10, "C20": c20, "K": ratio * 2.0 * c10}
    return out, {"modulus_factors": {k: round(v, 4) for k, v in factors.items()},
                 "bulk_to_shear": round(ratio, 1)}


@numba.njit(cache=True)
def _zbuffer(V, F, x0, z0, h, nx, nz):
    """Largest y (the surface nearest a frontal viewer looking along -y) on the (x, z) grid."""
    depth = np.full((nz, nx), -np.inf)
    for t in range(F.shape[0]):
        a, b, c = V[F[t, 0]], V[F[t, 1]], V[F[t, 2]]
        xmin = min(a[0], b[0], c[0])
        xmax = max(a[0], b[0], c[0])
        zmin = min(a[2], b[2], c[2])
        zmax = max(a[2], b[2], c[2])
        i0 = max(int(math.ceil((xmin - x0) / h)), 0)
        i1 = min(int(math.floor((xmax - x0) / h)), nx - 1)
        j0 = max(int(math.ceil((zmin - z0) / h)), 0)
        j1 = min(int(math.floor((zmax - z0) / h)), nz - 1)
        det = (b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])
        if abs(det) < 1e-14:
            continue
        for j in range(j0, j1 + 1):
            pz = z0 + j * h
            for i in range(i0, i1 + 1):
                px = x0 + i * h
                l1 = ((px - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (pz - a[2])) / det
                l2 = ((b[0] - a[0]) * (pz - a[2]) - (px - a[0]) * (b[2] - a[2])) / det
                l0 = 1.0 - l1 - l2
                if l0 >= -1e-12 and l1 >= -1e-12 and l2 >= -1e-12:
                    y = l0 * a[1] + l1 * b[1] + l2 * c[1]
                    if y > depth[j, i]:
                        depth[j, i] = y
    return depth


# The scanners a synthetic post-op scan can come from: each a list of views (yaw about the
# vertical axis, pitch about the transverse axis, degrees; (0, 0) looks at the face from in
# front) and how far below menton the scan goes (mm; None: to the mandible's lower border, which
# a frontal view cannot see past).
# - frontal: one range camera in front of the face (a structured-light or laser scanner's single
#   view);
# - wide: a stereophotogrammetry system of several pods (as 3dMDface / 3dMDtrio capture the face
#   ear to ear): in front, either side at 50 deg, and below the face looking up at 40 deg, so
#   that under the chin is seen down to 30 mm below menton.
SCANNERS = {"frontal": {"views": ((0.0, 0.0),), "below_menton_mm": None},
            "wide": {"views": ((0.0, 0.0), (-50.0, 0.0), (50.0, 0.0), (0.0, -40.0)),
                     "below_menton_mm": 30.0}}


MIN_PATCH = 200          # triangles: a smaller piece of a pod's patch is a speck, not scanned


def _view_rotation(yaw: float, pitch: float) -> np.ndarray:
    """R with x_view = R x: the viewer of (yaw, pitch) looks along -y_view (yaw turns the viewer
    towards +x about +z, pitch below the face about +x)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("zx", [yaw, -pitch], degrees=True).as_matrix()


def _range_image(V, F, keep, spacing, R, centre, window=None):
    """One view's range image of the surface (V, F): grid points (world frame) and their grid
    triangles (only cells whose 4 corners pass `keep(points)`), in the view frame R about
    `centre` (x_view = R (x - centre)); window: the grid's (x0, z0, nx, nz) in that frame
    (default: the box of the vertices `keep` passes)."""
    Vv = (V - centre) @ R.T
    if window is None:
        inside = keep(V)
        lo, hi = Vv[inside].min(axis=0), Vv[inside].max(axis=0)
        window = (lo[0], lo[2], int((hi[0] - lo[0]) / spacing) + 1, int((hi[2] - lo[2]) / spacing) + 1)
    x0, z0, nx, nz = window
    depth = _zbuffer(np.ascontiguousarray(Vv), np.ascontiguousarray(F), x0, z0, spacing, nx, nz)
    gx, gz = np.meshgrid(x0 + spacing * np.arange(nx), z0 + spacing * np.arange(nz))
    ok = np.isfinite(depth)
    pv = np.stack([gx, np.where(ok, depth, 0.0), gz], axis=-1)
    pw = pv @ R + centre
    ok &= keep(pw.reshape(-1, 3)).reshape(ok.shape)
    idx = -np.ones((nz, nx), np.int64)
    idx[ok] = np.arange(ok.sum())
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return pw[ok], tri[(tri >= 0).all(axis=1)]


def scan_like_surface(vertices, faces, landmarks: dict, rng, *, spacing: float = 0.6,
                      noise: float = 0.2, max_shift: float = 2.0, max_angle_deg: float = 2.0,
                      grazing: float = 0.3, scanner: str = "frontal"):
    """The surface as a surface scanner gives it (`SCANNERS`): per view a range image on a
    `spacing` mm grid (the frontal view along -y, RAS: the viewer in front), triangulated (0.6
    mm grid: median triangle edge ~0.8 mm with the diagonals and the face's slopes); the front
    of the face only (the landmarks' box: ear to ear is not seen; the wide scanner's box is 20
    mm wider either side), no triangle seen at a grazing angle (n . view < `grazing`: the frontal
    view misses the sides and under the chin), nothing across depth jumps, holes at the mouth
    slit (between the stomia, commissure to commissure) and the nostrils (beside subnasale).
    With several views each part of the face is taken from the view it faces most (the pods'
    patches, stitched without overlap). Gaussian noise of `noise` mm along the normals and a
    random rigid offset (translation up to `max_shift` mm, rotation up to `max_angle_deg`
    about the scan's centroid). Returns (vertices, faces, record of what was drawn)."""
    import trimesh

    if scanner not in SCANNERS:
        raise ValueError(f"scanner must be one of {', '.join(SCANNERS)}, got {scanner!r}")
    spec = SCANNERS[scanner]
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    lm = {k: np.asarray(v, float) for k, v in landmarks.items()}
    x_half = 0.5 * abs(lm["ChL"][0] - lm["ChR"][0]) + 30.0
    below = spec["below_menton_mm"]
    z_st = 0.5 * (lm["Stms"][2] + lm["Stmi"][2])
    half_w = 0.5 * abs(lm["ChL"][0] - lm["ChR"][0])

    def keep(P):
        gx, gz = P[:, 0], P[:, 2]
        if below is None:
            # menton is the lowest point of the face: below it a frontal view sees the neck;
            # the face ends at the lower border of the mandible, rising from menton towards
            # the angles (~0.9 mm per mm sideways from 12 mm off the midline)
            ok = (gx >= -x_half) & (gx <= x_half) & (gz <= lm["Prn"][2] + 50.0)
            ok &= gz >= lm["Me"][2] - 1.0 + 0.9 * np.maximum(np.abs(gx - lm["Me"][0]) - 12.0, 0.0)
        else:
            ok = (np.abs(gx) <= x_half + 20.0) & (gz <= lm["Prn"][2] + 50.0) & (gz >= lm["Me"][2] - below)
            # the back of the head and neck is no scanner's: in front of the ears' plane
            ok &= P[:, 1] >= lm["Me"][1] - 90.0
        # holes: the mouth slit (the stomion line between the commissures, 1.2 mm high) and
        # the nostrils (ellipses 3 x 2 mm at 6 mm either side of subnasale, 2 mm above it)
        ok &= ~((np.abs(gx - 0.5 * (lm["ChL"][0] + lm["ChR"][0])) < 0.95 * half_w) & (np.abs(gz - z_st) < 0.6))
        for side in (-1.0, 1.0):
            cx, cz = lm["Sn"][0] + 6.0 * side, lm["Sn"][2] + 2.0
            ok &= ~(((gx - cx) / 3.0) ** 2 + ((gz - cz) / 2.0) ** 2 < 1.0)
        return ok

    views = spec["views"]
    rotations = [_view_rotation(*v) for v in views]
    towards = np.array([R[1] for R in rotations])        # world directions to each viewer
    centre, window = lm["Prn"] - np.array([0.0, 40.0, 0.0]), None
    if below is None:
        # the frontal camera's window: the landmarks' box, from 1 mm below menton
        z_lo = lm["Me"][2] - 1.0
        centre, window = np.zeros(3), (-x_half, z_lo, int(2 * x_half / spacing) + 1,
                                       int((lm["Prn"][2] + 50.0 - z_lo) / spacing) + 1)
    parts = []
    for k, R in enumerate(rotations):
        pts, tri = _range_image(V, F, keep, spacing, R, centre, window)
        p = pts[tri]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        if np.median(n @ towards[k]) < 0:                # outward: towards the viewer
            tri = tri[:, [0, 2, 1]]
            n = -n
        edge = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
        facing = n @ towards.T                            # (triangles, views)
        ok = (facing[:, k] >= grazing) & (edge < 4.0 * spacing) & (np.argmax(facing, axis=1) == k)
        mesh = trimesh.Trimesh(pts, tri[ok], process=False)
        mesh.remove_unreferenced_vertices()
        if not len(mesh.faces):
            continue
        # keep the largest connected piece (specks left between holes are not scanned); of a
        # pod's patch, which the other pods' border in several places, every piece but specks
        pieces = mesh.split(only_watertight=False)
        if len(pieces) > 1:
            big = max(len(m.faces) for m in pieces)
            pieces = [m for m in pieces if len(m.faces) == big or (len(views) > 1 and len(m.faces) >= MIN_PATCH)]
            mesh = pieces[0] if len(pieces) == 1 else trimesh.util.concatenate(pieces)
        parts.append(mesh)
    mesh = parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)
    pts = np.asarray(mesh.vertices, float).copy()
    tri = np.asarray(mesh.faces, np.int64)
    pts += rng.normal(0.0, noise, size=(len(pts), 1)) * np.asarray(mesh.vertex_normals, float)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = float(rng.uniform(0.0, max_angle_deg))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    shift = direction * float(rng.uniform(0.0, max_shift))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
    centre = pts.mean(axis=0)
    pts = (pts - centre) @ R.T + centre + shift
    e = np.linalg.norm(pts[tri] - pts[np.roll(tri, 1, axis=1)], axis=2)
    record = {"scanner": scanner, "grid_mm": spacing, "median_edge_mm": round(float(np.median(e)), 3),
              "noise_sigma_mm": noise, "rigid_offset": {
                  "translation_mm": [round(float(v), 4) for v in shift],
                  "rotation_axis": [round(float(v), 4) for v in axis], "rotation_deg": round(angle, 4),
                  "centre": [round(float(v), 3) for v in centre]},
              "n_vertices": int(len(pts))}
    return pts, tri, record


def scan_coverage(points, vertices, faces, landmarks: dict, *, tol: float = 1.0,
                  scanner: str = "frontal") -> np.ndarray:
    """Which of `points` (near the surface `vertices`, `faces`: the nodes of a skin registered
    onto it) the `scanner`'s scan of `scan_like_surface` sees (its window, crop, holes and
    grazing rule): those within `tol` mm of a vertex of that scan made without noise or offset.
    The scan's vertices lie on a 0.6 mm grid per view, so a point on the scanned surface is
    within about 0.4 mm of one, more where the surface slopes away from the viewer."""
    from scipy.spatial import cKDTree

    V, _, _ = scan_like_surface(vertices, faces, landmarks, np.random.default_rng(0), noise=0.0,
                                max_shift=0.0, max_angle_deg=0.0, scanner=scanner)
    d, _ = cKDTree(V).query(np.asarray(points, float), distance_upper_bound=tol)
    return np.isfinite(d)


def displaced_surface(vertices, fe_nodes, fe_triangles, fe_displacement):
    """Vertices of a surface moved by the displacement of the FE skin it lies on: each
    vertex takes the displacement interpolated (barycentric) at its closest point on the FE
    skin triangles (the registered FE skin is within a fraction of a mm of the patient skin;
    exact closest points, `solver.geometry.TriangleTree`)."""
    from solver.geometry import TriangleTree

    V = np.asarray(vertices, float)
    T = np.asarray(fe_triangles, np.int64)
    _, bary, tri, _ = TriangleTree(np.asarray(fe_nodes, float), T).closest(V)
    u = np.einsum("ka,kai->ki", bary, np.asarray(fe_displacement, float)[T[tri]])
    return V + u
