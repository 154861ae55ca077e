"""Anatomical landmark search: plane cuts, summits, concavities and the mouth slit against
analytic geometry; on a synthetic head without landmarks, the located landmarks against the
head's true landmarks (their anatomical definitions on the exact skin)."""
import numpy as np
import pytest

from registration import MatchOptions, mesh_match_and_repair
from registration.landmark_search import (FISSURE_END_LEVEL, MENTON_TILT, STOMION_INSET_MM, _dense,
                                          _menton, anterior_summit, concave_corner,
                                          deepest_under_bitangent, fissure_end, lips_meeting,
                                          locate_landmarks, mirror_pairs, most_anterior, mouth_slit,
                                          plane_cut, sagittal_profile, skin_along_y,
                                          symmetry_plane)
from registration.surface import TargetSurface

trimesh = pytest.importorskip("trimesh")


def _sphere(radius, subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_plane_cut_of_a_sphere_is_one_closed_circle():
    v, f = _sphere(50.0)
    chains = plane_cut(v, f, 10.0)
    assert len(chains) == 1
    c = chains[0]
    assert np.allclose(c[0], c[-1])                      # closed
    assert np.allclose(c[:, 0], 10.0, atol=1e-5)
    r = np.linalg.norm(c[:, 1:], axis=1)
    # cut points lie on the facets' edges, chords of the sphere: inside it by at most the
    # sagitta e^2 / (8 R) of ~4 mm edges, 0.04 mm
    assert np.all(r <= np.sqrt(50.0**2 - 10.0**2) + 1e-9) and np.all(r > np.sqrt(50.0**2 - 10.0**2) - 0.06)
    # consecutive points are neighbours along the circle (chained, not shuffled)
    assert np.linalg.norm(np.diff(c, axis=0), axis=1).max() < 5.0


def _flat_summit():
    """A height field y = f(x, z), quadratic in x and cubic in z with a flat summit (the
    curvature radius along z is 20 mm, like a chin's), triangulated on a 3 mm grid that does
    not pass through the summit, and that summit."""
    def f(x, z):
        return 10.0 - x**2 / 30.0 - (z - 1.3) ** 2 / 40.0 - 0.002 * (z - 1.3) ** 3

    g = np.arange(-18.0, 18.1, 3.0) + 0.7
    xx, zz = np.meshgrid(g, g, indexing="ij")
    verts = np.column_stack([xx.ravel(), f(xx, zz).ravel(), zz.ravel()])
    n = len(g)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # summit: df/dz = -(z - 1.3) / 20 - 0.006 (z - 1.3)^2 = 0 at z = 1.3, x = 0
    return TargetSurface(verts, faces, "bump"), np.array([0.0, 10.0, 1.3])


def test_flat_summit_found_by_the_surface_fit():
    skin, top = _flat_summit()
    prof = sagittal_profile(skin, 0.0, top + [0.0, 0.0, 4.0], 15.0)
    assert len(prof) > 5 and prof[0, 2] > prof[-1, 2]    # ordered downwards
    raw = prof[np.argmax(prof[:, 1])]
    summit = anterior_summit(skin, most_anterior(prof), (-np.inf, np.inf), 8.0)
    # the fitted surface is of the field's own class and the vertices lie on the field: the
    # summit comes back exactly (to the least-squares round-off, 1e-6 mm is 1e5 times that),
    # then taken onto the facets along y (below it by their sagitta, 3^2 / (8 * 20) ~ 0.06 mm);
    # the facet point under the summit, found independently by a ray
    mesh = trimesh.Trimesh(skin.vertices, skin.faces, process=False)
    hits, _, _ = mesh.ray.intersects_location([[top[0], 100.0, top[2]]], [[0.0, -1.0, 0.0]])
    expected = hits[np.argmax(hits[:, 1])]
    assert np.linalg.norm(summit - expected) < 1e-6
    assert np.linalg.norm(summit - top) < 0.1
    # whereas the profile's best vertex is off along the flat top by a good part of a facet
    assert np.linalg.norm(raw - top) > 0.5


def test_summit_taken_onto_a_ridge_continuously():
    """A summit on a symmetric head lies on its mid-sagittal plane, on the ridge where the
    facets of both sides meet. A point just inside the skin there is equidistant from both
    facets: its closest skin point jumps from one to the other as x crosses 0 (here by 1e-7
    mm, a shift the fits upstream can make between two machines), whereas the skin point along
    y (`skin_along_y`) is continuous: it moves by about as much as the point did."""
    # a tent y = 10 - |x| / 2 over x, z in [-5, 5], ridge along x = 0
    verts = np.array([[-5.0, 7.5, -5.0], [0.0, 10.0, -5.0], [5.0, 7.5, -5.0],
                      [-5.0, 7.5, 5.0], [0.0, 10.0, 5.0], [5.0, 7.5, 5.0]])
    faces = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    skin = TargetSurface(verts, faces, "tent")
    left, right = (np.array([[x, 9.9, 0.3]]) for x in (-1e-7, 1e-7))
    jump = np.linalg.norm(skin.closest(left).points[0] - skin.closest(right).points[0])
    assert jump > 0.05                    # 2 * 0.1 mm * sin(tilt): the closest point jumps
    a, b = (skin_along_y(skin, p[0, 0], p[0, 2], p[0, 1]) for p in (left, right))
    # the tent's slope is 1/2: the points along y differ by 2e-7 in x and 1e-7 in y
    assert np.linalg.norm(a - b) < 1e-6
    np.testing.assert_allclose(a, [-1e-7, 10.0 - 0.5e-7, 0.3], atol=1e-12)


def test_deepest_point_under_the_bitangent():
    # two bumps at z = +-5 (y = 0) with a dip to y = -6.25 at z = 0 between them
    z = np.linspace(12.0, -12.0, 241)
    y = -((z**2 - 25.0) ** 2) / 100.0
    p = np.column_stack([np.zeros_like(z), y, z])
    k = deepest_under_bitangent(p, 0, len(p) - 1)
    assert abs(z[k]) < 0.11                              # the sampling step, 0.1 mm
    # a convex arc has no concavity: no point lies behind its hull
    y2 = -z**2 / 20.0
    q = np.column_stack([np.zeros_like(z), y2, z])
    k2 = deepest_under_bitangent(q, 0, len(q) - 1)
    assert k2 == 0


def test_menton_on_a_round_chin():
    """A chin of radius 12 mm (centre (y, z) = (80, -90)) sampled every 10 deg (~2.1 mm chords,
    vertices on the circle) from its front (pogonion, y max) round to a submental line that
    descends 15 deg backwards: menton is the circle's point along the direction MENTON_TILT
    deg in front of straight down."""
    c, r = np.array([80.0, -90.0]), 12.0
    ang = np.radians(np.arange(0.0, -106.0, -10.0))    # the extreme (-55 deg) between two vertices
    arc = c + r * np.column_stack([np.cos(ang), np.sin(ang)])
    end = arc[-1]
    tail = end + np.outer(np.arange(1, 8) * 3.0, [-np.cos(np.radians(15)), -np.sin(np.radians(15))])
    yz = np.vstack([arc, tail])
    p = np.column_stack([np.zeros(len(yz)), yz])
    a = np.radians(MENTON_TILT)
    d = np.array([np.sin(a), -np.cos(a)])
    me = _menton(p, 0)
    # the parabola through the vertices within 3 mm of arc refines the best vertex (5 deg,
    # ~1 mm off) to the extreme, on a chord: 0.1 mm covers the chord's sagitta 2.1^2 /
    # (8 * 12) ~ 0.05 mm and a parabola's fit to a circle over +-3 mm (0.046 mm measured)
    assert np.linalg.norm(me[1:] - (c + r * d)) < 0.1
    assert np.linalg.norm(p[np.argmax(yz @ d), 1:] - (c + r * d)) > 1.0
    # a profile that stops before turning round the chin has no menton
    assert _menton(p[:4], 0) is None


def test_menton_convention_is_the_synthetic_heads_one():
    hg = pytest.importorskip("facemodel.head_geometry")
    assert MENTON_TILT == hg.MENTON_TILT


def _extruded(profile_yz, half_width=10.0, n=6):
    """The (y, z) polyline extruded along x over +-half_width (n strips): a surface whose every
    sagittal cut is the polyline, its facets the polyline's chords."""
    xs = np.linspace(-half_width, half_width, n + 1)
    k = len(profile_yz)
    verts = np.array([[x, y, z] for x in xs for y, z in profile_yz])
    faces = []
    for a in range(n):
        for b in range(k - 1):
            i, j = a * k + b, (a + 1) * k + b
            faces += [[i, j, i + 1], [i + 1, j, j + 1]]
    return TargetSurface(verts, np.array(faces), "extruded")


def test_concave_corner_hidden_under_a_chord():
    """Subnasale-like corner: the columella descends from (120, -27) to the corner (104, -34),
    the upper lip runs from it to (108, -49); profile points every ~3.3 mm along each side,
    none on the corner, so that one chord bridges it. The two sides' last chords meet at the
    corner exactly (straight sides); the skin point closest to it is on the bridging chord."""
    corner = np.array([104.0, -34.0])
    col = corner + np.outer(np.linspace(1.0, 0.2, 6), [16.0, 7.0])
    lip = corner + np.outer(np.linspace(0.25, 1.0, 5), [4.0, -15.0])
    yz = np.vstack([[[125.0, -20.0]], col, lip])
    skin = _extruded(yz)
    p = np.column_stack([np.zeros(len(yz)), yz])
    found = concave_corner(skin, p, 0, len(p) - 1)
    bridge_a, bridge_b = col[-1], lip[0]
    u = bridge_b - bridge_a
    t = np.clip((corner - bridge_a) @ u / (u @ u), 0.0, 1.0)
    expected = bridge_a + t * u
    # exact up to round-off: straight sides, the closest point on a planar facet
    np.testing.assert_allclose(found, [0.0, *expected], atol=1e-6)
    # the deepest profile point (a vertex) is farther from the corner
    k = deepest_under_bitangent(p, 0, len(p) - 1)
    assert np.linalg.norm(p[k, 1:] - corner) > np.linalg.norm(found[1:] - corner) + 0.5


def test_symmetry_plane_of_a_shifted_ridge():
    """A nose-like ridge y = 10 - (x - 1.7)^2 / 8 - z^2 / 30, mirror-symmetric about x = 1.7,
    on a 1.5 mm grid that is not symmetric about that plane; the guess (the generic midline,
    x = 0) 1.7 mm off."""
    g = np.arange(-15.0, 15.1, 1.5) + 0.4
    xx, zz = np.meshgrid(g, g, indexing="ij")
    verts = np.column_stack([xx.ravel(), (10.0 - (xx - 1.7) ** 2 / 8.0 - zz**2 / 30.0).ravel(), zz.ravel()])
    n = len(g)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    skin = TargetSurface(verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]), "ridge")
    x0 = symmetry_plane(skin, np.array([1.7, 10.0, 0.0]), 0.0)
    # the reflected vertices miss the facets by the chords' sagitta (1.5^2 / 8 / 4 ~ 0.07 mm
    # across the ridge), symmetrically about the true plane: the parabola's minimum within
    # 0.1 mm of it
    assert abs(x0 - 1.7) < 0.1


