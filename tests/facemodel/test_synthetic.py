"""Synthetic heads: closed surfaces, deterministic per seed, different from the generic head,
landmarks on the skin, the CT volume giving back the skin; the `faceplan synth` command."""
import json

import numpy as np
import pytest
import trimesh

from facemodel import head_geometry as hg
from facemodel import synthetic as sy

# 3 mm skin facets (a level-5 geodesic sphere projected on the skin) keep the tests quick
FAST = dict(size=3.0)


@pytest.fixture(scope="module")
def head():
    return sy.synthetic_head(11, **FAST)


def test_surfaces_are_closed(head):
    assert head.skin.is_watertight and head.skin.is_winding_consistent and head.skin.volume > 0
    assert set(head.bones) == {"skull", "maxilla", "mandible", "chin"}
    for seg, m in head.bones.items():
        assert m.is_watertight and m.volume > 0, seg
    for arch, (v, f, seg) in head.teeth.items():
        t = trimesh.Trimesh(v, f, process=False)
        assert t.is_watertight and t.volume > 0
    assert head.teeth["upper"][2] == "maxilla" and head.teeth["lower"][2] == "mandible"


def _inside(surface, points):
    """Points enclosed by a closed surface (VTK's enclosed-points filter, fast)."""
    import pyvista as pv

    faces = np.hstack([np.full((len(surface.faces), 1), 3), surface.faces]).ravel()
    closed = pv.PolyData(np.asarray(surface.vertices), faces)
    sel = pv.PolyData(np.asarray(points, float)).select_interior_points(closed, check_surface=True)
    name = next(k for k in sel.point_data.keys() if "selected" in k.lower())
    return np.asarray(sel.point_data[name]).astype(bool)


def test_bones_and_teeth_inside_the_skin(head):
    for seg, m in head.bones.items():
        assert np.all(_inside(head.skin, m.vertices)), seg
    for arch, (v, f, _) in head.teeth.items():
        assert np.all(_inside(head.skin, v))


def test_landmarks_on_the_skin(head):
    names = list(hg.LANDMARK_ANGLES)
    pts = np.array([head.landmarks[k] for k in names])
    d = dict(zip(names, np.abs(trimesh.proximity.ProximityQuery(head.skin).signed_distance(pts))))
    # landmarks sit on the exact surface; ~3.3 mm facets deviate from it by their sagitta,
    # e^2 / (8 R) < 0.3 mm for the tightest curvature radius R ~ 5 mm (nose tip, lips): 1 mm.
    # The stomia sit at the crease where the upper lip overhangs the lower one (a step the
    # facets cut across): 2 mm there.
    for k, v in d.items():
        assert v < (2.0 if k in ("Stms", "Stmi") else 1.0), (k, v)


def test_deterministic_per_seed(head):
    again = sy.synthetic_head(11, **FAST)
    np.testing.assert_array_equal(again.skin.vertices, head.skin.vertices)
    np.testing.assert_array_equal(again.skin.faces, head.skin.faces)
    np.testing.assert_array_equal(again.teeth["upper"][0], head.teeth["upper"][0])
    for seg in head.bones:
        np.testing.assert_array_equal(again.bones[seg].vertices, head.bones[seg].vertices)
    assert again.shape == head.shape
    assert sy.random_shape(12) != head.shape


def test_heads_differ_from_the_generic_head():
    generic = {k: hg.to_cartesian(t, p, hg.skin_radius(t, p, side=s))
               for k, (t, p, s) in hg.LANDMARK_ANGLES.items()}
    for seed in range(12):
        shape = sy.random_shape(seed)
        assert sy.face_difference(shape) >= sy.MIN_DIFFERENCE
        assert abs(shape.mandible_ap - shape.maxilla_ap) >= 3.0 - 1e-9
        marks = sy.landmarks(shape)
        moved = np.mean([np.linalg.norm(marks[k] - generic[k]) for k in generic])
        assert moved > 2.0, seed


def test_ct_volume_gives_back_the_skin(head):
    from facemodel import ct
    from facemodel.ct_phantom import ct_volume_from_surfaces

    hu, affine = ct_volume_from_surfaces(head.skin, head.bones, spacing=1.5, seed=1)
    vol = ct.CTVolume(hu, affine)
    skin = ct.skin_surface(vol)
    d = np.abs(trimesh.proximity.ProximityQuery(head.skin).signed_distance(skin.vertices[::25]))
    assert d.mean() < 0.5


