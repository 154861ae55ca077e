"""The off-scan gate's message names the cause the placement allows.

With landmarks given, the face is placed by them: a covered skin node left beyond the gate is
a shape the registration did not follow (or a wrong landmark), not a face slid along the scan.
The gate is set far below any registration's largest node distance (0.3 mm against about
1 mm on this head) so that it trips on an ordinary registration.
"""
import pytest

from registration import MatchOptions, mesh_match_and_repair
from registration.errors import RegistrationFailure


def test_with_landmarks_an_off_scan_node_is_not_called_a_misplaced_face(generic):
    from facemodel import synthetic

    head = synthetic.synthetic_head(7)
    with pytest.raises(RegistrationFailure) as info:
        mesh_match_and_repair(generic, head.skin, head.bones, head.landmarks, cache=False,
                              options=MatchOptions(skin_off_scan_gate_mm=0.3))
    msg = str(info.value)
    assert "off the patient skin where the scan covers them (gate 0.3 mm)" in msg
    assert "placed by the landmarks" in msg and "misplaced" not in msg
    assert info.value.report["fit"]["skin_off_scan"]["n_nodes"] >= 1