def _lip_profile(upper_y, lower_y):
    """Upper lip vertical at y = upper_y from z = 0 to -9 (3 mm facets), a facet to the lower
    lip at (lower_y, -10), then the lower lip down to z = -19."""
    up = [[0.0, upper_y, z] for z in (0.0, -3.0, -6.0, -9.0)]
    low = [[0.0, lower_y, z] for z in (-10.0, -13.0, -16.0, -19.0)]
    return np.array(up + low)


def test_mouth_slit_on_a_bridged_step():
    # upper lip overhanging by 6 mm: the lower lip ends at the concave end (6, -10); the
    # upper lip continued down its last chord (vertical) to z = -10 is (12, -10), closest on
    # the bridge from (12, -9) to (6, -10) at t = 1/37 of its length
    stms, stmi = mouth_slit(_lip_profile(12.0, 6.0), np.array([0.0, 9.0, -9.5]))
    np.testing.assert_allclose(stmi, [0.0, 6.0, -10.0])
    a, b = np.array([0.0, 12.0, -9.0]), np.array([0.0, 6.0, -10.0])
    np.testing.assert_allclose(stms, a + (1.0 / 37.0) * (b - a), atol=1e-12)
    # lower lip protruding: the upper lip ends at the bridge's upper end, the lower lip at its
    # lower end
    stms, stmi = mouth_slit(_lip_profile(6.0, 12.0), np.array([0.0, 9.0, -9.5]))
    np.testing.assert_allclose(stms, [0.0, 6.0, -9.0])
    np.testing.assert_allclose(stmi, [0.0, 12.0, -10.0])
    # lips nearly flush (a 1 mm step is no bridge): nothing located
    assert mouth_slit(_lip_profile(8.0, 7.0), np.array([0.0, 7.5, -9.5])) is None