def test_synth_command_writes_case_folders(tmp_path):
    from planner.case import load_case
    from planner.cli import main
    from planner.plan import load_plan

    out = tmp_path / "cases"
    key = tmp_path / "key.json"
    assert main(["synth", "--out", str(out), "--count", "2", "--seed", "4", "--surface-size", "4",
                 "--key", str(key)]) == 0
    cases = sorted(p.name for p in out.iterdir())
    assert cases == ["synth_0004", "synth_0005"]
    case = load_case(out / "synth_0004")
    assert set(case.bones) == {"skull", "maxilla", "mandible", "chin"}
    assert set(case.landmarks) >= {"Prn", "Sn", "Ls", "Li", "Pog", "Me", "ChL", "ChR"}
    plan = load_plan(out / "synth_0004" / "plan.yaml")
    assert {"maxilla", "mandible", "chin"} <= set(plan.segments)
    truth = json.loads(key.read_text())
    assert [c["seed"] for c in truth] == [4, 5]
    assert truth[0]["shape"] == sy.random_shape(4).as_dict()
    assert truth[0]["effect"] is None and not (out / "synth_0004" / "postop").exists()


@pytest.mark.parametrize("argv", [["--withheld-effect", "wind"], ["--withheld-effect", "swelling=9"],
                                  ["--count", "0"], ["--seed", "-1"], ["--case-max-minutes", "0"],
                                  # no truth solve to log; a log inside --out names the effect
                                  ["--solve-log", "LOGS"],
                                  ["--withheld-effect", "none", "--solve-log", "OUT/logs"]])
def test_synth_refuses_bad_input(tmp_path, argv):
    from planner.cli import main

    out = tmp_path / "cases"
    argv = [a.replace("OUT", str(out)).replace("LOGS", str(tmp_path / "logs")) for a in argv]
    assert main(["synth", "--out", str(out), *argv]) == 2
    assert not out.exists() and not (tmp_path / "logs").exists()


