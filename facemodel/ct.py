"""CT volume -> skin and bone isosurfaces, in mm and patient RAS.

A CT volume is read either from a NIfTI file (nibabel; its affine already maps voxel indices to
RAS mm) or from a DICOM series folder (pydicom): slices are sorted by their ImagePositionPatient
projected on the slice normal (ImageOrientationPatient row x column cosines), stored values are
mapped to Hounsfield units with RescaleSlope/RescaleIntercept, and the voxel -> world affine is
built from ImageOrientationPatient, PixelSpacing and the slice positions, then converted from
DICOM's LPS frame to RAS (x -> -x, y -> -y).

Surfaces are isosurfaces (Lorensen & Cline 1987 marching cubes, Lewiner et al. 2003 variant in
scikit-image) at standard Hounsfield thresholds. The Hounsfield scale puts air at -1000 HU, fat
at -100...-50 HU, soft tissue at +20...+80 HU, cancellous bone at about +300...+700 HU and
cortical bone above +1000 HU (Hounsfield 1973, Br J Radiol 46:1016-1022; Buzug, *Computed
Tomography*, Springer 2008). The skin isosurface is taken at -400 HU: near the half-maximum
between air and the subcutaneous tissue (fat ... soft tissue, -100...+40 HU), which places a
partial-volume edge at its true position (the half-maximum-height principle, Spoor, Zonneveld &
Macho 1993, Am J Phys Anthropol 91:469-484). Bone is taken at +300 HU, the usual single
threshold for craniofacial bone models from CT (Friedli et al., Sci Rep 2020, studied the
effect of moving it). Before the skin is extracted, air lying deeper than a few mm inside the
body's outer envelope (a morphological closing: nasal cavity, sinuses, pharynx, trachea, all
open to the outside through the nostrils) is filled, so that the skin does not line the
airways; the skin keeps only the connected component enclosing the largest volume (the scanner
table is dropped); bone keeps every component of a sizeable area that lies inside the skin and
encloses material (marrow cavities, whose marching-cubes shells face inwards, are dropped), so
that a mandible separate from the skull is not lost. The surface is cleaned (merged vertices,
no degenerate or duplicate faces, normals outward) and optionally smoothed with Taubin's
lambda|mu filter (Taubin 1995, SIGGRAPH), which removes the marching-cubes staircase without
the shrinkage of plain Laplacian smoothing, and on request decimated (quadric error metric,
Garland & Heckbert 1997) to a triangle budget.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facemodel.errors import CTError

__all__ = ["CTError", "CTVolume", "CTSurfaces", "read_ct", "read_nifti", "read_dicom_series",
           "check_hounsfield", "isosurface", "skin_surface", "bone_surface", "body_mask",
           "decimate", "seal_airways", "ct_surfaces", "SKIN_HU", "BONE_HU", "AIR_HU"]

AIR_HU = -1000.0
SKIN_HU = -400.0
BONE_HU = 300.0
# Lowest value a CT in Hounsfield units must reach somewhere: the air around the patient is
# at -1000 HU, so a volume whose minimum stays above this is not in HU (an MR, a PNG stack,
# a volume normalised to [0, 1], or raw stored values without their rescale intercept).
AIR_MAX_HU = -500.0
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse
# Airway sealing: the body's envelope is its closing by a ball of this radius, wide enough to
# span an adult nostril (about 1 cm across) or a parted mouth; air deeper than
# AIRWAY_DEPTH_MM inside the envelope is airway, shallower is a fold of the face.
AIRWAY_CLOSING_MM = 10.0
AIRWAY_DEPTH_MM = 5.0
SEAL_VOXEL_MM = 2.0   # voxel size of the sealing's distance transforms (finer CTs are pooled)

NIFTI_SUFFIXES = (".nii", ".nii.gz")


@dataclass(frozen=True)
class CTVolume:
    """Hounsfield units on a voxel grid: `hu[i, j, k]` sits at `affine @ (i, j, k, 1)` (mm RAS)."""

    hu: np.ndarray
    affine: np.ndarray
    source: str = ""

    @property
    def spacing(self) -> np.ndarray:
        """Voxel edge lengths (mm) along i, j, k."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def to_world(self, ijk: np.ndarray) -> np.ndarray:
        """Voxel coordinates (..., 3) -> RAS mm (..., 3)."""
        ijk = np.asarray(ijk, dtype=float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def to_voxel(self, xyz: np.ndarray) -> np.ndarray:
        """RAS mm (..., 3) -> continuous voxel coordinates (..., 3)."""
        xyz = np.asarray(xyz, dtype=float)
        return (xyz - self.affine[:3, 3]) @ np.linalg.inv(self.affine[:3, :3]).T


@dataclass(frozen=True)
class CTSurfaces:
    """Skin and bone isosurfaces extracted from one CT volume."""

    skin: "trimesh.Trimesh"  # noqa: F821
    bone: "trimesh.Trimesh"  # noqa: F821
    volume: CTVolume


# ----------------------------------------------------------------------------------- reading
def read_ct(path: str | Path) -> CTVolume:
    """Read a CT volume from a NIfTI file or a DICOM series folder (or one of its files),
    checked to be in HU."""
    path = Path(path)
    if path.is_dir():
        volume = read_dicom_series(path)
    elif path.is_file():
        if path.name.lower().endswith(NIFTI_SUFFIXES):
            volume = read_nifti(path)
        elif _is_dicom_file(path):  # one slice named: the series is its folder
            volume = read_dicom_series(path.parent)
        else:
            raise CTError("not a CT volume: expected a NIfTI file (.nii, .nii.gz) or a DICOM "
                          "series folder", path)
    else:
        raise CTError("no such file or folder", path)
    check_hounsfield(volume)
    return volume


def _is_dicom_file(path: Path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(132)
    return path.suffix.lower() in (".dcm", ".dicom") or head[128:132] == b"DICM"


def read_nifti(path: str | Path) -> CTVolume:
    """A NIfTI volume as float32 HU with its voxel -> RAS affine (scaling applied by nibabel)."""
    import nibabel as nib

    try:
        img = nib.load(str(path))
        hu = np.asarray(img.get_fdata(dtype=np.float32))
        affine = np.asarray(img.affine, dtype=float)
    except Exception as exc:  # nibabel raises many kinds (ImageFileError, EOFError, zlib.error...)
        raise CTError(f"cannot read NIfTI file ({type(exc).__name__}: {exc})", path) from exc
    while hu.ndim > 3 and hu.shape[-1] == 1:
        hu = hu[..., 0]
    if hu.ndim != 3:
        raise CTError(f"expected a 3-D volume, got an array of shape {hu.shape}", path)
    _check_affine(affine, path)
    return CTVolume(hu=hu, affine=affine, source=str(path))


def _check_affine(affine: np.ndarray, file) -> None:
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise CTError("the voxel-to-world transform (affine) is singular or not finite", file)


def read_dicom_series(folder: str | Path) -> CTVolume:
    """One DICOM CT series from a folder: slices sorted along the normal, HU, RAS affine."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    folder = Path(folder)
    slices = []
    files = sorted(p for p in folder.rglob("*") if p.is_file()
                   and not any(part.startswith(".") for part in p.relative_to(folder).parts))
    for f in files:
        try:
            ds = pydicom.dcmread(f)
        except (InvalidDicomError, OSError, EOFError, ValueError, TypeError, AttributeError):
            continue  # not a DICOM file (a README, a thumbnail...): ignored like viewers do
        if "PixelData" not in ds:
            continue  # DICOMDIR, structured reports...
        if "LOCALIZER" in [str(v).upper() for v in getattr(ds, "ImageType", [])]:
            continue  # scout views are not part of the volume
        if int(getattr(ds, "NumberOfFrames", 1) or 1) > 1:
            raise CTError("multi-frame (enhanced) DICOM is not supported: export the CT as a "
                          "series of single-slice files", f)
        slices.append((f, ds))
    if not slices:
        raise CTError("no DICOM image files in this folder", folder)

    modalities = {str(getattr(ds, "Modality", "CT")) for _, ds in slices}
    if modalities != {"CT"}:
        raise CTError(f"modality {', '.join(sorted(modalities))}: not a CT series", folder)
    series: dict[str, list] = {}
    for f, ds in slices:
        series.setdefault(str(getattr(ds, "SeriesInstanceUID", "")), []).append(ds)
    if len(series) > 1:
        listing = "; ".join(f"{len(v)} slices '{getattr(v[0], 'SeriesDescription', '')}'"
                            for v in series.values())
        raise CTError(f"inconsistent DICOM series: the folder mixes {len(series)} series "
                      f"(SeriesInstanceUID: {listing}); put one series per folder", folder)
    for attr in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"):
        for f, ds in slices:
            if attr not in ds:
                raise CTError(f"DICOM slice without {attr}", f)
    if len(slices) < 2:
        raise CTError("a single DICOM slice is not a volume", folder)

    orient = np.array([[float(v) for v in ds.ImageOrientationPatient] for _, ds in slices])
    spacing = np.array([[float(v) for v in ds.PixelSpacing] for _, ds in slices])
    shapes = {(int(ds.Rows), int(ds.Columns)) for _, ds in slices}
    if np.abs(orient - orient[0]).max() > 1e-4:
        raise CTError("inconsistent DICOM series: slices have different ImageOrientationPatient",
                      folder)
    if np.abs(spacing - spacing[0]).max() > 1e-4:
        raise CTError("inconsistent DICOM series: slices have different PixelSpacing", folder)
    if len(shapes) > 1:
        raise CTError(f"inconsistent DICOM series: slices of different sizes {sorted(shapes)}",
                      folder)
    row_dir, col_dir = orient[0, :3], orient[0, 3:]
    if abs(np.linalg.norm(row_dir) - 1) > 1e-3 or abs(np.linalg.norm(col_dir) - 1) > 1e-3 \
            or abs(row_dir @ col_dir) > 1e-3:
        raise CTError("ImageOrientationPatient is not two orthonormal direction cosines", folder)
    normal = np.cross(row_dir, col_dir)

    positions = np.array([[float(v) for v in ds.ImagePositionPatient] for _, ds in slices])
    order = np.argsort(positions @ normal, kind="stable")
    slices = [slices[i] for i in order]
    positions = positions[order]
    depth = positions @ normal
    gaps = np.diff(depth)
    step = float(np.median(gaps))
    if gaps.min() < 1e-3:
        k = int(np.argmin(gaps))
        raise CTError(f"inconsistent DICOM series: two slices at the same position "
                      f"({slices[k][0].name}, {slices[k + 1][0].name})", folder)
    # Tolerance: 1 % of the slice step (plus 1 micron for rounding of DS strings) -- a missing
    # slice doubles one gap, far outside it; reconstruction jitter stays well inside.
    uneven = np.abs(gaps - step) > 0.01 * step + 1e-3
    if uneven.any():
        k = int(np.argmax(uneven))
        raise CTError(f"inconsistent DICOM series: uneven slice spacing ({gaps[k]:.3f} mm between "
                      f"{slices[k][0].name} and {slices[k + 1][0].name}, {step:.3f} mm elsewhere; "
                      "missing slice?)", folder)
    # In-plane offsets of the positions must follow one straight line (a gantry tilt is
    # allowed: a constant step vector); anything else is not one volume.
    step_vec = (positions[-1] - positions[0]) / (len(slices) - 1)
    line = positions[0] + np.arange(len(slices))[:, None] * step_vec
    if np.abs(positions - line).max() > 0.01 * abs(step) + 1e-3:
        raise CTError("inconsistent DICOM series: slice positions are not on a straight line",
                      folder)

    rows, cols = shapes.pop()
    hu = np.empty((cols, rows, len(slices)), dtype=np.float32)
    for k, (f, ds) in enumerate(slices):
        try:
            pixels = ds.pixel_array
        except Exception as exc:  # missing decoder for a compressed transfer syntax, bad data
            raise CTError(f"cannot decode the pixel data ({type(exc).__name__}: {exc})", f) from exc
        if pixels.shape != (rows, cols):
            raise CTError(f"pixel data of shape {pixels.shape}, expected {(rows, cols)}", f)
        slope = float(getattr(ds, "RescaleSlope", 1.0))
        intercept = float(getattr(ds, "RescaleIntercept", 0.0))
        hu[:, :, k] = (pixels.astype(np.float32) * slope + intercept).T

    d_row, d_col = spacing[0]  # PixelSpacing = (between rows, between columns)
    affine_lps = np.eye(4)
    affine_lps[:3, 0] = row_dir * d_col   # i: along a row = increasing column index
    affine_lps[:3, 1] = col_dir * d_row   # j: along a column = increasing row index
    affine_lps[:3, 2] = step_vec
    affine_lps[:3, 3] = positions[0]
    affine = LPS_TO_RAS @ affine_lps
    _check_affine(affine, folder)
    return CTVolume(hu=hu, affine=affine, source=str(folder))


def check_hounsfield(volume: CTVolume, skin_hu: float = SKIN_HU) -> None:
    """Refuse volumes that are empty or whose values are not Hounsfield units."""
    hu, file = volume.hu, volume.source or None
    if hu.size == 0 or min(hu.shape) < 2:
        raise CTError(f"empty volume (shape {hu.shape})", file)
    if not np.all(np.isfinite(hu)):
        raise CTError("the volume holds NaN or infinite values", file)
    lo, hi = float(hu.min()), float(hu.max())
    if hi - lo < 1e-6:
        raise CTError(f"empty volume: every voxel is {lo:g}", file)
    if lo > AIR_MAX_HU:
        hint = ""
        if lo >= -50 and hi > 1000:
            hint = ("; stored values without their rescale intercept? (air would be at 0 and "
                    "water at 1024: subtract 1024)")
        raise CTError(f"not a CT in Hounsfield units: values range {lo:.4g} ... {hi:.4g}, with no "
                      f"air (below {AIR_MAX_HU:g} HU; air is -1000 HU){hint}", file)
    if hi < skin_hu:
        raise CTError(f"empty volume: nothing but air (no value above {skin_hu:g} HU)", file)


# ----------------------------------------------------------------------------- isosurfaces
def _marching_cubes(volume: CTVolume, level: float):
    """Closed isosurface of the volume padded with air: vertices in RAS, faces outward."""
    from skimage.measure import marching_cubes

    pad = min(float(volume.hu.min()), level - 1.0)
    padded = np.pad(volume.hu, 1, mode="constant", constant_values=pad)
    verts, faces, _, _ = marching_cubes(padded, level=level, allow_degenerate=False)
    verts = volume.to_world(verts - 1.0)
    if np.linalg.det(volume.affine[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return verts, faces


def _components(mesh):
    """Label of the connected component (through shared edges) of each face."""
    import trimesh

    return trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))


def _clean(mesh, smooth_iterations: int, max_faces: int | None = None):
    import trimesh

    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    mesh.merge_vertices()
    if smooth_iterations > 0:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=int(smooth_iterations))
    if max_faces is not None and len(mesh.faces) > max_faces:
        mesh = decimate(mesh, max_faces)
    return mesh


def decimate(mesh, max_faces: int):
    """Quadric-error decimation (Garland & Heckbert 1997; VTK's vtkQuadricDecimation with
    volume preservation) down to about `max_faces` triangles, cleaned, normals outward."""
    import pyvista as pv
    import trimesh

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, float), faces)
    reduced = poly.decimate(1.0 - max_faces / len(mesh.faces), volume_preservation=True)
    out = trimesh.Trimesh(np.asarray(reduced.points, float),
                          reduced.faces.reshape(-1, 4)[:, 1:], process=True)
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    if out.volume < 0:
        out.invert()
    return out


def isosurface(volume: CTVolume, level: float, *, keep: str = "largest",
               min_area_fraction: float = 0.02, inside: np.ndarray | None = None,
               smooth_iterations: int = 10, max_faces: int | None = None):
    """Cleaned isosurface at `level` HU as a `trimesh.Trimesh` (mm, RAS, normals outward).

    keep="largest": only the connected component enclosing the largest volume. keep="objects": every
    component that encloses material (positive volume) with an area of at least
    `min_area_fraction` of the largest, and, when `inside` (a boolean voxel mask) is given,
    whose vertices lie mostly inside it. With `max_faces`, larger surfaces are decimated.
    """
    import trimesh

    verts, faces = _marching_cubes(volume, level)
    if len(faces) == 0:
        raise CTError(f"no isosurface at {level:g} HU", volume.source or None)
    mesh = trimesh.Trimesh(verts, faces, process=True)
    labels = _components(mesh)
    area = np.bincount(labels, weights=mesh.area_faces)
    # Orientation: marching cubes faces point from high to low values, so objects enclose a
    # positive volume and cavities a negative one. The largest component is an object.
    signed = _component_volumes(mesh, labels)
    if signed[np.argmax(area)] < 0:
        mesh.invert()
        signed = -signed
    if keep == "largest":
        kept = np.array([np.argmax(signed)])  # largest enclosed volume: the body, not a table
    elif keep == "objects":
        ok = (signed > 0) & (area >= min_area_fraction * area.max())
        if inside is not None:
            ok &= _mostly_inside(volume, mesh, labels, inside)
        kept = np.flatnonzero(ok)
        if len(kept) == 0:
            raise CTError(f"no closed structure at {level:g} HU", volume.source or None)
    else:
        raise ValueError(f"keep must be 'largest' or 'objects', not {keep!r}")
    mesh.update_faces(np.isin(labels, kept))
    mesh.remove_unreferenced_vertices()
    return _clean(mesh, smooth_iterations, max_faces)


def _component_volumes(mesh, labels) -> np.ndarray:
    """Signed enclosed volume per component (divergence theorem over its triangles)."""
    tri = mesh.triangles
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    return np.bincount(labels, weights=vol)


def _mostly_inside(volume: CTVolume, mesh, labels, inside: np.ndarray) -> np.ndarray:
    ijk = np.rint(volume.to_voxel(mesh.vertices)).astype(int)
    ijk = np.clip(ijk, 0, np.array(inside.shape) - 1)
    vert_in = inside[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    face_in = vert_in[mesh.faces].all(axis=1)
    n = np.bincount(labels)
    return np.bincount(labels, weights=face_in) >= 0.5 * n


def body_mask(volume: CTVolume, level: float = SKIN_HU, margin: int = 2) -> np.ndarray:
    """Voxels of the largest connected body above `level`, enclosed cavities filled, dilated
    by `margin` voxels (boolean (i, j, k))."""
    from scipy import ndimage

    tissue = volume.hu > level
    labels, n = ndimage.label(tissue)
    if n == 0:
        return tissue
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    body = labels == np.argmax(sizes)
    body = ndimage.binary_fill_holes(body)
    return ndimage.binary_dilation(body, iterations=margin) if margin > 0 else body


def seal_airways(volume: CTVolume, level: float = SKIN_HU, *, closing_mm: float = AIRWAY_CLOSING_MM,
                 depth_mm: float = AIRWAY_DEPTH_MM, fill_hu: float = 40.0) -> CTVolume:
    """The volume with the air deep inside the body turned to soft tissue (`fill_hu`).

    The outer envelope of the body is its morphological closing by a ball of `closing_mm`
    (it spans the nostrils, an open mouth, the trachea's cut), holes filled; air more than `depth_mm`
    inside that envelope -- nasal cavity, sinuses, pharynx, trachea -- is filled, so that the
    skin isosurface stops a few mm inside the nostrils instead of lining the airways. Air in
    the folds of the face (nasolabial, alar, mentolabial) stays: it lies within `depth_mm` of
    the envelope. Closing and erosion are thresholds of Euclidean distance transforms
    (scipy.ndimage), erosion by R then by d being erosion by R + d.
    """
    from scipy import ndimage

    body = body_mask(volume, level, margin=0)
    # The envelope is a 10 mm-scale shape: the distance transforms run on voxels of about
    # SEAL_VOXEL_MM (f x f x f blocks, a block is body if any voxel is), and the depth
    # threshold grows by one coarse voxel so that pooling never makes a fold look deeper.
    f = np.maximum(1, np.floor(SEAL_VOXEL_MM / volume.spacing)).astype(int)
    spacing = volume.spacing * f
    shape = np.array(body.shape)
    blocks = -(-shape // f)
    pooled = np.zeros(blocks * f, dtype=bool)
    pooled[: shape[0], : shape[1], : shape[2]] = body
    pooled = pooled.reshape(blocks[0], f[0], blocks[1], f[1], blocks[2], f[2]).any(axis=(1, 3, 5))
    pad = int(np.ceil((closing_mm + depth_mm) / spacing.min())) + 2
    pooled = np.pad(pooled, pad)
    dilated = ndimage.distance_transform_edt(~pooled, sampling=spacing) <= closing_mm
    # Cavities wider than the closing ball (pharynx, sinuses) stay holes of the dilated body
    # once the openings are spanned: they are inside the envelope too.
    dilated = ndimage.binary_fill_holes(dilated)
    depth = ndimage.distance_transform_edt(dilated, sampling=spacing)[pad:-pad, pad:-pad, pad:-pad]
    deep = depth > closing_mm + depth_mm + (spacing.max() if f.max() > 1 else 0.0)
    for axis in range(3):
        deep = np.repeat(deep, f[axis], axis=axis)
    deep = deep[: shape[0], : shape[1], : shape[2]]
    fill = deep & (volume.hu < level)
    if not fill.any():
        return volume
    hu = volume.hu.copy()
    hu[fill] = fill_hu
    return CTVolume(hu=hu, affine=volume.affine, source=volume.source)


def skin_surface(volume: CTVolume, level: float = SKIN_HU, smooth_iterations: int = 10,
                 max_faces: int | None = None, seal: bool = True):
    """The skin: the air/tissue isosurface enclosing the largest volume, with the airways
    sealed first (`seal_airways`) unless `seal=False`."""
    if seal:
        volume = seal_airways(volume, level)
    return isosurface(volume, level, keep="largest", smooth_iterations=smooth_iterations,
                      max_faces=max_faces)


def bone_surface(volume: CTVolume, level: float = BONE_HU, skin_level: float = SKIN_HU,
                 smooth_iterations: int = 10, min_area_fraction: float = 0.02,
                 max_faces: int | None = None):
    """The bones: every sizeable closed bone isosurface inside the body (one mesh)."""
    if float(volume.hu.max()) <= level:
        raise CTError(f"no bone: no value above {level:g} HU", volume.source or None)
    return isosurface(volume, level, keep="objects", min_area_fraction=min_area_fraction,
                      inside=body_mask(volume, skin_level), smooth_iterations=smooth_iterations,
                      max_faces=max_faces)


def ct_surfaces(source, *, skin_hu: float = SKIN_HU, bone_hu: float = BONE_HU,
                smooth_iterations: int = 10, max_faces: int | None = None,
                seal: bool = True) -> CTSurfaces:
    """Skin and bone surfaces of a CT (a path to NIfTI / DICOM folder, or a `CTVolume`).

    `max_faces` caps the triangle count of each surface (quadric decimation): a 0.5 mm CT
    gives a skin of over a million triangles, more than registration needs. `seal` fills
    the airways before the skin is extracted (`seal_airways`).
    """
    volume = source if isinstance(source, CTVolume) else read_ct(source)
    if isinstance(source, CTVolume):
        check_hounsfield(volume, skin_hu)
    skin = skin_surface(volume, skin_hu, smooth_iterations, max_faces, seal=seal)
    bone = bone_surface(volume, bone_hu, skin_hu, smooth_iterations, max_faces=max_faces)
    return CTSurfaces(skin=skin, bone=bone, volume=volume)
