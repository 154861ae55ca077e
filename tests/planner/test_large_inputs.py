"""Reading surfaces of real size: the vectorised reader and checks give what trimesh's full
processing gave (merged vertices, no degenerate or repeated triangle, consistent outward
winding), the bone-to-skin gap is exact where it decides, and the OBJ writer round-trips."""
import numpy as np
import pytest
import trimesh

from planner import case as pc
from planner.errors import InputError


def sphere(subdivisions=3, radius=60.0):
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def test_binary_stl_read_directly_is_the_surface_trimesh_reads(tmp_path):
    s = sphere()
    path = tmp_path / "skin.stl"
    path.write_bytes(s.export(file_type="stl"))
    assert pc._read_binary_stl(path) is not None      # the direct path is the one taken
    mesh = pc.load_surface(path, "skin")
    ref = trimesh.load(path, force="mesh", process=True)
    # the same merged vertices and triangles; STL stores float32 (rounding 1e-5 mm at 60 mm)
    assert len(mesh.vertices) == len(ref.vertices) == len(s.vertices)
    assert len(mesh.faces) == len(s.faces)
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.area == pytest.approx(s.area, rel=1e-6) and mesh.volume == pytest.approx(s.volume, rel=1e-6)


def test_an_ascii_stl_still_goes_through_trimesh(tmp_path):
    path = tmp_path / "skin.stl"
    path.write_text(sphere(2).export(file_type="stl_ascii"))
    assert pc._read_binary_stl(path) is None
    assert pc.load_surface(path, "skin").is_watertight


def test_clean_triangles_drops_what_trimesh_processing_dropped():
    s = sphere(2)
    v = np.asarray(s.vertices)
    f = np.asarray(s.faces)
    n = len(v)
    # an unreferenced vertex, a repeated triangle (other order), a triangle with a repeated
    # corner, a zero-height sliver (three collinear points) and a duplicate of vertex 0
    extra_v = np.array([[500.0, 0, 0], [0, 0, 100.0], [0, 0, 101.0], [0, 0, 102.0], v[0]])
    v2 = np.vstack([v, extra_v])
    f2 = np.vstack([f, f[5][[1, 2, 0]][None], [[0, 0, 1]], [[n + 1, n + 2, n + 3]],
                    [[n + 4, f[0, 1], f[0, 2]]]])
    cv, cf = pc.clean_triangles(v2, f2)
    # duplicate vertex merged into vertex 0: its triangle is then triangle 0 again, repeated
    assert len(cf) == len(f) and len(cv) == len(v)
    assert trimesh.Trimesh(cv, cf, process=False).area == pytest.approx(s.area, rel=1e-12)
    # vertices keep the order of their first appearance
    assert np.array_equal(cv, v)


def test_every_triangle_degenerate_is_refused(tmp_path):
    v = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [0, 30, 0]], float)
    path = tmp_path / "skin.stl"
    path.write_bytes(trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 1]], process=False).export(file_type="stl"))
    with pytest.raises(InputError, match="degenerate") as exc:
        pc.load_surface(path, "skin")
    assert exc.value.file == str(path)


def _consistent(f):
    d = np.sort(pc._edge_keys(f, int(f.max()) + 1)[0])
    return not np.any(d[1:] == d[:-1])


def test_mixed_and_inward_winding_is_made_consistent_and_outward():
    s = sphere(2)
    f = np.asarray(s.faces).copy()
    f[::3] = f[::3, ::-1]                      # a third of the triangles turned
    assert not _consistent(f)
    assert pc.check_closed(f, True, "x", "skin")
    v, g = pc.orient_faces(np.asarray(s.vertices), f, True)
    assert _consistent(g)
    assert trimesh.Trimesh(v, g, process=False).volume == pytest.approx(s.volume, rel=1e-12)
    # wholly inward: turned outward
    v, g = pc.orient_faces(np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1], True)
    assert trimesh.Trimesh(v, g, process=False).volume == pytest.approx(s.volume, rel=1e-12)
    # an open surface is made consistent, not turned (it has no inside)
    cap = s.faces[s.triangles_center[:, 2] > 0]
    cap = np.asarray(cap).copy()
    cap[::4] = cap[::4, ::-1]
    assert not pc.check_closed(cap, False, "x", "skin")
    with pytest.raises(InputError, match="not closed"):
        pc.check_closed(cap, True, "x", "skin")
    _, g = pc.orient_faces(np.asarray(s.vertices), cap, False)
    assert _consistent(g)


def test_bone_gaps_exact_where_they_decide():
    rng = np.random.default_rng(1)
    skin = sphere(5, 80.0).vertices                     # ~10k vertices, edges ~4 mm
    from scipy.spatial import cKDTree

    tree = cKDTree(skin)
    near = rng.normal(size=(300, 3)) * 5 + [0, 0, 60.0]       # ~20 mm under the skin
    far = rng.normal(size=(300, 3)) * 5                       # ~80 mm under it
    gaps = pc.nearest_vertex_gaps(skin, {"near": near, "far": far}, 30.0)
    exact_near, exact_far = tree.query(near)[0].min(), tree.query(far)[0].min()
    # below the threshold: an overestimate by at most the cell diagonal (one vertex per cell
    # stands for those within the diagonal of it)
    assert exact_near <= gaps["near"] <= exact_near + np.sqrt(3) * pc.GAP_CELL_MM + 1e-12
    assert gaps["near"] < 30.0
    # beyond it (the case refused): exact, as the message reports it
    assert gaps["far"] == pytest.approx(exact_far, abs=1e-12) and gaps["far"] > 30.0


def test_obj_writer_round_trips(tmp_path):
    from planner import export

    s = sphere(2)
    path = export.write_mesh_obj(s.vertices, s.faces, tmp_path / "f.obj")
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.faces) == len(s.faces)
    # 6 decimals in the file: 1e-6 mm
    assert np.allclose(np.asarray(back.vertices)[np.asarray(back.faces)],
                       np.asarray(s.vertices)[np.asarray(s.faces)], atol=1e-6)
