"""Benchmark: the skin change a withheld effect's value reaches against its drawn target.

`faceplan synth` sets swelling, posture and tone from a skin-change target drawn from the
published range (`planner.commands.synth.SKIN_CHANGE_MM`), measured where the post-op scan
sees the skin, in the effect's regions. For `--count` seeds from `--seed` and each of these
effects this makes the case through the command's own code (`make_case`, the truth at
`--truth-resolution`, lip contact on unless `--no-contact`) and prints one line per case: the
value, the target, the change reached (max and RMS, mm), whether it lies in the range, the
secant corrections and the reductions after a failed solve. The summary line counts the
changes in their range.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--count", type=int, default=6)
    ap.add_argument("--effects", default="swelling,gravity,muscle_tone")
    ap.add_argument("--truth-resolution", default="coarse", choices=("coarse", "standard"))
    ap.add_argument("--no-contact", action="store_true")
    args = ap.parse_args()

    from planner.commands import synth
    from planner.errors import SolveError

    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    for e in effects:
        if e not in synth.SKIN_CHANGE_MM:
            ap.error(f"{e}: not set from a skin-change target (those: {', '.join(synth.SKIN_CHANGE_MM)})")
    inside = total = 0
    t_all = time.perf_counter()
    print(f"{'effect':12s} {'seed':>5s} {'value':>8s} {'target':>7s} {'max':>6s} {'rms':>6s} in-range  notes")
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-targets-") as tmp:
        for effect in effects:
            lo, hi = synth.SKIN_CHANGE_MM[effect]
            for seed in range(args.seed, args.seed + args.count):
                opts = {"withheld": (effect, None), "truth_resolution": args.truth_resolution,
                        "surface_size": 1.0, "mesher": "sphere", "ct": False, "ct_spacing": 1.0,
                        "contact": not args.no_contact}
                t0 = time.perf_counter()
                try:
                    r = synth.make_case(str(Path(tmp) / f"{effect}_{seed}"), seed, opts)
                except SolveError as exc:
                    print(f"{effect:12s} {seed:5d} truth failed: {exc}", flush=True)
                    continue
                ch = r["effect_skin_change_mm"]
                ok = lo <= ch["max_mm"] <= hi
                inside += ok
                total += 1
                notes = []
                for c in r["value_corrections"]:
                    notes.append(f"corrected {c['from']} -> {c['to']}")
                for c in r["value_reductions"]:
                    notes.append(f"reduced {c.get('from')} -> {c.get('to')}")
                target = ch["target_max_mm"]
                print(f"{effect:12s} {seed:5d} {r['value'][effect]:8.4f} "
                      f"{(target if target is not None else float('nan')):7.3f} {ch['max_mm']:6.3f} "
                      f"{ch['rms_mm']:6.3f} {'yes' if ok else 'no':>8s}  {'; '.join(notes)} "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"in_range={inside}/{total} total_s={time.perf_counter() - t_all:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
