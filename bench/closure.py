"""Closing the mandible 8 mm on the generic face, with lip-lip and lip-teeth contact.

The generic face is in occlusion, so the closure starts from the face with the mouth opened
by the same distance about the condylar hinge axis (`facemodel.jaw.opened_model`, an FE solve
with contact taken as the new rest shape) and closes by the reverse hinge rotation (mandible
and chin). Prints the incisal relation, the opening and closure solves (time, Newton
iterations, load steps), the deepest lip-in-lip and lip-in-teeth penetrations, and where the
closure stops if it does; with --images DIR writes mid-sagittal sections (tissues, lip contact surfaces,
teeth) of the opened and the closed face.
Usage: python bench/closure.py [--resolution coarse|standard|fine] [--closure MM] [--images DIR]
Last line: closure_mm=<x> max_penetration_mm=<x>
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def _render(model, x, teeth, path, title):
    """Mid-sagittal section seen from the right: the elements just left of the mid-sagittal
    node plane, tissues coloured, the lip contact surfaces outlined (upper red, lower blue) and
    the outline of the teeth 0.5 mm left of the mid-sagittal plane."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    hexes = np.asarray(model.hexes)
    # the mid-sagittal node plane, to the solver's symmetry (contact: ~0.01 mm)
    on_mid = np.any(np.abs(np.asarray(model.nodes)[hexes][:, :, 0]) < 0.05, axis=1)
    left = np.flatnonzero(on_mid & (x[hexes].mean(1)[:, 0] < 0.0))
    grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: hexes[left]}, x)
    grid.cell_data["tissue"] = np.asarray(model.labels)[left]
    pl = pv.Plotter(off_screen=True, window_size=(900, 900))
    pl.add_mesh(grid, scalars="tissue", cmap="tab20", show_edges=True, edge_color="grey",
                clim=[0, len(model.label_names) - 1], show_scalar_bar=False)
    fs = model.facet_sets
    for key, colour in (("lip_upper_contact", "red"), ("lip_lower_contact", "blue")):
        q = np.asarray(fs[key])
        q = q[x[q].mean(1)[:, 0] <= 0.0]
        lines = np.hstack([np.full((len(q), 1), 5), q, q[:, :1]]).ravel()
        pl.add_mesh(pv.PolyData(x, lines=lines), color=colour, line_width=4)
    for name, (V, F, _) in teeth.items():
        F = np.asarray(F)
        arch = pv.PolyData(np.asarray(V, float), np.hstack([np.full((len(F), 1), 3), F]).ravel())
        section = arch.slice(normal="x", origin=(-0.5, 0.0, 0.0))
        pl.add_mesh(section, color="black", line_width=4)
    pl.view_yz()
    pl.enable_parallel_projection()
    pl.camera.zoom(1.4)
    pl.add_text(title, font_size=10)
    pl.screenshot(str(path))
    pl.close()
    print(f"wrote {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", default="coarse")
    ap.add_argument("--closure", type=float, default=8.0, help="mm at the lower incisal edge")
    ap.add_argument("--images", default=None, help="folder for the renders (optional)")
    args = ap.parse_args(argv)
    import generic_mesh
    from facemodel import jaw
    from facemodel.simulation import lip_penetrations, simulate
    from solver.contact import ramped_rigid_motion
    from solver.errors import SolveFailed

    face = generic_mesh.load(args.resolution)
    print(f"face '{args.resolution}': {face.n_nodes} nodes, {face.n_elements} hexes; incisal "
          f"relation " + ", ".join(f"{k} {v:.2f}" for k, v in jaw.incisal_relation(face).items()))
    t0 = time.perf_counter()
    try:
        opened, _ = jaw.opened_model(face, args.closure)
    except SolveFailed as exc:
        print(f"opening by {args.closure} mm failed: {exc}")
        print("closure_mm=nan max_penetration_mm=nan")
        return 3
    pen0 = lip_penetrations(opened, opened.nodes)
    print(f"opened by {args.closure} mm in {time.perf_counter() - t0:.1f} s; deepest "
          f"penetration at the start {max(pen0.values()):.3f} mm")
    angle = jaw.hinge_closure(opened, args.closure)
    T = jaw.hinge_rotation(angle)
    motions = {"mandible": T, "chin": T}
    edge = jaw.incisal_edges(opened)["lower"]

    def rise(load):
        Tl = ramped_rigid_motion(T, load)
        return float((Tl[:3, :3] @ edge + Tl[:3, 3] - edge)[2])

    t0 = time.perf_counter()
    try:
        res = simulate(opened, motions)
        x, load = res.x, res.load
        print(f"closed by a {angle:.2f} deg hinge rotation in {time.perf_counter() - t0:.1f} s: "
              f"{res.iterations} Newton iterations, {res.steps} steps, min v/V "
              f"{res.volume_ratio.min():.3f}")
    except SolveFailed as exc:
        load = exc.last_converged_load
        x = exc.state.x if exc.state is not None else opened.nodes
        print(f"closure stopped at load {load:.3f} ({rise(load):.2f} of {args.closure} mm), "
              f"worst element {exc.worst_element}: {exc}")
    pen = lip_penetrations(opened, x, load=load, motions=motions)
    print("deepest penetration (mm): " + ", ".join(f"{k} {v:.4f}" for k, v in pen.items()))
    L = face.landmarks
    back = max(np.linalg.norm(x[L[n]] - face.nodes[L[n]]) for n in ("Stms", "Stmi", "Ls", "Li"))
    print(f"lips after opening and closing: within {back:.3f} mm of the generic face")
    if args.images:
        from pathlib import Path

        out = Path(args.images)
        out.mkdir(parents=True, exist_ok=True)
        closed = opened.with_nodes(x, teeth=jaw.move_teeth(opened, {s: ramped_rigid_motion(T, load)
                                                                    for s in motions}))
        _render(opened, opened.nodes, opened.teeth, out / "mandible_opened_section.png",
                f"mouth opened {args.closure:g} mm about the hinge axis (start)")
        _render(closed, x, closed.teeth, out / "mandible_closed_section.png",
                f"closed {rise(load):.1f} mm: deepest lip/teeth penetration {max(pen.values()):.3f} mm")
    print(f"closure_mm={rise(load):.2f} max_penetration_mm={max(pen.values()):.4f}")
    return 0 if load == 1.0 else 3


if __name__ == "__main__":
    raise SystemExit(main())
