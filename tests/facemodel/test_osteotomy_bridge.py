"""The tissue that bridges an osteotomy (`facemodel.attachments.osteotomy_bridges`).

Tied on both sides of a cut, the relative move d of two bone segments shears the one element
row between them by about d / h (h the mesh spacing): the strain there grows as 1 / h under
refinement, twice a halving. Released within the bridge width on either side, the move is
spread over a bridge about twice that wide on every mesh finer than it; what is left is the
weak singularity where tied tissue meets free tissue on a boundary (the strain grows as
r^(-1/2) towards that point, Williams 1952: sqrt(2) a halving).

Checked on a plane-strain strip of tissue on a bone cut in two (one half advanced along the
bone's normal, as a Le Fort I advance moves the maxilla out of the skull's plane), and on the
generic face's meshes (which nodes the rule releases, and where).
"""
from types import SimpleNamespace

import numpy as np
import pytest

import generic_mesh
import solver
from facemodel.attachments import BRIDGE_WIDTH_MM, PROXIMAL, attachment_sets, osteotomy_bridges
from solver.examples import block

LENGTH, DEPTH, STEP = 32.0, 8.0, 1.0      # strip length and tissue depth, advance (mm)


def _strip(h, width):
    """Largest principal stretch in the strip of spacing h, its bone (z = 0) cut at the middle
    and the half x > L/2 advanced by STEP along z, bridges of `width` released."""
    nodes, hexes, sets = block((LENGTH, h, DEPTH), (round(LENGTH / h), 1, round(DEPTH / h)))
    base = np.asarray(sets["zmin"])
    model = SimpleNamespace(
        nodes=nodes, segments=("skull", "maxilla"),
        node_sets={"attach_skull": base[nodes[base, 0] < LENGTH / 2 - 1e-9],
                   "attach_maxilla": base[nodes[base, 0] > LENGTH / 2 - 1e-9]})
    T = np.eye(4)
    T[2, 3] = STEP
    tied = attachment_sets(model, {"maxilla": T}, bridge_width=width)
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(2.5, 1.175, 0.0, K=500.0))
    cons = [solver.fix(tied["skull"]), solver.Prescribed(tied["maxilla"], (0.0, 0.0, STEP)),
            solver.fix(np.union1d(sets["ymin"], sets["ymax"]), components=(1,))]
    res = solver.newton_solve(body, cons, steps=4, rtol=1e-9)
    assert res.converged
    # the centroid gradient of each box element: the least-squares affine fit of its 8 nodes
    X, x = nodes[hexes], res.x[hexes]
    Xc = X - X.mean(axis=1, keepdims=True)
    xc = x - x.mean(axis=1, keepdims=True)
    F = np.linalg.solve(np.einsum("eai,eaj->eij", Xc, Xc), np.einsum("eai,eaj->eij", Xc, xc))
    F = np.transpose(F, (0, 2, 1))
    C = np.einsum("eki,ekj->eij", F, F)
    return float(np.sqrt(np.linalg.eigvalsh(C)[:, -1].max())), tied


def test_a_tied_cut_shears_as_one_over_h_a_bridged_one_as_its_ends_weak_singularity():
    spacings = (2.0, 1.0, 0.5)
    tied = [_strip(h, 0.0)[0] - 1.0 for h in spacings]
    bridged = [_strip(h, BRIDGE_WIDTH_MM)[0] - 1.0 for h in spacings]
    # tied: the nominal shear d / h doubles a halving (the free tissue above relieves a little
    # of it on the coarsest strip): at least 1.8x
    assert tied[1] > 1.8 * tied[0] and tied[2] > 1.8 * tied[1]
    # bridged: the r^(-1/2) field of the bridge's ends sampled at the element size grows about
    # sqrt(2) a halving, the strips before the asymptotic range scatter about it: at most 1.6x
    # (a halving that doubled it would be the tied cut's law), and far below the tied strain
    assert bridged[1] < 1.6 * bridged[0] and bridged[2] < 1.6 * bridged[1]
    assert bridged[2] < 0.25 * tied[2]


def test_the_strip_releases_both_sides_within_the_width():
    for h in (1.0, 0.5):
        _, tied = _strip(h, BRIDGE_WIDTH_MM)
        nodes = block((LENGTH, h, DEPTH), (round(LENGTH / h), 1, round(DEPTH / h)))[0]
        x_skull = nodes[tied["skull"], 0].max()
        x_max = nodes[tied["maxilla"], 0].min()
        # every tied node is at least the width from the other segment's attachment
        assert x_max - x_skull >= 2 * BRIDGE_WIDTH_MM - h - 1e-9
        assert x_max - x_skull <= 2 * BRIDGE_WIDTH_MM + 2 * h + 1e-9


def _le_fort(advance=5.0):
    T = np.eye(4)
    T[1, 3] = advance
    return {"maxilla": T}


