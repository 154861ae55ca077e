"""`faceplan predict CASE`: the case's plan -> the predicted face (see planner.pipeline)."""
from __future__ import annotations

from planner.plan import RESOLUTIONS


def add_arguments(parser) -> None:
    parser.add_argument("case", help="case folder (preop/, plan.yaml, ...)")
    parser.add_argument("--out", metavar="DIR", help="output folder (default CASE/predict)")
    parser.add_argument("--resolution", choices=RESOLUTIONS,
                        help="face model resolution (default: the plan's model.resolution, else standard)")
    parser.add_argument("--effect", action="append", metavar="NAME=VALUE", default=[],
                        help="add an effect to the prediction (docs/effects.md): sliding=1|SEGMENT, "
                             "muscle_tone=A (0..1), swelling=THETA (peak growth ratio, 1 = none), "
                             "gravity=M (posture factor, 1 = supine CT to upright scan), "
                             "stiffness=F or stiffness.LAYER=F (dermis, hypodermis, muscle, mucosa, "
                             "nose), bone_execution=1 (postop/plan_actual.yaml) or "
                             "bone_execution.SEGMENT=[tx,ty,tz,rx,ry,rz] (mm, deg); repeatable")
    parser.add_argument("--allow-large-movements", action="store_true",
                        help="accept bone movements beyond 25 mm / 30 deg (refused by default)")
    parser.add_argument("--no-images", action="store_true", help="skip the renders")
    parser.add_argument("--quiet", action="store_true", help="no progress display")


def run(args) -> int:
    from planner.pipeline import parse_effects, predict_case

    effects = parse_effects(args.effect)
    big = {"max_translation_mm": 1e3, "max_rotation_deg": 180.0} if args.allow_large_movements else {}
    out = predict_case(args.case, args.out, resolution=args.resolution, effects=effects,
                       render=not args.no_images, echo=not args.quiet, **big)
    print(out)
    return 0
