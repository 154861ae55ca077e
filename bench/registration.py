"""Benchmark of Mesh-Match-and-Repair on synthetic heads whose truth is known (issue 4).

Ten heads: seven drawn by `facemodel.synthetic.random_shape` and three extremes built on
purpose (strong class III, strong class II, asymmetric lower face), each registered at coarse
and standard resolution from its skin (a scan-like ~1 mm triangulation over the face,
`synthetic.SCAN_SIZE` / `SCAN_ZOOM`), bone segments and landmarks. Prints one line per run
(fit errors, quality, repaired elements, landmark errors, time per stage) and a summary with
the targets; the last line is
    register_s=<t> skin_mean_mm=<x> skin_p95_mm=<x> min_scaled_jacobian=<x>
with worst cases over the heads: the longest standard-resolution registration, the largest
per-head skin mean and 95th percentile, the smallest scaled Jacobian over every run.

Landmark errors are distances from the carried landmark nodes to the true landmarks (skin
points at their anatomical definitions, `facemodel.synthetic.landmarks`) with the landmarks
given to the registration (the landmark nodes are then moved onto them: a check of the
mechanism, not of the carrying); at `--held-out` resolutions also with the lip landmarks, then
the others, left out of the registration (each measured when not given), and at
`--surfaces-alone` resolutions from a registration without any landmark. Those two passes run
with the landmarks the case does not give located on the skin by their anatomical definitions
(`registration.landmark_search`, "after") and, at `--before` resolutions, also without that
search (the registration's carrying alone, "before"); the summary gives per landmark the
median / max error and the count within 1.5 mm.

Usage: python bench/registration.py [--heads N] [--resolutions coarse,standard]
                                    [--held-out coarse] [--surfaces-alone coarse] [--before coarse]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

# `python bench/registration.py` puts bench/ first on sys.path, where this very file would
# shadow the `registration` package: drop the script's folder, put the repository root first
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import generic_mesh  # noqa: E402
from facemodel import head_geometry as hg  # noqa: E402
from facemodel import synthetic  # noqa: E402
from registration import MatchOptions, mesh_match_and_repair  # noqa: E402
from registration.quality import min_scaled_jacobian  # noqa: E402

EXTREMES = {
    "class_III": hg.HeadShape(maxilla_ap=-4.0, mandible_ap=7.0, chin_projection=2.0),
    "class_II": hg.HeadShape(maxilla_ap=3.0, mandible_ap=-7.0, chin_projection=-3.0, soft_tissue=1.15),
    "asymmetric": hg.HeadShape(asymmetry=2.5, width=1.06, mandible_ap=3.0, height=0.94),
}


def heads(n: int):
    """Up to three extreme shapes (when n > 7) then random synthetic heads, n in all."""
    n_extreme = min(len(EXTREMES), max(0, n - 7))
    for name, shape in list(EXTREMES.items())[:n_extreme]:
        skin = synthetic.skin_surface(shape, synthetic.SCAN_SIZE, zoom=synthetic.SCAN_ZOOM)
        yield name, synthetic.SyntheticHead(
            seed=-1, shape=shape, skin=skin, bones=synthetic.bone_surfaces(shape),
            teeth={}, landmarks=synthetic.landmarks(shape, skin))
    for seed in range(n - n_extreme):
        yield f"seed_{seed}", synthetic.synthetic_head(seed)


def landmark_errors(generic, patient, head) -> dict:
    """Distance of each carried landmark node to the head's true landmark (a skin point)."""
    return {name: float(np.linalg.norm(patient.nodes[node] - np.asarray(head.landmarks[name])))
            for name, node in generic.landmarks.items()}


# landmarks held out of the registration in turn, to measure how well the rest carries them
HELD_OUT = (("Ls", "Stms", "Stmi", "Li", "ChL", "ChR"), ("Prn", "Sn", "Pog", "Me"))


def held_out_errors(generic, head, options=None) -> dict:
    """Error of every landmark when its group is not given (registered from the others)."""
    out = {}
    for group in HELD_OUT:
        given = {k: v for k, v in head.landmarks.items() if k not in group}
        patient, _ = mesh_match_and_repair(generic, head.skin, head.bones, given, cache=False, options=options)
        e = landmark_errors(generic, patient, head)
        out.update({k: e[k] for k in group})
    return out


NO_SEARCH = MatchOptions(locate_landmarks=False)