def _dense_lips(upper_y, lower_y, split=False, step=0.4):
    """A densely sampled profile (0.4 mm): the upper lip vertical at y = upper_y from z = 0 to
    -9, the scan's bridge to the lower lip at (lower_y, -10) (cut in two collinear segments when
    `split`: the plane crossed two of the bridging facets), the lower lip down to z = -19."""
    n = int(round(9.0 / step)) + 1
    up = [[0.0, upper_y, z] for z in np.linspace(0.0, -9.0, n)]
    low = [[0.0, lower_y, z] for z in np.linspace(-10.0, -19.0, n)]
    mid = [[0.0, 0.5 * (upper_y + lower_y), -9.5]] if split else []
    return np.array(up + mid + low)


def test_lips_meeting_on_a_densely_sampled_step():
    centre = np.array([0.0, 9.0, -9.5])
    for upper_y, lower_y in ((12.0, 6.0), (6.0, 12.0), (9.0, 7.6)):
        for split in (False, True):
            p = _dense_lips(upper_y, lower_y, split)
            assert _dense(p, centre)
            stms, stmi = lips_meeting(p, centre)
            # the bridge's ends are the lips' ends, exactly (profile vertices), whichever lip
            # overhangs, the bridge in one piece or two; a 1.4 mm offset is still a step
            np.testing.assert_allclose(stms, [0.0, upper_y, -9.0], atol=1e-12)
            np.testing.assert_allclose(stmi, [0.0, lower_y, -10.0], atol=1e-12)
    # a sparse (3 mm) profile is not dense: the bridged-facet rule (mouth_slit) applies there
    assert not _dense(_lip_profile(12.0, 6.0), centre)


