"""Contact overhead on the generic face: the same solve with and without contact, two cases.

1. The surgical prediction (`--case surgical`): the demo's bimaxillary plan (Le Fort I
   advancement, mandibular setback, genioplasty, resting orbicularis oris / mentalis tone
   0.05) solved on the registered demo head at the chosen resolution with
   `planner.pipeline.solve_plan`, the registration cached first; with contact the arches
   are first cleared of the lips (`facemodel.teeth.clear_teeth`), which is timed too.
2. The worst case for contact (`--case orbicularis`): an orbicularis oris activation
   (a = 0.1: the lips purse and press onto each other and the teeth) on the generic face
   with `facemodel.simulation.simulate`.
Each is solved with lip-lip and lip-teeth contact and without, in this process (the
surgical case once, the orbicularis case `--repeat` times alternately, default 5, the median
time counting: on a shared machine single timings move by 10-20 %; both paths' compiled code warmed up first; the warm-up also builds the generic teeth's
signed-distance grids, which later solves of the process share, `SignedDistanceGrid.shared`,
while the registered head's teeth are built within the surgical solve), and the script prints
the wall-clock times, Newton iterations, the per-iteration cost and the relative overhead of
contact.
With --images DIR it also renders the orbicularis oris activation (lips pursed and
protruded, pressed on each other and the teeth) as profile and frontal views of the skin with
the displacement magnitude. (The 8 mm mandible closure has its own script, `bench/closure.py`:
the generic face is in occlusion, so it closes from the mouth opened about the hinge axis.)
Usage: python bench/contact.py [--resolution standard|coarse|fine] [--case both|surgical|orbicularis]
       [--repeat N] [--images DIR]
Lines: surgical_contact_overhead_pct=<x>, then last contact_overhead_pct=<x> (orbicularis, the
worst case).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# `python bench/contact.py` puts bench/ first on sys.path, where bench/registration.py would
# shadow the registration package: drop it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


def _motion(dy=-3.0, dz=4.0):
    T = np.eye(4)
    T[:3, 3] = [0.0, dy, dz]
    return T


def _images(model, folder):
    """Profile and frontal renders of the orbicularis oris check (off-screen pyvista)."""
    from pathlib import Path

    import pyvista as pv

    from facemodel.simulation import lip_penetrations, simulate
    pv.OFF_SCREEN = True
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    cases = {"orbicularis_oris": ({}, {"orbicularis_oris": 0.1})}
    quads = np.asarray(model.facet_sets["skin"])
    faces = np.hstack([np.full((len(quads), 1), 4), quads]).ravel()
    from solver.errors import SolveFailed
    for name, (motions, acts) in cases.items():
        try:
            res = simulate(model, motions, acts)
        except SolveFailed as exc:
            print(f"{name}: not solved ({exc})")
            continue
        pen = lip_penetrations(model, res.x, motions=motions)
        for view in ("yz", "xz"):
            pl = pv.Plotter(off_screen=True, window_size=(900, 900))
            ref = pv.PolyData(model.nodes, faces)
            pl.add_mesh(ref, style="wireframe", color="grey", opacity=0.25)
            cur = pv.PolyData(res.x, faces)
            cur["displacement (mm)"] = np.linalg.norm(res.displacement, axis=1)
            pl.add_mesh(cur, scalars="displacement (mm)", cmap="viridis")
            lips = np.unique(np.vstack([model.facet_sets["lip_upper_contact"],
                                        model.facet_sets["lip_lower_contact"]]))
            pl.add_points(res.x[lips], color="red", point_size=6)
            if view == "yz":
                pl.view_yz()
            else:
                pl.view_xz()
            pl.add_text(f"{name}: deepest lip/teeth penetration "
                        f"{max(pen.values()):.3f} mm", font_size=10)
            path = out / f"{name}_{'profile' if view == 'yz' else 'front'}.png"
            pl.screenshot(str(path))
            pl.close()
            print(f"wrote {path}")


def _per_iteration(res) -> str:
    tm = res.info["timings"]
    its = max(res.iterations, 1)
    return (f"  per iteration: {(tm['assembly'] + tm['solve']) / its:.3f} s "
            f"(assembly {tm['assembly'] / its:.3f}, linear solve {tm['solve'] / its:.3f}); "
            f"{res.newton.factorizations} factorisations, "
            f"{res.newton.krylov_iterations / its:.1f} CG iterations per iteration")


def surgical(resolution: str) -> float:
    """The demo plan's prediction solve with and without contact; the overhead in %."""
    import facemodel.simulation as fs
    from planner.case import load_case
    from planner.errors import SolveError
    from planner.pipeline import DEMO_PLAN, Progress, register_case, solve_plan, write_demo_case
    from planner.plan import load_plan

    results = []
    original = fs.simulate

    def keep(*args, **kwargs):            # the solver statistics of each solve
        res = original(*args, **kwargs)
        results.append(res)
        return res

    times = {}
    with tempfile.TemporaryDirectory(prefix="faceplan-contact-") as tmp:
        for contact in (False, True):
            plan = dict(DEMO_PLAN, muscles={"orbicularis_oris": 0.05, "mentalis": 0.05},
                        model={"resolution": resolution, "contact": contact})
            case = load_case(write_demo_case(Path(tmp) / f"case_{contact}", plan))
            patient, _ = register_case(case, resolution, Progress(echo=False))
            plan_obj = load_plan(case.require_plan())
            fs.simulate = keep
            t0 = time.perf_counter()
            try:
                solve_plan(patient, plan_obj, case.bones)
            except SolveError as exc:
                print(f"surgical, contact={contact}: not solved after "
                      f"{time.perf_counter() - t0:.1f} s ({exc})")
                return float("nan")
            finally:
                fs.simulate = original
            times[contact] = time.perf_counter() - t0
            res = results[-1]
            print(f"surgical, contact={contact}: {times[contact]:.2f} s, {res.iterations} Newton "
                  f"iterations, {res.steps} steps, {res.info['cutbacks']} cut-backs, penetration "
                  f"{ {k: round(v, 3) for k, v in res.info.get('penetration_mm', {}).items()} }")
            print(_per_iteration(res))
    return 100.0 * (times[True] - times[False]) / times[False]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", default="standard")
    ap.add_argument("--images", default=None, help="folder for the face images (optional)")
    ap.add_argument("--images-only", action="store_true", help="only render the face checks")
    ap.add_argument("--case", default="both", choices=("both", "surgical", "orbicularis"))
    ap.add_argument("--repeat", type=int, default=5,
                    help="orbicularis solves per variant (median time; default 5)")
    args = ap.parse_args(argv)
    import generic_mesh
    from facemodel.simulation import simulate

    model = generic_mesh.load(resolution=args.resolution)
    if args.images:
        _images(model, args.images)
        if args.images_only:
            return
    motions, activations = {}, {"orbicularis_oris": 0.1}
    print(f"face '{args.resolution}': {len(model.nodes)} nodes, {len(model.hexes)} hexes")
    # JIT warm-up of both paths (numba's compiled-code cache is loaded once per process)
    for contact in (False, True):
        simulate(model, {"mandible": _motion(0.0, 0.5)}, contact=contact, n_steps=1)
    if args.case in ("both", "surgical"):
        print(f"surgical_contact_overhead_pct={surgical(args.resolution):.1f}")
        if args.case == "surgical":
            return 0
    from solver.errors import SolveFailed

    times = {False: [], True: []}
    results = {}
    for _ in range(max(args.repeat, 1)):      # alternately, so that a busy spell hits both
        for contact in (False, True):
            t0 = time.perf_counter()
            try:
                results[contact] = simulate(model, motions, activations, contact=contact)
            except SolveFailed as exc:
                print(f"contact={contact}: not solved after {time.perf_counter() - t0:.1f} s "
                      f"({exc})")
                print("contact_overhead_pct=nan")
                return 3
            times[contact].append(time.perf_counter() - t0)
    runs = {c: ", ".join(f"{t:.2f}" for t in ts) for c, ts in times.items()}
    times = {c: float(np.median(ts)) for c, ts in times.items()}
    for contact in (False, True):
        res = results[contact]
        term_time = 0.0
        if contact:
            x = res.x
            for name, term in res.terms.items():
                t1 = time.perf_counter()
                term.assemble(x, 1.0)
                term_time += time.perf_counter() - t1
        print(f"orbicularis, contact={contact}: {times[contact]:.2f} s (median of "
              f"{runs[contact]}), {res.iterations} Newton iterations, {res.steps} steps, "
              f"penetration { {k: round(v, 3) for k, v in res.info.get('penetration_mm', {}).items()} }")
        print(_per_iteration(res))
        if contact:
            print(f"  one evaluation of all contact terms: {1e3 * term_time:.1f} ms "
                  f"(x {res.iterations} iterations ~ {term_time * res.iterations:.2f} s)")
    pct = 100.0 * (times[True] - times[False]) / times[False]
    print(f"contact_overhead_pct={pct:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
