"""Off-screen pictures of faces and simple charts for the faceplan reports.

Faces (a `trimesh.Trimesh` or a `pyvista.PolyData`) are drawn with pyvista/VTK off screen
(`pv.OFF_SCREEN = True`, EGL/OSMesa wheels, no display needed) from the standard clinical views
of the patient's head frame (RAS: +x patient's right, +y anterior, +z superior): *frontal*
(camera in front of the face at +y looking along -y, so a symmetric face is drawn symmetric,
the patient's right on the picture's left as when facing the patient), *profile* (right: camera
at +x looking along -x) and *profile_left*, *three_quarter* (right) and *three_quarter_left*
(45 degrees between frontal and profile), and *submental* (the worm's-eye view: camera below
the chin tilted 20 degrees forward, anterior up). A scan lying in another pose is shown in the
patient's frame when its head frame is given: `head_frame` is the rotation of the best rigid fit
(Kabsch, Arun et al. IEEE PAMI 9:698, 1987) of a reference in the canonical frame (the generic
face model) onto the patient's (the registered model), and every camera direction is rotated by
it. z (superior) is up on every side view and a parallel projection is used so that lengths on
the picture are comparable; two surfaces drawn with the same `bounds` get the same camera.
Skin is drawn smooth-shaded with a skin-like diffuse/specular material under soft camera lights
(key, fill and head light); a scalar field (displacement, signed distance) is drawn with a
colour map, a colour bar in mm and optional iso-lines; landmarks as labelled dots. Histograms,
bar charts and profiles are drawn with matplotlib (Agg backend); a turntable animation is a GIF
(Pillow).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

__all__ = [
    "VIEWS",
    "SKIN_COLOR",
    "to_polydata",
    "head_frame",
    "view_camera",
    "render_views",
    "render_overlay",
    "render_turntable",
    "union_bounds",
    "histogram_chart",
    "bar_chart",
    "profile_chart",
    "landmark_profile_chart",
]

_S20, _C20 = float(np.sin(np.radians(20.0))), float(np.cos(np.radians(20.0)))
_H = float(np.sqrt(0.5))
# view name -> (direction from the focal point to the camera, view-up), in the head frame (RAS).
VIEWS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "frontal": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "profile": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "profile_left": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "three_quarter": ((_H, _H, 0.0), (0.0, 0.0, 1.0)),
    "three_quarter_left": ((-_H, _H, 0.0), (0.0, 0.0, 1.0)),
    "submental": ((0.0, _S20, -_C20), (0.0, _C20, _S20)),
}
VIEW_TITLES = {"frontal": "frontal", "profile": "right profile", "profile_left": "left profile",
               "three_quarter": "right three-quarter", "three_quarter_left": "left three-quarter",
               "submental": "submental (worm's-eye)"}
SKIN_COLOR = "#e3b8a0"
# skin-like material: mostly diffuse, a faint broad highlight (skin is not glossy)
_SKIN_MATERIAL = dict(ambient=0.18, diffuse=0.82, specular=0.12, specular_power=12.0)


def offscreen_pyvista():
    """pyvista set up for off-screen rendering (the EGL window is chosen in `planner/__init__`)."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv


_pyvista = offscreen_pyvista


def to_polydata(mesh):
    """A pyvista PolyData from a trimesh.Trimesh, a PolyData/UnstructuredGrid or (vertices, faces)."""
    pv = _pyvista()
    if isinstance(mesh, pv.PolyData):
        return mesh.copy(deep=False)
    if isinstance(mesh, pv.DataSet):
        return mesh.extract_surface()
    if isinstance(mesh, tuple) and len(mesh) == 2:
        vertices, faces = mesh
    else:
        vertices, faces = mesh.vertices, mesh.faces
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    cells = np.hstack([np.full((len(faces), 1), faces.shape[1], dtype=np.int64), faces]).ravel()
    return pv.PolyData(vertices, cells)


