"""`mesh_match_and_repair`: the generic FaceModel registered onto a patient's surfaces.

Wraps the array pipeline of `registration.mesh_match` for a `facemodel.FaceModel`: the skin
facet set and the bone attachment node sets (attach_<segment>) drive the registration; the
result keeps the model's connectivity, labels, node and facet sets, regions and landmarks
(node ids), re-orients the fibres with the deformation gradient of each element
(f' = F f / |F f|, F = J' J^-1 from the isoparametric Jacobians at the element centre) and
carries the teeth: the patient's own arches when given (`teeth=`), else each generic arch
moved with the similarity that best maps its bone segment's attachment nodes (Umeyama), with
the lips cleared of them (`registration.teeth`) and kept apart from each other (`registration.lips`). Results are cached on disk under a key hashing every input (model arrays,
patient surfaces, landmarks, options and the registration code itself), so that re-running a
prediction on the same case reuses the registration. A cache entry is a folder holding
`result.npz`, `report.json` and, written last, `digest.json` (the key and the SHA-256 of both
files); an entry whose digest is missing or does not match, or whose arrays or report do not
have the shapes of this model, is damaged: it is deleted with a `CacheWarning` and the
registration is computed again, never used.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import warnings
from dataclasses import asdict, replace
from types import SimpleNamespace
from pathlib import Path

import numpy as np

from registration.errors import RegistrationFailure, RegistrationInputError
from registration.mesh_match import MatchInput, MatchOptions, covered_skin, match_and_repair_arrays
from registration.quality import EDGE_OPERATOR
from registration.surface import (WORKING_MAX_FACES, TargetSurface, simplifies, surface_deviation,
                                  working_surface)
from registration.teeth import ARCH_SEGMENT, teeth_arrays
from solver.geometry import TriangleTree

CACHE_FORMAT = 3
CACHE_FILES = ("result.npz", "report.json")


class CacheWarning(UserWarning):
    """A damaged cache entry was found, deleted and is being rebuilt."""


def surface_arrays(surface, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) float, triangles (m, 3) int64) of a trimesh / pyvista-like object, a
    (vertices, faces) pair or a TargetSurface; RegistrationInputError when it is not a finite
    triangle surface."""
    if isinstance(surface, TargetSurface) or (hasattr(surface, "vertices") and hasattr(surface, "faces")
                                              and not isinstance(surface, (tuple, list))):
        v, f = surface.vertices, surface.faces
    elif isinstance(surface, (tuple, list)) and len(surface) == 2:
        v, f = surface
    elif hasattr(surface, "points") and hasattr(surface, "faces"):  # pyvista PolyData
        tri = surface.triangulate() if hasattr(surface, "triangulate") else surface
        v, f = tri.points, tri.faces
    else:
        raise RegistrationInputError(f"{name}: expected a triangle surface, got {type(surface).__name__}",
                                     field=name)
    v = np.asarray(v, dtype=float)
    f = np.asarray(f)
    if f.ndim == 1:  # VTK cell array [3, a, b, c, 3, ...]
        f = f.reshape(-1, 4)[:, 1:]
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise RegistrationInputError(f"{name}: expected vertices (n, 3) and triangles (m, 3)", field=name)
    if not np.all(np.isfinite(v)):
        raise RegistrationInputError(f"{name}: vertices contain NaN or infinite values", field=name)
    if f.min() < 0 or f.max() >= len(v):
        raise RegistrationInputError(f"{name}: triangles refer to vertices that do not exist", field=name)
    return v, f.astype(np.int64)


def as_target(surface, name: str, max_faces: int | None = None) -> TargetSurface:
    """TargetSurface from a trimesh / pyvista-like object, a (vertices, faces) pair or itself;
    with `max_faces`, of the surface simplified to that many triangles when it has more
    (`registration.surface.working_surface`; a TargetSurface is taken as it is)."""
    if isinstance(surface, TargetSurface):
        return surface
    v, f = surface_arrays(surface, name)
    if max_faces is not None:
        v, f = working_surface(v, f, max_faces)
    try:
        return TargetSurface(v, f, name)
    except ValueError as exc:
        raise RegistrationInputError(str(exc), field=name) from exc


