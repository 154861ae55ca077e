"""Checks of the committed generic face meshes (issue 3): counts, quality, symmetry, labels
and fibres, the open mouth, attachments, contact facets, teeth, regions and landmarks."""
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

import generic_mesh
from facemodel import head_geometry as hg
from facemodel.model import ATTACHMENT_SETS, LABEL_NAMES, LANDMARK_NAMES, MUSCLES
from generic_mesh import builder
from generic_mesh.quality import HEX_FACES, hex_volumes, scaled_jacobian

RESOLUTIONS = ("coarse", "standard", "fine")


@pytest.fixture(scope="module", params=RESOLUTIONS)
def model(request):
    return generic_mesh.load(request.param)


@pytest.fixture(scope="module")
def coarse():
    return generic_mesh.load("coarse")


@pytest.fixture(scope="module")
def standard():
    return generic_mesh.load("standard")


def test_element_counts():
    assert generic_mesh.load("coarse").n_elements <= 2000
    assert 8000 <= generic_mesh.load("standard").n_elements <= 15000
    assert generic_mesh.load("fine").n_elements >= 40000


def test_committed_files_are_the_builder_output(coarse):
    # The committed coarse mesh must be what the builder produces now (rebuild with
    # `python -m generic_mesh` after changing the geometry); 1e-9 mm: written in float64.
    fresh = builder.build("coarse")
    np.testing.assert_allclose(fresh.nodes, coarse.nodes, atol=1e-9)
    np.testing.assert_array_equal(fresh.hexes, coarse.hexes)
    np.testing.assert_array_equal(fresh.labels, coarse.labels)


