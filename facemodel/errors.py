"""Errors of the anatomy layer (`facemodel`), free of the application's error classes.

`CTError` is raised by `facemodel.ct` for a CT volume that cannot be used (unreadable, empty,
not in Hounsfield units, an inconsistent DICOM series); the planner turns it into an
`InputError` naming the file.
"""
from __future__ import annotations

from pathlib import Path


class CTError(ValueError):
    """A CT volume that cannot be used: unreadable, empty, not CT, or an inconsistent series."""

    def __init__(self, reason: str, file: str | Path | None = None):
        self.reason = reason
        self.file = str(file) if file is not None else None
        super().__init__(f"{self.file}: {reason}" if self.file else reason)
