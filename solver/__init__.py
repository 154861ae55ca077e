"""faceplan's generic nonlinear finite-element core.

Total Lagrangian 8-node hexahedra (2x2x2 Gauss), nearly incompressible hyperelasticity with the
Q1/P0 mean-dilatation formulation (Simo, Taylor & Pister 1985) or the plain displacement
formulation, prescribed and local-frame constraints, follower pressure and body force, and a
Newton-Raphson solver with line search and adaptive load stepping (`SolverControl`). It knows
nothing of faces.

Typical use::

    mesh = HexMesh(nodes, hexes, labels)
    body = SolidBody(mesh, {0: Yeoh(C10=2.5, C20=1.175, K=2500)})
    res = newton_solve(body, [fix(clamped), Prescribed(pulled, [0, 0, 6.0])], steps=4)
    write_vtu("out.vtu", mesh.nodes, mesh.hexes, res.u, body.cauchy_stress(res.x))
"""
from solver.errors import (BoundaryConditionError, MaterialError, MeshError, SolveFailed,
                           SolverError)
from solver.constitution import Material, NeoHooke, Yeoh, i1_bar, i4_bar, volumetric_function
from solver.terms import Term
from solver.mesh import HexMesh, boundary_facets, check_mesh, scaled_jacobian
from solver.mechanics import SolidBody
from solver.bc import LocalFrame, Prescribed, fix
from solver.loads import BodyForce, FollowerPressure, NodalForce, TangentialSupport, surface_traction
from solver.linalg import SymmetricSolver, available_backends
from solver.control import SolverControl
from solver.newton import NewtonResult, newton_solve
from solver.io import read_vtu, write_vtu

__all__ = [
    "SolverError", "MeshError", "MaterialError", "BoundaryConditionError", "SolveFailed",
    "Material", "NeoHooke", "Yeoh", "i1_bar", "i4_bar", "volumetric_function", "Term",
    "HexMesh", "boundary_facets", "check_mesh", "scaled_jacobian", "SolidBody",
    "Prescribed", "LocalFrame", "fix", "BodyForce", "FollowerPressure", "NodalForce", "TangentialSupport",
    "surface_traction", "SymmetricSolver", "available_backends", "NewtonResult",
    "SolverControl", "newton_solve", "read_vtu", "write_vtu",
]
