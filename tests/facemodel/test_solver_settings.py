"""The face's Newton step control (`facemodel.solver_settings`): the increment limit of the
contact nodes does not shrink with the mesh below what the teeth's advance per load step asks."""
import numpy as np
import pytest

import generic_mesh
from facemodel.simulation import _typical_size, teeth_advance
from facemodel.solver_settings import FACE_SOLVER


def _lip_size(model):
    fs = model.facet_sets
    return _typical_size(np.asarray(model.nodes, float),
                         np.vstack([fs["lip_upper_contact"], fs["lip_lower_contact"]]))


def test_teeth_advance_of_a_translation_is_the_translation_times_the_load():
    """A translated arch: every vertex moves by load * |t| (exact, rigid motion ramped
    linearly in its translation); a segment without motion does not move its arch."""
    model = generic_mesh.load("coarse")
    t = np.eye(4)
    t[:3, 3] = [0.0, 6.0, -8.0]                      # |t| = 10 mm
    segs = {seg for _, _, seg in model.teeth.values()}
    assert teeth_advance(model, {s: t for s in segs}, 0.25) == pytest.approx(2.5, abs=1e-12)
    assert teeth_advance(model, {}, 0.25) == 0.0


def test_increment_limit_follows_the_teeth_not_the_mesh(seed7_motions):
    """At coarse, standard and fine, with 4 load steps of the seed-7 plan (lower teeth
    +2.2 mm per step): the limit is at least the teeth's advance per step, so the mucosa can
    follow the teeth in one limited iteration at every resolution (without the floor the fine
    limit, 0.35 of a 1.7 mm lip facet, is 0.61 mm: four iterations); the advance is the
    teeth's, the same on every mesh, so the limit is too. Where the lip facets alone give more
    than the advance (a smaller advance on the coarse face) the limit is theirs."""
    motions = seed7_motions
    caps, advances, sizes = {}, {}, {}
    for res in ("coarse", "standard", "fine"):
        model = generic_mesh.load(res)
        sizes[res] = _lip_size(model)
        advances[res] = teeth_advance(model, motions, 1.0 / 4)
        caps[res] = FACE_SOLVER.control(4, 25, np.arange(3), sizes[res], advances[res]).max_increment
    # the lip facets refine (coarse > standard > fine) but the teeth's advance does not
    assert sizes["coarse"] > sizes["standard"] > sizes["fine"]
    assert max(advances.values()) - min(advances.values()) < 1e-9
    adv = advances["fine"]
    assert adv == pytest.approx(2.215, abs=0.01)      # 8.86 mm / 4 at the lower incisors
    for res in caps:
        # one limited iteration covers the step's advance (1e-12: round-off of the max)
        assert caps[res] >= adv - 1e-12, res
        assert caps[res] >= FACE_SOLVER.increment_fraction * sizes[res] - 1e-12
        # the floor sets the limit on every mesh here: mesh-independent
        assert caps[res] == pytest.approx(caps["fine"], rel=1e-12), res
    # an advance below the coarse lip facets' limit (1.9 mm) leaves that limit as it was
    lip = FACE_SOLVER.increment_fraction * sizes["coarse"]
    small = 0.5 * lip
    assert FACE_SOLVER.control(4, 25, np.arange(3), sizes["coarse"], small).max_increment == \
        pytest.approx(lip, rel=1e-12)


def test_no_contact_no_limit_and_no_teeth_no_floor():
    """Without contact terms no limit; contact without teeth keeps the lip facets' limit."""
    assert FACE_SOLVER.control(4, 25, None, 1.0, 5.0).max_increment is None
    assert FACE_SOLVER.control(4, 25, np.arange(3), 1.0, 0.0).max_increment == pytest.approx(
        FACE_SOLVER.increment_fraction * 1.0)
