"""Soft- and hard-tissue movement figures for the prediction report.

From the pre-op patient model, its predicted nodal displacement u (n, 3) in mm and the plan, this
computes what a surgeon reads in a prediction: per bone segment the planned movement (rotation
angle, displacement of the segment's bone centroid, largest bone-point displacement); per skin
region the mean, RMS, largest and mean-vector soft-tissue movement; per landmark the pre-op and
predicted positions, the displacement and — for the classic soft-to-hard-tissue ratios
(Ls, Sn, Prn over the maxilla; Li over the mandible; Pog, Me over the chin or mandible) — the
antero-posterior (RAS y) movement of the landmark divided by that of the closest bone point of its
segment, the quantity reported in orthognathic follow-up studies. It also gives a mesh-quality
check of the deformed mesh (Jacobian at the 2x2x2 Gauss points, where the tissue is evaluated:
inverted if non-positive; and at the 8 corners, a stricter distortion figure) so an inverted
element is reported, never hidden.
"""
from __future__ import annotations

import numpy as np

# landmark -> segments whose bone it follows, in order of preference (first moved one wins).
LANDMARK_BONE = {
    "Prn": ("maxilla",), "Sn": ("maxilla",), "Ls": ("maxilla",), "Stms": ("maxilla",),
    "Stmi": ("mandible",), "Li": ("mandible",), "Pog": ("chin", "mandible"), "Me": ("chin", "mandible"),
}

# VTK hexahedron: for each corner, its three edge neighbours ordered so that (a-c, b-c, d-c)
# is right-handed in the reference element.
_HEX_CORNERS = np.array([
    [0, 1, 3, 4], [1, 2, 0, 5], [2, 3, 1, 6], [3, 0, 2, 7],
    [4, 7, 5, 0], [5, 4, 6, 1], [6, 5, 7, 2], [7, 6, 4, 3],
])


def corner_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Determinant of the three edge vectors at each of the 8 corners of every hex, (m, 8)."""
    x = np.asarray(nodes, float)[np.asarray(hexes)]                     # (m, 8, 3)
    c = x[:, _HEX_CORNERS[:, 0]]
    e1 = x[:, _HEX_CORNERS[:, 1]] - c
    e2 = x[:, _HEX_CORNERS[:, 2]] - c
    e3 = x[:, _HEX_CORNERS[:, 3]] - c
    return np.einsum("mki,mki->mk", np.cross(e1, e2), e3)


# Reference coordinates of the VTK hexahedron's nodes and the 2x2x2 Gauss points.
_HEX_REF = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float)
_GAUSS = _HEX_REF / np.sqrt(3.0)


def _shape_derivatives() -> np.ndarray:
    """dN_a/dxi_j of the trilinear hexahedron at the 2x2x2 Gauss points, (8, 8, 3)."""
    out = np.empty((8, 8, 3))
    for g, xi in enumerate(_GAUSS):
        terms = 1.0 + _HEX_REF * xi                      # (8, 3): (1 + xi_a,k xi_k)
        for j in range(3):
            others = np.prod(np.delete(terms, j, axis=1), axis=1)
            out[g, :, j] = _HEX_REF[:, j] * others / 8.0
    return out


_DN = _shape_derivatives()


def gauss_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """det(dx/dxi) of every hexahedron at its 2x2x2 Gauss points, (m, 8): where the FE solve
    evaluates the tissue, so a non-positive value there is an inverted element."""
    x = np.asarray(nodes, float)[np.asarray(hexes)]                   # (m, 8, 3)
    jac = np.einsum("mai,gaj->mgij", x, _DN)
    return np.linalg.det(jac)


def inverted_elements(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Indices of hexahedra with a non-positive Jacobian at a Gauss point (inverted)."""
    return np.flatnonzero((gauss_jacobians(nodes, hexes) <= 0.0).any(axis=1))