def test_lips_meeting_flush_lips_at_the_groove():
    """Flush lips (y = 10) with a groove 1.5 mm deep and ~1.4 mm wide along their contact
    line at z = -9.5, sampled every 0.25 mm: the stomia are the groove's bottom moved
    STOMION_INSET_MM of profile up and down."""
    z = np.arange(0.0, -19.0 - 1e-9, -0.25)
    y = 10.0 - 1.5 * np.exp(-((z + 9.5) / 1.4) ** 2)
    p = np.column_stack([np.zeros_like(z), y, z])
    stms, stmi = lips_meeting(p, np.array([0.0, 9.0, -9.0]))
    # the bottom is a vertex (z = -9.5); the arc from it to each stomion is STOMION_INSET_MM,
    # so each lies within that of the bottom and above / below it
    bottom = np.array([0.0, 8.5, -9.5])
    for q, sgn in ((stms, 1.0), (stmi, -1.0)):
        assert np.linalg.norm(q - bottom) <= STOMION_INSET_MM + 1e-9
        assert np.linalg.norm(q - bottom) > 0.8 * STOMION_INSET_MM   # the groove's curvature
        assert sgn * (q[2] - bottom[2]) > 0.3


def _grooved_sheet(x_end, fade, depth=1.5, h=0.5):
    """A surface y = 100 - z^2 / 60 (the lips' vertical curvature, 30 mm radius) over
    x in [-20, 20], z in [-12, 12], with a groove along z = 0 of depth `depth` (gaussian, 1.4 mm
    wide) that runs full for x < x_end - fade and fades out by a smoothstep over `fade` mm,
    ending at x = x_end; triangulated on an h-mm grid offset from the groove's end."""
    g_x = np.arange(-20.0, 20.0 + 1e-9, h) + 0.13
    g_z = np.arange(-12.0, 12.0 + 1e-9, h) + 0.07
    xx, zz = np.meshgrid(g_x, g_z, indexing="ij")
    u = np.clip((xx - (x_end - fade)) / fade, 0.0, 1.0)
    taper = 1.0 - u * u * (3.0 - 2.0 * u)
    yy = 100.0 - zz**2 / 60.0 - depth * taper * np.exp(-(zz / 1.4) ** 2)
    verts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    nx, nz = len(g_x), len(g_z)
    idx = np.arange(nx * nz).reshape(nx, nz)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    return TargetSurface(verts, faces, "grooved sheet")