@pytest.mark.parametrize("shape", [
    hg.GENERIC,
    hg.HeadShape(maxilla_ap=-4.0, mandible_ap=7.0, chin_projection=2.0),               # strong III
    hg.HeadShape(maxilla_ap=3.0, mandible_ap=-7.0, chin_projection=-3.0, soft_tissue=1.15),  # strong II
    hg.HeadShape(asymmetry=2.5, width=1.06, mandible_ap=3.0, height=0.94),
], ids=["generic", "class_III", "class_II", "asymmetric"])
def test_landmarks_at_their_anatomical_definitions(shape):
    """Each landmark checked against its definition by an independent search: bounded scalar
    optimisation along the midline ray curve for the most anterior points, scipy's convex hull
    for the deepest points of the concavities."""
    from scipy.optimize import minimize_scalar
    from scipy.spatial import ConvexHull

    lm = hg.anatomical_landmarks(shape)

    def point(phi):
        side = 1.0 if phi >= hg.PHI_STOMION else -1.0
        return hg.to_cartesian(0.0, phi, hg.skin_radius(0.0, phi, shape, side=side), shape)

    def elevation(p):
        return float(hg.from_cartesian(p, shape)[1])

    def most_anterior(lo, hi):
        r = minimize_scalar(lambda f: -point(f)[1], bounds=(lo, hi), method="bounded",
                            options={"xatol": 1e-4})
        return point(r.x)

    # the profile is sampled every 0.02 deg (~0.035 mm): 0.05 mm covers the sampling; a flat
    # maximum is compared by its height (y) as well, which the sampling cannot miss by more
    # than ~1e-4 mm
    prn = most_anterior(-15.0, 25.0)
    assert abs(prn[1] - lm["Prn"][1]) < 1e-3 and np.linalg.norm(prn - lm["Prn"]) < 0.3
    phi_st = hg.PHI_STOMION
    assert elevation(lm["Stms"]) == pytest.approx(phi_st + hg.STOMION_INSET, abs=0.03)
    assert elevation(lm["Stmi"]) == pytest.approx(phi_st - hg.STOMION_INSET, abs=0.03)
    # subnasale: the deepest point under the anterior hull of the arc pronasale -> stomion
    phis = np.arange(elevation(lm["Prn"]), phi_st + hg.STOMION_INSET, -0.02)
    yz = np.array([point(f)[1:] for f in phis])
    hull = ConvexHull(np.vstack([yz, [[-1e3, 0.5 * (yz[0, 1] + yz[-1, 1])]]]))  # closed behind
    depth_best, sn = -1.0, None
    for i, j in hull.simplices:
        if max(i, j) >= len(yz) or abs(i - j) < 2:
            continue
        i, j = sorted((i, j))
        chord = yz[j] - yz[i]
        inward = np.array([chord[1], -chord[0]]) / np.linalg.norm(chord)
        inward = -inward if inward[0] > 0 else inward
        d = (yz[i + 1:j] - yz[i]) @ inward
        if d.max() > depth_best:
            depth_best, sn = d.max(), yz[i + 1 + int(np.argmax(d))]
    assert np.linalg.norm(sn - lm["Sn"][1:]) < 0.05 and abs(lm["Sn"][0] - point(0.0)[0]) < 0.05 + abs(shape.asymmetry)
    # labrale superius: the most anterior point between subnasale and stomion superius
    ls = most_anterior(phi_st + hg.STOMION_INSET, elevation(lm["Sn"]))
    assert abs(ls[1] - lm["Ls"][1]) < 1e-3
    # lower lip and chin: the most anterior points above / below the labiomental fold, the
    # fold lying between them and behind both
    li = most_anterior(elevation(lm["Pog"]) + 1.0, phi_st - hg.STOMION_INSET)
    pog = most_anterior(-62.0, elevation(lm["Li"]) - 1.0)
    assert abs(li[1] - lm["Li"][1]) < 1e-3 and abs(pog[1] - lm["Pog"][1]) < 1e-3
    between = np.array([point(f)[1] for f in np.arange(elevation(lm["Li"]), elevation(lm["Pog"]), -0.1)])
    # (the receding chin of the strong class II leaves a fold only ~0.4 mm deep)
    assert between.min() < min(lm["Li"][1], lm["Pog"][1]) - 0.2
    # menton: the chin's extreme below pogonion along the direction MENTON_TILT deg in front of
    # straight down, by bounded optimisation (same 1e-3 mm on the extreme's height as for the
    # most anterior points), an interior extreme (not the bound: the submental contour
    # descends less steeply), where the profile's tangent descends MENTON_TILT deg backwards
    # (central difference over +-0.2 deg: 1.5 deg covers the chord and the curvature change)
    a = np.radians(hg.MENTON_TILT)
    d = np.array([np.sin(a), -np.cos(a)])
    r = minimize_scalar(lambda f: -point(f)[1:] @ d, bounds=(-70.0, elevation(lm["Pog"])),
                        method="bounded", options={"xatol": 1e-4})
    assert abs(point(r.x)[1:] @ d - lm["Me"][1:] @ d) < 1e-3
    assert -69.0 < r.x < elevation(lm["Pog"]) - 1.0 and lm["Me"][2] < lm["Pog"][2] - 2.0
    t = point(r.x - 0.2)[1:] - point(r.x + 0.2)[1:]
    assert np.degrees(np.arctan2(-t[1], -t[0])) == pytest.approx(hg.MENTON_TILT, abs=1.5)
    # midline landmarks on the face's own midline: x = 0 on a symmetric head; the chin of an
    # asymmetric one shifted with the lower face
    if shape.asymmetry == 0.0:
        for k in ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me"):
            assert abs(lm[k][0]) < 1e-9, k
    else:
        assert lm["Pog"][0] > 0.8 * shape.asymmetry


