"""CT-like volumes from closed surfaces, to test the CT path end to end.

A head given as closed triangle surfaces (skin, bone segments) is turned into a Hounsfield-unit
volume: air -1000 HU outside the skin, soft tissue +40 HU between skin and bone, bone +1000 HU
(Hounsfield scale values as in Buzug, *Computed Tomography*, Springer 2008). Partial
volume is modelled as the exact fraction of each voxel occupied by each material: rays parallel
to the k (z) axis are cast through `supersample**2` points per voxel column, their crossings
with the surfaces are sorted and swept with the winding number (inside where > 0, so that
overlapping bone segments form their union), and each inside interval adds its exact length
to the voxels it overlaps (the scan-line voxelisation of Nooruddin & Turk 2003, IEEE TVCG 9(2),
made fractional). Values mix linearly with the fractions, optionally blurred by a Gaussian
point-spread function, plus white Gaussian noise of `noise_hu` standard deviation.

The volume can be written as NIfTI (nibabel, RAS affine) or as a DICOM CT Image Storage series
(pydicom): one file per axial slice, stored values = HU + 1024 (signed 16 bit) with
RescaleIntercept -1024,
positions and orientation in DICOM's LPS frame (x, y of RAS negated), in-plane axes ordered as
scanners do (columns towards patient Left, rows towards Posterior).
"""
from __future__ import annotations

import datetime
from pathlib import Path

import numba
import numpy as np

AIR_HU = -1000.0
TISSUE_HU = 40.0
BONE_HU = 1000.0
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


@numba.njit(cache=True)
def _crossings(tri, x0, y0, dx, dy, nx, ny, count_only, counts, offsets, z_out, s_out):
    """Crossings of the rays (p, q) (at x0 + p dx, y0 + q dy, along +z) with triangles.

    tri: (T, 3, 3). Ray r = p * ny + q. With count_only, counts[r] is incremented; otherwise
    crossing z and winding sign (+1 entering, -1 leaving) go to z_out/s_out from offsets[r].
    """
    fill = offsets.copy()
    for t in range(tri.shape[0]):
        ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
        bx, by, bz = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
        cx, cy, cz = tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue  # parallel to the rays
        p0 = int(np.ceil((min(ax, bx, cx) - x0) / dx))
        p1 = int(np.floor((max(ax, bx, cx) - x0) / dx))
        q0 = int(np.ceil((min(ay, by, cy) - y0) / dy))
        q1 = int(np.floor((max(ay, by, cy) - y0) / dy))
        p0, q0 = max(p0, 0), max(q0, 0)
        p1, q1 = min(p1, nx - 1), min(q1, ny - 1)
        for p in range(p0, p1 + 1):
            x = x0 + p * dx
            for q in range(q0, q1 + 1):
                y = y0 + q * dy
                w0 = (cx - bx) * (y - by) - (cy - by) * (x - bx)
                w1 = (ax - cx) * (y - cy) - (ay - cy) * (x - cx)
                w2 = (bx - ax) * (y - ay) - (by - ay) * (x - ax)
                if area > 0.0:
                    inside = w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0
                else:
                    inside = w0 <= 0.0 and w1 <= 0.0 and w2 <= 0.0
                if not inside:
                    continue
                r = p * ny + q
                if count_only:
                    counts[r] += 1
                else:
                    z = (w0 * az + w1 * bz + w2 * cz) / area
                    z_out[fill[r]] = z
                    s_out[fill[r]] = -1 if area > 0.0 else 1  # +z normal: the ray leaves
                    fill[r] += 1


@numba.njit(cache=True)
def _sweep(offsets, z_all, s_all, ny_rays, s, nz, z0, dz, weight, occupancy):
    """Add the inside length of every ray to the voxels of its column (fraction of a voxel)."""
    for r in range(offsets.shape[0] - 1):
        a, b = offsets[r], offsets[r + 1]
        if b - a < 2:
            continue
        order = np.argsort(z_all[a:b])
        p, q = r // ny_rays, r % ny_rays
        i, j = p // s, q // s
        wind = 0
        start = 0.0
        for m in range(b - a):
            z = z_all[a + order[m]]
            before = wind
            wind += s_all[a + order[m]]
            if before <= 0 and wind > 0:
                start = z
            elif before > 0 and wind <= 0:
                # interval [start, z] in units of voxels, voxel k spans [k - 0.5, k + 0.5]
                u0 = (start - z0) / dz + 0.5
                u1 = (z - z0) / dz + 0.5
                k0 = max(int(np.floor(u0)), 0)
                k1 = min(int(np.floor(u1)), nz - 1)
                for k in range(k0, k1 + 1):
                    lo = max(u0, k)
                    hi = min(u1, k + 1.0)
                    if hi > lo:
                        occupancy[i, j, k] += weight * (hi - lo)


