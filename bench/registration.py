"""Benchmark of Mesh-Match-and-Repair on synthetic heads whose truth is known (issue 4).

Ten heads: seven drawn by `facemodel.synthetic.random_shape` and three extremes built on
purpose (strong class III, strong class II, asymmetric lower face), each registered at coarse
and standard resolution from its skin, bone segments and landmarks. Prints one line per run
(fit errors, quality, repaired elements, landmark errors, time per stage) and a summary with
the targets; the last line is
    register_s=<t> skin_mean_mm=<x> skin_p95_mm=<x> min_scaled_jacobian=<x>
with worst cases over the heads: the longest standard-resolution registration, the largest
per-head skin mean and 95th percentile, the smallest scaled Jacobian over every run.

Usage: python bench/registration.py [--heads N] [--resolutions coarse,standard]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import generic_mesh  # noqa: E402
from facemodel import head_geometry as hg  # noqa: E402
from facemodel import synthetic  # noqa: E402
from registration import mesh_match_and_repair  # noqa: E402
from registration.quality import min_scaled_jacobian  # noqa: E402
from registration.surface import TargetSurface  # noqa: E402

EXTREMES = {
    "class_III": hg.HeadShape(maxilla_ap=-4.0, mandible_ap=7.0, chin_projection=2.0),
    "class_II": hg.HeadShape(maxilla_ap=3.0, mandible_ap=-7.0, chin_projection=-3.0, soft_tissue=1.15),
    "asymmetric": hg.HeadShape(asymmetry=2.5, width=1.06, mandible_ap=3.0, height=0.94),
}


def heads(n: int):
    """Up to three extreme shapes (when n > 7) then random synthetic heads, n in all."""
    n_extreme = min(len(EXTREMES), max(0, n - 7))
    for name, shape in list(EXTREMES.items())[:n_extreme]:
        yield name, synthetic.SyntheticHead(
            seed=-1, shape=shape, skin=synthetic.skin_surface(shape), bones=synthetic.bone_surfaces(shape),
            teeth={}, landmarks=synthetic.landmarks(shape))
    for seed in range(n - n_extreme):
        yield f"seed_{seed}", synthetic.synthetic_head(seed)


def run_one(generic, head) -> dict:
    t = time.perf_counter()
    patient, rep = mesh_match_and_repair(generic, head.skin, head.bones, head.landmarks, cache=False)
    wall = time.perf_counter() - t
    skin = TargetSurface(np.asarray(head.skin.vertices), np.asarray(head.skin.faces))
    lm_err, lm_beyond = {}, {}
    for name, node in generic.landmarks.items():
        truth = np.asarray(head.landmarks[name])
        err = float(np.linalg.norm(patient.nodes[node] - truth))
        off = float(skin.closest(truth[None]).distance[0])  # the truth's own distance to the skin
        lm_err[name], lm_beyond[name] = err, max(err - off, 0.0)
    q = min_scaled_jacobian(patient.nodes, patient.hexes)
    return {"wall_s": wall, "rep": rep, "min_sj": float(q.min()), "n_inverted": int((q <= 0).sum()),
            "lm_max": max(lm_err.values()), "lm_beyond_max": max(lm_beyond.values()),
            "lm_worst": max(lm_err, key=lm_err.get)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heads", type=int, default=10)
    ap.add_argument("--resolutions", default="coarse,standard")
    args = ap.parse_args()
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
            res = run_one(generics[r], head)
            rep, fit, t = res["rep"], res["rep"]["fit"], res["rep"]["time"]
            results[r].append(res)
            print(f"  {r:8s} skin {fit['skin']['mean_mm']:.3f}/{fit['skin']['p95_mm']:.3f}/{fit['skin']['max_mm']:.2f} mm "
                  f"(patient->mesh {fit['skin_patient_to_mesh']['mean_mm']:.3f}) bone {fit['bone']['mean_mm']:.3f} mm  "
                  f"repaired {rep['repair']['elements_needing_repair']:3d} (inverted {rep['repair']['elements_inverted_before']:3d})  "
                  f"min SJ {res['min_sj']:.3f}  landmarks max {res['lm_max']:.2f} mm ({res['lm_worst']}; "
                  f"beyond truth-to-skin {res['lm_beyond_max']:.2f})")
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
              f"landmarks max {max(x['lm_max'] for x in rs):.2f} (beyond truth-to-skin {max(x['lm_beyond_max'] for x in rs):.2f}), "
              f"time mean {np.mean([x['wall_s'] for x in rs]):.1f} s max {max(x['wall_s'] for x in rs):.1f} s")
    key = "standard" if "standard" in results else resolutions[-1]
    rs = results[key]
    print(f"register_s={max(x['wall_s'] for x in rs):.2f} "
          f"skin_mean_mm={max(x['rep']['fit']['skin']['mean_mm'] for x in rs):.3f} "
          f"skin_p95_mm={max(x['rep']['fit']['skin']['p95_mm'] for x in rs):.3f} "
          f"min_scaled_jacobian={min(x['min_sj'] for r in resolutions for x in results[r]):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
