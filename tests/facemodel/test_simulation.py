"""Face-level checks of `facemodel.simulation` on the coarse generic face."""
import numpy as np
import pytest

import generic_mesh
from facemodel.simulation import lip_penetrations, rigid_motion_ok, simulate


@pytest.fixture(scope="module")
def face():
    return generic_mesh.load("coarse")


def _translation(dz=0.0, dy=0.0):
    T = np.eye(4)
    T[1, 3], T[2, 3] = dy, dz
    return T


@pytest.mark.parametrize("motions, activations, message", [
    ({"jaw": np.eye(4)}, {}, "unknown bone segment"),
    ({"mandible": np.diag([2.0, 1.0, 1.0, 1.0])}, {}, "rigid"),
    ({}, {"orbicularis_oris": 1.5}, "activation"),
    ({}, {"tongue": 0.2}, "unknown muscle"),
])
def test_bad_motions_and_activations_are_refused(face, motions, activations, message):
    with pytest.raises(ValueError, match=message):
        simulate(face, motions, activations)


def test_rigid_motion_check():
    R = np.eye(4)
    R[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    assert rigid_motion_ok(R)
    assert not rigid_motion_ok(np.diag([1, 1, -1, 1.0]))       # a reflection
    assert not rigid_motion_ok(np.full((4, 4), np.nan))


def test_orbicularis_oris_activation_purses_and_protrudes_the_lips(face):
    """Activation of the ring muscle alone (bones still): the commissures come together
    and the lips move forward (anterior = +y), without the lips entering each other."""
    res = simulate(face, {}, {"orbicularis_oris": 0.1})
    L = face.landmarks
    X, x = face.nodes, res.x
    width0 = np.linalg.norm(X[L["ChL"]] - X[L["ChR"]])
    width = np.linalg.norm(x[L["ChL"]] - x[L["ChR"]])
    # measured on this mesh: about -1.7 mm (3 %); a 0.5 mm threshold cannot pass by noise
    assert width < width0 - 0.5
    for name in ("Ls", "Li", "Stms", "Stmi"):
        assert res.displacement[L[name], 1] > 0.2           # forward by > 0.2 mm
    # symmetric face, symmetric activation: mirror symmetry of the solution (1e-6 mm scale
    # of the solver tolerance, 1e-3 mm allowed for the augmented-Lagrangian tolerance)
    assert abs(x[L["ChL"], 0] + x[L["ChR"], 0]) < 1e-3
    pen = lip_penetrations(face, x)
    assert max(pen.values()) < 0.05
