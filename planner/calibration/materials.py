"""Calibrated materials into a prediction: `faceplan predict CASE --materials calibration.json`
and `faceplan diagnose CASE --materials calibration.json`.

`read_materials` reads the `materials` block of a `calibration.json` (per tissue label, the
parameter names of `facemodel.materials`, the form `model.materials` of a plan takes) and
checks it; `with_materials` merges it into a plan's `model.materials`, label by label and
parameter by parameter (the calibration's values win over the plan's for the parameters it
gives; the plan's other entries stay). `read_moduli_spread` gives the diagnosis the
calibrated layers' uncertainty: the standard deviation of the logarithm of each modulus from
the pooled 90 % interval, ln(hi / lo) / (2 z_0.95), z_0.95 = 1.645 (a log-normal's interval;
the calibration's posterior is close to one in log C10, `planner.calibration.identify`)."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from planner.errors import InputError

__all__ = ["read_materials", "with_materials", "read_moduli_spread"]


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


Z90 = 1.6448536269514722        # the standard normal's 95 % quantile: a 90 % interval is +- Z90 sd


def read_moduli_spread(path) -> dict[str, float]:
    """{layer: standard deviation of log modulus} for the layers a calibration.json measured:
    the hypodermis from the pooled C10's 90 % interval, the dermis as well when its ratio to
    the hypodermis was identified (its variance is then the sum of theirs; the two are
    treated as independent, which overstates it when they are anti-correlated). Layers it
    does not give keep the diagnosis's own prior."""
    path = Path(path)
    read_materials(path)                          # the same file checks
    doc = json.loads(path.read_text())
    pooled = doc.get("pooled") if isinstance(doc, dict) else None

    def log_sd(block, field):
        iv = (block or {}).get("interval_90") if isinstance(block, dict) else None
        if iv is None:
            return None
        if not (isinstance(iv, list) and len(iv) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                              and math.isfinite(v) and v > 0 for v in iv)
                and iv[0] <= iv[1]):
            raise InputError(f"must be [low, high] with 0 < low <= high, got {iv!r}", file=str(path),
                             field=f"pooled.{field}.interval_90")
        return math.log(iv[1] / iv[0]) / (2.0 * Z90)

    if not isinstance(pooled, dict):
        raise InputError("no 'pooled' record (write one with faceplan calibrate)", file=str(path),
                         field="pooled")
    out = {}
    hyp = log_sd(pooled.get("C10_kpa"), "C10_kpa")
    if hyp is None:
        raise InputError("the pooled C10 has no interval_90", file=str(path), field="pooled.C10_kpa.interval_90")
    out["hypodermis"] = hyp
    ratio = pooled.get("dermis_ratio")
    if isinstance(ratio, dict) and ratio.get("identifiable"):
        r = log_sd(ratio, "dermis_ratio")
        if r is not None:
            out["dermis"] = math.sqrt(hyp * hyp + r * r)
    return out