def test_scaled_jacobian_reference_shapes():
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                     [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    h = np.arange(8)[None]
    assert scaled_jacobian(cube, h)[0] == pytest.approx(1.0, abs=1e-12)
    # a parallelepiped sheared by angle a in the x-z plane: every corner has sin(90 - a)
    a = np.radians(50.0)
    sheared = cube.copy()
    sheared[4:, 0] += np.tan(a)
    assert scaled_jacobian(sheared, h)[0] == pytest.approx(np.cos(a), abs=1e-12)
    assert hex_volumes(sheared, h)[0] == pytest.approx(1.0, abs=1e-12)
    inverted = cube[[4, 5, 6, 7, 0, 1, 2, 3]]
    assert scaled_jacobian(inverted, h)[0] < 0


def test_quality(model):
    sj = scaled_jacobian(model.nodes, model.hexes)
    assert sj.min() >= 0.3
    assert np.all(hex_volumes(model.nodes, model.hexes) > 0)


def test_mirror_symmetry(model):
    # mirrored nodes coincide to 1e-9 mm (the builder mirrors the right half exactly)
    tree = cKDTree(model.nodes)
    d, mirror = tree.query(model.nodes * [-1.0, 1.0, 1.0])
    assert d.max() < 1e-9
    # labels and (axial) fibres are mirrored too
    c = model.element_centres
    d, emirror = cKDTree(c).query(c * [-1.0, 1.0, 1.0])
    assert d.max() < 1e-9
    np.testing.assert_array_equal(model.labels, model.labels[emirror])
    f, fm = model.fibres, model.fibres[emirror] * [-1.0, 1.0, 1.0]
    cos = np.abs(np.einsum("ij,ij->i", f, fm))
    muscle = np.isin(model.labels, [model.label_id(m) for m in MUSCLES])
    assert np.all(cos[muscle] > 1 - 1e-9)


def test_labels_and_fibres(model):
    assert model.label_names == LABEL_NAMES
    counts = np.bincount(model.labels, minlength=len(LABEL_NAMES))
    assert np.all(counts > 0), dict(zip(LABEL_NAMES, counts))
    muscle = np.isin(model.labels, [model.label_id(m) for m in MUSCLES])
    norms = np.linalg.norm(model.fibres, axis=1)
    np.testing.assert_allclose(norms[muscle], 1.0, atol=1e-12)
    assert np.all(norms[~muscle] == 0.0)
    # dermis is the outer layer: every skin facet belongs to a dermis element
    skin_el = _owner(model, model.facet_sets["skin"])
    assert np.all(model.labels[skin_el] == model.label_id("dermis"))


def _owner(model, quads):
    """Element owning each quad (the one containing its four nodes)."""
    key = {tuple(sorted(f)): e for e, fs in enumerate(model.hexes[:, HEX_FACES]) for f in fs}
    return np.array([key[tuple(sorted(q))] for q in quads])


def _gradient_at_centre(model, elements, values):
    """3D gradient of a nodal field at element centres (trilinear map, exact)."""
    x = model.nodes[model.hexes[elements]]
    v = values[model.hexes[elements]]
    ref = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                    [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float) / 8.0
    jac = np.einsum("mia,ib->mab", x, ref)          # dx/dxi at the centre
    gxi = np.einsum("mi,ib->mb", v, ref)            # dv/dxi
    return np.linalg.solve(np.transpose(jac, (0, 2, 1)), gxi[..., None])[..., 0]


def test_orbicularis_fibres_run_around_the_mouth(model):
    orb = model.elements_with_label("orbicularis_oris")
    theta, phi, _ = hg.from_cartesian(model.nodes)
    q = builder.orbicularis_ring(theta, phi)
    g = _gradient_at_centre(model, orb, q)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    f = model.fibres[orb]
    # tangent to the rings q = const: the fibre has no component along grad q. On the tensor
    # grid q is quadratic in (theta, phi) and the centre derivatives are exact, so only
    # round-off remains (1e-9); in the rows beside the mouth gap the nodes bend by up to
    # LIP_GAP / 2 (~0.3 deg) across an element, an O(gap / element height) deviation: 0.02
    # (the fibre within 1.2 deg of the ring).
    dots = np.abs(np.einsum("ij,ij->i", f, g))
    assert dots.max() < 0.02
    assert np.median(dots) < 1e-9
    # near the midline the ring is horizontal: fibres run left-right (|f_x| ~ 1); 0.85 allows
    # the lip surface curving backwards across the first coarse column (up to ~30 deg)
    c = model.element_centres[orb]
    near = np.abs(c[:, 0]) < 5.0
    assert near.sum() > 0 and np.all(np.abs(f[near, 0]) > 0.85)


def test_mouth_is_open_between_commissures(model):
    up = model.facet_sets["lip_upper_contact"]
    lo = model.facet_sets["lip_lower_contact"]
    assert len(up) == len(lo) > 0
    shared = np.intersect1d(up, lo)
    # the only shared nodes are on the commissure columns (theta = +-THETA_COMMISSURE)
    theta, phi, _ = hg.from_cartesian(model.nodes[shared])
    np.testing.assert_allclose(np.abs(theta), hg.THETA_COMMISSURE, atol=1e-9)
    # the upper lip's elements and the lower lip's share no node between the commissures
    e_up, e_lo = _owner(model, up), _owner(model, lo)
    common = np.intersect1d(model.hexes[e_up], model.hexes[e_lo])
    t2, _, _ = hg.from_cartesian(model.nodes[common])
    assert np.all(np.abs(np.abs(t2) - hg.THETA_COMMISSURE) < 1e-9)
    # facing each other: upper lip facets point down, lower lip facets up (on the midline)
    n_up = _normals(model.nodes, up)
    n_lo = _normals(model.nodes, lo)
    assert np.all(n_up[:, 2] < 0) and np.all(n_lo[:, 2] > 0)
    # stomion nodes separate; gap ~1 mm at the midline (LIP_GAP), more with the overjet
    stms, stmi = (model.nodes[model.landmarks[k]] for k in ("Stms", "Stmi"))
    assert stms[2] > stmi[2] and 0.8 < np.linalg.norm(stms - stmi) < 5.0


def _normals(nodes, quads):
    a, b, c, d = (nodes[quads[:, i]] for i in range(4))
    n = np.cross(c - a, d - b)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("name", ["skin", "lip_upper_contact", "lip_lower_contact",
                                  "lip_upper_teeth", "lip_lower_teeth", "deep_bone"])
def test_facets_point_outward(standard, name):
    quads = standard.facet_sets[name]
    assert len(quads) > 0
    owner = _owner(standard, quads)
    out = standard.nodes[quads].mean(1) - standard.element_centres[owner]
    assert np.all(np.einsum("ij,ij->i", _normals(standard.nodes, quads), out) > 0)


def test_attachments(model):
    sets = [model.node_sets[ATTACHMENT_SETS[s]] for s in model.segments]
    free = model.node_sets["deep_free"]
    allsets = sets + [free]
    for i in range(len(allsets)):
        assert len(allsets[i]) > 0
        for j in range(i + 1, len(allsets)):
            assert len(np.intersect1d(allsets[i], allsets[j])) == 0
    # every deep node is attached or free, and no skin node is either
    deep = np.unique(model.hexes[:, [0, 1, 2, 3]][_deep_layer(model)])
    np.testing.assert_array_equal(np.sort(np.concatenate(allsets)), deep)
    assert len(np.intersect1d(np.concatenate(allsets), model.node_sets["skin"])) == 0
    z = {s: model.nodes[model.node_sets[ATTACHMENT_SETS[s]], 2].mean() for s in model.segments}
    assert z["skull"] > z["maxilla"] > model.nodes[model.landmarks["Stms"], 2] > z["chin"]
    # the chin segment is the midline part of the lower face
    assert np.abs(model.nodes[model.node_sets["attach_chin"], 0]).max() < 35.0


def _deep_layer(model):
    """Elements of the deepest layer (the builder orders elements with the layer fastest)."""
    n_layers = round(len(model.hexes) / len(model.facet_sets["skin"]))
    return np.arange(len(model.hexes)) % n_layers == 0


def test_landmarks(model):
    assert set(model.landmarks) == set(LANDMARK_NAMES)
    skin = set(model.node_sets["skin"].tolist())
    assert all(v in skin for v in model.landmarks.values())
    p = model.landmark_positions
    # mid-sagittal landmarks on x = 0; commissures on their side
    for k in ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me"):
        assert abs(p[k][0]) < 1e-9
    assert p["ChL"][0] < -15 and p["ChR"][0] > 15
    # pronasale is the most anterior skin point; the vertical order of the profile
    assert p["Prn"][1] == pytest.approx(model.nodes[model.node_sets["skin"], 1].max(), abs=1e-9)
    zs = [p[k][2] for k in ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me")]
    assert all(a > b for a, b in zip(zs[1:], zs[2:]))
    assert p["Ls"][1] > p["ChR"][1] + 10.0 and p["Pog"][1] > p["Me"][1]


def test_soft_tissue_thickness_is_realistic(standard):
    m = standard
    deep_quads = m.hexes[_deep_layer(m)][:, [0, 3, 2, 1]]
    deep = trimesh.Trimesh(m.nodes, np.concatenate([deep_quads[:, [0, 1, 2]], deep_quads[:, [0, 2, 3]]]),
                           process=False)
    pq = trimesh.proximity.ProximityQuery(deep)

    def thickness(idx):
        return np.abs(pq.signed_distance(m.nodes[np.atleast_1d(idx)]))

    # upper lip 12-15 mm, chin 10-12 mm (Holdaway 1983), +-1 mm for the normal-vs-ray
    # measure and the facetted deep surface; cheeks 10-20 mm.
    assert 11.0 <= thickness(m.landmarks["Ls"])[0] <= 16.0
    assert 9.0 <= thickness(m.landmarks["Pog"])[0] <= 13.0
    cheek = np.abs(thickness(m.regions["cheek_right"]))
    assert 10.0 <= np.median(cheek) <= 20.0


def test_regions_partition_the_skin(model):
    need = {"nose", "upper_lip", "lower_lip", "chin", "cheek_left", "cheek_right",
            "infraorbital_left", "infraorbital_right", "submental"}
    assert need <= set(model.regions)
    allr = np.concatenate(list(model.regions.values()))
    assert len(allr) == len(np.unique(allr))
    np.testing.assert_array_equal(np.sort(allr), np.sort(model.node_sets["skin"]))
    assert set(model.unoperated_regions) <= set(model.regions)
    assert np.all(model.nodes[model.regions["cheek_right"], 0] > 0)
    assert np.all(model.nodes[model.regions["cheek_left"], 0] < 0)
    assert model.landmarks["Ls"] in model.regions["upper_lip"]
    assert model.landmarks["Li"] in model.regions["lower_lip"]
    assert model.landmarks["Prn"] in model.regions["nose"]


def test_teeth(model):
    assert model.teeth["upper"][2] == "maxilla" and model.teeth["lower"][2] == "mandible"
    upper, lower = model.teeth_mesh("upper"), model.teeth_mesh("lower")
    for t in (upper, lower):
        assert t.is_watertight and t.volume > 0
    # the front teeth part along the mouth-line cone (phi = PHI_STOMION seen from C), like
    # the lips; the back teeth meet on the flat occlusal plane
    tu, pu, _ = hg.from_cartesian(upper.vertices)
    tl, pl, _ = hg.from_cartesian(lower.vertices)
    assert pu[np.abs(tu) < 14.0].min() > hg.PHI_STOMION
    assert pl[np.abs(tl) < 14.0].max() < hg.PHI_STOMION
    assert upper.vertices[:, 2].min() > lower.vertices[:, 2].max() - 10.0
    # no node of the face starts inside a tooth (contact starts without penetration)
    for t in (upper, lower):
        lo, hi = t.bounds
        near = np.all((model.nodes > lo - 1.0) & (model.nodes < hi + 1.0), axis=1)
        assert trimesh.proximity.signed_distance(t, model.nodes[near]).max() < 0.0
    # the teeth stay behind the soft tissue: on every ray, inside the deep surface
    for arch in ("upper", "lower"):
        v = model.teeth[arch][0]
        t, p, r = hg.from_cartesian(v)
        side = np.full_like(t, 1.0 if arch == "upper" else -1.0)
        assert np.all(r <= hg.deep_radius(t, p, side=side) + 1e-6), arch
    # the lips rest on the incisors: the lip/teeth facets near the midline lie within 1 mm
    # of the teeth surface (TEETH_GAP = 0.25 mm plus the facetting of both surfaces)
    for facets, t in (("lip_upper_teeth", upper), ("lip_lower_teeth", lower)):
        c = model.nodes[model.facet_sets[facets]].mean(1)
        near = np.abs(c[:, 0]) < 6.0
        d = np.abs(trimesh.proximity.ProximityQuery(t).signed_distance(c[near]))
        assert near.sum() > 0 and d.min() < 1.0


def test_load_rejects_unknown_resolution():
    with pytest.raises(ValueError):
        generic_mesh.load("huge")


def test_mean_head_is_the_generic_geometry(coarse):
    head = generic_mesh.mean_head(size=4.0)
    assert head.skin.is_watertight and all(m.is_watertight for m in head.bones.values())
    # the generic skin nodes lie on the mean head's skin (facets of ~3.3 mm: sagitta < 0.5 mm
    # away from the lip crease and the nose tip)
    d = np.abs(trimesh.proximity.ProximityQuery(head.skin).signed_distance(
        coarse.nodes[coarse.node_sets["skin"]]))
    assert np.median(d) < 0.2 and np.percentile(d, 95) < 1.0
    # The mean head's landmarks are located by their anatomical definitions on its exact skin
    # (head_geometry.anatomical_landmarks); the generic mesh's are the skin nodes nearest their
    # rays (head_geometry.LANDMARK_ANGLES). They coincide where the definition is the ray point
    # (cheilia) and otherwise agree to within half a coarse skin facet edge (measured up to
    # 3.4 mm, Ls, against a median edge of 9 mm; menton, the chin's extreme along
    # head_geometry.MENTON_TILT, lies 0.54 mm from its ray).
    quads = coarse.facet_sets["skin"]
    edge = np.median(np.linalg.norm(coarse.nodes[quads] - coarse.nodes[np.roll(quads, 1, axis=1)], axis=2))
    for k, v in head.landmarks.items():
        d = np.linalg.norm(np.asarray(v) - coarse.landmark_positions[k])
        assert d < (1e-9 if k in ("ChL", "ChR") else 0.5 * edge), (k, d)


def test_attached_nodes_lie_on_their_bone(standard):
    # every attachment node sits on the closed bone surface of its segment in the mean head
    # (the deep surface is the bone wherever tissue is tied); 1 mm covers the facetting of the
    # shells (structured, ~2 mm facets on curved bone)
    head = generic_mesh.mean_head(size=4.0)
    for seg in standard.segments:
        x = standard.nodes[standard.node_sets[ATTACHMENT_SETS[seg]]]
        _, d, _ = trimesh.proximity.closest_point(head.bones[seg], x)
        assert d.max() < 1.0, seg


def test_genioplasty_release(model):
    # The tissue a genioplasty degloves (between the vestibule fornix and the osteotomy,
    # between the mental foramina, and the tunnel along the cut) is listed as
    # "release_genioplasty": mandible-tied nodes, and every mandible-tied node in that region.
    th, ph, _ = hg.from_cartesian(model.nodes)
    man = model.node_sets["attach_mandible"]
    rel = model.node_sets["release_genioplasty"]
    assert len(rel) > 0 and np.all(np.isin(rel, man))
    at, ap = np.abs(th[man]), ph[man]
    gen = hg.genioplasty_line(at)
    # 1e-6 deg: the round trip through Cartesian coordinates
    inside = ((at <= builder.MENTAL_FORAMEN - 1e-6) & (ap < builder.VESTIBULE[1] - 1e-6)) \
        | ((ap < gen + builder.GENIOPLASTY_TUNNEL - 1e-6) & (gen >= hg.MANDIBLE_BORDER + 1e-6))
    assert np.all(np.isin(man[inside], rel))
    # and nothing of the chin segment (its tissue is its pedicle)
    chin = model.node_sets["attach_chin"]
    assert not np.isin(rel, chin).any() and np.all(ph[rel] > hg.genioplasty_line(np.abs(th[rel])) - 1e-6)