def head_frame(reference: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The head's axes in the data's coordinates: the rotation R (3, 3) of the best rigid fit
    `points ~ R @ reference + t` (Kabsch with the reflection excluded), so that column k of R is
    the patient's k-th RAS axis as it lies in the scan. `reference` holds the same points in the
    canonical frame (e.g. the generic model's nodes, `points` the registered patient nodes)."""
    a = np.asarray(reference, float)
    b = np.asarray(points, float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise ValueError(f"head_frame needs two (n, 3) arrays of the same points, got {a.shape} and {b.shape}")
    h = (a - a.mean(axis=0)).T @ (b - b.mean(axis=0))
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def view_camera(view: str, frame: np.ndarray | None = None):
    """(direction from focal point to camera, view-up) of `view` in data coordinates."""
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; choose from {sorted(VIEWS)}")
    direction, up = (np.asarray(v, float) for v in VIEWS[view])
    if frame is not None:
        frame = np.asarray(frame, float)
        direction, up = frame @ direction, frame @ up
    return direction, up


def _camera(poly, view: str, zoom: float = 1.0, frame=None):
    direction, up = view_camera(view, frame)
    centre = np.asarray(poly.center, dtype=float)
    radius = max(float(poly.length), 1e-9)
    position = centre + 2.0 * radius * direction
    return [tuple(position), tuple(centre), tuple(up)]


def _plotter(window_size):
    pv = _pyvista()
    pl = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="none")
    pl.set_background("white")
    pl.enable_parallel_projection()
    # soft lights that follow the camera: a key light above and to the picture's left, a
    # weaker fill from the other side and below, a head light that lifts the shadows
    for position, intensity in (((-1.0, 1.2, 1.5), 0.55), ((1.2, -0.4, 1.0), 0.3), ((0.0, 0.0, 1.0), 0.3)):
        pl.add_light(pv.Light(position=position, focal_point=(0.0, 0.0, 0.0), intensity=intensity,
                              light_type="camera light"))
    return pl


class _Bounds:
    """The centre and diagonal of a box, as `_camera` reads them from a PolyData."""

    def __init__(self, bounds):
        b = np.asarray(bounds, float).reshape(3, 2)
        self.bounds = tuple(b.ravel())
        self.center = tuple(b.mean(axis=1))
        self.length = float(np.linalg.norm(b[:, 1] - b[:, 0]))


def union_bounds(polys) -> tuple:
    b = np.array([p.bounds for p in polys], float).reshape(-1, 3, 2)
    return tuple(np.stack([b[:, :, 0].min(axis=0), b[:, :, 1].max(axis=0)], axis=1).ravel())


def _set_camera(pl, box: _Bounds, view: str, frame=None, zoom: float = 1.15):
    # set the camera on the VTK objects directly (pyvista's setters each trigger a render, and
    # software rendering makes every render count), then mark it as set: otherwise pyvista
    # replaces it by its default isometric view at the first render
    position, focal, up = _camera(box, view, frame=frame)
    cam = pl.renderer.GetActiveCamera()
    cam.SetFocalPoint(*focal)
    cam.SetPosition(*position)
    cam.SetViewUp(*up)
    pl.renderer.ResetCamera(*box.bounds)
    cam.Zoom(zoom)
    pl.renderer.ResetCameraClippingRange()
    pl.camera_set = True


def _screenshot(pl) -> np.ndarray:
    pl.render()      # the camera was moved on the VTK objects: draw before reading the pixels
    return np.asarray(pl.screenshot(return_img=True))


def _save_png(img: np.ndarray, path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    # light PNG compression: a third of the encoding time for files ~1.5x larger
    Image.fromarray(img).save(path, compress_level=2)
    return path


def _shoot(pl, box, view: str, path: Path, title: str | None, frame=None, title_position="upper_left"):
    _set_camera(pl, box if isinstance(box, _Bounds) else _Bounds(box.bounds), view, frame)
    if title:
        pl.add_text(title, position=title_position, font_size=10, color="black", name="title")
    pl.add_text(VIEW_TITLES.get(view, view), position="lower_left", font_size=8, color="gray",
                name="view")
    return _save_png(_screenshot(pl), path)


def _landmark_points(poly, landmarks: Mapping[str, Sequence[float]], lift: float = 1.0):
    """Landmark names, the points, the points lifted `lift` mm off the surface along its normal
    (so that the dots are not hidden in the surface they lie on) and a locator of the surface
    for the visibility test."""
    from scipy.spatial import cKDTree
    import vtk

    names = list(landmarks or {})
    pts = np.array([landmarks[n] for n in names], float).reshape(-1, 3)
    if not len(pts):
        return names, pts, pts, None
    normals = np.asarray(poly.compute_normals(auto_orient_normals=False, split_vertices=False,
                                              consistent_normals=True).point_data["Normals"])
    _, idx = cKDTree(np.asarray(poly.points)).query(pts)
    tree = vtk.vtkStaticCellLocator()
    tree.SetDataSet(poly)
    tree.BuildLocator()
    return names, pts, pts + lift * normals[idx], (tree, max(float(poly.length), 1.0))


def _visible(locator, points: np.ndarray, direction: np.ndarray, clearance: float = 1.5) -> np.ndarray:
    """Which points see the camera: nothing of the surface on the segment from `clearance` mm
    in front of the point (towards the camera) to beyond the surface's extent. Given the
    lifted points, a ray grazing the outline (a profile's midline) runs just off the surface."""
    import vtk

    tree, length = locator
    hits, cells = vtk.vtkPoints(), vtk.vtkIdList()
    out = np.zeros(len(points), bool)
    for i, p in enumerate(points):
        start = p + clearance * direction
        tree.IntersectWithLine(tuple(start), tuple(start + 2.0 * length * direction), 1e-6, hits, cells)
        out[i] = hits.GetNumberOfPoints() == 0
    return out


def _add_landmarks(pl, marks, direction, color="#1f4e9c"):
    """Dots and names of the landmarks the camera sees (a ray test against the surface): a
    landmark behind the face or inside the mouth slit is not drawn in that view."""
    names, pts, lifted, locator = marks
    pl.remove_actor("landmarks")
    if not len(pts):
        return
    seen = _visible(locator, lifted, np.asarray(direction, float))
    if not seen.any():
        return
    pl.add_point_labels(lifted[seen], [n for n, f in zip(names, seen) if f], point_color=color,
                        point_size=9, font_size=13, text_color="#102a52", shape_color="white",
                        shape_opacity=0.6, render_points_as_spheres=True, always_visible=True,
                        bold=True, name="landmarks")


def render_views(
    mesh,
    out_prefix: str | os.PathLike,
    scalars: np.ndarray | str | None = None,
    cmap: str = "RdBu_r",
    clim: tuple[float, float] | None = None,
    title: str | None = None,
    scalar_bar_title: str = "mm",
    views: Iterable[str] = ("frontal", "profile", "three_quarter"),
    window_size: tuple[int, int] = (800, 800),
    nan_color: str = "lightgray",
    color: str = SKIN_COLOR,
    frame: np.ndarray | None = None,
    bounds: Sequence[float] | None = None,
    isolines: Sequence[float] | None = None,
    landmarks: Mapping[str, Sequence[float]] | None = None,
    title_position: str = "upper_left",
) -> dict[str, Path]:
    """Render `mesh` from each view into `<out_prefix>_<view>.png`; return {view: path}.

    `scalars` is a per-vertex (or per-face) array, or the name of point data on a PolyData;
    NaN values (e.g. no distance there) are drawn in `nan_color`. Without scalars the surface
    is drawn in a skin colour. `clim` defaults to a symmetric range for diverging maps.
    `frame`: the head's axes in the data (`head_frame`); `bounds` (xmin, xmax, ymin, ...): the
    box the camera frames (give the same box to draw two surfaces with the same camera);
    `isolines`: values of the scalar field drawn as black lines; `landmarks`: {name: point}.
    """
    poly = to_polydata(mesh)
    if poly.n_points == 0:
        raise ValueError("cannot render an empty surface")
    out_prefix = Path(out_prefix)
    field = None
    if scalars is not None:
        if isinstance(scalars, str):
            field = scalars
            values = np.asarray(poly[field], dtype=float)
        else:
            values = np.asarray(scalars, dtype=float)
            field = scalar_bar_title
            if len(values) == poly.n_points:
                poly.point_data[field] = values
            elif len(values) == poly.n_cells:
                poly.cell_data[field] = values
            else:
                raise ValueError(f"scalars has {len(values)} values for {poly.n_points} points "
                                 f"and {poly.n_cells} faces")
        if clim is None:
            finite = values[np.isfinite(values)]
            m = float(np.max(np.abs(finite))) if finite.size else 1.0
            clim = (-m, m) if cmap in ("RdBu_r", "RdBu", "coolwarm", "bwr", "seismic") else (
                float(finite.min()) if finite.size else 0.0, m)
    views = list(views)
    for view in views:
        view_camera(view)
    if field is not None and field not in poly.point_data:
        poly = poly.cell_data_to_point_data()
    box = _Bounds(bounds if bounds is not None else poly.bounds)
    # one plotter for all views: the surface is uploaded and shaded once, only the camera moves
    pl = _plotter(window_size)
    if field is None:
        pl.add_mesh(poly, color=color, smooth_shading=True, **_SKIN_MATERIAL)
    else:
        pl.add_mesh(poly, scalars=field, cmap=cmap, clim=clim, nan_color=nan_color,
                    smooth_shading=True, show_scalar_bar=False, ambient=0.3, diffuse=0.7,
                    specular=0.05)
        pl.add_scalar_bar(title=scalar_bar_title, color="black", vertical=True,
                          position_x=0.86, position_y=0.15, height=0.7, width=0.07,
                          n_labels=7, fmt="%.1f", title_font_size=14, label_font_size=12)
        if isolines:
            lines = poly.contour(isosurfaces=[float(v) for v in isolines], scalars=field)
            if lines.n_points:
                pl.add_mesh(lines, color="black", line_width=2.0, render_lines_as_tubes=False)
                pl.add_text("lines: " + ", ".join(f"{v:g}" for v in isolines) + f" {scalar_bar_title}",
                            position="lower_right", font_size=8, color="black", name="isolines")
    marks = _landmark_points(poly, landmarks)
    written: dict[str, Path] = {}
    try:
        for view in views:
            path = out_prefix.parent / f"{out_prefix.name}_{view}.png"
            _add_landmarks(pl, marks, view_camera(view, frame)[0])
            _shoot(pl, box, view, path, title, frame, title_position)
            written[view] = path
    finally:
        pl.close()
    return written


def render_turntable(
    mesh,
    path: str | os.PathLike,
    frame: np.ndarray | None = None,
    n_frames: int = 20,
    swing_deg: float = 75.0,
    size: int = 320,
    color: str = SKIN_COLOR,
    duration_ms: int = 110,
) -> Path:
    """A turntable GIF: the face turning about the head's vertical axis from the left
    three-quarter through the frontal view to the right and back (azimuth
    swing_deg * sin(2 pi k / n_frames)), lit and shaded as `render_views` draws skin."""
    from PIL import Image

    poly = to_polydata(mesh)
    if poly.n_points == 0:
        raise ValueError("cannot render an empty surface")
    box = _Bounds(poly.bounds)
    frame = np.eye(3) if frame is None else np.asarray(frame, float)
    pl = _plotter((size, size))
    pl.add_mesh(poly, color=color, smooth_shading=True, **_SKIN_MATERIAL)
    images = []
    try:
        for k in range(int(n_frames)):
            a = np.radians(swing_deg) * np.sin(2.0 * np.pi * k / n_frames)
            # rotating the head frame about its own S axis turns the frontal camera around the face
            turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            _set_camera(pl, box, "frontal", frame @ turn.T)
            images.append(Image.fromarray(_screenshot(pl)).convert("P", palette=Image.ADAPTIVE, colors=128))
    finally:
        pl.close()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(duration_ms), loop=0,
                   optimize=True)
    return path


def render_overlay(
    meshes: Sequence,
    out_prefix: str | os.PathLike,
    colors: Sequence[str] = ("#9a9a9a", "#d95f02", "#1b9e77", "#7570b3"),
    labels: Sequence[str] | None = None,
    opacity: Sequence[float] | None = None,
    title: str | None = None,
    views: Iterable[str] = ("profile", "frontal"),
    window_size: tuple[int, int] = (800, 800),
    frame: np.ndarray | None = None,
) -> dict[str, Path]:
    """Overlay several surfaces (e.g. pre-op grey, prediction orange) in each view."""
    polys = [to_polydata(m) for m in meshes]
    if not polys:
        raise ValueError("nothing to overlay")
    if opacity is None:
        opacity = [1.0] + [0.6] * (len(polys) - 1)
    box = _Bounds(union_bounds(polys))
    out_prefix = Path(out_prefix)
    written = {}
    pl = _plotter(window_size)
    for i, poly in enumerate(polys):
        actor = pl.add_mesh(poly, color=colors[i % len(colors)], opacity=float(opacity[i]),
                            smooth_shading=True, **_SKIN_MATERIAL)
        # where surfaces coincide the later one is drawn: each earlier one is pushed back in
        # depth (polygon offset) instead of the two flickering through each other
        actor.GetMapper().SetRelativeCoincidentTopologyPolygonOffsetParameters(
            2.0 * (len(polys) - 1 - i), 4.0 * (len(polys) - 1 - i))
    if labels is not None:
        # the legend as coloured words in the upper right corner, inside the picture
        for i, label in enumerate(labels):
            pl.add_text(str(label), position=(int(window_size[0] - 12 * max(len(l) for l in labels) - 24),
                                                     int(window_size[1] - 34 - 24 * i)),
                        font_size=11, color=colors[i % len(colors)], name=f"legend{i}")
    try:
        for view in views:
            path = out_prefix.parent / f"{out_prefix.name}_{view}.png"
            _shoot(pl, box, view, path, title, frame)
            written[view] = path
    finally:
        pl.close()
    return written


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def histogram_chart(
    values: np.ndarray,
    path: str | os.PathLike,
    bins: int | np.ndarray = 60,
    xlabel: str = "signed distance (mm)",
    title: str | None = None,
    threshold: float | None = 2.0,
    range_: tuple[float, float] | None = None,
) -> Path:
    """Histogram of `values` (NaN ignored) with dashed lines at +-threshold; saved as PNG."""
    plt = _pyplot()
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    if values.size:
        ax.hist(values, bins=bins, range=range_, color="#4c72b0", edgecolor="white", linewidth=0.3)
    if threshold is not None:
        for t in (-threshold, threshold):
            ax.axvline(t, color="#c44e52", linestyle="--", linewidth=1)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("points")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    return _save_figure(fig, path)


def bar_chart(
    labels: Sequence[str],
    values: Sequence[float],
    path: str | os.PathLike,
    errors: Sequence[float] | None = None,
    ylabel: str = "mm",
    title: str | None = None,
    threshold: float | None = 2.0,
    series: dict[str, Sequence[float]] | None = None,
) -> Path:
    """Bar chart of `values` per label (optional error bars, a dashed threshold line).

    `series` draws grouped bars instead: {series name: values per label}.
    """
    plt = _pyplot()
    labels = list(labels)
    fig, ax = plt.subplots(figsize=(max(5.0, 0.6 * len(labels) + 2), 4), dpi=100)
    x = np.arange(len(labels))
    if series:
        width = 0.8 / len(series)
        for k, (name, vals) in enumerate(series.items()):
            ax.bar(x - 0.4 + width * (k + 0.5), np.asarray(vals, float), width, label=name)
        ax.legend()
    else:
        ax.bar(x, np.asarray(values, float), 0.7, color="#4c72b0",
               yerr=None if errors is None else np.asarray(errors, float), capsize=3)
    if threshold is not None:
        ax.axhline(threshold, color="#c44e52", linestyle="--", linewidth=1)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=40, ha="right")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    return _save_figure(fig, path)


def profile_chart(
    meshes: Sequence,
    path: str | os.PathLike,
    labels: Sequence[str] | None = None,
    x: float = 0.0,
    colors: Sequence[str] = ("#555555", "#d95f02", "#1b9e77", "#7570b3"),
    title: str | None = None,
) -> Path:
    """Mid-sagittal profiles: the sections of the surfaces by the plane x = `x`, drawn as
    curves in the (y anterior, z superior) plane with equal axes -- the classic soft-tissue
    profile comparison (e.g. pre-op vs predicted vs post-op)."""
    from matplotlib.collections import LineCollection

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 6), dpi=100)
    drawn = False
    for i, mesh in enumerate(meshes):
        poly = to_polydata(mesh)
        section = poly.slice(normal=(1.0, 0.0, 0.0), origin=(x, 0.0, 0.0))
        if section.n_points == 0:
            continue
        pts = np.asarray(section.points)
        lines = np.asarray(section.lines).reshape(-1, 3)[:, 1:] if section.n_lines else np.zeros((0, 2), int)
        segs = pts[lines][:, :, 1:]                       # (k, 2, [y, z])
        ax.add_collection(LineCollection(segs, colors=colors[i % len(colors)], linewidths=1.6,
                                         label=None if labels is None else labels[i]))
        drawn = True
    if drawn:
        ax.autoscale()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("anterior y (mm)")
    ax.set_ylabel("superior z (mm)")
    if labels is not None and drawn:
        ax.legend(loc="best")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    return _save_figure(fig, path)