@pytest.mark.parametrize("carried_dx", [-4.0, 0.0, 3.5])
def test_fissure_end_on_a_grooved_sheet(carried_dx):
    """The groove's depth falls to FISSURE_END_LEVEL of its drop where the smoothstep taper is
    FISSURE_END_LEVEL (u = 0.804 for 0.1): 0.196 fade before its end. The cheilion is found
    there from a carried point up to 4 mm off along the mouth line and 1.2 mm off in height."""
    x_end, fade = 5.0, 1.5
    skin = _grooved_sheet(x_end, fade)
    from scipy.optimize import brentq

    u = brentq(lambda v: v * v * (3.0 - 2.0 * v) - (1.0 - FISSURE_END_LEVEL), 0.0, 1.0)
    expected_x = x_end - fade * (1.0 - u)
    carried = np.array([x_end + carried_dx, 100.0, 1.2])
    point, info = fissure_end(skin, carried, np.array([-20.0, 100.0, 0.0]))
    assert point is not None, info
    # the depth is sampled every FISSURE_STEP_MM (0.25) on 0.5 mm facets and the chord depth
    # blurs the taper by the groove's width: 0.3 mm along x; on the groove's line in height to
    # half a facet (the groove's bottom is a profile vertex, 0.5 mm apart, and only 10 % of
    # the groove's depth is left there): 0.3 mm
    assert abs(point[0] - expected_x) < 0.3, (point, expected_x)
    assert abs(point[2]) < 0.3
    assert info["fissure_depth_mm"] == pytest.approx(1.5, abs=0.25)


def test_fissure_end_needs_a_fissure():
    point, reason = fissure_end(_grooved_sheet(5.0, 1.5, depth=0.0), np.array([5.0, 100.0, 0.0]),
                                np.array([-20.0, 100.0, 0.0]))
    assert point is None and "fissure" in reason


def test_mirror_pairs_of_a_symmetric_point_set():
    pts = np.array([[-3.0, 1, 2], [3.0, 1, 2], [0.0, 5, 5], [2.0, 7, 7], [-2.0, 7, 7.5]])
    pairs = mirror_pairs(pts, np.arange(5))
    assert sorted(map(tuple, pairs.tolist())) == [(0, 1), (2, 2)]


