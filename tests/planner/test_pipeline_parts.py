"""Parts of the prediction pipeline that need no solve: segment assignment by proximity and cut
planes, the corner-Jacobian inversion check, effects parsing, skin extraction and the report's
soft-to-hard ratios. Exact arithmetic on small hand-built inputs (tolerance 1e-12)."""
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from planner.errors import InputError
from planner.pipeline import parse_effects, region_of_nodes, skin_surface
from planner.plan import parse_plan
from planner.report import corner_jacobians, inverted_elements, landmark_movements
from planner.segments import assign_segments, with_segments

CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                 [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)


def test_corner_jacobians_of_a_cube_and_its_images():
    hexes = np.arange(8)[None]
    assert np.allclose(corner_jacobians(CUBE, hexes), 1.0, atol=1e-12)
    r = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])[:3, :3]
    assert np.allclose(corner_jacobians(2.0 * CUBE @ r.T + 5, hexes), 8.0, atol=1e-12)
    flat = CUBE.copy()
    flat[6] = [0.2, 0.2, -0.5]                     # corner 6 pushed through the cell: inverted
    assert inverted_elements(flat, hexes).tolist() == [0]
    assert inverted_elements(CUBE, hexes).size == 0


@dataclass(frozen=True)
class _Frozen:
    nodes: np.ndarray
    node_sets: dict


def _box(centre, size):
    return trimesh.creation.box(extents=size, transform=trimesh.transformations.translation_matrix(centre))


def _model(points, sets):
    return SimpleNamespace(nodes=np.asarray(points, float), node_sets=sets,
                           segments=("skull", "maxilla", "mandible", "chin"))


def test_assignment_follows_the_patient_bone_not_the_generic_labels():
    # Four nodes; the generic labels are all "skull", but nodes 1-3 lie on the patient's maxilla.
    pts = [[0, 0, 50], [0, 0, 1.2], [3, 0, -1.1], [0, 0, 0.0]]
    model = _model(pts, {"attach_skull": np.arange(4), "skin": np.array([0])})
    bones = {"skull": _box([0, 0, 50], [20, 20, 2]), "maxilla": _box([0, 0, 0], [10, 10, 2])}
    plan = parse_plan({"faceplan": 1, "segments": {"maxilla": {"translation": [0, 3, 0]}}})
    a = assign_segments(model, bones, plan)
    assert a.node_sets["attach_skull"].tolist() == [0]
    assert a.node_sets["attach_maxilla"].tolist() == [1, 2, 3]
    assert a.node_sets["attach_chin"].size == 0
    # distances to the surfaces: 1.0 (top face at z=1 vs node at 50... node 0 is inside the box,
    # 1 mm from its faces), 0.2, 0.1, 1.0
    assert np.allclose(np.sort(a.distance_mm), [0.1, 0.2, 1.0, 1.0], atol=1e-9)


def test_cut_planes_split_one_surface_and_chain():
    # One CT bone surface; the mandible is everything below z = 0, the chin below z = -20 of it.
    pts = [[0, 0, 10.5], [0, 0, -10.5], [0, 0, -30.5], [0, 5, -30.5]]
    model = _model(pts, {"attach_skull": np.array([0, 1]), "attach_mandible": np.array([2, 3])})
    bones = {"bone": _box([0, 0, 0], [10, 10, 60])}
    plan = parse_plan({"faceplan": 1, "segments": {
        "chin": {"translation": [0, 2, 0], "from": "mandible",
                 "cut_planes": [{"point": [0, 0, -20], "normal": [0, 0, -1]}, {"point": [0, 2, 0], "normal": [0, 1, 0]}]},
        "mandible": {"translation": [0, -3, 0], "from": "bone",
                     "cut_planes": [{"point": [0, 0, 0], "normal": [0, 0, -1]}]}}})
    a = assign_segments(model, bones, plan)
    assert a.node_sets["attach_skull"].tolist() == [0]          # the rest of "bone": generic label
    assert a.node_sets["attach_mandible"].tolist() == [1, 2]
    assert a.node_sets["attach_chin"].tolist() == [3]
    # with_segments replaces the attachment sets of a frozen dataclass model, keeping the rest.
    frozen = _Frozen(model.nodes, {"attach_skull": np.array([0, 1, 2, 3]), "skin": np.array([7])})
    m2 = with_segments(frozen, a)
    assert m2.node_sets["attach_chin"].tolist() == [3] and m2.node_sets["skin"].tolist() == [7]
    assert frozen.node_sets["attach_skull"].tolist() == [0, 1, 2, 3]


