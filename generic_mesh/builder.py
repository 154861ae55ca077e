"""Builder of the generic structured hexahedral face mesh (Payan / Chabanas generic model).

The facial soft tissue between the deep surface (bone, teeth, vestibule) and the skin of the
parametric mean head (`facemodel.head_geometry`) is meshed ray by ray: a tensor grid of
azimuths theta (columns, symmetric about the mid-sagittal plane, a column on it) and
elevations phi (rows, with rows on the soft-tissue landmarks and the mouth line) carries,
along each ray, layers from the deep surface to the skin: muscle / mucosa, hypodermis
(fat), and a 1.8 mm dermis (Payan's layered generic face; Chabanas, Luboz & Payan, Med Image
Anal 7:131-151, 2003; dermis thickness ~1.5-2 mm, e.g. Chopra K. et al., Skin Res Technol
21:1-7, 2015). Between the commissures the nodes of the mouth-line row are doubled through
the whole thickness, so the lips are separate, with a 1 mm gap at the midline closing to
zero at the commissures. Elements are labelled by layer and by the anatomical maps of the
perioral muscles in the (theta, phi) chart (orbicularis oris ring, zygomaticus major,
levator labii superioris, risorius, buccinator, depressor anguli oris, depressor labii
inferioris, mentalis; attachments after Standring (ed.), Gray's Anatomy, 41st ed., 2016),
with fibre directions mapped from the chart through each element's Jacobian. Deep nodes are
attached to the bone segment under them (skull, maxilla, mandible, chin), except where they
face the teeth or the oral cavity.
"""
from __future__ import annotations

import numpy as np

from facemodel import head_geometry as hg
from facemodel.model import ATTACHMENT_SETS, LABEL_NAMES, SEGMENTS, FaceModel
from generic_mesh.quality import HEX_FACES, hex_volumes, scaled_jacobian

DERMIS = 1.8            # mm
LIP_GAP = 1.0           # mm between the lips at the midline
CHART_RADIUS = 90.0     # mm per radian in the (theta, phi) chart

# Row knots (deg): floor of the mouth ... infraorbital; the rows above PHI_MID rise to
# PHI_TOP(theta) (nasion on the midline, the infraorbital rim laterally).
PHI_KNOTS = [-77.0, -60.0, -47.0, -40.0, -33.0, -23.0, hg.PHI_STOMION, -14.0, -7.6, 1.0, 6.0]
THETA_KNOTS = [0.0, 9.0, hg.THETA_COMMISSURE, 34.0, 50.0, 68.0, 88.0]

RESOLUTIONS = {
    #            rows per phi interval            , top rows, cols per theta interval, layers
    "coarse":   ([2, 2, 1, 1, 2, 1, 1, 1, 2, 1], 3, [2, 2, 2, 2, 2, 2], 4),
    "standard": ([4, 4, 3, 3, 4, 3, 3, 3, 4, 2], 7, [4, 4, 4, 4, 4, 5], 5),
    "fine":     ([7, 7, 5, 5, 7, 5, 5, 5, 7, 4], 12, [7, 7, 7, 7, 7, 9], 7),
}


def phi_top(theta):
    return 12.5 + 14.0 * np.exp(-(np.asarray(theta) / 14.0) ** 2)


def _graded(knots, counts):
    out = [knots[0]]
    for a, b, n in zip(knots[:-1], knots[1:], counts):
        out.extend(np.linspace(a, b, n + 1)[1:])
    return np.array(out)


def _layer_fractions(thickness, n_layers):
    """Radial positions (fractions of the thickness, deep 0 -> skin 1) of the layer nodes:
    the dermis is the outer DERMIS mm; the rest is half muscle/mucosa, half hypodermis."""
    n_deep = n_layers // 2
    n_hypo = n_layers - 1 - n_deep
    frac_dermis = np.minimum(DERMIS / thickness, 0.3)
    inner = 1.0 - frac_dermis
    cols = [np.zeros_like(thickness)]
    for k in range(1, n_deep + 1):
        cols.append(inner * 0.5 * k / n_deep)
    for k in range(1, n_hypo + 1):
        cols.append(inner * (0.5 + 0.5 * k / n_hypo))
    cols.append(np.ones_like(thickness))
    return np.stack(cols, axis=-1), n_deep


