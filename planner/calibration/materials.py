"""Calibrated materials into a prediction: `faceplan predict CASE --materials calibration.json`.

`read_materials` reads the `materials` block of a `calibration.json` (per tissue label, the
parameter names of `facemodel.materials`, the form `model.materials` of a plan takes) and
checks it; `with_materials` merges it into a plan's `model.materials`, label by label and
parameter by parameter (the calibration's values win over the plan's for the parameters it
gives; the plan's other entries stay)."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from planner.errors import InputError

__all__ = ["read_materials", "with_materials"]


def read_materials(path) -> dict[str, dict[str, float]]:
    """The `materials` block of a calibration.json (or of any JSON holding one)."""
    from facemodel.model import LABEL_NAMES

    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("materials file not found", file=str(path), field="--materials") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a readable JSON file: {exc}", file=str(path),
                         field="--materials") from None
    block = doc.get("materials") if isinstance(doc, dict) else None
    if not isinstance(block, dict) or not block:
        raise InputError("no 'materials' mapping (write one with faceplan calibrate)",
                         file=str(path), field="materials")
    out = {}
    for label, params in block.items():
        if label not in LABEL_NAMES:
            raise InputError(f"unknown tissue label {label!r} (labels: {', '.join(LABEL_NAMES)})",
                             file=str(path), field=f"materials.{label}")
        if not isinstance(params, dict):
            raise InputError("must map parameter names to numbers", file=str(path),
                             field=f"materials.{label}")
        out[label] = {}
        for k, v in params.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0 or (v == 0 and k in ("C10", "K")):
                raise InputError(f"must be a finite non-negative number, got {v!r}",
                                 file=str(path), field=f"materials.{label}.{k}")
            out[label][str(k)] = float(v)
    return out


def with_materials(plan, materials: dict[str, dict[str, float]] | None):
    """The plan with `materials` merged into its model.materials."""
    if not materials:
        return plan
    merged = {label: dict(p) for label, p in plan.model.materials.items()}
    for label, params in materials.items():
        merged.setdefault(label, {}).update(params)
    return dataclasses.replace(plan, model=dataclasses.replace(plan.model, materials=merged))
