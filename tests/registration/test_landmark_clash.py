"""Given landmarks that contradict each other for the face model.

A labrale inferius taken at the stomion (a lower lip without a prominence, where "the lower
lip's most anterior point" is its top) puts two landmarks on one point whose nodes the model
holds a lower vermilion (about 8 mm) apart; pulling both nodes there folds the lip's
elements beyond repair on some heads. `contradicting_landmarks` names the one farther from
its node (set aside when a registration following both fails), and leaves alone what faces
do: lips that close (stomia given together, model nodes 2 mm apart across the slit) and
proportions within a factor of two of the generic face's.
"""
import numpy as np

from registration.landmark_fit import CLASH_MM, CLASH_RATIO, contradicting_landmarks

# model landmark nodes as the similarity placed them: Stms, Stmi (across the open slit), Li
# (a lower vermilion below Stmi), Pog
NODES = np.array([[0.0, 100.0, -40.0], [0.0, 99.5, -42.0], [0.0, 100.5, -50.0], [0.0, 97.0, -70.0]])


def test_a_labrale_inferius_given_at_the_stomion_is_set_aside():
    given = NODES.copy()
    given[2] = given[1] + [0.0, 0.2, 0.1]        # Li 0.22 mm from Stmi, 8 mm above its node
    use, clashes = contradicting_landmarks(NODES, given)
    assert use.tolist() == [True, True, False, True]
    assert len(clashes) == 1 and clashes[0]["pair"] == [1, 2] and clashes[0]["not_used"] == 2
    assert clashes[0]["given_apart_mm"] < 0.3 and abs(clashes[0]["model_apart_mm"] - 8.06) < 0.01


def test_the_one_farther_from_its_node_is_set_aside_whichever_it_is():
    given = NODES.copy()
    given[1] = given[2] + [0.0, 0.1, 0.2]        # now Stmi given down at Li
    use, clashes = contradicting_landmarks(NODES, given)
    assert use.tolist() == [True, False, True, True] and clashes[0]["not_used"] == 1


def test_closed_lips_and_other_proportions_are_kept():
    given = NODES.copy()
    given[0] = given[1] + [0.0, 0.0, 0.2]        # the stomia together: lips closed (2 mm apart)
    given[2] = given[1] + [0.0, 0.5, -4.5]       # a lower vermilion 4.5 mm high (0.56 of 8 mm)
    use, clashes = contradicting_landmarks(NODES, given)
    assert use.all() and clashes == []


def test_each_bound_alone_keeps_a_pair():
    # held 3 mm apart, given on one point: fifteenfold closer, but by less than CLASH_MM
    # (within what placing two landmarks by hand can err)
    nodes = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [0.0, 0.0, 30.0]])
    given = nodes.copy()
    given[1] = [0.0, 0.0, 0.2]
    assert 0.2 < CLASH_RATIO * 3.0 and 3.0 - 0.2 < CLASH_MM
    assert contradicting_landmarks(nodes, given)[0].all()
    # held 20 mm apart, given 6 mm apart: 14 mm closer, but not fourfold (a short face)
    nodes[1] = [0.0, 0.0, 20.0]
    given[1] = [0.0, 0.0, 6.0]
    assert 6.0 > CLASH_RATIO * 20.0 and 20.0 - 6.0 > CLASH_MM
    assert contradicting_landmarks(nodes, given)[0].all()


def test_a_registration_given_li_at_the_stomion_reports_it_and_can_set_it_aside(generic):
    """Coarse, own head seed 7 (3 mm skin), Li given 0.15 mm from Stmi. This head's lip takes
    the compression: the registration follows both and names the pair. Made with the pair
    set aside (as `match_and_repair_arrays` retries a failed registration), Li is not used:
    its node stays on the lower lip, several mm from the point given, and the other
    landmarks are placed."""
    import pytest

    from registration import mesh_match_and_repair
    from registration.mesh_match import MatchOptions

    synthetic = pytest.importorskip("facemodel.synthetic")
    head = synthetic.synthetic_head(7, size=3.0, zoom=1.0)
    lm = dict(head.landmarks)
    lm["Li"] = np.asarray(lm["Stmi"], float) + [0.0, 0.1, -0.1]
    _, rep = mesh_match_and_repair(generic, head.skin, head.bones, lm, cache=False)
    (clash,) = rep["landmarks_contradicting"]
    assert sorted(clash["pair"]) == ["Li", "Stmi"] and clash["not_used"] == "Li"
    assert clash["set_aside"] is False
    _, rep = mesh_match_and_repair(generic, head.skin, head.bones, lm, cache=False,
                                   options=MatchOptions(set_aside_contradicting=True))
    (clash,) = rep["landmarks_contradicting"]
    assert clash["set_aside"] is True
    assert rep["landmarks"]["Li"]["error_mm"] > CLASH_MM
    # the landmarks used are placed: within the snap's closest-point precision
    assert max(v["error_mm"] for k, v in rep["landmarks"].items() if k != "Li") < 0.05


def _attempts(monkeypatch, outcomes):
    """match_and_repair_arrays with its single attempt replaced: each call takes the next of
    `outcomes` (an exception to raise or a value to return); returns the options of each call."""
    import registration.mesh_match as mm

    seen = []

    def attempt(model, skin, bones, landmarks, opt, files, teeth):
        seen.append(opt)
        out = outcomes[len(seen) - 1]
        if isinstance(out, BaseException):
            raise out
        return out

    monkeypatch.setattr(mm, "_match_and_repair_arrays", attempt)
    return mm.match_and_repair_arrays, seen


def _failure(text, clashes):
    from registration.errors import RegistrationFailure

    return RegistrationFailure(text, {"landmarks_contradicting": clashes} if clashes else {})


CLASH = [{"pair": ["Stmi", "Li"], "not_used": "Li", "set_aside": False}]


def test_a_failure_with_contradicting_landmarks_is_tried_once_more_setting_them_aside(monkeypatch):
    run, seen = _attempts(monkeypatch, [_failure("folded", CLASH), "registered"])
    assert run(None, None, {}, {"Li": (0, 0, 0)}) == "registered"
    assert [o.set_aside_contradicting for o in seen] == [False, True]


def test_a_failure_without_contradicting_landmarks_is_not_tried_again(monkeypatch):
    import pytest

    from registration.errors import RegistrationFailure

    run, seen = _attempts(monkeypatch, [_failure("folded", []), "registered"])
    with pytest.raises(RegistrationFailure, match="folded"):
        run(None, None, {}, {"Li": (0, 0, 0)})
    assert len(seen) == 1


def test_when_the_second_attempt_fails_too_the_first_failure_is_reported(monkeypatch):
    import pytest

    from registration.errors import RegistrationFailure

    run, seen = _attempts(monkeypatch, [_failure("first", CLASH), _failure("second", CLASH)])
    with pytest.raises(RegistrationFailure, match="first"):
        run(None, None, {}, {"Li": (0, 0, 0)})
    assert len(seen) == 2
