"""Writing a diagnosis: `diagnosis.json`, pictures and a self-contained `report.html`.

The pictures are the gap on the superimposed post-op scan before and after the winning effect
(post-op minus prediction, mm, the same diverging scale), and a bar chart of every effect's
held-out shrinkage of the RMS gap with its bootstrap spread over the cross-validation regions
(dashed: the share an effect must remove to be named). Everything goes into a temporary folder
moved into place only when complete (`planner.atomic`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from planner.diagnosis import analysis
from planner.diagnosis.analysis import MIN_HELDOUT_SHRINK_PCT

__all__ = ["write_diagnosis", "params_text", "verdict_text"]

CLIM_MM = 3.0


def _clean(o):
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (np.floating, float)):
        return float(o) if np.isfinite(o) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def _images(result: dict, img: Path) -> list[tuple[Path, str]]:
    from planner import render

    img.mkdir(parents=True, exist_ok=True)
    record, data, winner = result["record"], result["data"], result["analysis"]["winner"]
    out = []
    views = ("frontal", "profile") if len(data) == 1 else ("frontal",)
    for c, d in enumerate(data):
        g = d.gap
        prefix = "" if len(data) == 1 else f"{c:02d}_"
        mesh = (g.scan_vertices, g.scan_faces)
        for view, path in render.render_views(mesh, img / f"{prefix}gap_before", scalars=g.on_scan(d.r0),
                                              cmap="RdBu_r", clim=(-CLIM_MM, CLIM_MM), views=views,
                                              title=f"{d.case.name}: gap, baseline (mm)").items():
            out.append((path, f"{d.case.name}: post-op minus baseline prediction (mm), {view}"))
        if winner is not None:
            for view, path in render.render_views(mesh, img / f"{prefix}gap_after", scalars=g.on_scan(winner.fitted[c]),
                                                  cmap="RdBu_r", clim=(-CLIM_MM, CLIM_MM), views=views,
                                                  title=f"{d.case.name}: gap with {winner.cand.name} (mm)").items():
                out.append((path, f"{d.case.name}: post-op minus prediction with {winner.cand.name} (mm), {view}"))
    effects = [e for e in record["effects"] if e["heldout_shrink_pct"] is not None]
    if effects:
        path = render.bar_chart([e["name"] + ("" if e["identifiable"] else " (n.i.)") for e in effects],
                                [max(e["heldout_shrink_pct"], -100.0) for e in effects], img / "heldout_shrinkage.png",
                                errors=[e["heldout_shrink_spread_pct"] or 0.0 for e in effects],
                                ylabel="held-out shrinkage of the RMS gap (%)", threshold=None,
                                title="held-out shrinkage per effect")
        out.append((path, "held-out shrinkage of the RMS gap per effect, bootstrap spread over regions "
                          f"(to be named an effect must remove {MIN_HELDOUT_SHRINK_PCT:.0f}% of the gap beyond the scan "
                          "noise, `heldout_noise_shrink_pct`; n.i.: not identifiable)"))
    return out


def _number(v) -> str:
    return f"{float(v):.3g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def _param_text(key: str, v) -> str:
    """One entry of an effect's `params` as a sentence fragment."""
    from planner.diagnosis.effects import BONE_DOF

    parts = key.split(".")
    if parts[0] == "bone_execution" and len(parts) == 2 and isinstance(v, list) and len(v) == len(BONE_DOF):
        move = ", ".join(f"{float(x):+.2f}" for x in v[:3])
        turn = ", ".join(f"{float(x):+.2f}" for x in v[3:])
        return f"{parts[1]} corrected by ({move}) mm and ({turn}) deg"
    if key == "bone_execution":
        return "the achieved movements of postop/plan_actual.yaml"
    if key == "sliding":
        return "the tissue slides on every moved segment" if v == 1 else f"the tissue slides on the {v}"
    if key == "sliding.hold":
        return f"interface hold {_number(v)}"
    return f"{key} {_number(v)}"


def params_text(params) -> str:
    """An effect's `params` (diagnosis.json) as a reader takes them: each value to three
    significant digits, a bone correction as its translation (mm) and rotation (degrees), a
    switch in words, per case where the values are case-specific; "-" for none."""
    if isinstance(params, dict) and "per_case" in params:
        return "; ".join(f"case {k + 1}: {params_text(p)}" for k, p in enumerate(params["per_case"]))
    if not params:
        return "-"
    return "; ".join(_param_text(k, v) for k, v in params.items())


