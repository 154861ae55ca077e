"""Genioplasty advancement on the generic face: with the tissue the genioplasty degloves
released (`facemodel.attachments.release_for_plan`), the soft-tissue pogonion follows the chin
segment by the published 0.8-1.0 (San Miguel Moragas et al., Int J Oral Maxillofac Surg
44:1009, 2015 review) and the ratio converges under mesh refinement; tied, the bony step at
the cut is imposed on the tissue and pushes pogonion ahead of the bone.

Solved without contact (the lips are far from the chin segment; contact is checked in
test_simulation / test_closure) so that the standard mesh stays within the test budget.
"""
import numpy as np
import pytest

import generic_mesh
from facemodel.attachments import has_genioplasty, release_for_plan
from facemodel.simulation import simulate

ADVANCE = 5.0           # mm, anterior


def _motions():
    T = np.eye(4)
    T[1, 3] = ADVANCE
    return {"chin": T}


def _pogonion_ratio(model, landmarks):
    res = simulate(model, _motions(), contact=False)
    assert res.converged
    return res.displacement[landmarks["Pog"], 1] / ADVANCE


@pytest.fixture(scope="module")
def ratios():
    out = {}
    for resolution in ("coarse", "standard"):
        face = generic_mesh.load(resolution)
        out[resolution] = _pogonion_ratio(release_for_plan(face, _motions()), face.landmarks)
    return out


def test_release_only_for_a_genioplasty():
    face = generic_mesh.load("coarse")
    T = _motions()["chin"]
    assert not has_genioplasty({}) and not has_genioplasty({"mandible": T, "chin": T})
    assert has_genioplasty({"chin": T}) and has_genioplasty({"mandible": T})
    # a BSSO moving the chin with the mandible keeps every attachment
    assert release_for_plan(face, {"mandible": T, "chin": T}) is face
    released = release_for_plan(face, {"chin": T})
    ids = face.node_sets["release_genioplasty"]
    assert len(ids) and not np.isin(ids, released.node_sets["attach_mandible"]).any()
    assert np.isin(ids, released.node_sets["deep_free"]).all()
    assert len(released.node_sets["attach_mandible"]) == len(face.node_sets["attach_mandible"]) - len(ids)


def test_pogonion_follows_the_chin_in_the_published_range(ratios):
    # standard resolution (0.978 measured; fine 0.975). The coarse face has a single element
    # row between pogonion and the labiomental fold, the cut inside it: 1.014, checked below.
    assert 0.8 <= ratios["standard"] <= 1.0, ratios


def test_coarse_and_standard_agree_with_the_release(ratios):
    # measured 1.014 (coarse) and 0.978 (standard); tied across the cut they are 1.035 and
    # 0.966 (and the fine mesh inverts elements). 0.05 is the coarse mesh's share of the
    # published 0.8-1.0 band it must be able to place a prediction in (a quarter of it).
    assert abs(ratios["coarse"] - ratios["standard"]) < 0.05, ratios


def test_tied_degloved_tissue_pushes_pogonion_ahead_of_the_bone(ratios):
    # The cause of the ratio above 1: the degloved nodes tied to the (fixed) mandible, the
    # 5 mm step at the cut is imposed across one element row and squeezes the tissue over the
    # chin up and forward, so pogonion moves more than the bone (1.035 measured, 1.014 with
    # the release on the same mesh).
    face = generic_mesh.load("coarse")
    tied = _pogonion_ratio(face, face.landmarks)
    assert tied > 1.0 and tied > ratios["coarse"]
