"""An analytic face phantom with labelled regions and landmarks, for tests and benchmarks.

The surface is star-shaped about a centre C: P(u) = C + (rho(u) + H(q)) u, where u is a unit
direction (azimuth about z from +y, elevation), rho(u) the radius of a base ellipsoid (semi-axes
75 x 100 x 125 mm in x, y, z) and H a sum of smooth Gaussian features evaluated at the base
point q = C + rho(u) u: nasal bridge and tip, upper and lower lips with the mouth fissure and
commissure dimples, chin, brow ridge, and a submental recess that makes the chin's underside
curve back (so soft-tissue menton is an interior lowest point). Being a closed-form surface, it
can be triangulated at any density and with any jitter -- two triangulations of the same face
differ only by the chord error (about h^2 kappa / 8). Regions are assigned from the base
coordinates (q_x, q_z) with the names the face model uses, in patient RAS.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay

from planner.compare.landmarks import _ME

__all__ = ["Phantom", "face_phantom", "REGION_NAMES", "UNOPERATED"]

CENTRE = np.array([0.0, 0.0, -10.0])
AXES = np.array([75.0, 100.0, 125.0])
AZ_MAX = np.radians(70.0)
EL_MIN, EL_MAX = np.radians(-78.0), np.radians(58.0)

REGION_NAMES = (
    "forehead", "nasal_bridge", "infraorbital_left", "infraorbital_right", "nose", "upper_lip",
    "lower_lip", "chin", "submental", "cheek_left", "cheek_right",
)
UNOPERATED = ("forehead", "nasal_bridge", "infraorbital_left", "infraorbital_right")

# landmark -> base coordinates (q_x, q_z) in mm
_LANDMARKS = {
    "Prn": (0.0, 8.0), "Sn": (0.0, -8.0), "Ls": (0.0, -20.0), "Stms": (0.0, -29.5),
    "Li": (0.0, -40.0), "Pog": (0.0, -76.0),
    "ChR": (26.0, -30.0), "ChL": (-26.0, -30.0),
}


def _g(x, z, x0, z0, sx, sz):
    return np.exp(-(((x - x0) / sx) ** 2) - ((z - z0) / sz) ** 2)


def features(qx: np.ndarray, qz: np.ndarray) -> np.ndarray:
    """Radial feature height H (mm) at base coordinates (q_x, q_z)."""
    h = 7.0 * _g(qx, qz, 0, 35, 7, 18) + 20.0 * _g(qx, qz, 0, 8, 10, 11)       # nose
    h += 7.0 * _g(qx, qz, 0, -20, 20, 7) + 6.0 * _g(qx, qz, 0, -40, 18, 6)     # lips
    h -= 2.5 * _g(qx, qz, 0, -30, 22, 2.2)                                      # mouth fissure
    h -= 2.0 * _g(np.abs(qx), qz, 26, -30, 3, 3)                                # commissures
    h += 14.0 * _g(qx, qz, 0, -76, 17, 13)                                      # chin
    h += 4.0 * np.exp(-((qz - 52) / 8) ** 2) * np.exp(-((qx / 45) ** 2))       # brow ridge
    h -= 28.0 / (1.0 + np.exp((qz + 100.0) / 4.0))                              # submental
    return h


def _directions(az, el):
    return np.stack([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)], axis=-1)


def _surface(u):
    rho = 1.0 / np.sqrt(np.sum((u / AXES) ** 2, axis=-1))
    q = CENTRE + rho[..., None] * u
    return CENTRE + (rho + features(q[..., 0], q[..., 2]))[..., None] * u, q


def surface_at(qx: float, qz: float) -> np.ndarray:
    """The phantom surface point above base coordinates (q_x, q_z)."""
    zc = qz - CENTRE[2]
    qy = AXES[1] * np.sqrt(max(1.0 - (qx / AXES[0]) ** 2 - (zc / AXES[2]) ** 2, 0.0))
    u = np.array([qx, qy, zc]) / np.linalg.norm([qx, qy, zc])
    return _surface(u[None])[0][0]


def regions_from_base(qx: np.ndarray, qz: np.ndarray) -> np.ndarray:
    """Region index (into REGION_NAMES) from base coordinates."""
    idx = {n: i for i, n in enumerate(REGION_NAMES)}
    r = np.where(qx >= 0, idx["cheek_right"], idx["cheek_left"])
    ax = np.abs(qx)
    r = np.where(qz >= 20, np.where(qx >= 0, idx["infraorbital_right"], idx["infraorbital_left"]), r)
    r = np.where(qz >= 45, idx["forehead"], r)
    r = np.where((ax < 12) & (qz >= 25) & (qz < 45), idx["nasal_bridge"], r)
    r = np.where((ax < 24) & (qz >= -30) & (qz < 20), idx["upper_lip"], r)
    r = np.where((qx / 16) ** 2 + ((qz - 10) / 17) ** 2 < 1, idx["nose"], r)
    r = np.where((ax < 24) & (qz >= -50) & (qz < -30), idx["lower_lip"], r)
    r = np.where((ax < 30) & (qz < -50) & (qz >= -98), idx["chin"], r)
    r = np.where(qz < -98, idx["submental"], r)
    return r.astype(np.int64)


@dataclass(frozen=True)
class Phantom:
    vertices: np.ndarray        # (n, 3) mm RAS
    faces: np.ndarray           # (m, 3), outward normals
    region: np.ndarray          # (n,) index into region_names
    region_names: tuple[str, ...]
    landmarks: dict[str, list[float]]
    unoperated_regions: tuple[str, ...]

    def trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def face_phantom(spacing: float = 1.5, jitter: float = 0.0, seed: int = 0,
                 offset: float = 0.0) -> Phantom:
    """Triangulate the phantom with about `spacing` mm between vertices.

    `jitter` moves the parameter-grid points randomly by that fraction of a cell (a different
    triangulation of the same surface); `offset` shifts the grid by a fraction of a cell.
    """
    rng = np.random.default_rng(seed)
    step = spacing / 105.0                         # radians per vertex at a typical radius
    ys = np.arange(EL_MIN, EL_MAX + 1e-12, step) + offset * step
    pts = []
    for el in ys:
        half = AZ_MAX * np.cos(el)
        xs = np.arange(-half, half + 1e-12, step) + offset * step
        pts.append(np.column_stack([xs, np.full_like(xs, el)]))
    p = np.vstack(pts)
    if jitter > 0:
        p = p + rng.uniform(-0.5, 0.5, p.shape) * jitter * step
    el = np.clip(p[:, 1], EL_MIN, EL_MAX)
    az = np.clip(p[:, 0] / np.cos(el), -AZ_MAX, AZ_MAX)
    tri = Delaunay(np.column_stack([az * np.cos(el), el]))
    faces = tri.simplices.astype(np.int64)
    u = _directions(az, el)
    vertices, q = _surface(u)
    # drop the slivers Delaunay makes along the curved parameter boundary (long in the
    # parameter plane; steep features such as the nose are long only in 3D and are kept)
    uv = tri.points
    e = uv[faces[:, [1, 2, 0]]] - uv[faces]
    longest = np.linalg.norm(e, axis=2).max(axis=1)
    faces = faces[longest < 3.0 * step]
    n = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    outward = np.einsum("ij,ij->i", n, vertices[faces[:, 0]] - CENTRE) > 0
    faces = np.where(outward[:, None], faces, faces[:, ::-1])
    used = np.unique(faces)
    remap = -np.ones(len(vertices), np.int64)
    remap[used] = np.arange(len(used))
    vertices, q, faces = vertices[used], q[used], remap[faces]
    landmarks = {k: surface_at(*v).tolist() for k, v in _LANDMARKS.items()}
    # profile landmarks at their analytic extremes on the dense mid-sagittal profile (the
    # definitions planner.compare.landmarks uses): most anterior point of nose, lips and chin,
    # deepest point below the nose, lowest chin point measured downwards and MENTON_TILT
    # degrees forwards (menton, the convention of planner.compare.landmarks)
    el = np.radians(np.arange(-75.0, 40.0, 0.005))
    prof, _ = _surface(_directions(np.zeros_like(el), el))
    z = prof[:, 2]
    me = np.array(_ME)
    for name, lo, hi, h in (("Prn", -5, 30, prof[:, 1]), ("Sn", -14, -2, -prof[:, 1]),
                            ("Ls", -28, -12, prof[:, 1]), ("Li", -48, -34, prof[:, 1]),
                            ("Pog", -88, -62, prof[:, 1]), ("Me", -100, -80, prof @ me)):
        sel = np.flatnonzero((z > lo) & (z < hi))
        landmarks[name] = prof[sel[np.argmax(h[sel])]].tolist()
    return Phantom(vertices, faces, regions_from_base(q[:, 0], q[:, 2]), REGION_NAMES,
                   landmarks, UNOPERATED)


def write_prediction_folder(folder, vertices, faces, region, region_names, landmarks,
                            unoperated_regions=None) -> None:
    """Write a prediction folder in the `faceplan predict` layout (for tests and benchmarks).

    `skin_predicted.vtp` with point data `region` and field data `region_names` (and
    `unoperated_regions` when given), `skin_predicted.stl`, and `report.json` with
    `landmarks_predicted`.
    """
    import json
    from pathlib import Path

    import pyvista as pv
    import trimesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cells = np.hstack([np.full((len(faces), 1), 3, np.int64), faces]).ravel()
    poly = pv.PolyData(np.asarray(vertices, float), cells)
    poly.point_data["region"] = np.asarray(region, np.int32)
    poly.field_data["region_names"] = np.array(list(region_names))
    if unoperated_regions:
        poly.field_data["unoperated_regions"] = np.array(list(unoperated_regions))
    poly.save(str(folder / "skin_predicted.vtp"))
    trimesh.Trimesh(vertices, faces, process=False).export(folder / "skin_predicted.stl")
    report = {"landmarks_predicted": {k: list(map(float, v)) for k, v in landmarks.items()},
              "region_names": list(region_names)}
    (folder / "report.json").write_text(json.dumps(report, indent=2))
