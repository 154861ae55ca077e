"""Sim-to-real gap diagnosis (`faceplan diagnose`): where a prediction misses the post-op face,
which unmodelled effect explains it, and how far the gap shrinks with it.

`effects` describes the testable effects as parameters with bounds and a "none" value,
`forward` solves predictions with effects (dask.distributed tasks), `gap` measures the scan
against a prediction with `faceplan compare`'s superimposition and distances and estimates the
noise floor, `fit` holds the statistics (bounded Gauss-Newton, Fisher information, BIC),
`analysis` fits, cross-validates and judges the effects, `run` goes from case folders to the
record, `outputs` writes it, and `synthetic` makes scans with a withheld effect on a perturbed
model for the checks.
"""
from planner.diagnosis.effects import Effect, Parameter, available_effects
from planner.diagnosis.forward import CaseModel, Forward, Runner, prepare_case
from planner.diagnosis.run import diagnose_cases, diagnose_data

__all__ = ["Effect", "Parameter", "available_effects", "CaseModel", "Forward", "Runner", "prepare_case",
           "diagnose_cases", "diagnose_data"]
