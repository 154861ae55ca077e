"""Reading a patient case folder (see CONTRACT.md, "A case folder") into a checked `Case`.

The pre-op skin comes from `preop/skin.*` (stl, ply, obj, off read by trimesh; vtk, vtp, vtu
read by pyvista) or, when no skin surface is given, is extracted from a CT volume
(`preop/ct.nii.gz`, `preop/ct.nii` or a DICOM series folder `preop/ct/`) with `facemodel.ct`
(skin at -400 HU with the airways sealed, bone at +300 HU; thresholds overridable in
`case.yaml` as `ct: {skin_hu: ..., bone_hu: ...}`, e.g. for a cone-beam CT whose grey values
are only roughly HU). Bone surfaces come from `preop/bone/<segment>.*`, one per segment, or
from the same CT as one `bone` surface; dental arches, when given apart, from
`preop/teeth/<arch>.*`. Landmarks are read from `preop/landmarks.json` (`{"Prn": [x, y, z],
...}` in mm RAS), from a 3D Slicer markups file `preop/landmarks.mrk.json` (labelled control
points in the file's `coordinateSystem`, LPS by default as in Slicer, turned to RAS by
negating x and y) or from an older Slicer fiducial list `preop/landmarks.fcsv`. Every
surface is checked for what goes wrong in practice: unreadable, empty, NaN coordinates, and
the size of a head in metres rather than millimetres; the skin (from a file or a CT) for a face
looking along -y (an LPS frame read as RAS: `face_direction`). Each surface is then cleaned with
vectorised array operations (a binary STL read straight into arrays, coincident vertices merged,
degenerate and repeated triangles dropped, the winding made consistent and a closed surface
turned outward: `clean_triangles`, `check_closed`, `orient_faces`), so that a scan of 10^6
triangles is read in seconds. Every problem raises
`planner.errors.InputError` naming the file and the field. Surfaces extracted from a CT are
cached by the CT's content hash: `KEY.npz` and, written last, `KEY.sha256` (its SHA-256); an
entry without a matching digest or with arrays that are not triangle surfaces is deleted
with a warning and the CT segmented again, never used.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from planner.errors import InputError

TRIMESH_FORMATS = (".stl", ".ply", ".obj", ".off")
VTK_FORMATS = (".vtk", ".vtp", ".vtu")
SURFACE_FORMATS = TRIMESH_FORMATS + VTK_FORMATS
# A surface whose bounding-box diagonal is below this many mm cannot be a human skin or bone
# (the smallest segment, a chin, is ~40 mm across) but is what a head in metres looks like.
METRES_DIAGONAL_MM = 1.0
# A landmark farther than this from the skin belongs to another frame, unit or patient:
# soft-tissue landmarks sit on the skin, bony ones within the soft-tissue thickness (at most
# ~20 mm on the face), so 30 mm leaves room for both. (An LPS/RAS mix-up on a closed head
# surface can land on the back of the head and pass; on a face-only surface it is caught.)
LANDMARK_MAX_SKIN_DISTANCE_MM = 30.0
# The accepted landmark names are all soft-tissue landmarks, placed on the skin: placement and
# surface differences (another isosurface of the same CT) stay within ~1-2 mm, so a median
# distance above this is another frame or another scan.
LANDMARK_MEDIAN_SKIN_DISTANCE_MM = 4.0
# A bone segment whose nearest point is farther than this from the skin is not under that skin
# (facial soft tissue is 3-25 mm thick over bone): another frame origin, units or patient.
BONE_MAX_SKIN_DISTANCE_MM = 30.0
# A skin facing the other way than RAS anterior is looked for along the antero-posterior line
# through the jaws, within this radius (mm) of it in the x-z plane.
FACING_LINE_RADIUS_MM = 15.0
# The most anterior part of a head is the nose tip: the skin within this depth of the head's
# extreme along +y is the tip of the nose (~25 mm across, ~1000 mm2), while the skin within the
# same depth of the extreme along -y is a cap of the rounded back of the head (a spherical cap
# of radius R ~ 80-100 mm has the area 2 pi R h ~ 5000-6000 mm2). A closed skin whose cap along
# -y is this many times smaller than its cap along +y has its nose at the back: it looks along
# -y. Between the two ratios nothing is concluded (a forehead or a truncated CT may be extreme).
FACE_CAP_DEPTH_MM = 10.0
FACE_CAP_RATIO = 2.0
# Landmark spellings accepted besides the model's names (matched case-insensitively).
LANDMARK_ALIASES = {
    "pronasale": "Prn", "subnasale": "Sn", "labrale_superius": "Ls", "labialesuperius": "Ls",
    "labrale_inferius": "Li", "labialeinferius": "Li", "stomion_superius": "Stms",
    "stomion_inferius": "Stmi", "cheilion_left": "ChL", "cheilion_right": "ChR",
    "pogonion": "Pog", "soft_tissue_pogonion": "Pog", "menton": "Me", "soft_tissue_menton": "Me",
}
LANDMARKS_MAX_BYTES = 10_000_000
CASE_INFO_KEYS = ("id", "follow_up_months", "notes", "age_years", "sex", "synthetic", "seed", "ct")
CT_KEYS = ("skin_hu", "bone_hu")   # case.yaml `ct:` thresholds, e.g. for a CBCT's grey values
SLICER_UNITS_TO_MM = {"mm": 1.0, "um": 1e-3}
# Triangle budget of surfaces extracted from a CT: a 0.5 mm CT gives a skin of over a million
# triangles; 200,000 keeps the skin's detail (edges ~1 mm) at a fraction of the cost downstream.
CT_MAX_FACES = 200_000
CT_EXTRACTION_VERSION = "faceplan-ct-3"   # part of the CT cache key: bump when extraction changes


@dataclass(frozen=True)
class CaseInfo:
    """`case.yaml`: identifier, follow-up time of the post-op scan, free notes."""

    id: str
    follow_up_months: float | None = None
    notes: str = ""
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Case:
    """A checked case folder. Surfaces are `trimesh.Trimesh` in mm RAS."""

    root: Path
    skin: "trimesh.Trimesh"  # noqa: F821
    bones: dict
    landmarks: dict
    plan_path: Path | None
    postop_skin_path: Path | None
    postop_plan_path: Path | None
    info: CaseInfo
    skin_path: Path | None = None      # the surface file, or the CT it was extracted from
    ct_path: Path | None = None
    teeth: dict = field(default_factory=dict)   # optional preop/teeth/<arch>.* (upper, lower)

    @property
    def from_ct(self) -> bool:
        return self.ct_path is not None and self.skin_path == self.ct_path

    @cached_property
    def postop_skin(self):
        """The post-op surface scan (may be partial), or None when the case has none."""
        if self.postop_skin_path is None:
            return None
        return load_surface(self.postop_skin_path, "postop skin", closed=False)

    def require_plan(self) -> Path:
        if self.plan_path is None:
            raise InputError("the case has no plan.yaml", file=str(self.root / "plan.yaml"))
        return self.plan_path


# ----------------------------------------------------------------------------------- surfaces
def load_surface(path, what: str = "surface", *, closed: bool = False):
    """A triangle surface from stl/ply/obj/off/vtk/vtp/vtu, checked; InputError otherwise.

    `what` names the surface in messages (it becomes the `field` of the error). With
    `closed=True` the surface must be watertight.
    """
    import trimesh

    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise InputError(f"{what}: no such file", file=file, field=what)
    suffix = path.suffix.lower()
    if suffix not in SURFACE_FORMATS:
        raise InputError(f"{what}: unsupported surface format {suffix or '(none)'}; use one of "
                         f"{', '.join(SURFACE_FORMATS)}", file=file, field=what)
    try:
        binary_stl = _read_binary_stl(path) if suffix == ".stl" else None
        if suffix in VTK_FORMATS:
            vertices, faces = _read_vtk_surface(path)
        elif binary_stl is not None:
            vertices, faces = binary_stl
        else:
            mesh = trimesh.load(str(path), force="mesh", process=False)
            vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    except InputError:
        raise
    except Exception as exc:  # readers raise anything from ValueError to struct.error
        raise InputError(f"{what}: unreadable surface file ({type(exc).__name__}: {exc})",
                         file=file, field=what) from exc
    vertices = np.asarray(vertices, dtype=float).reshape(-1, 3)
    faces = np.asarray(faces).reshape(-1, 3) if len(faces) else np.zeros((0, 3), int)
    if len(faces) == 0 or len(vertices) < 3:
        raise InputError(f"{what}: the surface is empty (no triangles)", file=file, field=what)
    if not np.all(np.isfinite(vertices)):
        bad = int((~np.isfinite(vertices).all(axis=1)).sum())
        raise InputError(f"{what}: {bad} vertices have NaN or infinite coordinates",
                         file=file, field=what)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"{what}: triangles refer to vertices that do not exist",
                         file=file, field=what)
    referenced = np.zeros(len(vertices), bool)
    referenced[faces.ravel()] = True
    used = vertices[referenced]
    diagonal = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    if diagonal < METRES_DIAGONAL_MM:
        raise InputError(f"{what}: the surface is only {diagonal:.4g} across, which looks like "
                         "metres: multiply by 1000 (faceplan works in mm)", file=file, field=what)
    vertices, faces = clean_triangles(vertices, faces)
    if len(faces) == 0:
        raise InputError(f"{what}: every triangle is degenerate", file=file, field=what)
    watertight = check_closed(faces, closed, file, what)
    vertices, faces = orient_faces(vertices, faces, watertight)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    # what was just established, so that trimesh does not recompute it on a large surface
    mesh._cache["is_watertight"] = watertight
    mesh._cache["is_winding_consistent"] = True
    return mesh


# Vertices closer than this (mm, per coordinate after rounding) are one vertex: STL stores every
# triangle's corners separately, and exporters round the shared corners identically.
MERGE_DECIMALS = 8
# A triangle whose height over its longest edge is below this (mm) has no area to speak of: it
# gives no normal and no closest-point answer of its own.
DEGENERATE_HEIGHT_MM = 1e-8


def clean_triangles(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coincident vertices merged (`MERGE_DECIMALS`), then degenerate triangles (a repeated
    corner, or a height below `DEGENERATE_HEIGHT_MM`) and repeated triangles (the same three
    corners in any order) dropped, and vertices no triangle uses removed. Vectorised (a hash of
    the rows, `registration.surface.unique_rows`), so a 10^6-triangle scan costs about a second;
    the order of the kept triangles and their winding are those of the file."""
    from registration.surface import unique_rows

    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    first, inverse = unique_rows(np.round(v, MERGE_DECIMALS) + 0.0)   # + 0.0: -0.0 becomes 0.0
    v, f = v[first], inverse[f]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    tri = v[f]
    twice_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    longest = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(axis=1)
    keep &= twice_area > DEGENERATE_HEIGHT_MM * longest
    f = f[keep]
    if len(f):
        once, _ = unique_rows(np.sort(f, axis=1))
        f = f[np.sort(once)]
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    renumber = np.cumsum(used) - 1
    return v[used], renumber[f]


