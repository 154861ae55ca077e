"""Files written by `faceplan compare` for one case.

`distances.vtp` (the post-op scan superimposed on the pre-op frame, point data
`signed_distance_mm` -- NaN where the surfaces do not overlap -- `abs_distance_mm`, `region`
and `valid`, field data `region_names` and `alignment_matrix`), `distances_reverse.vtp` (the
prediction with the reverse distances), `images/*.png` (signed-distance colour maps on both
surfaces in the frontal, profile and three-quarter views with a diverging +-3 mm scale and
iso-lines at +-1 and +-2 mm, a histogram, a per-region bar chart, a profile overlay, and the
predicted and post-op faces drawn with the same camera in the frontal and profile views),
`report.json` and `report.html` (with a slider between the predicted and post-op pictures of
each view, as the prediction's report has between pre-op and predicted).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from planner.compare.comparison import Comparison

__all__ = ["write_comparison", "region_table", "CLIM_MM"]

CLIM_MM = 3.0
ISOLINES_MM = (-2.0, -1.0, 1.0, 2.0)
SIDE_BY_SIDE_VIEWS = ("frontal", "profile")


def _polydata(vertices, faces):
    import pyvista as pv

    cells = np.hstack([np.full((len(faces), 1), 3, np.int64), faces]).ravel()
    return pv.PolyData(np.asarray(vertices, float), cells)


def region_table(metrics: dict) -> tuple[list[str], list[list]]:
    """(columns, rows) of the per-region metrics, regions with points first, overall last."""
    cols = ["region", "mean_abs_mm", "rms_mm", "p90_mm", "p95_mm", "within_2mm_pct", "n_points"]
    rows = [[name] + [m.get(c) for c in cols[1:]] for name, m in metrics["regions"].items()
            if m.get("n_points")]
    rows.append(["overall"] + [metrics["overall"].get(c) for c in cols[1:]])
    return cols, rows


def write_comparison(result: Comparison, out: Path, header: dict, render_images: bool = True) -> dict:
    """Write every output of one comparison into folder `out`; returns the report dict."""
    from planner import render
    from planner.html_report import write_html_report

    pred = result.prediction
    names = list(pred.region_names)
    scan = _polydata(result.scan_vertices, result.scan_faces)
    scan.point_data["signed_distance_mm"] = result.signed
    scan.point_data["abs_distance_mm"] = np.abs(result.signed)
    scan.point_data["region"] = result.region.astype(np.int32)
    scan.point_data["valid"] = np.isfinite(result.signed).astype(np.uint8)
    scan.field_data["region_names"] = np.array(names)
    scan.field_data["alignment_matrix"] = np.asarray(result.alignment.matrix).ravel()
    scan.save(str(out / "distances.vtp"))
    pp = _polydata(pred.vertices, pred.faces)
    pp.point_data["signed_distance_mm"] = result.reverse_signed
    pp.point_data["region"] = pred.region.astype(np.int32)
    pp.field_data["region_names"] = np.array(names)
    pp.save(str(out / "distances_reverse.vtp"))

    report = dict(header)
    report.update(result.report())
    report["files"] = {"distances": "distances.vtp", "distances_reverse": "distances_reverse.vtp",
                       "html": "report.html"}
    images: list[tuple[Path, str]] = []
    pairs: list = []
    if render_images:
        img = out / "images"
        img.mkdir()
        clim = (-CLIM_MM, CLIM_MM)
        for view, path in render.render_views(scan, img / "distance_postop", scalars=result.signed,
                                              cmap="RdBu_r", clim=clim, scalar_bar_title="mm",
                                              isolines=ISOLINES_MM,
                                              title="post-op minus predicted (mm)").items():
            images.append((path, f"signed distance on the post-op scan, {view.replace('_', '-')}"))
        for view, path in render.render_views(pp, img / "distance_prediction",
                                              scalars=result.reverse_signed, cmap="RdBu_r",
                                              clim=clim, scalar_bar_title="mm", isolines=ISOLINES_MM,
                                              title="post-op minus predicted, on the prediction (mm)",
                                              views=("three_quarter",)).items():
            images.append((path, f"signed distance on the prediction, {view.replace('_', '-')}"))
        box = render.union_bounds([pp, scan])
        shots = [render.render_views(mesh, img / name, title=title, views=SIDE_BY_SIDE_VIEWS, bounds=box,
                                     title_position=where)
                 for mesh, name, title, where in ((pp, "predicted", "predicted face", "upper_left"),
                                                  (scan, "postop", "post-op face", "upper_right"))]
        pairs = [(render.VIEW_TITLES[v], shots[0][v], shots[1][v]) for v in SIDE_BY_SIDE_VIEWS]
        finite = result.signed[np.isfinite(result.signed)]
        lim = max(CLIM_MM, float(np.percentile(np.abs(finite), 99.5)) if finite.size else CLIM_MM)
        images.append((render.histogram_chart(finite, img / "histogram.png", bins=80,
                                              range_=(-lim, lim),
                                              title="signed distances, post-op to prediction"),
                       "histogram of signed distances (dashed: +-2 mm)"))
        cols, rows = region_table(result.metrics)
        labels = [r[0] for r in rows]
        images.append((render.bar_chart(labels, [0.0] * len(labels), img / "regions.png",
                                        series={"mean |d|": [r[1] for r in rows],
                                                "90th pct": [r[3] for r in rows]},
                                        ylabel="mm", title="distance per region"),
                       "mean absolute and 90th-percentile distance per region (dashed: 2 mm)"))
        images.append((render.profile_chart([pp, scan], img / "profile.png",
                                            labels=["predicted", "post-op"],
                                            title="mid-sagittal profile (x = 0)"),
                       "mid-sagittal profiles: predicted vs post-op"))
        report["files"]["images"] = [str(p.relative_to(out)) for p, _ in images] + [
            str(p.relative_to(out)) for _, a, b in pairs for p in (a, b)]
    report = _clean(json.loads(json.dumps(report, default=_jsonable)))
    (out / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False))
    cols, rows = region_table(result.metrics)
    tables = {"Distances per region (post-op scan to prediction)": (cols, rows)}
    lm = result.metrics.get("landmarks") or {}
    if lm:
        tables["Landmark errors"] = (["landmark", "error_mm", "dx_mm", "dy_mm", "dz_mm"],
                                     [[k, v["error_mm"], *v["vector_mm"]] for k, v in lm.items()])
    a = result.alignment
    tables["Superimposition on unoperated regions"] = (
        ["", "value"],
        [["regions", ", ".join(pred.unoperated_regions)], ["residual RMS (mm)", a.residual_rms_mm],
         ["residual mean |d| (mm)", a.residual_mean_abs_mm], ["inlier points", a.n_points],
         ["rotation (deg)", a.rotation_deg], ["translation (mm)", a.translation_mm]])
    write_html_report(out / "report.html", f"faceplan compare: {header.get('case', '')}",
                      report, images, tables=tables, before_after=pairs,
                      before_after_labels=("predicted", "post-op"),
                      intro="Post-op scan superimposed on the pre-op frame by trimmed ICP on the "
                            "unoperated regions; " + result.report()["sign_convention"] + ".")
    return report


def _clean(o):
    """NaN and infinities become null (JSON has no NaN)."""
    if isinstance(o, float):
        return o if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, list):
        return [_clean(v) for v in o]
    return o


def _jsonable(o):
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