# --------------------------------------------------------------- on a synthetic head
@pytest.fixture(scope="module")
def head():
    """The strong class III of the bench (maxilla 4 mm back, mandible 7 mm forward): the lower
    lip 8.5 mm in front of the upper one, the opposite of the generic lips; the registration
    alone leaves stomion superius ~6.5 mm off."""
    synthetic = pytest.importorskip("facemodel.synthetic")
    hg = pytest.importorskip("facemodel.head_geometry")
    shape = hg.HeadShape(maxilla_ap=-4.0, mandible_ap=7.0, chin_projection=2.0)
    skin = synthetic.skin_surface(shape, synthetic.SCAN_SIZE, zoom=synthetic.SCAN_ZOOM)
    return synthetic.SyntheticHead(seed=-1, shape=shape, skin=skin, bones=synthetic.bone_surfaces(shape),
                                   teeth={}, landmarks=synthetic.landmarks(shape, skin))


@pytest.fixture(scope="module")
def without_landmarks(generic, head):
    searched = mesh_match_and_repair(generic, head.skin, head.bones, None, cache=False)
    # the registration from the surfaces alone: neither the landmark search nor the profile's
    # features (registration.profile_pose, which guide the elastic stage) place the landmarks
    carried = mesh_match_and_repair(generic, head.skin, head.bones, None, cache=False,
                                    options=MatchOptions(locate_landmarks=False, profile_pose=False))
    return searched, carried


LOCATED_HERE = ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "ChL", "ChR", "Pog", "Me")


def test_located_landmarks_are_the_true_ones(generic, head, without_landmarks):
    (patient, report), (carried, _) = without_landmarks
    located = report["landmark_search"]["located"]
    assert set(LOCATED_HERE) <= set(located)
    err = {k: float(np.linalg.norm(patient.nodes[generic.landmarks[k]] - head.landmarks[k])) for k in located}
    before = {k: float(np.linalg.norm(carried.nodes[generic.landmarks[k]] - head.landmarks[k])) for k in located}
    # the target of issue 4: within 1.5 mm of the head's true landmarks (the anatomical points
    # on the exact skin, picked on the scan: the search finds them on the scan's ~3 mm facets)
    for k in LOCATED_HERE:
        assert err[k] < 1.5, (k, err[k], before[k])
    # and the search (with the profile's features) is what brings them there: the registration from
    # the surfaces alone leaves the stomion superius on the facets between the lips, several mm off
    assert before["Stms"] > 3.0 and max(err.values()) < max(before.values())
    # the landmark nodes sit on the located points, reported in the patient frame -- but for the
    # stomia the lip separation released to make room where the lips still crossed (their
    # distance to the truth is checked above)
    released = set(report["lip_separation"]["landmark_nodes_released"])
    for k, v in located.items():
        if generic.landmarks[k] not in released:
            np.testing.assert_allclose(patient.nodes[generic.landmarks[k]], v["point"], atol=1e-6)
    assert report["quality"]["n_inverted"] == 0 and report["quality"]["min_scaled_jacobian"] >= 0.2
    assert report["fit"]["skin"]["mean_mm"] < 0.3 and report["fit"]["skin"]["p95_mm"] < 1.0
    lips = report["lip_separation"]["after"]
    assert lips["min_gap_mm"] >= 0.1 - 1e-6