def _edge_keys(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Per directed edge (three per triangle): its key and the key of its undirected edge."""
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    n = np.int64(n_vertices)
    return a * n + b, np.minimum(a, b) * n + np.maximum(a, b)


def check_closed(faces: np.ndarray, required: bool, file: str, what: str) -> bool:
    """Whether the surface is closed (every edge shared by exactly two triangles); InputError
    when `required` and it is not."""
    _, undirected = _edge_keys(faces, int(faces.max()) + 1)
    key = np.sort(undirected)
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    closed = bool(np.all(np.diff(starts) == 2))
    if required and not closed:
        raise InputError(f"{what}: the surface is not closed (it has holes)", file=file, field=what)
    return closed


def orient_faces(vertices: np.ndarray, faces: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Triangles wound consistently (neighbours run their shared edge in opposite directions)
    and, on a closed surface, outward (positive enclosed volume): some exporters write them
    inward or mixed. Consistency is tested vectorised (no directed edge twice); only a surface
    that fails it is re-wound (trimesh's breadth-first `fix_winding`)."""
    import trimesh

    directed = np.sort(_edge_keys(faces, len(vertices))[0])
    if np.any(directed[1:] == directed[:-1]):
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        trimesh.repair.fix_winding(mesh)
        faces = np.asarray(mesh.faces, np.int64)
    if closed:
        tri = vertices[faces]
        volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
        if volume < 0:
            faces = faces[:, ::-1].copy()
    return vertices, faces


STL_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


def _read_binary_stl(path: Path):
    """(vertices, faces) of a binary STL read straight into arrays (80-byte header, uint32
    count, 50-byte records), every corner its own vertex (`clean_triangles` merges them); None
    when the file is not a binary STL of exactly that size (an ASCII STL, or a damaged file,
    which trimesh's reader then reads or refuses)."""
    size = path.stat().st_size
    if size < 84:
        return None
    with open(path, "rb") as fh:
        head = fh.read(84)
        n = int(np.frombuffer(head, "<u4", 1, 80)[0])
        if n == 0 or size != 84 + 50 * n:
            return None
        records = np.fromfile(fh, STL_RECORD, n)
    vertices = records["corners"].reshape(-1, 3).astype(float)
    return vertices, np.arange(3 * n, dtype=np.int64).reshape(n, 3)


def _read_vtk_surface(path: Path):
    import pyvista as pv

    data = pv.read(str(path))
    if isinstance(data, pv.MultiBlock):
        data = data.combine()
    if isinstance(data, pv.PolyData):
        surface = data
    else:  # a volume mesh: its boundary
        try:
            surface = data.extract_surface(algorithm=None)
        except TypeError:  # pyvista < 0.47 has no algorithm choice
            surface = data.extract_surface()
    surface = surface.triangulate()
    if surface.n_cells == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    faces = surface.faces.reshape(-1, 4)
    return np.asarray(surface.points, float), faces[:, 1:]


def _surface_files(folder: Path, stem: str) -> list[Path]:
    return sorted(p for p in folder.glob(f"{stem}.*")
                  if p.is_file() and p.suffix.lower() in SURFACE_FORMATS)


def _one_surface_file(folder: Path, stem: str, what: str) -> Path | None:
    files = _surface_files(folder, stem)
    if len(files) > 1:
        raise InputError(f"{what}: several files ({', '.join(p.name for p in files)}); keep one",
                         file=str(folder / stem), field=what)
    return files[0] if files else None


def _optional(p: Path) -> Path | None:
    return p if p.is_file() else None


def _ct_source(preop: Path) -> Path | None:
    for name in ("ct.nii.gz", "ct.nii"):
        if (preop / name).is_file():
            return preop / name
    if (preop / "ct").is_dir():
        return preop / "ct"
    return None


def default_cache_dir() -> Path:
    """Where surfaces extracted from CTs are kept: $FACEPLAN_CACHE/ct, else
    $XDG_CACHE_HOME/faceplan/ct (~/.cache/faceplan/ct), next to the registration cache."""
    env = os.environ.get("FACEPLAN_CACHE")
    if env:
        return Path(env) / "ct"
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "faceplan" / "ct"


def _ct_cache_key(ct_path: Path, options: dict) -> str:
    """Content hash of the CT (every file of a DICOM folder, with its relative name) and of
    the extraction options: a changed file or threshold never reuses old surfaces."""
    h = hashlib.sha256(CT_EXTRACTION_VERSION.encode())
    files = sorted(q for q in ct_path.rglob("*") if q.is_file()) if ct_path.is_dir() else [ct_path]
    for q in files:
        h.update(str(q.relative_to(ct_path) if ct_path.is_dir() else q.name).encode())
        with open(q, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    h.update(json.dumps(options, sort_keys=True).encode())
    return h.hexdigest()[:24]


class CacheWarning(UserWarning):
    """A damaged CT cache entry was found, deleted and is being rebuilt."""


def _cache_load(path: Path):
    """The cached {"skin", "bone"} surfaces of entry `path` (KEY.npz), None when absent; a
    damaged entry is deleted with a CacheWarning (the caller extracts the surfaces again)."""
    import warnings

    import trimesh

    from registration.face import file_sha256

    digest = path.with_suffix(".sha256")
    if not path.is_file():
        return None
    try:
        recorded = digest.read_text().strip() if digest.is_file() else None
        if recorded is None:
            raise ValueError("no digest (the entry was never completed)")
        if recorded != file_sha256(path):
            raise ValueError("content does not match its recorded SHA-256 (truncated or altered)")
        out = {}
        with np.load(path, allow_pickle=False) as z:
            for k in ("skin", "bone"):
                v, f = np.asarray(z[f"{k}_vertices"], float), np.asarray(z[f"{k}_faces"])
                if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or not len(f) \
                        or not np.all(np.isfinite(v)) or f.min() < 0 or f.max() >= len(v):
                    raise ValueError(f"{k} is not a valid triangle surface")
                out[k] = trimesh.Trimesh(v, f, process=False)
        return out
    except (OSError, KeyError, ValueError, EOFError, TypeError) as exc:
        warnings.warn(f"CT cache entry {path} is damaged: {exc}; it is deleted and the CT "
                      "segmented again", CacheWarning, stacklevel=3)
        for q in (path, digest):
            q.unlink(missing_ok=True)
        return None


def _cache_store(path: Path, surfaces: dict) -> None:
    """Write KEY.npz through a temporary file, then KEY.sha256 (also through one) last; a cache
    that cannot be written only costs time, and nothing half-written stays behind."""
    from registration.face import file_sha256

    tmp = path.with_name(f"{path.stem}.tmp-{os.getpid()}.npz")
    tmp_digest = path.with_name(f"{path.stem}.tmp-{os.getpid()}.sha256")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.with_suffix(".sha256").unlink(missing_ok=True)
        np.savez_compressed(tmp, **{f"{k}_{a}": getattr(m, a) for k, m in surfaces.items()
                                    for a in ("vertices", "faces")})
        tmp_digest.write_text(file_sha256(tmp))
        os.replace(tmp, path)
        os.replace(tmp_digest, path.with_suffix(".sha256"))
    except OSError:
        tmp.unlink(missing_ok=True)
        tmp_digest.unlink(missing_ok=True)
    from registration.face import clean_orphan_temporaries

    clean_orphan_temporaries(path.parent)


def _surfaces_from_ct(ct_path: Path, thresholds: dict, cache_dir: Path | None) -> dict:
    """{"skin", "bone"} surfaces of the case's CT, from the cache when extracted before."""
    from facemodel.ct import CTError, ct_surfaces

    options = {"max_faces": CT_MAX_FACES, **{k: float(v) for k, v in thresholds.items()}}
    cached = None
    if cache_dir is not None:
        cached = cache_dir / f"{_ct_cache_key(ct_path, options)}.npz"
        hit = _cache_load(cached)
        if hit is not None:
            return hit
    try:
        surfaces = ct_surfaces(ct_path, **options)
    except CTError as exc:
        raise InputError(exc.reason, file=exc.file or str(ct_path), field="preop CT") from exc
    out = {"skin": surfaces.skin, "bone": surfaces.bone}
    if cached is not None:
        _cache_store(cached, out)
    return out


def _load_parts(folder: Path, kind: str) -> dict:
    """Every surface file of a folder, by name (`preop/bone/maxilla.stl` -> "maxilla")."""
    parts: dict = {}
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    for p in files:
        if p.suffix.lower() not in SURFACE_FORMATS:
            raise InputError(f"{kind}: {p.name} is not a surface file ({', '.join(SURFACE_FORMATS)})",
                             file=str(p), field=kind)
        name = p.name[: -len(p.suffix)]
        if name in parts:
            raise InputError(f"{kind} {name}: several files for one part; keep one",
                             file=str(p), field=f"{kind}.{name}")
        parts[name] = load_surface(p, f"{kind}.{name}")
    return parts


def _load_bones(folder: Path) -> dict:
    bones = _load_parts(folder, "bone")
    if not bones:
        raise InputError("no bone surface in preop/bone/ (expected <segment>.stl files: skull, "
                         "maxilla, mandible, chin...)", file=str(folder), field="bone")
    return bones


# ---------------------------------------------------------------------------------- landmarks
def _point(value, file: str, name: str) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        p = None
    if p is None or p.shape != (3,):
        raise InputError(f"landmark {name}: expected three coordinates [x, y, z], got {value!r}",
                         file=file, field=f"landmarks.{name}")
    if not np.all(np.isfinite(p)):
        raise InputError(f"landmark {name}: NaN or infinite coordinate", file=file,
                         field=f"landmarks.{name}")
    return p


def known_landmark_names() -> tuple[str, ...]:
    from facemodel.model import LANDMARK_NAMES

    return tuple(LANDMARK_NAMES)


def canonical_landmarks(landmarks: dict, file: str) -> dict[str, np.ndarray]:
    """Landmarks renamed to the model's names (`Prn`, `Sn`, ...): a name matching one of them
    or an alias (`pronasale`) case-insensitively is accepted; any other name is refused (a
    landmark silently ignored would misalign the face), with the known names suggested."""
    import difflib

    known = known_landmark_names()
    lookup = {k.lower(): k for k in known}
    lookup.update({a.lower(): k for a, k in LANDMARK_ALIASES.items()})
    out: dict[str, np.ndarray] = {}
    unknown = []
    for name, p in landmarks.items():
        key = lookup.get(str(name).strip().lower().replace(" ", "_").replace("-", "_"))
        if key is None:
            unknown.append(str(name))
            continue
        if key in out:
            raise InputError(f"landmarks: {key} is given twice (as {name!r} too)", file=file,
                             field=f"landmarks.{name}")
        out[key] = p
    if unknown:
        hints = []
        for u in unknown[:5]:
            close = difflib.get_close_matches(u.lower(), list(lookup), n=1, cutoff=0.5)
            if close:
                hints.append(f"{u!r} -> {lookup[close[0]]}?")
        raise InputError(f"landmarks: unrecognised name(s) {', '.join(map(repr, unknown))}; known "
                         f"names (any case): {', '.join(known)}" + (f" (did you mean {'; '.join(hints)})"
                                                                    if hints else ""),
                         file=file, field=f"landmarks.{unknown[0]}")
    return out


def load_landmarks(path) -> dict[str, np.ndarray]:
    """Landmarks in mm RAS from the simple json form, a 3D Slicer `.mrk.json` markups file or
    an older Slicer `.fcsv` fiducial list, under the model's names (`canonical_landmarks`)."""
    path = Path(path)
    return canonical_landmarks(_read_landmarks(path), str(path))


def _read_landmarks(path: Path) -> dict[str, np.ndarray]:
    file = str(path)
    if path.name.lower().endswith(".fcsv"):
        return _slicer_fcsv(path)
    try:
        if path.stat().st_size > LANDMARKS_MAX_BYTES:
            raise InputError(f"landmarks: the file is over {LANDMARKS_MAX_BYTES // 10**6} MB, not a "
                             "landmarks file", file=file, field="landmarks")
        data = json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=_unique_keys(file))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"landmarks: unreadable json ({exc})", file=file, field="landmarks") from exc
    if isinstance(data, dict) and "markups" in data:
        return _slicer_markups(data, file)
    if not isinstance(data, dict) or not data:
        raise InputError('landmarks: expected an object {"Prn": [x, y, z], ...} or 3D Slicer '
                         "markups", file=file, field="landmarks")
    out = {}
    for name, value in data.items():
        if not isinstance(name, str) or not name.strip():
            raise InputError("landmarks: empty landmark name", file=file, field="landmarks")
        out[name] = _point(value, file, name)
    return out


