"""Errors raised by the registration package.

`registration` sits below `planner` in the import graph, so it cannot raise
`planner.errors.InputError` itself. `RegistrationInputError` carries the same `file` / `field`
information and the planner maps it to `InputError` (exit status 2).
"""
from __future__ import annotations


class RegistrationInputError(ValueError):
    """The patient data cannot be registered: wrong units, no overlap, inconsistent landmarks."""

    def __init__(self, message: str, *, file: str | None = None, field: str | None = None):
        super().__init__(message)
        self.file = file
        self.field = field


class RegistrationFailure(RuntimeError):
    """The registration ran but its result does not meet the validity gates (never returned).

    `report` holds the figures of the failed attempt, for diagnosis."""

    def __init__(self, message: str, report: dict | None = None):
        super().__init__(message)
        self.report = report or {}