def _section(poly, origin, normal):
    """Segments (k, 2, 3) where a surface crosses the plane (origin, normal)."""
    section = poly.slice(normal=tuple(normal), origin=tuple(origin))
    if section.n_points == 0 or section.n_lines == 0:
        return np.zeros((0, 2, 3))
    pts = np.asarray(section.points)
    lines = np.asarray(section.lines).reshape(-1, 3)[:, 1:]
    return pts[lines]


def landmark_profile_chart(
    meshes: Sequence,
    path: str | os.PathLike,
    labels: Sequence[str] = ("pre-op", "predicted"),
    landmarks: Sequence[Mapping[str, Sequence[float]]] = (),
    notes: Mapping[str, str] | None = None,
    frame: np.ndarray | None = None,
    origin: Sequence[float] | None = None,
    colors: Sequence[str] = ("#777777", "#d95f02", "#1b9e77"),
    title: str = "mid-sagittal profile",
) -> Path | None:
    """The mid-sagittal profiles of `meshes` seen from the patient's right (anterior to the
    right of the picture, superior up, equal axes in mm) with each set of `landmarks`
    ({name: point}, one set per mesh) marked, the last set named, and `notes` ({name: text},
    e.g. the soft-to-hard tissue ratio) beside the names. The plane is the head frame's
    sagittal plane (normal = its R axis) through `origin` (default: the frame's origin, x = 0).
    None if no profile crosses the plane."""
    from matplotlib.collections import LineCollection

    frame = np.eye(3) if frame is None else np.asarray(frame, float)
    origin = np.zeros(3) if origin is None else np.asarray(origin, float)
    a_axis, s_axis = frame[:, 1], frame[:, 2]

    def plane_xy(p):
        d = np.asarray(p, float) - origin
        return np.stack([d @ a_axis, d @ s_axis], axis=-1)

    segs = [_section(to_polydata(m), origin, frame[:, 0]) for m in meshes]
    if any(len(sg) == 0 for sg in segs):
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 6.5), dpi=100)
    for i, sg in enumerate(segs):
        ax.add_collection(LineCollection(plane_xy(sg), colors=colors[i % len(colors)], linewidths=2,
                                         label=labels[i] if i < len(labels) else None))
    allpts = np.concatenate([plane_xy(sg).reshape(-1, 2) for sg in segs])
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    notes = notes or {}
    marked = [np.zeros((0, 2))]
    named: list[tuple[str, float, float]] = []
    for i, lm in enumerate(landmarks):
        if not lm:
            continue
        names = list(lm)
        q = plane_xy(np.array([lm[n] for n in names], float).reshape(-1, 3))
        ax.plot(q[:, 0], q[:, 1], "o", color=colors[i % len(colors)], ms=5, mec="black", mew=0.5)
        marked.append(q)
        if i == len(landmarks) - 1:
            named = [(n, float(u), float(v)) for n, (u, v) in zip(names, q)]
    marked = np.concatenate(marked)
    if len(marked):
        # the face: from 40 mm above the highest landmark to 25 mm below the lowest, 70 mm
        # behind the most anterior one
        lo = np.array([max(lo[0], marked[:, 0].max() - 70.0), max(lo[1], marked[:, 1].min() - 25.0)])
        hi = np.array([max(hi[0], marked[:, 0].max()), min(hi[1], marked[:, 1].max() + 40.0)])
    if named:
        # names in a column in front of the face, kept apart, each joined to its point
        named.sort(key=lambda t: -t[2])
        gap = 0.045 * (hi[1] - lo[1])
        x_text = hi[0] + 6.0
        y_prev = np.inf
        for n, u, v in named:
            y_text = min(v, y_prev - gap)
            y_prev = y_text
            text = n + (f"  {notes[n]}" if n in notes else "")
            ax.annotate(text, (u, v), xytext=(x_text, y_text), textcoords="data", va="center",
                        fontsize=8, arrowprops=dict(arrowstyle="-", color="#999999", lw=0.6))
        lo[1] = min(lo[1], y_prev - gap)
    ax.set_xlim(lo[0] - 5, hi[0] + 45)
    ax.set_ylim(lo[1] - 5, hi[1] + 5)
    ax.set_aspect("equal")
    ax.set_xlabel("anterior (mm)")
    ax.set_ylabel("superior (mm)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    return _save_figure(fig, path)


def _save_figure(fig, path) -> Path:
    """Lay out, write (creating the folder) and close a matplotlib figure."""
    plt = _pyplot()

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
