"""Rigid teeth against the lips: contact starts without penetration."""
from dataclasses import replace

import numpy as np
import pytest

import generic_mesh
from facemodel.teeth import clear_teeth, teeth_penetration


@pytest.fixture(scope="module")
def coarse():
    return generic_mesh.load("coarse")


def test_generic_lips_start_clear_of_the_teeth(coarse):
    # the generic lips rest 0.25 mm (TEETH_GAP) in front of the incisors
    depth = teeth_penetration(coarse)
    assert max(depth.values()) == pytest.approx(-0.25, abs=0.02)
    model, shifts = clear_teeth(coarse, clearance=0.2)
    assert shifts == {"upper": 0.0, "lower": 0.0}
    assert model.teeth["upper"][0] is coarse.teeth["upper"][0]


def test_teeth_pushed_into_the_lips_are_moved_back(coarse):
    v, f, seg = coarse.teeth["upper"]
    pushed = replace(coarse, teeth={**coarse.teeth, "upper": (v + [0.0, 1.5, 0.0], f, seg)})
    assert teeth_penetration(pushed)["upper"] > 1.0
    fixed, shifts = clear_teeth(pushed, clearance=0.25)
    # penetration removed to the clearance, by bisection (1e-6 mm); moving straight back
    # undoes the 1.5 mm push: the shift lies between the 1.25 mm overlap and the push + 0.5 mm
    # (the lips' deep surface is curved, so the deepest node need not be the frontmost)
    assert teeth_penetration(fixed)["upper"] <= -0.25 + 1e-6
    assert 1.25 <= shifts["upper"] <= 2.0
    # the other arch is cleared on its own: pushing the upper one does not move it (the generic
    # lower lip lies within micrometres of the 0.25 mm clearance, so its own shift need not be 0)
    assert shifts["lower"] == clear_teeth(coarse, clearance=0.25)[1]["lower"] < 0.01
    moved = fixed.teeth["upper"][0] - v
    assert np.allclose(moved, moved[0])                       # rigid translation
    with pytest.raises(ValueError):
        clear_teeth(pushed, clearance=0.25, max_shift=0.5)


def test_an_arch_in_a_slot_of_tissue_is_moved_where_it_clears_both_sides():
    """A tooth block 4 mm deep in a slot: a node 0.4 mm inside its front face near the top
    (the lip mucosa), tissue from 0.3 mm behind its back face on back (nodes every 1 mm). Moved
    straight back, the block meets the tissue behind before the front node is clear (0.65 mm
    needed, 0.05 mm allowed); moved straight down by 1.25 mm the front node is 0.25 mm above
    its top face and the tissue behind stays 0.3 mm behind it. Every tilt between takes the
    block into the tissue behind first, so the smallest clearing move is straight down, 1.25 mm
    (bisection: 1e-6 mm)."""
    from dataclasses import dataclass

    import trimesh

    @dataclass(frozen=True)
    class Tissue:
        nodes: np.ndarray
        teeth: dict

    box = trimesh.creation.box(extents=(10.0, 4.0, 10.0))
    box.apply_translation((0.0, 2.0, 5.0))                  # y in [0, 4], z in [0, 10]
    front = [[0.0, 3.6, 9.0]]
    behind = [[x, y, z] for x in (-4.0, 0.0, 4.0) for y in -0.3 - np.arange(10.0)
              for z in np.linspace(0.5, 9.5, 10)]
    tissue = Tissue(np.array(front + behind), {"upper": (np.asarray(box.vertices), np.asarray(box.faces), "maxilla")})
    moved, shifts = clear_teeth(tissue, clearance=0.25)
    assert shifts["upper"] == pytest.approx(1.25, abs=1e-6)
    d = moved.teeth["upper"][0] - box.vertices
    assert np.allclose(d, [0.0, 0.0, -shifts["upper"]], atol=1e-12)
    sd = trimesh.proximity.signed_distance(trimesh.Trimesh(moved.teeth["upper"][0], box.faces), tissue.nodes)
    assert sd.max() <= -0.25 + 1e-6
    # a slot too narrow for any move within max_shift is refused, naming the arch
    with pytest.raises(ValueError, match="upper"):
        clear_teeth(tissue, clearance=0.25, max_shift=1.0)


def test_the_lips_corners_are_not_at_the_incisal_edges(coarse):
    """The lips' inner corners (the nodes shared by a lip's contact surface and its teeth
    surface) meet on the mouth line, and each arch's incisal edge stands INCISAL_CLEARANCE off
    it, so that a jaw move sliding one arch over the other does not pinch the corners between
    the edges (docs/solver_control.md, Limitations). With the edges on the mouth line the
    upper lip's corner lay 0.26 mm from the upper incisal edge."""
    from facemodel import head_geometry as hg
    from facemodel import jaw

    X = np.asarray(coarse.nodes)
    fs = {k: set(np.asarray(v).ravel().tolist()) for k, v in coarse.facet_sets.items()}
    edges = np.array(list(jaw.incisal_edges(coarse).values()))
    for lip in ("upper", "lower"):
        corner = np.array(sorted(fs[f"lip_{lip}_contact"] & fs[f"lip_{lip}_teeth"]))
        mid = corner[np.argmin(np.abs(X[corner, 0]))]           # the midsagittal corner node
        assert abs(X[mid, 0]) < 1e-6
        # the edge points are the stored teeth's (rounded to 1e-6 mm): no other tolerance
        assert np.linalg.norm(edges - X[mid], axis=1).min() >= hg.INCISAL_CLEARANCE
