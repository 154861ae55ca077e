"""`faceplan demo`: the solver showcase (Cook's membrane and a stretched Yeoh block).

Writes VTUs, PNGs and summary.json into --out (default out/demo), all or nothing. To be
replaced by the whole-prediction demo once the planner pipeline provides it.
"""
from __future__ import annotations


def add_arguments(parser):
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")


def run(args) -> int:
    from planner.showcase import run as showcase

    showcase(args.out)
    return 0