def test_no_element_of_the_fine_face_is_tied_to_both_sides_of_the_le_fort_cut():
    face = generic_mesh.load("fine")
    raw = attachment_sets(face, _le_fort(), bridge_width=0.0)
    tied = attachment_sets(face, _le_fort())
    H = np.asarray(face.hexes)

    def on(ids):
        mask = np.zeros(len(face.nodes), bool)
        mask[ids] = True
        return mask[H].any(axis=1)

    assert np.any(on(raw["maxilla"]) & on(raw["skull"]))        # the cut runs between elements
    assert not np.any(on(tied["maxilla"]) & on(tied["skull"]))
    # only maxilla and skull nodes by the cut are released, on both sides
    for seg in ("maxilla", "skull"):
        freed = np.setdiff1d(raw[seg], tied[seg])
        assert len(freed) > 0
        other = raw["skull" if seg == "maxilla" else "maxilla"]
        d = np.linalg.norm(face.nodes[freed][:, None] - face.nodes[other][None], axis=2).min(1)
        assert d.max() < BRIDGE_WIDTH_MM
    for seg in ("mandible", "chin"):
        assert np.array_equal(raw[seg], tied[seg])


def test_bridges_only_where_the_plan_moves_segments_apart():
    face = generic_mesh.load("fine")
    raw = attachment_sets(face, {}, bridge_width=0.0)
    # no move, or a mandible moved with its chin: its attachments are far from the skull's
    T = np.eye(4)
    T[1, 3] = 4.0
    for motions, proximal in (({}, "seated"), ({"mandible": T, "chin": T}, "moved")):
        tied = attachment_sets(face, motions, proximal=proximal)
        assert set(tied) == set(raw) and all(np.array_equal(raw[s], tied[s]) for s in raw)
    # a sagittal split (the default reading of a moved mandible): the proximal segments' nodes
    # change owner; the released band around the buccal cut (about 15 mm wide) leaves no
    # bridge between them and the distal segment's
    tied = attachment_sets(face, {"mandible": T, "chin": T})
    assert len(tied[PROXIMAL]) > 100 and len(tied["mandible"]) > 100
    assert np.array_equal(np.union1d(tied[PROXIMAL], tied["mandible"]), raw["mandible"])
    assert np.array_equal(tied[PROXIMAL], np.intersect1d(raw["mandible"], face.node_sets["mandible_proximal"]))
    # a genioplasty: the chin moved on the mandible opens the cut between them
    bridge = osteotomy_bridges(face, raw, {"mandible": T})
    assert np.isin(bridge, raw["chin"]).any() and np.isin(bridge, raw["mandible"]).any()
    assert not np.isin(bridge, raw["skull"]).any()


@pytest.mark.parametrize("resolution", ["coarse", "standard"])
def test_faces_coarser_than_the_width_keep_their_attachments(resolution):
    # their attached nodes across the Le Fort I line (5.5 mm at coarse, 2.75 mm at standard)
    # are farther apart than the width: the element row between them is the bridge
    face = generic_mesh.load(resolution)
    raw = attachment_sets(face, _le_fort(), bridge_width=0.0)
    tied = attachment_sets(face, _le_fort())
    assert all(np.array_equal(raw[s], tied[s]) for s in raw)


def test_the_solver_ties_no_bridge_node_and_counts_them():
    from facemodel.simulation import build_problem

    face = generic_mesh.load("fine")
    raw = attachment_sets(face, _le_fort(), bridge_width=0.0)
    bridge = osteotomy_bridges(face, raw, _le_fort())
    body, constraints, *_ = build_problem(face, _le_fort(), contact=False)
    held = np.concatenate([np.asarray(c.nodes) for c in constraints])
    assert body.bridge_nodes == len(bridge) > 0
    assert not np.isin(bridge, held).any()
    assert len(held) == sum(len(v) for v in raw.values()) - len(bridge)


def test_the_febio_export_ties_the_nodes_the_solver_ties(tmp_path):
    import xml.etree.ElementTree as ET

    from planner.export import write_feb

    h = 1.0
    nodes, hexes, sets = block((LENGTH, h, DEPTH), (round(LENGTH / h), 1, round(DEPTH / h)))
    base = np.asarray(sets["zmin"])
    model = SimpleNamespace(
        nodes=nodes, hexes=hexes, labels=np.zeros(len(hexes), int), label_names=("hypodermis",),
        segments=("skull", "maxilla"),
        node_sets={"attach_skull": base[nodes[base, 0] < LENGTH / 2 - 1e-9],
                   "attach_maxilla": base[nodes[base, 0] > LENGTH / 2 - 1e-9]})
    T = np.eye(4)
    T[2, 3] = STEP
    motions = {"skull": np.eye(4), "maxilla": T}
    tied = attachment_sets(model, motions)
    assert len(osteotomy_bridges(model, attachment_sets(model, motions, 0.0), motions)) > 0
    path = write_feb(model, motions, {"hypodermis": {"C10": 2.5, "C20": 1.175, "K": 5000.0}},
                     tmp_path / "strip.feb")
    exported = {s.get("name"): sorted(int(v) - 1 for v in s.text.split(","))
                for s in ET.parse(path).getroot().find("Mesh").findall("NodeSet")}
    assert exported == {"attach_" + s: sorted(ids.tolist()) for s, ids in tied.items()}
