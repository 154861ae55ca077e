"""faceplan's FE core vs. FElupe + PARDISO on the same nearly incompressible Yeoh cube.

Problem (issue 2): a 20 x 20 x 20 hexahedral cube of 20 mm, Yeoh C10 = 2.5, C20 = 1.175 kPa,
K = 2500 kPa with U = K/2 (J - 1)^2 (FElupe's `NearlyIncompressible` volumetric function), the
Q1/P0 mean-dilatation formulation in both codes (FElupe: `FieldsMixed(n=3)` with piecewise
constant pressure and dilatation + `NearlyIncompressible`), face x = 0 clamped, face x = 20
pulled 6 mm in x (free laterally) in 4 equal steps, PARDISO as FElupe's linear solver (in
symmetric indefinite mode, mtype -2, like faceplan's: here `pypardiso.spsolve`'s default
unsymmetric LU returned a singular first update, |dx| ~ 1e11, and FElupe stopped; pass
`--felupe-pardiso unsymmetric` to try it). (With
the pulled face also held laterally FElupe's Newton produces NaN in the first step at this
mesh size: it has no cut-back; faceplan solves that variant too.) Prints
both wall times (set-up included; both codes warmed up first on a 2x2x2 cube, so that library
imports and numba cache loading are not timed; the codes run alternately `--repeat` times,
default 3, and the fastest run of each is compared, every run being printed), the ratio and the largest displacement difference relative
to the largest displacement; then a DOF-scaling table of faceplan's solver (each size in a
fresh process: assembly s per tangent, numerical factorisation s of the symmetric indefinite
LDL^T (double) and of the single-precision Cholesky preconditioner ("SP chol"), Newton
iterations and factorisations of the 4-step pull, peak resident memory). The last line is
`speedup=<x> max_rel_diff=<y> faceplan_s=<t> felupe_s=<t>`.

Both codes run in the same process with the same MKL threading (`--threads`, default 1: on the
shared, loaded 2-core machine PARDISO factorises the 28k-DOF tangent in ~1.6 s on one thread
against 2.4-2.7 s on two, and substitutes in 0.05 s against 0.17 s; `--threads 0` leaves MKL's
default). `--strategy` picks faceplan's Newton linear strategy: "auto" (`newton_solve`'s
default: lagged from 20k unknowns on, so lagged here), "exact" (a symmetric indefinite LDL^T
factorisation per Newton iteration, like FElupe) or "lagged" (CG on each fresh tangent
preconditioned with a single-precision Cholesky factor of an earlier one, kept across
iterations and load steps, refactorising when CG stalls; the same converged solution with
fewer, cheaper factorisations). `--predictor` picks the load-step predictor: "auto" (secant /
quadratic extrapolation of the previous steps here, as no contact terms are given), "tangent"
(FElupe's: start from the last converged state), "secant". The faceplan line breaks its time
down into assembly (element kernels, scatter, constraints), PARDISO phases, the rest of the
Newton loop and the set-up (mesh, sparsity pattern, geometry).

Usage: python bench/solver_peer.py [--no-scaling] [--sizes 15,24,33,40] [--threads 1] [--repeat 3]
       [--strategy auto|exact|lagged] [--predictor auto|tangent|secant]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

N, L, PULL, STEPS = 20, 20.0, 6.0, 4
VERBOSE = 0
# Convergence at FElupe's level: FElupe stops on the residual alone (|r_free| / |reactions| <
# sqrt(eps), `felupe.tools._newton.check`); faceplan here too: |R_free| <= RTOL * |f_int| with
# the energy-norm test switched off (ETOL = 1: FEBio's energy ratio is relative to the step's
# first iteration, which faceplan's extrapolating predictor makes small, so it would ask for
# more than FElupe does). RTOL = 1e-6 stops the tangent-predictor path (`--predictor tangent
# --strategy exact`) at exactly FElupe's iterates (13 iterations, max_rel_diff ~1e-15); the
# printed max_rel_diff shows the displacements agree far below 1e-4.
RTOL = 1e-6
ETOL = 1.0
C10, C20, C30, K = 2.5, 1.175, 0.0, 2500.0
STRATEGY = "auto"
PREDICTOR = "auto"


def faceplan_run(n=N, steps=STEPS, collect=False, strategy=None):
    import solver
    from solver.examples import block

    t0 = time.perf_counter()
    nodes, hexes, s = block((L, L, L), (n, n, n))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes),
                            solver.Yeoh(C10, C20, C30, K=K, volumetric="quadratic"))
    bcs = [solver.fix(s["xmin"]), solver.Prescribed(s["xmax"], [PULL, 0.0, 0.0], (0,))]
    res = solver.newton_solve(body, bcs, steps=steps, grow=False, rtol=RTOL, etol=ETOL,
                              linear_strategy=strategy or STRATEGY, predictor=PREDICTOR)
    t = time.perf_counter() - t0
    return nodes, res, t, body


def pardiso_for_felupe(mode):
    """PARDISO as FElupe's linear solver: pypardiso.spsolve (unsymmetric LU, mtype 11), or
    symmetric indefinite (mtype -2) on the upper triangle of FElupe's symmetric matrix."""
    import pypardiso
    import scipy.sparse as sp

    if mode == "unsymmetric":
        return pypardiso.spsolve
    ps = pypardiso.PyPardisoSolver(mtype=-2)

    def solve(A, b):
        U = sp.triu(sp.csr_matrix(A), format="csr")
        U.sort_indices()
        ps.set_phase(13)
        return ps._call_pardiso(U, np.ascontiguousarray(b, dtype=float).reshape(len(b), -1)
                                if np.ndim(b) > 1 else np.ascontiguousarray(b, dtype=float))

    return solve


