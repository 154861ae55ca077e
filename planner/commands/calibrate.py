"""`faceplan calibrate DATA`: patient-specific Yeoh parameters, with their uncertainty, from
in-vivo aspiration and indentation curves (see planner.calibration and docs/calibration.md).

Writes `calibration.json`, `images/*.png` and `report.html` into `--out DIR` (default
`calibrate/` in the DATA folder or beside the DATA file), whole or not at all.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from planner.errors import InputError, SolveError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA",
                   help="calibration data: a YAML file, or a folder holding sites.yaml and the "
                        "curves' CSV files (an example ships in planner/data/calibration_example)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: calibrate/ in the DATA folder, or beside the DATA file)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="dask scheduler to run the forward runs on (default: a LocalCluster "
                        "of --workers processes)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="processes of the LocalCluster (default 2)")
    p.add_argument("--runs", type=int, default=24, metavar="N",
                   help="forward runs per site in the focused design (default 24; the prior "
                        "design has 2/3 of it, the held-out set 1/3)")
    p.add_argument("--resolution", choices=("coarse", "standard", "fine"), default="standard",
                   help="slab mesh resolution (default standard)")
    p.add_argument("--seed", type=int, default=0, help="seed of the designs and sampling")
    p.add_argument("--no-images", action="store_true", help="skip the pictures")


RESOLUTION = {"coarse": 6, "standard": 8, "fine": 12}


def run(args) -> int:
    from planner.atomic import atomic_output_dir, prepare_output
    from planner.calibration.data import read_calibration_data
    from planner.calibration.emulator import dask_client
    from planner.calibration.outputs import write_outputs
    from planner.calibration.run import calibrate_sites
    from planner.calibration.slab import ForwardError, MeshOptions

    if not 1 <= args.workers <= 64:
        raise InputError("must be in 1..64", field="--workers")
    if not 6 <= args.runs <= 400:
        raise InputError("must be in 6..400", field="--runs")
    data = Path(args.data)
    out = prepare_output(Path(args.out) if args.out else
                         (data if data.is_dir() else data.parent) / "calibrate",
                         "calibrate", inputs=[data])
    sites = read_calibration_data(args.data)
    opt = MeshOptions(n_fine=RESOLUTION[args.resolution])
    try:
        with dask_client(args.scheduler, args.workers) as client:
            report, extras = calibrate_sites(
                sites, client, opt=opt, n_stage1=max(6, (2 * args.runs) // 3),
                n_stage2=args.runs, n_heldout=max(3, args.runs // 3), seed=args.seed)
    except ForwardError as exc:
        raise SolveError(f"calibration forward model: {exc}") from None
    report["data"] = str(data.resolve())
    with atomic_output_dir(out, "calibrate", inputs=[data]) as tmp:
        write_outputs(tmp, report, extras, render=not args.no_images)
    print(out)
    return 0