def _segment_distance(theta, phi, segment):
    return hg.segment_region(segment, theta, phi)


# Muscle maps in the chart (deg): capsules (theta1, phi1) -> (theta2, phi2), half-width in mm;
# right side given, mirrored to the left. Fibres run from the first point to the second.
_S = hg.PHI_STOMION
_C = hg.THETA_COMMISSURE
CAPSULES = {
    "zygomaticus_major": ((48.0, 3.0), (_C + 2.0, _S + 1.5), 5.0),
    "levator_labii_superioris": ((13.0, 11.0), (8.0, _S + 6.0), 4.5),
    "risorius": ((60.0, _S + 1.0), (_C + 3.0, _S), 4.0),
    "depressor_anguli_oris": ((_C + 1.5, _S - 2.5), (_C + 11.0, -49.0), 5.0),
    "depressor_labii_inferioris": ((6.0, _S - 6.0), (14.0, -45.0), 4.0),
    "mentalis": ((3.0, -31.0), (5.0, -44.0), 4.5),
}
PRIORITY = ["mentalis", "depressor_labii_inferioris", "depressor_anguli_oris",
            "levator_labii_superioris", "zygomaticus_major", "risorius"]
ORBICULARIS_A = _C + 5.0            # ring half-width (deg)
ORBICULARIS_CORE = 9.0              # straight middle part of the rings (a column knot, deg)
ORBICULARIS_B_UP = _S - (-7.6)      # mouth line to subnasale
ORBICULARIS_B_LOW = -32.0 - _S      # mouth line to the labiomental fold (negative)
BUCCINATOR = (_C + 3.0, 48.0, 7.0)  # |theta| range and |phi - phi_s| half-height
VESTIBULE = (48.0, _S - 10.5, _S + 10.0)   # free deep surface: |theta| < .., phi in (.., ..)
FLOOR_OF_MOUTH = -62.0              # below: free deep surface (floor of mouth, neck)
BSSO_RELEASE = (44.0, 56.0)         # |theta| band released around the sagittal split (deg)
MENTAL_FORAMEN = 22.0               # |theta| of the mental foramina (below the 2nd premolars)
GENIOPLASTY_TUNNEL = 3.0            # deg released above the osteotomy line out to the border


def orbicularis_ring(theta, phi):
    """Ring coordinate q of orbicularis oris (q = 1 on its outer border): level sets parallel
    to the lip margins along the middle of the lips, turning around the commissures (the
    fibres run along the lips and loop at the modioli)."""
    b = np.where(phi >= _S, ORBICULARIS_B_UP, ORBICULARIS_B_LOW)
    dt = np.maximum(np.abs(theta) - ORBICULARIS_CORE, 0.0)
    return (dt / (ORBICULARIS_A - ORBICULARIS_CORE)) ** 2 + ((phi - _S) / b) ** 2


def orbicularis_tangent(theta, phi):
    """Chart direction (dtheta, dphi) tangent to the rings q = const."""
    b = np.where(phi >= _S, ORBICULARIS_B_UP, ORBICULARIS_B_LOW)
    dt = np.sign(theta) * np.maximum(np.abs(theta) - ORBICULARIS_CORE, 0.0)
    return np.stack([-(phi - _S) / b**2, dt / (ORBICULARIS_A - ORBICULARIS_CORE) ** 2], axis=-1)


