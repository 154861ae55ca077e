"""The registration quality gate names figures far outside their normal range and the cause."""
from planner.registration_gate import registration_notes


def _report(skin_p95=0.7, skin_max=2.3, bone_mean=0.3, bone_max=9.2, repaired=22, n=1632):
    return {"fit": {"skin": {"mean_mm": 0.2, "p95_mm": skin_p95, "max_mm": skin_max},
                    "bone": {"mean_mm": bone_mean, "p95_mm": 0.1, "max_mm": bone_max},
                    "bone_segments": {"maxilla": {"max_mm": 1.0}, "mandible": {"max_mm": bone_max}}},
            "repair": {"elements_needing_repair": repaired}, "n_elements": n}


def test_the_demo_registration_figures_pass():
    # the embedded demo head registered at the coarse resolution (faceplan register)
    assert registration_notes(_report()) == []


def test_each_figure_out_of_range_is_named_with_its_cause():
    # an LPS skin with RAS landmarks as probed: skin fit p95 3.7 mm, max 10.1 mm
    (note,) = registration_notes(_report(skin_p95=3.7, skin_max=10.1))
    assert "LPS" in note and "3.7" in note
    # swapped maxilla/mandible files as probed: bone fit max 31.9 mm
    (note,) = registration_notes(_report(bone_mean=3.0, bone_max=31.9))
    assert "swapped" in note and "mandible" in note
    # one part far while the bulk fits (second-family face scans: one node 8.5 mm off, p95
    # 1.0 mm): a local misfit, not a frame mix-up, which would move the whole skin
    (note,) = registration_notes(_report(skin_p95=1.0, skin_max=8.5))
    assert "8.5" in note and "local" in note and "LPS" not in note
    (note,) = registration_notes(_report(repaired=274))
    assert "274 of 1632" in note
    assert registration_notes({}) == []          # a report without figures: nothing to say


def test_landmarks_located_without_the_head_frame_are_flagged():
    """A refused skull frame (registration.mesh_match._head_frame) means the landmarks were
    located in the alignment's axes: the user is told, with the remedy."""
    rep = _report()
    rep["landmark_search"] = {"head_frame_refused": "the skull fit turns the head by 47.8 deg"}
    (note,) = registration_notes(rep)
    assert "47.8 deg" in note and "landmarks" in note


def test_landmarks_that_contradict_each_other_are_named():
    """`registration.landmark_fit.contradicting_landmarks`: the user learns which landmark
    was not used, against which, and where to look."""
    rep = _report()
    rep["landmarks_contradicting"] = [{"pair": ["Stmi", "Li"], "given_apart_mm": 0.157,
                                       "model_apart_mm": 8.454, "not_used": "Li", "set_aside": True}]
    (note,) = registration_notes(rep)
    assert "Li was not used" in note and "Stmi" in note and "0.2 mm" in note and "8.5 mm" in note
    assert "landmarks.json" in note
    # found, but the registration succeeded with both followed: still worth a check
    rep["landmarks_contradicting"][0]["set_aside"] = False
    (note,) = registration_notes(rep)
    assert "both were followed" in note and "not used" not in note


def test_a_mouth_found_on_the_skin_and_set_aside_is_flagged():
    """Without landmarks, both stomia found on the skin set aside (found 8-16 mm from where
    the profile-guided registration carried them, or one with its partner): nothing on the
    skin confirmed where the lips are (second-family head 1500 below the eyes: its lower lip
    11 mm off). The user is told, with the largest distance and the remedy. One stomion set
    aside alone (the other used) says nothing: the slit was confirmed at one end."""
    rep = _report()
    rep["landmark_search"] = {"not_used_far_from_profile_pose": ["Li", "Stmi", "Stms"],
                              "located": {"Stms": {"moved_mm": 8.08}, "Stmi": {"moved_mm": 15.89}}}
    (note,) = registration_notes(rep)
    assert "16 mm" in note and "landmarks" in note and "lips" in note
    rep["landmark_search"] = {"not_used_far_from_profile_pose": ["Stmi"],
                              "not_used_partner_set_aside": ["Stms"], "located": {}}
    (note,) = registration_notes(rep)
    assert "mouth slit" in note
    rep["landmark_search"] = {"not_used_far_from_profile_pose": ["Li"], "located": {}}
    assert registration_notes(rep) == []
    rep["landmark_search"] = {"not_used_far_from_profile_pose": ["Stmi"], "located": {}}
    assert registration_notes(rep) == []


def test_given_landmarks_the_repair_moved_are_named():
    """`registration.mesh_match`: held on their given place, the landmark nodes left an element
    below the quality threshold, and the repair freed them (second-family head 106 at
    standard, below the eyes: Stmi 2.3 mm, Li 1.2 mm, Stms 0.1 mm). Those beyond the landmark
    precision (1 mm) are named, largest first; a move within it is not worth a note."""
    rep = _report()
    rep["repair"]["landmarks_moved_mm"] = {"Stms": 0.594, "Stmi": 2.213, "Li": 1.224}
    (note,) = registration_notes(rep)
    assert "Stmi 2.2 mm, Li 1.2 mm" in note and "Stms" not in note and "landmarks.json" in note
    rep["repair"]["landmarks_moved_mm"] = {"Stms": 0.594}
    assert registration_notes(rep) == []
