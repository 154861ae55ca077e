"""`faceplan register CASE`: the generic face mesh fitted to the patient (Mesh-Match-and-Repair).

Reads the case (pre-op skin, bone segments, optional landmarks), registers the generic
hexahedral model of the chosen resolution onto them exactly as a prediction does
(`planner.pipeline.register_case` -> `registration.mesh_match_and_repair`: similarity from landmarks or surfaces, joint elastic registration of skin and bone
attachments, repair of every element below the scaled-Jacobian threshold, teeth clearance and
lip separation) and writes, into
`CASE/register/` or `--out DIR`, all at once or not at all:
  patient_mesh.vtu + patient_mesh.json   the patient FaceModel (`FaceModel.load` reads it back)
  report.json                            fit errors (skin, bone), quality histogram, elements
                                         repaired, time per stage, alignment
  images/overlay_*.png, images/fit_*.png the registered skin over the patient skin, and the
                                         registered skin coloured by its distance to it
Bad input (wrong units, a surface covering too little of the face, inconsistent landmarks)
exits with status 2; a registration that cannot meet the validity gates exits with 3.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from planner.errors import InputError

RESOLUTIONS = ("coarse", "standard", "fine")
DEFAULT_THRESHOLD = 0.2  # the registration's minimum scaled Jacobian after repair


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("case", metavar="CASE", help="case folder (preop/skin.*, preop/bone/*, ...)")
    p.add_argument("--out", metavar="DIR", help="output folder (default CASE/register)")
    p.add_argument("--resolution", choices=RESOLUTIONS, default="standard",
                   help="generic mesh resolution (default standard)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD, metavar="SJ",
                   help=f"minimum scaled Jacobian after repair (default {DEFAULT_THRESHOLD:g})")
    p.add_argument("--no-landmarks", action="store_true",
                   help="ignore preop landmarks: align from the surfaces alone")
    p.add_argument("--no-cache", action="store_true", help="recompute even if a cached result exists")
    p.add_argument("--no-images", action="store_true", help="skip the pictures")


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.floating, float)):
        return None if not np.isfinite(v) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def register(case_dir, *, resolution: str = "standard", threshold: float = DEFAULT_THRESHOLD,
             use_landmarks: bool = True, cache: bool = True):
    """Load the case and register it the way a prediction does (`planner.pipeline.register_case`,
    one error mapping for both): returns (case, patient FaceModel, report dict).

    Without landmarks the case is registered with its landmarks left out; without the cache the
    registration's cache ($FACEPLAN_CACHE) points at a fresh folder for this call, so nothing is
    reused. threshold: the repair's scaled-Jacobian threshold."""
    import os
    import tempfile
    from dataclasses import replace

    from planner.case import load_case
    from planner.pipeline import Progress, register_case

    if not 0.0 < threshold < 1.0:
        raise InputError("--threshold must be in (0, 1)", field="--threshold")
    extra = {} if threshold == DEFAULT_THRESHOLD else {"threshold": threshold}
    case = load_case(case_dir)
    if not use_landmarks:
        case = replace(case, landmarks={})
    if cache:
        patient, report = register_case(case, resolution, Progress(echo=False), **extra)
        return case, patient, report
    saved = os.environ.get("FACEPLAN_CACHE")
    with tempfile.TemporaryDirectory(prefix="faceplan-register-") as fresh:
        os.environ["FACEPLAN_CACHE"] = fresh
        try:
            patient, report = register_case(case, resolution, Progress(echo=False), **extra)
        finally:
            if saved is None:
                os.environ.pop("FACEPLAN_CACHE", None)
            else:
                os.environ["FACEPLAN_CACHE"] = saved
    return case, patient, report


def _skin_trimesh(model, nodes=None):
    import trimesh

    q = np.asarray(model.facet_sets["skin"])
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    used, inv = np.unique(tri, return_inverse=True)
    x = model.nodes if nodes is None else nodes
    return trimesh.Trimesh(x[used], inv.reshape(tri.shape), process=False), used


def write_images(case, patient, out: Path) -> list[str]:
    from planner.render import render_overlay, render_views
    from registration.surface import TargetSurface

    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    skin_mesh, used = _skin_trimesh(patient)
    patient_skin = TargetSurface(np.asarray(case.skin.vertices), np.asarray(case.skin.faces))
    # distance at the triangle centroids: the nodes lie on the patient skin, the facets between
    # them show the remaining fit error
    d = patient_skin.closest(np.asarray(skin_mesh.triangles_center)).distance
    written = render_overlay([case.skin, skin_mesh], images / "overlay",
                             labels=["patient skin", "registered mesh"], opacity=[1.0, 0.55],
                             title="registered generic mesh over the patient skin")
    written.update({f"fit_{k}": v for k, v in render_views(
        skin_mesh, images / "fit", scalars=d, cmap="viridis", clim=(0.0, 1.0),
        title="registered skin: distance to the patient skin", scalar_bar_title="mm",
        views=("frontal", "profile")).items()})
    return sorted(str(p.relative_to(out)) for p in written.values())


def run(args) -> int:
    from planner.atomic import atomic_output_dir, prepare_output

    t0 = time.perf_counter()
    case_dir = Path(args.case)
    if not case_dir.is_dir():
        raise InputError("case folder not found", file=str(case_dir), field="case")
    out = prepare_output(args.out if args.out else case_dir / "register", "register", inputs=[case_dir])
    case, patient, report = register(case_dir, resolution=args.resolution, threshold=args.threshold,
                                     use_landmarks=not args.no_landmarks, cache=not args.no_cache)
    with atomic_output_dir(out, "register", inputs=[case_dir]) as tmp:
        t1 = time.perf_counter()
        patient.save(tmp / "patient_mesh.vtu")
        images = [] if args.no_images else write_images(case, patient, tmp)
        report = dict(report)
        report["time"] = {**report.get("time", {}), "write_s": time.perf_counter() - t1,
                          "command_s": time.perf_counter() - t0}
        report["inputs"] = {
            "case": str(case_dir.resolve()), "case_id": case.info.id, "resolution": args.resolution,
            "skin": str(case.skin_path) if case.skin_path else None, "bones": sorted(case.bones),
            "landmarks": sorted(case.landmarks) if not args.no_landmarks else [],
            "threshold": args.threshold,
        }
        report["outputs"] = {"mesh": "patient_mesh.vtu", "model_sidecar": "patient_mesh.json",
                             "images": images}
        (tmp / "report.json").write_text(json.dumps(_jsonable(report), indent=1))
    fit = report["fit"]
    q = report["quality"]
    print(f"faceplan register: {case.info.id} ({args.resolution}) -> {out}\n"
          f"  skin fit mean {fit['skin']['mean_mm']:.3f} mm, p95 {fit['skin']['p95_mm']:.3f} mm; "
          f"bone fit mean {fit['bone']['mean_mm'] if fit['bone']['mean_mm'] is not None else float('nan'):.3f} mm\n"
          f"  {report['repair']['elements_needing_repair']} element(s) repaired; min scaled Jacobian "
          f"{q['min_scaled_jacobian']:.3f}, {q['n_inverted']} inverted; "
          f"{'cached' if report.get('cached') else 'computed'} in {report['time'].get('total_s', 0):.1f} s")
    return 0