def test_search_works_in_the_head_frame(generic, head, without_landmarks):
    """A rotated and shifted copy of the patient gives the same landmarks, rotated and shifted
    (the definitions use the head's own axes, not the scanner's)."""
    (patient, report), _ = without_landmarks
    skin = TargetSurface(np.asarray(head.skin.vertices), np.asarray(head.skin.faces), "skin")
    x = patient.nodes
    pairs = mirror_pairs(generic.nodes, np.unique(generic.facet_sets["skin"]))
    carried = {k: x[i] for k, i in generic.landmarks.items()}
    found, _ = locate_landmarks(skin, x, pairs, carried, LOCATED_HERE)
    t = np.radians(12.0)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    shift = np.array([5.0, -20.0, 8.0])
    from registration.alignment import Similarity

    frame = Similarity(1.0, rot, shift)
    moved = locate_landmarks(skin.transformed(1.0, rot, shift), frame.apply(x), pairs,
                             {k: frame.apply(v) for k, v in carried.items()}, LOCATED_HERE, frame=frame)[0]
    for k in found:
        # the same scan, re-posed: the same points up to the transforms' round-off (1e-13 mm)
        # amplified by the fits and cuts (least-squares conditioning ~1e3; `plane_cut` moves a
        # plane 1e-6 mm off a vertex it would pass through, which one pose may do and the
        # other not): 1e-5 mm. A flip of a discrete choice (a facet, a profile vertex, a
        # window's member) moves a landmark by micrometres to millimetres and fails this.
        np.testing.assert_allclose(moved[k], frame.apply(found[k]), rtol=0, atol=1e-5)


def test_menton_of_a_short_retruded_chin(generic):
    """Synthetic head 3 (mandible 6 mm back, chin short): its menton by the definition lies
    ~5 mm of profile below pogonion, 13 mm from where the registration carries the generic's
    menton node. A located landmark may move its node that far (`located_max_correction_mm`,
    25 mm; a given one 10 mm), and the node lands on the head's true menton."""
    synthetic = pytest.importorskip("facemodel.synthetic")
    head = synthetic.synthetic_head(3)
    patient, report = mesh_match_and_repair(generic, head.skin, head.bones, None, cache=False)
    assert report["landmark_search"]["located"]["Me"]["moved_mm"] > 10.0
    assert "Me" not in report["landmark_correction"]["landmarks_not_followed"]
    # the 1.5 mm (measured 0.25 mm)
    assert np.linalg.norm(patient.nodes[generic.landmarks["Me"]] - head.landmarks["Me"]) < 1.5
    assert report["quality"]["n_inverted"] == 0 and report["quality"]["min_scaled_jacobian"] >= 0.2


def test_a_located_landmark_out_of_profile_order_is_not_used():
    """Profile landmarks keep their top-to-bottom order (heights in the head frame, z up): a
    located subnasale found below the located labrale superius (the lip's summit taken for the
    nasolabial corner) breaks it, and both located landmarks of the pair are returned; a
    carried neighbour is never returned; heights within the 0.5 mm tolerance do not count."""
    from registration.landmark_search import ORDER_TOL_MM, out_of_profile_order

    carried = {"Prn": [0, 110, -15], "Sn": [0, 98, -32], "Ls": [0, 102, -41], "Stms": [0, 99, -48],
               "Stmi": [0, 98, -49], "Li": [0, 100, -56], "Pog": [0, 92, -78], "Me": [0, 86, -95]}
    carried = {k: np.asarray(v, float) for k, v in carried.items()}
    assert out_of_profile_order({k: v + [0, 0.3, -0.2] for k, v in carried.items()}, carried) == []
    found = {"Sn": np.array([0, 100, -43.0]), "Ls": np.array([0, 102, -41.0])}
    assert out_of_profile_order(found, carried) == ["Ls", "Sn"]
    # only the located one of a disordered pair: Pog found above the carried Li
    assert out_of_profile_order({"Pog": np.array([0, 95, -50.0])}, carried) == ["Pog"]
    # stomia may cross (overhanging lips); within the tolerance nothing is out of order
    assert out_of_profile_order({"Stmi": np.array([0, 98, -46.0])}, carried) == []
    assert out_of_profile_order({"Li": np.array([0, 100, -49.0 + 0.9 * ORDER_TOL_MM])}, carried) == []
