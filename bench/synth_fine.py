"""Benchmark: one synthetic case with its post-op scan, stage by stage, at a truth resolution.

Makes the case folder of `faceplan synth` for `--seed` (head, plan, case.yaml) and its post-op
scan with the withheld effect `--effect` (`planner.commands.synth.make_postop`, the code the
command runs), at `--truth-resolution` (default fine: the truth model registered at the
standard resolution and carried to the fine mesh, `planner.commands.synth.prolonged_patient`).
Prints the time of every stage (head and case folder, registration, carrying to the finer
mesh, each solve with its Newton steps, iterations, cut-backs and factorisations, the
sensitivity of a target-set effect, the scan) and the load average of the machine before and
after (the machine is shared: the seconds depend on it, the counts do not). A truth solve that
fails, or a case still running after `--max-minutes`, is reported with the stages done and the
last Newton iteration logged (its load step and load fraction) instead of the end-to-end line.
`--no-blowup-guard` makes the peer run with the Newton solver's blow-up guard off,
`--no-osteotomy-bridges` the one with the tissue over the osteotomies tied to both segments
(`facemodel.attachments.BRIDGE_WIDTH_MM` 0), `--release-freed-memory` the one with freed arrays
returned to the kernel (`solver.memory.KEEP_FREED_MEMORY` False), `--teeth-increment-fraction
F` the one with another floor of the contact nodes' increment limit
(`FaceSolverSettings.teeth_increment_fraction`). The last line gives the process's peak
resident memory.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import sys
import tempfile
import time
from pathlib import Path

from _peers import add_teeth_increment_fraction, apply_teeth_increment_fraction

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


class _Echo(dict):
    """The stage times, each also printed to stderr as it is recorded."""

    def __setitem__(self, key, value):
        super().__setitem__(key, value)
        if isinstance(value, float):
            print(f"  {key}: {value:.1f} s (load {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)


class _OutOfTime(BaseException):
    """--max-minutes reached (a BaseException: no solver's error handling takes it)."""


def _out_of_time(signum, frame):
    raise _OutOfTime()


def _split(s) -> str:
    """A solve's time split (assembly with contact, linear solves), when recorded."""
    if s.get("newton_s") is None:
        return ""
    return (f"; Newton {s['newton_s']:.1f} s: assembly {s['assembly_s']:.1f} s, linear solves "
            f"{s['linear_s']:.1f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--effect", default="gravity", help="withheld effect (default gravity)")
    parser.add_argument("--truth-resolution", default="fine", choices=("coarse", "standard", "fine"))
    parser.add_argument("--no-contact", action="store_true", help="lip contact off in the truth model")
    parser.add_argument("--no-blowup-guard", action="store_true",
                        help="the peer run: the Newton blow-up guard off "
                             "(FaceSolverSettings.blowup_factor None)")
    parser.add_argument("--no-osteotomy-bridges", action="store_true",
                        help="the peer run: no osteotomy bridges (the attachments tied on both "
                             "sides of every cut)")
    parser.add_argument("--release-freed-memory", action="store_true",
                        help="the peer run: freed arrays go back to the kernel (solver.memory off)")
    add_teeth_increment_fraction(parser)
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop the case after this many minutes and report how far it got")
    args = parser.parse_args()

    from facemodel.synthetic import synthetic_head
    from planner.commands.synth import FOLLOW_UP_MONTHS, _rng, make_postop, parse_withheld, write_case
    from planner.errors import SolveError

    if args.no_blowup_guard:
        import dataclasses

        import facemodel.simulation as simulation

        simulation.FACE_SOLVER = dataclasses.replace(simulation.FACE_SOLVER, blowup_factor=None)

    if args.no_osteotomy_bridges:
        import facemodel.attachments as attachments

        attachments.BRIDGE_WIDTH_MM = 0.0

    if args.release_freed_memory:
        import solver.memory

        solver.memory.KEEP_FREED_MEMORY = False

    apply_teeth_increment_fraction(args.teeth_increment_fraction)

    load0 = os.getloadavg()
    stages = {}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-synth-fine-") as tmp:
        folder = Path(tmp) / f"synth_{args.seed:04d}"
        folder.mkdir()
        t0 = time.perf_counter()
        fu = float(_rng(args.seed + 10**6).uniform(*FOLLOW_UP_MONTHS))
        head = synthetic_head(args.seed)
        write_case(folder, head, follow_up_months=fu)
        stages["head_and_case_s"] = time.perf_counter() - t0
        timings = _Echo()
        last = [None]

        def newton(line):
            if " it " in line:
                last[0] = line.split("] ", 1)[-1]
                print("    " + last[0], file=sys.stderr, flush=True)

        if args.max_minutes:
            signal.signal(signal.SIGALRM, _out_of_time)
            signal.alarm(max(1, int(round(60 * args.max_minutes))))
        record, failure = None, None
        try:
            record = make_postop(str(folder), args.seed, parse_withheld(args.effect), args.truth_resolution,
                                 contact=not args.no_contact, timings=timings, log=newton)
        except SolveError as exc:
            failure = f"failed: {exc}"
        except _OutOfTime:
            failure = f"stopped after {args.max_minutes:g} min (--max-minutes)"
        finally:
            signal.alarm(0)
    total = time.perf_counter() - t_all
    solves = timings.pop("solves", [])
    stages.update(timings)
    if record is None:
        print(f"one synthetic case, seed {args.seed}, withheld {args.effect}, truth {args.truth_resolution}, "
              f"lip contact {'off' if args.no_contact else 'on'}{_peer(args)}: {failure}")
        _print_stages(load0, stages, "time until stopped", total, solves)
        print(f"  last Newton iteration: {last[0]}")
        return 3
    print(f"one synthetic case, seed {args.seed}, withheld {args.effect} -> {record['effect']}="
          f"{json.dumps(record['value'])}, truth {args.truth_resolution} (registered at "
          f"{record['perturbation'].get('registered_at')}), lip contact "
          f"{'off' if args.no_contact else 'on'}{_peer(args)}")
    _print_stages(load0, stages, "total (end to end)", total, solves)
    print(f"  effect skin change (max, mm): {record['effect_skin_change_mm']['max_mm']}")
    # ru_maxrss is in kB on Linux
    print(f"  peak resident memory: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0


def _peer(args) -> str:
    """What a peer run leaves out, for the header line."""
    off = [name for name, flag in (("blow-up guard", args.no_blowup_guard),
                                   ("osteotomy bridges", args.no_osteotomy_bridges),
                                   ("freed-memory reuse", args.release_freed_memory)) if flag]
    out = "".join(f", {name} off" for name in off)
    if args.teeth_increment_fraction is not None:
        out += f", teeth increment fraction {args.teeth_increment_fraction:g}"
    return out


def _print_stages(load0, stages: dict, total_label: str, total: float, solves: list) -> None:
    """The machine's load, the time of each stage, the total and each solve's Newton figures."""
    print(f"load average before {load0[0]:.1f}, after {os.getloadavg()[0]:.1f} (2 cores)")
    for k, v in stages.items():
        print(f"  {k:28s} {v:7.1f} s")
    print(f"  {total_label:28s} {total:7.1f} s")
    for s in solves:
        print(f"  solve {s['solve']:7s} {s['nodes']} nodes: {s['steps']} steps, {s['iterations']} Newton "
              f"iterations, {s['cutbacks']} cut-backs, {s['factorizations']} factorisations"
              + _split(s))


if __name__ == "__main__":
    sys.exit(main())
