"""Shared inputs of the face model tests."""
import numpy as np
import pytest


@pytest.fixture
def seed7_motions():
    """The bone motions of `faceplan synth --seed 7`'s plan: Le Fort I +4.4 mm forward and
    1 mm up with a 2 deg pitch about the maxilla's centre, mandible and chin +8.86 mm forward
    (segment -> 4x4 matrix)."""
    c = np.array([0.0, 81.56, -31.19])
    a = np.deg2rad(-2.0)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    maxilla = np.eye(4)
    maxilla[:3, :3] = R
    maxilla[:3, 3] = c - R @ c + [0.0, 4.44, 1.0]
    mandible = np.eye(4)
    mandible[1, 3] = 8.86
    return {"maxilla": maxilla, "mandible": mandible, "chin": mandible}