def folded_corners(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Indices of hexahedra with a non-positive corner Jacobian (a stricter quality test: such
    an element is distorted at a corner although valid where the tissue is evaluated)."""
    return np.flatnonzero((corner_jacobians(nodes, hexes) <= 0.0).any(axis=1))


def _apply(matrix: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ matrix[:3, :3].T + matrix[:3, 3]


def segment_movements(plan, bone_vertices: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per planned segment: rotation, centroid displacement and largest bone-point displacement."""
    out = {}
    for name, sp in plan.segments.items():
        v = np.asarray(bone_vertices.get(sp.source or name, np.zeros((0, 3))), float)
        for cp in sp.cut_planes:
            v = v[cp.keeps(v)]
        entry = {"form": sp.form, "rotation_deg": round(sp.rotation_deg, 3),
                 "matrix_ras": np.round(sp.matrix, 6).tolist()}
        if len(v):
            c = v.mean(axis=0)
            d = _apply(sp.matrix, c[None])[0] - c
            entry.update(centroid_mm=np.round(c, 3).tolist(), centroid_displacement_mm=np.round(d, 3).tolist(),
                         centroid_displacement_norm_mm=round(float(np.linalg.norm(d)), 3),
                         max_bone_displacement_mm=round(float(np.linalg.norm(_apply(sp.matrix, v) - v, axis=1).max()), 3))
        out[name] = entry
    return out


def region_movements(model, u: np.ndarray) -> dict[str, dict]:
    """Per skin region: n_nodes, mean/RMS/max displacement magnitude and mean vector (mm)."""
    out = {}
    mag = np.linalg.norm(u, axis=1)
    for name, ids in model.regions.items():
        ids = np.asarray(ids, int)
        if ids.size == 0:
            continue
        m = mag[ids]
        out[name] = {"n_nodes": int(ids.size), "mean_mm": round(float(m.mean()), 4),
                     "rms_mm": round(float(np.sqrt((m ** 2).mean())), 4), "max_mm": round(float(m.max()), 4),
                     "mean_vector_mm": np.round(u[ids].mean(axis=0), 4).tolist()}
    return out


def landmark_movements(model, u: np.ndarray, plan=None, bone_vertices=None) -> dict[str, dict]:
    """Per landmark: pre-op and predicted position, displacement, and the soft-to-hard ratio of
    antero-posterior movement over the closest bone point of the segment it follows."""
    out = {}
    motions = plan.motions() if plan is not None else {}
    for name, node in model.landmarks.items():
        p = np.asarray(model.nodes[node], float)
        d = np.asarray(u[node], float)
        entry = {"node": int(node), "preop": np.round(p, 4).tolist(), "predicted": np.round(p + d, 4).tolist(),
                 "displacement_mm": np.round(d, 4).tolist(), "magnitude_mm": round(float(np.linalg.norm(d)), 4)}
        for seg in LANDMARK_BONE.get(name, ()):
            if seg not in motions or bone_vertices is None:
                continue
            sp = plan.segments[seg]
            v = np.asarray(bone_vertices.get(sp.source or seg, np.zeros((0, 3))), float)
            for cp in sp.cut_planes:
                v = v[cp.keeps(v)]
            if not len(v):
                continue
            b = v[np.argmin(np.linalg.norm(v - p, axis=1))]
            hard = _apply(sp.matrix, b[None])[0] - b
            entry["bone_segment"] = seg
            entry["hard_tissue_displacement_mm"] = np.round(hard, 4).tolist()
            if abs(hard[1]) > 0.1:   # ratio of AP movements; below 0.1 mm it is meaningless
                entry["soft_to_hard_ratio_ap"] = round(float(d[1] / hard[1]), 4)
            break
        out[name] = entry
    return out


def predicted_landmarks(model, u: np.ndarray) -> dict[str, list[float]]:
    return {n: [float(c) for c in np.asarray(model.nodes[i], float) + u[i]] for n, i in model.landmarks.items()}


def solve_summary(report: dict) -> dict:
    """The solve's figures from a written prediction report (`report.json`): Newton iterations,
    load steps, cut-backs, the load the continuation resumed from, the contacts left unmet
    ({name: mm}), whether a soft-contact fallback was used, and the deformed mesh's inverted
    (Gauss point) and folded (corner) element counts. The benches tabulate these."""
    solver = report.get("solver") or {}
    info = solver.get("info") or {}
    quality = report.get("mesh_quality") or {}
    return {"newton_iterations": solver.get("iterations"), "load_steps": solver.get("steps"),
            "cutbacks": info.get("cutbacks"), "continuation_from_load": info.get("continuation_from_load"),
            "contact_unmet_mm": info.get("contact_unmet_mm") or {},
            "contact_fallback": bool(info.get("contact_fallback")),
            "inverted_elements": int(quality.get("inverted_elements", 0)),
            "folded_corner_elements": int(quality.get("folded_corner_elements", 0))}
