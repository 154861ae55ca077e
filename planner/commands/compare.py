"""`faceplan compare CASE [CASE ...]`: predictions against post-operative scans.

For each case: read the prediction (`CASE/predict/`, or `--prediction DIR_OR_SURFACE`) and the
post-op scan (`CASE/postop/skin.*`, or `--postop FILE`), superimpose the scan on the unoperated
regions, measure signed distances both ways, per region and at landmarks, and write
`report.json`, `distances.vtp`, `distances_reverse.vtp`, `images/*.png` and `report.html` into
`CASE/compare/` (or `--out DIR` for a single case). With several cases each case's results go
to its own `CASE/compare/` and a cohort summary (`summary.csv`, `cases.csv`, `summary.json`,
`summary.html`: mean +- SD per region) goes to `--out DIR` (default: `compare_summary/` beside
the first case). Every case is computed before anything is written, so bad input in any case
writes nothing.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from planner.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cases", nargs="+", metavar="CASE", help="case folder(s)")
    p.add_argument("--prediction", metavar="DIR_OR_SURFACE",
                   help="prediction folder from `faceplan predict` or any surface file "
                        "(default CASE/predict); a relative path is looked up in each case first")
    p.add_argument("--postop", metavar="FILE", help="post-op scan (default CASE/postop/skin.*)")
    p.add_argument("--postop-landmarks", metavar="FILE",
                   help="landmarks placed on the post-op scan (json, Slicer .mrk.json or .fcsv; "
                        "default CASE/postop/landmarks.* when present); they replace the "
                        "automatic location for the landmarks they name")
    p.add_argument("--out", metavar="DIR",
                   help="output folder (one case: default CASE/compare; several cases: the "
                        "cohort summary, default compare_summary/ beside the first case)")
    p.add_argument("--gate", type=float, default=10.0, metavar="MM",
                   help="ignore scan points farther than this from the prediction (default 10)")
    p.add_argument("--keep", type=float, default=0.9, metavar="FRACTION",
                   help="fraction of best-matching points kept by the trimmed ICP (default 0.9)")
    p.add_argument("--no-align", action="store_true",
                   help="the scan is already superimposed on the pre-op frame: skip the ICP")
    p.add_argument("--global-init", action="store_true",
                   help="the scan is in its own (camera) frame: search a rough placement over "
                        "24 orientations before the ICP (by default the scan must be in the "
                        "patient's RAS frame, within ~2 cm and ~15 degrees)")
    p.add_argument("--no-images", action="store_true", help="skip the pictures")


def _check_args(args) -> None:
    if not 0.0 < args.gate <= 100.0:
        raise InputError("--gate must be in (0, 100] mm", field="--gate")
    if not 0.3 <= args.keep <= 1.0:
        raise InputError("--keep must be in [0.3, 1]", field="--keep")
    if args.global_init and args.no_align:
        raise InputError("--global-init and --no-align exclude each other", field="--global-init")
    if args.postop_landmarks and len(args.cases) > 1:
        raise InputError("--postop-landmarks works with a single case only", field="--postop-landmarks")
    if args.postop and len(args.cases) > 1:
        raise InputError("--postop works with a single case only", field="--postop")
    for c in args.cases:
        if not Path(c).is_dir():
            raise InputError("case folder not found", file=str(c))


def _postop_landmarks_file(case: Path, given: str | None) -> Path | None:
    if given:
        p = Path(given)
        if not p.is_file():
            raise InputError("post-op landmarks file not found", file=str(p), field="--postop-landmarks")
        return p
    for name in ("landmarks.json", "landmarks.mrk.json", "landmarks.fcsv"):
        if (case / "postop" / name).is_file():
            return case / "postop" / name
    return None


def run(args) -> int:
    from planner.atomic import atomic_output_dir, prepare_output
    from planner.compare.cohort import write_cohort
    from planner.compare.comparison import check_same_patient, compare_surfaces
    from planner.compare.inputs import check_not_preop, find_postop, load_surface, read_prediction
    from planner.compare.outputs import write_comparison

    _check_args(args)
    cases = [Path(c) for c in args.cases]
    # every output folder is checked before any work: nothing the user has is replaced
    outs = [prepare_output(Path(args.out) if (args.out and len(cases) == 1) else case / "compare",
                           "compare", inputs=cases) for case in cases]
    summary_dir = None
    if len(cases) > 1:
        summary_dir = prepare_output(Path(args.out) if args.out else cases[0].resolve().parent / "compare_summary",
                                     "compare-summary", inputs=cases)
    results = []
    for case in cases:
        t0 = time.perf_counter()
        prediction = read_prediction(case, args.prediction)
        postop_path = find_postop(case, args.postop)
        scan = load_surface(postop_path, "post-op scan")
        check_not_preop(case, scan, postop_path)
        lm_path = _postop_landmarks_file(case, args.postop_landmarks)
        manual = None
        if lm_path is not None:
            from planner.case import load_landmarks

            manual = load_landmarks(lm_path)
        result = compare_surfaces(prediction, scan, gate=args.gate, keep=args.keep,
                                  align=not args.no_align, global_init=args.global_init,
                                  postop_landmarks=manual,
                                  postop_landmarks_file=None if lm_path is None else str(lm_path))
        header = {
            "faceplan": 1,
            "command": "compare",
            "case": case.resolve().name,
            "case_dir": str(case.resolve()),
            "prediction": str(prediction.path),
            "postop": str(postop_path),
            "postop_landmarks": None if lm_path is None else str(lm_path),
            "settings": {"gate_mm": args.gate, "keep": args.keep, "align": not args.no_align,
                         "global_init": args.global_init, "threshold_mm": 2.0},
            "n_scan_vertices": int(len(scan.vertices)),
            "timings_s": {"compare": round(time.perf_counter() - t0, 3)},
        }
        if not args.no_align:
            check_same_patient(result, postop_path)
        results.append((case, result, header))

    reports = {}
    for (case, result, header), out in zip(results, outs):
        with atomic_output_dir(out, "compare", inputs=cases) as tmp:
            report = write_comparison(result, tmp, header, render_images=not args.no_images)
        reports[header["case"]] = report
        o = report["metrics"]["overall"]
        print(f"{header['case']}: mean |d| {o['mean_abs_mm']:.2f} mm, RMS {o['rms_mm']:.2f} mm, "
              f"{o['within_2mm_pct']:.1f}% within 2 mm over {o['n_points']} points; alignment "
              f"residual {result.alignment.residual_rms_mm:.2f} mm -> {out}")
        for w in result.warnings:
            print(f"  note: {w}")
    if len(cases) > 1:
        if len(set(reports)) < len(cases):
            reports = {str(c.resolve()): r for c, r in zip(cases, reports.values())}
        with atomic_output_dir(summary_dir, "compare-summary", inputs=cases) as tmp:
            write_cohort(tmp, reports)
        print(f"cohort summary of {len(cases)} cases -> {summary_dir}")
    return 0