def run_one(generic, head, surfaces_alone: bool, held_out: bool, before: bool) -> dict:
    t = time.perf_counter()
    patient, rep = mesh_match_and_repair(generic, head.skin, head.bones, head.landmarks, cache=False)
    wall = time.perf_counter() - t
    lm_err = landmark_errors(generic, patient, head)
    q = min_scaled_jacobian(patient.nodes, patient.hexes)
    out = {"wall_s": wall, "rep": rep, "min_sj": float(q.min()), "n_inverted": int((q <= 0).sum()),
           "lm_max": max(lm_err.values()), "lm_worst": max(lm_err, key=lm_err.get)}
    # lips across the mouth slit, before / after the lip separation stage (deepest crossing of
    # either lip into the other) and the smallest gap left
    lips = rep.get("lip_separation") or {}
    crossed = lambda d: max(d.get("lower_in_upper_mm", 0.0), d.get("upper_in_lower_mm", 0.0))
    out.update(lip_before=crossed(lips.get("before", {})), lip_after=crossed(lips.get("after", {})),
               lip_gap=float((lips.get("after") or {}).get("min_gap_mm") or 0.0))
    if surfaces_alone:  # the same head without its landmarks: what the surfaces alone carry
        p2, rep2 = mesh_match_and_repair(generic, head.skin, head.bones, None, cache=False)
        e2 = landmark_errors(generic, p2, head)
        out.update(free_lm=e2, free_skin_mean=rep2["fit"]["skin"]["mean_mm"],
                   free_min_sj=float(min_scaled_jacobian(p2.nodes, p2.hexes).min()))
        if before:
            p3, _ = mesh_match_and_repair(generic, head.skin, head.bones, None, cache=False, options=NO_SEARCH)
            out["free_lm_before"] = landmark_errors(generic, p3, head)
    if held_out:
        out["held_lm"] = held_out_errors(generic, head)
        if before:
            out["held_lm_before"] = held_out_errors(generic, head, NO_SEARCH)
    return out


