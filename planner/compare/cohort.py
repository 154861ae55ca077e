"""Cohort summary of `faceplan compare` over several cases.

For every region (overall, each face region, each landmark) and every metric, the mean and
sample standard deviation (n - 1) over the cases that have it, as validation studies tabulate
them ("mean +- SD"). Written as `summary.csv` (long form: region, metric, mean, sd, n_cases),
`cases.csv` (one row per case and region), `summary.json`, a bar chart `summary_regions.png`
and a self-contained `summary.html`.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from planner.compare.metrics import METRIC_NAMES

__all__ = ["cohort_summary", "write_cohort"]

_STATS = tuple(m for m in METRIC_NAMES if m != "n_points") + ("n_points",)


def _rows_of(report: dict):
    m = report["metrics"]
    yield "overall", m["overall"]
    for name, block in m["regions"].items():
        yield name, block
    for name, block in (m.get("landmarks") or {}).items():
        yield f"landmark {name}", {"error_mm": block["error_mm"]}


def cohort_summary(reports: dict[str, dict]) -> dict:
    """{region: {metric: {mean, sd, n_cases}}} over the cases' report dicts."""
    values: dict[str, dict[str, list[float]]] = {}
    for report in reports.values():
        for region, block in _rows_of(report):
            if region != "overall" and not region.startswith("landmark") and not block.get("n_points"):
                continue
            for metric, v in block.items():
                if metric == "mean_signed_mm" or v is None:
                    continue
                values.setdefault(region, {}).setdefault(metric, []).append(float(v))
    out: dict[str, dict] = {}
    for region, metrics in values.items():
        out[region] = {}
        for metric, vals in metrics.items():
            a = np.asarray(vals)
            out[region][metric] = {"mean": float(a.mean()),
                                   "sd": float(a.std(ddof=1)) if len(a) > 1 else None,
                                   "n_cases": int(len(a))}
    return out


def _pm(stat: dict | None) -> str:
    if not stat:
        return ""
    if stat["sd"] is None:
        return f"{stat['mean']:.2f}"
    return f"{stat['mean']:.2f} ± {stat['sd']:.2f}"


def write_cohort(out: Path, reports: dict[str, dict]) -> dict:
    """Write the cohort files into folder `out`; returns the summary dict."""
    from planner.html_report import write_html_report

    summary = cohort_summary(reports)
    with open(out / "summary.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["region", "metric", "mean", "sd", "n_cases"])
        for region, metrics in summary.items():
            for metric, s in metrics.items():
                w.writerow([region, metric, f"{s['mean']:.6g}",
                            "" if s["sd"] is None else f"{s['sd']:.6g}", s["n_cases"]])
    cols = ["case", "region", *METRIC_NAMES, "error_mm"]
    with open(out / "cases.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for case, report in reports.items():
            for region, block in _rows_of(report):
                w.writerow([case, region] + ["" if block.get(c) is None else block.get(c)
                                             for c in cols[2:]])
    doc = {"cases": list(reports), "n_cases": len(reports), "summary": summary}
    (out / "summary.json").write_text(json.dumps(doc, indent=2))
    metric_cols = ["mean_abs_mm", "rms_mm", "p90_mm", "p95_mm", "within_2mm_pct"]
    table_rows = [[region] + [_pm(m.get(c)) for c in metric_cols] + [
        (m.get("mean_abs_mm") or m.get("error_mm") or {}).get("n_cases", "")]
        for region, m in summary.items() if not region.startswith("landmark")]
    lm_rows = [[region.split(" ", 1)[1], _pm(m.get("error_mm")), m["error_mm"]["n_cases"]]
               for region, m in summary.items() if region.startswith("landmark")]
    per_case = [[case, r["metrics"]["overall"].get("mean_abs_mm"), r["metrics"]["overall"].get("rms_mm"),
                 r["metrics"]["overall"].get("within_2mm_pct"), r.get("alignment", {}).get("residual_rms_mm")]
                for case, r in reports.items()]
    tables = {"Metrics across cases (mean ± SD, mm; % within 2 mm)":
              (["region"] + metric_cols + ["cases"], table_rows)}
    if lm_rows:
        tables["Landmark errors across cases (mm)"] = (["landmark", "error_mm", "cases"], lm_rows)
    tables["Per case (overall)"] = (["case", "mean_abs_mm", "rms_mm", "within_2mm_pct",
                                     "alignment residual (mm)"], per_case)
    from planner.render import bar_chart

    regions = [r for r, m in summary.items() if not r.startswith("landmark") and "mean_abs_mm" in m]
    chart = bar_chart(regions, [summary[r]["mean_abs_mm"]["mean"] for r in regions],
                      out / "summary_regions.png",
                      errors=[summary[r]["mean_abs_mm"]["sd"] or 0.0 for r in regions],
                      ylabel="mean |d| (mm)",
                      title=f"mean absolute distance per region, mean ± SD over {len(reports)} cases")
    write_html_report(out / "summary.html", f"faceplan compare: {len(reports)} cases",
                      {"cases": list(reports), "n_cases": len(reports)},
                      [(chart, "mean absolute distance per region (mean ± SD over cases; dashed: 2 mm)")],
                      tables=tables)
    return doc