def _capsule_distance(t, p, a, b):
    """Chart distance (mm) from points (t, p) to the segment a-b (deg)."""
    P = np.stack([t, p], -1) * np.radians(1.0) * CHART_RADIUS
    A = np.asarray(a) * np.radians(1.0) * CHART_RADIUS
    B = np.asarray(b) * np.radians(1.0) * CHART_RADIUS
    ab = B - A
    s = np.clip(((P - A) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (A + s[..., None] * ab), axis=-1)


def chart_to_3d(nodes, hexes, node_theta, node_phi, direction_chart):
    """Map chart directions (m, 2) (dtheta, dphi) of elements to unit 3D vectors, through the
    Jacobian of the trilinear map at the element centre."""
    x = nodes[hexes]                      # (m, 8, 3)
    t = node_theta[hexes]
    p = node_phi[hexes]
    # derivatives at the centre along xi1 (rows, 0->1) and xi2 (columns, 0->3)
    def d1(v):
        return ((v[:, 1] - v[:, 0]) + (v[:, 2] - v[:, 3]) + (v[:, 5] - v[:, 4]) + (v[:, 6] - v[:, 7])) / 4.0

    def d2(v):
        return ((v[:, 3] - v[:, 0]) + (v[:, 2] - v[:, 1]) + (v[:, 7] - v[:, 4]) + (v[:, 6] - v[:, 5])) / 4.0

    A = np.stack([np.stack([d1(t), d2(t)], -1), np.stack([d1(p), d2(p)], -1)], -2)   # (m,2,2)
    alpha = np.linalg.solve(A, direction_chart[..., None])[..., 0]
    f = alpha[:, :1] * d1(x) + alpha[:, 1:] * d2(x)
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def build(resolution: str = "standard") -> FaceModel:
    """Build the generic face model at a resolution ('coarse', 'standard', 'fine')."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {sorted(RESOLUTIONS)}, got {resolution!r}")
    rows, n_top, cols, n_layers = RESOLUTIONS[resolution]
    phis = _graded(PHI_KNOTS, rows)
    j_mid = len(phis) - 1
    j_s = int(np.flatnonzero(np.isclose(phis, hg.PHI_STOMION))[0])
    half = _graded(THETA_KNOTS, cols)
    thetas = np.concatenate([-half[:0:-1], half])
    ni, nj, nk = len(thetas) - 1, j_mid + n_top, n_layers
    i_mid = ni // 2
    # node (theta, phi) grid: rows above j_mid rise to phi_top(theta)
    TH = np.broadcast_to(thetas, (nj + 1, ni + 1)).copy()
    PH = np.empty((nj + 1, ni + 1))
    PH[: j_mid + 1] = phis[:, None]
    s = np.arange(1, n_top + 1)[:, None] / n_top
    PH[j_mid + 1:] = phis[-1] + s * (phi_top(thetas)[None, :] - phis[-1])
    SIDE = np.where(np.arange(nj + 1)[:, None] >= j_s, 1.0, -1.0) * np.ones((1, ni + 1))
    # the mouth slit: interior columns between the commissures
    slit_cols = np.flatnonzero(np.abs(thetas) < hg.THETA_COMMISSURE - 1e-9)
    i_chl, i_chr = slit_cols[0] - 1, slit_cols[-1] + 1
    delta = np.degrees(0.5 * LIP_GAP / 95.0) * np.sqrt(np.clip(1.0 - (thetas / hg.THETA_COMMISSURE) ** 2, 0, 1))
    PH[j_s, slit_cols] = hg.PHI_STOMION + delta[slit_cols]
    # lower-lip copies of the slit row
    th_low = thetas[slit_cols]
    ph_low = hg.PHI_STOMION - delta[slit_cols]

    node_th = np.concatenate([TH.ravel(), th_low])
    node_ph = np.concatenate([PH.ravel(), ph_low])
    node_side = np.concatenate([SIDE.ravel(), -np.ones_like(th_low)])
    n_col = len(node_th)
    # compute on the right half (theta >= 0) and mirror, for exact symmetry
    right = node_th >= 0.0
    rb = hg.deep_radius(node_th[right], node_ph[right], side=node_side[right])
    thick = hg.soft_tissue_thickness(node_th[right], node_ph[right])
    frac, n_deep = _layer_fractions(thick, nk)
    rho = rb[:, None] + frac * thick[:, None]                          # (n_right, nk+1)
    pts_r = hg.to_cartesian(np.repeat(node_th[right], nk + 1), np.repeat(node_ph[right], nk + 1),
                            rho.ravel()).reshape(-1, nk + 1, 3)
    pts = np.empty((n_col, nk + 1, 3))
    pts[right] = pts_r
    # mirror map of columns: same row, theta -> -theta
    key = {(round(t, 9), round(p, 9), sd): c for c, (t, p, sd) in
           enumerate(zip(node_th, node_ph, node_side)) if t >= 0}
    left = np.flatnonzero(~right)
    mirror_of = np.array([key[(round(-node_th[c], 9), round(node_ph[c], 9), node_side[c])] for c in left])
    pts[left] = pts[mirror_of] * np.array([-1.0, 1.0, 1.0])
    pts[np.isclose(node_th, 0.0), :, 0] = 0.0
    nodes = pts.reshape(-1, 3)
    nid = np.arange(n_col * (nk + 1)).reshape(n_col, nk + 1)
    grid = nid[: (nj + 1) * (ni + 1)].reshape(nj + 1, ni + 1, nk + 1)
    low = nid[(nj + 1) * (ni + 1):]                                    # (n_slit, nk+1)
    n_theta = np.repeat(node_th, nk + 1)
    n_phi = np.repeat(node_ph, nk + 1)
    n_side = np.repeat(node_side, nk + 1)
    n_layer = np.tile(np.arange(nk + 1), n_col)

    # hexahedra (xi1 = row, xi2 = column, xi3 = layer)
    J, I, K = np.meshgrid(np.arange(nj), np.arange(ni), np.arange(nk), indexing="ij")
    J, I, K = J.ravel(), I.ravel(), K.ravel()
    top_row = grid.copy()
    # the lower lip's elements (row j_s - 1) take the lower copies on their top side
    lower_view = grid.copy()
    lower_view[j_s, slit_cols] = low
    def g(j, i, k, lower):
        return np.where(lower, lower_view[j, i, k], top_row[j, i, k])
    is_low = (J == j_s - 1)
    hexes = np.stack([
        grid[J, I, K], g(J + 1, I, K, is_low), g(J + 1, I + 1, K, is_low), grid[J, I + 1, K],
        grid[J, I, K + 1], g(J + 1, I, K + 1, is_low), g(J + 1, I + 1, K + 1, is_low), grid[J, I + 1, K + 1],
    ], axis=1)
    vol = hex_volumes(nodes, hexes)
    if np.any(vol <= 0):
        raise RuntimeError(f"{np.sum(vol <= 0)} inverted elements in the {resolution} mesh")

    # --------------------------------------------------------------- labels, fibres
    et = n_theta[hexes].mean(1)
    ep = n_phi[hexes].mean(1)
    lab = np.full(len(hexes), LABEL_NAMES.index("hypodermis"))
    lab[K == nk - 1] = LABEL_NAMES.index("dermis")
    deep = K < n_deep
    chart_dir = np.zeros((len(hexes), 2))
    # deep-surface state of each node column (free or attached)
    free_col = _free_deep(node_th, node_ph)
    e_free = np.all(free_col[hexes[:, :4] // (nk + 1)], axis=1)
    # muscles in the deep group
    h_elem = np.radians(np.maximum(np.ptp(n_theta[hexes], 1), np.ptp(n_phi[hexes], 1))) * CHART_RADIUS
    claimed = np.zeros(len(hexes), bool)
    ring = orbicularis_ring(et, ep)
    orb = deep & (ring <= 1.0) & (ep > -32.0)
    lab[orb] = LABEL_NAMES.index("orbicularis_oris")
    chart_dir[orb] = orbicularis_tangent(et[orb], ep[orb])
    claimed |= orb
    for name in PRIORITY:
        a, b, r = CAPSULES[name]
        sgn = np.where(et >= 0, 1.0, -1.0)
        dist = _capsule_distance(np.abs(et), ep, a, b)
        m = deep & ~claimed & (dist <= np.maximum(r, 0.5 * h_elem))
        lab[m] = LABEL_NAMES.index(name)
        chart_dir[m] = np.stack([sgn[m] * (b[0] - a[0]), np.full(m.sum(), b[1] - a[1])], -1)
        claimed |= m
    t0, t1, hh = BUCCINATOR
    bucc = deep & ~claimed & (np.abs(et) >= t0) & (np.abs(et) <= t1) & (np.abs(ep - _S) <= hh)
    lab[bucc] = LABEL_NAMES.index("buccinator")
    chart_dir[bucc] = np.stack([np.where(et[bucc] >= 0, 1.0, -1.0), np.zeros(bucc.sum())], -1)
    claimed |= bucc
    # mucosa: the lining where tissue faces the teeth / oral cavity
    muc = deep & (K == 0) & e_free & (ep > FLOOR_OF_MOUTH)
    lab[muc] = LABEL_NAMES.index("mucosa")
    claimed &= ~muc
    # nose (cartilage and its soft tissue), all but the dermis
    nose = (K < nk - 1) & (hg.nose_weight(et, ep) >= 0.5) & (ep > -7.6)
    lab[nose] = LABEL_NAMES.index("nose")
    claimed &= ~nose
    chart_dir[~claimed] = 0.0
    fibres = np.zeros((len(hexes), 3))
    fibres[claimed] = chart_to_3d(nodes, hexes[claimed], n_theta, n_phi, chart_dir[claimed])

    # ---------------------------------------------------------------- node sets
    deep_nodes = np.flatnonzero(n_layer == 0)
    skin_nodes = np.flatnonzero(n_layer == nk)
    free = free_col[deep_nodes // (nk + 1)]
    dist = np.stack([_segment_distance(n_theta[deep_nodes], n_phi[deep_nodes], sname)
                     for sname in SEGMENTS], -1)
    seg = np.argmin(dist, axis=1)
    # the tissue a genioplasty degloves stays tied to the mandible here (no other plan releases
    # it); when the chin moves on the mandible `facemodel.attachments.genioplasty_sliding` makes
    # it slide on the bone (with the chin segment's anterior face)
    released = ~free & (seg == SEGMENTS.index("mandible")) \
        & _genioplasty_release(n_theta[deep_nodes], n_phi[deep_nodes])
    node_sets = {"skin": skin_nodes, "deep_free": deep_nodes[free],
                 "release_genioplasty": deep_nodes[released]}
    att = deep_nodes[~free]
    seg = seg[~free]
    for si, sname in enumerate(SEGMENTS):
        node_sets[ATTACHMENT_SETS[sname]] = att[seg == si]
    border_cols = np.zeros((nj + 1, ni + 1), bool)
    border_cols[0] = border_cols[-1] = True
    border_cols[:, 0] = border_cols[:, -1] = True
    node_sets["border"] = grid[border_cols].ravel()
    # the neck cut: the mesh's inferior border row (every layer), where the tissue goes on down
    # the neck; free unless a plan holds it (`model.neck`, `facemodel.simulation.build_problem`)
    node_sets["neck"] = grid[0].ravel()
    # the floor of the mouth: the free deep surface under the mandible (where the suprahyoid
    # muscles and the hyoid lie); free unless a plan holds it (`model.floor`,
    # `facemodel.simulation.build_problem`)
    node_sets["floor_of_mouth"] = deep_nodes[free & (n_phi[deep_nodes] < FLOOR_OF_MOUTH)]
    # the proximal segments of a sagittal split (BSSO): the mandible's attached tissue behind
    # the released band around the buccal cut (ramus, angle: the masseter's insertion), which
    # stays with the condyles when the split moves the tooth-bearing mandible
    # (`model.proximal`, `facemodel.attachments.attachment_sets`)
    mand = node_sets[ATTACHMENT_SETS["mandible"]]
    node_sets["mandible_proximal"] = mand[np.abs(n_theta[mand]) >= BSSO_RELEASE[1]]

    # ---------------------------------------------------------------- facet sets
    faces = hexes[:, HEX_FACES]                                        # (m, 6, 4)
    in_slit = (I >= i_chl) & (I < i_chr)
    facet_sets = {"skin": faces[K == nk - 1, 1]}
    facet_sets["lip_upper_contact"] = faces[(J == j_s) & in_slit, 2]
    facet_sets["lip_lower_contact"] = faces[(J == j_s - 1) & in_slit, 3]
    deep_face = faces[:, 0]
    attached = np.zeros(len(nodes), bool)
    attached[att] = True
    free_node = np.zeros(len(nodes), bool)
    free_node[node_sets["deep_free"]] = True
    lipzone = np.abs(et) <= hg.THETA_COMMISSURE + 8.0
    k0 = K == 0
    all_free = np.all(free_node[deep_face], axis=1)
    facet_sets["lip_upper_teeth"] = deep_face[k0 & all_free & lipzone & (J >= j_s) & (ep < VESTIBULE[2])]
    facet_sets["lip_lower_teeth"] = deep_face[k0 & all_free & lipzone & (J < j_s) & (ep > VESTIBULE[1])]
    facet_sets["deep_bone"] = deep_face[k0 & np.all(attached[deep_face], axis=1)]

    # -------------------------------------------------------- regions, landmarks
    regions = _skin_regions(skin_nodes, n_theta, n_phi, n_side)
    landmarks = {}
    for name, (t, p, sd) in hg.LANDMARK_ANGLES.items():
        cand = skin_nodes
        if sd:
            cand = cand[n_side[cand] == sd]
        dd = (n_theta[cand] - t) ** 2 + (n_phi[cand] - p) ** 2
        landmarks[name] = int(cand[np.argmin(dd)])
    teeth = {"upper": (*hg.teeth_arch("upper"), "maxilla"), "lower": (*hg.teeth_arch("lower"), "mandible")}
    return FaceModel(
        nodes=nodes, hexes=hexes, labels=lab, label_names=LABEL_NAMES, fibres=fibres,
        node_sets=node_sets, facet_sets=facet_sets, teeth=teeth, regions=regions,
        unoperated_regions=("nasal_root", "infraorbital_left", "infraorbital_right",
                            "preauricular_left", "preauricular_right"),
        landmarks=landmarks, segments=SEGMENTS,
    )


def _free_deep(theta, phi):
    """Deep points not tied to bone: facing the teeth / oral cavity, the floor of the mouth,
    and the periosteum released around the sagittal split of the ramus (BSSO: the masseter
    region between the distal segment and the ramus, and along the ramus's upper border),
    where the surgeon strips the tissue off the bone and where a tie would shear the tissue
    across a single element."""
    th = np.abs(theta)
    vest = (th < VESTIBULE[0]) & (phi > VESTIBULE[1]) & (phi < VESTIBULE[2])
    bsso = (th > BSSO_RELEASE[0]) & (th < BSSO_RELEASE[1]) \
        & (phi < np.where(th >= hg.RAMUS, 2.0, VESTIBULE[2]))
    ramus_top = (th >= hg.RAMUS) & (phi > -8.0) & (phi < 4.0)
    return vest | (phi < FLOOR_OF_MOUTH) | bsso | ramus_top


def _genioplasty_release(theta, phi):
    """Region (chart) of the mandible's deep points degloved for a genioplasty (the builder
    lists the mandible-attached points in it as node set "release_genioplasty"): the
    anterior mandible between the vestibule fornix and the osteotomy line, between the mental
    foramina, and a subperiosteal tunnel GENIOPLASTY_TUNNEL deg high along the cut out to the
    lower border. The chin segment keeps its soft tissue (the pedicle over its anterior and
    inferior surfaces). This is the intra-oral sliding genioplasty (Trauner R., Obwegeser H.,
    Oral Surg Oral Med Oral Pathol 10:677-689, 1957; Hoenig J.F., Aesthetic Plast Surg
    31:384-391, 2007); the mental foramen lies below the second premolar (Greenstein G.,
    Tarnow D., J Periodontol 77:1933-1943, 2006). Tying the tissue on both sides of the cut
    imposes the bony step on the tissue itself: a displacement jump between neighbouring
    nodes, which has no limit under mesh refinement (the fine mesh inverts elements there)."""
    th = np.abs(theta)
    gen = hg.genioplasty_line(th)
    front = (th <= MENTAL_FORAMEN) & (phi <= VESTIBULE[1])
    tunnel = phi < gen + GENIOPLASTY_TUNNEL
    return (front | tunnel) & (gen >= hg.MANDIBLE_BORDER)


def _skin_regions(skin, theta, phi, side):
    t, p, s = theta[skin], phi[skin], side[skin]
    at = np.abs(t)
    name = np.full(len(skin), "", dtype=object)
    nw = hg.nose_weight(t, p)

    def put(mask, value):
        m = mask & (name == "")
        name[m] = value

    put((nw >= 0.35) & (p > -7.6) & (p < 16.0), "nose")
    put((nw >= 0.35) & (p >= 16.0), "nasal_root")
    lips = at <= hg.THETA_COMMISSURE + 4.0
    put(lips & (p <= -7.6) & (p >= _S), "upper_lip")
    put(lips & (p >= -32.0) & (p < _S), "lower_lip")
    put((at <= 26.0) & (p >= -52.0) & (p < -32.0), "chin")
    put((at <= 40.0) & (p < -52.0), "submental")
    lr = np.where(t >= 0, "right", "left")
    for m_name, mask in [("infraorbital", (p >= 4.0) & (at <= 62.0)),
                         ("preauricular", (at > 62.0) & (p >= -50.0)),
                         ("cheek", p >= -52.0), ("submandibular", np.ones_like(p, bool))]:
        for side_name in ("left", "right"):
            put(mask & (lr == side_name), f"{m_name}_{side_name}")
    return {r: skin[name == r] for r in sorted(set(name))}


def report(model: FaceModel, resolution: str) -> str:
    sj = scaled_jacobian(model.nodes, model.hexes)
    counts = np.bincount(model.labels, minlength=len(model.label_names))
    lines = [f"{resolution}: {model.n_elements} hexahedra, {model.n_nodes} nodes; "
             f"scaled Jacobian min {sj.min():.3f}, mean {sj.mean():.3f}, "
             f"elements below 0.5: {int(np.sum(sj < 0.5))}"]
    lines.append("  labels: " + ", ".join(f"{n} {c}" for n, c in zip(model.label_names, counts)))
    lines.append("  node sets: " + ", ".join(f"{k} {len(v)}" for k, v in model.node_sets.items()))
    lines.append("  facet sets: " + ", ".join(f"{k} {len(v)}" for k, v in model.facet_sets.items()))
    # soft-tissue thickness along the rays (skin node to the deep node of its column)
    nk = round(model.n_elements / len(model.facet_sets["skin"]))
    def thick(nodes):
        nodes = np.atleast_1d(nodes)
        return np.linalg.norm(model.nodes[nodes] - model.nodes[nodes - nk], axis=1)
    marks = ", ".join(f"{k} {thick(model.landmarks[k])[0]:.1f}" for k in ("Prn", "Sn", "Ls", "Li", "Pog", "Me"))
    cheek = np.median(thick(model.regions["cheek_right"]))
    infra = np.median(thick(model.regions["infraorbital_right"]))
    layer = [np.median(np.linalg.norm(model.nodes[model.node_sets["skin"] - nk + k + 1]
                                      - model.nodes[model.node_sets["skin"] - nk + k], axis=1))
             for k in range(nk)]
    lines.append(f"  soft-tissue thickness (mm): {marks}; cheek median {cheek:.1f}, "
                 f"infraorbital median {infra:.1f}")
    lines.append("  median layer thickness deep -> skin (mm): " + ", ".join(f"{t:.1f}" for t in layer))
    return "\n".join(lines)
