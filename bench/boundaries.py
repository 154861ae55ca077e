"""How much the model's boundary choices change the face: a mandibular advancement solved with
each choice against the default.

The choices (`facemodel.simulation.simulate`, plan key `model.*`):
- `proximal`: "seated" (default, a sagittal split: the ramus and angle tissue stays with the
  skull) against "moved" (the whole mandible moves as one body);
- `neck`: "held" against "free" (default), the cut through the neck;
- `floor`: "held" against "free" (default), the floor of the mouth.

The mandible and chin are advanced `--advance` mm (no contact: the choices, not the lips) on the
generic face. For each choice the script prints, per skin region, the mean forward
displacement under both conditions and the RMS of their difference, then the cosine between
the held floor's and the held neck's change of the skin displacement over the whole skin and
over what a frontal scan sees (`facemodel.synthetic.scan_coverage`). These are the figures of
docs/effects.md ("Sagittal split") and docs/diagnosis.md ("Boundary conditions").
Usage: python bench/boundaries.py [--resolution coarse|standard|fine] [--advance MM]
Last line: preauricular_moved_mm=<x> preauricular_seated_mm=<x> floor_neck_cosine=<x>
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def _solve(face, motions, **choice):
    from facemodel.simulation import simulate

    t = time.perf_counter()
    res = simulate(face, motions, contact=False, **choice)
    if not res.converged:
        raise SystemExit(f"the solve with {choice or 'the defaults'} did not converge (load {res.load})")
    print(f"  solved {choice or 'defaults'} in {time.perf_counter() - t:.1f} s")
    return res.displacement


def _table(face, title, a, b, names):
    print(f"\n{title}: mean forward displacement (mm) and RMS of the difference (mm) per region")
    print(f"  {'region':22s} {names[0]:>9s} {names[1]:>9s} {'diff RMS':>9s} {'diff max':>9s}")
    for name in sorted(face.regions):
        ids = np.asarray(face.regions[name])
        d = np.linalg.norm(b[ids] - a[ids], axis=1)
        print(f"  {name:22s} {a[ids, 1].mean():9.2f} {b[ids, 1].mean():9.2f} "
              f"{np.sqrt(np.mean(d * d)):9.2f} {d.max():9.2f}")


def _cosine(a, b):
    return float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolution", default="standard", choices=("coarse", "standard", "fine"))
    ap.add_argument("--advance", type=float, default=6.0, help="mandible and chin advancement (mm)")
    args = ap.parse_args(argv)

    import generic_mesh
    from facemodel.synthetic import scan_coverage
    from planner.pipeline import skin_surface

    face = generic_mesh.load(args.resolution)
    T = np.eye(4)
    T[1, 3] = args.advance
    motions = {"mandible": T, "chin": T}
    print(f"generic face, {args.resolution}: mandible and chin advanced {args.advance} mm, no contact")
    base = _solve(face, motions)
    moved = _solve(face, motions, proximal="moved")
    neck = _solve(face, motions, neck="held")
    floor = _solve(face, motions, floor="held")
    _table(face, "proximal segments (moved -> seated, the default)", moved, base, ("moved", "seated"))
    _table(face, "neck (free, the default -> held)", base, neck, ("free", "held"))
    _table(face, "floor of the mouth (free, the default -> held)", base, floor, ("free", "held"))

    V, F, skin = skin_surface(face)
    landmarks = {k: face.nodes[i] for k, i in face.landmarks.items()}
    seen = scan_coverage(V, V, F, landmarks)
    dn, df = neck[skin] - base[skin], floor[skin] - base[skin]
    cos_all, cos_seen = _cosine(dn, df), _cosine(dn[seen], df[seen])
    print(f"\ncosine of the held floor's and the held neck's change of the skin: {cos_all:.3f} over the "
          f"skin, {cos_seen:.3f} over what a frontal scan sees ({int(seen.sum())} of {len(skin)} nodes)")
    pre = np.concatenate([face.regions["preauricular_left"], face.regions["preauricular_right"]])
    print(f"preauricular_moved_mm={moved[pre, 1].mean():.3f} preauricular_seated_mm={base[pre, 1].mean():.3f} "
          f"floor_neck_cosine={cos_all:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
