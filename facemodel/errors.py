"""Errors of the anatomy layer (`facemodel`), free of the application's error classes.

`CTError` is raised by `facemodel.ct` for a CT volume that cannot be used (unreadable, empty,
not in Hounsfield units, an inconsistent DICOM series); `ModelInputError` by
`facemodel.simulation.simulate` for motions, activations, materials or model parts it cannot
use. The planner turns both into an `InputError`; any other exception is a bug.
"""
from __future__ import annotations

from pathlib import Path


class CTError(ValueError):
    """A CT volume that cannot be used: unreadable, empty, not CT, or an inconsistent series."""

    def __init__(self, reason: str, file: str | Path | None = None):
        self.reason = reason
        self.file = str(file) if file is not None else None
        super().__init__(f"{self.file}: {reason}" if self.file else reason)


class ModelInputError(ValueError):
    """Input the face model cannot use: an unknown segment or muscle, a motion that is not
    rigid, an activation outside [0, 1], a label without a material, contact asked of a model
    without lip contact surfaces."""
