"""registration: the generic face mesh fitted to a patient (Mesh-Match-and-Repair).

Public API: `mesh_match_and_repair(model, skin, bones, landmarks=None, ...) -> (patient, report)`
for a FaceModel; the array-level stages (`align_surfaces`, `umeyama`, `elastic_register`,
`repair_mesh`, `place_teeth`, `clear_teeth`) and hexahedron quality (`scaled_jacobians`, `min_scaled_jacobian`).
"""
from registration.alignment import Similarity, align_surfaces, trimmed_icp, umeyama
from registration.elastic import ElasticSchedule, elastic_register
from registration.errors import RegistrationFailure, RegistrationInputError
from registration.face import mesh_match_and_repair
from registration.mesh_match import MatchInput, MatchOptions, match_and_repair_arrays
from registration.quality import min_scaled_jacobian, quality_summary, scaled_jacobians
from registration.repair import SurfaceConstraint, repair_mesh
from registration.surface import TargetSurface
from registration.teeth import Arch, clear_teeth, place_teeth

__all__ = [
    "Arch", "clear_teeth", "place_teeth",
    "ElasticSchedule", "MatchInput", "MatchOptions", "RegistrationFailure",
    "RegistrationInputError", "Similarity", "SurfaceConstraint", "TargetSurface",
    "align_surfaces", "elastic_register", "match_and_repair_arrays", "mesh_match_and_repair",
    "min_scaled_jacobian", "quality_summary", "repair_mesh", "scaled_jacobians", "trimmed_icp",
    "umeyama",
]