def landmark_table(label: str, errors: list[dict]) -> str:
    """Per landmark median / max error (mm) and count within 1.5 mm over the heads."""
    names = list(errors[0])
    within = sum(v < 1.5 for e in errors for v in e.values())
    return (f"{label}: within 1.5 mm {within}/{len(errors) * len(names)}, heads with all within "
            f"{sum(max(e.values()) < 1.5 for e in errors)}/{len(errors)}, max "
            f"{max(max(e.values()) for e in errors):.2f} mm; per landmark median/max (within): "
            + ", ".join(f"{k} {np.median([e[k] for e in errors]):.1f}/{max(e[k] for e in errors):.1f} "
                        f"({sum(e[k] < 1.5 for e in errors)})" for k in names))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heads", type=int, default=10)
    ap.add_argument("--resolutions", default="coarse,standard")
    ap.add_argument("--held-out", default="coarse",
                    help="resolutions also registered twice with a group of landmarks held out "
                         f"({' / '.join(', '.join(g) for g in HELD_OUT)}), the held-out ones "
                         "measured; 'none' to skip")
    ap.add_argument("--surfaces-alone", default="coarse",
                    help="resolutions also registered without any landmark; 'none' to skip")
    ap.add_argument("--before", default="coarse",
                    help="resolutions where the held-out and landmark-free passes also run without "
                         "the anatomical landmark search (the carrying alone); 'none' to skip")
    args = ap.parse_args()
    free_res = set(args.surfaces_alone.split(","))
    held_res = set(args.held_out.split(","))
    before_res = set(args.before.split(","))
    resolutions = args.resolutions.split(",")
    generics = {r: generic_mesh.load(r) for r in resolutions}
    for r, g in generics.items():
        print(f"generic {r}: {g.n_nodes} nodes, {g.n_elements} hexahedra")
    results = {r: [] for r in resolutions}
    for name, head in heads(args.heads):
        s = head.shape
        print(f"\n{name}: maxilla_ap {s.maxilla_ap:+.1f} mandible_ap {s.mandible_ap:+.1f} chin {s.chin_projection:+.1f} "
              f"asym {s.asymmetry:+.1f} width {s.width:.2f} height {s.height:.2f}")
        for r in resolutions:
            res = run_one(generics[r], head, r in free_res, r in held_res, r in before_res)
            rep, fit, t = res["rep"], res["rep"]["fit"], res["rep"]["time"]
            results[r].append(res)
            print(f"  {r:8s} skin {fit['skin']['mean_mm']:.3f}/{fit['skin']['p95_mm']:.3f}/{fit['skin']['max_mm']:.2f} mm "
                  f"(patient->mesh {fit['skin_patient_to_mesh']['mean_mm']:.3f}) bone {fit['bone']['mean_mm']:.3f} mm  "
                  f"repaired {rep['repair']['elements_needing_repair']:3d} (inverted {rep['repair']['elements_inverted_before']:3d})  "
                  f"min SJ {res['min_sj']:.3f}  landmarks max {res['lm_max']:.2f} mm ({res['lm_worst']})  "
                  f"lips crossed {res['lip_before']:.2f} -> {res['lip_after']:.2f} mm (gap {res['lip_gap']:+.2f})")
            if "held_lm" in res:
                e = res["held_lm"]
                print("           held out: " + ", ".join(f"{k} {v:.2f}" for k, v in e.items()) + " mm")
            if "held_lm_before" in res:
                e = res["held_lm_before"]
                print("           held out, before: " + ", ".join(f"{k} {v:.2f}" for k, v in e.items()) + " mm")
            if "free_lm" in res:
                e = res["free_lm"]
                print(f"           without landmarks (skin {res['free_skin_mean']:.3f} mm, min SJ "
                      f"{res['free_min_sj']:.3f}): " + ", ".join(f"{k} {v:.2f}" for k, v in e.items()) + " mm")
            if "free_lm_before" in res:
                e = res["free_lm_before"]
                print("           without landmarks, before: " + ", ".join(f"{k} {v:.2f}" for k, v in e.items()) + " mm")
            print(f"           time {res['wall_s']:.1f} s: " + ", ".join(
                f"{k[:-2]} {v:.2f}" for k, v in t.items() if k.endswith("_s") and k != "total_s"))
    print("\nsummary (targets: skin mean < 0.3, p95 < 1.0, bone mean < 0.5 mm, no inverted element, "
          "min SJ >= 0.2, landmarks within 1.5 mm, standard < 30 s)")
    for r in resolutions:
        rs = results[r]
        sm = [x["rep"]["fit"]["skin"]["mean_mm"] for x in rs]
        sp = [x["rep"]["fit"]["skin"]["p95_mm"] for x in rs]
        bm = [x["rep"]["fit"]["bone"]["mean_mm"] for x in rs]
        print(f"  {r:8s} heads {len(rs)}: skin mean max {max(sm):.3f}, p95 max {max(sp):.3f}, bone mean max {max(bm):.3f}, "
              f"inverted {sum(x['n_inverted'] for x in rs)}, min SJ {min(x['min_sj'] for x in rs):.3f}, "
              f"landmarks max {max(x['lm_max'] for x in rs):.2f}, "
              f"lips crossed max {max(x['lip_before'] for x in rs):.2f} -> {max(x['lip_after'] for x in rs):.2f} mm "
              f"(min gap {min(x['lip_gap'] for x in rs):.2f}), "
              f"time mean {np.mean([x['wall_s'] for x in rs]):.1f} s max {max(x['wall_s'] for x in rs):.1f} s")
        for key, label in (("held_lm_before", "held-out landmarks, before"), ("held_lm", "held-out landmarks, after"),
                           ("free_lm_before", "without landmarks, before"), ("free_lm", "without landmarks, after")):
            errs = [x[key] for x in rs if key in x]
            if errs:
                print(f"  {r:8s} " + landmark_table(label, errs))
        if any("free_min_sj" in x for x in rs):
            print(f"  {r:8s} without landmarks: min SJ {min(x['free_min_sj'] for x in rs if 'free_min_sj' in x):.3f}, "
                  f"skin mean max {max(x['free_skin_mean'] for x in rs if 'free_skin_mean' in x):.3f} mm")
    key = "standard" if "standard" in results else resolutions[-1]
    rs = results[key]
    print(f"register_s={max(x['wall_s'] for x in rs):.2f} "
          f"skin_mean_mm={max(x['rep']['fit']['skin']['mean_mm'] for x in rs):.3f} "
          f"skin_p95_mm={max(x['rep']['fit']['skin']['p95_mm'] for x in rs):.3f} "
          f"min_scaled_jacobian={min(x['min_sj'] for r in resolutions for x in results[r]):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