def occupancy(meshes, shape, affine, supersample: int = 4) -> np.ndarray:
    """Fraction (i, j, k) of each voxel inside the union of closed, outward meshes.

    `affine` must be axis-aligned (diagonal 3x3 part, positive): voxel (i, j, k) is centred at
    origin + (i dx, j dy, k dz).
    """
    nx, ny, nz = shape
    dx, dy, dz = np.diag(affine)[:3]
    ox, oy, oz = affine[:3, 3]
    s = int(supersample)
    tri = np.concatenate([np.asarray(m.triangles, dtype=np.float64) for m in meshes])
    # Sub-ray positions: s per voxel width, centred; the tiny irrational shifts keep rays off
    # mesh edges and vertices (a ray through a shared edge would count the crossing twice).
    x0 = ox - 0.5 * dx + (0.5 + 1.2345e-5 * np.pi) * dx / s
    y0 = oy - 0.5 * dy + (0.5 + 2.3456e-5 * np.e) * dy / s
    nrx, nry = nx * s, ny * s
    counts = np.zeros(nrx * nry, dtype=np.int64)
    empty_f, empty_i = np.zeros(0), np.zeros(0, dtype=np.int8)
    _crossings(tri, x0, y0, dx / s, dy / s, nrx, nry, True, counts, np.zeros(nrx * nry + 1, np.int64),
               empty_f, empty_i)
    offsets = np.zeros(nrx * nry + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    z_all = np.empty(offsets[-1], dtype=np.float64)
    s_all = np.empty(offsets[-1], dtype=np.int8)
    _crossings(tri, x0, y0, dx / s, dy / s, nrx, nry, False, counts, offsets, z_all, s_all)
    occ = np.zeros(shape, dtype=np.float64)
    _sweep(offsets, z_all, s_all, nry, s, nz, oz, dz, 1.0 / (s * s), occ)
    return np.clip(occ, 0.0, 1.0)


def cap_holes(mesh):
    """Close every boundary loop by a fan of triangles from the loop's centroid.

    Meant for the large, nearly planar openings of head surfaces (the neck cut, a face scan's
    rim): the fan follows the loop, with the winding of the faces next to it.
    """
    import trimesh

    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = mesh.edges  # directed, as the faces run
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse.ravel()] == 1]   # edges of a single face
    if len(boundary) == 0:
        return mesh
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    loops, loop_of_edge = np.unique(label[boundary[:, 0]], return_inverse=True)
    centroids = np.array([mesh.vertices[np.unique(boundary[loop_of_edge == k])].mean(axis=0)
                          for k in range(len(loops))])
    centre_ids = n + loop_of_edge
    caps = np.column_stack([boundary[:, 1], boundary[:, 0], centre_ids])
    return trimesh.Trimesh(np.vstack([mesh.vertices, centroids]), np.vstack([mesh.faces, caps]),
                           process=True)


def is_closed_cycle(mesh) -> bool:
    """True when every edge is run as often in one direction as in the other.

    That is what the winding number needs: a closed, consistently oriented surface, pinched
    (non-manifold) edges allowed, as surface meshers leave where two thin shells touch.
    """
    edges = mesh.edges
    key = np.sort(edges, axis=1)
    forward = edges[:, 0] < edges[:, 1]
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    balance = np.bincount(inverse.ravel(), weights=np.where(forward, 1.0, -1.0))
    return bool(np.all(balance == 0))


def _closed_outward(mesh, what: str):
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), process=True)
    if not is_closed_cycle(mesh):
        mesh = cap_holes(mesh)
    if not is_closed_cycle(mesh):
        raise ValueError(f"{what} surface is not closed and its holes cannot be capped: a CT "
                         "phantom needs closed surfaces")
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def ct_volume_from_surfaces(skin, bones: dict, spacing=(1.0, 1.0, 1.0), margin: float = 10.0,
                            noise_hu: float = 20.0, seed: int = 0, *, supersample: int = 4,
                            psf_sigma_mm: float = 0.0, tissue_hu: float = TISSUE_HU,
                            bone_hu: float = BONE_HU):
    """A CT-like HU volume of a head given by closed surfaces (mm, RAS).

    Returns `(hu, affine)`: `hu` float32 (i, j, k) on an axis-aligned grid covering the skin
    (and bones) plus `margin` mm, `affine` 4x4 voxel -> RAS mm. Open surfaces (a skin cut at
    the neck) are closed first by `cap_holes`.
    """
    spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (3,))
    if np.any(spacing <= 0):
        raise ValueError(f"spacing must be positive, got {tuple(spacing)}")
    skin = _closed_outward(skin, "skin")
    bone_meshes = [_closed_outward(m, f"bone {name!r}") for name, m in bones.items()]
    lo = np.min([skin.bounds[0]] + [m.bounds[0] for m in bone_meshes], axis=0) - margin
    hi = np.max([skin.bounds[1]] + [m.bounds[1] for m in bone_meshes], axis=0) + margin
    shape = tuple(int(n) for n in np.floor((hi - lo) / spacing).astype(int) + 1)
    affine = np.eye(4)
    affine[:3, :3] = np.diag(spacing)
    affine[:3, 3] = lo

    f_skin = occupancy([skin], shape, affine, supersample)
    f_bone = occupancy(bone_meshes, shape, affine, supersample) if bone_meshes else 0.0
    f_bone = np.minimum(f_bone, f_skin)  # bone only inside the body
    hu = AIR_HU + (tissue_hu - AIR_HU) * f_skin + (bone_hu - tissue_hu) * f_bone
    if psf_sigma_mm > 0:
        from scipy.ndimage import gaussian_filter

        hu = gaussian_filter(hu, psf_sigma_mm / spacing, mode="nearest")
    if noise_hu > 0:
        hu = hu + np.random.default_rng(seed).normal(0.0, noise_hu, size=hu.shape)
    return hu.astype(np.float32), affine


