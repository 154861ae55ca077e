"""Off-screen renders of the generic face model for the README: element labels in colour,
and the muscle fibre field (pyvista / VTK, Mesa off-screen).

`python -m generic_mesh.render [resolution]` writes generic_mesh/images/labels.png and
fibres.png.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

IMAGES = Path(__file__).parent / "images"

# one distinguishable colour per label (tissues in skin tones, muscles in reds/purples)
LABEL_COLOURS = {
    "dermis": "#f2d3bd", "hypodermis": "#f7e7a6", "mucosa": "#e88fa0", "nose": "#9fd3e8",
    "orbicularis_oris": "#c0392b", "zygomaticus_major": "#8e44ad",
    "levator_labii_superioris": "#2e86c1", "risorius": "#d35400", "buccinator": "#16a085",
    "depressor_anguli_oris": "#7d3c98", "depressor_labii_inferioris": "#b03a2e",
    "mentalis": "#1e8449",
}


def _grid(model):
    import pyvista as pv

    cells = np.hstack([np.full((model.n_elements, 1), 8), model.hexes]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(model.n_elements, pv.CellType.HEXAHEDRON), model.nodes)
    grid.cell_data["label"] = model.labels
    return grid


def render_labels(model, path, window=(1400, 1000)):
    """Frontal-oblique view of the mesh with the dermis peeled off the right half of the
    face, so that the muscle layer shows; every label coloured, with a legend."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    grid = _grid(model)
    dermis = model.label_id("dermis")
    hypo = model.label_id("hypodermis")
    c = model.element_centres
    show = ~(((model.labels == dermis) | (model.labels == hypo)) & (c[:, 0] > 0))
    p = pv.Plotter(off_screen=True, window_size=window)
    legend = []
    for i, name in enumerate(model.label_names):
        sel = np.flatnonzero((model.labels == i) & show)
        if len(sel):
            p.add_mesh(grid.extract_cells(sel), color=LABEL_COLOURS[name], show_edges=True,
                       edge_color="#555555", line_width=0.3)
            legend.append([name.replace("_", " "), LABEL_COLOURS[name]])
    for name, (v, f, _) in model.teeth.items():
        faces = np.hstack([np.full((len(f), 1), 3), f]).ravel()
        p.add_mesh(pv.PolyData(np.asarray(v), faces), color="#fdfefe")
    p.add_legend(legend, bcolor="white", size=(0.25, 0.4), loc="lower left")
    p.camera_position = [(150.0, 300.0, 20.0), (0.0, 60.0, -40.0), (0.0, 0.0, 1.0)]
    p.camera.zoom(1.3)
    p.add_text("generic face model: labels (dermis and fat removed on the right half)",
               font_size=10)
    p.screenshot(str(path))
    p.close()
    return Path(path)


def render_fibres(model, path, window=(1400, 1000)):
    """Muscle elements and their fibre directions (glyphs), frontal view."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    grid = _grid(model)
    muscles = np.flatnonzero(np.linalg.norm(model.fibres, axis=1) > 0)
    p = pv.Plotter(off_screen=True, window_size=window)
    skin = grid.extract_cells(np.flatnonzero(model.labels == model.label_id("dermis")))
    p.add_mesh(skin.extract_surface(), color="#f2d3bd", opacity=0.15)
    m = grid.extract_cells(muscles)
    p.add_mesh(m, scalars="label", cmap="tab20", show_edges=False, opacity=0.5, show_scalar_bar=False)
    pts = pv.PolyData(model.element_centres[muscles])
    pts["fibre"] = model.fibres[muscles]
    pts["label"] = model.labels[muscles]
    arrows = pts.glyph(orient="fibre", scale=False, factor=4.0, geom=pv.Line(pointa=(-0.5, 0, 0), pointb=(0.5, 0, 0)))
    p.add_mesh(arrows, color="black", line_width=2)
    p.camera_position = [(0.0, 330.0, -40.0), (0.0, 60.0, -45.0), (0.0, 0.0, 1.0)]
    p.add_text("generic face model: muscle fibre directions", font_size=10)
    p.screenshot(str(path))
    p.close()
    return Path(path)


def main(argv=None) -> int:
    import generic_mesh

    args = argv if argv is not None else sys.argv[1:]
    model = generic_mesh.load(args[0] if args else "standard")
    IMAGES.mkdir(exist_ok=True)
    print(render_labels(model, IMAGES / "labels.png"))
    print(render_fibres(model, IMAGES / "fibres.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
