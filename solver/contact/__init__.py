"""Contact and sliding terms for the Newton solver (penalty / augmented Lagrangian).

`RigidSurfaceContact`: nodes against a rigid triangulated surface moving with a prescribed
rigid motion (unilateral contact, or bilateral sliding on the surface). `SurfaceContact`:
two-pass node-to-segment contact between deformable facet sets. `SegmentContact`:
two-half-pass Gauss-point-to-segment contact between deformable facet sets (passes the contact
patch test on non-matching meshes; experimental). All derive from `ContactTerm` (a
`solver.terms.Term`) and take their penalty / augmented-Lagrangian settings as one
`AugmentedLagrangian`.
"""
from solver.contact._geometry import (TriangleSurface, closest_point_on_triangles, nodal_areas,
                                      plane_gap, triangulate)
from solver.contact._uzawa import AugmentedLagrangian, ContactTerm
from solver.contact.rigid import RigidSurfaceContact, ramped_rigid_motion
from solver.contact.segment import SegmentContact, facet_quadrature
from solver.contact.surface import SurfaceContact

__all__ = ["AugmentedLagrangian", "ContactTerm", "RigidSurfaceContact", "SegmentContact", "SurfaceContact", "TriangleSurface",
           "ramped_rigid_motion", "facet_quadrature", "closest_point_on_triangles", "nodal_areas", "plane_gap", "triangulate"]
