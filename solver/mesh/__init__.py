"""Hexahedral mesh record, validation, quality measures and boundary facets."""
from solver.mesh._hexmesh import (HexMesh, boundary_facets, check_mesh, corner_jacobians,
                                  scaled_jacobian)

__all__ = ["HexMesh", "boundary_facets", "check_mesh", "corner_jacobians", "scaled_jacobian"]