def full_resolution_fit(x: np.ndarray, skin_quads: np.ndarray, working: TargetSurface,
                        full: tuple[np.ndarray, np.ndarray]) -> dict:
    """The registered skin measured against the full-resolution patient skin `full` (vertices,
    faces) over the points the registration measures against its working surface `working`:
    the skin nodes whose closest working-surface point is inside it with an agreeing normal,
    and five points inside each skin facet whose four nodes are such (`mesh_match`'s measure).
    Distances are exact point-to-triangle distances (`TriangleTree`)."""
    quads = np.asarray(skin_quads, np.int64)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    node_ok, inside = covered_skin(x, quads, tris, working)
    uv = np.array([[0.5, 0.5], [0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]])
    shape = np.stack([(1 - uv[:, 0]) * (1 - uv[:, 1]), uv[:, 0] * (1 - uv[:, 1]),
                      uv[:, 0] * uv[:, 1], (1 - uv[:, 0]) * uv[:, 1]], axis=1)
    points = np.concatenate([x[node_ok], np.einsum("sc,qcd->qsd", shape, x[inside]).reshape(-1, 3)])
    if not len(points):
        return {"mean_mm": None, "p95_mm": None, "max_mm": None, "n_points": 0}
    d = TriangleTree(*full).closest(points)[3]
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max()),
            "n_points": int(len(d))}


