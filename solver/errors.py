"""Exceptions raised by the finite-element core.

The core knows nothing of faces or of the command line: it raises these, and the application
maps them to its own errors (bad input, solve failure).
"""
from __future__ import annotations


class SolverError(Exception):
    """Base class of every error raised by `solver`."""


class MeshError(SolverError, ValueError):
    """The mesh is unusable (bad shapes, indices out of range, inverted elements).

    `elements` holds the offending element indices when there are any.
    """

    def __init__(self, message: str, elements=None):
        super().__init__(message)
        self.elements = [] if elements is None else [int(e) for e in elements]


class MaterialError(SolverError, ValueError):
    """A material parameter is missing, not finite or outside its admissible range."""

    def __init__(self, message: str, parameter: str | None = None):
        super().__init__(message)
        self.parameter = parameter


class BoundaryConditionError(SolverError, ValueError):
    """A boundary condition or load refers to missing nodes/facets or has bad values."""


class SolveFailed(SolverError, RuntimeError):
    """Newton's method could not reach the requested load, even after cut-backs.

    Attributes: `step` (1-based index of the step that failed), `load` (load fraction that was
    attempted), `last_converged_load`, `worst_element` (element with the smallest Jacobian
    determinant or largest residual at failure, or None), `state` (the last converged
    `NewtonResult`-like state, nodal coordinates included, or None).
    """

    def __init__(self, message: str, *, step: int, load: float, last_converged_load: float,
                 worst_element: int | None = None, state=None):
        super().__init__(message)
        self.step = step
        self.load = load
        self.last_converged_load = last_converged_load
        self.worst_element = worst_element
        self.state = state
