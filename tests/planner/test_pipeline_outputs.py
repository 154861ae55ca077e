"""The prediction writer on a small hand-built block model with a known displacement field:
every output file is there, readable, and carries exactly the data written (round trip at
float32/float64 storage precision), and a failure leaves no output folder."""
import json
from types import SimpleNamespace

import meshio
import numpy as np
import pytest
import pyvista as pv
import trimesh

from planner import render
from planner.errors import SolveError
from planner.pipeline import Prediction, Progress, write_outputs
from planner.plan import parse_plan


def block_model(nx=3, ny=2, nz=2, h=10.0):
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    nodes = g.reshape(-1, 3).astype(float) * h - [nx * h / 2, 0, 0]
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    hexes = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                hexes.append([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                              idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]])
    # "skin" = the anterior face y = ny*h, outward +y: quad order giving a +y normal.
    j = ny
    quads = [[idx[i, j, k], idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j, k]]
             for i in range(nx) for k in range(nz)]
    front = idx[:, j, :].ravel()
    return SimpleNamespace(
        nodes=nodes, hexes=np.array(hexes), labels=np.zeros(len(hexes), int), label_names=("dermis",),
        facet_sets={"skin": np.array(quads)}, node_sets={"attach_maxilla": idx[:, 0, :].ravel()},
        regions={"upper_lip": front[front % 2 == 0], "chin": front[front % 2 == 1]},
        landmarks={"Ls": int(idx[1, j, 1]), "Pog": int(idx[2, j, 0])},
        segments=("skull", "maxilla", "mandible", "chin"))


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    model = block_model()
    u = np.zeros_like(model.nodes)
    u[:, 1] = 0.1 * model.nodes[:, 1]          # a stretch along y: 0 to 2 mm
    stress = np.tile(np.diag([1.0, 2.0, 3.0]), (len(model.hexes), 1, 1))
    plan = parse_plan({"faceplan": 1, "segments": {"maxilla": {"translation": [0, 2, 0]}}})
    pred = Prediction(model, plan, u, stress, {"converged": True, "iterations": [3, 2]},
                      {"maxilla": model.nodes[:4]})
    out = tmp_path_factory.mktemp("pred") / "predict"
    write_outputs(pred, out, Progress(echo=False), {"case": "block"})
    return model, u, out


def test_volume_mesh(written):
    model, u, out = written
    m = meshio.read(out / "prediction.vtu")
    assert np.allclose(m.points, model.nodes + u, atol=1e-12)
    assert np.allclose(m.point_data["displacement"], u, atol=1e-12)
    assert m.cells[0].type == "hexahedron" and np.array_equal(m.cells[0].data, model.hexes)
    vm = m.cell_data["von_mises"][0]
    # von Mises of diag(1, 2, 3) kPa: sqrt(((1-2)^2 + (2-3)^2 + (3-1)^2) / 2) = sqrt(3)
    assert np.allclose(vm, np.sqrt(3.0), atol=1e-12)


def test_skin_surfaces_and_regions(written):
    model, u, out = written
    stl = trimesh.load(out / "skin_predicted.stl", process=False)
    ply = trimesh.load(out / "skin_predicted.ply", process=False)
    # STL stores float32: 1e-5 mm on coordinates of ~30 mm.
    assert np.allclose(np.sort(stl.vertices[:, 1]), 22.0, atol=1e-5)   # y = 20 mm stretched by 10 %
    assert len(ply.faces) == 2 * len(model.facet_sets["skin"])
    assert np.allclose(ply.face_normals[:, 1], 1.0)                   # outward normal preserved
    vtp = pv.read(out / "skin_predicted.vtp")
    names = list(vtp.field_data["region_names"])
    assert names == ["upper_lip", "chin"]
    node_id = np.asarray(vtp.point_data["node_id"])
    region = np.asarray(vtp.point_data["region"])
    for r, name in enumerate(names):
        assert set(node_id[region == r]) == set(model.regions[name].tolist())


def test_report_and_images(written):
    model, u, out = written
    report = json.loads((out / "report.json").read_text())
    assert report["landmarks_predicted"]["Ls"] == pytest.approx((model.nodes[model.landmarks["Ls"]] + u[model.landmarks["Ls"]]).tolist())
    assert report["regions"]["upper_lip"]["max_mm"] == pytest.approx(2.0)
    assert report["mesh_quality"]["inverted_elements"] == 0
    # the block is stretched by 10 % along y: every corner Jacobian grows by exactly 1.1
    assert report["mesh_quality"]["min_corner_jacobian_ratio"] == pytest.approx(1.1, abs=1e-4)
    assert report["segments"]["maxilla"]["max_bone_displacement_mm"] == pytest.approx(2.0)
    for name in ["preop_frontal", "preop_profile", "preop_three_quarter", "predicted_frontal",
                 "predicted_profile", "predicted_three_quarter", "displacement_frontal", "overlay_profile"]:
        assert (out / "images" / f"{name}.png").stat().st_size > 1000
    html = (out / "report.html").read_text()
    assert "data:image/png;base64" in html and "Ls" in html


def test_solve_summary_reads_the_written_report(written):
    from planner.report import solve_summary

    _, _, out = written
    s = solve_summary(json.loads((out / "report.json").read_text()))
    assert s["newton_iterations"] == [3, 2] and s["inverted_elements"] == 0
    assert s["folded_corner_elements"] == 0 and s["contact_unmet_mm"] == {}
    assert s["contact_fallback"] is False


def test_failure_leaves_no_output(tmp_path, monkeypatch):
    model = block_model()
    plan = parse_plan({"faceplan": 1})
    pred = Prediction(model, plan, np.full_like(model.nodes, np.nan), None, {})
    with pytest.raises(SolveError):
        write_outputs(pred, tmp_path / "a" / "predict", Progress(echo=False), {})
    assert not (tmp_path / "a").exists()

    # A failure half-way (meshes written, rendering fails) leaves nothing either.
    def broken(*args, **kwargs):
        raise RuntimeError("no OpenGL")

    monkeypatch.setattr(render, "render_views", broken)
    pred = Prediction(model, plan, np.zeros_like(model.nodes), None, {})
    with pytest.raises(RuntimeError):
        write_outputs(pred, tmp_path / "b" / "predict", Progress(echo=False), {})
    assert not (tmp_path / "b").exists()