def centre_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Isoparametric Jacobians (m, 3, 3) at the element centres (columns: d x / d xi_k, x 2)."""
    e = np.einsum("kn,mnd->mdk", EDGE_OPERATOR[8], np.asarray(nodes)[np.asarray(hexes)])
    return e


def reorient_fibres(old_nodes, new_nodes, hexes, fibres) -> np.ndarray:
    fibres = np.asarray(fibres, dtype=float)
    norm = np.linalg.norm(fibres, axis=1)
    out = np.zeros_like(fibres)
    sel = norm > 0
    if not sel.any():
        return out
    j0 = centre_jacobians(old_nodes, hexes[sel])
    j1 = centre_jacobians(new_nodes, hexes[sel])
    f = j1 @ np.linalg.solve(j0, fibres[sel][..., None])
    f = f[..., 0]
    out[sel] = f / np.linalg.norm(f, axis=1)[:, None]
    return out


def _hash_arrays(h, *arrays):
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())


def cache_key(model, skin: TargetSurface, bones: dict, landmarks, options: MatchOptions,
              teeth: dict | None = None, working_faces: int | None = None) -> str:
    h = hashlib.sha256()
    h.update(f"faceplan-registration-{CACHE_FORMAT}-working-{working_faces}".encode())
    src = Path(__file__).parent
    for py in sorted(src.glob("*.py")):  # the code is part of the key
        h.update(py.read_bytes())
    _hash_arrays(h, model.nodes, model.hexes, model.facet_sets["skin"])
    for k in sorted(model.node_sets):
        h.update(k.encode()); _hash_arrays(h, model.node_sets[k])
    _hash_arrays(h, skin.vertices, skin.faces)
    for k in sorted(bones):
        h.update(k.encode()); _hash_arrays(h, bones[k].vertices, bones[k].faces)
    for k in sorted(landmarks or {}):
        h.update(k.encode()); _hash_arrays(h, np.asarray(landmarks[k], float))
    for k in sorted(model.teeth):
        h.update(f"generic-teeth-{k}-{model.teeth[k][2]}".encode())
        _hash_arrays(h, np.asarray(model.teeth[k][0], float), np.asarray(model.teeth[k][1]))
    for k in sorted(teeth or {}):
        v, f, seg = teeth[k]
        h.update(f"patient-teeth-{k}-{seg}".encode()); _hash_arrays(h, v, f)
    h.update(json.dumps(asdict(options), sort_keys=True, default=str).encode())
    return h.hexdigest()[:24]


def default_cache_dir() -> Path:
    env = os.environ.get("FACEPLAN_CACHE")
    if env:
        return Path(env) / "registration"
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "faceplan" / "registration"


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's content, read in 1 MiB blocks (cache entries' digests)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _check_entry(path: Path, model) -> tuple:
    """(nodes, fibres, teeth, report) of a cache entry; ValueError saying what is damaged."""
    try:
        digest = json.loads((path / "digest.json").read_text())
    except FileNotFoundError:
        raise ValueError("no digest.json (the entry was never completed)") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"unreadable digest.json ({exc})") from None
    if not isinstance(digest, dict) or digest.get("key") != path.name or not isinstance(digest.get("files"), dict):
        raise ValueError("digest.json does not describe this entry")
    for name in CACHE_FILES:
        if not (path / name).is_file():
            raise ValueError(f"{name} is missing")
        if file_sha256(path / name) != digest["files"].get(name):
            raise ValueError(f"{name} does not match its recorded SHA-256 (truncated or altered)")
    try:
        report = json.loads((path / "report.json").read_text())
        with np.load(path / "result.npz", allow_pickle=False) as z:
            nodes, fibres = np.asarray(z["nodes"]), np.asarray(z["fibres"])
            if not isinstance(report, dict) or not isinstance(report.get("teeth"), dict):
                raise ValueError("report.json has the wrong shape")
            teeth = {k: (np.asarray(z[f"teeth_{k}"]), np.asarray(z[f"teeth_faces_{k}"]), report["teeth"][k]["segment"])
                     for k in report["teeth"]}
    except (OSError, KeyError, TypeError, EOFError, ValueError) as exc:
        raise ValueError(f"unreadable content ({type(exc).__name__}: {exc})") from None
    if nodes.shape != np.shape(model.nodes) or fibres.shape != np.shape(model.fibres):
        raise ValueError(f"arrays of shape {nodes.shape}/{fibres.shape}, the model has {np.shape(model.nodes)}")
    if not (np.all(np.isfinite(nodes)) and np.all(np.isfinite(fibres))):
        raise ValueError("non-finite coordinates")
    for k, (v, f, _) in teeth.items():
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or not np.all(np.isfinite(v)) \
                or (f.size and (f.min() < 0 or f.max() >= len(v))):
            raise ValueError(f"teeth arch {k!r} is not a valid triangle surface")
    return nodes, fibres, teeth, report


def _cache_load(path: Path, model):
    """The cached (patient model, report) of entry `path`, or None when absent; a damaged entry
    is deleted with a CacheWarning (the caller computes the registration again)."""
    if not path.is_dir():
        return None
    try:
        nodes, fibres, teeth, report = _check_entry(path, model)
    except ValueError as exc:
        warnings.warn(f"registration cache entry {path} is damaged: {exc}; it is deleted and the "
                      "registration computed again", CacheWarning, stacklevel=3)
        shutil.rmtree(path, ignore_errors=True)
        return None
    return replace(model, nodes=nodes, fibres=fibres, teeth=teeth), report


def _pid_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def clean_orphan_temporaries(folder: Path) -> None:
    """Remove `NAME.tmp-PID[.EXT]` files and folders of cache writers that no longer run
    (killed mid-write): the registration cache's and the CT cache's (`planner.case`)."""
    try:
        entries = list(folder.glob("*.tmp-*"))
    except OSError:
        return
    for p in entries:
        pid = p.name.rsplit(".tmp-", 1)[-1].split(".", 1)[0]
        if not (pid.isdigit() and int(pid) != os.getpid() and _pid_gone(int(pid))):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _cache_store(path: Path, patient, report: dict) -> None:
    """Write the entry into a temporary sibling, `digest.json` last, then rename it into place;
    a cache that cannot be written only costs time (nothing half-written stays behind)."""
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        clean_orphan_temporaries(path.parent)
        tmp.mkdir(exist_ok=True)
        np.savez_compressed(tmp / "result.npz", nodes=patient.nodes, fibres=patient.fibres,
                            **{f"teeth_{k}": np.asarray(v[0]) for k, v in patient.teeth.items()},
                            **{f"teeth_faces_{k}": np.asarray(v[1]) for k, v in patient.teeth.items()})
        (tmp / "report.json").write_text(json.dumps(report))
        digest = {"key": path.name, "files": {n: file_sha256(tmp / n) for n in CACHE_FILES}}
        (tmp / "digest.json").write_text(json.dumps(digest))
        os.replace(tmp, path)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)


def mesh_match_and_repair(model, skin, bones: dict | None = None, landmarks: dict | None = None, *,
                          options: MatchOptions | None = None, threshold: float | None = None,
                          cache: bool = True, cache_dir: str | os.PathLike | None = None,
                          files: dict | None = None, teeth: dict | None = None,
                          working_faces: int | None = WORKING_MAX_FACES):
    """Register the generic `model` onto the patient: returns (patient_model, report).

    skin: the patient skin (trimesh, (vertices, faces) or TargetSurface); bones: segment name ->
    bone surface (a segment missing from `bones` is fitted to the union of the others);
    landmarks: optional name -> (3,) mm RAS; teeth: optional arch name ("upper", "lower") ->
    the patient's own teeth surface in the same frame (trimesh, (vertices, faces[, segment]) or
    TargetSurface; e.g. `Case.teeth`), used instead of the generic arches. working_faces: a
    skin or bone surface with more triangles is registered onto its simplification to that many
    (`registration.surface.working_surface`; None: never), the skin fit then measured on the
    full surface too (report `fit.skin_full_resolution`, under the same gate) and the
    simplification's deviation reported (`working_surfaces`). Raises RegistrationInputError for data that cannot
    be registered and RegistrationFailure if the result would not be valid."""
    t0 = time.perf_counter()
    opt = options or MatchOptions()
    if threshold is not None:
        opt = replace(opt, threshold=float(threshold))
    # the surfaces as given (hashed for the cache, the skin's kept to measure the fit on), and
    # the working surfaces the registration runs on
    given = {"skin": skin, **{f"bone.{k}": v for k, v in (bones or {}).items()}}
    full = {name: None if isinstance(v, TargetSurface) else surface_arrays(v, name) for name, v in given.items()}
    keyed = {name: v if full[name] is None else SimpleNamespace(vertices=full[name][0], faces=full[name][1])
             for name, v in given.items()}
    lms = {k: np.asarray(v, dtype=float).reshape(3) for k, v in (landmarks or {}).items()}
    known = set(model.teeth) | set(ARCH_SEGMENT)
    unknown = sorted(set(teeth or {}) - known)
    if unknown:
        raise RegistrationInputError(f"teeth: unknown arch name(s) {', '.join(map(str, unknown))}; "
                                     f"expected {', '.join(sorted(known))}", field="teeth")
    own_teeth = {k: teeth_arrays(v, k) for k, v in (teeth or {}).items()}
    own_teeth = {k: (v, f, seg or (model.teeth[k][2] if k in model.teeth else ARCH_SEGMENT[k]))
                 for k, (v, f, seg) in own_teeth.items()}
    key = cache_key(model, keyed["skin"], {k: keyed[f"bone.{k}"] for k in (bones or {})}, lms, opt,
                    own_teeth, working_faces)
    cdir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    if cache:
        hit = _cache_load(cdir / key, model)
        if hit is not None:
            patient, report = hit
            report.update(cached=True, cache_key=key)
            return patient, report
    t_w = time.perf_counter()
    skin_t = as_target(full["skin"] or skin, "skin", working_faces)
    bone_t = {k: as_target(full[f"bone.{k}"] or v, f"bone.{k}", working_faces) for k, v in (bones or {}).items()}
    simplified = {name: t for name, t in (("skin", skin_t), *((f"bone.{k}", b) for k, b in bone_t.items()))
                  if full[name] is not None and simplifies(len(full[name][1]), working_faces)}
    working_s = time.perf_counter() - t_w
    segs = [s for s in model.segments if f"attach_{s}" in model.node_sets]
    arrays = MatchInput(
        nodes=np.asarray(model.nodes, float), hexes=np.asarray(model.hexes),
        skin_quads=np.asarray(model.facet_sets["skin"]),
        bone_node_sets={s: np.asarray(model.node_sets[f"attach_{s}"]) for s in segs},
        landmark_nodes=dict(model.landmarks),
        bone_quads=np.asarray(model.facet_sets["deep_bone"]) if "deep_bone" in model.facet_sets else None,
        teeth=dict(model.teeth),
        lip_quads=(np.asarray(model.facet_sets["lip_upper_contact"]),
                   np.asarray(model.facet_sets["lip_lower_contact"]))
        if {"lip_upper_contact", "lip_lower_contact"} <= set(model.facet_sets) else None,
        regions={k: np.asarray(v) for k, v in getattr(model, "regions", {}).items()},
        edge_nodes=np.asarray(model.node_sets["border"]) if "border" in model.node_sets else None,
    )
    x, sim, report, placed = match_and_repair_arrays(arrays, skin_t, bone_t, lms or None, opt, files,
                                                     teeth=own_teeth or None)
    report["time"]["working_surfaces_s"] = working_s
    if simplified:
        t_f = time.perf_counter()
        report["working_surfaces"] = {name: {"triangles_given": int(len(full[name][1])),
                                             "triangles_working": int(len(t.faces)),
                                             "deviation": surface_deviation(full[name][0], t)}
                                      for name, t in simplified.items()}
        if "skin" in simplified:
            fit = full_resolution_fit(x, arrays.skin_quads, skin_t, full["skin"])
            report["fit"]["skin_full_resolution"] = fit
            if fit["mean_mm"] is None or fit["mean_mm"] > opt.skin_mean_gate_mm:
                raise RegistrationFailure(f"the registered skin misses the full-resolution patient skin by "
                                          f"{fit['mean_mm']} mm on average (gate {opt.skin_mean_gate_mm} mm)",
                                          report)
        report["time"]["full_resolution_fit_s"] = time.perf_counter() - t_f
    t1 = time.perf_counter()
    fibres = reorient_fibres(model.nodes, x, np.asarray(model.hexes), model.fibres)
    patient = replace(model, nodes=x, fibres=fibres, teeth=placed)
    report["time"]["carry_s"] = time.perf_counter() - t1
    report["time"]["total_s"] = time.perf_counter() - t0
    report["elements_repaired"] = report["repair"]["elements_needing_repair"]
    report["n_nodes"], report["n_elements"] = int(len(x)), int(len(model.hexes))
    report.update(cached=False, cache_key=key)
    if cache:
        _cache_store(cdir / key, patient, report)
    return patient, report
