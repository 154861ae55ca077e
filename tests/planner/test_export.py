"""Files other tools open, read back by their own readers, and the whole-face blend checked
against what it must preserve: a displacement linear over the patch is carried over exactly
inside it, nothing moves away from it, and the fade across the border band has no seam (the
displacement's slope between neighbouring vertices stays below the bound the fade allows)."""
import json
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from planner import export


def grid(n, size, z=0.0, offset=(0.0, 0.0)):
    """A square n x n-vertex triangulated grid of side `size` centred at `offset`, at height z."""
    t = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(t + offset[0], t + offset[1], indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


A = np.array([[0.02, -0.01, 0.0], [0.01, 0.03, 0.0], [0.0, 0.02, 0.01]])
B = np.array([0.5, 2.0, -1.0])


@pytest.fixture(scope="module")
def blended():
    # the patient's skin: a 160 mm square with 2 mm edges; the model's patch: a coarser
    # (5 mm edges) 80 mm square 0.4 mm in front of it, carrying the linear field u = A x + B
    pv, pf = grid(81, 160.0)
    xv, xf = grid(17, 80.0, z=0.4, offset=(5.0, -3.0))
    u = xv @ A.T + B
    return pv, pf, xv, xf, export.blend_face(pv, pf, xv, xf, u, band_mm=15.0, gap_mm=4.0)


def test_linear_field_carried_over_exactly_inside(blended):
    pv, _, xv, _, bf = blended
    lo, hi = xv.min(axis=0), xv.max(axis=0)
    inner = np.all((pv[:, :2] >= lo[:2] + 15.0) & (pv[:, :2] <= hi[:2] - 15.0), axis=1)
    assert inner.sum() > 50
    # barycentric interpolation reproduces a linear field; the closest point of a patient
    # vertex is its projection on the patch (z = 0.4), where the field is A x + B: rounding only
    proj = pv[inner] + [0.0, 0.0, 0.4]
    assert np.allclose(bf.displacement[inner], proj @ A.T + B, atol=1e-9)
    assert np.allclose(bf.weight[inner], 1.0)


def test_nothing_moves_away_from_the_patch(blended):
    pv, _, xv, _, bf = blended
    lo, hi = xv.min(axis=0), xv.max(axis=0)
    outside = np.any((pv[:, :2] < lo[:2] - 1e-9) | (pv[:, :2] > hi[:2] + 1e-9), axis=1)
    assert outside.sum() > 1000
    # outside the patch the closest point lies on its boundary: weight exactly 0
    assert np.abs(bf.displacement[outside]).max() == 0.0


def _max_slope(v, f, d):
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    return float(np.max(np.linalg.norm(d[e[:, 0]] - d[e[:, 1]], axis=1)
                        / np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)))


def test_no_seam_at_the_border(blended):
    pv, pf, xv, xf, bf = blended
    u = xv @ A.T + B
    # d = w u with w = s(dist / band): |grad d| <= |A| (spectral norm) + max|u| * max s' / band,
    # max s' = 1.5 for the smoothstep, the boundary distance being 1-Lipschitz
    bound = np.linalg.norm(A, 2) + np.linalg.norm(u, axis=1).max() * 1.5 / 15.0
    slope = _max_slope(pv, pf, bf.displacement)
    assert slope <= bound * 1.02, (slope, bound)  # 2 %: the chord of a curved fade on 2 mm edges
    # the check can fail: without a band (0.1 mm) the displacement jumps at the border
    hard = export.blend_face(pv, pf, xv, xf, u, band_mm=0.1, gap_mm=4.0)
    assert _max_slope(pv, pf, hard.displacement) > 3 * bound