def test_moved_segment_without_nodes_is_refused():
    model = _model([[0, 0, 50]], {"attach_skull": np.array([0])})
    bones = {"skull": _box([0, 0, 50], [20, 20, 2]), "chin": _box([0, 0, -50], [5, 5, 5])}
    plan = parse_plan({"faceplan": 1, "segments": {"chin": {"translation": [0, 3, 0]}}})
    with pytest.raises(InputError, match="no soft-tissue attachment node"):
        assign_segments(model, bones, plan)


def test_effects_parsing():
    assert parse_effects(["sliding=1", "muscle_tone=0.2", "stiffness"]).as_dict() == \
        {"sliding": 1.0, "muscle_tone": 0.2}
    for bad in (["swelling=0.5"], ["nonsense=1"], ["sliding=x"], ["muscle_tone=2"], ["stiffness=nan"]):
        with pytest.raises(InputError):
            parse_effects(bad)


def test_skin_surface_regions_and_ratio():
    quads = np.array([[0, 1, 2, 3], [1, 4, 5, 2]])
    nodes = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1], [2, 0, 0], [2, 0, 1.0]])
    model = SimpleNamespace(nodes=nodes, facet_sets={"skin": quads},
                            regions={"upper_lip": np.array([0, 1, 2, 3, 4, 5]), "nose": np.array([5])},
                            landmarks={"Ls": 2})
    x, tris, ids = skin_surface(model)
    assert ids.tolist() == list(range(6)) and tris.shape == (4, 3)
    # triangles keep the quads' orientation: normals of quad 0 (0,1,2,3) point along -y
    n = np.cross(x[tris[0, 1]] - x[tris[0, 0]], x[tris[0, 2]] - x[tris[0, 0]])
    assert n[1] < 0
    region, names = region_of_nodes(model, ids)
    assert names == ["upper_lip", "nose"] and region.tolist() == [0, 0, 0, 0, 0, 1]
    u = np.zeros((6, 3))
    u[2] = [0, 3.5, 0.2]
    plan = parse_plan({"faceplan": 1, "segments": {"maxilla": {"translation": [0, 5, 0]}}})
    lm = landmark_movements(model, u, plan, {"maxilla": np.array([[1, -10, 1.0], [9, 9, 9]])})
    assert lm["Ls"]["soft_to_hard_ratio_ap"] == pytest.approx(0.7, abs=1e-12)
    assert lm["Ls"]["bone_segment"] == "maxilla"


def _trilinear(x8, xi):
    ref = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                    [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float)
    n = np.prod(1.0 + ref * xi, axis=1) / 8.0
    return n @ x8


def test_gauss_jacobians_against_finite_differences():
    from planner.report import folded_corners, gauss_jacobians

    hexes = np.arange(8)[None]
    # unit cube: dx/dxi = I/2 everywhere, det 1/8
    assert np.allclose(gauss_jacobians(CUBE, hexes), 0.125, atol=1e-14)
    rng = np.random.default_rng(3)
    x8 = CUBE + 0.15 * rng.standard_normal((8, 3))
    g = gauss_jacobians(x8, hexes)[0]
    # central differences of the trilinear map at each Gauss point (the map is polynomial of
    # degree <= 1 in each variable, so central differences are exact up to round-off: 1e-9)
    h = 1e-5
    for k, xi in enumerate(np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                                     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]]) / np.sqrt(3)):
        jac = np.column_stack([(_trilinear(x8, xi + h * e) - _trilinear(x8, xi - h * e)) / (2 * h)
                               for e in np.eye(3)])
        assert g[k] == pytest.approx(np.linalg.det(jac), abs=1e-9)
    # a corner pulled towards the centre folds that corner but the element stays valid at the
    # Gauss points
    bent = CUBE.copy()
    bent[6] = [0.6, 0.6, 0.6]           # corner Jacobian -0.2, smallest Gauss-point one +0.03
    assert folded_corners(bent, hexes).tolist() == [0]
    assert inverted_elements(bent, hexes).size == 0