# ------------------------------------------------------------------------------------ writing
def write_nifti(path, hu: np.ndarray, affine: np.ndarray) -> Path:
    """Save as NIfTI-1 (int16 HU, mm, scanner-based RAS sform and qform)."""
    import nibabel as nib

    path = Path(path)
    data = np.clip(np.rint(hu), -32768, 32767).astype(np.int16)
    img = nib.Nifti1Image(data, np.asarray(affine, float))
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    img.header.set_xyzt_units("mm")
    img.header.set_slope_inter(1.0, 0.0)
    path.parent.mkdir(parents=True, exist_ok=True)
    nib.save(img, str(path))
    return path


def _ds_number(x: float) -> str:
    """A DICOM decimal string (at most 16 characters)."""
    text = f"{x:.10g}"
    return text if len(text) <= 16 else f"{x:.6e}"


def write_dicom_series(folder, hu: np.ndarray, affine: np.ndarray, *, patient_id: str = "PHANTOM",
                       series_description: str = "faceplan CT phantom") -> Path:
    """Save as a DICOM CT Image Storage series, one file per slice along k (LPS positions).

    The in-plane axes of `affine` must be orthogonal; the slice axis may be tilted.
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    folder = Path(folder)
    hu = np.asarray(hu)
    a_lps = LPS_TO_RAS @ np.asarray(affine, float)
    # Conventional axial orientation: columns increase towards +L, rows towards +P.
    for axis in (0, 1):
        col = a_lps[:3, axis]
        if col[np.argmax(np.abs(col))] < 0:
            hu = np.flip(hu, axis=axis)
            a_lps[:3, 3] += a_lps[:3, axis] * (hu.shape[axis] - 1)
            a_lps[:3, axis] = -a_lps[:3, axis]
    d_col, d_row = np.linalg.norm(a_lps[:3, 0]), np.linalg.norm(a_lps[:3, 1])
    row_dir, col_dir = a_lps[:3, 0] / d_col, a_lps[:3, 1] / d_row
    if abs(row_dir @ col_dir) > 1e-6:
        raise ValueError("DICOM needs orthogonal in-plane axes (columns i and rows j)")
    normal = np.cross(row_dir, col_dir)
    step = a_lps[:3, 2]
    thickness = abs(step @ normal)

    stored = np.clip(np.rint(hu) + 1024, -32768, 32767).astype(np.int16)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    now = datetime.datetime.now()
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(hu.shape[2]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CT_IMAGE_STORAGE
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.Modality = "CT"
        ds.Manufacturer = "faceplan"
        ds.PatientName = patient_id
        ds.PatientID = patient_id
        ds.PatientBirthDate = ds.PatientSex = ""
        ds.ReferringPhysicianName = ds.AccessionNumber = ""
        ds.StudyID = "1"
        ds.PositionReferenceIndicator = ""
        ds.KVP = ""
        ds.AcquisitionNumber = 1
        ds.PatientPosition = "HFS"
        ds.StudyDate = ds.SeriesDate = now.strftime("%Y%m%d")
        ds.StudyTime = ds.SeriesTime = now.strftime("%H%M%S")
        ds.SeriesDescription = series_description
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.SeriesNumber = 1
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [_ds_number(v) for v in a_lps[:3, 3] + k * step]
        ds.ImageOrientationPatient = [_ds_number(v) for v in (*row_dir, *col_dir)]
        ds.PixelSpacing = [_ds_number(d_row), _ds_number(d_col)]
        ds.SliceThickness = _ds_number(thickness)
        ds.SpacingBetweenSlices = _ds_number(thickness)
        ds.SliceLocation = _ds_number(float((a_lps[:3, 3] + k * step) @ normal))
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.Rows, ds.Columns = hu.shape[1], hu.shape[0]
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
        ds.PixelRepresentation = 1  # signed: values below -1024 HU (noise in air) survive
        ds.RescaleIntercept = "-1024"
        ds.RescaleSlope = "1"
        ds.RescaleType = "HU"
        ds.WindowCenter, ds.WindowWidth = "40", "400"
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T).tobytes()
        path = folder / f"CT{k + 1:05d}.dcm"
        if int(pydicom.__version__.split(".")[0]) >= 3:
            ds.save_as(path, enforce_file_format=True)
        else:
            ds.is_little_endian, ds.is_implicit_VR = True, False
            ds.save_as(path, write_like_original=False)
    return folder
