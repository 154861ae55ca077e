"""`faceplan diagnose CASE [CASE ...]`: where a prediction misses the post-op face, which
unmodelled effect explains it and how far the gap shrinks (see `planner.diagnosis`).

Writes `diagnosis.json`, `images/*.png` and `report.html` into `CASE/diagnose/` (one case) or
`--out DIR` (several cases: default `diagnose_cohort/` beside the first case). The forward
solves run as dask.distributed tasks: on a LocalCluster started here (`--workers N`), on an
existing cluster (`--scheduler ADDRESS`), or in this process (`--workers 0`).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from planner.errors import InputError
from planner.plan import RESOLUTIONS


def add_arguments(p) -> None:
    p.add_argument("cases", nargs="+", metavar="CASE", help="case folder(s) with postop/skin.*")
    p.add_argument("--out", metavar="DIR", help="output folder (default CASE/diagnose; several "
                   "cases: diagnose_cohort/ beside the first case)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask.distributed scheduler of an existing "
                   "cluster (default: a LocalCluster started for the run)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="LocalCluster workers (default: the CPU count, at most 4; 0: solve in this process)")
    p.add_argument("--resolution", choices=RESOLUTIONS,
                   help="face model resolution (default: the plan's model.resolution, else standard)")
    p.add_argument("--effects", metavar="NAMES", help="comma-separated effects to test (default: every "
                   "effect the model can add)")
    p.add_argument("--mesh-reference", default="auto", choices=("auto", "none") + tuple(RESOLUTIONS),
                   help="second mesh whose baseline estimates the model mesh's own discretisation error "
                        "(default auto: the next coarser resolution, none at coarse)")
    p.add_argument("--boundary-uncertainty", default="neck", metavar="neck[,floor]|none",
                   help="model boundary conditions whose other choice the error model carries as a "
                        "discrepancy direction, one more solve per case each (default neck: the "
                        "neck cut's; floor: the floor of the mouth's, nearly the neck's direction; "
                        "none: not)")
    p.add_argument("--layer-uncertainty", default="none", choices=("thicker", "none"),
                   help="layer proportions the CT does not show, carried by the error model as "
                        "discrepancy directions (thicker: the baseline is also solved with the "
                        "dermis, and with the deep layers, a fifth thicker, two more solves per "
                        "case; default none: not)")
    p.add_argument("--materials", metavar="CALIBRATION_JSON",
                   help="patient-specific materials from `faceplan calibrate` (its calibration.json): "
                        "merged into the plan's model.materials, and their measured spread used for "
                        "the named effect's intervals with the moduli unknown")
    p.add_argument("--finite-differences", action="store_true",
                   help="sensitivities by finite differences of full solves instead of the model's "
                        "tangent (slower; a check of the tangent)")
    p.add_argument("--no-images", action="store_true", help="skip the pictures")
    p.add_argument("--quiet", action="store_true", help="no progress display")


def _check(args) -> tuple[list[Path], tuple[str, ...] | None]:
    from planner.compare.inputs import find_postop
    from planner.plan import EFFECTS

    cases = [Path(c) for c in args.cases]
    for c in cases:
        if not c.is_dir():
            raise InputError("case folder not found", file=str(c))
        find_postop(c)                      # no post-op scan: bad input before any work
    if args.workers is not None and not 0 <= args.workers <= 64:
        raise InputError("--workers must be in 0..64", field="--workers")
    if args.scheduler and args.workers is not None:
        raise InputError("--scheduler and --workers exclude each other", field="--workers")
    names = None
    if args.effects:
        names = tuple(n.strip() for n in args.effects.split(",") if n.strip())
        bad = [n for n in names if n not in EFFECTS]
        if bad or not names:
            raise InputError(f"unknown effect(s) {', '.join(bad) or '(none given)'} (known: {', '.join(EFFECTS)})",
                             field="--effects")
    if len(set(c.resolve() for c in cases)) < len(cases):
        raise InputError("a case is given twice", field="CASE")
    from planner.diagnosis.run import parse_boundaries

    try:
        args.boundaries = parse_boundaries(args.boundary_uncertainty)
    except ValueError as exc:
        raise InputError(str(exc), field="--boundary-uncertainty") from None
    if getattr(args, "materials", None):
        from planner.calibration.materials import read_moduli_spread

        read_moduli_spread(args.materials)      # the whole file checked: bad input before any work
    return cases, names


def _client(args):
    """A dask.distributed client (None: solve in this process) and what to close afterwards."""
    if args.workers == 0:
        return None, []
    import logging

    from distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.ERROR)
    if args.scheduler:
        try:
            client = Client(args.scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"cannot reach the dask scheduler ({exc})", field="--scheduler") from None
        return client, [client]
    n = args.workers or max(1, min(4, os.cpu_count() or 1))
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=logging.ERROR)
    client = Client(cluster)
    return client, [client, cluster]


def run(args) -> int:
    from planner.diagnosis.forward import Runner
    from planner.diagnosis.outputs import verdict_text, write_diagnosis
    from planner.diagnosis.run import diagnose_cases
    from planner.pipeline import Progress

    cases, names = _check(args)
    progress = Progress(echo=not args.quiet)
    client, closing = _client(args)
    try:
        result = diagnose_cases(cases, resolution=args.resolution, runner=Runner(client), say=progress.say,
                                effect_names=names, tangent=not args.finite_differences,
                                reference=args.mesh_reference,
                                boundary=args.boundaries,
                                layers=args.layer_uncertainty == "thicker",
                                materials=Path(args.materials) if getattr(args, "materials", None) else None)
    finally:
        for obj in closing:
            obj.close()
    if args.out:
        out = Path(args.out)
    elif len(cases) == 1:
        out = cases[0] / "diagnose"
    else:
        out = cases[0].resolve().parent / "diagnose_cohort"
    record = write_diagnosis(result, out, render_images=not args.no_images, say=progress.say)
    print(f"verdict: {verdict_text(record)} -> {out}")
    for w in record.get("warnings", []):
        print(f"  warning: {w}", file=sys.stderr)
    return 0