FELUPE_PARDISO = "symmetric"


def felupe_run(n=N, steps=STEPS):
    import felupe as fem

    t0 = time.perf_counter()
    mesh = fem.Cube(a=(0, 0, 0), b=(L, L, L), n=n + 1)
    region = fem.RegionHexahedron(mesh)
    field = fem.FieldsMixed(region, n=3)
    umat = fem.NearlyIncompressible(fem.Hyperelastic(fem.yeoh, C10=C10, C20=C20, C30=C30), bulk=K)
    solid = fem.SolidBody(umat, field)
    bounds = {
        "fixed": fem.Boundary(field[0], fx=0.0),
        "move": fem.Boundary(field[0], fx=L, skip=(0, 1, 1)),
    }
    ramp = {bounds["move"]: fem.math.linsteps([0, PULL], num=steps)[1:]}
    step = fem.Step(items=[solid], ramp=ramp, boundaries=bounds)
    job = fem.Job(steps=[step])
    job.evaluate(solver=pardiso_for_felupe(FELUPE_PARDISO), verbose=VERBOSE)
    t = time.perf_counter() - t0
    return mesh.points.copy(), field[0].values.copy(), t


def _match(pa, pb):
    """Index array j with pb[j] == pa (same lattice, different numbering)."""
    key = lambda p: np.round(p / (L / N) * 4).astype(np.int64)
    ka, kb = key(pa), key(pb)
    order_b = np.lexsort(kb.T[::-1])
    order_a = np.lexsort(ka.T[::-1])
    j = np.empty(len(pa), dtype=np.int64)
    j[order_a] = order_b
    assert np.array_equal(ka, kb[j])
    return j


