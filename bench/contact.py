"""Contact overhead on the generic face: the same surgical solve with and without contact.

Solves a mandibular set-back/closure (the mandible moved up and back, lips pressed together
and onto the teeth) on the generic face with `facemodel.simulation.simulate`, once with lip-lip
and lip-teeth contact and once without, and reports the wall-clock times, Newton iterations,
time spent in the contact terms (search + assembly) and the relative overhead.
Usage: python bench/contact.py [--resolution standard|coarse|fine]
Last line: contact_overhead_pct=<x>
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def _motion(dy=-3.0, dz=4.0):
    T = np.eye(4)
    T[:3, 3] = [0.0, dy, dz]
    return T


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", default="standard")
    args = ap.parse_args(argv)
    import generic_mesh
    from facemodel.simulation import simulate

    model = generic_mesh.load(resolution=args.resolution)
    motions = {"mandible": _motion()}
    print(f"face '{args.resolution}': {len(model.nodes)} nodes, {len(model.hexes)} hexes")
    simulate(model, {"mandible": _motion(0.0, 0.5)}, contact=False, n_steps=1)   # JIT warm-up
    times = {}
    for contact in (False, True):
        t0 = time.perf_counter()
        res = simulate(model, motions, contact=contact)
        times[contact] = time.perf_counter() - t0
        term_time = 0.0
        if contact:
            x = res.x
            for name, term in res.terms.items():
                t1 = time.perf_counter()
                term.assemble(x, 1.0)
                term_time += time.perf_counter() - t1
        print(f"contact={contact}: {times[contact]:.2f} s, {res.iterations} Newton iterations, "
              f"{res.steps} steps, penetration {res.info.get('penetration_mm', {})}")
        if contact:
            print(f"  one evaluation of all contact terms: {1e3 * term_time:.1f} ms "
                  f"(x {res.iterations} iterations ~ {term_time * res.iterations:.2f} s)")
    pct = 100.0 * (times[True] - times[False]) / times[False]
    print(f"contact_overhead_pct={pct:.1f}")


if __name__ == "__main__":
    main()
