"""faceplan's generic nonlinear finite-element core.

Total Lagrangian 8-node hexahedra (2x2x2 Gauss), nearly incompressible hyperelasticity with the
Q1/P0 mean-dilatation formulation (Simo, Taylor & Pister 1985) or the plain displacement
formulation, prescribed and local-frame constraints, follower pressure and body force, and a
Newton-Raphson solver with line search and adaptive load stepping. It knows nothing of faces.
"""
from solver.errors import (BoundaryConditionError, MaterialError, MeshError, SolveFailed,
                           SolverError)
from solver.constitution import Material, NeoHooke, Yeoh, i1_bar, i4_bar
from solver.terms import Term

__all__ = [
    "SolverError", "MeshError", "MaterialError", "BoundaryConditionError", "SolveFailed",
    "Material", "NeoHooke", "Yeoh", "i1_bar", "i4_bar", "Term",
]