def _unique_keys(file: str):
    def hook(pairs):
        out = {}
        for k, v in pairs:
            if k in out:
                raise InputError(f"landmarks: the key {k!r} appears twice", file=file, field=f"landmarks.{k}")
            out[k] = v
        return out
    return hook


def _slicer_markups(data: dict, file: str) -> dict[str, np.ndarray]:
    markups = data["markups"]
    if not isinstance(markups, list):
        raise InputError("landmarks: 'markups' must be a list", file=file, field="markups")
    out: dict[str, np.ndarray] = {}
    for m, markup in enumerate(markups):
        where = f"markups[{m}]"
        if not isinstance(markup, dict):
            raise InputError("landmarks: a markup must be an object", file=file, field=where)
        system = str(markup.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise InputError(f"landmarks: coordinateSystem {system!r} is neither LPS nor RAS",
                             file=file, field=f"{where}.coordinateSystem")
        units = str(markup.get("coordinateUnits", "mm"))
        if units not in SLICER_UNITS_TO_MM:
            raise InputError(f"landmarks: coordinateUnits {units!r}; expected mm or um",
                             file=file, field=f"{where}.coordinateUnits")
        flip = np.array([-1.0, -1.0, 1.0]) if system == "LPS" else np.ones(3)
        points = markup.get("controlPoints", [])
        if not isinstance(points, list):
            raise InputError("landmarks: controlPoints must be a list", file=file,
                             field=f"{where}.controlPoints")
        for c, point in enumerate(points):
            field_name = f"{where}.controlPoints[{c}]"
            if not isinstance(point, dict):
                raise InputError("landmarks: a control point must be an object", file=file,
                                 field=field_name)
            if point.get("positionStatus", "defined") not in ("defined", "preview"):
                continue  # placeholder points Slicer keeps for landmarks not yet placed
            label = point.get("label")
            if not isinstance(label, str) or not label.strip():
                raise InputError("landmarks: control point without a label", file=file,
                                 field=f"{field_name}.label")
            if label in out:
                raise InputError(f"landmarks: label {label!r} appears twice", file=file,
                                 field=f"{field_name}.label")
            if "position" not in point:
                raise InputError(f"landmark {label}: no position", file=file,
                                 field=f"{field_name}.position")
            p = _point(point["position"], file, label)
            out[label] = p * flip * SLICER_UNITS_TO_MM[units]
    if not out:
        raise InputError("landmarks: the markups file holds no placed control point", file=file,
                         field="markups")
    return out


def _slicer_fcsv(path: Path) -> dict[str, np.ndarray]:
    """Slicer fiducial CSV: `# CoordinateSystem = LPS|RAS|0|1` (0 = RAS, 1 = LPS; RAS when
    absent, as in Slicer 4), `# columns = id,x,y,z,...,label,...`, one point per line."""
    import csv

    file = str(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"landmarks: unreadable file ({exc})", file=file, field="landmarks") from exc
    system, columns = "RAS", ["id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock",
                              "label", "desc", "associatedNodeID"]
    rows = []
    for line in lines:
        if line.startswith("#"):
            key, _, value = line[1:].partition("=")
            key, value = key.strip().lower(), value.strip()
            if key == "coordinatesystem":
                system = {"0": "RAS", "1": "LPS"}.get(value, value.upper())
            elif key == "columns":
                columns = [c.strip() for c in value.split(",")]
        elif line.strip():
            rows.append(line)
    if system not in ("RAS", "LPS"):
        raise InputError(f"landmarks: CoordinateSystem {system!r} is neither LPS nor RAS",
                         file=file, field="CoordinateSystem")
    if not {"x", "y", "z", "label"} <= set(columns):
        raise InputError("landmarks: the columns line lacks x, y, z or label", file=file,
                         field="columns")
    flip = np.array([-1.0, -1.0, 1.0]) if system == "LPS" else np.ones(3)
    out: dict[str, np.ndarray] = {}
    for n, values in enumerate(csv.reader(rows)):
        record = dict(zip(columns, values))
        label = record.get("label", "").strip()
        if not label:
            raise InputError(f"landmarks: point {n + 1} has no label", file=file, field="label")
        if label in out:
            raise InputError(f"landmarks: label {label!r} appears twice", file=file, field=label)
        out[label] = _point([record.get(c) for c in "xyz"], file, label) * flip
    if not out:
        raise InputError("landmarks: the fiducial file holds no point", file=file, field="landmarks")
    return out


def _check_landmarks_near_skin(landmarks: dict, skin, file: str) -> None:
    import trimesh

    if not landmarks:
        return
    from scipy.spatial import cKDTree

    names = list(landmarks)
    points = np.array([landmarks[n] for n in names])
    # The nearest vertex overestimates the distance to the surface by less than an edge, so
    # only the points it finds far are measured exactly (a triangle tree costs ~1 s on a CT skin).
    distance, _ = cKDTree(skin.vertices).query(points)
    check = distance > LANDMARK_MAX_SKIN_DISTANCE_MM
    if check.any():
        _, distance[check], _ = trimesh.proximity.closest_point(skin, points[check])
    far = distance > LANDMARK_MAX_SKIN_DISTANCE_MM
    if not far.any() and len(points) >= 3 and np.median(distance) > LANDMARK_MEDIAN_SKIN_DISTANCE_MM:
        # every accepted name is a soft-tissue landmark: together they lie on the skin (the
        # nearest-vertex distance is an upper bound, so only then is the exact one needed)
        _, exact, _ = trimesh.proximity.closest_point(skin, points)
        if np.median(exact) > LANDMARK_MEDIAN_SKIN_DISTANCE_MM:
            k = int(np.argmax(exact))
            raise InputError(f"the landmarks do not lie on the skin (median {np.median(exact):.1f} mm off, "
                             f"{names[k]} {exact[k]:.1f} mm): the skin or the landmarks are in another "
                             "frame (LPS vs RAS) or of another scan", file=file, field=f"landmarks.{names[k]}")
    if far.any():
        k = int(np.argmax(distance))
        raise InputError(f"landmark {names[k]} lies {distance[k]:.0f} mm from the skin surface "
                         f"({int(far.sum())} landmark(s) beyond {LANDMARK_MAX_SKIN_DISTANCE_MM:g} "
                         "mm): wrong coordinate system (LPS vs RAS), units, or another patient?",
                         file=file, field=f"landmarks.{names[k]}")


# ------------------------------------------------------------------------------------ anatomy
# Cell size (mm) of the skin's vertex grid used for the bone-to-skin gaps: one vertex per cell
# stands for the others, which lie within a cell diagonal of it.
GAP_CELL_MM = 1.0


def nearest_vertex_gaps(skin_vertices: np.ndarray, parts: dict, threshold: float) -> dict:
    """Per part (name -> (n, 3) points, up to 4000 of them used): the smallest distance from its
    points to the skin's vertices. Measured first against one skin vertex per `GAP_CELL_MM`
    cell (a dense scan makes nearest-neighbour searches from centimetres away slow: every
    vertex of a wide shell is a candidate), which overestimates by at most the cell diagonal;
    a part whose gap could then exceed `threshold` is measured against every vertex, so the
    test against `threshold` and the gap reported beyond it are exact."""
    from scipy.spatial import cKDTree

    from registration.surface import unique_rows

    sv = np.asarray(skin_vertices, float)
    first, _ = unique_rows(np.floor(sv / GAP_CELL_MM))
    coarse = cKDTree(sv[first]) if len(first) < len(sv) else None
    full = None
    gaps = {}
    for name, pts in parts.items():
        q = np.asarray(pts, float)[:: max(1, len(pts) // 4000)]
        if coarse is not None:
            d = float(coarse.query(q)[0].min())
            if d <= threshold - np.sqrt(3.0) * GAP_CELL_MM:
                gaps[name] = d
                continue
        if full is None:
            full = cKDTree(sv)
        gaps[name] = float(full.query(q)[0].min())
    return gaps


def _jaw_centre(bones: dict) -> np.ndarray | None:
    jaws = [np.asarray(bones[s].vertices, float) for s in ("maxilla", "mandible", "chin") if s in bones]
    return np.concatenate(jaws).mean(axis=0) if jaws else None


def face_direction(skin, jaw_centre=None) -> tuple[int, str]:
    """Which way the face looks along y: +1 (anterior, RAS), -1 (posterior: an LPS frame read
    as RAS, or a volume flipped front to back) or 0 (the surface cannot tell), with the evidence.

    Two anatomical rules, each on its own sufficient to say -1:
    - along the antero-posterior line through the jaws (`jaw_centre`, from the bone surfaces),
      the skin nearest the jaws lies behind them instead of in front;
    - on a closed skin, the nose (the narrow cap of skin within `FACE_CAP_DEPTH_MM` of the
      extreme) lies at the -y extreme, the broad cap of the back of the head at +y.
    """
    sv = np.asarray(skin.vertices, float)
    if jaw_centre is not None:
        c = np.asarray(jaw_centre, float)
        near = np.hypot(sv[:, 0] - c[0], sv[:, 2] - c[2]) < FACING_LINE_RADIUS_MM
        front = sv[near & (sv[:, 1] > c[1]), 1] - c[1]
        back = c[1] - sv[near & (sv[:, 1] < c[1]), 1]
        if len(back) and (not len(front) or back.min() < front.min()):
            return -1, "the skin in front of the jaws is behind them"
    if not skin.is_watertight:
        return 0, "an open surface has no back of the head to compare the nose with"
    y = np.asarray(skin.triangles_center, float)[:, 1]
    area = np.asarray(skin.area_faces, float)
    cap_front = float(area[y > sv[:, 1].max() - FACE_CAP_DEPTH_MM].sum())
    cap_back = float(area[y < sv[:, 1].min() + FACE_CAP_DEPTH_MM].sum())
    if cap_back * FACE_CAP_RATIO < cap_front:
        return -1, (f"the nose is at the back: the skin's -y extreme is a narrow tip ({cap_back:.0f} mm2 "
                    f"within {FACE_CAP_DEPTH_MM:g} mm) and its +y extreme a broad cap ({cap_front:.0f} mm2)")
    if cap_front * FACE_CAP_RATIO < cap_back:
        return 1, "the nose tip is the skin's +y extreme"
    return 0, "the skin's two antero-posterior extremes are alike"


def _ct_orientation_field(ct_path: Path) -> tuple[str, str]:
    """The field of a CT that sets its orientation, and how to correct it."""
    if ct_path.is_dir() or not ct_path.name.lower().endswith((".nii", ".nii.gz")):
        return ("ImageOrientationPatient",
                "the DICOM slices' ImageOrientationPatient / ImagePositionPatient put the head "
                "front to back; check the export")
    codes = ""
    try:
        import nibabel as nib

        header = nib.load(str(ct_path)).header
        codes = f" (sform_code {int(header['sform_code'])}, qform_code {int(header['qform_code'])})"
    except Exception:  # the volume was read before: only the detail of the message is lost
        pass
    return ("affine", f"the NIfTI affine{codes} maps the voxels to LPS (DICOM) coordinates or "
                      "flips them front to back; NIfTI world coordinates are RAS: negate the first "
                      "two rows of the affine (sform and qform)")


def check_face_direction(skin, file, *, jaw_centre=None, from_ct: bool = False) -> None:
    """Refuse (InputError naming `file`) a skin whose face looks along -y (`face_direction`):
    surfaces in LPS read as RAS, or a CT (`from_ct`) whose affine or slice orientation is LPS."""
    sign, evidence = face_direction(skin, jaw_centre)
    if sign >= 0:
        return
    if from_ct:
        field, fix = _ct_orientation_field(Path(file))
        raise InputError(f"the face in this CT looks along -y ({evidence}): {fix}",
                         file=str(file), field=field)
    raise InputError(f"the face looks along -y ({evidence}): the surfaces are in LPS (DICOM) "
                     "coordinates or rotated; faceplan reads RAS (negate x and y)",
                     file=str(file), field="skin")


def check_anatomy(skin, bones: dict, files: dict, landmarks: dict | None = None, *,
                  from_ct: bool = False) -> None:
    """Refuse (InputError naming the file) what cannot be a head in patient RAS mm:
    maxilla below the mandible or chin above the maxilla (bone files swapped); a jaw segment
    (maxilla, mandible, chin) whose nearest point is > 30 mm from the skin (another frame or patient); a face looking
    along -y (LPS surfaces read as RAS); an open skin whose normals point into the tissue
    (inside-out); landmarks behind the jaws or with left and right swapped (an LPS or mirrored
    landmarks file). files: 'skin', 'bone.<segment>', 'landmarks' -> path, for the messages;
    from_ct: the skin was extracted from the CT `files['skin']`."""
    from scipy.spatial import cKDTree

    def where(key):
        return str(files.get(key, key))

    z = {s: float(np.asarray(m.vertices, float)[:, 2].mean()) for s, m in bones.items()}
    for low, high in (("mandible", "maxilla"), ("chin", "maxilla"), ("maxilla", "skull")):
        if low in z and high in z and z[low] >= z[high]:
            raise InputError(f"bone.{high} lies below bone.{low} (mean height {z[high]:.0f} mm against "
                             f"{z[low]:.0f} mm): are the two bone files swapped ({where('bone.' + high)}, "
                             f"{where('bone.' + low)})?", file=where("bone." + high), field=f"bone.{high}")
    sv = np.asarray(skin.vertices, float)
    # the jaws lie under the facial skin; the skull may lie under parts a face scan leaves out
    near_face = [s for s in ("maxilla", "mandible", "chin") if s in bones] or list(bones)
    gaps = nearest_vertex_gaps(sv, {s: np.asarray(bones[s].vertices, float) for s in near_face},
                               BONE_MAX_SKIN_DISTANCE_MM)
    for s, d in gaps.items():
        if d > BONE_MAX_SKIN_DISTANCE_MM:
            raise InputError(f"bone.{s} lies {d:.0f} mm from the skin at its nearest point (soft tissue "
                             f"is at most ~25 mm thick): skin and bones are not in the same frame, "
                             "units or patient", file=where("bone." + s), field=f"bone.{s}")
    c = _jaw_centre(bones)
    check_face_direction(skin, where("skin"), jaw_centre=c, from_ct=from_ct)
    if c is None:
        return
    if not skin.is_watertight:
        # the skin nearest the jaws must face away from them
        jv = np.concatenate([np.asarray(bones[s].vertices, float) for s in ("maxilla", "mandible", "chin")
                             if s in bones])
        jv = jv[:: max(1, len(jv) // 2000)]
        _, i = cKDTree(sv).query(jv)
        i = np.unique(i)
        _, j = cKDTree(jv).query(sv[i])
        outward = np.einsum("ij,ij->i", np.asarray(skin.vertex_normals)[i], sv[i] - jv[j])
        if np.mean(outward < 0) > 0.7:
            raise InputError("the skin is inside-out: its normals point into the tissue (towards the "
                             "bones); flip the triangles' orientation when exporting", file=where("skin"),
                             field="skin")
    if landmarks:
        p = np.array(list(landmarks.values()), float)
        if np.median(p[:, 1]) < c[1]:
            k = list(landmarks)[int(np.argmin(p[:, 1]))]
            raise InputError(f"the landmarks lie behind the jaws (median y {np.median(p[:, 1]):.0f} mm, "
                             f"jaws at {c[1]:.0f} mm): LPS coordinates in a RAS file? (Slicer .mrk.json "
                             "files declare their coordinateSystem)", file=where("landmarks"),
                             field=f"landmarks.{k}")
        if "ChL" in landmarks and "ChR" in landmarks and landmarks["ChL"][0] > landmarks["ChR"][0]:
            raise InputError("ChL (the patient's left) lies on the right of ChR (RAS: +x is the "
                             "patient's right): left and right swapped, or LPS coordinates",
                             file=where("landmarks"), field="landmarks.ChL")


# ----------------------------------------------------------------------------------- case.yaml
def load_case_info(path: Path | None, default_id: str) -> CaseInfo:
    if path is None or not path.is_file():
        return CaseInfo(id=default_id)
    from planner.plan import read_yaml

    file = str(path)
    data = read_yaml(path, file)
    if data is None:
        return CaseInfo(id=default_id)
    if not isinstance(data, dict):
        raise InputError("case.yaml: expected a mapping of keys to values", file=file, field="case")
    unknown = sorted(str(k) for k in data if k not in CASE_INFO_KEYS)
    if unknown:
        raise InputError(f"case.yaml: unknown key(s) {', '.join(unknown)}; known keys are "
                         f"{', '.join(CASE_INFO_KEYS)}", file=file, field=unknown[0])
    case_id = data.get("id", default_id)
    if not isinstance(case_id, (str, int)) or isinstance(case_id, bool) or str(case_id).strip() == "":
        raise InputError(f"id must be a non-empty text, got {case_id!r}", file=file, field="id")
    months = data.get("follow_up_months")
    if months is not None:
        if isinstance(months, bool) or not isinstance(months, (int, float)) \
                or not math.isfinite(months) or months < 0:
            raise InputError(f"follow_up_months must be a number >= 0, got {months!r}",
                             file=file, field="follow_up_months")
        months = float(months)
    notes = data.get("notes", "")
    if notes is None:
        notes = ""
    if not isinstance(notes, str):
        raise InputError("notes must be text", file=file, field="notes")
    ct = data.get("ct") or {}
    if not isinstance(ct, dict):
        raise InputError("ct must be a mapping (skin_hu, bone_hu)", file=file, field="ct")
    for key, value in ct.items():
        if key not in CT_KEYS:
            raise InputError(f"ct: unknown key {key}; known keys are {', '.join(CT_KEYS)}",
                             file=file, field=f"ct.{key}")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"ct.{key} must be a number (HU), got {value!r}", file=file,
                             field=f"ct.{key}")
    if "skin_hu" in ct and "bone_hu" in ct and not ct["skin_hu"] < ct["bone_hu"]:
        raise InputError("ct.skin_hu must be below ct.bone_hu", file=file, field="ct.skin_hu")
    extra = {k: data[k] for k in data if k not in ("id", "follow_up_months", "notes")}
    return CaseInfo(id=str(case_id), follow_up_months=months, notes=notes, extra=extra)


# --------------------------------------------------------------------------------------- case
def load_case(path, *, cache: bool = True, cache_dir: str | Path | None = None) -> Case:
    """Read and check a case folder; `InputError` (file + field) on anything wrong.

    Surfaces extracted from a CT are cached by content hash (`cache_dir`, default
    `default_cache_dir()`), so that each command does not segment the CT again.
    """
    root = Path(path)
    if not root.exists():
        raise InputError("no such case folder", file=str(root), field="case")
    if not root.is_dir():
        raise InputError("a case is a folder (with preop/, plan.yaml...), not a file",
                         file=str(root), field="case")
    preop = root / "preop"
    if not preop.is_dir():
        raise InputError("the case has no preop/ folder (pre-op skin and bone surfaces or CT)",
                         file=str(preop), field="preop")

    info = load_case_info(_optional(root / "case.yaml") or _optional(root / "case.yml"), root.name)
    skin_file = _one_surface_file(preop, "skin", "skin")
    ct_path = _ct_source(preop)
    bone_dir = preop / "bone"
    has_bone_dir = bone_dir.is_dir()
    ct = None
    if skin_file is None or not has_bone_dir:
        if ct_path is None:
            missing = "skin surface (preop/skin.stl)" if skin_file is None else \
                "bone surfaces (preop/bone/<segment>.stl)"
            raise InputError(f"the case has no pre-op {missing} and no CT (preop/ct.nii.gz or "
                             "preop/ct/) to extract it from",
                             file=str(preop / ("skin.stl" if skin_file is None else "bone")),
                             field="skin" if skin_file is None else "bone")
        ct = _surfaces_from_ct(ct_path, info.extra.get("ct") or {},
                               (Path(cache_dir) if cache_dir else default_cache_dir()) if cache else None)
    if skin_file is not None:
        skin = load_surface(skin_file, "skin")
        skin_path = skin_file
    else:
        skin, skin_path = ct["skin"], ct_path
    bones = _load_bones(bone_dir) if has_bone_dir else {"bone": ct["bone"]}
    skin_from_ct = skin_file is None
    # before the landmarks are compared with it: a skin facing backwards is the skin's (or the
    # CT's) fault, not the landmarks'
    check_face_direction(skin, skin_path, from_ct=skin_from_ct)

    landmarks: dict = {}
    landmark_file = None
    for name in ("landmarks.json", "landmarks.mrk.json", "landmarks.fcsv"):
        if (preop / name).is_file():
            if landmark_file is not None:
                raise InputError(f"two landmark files ({landmark_file.name} and {name}); keep one",
                                 file=str(preop / name), field="landmarks")
            landmark_file = preop / name
    if landmark_file is not None:
        landmarks = load_landmarks(landmark_file)
        _check_landmarks_near_skin(landmarks, skin, str(landmark_file))
    if has_bone_dir:
        files = {"skin": skin_path, "landmarks": landmark_file,
                 **{f"bone.{p.name[: -len(p.suffix)]}": p for p in bone_dir.iterdir() if p.is_file()}}
        check_anatomy(skin, bones, files, landmarks, from_ct=skin_from_ct)

    plan_path = _optional(root / "plan.yaml") or _optional(root / "plan.yml")
    postop = root / "postop"
    postop_skin = _one_surface_file(postop, "skin", "postop skin") if postop.is_dir() else None
    postop_plan = _optional(postop / "plan_actual.yaml") or _optional(postop / "plan_actual.yml")
    teeth = _load_parts(preop / "teeth", "teeth") if (preop / "teeth").is_dir() else {}
    return Case(root=root, skin=skin, bones=bones, landmarks=landmarks, plan_path=plan_path,
                postop_skin_path=postop_skin, postop_plan_path=postop_plan, info=info,
                skin_path=skin_path, ct_path=ct_path, teeth=teeth)
