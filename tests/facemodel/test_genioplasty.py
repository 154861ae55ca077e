"""Genioplasty advancement on the generic face: the tissue the operation degloves (anterior
mandible between the vestibule and the cut, anterior face of the chin segment) slides on its
bone (`facemodel.attachments.genioplasty_sliding`), the pedicle on the chin's inferior border
stays tied, and the soft-tissue pogonion follows the chin segment by the published 0.8-1.0
(San Miguel Moragas et al., Int J Oral Maxillofac Surg 44:1009, 2015 review), converging under
mesh refinement; tied, the chin's anterior face drags the tissue and pushes pogonion ahead of
the bone.

Solved without contact (the lips are far from the chin segment; contact is checked in
test_simulation / test_closure and the demo test) so that the standard mesh stays within the
test budget.
"""
import inspect

import numpy as np
import pytest

import generic_mesh
from facemodel.attachments import (bone_frames, bone_normals, genioplasty_sliding, has_genioplasty,
                                   release_for_plan)
from facemodel.simulation import simulate

ADVANCE = 5.0           # mm, anterior
# The solves with sliding need `simulate(..., sliding_nodes=)` (LocalFrame sliding of part of a
# segment's nodes, see facemodel.attachments): skipped, with this reason, where it is missing.
needs_sliding_nodes = pytest.mark.skipif(
    "sliding_nodes" not in inspect.signature(simulate).parameters,
    reason="facemodel.simulation.simulate takes no sliding_nodes argument")


def _motions():
    T = np.eye(4)
    T[1, 3] = ADVANCE
    return {"chin": T}


def _solve(model, sliding_nodes=None):
    kw = {"sliding_nodes": sliding_nodes} if sliding_nodes else {}
    res = simulate(model, _motions(), contact=False, **kw)
    assert res.converged
    return res


def _pogonion_ratio(model, res):
    return res.displacement[model.landmarks["Pog"], 1] / ADVANCE


@pytest.fixture(scope="module")
def coarse():
    return generic_mesh.load("coarse")


@pytest.fixture(scope="module")
def slid(coarse):
    """{resolution: (model, sliding sets, result)} with the degloved tissue sliding."""
    out = {}
    for resolution in ("coarse", "standard"):
        face = coarse if resolution == "coarse" else generic_mesh.load(resolution)
        sets = genioplasty_sliding(face, _motions())
        out[resolution] = (face, sets, _solve(face, sets))
    return out


def test_sliding_only_for_a_genioplasty(coarse):
    T = _motions()["chin"]
    assert not has_genioplasty({}) and not has_genioplasty({"mandible": T, "chin": T})
    assert has_genioplasty({"chin": T}) and has_genioplasty({"mandible": T})
    # a BSSO moving the chin with the mandible keeps every attachment tied
    assert genioplasty_sliding(coarse, {"mandible": T, "chin": T}) == {}
    assert release_for_plan(coarse, {"mandible": T, "chin": T}) is coarse
    sets = genioplasty_sliding(coarse, {"chin": T})
    assert set(sets) == {"mandible", "chin"}
    ns = coarse.node_sets
    # the mandible's degloved tissue is the generic face's release set, on the mandible
    assert np.array_equal(sets["mandible"], np.intersect1d(ns["release_genioplasty"], ns["attach_mandible"]))
    # on the chin: its anterior face slides, the pedicle on the inferior border stays tied
    chin = ns["attach_chin"]
    assert np.isin(sets["chin"], chin).all()
    pedicle = np.setdiff1d(chin, sets["chin"])
    n = bone_normals(coarse)
    assert len(pedicle) and (n[pedicle, 2] < -np.abs(n[pedicle, 1]) + 1e-12).all()
    assert (n[sets["chin"], 1] > -n[sets["chin"], 2]).all()
    # the mid-sagittal chin node nearest pogonion (on the anterior face) slides
    X = coarse.nodes
    mid = chin[np.abs(X[chin, 0]) < 1e-9]
    near_pog = mid[np.argmin(np.linalg.norm(X[mid] - X[coarse.landmarks["Pog"]], axis=1))]
    assert near_pog in sets["chin"]


def test_bone_frames(coarse):
    ids = np.concatenate(list(genioplasty_sliding(coarse, _motions()).values()))
    R = bone_frames(coarse, ids)
    # orthonormal, right-handed (to round-off)
    assert np.allclose(np.einsum("kij,klj->kil", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # the normal points out of the bone, into the soft tissue: towards the nearest skin node
    X = coarse.nodes
    skin = coarse.node_sets["skin"]
    nearest = skin[np.argmin(np.linalg.norm(X[skin][None] - X[ids][:, None], axis=2), axis=1)]
    assert (np.einsum("ki,ki->k", R[:, 0], X[nearest] - X[ids]) > 0).all()
    with pytest.raises(ValueError):
        bone_frames(coarse, coarse.node_sets["skin"][:3])


@needs_sliding_nodes
def test_degloved_tissue_slides_on_its_bone(slid):
    face, sets, res = slid["coarse"]
    u = res.displacement
    bone = {"chin": np.array([0.0, ADVANCE, 0.0]), "mandible": np.zeros(3)}
    for seg, ids in sets.items():
        R = bone_frames(face, ids)
        rel = u[ids] - bone[seg]
        # normal displacement = the bone's (an essential condition: to round-off)
        assert np.abs(np.einsum("ki,ki->k", R[:, 0], rel)).max() < 1e-9, seg
        # and it does slide: tangential movement relative to the bone of a tenth of a mm or
        # more (measured: up to 2.1 mm on the chin, 0.8 mm on the mandible)
        assert np.linalg.norm(rel, axis=1).max() > 0.1, seg
    tied = np.setdiff1d(face.node_sets["attach_chin"], sets["chin"])
    assert np.allclose(u[tied], [0.0, ADVANCE, 0.0], atol=1e-9)


@needs_sliding_nodes
def test_pogonion_follows_the_chin_in_the_published_range(slid):
    # measured 0.980 (coarse) and 0.969 (standard); fine 0.962 (bench figure, 6 min)
    ratios = {r: _pogonion_ratio(f, res) for r, (f, _, res) in slid.items()}
    assert all(0.8 <= v <= 1.0 for v in ratios.values()), ratios


@needs_sliding_nodes
def test_coarse_and_standard_agree(slid):
    # measured 0.980 and 0.969: 0.011 apart. 0.05 is a quarter of the published 0.8-1.0 band,
    # the resolution at which the coarse mesh must be able to place a prediction in it.
    ratios = [_pogonion_ratio(f, res) for f, _, res in slid.values()]
    assert abs(ratios[0] - ratios[1]) < 0.05, ratios


@pytest.fixture(scope="module")
def tied(coarse):
    return _pogonion_ratio(coarse, _solve(coarse))


def test_tied_or_freed_pogonion_runs_ahead_of_the_bone(coarse, tied):
    # The cause of the ratio above 1 without the degloving: the tissue tied to the chin's
    # anterior face is dragged with it, and squeezed up and forward against the tissue tied
    # to the (fixed) mandible above the cut: pogonion moves more than the bone (1.035
    # measured). Freeing the mandible's degloved tissue is not enough (1.014): it is the
    # chin's anterior face that must slide (0.980 with both sliding, below).
    freed = _pogonion_ratio(coarse, _solve(release_for_plan(coarse, _motions())))
    assert tied > freed > 1.0, (tied, freed)


@needs_sliding_nodes
def test_sliding_brings_pogonion_behind_the_bone(coarse, slid, tied):
    assert _pogonion_ratio(coarse, slid["coarse"][2]) < 1.0 < tied
