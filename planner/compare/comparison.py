"""Prediction versus post-operative scan: superimposition, distances, metrics, landmarks.

The post-op scan is superimposed on the pre-op frame by trimmed point-to-plane ICP on the
regions surgery leaves untouched (`alignment`), then signed point-to-surface distances are
measured from every scan vertex to the predicted skin (positive: the real face lies outside the
prediction, i.e. it is fuller than predicted) and, in reverse, from every prediction vertex to
the scan (same sign convention). Only distances between existing surfaces count: a point whose
closest point on the other surface is on that surface's boundary, or farther than the gate, is
dropped (a point right above the other surface's edge is kept). Statistics are weighted by the area each vertex represents, so that the figures do not
depend on the scan density (`metrics`). Each scan point takes the region of the nearest corner
of its closest predicted triangle. Landmarks are located on both surfaces with the same
anatomical operator (`landmarks`) and their distance is the landmark error.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner.compare.alignment import Alignment, apply, superimpose
from planner.compare.distances import TriangleSurface, vertex_areas
from planner.compare.inputs import Prediction, Surface
from planner.compare.landmarks import RULES, LandmarkLocator
from planner.compare.metrics import distance_metrics
from planner.errors import InputError

__all__ = ["Comparison", "compare_surfaces", "check_same_patient", "SIGN_CONVENTION"]

SIGN_CONVENTION = ("signed distance = post-op minus prediction along the predicted outward "
                   "normal: > 0 where the real face is fuller (more outward) than predicted")
REPORTED_LANDMARKS = ("Sn", "Ls", "Li", "Pog", "Me", "ChL", "ChR", "Prn")


@dataclass
class Comparison:
    alignment: Alignment
    scan_vertices: np.ndarray          # aligned into the pre-op frame
    scan_faces: np.ndarray
    signed: np.ndarray                 # (n_scan,) NaN where dropped
    region: np.ndarray                 # (n_scan,) region index, -1 where dropped
    reverse_signed: np.ndarray         # (n_pred,) NaN where dropped
    prediction: Prediction
    metrics: dict
    metrics_reverse: dict
    landmarks: dict
    warnings: list[str] = field(default_factory=list)

    def report(self) -> dict:
        return {
            "alignment": self.alignment.to_dict(),
            "metrics": self.metrics,
            "metrics_reverse": self.metrics_reverse,
            "sign_convention": SIGN_CONVENTION,
            "region_names": list(self.prediction.region_names),
            "unoperated_regions": list(self.prediction.unoperated_regions),
            "warnings": list(self.warnings),
        }


def _region_metrics(signed, weights, region, names) -> dict:
    out = {}
    for k, name in enumerate(names):
        sel = region == k
        out[name] = distance_metrics(signed[sel], weights[sel])
    return out


def _densified(vertices: np.ndarray, faces: np.ndarray, centres: list[np.ndarray], radius: float,
               max_edge: float = 0.8) -> np.ndarray:
    """Vertices of the surface near `centres`, subdivided to edges <= max_edge mm."""
    import trimesh.remesh

    if not centres:
        return vertices
    c = np.asarray(centres)
    near_v = np.min(np.linalg.norm(vertices[:, None, :] - c[None], axis=2), axis=1) < radius + 4 * max_edge
    sel = faces[np.any(near_v[faces], axis=1)]
    if len(sel) == 0:
        return vertices[near_v]
    v, _ = trimesh.remesh.subdivide_to_size(vertices, sel, max_edge=max_edge, max_iter=12)
    return np.asarray(v)


def _locate_landmarks(pred: Prediction, pred_surface: TriangleSurface, scan: TriangleSurface,
                      radius: float = 8.0, manual: dict[str, np.ndarray] | None = None) -> dict:
    """Landmark errors. `manual`: landmarks placed on the post-op scan (pre-op frame), used
    instead of the automatic location on the scan where given."""
    manual = manual or {}
    names = [n for n in REPORTED_LANDMARKS if n in pred.landmarks] + [
        n for n in pred.landmarks if (n in RULES or n in manual) and n not in REPORTED_LANDMARKS]
    if not names:
        return {}
    guesses = [pred.landmarks[n] for n in names]
    # the same operator on both surfaces: search and fit balls scale with the coarser mesh
    # (a piecewise-linear surface needs a fit over a few facets to have a curvature at all)
    spacing = max(pred_surface.mean_edge_length, scan.mean_edge_length)
    radius = max(radius, 1.5 * spacing)
    fit_radius = max(3.0, 1.2 * spacing)
    pred_pts = _densified(pred_surface.vertices, pred_surface.faces, guesses, radius)
    on_pred = LandmarkLocator(pred_pts, pred_surface.vertices[pred_surface.vertex_on_boundary],
                              radius=radius, fit_radius=fit_radius)
    found = {}
    for name, guess in zip(names, guesses):
        p = on_pred.locate(name, guess)
        if p is not None:
            found[name] = p
        elif name in manual:          # no definition to refine with: the model's own point
            found[name] = np.asarray(guess, float)
    if not found:
        return {}
    scan_pts = _densified(scan.vertices, scan.faces, list(found.values()), radius)
    on_scan = LandmarkLocator(scan_pts, scan.vertices[scan.vertex_on_boundary], radius=radius,
                              fit_radius=fit_radius)
    out = {}
    for name, p in found.items():
        source = "manual" if name in manual else "located"
        q = manual[name] if name in manual else on_scan.locate(name, p)
        if q is None:
            continue
        out[name] = {
            "error_mm": float(np.linalg.norm(q - p)),
            "vector_mm": (q - p).tolist(),
            "predicted": p.tolist(),
            "postop": np.asarray(q, float).tolist(),
            "postop_source": source,
        }
    return out


def _superimpose_checked(pred: Prediction, scan: Surface, pred_surface: TriangleSurface,
                         unop_faces: np.ndarray, keep: float, global_init: bool,
                         max_residual_mm: float, warnings: list[str]) -> Alignment:
    """The scan's pose on the prediction's unoperated regions; InputError when there is none."""
    scan_pts = scan.vertices
    alignment = superimpose(scan_pts, pred_surface, unop_faces, keep=keep, global_init=global_init)
    if alignment.strategy == "global" and not global_init:
        c = scan_pts.mean(axis=0)
        shift = float(np.linalg.norm(apply(alignment.matrix, c[None])[0] - c))
        lo = np.maximum(scan_pts.min(axis=0), pred.vertices.min(axis=0))
        hi = np.minimum(scan_pts.max(axis=0), pred.vertices.max(axis=0))
        if np.any(lo > hi):
            # where it was given, the scan's bounding box misses the face altogether
            raise InputError(
                "the post-op scan does not overlap the predicted face (their bounding boxes "
                f"are disjoint; it would fit {shift:.0f} mm away): give it in the patient's "
                "frame (RAS, mm), or use --global-init if it is in its scanner's own frame",
                file=str(scan.path))
        warnings.append("the scan did not fit from its own position; its pose was found by a "
                        f"global search (moved {shift:.1f} mm, rotated "
                        f"{alignment.rotation_deg:.1f} degrees)")
    if alignment.n_points < 50:
        raise InputError(
            "the post-op scan does not overlap the predicted face's unoperated regions "
            f"({', '.join(pred.unoperated_regions)}): only {alignment.n_points} scan points "
            "lie on them; is the scan in the patient's frame (RAS, mm)?", file=str(scan.path))
    if not alignment.residual_rms_mm <= max_residual_mm:
        raise InputError(
            f"the post-op scan cannot be superimposed on the unoperated regions (residual "
            f"{alignment.residual_rms_mm:.2f} mm > {max_residual_mm} mm): wrong patient, or "
            "not overlapping the face", file=str(scan.path))
    if alignment.residual_rms_mm > 1.0:
        warnings.append(f"alignment residual {alignment.residual_rms_mm:.2f} mm is large: "
                        "distances below it are within the noise floor")
    return alignment


def compare_surfaces(pred: Prediction, scan: Surface, gate: float = 10.0, keep: float = 0.9,
                     align: bool = True, max_residual_mm: float = 3.0,
                     global_init: bool = False, alignment: Alignment | None = None,
                     landmarks: bool = True,
                     postop_landmarks: dict[str, np.ndarray] | None = None,
                     postop_landmarks_file: str | None = None) -> Comparison:
    """Superimpose `scan` on the prediction's unoperated regions and measure the differences.

    `alignment` reuses a superimposition computed before (e.g. when many candidate
    predictions of one case are compared with its scan) instead of running the ICP;
    `landmarks=False` skips the landmark search. `postop_landmarks` ({name: [x, y, z]} in
    the scan's frame, e.g. placed by hand in 3D Slicer) replace the automatic location on the
    scan for the landmarks they name.
    """
    warnings: list[str] = list(pred.notes)
    pred_surface = TriangleSurface(pred.vertices, pred.faces)
    names = pred.region_names
    # a face's outward normals point away from the head's inside, which lies behind the
    # centroid of the face surface
    centre = pred.vertices.mean(axis=0)
    outward = np.sum(pred_surface.face_normals * (pred.vertices[pred.faces].mean(axis=1) - centre))
    if outward < 0:
        raise InputError("the predicted skin's normals point inwards (flipped triangle winding)",
                         file=str(pred.path))
    unop_ids = [names.index(n) for n in pred.unoperated_regions]
    if not unop_ids:
        raise InputError("the prediction lists no unoperated regions to superimpose on "
                         f"(regions: {', '.join(names)})", file=str(pred.path), field="unoperated_regions")
    unop_vertex = np.isin(pred.region, unop_ids)
    unop_faces = np.all(unop_vertex[pred.faces], axis=1)

    scan_pts = scan.vertices
    if alignment is None:
        alignment = (_superimpose_checked(pred, scan, pred_surface, unop_faces, keep, global_init,
                                          max_residual_mm, warnings)
                     if align else Alignment(np.eye(4), float("nan"), float("nan"), 0, 0, True))
    aligned = apply(alignment.matrix, scan_pts)
    fwd = pred_surface.closest(aligned)
    valid = ~fwd.beyond_boundary & (fwd.distance <= gate)
    n_valid = int(valid.sum())
    scan_surface = TriangleSurface(aligned, scan.faces)
    weights = vertex_areas(aligned, scan.faces)
    covered = float(weights[valid].sum() / max(weights.sum(), 1e-300))
    if n_valid < 100 or covered < 0.05:
        raise InputError(f"the post-op scan does not overlap the predicted face (only {n_valid} "
                         f"points, {100 * covered:.1f}% of its area, lie within {gate} mm of it)",
                         file=str(scan.path))
    # flipped scan normals: the scan's vertex normals oppose the prediction's where they overlap
    agree = np.einsum("pi,pi->p", scan_surface.vertex_normals[valid], fwd.normal[valid])
    if np.sum(weights[valid] * agree) < 0:
        raise InputError("the post-op scan's normals point inwards (flipped triangle winding); "
                         "re-export it with outward normals", file=str(scan.path))
    corner = pred.faces[fwd.face, np.argmax(fwd.bary, axis=1)]
    region = np.where(valid, pred.region[corner], -1)
    signed = np.where(valid, fwd.signed, np.nan)
    metrics = {"overall": distance_metrics(signed, weights),
               "regions": _region_metrics(signed, weights, region, names)}
    # reverse: prediction vertices to the scan, same sign (post-op minus prediction)
    rev = scan_surface.closest(pred.vertices)
    rvalid = ~rev.beyond_boundary & (rev.distance <= gate)
    reverse = np.where(rvalid, -rev.signed, np.nan)
    rweights = vertex_areas(pred.vertices, pred.faces)
    metrics_reverse = {"overall": distance_metrics(reverse, rweights),
                       "regions": _region_metrics(reverse, rweights, np.where(rvalid, pred.region, -1), names)}
    manual = None
    if postop_landmarks:
        names_m = list(postop_landmarks)
        manual_pts = apply(alignment.matrix, np.array([postop_landmarks[n] for n in names_m], float))
        off = scan_surface.closest(manual_pts).distance
        far = [f"{n} ({d:.1f} mm)" for n, d in zip(names_m, off) if d > 5.0]
        if far:
            raise InputError("post-op landmarks lie off the post-op scan (another frame?): "
                             + ", ".join(far), file=postop_landmarks_file)
        manual = dict(zip(names_m, manual_pts))
    metrics["landmarks"] = (_locate_landmarks(pred, pred_surface, scan_surface, manual=manual)
                            if landmarks else {})
    missing = [n for n in REPORTED_LANDMARKS if n in pred.landmarks and n not in metrics["landmarks"]]
    if missing:
        warnings.append("landmarks not found on the post-op scan (not covered or ambiguous): "
                        + ", ".join(missing))
    if landmarks and not pred.landmarks:
        warnings.append("the prediction gives no landmarks (report.json landmarks_predicted)")
    return Comparison(alignment, aligned, scan.faces, signed, region, reverse, pred, metrics,
                      metrics_reverse, metrics["landmarks"], warnings)


# A triangle of an unoperated region takes part in the same-patient checks only where the
# prediction moves none of its vertices by more than this: even a model wrong by the whole of
# such a movement stays within the checks' tolerances (a median of 0.6 mm is doubtful; 2.5 % of
# a width of ~80 mm is 2 mm).
STILL_MM = 0.5


def check_same_patient(result: Comparison, scan_path) -> None:
    """Refuse (InputError naming the scan) a superimposed post-op scan of another patient:
    its unoperated regions lie a median of more than `OTHER_PATIENT_MEDIAN_MM` from the
    prediction's, or its face is more than `OTHER_PATIENT_SCALE_PCT` wider or narrower there
    (`unoperated_width_scale_pct`). A median above `DOUBTFUL_MEDIAN_MM` adds a warning. Both figures
    go to the report's `alignment`. Where the prediction carries its displacement from the pre-op
    skin (`Prediction.displacement`), the regions' triangles it moves by more than `STILL_MM`
    are left out of both checks: the regions are unoperated, but not unmoved, in every plan."""
    from planner.compare.alignment import (DOUBTFUL_MEDIAN_MM, OTHER_PATIENT_MEDIAN_MM,
                                           OTHER_PATIENT_SCALE_PCT, SCALE_IGNORED_REGIONS,
                                           SCALE_MAX_STDERR_PCT, unoperated_median_mm,
                                           unoperated_width_scale_pct)

    pred = result.prediction
    surface = TriangleSurface(pred.vertices, pred.faces)
    # where the prediction moves the skin of an "unoperated" region (a large maxillary
    # advancement draws the infra-orbital skin), the model's error in that movement is not
    # another face: the checks keep the triangles it leaves within `STILL_MM`
    still = np.ones(len(pred.faces), bool)
    if pred.displacement is not None:
        moved = np.linalg.norm(np.asarray(pred.displacement, float), axis=1) > STILL_MM
        still = ~np.any(moved[pred.faces], axis=1)

    def in_regions(names):
        ids = [pred.region_names.index(n) for n in names]
        return np.all(np.isin(pred.region, ids)[pred.faces], axis=1)

    def faces_of(names):
        return in_regions(names) & still

    unop = faces_of(pred.unoperated_regions)
    note = ""
    if pred.displacement is not None:
        area = surface.face_areas
        whole = float(area[in_regions(pred.unoperated_regions)].sum())
        result.alignment.unoperated_still_pct = round(100.0 * float(area[unop].sum()) / max(whole, 1e-300), 1)
        if not still.all():
            note = f"; where the prediction moves the skin by under {STILL_MM:g} mm"
        if not unop.any():
            result.warnings.append(
                f"the prediction moves every unoperated region ({', '.join(pred.unoperated_regions)}) by more "
                f"than {STILL_MM:g} mm: whether the post-op scan is this patient's was not checked")
    median = unoperated_median_mm(result.scan_vertices, surface, unop)
    where = ", ".join(pred.unoperated_regions) + note
    if median > OTHER_PATIENT_MEDIAN_MM:
        raise InputError(f"the post-op scan does not match the face where surgery changes nothing "
                         f"({where}): median distance {median:.2f} mm after superimposition (the "
                         f"same person's scans agree within ~0.3 mm): another patient's scan?",
                         file=str(scan_path), field="post-op scan")
    over_bone = [n for n in pred.unoperated_regions if n not in SCALE_IGNORED_REGIONS]
    scale, stderr, converged = unoperated_width_scale_pct(
        result.scan_vertices, surface, faces_of(over_bone),
        weights=vertex_areas(result.scan_vertices, result.scan_faces))
    if not converged:
        raise InputError(f"the post-op scan's face has another shape than the predicted patient's "
                         f"where surgery changes nothing ({', '.join(over_bone)}{note}): no width brings "
                         f"the two into agreement (the fit drifted to {abs(scale):.0f}% "
                         f"{'wider' if scale > 0 else 'narrower'}): another patient's scan?",
                         file=str(scan_path), field="post-op scan")
    if abs(scale) > OTHER_PATIENT_SCALE_PCT and stderr < SCALE_MAX_STDERR_PCT:
        raise InputError(f"the post-op scan's face is {abs(scale):.1f}% "
                         f"{'wider' if scale > 0 else 'narrower'} than the predicted patient's "
                         f"where surgery changes nothing ({', '.join(over_bone)}{note}; the same person's "
                         f"scans agree within ~1%, refused beyond {OTHER_PATIENT_SCALE_PCT:g}%): "
                         "another patient's scan?", file=str(scan_path), field="post-op scan")
    if median > DOUBTFUL_MEDIAN_MM:
        result.warnings.append(f"the unoperated regions ({where}) differ by a median {median:.2f} mm: "
                               "is this the same patient? (the same person's scans agree within ~0.3 mm)")
    result.alignment.unoperated_median_mm = median
    result.alignment.unoperated_width_scale_pct = round(float(scale), 3)