def _peak_mb():
    """Peak resident memory of this process in MB: VmHWM (reset by exec, unlike ru_maxrss,
    which a child started from the big parent process inherits on Linux)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scaling_point(n, newton=True, strategy="auto", predictor="auto"):
    """One row of the scaling table (run in a child process for a clean peak memory)."""
    import solver
    from solver.examples import block
    from solver.linalg import SymmetricSolver
    from solver.bc import ConstraintSet
    from solver.newton import _System

    nodes, hexes, s = block((L, L, L), (n, n, n))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes),
                            solver.Yeoh(C10, C20, C30, K=K, volumetric="quadratic"))
    cons = ConstraintSet(len(nodes), [solver.fix(s["xmin"]), solver.fix(s["xmax"])])
    system = _System(body, cons, [], None)
    # a stretched state (5%, ends held): the tangent is indefinite there (hydrostatic tension
    # in the held block), so the symmetric indefinite LDL^T factorisation is timed on it; the
    # single-precision Cholesky preconditioner factorisation on the (SPD) reference tangent
    x = nodes.copy()
    x[:, 0] *= 1.05
    system.evaluate(x, 1.0)                                   # warm-up (numba cache load)
    t = time.perf_counter()
    ev, r, A, _ = system.evaluate(x, 1.0)
    t_asm = time.perf_counter() - t
    lin = SymmetricSolver()
    t = time.perf_counter()
    lin.solve(A, r)                                           # analysis + factorisation
    t_first = time.perf_counter() - t
    t = time.perf_counter()
    lin.solve(A, r)                                           # factorisation only (reused analysis)
    t_fact = time.perf_counter() - t
    t_prec = float("nan")
    if lin.backend == "pardiso":
        from solver.linalg import _Pardiso

        _, _, A0, _ = system.evaluate(nodes.copy(), 1.0)
        prec = _Pardiso(mtype=2, single=True)
        prec.factorize(A0)                                    # analysis + factorisation
        t = time.perf_counter()
        prec.factorize(A0)
        t_prec = time.perf_counter() - t
        prec.release()
    bcs = [solver.fix(s["xmin"]), solver.Prescribed(s["xmax"], [PULL, 0.0, 0.0], (0,))]
    iterations, factorizations, t_solve = -1, -1, float("nan")
    if newton:
        t = time.perf_counter()
        res = solver.newton_solve(body, bcs, steps=STEPS, grow=False, rtol=RTOL, etol=ETOL,
                                  linear_strategy=strategy, predictor=predictor)
        t_solve = time.perf_counter() - t
        iterations, factorizations = res.iterations, res.factorizations
    peak = _peak_mb()
    return {"n": n, "dofs": 3 * len(nodes), "assembly_s": t_asm, "analysis+factor_s": t_first,
            "factor_s": t_fact, "precond_factor_s": t_prec, "newton_iterations": iterations,
            "factorizations": factorizations, "solve_s": t_solve,
            "peak_MB": peak, "backend": lin.backend}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--sizes", default="15,24,33,40")
    ap.add_argument("--felupe-pardiso", choices=["symmetric", "unsymmetric"], default="symmetric")
    ap.add_argument("--newton-max-dofs", type=int, default=60000,
                    help="run the full Newton solve in the scaling table up to this many DOF")
    ap.add_argument("--repeat", type=int, default=3,
                    help="alternate runs of both codes; the fastest of each is compared")
    ap.add_argument("--threads", type=int, default=1,
                    help="MKL threads for PARDISO in both codes (0: MKL's default)")
    ap.add_argument("--strategy", choices=["auto", "exact", "lagged"], default="auto",
                    help="faceplan's Newton linear strategy")
    ap.add_argument("--predictor", choices=["auto", "tangent", "secant"], default="auto",
                    help="faceplan's load-step predictor")
    ap.add_argument("--scaling-point", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--no-newton", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.threads > 0:                     # before MKL is loaded (pypardiso loads it lazily)
        os.environ["MKL_NUM_THREADS"] = str(a.threads)
    if a.scaling_point:
        print(json.dumps(scaling_point(a.scaling_point, newton=not a.no_newton,
                                       strategy=a.strategy, predictor=a.predictor)))
        return 0
    global FELUPE_PARDISO, STRATEGY, PREDICTOR
    FELUPE_PARDISO = a.felupe_pardiso
    STRATEGY = a.strategy
    PREDICTOR = a.predictor
    print(f"MKL_NUM_THREADS={os.environ.get('MKL_NUM_THREADS', '(default)')}, faceplan Newton "
          f"strategy {STRATEGY}; load average {os.getloadavg()[0]:.1f}", flush=True)
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path.insert(0, os.path.dirname(here))

    # warm-up of both codes (imports, numba caches, MKL loading) on a 2x2x2 cube: the timed
    # runs below measure set-up and solution, not library loading
    faceplan_run(n=2, steps=1, strategy="exact")
    faceplan_run(n=2, steps=1, strategy="lagged")
    felupe_run(n=2, steps=1)
    # the codes run alternately `--repeat` times; the fastest run of each is compared (the
    # timeit convention: on a shared machine the minimum is the run least disturbed by other
    # jobs; every run is printed)
    t_fps, t_fes = [], []
    for k in range(max(a.repeat, 1)):
        nodes, res, t_fp, body = faceplan_run()
        t_fps.append(t_fp)
        print(f"faceplan ({res.linear_strategy} Newton): {t_fp:.2f} s, {res.iterations} Newton "
              f"iterations in {len(res.steps)} steps, "
              f"{res.factorizations} factorisations, {res.krylov_iterations} CG iterations "
              f"(assembly {res.timings['assembly']:.2f} s, linear solves {res.timings['solve']:.2f} s: "
              f"PARDISO analysis {res.timings.get('pardiso_analysis', 0):.2f} s, factorisations "
              f"{res.timings.get('pardiso_factorization', 0):.2f} s, substitutions "
              f"{res.timings.get('pardiso_substitution', 0):.2f} s; rest of Newton "
              f"{res.timings['total'] - res.timings['assembly'] - res.timings['solve']:.2f} s, set-up "
              f"{t_fp - res.timings['total']:.2f} s)",
              flush=True)
        pts, u_fe, t_fe = felupe_run()
        t_fes.append(t_fe)
        print(f"FElupe + PARDISO: {t_fe:.2f} s (load average {os.getloadavg()[0]:.1f})",
              flush=True)
    t_fp, t_fe = min(t_fps), min(t_fes)
    print(f"fastest of {len(t_fps)}: faceplan {t_fp:.2f} s, FElupe {t_fe:.2f} s; ratios run by run "
          + " ".join(f"{b / a_:.2f}" for a_, b in zip(t_fps, t_fes)), flush=True)
    j = _match(nodes, pts)
    diff = np.abs(res.u - u_fe[j]).max() / np.abs(u_fe).max()
    speed = t_fe / t_fp
    if not a.no_scaling:
        print("\nDOF scaling of faceplan's solver (Yeoh cube, 4-step 6 mm pull, PARDISO):")
        print(f"{'elements':>9} {'DOF':>8} {'assembly s':>11} {'analysis+fact s':>16} "
              f"{'fact s':>7} {'SP chol s':>10} {'Newton it':>10} {'factor.':>8} {'solve s':>8} "
              f"{'peak MB':>8}")
        for n in [int(v) for v in a.sizes.split(",")]:
            cmd = [sys.executable, __file__, "--scaling-point", str(n), "--threads",
                   str(a.threads), "--strategy", a.strategy, "--predictor", a.predictor]
            if 3 * (n + 1) ** 3 > a.newton_max_dofs:
                cmd.append("--no-newton")
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{n ** 3:>9} failed: {out.stderr.strip().splitlines()[-1:]}")
                continue
            row = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"{n ** 3:>9} {row['dofs']:>8} {row['assembly_s']:>11.2f} "
                  f"{row['analysis+factor_s']:>16.2f} {row['factor_s']:>7.2f} "
                  f"{row['precond_factor_s']:>10.2f} "
                  f"{row['newton_iterations'] if row['newton_iterations'] >= 0 else '-':>10} "
                  f"{row['factorizations'] if row['factorizations'] >= 0 else '-':>8} "
                  f"{row['solve_s']:>8.1f} {row['peak_MB']:>8.0f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at the end", flush=True)
    print(f"speedup={speed:.2f} max_rel_diff={diff:.2e} faceplan_s={t_fp:.2f} felupe_s={t_fe:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