def verdict_text(record: dict) -> str:
    """The verdict of a diagnosis record as one sentence: the named effect with its confidence,
    its regions and the effects a surface scan cannot tell from it; or `null` / `unexplained`
    with the probability of the prediction without an effect, and the effects the data
    support that remove too little of the held-out gap to be named, each with that share and
    the share naming asks (`analysis.naming_share`)."""
    v = record["verdict"]
    name = v["effect"]
    regions = ", ".join(v.get("regions") or ())
    if name not in (None, "unexplained"):
        return (f"{name} (confidence {v['confidence']:.2f}, the probability of the models that contain it)"
                + (f" in {regions}" if regions else "")
                + "".join(f"; a surface scan cannot tell it from {other}: "
                          f"{analysis.confound_between(name, other).settled_by} would tell them apart"
                          for other in v.get("confounded_on_surface") or ()))
    if name is None:
        text = "no effect named: the gap is within the scan noise and the model-form discrepancy"
    else:
        text = (f"unexplained: a gap beyond the scan noise and the model-form discrepancy remains"
                + (f" in {regions}" if regions else "") + " and no effect removes it")
    text += f" (probability of the prediction without an effect {v['confidence']:.2f})"
    effects = {e["name"]: e for e in record.get("effects") or ()}
    supported = []
    for other in v.get("supported_not_named") or ():
        e = effects.get(other, {})
        share, spread = e.get("heldout_noise_shrink_pct"), e.get("heldout_noise_shrink_spread_pct")
        if share is None or spread is None:
            supported.append(other)
            continue
        need = analysis.naming_share(spread)
        supported.append(f"{other} ({share:.0f} ± {spread:.0f} % of the held-out gap beyond the noise "
                         f"removed, {need:.0f} % needed)")
    if supported:
        text += ("; supported by the data but removing too little of the held-out gap to be named: "
                 + ", ".join(supported))
    return text


def _shown(x):
    """A per-parameter report value for a table cell: one value, or the cases' values."""
    if isinstance(x, dict) and "per_case" in x:
        return "; ".join(json.dumps(v) for v in x["per_case"])
    return json.dumps(x) if isinstance(x, list) else x