# ------------------------------------------------------------------ the patient skin as a scan
def test_face_zoom_is_the_conformal_zoom_of_the_sphere():
    """Directions keep unit length and their azimuth about the face's centre, and their angle
    a from it becomes 2 atan(tan(a/2) / zoom) (the stereographic plane scaled by 1/zoom)."""
    rng = np.random.default_rng(3)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_array_equal(sy.face_zoom(d, 1.0), d)
    c = hg.direction(*sy.FACE_CENTRE)
    z = sy.face_zoom(d, 2.5)
    np.testing.assert_allclose(np.linalg.norm(z, axis=1), 1.0, atol=1e-12)
    a = np.arccos(np.clip(d @ c, -1.0, 1.0))
    a2 = np.arccos(np.clip(z @ c, -1.0, 1.0))
    # arccos near 0 loses ~1e-8 rad to round-off
    np.testing.assert_allclose(a2, 2.0 * np.arctan(np.tan(a / 2.0) / 2.5), atol=1e-7)
    # same half-plane through the centre: the component across it is unchanged in direction
    perp = lambda v: v - np.outer(v @ c, c)   # noqa: E731
    pd, pz = perp(d), perp(z)
    cos = np.einsum("ij,ij->i", pd, pz) / np.linalg.norm(pd, axis=1) / np.linalg.norm(pz, axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    np.testing.assert_allclose(sy.face_zoom(c[None], 2.5)[0], c, atol=1e-12)


@pytest.fixture(scope="module")
def scan():
    """Patient 11's skin as `synthetic_head` gives it by default (SCAN_SIZE, SCAN_ZOOM)."""
    shape = sy.random_shape(11)
    return shape, sy.skin_surface(shape, sy.SCAN_SIZE, zoom=sy.SCAN_ZOOM)


def test_scan_skin_samples_the_face_like_a_ct_skin(scan):
    """A CT-derived skin (marching cubes on 0.5-1 mm voxels) has vertices every 0.5-1 mm: the
    synthetic scan's edges over lips, nose and chin have a median of at most 1.05 mm (measured
    0.74 / 0.97 / 1.02), 95 % under 1.6 mm; the whole head in under 50,000 vertices."""
    shape, skin = scan
    assert skin.is_watertight and skin.is_winding_consistent and skin.volume > 0
    assert len(skin.vertices) < 50_000
    v = np.asarray(skin.vertices)
    e = skin.edges_unique
    length = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    th, ph, _ = hg.from_cartesian(0.5 * (v[e[:, 0]] + v[e[:, 1]]), shape)
    regions = {"lips": (np.abs(th) < 25) & (ph > -26) & (ph < -12),
               "nose": (np.abs(th) < 15) & (ph > -10) & (ph < 25),
               "chin": (np.abs(th) < 25) & (ph > -55) & (ph < -30)}
    for name, sel in regions.items():
        # the lips' step (upper and lower lip offset) is bridged by one long facet per column:
        # the percentile, not the maximum
        assert np.median(length[sel]) < 1.05, name
        assert np.percentile(length[sel], 95) < 1.6, name
    # the back of the head is coarser (the zoom moves the vertices to the face)
    assert np.median(length[np.abs(th) > 120]) > 3.0


def test_mouth_corner_is_the_end_of_the_fissure():
    """The patients' oral fissure (the groove along the lips' contact line) ends at the
    commissure within `fissure_fade` (1 deg) and the generic head keeps its 6 deg fade (its
    committed mesh is built from it): the soft tissue along the mouth line differs between
    the two exactly by the groove's 1.5 mm times the difference of the tapers."""
    theta = np.linspace(0.0, 25.0, 251)
    phi = np.full_like(theta, hg.PHI_STOMION)
    patient = hg.HeadShape()
    assert patient.fissure_fade == 1.0 and hg.GENERIC.fissure_fade == 6.0
    np.testing.assert_array_equal(hg.fissure_taper(theta, hg.GENERIC), hg.slit_taper(theta))
    diff = hg.soft_tissue_thickness(theta, phi, patient) - hg.soft_tissue_thickness(theta, phi, hg.GENERIC)
    expected = -1.5 * (hg.fissure_taper(theta, patient) - hg.slit_taper(theta))
    np.testing.assert_allclose(diff, expected, atol=1e-12)
    tap = hg.fissure_taper(theta, patient)
    assert np.all(tap[theta <= hg.THETA_COMMISSURE - 1.0] == 1.0)
    assert np.all(tap[theta >= hg.THETA_COMMISSURE] == 0.0)
    # the cheilion, on the mouth line at the commissure, is where the groove has just ended
    assert hg.fissure_taper(hg.THETA_COMMISSURE, patient) == 0.0
