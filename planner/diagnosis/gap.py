"""Where the prediction misses: the gap between a predicted skin and the post-op scan.

The scan is superimposed on the baseline prediction's unoperated regions and measured against
it by `faceplan compare` (`planner.compare.compare_surfaces`: trimmed point-to-plane ICP,
exact signed point-to-surface distances, positive where the real face is fuller than
predicted, area weights). A scan is refused as another patient's when the superimposition
residual exceeds 3 mm (compare's rule) or when less than half of it lies within 2 mm of the
predicted face once superimposed. The scan points that overlap the baseline prediction are then kept
fixed, so that every candidate prediction (an effect added) is measured on the same points with
the same weights: `ScanGap.distances(skin)`, with the scan's pose re-fitted to that prediction
on the trimmed unoperated points (`ScanGap.repose`: Gauss-Newton steps of the point-to-plane fit
at fresh closest points), since an effect can move the regions the superimposition rests on.
The gap's derivatives (`ScanGap.linearised`) re-fit the pose to first order about the
baseline's (`ScanGap.realign`).

The noise floor comes from the data: the larger of the superimposition residual on the
unoperated regions (scanner noise plus what registration leaves there) and the scan's own
roughness (the residual of a local quadric fitted to each vertex's neighbourhood, corrected for
the fit's six degrees of freedom). A region's gap is `significant` when its systematic part
exceeds the floor, rms^2 - sigma^2 >= sigma^2 (a miss as large as the noise itself), and its
area-weighted mean square exceeds sigma^2 by more than three standard deviations of a mean
square of independent Gaussian noise, sigma^2 (1 + 3 sqrt(2 / n_eff)), n_eff the region's
independent samples (below). Spatially correlated residuals carry fewer independent samples than points:
n_eff = area / (pi l^2) with l the distance at which the gap's empirical correlogram first falls
below 1/e (Cressie, *Statistics for spatial data*, 1993, ch. 2), at least the scan's spacing.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner.compare.alignment import apply, point_to_plane_step, rigid_basis
from planner.compare.comparison import check_same_patient, compare_surfaces
from planner.compare.distances import TriangleSurface, vertex_areas
from planner.compare.inputs import Prediction as ComparePrediction
from planner.compare.inputs import Surface
from planner.compare.metrics import distance_metrics
from planner.errors import InputError

__all__ = ["ScanGap", "measure_gap", "scan_roughness", "correlation_length", "MIN_COVERAGE"]

MIN_FACE_MATCH = 0.5         # share of the scan within 2 mm of the face once superimposed
MIN_COVERAGE = 0.20          # a scan covering less of the modelled face gets a warning
REGION_COVERED = 0.25        # a region with less of its area covered is reported uncovered
REALIGN_KEEP = 0.9           # unoperated points kept for the pose (compare's trimmed ICP keeps 0.9)
# the pose of a full prediction's gap (`ScanGap.distances_to`): Gauss-Newton steps of the
# point-to-plane fit at fresh closest points, until a step moves the unoperated points by less
# than REPOSE_TOL_MM (RMS) or after REPOSE_STEPS steps. A prediction that moves the superimposed
# regions can need a pose millimetres away from the baseline's, mostly along those regions'
# surfaces, where the fit about the baseline's closest points is not its first order
REPOSE_STEPS = 8
REPOSE_TOL_MM = 1e-3


@dataclass
class ScanGap:
    """The post-op scan of one case, superimposed and restricted to where it meets the face."""

    points: np.ndarray            # (n, 3) scan vertices in the pre-op frame
    weights: np.ndarray           # (n,) scan area per point (mm^2)
    region: np.ndarray            # (n,) region index
    region_names: tuple[str, ...]
    faces: np.ndarray             # the predicted skin's triangles (vertex order of CaseModel)
    alignment: dict
    roughness_mm: float
    noise_floor_mm: float
    correlation_mm: float
    coverage: float               # covered fraction of the modelled face's area
    region_coverage: dict
    baseline_metrics: dict        # the contract's `metrics` block of the baseline
    scan_vertices: np.ndarray     # the whole aligned scan (pictures)
    scan_faces: np.ndarray
    scan_valid: np.ndarray | None = None   # which scan vertices are the points
    scan_path: str = ""
    warnings: list[str] = field(default_factory=list)
    unoperated: np.ndarray | None = None   # (n,) points on the unoperated regions (the pose)
    surface: object = None        # forward.PatientSurface: the faces are the patient's skin's
    discrepancy_mm: float = 0.0   # model-form discrepancy amplitude (`discrepancy`), once estimated
    discrepancy_ell_mm: float = 0.0
    mesh_error_mm: float = 0.0    # RMS of the estimated discretisation error (`discrepancy`), once estimated
    mesh_offset: np.ndarray | None = None  # that error on the points, taken out of every gap (`distances`)
    error_test: object = None     # (r, mask) -> p-value of the gap under noise + discrepancy

    @property
    def error_level_mm(self) -> float:
        """RMS of the gap expected without any effect: noise and discrepancy together."""
        return float(np.hypot(self.noise_floor_mm, self.discrepancy_mm))

    def on_scan(self, r: np.ndarray) -> np.ndarray:
        """Values on the fixed points spread to every scan vertex (NaN elsewhere)."""
        out = np.full(len(self.scan_vertices), np.nan)
        out[self.scan_valid] = r
        return out

    def linearised(self, skin: np.ndarray, dskin: np.ndarray, pose: bool = True) -> np.ndarray:
        """d(distances)/dp for skin vertex velocities `dskin` (n_skin, 3) about `skin`: the
        closest point moves with its triangle's barycentric combination of the vertices'."""
        key = id(skin)
        if getattr(self, "_lin_key", None) != key:
            self._lin = self._closest_with_direction(self.vertices(skin), self.faces)
            self._lin_key = key
        dskin = np.asarray(dskin, float)
        if self.surface is not None:
            dskin = self.surface.carry_velocity(dskin)
        out = self._distance_velocity(self._lin, self.faces, dskin)
        return self.realign(out) if pose else out

    def linearised_on(self, vertices: np.ndarray, faces: np.ndarray, dvertices: np.ndarray,
                      pose: bool = True) -> np.ndarray:
        """d(distances_to(vertices, faces))/dp for vertex velocities `dvertices`: the same
        linearisation as `linearised`, on another predicted face (a second mesh's)."""
        cp = self._closest_with_direction(np.asarray(vertices, float), np.asarray(faces))
        out = self._distance_velocity(cp, np.asarray(faces), np.asarray(dvertices, float))
        return self.realign(out) if pose else out

    def _closest_with_direction(self, vertices, faces):
        """`_closest_with_direction` of the scan points on (vertices, faces)."""
        return _closest_with_direction(TriangleSurface(vertices, faces), self.points)

    @staticmethod
    def _distance_velocity(closest, faces, dvertices):
        """-u . dc with dc the closest point's velocity, its triangle's barycentric combination
        of the vertex velocities; `closest` from `_closest_with_direction`."""
        cp, u = closest
        dc = np.einsum("nj,njk->nk", cp.bary, dvertices[faces[cp.face]])
        return -np.einsum("nk,nk->n", u, dc)

    def distances(self, skin: np.ndarray, pose: bool = True) -> np.ndarray:
        """Signed distances (post-op minus prediction) of the fixed scan points to `skin`, with
        the scan superimposed on this prediction's unoperated regions (`realign`; `pose` False:
        in the baseline's superimposition), less the mesh's estimated discretisation error
        (`mesh_offset`) once it is known."""
        d = self.distances_to(self.vertices(skin), self.faces, pose)
        return d if self.mesh_offset is None else d - self.mesh_offset

    def distances_to(self, vertices: np.ndarray, faces: np.ndarray, pose: bool = True) -> np.ndarray:
        """Signed distances of the fixed scan points to another predicted face (vertices,
        faces): in the baseline's superimposition (`pose` False), or with the scan's pose
        re-fitted on the unoperated regions to this face (`repose`): the gap a prediction of
        the same case, or on another mesh, leaves on the same points."""
        surface = TriangleSurface(np.asarray(vertices, float), np.asarray(faces))
        return self.repose(surface) if pose else surface.closest(self.points).signed

    def repose(self, surface: TriangleSurface) -> np.ndarray:
        """The distances of the scan points to `surface` with the scan's pose re-fitted on the
        trimmed unoperated points (`fix_pose`; the baseline's pose without them): the rigid
        motion of the scan that `realign` fits to first order, solved by Gauss-Newton steps of
        the same point-to-plane fit at fresh closest points (`REPOSE_STEPS`, each compare's ICP
        step `point_to_plane_step`, area-weighted). Its first step is `realign`'s, so the two
        agree to first order about the baseline, and the Jacobians (`linearised`) keep the
        linear map."""
        pose = getattr(self, "_pose", None)
        if pose is None:
            return surface.closest(self.points).signed
        _, idx, _ = pose
        w = self.weights[idx] / self.weights[idx].sum()
        points = self.points
        for _ in range(REPOSE_STEPS):
            cp, u = _closest_with_direction(surface, points[idx])
            step = point_to_plane_step(points[idx], cp.signed, u, w)[0]
            moved = apply(step, points)
            motion = moved[idx] - points[idx]
            points = moved
            if np.sqrt(w @ np.sum(motion * motion, axis=1)) < REPOSE_TOL_MM:
                break
        return surface.closest(points).signed

    def vertices(self, skin: np.ndarray) -> np.ndarray:
        """The predicted face's vertices (`faces`) for the model's skin positions `skin`."""
        return np.asarray(skin, float) if self.surface is None else self.surface.carry(skin)

    def fix_pose(self, skin: np.ndarray) -> None:
        """Set up `realign` about the baseline prediction `skin`: the rigid basis of the scan's
        pose (a small rotation omega about the unoperated points' centroid and a translation t
        move the signed distance by u . (omega x q + t) = (q x u) . omega + u . t, u the unit
        direction from the closest point, q the point about the centroid) and the trimmed
        unoperated points that determine it (`REALIGN_KEEP` of them with the smallest baseline
        gap, as compare's trimmed ICP keeps)."""
        self._pose = None
        if self.unoperated is None or self.unoperated.sum() < 12:
            return
        self.linearised(skin, np.zeros((len(skin), 3)))    # the closest points and u
        cp, u = self._lin
        raw = cp.signed
        q = self.points - np.average(self.points[self.unoperated], axis=0, weights=self.weights[self.unoperated])
        R = rigid_basis(q, u)
        idx = np.nonzero(self.unoperated)[0]
        dev = np.abs(raw[idx] - np.median(raw[idx]))
        idx = idx[dev <= np.quantile(dev, REALIGN_KEEP)]
        sw = np.sqrt(self.weights[idx])
        A = R[idx] * sw[:, None]
        if np.linalg.matrix_rank(A) < 6:
            return
        # rho(r) = -M r[idx]: the weighted least-squares pose correction; realign(r) = r + R rho
        M = np.linalg.pinv(A) * sw[None, :]
        self._pose = (R, idx, M)

    def realign(self, r: np.ndarray) -> np.ndarray:
        """The gap `r` (n,) or its derivatives (n, k) after the scan's pose is corrected by the
        rigid motion that best fits it on the unoperated regions (linearised point-to-plane,
        about the baseline's superimposition): what `faceplan compare` does for a prediction
        that moves the unoperated regions too (posture and swelling move the preauricular
        skin). Without the correction the pose fitted to the baseline keeps part of such an
        effect, and adding the effect cannot remove the tilt the pose took up. Linear in r, so
        the gap stays linear in the effect's parameters."""
        pose = getattr(self, "_pose", None)
        if pose is None:
            return r
        R, idx, M = pose
        r = np.asarray(r, float)
        return r - R @ (M @ r[idx])

    @property
    def uncovered_regions(self) -> list[str]:
        return [n for n, c in self.region_coverage.items() if c < REGION_COVERED]

    def n_eff(self, mask: np.ndarray | None = None) -> float:
        """Independent samples in the points `mask` (all by default)."""
        w = self.weights if mask is None else self.weights[mask]
        n = len(w)
        return float(np.clip(w.sum() / (np.pi * self.correlation_mm ** 2), min(n, 1.0), n))

    def noise_n_eff(self, mask: np.ndarray | None = None) -> float:
        """Independent samples of the scan noise in the points `mask`: the noise floor is the
        scan's roughness (white at the vertex spacing s, `scan_roughness`) or the pose
        residual, so area / (pi s^2), s = sqrt(median point area). Not the gap's correlation
        length (`n_eff`): a large smooth effect makes the gap smooth, and judging its own
        identifiability on that length would make an effect the less identifiable the larger
        it is."""
        w = self.weights if mask is None else self.weights[mask]
        n = len(w)
        spacing2 = float(np.median(self.weights)) if len(self.weights) else 1.0
        return float(np.clip(w.sum() / (np.pi * spacing2), min(n, 1.0), n))

    def rms(self, r: np.ndarray, mask: np.ndarray | None = None) -> float:
        w = self.weights if mask is None else self.weights[mask]
        r = r if mask is None else r[mask]
        return float(np.sqrt(np.sum(w * r * r) / max(w.sum(), 1e-300)))

    def significant(self, rms: float, mask: np.ndarray | None = None, noise_only: bool = False,
                    r: np.ndarray | None = None) -> bool:
        """The gap beyond the error level e (noise and discrepancy; the noise floor alone with
        `noise_only`), sqrt(rms^2 - e^2), is at least e, and the gap is unlikely under the
        error: against the noise alone, its mean square exceeds e^2 beyond three standard
        deviations of a mean square of independent Gaussian errors; against noise +
        discrepancy (once estimated, given the gap `r`), the region's chi-square p-value under
        the error model is below `discrepancy.REGION_P`."""
        from planner.diagnosis.discrepancy import REGION_P

        s2 = (self.noise_floor_mm if noise_only else self.error_level_mm) ** 2
        if rms ** 2 < 2.0 * s2:
            return False
        if not noise_only and self.error_test is not None and r is not None:
            m = np.ones(len(self.points), bool) if mask is None else mask
            return bool(self.error_test(r, m) < REGION_P)
        n = self.n_eff(mask)
        return bool(rms ** 2 > s2 * (1.0 + 3.0 * np.sqrt(2.0 / max(n, 1.0))))

    def region_masks(self, min_points: int = 8) -> dict[str, np.ndarray]:
        out = {}
        for k, name in enumerate(self.region_names):
            m = self.region == k
            if m.sum() >= min_points and name not in self.uncovered_regions:
                out[name] = m
        return out


def scan_roughness(vertices: np.ndarray, k: int = 16, max_points: int = 3000, seed: int = 0) -> float:
    """The scan's noise: RMS residual of local quadrics z = f(x, y) in each sampled vertex's
    tangent frame over its k nearest neighbours, times sqrt(k / (k - 6)) for the six fitted
    coefficients; the median over the sampled vertices (robust to edges and creases)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, float)
    if len(v) < k + 1:
        return float("nan")
    rng = np.random.default_rng(seed)
    sample = rng.choice(len(v), min(max_points, len(v)), replace=False)
    _, nb = cKDTree(v).query(v[sample], k=k)
    p = v[nb] - v[nb].mean(axis=1, keepdims=True)                 # (s, k, 3)
    _, _, vt = np.linalg.svd(p, full_matrices=False)               # frames: vt[:, 2] normal
    local = np.einsum("skj,sij->ski", p, vt)                       # (s, k, 3) in the frame
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)
    AtA = np.einsum("ski,skj->sij", A, A) + 1e-9 * np.eye(6)
    Atz = np.einsum("ski,sk->si", A, z)
    coef = np.linalg.solve(AtA, Atz[..., None])[..., 0]
    res = z - np.einsum("ski,si->sk", A, coef)
    rms = np.sqrt(np.mean(res ** 2, axis=1) * k / (k - 6))
    return float(np.median(rms))


def correlation_length(points: np.ndarray, r: np.ndarray, weights: np.ndarray,
                       max_points: int = 1500, seed: int = 0) -> float:
    """Distance (mm) at which the correlogram of `r` first drops below 1/e (2 mm bins)."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(points), min(max_points, len(points)), replace=False)
    p, x = points[idx], r[idx] - np.average(r, weights=weights)
    var = float(np.mean(x * x))
    spacing = float(np.sqrt(np.median(weights)))
    if var <= 0:
        return spacing
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    prod = x[:, None] * x[None]
    edges = np.arange(0.0, 60.0 + 2.0, 2.0)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (d > lo) & (d <= hi)
        if sel.sum() < 20:
            continue
        if np.mean(prod[sel]) / var < np.exp(-1.0):
            return float(max(0.5 * (lo + hi), spacing))
    return float(edges[-1])


def baseline_prediction(case, skin: np.ndarray) -> ComparePrediction:
    """The baseline skin as `faceplan compare` reads a prediction."""
    from pathlib import Path

    landmarks = {}
    for name, node in case.landmark_ids.items():
        hit = np.nonzero(case.skin_ids == node)[0]
        if hit.size:
            landmarks[name] = np.asarray(skin[hit[0]], float)
    vertices, faces = case.predicted_surface(skin)
    rest = case.predicted_surface(np.asarray(case.model.nodes, float)[np.asarray(case.skin_ids)])[0]
    region = case.region if case.surface is None else case.surface.region
    return ComparePrediction(vertices, np.asarray(faces), np.asarray(region),
                             tuple(case.region_names), tuple(case.unoperated), landmarks,
                             Path(f"<baseline prediction of {case.name}>"),
                             displacement=np.asarray(vertices, float) - np.asarray(rest, float))


def _closest_with_direction(surface: TriangleSurface, points: np.ndarray):
    """(closest points of `points` on `surface`, u): the signed distance is s = u . (p - c),
    u the unit direction from the closest point c to p (outward-signed), so ds = -u . dc; u is
    the face normal where p lies over a triangle's interior, the direction to an edge or
    corner otherwise."""
    cp = surface.closest(points)
    off = points - cp.point
    far = np.abs(cp.signed) > 1e-9
    return cp, np.where(far[:, None], off / np.where(far, cp.signed, 1.0)[:, None], cp.normal)


def measure_gap(case, skin: np.ndarray, scan: Surface, max_residual_mm: float = 3.0) -> ScanGap:
    """Superimpose the scan on the baseline prediction and keep the points that meet it.

    InputError (from compare) when the scan cannot be superimposed: another patient
    (residual > `max_residual_mm`), no overlap, flipped normals."""
    pred = baseline_prediction(case, skin)
    comp = compare_surfaces(pred, scan, max_residual_mm=max_residual_mm, landmarks=bool(pred.landmarks))
    check_same_patient(comp, scan.path)   # the unoperated regions' distance and width, as compare
    match = float(comp.alignment.face_coverage)
    if np.isfinite(match) and match < MIN_FACE_MATCH:
        # the same patient's face lies within 2 mm of its prediction almost everywhere (the
        # effects move the operated lower face by a few mm at most); another face does not
        raise InputError(
            f"the post-op scan does not match this patient's face: once superimposed only "
            f"{100 * match:.0f}% of it lies within 2 mm of the predicted face (at least "
            f"{100 * MIN_FACE_MATCH:.0f}% expected; residual {comp.alignment.residual_rms_mm:.2f} mm "
            "on the unoperated regions): a scan of another patient?", file=str(scan.path))
    valid = np.isfinite(comp.signed)
    weights_all = vertex_areas(comp.scan_vertices, comp.scan_faces)
    points, weights = comp.scan_vertices[valid], weights_all[valid]
    region = comp.region[valid]
    signed = comp.signed[valid]
    # coverage of the modelled face: predicted skin area whose distance to the scan exists
    rvalid = np.isfinite(comp.reverse_signed)
    rweights = vertex_areas(pred.vertices, pred.faces)
    face = pred.region >= 0
    coverage = float(rweights[face & rvalid].sum() / max(rweights[face].sum(), 1e-300))
    region_coverage = {}
    for k, name in enumerate(pred.region_names):
        m = pred.region == k
        if m.any():
            region_coverage[name] = float(rweights[m & rvalid].sum() / max(rweights[m].sum(), 1e-300))
    warnings = list(comp.warnings)
    if coverage < MIN_COVERAGE:
        warnings.append(f"the post-op scan covers only {100 * coverage:.0f}% of the modelled face "
                        f"(< {100 * MIN_COVERAGE:.0f}%): the diagnosis rests on the covered part")
    rough = scan_roughness(comp.scan_vertices)
    residual = float(comp.alignment.residual_rms_mm)
    floor = float(np.nanmax([residual, rough]))
    ell = correlation_length(points, signed, weights)
    metrics = dict(comp.metrics)
    unop = np.isin(region, [k for k, n in enumerate(pred.region_names) if n in pred.unoperated_regions])
    gap = ScanGap(points, weights, region, tuple(pred.region_names), np.asarray(pred.faces),
                  comp.alignment.to_dict(), rough, floor, ell, coverage, region_coverage,
                  metrics, comp.scan_vertices, comp.scan_faces, valid, str(scan.path), warnings,
                  unoperated=unop, surface=case.surface)
    gap.fix_pose(skin)
    uncovered = gap.uncovered_regions
    if uncovered:
        gap.warnings.append("regions without scan coverage (not diagnosed): " + ", ".join(uncovered))
    return gap


def region_table(gap: ScanGap, r: np.ndarray) -> list[dict]:
    """`localization`: per region the gap's RMS and whether it is above the noise floor."""
    out = []
    for k, name in enumerate(gap.region_names):
        m = gap.region == k
        if name in gap.uncovered_regions or m.sum() == 0:
            out.append({"region": name, "rms_mm": None, "significant": False, "covered": False})
            continue
        rms = gap.rms(r, m)
        out.append({"region": name, "rms_mm": round(rms, 4), "significant": gap.significant(rms, m, r=r),
                    "above_noise": gap.significant(rms, m, noise_only=True),
                    "covered": True, "mean_signed_mm": round(float(np.average(r[m], weights=gap.weights[m])), 4),
                    "n_points": int(m.sum())})
        if gap.error_test is not None:
            # the chi-square p-value of the region's gap under noise + discrepancy
            out[-1]["p_value"] = float(f"{gap.error_test(r, m):.3g}")
    return out


def metrics_block(gap: ScanGap, r: np.ndarray) -> dict:
    """The contract's metric block (overall and per region) for gap values on the fixed points."""
    return {"overall": distance_metrics(r, gap.weights),
            "regions": {name: distance_metrics(r[gap.region == k], gap.weights[gap.region == k])
                        for k, name in enumerate(gap.region_names)}}
