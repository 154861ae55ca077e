"""Anatomy on top of the solver: the FaceModel (mesh, labels, fibres, attachments, contact
surfaces, teeth, regions, landmarks), the default materials table, the parametric head
geometry and the synthetic heads."""
from facemodel.model import FaceModel, LABEL_NAMES, LANDMARK_NAMES, MUSCLES, SEGMENTS

__all__ = ["FaceModel", "LABEL_NAMES", "LANDMARK_NAMES", "MUSCLES", "SEGMENTS"]