def write_diagnosis(result: dict, out_dir: Path, render_images: bool = True, say=lambda s: None) -> dict:
    """Write diagnosis.json, images/*.png and report.html into `out_dir` (whole or not at all)."""
    from planner.atomic import atomic_output_dir
    from planner.html_report import write_html_report

    record = _clean(json.loads(json.dumps(result["record"], default=_clean)))
    with atomic_output_dir(out_dir) as tmp:
        images = _images(result, tmp / "images") if render_images else []
        record["files"] = {"html": "report.html",
                           "images": [str(p.relative_to(tmp)) for p, _ in images]}
        (tmp / "diagnosis.json").write_text(json.dumps(record, indent=2, allow_nan=False))
        tables = {"Effects, best first (held-out shrinkage of the RMS gap)": (
            ["effect", "params", "identifiable", "RMS after (mm)", "shrink %", "held-out shrink %",
             "spread %", "held-out shrink beyond noise %", "held-out log density gain", "probability", "significant"],
            [[e["name"], params_text(e["params"]), e["identifiable"], e["rms_after_mm"], e["shrink_pct"],
              e["heldout_shrink_pct"], e["heldout_shrink_spread_pct"], e.get("heldout_noise_shrink_pct"),
              None if e.get("heldout_lpd_gain") is None else
              f"{e['heldout_lpd_gain']} ± {e['heldout_lpd_gain_se']} (P > 0: {e.get('heldout_lpd_gain_probability')})",
              e["probability"], e["significant"]]
             for e in record["effects"]]),
            "Where the prediction misses (RMS gap per region)": (
            ["region", "RMS (mm)", "beyond noise + discrepancy", "above noise", "covered"],
            [[r["region"], r["rms_mm"], r["significant"], r.get("above_noise"), r.get("covered", True)]
             for r in record["localization"]])}
        named = next((e for e in record["effects"] if e["name"] == record["verdict"]["effect"]), None)
        rows = [[key, _shown(q.get("value")), _shown(q.get("interval_95")), _shown(q.get("interval_95_marginal")),
                 q.get("unit"), q.get("standard_error"), _shown(q.get("standard_error_with_discrepancy")),
                 _shown(q.get("standard_error_marginal")), _shown(q.get("prior_sd")), q.get("coordinate")]
                for key, q in ((named or {}).get("parameters") or {}).items() if q.get("identifiable")]
        if rows:
            tables[f"Fitted values of {named['name']}, with their 95 % intervals under noise + discrepancy, "
                   "at the model's moduli and with the patient's layer moduli unknown"] = (
                ["parameter", "value", "95 % interval", "95 % interval, moduli unknown", "unit",
                 "standard error, noise alone", "standard error, noise + discrepancy",
                 "standard error, moduli unknown", "standard deviation of the prior (none: flat)",
                 "coordinate of the standard errors"], rows)
        alts = record["verdict"].get("alternatives") or []
        if alts:
            tables["Other effects that explain the gap with strong evidence in-sample, not named"] = (
                ["effect", "BIC gain over the baseline", "held-out shrink %", "held-out log density gain",
                 "P(held-out gain > 0)", "significant", "a surface scan cannot tell it from the verdict"],
                [[a["effect"], a["bic_gain"], a["heldout_shrink_pct"], a["heldout_lpd_gain"],
                  a["heldout_lpd_gain_probability"], a["significant"],
                  a["effect"] in (record["verdict"].get("confounded_on_surface") or ())] for a in alts])
        shrink = record.get("shrinkage")
        em = record.get("error_model") or {}
        if "level_mm" in em:
            tables["Error model of the baseline gap (noise + model-form discrepancy)"] = (
                ["noise (mm)", "short scale (mm)", "correlation length (mm)", "long scale (mm)",
                 "mesh error taken out (mm)", "boundary field (mm)", "layer-proportion field (mm)",
                 "scan's pose, 1 sd (deg; mm)", "discrepancy (mm)", "level (mm)"],
                [[em["noise_mm"], em.get("short_scale_mm"), em["correlation_length_mm"], em.get("long_scale_mm"),
                  em.get("mesh_error_mm"),
                  None if em.get("boundary_mm") is None else f"{em['boundary_mm']} ({em.get('boundary_direction')})",
                  None if em.get("layer_mm") is None else
                  f"{em['layer_mm']} ({', '.join(em.get('layer_directions') or ())})",
                  None if not em.get("pose_sd") else
                  f"{max(em['pose_sd']['rotation_deg'])}; {max(em['pose_sd']['translation_mm'])}",
                  em["discrepancy_mm"], em["level_mm"]]])
        if shrink and "attributable_shrink_pct" in shrink.get("overall", {}):
            o = shrink["overall"]
            tables["Held-out shrinkage: the whole gap and the gap beyond noise + discrepancy"] = (
                ["", "before (mm)", "held-out after (mm)", "shrink %"],
                [["whole gap", o["before_mm"], o["heldout_after_mm"], o["heldout_shrink_pct"]],
                 ["beyond noise + discrepancy", o["attributable_before_mm"], o["attributable_heldout_after_mm"],
                  o["attributable_shrink_pct"]]])
        if shrink and "regions" in shrink:
            tables["How far the gap shrinks with the verdict's effect"] = (
                ["region", "before (mm)", "after (mm)", "held-out after (mm)", "held-out shrink %"],
                [["overall", *[shrink["overall"][k] for k in ("before_mm", "after_mm", "heldout_after_mm", "heldout_shrink_pct")]]]
                + [[n, r["before_mm"], r["after_mm"], r["heldout_after_mm"], r["heldout_shrink_pct"]]
                   for n, r in shrink["regions"].items()])
        intro = (f"Verdict: {verdict_text(record)}. Noise floor {record['noise_floor_mm']:.2f} mm. Gap = "
                 "post-op minus prediction along the predicted outward normal (> 0: the real face is fuller).")
        write_html_report(tmp / "report.html", "faceplan diagnose", record, images, tables=tables, intro=intro)
    say(f"diagnosis written to {out_dir}")
    return record
