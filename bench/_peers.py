"""Peer-run settings shared by the benchmarks: the face solver's setting changed for one run,
so that a figure can be set against the same command with the former value."""
from __future__ import annotations


def add_teeth_increment_fraction(parser) -> None:
    parser.add_argument("--teeth-increment-fraction", type=float, default=None,
                        help="the peer run: this floor of the contact nodes' increment limit, as "
                             "a fraction of the teeth's advance per load step "
                             "(FaceSolverSettings.teeth_increment_fraction)")


def apply_teeth_increment_fraction(value: float | None) -> None:
    """Set `FaceSolverSettings.teeth_increment_fraction` for every face solve of this process
    (None: the face's own value)."""
    if value is None:
        return
    import dataclasses

    import facemodel.simulation as simulation

    simulation.FACE_SOLVER = dataclasses.replace(simulation.FACE_SOLVER, teeth_increment_fraction=value)