def test_glb_and_obj_read_back_with_normals(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    glb = export.write_mesh_glb(mesh.vertices, mesh.faces, tmp_path / "f.glb")
    obj = export.write_mesh_obj(mesh.vertices, mesh.faces, tmp_path / "f.obj")
    # GLB: the JSON chunk declares a NORMAL attribute; trimesh reads the same surface back
    raw = glb.read_bytes()
    assert raw[:4] == b"glTF"
    length = int.from_bytes(raw[12:16], "little")
    doc = json.loads(raw[20:20 + length])
    assert all("NORMAL" in p["attributes"] for m in doc["meshes"] for p in m["primitives"])
    back = trimesh.load(glb, force="mesh", process=False)
    assert len(back.vertices) == len(mesh.vertices) and len(back.faces) == len(mesh.faces)
    assert np.allclose(np.sort(back.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-4)
    # OBJ: one `vn` per vertex, and the normals read back are the sphere's (outward radial)
    text = obj.read_text()
    assert sum(line.startswith("vn ") for line in text.splitlines()) == len(mesh.vertices)
    back = trimesh.load(obj, force="mesh", process=False)
    assert len(back.vertices) == len(mesh.vertices)
    radial = back.vertices / np.linalg.norm(back.vertices, axis=1, keepdims=True)
    # area-weighted vertex normals of a subdivided icosphere are within ~2 degrees of radial
    assert np.min(np.sum(back.vertex_normals * radial, axis=1)) > 0.999


def test_markups_structure_and_round_trip(tmp_path):
    from planner.case import load_landmarks

    lm = {"Prn": [0.1, 95.0, 12.5], "Pog": [-0.2, 80.0, -60.25], "ChR": [25.0, 70.0, -20.0]}
    path = export.write_markups(lm, tmp_path / "landmarks_predicted.mrk.json")
    doc = json.loads(path.read_text())
    # the markups schema (v1.0.3): required fields and their types
    assert doc["@schema"].startswith("https://raw.githubusercontent.com/slicer/slicer/")
    assert isinstance(doc["markups"], list) and len(doc["markups"]) == 1
    m = doc["markups"][0]
    assert m["type"] == "Fiducial" and m["coordinateSystem"] == "RAS" and m["coordinateUnits"] == "mm"
    ids = set()
    for cp in m["controlPoints"]:
        assert set(cp) >= {"id", "label", "position", "orientation", "positionStatus"}
        assert isinstance(cp["id"], str) and cp["id"] not in ids
        ids.add(cp["id"])
        assert len(cp["position"]) == 3 and all(isinstance(c, float) for c in cp["position"])
        assert len(cp["orientation"]) == 9 and cp["positionStatus"] == "defined"
    assert isinstance(m["display"], dict)
    # read back by the case loader (which reads Slicer's files): the same points
    back = load_landmarks(path)
    assert set(back) == set(lm)
    for k, p in lm.items():
        assert np.allclose(back[k], p, atol=0)


def block(nx=3, ny=2, nz=2, h=10.0):
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    nodes = g.reshape(-1, 3).astype(float) * h
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    hexes = [[idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
              idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]]
             for i in range(nx) for j in range(ny) for k in range(nz)]
    hexes = np.array(hexes)
    labels = (nodes[hexes].mean(axis=1)[:, 2] > h).astype(int)       # two layers, two tissues
    return SimpleNamespace(nodes=nodes, hexes=hexes, labels=labels, label_names=("hypodermis", "dermis"),
                           node_sets={"attach_skull": idx[0].ravel(), "attach_maxilla": idx[-1].ravel()},
                           segments=("skull", "maxilla"))


def test_febio_file_has_every_element_material_and_motion(tmp_path):
    model = block()
    a = np.radians(3.0)
    motion = np.eye(4)
    motion[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    motion[:3, 3] = [0.0, 4.0, 1.5]
    mats = {"hypodermis": {"C10": 2.5, "C20": 1.175, "C30": 0.0, "K": 5000.0},
            "dermis": {"C10": 10.0, "C20": 4.7, "C30": 0.0, "K": 20000.0}}
    path = export.write_feb(model, {"skull": np.eye(4), "maxilla": motion}, mats, tmp_path / "model.feb")
    root = ET.parse(path).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    nodes = {int(n.get("id")): [float(c) for c in n.text.split(",")] for n in root.iter("node")
             if n.get("id") is not None}
    assert np.allclose([nodes[i + 1] for i in range(len(model.nodes))], model.nodes)
    # every element once, in its tissue's part, with its nodes (1-based)
    seen = {}
    for block_ in root.find("Mesh").findall("Elements"):
        assert block_.get("type") == "hex8"
        for e in block_.findall("elem"):
            seen[int(e.get("id"))] = (block_.get("name"), [int(v) - 1 for v in e.text.split(",")])
    assert sorted(seen) == list(range(1, len(model.hexes) + 1))
    got = sorted((name, tuple(c)) for name, c in seen.values())
    want = sorted((model.label_names[l], tuple(h)) for l, h in zip(model.labels, model.hexes))
    assert got == want
    # hex8 node order (FEBio's = VTK's): positive volume at the element centre
    for _, c in seen.values():
        x = model.nodes[c]
        j = np.column_stack([x[[1, 2, 5, 6]].mean(0) - x[[0, 3, 4, 7]].mean(0),
                             x[[2, 3, 6, 7]].mean(0) - x[[0, 1, 4, 5]].mean(0),
                             x[[4, 5, 6, 7]].mean(0) - x[[0, 1, 2, 3]].mean(0)])
        assert np.linalg.det(j) > 0
    # every material: FEBio's uncoupled Yeoh with its parameters, one solid domain each
    for m in root.find("Material").findall("material"):
        p = mats[m.get("name")]
        assert m.get("type") == "Yeoh"
        assert float(m.find("c1").text) == p["C10"] and float(m.find("c2").text) == p["C20"]
        assert float(m.find("k").text) == p["K"]
    assert {d.get("name"): d.get("mat") for d in root.find("MeshDomains")} == \
        {"hypodermis": "hypodermis", "dermis": "dermis"}
    # the skull fixed; the maxilla's nodes given the rigid displacement R X + t - X per axis
    bcs = {bc.get("name"): bc for bc in root.find("Boundary")}
    assert bcs["skull_fixed"].get("type") == "zero displacement"
    ids = model.node_sets["attach_maxilla"]
    x = model.nodes[ids]
    want = x @ motion[:3, :3].T + motion[:3, 3] - x
    maps = {nd.get("name"): nd for nd in root.find("MeshData").findall("NodeData")}
    for k, axis in enumerate("xyz"):
        bc = bcs[f"maxilla_u{axis}"]
        assert bc.get("type") == "prescribed displacement" and bc.find("dof").text == axis
        nd = maps[bc.find("value").text]
        vals = [float(n.text) for n in sorted(nd.findall("node"), key=lambda n: int(n.get("lid")))]
        assert np.allclose(vals, want[:, k], atol=1e-7)    # 9 significant digits written
    set_ids = [int(v) - 1 for v in root.find("Mesh").find("NodeSet[@name='attach_maxilla']").text.split(",")]
    assert set_ids == list(ids)


def test_pictures_use_a_simplified_face_that_keeps_shape_and_displacement():
    """A 327k-triangle sphere (radius 50 mm) with a smooth displacement field: the picture face
    has at most ~the budget of triangles, shared by pre-op and predicted, its vertices stay on
    the sphere within the chord error of the coarser triangulation, and its displacement is the
    field averaged over the few neighbouring vertices collapsed together (the field's gradient
    is 0.04 per mm, so a cluster of ~1 mm changes it by well under 0.1 mm). A face within the
    budget is returned as given."""
    s = trimesh.creation.icosphere(subdivisions=7, radius=50.0)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)

    def field(x):
        return np.stack([np.zeros(len(x)), 2.0 * np.sin(x[:, 2] / 25.0), np.zeros(len(x))], 1)

    d = field(v)
    w = np.clip((v[:, 2] + 50.0) / 100.0, 0, 1)
    post = export.BlendedFace(v + d, f, d, w)
    (pv, pf), q = export.face_for_pictures((v, f), post, max_triangles=20_000)
    assert len(pf) <= 21_000 and np.array_equal(q.faces, pf)
    # shape: on the sphere within the chord sag of ~2.5 mm edges (r - sqrt(r^2 - (e/2)^2) < 0.1 mm)
    assert np.abs(np.linalg.norm(pv, axis=1) - 50.0).max() < 0.1
    np.testing.assert_allclose(q.vertices - pv, q.displacement)
    np.testing.assert_allclose(q.displacement, field(pv), atol=0.1)
    assert q.weight.min() >= 0.0 and q.weight.max() <= 1.0
    small = export.face_for_pictures((v, f), post, max_triangles=len(f))
    assert small[1] is post and small[0][1] is f


def test_febio_file_constrains_the_nodes_faceplan_constrains(tmp_path):
    """On the coarse generic face with a mandibular advancement (a sagittal split), a held neck
    and a held floor of the mouth: the FEBio file's constrained node sets are exactly the
    constraints of faceplan's own solve (`facemodel.simulation.build_problem`), each set fixed
    or given its segment's motion; the split's proximal segments are fixed with the skull."""
    import generic_mesh
    from facemodel import materials as fm
    from facemodel.attachments import PROXIMAL
    from facemodel.simulation import build_problem

    face = generic_mesh.load("coarse")
    T = np.eye(4)
    T[1, 3] = 5.0
    motions = {"skull": np.eye(4), "maxilla": np.eye(4), "mandible": T, "chin": T}
    mats = {label: fm.parameters(label, 1.0) for label in face.label_names}
    path = export.write_feb(face, motions, mats, tmp_path / "model.feb", neck="held", floor="held")
    root = ET.parse(path).getroot()
    sets = {s.get("name"): np.array(sorted(int(v) - 1 for v in s.text.split(",")))
            for s in root.find("Mesh").findall("NodeSet")}
    body, constraints, *_ = build_problem(face, motions, contact=False, neck="held", floor="held")
    want = {}
    for c, owner in zip(constraints, body.constraint_segments):
        want.setdefault(owner, []).append(np.asarray(c.nodes))
    want = {k: np.sort(np.concatenate(v)) for k, v in want.items()}
    named = {k: ("held_" if k in ("neck", "floor") else "attach_") + k for k in want}
    assert {named[k] for k in want} == set(sets)
    for k, ids in want.items():
        assert np.array_equal(sets[named[k]], ids)
    bcs = {bc.get("name"): bc for bc in root.find("Boundary")}
    for fixed in ("skull", "maxilla", PROXIMAL, "neck", "floor"):
        assert bcs[f"{fixed}_fixed"].get("type") == "zero displacement"
        assert bcs[f"{fixed}_fixed"].get("node_set") == named[fixed]
    assert bcs["mandible_uy"].get("node_set") == "attach_mandible"
