"""`faceplan synth`: synthetic case folders from random plausible heads.

Each case (seed S + i) is a head of `facemodel.synthetic` written as the contract's case
folder: preop/skin.stl (closed), preop/bone/<segment>.stl (skull, maxilla, mandible, chin),
preop/teeth/<arch>.stl, preop/landmarks.json, a sample bimaxillary plan.yaml that corrects
the head's jaw discrepancy (Le Fort I, BSSO, genioplasty when the chin is off), case.yaml,
and with --ct a CT-like volume preop/ct.nii.gz of the same head. The shape parameters go
only to the --key file (the case folder stays blind). Post-op scans and withheld effects
come later: --withheld-effect accepts `none` for now.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from planner.errors import InputError


def add_arguments(parser) -> None:
    parser.add_argument("--out", required=True, help="folder that receives the case folders")
    parser.add_argument("--count", type=int, default=1, help="number of cases (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first case (default 0)")
    parser.add_argument("--withheld-effect", default="none",
                        help="effect withheld from the case and written to the key file only "
                             "(this build: none)")
    parser.add_argument("--key", default=None, help="JSON file receiving the ground truth of every case")
    parser.add_argument("--ct", action="store_true", help="also write a CT-like volume preop/ct.nii.gz")
    parser.add_argument("--ct-spacing", type=float, default=1.0, help="CT voxel size in mm (default 1)")
    parser.add_argument("--surface-size", type=float, default=1.0,
                        help="skin facet size over the face in mm (default 1, the density of a "
                             "skin segmented from a 1 mm CT; coarser towards the back of the head)")
    parser.add_argument("--mesher", choices=("sphere", "pygalmesh"), default="sphere",
                        help="skin mesher: projected geodesic sphere (default, reproducible) or "
                             "CGAL's Delaunay surface mesher via pygalmesh")


def _check(args) -> None:
    if args.count < 1 or args.count > 1000:
        raise InputError(f"--count must be between 1 and 1000, got {args.count}", field="--count")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}", field="--seed")
    effect = str(args.withheld_effect).strip().lower()
    if effect != "none":
        raise InputError(f"withheld effect {args.withheld_effect!r} is not available in this build "
                         "(only 'none'); post-operative scans come with the sim-to-real issue",
                         field="--withheld-effect")
    if not (0.2 <= args.ct_spacing <= 5.0):
        raise InputError(f"--ct-spacing must be in [0.2, 5] mm, got {args.ct_spacing}", field="--ct-spacing")
    if not (1.0 <= args.surface_size <= 10.0):
        raise InputError(f"--surface-size must be in [1, 10] mm, got {args.surface_size}", field="--surface-size")


def sample_plan(shape) -> dict:
    """A bimaxillary plan that brings the head's jaws towards the norm: maxillary advancement
    (at least 2 mm) with 1 mm impaction and a 2 deg pitch about A point; the mandible follows
    the maxilla and corrects its own discrepancy; a genioplasty when the chin is off by more
    than 1.5 mm (otherwise the chin moves with the mandible)."""
    from facemodel import head_geometry as hg

    adv = float(np.clip(2.0 - shape.maxilla_ap, 2.0, 7.0))
    mand = float(np.clip(adv - shape.mandible_ap + shape.maxilla_ap, -8.0, 10.0))
    a_point = hg.to_cartesian(0.0, -9.0, float(hg.bone_radius(0.0, -9.0, shape, side=1)), shape)
    segs = {
        "maxilla": {"translation": [0.0, round(adv, 2), 1.0],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0,
                                 "center": [round(float(c), 2) for c in a_point]}},
        "mandible": {"translation": [0.0, round(mand, 2), 0.0]},
    }
    # the chin is a separate bone surface: without a genioplasty it moves with the mandible
    # (distal segment); with one (chin off by more than 1.5 mm) it is also brought back
    chin = mand - float(shape.chin_projection) if abs(shape.chin_projection) > 1.5 else mand
    segs["chin"] = {"translation": [0.0, round(chin, 2), 0.0]}
    return {"faceplan": 1, "frame": "RAS", "segments": segs,
            "muscles": {"orbicularis_oris": 0.0, "mentalis": 0.0},
            "model": {"resolution": "standard"}}


def write_case(folder: Path, head, *, ct: bool = False, ct_spacing: float = 1.0) -> dict:
    """Write one synthetic head as a case folder (into an existing empty folder)."""
    import yaml

    preop = folder / "preop"
    (preop / "bone").mkdir(parents=True)
    (preop / "teeth").mkdir()
    head.skin.export(preop / "skin.stl")
    for seg, mesh in head.bones.items():
        mesh.export(preop / "bone" / f"{seg}.stl")
    import trimesh

    for arch, (v, f, _) in head.teeth.items():
        trimesh.Trimesh(v, f, process=False).export(preop / "teeth" / f"{arch}.stl")
    (preop / "landmarks.json").write_text(json.dumps(
        {k: [round(float(x), 4) for x in v] for k, v in head.landmarks.items()}, indent=1))
    plan = sample_plan(head.shape)
    (folder / "plan.yaml").write_text(
        "# faceplan synth: sample bimaxillary plan (Le Fort I, BSSO"
        + (", genioplasty" if abs(head.shape.chin_projection) > 1.5 else "") + ")\n"
        + yaml.safe_dump(plan, sort_keys=False))
    info = {"id": folder.name, "synthetic": True, "seed": int(head.seed)}
    (folder / "case.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    if ct:
        from facemodel.ct_phantom import ct_volume_from_surfaces, write_nifti

        hu, affine = ct_volume_from_surfaces(head.skin, head.bones, spacing=ct_spacing,
                                             seed=int(head.seed))
        write_nifti(preop / "ct.nii.gz", hu, affine)
    return {"id": folder.name, "seed": int(head.seed), "shape": head.shape.as_dict(),
            "withheld_effect": None, "plan": plan}


def run(args) -> int:
    from facemodel.synthetic import synthetic_head
    from planner.atomic import atomic_output_dir, atomic_write_file

    _check(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out exists and is not a folder", file=str(out), field="--out")
    truth = []
    with atomic_output_dir(out) as tmp:
        if out.is_dir():          # keep what the folder already holds
            import shutil

            shutil.copytree(out, tmp, dirs_exist_ok=True)
        for i in range(args.count):
            seed = args.seed + i
            head = synthetic_head(seed, size=args.surface_size, distance=args.surface_size / 12.0,
                                  mesher=args.mesher)
            name = f"synth_{seed:04d}"
            target = tmp / name
            if target.exists():
                import shutil

                shutil.rmtree(target)
            target.mkdir()
            truth.append(write_case(target, head, ct=args.ct, ct_spacing=args.ct_spacing))
            print(f"faceplan synth: {out / name} (seed {seed})")
    if args.key:
        with atomic_write_file(args.key) as fh:
            json.dump({"cases": truth}, fh, indent=1)
    return 0
