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
    assert shifts["lower"] == 0.0
    moved = fixed.teeth["upper"][0] - v
    assert np.allclose(moved, moved[0])                       # rigid translation
    with pytest.raises(ValueError):
        clear_teeth(pushed, clearance=0.25, max_shift=0.5)
