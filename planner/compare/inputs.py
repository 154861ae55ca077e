"""Reading what `faceplan compare` compares: a prediction and a post-operative scan.

A prediction is either a folder written by `faceplan predict` (`skin_predicted.vtp` with point
data `region` indexing the names in its field data `region_names` -- or in `report.json` -- and
`report.json` with `landmarks_predicted`), or any surface file; a bare surface gets its regions
and landmarks from the case's registered pre-op model (`CASE/register/patient_mesh.vtu` and its
`report.json`) by nearest point, and is refused otherwise. The regions to align on are the
prediction's `unoperated_regions` (field data or report), else the registered model's, else the
face model's standard list. Every problem with a file is an `InputError` naming the file.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planner.errors import InputError

__all__ = ["Prediction", "Surface", "load_surface", "read_prediction", "find_postop", "read_inputs",
           "DEFAULT_UNOPERATED", "SURFACE_SUFFIXES"]

SURFACE_SUFFIXES = (".stl", ".ply", ".obj", ".vtp", ".vtk", ".off", ".glb", ".gltf")
# face-model region names that orthognathic surgery leaves untouched (used when the prediction
# does not list them): upper face, nasal bridge, infra-orbital rims, temples, ears
DEFAULT_UNOPERATED = (
    "forehead", "glabella", "nasal_root", "nasal_bridge", "nose_bridge", "nasion", "upper_face",
    "preauricular_left", "preauricular_right",
    "infraorbital_left", "infraorbital_right", "orbit_left", "orbit_right", "temple_left",
    "temple_right", "ear_left", "ear_right", "eyes", "eye_left", "eye_right",
)


@dataclass(frozen=True)
class Surface:
    vertices: np.ndarray
    faces: np.ndarray
    path: Path


@dataclass
class Prediction:
    vertices: np.ndarray
    faces: np.ndarray
    region: np.ndarray                     # (n,) index into region_names, -1 for none
    region_names: tuple[str, ...]
    unoperated_regions: tuple[str, ...]
    landmarks: dict[str, np.ndarray]
    path: Path
    notes: list[str] = field(default_factory=list)
    # (n, 3) the prediction's displacement of each vertex from the pre-op skin (mm), None when
    # not known: where surgery moves the "unoperated" regions in this plan (`check_same_patient`)
    displacement: np.ndarray | None = None


def _read_pyvista(path: Path):
    import pyvista as pv

    try:
        data = pv.read(str(path))
    except Exception as exc:  # VTK readers raise assorted errors on bad files
        raise InputError(f"cannot read the surface ({exc})", file=str(path)) from None
    if isinstance(data, pv.MultiBlock):
        data = data.combine()
    if not isinstance(data, pv.PolyData):
        data = data.extract_surface()
    return data.triangulate()


def _own_load_surface(path: Path, what: str) -> Surface:
    if not path.exists():
        raise InputError(f"{what} not found", file=str(path))
    suffix = path.suffix.lower()
    if suffix in (".vtp", ".vtk"):
        poly = _read_pyvista(path)
        vertices = np.asarray(poly.points, float)
        faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:] if poly.n_cells else np.zeros((0, 3), int)
    else:
        import trimesh

        try:
            mesh = trimesh.load(str(path), force="mesh", process=False)
        except Exception as exc:  # trimesh raises assorted errors on bad files
            raise InputError(f"cannot read the {what} ({exc})", file=str(path)) from None
        vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), float)
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    return _validated(vertices, faces, path, what)


def _merge_coincident(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6):
    """Merge vertices closer than `tol` mm (quantised coordinates), keeping first occurrences."""
    key = np.round(vertices / tol).astype(np.int64)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    new_group = np.empty(len(order), bool)
    new_group[0] = True
    new_group[1:] = np.any(ks[1:] != ks[:-1], axis=1)
    if new_group.all():
        return vertices, faces
    group = np.cumsum(new_group) - 1                      # group id in sorted order
    first = np.full(group[-1] + 1, len(order), np.int64)
    np.minimum.at(first, group, order)                    # first occurrence of each group
    rank = np.empty_like(first)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    new_index = np.empty(len(order), np.int64)
    new_index[order] = rank[group]
    return vertices[np.sort(first)], new_index[faces]


def _validated(vertices, faces, path: Path, what: str, merge: bool = True) -> Surface:
    vertices = np.asarray(vertices, float).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(faces) == 0 or len(vertices) < 3:
        raise InputError(f"the {what} is empty (no triangles)", file=str(path))
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"the {what} has NaN or infinite coordinates", file=str(path))
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"the {what} has triangles referring to missing vertices", file=str(path))
    if merge:
        vertices, faces = _merge_coincident(vertices, faces)
    # drop degenerate triangles and unused vertices (STL soups, scanner debris)
    v = vertices
    area2 = np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
    faces = faces[(area2 > 0) & (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    if len(faces) == 0:
        raise InputError(f"the {what} has only degenerate triangles", file=str(path))
    used = np.unique(faces)
    if merge and len(used) < len(vertices):  # stray points without triangles carry no surface
        remap = np.full(len(vertices), -1, np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = vertices[used], remap[faces]
    extent = float(np.linalg.norm(np.ptp(vertices[used] if not merge else vertices, axis=0)))
    if extent < 30.0:
        unit = "metres" if extent < 1.0 else "centimetres"
        raise InputError(
            f"the {what} spans only {extent:.3g} units; faceplan expects millimetres "
            f"(is it in {unit}? scale it by {1000 if unit == 'metres' else 10})", file=str(path))
    return Surface(vertices, faces, path)


def load_surface(path: str | Path, what: str) -> Surface:
    """Read and check a surface file (mm, finite, non-empty); `what` names it in messages.

    Coincident vertices are merged (STL files store every triangle on its own), so that
    boundaries and vertex normals are those of the surface, not of a triangle soup.
    """
    path = Path(path)
    try:
        from planner.case import load_surface as case_load_surface
    except ImportError:
        return _own_load_surface(path, what)
    mesh = case_load_surface(path, what)
    return _validated(mesh.vertices, mesh.faces, path, what)


def find_postop(case: Path, override: str | None = None) -> Path:
    """The post-op scan: `--postop FILE`, else `CASE/postop/skin.*`."""
    if override:
        p = Path(override)
        if not p.exists():
            raise InputError("post-op scan not found", file=str(p))
        return p
    folder = case / "postop"
    for suffix in SURFACE_SUFFIXES:
        p = folder / f"skin{suffix}"
        if p.exists():
            return p
    raise InputError("no post-op scan: expected postop/skin.stl (or .ply, .obj, .vtp, .vtk)",
                     file=str(folder / "skin.stl"))


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read JSON ({exc})", file=str(path)) from None


def _landmarks(obj, path: Path, vertices: np.ndarray | None = None) -> dict[str, np.ndarray]:
    out = {}
    if not isinstance(obj, dict):
        return out
    for name, value in obj.items():
        if isinstance(value, int) and vertices is not None and 0 <= value < len(vertices):
            out[name] = vertices[value].astype(float)
            continue
        arr = np.asarray(value, dtype=float) if isinstance(value, (list, tuple)) else None
        if arr is None or arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise InputError(f"landmark {name} must be [x, y, z] in mm", file=str(path),
                             field=f"landmarks_predicted.{name}")
        out[name] = arr
    return out


def _field_strings(poly, name: str) -> tuple[str, ...] | None:
    if name not in poly.field_data:
        return None
    vals = poly.field_data[name]
    return tuple(str(v.decode() if isinstance(v, bytes) else v) for v in np.asarray(vals).ravel())


def _unoperated(names: tuple[str, ...], *candidates) -> tuple[tuple[str, ...], str]:
    for source, cand in candidates:
        if cand:
            chosen = tuple(n for n in cand if n in names)
            if chosen:
                return chosen, source
    chosen = tuple(n for n in DEFAULT_UNOPERATED if n in names)
    return chosen, "default list"


def read_prediction(case: Path | None, prediction: str | None) -> Prediction:
    """The prediction to compare: a predict folder, or a bare surface plus regions."""
    if prediction is None:
        if case is None:
            raise InputError("no prediction given")
        path = case / "predict"
    else:
        path = Path(prediction)
        if case is not None and not path.is_absolute() and not path.exists() and (case / path).exists():
            path = case / path
    if not path.exists():
        raise InputError("prediction not found (run `faceplan predict CASE` first, or give "
                         "--prediction DIR_OR_SURFACE)", file=str(path))
    if path.is_dir():
        return _read_prediction_folder(path)
    return _read_bare_prediction(case, path)


def _read_prediction_folder(folder: Path) -> Prediction:
    vtp = folder / "skin_predicted.vtp"
    if not vtp.exists():
        raise InputError("the prediction folder has no skin_predicted.vtp", file=str(vtp))
    report_path = folder / "report.json"
    report = _read_json(report_path) if report_path.exists() else {}
    poly = _read_pyvista(vtp)
    surf = _validated(np.asarray(poly.points), np.asarray(poly.faces).reshape(-1, 4)[:, 1:]
                      if poly.n_cells else np.zeros((0, 3)), vtp, "predicted skin", merge=False)
    names = _field_strings(poly, "region_names") or tuple(report.get("region_names") or ())
    if "region" not in poly.point_data or not names:
        raise InputError("skin_predicted.vtp needs point data 'region' and the region names "
                         "(field data 'region_names' or report.json 'region_names')", file=str(vtp),
                         field="region")
    region = np.asarray(poly.point_data["region"]).astype(np.int64).ravel()
    if region.max(initial=-1) >= len(names) or region.min(initial=0) < -1:
        raise InputError(f"region indices outside 0..{len(names) - 1}", file=str(vtp), field="region")
    unop, source = _unoperated(names, ("skin_predicted.vtp", _field_strings(poly, "unoperated_regions")),
                               ("report.json", report.get("unoperated_regions")))
    lms = _landmarks(report.get("landmarks_predicted", {}), report_path)
    disp = None
    if "displacement" in poly.point_data:
        disp = np.asarray(poly.point_data["displacement"], float)
        if disp.shape != surf.vertices.shape:
            raise InputError(f"point data 'displacement' has shape {disp.shape}, the surface "
                             f"{surf.vertices.shape}", file=str(vtp), field="displacement")
    return Prediction(surf.vertices, surf.faces, region, tuple(names), unop, lms, folder,
                      notes=[f"unoperated regions from {source}"], displacement=disp)


def _read_bare_prediction(case: Path | None, path: Path) -> Prediction:
    surf = load_surface(path, "predicted skin")
    ref = _registered_model(case)
    if ref is None:
        raise InputError(
            "a bare prediction surface has no regions; run `faceplan register CASE` first "
            "(regions come from CASE/register/patient_mesh.vtu) or give a folder from "
            "`faceplan predict`", file=str(path))
    points, region, names, unop, lms = ref
    from scipy.spatial import cKDTree

    d, nearest = cKDTree(points).query(surf.vertices, workers=-1)
    region_v = np.where(d < 15.0, region[nearest], -1)
    if lms:  # pre-op landmarks projected on the predicted surface: starting points only
        from planner.compare.distances import TriangleSurface

        names_l = list(lms)
        proj = TriangleSurface(surf.vertices, surf.faces).closest(np.array([lms[n] for n in names_l]))
        lms = {n: proj.point[i] for i, n in enumerate(names_l)}
    unop_names, source = _unoperated(names, ("register/report.json", unop))
    return Prediction(surf.vertices, surf.faces, region_v, names, unop_names, lms, path,
                      notes=[f"regions transferred by nearest point from {case / 'register'}",
                             f"unoperated regions from {source}"])


def _registered_model(case: Path | None):
    """(skin points, region per point, names, unoperated, landmarks) of the registered model."""
    if case is None:
        return None
    folder = case / "register"
    vtu = folder / "patient_mesh.vtu"
    if not vtu.exists():
        return None
    import pyvista as pv

    report = _read_json(folder / "report.json") if (folder / "report.json").exists() else {}
    if vtu.with_suffix(".json").exists():        # a FaceModel saved with its JSON sidecar
        from facemodel.model import FaceModel

        try:
            model = FaceModel.load(vtu)
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"cannot read the registered model ({exc})", file=str(vtu)) from None
        names = tuple(model.regions)
        ids = [np.asarray(model.regions[n], np.int64) for n in names]
        pts = model.nodes[np.concatenate(ids)]
        reg = np.concatenate([np.full(len(i), k) for k, i in enumerate(ids)])
        lms = {k: model.nodes[v].astype(float) for k, v in model.landmarks.items()}
        return pts, reg, names, list(model.unoperated_regions), lms
    try:
        grid = pv.read(str(vtu))
    except Exception as exc:  # VTK readers raise assorted errors on bad files
        raise InputError(f"cannot read the registered model ({exc})", file=str(vtu)) from None
    points = np.asarray(grid.points, float)
    names = None
    if "region_names" in grid.field_data:
        names = _field_strings(grid, "region_names")
    names = names or tuple(report.get("region_names") or ())
    if "region" in grid.point_data and names:
        region = np.asarray(grid.point_data["region"]).astype(np.int64).ravel()
        keep = region >= 0
        pts, reg = points[keep], region[keep]
    elif isinstance(report.get("regions"), dict) and report["regions"]:
        names = tuple(report["regions"])
        ids, reg = [], []
        for k, name in enumerate(names):
            node_ids = np.asarray(report["regions"][name], np.int64)
            ids.append(node_ids)
            reg.append(np.full(len(node_ids), k))
        ids = np.concatenate(ids)
        pts, reg = points[ids], np.concatenate(reg)
    else:
        raise InputError("the registered model has no regions (point data 'region' with "
                         "'region_names', or report.json 'regions')", file=str(vtu))
    lms_src = report.get("landmarks") or report.get("landmarks_registered") or {}
    lms = _landmarks(lms_src, folder / "report.json", points)
    return pts, reg, tuple(names), report.get("unoperated_regions"), lms


def read_inputs(case: str | Path, prediction: str | None = None,
                postop: str | None = None) -> tuple[Prediction, Surface]:
    """The prediction and the post-op scan of a case, as `faceplan compare` reads them."""
    case = Path(case)
    pred = read_prediction(case, prediction)
    path = find_postop(case, postop)
    return pred, load_surface(path, "post-op scan")


# A post-op scan whose points lie this close to the pre-op skin (median point-to-surface
# distance, mm) is that skin: a surface scanner's noise alone is ~0.1-0.3 mm, and surgery
# moves the lower face by millimetres.
PREOP_COPY_MEDIAN_MM = 0.05


def check_not_preop(case: Path, scan: Surface, scan_path: Path) -> None:
    """Refuse (InputError naming the scan) a post-op scan that is the case's pre-op skin: the
    same file, or a surface whose points lie on `preop/skin.*` (median distance below
    PREOP_COPY_MEDIAN_MM) in the frame it was given in."""
    import hashlib

    from planner.compare.distances import TriangleSurface

    preop = [case / "preop" / f"skin{s}" for s in SURFACE_SUFFIXES if (case / "preop" / f"skin{s}").is_file()]
    if not preop:
        return
    pre = preop[0]

    def digest(p):
        return hashlib.sha256(Path(p).read_bytes()).hexdigest()

    msg = (f"the post-op scan is the pre-op skin ({pre}): give the surface scanned after "
           "surgery")
    if Path(scan_path).resolve() == pre.resolve() or digest(scan_path) == digest(pre):
        raise InputError(msg, file=str(scan_path), field="post-op scan")
    surface = load_surface(pre, "pre-op skin")
    pts = scan.vertices[:: max(1, len(scan.vertices) // 5000)]
    d = TriangleSurface(surface.vertices, surface.faces).closest(pts).distance
    if float(np.median(d)) < PREOP_COPY_MEDIAN_MM:
        raise InputError(msg + f" (its points lie on it: median distance {np.median(d):.3f} mm)",
                         file=str(scan_path), field="post-op scan")
