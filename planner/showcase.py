"""Solver showcase: Cook's membrane and a stretched Yeoh block, solved, logged and rendered.

Runs two classic nonlinear problems with faceplan's FE core (`solver`): Cook's membrane
(nearly incompressible neo-Hookean, plane strain, Q1/P0 mean dilatation; reference tip
deflection about 6.9 mm, see tests/solver/test_cook.py) and a 10 mm Yeoh cube (C = 0.5, -0.1,
0.02 kPa, K/C10 = 1e3) clamped at the bottom and pulled 10 mm up. The Newton log of every
iteration is printed (FEBio-like: step, load, iteration, residual, energy and displacement
norms), each result is written as a VTU (displacement, Cauchy stress, J, labels) and an
off-screen PNG of the deformed body coloured by displacement magnitude, plus `summary.json`.
Called by `faceplan demo` until the prediction demo replaces it: `run(out_dir)`.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from planner.atomic import atomic_output_dir
from planner.errors import SolveError

__all__ = ["run", "cook_membrane_case", "yeoh_block_case"]


def _printer(name):
    def cb(rec):
        print(f"  [{name}] step {rec['step']:2d} load {rec['load']:.3f} it {rec['iteration']:2d} "
              f"|R| {rec['residual_norm']:.3e} (rel {rec['relative_residual']:.2e}) "
              f"E {rec['energy_norm']:.3e} |du| {rec['displacement_norm']:.3e} "
              f"s {rec['line_search']:.2f}", flush=True)
    return cb


def cook_membrane_case(n: int = 16, log=True):
    import solver
    from solver.examples import cook_membrane

    nodes, hexes, s = cook_membrane(n)
    mesh = solver.HexMesh(nodes, hexes)
    body = solver.SolidBody(mesh, solver.NeoHooke(mu=80.1938, K=400942.0))
    f = solver.surface_traction(nodes, s["right_facets"], [0.0, 6.25, 0.0])
    bcs = [solver.fix(s["left"]), solver.fix(np.arange(len(nodes)), [2])]
    res = solver.newton_solve(body, bcs, external=f.ravel(), steps=4,
                              callback=_printer("cook") if log else None)
    tip = float(res.u[s["top_right"], 1].mean())
    return mesh, body, res, {"tip_vertical_displacement_mm": tip, "reference_mm": 6.9,
                             "elements_per_side": n}


def yeoh_block_case(n: int = 6, log=True):
    import solver
    from solver.examples import block

    nodes, hexes, s = block((10.0, 10.0, 10.0), (n, n, n))
    mesh = solver.HexMesh(nodes, hexes)
    body = solver.SolidBody(mesh, solver.Yeoh(0.5, -0.1, 0.02, K=500.0))
    bcs = [solver.fix(s["zmin"]), solver.Prescribed(s["zmax"], [0.0, 0.0, 10.0])]
    res = solver.newton_solve(body, bcs, steps=5, callback=_printer("yeoh") if log else None)
    force = float(res.reactions[s["zmax"], 2].sum())
    return mesh, body, res, {"pull_mm": 10.0, "reaction_force_mN": force,
                             "min_volume_ratio": float(body.volume_ratio(res.x).min())}


def _render(mesh, u, path, title, view="iso"):
    from planner.render import offscreen_pyvista

    pv = offscreen_pyvista()
    cells = np.hstack([np.full((len(mesh.hexes), 1), 8), mesh.hexes]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(mesh.hexes), pv.CellType.HEXAHEDRON),
                               mesh.nodes + u)
    grid.point_data["|u| (mm)"] = np.linalg.norm(u, axis=1)
    ref = pv.UnstructuredGrid(cells, np.full(len(mesh.hexes), pv.CellType.HEXAHEDRON), mesh.nodes)
    pl = pv.Plotter(off_screen=True, window_size=(900, 700))
    pl.add_mesh(ref, style="wireframe", color="grey", opacity=0.3)
    pl.add_mesh(grid, scalars="|u| (mm)", show_edges=True, cmap="viridis",
                scalar_bar_args={"title": "|u| (mm)"})
    pl.add_text(title, font_size=10)
    if view == "xy":
        pl.view_xy()
    else:
        pl.view_isometric()
    pl.screenshot(str(path))
    pl.close()


def run(out_dir) -> dict:
    """Solve, log, write VTU + PNG of both showcase problems into out_dir; return the summary."""
    import solver

    out_dir = Path(out_dir)
    summary = {}
    with atomic_output_dir(out_dir, "showcase") as tmp:
        for name, case in (("cook_membrane", cook_membrane_case), ("yeoh_block", yeoh_block_case)):
            print(f"{name}:", flush=True)
            try:
                mesh, body, res, info = case()
            except solver.SolveFailed as exc:
                raise SolveError(f"{name}: {exc}") from exc
            info.update(newton_iterations=res.iterations, steps=len(res.steps),
                        cutbacks=res.cutbacks, wall_s=round(res.timings["total"], 3))
            solver.write_vtu(tmp / f"{name}.vtu", mesh.nodes, mesh.hexes, res.u,
                             cauchy=body.cauchy_stress(res.x), J=body.volume_ratio(res.x),
                             labels=mesh.labels)
            _render(mesh, res.u, tmp / f"{name}.png", f"{name.replace('_', ' ')} (deformed)",
                    view="xy" if name == "cook_membrane" else "iso")
            summary[name] = info
            print(f"  -> {json.dumps(info)}", flush=True)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote {out_dir}/cook_membrane.vtu|png, yeoh_block.vtu|png, summary.json")
    return summary
