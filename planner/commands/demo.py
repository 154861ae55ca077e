"""`faceplan demo`: the whole prediction on the embedded synthetic head with a bimaxillary plan.

Le Fort I advancement, mandibular setback and genioplasty (`planner.pipeline.DEMO_PLAN`) on the
synthetic head stored in the package, through registration, segment assignment, solve, renders
and reports (`planner.pipeline.run_demo`); writes what `faceplan predict` writes plus the case
folder it used (`case/`) into --out (default out/demo), all or nothing. `--showcase` runs the
solver showcase instead (Cook's membrane and a stretched Yeoh block, `planner.showcase`).
"""
from __future__ import annotations


def add_arguments(parser):
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    parser.add_argument("--resolution", choices=("coarse", "standard", "fine"), default="coarse",
                        help="face model resolution (default coarse: the demo runs in minutes)")
    parser.add_argument("--no-images", action="store_true", help="skip the renders")
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    parser.add_argument("--showcase", action="store_true",
                        help="run the solver showcase (Cook's membrane, Yeoh block) instead")


def run(args) -> int:
    from planner.atomic import prepare_output

    prepare_output(args.out, "showcase" if args.showcase else "demo")
    if args.showcase:
        from planner.showcase import run as showcase

        showcase(args.out)
        return 0
    from planner.pipeline import run_demo

    out = run_demo(args.out, resolution=args.resolution, render=not args.no_images, echo=not args.quiet)
    print(out)
    return 0
